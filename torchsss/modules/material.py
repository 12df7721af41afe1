"""Learnable materials: the dipole (Jensen 2001) and Burley's normalized diffusion, behind one interface.

A material is an ``nn.Module`` whose ``forward(r)`` evaluates its diffusion profile at distances ``r`` (mm), so
it can be handed to anything that takes a profile callable (the reference integrator, lookup tables, the
rendering modules). Parameters are stored unconstrained and mapped through ``softplus`` so that optimisation
can never leave the valid range.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchsss._checks import as_float_tensor, check_nonnegative, check_positive, is_tracing
from torchsss.physics.budget import r_max as _r_max
from torchsss.physics.burley import burley_params_from_dipole, burley_rd
from torchsss.physics.dipole import dipole_rd, total_diffuse_reflectance
from torchsss.physics.lut import ProfileTable, build_profile_table, lookup_profile_table
from torchsss.physics.materials import preset

__all__ = ["POSITIVE_FLOOR", "BurleyMaterial", "DipoleMaterial", "TabulatedMaterial"]

#: Smallest value a softplus-parameterised coefficient is initialised to. A coefficient given as exactly 0
#: (e.g. spectralon's absorption) becomes 1e-12 mm^-1 (an extinction length of 1e9 km), indistinguishable in
#: any rendering, while keeping the parameter finite and trainable.
POSITIVE_FLOOR = 1e-12

Number = float | int
Coeff = Tensor | Number | Sequence[Number]


def _softplus(x: Tensor) -> Tensor:
    """log(1 + e^x), switching to x above 40 (not torch's default 20, which is off by e^-20 ~ 2e-9 relative).

    Unlike ``logaddexp`` it exports to ONNX without losing float32 accuracy.
    """
    return F.softplus(x, beta=1.0, threshold=40.0)


def _inverse_softplus(x: Tensor) -> Tensor:
    x64 = x.to(torch.float64).clamp_min(POSITIVE_FLOOR)
    return (x64 + torch.log(-torch.expm1(-x64))).to(x.dtype)


def _like(dtype: torch.dtype | None) -> Tensor:
    """An empty tensor whose dtype Python numbers should take (the default dtype when none is asked for)."""
    return torch.empty(0, dtype=dtype or torch.get_default_dtype())


def _coeff(value: Coeff, name: str, dtype: torch.dtype | None, device: torch.device | str | None) -> Tensor:
    # Python numbers go straight to the requested dtype (never through float32 first).
    like = None if isinstance(value, Tensor) or dtype is None else _like(dtype)
    t = as_float_tensor(value, name, like=like)
    return t.detach().to(dtype=dtype or t.dtype, device=device).clone()


class DipoleMaterial(nn.Module):
    """A homogeneous material of the dipole model with learnable :math:`\\sigma_a`, :math:`\\sigma_s'`, :math:`\\eta`.

    Args:
        sigma_a: absorption coefficient in mm^-1, shape :math:`(C,)` (or a number: C = 1); >= 0.
        sigma_s_prime: reduced scattering coefficient in mm^-1, same shape as ``sigma_a``; >= 0, and
            ``sigma_a + sigma_s_prime > 0``.
        eta: relative index of refraction (> 0), a number or shape :math:`(C,)`.
        dtype, device: of the parameters (default: the tensors' own, float32 for numbers).

    Shapes:
        ``forward(r)``: :math:`(..., C)` or :math:`(..., 1)` distances in mm -> :math:`(..., C)` profile in mm^-2.

    Examples:
        >>> m = DipoleMaterial.from_preset("skin1")
        >>> [round(v, 4) for v in m.sigma_s_prime.tolist()]
        [0.74, 0.88, 1.01]
        >>> m(torch.tensor([[0.0], [1.0]])).shape
        torch.Size([2, 3])
    """

    def __init__(
        self,
        sigma_a: Coeff,
        sigma_s_prime: Coeff,
        eta: Coeff = 1.3,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        sa = _coeff(sigma_a, "sigma_a", dtype, device)
        ss = _coeff(sigma_s_prime, "sigma_s_prime", dtype or sa.dtype, sa.device)
        et = _coeff(eta, "eta", dtype or sa.dtype, sa.device)
        if sa.dim() > 1:
            raise ValueError(f"sigma_a: expected shape (C,) or a scalar, got {tuple(sa.shape)}")
        if ss.shape != sa.shape:
            raise ValueError(f"sigma_s_prime: expected the shape of sigma_a {tuple(sa.shape)}, got {tuple(ss.shape)}")
        if et.dim() > 1 or (et.dim() == 1 and et.shape[0] not in (1, max(sa.numel(), 1))):
            raise ValueError(f"eta: expected a scalar or shape ({sa.numel()},), got {tuple(et.shape)}")
        check_nonnegative(sa, "sigma_a")
        check_nonnegative(ss, "sigma_s_prime")
        check_positive(et, "eta")
        if bool(((sa + ss) <= 0).any()):
            raise ValueError("sigma_a + sigma_s_prime: expected > 0 in every channel, got 0")
        self.raw_sigma_a = nn.Parameter(_inverse_softplus(sa))
        self.raw_sigma_s_prime = nn.Parameter(_inverse_softplus(ss))
        self.raw_eta = nn.Parameter(_inverse_softplus(et))

    # -- constructors -------------------------------------------------------------------------------------------
    @classmethod
    def from_preset(cls, name: str, **kwargs) -> DipoleMaterial:
        """One of the 12 Jensen 2001 measurements (case-insensitive name, e.g. ``"marble"``, ``"Skin1"``).

        Raises:
            ValueError: unknown name (the message lists the valid ones).
        """
        p = preset(name)
        return cls(list(p.sigma_a), list(p.sigma_s_prime), p.eta, **kwargs)

    @classmethod
    def from_scattering(cls, sigma_a: Coeff, sigma_s: Coeff, g: Coeff, eta: Coeff = 1.3, **kwargs) -> DipoleMaterial:
        """From the scattering coefficient and the mean cosine: :math:`\\sigma_s' = (1 - g)\\sigma_s`.

        Args:
            sigma_a: absorption (mm^-1).
            sigma_s: scattering coefficient (mm^-1), >= 0.
            g: phase-function anisotropy in (-1, 1).
            eta: relative index of refraction.
            **kwargs: ``dtype`` and ``device``, as in the constructor.
        """
        ss = as_float_tensor(sigma_s, "sigma_s", like=_like(kwargs.get("dtype")))
        gg = as_float_tensor(g, "g", like=ss)
        check_nonnegative(ss, "sigma_s")
        if bool(((gg <= -1) | (gg >= 1) | torch.isnan(gg)).any()):
            raise ValueError(f"g: expected values in (-1, 1), got {gg.tolist()}")
        return cls(sigma_a, (1.0 - gg) * ss, eta, **kwargs)

    # -- parameters in physical units ---------------------------------------------------------------------------
    @property
    def sigma_a(self) -> Tensor:
        """Absorption coefficient (mm^-1), :math:`(C,)`."""
        return _softplus(self.raw_sigma_a)

    @property
    def sigma_s_prime(self) -> Tensor:
        """Reduced scattering coefficient (mm^-1), :math:`(C,)`."""
        return _softplus(self.raw_sigma_s_prime)

    @property
    def eta(self) -> Tensor:
        """Relative index of refraction."""
        return _softplus(self.raw_eta)

    @property
    def channels(self) -> int:
        """Number of colour channels C."""
        return max(self.raw_sigma_a.numel(), 1)

    def forward(
        self, r: Tensor, distance_scale: Tensor | None = None, irradiance_scale: Tensor | None = None
    ) -> Tensor:
        """Evaluate :math:`M_i R_d(r M_d)` (see :func:`torchsss.dipole_rd`); ``r`` in mm, result in mm^-2."""
        return dipole_rd(
            r, self.sigma_a, self.sigma_s_prime, self.eta,
            distance_scale=distance_scale, irradiance_scale=irradiance_scale,
        )

    def total_diffuse_reflectance(self) -> Tensor:
        """Closed-form albedo :math:`R_{total}` per channel."""
        return total_diffuse_reflectance(self.sigma_a, self.sigma_s_prime, self.eta)

    def r_max(self, eps: float = 0.01) -> Tensor:
        """Shah's splat radius per channel (mm), see :func:`torchsss.physics.r_max` (no gradient)."""
        return _r_max(self.sigma_a.detach(), self.sigma_s_prime.detach(), self.eta.detach(), eps)

    def table(
        self, size: int = 1024, eps: float = 0.01, warp: str = "sqrt", shared_range: bool = True
    ) -> ProfileTable:
        """A lookup table of this profile over :math:`[0, r_{max}(\\epsilon)]` (values keep gradients).

        See :func:`torchsss.physics.build_profile_table`; a shared range (default) is the fast layout.
        """
        rm = self.r_max(eps).to(self.raw_sigma_a.dtype).reshape(-1)
        return build_profile_table(self, rm, size, warp, shared_range)

    def extra_repr(self) -> str:
        """The coefficients in physical units, for ``repr``."""
        if is_tracing():
            return ""
        f = lambda t: [round(v, 6) for v in t.detach().reshape(-1).tolist()]  # noqa: E731
        return f"sigma_a={f(self.sigma_a)}, sigma_s_prime={f(self.sigma_s_prime)}, eta={f(self.eta)} (mm^-1)"


class BurleyMaterial(nn.Module):
    """Burley's normalized diffusion profile with learnable albedo :math:`A \\in (0, 1)` and shape :math:`s` (mm^-1).

    Same interface as :class:`DipoleMaterial`: ``forward(r, distance_scale=None, irradiance_scale=None)``.

    Args:
        albedo: :math:`(C,)` surface albedo in (0, 1).
        s: :math:`(C,)` shape parameter in mm^-1 (> 0).

    Examples:
        >>> m = BurleyMaterial.from_preset("marble")
        >>> m(torch.tensor([[1.0]])).shape
        torch.Size([1, 3])
    """

    def __init__(
        self, albedo: Coeff, s: Coeff, *, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> None:
        super().__init__()
        a = _coeff(albedo, "albedo", dtype, device)
        sv = _coeff(s, "s", dtype or a.dtype, a.device)
        if sv.shape != a.shape:
            raise ValueError(f"s: expected the shape of albedo {tuple(a.shape)}, got {tuple(sv.shape)}")
        if bool(((a <= 0) | (a >= 1) | torch.isnan(a)).any()):
            raise ValueError(f"albedo: expected values in (0, 1), got {a.tolist()}")
        check_positive(sv, "s")
        a64 = a.to(torch.float64)
        self.raw_albedo = nn.Parameter(torch.log(a64 / (1.0 - a64)).to(a.dtype))
        self.raw_s = nn.Parameter(_inverse_softplus(sv))

    @classmethod
    def from_dipole(cls, sigma_a: Coeff, sigma_s_prime: Coeff, eta: Coeff = 1.3, **kwargs) -> BurleyMaterial:
        """Match a dipole material (same total reflectance; see :func:`burley_params_from_dipole`)."""
        sa = as_float_tensor(sigma_a, "sigma_a", like=_like(kwargs.get("dtype")))
        a, s = burley_params_from_dipole(sa, sigma_s_prime, eta)
        eps = 1e-7
        return cls(a.clamp(eps, 1 - eps), s, **kwargs)

    @classmethod
    def from_preset(cls, name: str, **kwargs) -> BurleyMaterial:
        """Match one of the Jensen 2001 presets (see :meth:`from_dipole`)."""
        p = preset(name)
        return cls.from_dipole(list(p.sigma_a), list(p.sigma_s_prime), p.eta, **kwargs)

    @property
    def albedo(self) -> Tensor:
        """Surface albedo :math:`A`, :math:`(C,)`."""
        return torch.sigmoid(self.raw_albedo)

    @property
    def s(self) -> Tensor:
        """Shape parameter (mm^-1), :math:`(C,)`."""
        return _softplus(self.raw_s)

    def forward(
        self, r: Tensor, distance_scale: Tensor | None = None, irradiance_scale: Tensor | None = None
    ) -> Tensor:
        """Evaluate the profile (mm^-2) at distances ``r`` (mm), see :func:`torchsss.physics.burley_rd`."""
        return burley_rd(r, self.albedo, self.s, distance_scale=distance_scale, irradiance_scale=irradiance_scale)

    def total_diffuse_reflectance(self) -> Tensor:
        """The integral of the profile over the plane, which is the albedo by construction."""
        return self.albedo


class TabulatedMaterial(nn.Module):
    """A dipole material evaluated through a lookup table: the opt-in speed path of DESIGN.md §3.

    Each call samples the wrapped material at ``size`` nodes over :math:`[0, r_{max}(\\epsilon)]` (the table
    keeps the autograd graph, so the wrapped material's parameters still receive gradients) and interpolates
    linearly (:func:`torchsss.physics.lookup_profile_table`); beyond :math:`r_{max}` the profile is 0, which
    drops a fraction ``eps`` of the energy. The rendering modules cache what they evaluate while the material is
    unchanged, so the table is rebuilt only after a material edit, where it replaces one dipole evaluation per
    kernel tap and throughput entry by a gather and a lerp.

    ``sigma_a``, ``sigma_s_prime`` and ``eta`` are those of the wrapped material, so closed-form terms (the
    disk self term of the Lensch modules) stay exact. Gradients hold the table's nodes fixed (its range is a
    discrete budget): they are those of the interpolated profile and converge to the dipole's as ``size`` grows
    (relative error 1.4e-3 at 64 nodes, 3.7e-6 at 1024, 5e-8 at 8192; tested).

    Args:
        material: the :class:`DipoleMaterial` to tabulate (a submodule: its parameters are this module's).
        size: nodes per channel (>= 2).
        eps: tail fraction beyond the table's range, see :func:`torchsss.physics.r_max`.
        warp: node spacing, ``"sqrt"`` (default, dense near r = 0) or ``"linear"``.

    Examples:
        >>> m = TabulatedMaterial(DipoleMaterial.from_preset("skin1"), size=2048)
        >>> r = torch.tensor([[0.5], [2.0]])
        >>> bool(((m(r) - m.material(r)).abs() / m.material(r)).max() < 1e-3)
        True
    """

    def __init__(self, material: DipoleMaterial, size: int = 1024, eps: float = 1e-4, warp: str = "sqrt") -> None:
        super().__init__()
        if not isinstance(material, DipoleMaterial):
            raise TypeError(f"material: expected a DipoleMaterial, got {type(material).__name__}")
        if isinstance(size, bool) or not isinstance(size, int) or size < 2:
            raise ValueError(f"size: expected an int >= 2, got {size!r}")
        self.material = material
        self.size = size
        self.eps = float(eps)
        self.warp = warp
        self.table()  # validates eps and warp now rather than at the first call

    @property
    def sigma_a(self) -> Tensor:
        """Absorption coefficient of the wrapped material (mm^-1)."""
        return self.material.sigma_a

    @property
    def sigma_s_prime(self) -> Tensor:
        """Reduced scattering coefficient of the wrapped material (mm^-1)."""
        return self.material.sigma_s_prime

    @property
    def eta(self) -> Tensor:
        """Relative index of refraction of the wrapped material."""
        return self.material.eta

    def table(self) -> ProfileTable:
        """The current table (per-channel ranges; values keep gradients)."""
        return self.material.table(size=self.size, eps=self.eps, warp=self.warp, shared_range=False)

    def forward(
        self, r: Tensor, distance_scale: Tensor | None = None, irradiance_scale: Tensor | None = None
    ) -> Tensor:
        """:math:`M_i R_d(r M_d)` from the table; ``r`` :math:`(..., 1)` or :math:`(..., C)` mm -> :math:`(..., C)`."""
        if distance_scale is not None:
            r = r * distance_scale
        out = lookup_profile_table(r, self.table())
        if irradiance_scale is not None:
            out = out * irradiance_scale
        return out

    def total_diffuse_reflectance(self) -> Tensor:
        """Closed-form albedo of the wrapped material."""
        return self.material.total_diffuse_reflectance()
