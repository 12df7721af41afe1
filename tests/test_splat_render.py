"""Shah image-space splatting end to end: SplatTranslucency, render_splat and `render --method splat`."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from torch.func import functional_call

from torchsss.geometry import sphere
from torchsss.geometry.camera import Camera
from torchsss.geometry.shadow import bounding_sphere
from torchsss.modules import DipoleMaterial, SplatTranslucency
from torchsss.pipelines.splat import MIN_GRID, render_splat, splat_grid
from torchsss.registry import render_scene
from torchsss.scene import Material, Scene

SCENE = {"mesh": "sphere", "size_mm": 20.0, "material": "skin1",
         "lights": [{"type": "directional", "direction": [0.3, 0.0, -1.0], "irradiance": 1.0}],
         "camera": {"eye": [0.0, -40.0, 30.0], "target": [0.0, 0.0, 0.0], "up": [0, 0, 1], "fov_deg": 35.0,
                    "width": 32, "height": 32}}


def _rel_rmse(a, b, mask):
    m = mask.expand_as(b)
    return float(((a - b)[m].double().square().mean() / b[m].double().square().mean()).sqrt())


def test_no_sources_give_zeros_and_deformation_needs_no_rebuild():
    scene = Scene.from_dict(SCENE)
    mesh = scene.load_mesh()
    # a deformed mesh (squashed along z) renders directly, and differently
    squashed = dataclasses.replace(mesh, vertices=mesh.vertices * torch.tensor([1.0, 1.0, 0.6]))
    a = render_splat(mesh, scene.material, scene.lights, scene.camera).radiance
    b = render_splat(squashed, scene.material, scene.lights, scene.camera).radiance
    assert bool(torch.isfinite(b).all()) and float((a - b).abs().max()) > 0
    # no sources at all -> zeros, not NaN
    m = SplatTranslucency(DipoleMaterial.from_preset("skin1"))
    mask = torch.ones(1, 1, 8, 8, dtype=torch.bool)
    out = m(torch.zeros(1, 0, 3), torch.zeros(1, 0, 3), torch.zeros(1, 3, 8, 8), mask, torch.eye(4))
    assert bool((out == 0).all())


def test_material_gradients_flow_through_the_module():
    mat = DipoleMaterial.from_preset("marble", dtype=torch.float64)
    m = SplatTranslucency(mat)
    g = torch.Generator().manual_seed(0)
    src = torch.rand(1, 20, 3, generator=g, dtype=torch.float64) * 4 - 2
    src[..., 2] = 0.0
    cam = Camera(eye=(0.0, 0.0, 30.0), target=(0.0, 0.0, 0.0), width=8, height=8, fov_deg=20.0)
    vp = cam.view_proj(dtype=torch.float64)
    axis = torch.linspace(-4, 4, 8, dtype=torch.float64)
    ys, xs = torch.meshgrid(axis, axis, indexing="ij")
    pos = torch.stack([xs, -ys, torch.zeros_like(xs)]).unsqueeze(0)
    out = m(src, torch.ones(1, 20, 3, dtype=torch.float64), pos, torch.ones(1, 1, 8, 8, dtype=torch.bool), vp)
    out.sum().backward()
    assert mat.raw_sigma_a.grad is not None and bool(torch.isfinite(mat.raw_sigma_a.grad).all())
    assert float(mat.raw_sigma_s_prime.grad.abs().sum()) > 0


def test_splat_grid_budget_and_errors():
    mesh = sphere(10.0, 3)
    skin, ketchup = Material.from_json("skin1"), Material.from_json("ketchup")
    assert abs(splat_grid(mesh, skin) - 2 * splat_grid(mesh, skin, oversample=1.0)) <= 1
    assert splat_grid(mesh, skin, max_grid=16) == 16
    assert splat_grid(mesh, skin, eps=0.001) >= splat_grid(mesh, skin, eps=0.05)
    assert splat_grid(mesh, ketchup) > 1
    with pytest.raises(ValueError, match="max_grid"):
        splat_grid(mesh, skin, max_grid=1)
    with pytest.raises(ValueError, match="oversample"):
        splat_grid(mesh, skin, oversample=0.0)
    with pytest.raises(ValueError, match="min_grid"):
        splat_grid(mesh, skin, min_grid=0)
    with pytest.raises(TypeError, match="material"):
        SplatTranslucency("skin1")
    with pytest.raises(ValueError, match="eps"):
        SplatTranslucency(DipoleMaterial.from_preset("skin1"), eps=0.0)


def test_method_splat_in_the_registry():
    res = render_scene(Scene.from_dict(SCENE), "splat")
    assert res.radiance.shape == (1, 3, 32, 32) and bool(res.mask.any())
    assert res.stats["grid"] > 1 and res.stats["splats"] > 0


def test_module_gradcheck_wrt_flux_and_material():
    g = torch.Generator().manual_seed(1)
    src = torch.rand(1, 6, 3, generator=g, dtype=torch.float64) * 4 - 2
    src[..., 2] = 0.0
    cam = Camera(eye=(0.0, 0.0, 30.0), target=(0.0, 0.0, 0.0), width=5, height=5, fov_deg=15.0)
    vp = cam.view_proj(dtype=torch.float64)
    axis = torch.linspace(-3, 3, 5, dtype=torch.float64)
    ys, xs = torch.meshgrid(axis, axis, indexing="ij")
    pos = torch.stack([xs, -ys, torch.zeros_like(xs)]).unsqueeze(0)
    mask = torch.ones(1, 1, 5, 5, dtype=torch.bool)
    mat = DipoleMaterial.from_preset("skin1", dtype=torch.float64)
    m = SplatTranslucency(mat)
    flux = torch.rand(1, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f: m(src, f, pos, mask, vp), (flux,))

    def by_material(raw_sa, raw_ss):  # the module's own parameters as the gradcheck inputs
        params = {"materials.0.raw_sigma_a": raw_sa, "materials.0.raw_sigma_s_prime": raw_ss}
        return functional_call(m, params, (src, flux.detach(), pos, mask, vp))

    raw = (mat.raw_sigma_a.detach().clone().requires_grad_(), mat.raw_sigma_s_prime.detach().clone().requires_grad_())
    assert torch.autograd.gradcheck(by_material, raw)


def _h(material: Material, eps: float = 0.01) -> float:
    """The smallest channel's splat spacing (mm), from the profile module."""
    return float(DipoleMaterial.from_preset(material.name).double().spacing(eps).min())


def test_splat_grid_floor_scales_with_oversample():
    # a 5 mm potato sphere: the profile's spacing (mm) asks for fewer texels than MIN_GRID across the object, so the
    # light view samples the irradiance at MIN_GRID x oversample texels (a fixed floor left the error of such
    # objects where no oversampling moved it: benchmarks/results/splat_calibration.md)
    mesh = sphere(5.0, 3)
    potato = Material.from_json("potato")
    _, radius = bounding_sphere(mesh)
    assert 2.0 * float(radius) / _h(potato) < MIN_GRID  # the profile asks for fewer
    assert [splat_grid(mesh, potato, oversample=s) for s in (1.0, 2.0, 4.0, 8.0)] == [MIN_GRID * s for s in
                                                                                     (1, 2, 4, 8)]
    assert splat_grid(mesh, potato, oversample=0.5) == MIN_GRID // 2
    assert splat_grid(mesh, potato, oversample=8.0, max_grid=100) == 100
    assert splat_grid(mesh, potato, oversample=1.0, min_grid=8) == 8
    # where the profile asks for more, the floor does not bind: the budget's own n = ceil(s 2R / h)
    big, marble = sphere(60.0, 3), Material.from_json("marble")
    _, r_big = bounding_sphere(big)
    n = 2.0 * float(r_big) / _h(marble)
    assert n > MIN_GRID
    assert splat_grid(big, marble, oversample=2.0) == min(512, math.ceil(2.0 * n))
