"""Graded refinement towards creases and open boundaries (torchsss.geometry.refine) and its use in Lensch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import loop_edge_faces

from torchsss.geometry.mesh import Mesh, split_creases
from torchsss.geometry.procedural import plane, slab, sphere
from torchsss.geometry.refine import _distance_to_features, feature_edges, refine_creases

F64 = torch.float64


def _loop_features(mesh: Mesh, crease_deg: float) -> set[tuple[int, int]]:
    """Loop reference: every edge with one face, more than two, or two whose normals turn by more than the crease."""
    normals = mesh.face_normals.double()
    around = loop_edge_faces(mesh.faces.tolist())
    out = set()
    for e, fs in around.items():
        if len(fs) != 2 or float(normals[fs[0]] @ normals[fs[1]]) < math.cos(math.radians(crease_deg)):
            out.add(e)
    return out


@pytest.mark.parametrize("crease", [30.0, 60.0, 100.0])
def test_feature_edges_match_a_loop_reference(crease):
    for mesh in (slab(10.0, 8.0, 1.0, segments=3), plane(5.0, 5.0, segments=3), sphere(4.0, 1)):
        got = {tuple(e) for e in feature_edges(mesh, crease).tolist()}
        assert got == _loop_features(mesh, crease)


def test_feature_edges_of_closed_smooth_and_open_meshes():
    assert feature_edges(sphere(5.0, 2)).shape == (0, 2)
    assert feature_edges(plane(4.0, 4.0, segments=2)).shape[0] == 8  # the open square's boundary
    assert feature_edges(slab(10.0, 10.0, 1.0, segments=2)).shape[0] == 20  # 8 rim lines x 2 and 4 corner edges


def test_refined_slab_is_the_same_closed_surface():
    m = slab(17.7, 17.7, 0.88, segments=16, dtype=F64)
    r, parent = refine_creases(m, 0.08)
    assert r.num_vertices > 3 * m.num_vertices
    assert r.is_watertight
    # every new face lies in its parent: the parents' areas are conserved face by face, the normals kept
    area = torch.zeros(m.num_faces, dtype=F64).index_add_(0, parent, r.face_areas)
    torch.testing.assert_close(area, m.face_areas, rtol=1e-9, atol=0.0)
    torch.testing.assert_close(r.face_normals, m.face_normals[parent], rtol=0.0, atol=1e-9)
    assert float(r.face_areas.min()) > 0.0
    # no new vertex leaves the surface: each lies on its parent face's plane
    tri = m.vertices[m.faces[parent]]
    corner = r.vertices[r.faces]  # (F', 3, 3)
    off = ((corner - tri[:, :1]) * m.face_normals[parent][:, None]).sum(-1)
    assert float(off.abs().max()) < 1e-9


def test_rows_lie_at_the_graded_distances():
    """The new vertices of a flat plate's face lie on the level sets g_k = first * ratio^k of the distance to the
    boundary (within the linear interpolation of the distance on a face: exact on a plate's straight edges away
    from the corners)."""
    m = plane(20.0, 20.0, segments=8, dtype=F64)
    first, ratio, reach = 0.1, 1.6, 4.0
    r, _ = refine_creases(m, first, ratio=ratio, reach_mm=reach)
    v = r.vertices[m.num_vertices:]
    d = (10.0 - v[:, :2].abs()).amin(1)  # distance to the square's boundary
    # away from the corners (one edge, 2.5 mm, beyond where another side of the square is within the reach)
    inner = v[:, :2].abs().amin(1) < 10.0 - reach - 2.5
    levels = first * ratio ** torch.arange(12, dtype=F64)
    levels = levels[levels < reach]
    gap = (d[:, None] - levels[None, :]).abs().amin(1)
    assert inner.sum() > 50
    assert float(gap[inner].max()) < 1e-9
    # and every level is present
    for lv in levels.tolist():
        assert bool(((d - lv).abs() < 1e-9).any())


def test_distance_field_against_brute_force():
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(300, 3, generator=g, dtype=F64) * 10).numpy()
    a = (torch.rand(40, 3, generator=g, dtype=F64) * 10).numpy()
    b = a + (torch.rand(40, 3, generator=g, dtype=F64) - 0.5).numpy() * 4
    got = _distance_to_features(pts, a, b, 2.0)
    ab = b - a
    t = np.clip(((pts[:, None] - a[None]) * ab[None]).sum(-1) / (ab * ab).sum(-1)[None], 0, 1)
    want = np.linalg.norm(pts[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1).min(1)
    near = want <= 2.0
    np.testing.assert_allclose(got[near], want[near], rtol=1e-12)
    assert np.isinf(got[~near]).all()


def test_refinement_is_differentiable_and_keeps_uvs():
    m = plane(4.0, 4.0, segments=2, dtype=F64)
    uv = (m.vertices[:, :2] / 4.0 + 0.5)[m.faces]  # per-corner uv of the planar map
    v = m.vertices.clone().requires_grad_(True)
    m2 = Mesh(v, m.faces, face_uvs=uv)
    r, _ = refine_creases(m2, 0.2, reach_mm=1.0)
    r.vertices.sum().backward()
    # each new vertex is a convex combination of the originals: the gradient of the sum counts every vertex once
    assert float(v.grad.sum()) == pytest.approx(3.0 * r.num_vertices)
    # the interpolated uvs are the planar map at the new corners
    torch.testing.assert_close(r.face_uvs, (r.vertices.detach()[:, :2] / 4.0 + 0.5)[r.faces], rtol=0, atol=1e-12)


def test_nothing_to_refine_returns_the_mesh():
    s = sphere(5.0, 2)
    r, parent = refine_creases(s, 0.1)
    assert r is s and torch.equal(parent, torch.arange(s.num_faces))
    p = plane(4.0, 4.0, segments=2)
    r, _ = refine_creases(p, 5.0, reach_mm=1.0)  # the first row beyond the reach
    assert r is p


def test_typed_errors():
    m = slab(5.0, 5.0, 1.0, segments=2)
    with pytest.raises(TypeError, match="mesh"):
        refine_creases("slab", 0.1)
    with pytest.raises(TypeError, match="first_mm"):
        refine_creases(m, "0.1")
    with pytest.raises(ValueError, match="first_mm"):
        refine_creases(m, -0.1)
    with pytest.raises(ValueError, match="ratio"):
        refine_creases(m, 0.1, ratio=1.0)
    with pytest.raises(TypeError, match="ratio"):
        refine_creases(m, 0.1, ratio=None)
    with pytest.raises(ValueError, match="reach_mm"):
        refine_creases(m, 0.1, reach_mm=0.0)
    with pytest.raises(ValueError, match="crease_deg"):
        refine_creases(m, 0.1, crease_deg=200.0)
    with pytest.raises(ValueError, match="crease_deg"):
        feature_edges(m, 0.0)


def test_split_of_a_refined_slab_parts_its_rows_at_the_creases():
    """The refined slab's hats still part at the creases: a row vertex on a crease gets one copy per side."""
    m = slab(10.0, 10.0, 1.0, segments=4)
    r, _ = refine_creases(m, 0.1, reach_mm=1.5)
    split, origin = split_creases(r)
    assert split.num_vertices > r.num_vertices
    assert torch.equal(split.vertices, r.vertices[origin])


# ----------------------------------------------------------------------------------------------------------------
# in Lensch: the throughput's cut, the split of the radiosity, the texels lit on their parents, the rim-lit slab
# ----------------------------------------------------------------------------------------------------------------


def _cream():
    from torchsss.modules import DipoleMaterial

    return DipoleMaterial.from_preset("cream").requires_grad_(False)


def test_cut_area_gives_small_hats_the_reach_of_large_ones():
    from torchsss.geometry.lensch import (
        THROUGHPUT_THRESHOLD,
        _absolute_threshold,
        _keep_radius,
        _profile64,
        build_throughput,
        estimate_throughput_entries,
    )

    m = slab(12.0, 12.0, 0.6, segments=6)
    r, _ = refine_creases(m, 0.05, reach_mm=1.5)
    mat = _cream()
    plain = build_throughput(r, mat, max_entries=None)
    ref_area = float(m.vertex_areas.median())
    cut = build_throughput(r, mat, max_entries=None, cut_area=ref_area)
    assert cut.rows.numel() > plain.rows.numel()
    # a small source keeps every receiver out to the distance where a hat of the reference area drops them
    prof, _ = _profile64(mat, r.vertices.device)
    radius = _keep_radius(ref_area, prof, _absolute_threshold(r.vertex_areas.double(), prof, THROUGHPUT_THRESHOLD,
                                                              True), r.vertices.device)
    small = (r.vertex_areas < 0.2 * ref_area).nonzero()[:, 0]
    d = torch.cdist(r.vertices[small].double(), r.vertices.double())
    inside = int((d < 0.999 * radius).sum())
    assert inside > 0

    def kept(tp):
        sel = torch.isin(tp.rows, small) & (tp.distance.double() < 0.999 * radius)
        return int(sel.sum())

    assert kept(cut) == inside > kept(plain)
    est = estimate_throughput_entries(r, mat, cut_area=ref_area, rows=256)
    assert 0.8 < est / cut.rows.numel() < 1.25
    with pytest.raises(ValueError, match="cut_area"):
        build_throughput(r, mat, max_entries=None, cut_area=-1.0)


def test_split_parts_add_up_to_the_module():
    from torchsss.pipelines.lensch import build_lensch

    m = slab(8.0, 8.0, 0.8, segments=4)
    built = build_lensch(m, _cream(), resolution=128, refine_mm=0.1)
    assert built.parent_faces is not None and built.mesh.num_vertices > m.num_vertices
    g = torch.Generator().manual_seed(1)
    e = torch.rand(1, 3, 128, 128, generator=g) * built.atlas.valid_mask
    with torch.no_grad():
        whole = built.module(e)
        local, vert = built.module.split(e)
        torch.testing.assert_close(local + built.module.global_response.reconstruct(vert), whole, rtol=1e-5,
                                   atol=1e-7)
    with pytest.raises(ValueError, match="refine_mm"):
        build_lensch(m, _cream(), resolution=64, refine_mm="fine")
    with pytest.raises(ValueError, match="blend"):
        build_lensch(m, _cream(), resolution=64, refine_mm=0.1, blend=True)
    with pytest.raises(ValueError, match="refine_mm"):
        build_lensch(m, _cream(), resolution=64, refine_mm=0.1, detail=False)


def test_texels_of_a_refined_mesh_are_lit_on_their_parent_face():
    """No texel beside a crease takes the normal of the face across it (the rim's light on the face beside it)."""
    from torchsss import build

    m = slab(8.0, 8.0, 0.8, segments=4)
    r = build("lensch", m, _cream(), atlas_resolution=256, refine_mm=0.1)
    index, position, normal = r.view.lit_texels()
    face = r.built.parent_faces[r.atlas.face_id.reshape(-1)[index]]
    torch.testing.assert_close(normal, m.face_normals[face], rtol=0.0, atol=1e-5)
    # and every texel lies on its parent face
    off = ((position - m.vertices[m.faces[face, 0]]) * m.face_normals[face]).sum(-1)
    assert float(off.abs().max()) < 1e-4


def _rim_lit_slab(d: float, res: int, atlas: int):
    """The spread's rim-lit cream slab scene (its diagonal ``d`` mm, a 1:1:0.05 box of 16 x 16 quads a face, lit in
    its own plane from the side, a 5% fill beside the camera) and its reference, Lensch unrefined and graded."""
    from pathlib import Path

    from torchsss import build
    from torchsss.scene import Scene
    from torchsss.trade import image_error

    fill = (1.2 * d, 0.6 * d, 1.6 * d)
    scene = Scene.from_dict({
        "name": "rim-lit slab", "mesh": "slab", "size_mm": d, "material": "cream",
        "lights": [{"type": "point", "position": [2.5 * d, 0.5 * d, 0.0], "intensity": [(2.5 * d) ** 2] * 3},
                   {"type": "point", "position": list(fill), "intensity": [0.05 * sum(c * c for c in fill)] * 3}],
        "camera": {"eye": [0.0, 0.25 * d, 1.6 * d], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
                   "fov_deg": 30.0, "width": res, "height": res}}, base_dir=Path.cwd())
    m, lights, cam = scene.load_mesh(), scene.lights, scene.camera
    ref = build("reference", m, "cream").render(lights, cam)
    plain = build("lensch", m, "cream", atlas_resolution=atlas, refine_mm=None).render(lights, cam)
    graded = build("lensch", m, "cream", atlas_resolution=atlas, refine_mm="auto", max_entries=None)
    assert graded.knobs["refine_mm"] == pytest.approx(0.5 * float(_cream().spacing(0.01).min()))
    out = graded.render(lights, cam)
    assert graded.knobs["interpolation"] == "adaptive"
    graded.knobs["interpolation"] = "linear"  # a frame knob: the same build, the lights' radiosity kept
    out_linear = graded.render(lights, cam)
    both = (ref.mask & out.mask).expand_as(ref.radiance)
    mean = float(out.radiance[both].mean() / ref.radiance[both].mean())
    print("plain", image_error(plain, ref), "graded", image_error(out, ref), "linear", image_error(out_linear, ref))
    return (image_error(plain, ref)["rel_rmse"], image_error(out, ref)["rel_rmse"],
            image_error(out_linear, ref)["rel_rmse"], mean)


def test_rim_lit_small_slab_against_the_reference():
    """A 12.5 mm rim-lit cream slab at 48 x 48, atlas 512: graded rows along the creases cut Lensch's error to less
    than a third (measured 4.6% -> 0.98%; 1.48% with the rows interpolated linearly), its image mean within 2%."""
    e_plain, e_graded, e_linear, mean = _rim_lit_slab(12.5, 48, 512)
    assert e_plain > 0.035
    assert e_graded < 0.3 * e_plain and e_graded < 0.015
    assert e_graded < e_linear  # the geometric mean of the rows follows the fall-off beside the lit crease
    assert mean == pytest.approx(1.0, abs=0.02)


@pytest.mark.slow
def test_rim_lit_slab_against_the_reference():
    """The spread's 25 mm rim-lit slab at 64 x 64, atlas 1024, rows at ratio 1.6 (no entry cap): measured 7.1% ->
    2.95% (3.28% with the rows interpolated linearly; 18.4% before the vertex radiosity was read at each pixel); at
    256 x 256 with the renderer's defaults 7.3% -> 3.06% (benchmarks/results/spread_lensch_refine.md); the image
    mean within 2%."""
    e_plain, e_graded, e_linear, mean = _rim_lit_slab(25.0, 64, 1024)
    assert e_graded < e_linear
    assert e_plain > 0.05  # the hats cannot follow the radiosity beside the lit crease
    assert e_graded < 0.5 * e_plain and e_graded < 0.04
    assert mean == pytest.approx(1.0, abs=0.02)
