"""Shadow maps against exact ray casting and closed forms; camera and light-view G-buffers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import assert_eta_gradient

from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import bend_towards_viewer, camera_gbuffer, layer_gbuffer, light_view
from torchsss.geometry.lights import DirectionalLight, PointLight, SpotLight, surface_irradiance
from torchsss.geometry.mesh import mesh_from_arrays
from torchsss.geometry.procedural import plane, slab, sphere
from torchsss.geometry.sampling import surface_samples
from torchsss.geometry.shadow import build_shadow_map, light_camera, shadow_visibility
from torchsss.geometry.visibility import point_inside, ray_visibility
from torchsss.physics import fresnel_transmittance


def _occluder_scene():
    """A 60 mm floor at z = 0 and a 10 x 10 x 2 mm slab floating at z = 9..11 above its centre."""
    floor = plane(60.0, 60.0, 30)
    box = slab(10.0, 10.0, 2.0, 4)
    v = torch.cat([floor.vertices, box.vertices + torch.tensor([0.0, 0.0, 10.0])])
    f = torch.cat([floor.faces, box.faces + floor.num_vertices])
    with pytest.warns(UserWarning):
        return mesh_from_arrays(v, f)


def _floor_points():
    g = torch.linspace(-25, 25, 101)
    x, y = torch.meshgrid(g, g, indexing="ij")
    pts = torch.stack([x.flatten(), y.flatten(), torch.zeros(x.numel())], -1)
    return pts, torch.tensor([0.0, 0.0, 1.0]).expand_as(pts)


@pytest.mark.parametrize(("light", "half"), [
    (DirectionalLight((0, 0, -1), 1.0), 5.0),
    (PointLight((0, 0, 100), 1.0), 5.0 * 100 / 89),  # silhouette: the slab's top edge at z = 11
    (SpotLight((0, 0, 100), (0, 0, -1), 1.0, cone_deg=60), 5.0 * 100 / 89),
])
def test_shadow_of_an_occluder(light, half):
    mesh = _occluder_scene()
    pts, nrm = _floor_points()
    truth = ((pts[:, 0].abs() < half) & (pts[:, 1].abs() < half)).float()
    away = ((pts[:, :2].abs().amax(-1) - half).abs() > 0.5)
    sm = build_shadow_map(mesh, light, 1024)
    vis_map = shadow_visibility(sm, pts.unsqueeze(0), nrm.unsqueeze(0), light)[0]
    vis_ray = ray_visibility(mesh, light, pts, nrm)
    assert bool((vis_ray[away] == 1 - truth[away]).all())
    assert bool((vis_map[away] == 1 - truth[away]).all())
    assert float((vis_map == vis_ray).float().mean()) > 0.99


@pytest.mark.parametrize("light", [DirectionalLight((0.3, -0.2, -0.93), 1.0), PointLight((30.0, 5.0, 40.0), 1.0),
                                   SpotLight((0, 0, 100), (0, 0, -1), 1.0, cone_deg=30)])
def test_shadow_map_depth_is_the_interpolated_view_depth(light):
    """The depth read from the z-buffer equals the perspective-correct interpolation of the view depth."""
    from torchsss.geometry.camera import transform_points
    from torchsss.geometry.raster import interpolate, rasterize
    from torchsss.geometry.shadow import bounding_sphere

    mesh = _occluder_scene()
    sm = build_shadow_map(mesh, light, 256)
    centre, radius = bounding_sphere(mesh)
    cam = light_camera(light, centre, radius, 256)
    raster = rasterize(transform_points(mesh.vertices, cam.view_proj()), mesh.faces, (256, 256))
    want = interpolate(-transform_points(mesh.vertices, cam.view_matrix())[..., 2:3], raster, mesh.faces)
    assert bool((sm.depth.isfinite() == raster.mask).all()) and int(raster.mask.sum()) > 1000
    err = (sm.depth[raster.mask] - want[raster.mask]).abs() / want[raster.mask]
    assert float(err.max()) < 1e-5


def test_no_self_shadow_acne_and_terminator():
    mesh = sphere(10.0, 4)
    light = PointLight((30.0, 40.0, 60.0), 1.0)
    s = surface_samples(mesh, 1.0)
    to_l = torch.nn.functional.normalize(torch.tensor(light.position) - s.position, dim=-1)
    cos = (s.normal * to_l).sum(-1)
    sm = build_shadow_map(mesh, light, 1024)
    vis = shadow_visibility(sm, s.position.unsqueeze(0), s.normal.unsqueeze(0), light)[0]
    ray = ray_visibility(mesh, light, s.position, s.normal)
    assert bool((vis[cos > 0.15] == 1).all()), "shadow acne on the lit side"
    assert bool((vis[cos < -0.15] == 0).all()), "light leaks to the dark side"
    assert bool((ray[cos > 0.15] == 1).all()) and bool((ray[cos < -0.15] == 0).all())


def test_light_inside_bounding_sphere_raises():
    with pytest.raises(ValueError, match="outside the object's bounding sphere"):
        build_shadow_map(sphere(10.0, 2), PointLight((0, 0, 5), 1.0), 64)
    with pytest.raises(ValueError, match="radius"):
        light_camera(PointLight((0, 0, 50), 1.0), (0, 0, 0), 0.0, 64)
    assert point_inside(sphere(10.0, 2), (0, 0, 5)) is True
    assert point_inside(plane(), (0, 0, 5)) is None


def test_camera_gbuffer_on_sphere():
    mesh = sphere(10.0, 4)
    cam = Camera(eye=(0.0, 20.0, 60.0), target=(0.0, 0.0, 0.0), width=48, height=40)
    g = camera_gbuffer(mesh, cam)
    m = g.mask[0, 0]
    assert g.position.shape == (1, 3, 40, 48) and 200 < int(m.sum()) < 40 * 48
    p = g.position[0].permute(1, 2, 0)[m]
    n = g.normal[0].permute(1, 2, 0)[m]
    vd = g.view_dir[0].permute(1, 2, 0)[m]
    assert float((p.norm(dim=-1) - 10.0).abs().max()) < 0.05  # faceting of a level-4 icosphere
    assert float((n * p / p.norm(dim=-1, keepdim=True)).sum(-1).min()) > 0.999
    torch.testing.assert_close(vd, torch.nn.functional.normalize(torch.tensor(cam.eye) - p, dim=-1))
    assert bool(((n * vd).sum(-1) > -1e-3).all()), "visible points face the camera"
    assert bool((g.position[0, :, ~m] == 0).all()) and bool((g.face_id[0, 0][~m] == -1).all())


def test_camera_inside_mesh_raises():
    with pytest.raises(ValueError, match="near plane"):
        camera_gbuffer(sphere(10.0, 2), Camera(eye=(0.0, 0.0, 2.0), target=(0.0, 0.0, -5.0), width=8, height=8))


def _mean_transmittance(eta: float) -> float:
    mu = torch.linspace(0, 1, 20001, dtype=torch.float64)
    f = fresnel_transmittance(mu, eta) * mu
    return float(2 * torch.trapezoid(f, mu))


@pytest.mark.parametrize("light", [DirectionalLight((0, 0, -1), 2.0), PointLight((0, 0, 300), 2.0 * 290**2)])
def test_light_view_flux_is_the_intercepted_power(light):
    mesh = sphere(10.0, 5).with_dtype(torch.float64)
    lv = light_view(mesh, light, 512, 1.3)
    total = lv.flux.sum(dim=(0, 2, 3))
    if isinstance(light, DirectionalLight):
        want = 2.0 * math.pi * 100.0 * _mean_transmittance(1.3)
        torch.testing.assert_close(total, torch.full_like(total, want), rtol=0.01, atol=0)
    else:  # I times the integral of F_t over the solid angle of the sphere: sin(theta) = D sin(alpha) / R
        alpha = torch.linspace(0, math.asin(10.0 / 300.0), 200001, dtype=torch.float64)
        cos_t = torch.sqrt((1 - (300.0 * torch.sin(alpha) / 10.0) ** 2).clamp_min(0))
        want = light.intensity[0] * float(torch.trapezoid(fresnel_transmittance(cos_t, 1.3) * 2 * math.pi
                                                          * torch.sin(alpha), alpha))
        torch.testing.assert_close(total, torch.full_like(total, want), rtol=0.01, atol=0)
    # flux = E dA wherever dA is not clamped (cos > min_cos = 0.01)
    to_light = torch.nn.functional.normalize(
        (torch.tensor(light.position, dtype=torch.float64).view(1, 3, 1, 1) - lv.position)
        if isinstance(light, PointLight) else torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(1, 3, 1, 1)
        .expand_as(lv.position), dim=1)
    ok = lv.mask & ((lv.normal * to_light).sum(1, keepdim=True) > 0.0101)
    torch.testing.assert_close((lv.irradiance * lv.area)[ok.expand_as(lv.flux)], lv.flux[ok.expand_as(lv.flux)],
                               rtol=1e-9, atol=1e-12)
    assert bool(torch.isfinite(lv.area).all()) and bool(torch.isfinite(lv.flux).all())


def test_light_view_matches_surface_irradiance():
    mesh = sphere(10.0, 3)
    light = PointLight((20.0, 30.0, 40.0), (1e3, 2e3, 3e3))
    lv = light_view(mesh, light, 64)
    m = lv.mask[0, 0]
    p = lv.position[0].permute(1, 2, 0)[m].unsqueeze(0)
    n = lv.normal[0].permute(1, 2, 0)[m].unsqueeze(0)
    want = surface_irradiance(p, n, light, 1.3)[0]
    torch.testing.assert_close(lv.irradiance[0].permute(1, 2, 0)[m], want, rtol=1e-5, atol=1e-7)


def test_light_view_grazing_area_is_bounded():
    mesh = plane(10.0, 10.0, 4)
    light = DirectionalLight((1.0, 0.0, -1e-3), 1.0)  # almost parallel to the plane
    lv = light_view(mesh, light, 64, min_cos=0.05)
    assert bool(torch.isfinite(lv.area).all())
    assert float(lv.flux.sum()) == pytest.approx(0.0, abs=1e-3)  # grazing light delivers (almost) nothing
    cam = lv.camera
    s = 2.0 * cam.ortho_half_height / 64
    assert float(lv.area.max()) <= s * s / 0.05 * (1 + 1e-6)
    with pytest.raises(ValueError, match="min_cos"):
        light_view(mesh, light, 16, min_cos=0.0)


def test_unlit_light_view_is_zero_not_nan():
    mesh = plane(10.0, 10.0, 2)  # faces +z
    lv = light_view(mesh, DirectionalLight((0.0, 0.0, 1.0), 1.0), 32)  # light from below
    assert bool(torch.isfinite(lv.flux).all()) and float(lv.flux.abs().sum()) == 0.0
    assert np.isfinite(lv.area.numpy()).all()


@pytest.mark.parametrize("shape", [(), (1,)])
def test_light_view_eta_tensor_gradient_matches_finite_differences(shape):
    mesh = sphere(10.0, 3).with_dtype(torch.float64)
    light = PointLight((20.0, 30.0, 40.0), (1e3, 2e3, 3e3))

    def f(eta):
        lv = light_view(mesh, light, 32, eta)
        return lv.flux.sum() + lv.irradiance.sum()

    assert_eta_gradient(f, shape)
    # per channel: each channel as with its own number
    lv3 = light_view(mesh, light, 32, torch.tensor([1.2, 1.3, 1.5], dtype=torch.float64))
    for c, e in enumerate((1.2, 1.3, 1.5)):
        torch.testing.assert_close(lv3.flux[:, c], light_view(mesh, light, 32, e).flux[:, c], rtol=1e-15, atol=0)


def test_layer_gbuffer_nearest_and_farthest_layers():
    mesh = sphere(10.0, 4).with_dtype(torch.float64)
    cam = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0), width=24, height=32)
    vp = cam.view_proj(dtype=torch.float64)
    near = layer_gbuffer(mesh, vp, cam.resolution)
    far = layer_gbuffer(mesh, vp, cam.resolution, farthest=True)
    assert near.position.shape == (1, 3, 32, 24) and near.mask.shape == (1, 1, 32, 24)
    assert torch.equal(near.mask, far.mask) and bool(near.mask.any()) and not bool(near.mask.all())
    m = near.mask.expand_as(near.position)
    assert bool(near.position[~m].isnan().all()) and bool((near.normal[~m] == 0).all())
    # the near surface is nearer the eye (z = 60) than the far one at every pixel; both on the sphere, normals radial
    assert bool((near.position[:, 2][near.mask[:, 0]] > far.position[:, 2][far.mask[:, 0]]).all())
    for lay in (near, far):
        p = lay.position.permute(0, 2, 3, 1)[lay.mask[:, 0]]
        n = lay.normal.permute(0, 2, 3, 1)[lay.mask[:, 0]]
        assert float((p.norm(dim=-1) - 10.0).abs().max()) < 0.1
        assert float((n - p / p.norm(dim=-1, keepdim=True)).norm(dim=-1).max()) < 0.05
    assert bool((near.depth[near.mask] < far.depth[far.mask]).all()) and bool(near.depth[~near.mask].isinf().all())
    assert bool(far.depth[~far.mask].isinf().all()) and bool((far.depth[far.mask].abs() <= 1).all())
    # fill=0 and the camera G-buffer agree with it
    g = camera_gbuffer(mesh, cam)
    zero = layer_gbuffer(mesh, vp, cam.resolution, fill=0.0)
    # the camera's shading normals are the layer's, turned no more away from the eye than the visible face
    face_n = mesh.face_normals[g.face_id.clamp_min(0)[0, 0]].permute(2, 0, 1)[None]
    bent = bend_towards_viewer(torch.nan_to_num(near.normal), g.view_dir, face_n) * g.mask
    assert torch.equal(g.position, zero.position) and torch.allclose(g.normal, bent, atol=1e-12)
    kept = ((near.normal * g.view_dir).sum(1) >= (face_n * g.view_dir).sum(1).abs()) & g.mask[:, 0]
    assert bool(kept.any()) and torch.equal(g.normal.permute(0, 2, 3, 1)[kept], near.normal.permute(0, 2, 3, 1)[kept])
    assert torch.equal(g.face_id, near.face_id) and bool((zero.position[~m] == 0).all())
    assert layer_gbuffer(mesh, vp, 16).position.shape == (1, 3, 16, 16)


def test_light_camera_options():
    light = PointLight((0.0, 0.0, 100.0), 1.0)
    base = light_camera(light, (0, 0, 0), 10.0, 64)
    assert (base.near, base.far) == (100.0 - 10.2, 100.0 + 10.2)
    wide = light_camera(light, (0, 0, 0), 10.0, 64, margin=1.5)
    assert wide.fov_deg == pytest.approx(2 * math.degrees(math.asin(0.15)))
    # near and far around extra points; a nearer near plane
    pts = torch.tensor([[0.0, 0.0, -150.0], [0.0, 0.0, 95.0]], dtype=torch.float64)
    cam = light_camera(light, (0, 0, 0), 10.0, 64, points=pts, near_fraction=0.5)
    assert cam.near == pytest.approx(45.0) and cam.far == pytest.approx(250.0 * 1.01 + 1e-3)
    # the half-angle cap; with it a light just outside the sphere is accepted
    close = PointLight((0.0, 0.0, 12.0), 1.0)
    with pytest.raises(ValueError, match="light: expected a point light outside the object's bounding sphere"):
        light_camera(close, (0, 0, 0), 10.0, 64, margin=1.5)
    capped = light_camera(close, (0, 0, 0), 10.0, 64, margin=1.5, max_half_angle_deg=80.0)
    assert capped.fov_deg == pytest.approx(160.0)
    # directional: the box holds the points along the light, padded
    d = light_camera(DirectionalLight((0, 0, -1), 1.0), (0, 0, 0), 10.0, 64, margin=1.5, points=pts)
    assert d.ortho_half_height == pytest.approx(15.0)
    assert d.near == pytest.approx(30.0 - 95.0 - 0.101) and d.far == pytest.approx(30.0 + 150.0 + 0.101)
    for kw in ({"margin": 0.0}, {"max_half_angle_deg": 90.0}, {"near_fraction": 1.5},
               {"points": torch.zeros(0, 3)}, {"points": torch.zeros(3)}):
        with pytest.raises(ValueError):
            light_camera(light, (0, 0, 0), 10.0, 64, **kw)
    with pytest.raises(TypeError, match="margin"):
        light_camera(light, (0, 0, 0), 10.0, 64, margin="1")


def test_layer_gbuffer_interpolates_the_given_vertex_normals():
    """``normals=``: the default is the mesh's area-weighted normals; Max's (exact on a sphere) give the radial
    direction at every covered pixel to far better than the area weights; a wrong shape is refused by name."""
    m = sphere(10.0, 3, dtype=torch.float64)
    cam = Camera(eye=(0, 0, 60), target=(0, 0, 0), width=48, height=48)
    vp = cam.view_proj(dtype=torch.float64)
    default = layer_gbuffer(m, vp, 48)
    torch.testing.assert_close(layer_gbuffer(m, vp, 48, normals=m.vertex_normals).normal, default.normal)
    mx = layer_gbuffer(m, vp, 48, normals=m.vertex_normals_max)
    mask = mx.mask[0, 0]
    # the normal the pixel's flat-face point projects to radially (linear interpolation of exact vertex normals)
    radial = torch.nn.functional.normalize(mx.position[0].permute(1, 2, 0)[mask], dim=-1)
    err_max = float((mx.normal[0].permute(1, 2, 0)[mask] - radial).norm(dim=-1).max())
    err_area = float((default.normal[0].permute(1, 2, 0)[mask] - radial).norm(dim=-1).max())
    assert err_max < 1e-9 < 1e-4 < err_area
    with pytest.raises(ValueError, match=r"normals: expected a tensor of shape \(642, 3\)"):
        layer_gbuffer(m, vp, 48, normals=m.vertex_normals[:-1])
