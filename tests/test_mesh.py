"""Meshes: loading, clean-up, size normalisation, derived quantities, procedural shapes, decimation, formats."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
import trimesh

from torchsss.geometry.loading import builtin_mesh_names, builtin_mesh_path, load_mesh
from torchsss.geometry.mesh import Mesh, MeshWarning, decimate, mesh_from_arrays, normalize_to_size
from torchsss.geometry.procedural import plane, slab, sphere, torus


def signed_volume(mesh: Mesh) -> float:
    tri = mesh.triangles().double()
    return float((tri[:, 0] * torch.linalg.cross(tri[:, 1], tri[:, 2], dim=-1)).sum() / 6.0)


def check_normalised(mesh: Mesh, size_mm: float) -> None:
    assert mesh.size_mm == pytest.approx(size_mm, rel=1e-5)
    lo, hi = mesh.bounds.double()
    centre = 0.5 * (lo + hi)
    assert float(centre.abs().max()) <= 1e-5 * size_mm


@pytest.fixture
def meshes_dir(shared_dir):
    return shared_dir / "data" / "meshes"


# ------------------------------------------------------------------------------------------------------------
# size normalisation and built-ins
# ------------------------------------------------------------------------------------------------------------


def test_builtin_names_and_spot_file():
    assert builtin_mesh_names() == ("slab", "sphere", "spot", "torus")
    path = builtin_mesh_path("spot")
    assert path.is_file() and path.suffix == ".obj"
    assert path.stat().st_size < 1_000_000
    assert (path.parent / "spot_LICENSE.md").is_file()
    with pytest.raises(ValueError, match="name"):
        builtin_mesh_path("sphere")
    with pytest.raises(ValueError, match="name"):
        builtin_mesh_path("bunny")


def test_spot_normalised_with_uvs():
    raw = load_mesh("spot")
    assert raw.mm_per_unit == 1.0
    m = load_mesh("spot", size_mm=30.0)
    check_normalised(m, 30.0)
    assert m.mm_per_unit == pytest.approx(30.0 / raw.size_mm, rel=1e-6)
    assert m.name == "spot" and m.is_watertight
    # welding: 3225 position/uv vertices in the file, 2930 distinct positions; UVs stay per corner
    assert m.num_vertices == 2930 and m.num_faces == 5856
    assert m.face_uvs is not None and m.face_uvs.shape == (5856, 3, 2) and m.face_uvs.dtype == torch.float32
    uv = m.face_uvs
    assert bool(torch.isfinite(uv).all())
    # the file's texture coordinates are in [0, 1] except four corners a hair outside (-0.052 .. 1.0007)
    assert float(uv.min()) > -0.06 and float(uv.max()) < 1.01
    assert float(((uv >= 0) & (uv <= 1)).float().mean()) > 0.999
    # faces are the file's faces (same order), so the corner UVs are the file's vt for each corner
    tm = trimesh.load(builtin_mesh_path("spot"), force="mesh", process=False)
    np.testing.assert_allclose(uv.numpy(), tm.visual.uv[tm.faces], atol=1e-6)
    np.testing.assert_allclose(
        (raw.triangles()).numpy(), tm.vertices[tm.faces], atol=1e-6
    )  # welding changed indices, not corner positions


@pytest.mark.parametrize("name", ["stanford-bunny.obj", "teapot.obj"])
def test_shared_meshes_normalised_and_warn_open(meshes_dir, name):
    with pytest.warns(MeshWarning, match="not watertight"):
        m = load_mesh(meshes_dir / name, size_mm=25.0)
    check_normalised(m, 25.0)
    raw = load_mesh(meshes_dir / name, warn_open=False)
    assert m.mm_per_unit == pytest.approx(25.0 / raw.size_mm, rel=1e-6)
    assert m.num_faces == raw.num_faces
    assert m.area == pytest.approx(raw.area * m.mm_per_unit**2, rel=1e-5)


@pytest.mark.slow
def test_igea_normalised(meshes_dir):
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)  # igea is watertight: no warning
        m = load_mesh(meshes_dir / "igea.ply", size_mm=40.0)
    check_normalised(m, 40.0)
    assert m.num_faces == 268_686 and m.is_watertight


@pytest.mark.parametrize("name", ["sphere", "torus", "slab"])
def test_procedural_builtin_names(name):
    m = load_mesh(name)
    assert m.name == name and m.mm_per_unit == 1.0 and m.face_uvs is None
    s = load_mesh(name, size_mm=12.0, dtype=torch.float64)
    assert s.vertices.dtype == torch.float64
    check_normalised(s, 12.0)
    assert s.mm_per_unit == pytest.approx(12.0 / m.size_mm, rel=1e-6)


def test_normalize_to_size_composes_scale():
    m = sphere(radius_mm=1.0, subdivisions=2)
    m = m.with_dtype(torch.float64)
    shifted = Mesh(m.vertices + torch.tensor([5.0, -3.0, 2.0], dtype=torch.float64), m.faces)
    a = normalize_to_size(shifted, 10.0)
    b = normalize_to_size(a, 20.0)
    check_normalised(b, 20.0)
    assert b.mm_per_unit == pytest.approx(20.0 / (2 * math.sqrt(3)), rel=1e-12)
    assert a.vertices.dtype == torch.float64
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="size_mm"):
            normalize_to_size(m, bad)
    with pytest.raises(TypeError, match="size_mm"):
        normalize_to_size(m, "10")
    with pytest.raises(ValueError, match="size_mm"):
        load_mesh("sphere", size_mm=-3.0)


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="source"):
        load_mesh(tmp_path / "missing.obj")
    with pytest.raises(TypeError, match="source"):
        load_mesh(42)
    with pytest.raises(TypeError, match="dtype"):
        load_mesh("sphere", dtype=torch.int32)


# ------------------------------------------------------------------------------------------------------------
# derived quantities and procedural shapes
# ------------------------------------------------------------------------------------------------------------


def test_sphere_area_normals_volume():
    r = 7.0
    m = sphere(radius_mm=r, subdivisions=4)
    assert m.num_faces == 20 * 4**4 and m.num_vertices == 10 * 4**4 + 2
    assert m.area == pytest.approx(4 * math.pi * r**2, rel=1e-2)
    assert m.area < 4 * math.pi * r**2  # inscribed polyhedron
    # vertex areas sum to the total area
    assert float(m.vertex_areas.sum()) == pytest.approx(m.area, rel=1e-5)
    assert bool((m.vertex_areas > 0).all())
    # outward normals
    centroids = m.triangles().mean(dim=1)
    dots = (m.face_normals * centroids).sum(-1)
    assert float(dots.mean()) > 0 and bool((dots > 0).all())
    np.testing.assert_allclose(m.face_normals.norm(dim=-1).numpy(), 1.0, atol=1e-6)
    # vertex normals of a sphere are the radial directions
    radial = m.vertices / m.vertices.norm(dim=-1, keepdim=True)
    assert float((m.vertex_normals * radial).sum(-1).min()) > 0.999
    assert m.is_watertight
    assert signed_volume(m) == pytest.approx(4 / 3 * math.pi * r**3, rel=2e-2)
    assert m.to_trimesh().is_winding_consistent
    lo, hi = m.bounds
    np.testing.assert_allclose(lo.numpy(), -r, rtol=1e-5)
    np.testing.assert_allclose(hi.numpy(), r, rtol=1e-5)


@pytest.mark.parametrize("subdivisions", [1, 3, 5])
def test_max_vertex_normals_are_exact_on_a_sphere(subdivisions):
    """Max's weights: the radial direction to rounding at any tessellation and centre, where the area weights are off
    by up to 1e-2 rad (the quantity a caustic's focus amplifies)."""
    m = sphere(7.0, subdivisions, dtype=torch.float64)
    shift = torch.tensor([3.0, -40.0, 12.0], dtype=torch.float64)
    moved = mesh_from_arrays(m.vertices + shift, m.faces, dtype=torch.float64)
    radial = torch.nn.functional.normalize(moved.vertices - shift, dim=-1)
    assert float((moved.vertex_normals_max - radial).abs().max()) < 1e-12
    area_err = float(torch.acos((moved.vertex_normals * radial).sum(-1).clamp(-1, 1)).max())
    if subdivisions >= 3:  # (the symmetric one-rings of subdivision 1 make the area weights exact too)
        assert area_err > 1e-4  # the area weights are not exact: the check above can fail


def test_max_vertex_normals_on_an_ellipsoid_and_degenerate_corners():
    """On an ellipsoid (no longer exact) Max's normals are closer to the gradient normal than the area weights (worst
    vertex); a vertex whose only face is degenerate keeps its area-weighted normal (finite; zero there)."""
    ax = torch.tensor([11.0, 9.0, 8.0], dtype=torch.float64)
    s = sphere(1.0, 4, dtype=torch.float64)
    e = mesh_from_arrays(s.vertices * ax, s.faces, dtype=torch.float64)
    exact = torch.nn.functional.normalize(e.vertices / ax**2, dim=-1)

    def worst(n):
        return float(torch.acos((n * exact).sum(-1).clamp(-1, 1)).max())

    assert worst(e.vertex_normals_max) < 0.5 * worst(e.vertex_normals)
    # a face with a repeated vertex (zero-length edge) next to a healthy one: Mesh() keeps it (no clean-up)
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], dtype=torch.float64)
    m = Mesh(v, torch.tensor([[0, 1, 2], [3, 3, 1]]))
    n = m.vertex_normals_max
    assert bool(torch.isfinite(n).all())
    torch.testing.assert_close(n[:3], torch.tensor([[0.0, 0, 1]] * 3, dtype=torch.float64))
    torch.testing.assert_close(n[3], m.vertex_normals[3])


def test_torus_area_normals_volume():
    big, small = 10.0, 3.0
    m = torus(big, small)
    assert m.area == pytest.approx(4 * math.pi**2 * big * small, rel=1e-2)
    assert m.is_watertight and m.face_uvs is None
    assert signed_volume(m) == pytest.approx(2 * math.pi**2 * big * small**2, rel=2e-2)
    # outward: away from the tube's centre line (and the plain mean test of the contract)
    c = m.triangles().mean(dim=1)
    ring = c.clone()
    ring[:, 2] = 0
    ring = big * ring / ring.norm(dim=-1, keepdim=True)
    assert bool(((m.face_normals * (c - ring)).sum(-1) > 0).all())
    assert float((m.face_normals * c).sum(-1).mean()) > 0
    assert float(m.vertex_areas.sum()) == pytest.approx(m.area, rel=1e-5)
    with pytest.raises(ValueError, match="minor_radius_mm"):
        torus(3.0, 4.0)


def test_slab_exact_area_and_sides():
    w, h, t, s = 30.0, 20.0, 2.0, 8
    m = slab(w, h, t, segments=s)
    assert m.area == pytest.approx(2 * w * h + 2 * (w + h) * t, rel=1e-6)
    assert m.num_faces == 4 * s * s + 8 * s
    assert m.is_watertight
    assert signed_volume(m) == pytest.approx(w * h * t, rel=1e-6)
    np.testing.assert_allclose(m.bounds.numpy(), [[-w / 2, -h / 2, -t / 2], [w / 2, h / 2, t / 2]], rtol=1e-6)
    # each face normal is the axis on whose boundary the face lies, with that side's sign
    c = m.triangles().mean(dim=1)
    n = m.face_normals
    half = torch.tensor([w, h, t]) / 2
    on_side = (c.abs() - half).abs() < 1e-4  # which box side(s) the centroid lies on
    axis = n.abs().argmax(dim=-1)
    assert bool(on_side[torch.arange(len(c)), axis].all())
    assert bool((torch.sign(n[torch.arange(len(c)), axis]) == torch.sign(c[torch.arange(len(c)), axis])).all())
    np.testing.assert_allclose(n.abs().max(dim=-1).values.numpy(), 1.0, atol=1e-6)
    # large faces are a regular grid: all face areas on top equal
    top = n[:, 2] > 0.5
    areas = m.face_areas[top]
    np.testing.assert_allclose(areas.numpy(), (w * h) / (2 * s * s), rtol=1e-5)


def test_plane_open_area_and_facing():
    m = plane(50.0, 20.0, segments=10)
    assert m.area == pytest.approx(1000.0, rel=1e-6)
    assert m.num_vertices == 121 and m.num_faces == 200
    assert not m.is_watertight
    assert float(m.face_normals[:, 2].min()) == pytest.approx(1.0)
    assert float(m.vertices[:, 2].abs().max()) == 0.0
    np.testing.assert_allclose(m.bounds.numpy(), [[-25, -10, 0], [25, 10, 0]])
    np.testing.assert_allclose(m.face_areas.numpy(), 5.0, rtol=1e-6)  # regular grid
    assert float(m.vertex_areas.sum()) == pytest.approx(m.area, rel=1e-6)
    # the procedural plane itself does not warn, clean-up of the same arrays does
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)
        plane()
    with pytest.warns(MeshWarning, match="not watertight"):
        mesh_from_arrays(m.vertices, m.faces)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)
        mesh_from_arrays(m.vertices, m.faces, warn_open=False)


def test_procedural_argument_checks():
    with pytest.raises(ValueError, match="radius_mm"):
        sphere(radius_mm=0.0)
    with pytest.raises(ValueError, match="subdivisions"):
        sphere(subdivisions=-1)
    with pytest.raises(TypeError, match="subdivisions"):
        sphere(subdivisions=2.0)
    with pytest.raises(ValueError, match="major_segments"):
        torus(major_segments=2)
    with pytest.raises(ValueError, match="segments"):
        slab(segments=0)
    with pytest.raises(TypeError, match="dtype"):
        plane(dtype=torch.int64)


# ------------------------------------------------------------------------------------------------------------
# clean-up and validation
# ------------------------------------------------------------------------------------------------------------


def test_triangle_soup_is_welded():
    ref = sphere(subdivisions=3)
    soup = ref.triangles().reshape(-1, 3)
    faces = torch.arange(len(soup)).reshape(-1, 3)
    m = mesh_from_arrays(soup, faces, name="soup")
    assert m.num_vertices == ref.num_vertices and m.num_faces == ref.num_faces
    assert m.is_watertight and m.name == "soup"
    assert m.area == pytest.approx(ref.area, rel=1e-6)
    np.testing.assert_allclose(m.triangles().numpy(), ref.triangles().numpy())  # face order and corners kept
    # without merging: soup stays a soup, and is still watertight in trimesh's welded notion
    raw = mesh_from_arrays(soup, faces, merge=False)
    assert raw.num_vertices == len(soup) and raw.is_watertight


def test_welding_keeps_face_uvs():
    ref = sphere(subdivisions=1)
    tri = ref.triangles()
    # UVs depending on the corner (not only the position): a seam everywhere
    uv = torch.rand(ref.num_faces, 3, 2, generator=torch.Generator().manual_seed(0))
    m = mesh_from_arrays(tri.reshape(-1, 3), torch.arange(3 * ref.num_faces).reshape(-1, 3), face_uvs=uv)
    assert m.num_vertices == ref.num_vertices
    assert torch.equal(m.face_uvs, uv)
    assert torch.equal(m.triangles(), tri)


def test_degenerate_face_dropped_with_warning():
    ref = sphere(subdivisions=1)
    v = torch.cat([ref.vertices, torch.tensor([[50.0, 0, 0], [51, 0, 0], [52, 0, 0]])])  # collinear
    n = ref.num_vertices
    extra = torch.tensor([[n, n + 1, n + 2], [0, 0, 1]])  # zero area, repeated index
    faces = torch.cat([ref.faces, extra])
    uv = torch.zeros(len(faces), 3, 2)
    uv[:, :, 0] = torch.arange(len(faces), dtype=torch.float32)[:, None] / len(faces)
    with pytest.warns(MeshWarning, match="dropped 2 degenerate faces") as record:
        m = mesh_from_arrays(v, faces, face_uvs=uv)
    assert sum(issubclass(r.category, MeshWarning) for r in record) == 1
    assert m.num_faces == ref.num_faces
    assert m.num_vertices == ref.num_vertices  # the collinear vertices became unreferenced and were removed
    assert torch.equal(m.face_uvs, uv[: ref.num_faces])
    # only degenerate faces: nothing left
    with pytest.raises(ValueError, match="degenerate"):
        mesh_from_arrays(v, extra)


def test_unreferenced_vertices_removed():
    ref = sphere(subdivisions=1)
    v = torch.cat([torch.full((5, 3), 1e3), ref.vertices])
    m = mesh_from_arrays(v, ref.faces + 5)
    assert m.num_vertices == ref.num_vertices
    assert m.size_mm == pytest.approx(ref.size_mm)


@pytest.mark.parametrize(
    ("vertices", "faces", "exc", "match"),
    [
        ([[0.0, 0, 0]], torch.zeros(1, 3, dtype=torch.long), TypeError, "vertices"),
        (torch.zeros(4, 2), torch.zeros(1, 3, dtype=torch.long), ValueError, "vertices"),
        (torch.zeros(4, 3, dtype=torch.bool), torch.zeros(1, 3, dtype=torch.long), TypeError, "vertices"),
        (torch.eye(3), torch.zeros(1, 3), TypeError, "faces"),
        (torch.eye(3), torch.zeros(1, 4, dtype=torch.long), ValueError, "faces"),
        (torch.eye(3), "faces", TypeError, "faces"),
        (torch.zeros(0, 3), torch.zeros(1, 3, dtype=torch.long), ValueError, "empty mesh"),
        (torch.eye(3), torch.zeros(0, 3, dtype=torch.long), ValueError, "mesh has no faces"),
        (torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, float("nan"), 0]]), torch.tensor([[0, 1, 2]]), ValueError,
         r"vertices.*finite"),
        (torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, float("inf"), 0]]), torch.tensor([[0, 1, 2]]), ValueError,
         r"vertices.*finite"),
        (torch.eye(3), torch.tensor([[0, 1, 3]]), ValueError, r"faces.*range"),
        (torch.eye(3), torch.tensor([[0, 1, -1]]), ValueError, r"faces.*range"),
    ],
)  # fmt: skip
def test_validation_errors(vertices, faces, exc, match):
    with pytest.raises(exc, match=match):
        mesh_from_arrays(vertices, faces)


def test_validation_face_uvs_and_options():
    v, f = torch.eye(3), torch.tensor([[0, 1, 2]])
    with pytest.raises(ValueError, match="face_uvs"):
        mesh_from_arrays(v, f, face_uvs=torch.zeros(2, 3, 2), warn_open=False)
    with pytest.raises(ValueError, match="face_uvs"):
        mesh_from_arrays(v, f, face_uvs=torch.zeros(1, 3, 3), warn_open=False)
    with pytest.raises(ValueError, match=r"face_uvs.*finite"):
        mesh_from_arrays(v, f, face_uvs=torch.full((1, 3, 2), float("nan")), warn_open=False)
    with pytest.raises(TypeError, match="face_uvs"):
        mesh_from_arrays(v, f, face_uvs=[[0.0, 0.0]] * 3, warn_open=False)
    with pytest.raises(ValueError, match="size_mm"):
        mesh_from_arrays(v, f, size_mm=0.0, warn_open=False)
    with pytest.raises(TypeError, match="dtype"):
        mesh_from_arrays(v, f, dtype=torch.int64, warn_open=False)
    with pytest.raises(TypeError, match="vertices"):
        Mesh(v.long(), f)
    with pytest.raises(TypeError, match="faces"):
        Mesh(v, f.float())


def test_numpy_input_and_dtypes():
    ref = sphere(subdivisions=1)
    m = mesh_from_arrays(ref.vertices.double().numpy(), ref.faces.numpy().astype(np.int32))
    assert m.vertices.dtype == torch.float32 and m.faces.dtype == torch.int64  # numpy -> default float32
    m64 = mesh_from_arrays(ref.vertices.double(), ref.faces)
    assert m64.vertices.dtype == torch.float64  # tensors keep their floating dtype
    m32 = mesh_from_arrays(ref.vertices.double(), ref.faces, dtype=torch.float32)
    assert m32.vertices.dtype == torch.float32


def test_open_sphere_warns():
    ref = sphere(subdivisions=2)
    with pytest.warns(MeshWarning, match="not watertight") as record:
        m = mesh_from_arrays(ref.vertices, ref.faces[3:])
    assert sum(issubclass(r.category, MeshWarning) for r in record) == 1
    assert not m.is_watertight
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)
        closed = mesh_from_arrays(ref.vertices, ref.faces)
    assert closed.is_watertight


def test_float64_path():
    m = sphere(radius_mm=3.0, subdivisions=3, dtype=torch.float64)
    assert m.vertices.dtype == torch.float64 and m.faces.dtype == torch.int64
    for t in (m.face_normals, m.face_areas, m.vertex_normals, m.vertex_areas, m.bounds, m.triangles()):
        assert t.dtype == torch.float64
    m32 = m.with_dtype(torch.float32)
    assert m32.vertices.dtype == torch.float32 and m32.area == pytest.approx(m.area, rel=1e-6)
    assert m.with_dtype(torch.float64) is m
    with pytest.raises(TypeError, match="dtype"):
        m.with_dtype(torch.int32)
    spot64 = load_mesh("spot", 30.0, dtype=torch.float64)
    assert spot64.vertices.dtype == torch.float64 and spot64.face_uvs.dtype == torch.float64
    check_normalised(spot64, 30.0)
    assert spot64.size_mm == pytest.approx(30.0, rel=1e-12)


def test_device_is_kept(device):
    ref = sphere(subdivisions=2).with_device(device)
    assert ref.vertices.device.type == device.type and ref.faces.device.type == device.type
    soup = ref.triangles().reshape(-1, 3)
    uv = torch.zeros(ref.num_faces, 3, 2, device=device)
    m = mesh_from_arrays(soup, torch.arange(len(soup), device=device).reshape(-1, 3), face_uvs=uv, size_mm=5.0)
    for t in (m.vertices, m.faces, m.face_uvs, m.face_normals, m.vertex_normals, m.vertex_areas):
        assert t.device.type == device.type
    assert m.num_vertices == ref.num_vertices and m.is_watertight
    check_normalised(m, 5.0)
    d = decimate(m, 100)
    assert d.vertices.device.type == device.type and d.faces.device.type == device.type


def test_read_only_numpy_input_does_not_warn():
    ref = sphere(subdivisions=1)
    v, f = ref.vertices.numpy().copy(), ref.faces.numpy().copy()
    v.flags.writeable = False
    f.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = mesh_from_arrays(v, f)
    assert m.num_faces == ref.num_faces


def test_mesh_is_frozen_and_gradients_flow():
    m = sphere(subdivisions=1)
    with pytest.raises(AttributeError):
        m.name = "x"
    v = m.vertices.clone().requires_grad_(True)
    g = mesh_from_arrays(v, m.faces)
    g.area  # noqa: B018 - recomputed (not cached) while vertices require grad
    g.face_areas.sum().backward()
    assert v.grad is not None and float(v.grad.abs().sum()) > 0
    assert "Mesh(name=''" in repr(g)


# ------------------------------------------------------------------------------------------------------------
# decimation and file formats
# ------------------------------------------------------------------------------------------------------------


def test_decimate_bunny(meshes_dir):
    full = load_mesh(meshes_dir / "stanford-bunny.obj", size_mm=30.0, warn_open=False)
    target = 2000
    small = decimate(full, target)
    assert abs(small.num_faces - target) <= 0.1 * target
    assert small.area == pytest.approx(full.area, rel=5e-2)
    assert small.size_mm == pytest.approx(full.size_mm, rel=2e-2)
    assert small.mm_per_unit == full.mm_per_unit and small.name == full.name
    assert small.faces.dtype == torch.int64 and small.vertices.dtype == torch.float32
    # the same through load_mesh, normalised after decimation
    loaded = load_mesh(meshes_dir / "stanford-bunny.obj", size_mm=30.0, decimate_to=target, warn_open=False)
    assert abs(loaded.num_faces - target) <= 0.1 * target
    check_normalised(loaded, 30.0)


def test_decimate_sphere_and_options():
    m = sphere(subdivisions=5)
    d = decimate(m, 2000)
    assert abs(d.num_faces - 2000) <= 200
    assert d.area == pytest.approx(m.area, rel=5e-2) and d.size_mm == pytest.approx(m.size_mm, rel=2e-2)
    assert signed_volume(d) > 0  # winding kept
    assert decimate(m, m.num_faces) is m and decimate(m, 10**7) is m
    with pytest.raises(ValueError, match="target_faces"):
        decimate(m, 3)
    with pytest.raises(TypeError, match="target_faces"):
        decimate(m, 2000.0)
    spot = load_mesh("spot")
    assert decimate(spot, 1000).face_uvs is None  # documented: decimation drops UVs


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "glb"])
def test_format_round_trip(tmp_path, ext):
    ref = torus(8.0, 3.0, 24, 12, dtype=torch.float64)
    path = tmp_path / f"torus.{ext}"
    ref.to_trimesh().export(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)  # closed after welding, whatever the format's layout
        m = load_mesh(path)
    assert m.name == "torus"
    assert m.num_faces == ref.num_faces and m.num_vertices == ref.num_vertices
    assert m.area == pytest.approx(ref.area, rel=1e-5)
    assert signed_volume(m) == pytest.approx(signed_volume(ref), rel=1e-5)
    s = load_mesh(path, size_mm=10.0)
    check_normalised(s, 10.0)


def test_scene_with_several_geometries_is_concatenated(tmp_path):
    a = sphere(2.0, subdivisions=2).to_trimesh()
    b = sphere(1.0, subdivisions=2).to_trimesh()
    b.apply_translation([10.0, 0.0, 0.0])
    path = tmp_path / "two.glb"
    trimesh.Scene([a, b]).export(path)
    m = load_mesh(path)
    assert m.num_faces == 640
    assert m.area == pytest.approx(a.area + b.area, rel=1e-5)


def test_surface_deviation_samples_a_large_mesh(monkeypatch):
    # past 8,192 vertices the quantile is read from a seeded sample of them: within 2% of all of them, the same
    # on every call
    import torchsss.geometry.mesh as mesh_module
    from torchsss.geometry.mesh import surface_deviation

    fine = sphere(10.0, 6)  # 40,962 vertices
    v = fine.vertices
    u = v / v.norm(dim=1, keepdim=True)
    bumps = 1.0 + 0.02 * torch.sin(25 * u[:, 0]) * torch.sin(25 * u[:, 1]) * torch.sin(25 * u[:, 2] + 1.0)
    fine = Mesh(vertices=v * bumps.unsqueeze(-1), faces=fine.faces, name="bumpy")
    coarse = decimate(fine, 2000)
    sampled = surface_deviation(fine, coarse)
    assert sampled == surface_deviation(fine, coarse) > 0
    monkeypatch.setattr(mesh_module, "_DEVIATION_SAMPLES", 10 ** 9)
    assert sampled == pytest.approx(surface_deviation(fine, coarse), rel=0.02)
