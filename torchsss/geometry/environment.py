"""Distant environment lighting in order-2 spherical harmonics (Shah 2007, section 6.4.2).

An :class:`EnvironmentLight` holds the 9 radiance coefficients :math:`L_{lm}` per RGB channel (basis and order of
:mod:`torchsss.physics.sh`) of the radiance arriving from direction :math:`\\omega` (the direction *towards* the
environment, i.e. the incident light travels along :math:`-\\omega`). :func:`environment_irradiance` gives the
transmitted irradiance :math:`E(n) = \\int L(\\omega) F_t(\\eta, n\\cdot\\omega) \\max(0, n\\cdot\\omega)
d\\omega` at surface normals through the Fresnel-cosine zonal lobe (Shah eq. 6.19-6.21).

Environment occlusion is ignored, as in Shah: every point receives the whole environment over its hemisphere,
including directions in which the object itself blocks the sky (concave regions are too bright). Units: the
radiance is per steradian in the scene's light units, so :math:`E` is irradiance (per mm^2).

Scene JSON forms (one of the three light sources besides ``"sh"``)::

    {"type": "environment", "sh": [[r, g, b], ... 9 triples]}
    {"type": "environment", "uniform": [r, g, b]}
    {"type": "environment", "sky": [r, g, b], "ground": [r, g, b], "up": [0, 1, 0]}
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsss._checks import check_shape, check_tensor
from torchsss.physics.sh import SH_COEFFS, fresnel_cosine_zonal, sh_basis, sh_irradiance

__all__ = ["EnvironmentLight", "environment_irradiance"]

_ENV_FORMS = {"sh": set(), "uniform": set(), "sky": {"ground"}}  # required companions of each form
_ENV_OPTIONAL = {"sh": set(), "uniform": set(), "sky": {"up"}}


def _triple(value: object, name: str, nonnegative: bool) -> tuple[float, float, float]:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = (value, value, value)
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise TypeError(f"{name}: expected 3 numbers, got {type(value).__name__}")
    if len(value) != 3:
        raise ValueError(f"{name}: expected 3 numbers, got {len(value)} entries: {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise TypeError(f"{name}: expected 3 numbers, got {value!r}")
        out.append(float(v))
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name}: expected finite numbers, got {value!r}")
    if nonnegative and min(out) < 0:
        raise ValueError(f"{name}: expected values >= 0, got {value!r}")
    return tuple(out)  # type: ignore[return-value]


@dataclass(frozen=True)
class EnvironmentLight:
    """A distant environment as 9 SH radiance coefficients per RGB channel.

    Attributes:
        sh: 9 triples ``(r, g, b)``, the coefficients :math:`L_{lm}` in the order of
            :func:`~torchsss.physics.sh.sh_basis`. Individual coefficients may be negative (only the function they
            describe should be mostly non-negative); they are validated as finite.

    Examples:
        >>> env = EnvironmentLight.uniform((1.0, 0.5, 0.25))
        >>> round(env.sh[0][0] / math.sqrt(4.0 * math.pi), 6), env.sh[1]
        (1.0, (0.0, 0.0, 0.0))
        >>> EnvironmentLight.from_dict({"type": "environment", "uniform": [1, 1, 1]}) == EnvironmentLight.uniform(1.0)
        True
    """

    sh: tuple[tuple[float, float, float], ...]
    kind = "environment"

    def __post_init__(self) -> None:
        sh = self.sh
        if isinstance(sh, Tensor):
            sh = sh.detach().cpu().tolist()
        if isinstance(sh, (str, bytes)) or not isinstance(sh, Sequence):
            raise TypeError(f"sh: expected 9 triples (r, g, b), got {type(sh).__name__}")
        if len(sh) != SH_COEFFS:
            raise ValueError(f"sh: expected {SH_COEFFS} triples (r, g, b), got {len(sh)} entries")
        object.__setattr__(self, "sh", tuple(_triple(c, f"sh[{i}]", False) for i, c in enumerate(sh)))

    @classmethod
    def uniform(cls, rgb: Sequence[float] | float) -> EnvironmentLight:
        """A constant radiance ``rgb`` (>= 0) from every direction: :math:`L_{00} = \\sqrt{4\\pi}\\,c`.

        With :math:`F_t \\equiv 1` a surface receives :math:`E = \\pi c` at every normal.
        """
        c = _triple(rgb, "rgb", True)
        k = math.sqrt(4.0 * math.pi)
        return cls(((c[0] * k, c[1] * k, c[2] * k),) + ((0.0, 0.0, 0.0),) * (SH_COEFFS - 1))

    @classmethod
    def sky(cls, sky_rgb: Sequence[float] | float, ground_rgb: Sequence[float] | float,
            up: Sequence[float] = (0.0, 1.0, 0.0)) -> EnvironmentLight:
        """A hemispherical environment: radiance ``sky_rgb`` where :math:`\\omega\\cdot up > 0`, ``ground_rgb`` below.

        Projected in closed form (Funk-Hecke with the step kernel, whose band integrals are
        :math:`2\\pi\\int_0^1 P_l = 2\\pi, \\pi, 0`): :math:`L_{lm} = \\sqrt{4\\pi}\\,g\\,\\delta_{l0} + (s - g)\\,
        (2\\pi, \\pi, 0)_l\\,Y_{lm}(up)`. The order-2 projection of the step is smooth (it rings a little:
        the projected radiance overshoots slightly past the sky value near the zenith and below the ground value at
        the nadir).

        Examples:
            >>> env = EnvironmentLight.sky(1.0, 0.0, up=(0, 0, 1))
            >>> [round(c[0], 4) for c in env.sh]
            [1.7725, 0.0, 1.5350, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        """
        s = _triple(sky_rgb, "sky_rgb", True)
        g = _triple(ground_rgb, "ground_rgb", True)
        u = _triple(up, "up", False)
        norm = math.sqrt(sum(c * c for c in u))
        if norm == 0.0:
            raise ValueError(f"up: expected a non-zero direction, got {up!r}")
        y = sh_basis(torch.tensor([c / norm for c in u], dtype=torch.float64)).tolist()
        band = (2.0 * math.pi, math.pi, 0.0)
        lvals = (0, 1, 1, 1, 2, 2, 2, 2, 2)
        coeffs = []
        for i in range(SH_COEFFS):
            coeffs.append(tuple((math.sqrt(4.0 * math.pi) * g[c] if i == 0 else 0.0)
                                + (s[c] - g[c]) * band[lvals[i]] * y[i] for c in range(3)))
        return cls(tuple(coeffs))

    @classmethod
    def from_dict(cls, d: Mapping) -> EnvironmentLight:
        """Build an environment from its scene-JSON block (module docstring for the three forms).

        Raises:
            TypeError: ``d`` not a mapping, values of the wrong type (the key is named).
            ValueError: a ``"type"`` other than ``"environment"``, none or several of ``"sh"``, ``"uniform"``,
                ``"sky"``, unknown or missing keys, bad values.

        Examples:
            >>> env = EnvironmentLight.from_dict({"type": "environment", "sky": [1, 1, 1], "ground": [0, 0, 0],
            ...                                   "up": [0, 0, 1]})
            >>> round(env.sh[2][1], 4)
            1.535
        """
        if not isinstance(d, Mapping):
            raise TypeError(f"environment: expected a JSON object, got {type(d).__name__}")
        if d.get("type") != "environment":
            raise ValueError(f"environment type: expected 'environment', got {d.get('type')!r}")
        keys = set(d) - {"type"}
        forms = sorted(keys & set(_ENV_FORMS))
        if len(forms) != 1:
            raise ValueError(f"environment: expected exactly one of {sorted(_ENV_FORMS)}, got {forms}")
        form = forms[0]
        required = {form} | _ENV_FORMS[form]
        if missing := required - keys:
            raise ValueError(f"environment ({form}): expected keys {sorted(required)}, missing {sorted(missing)}")
        if unknown := keys - required - _ENV_OPTIONAL[form]:
            raise ValueError(f"environment ({form}): unknown keys {sorted(unknown)}; allowed "
                             f"{sorted(required | _ENV_OPTIONAL[form])}")
        if form == "sh":
            return cls(d["sh"])
        if form == "uniform":
            return cls.uniform(d["uniform"])
        return cls.sky(d["sky"], d["ground"], d.get("up", (0.0, 1.0, 0.0)))

    def to_dict(self) -> dict:
        """The JSON ``"sh"`` form, which :meth:`from_dict` reads back."""
        return {"type": "environment", "sh": [list(c) for c in self.sh]}

    def coefficients(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """The coefficients as a :math:`(9, 3)` tensor (coefficient, RGB)."""
        return torch.tensor(self.sh, dtype=dtype, device=device)


def environment_irradiance(env: EnvironmentLight, normals: Tensor, eta: Tensor | float = 1.3, *,
                           fresnel: str = "exact", clamp: bool = True) -> Tensor:
    """Unshadowed transmitted irradiance :math:`E(n)` of an environment at surface normals (Shah eq. 6.19).

    :math:`E(n) = \\sum_{lm} A_l(\\eta) L_{lm} Y_{lm}(n)` with the zonal Fresnel-cosine lobe
    :func:`~torchsss.physics.sh.fresnel_cosine_zonal`; exact for the band-limited environment. Occlusion of the
    environment (by the object itself) is ignored, as in Shah. Clamped at 0 (see
    :func:`~torchsss.physics.sh.sh_irradiance`).

    Args:
        env: the environment.
        normals: :math:`(B, N, 3)` unit outward normals.
        eta: relative index of refraction, a number, a 0-dim tensor or a per-channel :math:`(3,)` tensor.
        fresnel: ``"exact"``, ``"schlick"`` or ``"none"``.
        clamp: clamp the irradiance at 0.

    Returns:
        :math:`(B, N, 3)` in the normals' dtype and device.

    Raises:
        TypeError: a non-environment ``env``, non-floating normals.
        ValueError: wrong shapes, a bad ``eta`` or ``fresnel``.

    Examples:
        >>> env = EnvironmentLight.uniform(1.0)
        >>> e = environment_irradiance(env, torch.tensor([[[0.0, 0.0, 1.0]]]), fresnel="none")
        >>> [round(v / math.pi, 6) for v in e[0, 0].tolist()]
        [1.0, 1.0, 1.0]
    """
    if not isinstance(env, EnvironmentLight):
        raise TypeError(f"env: expected an EnvironmentLight, got {type(env).__name__}")
    check_tensor(normals, "normals")
    check_shape(normals, "normals", "B,N,3")
    dtype, device = normals.dtype, normals.device
    eta_t = eta.to(device=device) if isinstance(eta, Tensor) else torch.tensor(eta, dtype=dtype, device=device)
    if eta_t.dim() > 1 or (eta_t.dim() == 1 and eta_t.shape[0] not in (1, 3)):
        raise ValueError(f"eta: expected a number, a 0-dim tensor or shape (3,), got {tuple(eta_t.shape)}")
    zonal = fresnel_cosine_zonal(eta_t, fresnel=fresnel)
    if zonal.dim() == 2:
        zonal = zonal.expand(3, 3)
    return sh_irradiance(env.coefficients(dtype, device), normals, zonal.to(dtype), clamp=clamp).to(dtype)
