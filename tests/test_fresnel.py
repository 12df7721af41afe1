import math

import pytest
import torch

from torchsss.physics import (
    diffuse_fresnel_reflectance,
    dipole_boundary_a,
    fresnel_reflectance,
    fresnel_transmittance,
    schlick_reflectance,
)
from torchsss.testing import assert_close


def _fresnel_loop(cos_i: float, eta: float) -> float:
    """Textbook Fresnel equations, one angle at a time (Snell's law with explicit angles)."""
    theta_i = math.acos(cos_i)
    sin_t = math.sin(theta_i) / eta
    if sin_t >= 1.0:
        return 1.0
    theta_t = math.asin(sin_t)
    if theta_i == 0.0:
        return ((eta - 1) / (eta + 1)) ** 2
    rs = math.sin(theta_i - theta_t) / math.sin(theta_i + theta_t)
    rp = math.tan(theta_i - theta_t) / math.tan(theta_i + theta_t)
    return 0.5 * (rs * rs + rp * rp)


@pytest.mark.parametrize("eta", [0.67, 0.8, 1.01, 1.3, 1.5, 2.5])
def test_matches_angle_form(eta, device):
    cos = torch.linspace(0.02, 1.0, 60, dtype=torch.float64, device=device)
    expected = torch.tensor([_fresnel_loop(c, eta) for c in cos.tolist()], dtype=torch.float64, device=device)
    assert_close(fresnel_reflectance(cos, eta), expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("eta", [1.01, 1.3, 1.5, 2.5, 0.8])
def test_limits(eta, dtype):
    one = torch.ones((), dtype=dtype)
    r0 = ((eta - 1) / (eta + 1)) ** 2
    rel = 1e-4 if dtype == torch.float32 else 1e-12  # (1 - eta) cancels: float32 keeps ~5 digits at 1.01
    assert fresnel_reflectance(one, eta).item() == pytest.approx(r0, rel=rel)
    assert fresnel_reflectance(0.0 * one, eta).item() == pytest.approx(1.0, abs=1e-6)
    assert fresnel_reflectance(torch.tensor(1e-6, dtype=dtype), eta).item() > 0.99
    assert fresnel_transmittance(one, eta).item() == pytest.approx(1 - r0, rel=1e-6)


def test_eta_one_is_transparent(dtype):
    cos = torch.linspace(0.0, 1.0, 11, dtype=dtype)
    assert torch.equal(fresnel_reflectance(cos, 1.0), torch.zeros_like(cos))


def test_total_internal_reflection():
    eta = 1 / 1.5
    critical = math.sqrt(1 - eta**2)  # cos of the critical angle
    cos = torch.tensor([critical * 0.99, critical * 0.5, 0.0], dtype=torch.float64)
    assert torch.all(fresnel_reflectance(cos, eta) == 1.0)
    assert fresnel_reflectance(torch.tensor(critical * 1.01, dtype=torch.float64), eta).item() < 1.0


def test_schlick_within_known_error():
    theta = torch.linspace(0.0, math.pi / 2, 4001, dtype=torch.float64)
    cos = torch.cos(theta)
    for eta in (1.3, 1.4, 1.5, 1.6, 2.0, 2.5):
        err = (schlick_reflectance(cos, eta) - fresnel_reflectance(cos, eta)).abs()
        mean = torch.trapezoid(err * 2 * cos * torch.sin(theta), theta).item()
        assert err.max().item() < (0.037 if eta == 1.5 else 0.085), (eta, err.max().item())
        assert mean < 0.011, (eta, mean)
    # and it is exact at normal incidence
    assert schlick_reflectance(1.0, 1.5).item() == pytest.approx(0.04, rel=1e-6)


def test_fresnel_gradcheck():
    cos = torch.linspace(0.05, 0.95, 7, dtype=torch.float64, requires_grad=True)
    eta = torch.tensor(1.3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(fresnel_reflectance, (cos, eta))
    eta_in = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(fresnel_reflectance, (cos, eta_in))


def test_gradient_finite_at_singular_points():
    cos = torch.tensor([0.0, 0.6, 1.0], dtype=torch.float64, requires_grad=True)
    for eta_v in (1.0, 0.6, 1.3):
        eta = torch.tensor(eta_v, dtype=torch.float64, requires_grad=True)
        g = torch.autograd.grad(fresnel_reflectance(cos, eta).sum(), (cos, eta))
        assert all(torch.isfinite(x).all() for x in g)


def test_fdr_constant_is_0668():
    # F_dr from the printed polynomial with 0.668 (Shah eq. 6.12 misprints 0.0668)
    for eta in (1.0, 1.3, 1.5, 2.0):
        expected = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
        assert diffuse_fresnel_reflectance(torch.tensor(eta, dtype=torch.float64)).item() == pytest.approx(
            expected, rel=1e-12)
    # near eta = 1 there is almost no boundary: F_dr ~ 0, A ~ 1 (with the typo F_dr would be -0.6)
    assert abs(diffuse_fresnel_reflectance(1.0).item()) < 0.01
    assert dipole_boundary_a(1.0).item() == pytest.approx(1.0, abs=0.01)


def test_fdr_below_one_branch():
    eta = 0.8
    expected = -0.4399 + 0.7099 / eta - 0.3319 / eta**2 + 0.0636 / eta**3
    assert diffuse_fresnel_reflectance(torch.tensor(eta, dtype=torch.float64)).item() == pytest.approx(expected)


def test_fdr_matches_hemispherical_integral():
    # F_dr is a fit to the cosine-weighted hemispherical average of the exact Fresnel reflectance seen from
    # inside the medium (relative index 1/eta, total internal reflection included). The fit is good to ~1e-3.
    theta = torch.linspace(0, math.pi / 2, 20001, dtype=torch.float64)
    for eta in (1.3, 1.5):
        f = fresnel_reflectance(torch.cos(theta), 1.0 / eta) * 2 * torch.cos(theta) * torch.sin(theta)
        integral = torch.trapezoid(f, theta).item()
        assert diffuse_fresnel_reflectance(eta).item() == pytest.approx(integral, abs=1e-3)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan")])
def test_bad_eta(bad):
    with pytest.raises(ValueError, match="eta"):
        fresnel_reflectance(torch.tensor(0.5), bad)
    with pytest.raises(ValueError, match="eta"):
        diffuse_fresnel_reflectance(bad)


def test_bad_types_and_shapes():
    with pytest.raises(TypeError, match="cos_theta"):
        fresnel_reflectance("a", 1.3)
    with pytest.raises(TypeError, match="cos_theta"):
        fresnel_reflectance(torch.tensor([1, 0]), 1.3)
    with pytest.raises(ValueError, match="broadcast"):
        fresnel_reflectance(torch.rand(4), torch.full((3,), 1.3))


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
def test_reduced_precision_computed_in_float32(low):
    cos = torch.linspace(0, 1, 50)
    out = fresnel_reflectance(cos.to(low), 1.3)
    assert out.dtype == low
    ref = fresnel_reflectance(cos.to(low).float(), 1.3)
    assert_close(out, ref.to(low))
