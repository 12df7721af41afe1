"""Lights: closed-form irradiance, spot falloff, Fresnel options, scene-JSON parsing and bad input."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_eta_gradient

from torchsss.geometry.lights import (
    DirectionalLight,
    PointLight,
    SpotLight,
    incident_light,
    light_from_dict,
    surface_irradiance,
)
from torchsss.physics import fresnel_transmittance, schlick_transmittance


def _pts(*p):
    return torch.tensor([p], dtype=torch.float64)


def test_point_light_closed_form(dtype):
    torch.manual_seed(0)
    pts = torch.randn(2, 50, 3, dtype=dtype) * 5
    nrm = torch.nn.functional.normalize(torch.randn(2, 50, 3, dtype=dtype), dim=-1)
    light = PointLight((10.0, -20.0, 30.0), (100.0, 200.0, 300.0))
    e = surface_irradiance(pts, nrm, light, 1.3)
    delta = torch.tensor(light.position, dtype=dtype) - pts
    d = delta.norm(dim=-1)
    cos = ((delta / d.unsqueeze(-1)) * nrm).sum(-1).clamp_min(0)
    want = torch.tensor(light.intensity, dtype=dtype) * (cos / d**2 * fresnel_transmittance(cos, 1.3)).unsqueeze(-1)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(e, want, rtol=tol, atol=tol * float(want.abs().max()))
    assert bool((e[cos == 0] == 0).all())


def test_directional_and_fresnel_options():
    nrm = torch.nn.functional.normalize(torch.tensor([[[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, -1.0]]]), dim=-1)
    pts = torch.zeros(1, 3, 3)
    light = DirectionalLight((0, 0, -1), (2.0, 2.0, 2.0))
    cos = torch.tensor([1.0, math.sqrt(0.5), 0.0])
    for kind, ft in (("exact", fresnel_transmittance(cos, 1.4)), ("schlick", schlick_transmittance(cos, 1.4)),
                     ("none", torch.ones(3))):
        e = surface_irradiance(pts, nrm, light, 1.4, fresnel=kind)
        torch.testing.assert_close(e[0, :, 0], 2.0 * cos * ft * (cos > 0))
    with pytest.raises(ValueError, match="fresnel"):
        surface_irradiance(pts, nrm, light, fresnel="fast")


def test_lights_add_and_visibility_masks():
    pts, nrm = torch.zeros(1, 2, 3), torch.tensor([[[0.0, 0.0, 1.0]] * 2])
    a, b = PointLight((0, 0, 10), 100.0), DirectionalLight((0, 0, -1), 3.0)
    both = surface_irradiance(pts, nrm, [a, b], fresnel="none", visibility=[torch.tensor([[1.0, 0.0]]), None])
    assert both[0, :, 0].tolist() == [4.0, 3.0]
    with pytest.raises(ValueError, match="visibility"):
        surface_irradiance(pts, nrm, [a, b], visibility=[None])
    with pytest.raises(ValueError, match="visibility"):
        surface_irradiance(pts, nrm, a, visibility=torch.ones(1, 3))


def test_spot_cone():
    light = SpotLight((0, 0, 10), (0, 0, -1), 100.0, cone_deg=30.0, inner_deg=20.0)
    angles = torch.tensor([0.0, 19.0, 25.0, 31.0, 60.0])
    pts = torch.stack([10 * torch.tan(torch.deg2rad(angles)), torch.zeros(5), torch.zeros(5)], -1).unsqueeze(0)
    _, d, e = incident_light(light, pts)
    ratio = (e[0, :, 0] * d[0] ** 2 / 100.0).tolist()
    assert ratio[0] == pytest.approx(1.0) and ratio[1] == pytest.approx(1.0)
    assert 0.0 < ratio[2] < 1.0
    assert ratio[3] == 0.0 and ratio[4] == 0.0


def test_point_at_light_is_zero_not_nan():
    light = PointLight((1.0, 2.0, 3.0), 10.0)
    to_l, d, e = incident_light(light, torch.tensor([[[1.0, 2.0, 3.0]]]))
    assert d.item() == 0.0 and bool((e == 0).all()) and bool((to_l == 0).all())
    out = surface_irradiance(torch.tensor([[[1.0, 2.0, 3.0]]]), torch.tensor([[[0.0, 0.0, 1.0]]]), light)
    assert bool(torch.isfinite(out).all()) and bool((out == 0).all())


def test_directional_distance_is_inf():
    _, d, e = incident_light(DirectionalLight((1, 0, 0), (1, 2, 3)), torch.zeros(1, 4, 3))
    assert bool(torch.isinf(d).all()) and e[0, 0].tolist() == [1.0, 2.0, 3.0]


def test_light_from_dict_round_trip_and_errors():
    spot = light_from_dict({"type": "spot", "position": [0, 0, 5], "direction": [0, 0, -3], "intensity": [1, 2, 3],
                            "cone_deg": 40})
    assert isinstance(spot, SpotLight) and spot.direction == (0.0, 0.0, -1.0) and spot.inner_deg == pytest.approx(32)
    with pytest.raises(ValueError, match="light type"):
        light_from_dict({"type": "area", "position": [0, 0, 0]})
    with pytest.raises(ValueError, match="missing keys"):
        light_from_dict({"type": "point", "position": [0, 0, 0]})
    with pytest.raises(ValueError, match="unknown keys"):
        light_from_dict({"type": "point", "position": [0, 0, 0], "intensity": 1, "colour": 2})
    with pytest.raises(ValueError, match="intensity"):
        PointLight((0, 0, 0), (-1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="position"):
        PointLight((0, float("nan"), 0), 1.0)
    with pytest.raises(ValueError, match="direction"):
        DirectionalLight((0, 0, 0), 1.0)
    with pytest.raises(ValueError, match="cone_deg"):
        SpotLight((0, 0, 0), (0, 0, 1), 1.0, cone_deg=120)
    with pytest.raises(TypeError, match="light"):
        light_from_dict([1, 2, 3])
    with pytest.raises(TypeError, match="light"):
        incident_light("sun", torch.zeros(1, 1, 3))
    with pytest.raises(ValueError, match="points"):
        incident_light(PointLight((0, 0, 1), 1.0), torch.zeros(4, 3))


def test_irradiance_gradcheck_float64():
    torch.manual_seed(1)
    pts = (torch.randn(1, 6, 3, dtype=torch.float64) * 3).requires_grad_()
    nrm = torch.nn.functional.normalize(torch.randn(1, 6, 3, dtype=torch.float64) + torch.tensor([0, 0, 2.0]),
                                        dim=-1).requires_grad_()
    lights = [PointLight((5.0, -4.0, 30.0), (1e3, 2e3, 3e3)), SpotLight((0, 0, 40), (0, 0, -1), 1e3, cone_deg=45),
              DirectionalLight((0.2, 0.1, -1.0), 2.0)]
    assert torch.autograd.gradcheck(lambda p, n: surface_irradiance(p, n, lights, 1.3), (pts, nrm))


@pytest.mark.parametrize("fresnel", ["exact", "schlick"])
@pytest.mark.parametrize("shape", [(), (1,)])
def test_eta_tensor_gradient_matches_finite_differences(fresnel, shape):
    """A tensor eta (the material module's, each frame) reaches the output differentiably, environment included."""
    from torchsss.geometry.environment import EnvironmentLight

    torch.manual_seed(1)
    pts = torch.randn(1, 20, 3, dtype=torch.float64) * 3
    nrm = torch.nn.functional.normalize(torch.randn(1, 20, 3, dtype=torch.float64), dim=-1)
    lights = [PointLight((10.0, -20.0, 30.0), (100.0, 200.0, 300.0)), DirectionalLight((0.2, 0.1, -1.0), 2.0),
              EnvironmentLight.sky((0.5, 0.6, 0.9), (0.2, 0.2, 0.1))]
    weights = torch.rand(1, 20, 3, dtype=torch.float64)

    def f(eta):
        return (surface_irradiance(pts, nrm, lights, eta, fresnel=fresnel) * weights).sum()

    eta = assert_eta_gradient(f, shape)
    # the tensor gives the same values as the number
    torch.testing.assert_close(surface_irradiance(pts, nrm, lights, eta.detach(), fresnel=fresnel),
                               surface_irradiance(pts, nrm, lights, 1.3, fresnel=fresnel), rtol=0, atol=0)


def test_per_channel_eta_and_bad_eta_shape():
    pts, nrm = torch.zeros(1, 4, 3, dtype=torch.float64), torch.tensor([[[0.0, 0.6, 0.8]] * 4], dtype=torch.float64)
    light = PointLight((0, 0, 10), 100.0)
    e = surface_irradiance(pts, nrm, light, torch.tensor([1.2, 1.3, 1.5], dtype=torch.float64))
    for c, eta in enumerate((1.2, 1.3, 1.5)):
        torch.testing.assert_close(e[..., c], surface_irradiance(pts, nrm, light, eta)[..., c], rtol=1e-15, atol=0)
    with pytest.raises(ValueError, match="eta"):
        surface_irradiance(pts, nrm, light, torch.full((4,), 1.3, dtype=torch.float64))
