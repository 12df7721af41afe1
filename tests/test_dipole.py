import itertools
import math

import numpy as np
import pytest
import torch

import torchsss
from torchsss.physics import (
    dipole_cumulative,
    dipole_rd,
    dipole_rd_shah,
    dipole_spectrum,
    dipole_terms,
    preset,
    preset_names,
    total_diffuse_reflectance,
)
from torchsss.testing import assert_close


def _radial_integral(f, scale: float, panels: int = 400, order: int = 16) -> torch.Tensor:
    """int_0^inf f(r) 2 pi r dr by composite Gauss-Legendre after r = scale * tan(theta)."""
    x, w = np.polynomial.legendre.leggauss(order)
    edges = np.linspace(0.0, math.pi / 2, panels + 1)
    a, b = edges[:-1, None], edges[1:, None]
    theta = torch.tensor((0.5 * (b - a) * x + 0.5 * (a + b)).ravel(), dtype=torch.float64)
    weights = torch.tensor((0.5 * (b - a) * w).ravel(), dtype=torch.float64)
    r = scale * torch.tan(theta)
    jac = scale / torch.cos(theta) ** 2
    vals = f(r.unsqueeze(-1))  # (K, C)
    return ((vals * (2 * math.pi * r * jac).unsqueeze(-1)) * weights.unsqueeze(-1)).sum(0)


def _material(name):
    sa, ss, _ = preset(name).tensors()
    return sa, ss, preset(name).eta


@pytest.mark.parametrize("name", preset_names())
def test_integral_matches_closed_form(name):
    sa, ss, eta = _material(name)
    z_r = (1.0 / (sa + ss)).min().item()
    numeric = _radial_integral(lambda r: dipole_rd(r, sa, ss, eta), z_r)
    closed = total_diffuse_reflectance(sa, ss, eta)
    assert_close(numeric, closed, rtol=1e-6, atol=0.0, msg=name)
    # and the closed-form cumulative integral reaches the same total
    assert_close(dipole_cumulative(torch.full((3,), math.inf, dtype=torch.float64), sa, ss, eta), closed,
                 rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("name", ["marble", "ketchup", "spectralon"])
def test_cumulative_matches_quadrature(name):
    sa, ss, eta = _material(name)
    for radius in (0.1, 1.0, 5.0):
        numeric = _radial_integral(lambda r, radius=radius: dipole_rd(r, sa, ss, eta) * (r <= radius), radius,
                                   panels=2000)
        # the indicator makes the integrand discontinuous: use a fine rule and compare to 1e-4
        assert_close(dipole_cumulative(torch.full((3,), radius, dtype=torch.float64), sa, ss, eta), numeric,
                     rtol=1e-4, atol=0.0)


def test_total_reflectance_monotone_in_albedo():
    ss = torch.ones(50, dtype=torch.float64)
    sa = torch.logspace(-4, 2, 50, dtype=torch.float64)
    rt = total_diffuse_reflectance(sa, ss, 1.3)
    assert torch.all(rt[1:] < rt[:-1]) and rt[0] < 1 and rt[-1] > 0
    assert total_diffuse_reflectance(0.0, 1.0, 1.3).item() == pytest.approx(1.0, abs=1e-15)


def test_two_printed_forms_agree():
    r = torch.logspace(-6, 3, 200, dtype=torch.float64).unsqueeze(-1)
    for name in preset_names():
        sa, ss, eta = _material(name)
        if name == "spectralon":
            continue  # sigma_a = 0 is covered below (Shah's form has sqrt(0) but no gradient is needed here)
        assert_close(dipole_rd(r, sa, ss, eta), dipole_rd_shah(r, sa, ss, eta), rtol=1e-12, atol=0.0, msg=name)
    sa, ss, eta = _material("spectralon")
    assert_close(dipole_rd(r, sa, ss, eta), dipole_rd_shah(r, sa, ss, eta), rtol=1e-12, atol=0.0)


def test_against_independent_scalar_formula():
    # Lensch Fig. 2 term by term in plain Python floats (z_v = z_r + 4 A D, D = 1/(3 sigma_t'))
    sa, ss, eta = 0.032, 0.74, 1.3
    fdr = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    a = (1 + fdr) / (1 - fdr)
    st = sa + ss
    z_r, d_coef = 1 / st, 1 / (3 * st)
    z_v = z_r + 4 * a * d_coef
    s_tr = math.sqrt(3 * sa * st)
    alpha = ss / st
    for r in (0.0, 0.3, 1.0, 7.5, 40.0):
        d_r, d_v = math.hypot(r, z_r), math.hypot(r, z_v)
        expected = alpha / (4 * math.pi) * (z_r * (1 + s_tr * d_r) * math.exp(-s_tr * d_r) / d_r**3
                                            + z_v * (1 + s_tr * d_v) * math.exp(-s_tr * d_v) / d_v**3)
        assert dipole_rd(torch.tensor(r, dtype=torch.float64), sa, ss, eta).item() == pytest.approx(expected,
                                                                                                   rel=1e-13)


def test_terms_spectrum_matches_dipole_spectrum():
    # DipoleTerms.spectrum, the solvers' unchecked form, is dipole_spectrum at every finite k >= 0
    sa = torch.tensor([0.0021, 0.0041, 0.0], dtype=torch.float64)
    ss = torch.tensor([2.19, 2.62, 3.0], dtype=torch.float64)
    k = torch.cat([torch.zeros(1, dtype=torch.float64), torch.logspace(-4, 4, 60, dtype=torch.float64)])[:, None]
    terms = dipole_terms(sa, ss, torch.tensor(1.3, dtype=torch.float64))
    want = dipole_spectrum(k, sa, ss, 1.3)
    torch.testing.assert_close(terms.spectrum(k), want, rtol=1e-12, atol=1e-300)


def test_spectrum_is_hankel_transform():
    sa, ss, eta = _material("skin1")
    for k in (0.0, 0.5, 3.0):
        numeric = _radial_integral(lambda r, k=k: dipole_rd(r, sa, ss, eta) * torch.special.bessel_j0(k * r), 0.5,
                                   panels=4000)
        assert_close(numeric, dipole_spectrum(torch.full((3,), k, dtype=torch.float64), sa, ss, eta),
                     rtol=1e-6, atol=1e-12)


def test_heterogeneous_modifiers():
    r = torch.linspace(0, 10, 11, dtype=torch.float64).unsqueeze(-1)
    sa, ss, eta = _material("marble")
    base = dipole_rd(r * 2.5, sa, ss, eta)
    assert_close(dipole_rd(r, sa, ss, eta, distance_scale=2.5, irradiance_scale=0.3), 0.3 * base, rtol=1e-14,
                 atol=0.0)
    md = torch.tensor([1.0, 2.0, 4.0], dtype=torch.float64)
    per_channel = dipole_rd(r, sa, ss, eta, distance_scale=md)
    for c in range(3):
        assert_close(per_channel[:, c], dipole_rd(r[:, 0] * md[c], sa[c], ss[c], eta), rtol=1e-14, atol=0.0)
    # a distance multiplier M_d scales the integral by 1 / M_d^2 (the profile shrinks, Shah ch. 7)
    integral = _radial_integral(lambda x: dipole_rd(x, sa, ss, eta, distance_scale=2.0), 0.1)
    assert_close(integral, total_diffuse_reflectance(sa, ss, eta) / 4.0, rtol=1e-6, atol=0.0)


R_EXTREME = [0.0] + [10.0**k for k in range(-9, 5)]
SA_EXTREME = [0.0] + [10.0**k for k in range(-8, 4)]
SS_EXTREME = [10.0**k for k in range(-6, 4)]
ETA_EXTREME = [0.8, 1.0, 1.01, 1.3, 2.5]


def test_extremes_finite_nonnegative_monotone_and_float32_accuracy():
    r64 = torch.tensor(R_EXTREME, dtype=torch.float64).unsqueeze(-1)
    grid = list(itertools.product(SA_EXTREME, SS_EXTREME, ETA_EXTREME))
    sa = torch.tensor([g[0] for g in grid], dtype=torch.float64)
    ss = torch.tensor([g[1] for g in grid], dtype=torch.float64)
    eta = torch.tensor([g[2] for g in grid], dtype=torch.float64)
    v64 = dipole_rd(r64, sa, ss, eta)  # (R, materials)
    assert torch.isfinite(v64).all() and (v64 >= 0).all()
    assert (v64[1:] <= v64[:-1]).all(), "R_d must be non-increasing in r"
    # float32 against float64 evaluated on the same (float32-rounded) inputs
    ins32 = [t.to(torch.float32) for t in (r64, sa, ss, eta)]
    v32 = dipole_rd(*ins32)
    ref = dipole_rd(*[t.to(torch.float64) for t in ins32])
    assert torch.isfinite(v32).all() and (v32 >= 0).all()
    assert (v32[1:] <= v32[:-1]).all()
    normal = ref >= torch.finfo(torch.float32).tiny
    assert normal.float().mean() > 0.5
    rel = (v32.double() - ref).abs() / ref
    assert rel[normal].max().item() < 1e-5


def test_extremes_gradients_finite():
    r = torch.tensor(R_EXTREME, dtype=torch.float64).unsqueeze(-1)
    grid = list(itertools.product(SA_EXTREME, SS_EXTREME, ETA_EXTREME))
    params = [torch.tensor([g[i] for g in grid], dtype=torch.float64, requires_grad=True) for i in range(3)]
    grads = torch.autograd.grad(dipole_rd(r, *params).sum(), params)
    for name, g in zip(("sigma_a", "sigma_s_prime", "eta"), grads):
        assert torch.isfinite(g).all(), name
    # each r separately too (a sum could hide an inf cancelled by nothing, but not a NaN)
    r_g = r.clone().requires_grad_(True)
    (g_r,) = torch.autograd.grad(dipole_rd(r_g, *[p.detach() for p in params]).sum(), r_g)
    assert torch.isfinite(g_r).all()


def test_gradient_at_zero_absorption_is_the_limit_of_the_exact_branch():
    # sigma_a = 0 takes the series branch, sigma_a = 1e-18 the closed form through sqrt: the gradients agree
    # (the difference is the sqrt(sigma_a) cusp of the next term, ~1e-9 here).
    r = torch.tensor([[0.0], [0.5], [2.0], [20.0]], dtype=torch.float64)
    grads = []
    for value in (0.0, 1e-18):
        sa = torch.full((1,), value, dtype=torch.float64, requires_grad=True)
        ss = torch.ones(1, dtype=torch.float64, requires_grad=True)
        grads.append(torch.cat(torch.autograd.grad(dipole_rd(r, sa, ss, 1.3).sum(), (sa, ss))))
    assert grads[0][0].item() < 0  # absorbing more light darkens the profile
    assert_close(grads[0], grads[1], rtol=1e-6, atol=0.0)
    # and against a central difference where the closed form is smooth
    sa = torch.full((1,), 1e-3, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(dipole_rd(r, sa, 1.0, 1.3).sum(), sa)
    h = 1e-7
    fd = (dipole_rd(r, 1e-3 + h, 1.0, 1.3).sum() - dipole_rd(r, 1e-3 - h, 1.0, 1.3).sum()) / (2 * h)
    assert g.item() == pytest.approx(fd.item(), rel=1e-6)


def test_gradcheck_profile():
    r = torch.tensor([[1e-3], [0.2], [1.5], [6.0]], dtype=torch.float64, requires_grad=True)
    sa = torch.tensor([0.01, 0.2, 1e-3], dtype=torch.float64, requires_grad=True)
    ss = torch.tensor([1.0, 2.5, 0.3], dtype=torch.float64, requires_grad=True)
    for eta_v in (1.3, 0.8):
        eta = torch.tensor([eta_v], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(dipole_rd, (r, sa, ss, eta))
    md = torch.tensor([1.5, 0.7, 1.0], dtype=torch.float64, requires_grad=True)
    mi = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda r_, m_d, m_i: dipole_rd(r_, sa, ss, 1.3, distance_scale=m_d, irradiance_scale=m_i), (r, md, mi))


@pytest.mark.parametrize("low,rtol", [(torch.float16, 2e-3), (torch.bfloat16, 1.6e-2)])
def test_reduced_precision(low, rtol):
    r = torch.linspace(0, 5, 64).unsqueeze(-1)
    sa, ss = torch.tensor([0.0021, 0.0041, 0.0071]), torch.tensor([2.19, 2.62, 3.00])
    out = dipole_rd(r.to(low), sa.to(low), ss.to(low), 1.3)
    assert out.dtype == low
    ref = dipole_rd(r.to(low).double(), sa.to(low).double(), ss.to(low).double(), 1.3)
    assert_close(out, ref.to(low), rtol=rtol, atol=0.0)
    # values beyond float16's range overflow honestly in the final cast (computed in float32 first)
    huge = dipole_rd(torch.zeros(1, dtype=torch.float16), 0.0, 1000.0, 1.3)
    assert torch.isinf(huge).all() and dipole_rd(torch.zeros(1), 0.0, 1000.0, 1.3).item() > 65504


def test_dtype_promotion_and_device(device, dtype):
    r = torch.rand(5, 1, dtype=dtype, device=device)
    out = dipole_rd(r, torch.tensor([0.1, 0.2], dtype=dtype, device=device), 1.0)
    assert out.dtype == dtype and out.device.type == device.type and out.shape == (5, 2)
    mixed = dipole_rd(r.float(), torch.tensor([0.1], dtype=torch.float64, device=device), 1.0)
    assert mixed.dtype == torch.float64  # never a silent downcast


@pytest.mark.parametrize(
    "kwargs,exc,match",
    [
        (dict(sigma_a=-0.1), ValueError, "sigma_a"),
        (dict(sigma_a=float("nan")), ValueError, "sigma_a"),
        (dict(sigma_s_prime=-1.0), ValueError, "sigma_s_prime"),
        (dict(sigma_s_prime=float("inf")), ValueError, "sigma_s_prime"),
        (dict(eta=0.0), ValueError, "eta"),
        (dict(eta=-1.3), ValueError, "eta"),
        (dict(sigma_a=0.0, sigma_s_prime=0.0), ValueError, "sigma_a \\+ sigma_s_prime"),
        (dict(r=torch.tensor([-1.0])), ValueError, "r:"),
        (dict(r=torch.tensor([float("nan")])), ValueError, "r:"),
        (dict(r=torch.tensor([1, 2])), TypeError, "r:"),
        (dict(r="one"), TypeError, "r:"),
        (dict(r=torch.rand(4, 2), sigma_a=torch.rand(3)), ValueError, "broadcast"),
        (dict(distance_scale=0.0), ValueError, "distance_scale"),
        (dict(irradiance_scale=-1.0), ValueError, "irradiance_scale"),
    ],
)
def test_bad_input(kwargs, exc, match):
    args = dict(r=torch.tensor([1.0]), sigma_a=0.1, sigma_s_prime=1.0, eta=1.3)
    args.update(kwargs)
    with pytest.raises(exc, match=match):
        dipole_rd(**args)


def test_terms():
    t = dipole_terms(torch.tensor([0.5]), torch.tensor([1.5]), 1.3)
    assert t.z_r.item() == pytest.approx(0.5)
    assert t.sigma_tr.item() == pytest.approx(math.sqrt(3 * 0.5 * 2.0))
    assert t.z_v.item() == pytest.approx(0.5 * (1 + 4 / 3 * t.a.item()))


def test_public_entry_points():
    assert torchsss.dipole_rd is dipole_rd
    assert torchsss.total_diffuse_reflectance is total_diffuse_reflectance
