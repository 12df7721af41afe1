"""EnvironmentLight (SH radiance, JSON forms) and the transmitted environment irradiance (Shah 2007, 6.4.2)."""

from __future__ import annotations

import math

import pytest
import torch
from scipy import integrate

from torchsss.geometry.environment import EnvironmentLight, environment_irradiance
from torchsss.physics.fresnel import fresnel_transmittance
from torchsss.physics.sh import project_sh, sh_basis

F64 = torch.float64


def _dirs(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=-1)


def test_uniform_coefficients_and_irradiance():
    env = EnvironmentLight.uniform((1.0, 0.5, 0.0))
    c = env.coefficients(F64)
    assert c.shape == (9, 3)
    assert torch.allclose(c[0], torch.tensor([1.0, 0.5, 0.0], dtype=F64) * math.sqrt(4 * math.pi))
    assert torch.count_nonzero(c[1:]) == 0
    normals = _dirs(20, 0)[None]
    e = environment_irradiance(env, normals, 1.3, fresnel="none")
    assert torch.allclose(e, torch.tensor([1.0, 0.5, 0.0], dtype=F64) * math.pi, atol=1e-13, rtol=0)
    # with Fresnel: E = c * 2 pi * integral_0^1 F_t(mu) mu dmu, every normal (adaptive quadrature reference)
    val, _ = integrate.quad(lambda mu: float(fresnel_transmittance(torch.tensor(mu, dtype=F64), 1.3)) * mu, 0, 1,
                            epsabs=1e-13)
    e = environment_irradiance(env, normals, 1.3)
    assert torch.allclose(e[..., 0], torch.full_like(e[..., 0], 2 * math.pi * val), atol=1e-12, rtol=0)


@pytest.mark.parametrize("seed", [0, 1])
def test_sky_irradiance_closed_form(seed):
    """The hemisphere sky's SH irradiance is exact: the step has no even bands >= 2, the cosine lobe no odd >= 3.

    So E(n) = pi [(1 + c) / 2 * sky + (1 - c) / 2 * ground], c = n . up (the classic hemisphere-light formula).
    """
    up = _dirs(1, 100 + seed)[0]
    sky, ground = (2.0, 1.0, 0.5), (0.1, 0.3, 0.0)
    env = EnvironmentLight.sky(sky, ground, up=tuple(up.tolist()))
    normals = _dirs(30, seed)
    normals[0] = up
    normals[1] = -up
    e = environment_irradiance(env, normals[None], 1.3, fresnel="none")[0]
    cos = (normals @ up)[:, None]
    ref = math.pi * ((1 + cos) / 2 * torch.tensor(sky, dtype=F64) + (1 - cos) / 2 * torch.tensor(ground, dtype=F64))
    assert torch.allclose(e, ref, atol=1e-12, rtol=0)


def test_sky_coefficients_match_projection():
    sky, ground = (1.0, 2.0, 3.0), (0.5, 0.0, 0.25)

    def step(d):
        up = d[:, 2:3] > 0  # the split quadrature integrates a step at z = 0 exactly
        return torch.where(up, torch.tensor(sky, dtype=d.dtype), torch.tensor(ground, dtype=d.dtype))

    ref = project_sh(step, n_theta=8)
    env = EnvironmentLight.sky(sky, ground, up=(0.0, 0.0, 3.0))  # up is normalised
    assert torch.allclose(env.coefficients(F64), ref, atol=1e-12, rtol=0)
    # default up = +y: the step is not at the quadrature's equator, so a dense rule converges slowly (loose)
    ref_y = project_sh(lambda d: torch.where(d[:, 1:2] > 0, torch.tensor(sky, dtype=d.dtype),
                                             torch.tensor(ground, dtype=d.dtype)), n_theta=60)
    assert torch.allclose(EnvironmentLight.sky(sky, ground).coefficients(F64), ref_y, atol=2e-3, rtol=0)


def test_from_dict_forms_and_round_trip():
    sh = [[0.1 * i, -0.2 * i, 0.3] for i in range(9)]
    env = EnvironmentLight.from_dict({"type": "environment", "sh": sh})
    assert torch.equal(env.coefficients(F64), torch.tensor(sh, dtype=F64))
    assert EnvironmentLight.from_dict(env.to_dict()) == env
    assert EnvironmentLight.from_dict({"type": "environment", "uniform": 2}) == EnvironmentLight.uniform((2, 2, 2))
    d = {"type": "environment", "sky": [1, 1, 1], "ground": [0, 0, 0], "up": [0, 0, 1]}
    assert EnvironmentLight.from_dict(d) == EnvironmentLight.sky(1.0, 0.0, (0, 0, 1))
    assert EnvironmentLight.from_dict({"type": "environment", "sky": 1, "ground": 0}) == EnvironmentLight.sky(1, 0)
    env_t = EnvironmentLight(torch.ones(9, 3))
    assert env_t.sh[8] == (1.0, 1.0, 1.0)


@pytest.mark.parametrize("d, exc, match", [
    ({"type": "point", "uniform": [1, 1, 1]}, ValueError, "environment type"),
    ({"type": "environment"}, ValueError, "exactly one of"),
    ({"type": "environment", "uniform": [1, 1, 1], "sky": [1, 1, 1]}, ValueError, "exactly one of"),
    ({"type": "environment", "sky": [1, 1, 1]}, ValueError, "missing"),
    ({"type": "environment", "uniform": [1, 1, 1], "up": [0, 1, 0]}, ValueError, "unknown keys"),
    ({"type": "environment", "sh": [[1, 1, 1]] * 8}, ValueError, "9 triples"),
    ({"type": "environment", "sh": [[1, 1]] * 9}, ValueError, "sh\\[0\\]"),
    ({"type": "environment", "sh": [[1, 1, "a"]] * 9}, TypeError, "sh\\[0\\]"),
    ({"type": "environment", "sh": [[1, 1, float("inf")]] * 9}, ValueError, "finite"),
    ({"type": "environment", "uniform": [1, -1, 1]}, ValueError, "rgb: expected values >= 0"),
    ({"type": "environment", "sky": [1, 1, 1], "ground": [0, 0, 0], "up": [0, 0, 0]}, ValueError, "up"),
    ({"type": "environment", "sky": "blue", "ground": [0, 0, 0]}, TypeError, "sky_rgb"),
    ([1, 2, 3], TypeError, "JSON object"),
])
def test_from_dict_errors(d, exc, match):
    with pytest.raises(exc, match=match):
        EnvironmentLight.from_dict(d)


def test_irradiance_per_channel_eta_and_dtypes():
    env = EnvironmentLight.sky((3.0, 2.0, 1.0), (0.2, 0.1, 0.0), up=(0.3, 1.0, 0.2))
    normals = _dirs(10, 2)[None]
    eta = torch.tensor([1.1, 1.3, 1.6], dtype=F64)
    e = environment_irradiance(env, normals, eta)
    for c in range(3):
        ec = environment_irradiance(env, normals, float(eta[c]))[..., c]
        assert torch.allclose(e[..., c], ec, atol=1e-14, rtol=0)
    e32 = environment_irradiance(env, normals.float(), 1.3)
    assert e32.dtype == torch.float32 and e32.shape == (1, 10, 3)
    assert torch.allclose(e32.double(), environment_irradiance(env, normals, 1.3), atol=1e-5)


def test_irradiance_clamped_non_negative_and_raw_matches_basis():
    # a bright "sun" projected to order 2 rings negative on its far side
    sun = torch.nn.functional.normalize(torch.tensor([0.2, 1.0, 0.1], dtype=F64), dim=0)
    coeffs = 10.0 * sh_basis(sun)[:, None].expand(9, 3)
    env = EnvironmentLight(coeffs)
    normals = _dirs(200, 3)[None]
    e = environment_irradiance(env, normals, 1.3)
    raw = environment_irradiance(env, normals, 1.3, clamp=False)
    assert (raw < 0).any() and (e >= 0).all()
    assert torch.equal(e, raw.clamp_min(0.0))


def test_irradiance_gradcheck_eta_and_normals():
    env = EnvironmentLight.sky((1.0, 2.0, 0.5), (0.3, 0.2, 0.1), up=(0.0, 0.6, 0.8))
    normals = _dirs(4, 5)[None].requires_grad_(True)
    eta = torch.tensor([0.9, 1.3, 1.7], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda n, e: environment_irradiance(env, n, e, clamp=False), (normals, eta))


def test_irradiance_errors():
    env = EnvironmentLight.uniform(1.0)
    with pytest.raises(TypeError, match="env"):
        environment_irradiance({"type": "environment"}, torch.zeros(1, 2, 3))
    with pytest.raises(ValueError, match="normals"):
        environment_irradiance(env, torch.zeros(2, 3))
    with pytest.raises(TypeError, match="normals"):
        environment_irradiance(env, torch.zeros(1, 2, 3, dtype=torch.int64))
    with pytest.raises(ValueError, match="eta"):
        environment_irradiance(env, torch.zeros(1, 2, 3), torch.tensor([1.3, 1.4]))
    with pytest.raises(ValueError, match="eta"):
        environment_irradiance(env, torch.zeros(1, 2, 3), -1.0)
    with pytest.raises(ValueError, match="fresnel"):
        environment_irradiance(env, torch.zeros(1, 2, 3), fresnel="approx")
    with pytest.raises(ValueError, match="sh"):
        EnvironmentLight(((1.0, 1.0, 1.0),) * 3)
