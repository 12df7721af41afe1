"""Regression tests for the physics defects found by the reliability battery.

Values are checked against closed forms or float64 transcriptions, gradients against finite differences, and
every gradient must be finite *and* correct (exactly zero where the true derivative is zero), in float32 and
float64.
"""

import math

import pytest
import torch

from torchsss import BurleyMaterial, DipoleMaterial, TabulatedMaterial
from torchsss.modules.material import material_module
from torchsss.physics import (
    ProfileTable,
    build_profile_table,
    burley_cumulative,
    burley_rd,
    dipole_cumulative,
    dipole_rd,
    dipole_rd_shah,
    dipole_spectrum,
    lookup_profile_table,
    preset_names,
    total_diffuse_reflectance,
)
from torchsss.physics.fresnel import dipole_boundary_a

INF = float("inf")
FLOATS = [torch.float32, torch.float64]
REDUCED = [torch.float16, torch.bfloat16]


def _leaves(*values, dtype):
    return [torch.tensor(v, dtype=dtype, requires_grad=True) for v in values]


def _grads(out, inputs):
    return torch.autograd.grad(out.sum(), inputs, allow_unused=True)


def _rd0_closed_form(sa: float, ss: float, eta: float) -> float:
    """R_d(0) = sigma_s' sigma_t' / (4 pi) [h(beta) + h(beta zeta) / zeta^2] in plain Python floats (float64)."""
    st = sa + ss
    beta = math.sqrt(3.0 * sa / st)
    zeta = 1.0 + 4.0 / 3.0 * float(dipole_boundary_a(torch.tensor(eta, dtype=torch.float64)))

    def h(x):
        return (1.0 + x) * math.exp(-x)

    return ss * st / (4.0 * math.pi) * (h(beta) + h(beta * zeta) / zeta**2)


# --- 1. dipole_rd at r = inf: value 0, gradient 0, and no NaN in a batch's shared material gradient ---------------


@pytest.mark.parametrize("dtype", FLOATS)
def test_dipole_inf_distance_has_zero_gradient_and_does_not_poison_the_batch(dtype):
    r = torch.tensor([[1.0], [INF]], dtype=dtype, requires_grad=True)
    sa, ss, eta = _leaves([0.01, 0.2], [1.0, 2.0], 1.3, dtype=dtype)
    out = dipole_rd(r, sa, ss, eta)
    assert out[1].eq(0).all() and torch.isfinite(out).all()
    g_r, g_sa, g_ss, g_eta = _grads(out, (r, sa, ss, eta))
    assert g_r[1].item() == 0.0  # d/dr at r = inf: true derivative 0
    # the material gradient of the batch equals that of the finite row alone
    r1 = torch.tensor([[1.0]], dtype=dtype)
    ref = _grads(dipole_rd(r1, sa, ss, eta), (sa, ss, eta))
    for got, want in zip((g_sa, g_ss, g_eta), ref):
        assert torch.isfinite(got).all()
        torch.testing.assert_close(got, want)


def test_dipole_inf_distance_with_distance_scale_and_irradiance_scale():
    r = torch.tensor([[INF], [2.0]], dtype=torch.float64)
    md, mi = _leaves([1.5], [0.7], dtype=torch.float64)
    out = dipole_rd(r, 0.01, 1.0, 1.3, distance_scale=md, irradiance_scale=mi)
    g_md, g_mi = _grads(out, (md, mi))
    ref = _grads(dipole_rd(r[1:], 0.01, 1.0, 1.3, distance_scale=md, irradiance_scale=mi), (md, mi))
    assert out[0].item() == 0.0
    torch.testing.assert_close(g_md, ref[0])
    torch.testing.assert_close(g_mi, ref[1])


@pytest.mark.parametrize("r_value", [2e19, 1e25, 3e38])
def test_float32_huge_finite_distance_gives_zero_with_zero_gradient(r_value):
    r = torch.tensor([[r_value]], requires_grad=True)
    sa, ss, eta = _leaves([0.01], [1.0], 1.3, dtype=torch.float32)
    out = dipole_rd(r, sa, ss, eta)
    assert out.item() == 0.0
    for g in _grads(out, (r, sa, ss, eta)):
        assert torch.isfinite(g).all() and (g.abs() < 1e-30).all()  # true derivatives: ~1e-60 or less


def test_dipole_gradient_in_r_is_zero_at_zero_and_matches_finite_differences():
    for dtype in FLOATS:
        r = torch.tensor([[0.0]], dtype=dtype, requires_grad=True)
        (g,) = _grads(dipole_rd(r, torch.tensor([0.01, 0.0], dtype=dtype), 1.0, 1.3), (r,))
        assert g.item() == 0.0  # R_d is even in r
    r = torch.tensor([[0.3], [2.0], [40.0]], dtype=torch.float64, requires_grad=True)
    (g,) = _grads(dipole_rd(r, 0.02, 1.5, 1.3), (r,))
    h = 1e-6
    fd = (dipole_rd(r.detach() + h, 0.02, 1.5, 1.3) - dipole_rd(r.detach() - h, 0.02, 1.5, 1.3)) / (2 * h)
    torch.testing.assert_close(g, fd, rtol=1e-6, atol=0.0)


@pytest.mark.parametrize("sa", [0.0, 1e-12, 1e-9, 1e-6, 1e-4, 1e-2])
def test_float32_gradients_match_float64_down_to_zero_absorption(sa):
    # the closed form's sigma_a derivative cancels for tiny sigma_tr d (1% off in float32 at 1e-12 before the fix)
    r64 = torch.tensor([[0.0], [0.05], [0.5], [3.0], [30.0]], dtype=torch.float64)
    grads = {}
    for dtype in FLOATS:
        r = r64.to(dtype).requires_grad_(True)
        leaves = _leaves([sa, sa], [1.0, 40.0], 1.3, dtype=dtype)
        grads[dtype] = [g.double() for g in _grads(dipole_rd(r, *leaves), (r, *leaves))]
    for g32, g64 in zip(grads[torch.float32], grads[torch.float64]):
        assert torch.isfinite(g32).all()
        torch.testing.assert_close(g32, g64, rtol=2e-5, atol=1e-12)


def test_gradcheck_across_the_series_switch():
    # u = 3 sigma_a / sigma_t' (r sigma_t')^2 crosses the series threshold 1e-4 between these distances
    r = torch.tensor([[1e-3], [0.3], [1.0], [3.0], [10.0]], dtype=torch.float64, requires_grad=True)
    sa = torch.tensor([1e-7, 1e-5, 1e-9], dtype=torch.float64, requires_grad=True)
    ss = torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64, requires_grad=True)
    eta = torch.tensor([1.3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda *a: dipole_rd(*a), (r, sa, ss, eta), eps=1e-10, atol=1e-7, rtol=1e-4)
    # the cumulative: gradcheck away from R = 0 (values ~R^2 there, below what an FD step resolves), and
    # d/dR = 2 pi R R_d(R) exactly everywhere
    radius = torch.tensor([[0.05], [0.3], [1.0], [3.0], [10.0]], dtype=torch.float64, requires_grad=True)
    sa_pos = torch.tensor([1e-7, 1e-5, 1e-3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda *a: dipole_cumulative(*a), (radius, sa_pos, ss, eta), eps=1e-8, atol=1e-7,
                                    rtol=1e-4)
    for dtype in FLOATS:
        mat = [torch.tensor(v, dtype=dtype) for v in ([0.0, 1e-9, 0.01], [1.0, 0.5, 2.0])]
        r3 = torch.tensor([[0.0], [1e-3], [0.3], [3.0], [INF]], dtype=dtype).expand(5, 3).clone().requires_grad_(True)
        (g3,) = _grads(dipole_cumulative(r3, *mat, 1.3), (r3,))
        expected = 2 * math.pi * r3.detach() * dipole_rd(r3.detach(), *mat, 1.3)
        expected[-1] = 0.0  # R = inf: 0 * R_d(inf)
        torch.testing.assert_close(g3, expected, rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=1e-30)


# --- 2. float32 overflow of intermediates for huge coefficients ---------------------------------------------------


@pytest.mark.parametrize("sa,ss", [(1e20, 1.0), (1e25, 1.0), (1e30, 2.0), (1e15, 1e15), (1e18, 1e17), (0.0, 1e15)])
def test_float32_huge_coefficients_are_finite_and_correct(sa, ss):
    r = torch.tensor([[0.0], [1e-3 / (sa + ss)], [0.5 / (sa + ss)], [2.0 / (sa + ss)], [1.0]])
    out = dipole_rd(r, torch.tensor([sa]), torch.tensor([ss]), 1.3)
    assert torch.isfinite(out).all() and (out >= 0).all()
    assert out[0].item() == pytest.approx(_rd0_closed_form(sa, ss, 1.3), rel=1e-5)
    # against an independent float64 transcription (Shah's printed form) on the same float32 inputs
    ref = dipole_rd_shah(r.double(), torch.tensor([sa]).double(), torch.tensor([ss]).double(), 1.3)
    big = ref >= torch.finfo(torch.float32).tiny
    torch.testing.assert_close(out.double()[big], ref[big], rtol=1e-5, atol=0.0)
    assert (out.double()[~big] <= torch.finfo(torch.float32).tiny).all()
    # and the gradients are finite
    leaves = _leaves([sa], [ss], 1.3, dtype=torch.float32)
    for g in _grads(dipole_rd(r, *leaves), leaves):
        assert torch.isfinite(g).all()


def test_huge_absorption_gradient_matches_finite_differences():
    # d R_d(0) / d sigma_s' for sigma_a = 1e20: R_d(0) ~ sigma_s' sigma_t' (...), so the derivative is ~1e20 / (4 pi)
    ss = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    r = torch.zeros(1, 1, dtype=torch.float64)
    (g,) = _grads(dipole_rd(r, 1e20, ss, 1.3), (ss,))
    h = 1e-4
    fd = (_rd0_closed_form(1e20, 1.0 + h, 1.3) - _rd0_closed_form(1e20, 1.0 - h, 1.3)) / (2 * h)
    assert g.item() == pytest.approx(fd, rel=1e-6)
    ss32 = torch.ones(1, requires_grad=True)
    (g32,) = _grads(dipole_rd(r.float(), 1e20, ss32, 1.3), (ss32,))
    assert g32.item() == pytest.approx(fd, rel=1e-5)


# --- 3. total_diffuse_reflectance at sigma_a = 0 ------------------------------------------------------------------


@pytest.mark.parametrize("dtype", FLOATS)
def test_total_reflectance_at_zero_absorption_has_finite_documented_gradient(dtype):
    sa, ss, eta = _leaves([0.0, 0.0], [1.0, 7.0], 1.3, dtype=dtype)
    out = total_diffuse_reflectance(sa, ss, eta)
    assert (out == 1).all()  # exact value
    g_sa, g_ss, g_eta = _grads(out, (sa, ss, eta))
    # R_total = 1 for every sigma_s' (and eta) when nothing absorbs: the derivatives are exactly 0
    assert (g_ss == 0).all() and g_eta.item() == 0.0
    # d/dsigma_a: the sqrt derivative clamped at 3 sigma_a / sigma_t' = 1e-12 (true value: -inf)
    a = float(dipole_boundary_a(torch.tensor(1.3, dtype=torch.float64)))
    expected = -(1.0 + 2.0 * a / 3.0) * 0.5 / math.sqrt(1e-12) * 3.0 / torch.tensor([1.0, 7.0], dtype=torch.float64)
    assert torch.isfinite(g_sa).all() and (g_sa < 0).all()
    torch.testing.assert_close(g_sa.double(), expected, rtol=1e-5, atol=0.0)


@pytest.mark.parametrize("sa", [1e-6, 1e-3, 0.5, 30.0])
def test_total_reflectance_gradient_matches_finite_differences(sa):
    leaves = _leaves([sa], [1.3], 1.4, dtype=torch.float64)
    grads = _grads(total_diffuse_reflectance(*leaves), leaves)
    for i, g in enumerate(grads):
        h = 1e-7 * max(abs(leaves[i].item()), 1e-3)
        plus = [v.detach().clone() for v in leaves]
        minus = [v.detach().clone() for v in leaves]
        plus[i] += h
        minus[i] -= h
        fd = (total_diffuse_reflectance(*plus) - total_diffuse_reflectance(*minus)) / (2 * h)
        assert g.item() == pytest.approx(fd.item(), rel=1e-5, abs=1e-12)


@pytest.mark.parametrize("dtype", FLOATS)
def test_spectralon_module_reflectance_gradients_are_finite(dtype):
    m = DipoleMaterial.from_preset("spectralon", dtype=dtype)
    m.total_diffuse_reflectance().sum().backward()
    for p in m.parameters():
        assert torch.isfinite(p.grad).all()
    assert (m.raw_sigma_a.grad < 0).all()  # more absorption, less light
    m.zero_grad()
    m(torch.tensor([[0.0], [1.0], [INF]], dtype=dtype)).sum().backward()
    m.cumulative(torch.tensor([[0.5], [INF]], dtype=dtype)).sum().backward()
    for p in m.parameters():
        assert torch.isfinite(p.grad).all()


def test_total_reflectance_accurate_for_tiny_albedo():
    # alpha' = sigma_s'/sigma_t' is not computed as 1 - sigma_a/sigma_t' where it would cancel
    sa, ss = torch.tensor([1.0]), torch.tensor([1e-10])
    expected = _rt64(1.0, 1e-10, 1.3)
    assert total_diffuse_reflectance(sa, ss, 1.3).item() == pytest.approx(expected, rel=1e-6)


def _rt64(sa, ss, eta):
    st = sa + ss
    alpha = ss / st
    root = math.sqrt(3.0 * sa / st)
    a = float(dipole_boundary_a(torch.tensor(eta, dtype=torch.float64)))
    return 0.5 * alpha * (1.0 + math.exp(-4.0 / 3.0 * a * root)) * math.exp(-root)


# --- the same defect class in the other closed forms of dipole.py and burley.py ---------------------------------


@pytest.mark.parametrize("dtype", FLOATS)
def test_cumulative_and_spectrum_at_infinity_and_zero_absorption(dtype):
    for sa_v in (0.0, 0.02):
        sa, ss, eta = _leaves([sa_v], [1.0], 1.3, dtype=dtype)
        cum = dipole_cumulative(torch.tensor([[0.7], [INF]], dtype=dtype), sa, ss, eta)
        torch.testing.assert_close(cum[1], total_diffuse_reflectance(sa, ss, eta))
        spec = dipole_spectrum(torch.tensor([[0.0], [3.0], [INF]], dtype=dtype), sa, ss, eta)
        assert spec[2].item() == 0.0
        torch.testing.assert_close(spec[0], total_diffuse_reflectance(sa, ss, eta))
        for out in (cum, spec):
            for g in _grads(out, (sa, ss, eta)):
                assert torch.isfinite(g).all()


def test_cumulative_gradient_at_zero_absorption_is_the_one_sided_limit():
    # for a finite radius the captured reflectance is smooth in sigma_a at 0 (no cusp). With sigma_s' = 1 and
    # zeta = z_v/z_r, each source gives 1 - zeta/D + (zeta^2 - zeta D) beta^2 / 2 + O(beta^3), beta^2 = 3 sigma_a,
    # D = sqrt(R^2 + zeta^2), times alpha'/2 = (1 - sigma_a)/2, and R enters as R sigma_t' = R (1 + sigma_a).
    radius = torch.tensor([[0.3], [2.0], [50.0]], dtype=torch.float64)
    sa = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    (g0,) = _grads(dipole_cumulative(radius, sa, 1.0, 1.3), (sa,))
    zeta = 1.0 + 4.0 / 3.0 * float(dipole_boundary_a(torch.tensor(1.3, dtype=torch.float64)))
    expected = 0.0
    for rr in (0.3, 2.0, 50.0):
        for z in (1.0, zeta):
            d = math.hypot(rr, z)
            expected += 0.5 * (-(1.0 - z / d) + 1.5 * (z * z - z * d) + z * rr * rr / d**3)
    assert g0.item() == pytest.approx(expected, rel=1e-12)
    # the one-sided difference converges to it (its error is O(sqrt(h)), the beta^3 term)
    h = 1e-14
    fd = (dipole_cumulative(radius, h, 1.0, 1.3).sum() - dipole_cumulative(radius, 0.0, 1.0, 1.3).sum()) / h
    assert g0.item() == pytest.approx(fd.item(), rel=1e-4)
    # and the closed-form (exact) branch just above 0 tends to it
    sa1 = torch.full((1,), 1e-12, dtype=torch.float64, requires_grad=True)
    (g1,) = _grads(dipole_cumulative(radius, sa1, 1.0, 1.3), (sa1,))
    assert g0.item() == pytest.approx(g1.item(), rel=1e-3)
    # R = inf: the d/dsigma_s' of R_total at sigma_a = 0 is exactly 0
    ss = torch.ones(1, dtype=torch.float64, requires_grad=True)
    (g_ss,) = _grads(dipole_cumulative(INF, 0.0, ss, 1.3), (ss,))
    assert g_ss.item() == 0.0


def test_cumulative_and_spectrum_match_the_previous_closed_forms():
    sa = torch.tensor([0.0021, 0.17, 3.0], dtype=torch.float64)
    ss = torch.tensor([2.19, 0.88, 0.1], dtype=torch.float64)
    st = sa + ss
    sig = torch.sqrt(3 * sa * st)
    a = dipole_boundary_a(torch.tensor(1.3, dtype=torch.float64))
    zr, zv = 1 / st, (1 + 4 / 3 * a) / st
    radius = torch.tensor([[0.0], [0.1], [1.0], [10.0]], dtype=torch.float64)
    expected = 0.0
    for z in (zr, zv):
        d = torch.sqrt(radius**2 + z**2)
        expected = expected + torch.exp(-sig * z) - z / d * torch.exp(-sig * d)
    torch.testing.assert_close(dipole_cumulative(radius, sa, ss, 1.3), 0.5 * ss / st * expected, rtol=1e-12, atol=1e-15)
    k = torch.tensor([[0.0], [0.5], [4.0]], dtype=torch.float64)
    q = torch.sqrt(k**2 + sig**2)
    expected = 0.5 * ss / st * (torch.exp(-zr * q) + torch.exp(-zv * q))
    torch.testing.assert_close(dipole_spectrum(k, sa, ss, 1.3), expected, rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("dtype", FLOATS)
def test_cumulative_has_no_cancellation_at_small_radius(dtype):
    mp = pytest.importorskip("mpmath")
    mp.mp.dps = 40
    sa, ss, eta = 0.032, 0.74, 1.3
    zeta = 1 + 4 / 3 * float(dipole_boundary_a(torch.tensor(eta, dtype=torch.float64)))

    def exact(radius):
        st = mp.mpf(sa) + mp.mpf(ss)
        sig = mp.sqrt(3 * mp.mpf(sa) * st)
        total = 0
        for z in (1 / st, zeta / st):
            d = mp.sqrt(mp.mpf(radius) ** 2 + z * z)
            total += mp.exp(-sig * z) - z / d * mp.exp(-sig * d)
        return float(mp.mpf(ss) / st / 2 * total)

    radii = [0.0, 1e-6, 1e-4, 1e-2, 0.5, 5.0]
    got = dipole_cumulative(torch.tensor(radii, dtype=dtype).unsqueeze(-1), sa, ss, eta).flatten()
    assert got[0].item() == 0.0
    rtol = 1e-5 if dtype == torch.float32 else 1e-12
    for g, rr in zip(got[1:].tolist(), radii[1:]):
        assert g == pytest.approx(exact(rr), rel=rtol)


# --- 4. burley_rd: r = inf and the albedo range --------------------------------------------------------------------


@pytest.mark.parametrize("dtype", FLOATS)
def test_burley_inf_distance_has_zero_gradient(dtype):
    r = torch.tensor([[1.0], [INF]], dtype=dtype, requires_grad=True)
    a, s, md = _leaves([0.8], [2.0], [1.5], dtype=dtype)
    out = burley_rd(r, a, s, distance_scale=md)
    assert out[1].item() == 0.0
    g_r, g_a, g_s, g_md = _grads(out, (r, a, s, md))
    assert g_r[1].item() == 0.0
    ref = _grads(burley_rd(r[:1].detach(), a, s, distance_scale=md), (a, s, md))
    for got, want in zip((g_a, g_s, g_md), ref):
        torch.testing.assert_close(got, want)
    # the closed form of the gradient in s at r = 1.5 (r M_d): d/ds [A s (e^{-sr} + e^{-sr/3}) / (8 pi r)]
    rr = 1.5
    e1, e3 = math.exp(-2.0 * rr), math.exp(-2.0 * rr / 3)
    expected = 0.8 * ((e1 + e3) - 2.0 * rr * (e1 + e3 / 3)) / (8 * math.pi * rr)
    assert g_s.item() == pytest.approx(expected, rel=1e-5)
    # burley_cumulative at inf: the albedo, d/ds = 0, d/dA = 1
    cum = burley_cumulative(torch.tensor([[INF]], dtype=dtype), a, s)
    assert cum.item() == pytest.approx(0.8, rel=1e-6)
    g_a, g_s = _grads(cum, (a, s))
    assert g_s.item() == 0.0 and g_a.item() == 1.0


@pytest.mark.parametrize("albedo", [1.5, -0.1, float("nan"), 1.0 + 1e-6])
def test_burley_rejects_albedo_outside_unit_interval(albedo):
    with pytest.raises(ValueError, match=r"albedo: expected values in \[0, 1\]"):
        burley_rd(torch.tensor([1.0]), torch.tensor([albedo]), 1.0)


def test_burley_accepts_albedo_bounds():
    out = burley_rd(torch.tensor([[1.0]]), torch.tensor([0.0, 1.0]), 1.0)
    assert out[0, 0].item() == 0.0 and out[0, 1].item() > 0


@pytest.mark.parametrize("dtype", FLOATS)
def test_burley_module_core_and_cumulative_at_infinity(dtype):
    m = BurleyMaterial.from_preset("marble", dtype=dtype)
    (m(torch.tensor([[0.0], [0.5], [INF]], dtype=dtype)).sum() + m.cumulative(torch.tensor([[INF]], dtype=dtype)).sum()
     ).backward()
    for p in m.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()
    assert (m.raw_s.grad != 0).all()  # the finite distances still carry their gradient


# --- 5. TabulatedMaterial: d/dr at r = 0 --------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", FLOATS)
@pytest.mark.parametrize("name", preset_names())
def test_tabulated_slope_at_zero_is_finite_and_zero(name, dtype):
    m = TabulatedMaterial(DipoleMaterial.from_preset(name, dtype=dtype), size=256)
    r = torch.zeros(1, 1, dtype=dtype, requires_grad=True)
    (g,) = _grads(m(r), (r,))
    assert g.item() == 0.0  # the dipole is even in r (and so is its table's first segment, linear in r^2)


def test_tabulated_first_segment_is_smooth_and_accurate():
    m = TabulatedMaterial(DipoleMaterial.from_preset("skin1", dtype=torch.float64), size=64)
    tab = m.table()
    r1 = tab.r_max / 63**2  # first node after 0
    r = (torch.linspace(0.0, 0.95, 11, dtype=torch.float64).unsqueeze(-1) * r1).requires_grad_(True)
    out = m(r)
    v0, v1 = tab.values[0].detach(), tab.values[1].detach()
    torch.testing.assert_close(out.detach(), v0 + (v1 - v0) * (r.detach() / r1) ** 2)  # linear in r^2
    (g,) = _grads(out, (r,))
    slope = 2 * (v1 - v0) * r.detach() / r1**2  # (11, 3): per-channel distances
    torch.testing.assert_close(g, slope)
    assert (g[0] == 0).all()
    assert torch.isfinite(g).all()
    # second segment onwards: the interpolant's derivative matches a central difference
    rr = torch.tensor([[0.05], [0.7], [3.0]], dtype=torch.float64, requires_grad=True)
    (g2,) = _grads(m(rr), (rr,))
    h = 1e-7
    fd = ((m(rr.detach() + h) - m(rr.detach() - h)) / (2 * h)).sum(-1, keepdim=True)
    torch.testing.assert_close(g2, fd, rtol=1e-5, atol=0.0)
    # the quadratic first segment is closer to the dipole than the old sqrt-linear one
    exact = m.material(r.detach())
    old = v0 + (v1 - v0) * torch.sqrt(r.detach() / r1)
    assert ((out.detach() - exact).abs() <= (old - exact).abs() + 1e-15).all()


def test_lookup_first_segment_gradient_on_a_hand_table():
    values = torch.tensor([[4.0], [3.0], [1.0]], dtype=torch.float64)
    tab = ProfileTable(values, torch.tensor([4.0], dtype=torch.float64), "sqrt")  # nodes at r = 0, 1, 4
    r = torch.tensor([[0.0], [0.5], [1.0], [2.25], [INF]], dtype=torch.float64, requires_grad=True)
    out = lookup_profile_table(r, tab)
    torch.testing.assert_close(out.detach().flatten(), torch.tensor([4.0, 3.75, 3.0, 2.0, 0.0], dtype=torch.float64))
    (g,) = _grads(out, (r,))
    # first segment 4 - r^2: slopes 0, -1; second segment 3 - 2 (sqrt(r) - 1): slope -1/sqrt(r) at 2.25; 0 beyond
    torch.testing.assert_close(g.flatten()[[0, 1, 3, 4]], torch.tensor([0.0, -1.0, -1 / 1.5, 0.0], dtype=torch.float64))


# --- 6. reduced precision --------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", REDUCED)
@pytest.mark.parametrize("name", preset_names())
def test_burley_from_preset_in_reduced_precision(name, dtype):
    m = BurleyMaterial.from_preset(name, dtype=dtype)
    a = m.albedo
    assert a.dtype == dtype and ((a > 0) & (a < 1)).all()
    ref = BurleyMaterial.from_preset(name, dtype=torch.float64)
    tol = 2 * torch.finfo(dtype).eps
    torch.testing.assert_close(a.double(), ref.albedo.detach(), rtol=tol, atol=tol)
    out = m(torch.tensor([[0.0], [1.0]], dtype=dtype))
    assert out.dtype == dtype and torch.isfinite(out).all()


def test_burley_from_dipole_clamps_below_one_in_the_target_dtype():
    for dtype in (*REDUCED, *FLOATS):
        m = BurleyMaterial.from_dipole(0.0, 1.0, dtype=dtype)
        largest_below_one = 1.0 - torch.finfo(dtype).eps / 2
        assert m.albedo.dtype == dtype and m.albedo.item() < 1.0
        assert m.albedo.item() >= min(largest_below_one, 1 - 1e-7) - 2 * torch.finfo(dtype).eps


@pytest.mark.parametrize("dtype", REDUCED)
@pytest.mark.parametrize("kind", ["dipole", "burley"])
def test_tabulated_reduced_precision_presets(kind, dtype):
    r = torch.tensor([[0.0], [0.01], [0.3], [1.0], [10.0], [INF]])
    for name in preset_names():
        base = (DipoleMaterial.from_preset(name, dtype=dtype) if kind == "dipole"
                else BurleyMaterial.from_preset(name, dtype=dtype))
        for eps in (1e-2, 1e-4, 1e-6):  # spectralon's sigma_a = 1e-12 is 0 in float16: r_max(1e-6) > 65504 mm
            m = TabulatedMaterial(base, size=512, eps=eps)
            out = m(r.to(dtype))
            assert out.dtype == dtype and torch.isfinite(out).all(), (name, eps)
            assert (out[-1] == 0).all()
            assert m.table().values.dtype == torch.float32
        # close to the material itself (512 nodes over r_max(0.01) resolve every preset)
        m = TabulatedMaterial(base, size=512, eps=1e-2)
        got, want = m(r[:-1].to(dtype)).float(), m.material(r[:-1].to(dtype)).float()
        inside = r[:-1] <= m.table().r_max
        tol = 8 * torch.finfo(dtype).eps
        assert (((got - want).abs() <= tol * want.abs() + 1e-3 * want.amax(0)) | ~inside).all(), name


def test_tabulated_float16_overflow_is_inf_not_nan():
    m = TabulatedMaterial(DipoleMaterial([0.1], [1000.0], dtype=torch.float16))
    r = torch.tensor([[0.0], [1e-4], [1e-3]], dtype=torch.float16)
    out = m(r)
    assert not torch.isnan(out).any() and torch.isinf(out[0]).all()
    assert torch.isinf(m.material(r[:1])).all()  # the same as the material's own forward
    assert out[2].item() == pytest.approx(m.material(r[2:]).item(), rel=1e-2)
    # float32 distances get float32 results, as from the material itself
    assert m(r.float()).dtype == torch.float32 and torch.isfinite(m(r.float())).all()


def test_tabulated_refuses_only_by_naming_its_own_argument():
    m = TabulatedMaterial(DipoleMaterial.from_preset("spectralon", dtype=torch.float16), eps=1e-6)
    assert torch.isfinite(m.table().r_max).all()  # 2.4e5 mm: beyond float16, kept in float32
    with pytest.raises(ValueError, match=r"^eps: "):
        TabulatedMaterial(_NoRange(), eps=0.01)


class _NoRange(torch.nn.Module):
    """A contract module whose r_max is infinite (no finite range to tabulate)."""

    eta = torch.tensor(1.3)
    channels = 1

    def forward(self, r, distance_scale=None, irradiance_scale=None):
        return torch.ones_like(r)

    def r_max(self, eps=0.01):
        return torch.tensor([INF])

    def cumulative(self, radius):
        return radius

    def spacing(self, eps=0.01):
        return torch.tensor([1.0])

    def total_diffuse_reflectance(self):
        return torch.ones(1)


@pytest.mark.parametrize("dtype", REDUCED)
def test_lookup_of_reduced_precision_table_indexes_in_float32(dtype):
    values = torch.linspace(1.0, 0.0, 1024).unsqueeze(-1)
    rmax = torch.tensor([10.0])
    ref = lookup_profile_table(torch.tensor([[9.99], [10.0], [5.0]]), ProfileTable(values, rmax, "sqrt"))
    low = lookup_profile_table(torch.tensor([[9.99], [10.0], [5.0]], dtype=dtype),
                               ProfileTable(values.to(dtype), rmax.to(dtype), "sqrt"))
    assert low.dtype == dtype
    torch.testing.assert_close(low.float(), ref, rtol=2 * torch.finfo(dtype).eps, atol=2 * torch.finfo(dtype).eps)


@pytest.mark.parametrize("dtype", REDUCED)
def test_dipole_material_table_in_reduced_precision(dtype):
    m = DipoleMaterial.from_preset("spectralon", dtype=dtype)
    tab = m.table(size=256, eps=1e-6)  # r_max(1e-6) ~ 2.4e5 mm: beyond float16
    assert tab.values.dtype == torch.float32 and torch.isfinite(tab.values).all() and torch.isfinite(tab.r_max).all()
    big = DipoleMaterial([0.1], [1000.0], dtype=dtype).table(size=256)
    assert torch.isfinite(big.values).all() and big.values[0].item() > 65504  # R_d(0) kept in the float32 table
    out = lookup_profile_table(torch.tensor([[0.0], [1.0]], dtype=dtype), tab)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()
    for dt in FLOATS:  # unchanged for full-precision materials
        mf = DipoleMaterial.from_preset("marble", dtype=dt)
        torch.testing.assert_close(mf.table(size=64).r_max, mf.r_max(0.01).expand(3).amax().expand(3), rtol=0, atol=0)


def test_material_module_tabulated_in_reduced_precision():
    for dtype in REDUCED:
        m = material_module("spectralon", "tabulated", dtype=dtype)
        out = m(torch.tensor([[0.0], [2.0]], dtype=dtype))
        assert out.dtype == dtype and torch.isfinite(out).all()


def test_build_profile_table_keeps_gradients_through_float32_table_of_a_float16_material():
    base = DipoleMaterial.from_preset("marble", dtype=torch.float16)
    m = TabulatedMaterial(base, size=128)
    m(torch.tensor([[0.5], [2.0]], dtype=torch.float16)).sum().backward()
    for p in base.parameters():
        assert p.grad is not None and p.grad.dtype == torch.float16 and torch.isfinite(p.grad).all()
    tab = build_profile_table(base, torch.full((3,), 5.0), 16)
    assert tab.values.dtype == torch.float32  # float32 nodes promote the float16 material's profile


@pytest.mark.parametrize("dtype", FLOATS)
@pytest.mark.parametrize("preset", ["spectralon", "skin1"])  # albedo 1 (sigma_a = 0) and an absorbing one
@pytest.mark.parametrize("kind", ["dipole", "burley", "tabulated"])
def test_every_material_module_at_r_zero_and_inf(kind, preset, dtype):
    """Values and gradients of each module at r = 0 and r = inf: finite, d/dr = 0 at both ends (the profiles are
    smooth functions of r^2 near 0 and vanish with all derivatives at inf), R_d(inf) = 0, parameter gradients
    finite and zero at inf."""
    material = material_module(preset, kind, dtype=dtype)
    r = torch.tensor([[0.0], [INF]], dtype=dtype, requires_grad=True)
    out = material(r)
    assert bool(torch.isfinite(out).all()) and bool((out[0] > 0).all()) and bool((out[1] == 0).all())
    grads = torch.autograd.grad(out.sum(), [r, *material.parameters()], allow_unused=True, retain_graph=True)
    assert bool(torch.isfinite(grads[0]).all())
    assert float(grads[0].abs().max()) == 0.0, f"d/dr at r = 0 and inf: {grads[0].flatten().tolist()}"
    for g in grads[1:]:
        assert g is None or bool(torch.isfinite(g).all())
    at_inf = torch.autograd.grad(out[1].sum(), list(material.parameters()), allow_unused=True)
    for g in at_inf:
        assert g is None or float(g.abs().max()) == 0.0
