import math

import numpy as np
import pytest
import torch

from torchsss import BurleyMaterial, DipoleMaterial
from torchsss.physics import (
    ProfileTable,
    build_profile_table,
    burley_cumulative,
    burley_params_from_dipole,
    burley_rd,
    dipole_rd,
    lookup_profile_table,
    preset,
    profile_table_error,
    r_max,
    total_diffuse_reflectance,
)
from torchsss.testing import assert_close


def _mat64(name):
    sa, ss, _ = preset(name).tensors()
    return sa, ss, preset(name).eta


def test_lookup_against_loop_interpolation():
    vals = torch.tensor([[4.0, 1.0], [2.0, 0.5], [1.0, 0.25], [0.0, 0.0]], dtype=torch.float64)
    rmax = torch.tensor([3.0, 6.0], dtype=torch.float64)
    tab = ProfileTable(vals, rmax, "linear")
    r = torch.tensor([[0.0, 0.0], [1.5, 3.0], [2.9, 7.0], [3.0, 6.0]], dtype=torch.float64)
    got = lookup_profile_table(r, tab)
    for i in range(r.shape[0]):
        for c in range(2):
            x = r[i, c].item()
            expected = 0.0 if x > rmax[c].item() else float(np.interp(x, np.linspace(0, rmax[c].item(), 4),
                                                                     vals[:, c].numpy()))
            assert got[i, c].item() == pytest.approx(expected, abs=1e-14)


@pytest.mark.parametrize("warp", ["sqrt", "linear"])
def test_table_error_converges_quadratically(warp):
    sa, ss, eta = _mat64("marble")
    rm = r_max(sa, ss, eta, 0.01)

    def prof(r):
        return dipole_rd(r, sa, ss, eta)

    e1 = profile_table_error(build_profile_table(prof, rm, 512, warp), prof)
    e2 = profile_table_error(build_profile_table(prof, rm, 1024, warp), prof)
    ratio = (e1 / e2).min().item()
    assert 3.0 < ratio < 5.0  # linear interpolation: error ~ h^2


def test_table_of_1024_nodes_is_accurate():
    sa, ss, eta = _mat64("skin1")
    rm = r_max(sa, ss, eta, 0.01)

    def prof(r):
        return dipole_rd(r, sa, ss, eta)

    e_sqrt = profile_table_error(build_profile_table(prof, rm, 1024, "sqrt"), prof)
    e_lin = profile_table_error(build_profile_table(prof, rm, 1024, "linear"), prof)
    assert torch.all(e_sqrt < 1e-4) and torch.all(e_lin < 1e-4)
    # direct check of the error report at random points
    tab = build_profile_table(prof, rm, 1024, "sqrt")
    r = torch.rand(20000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * rm
    rel = ((lookup_profile_table(r, tab) - prof(r)).abs() / prof(r)).amax(0)
    assert torch.all(rel <= e_sqrt * (1 + 1e-9))


def test_lookup_gradients_flow_to_material():
    m = DipoleMaterial.from_preset("marble", dtype=torch.float64)
    tab = m.table(size=64)
    r = torch.rand(100, 1, dtype=torch.float64) * 5
    lookup_profile_table(r, tab).sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in m.parameters())
    vals = tab.values.detach().requires_grad_(True)
    rr = torch.rand(30, 3, dtype=torch.float64) * tab.r_max * 0.99
    assert torch.autograd.gradcheck(lambda v: lookup_profile_table(rr, ProfileTable(v, tab.r_max, "sqrt")), (vals,))


def test_lookup_bad_input():
    tab = ProfileTable(torch.ones(8, 3), torch.ones(3), "sqrt")
    with pytest.raises(ValueError, match="r:"):
        lookup_profile_table(torch.ones(5, 2), tab)
    with pytest.raises(ValueError, match="r:"):
        lookup_profile_table(-torch.ones(5, 3), tab)
    with pytest.raises(ValueError, match="warp"):
        build_profile_table(lambda r: r, torch.ones(3), 8, "log")
    with pytest.raises(ValueError, match="size"):
        build_profile_table(lambda r: r, torch.ones(3), 1)
    with pytest.raises(ValueError, match="r_max"):
        build_profile_table(lambda r: r, torch.zeros(3), 8)
    with pytest.raises(ValueError, match="profile"):
        build_profile_table(lambda r: r[:, :1], torch.ones(3), 8)


@pytest.mark.parametrize("albedo,s", [(0.8, 2.0), (0.3, 0.2), (0.99, 15.0)])
def test_burley_integrates_to_albedo(albedo, s):
    # int_0^inf R(r) 2 pi r dr, substituting r = t / s; integrand is smooth (the 1/r cancels)
    x, w = np.polynomial.legendre.leggauss(64)
    edges = np.linspace(0.0, 1.0, 201)
    a, b = edges[:-1, None], edges[1:, None]
    u = torch.tensor((0.5 * (b - a) * x + 0.5 * (a + b)).ravel(), dtype=torch.float64)  # u in (0, 1)
    wt = torch.tensor((0.5 * (b - a) * w).ravel(), dtype=torch.float64)
    r = (u / (1 - u)) * 3.0 / s  # map (0,1) -> (0, inf)
    jac = 3.0 / s / (1 - u) ** 2
    vals = burley_rd(r, albedo, s).to(torch.float64)
    integral = (vals * 2 * math.pi * r * jac * wt).sum().item()
    assert integral == pytest.approx(albedo, rel=1e-9)


def test_burley_formula_and_singularity():
    r = torch.tensor([0.5, 1.0, 4.0], dtype=torch.float64)
    expected = [0.8 * 2.0 * (math.exp(-2 * x) + math.exp(-2 * x / 3)) / (8 * math.pi * x) for x in r.tolist()]
    assert_close(burley_rd(r, 0.8, 2.0), torch.tensor(expected, dtype=torch.float64), rtol=1e-14, atol=0)
    at_zero = burley_rd(torch.zeros(1, dtype=torch.float64), 0.8, 2.0)
    assert torch.isfinite(at_zero).all() and at_zero.item() > burley_rd(torch.tensor([1e-3]), 0.8, 2.0).item()
    r_g = torch.tensor([0.3, 2.0], dtype=torch.float64, requires_grad=True)
    a_g = torch.tensor([0.7], dtype=torch.float64, requires_grad=True)
    s_g = torch.tensor([1.5], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda r_, a_, s_: burley_rd(r_.unsqueeze(-1), a_, s_), (r_g, a_g, s_g))


def test_burley_matches_dipole_energy_and_module():
    sa, ss, eta = _mat64("skin1")
    a, s = burley_params_from_dipole(sa, ss, eta)
    assert_close(a, total_diffuse_reflectance(sa, ss, eta))
    m = BurleyMaterial.from_preset("skin1", dtype=torch.float64)
    assert_close(m.albedo, a, rtol=1e-9, atol=0)
    assert_close(m.s, s, rtol=1e-9, atol=0)
    r = torch.linspace(0.1, 5, 10, dtype=torch.float64).unsqueeze(-1)
    exact = BurleyMaterial.from_preset("skin1", dtype=torch.float64, core=0.0)
    assert_close(exact(r), burley_rd(r, a, s), rtol=1e-9, atol=0)
    # the default core (radius 1/s) is the exact profile outside and its disk mean inside: same total energy
    outside = r >= 1.0 / s
    assert_close(m(r)[outside.expand(-1, 3)], burley_rd(r, a, s)[outside.expand(-1, 3)], rtol=1e-9, atol=0)
    rho = (1.0 / s).unsqueeze(0)
    mean = burley_cumulative(rho, a, s) / (math.pi * rho**2)
    assert_close(m(torch.zeros(1, 1, dtype=torch.float64)), mean, rtol=1e-12, atol=0)
    assert_close(m.cumulative(torch.full((1, 1), math.inf, dtype=torch.float64))[0], a, rtol=1e-12, atol=0)
    # the core's cumulative is the quadrature of the evaluated profile (closed form against numbers)
    rr = torch.linspace(0.0, 3.0, 30001, dtype=torch.float64).unsqueeze(-1)
    f = m(rr) * 2.0 * math.pi * rr
    quad = ((f[1:] + f[:-1]) * 0.5 * (rr[1:] - rr[:-1])).sum(0)
    assert_close(quad, m.cumulative(torch.full((1, 1), 3.0, dtype=torch.float64))[0], rtol=1e-4, atol=0)
    with pytest.raises(ValueError, match="core"):
        BurleyMaterial([0.5], [1.0], core=-1.0)
    m(r).sum().backward()
    assert torch.isfinite(m.raw_albedo.grad).all() and torch.isfinite(m.raw_s.grad).all()
    with pytest.raises(ValueError, match="albedo"):
        BurleyMaterial([1.2], [1.0])
    with pytest.raises(ValueError, match="s"):
        BurleyMaterial([0.5], [0.0])


def test_shared_range_row_path_matches_per_channel_path():
    sa, ss, eta = _mat64("skin1")
    rm = r_max(sa, ss, eta, 0.01)

    def prof(r):
        return dipole_rd(r, sa, ss, eta)

    shared = build_profile_table(prof, rm, 512, "sqrt", shared_range=True)
    assert torch.all(shared.r_max == rm.max())
    r1 = torch.rand(5000, 1, dtype=torch.float64) * rm.max() * 1.1  # includes r beyond the range
    fast = lookup_profile_table(r1, shared)  # row-gather path (outside autograd: the in-place form, _lookup_rows)
    general = lookup_profile_table(r1.expand(-1, 3).contiguous(), shared)  # per-channel path, same table
    assert_close(fast, general, rtol=1e-13, atol=0)  # p^4 for q^2 in the first segment: rounding only
    with torch.enable_grad():  # the row path's autograd form (masked square root) gives the same values
        graded = lookup_profile_table(r1.clone().requires_grad_(True), shared)
    assert_close(fast, graded.detach(), rtol=1e-13, atol=0)
    tiny = torch.tensor([[0.0], [0.3], [0.99]], dtype=torch.float64) * rm.max() / 511 ** 2  # the first segment
    with torch.enable_grad():
        expect = lookup_profile_table(tiny.clone().requires_grad_(True), shared).detach()
    assert_close(lookup_profile_table(tiny, shared), expect, rtol=1e-13, atol=0)
    assert torch.all(fast[r1[:, 0] > rm.max()] == 0)
    err = profile_table_error(shared, prof)
    assert torch.all(err < 1e-3)
    # gradients flow through the row path
    vals = shared.values.detach().requires_grad_(True)
    lookup_profile_table(r1[:50], ProfileTable(vals, shared.r_max, "sqrt", True)).sum().backward()
    assert vals.grad.abs().sum() > 0
