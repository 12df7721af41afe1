"""Order-2 real spherical harmonics, the Fresnel-cosine zonal lobe and SH irradiance (Shah 2007, 6.4.2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate
from scipy.special import sph_harm_y

from torchsss.physics.fresnel import fresnel_transmittance, schlick_transmittance
from torchsss.physics.sh import (
    fresnel_cosine_zonal,
    project_sh,
    sh_basis,
    sh_irradiance,
    sphere_quadrature,
)

F64 = torch.float64
LM = [(0, 0), (1, -1), (1, 0), (1, 1), (2, -2), (2, -1), (2, 0), (2, 1), (2, 2)]
RH = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)


def _gl_sphere(n: int = 24):
    """Independent product quadrature: Gauss-Legendre in cos(theta) on [-1, 1] x uniform azimuth (numpy)."""
    x, w = np.polynomial.legendre.leggauss(n)
    phi = np.arange(2 * n) * (math.pi / n)
    zz, pp = np.meshgrid(x, phi, indexing="ij")
    r = np.sqrt(1.0 - zz * zz)
    d = np.stack([r * np.cos(pp), r * np.sin(pp), zz], -1).reshape(-1, 3)
    wt = (w[:, None] * np.full(2 * n, math.pi / n)).reshape(-1)
    return torch.tensor(d), torch.tensor(wt)


def _random_dirs(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=-1)


# -- basis ----------------------------------------------------------------------------------------------------------
def test_orthonormal_by_quadrature():
    d, w = _gl_sphere(24)
    y = sh_basis(d)
    gram = (y * w[:, None]).T @ y
    assert torch.allclose(gram, torch.eye(9, dtype=F64), atol=1e-12, rtol=0)


def test_matches_scipy_real_harmonics():
    d = _random_dirs(50)
    theta = torch.arccos(d[:, 2].clamp(-1, 1)).numpy()
    phi = torch.atan2(d[:, 1], d[:, 0]).numpy()
    y = sh_basis(d).numpy()
    for i, (deg, m) in enumerate(LM):
        c = sph_harm_y(deg, abs(m), theta, phi)  # complex, with the Condon-Shortley phase
        if m == 0:
            ref = c.real
        elif m > 0:
            ref = math.sqrt(2.0) * (-1) ** m * c.real
        else:
            ref = math.sqrt(2.0) * (-1) ** m * c.imag
        np.testing.assert_allclose(y[:, i], ref, atol=1e-13)


def test_basis_shapes_and_errors():
    assert sh_basis(torch.zeros(2, 5, 3)).shape == (2, 5, 9)
    assert sh_basis(torch.zeros(3, dtype=F64)).dtype == F64
    with pytest.raises(ValueError, match="directions: expected shape"):
        sh_basis(torch.zeros(4, 2))
    with pytest.raises(TypeError, match="directions"):
        sh_basis(torch.zeros(4, 3, dtype=torch.int64))


def test_sphere_quadrature_exact_for_polynomials():
    d, w = sphere_quadrature(5)
    assert d.shape == (100, 3) and math.isclose(float(w.sum()), 4 * math.pi, rel_tol=1e-14)
    # integral of x^4 y^2 z^2 over the sphere = 4 pi * 3!! 1!! 1!! / 9!! = 4 pi * 3 / 945 (degree 8 < 10)
    val = float((w * d[:, 0] ** 4 * d[:, 1] ** 2 * d[:, 2] ** 2).sum())
    assert math.isclose(val, 4 * math.pi * 3 / 945, rel_tol=1e-12)
    with pytest.raises(ValueError, match="n_theta"):
        sphere_quadrature(0)
    with pytest.raises(TypeError, match="n_theta"):
        sphere_quadrature(2.0)


# -- zonal lobe -----------------------------------------------------------------------------------------------------
def test_zonal_without_fresnel_is_rh_cosine_lobe():
    for eta in (0.5, 1.0, 1.3, 3.0):
        a = fresnel_cosine_zonal(torch.tensor(eta, dtype=F64), fresnel="none")
        assert torch.allclose(a, torch.tensor(RH, dtype=F64), atol=1e-13, rtol=0)
    # eta == 1: F_t == 1 exactly, so the exact lobe is the cosine lobe too
    assert torch.allclose(fresnel_cosine_zonal(torch.tensor(1.0, dtype=F64)), torch.tensor(RH, dtype=F64),
                          atol=1e-13, rtol=0)


def _quad_zonal(eta: float, fresnel: str) -> list[float]:
    ft_fn = fresnel_transmittance if fresnel == "exact" else schlick_transmittance
    mu_c = math.sqrt(max(0.0, 1.0 - eta * eta))
    legendre = (lambda m: 1.0, lambda m: m, lambda m: 1.5 * m * m - 0.5)
    out = []
    for p in legendre:
        def f(mu, p=p):
            return float(ft_fn(torch.tensor(mu, dtype=F64), eta)) * mu * p(mu)
        val, _ = integrate.quad(f, mu_c, 1.0, epsabs=1e-13, epsrel=1e-13, limit=200)
        out.append(2.0 * math.pi * val)
    return out


@pytest.mark.parametrize("eta", [0.5, 0.8, 0.99, 1.01, 1.3, 1.5, 3.0])
@pytest.mark.parametrize("fresnel", ["exact", "schlick"])
def test_zonal_against_adaptive_quadrature(eta, fresnel):
    a = fresnel_cosine_zonal(torch.tensor(eta, dtype=F64), fresnel=fresnel)
    ref = torch.tensor(_quad_zonal(eta, fresnel), dtype=F64)
    assert torch.allclose(a, ref, atol=1e-11, rtol=0), (a - ref).abs().max()


def test_zonal_per_channel_and_extremes():
    eta = torch.tensor([[0.7, 1.3, 2.0], [1.0, 1.5, 1.1]], dtype=F64)
    a = fresnel_cosine_zonal(eta)
    assert a.shape == (2, 3, 3)
    for idx in np.ndindex(2, 3):
        single = fresnel_cosine_zonal(eta[idx])
        assert torch.allclose(a[idx], single, atol=1e-15, rtol=0)
    assert fresnel_cosine_zonal(1.3).dtype == torch.float32
    # transmitted energy below the cosine lobe; it falls as eta moves away from 1 either way
    a0 = fresnel_cosine_zonal(torch.tensor([0.05, 0.5, 1.0, 2.0, 100.0], dtype=F64))[:, 0]
    assert torch.isfinite(a0).all() and (a0 > 0).all() and (a0 <= math.pi + 1e-12).all()
    assert a0[0] < a0[1] < a0[2] and a0[2] > a0[3] > a0[4]


def test_zonal_gradcheck():
    eta = torch.tensor([0.8, 1.3, 2.0], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda e: fresnel_cosine_zonal(e), (eta,))
    assert torch.autograd.gradcheck(lambda e: fresnel_cosine_zonal(e, fresnel="schlick"), (eta,))


def test_zonal_errors():
    with pytest.raises(ValueError, match="eta"):
        fresnel_cosine_zonal(0.0)
    with pytest.raises(ValueError, match="eta"):
        fresnel_cosine_zonal(torch.tensor([1.3, float("nan")]))
    with pytest.raises(ValueError, match="fresnel"):
        fresnel_cosine_zonal(1.3, fresnel="fancy")
    with pytest.raises(TypeError, match="eta"):
        fresnel_cosine_zonal("1.3")


# -- irradiance -----------------------------------------------------------------------------------------------------
def _frame(n: torch.Tensor):
    a = torch.tensor([1.0, 0.0, 0.0], dtype=F64) if abs(float(n[0])) < 0.9 else torch.tensor([0.0, 1.0, 0.0],
                                                                                                 dtype=F64)
    t = torch.nn.functional.normalize(torch.linalg.cross(n, a), dim=0)
    return t, torch.linalg.cross(n, t)


def _direct_irradiance(coeffs: torch.Tensor, n: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Integral of L_SH(w) F_t(eta, n.w) max(0, n.w) dw over the hemisphere around n, by quadrature in n's frame.

    mu = n.w by Gauss-Legendre on [mu_c, 1] with mu = mu_c + (1 - mu_c) s^2 (mu_c the critical angle of eta < 1),
    the azimuth uniformly (L is a polynomial of degree 2, so 8 azimuths are exact). Per channel (eta per channel).
    """
    t, b = _frame(n)
    s, ws = np.polynomial.legendre.leggauss(80)
    s, ws = torch.tensor(0.5 * (s + 1)), torch.tensor(0.5 * ws)
    phi = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    out = []
    for c in range(coeffs.shape[1]):
        mu_c = math.sqrt(max(0.0, 1.0 - float(eta[c]) ** 2))
        mu = mu_c + (1 - mu_c) * s * s
        jac = 2 * (1 - mu_c) * s
        r = torch.sqrt(1 - mu * mu)
        w = (mu[:, None, None] * n + (r[:, None] * torch.cos(phi))[..., None] * t
             + (r[:, None] * torch.sin(phi))[..., None] * b)  # (Q, P, 3)
        lval = sh_basis(w) @ coeffs[:, c]
        ft = fresnel_transmittance(mu, eta[c])
        out.append(float(((ws * jac * ft * mu)[:, None] * lval).sum() * (2 * math.pi / 8)))
    return torch.tensor(out, dtype=F64)


def test_irradiance_against_direct_quadrature():
    g = torch.Generator().manual_seed(3)
    coeffs = torch.randn(9, 3, generator=g, dtype=F64)
    normals = _random_dirs(6, seed=4)
    eta = torch.tensor([0.8, 1.3, 2.0], dtype=F64)
    e = sh_irradiance(coeffs, normals, fresnel_cosine_zonal(eta), clamp=False)
    assert e.shape == (6, 3)
    for i in range(6):
        ref = _direct_irradiance(coeffs, normals[i], eta)
        assert torch.allclose(e[i], ref, atol=1e-11, rtol=0), (e[i] - ref).abs().max()


def test_irradiance_batch_broadcast_shared_zonal():
    g = torch.Generator().manual_seed(5)
    coeffs = torch.randn(2, 9, 3, generator=g, dtype=F64)
    normals = _random_dirs(8, seed=6).view(2, 4, 3)
    zonal = fresnel_cosine_zonal(torch.tensor(1.3, dtype=F64))
    e = sh_irradiance(coeffs, normals, zonal, clamp=False)
    assert e.shape == (2, 4, 3)
    scale = zonal[[0, 1, 1, 1, 2, 2, 2, 2, 2]]
    for b in range(2):
        ref = torch.einsum("nk,k,kc->nc", sh_basis(normals[b]), scale, coeffs[b])  # loop reference
        assert torch.allclose(e[b], ref, atol=1e-13, rtol=0)
    # one environment, several normal sets: leading dims broadcast
    e2 = sh_irradiance(coeffs[0], normals, zonal, clamp=False)
    assert torch.allclose(e2[1], sh_irradiance(coeffs[0], normals[1], zonal, clamp=False))


def test_irradiance_clamp():
    coeffs = torch.zeros(9, 1, dtype=F64)
    coeffs[0, 0] = 0.2
    coeffs[2, 0] = 1.0  # a strong z gradient: negative on the -z side
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=F64)
    zonal = torch.tensor(RH, dtype=F64)
    raw = sh_irradiance(coeffs, normals, zonal, clamp=False)
    assert raw[1, 0] < 0 < raw[0, 0]
    assert torch.equal(sh_irradiance(coeffs, normals, zonal), raw.clamp_min(0.0))


def test_irradiance_gradcheck():
    g = torch.Generator().manual_seed(7)
    coeffs = torch.randn(9, 2, generator=g, dtype=F64, requires_grad=True)
    normals = _random_dirs(3, seed=8).requires_grad_(True)
    zonal = torch.tensor([[3.0, 2.0, 0.7], [2.5, 1.5, 0.5]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, n, z: sh_irradiance(c, n, z, clamp=False), (coeffs, normals, zonal))


def test_irradiance_errors():
    n = torch.zeros(4, 3)
    with pytest.raises(ValueError, match="coeffs"):
        sh_irradiance(torch.zeros(8, 3), n, torch.zeros(3))
    with pytest.raises(ValueError, match="normals"):
        sh_irradiance(torch.zeros(9, 3), torch.zeros(4, 2), torch.zeros(3))
    with pytest.raises(ValueError, match="zonal"):
        sh_irradiance(torch.zeros(9, 3), n, torch.zeros(2, 3))
    with pytest.raises(TypeError, match="coeffs"):
        sh_irradiance([0.0] * 9, n, torch.zeros(3))


# -- projection -----------------------------------------------------------------------------------------------------
def test_project_constant_and_round_trip():
    c = project_sh(lambda d: torch.full((d.shape[0], 3), 1.5, dtype=d.dtype))
    assert torch.allclose(c[0], torch.full((3,), 1.5 * math.sqrt(4 * math.pi), dtype=F64), atol=1e-13, rtol=0)
    assert c[1:].abs().max() < 1e-13
    g = torch.Generator().manual_seed(9)
    coeffs = torch.randn(9, 2, generator=g, dtype=F64)
    back = project_sh(lambda d: sh_basis(d) @ coeffs, n_theta=4)
    assert torch.allclose(back, coeffs, atol=1e-13, rtol=0)


def test_project_clamped_cosine_sky_gives_rh_constants():
    c = project_sh(lambda d: d[:, 2].clamp_min(0.0))  # kink at the equator: split quadrature is exact
    y_z = sh_basis(torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    ref = torch.tensor([RH[lv] for lv in (0, 1, 1, 1, 2, 2, 2, 2, 2)], dtype=F64) * y_z  # Funk-Hecke
    assert torch.allclose(c, ref, atol=1e-13, rtol=0)
    assert math.isclose(float(c[0]), math.sqrt(math.pi) / 2, rel_tol=1e-13)


def test_project_samples_matches_callable():
    d, w = sphere_quadrature(12)

    def fn(x):
        return torch.stack([torch.exp(x[:, 0]), x[:, 1] ** 4], dim=-1)

    assert torch.allclose(project_sh(fn(d), d, w), project_sh(fn, n_theta=12), atol=1e-14, rtol=0)
    # Monte Carlo samples: unbiased, loose
    dirs = _random_dirs(200000, seed=11)
    mc = project_sh(fn(dirs), dirs, torch.full((dirs.shape[0],), 4 * math.pi / dirs.shape[0], dtype=F64))
    assert torch.allclose(mc, project_sh(fn), atol=0.03)
    assert project_sh(d[:, 2], d, w).shape == (9,)


def test_project_errors():
    d, w = sphere_quadrature(2)
    with pytest.raises(ValueError, match="directions"):
        project_sh(torch.zeros(d.shape[0], 3, dtype=F64))
    with pytest.raises(ValueError, match="weights"):
        project_sh(torch.zeros(d.shape[0], 3, dtype=F64), d, w[:-1])
    with pytest.raises(ValueError, match="fn"):
        project_sh(torch.zeros(3, 3, dtype=F64), d, w)
    with pytest.raises(TypeError, match="fn"):
        project_sh("sky")
    with pytest.raises(TypeError, match="fn"):
        project_sh(lambda x: 1.0)
