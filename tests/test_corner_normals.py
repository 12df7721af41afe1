"""Creased shading normals (``Mesh.corner_normals``): a loop reference, closed cases, gradients, and their use."""

from __future__ import annotations

import math

import pytest
import torch

from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import interpolate_normals, layer_gbuffer
from torchsss.geometry.mesh import CREASE_DEG, Mesh
from torchsss.geometry.procedural import slab, sphere, torus
from torchsss.geometry.raster import rasterize
from torchsss.geometry.sampling import surface_samples


def _loop_corner_normals(mesh: Mesh, crease_deg: float) -> torch.Tensor:
    """Per corner: the area-weighted normal of the faces at its vertex within ``crease_deg`` of its face (loops)."""
    v, f = mesh.vertices.double(), mesh.faces.tolist()
    cross = [torch.linalg.cross(v[b] - v[a], v[c] - v[a], dim=-1) for a, b, c in f]
    unit = [c / c.norm() if c.norm() > 0 else c * 0 for c in cross]
    around: dict[int, list[int]] = {}
    for i, face in enumerate(f):
        for vert in face:
            around.setdefault(vert, []).append(i)
    cos = math.cos(math.radians(crease_deg))
    out = torch.zeros(len(f), 3, 3, dtype=torch.float64)
    for i, face in enumerate(f):
        for k, vert in enumerate(face):
            kept = [cross[j] for j in around[vert] if float(unit[i] @ unit[j]) >= cos]
            acc = sum(kept, torch.zeros(3, dtype=v.dtype))
            out[i, k] = acc / acc.norm()
    return out


def _creased_torus() -> Mesh:
    """A coarse torus (5 x 4 segments: dihedral angles 72° and 90°) with one vertex pulled out into a spike."""
    m = torus(10.0, 4.0, major_segments=5, minor_segments=4, dtype=torch.float64)
    v = m.vertices.clone()
    v[0] = v[0] * 1.6
    return Mesh(v, m.faces)


@pytest.mark.parametrize("crease", [30.0, 60.0, 80.0, 100.0])
def test_corner_normals_match_a_loop_reference(crease):
    m = _creased_torus()
    ref = _loop_corner_normals(m, crease)
    torch.testing.assert_close(m.corner_normals(crease), ref, rtol=0, atol=1e-12)


def test_corner_normals_closed_cases():
    """A slab (only 0° and 90° edges): every corner the flat face normal, where the smooth normals tilt 45° at the
    rims; a sphere (no crease): the vertex normals exactly; crease 180°: the vertex normals everywhere."""
    s = slab(10.0, 8.0, 2.0, segments=3, dtype=torch.float64)
    flat = s.face_normals[:, None].expand(-1, 3, -1)
    torch.testing.assert_close(s.corner_normals(), flat, rtol=0, atol=1e-12)
    assert float((s.vertex_normals[s.faces] - flat).norm(dim=-1).max()) > 0.7  # smoothed over the rims: 45° off
    sp = sphere(10.0, 3, dtype=torch.float64)
    assert torch.equal(sp.corner_normals(), sp.vertex_normals[sp.faces])
    m = _creased_torus()
    torch.testing.assert_close(m.corner_normals(180.0), m.vertex_normals[m.faces], rtol=0, atol=1e-12)
    assert CREASE_DEG == 60.0
    assert m.corner_normals() is m.corner_normals(60)  # cached per angle


def test_corner_normals_extremes_and_bad_input():
    # a degenerate face (repeated vertex) next to a healthy one: finite, the healthy face keeps its normal
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], dtype=torch.float64)
    m = Mesh(v, torch.tensor([[0, 1, 2], [3, 3, 1]]))
    n = m.corner_normals()
    assert bool(torch.isfinite(n).all())
    torch.testing.assert_close(n[0], torch.tensor([[0.0, 0, 1]] * 3, dtype=torch.float64))
    empty = Mesh(torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int64))
    assert tuple(empty.corner_normals().shape) == (0, 3, 3)
    # a knife edge (two faces folded back onto each other): each keeps its own side
    fold = Mesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 1e-3]], dtype=torch.float64),
                torch.tensor([[0, 1, 2], [0, 3, 1]]))
    torch.testing.assert_close(fold.corner_normals(), fold.face_normals[:, None].expand(-1, 3, -1))
    with pytest.raises(TypeError, match="crease_deg"):
        m.corner_normals("60")
    for bad in (0.0, -5.0, 181.0, math.nan):
        with pytest.raises(ValueError, match="crease_deg"):
            m.corner_normals(bad)


def test_corner_normals_gradcheck():
    m = _creased_torus()
    v0 = m.vertices.clone().requires_grad_(True)
    weights = torch.randn(m.num_faces, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def f(v):
        return (Mesh(v, m.faces).corner_normals() * weights).sum()

    assert torch.autograd.gradcheck(f, (v0,))


def test_gbuffer_and_samples_use_creased_normals():
    """Seen from an oblique camera, every pixel of a slab carries its face's flat normal (the default); the
    smoothed vertex normals bend the rims' pixels; surface samples carry the flat normals too."""
    s = slab(20.0, 20.0, 4.0, segments=4, dtype=torch.float64)
    cam = Camera(eye=(30.0, 25.0, 40.0), target=(0, 0, 0), width=64, height=64)
    vp = cam.view_proj(dtype=torch.float64)
    layer = layer_gbuffer(s, vp, 64)
    mask = layer.mask[0, 0]
    face = layer.face_id[0, 0][mask]
    got = layer.normal[0].permute(1, 2, 0)[mask]
    torch.testing.assert_close(got, s.face_normals[face], rtol=0, atol=1e-9)
    smooth = layer_gbuffer(s, vp, 64, normals=s.vertex_normals).normal[0].permute(1, 2, 0)[mask]
    assert float((smooth - s.face_normals[face]).norm(dim=-1).max()) > 0.3
    per_corner = layer_gbuffer(s, vp, 64, normals=s.corner_normals()).normal
    torch.testing.assert_close(per_corner, layer.normal)
    raster = rasterize(torch.nn.functional.pad(s.vertices, (0, 1), value=1.0) @ vp.T, s.faces, (64, 64))
    with pytest.raises(ValueError, match=r"normals: expected a tensor of shape .* or \(96, 3, 3\)"):
        interpolate_normals(s, raster, s.corner_normals()[:-1])
    samples = surface_samples(s, 2.0)
    torch.testing.assert_close(samples.normal, s.face_normals[samples.face_id], rtol=0, atol=1e-12)
