"""Frames whose camera alone moved reuse what depends on the lights and the material (``Renderer._per_lights``)."""

from __future__ import annotations

import pytest
import torch

from torchsss.geometry import Camera, DirectionalLight, PointLight, sphere
from torchsss.pipelines import build

LIGHTS = [PointLight((30.0, 20.0, 40.0), (3e3, 3e3, 3e3))]
CAM_A = Camera(eye=(0.0, 0.0, 45.0), target=(0.0, 0.0, 0.0), width=24, height=24)
CAM_B = Camera(eye=(30.0, 10.0, 30.0), target=(0.0, 0.0, 0.0), width=24, height=24)


@pytest.fixture(scope="module")
def mesh():
    return sphere(8.0, 2)


def _fresh(renderer, lights, camera):
    """The same renderer's frame with nothing reused."""
    renderer.reuse_lights = False
    try:
        return renderer.render(lights, camera)
    finally:
        renderer.reuse_lights = True


@pytest.mark.parametrize(("method", "knobs"), [("lensch", {"atlas_resolution": 64, "blend": False}),
                                               ("icdf", {"atlas_resolution": 64, "samples": 256}),
                                               ("splat", {"eps": 0.03})])
def test_camera_moves_reuse_lights_and_material_changes_do_not(mesh, method, knobs):
    r = build(method, mesh, "skin1", **knobs)
    first = r.render(LIGHTS, CAM_A)
    assert first.stats["relit"] is True
    moved = r.render(list(LIGHTS), CAM_B)  # equal lights (a new list): the camera alone moved
    assert moved.stats["relit"] is False
    torch.testing.assert_close(moved.radiance, _fresh(r, LIGHTS, CAM_B).radiance, rtol=0, atol=0)
    # new lights: relit, and equal to a frame that reuses nothing
    other = [DirectionalLight((0.0, -0.6, -0.8), (2.0, 2.0, 2.0))]
    relit = r.render(other, CAM_B)
    assert relit.stats["relit"] is True
    torch.testing.assert_close(relit.radiance, _fresh(r, other, CAM_B).radiance, rtol=0, atol=0)
    # an in-place material edit (as an optimiser step) changes the key: relit
    with torch.no_grad():
        next(r.material.parameters()).add_(0.05)
    edited = r.render(other, CAM_B)
    assert edited.stats["relit"] is True
    assert not torch.equal(edited.radiance, relit.radiance)
    torch.testing.assert_close(edited.radiance, _fresh(r, other, CAM_B).radiance, rtol=0, atol=0)
    # switched off: every frame relit
    r.reuse_lights = False
    assert r.render(other, CAM_A).stats["relit"] is True
    assert r.render(other, CAM_A).stats["relit"] is True


def test_nothing_is_reused_while_gradients_are_recorded(mesh):
    r = build("lensch", mesh, "skin1", atlas_resolution=64, blend=False, differentiable=True)
    for _ in range(2):
        out = r.render(LIGHTS, CAM_A)
        assert out.stats["relit"] is True and out.radiance.requires_grad
    grads = torch.autograd.grad(out.radiance.sum(), list(r.material.parameters()), allow_unused=True)
    assert any(g is not None and bool(g.abs().sum() > 0) for g in grads)
    with torch.no_grad():  # outside autograd the same renderer reuses
        r.render(LIGHTS, CAM_A)
        assert r.render(LIGHTS, CAM_B).stats["relit"] is False


def test_a_light_holding_a_tensor_is_never_reused(mesh):
    """A tensor intensity can change in place (a finite-difference step, an optimiser): such lights relight."""
    r = build("lensch", mesh, "skin1", atlas_resolution=64, blend=False)
    intensity = torch.tensor([3e3, 3e3, 3e3])
    lights = [PointLight((30.0, 20.0, 40.0), intensity)]
    with torch.no_grad():
        a = r.render(lights, CAM_A)
        intensity.mul_(2.0)
        b = r.render(lights, CAM_A)
    assert a.stats["relit"] is True and b.stats["relit"] is True
    torch.testing.assert_close(b.radiance, 2.0 * a.radiance)
