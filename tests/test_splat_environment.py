"""render_splat with environment lights (Shah 6.4.2) and per-vertex heterogeneous modifiers (Shah eq. 7.4)."""

from __future__ import annotations

import pytest
import torch

from torchsss.geometry.camera import Camera
from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.gbuffer import camera_gbuffer
from torchsss.geometry.lights import DirectionalLight
from torchsss.geometry.procedural import plane, sphere, torus
from torchsss.pipelines.reference import render_reference
from torchsss.pipelines.splat import render_splat
from torchsss.registry import render_scene
from torchsss.scene import Material, Scene

SKY = {"type": "environment", "sky": [1.0, 0.9, 0.8], "ground": [0.1, 0.1, 0.1], "up": [0, 0, 1]}
CAM = {"eye": [0.0, -40.0, 30.0], "target": [0.0, 0.0, 0.0], "up": [0, 0, 1], "fov_deg": 35.0,
       "width": 32, "height": 32}
# a dense material: r_max ~ 1.5 mm, so painted regions are much wider than a splat
DENSE = Material.from_json({"sigma_a": [0.5, 0.4, 0.3], "sigma_s_prime": [5.0, 6.0, 7.0], "eta": 1.3})


def _rel_rmse(a, b, mask):
    m = mask.expand_as(b)
    return float(((a - b)[m].double().square().mean() / b[m].double().square().mean()).sqrt())


@pytest.mark.parametrize("mesh_name", ["sphere", "torus"])
def test_environment_light_matches_the_reference(mesh_name):
    """Unshadowed order-2 SH environment: the depth-peeled splats against the all-pairs reference integral."""
    mesh = sphere(10.0, 3) if mesh_name == "sphere" else torus(10.0, 4.0, 48, 24)
    scene = Scene.from_dict({"mesh": "sphere", "size_mm": 20.0, "material": "skin1", "lights": [SKY],
                             "camera": CAM})
    ref = render_reference(mesh, scene.material, scene.lights, scene.camera, spacing_mm=0.4)
    res = render_splat(mesh, scene.material, scene.lights, scene.camera)
    assert bool(torch.isfinite(res.radiance).all()) and float(ref.radiance.amax()) > 0
    err = _rel_rmse(res.radiance, ref.radiance, res.mask & ref.mask)
    assert err < 0.03, err  # measured 0.24% (sphere)
    # the environment's sky is brighter than its ground: pixels facing up are brighter than pixels facing down
    # (a property of the input, checked so that a wrong SH orientation cannot pass the comparison above)
    top, bottom = res.radiance[0, 0, :8][res.mask[0, 0, :8]], res.radiance[0, 0, -8:][res.mask[0, 0, -8:]]
    if mesh_name == "sphere":
        assert float(top.mean()) > float(bottom.mean())


def test_environment_scene_methods():
    scene = Scene.from_dict({"mesh": "sphere", "size_mm": 20.0, "material": "skin1", "lights": [SKY],
                             "camera": dict(CAM, width=16, height=16)})
    assert isinstance(scene.lights[0], EnvironmentLight)
    res = render_scene(scene, "splat")
    assert res.stats["splats"] > 0 and bool(torch.isfinite(res.radiance).all())
    with pytest.raises(ValueError, match="environment light"):
        render_scene(scene, "lensch")
    # the environment adds to a directional light (both kinds of sources in one render)
    both = Scene.from_dict({"mesh": "sphere", "size_mm": 20.0, "material": "skin1", "camera": dict(CAM, width=16,
                            height=16), "lights": [SKY, {"type": "directional", "direction": [0, 0, -1],
                                                         "irradiance": 1.0}]})
    sun = Scene.from_dict({"mesh": "sphere", "size_mm": 20.0, "material": "skin1", "camera": dict(CAM, width=16,
                           height=16), "lights": [{"type": "directional", "direction": [0, 0, -1],
                                                   "irradiance": 1.0}]})
    a, b, c = (render_scene(s, "splat").radiance for s in (both, scene, sun))
    torch.testing.assert_close(a, b + c, rtol=1e-4, atol=1e-7)


def _painted_sphere():
    mesh = sphere(10.0, 4)
    cam = Camera(eye=(0.0, -60.0, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov_deg=30.0, width=32,
                 height=32)
    light = DirectionalLight((0.0, 1.0, 0.0), 1.0)  # from the camera's side
    return mesh, cam, [light]


def test_painted_irradiance_modulation_renders_brighter():
    mesh, cam, lights = _painted_sphere()
    z = mesh.vertices[:, 2]
    paint = torch.where(z > 4.0, 2.0, 1.0)  # the top cap, painted 2x
    plain = render_splat(mesh, DENSE, lights, cam, grid=96, method="window")
    bright = render_splat(mesh, DENSE, lights, cam, grid=96, method="window", irradiance_scale=paint)
    gpos = camera_gbuffer(mesh, cam).position[:, 2:3]  # pixel heights (an independent rasterization)
    reach = 2.0  # > r_max of DENSE plus the interpolation band of one face
    deep, far = plain.mask & (gpos > 4.0 + reach), plain.mask & (gpos < 4.0 - reach)
    assert int(deep.sum()) > 10 and int(far.sum()) > 50
    ratio = bright.radiance[deep.expand_as(bright.radiance)] / plain.radiance[deep.expand_as(plain.radiance)]
    torch.testing.assert_close(ratio, torch.full_like(ratio, 2.0), rtol=1e-4, atol=0.0)
    torch.testing.assert_close(bright.radiance[far.expand_as(bright.radiance)],
                               plain.radiance[far.expand_as(plain.radiance)], rtol=1e-6, atol=0.0)


def test_painted_distance_multiplier_renders_brighter_and_blurrier_by_the_model():
    """On a lit plane, M_d everywhere scales the interior radiosity by 1 / M_d^2 (int R_d(r M) dA = R / M^2)."""
    mesh = plane(16.0, 16.0, 16)
    cam = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0), fov_deg=6.0, width=16, height=16)  # |x| < 3.2
    lights = [DirectionalLight((0.0, 0.0, -1.0), 1.0)]
    md = torch.full((mesh.vertices.shape[0],), 0.8)
    plain = render_splat(mesh, DENSE, lights, cam, grid=256, method="window")  # 0.09 mm splat spacing
    wide = render_splat(mesh, DENSE, lights, cam, grid=256, method="window", distance_scale=md)
    ratio = wide.radiosity[plain.mask.expand_as(plain.radiosity)] / plain.radiosity[plain.mask.expand_as(
        plain.radiosity)]
    assert float((ratio - 1 / 0.64).abs().amax()) < 0.03 / 0.64, ratio  # the splat lattice, r_max truncation


def test_modifier_errors():
    mesh, cam, lights = _painted_sphere()
    v = mesh.vertices.shape[0]
    with pytest.raises(ValueError, match="distance_scale"):
        render_splat(mesh, DENSE, lights, cam, distance_scale=torch.ones(v + 1))
    with pytest.raises(ValueError, match="distance_scale"):
        render_splat(mesh, DENSE, lights, cam, distance_scale=torch.zeros(v))
    with pytest.raises(ValueError, match="irradiance_scale"):
        render_splat(mesh, DENSE, lights, cam, irradiance_scale=torch.full((v,), float("nan")))
    with pytest.raises(TypeError, match="irradiance_scale"):
        render_splat(mesh, DENSE, lights, cam, irradiance_scale=[1.0] * v)
    with pytest.raises(ValueError, match="lights"):
        render_splat(mesh, DENSE, [], cam)
