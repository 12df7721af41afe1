"""Rasterizer: coverage against brute force, depth test, crack-free meshes, ray-casting agreement, interpolation."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from torchsss.geometry import raster as raster_module
from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.raster import Raster, interpolate, rasterize, rasterize_uv

F64 = torch.float64


# -- helpers --------------------------------------------------------------------------------------------------------
def _clip(ndc_xy, z=0.0, w=1.0, dtype=F64) -> torch.Tensor:
    """Clip coordinates of points given in NDC (x, y) at NDC depth z, scaled by w (so that x / w = ndc)."""
    pts = torch.as_tensor(ndc_xy, dtype=F64)
    n = pts.shape[0]
    w_t = torch.as_tensor(w, dtype=F64).expand(n)
    z_t = torch.as_tensor(z, dtype=F64).expand(n)
    return torch.stack([pts[:, 0] * w_t, pts[:, 1] * w_t, z_t * w_t, w_t], dim=1).to(dtype)


def _pixel_of_ndc(x, y, height, width):
    """Continuous pixel coordinates (column, row) of an NDC point; centres at i + 0.5, row 0 at the top."""
    return (x + 1) / 2 * width, (1 - y) / 2 * height


def _contains(tri, px, py) -> bool:
    """Inclusive point-in-triangle test in exact arithmetic (tri: three (col, row) Fractions)."""
    (ax, ay), (bx, by), (cx, cy) = tri
    d1 = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
    d2 = (cx - bx) * (py - by) - (cy - by) * (px - bx)
    d3 = (ax - cx) * (py - cy) - (ay - cy) * (px - cx)
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    if area == 0:
        return False
    return (d1 >= 0 and d2 >= 0 and d3 >= 0) or (d1 <= 0 and d2 <= 0 and d3 <= 0)


def _brute_force(ndc_tris, height, width) -> list[list[set[int]]]:
    """For every pixel centre, the set of triangles (given by NDC corners, w = 1) that contain it, exactly."""
    tris = []
    for tri in ndc_tris:
        tris.append([tuple(map(Fraction, _pixel_of_ndc(Fraction(x), Fraction(y), height, width))) for x, y in tri])
    out = []
    for r in range(height):
        row = []
        for c in range(width):
            p = (Fraction(2 * c + 1, 2), Fraction(2 * r + 1, 2))
            row.append({i for i, t in enumerate(tris) if _contains(t, *p)})
        out.append(row)
    return out


def _grid_mesh(n: int, lo: float, hi: float, pattern: str):
    """An n x n grid of squares over [lo, hi]^2 (NDC): '/' or '\\' diagonals, or 'x' (both, with a centre vertex)."""
    ticks = [lo + (hi - lo) * i / n for i in range(n + 1)]
    verts = [(x, y) for y in ticks for x in ticks]
    faces = []

    def vid(i, j):
        return j * (n + 1) + i

    for j in range(n):
        for i in range(n):
            a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)  # CCW in NDC (y up)
            if pattern == "/":
                faces += [(a, b, c), (a, c, d)]
            elif pattern == "\\":
                faces += [(a, b, d), (b, c, d)]
            else:
                m = len(verts)
                verts.append(((ticks[i] + ticks[i + 1]) / 2, (ticks[j] + ticks[j + 1]) / 2))
                faces += [(a, b, m), (b, c, m), (c, d, m), (d, a, m)]
    return verts, faces


def _load_scaled(path, size_mm=100.0):
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.load(str(path), force="mesh")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    v = (v - (lo + hi) / 2) * (size_mm / np.linalg.norm(hi - lo))
    return trimesh.Trimesh(v, np.asarray(mesh.faces), process=False)


def _embree_agreement(mesh, cam: Camera):
    """Face ids from rasterize vs trimesh ray casting (first hit) through the same pixel centres."""
    verts = torch.tensor(mesh.vertices, dtype=torch.float32)
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    ras = rasterize(transform_points(verts, cam.view_proj()), faces, cam.resolution)
    o, d = cam.rays(dtype=F64)
    hit = mesh.ray.intersects_first(o[0].reshape(3, -1).T.numpy(), d[0].reshape(3, -1).T.numpy())
    ref = torch.as_tensor(hit, dtype=torch.int64).view(1, 1, *cam.resolution)
    mask_ref = ref >= 0
    mask_agree = (mask_ref == ras.mask).double().mean().item()
    background = (~mask_ref | ~ras.mask).double()
    interior = F.max_pool2d(background, 3, stride=1, padding=1) == 0  # 3x3 neighbourhood fully covered in both
    agree = (ras.face_id[interior] == ref[interior]).double().mean().item()
    return agree, mask_agree, int(interior.sum())


# -- a single triangle ----------------------------------------------------------------------------------------------
TRI_NDC = [(-0.83, -0.71), (0.77, -0.29), (-0.13, 0.91)]  # CCW; no pixel centre of a 13 x 17 image on an edge


def test_single_triangle_coverage_matches_brute_force(dtype, device):
    height, width = 13, 17
    ras = rasterize(_clip(TRI_NDC, z=0.25, dtype=dtype).to(device), torch.tensor([[0, 1, 2]], device=device),
                    (height, width))
    assert isinstance(ras, Raster)
    assert ras.face_id.shape == (1, 1, height, width) and ras.face_id.dtype == torch.int64
    assert ras.bary.shape == (1, 3, height, width) and ras.bary.dtype == dtype
    assert ras.depth.shape == (1, 1, height, width) and ras.depth.dtype == dtype
    assert ras.mask.shape == (1, 1, height, width) and ras.mask.dtype == torch.bool
    assert ras.face_id.device.type == device.type
    ref = _brute_force([TRI_NDC], height, width)
    expect = torch.tensor([[bool(s) for s in row] for row in ref])
    assert 40 < int(expect.sum()) < height * width  # a real test: some pixels in, some out
    assert torch.equal(ras.mask[0, 0].cpu(), expect)
    assert torch.equal(ras.face_id[0, 0].cpu(), torch.where(expect, 0, -1))
    # background conventions
    bg = ~ras.mask
    assert bool((ras.bary.masked_select(bg) == 0).all()) and bool(torch.isinf(ras.depth[bg]).all())
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(ras.depth[ras.mask], torch.full_like(ras.depth[ras.mask], 0.25), rtol=0, atol=tol)


@pytest.mark.parametrize("perspective_w", [False, True])
def test_barycentrics_reproduce_pixel_centres(dtype, perspective_w):
    height, width = 13, 17
    w = [1.7, 0.4, 3.1] if perspective_w else 1.0
    clip = _clip(TRI_NDC, z=0.1, w=w, dtype=dtype)
    ras = rasterize(clip, torch.tensor([[0, 1, 2]]), (height, width))
    m = ras.mask[0, 0]
    b = ras.bary[0][:, m].double()  # (3, K), perspective-correct
    torch.testing.assert_close(b.sum(0), torch.ones(b.shape[1], dtype=F64), rtol=0, atol=1e-6)
    assert bool((b >= 0).all())
    # clip coordinates interpolate linearly with perspective-correct weights; the divide gives the pixel centre
    c = clip.double()
    x = (b * c[:, 0:1]).sum(0) / (b * c[:, 3:4]).sum(0)
    y = (b * c[:, 1:2]).sum(0) / (b * c[:, 3:4]).sum(0)
    rows, cols = torch.nonzero(m, as_tuple=True)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(x, (2 * (cols.double() + 0.5) / width - 1), rtol=0, atol=tol)
    torch.testing.assert_close(y, (1 - 2 * (rows.double() + 0.5) / height), rtol=0, atol=tol)


def test_perspective_correct_interpolation_equals_ray_plane_intersection():
    cam = Camera(eye=(30.0, 20.0, 150.0), target=(0.0, 0.0, 0.0), fov_deg=40.0, width=48, height=40)
    world = torch.tensor([[-40.0, -30.0, -35.0], [45.0, -20.0, 30.0], [-5.0, 45.0, 10.0]], dtype=F64)  # tilted
    faces = torch.tensor([[0, 1, 2]])
    ras = rasterize(transform_points(world, cam.view_proj(dtype=F64)), faces, cam.resolution)
    assert int(ras.mask.sum()) > 300
    pos = interpolate(world, ras, faces)  # (1, 3, H, W)
    o, d = cam.rays(dtype=F64)
    normal = torch.linalg.cross(world[1] - world[0], world[2] - world[0])
    t = ((world[0] - o[0].permute(1, 2, 0)) @ normal) / (d[0].permute(1, 2, 0) @ normal)
    hit = o[0] + t * d[0]  # (3, H, W)
    m = ras.mask[0, 0]
    err = (pos[0][:, m] - hit[:, m]).abs().max().item()
    assert err < 1e-9, err
    assert bool((pos[0][:, ~m] == 0).all())
    # depth is the NDC z of the hit point
    clip_hit = transform_points(hit[:, m].T, cam.view_proj(dtype=F64))[0]
    torch.testing.assert_close(ras.depth[0, 0][m], clip_hit[:, 2] / clip_hit[:, 3], rtol=0, atol=1e-12)


# -- visibility -----------------------------------------------------------------------------------------------------
def test_nearer_triangle_wins_and_face_order_does_not_matter(dtype):
    tri_a = [(-0.9, -0.9), (0.6, -0.8), (-0.7, 0.7)]  # far, z = 0.5
    tri_b = [(-0.5, -0.6), (0.9, -0.2), (0.1, 0.9)]  # near, z = -0.2
    clip = torch.cat([_clip(tri_a, z=0.5, dtype=dtype), _clip(tri_b, z=-0.2, dtype=dtype)])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    res = (24, 32)
    ras = rasterize(clip, faces, res)
    only_a = rasterize(clip, faces[:1], res).mask[0, 0]
    only_b = rasterize(clip, faces[1:], res).mask[0, 0]
    both = only_a & only_b
    assert int(both.sum()) > 30
    fid = ras.face_id[0, 0]
    assert bool((fid[only_b] == 1).all()) and bool((fid[only_a & ~only_b] == 0).all())
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(ras.depth[0, 0][both], torch.full_like(ras.depth[0, 0][both], -0.2), rtol=0, atol=tol)
    swapped = rasterize(clip, faces.flip(0), res)
    assert torch.equal(torch.where(swapped.face_id >= 0, 1 - swapped.face_id, -1), ras.face_id)
    assert torch.equal(swapped.depth, ras.depth) and torch.equal(swapped.mask, ras.mask)
    assert torch.equal(swapped.bary, ras.bary)


def test_depth_ties_go_to_lower_face_id_and_result_is_deterministic():
    clip = _clip(TRI_NDC, z=0.3)
    faces = torch.tensor([[0, 1, 2], [1, 2, 0], [2, 0, 1]])  # the same triangle three times
    ras = rasterize(clip, faces, (13, 17))
    assert set(ras.face_id[ras.mask].tolist()) == {0}
    again = rasterize(clip, faces, (13, 17))
    for a, b in zip(ras, again):
        assert torch.equal(a, b)
    last = rasterize(clip, faces[[2, 1]], (13, 17))  # ids are input positions
    assert set(last.face_id[last.mask].tolist()) == {0}
    # the same point gets the same barycentric weights, relabelled with the face's vertex order
    torch.testing.assert_close(last.bary[0, :, 6, 8], ras.bary[0, [2, 0, 1], 6, 8])


def test_backface_culling():
    cw = [TRI_NDC[0], TRI_NDC[2], TRI_NDC[1]]
    clip = torch.cat([_clip(TRI_NDC), _clip(cw)])
    front, back = torch.tensor([[0, 1, 2]]), torch.tensor([[3, 4, 5]])
    assert int(rasterize(clip, back, (13, 17)).mask.sum()) > 40
    assert int(rasterize(clip, back, (13, 17), cull_backfaces=True).mask.sum()) == 0
    assert torch.equal(rasterize(clip, front, (13, 17), cull_backfaces=True).mask,
                       rasterize(clip, back, (13, 17)).mask)
    # winding does not change the weights of a vertex
    r_cw = rasterize(clip, back, (13, 17))
    r_ccw = rasterize(clip, front, (13, 17))
    torch.testing.assert_close(r_cw.bary[:, [0, 2, 1]], r_ccw.bary)


# -- shared edges ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("pattern", ["/", "\\", "x"])
def test_grid_mesh_has_no_cracks_and_matches_brute_force(pattern):
    # vertices on integer pixel coordinates: the diagonals pass exactly through many pixel centres
    height, width = 16, 16
    verts, faces = _grid_mesh(6, -0.75, 0.75, pattern)
    ref = _brute_force([[verts[i] for i in f] for f in faces], height, width)
    ras = rasterize(_clip(verts, z=0.0), torch.tensor(faces), (height, width))
    fid = ras.face_id[0, 0]
    on_edge = 0
    for r in range(height):
        for c in range(width):
            inside_square = 2 <= r <= 13 and 2 <= c <= 13  # NDC [-0.75, 0.75] = pixels [2, 14]
            assert bool(ref[r][c]) == inside_square
            assert bool(ras.mask[0, 0, r, c]) == inside_square, (r, c)
            if inside_square:
                assert int(fid[r, c]) in ref[r][c], (r, c, int(fid[r, c]), ref[r][c])
                on_edge += len(ref[r][c]) > 1
    assert on_edge > 10  # the test really exercises centres on shared edges
    # each triangle on its own: a centre strictly inside one triangle is covered by it alone; one on a shared
    # edge by every triangle that shares it (the inclusive rule), so the union has no cracks
    count = torch.zeros(height, width, dtype=torch.int64)
    for f in range(len(faces)):
        count += rasterize(_clip(verts), torch.tensor(faces[f:f + 1]), (height, width)).mask[0, 0].long()
    expect = torch.tensor([[len(s) for s in row] for row in ref])
    assert torch.equal(count, expect)


def test_jittered_perspective_grid_has_no_cracks(dtype):
    # a grid with random interior vertices and random w (perspective), outer boundary fixed: the union is the square
    gen = torch.Generator().manual_seed(0)
    height, width = 40, 56
    n = 9
    verts, faces = _grid_mesh(n, -0.8, 0.8, "/")
    xy = torch.tensor(verts, dtype=F64)
    interior = (xy.abs() < 0.79).all(1)
    xy[interior] += (torch.rand(int(interior.sum()), 2, generator=gen, dtype=F64) - 0.5) * (1.6 / n) * 0.6
    w = 0.5 + 2 * torch.rand(xy.shape[0], generator=gen, dtype=F64)
    z = torch.rand(xy.shape[0], generator=gen, dtype=F64) * 0.5
    clip = torch.cat([xy * w[:, None], (z * w)[:, None], w[:, None]], 1).to(dtype)
    ras = rasterize(clip, torch.tensor(faces), (height, width))
    cols = (torch.arange(width, dtype=F64) + 0.5) * 2 / width - 1
    rows = 1 - (torch.arange(height, dtype=F64) + 0.5) * 2 / height
    inside = (rows.abs()[:, None] < 0.8) & (cols.abs()[None, :] < 0.8)
    assert torch.equal(ras.mask[0, 0], inside)


# -- ray-casting agreement ------------------------------------------------------------------------------------------
def test_face_ids_agree_with_embree_bunny(shared_dir):
    mesh = _load_scaled(shared_dir / "data" / "meshes" / "stanford-bunny.obj")
    cam = Camera(eye=(60.0, 40.0, 230.0), target=(0.0, 0.0, 0.0), fov_deg=40.0, width=512, height=512)
    agree, mask_agree, n = _embree_agreement(mesh, cam)
    print(f"\nbunny 512x512: face-id agreement {agree:.5f} on {n} interior pixels, mask agreement {mask_agree:.5f}")
    assert n > 10000
    assert agree >= 0.995, agree
    assert mask_agree > 0.99, mask_agree


def test_face_ids_agree_with_embree_spot(shared_dir):
    mesh = _load_scaled(shared_dir / "data" / "meshes" / "spot.obj")
    cam = Camera(eye=(-150.0, 60.0, 180.0), target=(0.0, 0.0, 0.0), fov_deg=40.0, width=256, height=256)
    agree, mask_agree, n = _embree_agreement(mesh, cam)
    print(f"\nspot 256x256: face-id agreement {agree:.5f} on {n} interior pixels, mask agreement {mask_agree:.5f}")
    assert n > 3000
    assert agree >= 0.995, agree
    assert mask_agree > 0.99, mask_agree


def test_face_ids_agree_with_embree_sphere():
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=30.0)
    cam = Camera(eye=(20.0, 50.0, 120.0), target=(0.0, 0.0, 0.0), fov_deg=40.0, width=128, height=96)
    agree, mask_agree, n = _embree_agreement(mesh, cam)
    assert n > 2000
    assert agree >= 0.995, agree
    assert mask_agree > 0.99, mask_agree


# -- interpolate ----------------------------------------------------------------------------------------------------
def _small_scene(dtype=F64):
    verts = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.2, 0.3], [1.1, 1.0, -0.2], [-0.9, 1.0, 0.1]], dtype=dtype)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    cam = Camera(eye=(0.5, 0.3, 4.0), target=(0.0, 0.0, 0.0), width=7, height=6, fov_deg=50.0)
    return verts, faces, cam


def test_interpolate_gradcheck():
    verts, faces, cam = _small_scene()
    ras = rasterize(transform_points(verts, cam.view_proj(dtype=F64)), faces, cam.resolution)
    assert int(ras.mask.sum()) > 10
    attr = torch.randn(4, 2, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: interpolate(a, ras, faces), (attr,))
    battr = torch.randn(1, 4, 3, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: interpolate(a, ras, faces), (battr,))


def test_bary_and_depth_are_differentiable_wrt_clip():
    clip = _clip(TRI_NDC, z=0.2, w=[1.3, 0.8, 2.0]).requires_grad_(True)
    faces = torch.tensor([[0, 1, 2]])

    def f(c):
        r = rasterize(c, faces, (13, 17))
        return r.bary, r.depth.nan_to_num(posinf=0.0)

    assert torch.autograd.gradcheck(f, (clip,), eps=1e-7, atol=1e-6)


@pytest.mark.parametrize("setup_faces", [None, 2])
def test_interpolate_batched_cameras_equal_separate_calls(setup_faces, monkeypatch):
    if setup_faces is not None:  # force one batch element per setup group (the large-mesh path)
        monkeypatch.setattr(raster_module, "_SETUP_FACES", setup_faces)
    verts, faces, cam = _small_scene()
    cam2 = Camera(eye=(-2.0, 1.0, 3.0), target=(0.1, 0.0, 0.0), width=7, height=6, fov_deg=60.0)
    mats = torch.stack([cam.view_proj(dtype=F64), cam2.view_proj(dtype=F64)])
    clip = transform_points(verts, mats)
    assert clip.shape == (2, 4, 4)
    ras = rasterize(clip, faces, cam.resolution)
    attr = torch.randn(2, 4, 5, dtype=F64)
    out = interpolate(attr, ras, faces)
    assert out.shape == (2, 5, 6, 7)
    for b in range(2):
        single = rasterize(clip[b], faces, cam.resolution)
        for a, s in zip(ras, single):
            assert torch.equal(a[b:b + 1], s)
        torch.testing.assert_close(out[b:b + 1], interpolate(attr[b], single, faces), rtol=0, atol=1e-15)
    assert not torch.equal(ras.face_id[0], ras.face_id[1])  # the two views really differ


def test_orthographic_interpolation_equals_ray_plane_intersection():
    cam = Camera(eye=(10.0, 80.0, 100.0), target=(0.0, 0.0, 0.0), width=40, height=30, projection="orthographic",
                 ortho_half_height=40.0, near=1.0, far=400.0)
    world = torch.tensor([[-40.0, -10.0, -30.0], [35.0, -25.0, 20.0], [0.0, 30.0, 10.0]], dtype=F64)
    faces = torch.tensor([[0, 1, 2]])
    ras = rasterize(transform_points(world, cam.view_proj(dtype=F64)), faces, cam.resolution)
    assert int(ras.mask.sum()) > 100
    pos = interpolate(world, ras, faces)
    o, d = cam.rays(dtype=F64)
    normal = torch.linalg.cross(world[1] - world[0], world[2] - world[0])
    t = ((world[0] - o[0].permute(1, 2, 0)) @ normal) / (d[0].permute(1, 2, 0) @ normal)
    hit = o[0] + t * d[0]
    m = ras.mask[0, 0]
    assert (pos[0][:, m] - hit[:, m]).abs().max().item() < 1e-9


def test_interpolate_errors():
    verts, faces, cam = _small_scene()
    ras = rasterize(transform_points(verts, cam.view_proj(dtype=F64)), faces, cam.resolution)
    with pytest.raises(TypeError, match="attributes"):
        interpolate(torch.zeros(4, 2, dtype=torch.int64), ras, faces)
    with pytest.raises(ValueError, match="attributes"):
        interpolate(torch.zeros(3, 4, 2, dtype=F64), ras, faces)
    with pytest.raises(ValueError, match="faces"):
        interpolate(torch.zeros(3, 2, dtype=F64), ras, faces)  # faces index vertex 3
    with pytest.raises(TypeError, match="raster"):
        interpolate(torch.zeros(4, 2, dtype=F64), tuple(ras), faces)


# -- rasterize_uv ---------------------------------------------------------------------------------------------------
def _uv_layout():
    """Triangles in texture space: a 3 x 3 grid of charts (squares split into two triangles), with gaps."""
    tris = []
    for j in range(3):
        for i in range(3):
            u0, v0 = 0.04 + i * 0.32, 0.05 + j * 0.32
            s = 0.29
            a, b, c, d = (u0, v0), (u0 + s, v0), (u0 + s, v0 + s), (u0, v0 + s)
            tris += [(a, b, c), (a, c, d)]
    return torch.tensor(tris, dtype=F64)


def test_rasterize_uv_face_ids_match_brute_force():
    uvs = _uv_layout()
    height, width = 24, 32
    ras = rasterize_uv(uvs, (height, width))
    assert ras.face_id.shape == (1, 1, height, width)
    ndc = [[(2 * u - 1, 2 * v - 1) for u, v in tri.tolist()] for tri in uvs]
    ref = _brute_force(ndc, height, width)
    covered = 0
    for r in range(height):
        for c in range(width):
            fid = int(ras.face_id[0, 0, r, c])
            if ref[r][c]:
                assert fid in ref[r][c]
                assert fid == min(ref[r][c])  # all at depth 0: the lower face id wins
                covered += 1
            else:
                assert fid == -1
    assert covered > 300
    # texel (r, c) has its centre at uv = ((c + 0.5) / W, 1 - (r + 0.5) / H): interpolating the corner uvs gives it
    m = ras.mask[0, 0]
    uv = interpolate(uvs.reshape(-1, 2), ras, torch.arange(3 * uvs.shape[0]).view(-1, 3))
    rows, cols = torch.nonzero(m, as_tuple=True)
    torch.testing.assert_close(uv[0, 0][m], (cols.double() + 0.5) / width, rtol=0, atol=1e-12)
    torch.testing.assert_close(uv[0, 1][m], 1 - (rows.double() + 0.5) / height, rtol=0, atol=1e-12)


def test_rasterize_uv_texel_counts_approach_triangle_areas():
    uvs = _uv_layout()
    res = 256
    ras = rasterize_uv(uvs, (res, res))
    counts = torch.bincount(ras.face_id[ras.mask], minlength=uvs.shape[0]).double()
    e1, e2 = uvs[:, 1] - uvs[:, 0], uvs[:, 2] - uvs[:, 0]
    area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).abs()
    rel = (counts / (res * res) - area).abs() / area
    assert rel.max().item() < 0.02, rel.max().item()


def test_rasterize_uv_errors():
    with pytest.raises(ValueError, match="face_uvs"):
        rasterize_uv(torch.zeros(4, 3, 3), (8, 8))
    with pytest.raises(TypeError, match="face_uvs"):
        rasterize_uv(torch.zeros(4, 3, 2, dtype=torch.int64), (8, 8))
    with pytest.raises(ValueError, match="face_uvs"):
        rasterize_uv(torch.full((1, 3, 2), float("nan")), (8, 8))


# -- extremes -------------------------------------------------------------------------------------------------------
FULL_SCREEN = [(-1.0, -1.0), (3.0, -1.0), (-1.0, 3.0)]


def test_full_screen_triangle_chunked_equals_default(dtype):
    clip = _clip(FULL_SCREEN, z=0.5, w=[1.0, 2.0, 0.5], dtype=dtype)
    faces = torch.tensor([[0, 1, 2]])
    ref = rasterize(clip, faces, (64, 48))
    assert bool(ref.mask.all())
    for budget in (1, 7, 100, 1000):
        small = rasterize(clip, faces, (64, 48), max_candidates=budget)
        for a, b in zip(ref, small):
            assert torch.equal(a, b)


def test_many_faces_chunked_equals_default():
    verts, faces = _grid_mesh(7, -0.9, 0.95, "x")
    clip = _clip(verts, z=torch.linspace(-0.5, 0.5, len(verts)))
    ref = rasterize(clip, torch.tensor(faces), (33, 29))
    for budget in (3, 50, 500):
        small = rasterize(clip, torch.tensor(faces), (33, 29), max_candidates=budget)
        for a, b in zip(ref, small):
            assert torch.equal(a, b)


def test_triangle_behind_the_eye_is_dropped_and_near_plane_clips_per_pixel():
    cam = Camera(eye=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), fov_deg=90.0, width=32, height=32, near=1.0)
    vp = cam.view_proj(dtype=F64)
    faces = torch.tensor([[0, 1, 2]])
    # a big triangle at 5 mm in front of the camera, then the same with one vertex behind the eye (w < 0)
    front = torch.tensor([[-20.0, -20.0, -5.0], [20.0, -20.0, -5.0], [0.0, 20.0, -5.0]], dtype=F64)
    assert int(rasterize(transform_points(front, vp), faces, cam.resolution).mask.sum()) > 500
    behind = front.clone()
    behind[2, 2] = 3.0
    assert int(rasterize(transform_points(behind, vp), faces, cam.resolution).mask.sum()) == 0
    # a tilted triangle in front of the eye crossing the near plane (distance 0.5 to 5 mm): only the part beyond
    # the near plane (NDC z >= -1) is drawn
    crossing = torch.tensor([[-0.3, -0.3, -0.5], [0.3, -0.3, -0.5], [0.0, 2.0, -5.0]], dtype=F64)
    ras = rasterize(transform_points(crossing, vp), faces, cam.resolution)
    assert int(ras.mask.sum()) > 20
    assert bool((ras.depth[ras.mask] >= -1.0).all())
    pos = interpolate(crossing, ras, faces)  # world = view space here
    assert bool((pos[0, 2][ras.mask[0, 0]] <= -1.0 + 1e-9).all())
    # with the near plane at 0.1 mm nothing is clipped: the extra pixels are exactly those nearer than 1 mm
    cam_near = Camera(eye=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), fov_deg=90.0, width=32, height=32, near=0.1)
    full = rasterize(transform_points(crossing, cam_near.view_proj(dtype=F64)), faces, cam.resolution)
    extra = full.mask & ~ras.mask
    assert int(extra.sum()) > 20 and not bool((ras.mask & ~full.mask).any())
    pos_full = interpolate(crossing, full, faces)
    assert bool((pos_full[0, 2][extra[0, 0]] > -1.0 - 1e-9).all())
    assert bool((pos_full[0, 2][ras.mask[0, 0]] <= -1.0 + 1e-9).all())


def test_far_plane_clips_per_pixel():
    clip = _clip(TRI_NDC, z=torch.tensor([0.5, 1.5, 0.5]))
    ras = rasterize(clip, torch.tensor([[0, 1, 2]]), (13, 17))
    full = rasterize(_clip(TRI_NDC, z=0.5), torch.tensor([[0, 1, 2]]), (13, 17))
    assert 0 < int(ras.mask.sum()) < int(full.mask.sum())
    assert bool((ras.depth[ras.mask] <= 1.0).all())


def test_degenerate_triangle_covers_nothing():
    clip = _clip([(-0.9, -0.9), (0.0, 0.0), (0.9, 0.9)])  # a line through pixel centres
    ras = rasterize(clip, torch.tensor([[0, 1, 2], [0, 0, 1]]), (16, 16))
    assert int(ras.mask.sum()) == 0


def test_empty_and_fully_clipped_face_lists_give_background(dtype):
    clip = _clip(TRI_NDC, dtype=dtype)
    for faces in (torch.zeros(0, 3, dtype=torch.int64), torch.tensor([[0, 1, 2]])):
        c = clip if faces.numel() == 0 else clip * torch.tensor([1.0, 1.0, 1.0, -1.0], dtype=dtype)  # w < 0
        ras = rasterize(c, faces, (5, 6))
        assert ras.face_id.shape == (1, 1, 5, 6) and bool((ras.face_id == -1).all())
        assert not bool(ras.mask.any()) and bool((ras.bary == 0).all()) and bool(torch.isinf(ras.depth).all())
        assert ras.bary.dtype == dtype
        assert bool((interpolate(torch.ones(3, 2, dtype=dtype), ras, faces) == 0).all())


def test_offscreen_triangle_and_one_pixel_image():
    off = rasterize(_clip([(1.5, 1.5), (3.0, 1.5), (2.0, 3.0)]), torch.tensor([[0, 1, 2]]), (8, 8))
    assert int(off.mask.sum()) == 0
    one = rasterize(_clip(TRI_NDC), torch.tensor([[0, 1, 2]]), (1, 1))  # centre (0, 0) is inside TRI_NDC
    assert one.face_id.tolist() == [[[[0]]]]
    torch.testing.assert_close(one.bary.sum(1), torch.ones(1, 1, 1, dtype=F64))
    miss = rasterize(_clip([(0.1, 0.1), (0.9, 0.1), (0.5, 0.9)]), torch.tensor([[0, 1, 2]]), (1, 1))
    assert miss.face_id.tolist() == [[[[-1]]]]


def test_validation_errors():
    clip = _clip(TRI_NDC)
    faces = torch.tensor([[0, 1, 2]])
    bad = clip.clone()
    bad[1, 0] = float("nan")
    with pytest.raises(ValueError, match="clip_pos"):
        rasterize(bad, faces, (4, 4))
    bad[1, 0] = float("inf")
    with pytest.raises(ValueError, match="clip_pos"):
        rasterize(bad, faces, (4, 4))
    with pytest.raises(ValueError, match="faces"):
        rasterize(clip, torch.tensor([[0, 1, 3]]), (4, 4))
    with pytest.raises(ValueError, match="faces"):
        rasterize(clip, torch.tensor([[0, -1, 2]]), (4, 4))
    with pytest.raises(ValueError, match="faces"):
        rasterize(clip, torch.tensor([0, 1, 2]), (4, 4))
    with pytest.raises(TypeError, match="faces"):
        rasterize(clip, faces.double(), (4, 4))
    with pytest.raises(TypeError, match="clip_pos"):
        rasterize(clip.long(), faces, (4, 4))
    with pytest.raises(ValueError, match="clip_pos"):
        rasterize(clip[:, :3], faces, (4, 4))
    with pytest.raises(ValueError, match="resolution"):
        rasterize(clip, faces, (0, 4))
    with pytest.raises(TypeError, match="resolution"):
        rasterize(clip, faces, (4.0, 4))
    with pytest.raises(TypeError, match="resolution"):
        rasterize(clip, faces, 4)
    with pytest.raises(ValueError, match="max_candidates"):
        rasterize(clip, faces, (4, 4), max_candidates=0)


def test_device_and_dtype_follow_inputs(device, dtype):
    verts, faces, cam = _small_scene(dtype)
    clip = transform_points(verts, cam.view_proj(dtype=dtype)).to(device)
    ras = rasterize(clip, faces.to(device), cam.resolution)
    assert all(t.device.type == device.type for t in ras)
    assert ras.bary.dtype == dtype and ras.depth.dtype == dtype
    out = interpolate(verts.to(device), ras, faces.to(device))
    assert out.device.type == device.type and out.dtype == dtype
    ref = rasterize(clip.cpu().double(), faces, cam.resolution)
    assert torch.equal(ras.face_id.cpu(), ref.face_id)
    assert math.isclose(float(ras.bary.sum()), float(ref.bary.sum()), rel_tol=1e-5)


# -- the depth pass alone -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_rasterize_depth_is_rasterize_depth_without_barycentrics(dtype):
    """Same coverage and winner as rasterize; the depth within the quantisation step (plus float rounding)."""
    from torchsss.geometry.procedural import torus
    from torchsss.geometry.raster import rasterize_depth

    mesh = torus(8.0, 3.0, 32, 16, dtype=dtype)  # overlapping layers: the depth test decides
    cam = Camera(eye=(5.0, 30.0, 25.0), target=(0.0, 0.0, 0.0), width=96, height=80, near=20.0, far=60.0)
    clip = transform_points(mesh.vertices, cam.view_proj(dtype=dtype))  # the near plane clips part of the ring
    full = rasterize(clip, mesh.faces, (80, 96))
    depth = rasterize_depth(clip, mesh.faces, (80, 96))
    assert depth.shape == (1, 1, 80, 96) and depth.dtype == dtype
    assert bool((depth.isfinite() == full.mask).all())
    assert 0 < int(full.mask.sum()) < 80 * 96
    tol = 2.0 ** -30 + (1e-12 if dtype == F64 else 1e-5)
    assert float((depth[full.mask] - full.depth[full.mask]).abs().max()) <= tol
    assert bool(depth[~full.mask].isinf().all())
    # a batch of two views, and culling, as rasterize
    top = Camera(eye=(0.0, 0.0, 40.0), target=(0, 0, 0), width=96, height=80)
    clip_top = transform_points(mesh.vertices, top.view_proj(dtype=dtype)).reshape(-1, 4)
    clip2 = torch.stack([clip.reshape(-1, 4), clip_top])
    for cull in (False, True):
        full2 = rasterize(clip2, mesh.faces, (80, 96), cull_backfaces=cull)
        depth2 = rasterize_depth(clip2, mesh.faces, (80, 96), cull_backfaces=cull)
        assert bool((depth2.isfinite() == full2.mask).all())
        assert float((depth2[full2.mask] - full2.depth[full2.mask]).abs().max()) <= tol
    assert not depth.requires_grad


def test_rasterize_depth_empty_and_bad_input():
    from torchsss.geometry.raster import rasterize_depth

    clip = _clip([[-1.0, -1.0], [3.0, -1.0], [-1.0, 3.0]], z=0.25)
    assert bool(rasterize_depth(clip, torch.zeros(0, 3, dtype=torch.long), (4, 5)).isinf().all())
    assert torch.allclose(rasterize_depth(clip, torch.tensor([[0, 1, 2]]), (4, 5)), torch.full((1, 1, 4, 5), 0.25,
                                                                                               dtype=F64))
    with pytest.raises(TypeError, match="clip_pos"):
        rasterize_depth(clip.long(), torch.tensor([[0, 1, 2]]), (4, 5))
    with pytest.raises(ValueError, match="faces"):
        rasterize_depth(clip, torch.tensor([[0, 1, 7]]), (4, 5))
    with pytest.raises(ValueError):
        rasterize_depth(clip, torch.tensor([[0, 1, 2]]), (0, 5))
