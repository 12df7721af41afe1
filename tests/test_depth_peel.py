"""Depth peeling (raster.depth_peel) and the depth-peeled environment splat sources (peel.environment_splats)."""

from __future__ import annotations

import math

import pytest
import torch

from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.peel import axis_camera, environment_splats
from torchsss.geometry.procedural import sphere, torus
from torchsss.geometry.raster import depth_peel, rasterize
from torchsss.physics.sh import sh_basis

F64 = torch.float64


def _quads(depths, perm_seed=None):
    """Full-screen quads (NDC corners +-1, so the diagonals pass exactly through pixel centres) at NDC depths."""
    verts, faces = [], []
    for q, z in enumerate(depths):
        verts += [[-1.0, -1.0, z, 1.0], [1.0, -1.0, z, 1.0], [1.0, 1.0, z, 1.0], [-1.0, 1.0, z, 1.0]]
        faces += [[4 * q, 4 * q + 1, 4 * q + 2], [4 * q, 4 * q + 2, 4 * q + 3]]
    faces = torch.tensor(faces)
    order = torch.arange(faces.shape[0])
    if perm_seed is not None:
        order = torch.randperm(faces.shape[0], generator=torch.Generator().manual_seed(perm_seed))
    return torch.tensor(verts, dtype=F64), faces[order], order


def _rotation(seed):
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=F64))
    return q


# -- depth_peel -----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [None, 1, 2])
def test_stacked_quads_peel_in_depth_order(seed):
    depths = [0.6, -0.2, 0.1, -0.7]
    clip, faces, order = _quads(depths, seed)
    layers = depth_peel(clip, faces, (8, 8), max_layers=10)
    assert len(layers) == 4  # no duplicate layers at the pixels on the diagonals
    quad_of_face = order // 2  # face index in `faces` -> its quad
    for k, q in enumerate(sorted(range(4), key=lambda i: depths[i])):
        assert bool(layers[k].mask.all())
        assert bool((quad_of_face[layers[k].face_id] == q).all())
        assert torch.allclose(layers[k].depth, torch.full_like(layers[k].depth, depths[q]), atol=1e-12)
        assert torch.allclose(layers[k].bary.sum(1), torch.ones(1, 8, 8, dtype=F64))
    # the test exercises edge duplicates: both triangles of a quad cover the diagonal's pixel centres
    one = rasterize(clip, faces[quad_of_face == 0][:1], (8, 8)).mask
    other = rasterize(clip, faces[quad_of_face == 0][1:], (8, 8)).mask
    assert bool((one & other).any())


def test_vertex_on_pixel_centre_is_peeled_once():
    # a fan of 6 triangles around a vertex at NDC (0, 0), the centre of pixel (2, 2) of a 5 x 5 image
    ang = torch.arange(6, dtype=F64) * (math.pi / 3)
    rim = torch.stack([0.9 * torch.cos(ang), 0.9 * torch.sin(ang)], -1)
    xy = torch.cat([torch.zeros(1, 2, dtype=F64), rim])
    clip = torch.cat([xy, torch.zeros(7, 1, dtype=F64), torch.ones(7, 1, dtype=F64)], 1)
    faces = torch.tensor([[0, 1 + i, 1 + (i + 1) % 6] for i in range(6)])
    covering = sum(int(rasterize(clip, faces[i:i + 1], (5, 5)).mask[0, 0, 2, 2]) for i in range(6))
    assert covering >= 2  # inclusive coverage: several faces cover the centre pixel
    layers = depth_peel(clip, faces, (5, 5), max_layers=8)
    assert len(layers) == 1


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_grid_with_vertices_on_pixel_centres_is_one_layer(dtype):
    # every vertex of a 12 x 12 grid (two triangles per cell, alternating diagonals) sits on a pixel centre of a
    # 16 x 16 image, every edge runs through pixel centres: a bumpy height field is still a single layer
    n, res = 12, 16
    c = (torch.arange(n + 1, dtype=F64) + 2.5) * (2.0 / res) - 1.0
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    zz = 0.1 * torch.sin(3 * xx) * torch.cos(2 * yy)
    clip = torch.stack([xx, yy, zz, torch.ones_like(xx)], -1).view(-1, 4).to(dtype)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b, d, e = i * (n + 1) + j, i * (n + 1) + j + 1, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1
            faces += [[a, b, e], [a, e, d]] if (i + j) % 2 else [[a, b, d], [b, e, d]]
    layers = depth_peel(clip, torch.tensor(faces), (res, res), max_layers=8)
    assert len(layers) == 1
    assert int(layers[0].mask.sum()) == (n + 1) ** 2


def test_coplanar_faces_come_out_in_face_id_order():
    clip, faces, _ = _quads([0.25, 0.25])  # two coincident quads: distinct surfaces (no shared vertices)
    layers = depth_peel(clip, faces, (4, 4), max_layers=8)
    assert len(layers) == 2
    assert bool((layers[0].face_id < 2).all()) and bool((layers[1].face_id >= 2).all())


def test_max_layers_caps_and_validation():
    clip, faces, _ = _quads([0.1, 0.2, 0.3, 0.4, 0.5])
    assert len(depth_peel(clip, faces, (4, 4), max_layers=3)) == 3
    assert len(depth_peel(clip, faces, (4, 4), max_layers=1)) == 1
    with pytest.raises(ValueError, match="max_layers"):
        depth_peel(clip, faces, (4, 4), max_layers=0)
    with pytest.raises(TypeError, match="max_layers"):
        depth_peel(clip, faces, (4, 4), max_layers=2.0)
    with pytest.raises(TypeError, match="max_layers"):
        depth_peel(clip, faces, (4, 4), max_layers=True)
    with pytest.raises(ValueError, match="faces"):
        depth_peel(clip, faces + 100, (4, 4), max_layers=2)


def test_empty_inputs_give_no_layers():
    clip, faces, _ = _quads([0.0])
    assert depth_peel(clip, faces[:0], (4, 4), max_layers=4) == []
    off = clip.clone()
    off[:, 0] += 5.0  # entirely off screen
    assert depth_peel(off, faces, (4, 4), max_layers=4) == []
    far = clip.clone()
    far[:, 2] = 2.0  # beyond the far plane
    assert depth_peel(far, faces, (4, 4), max_layers=4) == []


def _sphere_clip(mesh, seed, dtype):
    v = mesh.vertices.to(F64) @ _rotation(seed)
    return torch.cat([v[:, :2], 0.5 * v[:, 2:3], torch.ones_like(v[:, :1])], 1).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_closed_sphere_has_two_layers_and_first_equals_rasterize(dtype):
    mesh = sphere(1.0, 3)
    clip = _sphere_clip(mesh, 0, dtype)
    layers = depth_peel(clip, mesh.faces, (40, 40), max_layers=8)
    assert len(layers) == 2
    ref = rasterize(clip, mesh.faces, (40, 40))
    for a, b in zip(layers[0], ref):
        assert torch.equal(a, b)
    c = (torch.arange(40, dtype=F64) + 0.5) / 20 - 1
    rho = torch.sqrt(c[None, :] ** 2 + c[:, None] ** 2)
    interior = rho < 0.95
    assert bool(layers[0].mask[0, 0][interior].all()) and bool(layers[1].mask[0, 0][interior].all())
    assert bool((layers[1].mask <= layers[0].mask).all())
    front, back = layers[0].depth[0, 0][interior].double(), layers[1].depth[0, 0][interior].double()
    zs = 0.5 * torch.sqrt(1 - rho[interior] ** 2)  # the sphere (radius 1, NDC z = 0.5 z)
    assert torch.allclose(front, -zs, atol=0.01) and torch.allclose(back, zs, atol=0.01)


def _ray_counts(clip, faces, res):
    """Independent reference: number of triangles (float64, barycentric test) crossing each pixel-centre ray."""
    c = (torch.arange(res, dtype=F64) + 0.5) * (2.0 / res) - 1.0
    px, py = c[None, :].expand(res, res).reshape(-1), c.flip(0)[:, None].expand(res, res).reshape(-1)
    tri = clip[faces][..., :2].double()  # (F, 3, 2)
    a, b, cc = tri[:, 0], tri[:, 1], tri[:, 2]
    det = (b[:, 0] - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (cc[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    dx, dy = px[:, None] - a[:, 0], py[:, None] - a[:, 1]
    u = (dx * (cc[:, 1] - a[:, 1]) - dy * (cc[:, 0] - a[:, 0])) / det
    v = (dy * (b[:, 0] - a[:, 0]) - dx * (b[:, 1] - a[:, 1])) / det
    w = 1 - u - v
    inside = (u > 0) & (v > 0) & (w > 0)
    near_edge = (torch.stack([u, v, w]).abs().amin(0) < 1e-7).any(1)
    return inside.sum(1).view(res, res), near_edge.view(res, res)


def test_layer_count_matches_ray_casting_on_torus():
    mesh = torus(1.0, 0.4, 24, 12)
    v = mesh.vertices.double() @ _rotation(3) * 0.65
    clip = torch.cat([v[:, :2], 0.5 * v[:, 2:3], torch.ones_like(v[:, :1])], 1)
    layers = depth_peel(clip, mesh.faces, (48, 48), max_layers=10)
    count = sum(lay.mask[0, 0].long() for lay in layers)
    ref, near_edge = _ray_counts(clip, mesh.faces, 48)
    assert int(ref.max()) == 4 and len(layers) == 4
    assert torch.equal(count[~near_edge], ref[~near_edge])
    # depths increase strictly through the layers wherever both are covered
    for k in range(1, len(layers)):
        both = layers[k].mask & layers[k - 1].mask
        assert bool((layers[k].depth[both] > layers[k - 1].depth[both]).all())
        assert bool((layers[k].mask <= layers[k - 1].mask).all())


def test_batched_peel_matches_single():
    mesh = sphere(1.0, 2)
    clips = torch.stack([_sphere_clip(mesh, s, F64) for s in (4, 5)])
    clips[1, :, :2] *= 0.5
    batched = depth_peel(clips, mesh.faces, (16, 16), max_layers=4)
    for b in range(2):
        single = depth_peel(clips[b], mesh.faces, (16, 16), max_layers=4)
        assert len(single) == len(batched)
        for ls, lb in zip(single, batched):
            assert torch.equal(ls.face_id[0], lb.face_id[b]) and torch.allclose(ls.bary[0], lb.bary[b])


def test_peel_gradcheck_second_layer():
    g = torch.Generator().manual_seed(0)
    xy = torch.tensor([[-0.83, -0.71], [0.91, -0.62], [-0.12, 0.88]], dtype=F64)
    tri = torch.cat([xy, xy + 0.03 * torch.randn(3, 2, generator=g, dtype=F64)])
    z = torch.tensor([[0.1], [0.2], [0.05], [0.5], [0.6], [0.4]], dtype=F64)
    clip = torch.cat([tri, z, torch.tensor([[1.0], [1.1], [0.9], [1.0], [1.2], [0.95]], dtype=F64)], 1)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    layers = depth_peel(clip, faces, (6, 6), max_layers=2)
    assert len(layers) == 2
    mask = layers[1].mask.expand(1, 3, 6, 6)

    def f(c):
        lay = depth_peel(c, faces, (6, 6), max_layers=2)[1]
        return lay.bary[mask], lay.depth[layers[1].mask]

    assert torch.autograd.gradcheck(f, (clip.clone().requires_grad_(True),))


# -- environment_splats ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sphere_mesh():
    return sphere(10.0, 3, dtype=F64)


@pytest.fixture(scope="module")
def torus_mesh():
    return torus(10.0, 4.0, 32, 16, dtype=F64)


def test_splat_area_sums_to_surface_area(sphere_mesh, torus_mesh):
    env = EnvironmentLight.uniform(1.0)
    for mesh, layers in ((sphere_mesh, [2, 2, 2]), (torus_mesh, [4, 4, 2])):
        sp = environment_splats(mesh, env, 96, fresnel="none")
        assert sp.layers == layers
        assert abs(float(sp.area.sum()) / mesh.area - 1.0) < 0.01
        # uniform environment without Fresnel: E = pi everywhere, so flux = pi dA exactly
        assert torch.allclose(sp.irradiance, torch.full_like(sp.irradiance, math.pi), atol=1e-12, rtol=0)
        assert math.isclose(float(sp.flux.sum()), math.pi * 3 * float(sp.area.sum()), rel_tol=1e-12)
        s = 2.0 * axis_camera(0, (0.0, 0.0, 0.0), 1.0, 96).ortho_half_height / 96
        radius = float((mesh.vertices - 0.5 * (mesh.vertices.amin(0) + mesh.vertices.amax(0))).norm(dim=1).max())
        assert float(sp.area.max()) <= (s * radius) ** 2 * (1 + 1e-12)  # bounded at every angle (dA <= s^2)
        assert bool((sp.area > 0).all())


def test_splat_geometry_and_sky_irradiance(sphere_mesh):
    up = (0.2, 0.9, -0.3)
    sky, ground = (2.0, 1.0, 0.5), (0.1, 0.2, 0.3)
    env = EnvironmentLight.sky(sky, ground, up)
    sp = environment_splats(sphere_mesh, env, 48, fresnel="none")
    s_count = sp.face_id.shape[0]
    assert sp.position.shape == (1, s_count, 3) and sp.flux.shape == (1, s_count, 3)
    assert sp.bary.shape == (s_count, 3) and sp.area.shape == (1, s_count, 1)
    corners = sphere_mesh.vertices[sphere_mesh.faces[sp.face_id]]  # (S, 3, 3)
    assert torch.allclose(sp.position[0], (sp.bary[:, :, None] * corners).sum(1), atol=1e-12)
    r = sp.position[0].norm(dim=1)
    assert bool((r <= 10.0 + 1e-9).all()) and bool((r > 9.8).all())  # on the icosphere (chord sag < 2%)
    assert torch.allclose(sp.normal[0], sp.position[0] / r[:, None], atol=0.02)
    u = torch.tensor(up, dtype=F64) / math.sqrt(sum(c * c for c in up))
    cos = (sp.normal[0] @ u)[:, None]
    ref = math.pi * ((1 + cos) / 2 * torch.tensor(sky, dtype=F64) + (1 - cos) / 2 * torch.tensor(ground, dtype=F64))
    assert torch.allclose(sp.irradiance[0], ref, atol=1e-10)  # the hemisphere-light closed form
    assert torch.allclose(sp.flux, sp.irradiance * sp.area)


def test_splat_flux_finite_non_negative_with_fresnel_and_gradient(sphere_mesh):
    sun = torch.nn.functional.normalize(torch.tensor([0.3, 1.0, 0.2], dtype=F64), dim=0)
    env = EnvironmentLight(20.0 * sh_basis(sun)[:, None].expand(9, 3))  # a ringing order-2 "sun"
    eta = torch.tensor(1.3, dtype=F64, requires_grad=True)
    sp = environment_splats(sphere_mesh, env, 32, eta)
    assert torch.isfinite(sp.flux).all() and bool((sp.flux >= 0).all()) and bool((sp.flux == 0).any())
    sp.flux.sum().backward()
    assert eta.grad is not None and torch.isfinite(eta.grad)


def test_splat_layer_caps_and_single_axis(torus_mesh):
    env = EnvironmentLight.uniform(1.0)
    sp = environment_splats(torus_mesh, env, 32, max_layers=3, fresnel="none")
    assert sp.layers == [3, 3, 2]
    sp1 = environment_splats(torus_mesh, env, 32, axes=1, fresnel="none")
    assert sp1.layers == [2]  # the view along z crosses the tube twice
    s = 2.0 * axis_camera(2, (0.0, 0.0, 0.0), 14.0, 32).ortho_half_height / 32
    assert float(sp1.area.min()) >= s * s * (1 - 1e-9)  # s^2 / max(|n_z|, min_cos) >= s^2
    assert float(sp1.area.max()) <= s * s / 1e-2 * (1 + 1e-9)


def test_splat_errors(sphere_mesh):
    env = EnvironmentLight.uniform(1.0)
    with pytest.raises(ValueError, match="axes"):
        environment_splats(sphere_mesh, env, 16, axes=2)
    with pytest.raises(TypeError, match="env"):
        environment_splats(sphere_mesh, {"uniform": 1}, 16)
    with pytest.raises(ValueError, match="resolution"):
        environment_splats(sphere_mesh, env, 0)
    with pytest.raises(TypeError, match="resolution"):
        environment_splats(sphere_mesh, env, 16.0)
    with pytest.raises(ValueError, match="max_layers"):
        environment_splats(sphere_mesh, env, 16, max_layers=0)
    with pytest.raises(ValueError, match="min_cos"):
        environment_splats(sphere_mesh, env, 16, axes=1, min_cos=0.0)
    with pytest.raises(ValueError, match="fresnel"):
        environment_splats(sphere_mesh, env, 16, fresnel="x")
    with pytest.raises(TypeError, match="mesh"):
        environment_splats("sphere", env, 16)
    empty = Mesh(torch.zeros(3, 3), torch.zeros(0, 3, dtype=torch.int64))
    with pytest.raises(ValueError, match="mesh"):
        environment_splats(empty, env, 16)
