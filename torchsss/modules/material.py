"""Learnable materials: the dipole (Jensen 2001), Burley's normalized diffusion and the tabulated dipole.

**The profile contract.** Every method of the library renders any ``nn.Module`` that provides

- ``forward(r, distance_scale=None, irradiance_scale=None)``: :math:`M_i R_d(r M_d)` in mm^-2 at distances ``r``
  :math:`(..., 1)` or :math:`(..., C)` in mm, returning :math:`(..., C)`;
- ``eta``: the relative index of refraction, a tensor :math:`()` (or :math:`(C,)`). This is the one home of eta:
  the renderers read it every frame for the Fresnel terms of the irradiance and of the exit radiance, so an edit
  (or a gradient step) changes the whole image consistently;
- ``channels``: the number of colour channels C;
- ``r_max(eps)``: :math:`(C,)` radius in mm beyond which the profile holds a fraction ``eps`` of its energy (no
  gradient; Shah eq. 6.16);
- ``cumulative(radius)``: :math:`\\int_0^R R_d(r) 2\\pi r\\,dr`, :math:`(..., C)` for radii :math:`(..., 1)`
  (the self term of an atlas texel or a vertex);
- ``spacing(eps)``: :math:`(C,)` largest spacing (mm) of a lattice of sources whose sum integrates the profile to
  within ``eps`` (the sample spacing of the reference and the splat grid; no gradient);
- ``total_diffuse_reflectance()``: :math:`(C,)` albedo.

:class:`DipoleMaterial`, :class:`BurleyMaterial` and :class:`TabulatedMaterial` follow it;
:func:`material_module` is the one way to make such a module from a :class:`~torchsss.physics.Material` record,
and :func:`check_profile` tells whether a module follows the contract. Parameters are stored unconstrained and
mapped through ``softplus`` (or a sigmoid for Burley's albedo) so that optimisation can never leave the valid range.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchsss._checks import as_float_tensor, check_nonnegative, check_positive, is_tracing
from torchsss.physics.budget import r_max as _r_max
from torchsss.physics.budget import splat_spacing
from torchsss.physics.burley import burley_cumulative, burley_params_from_dipole, burley_r_max, burley_rd
from torchsss.physics.dipole import dipole_cumulative, dipole_rd, total_diffuse_reflectance
from torchsss.physics.lut import (
    BULK_MIN_VALUES,
    BULK_TOLERANCE,
    ProfileTable,
    build_profile_table,
    bulk_profile,
    lookup_profile_table,
)
from torchsss.physics.materials import PROFILES, Material, preset

__all__ = ["BULK_MIN_VALUES", "BULK_TOLERANCE", "POSITIVE_FLOOR", "BurleyMaterial", "DipoleMaterial",
           "TabulatedMaterial", "bulk_profile", "check_profile", "material_module"]

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
        return cls.from_material(preset(name), **kwargs)

    @classmethod
    def from_material(cls, material: Material, **kwargs) -> DipoleMaterial:
        """From a :class:`~torchsss.physics.Material` record (its coefficients and eta; ``dtype``, ``device``)."""
        return cls(list(material.sigma_a), list(material.sigma_s_prime), material.eta, **kwargs)

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

    def dipole_coefficients(self) -> tuple[Tensor, Tensor, Tensor]:
        """``(sigma_a, sigma_s_prime, eta)`` in mm^-1, mm^-1 and 1: what a fused integrator needs of the profile.

        A profile that offers this method is the plain dipole of :func:`torchsss.dipole_rd` with these coefficients,
        so :func:`~torchsss.ops.reference.reference_radiosity` may evaluate it in its fused kernel
        (:mod:`torchsss.ops.fused`) instead of calling :meth:`forward` on chunks of distances.
        """
        return self.sigma_a, self.sigma_s_prime, self.eta

    def total_diffuse_reflectance(self) -> Tensor:
        """Closed-form albedo :math:`R_{total}` per channel."""
        return total_diffuse_reflectance(self.sigma_a, self.sigma_s_prime, self.eta)

    def r_max(self, eps: float = 0.01) -> Tensor:
        """Shah's splat radius per channel (mm), see :func:`torchsss.physics.r_max` (no gradient)."""
        return _r_max(self.sigma_a.detach(), self.sigma_s_prime.detach(), self.eta.detach(), eps)

    def cumulative(self, radius: Tensor) -> Tensor:
        """:math:`\\int_0^R R_d\\,2\\pi r\\,dr` for radii :math:`(..., 1)` mm -> :math:`(..., C)` (closed form)."""
        return dipole_cumulative(radius, self.sigma_a, self.sigma_s_prime, self.eta)

    def spacing(self, eps: float = 0.01) -> Tensor:
        """Largest lattice spacing per channel (mm) at ``eps``, :func:`torchsss.physics.splat_spacing` (no grad)."""
        return splat_spacing(self.sigma_a.detach(), self.sigma_s_prime.detach(), self.eta.detach(), eps)

    def table(
        self, size: int = 1024, eps: float = 0.01, warp: str = "sqrt", shared_range: bool = True
    ) -> ProfileTable:
        """A lookup table of this profile over :math:`[0, r_{max}(\\epsilon)]` (values keep gradients).

        See :func:`torchsss.physics.build_profile_table`; a shared range (default) is the fast layout. A
        float16/bfloat16 material is tabulated in float32 (range and values), so that neither a range beyond
        65504 mm nor a profile value beyond the reduced format's range overflows in the table.
        """
        dtype = self.raw_sigma_a.dtype
        work = torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
        coeffs = (t.detach().to(work) for t in (self.sigma_a, self.sigma_s_prime, self.eta))
        rm = _r_max(*coeffs, eps).reshape(-1)  # Shah's r_max, as self.r_max(eps), in the table's dtype
        return build_profile_table(self, rm, size, warp, shared_range)

    def extra_repr(self) -> str:
        """The coefficients in physical units, for ``repr``."""
        if is_tracing():
            return ""
        f = lambda t: [round(v, 6) for v in t.detach().reshape(-1).tolist()]  # noqa: E731
        return f"sigma_a={f(self.sigma_a)}, sigma_s_prime={f(self.sigma_s_prime)}, eta={f(self.eta)} (mm^-1)"


class BurleyMaterial(nn.Module):
    """Burley's normalized diffusion profile with learnable albedo :math:`A \\in (0, 1)`, shape :math:`s` (mm^-1), eta.

    Same contract as :class:`DipoleMaterial` (module docstring): ``forward(r, distance_scale=None,
    irradiance_scale=None)``, ``eta``, ``channels``, ``r_max(eps)``, ``cumulative(radius)``.

    **The core.** The profile's :math:`1/r` peak is integrable but cannot be point-sampled: every method sums the
    profile at discrete source-receiver distances, and a source that lands close to a receiver adds an unbounded
    term (relative errors of 30-130% were measured on a 24 x 24 sphere with the exact peak). Within
    :math:`\\rho = ` ``core`` :math:`/ s` the module therefore evaluates the profile's mean over the disk of
    radius :math:`\\rho` (the closed-form :meth:`cumulative` divided by :math:`\\pi \\rho^2`), which keeps the
    total reflectance exactly and bounds the peak; ``core=0`` gives the exact profile (floored at
    :data:`~torchsss.physics.burley.BURLEY_R_FLOOR`). :meth:`cumulative` is that of the evaluated profile.

    Args:
        albedo: :math:`(C,)` surface albedo in (0, 1).
        s: :math:`(C,)` shape parameter in mm^-1 (> 0).
        eta: relative index of refraction of the boundary (> 0), used by the renderers' Fresnel terms.
        core: radius of the averaged core in units of :math:`1/s` (>= 0; default 1).
        dtype, device: of the parameters.

    Examples:
        >>> m = BurleyMaterial.from_preset("marble")
        >>> m(torch.tensor([[1.0]])).shape, round(m.eta.item(), 4)
        (torch.Size([1, 3]), 1.3)
    """

    def __init__(
        self, albedo: Coeff, s: Coeff, eta: Coeff = 1.3, *, core: float = 1.0, dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        if isinstance(core, bool) or not isinstance(core, (int, float)) or not (math.isfinite(core) and core >= 0):
            raise ValueError(f"core: expected a finite number >= 0 (units of 1/s), got {core!r}")
        self.core = float(core)
        a = _coeff(albedo, "albedo", dtype, device)
        sv = _coeff(s, "s", dtype or a.dtype, a.device)
        et = _coeff(eta, "eta", dtype or a.dtype, a.device)
        if sv.shape != a.shape:
            raise ValueError(f"s: expected the shape of albedo {tuple(a.shape)}, got {tuple(sv.shape)}")
        if bool(((a <= 0) | (a >= 1) | torch.isnan(a)).any()):
            raise ValueError(f"albedo: expected values in (0, 1), got {a.tolist()}")
        if et.dim() > 1 or (et.dim() == 1 and et.shape[0] not in (1, max(a.numel(), 1))):
            raise ValueError(f"eta: expected a scalar or shape ({a.numel()},), got {tuple(et.shape)}")
        check_positive(sv, "s")
        check_positive(et, "eta")
        a64 = a.to(torch.float64)
        self.raw_albedo = nn.Parameter(torch.log(a64 / (1.0 - a64)).to(a.dtype))
        self.raw_s = nn.Parameter(_inverse_softplus(sv))
        self.raw_eta = nn.Parameter(_inverse_softplus(et))

    @classmethod
    def from_dipole(cls, sigma_a: Coeff, sigma_s_prime: Coeff, eta: Coeff = 1.3, **kwargs) -> BurleyMaterial:
        """Match a dipole material (same total reflectance and eta; see :func:`burley_params_from_dipole`).

        The parameters are computed in float64 and the albedo clamped to the open interval (0, 1) *in the target
        dtype* (a fully reflecting material such as spectralon gets the largest value below 1 that the dtype
        holds, e.g. 1 - 2^-11 in float16), then cast.
        """
        dtype = kwargs.get("dtype")
        sa = as_float_tensor(sigma_a, "sigma_a", like=_like(dtype))
        target = dtype or sa.dtype
        work = torch.float32 if sa.device.type == "mps" else torch.float64  # MPS has no float64
        sa_w = sa.detach().to(work)
        ss_w = as_float_tensor(sigma_s_prime, "sigma_s_prime", like=sa_w).detach().to(work)
        et_w = as_float_tensor(eta, "eta", like=sa_w).detach().to(work)
        a, s = burley_params_from_dipole(sa_w, ss_w, et_w)
        info = torch.finfo(target)
        lo = max(1e-7, info.tiny)  # smallest normal number of the target dtype at least
        hi = min(1.0 - 1e-7, 1.0 - info.eps / 2.0)  # 1 - eps/2: the largest number below 1 in a binary format
        return cls(a.clamp(lo, hi).to(target), s.to(target), eta, **kwargs)

    @classmethod
    def from_preset(cls, name: str, **kwargs) -> BurleyMaterial:
        """Match one of the Jensen 2001 presets (see :meth:`from_dipole`)."""
        return cls.from_material(preset(name), **kwargs)

    @classmethod
    def from_material(cls, material: Material, **kwargs) -> BurleyMaterial:
        """Match a :class:`~torchsss.physics.Material` record's dipole (see :meth:`from_dipole`)."""
        return cls.from_dipole(list(material.sigma_a), list(material.sigma_s_prime), material.eta, **kwargs)

    @property
    def albedo(self) -> Tensor:
        """Surface albedo :math:`A`, :math:`(C,)`."""
        return torch.sigmoid(self.raw_albedo)

    @property
    def s(self) -> Tensor:
        """Shape parameter (mm^-1), :math:`(C,)`."""
        return _softplus(self.raw_s)

    @property
    def eta(self) -> Tensor:
        """Relative index of refraction."""
        return _softplus(self.raw_eta)

    @property
    def channels(self) -> int:
        """Number of colour channels C."""
        return max(self.raw_albedo.numel(), 1)

    def forward(
        self, r: Tensor, distance_scale: Tensor | None = None, irradiance_scale: Tensor | None = None
    ) -> Tensor:
        """Evaluate the profile (mm^-2) at distances ``r`` (mm), :func:`torchsss.physics.burley_rd` outside the core."""
        a, s = self.albedo, self.s
        if distance_scale is not None:
            r = r * distance_scale
        if self.core > 0:
            rho = self.core / s
            inside = r < rho
            mean = burley_cumulative(rho, a, s) / (math.pi * rho * rho)
            out = torch.where(inside, mean, burley_rd(torch.maximum(r, rho), a, s))
        else:
            out = burley_rd(r, a, s)
        return out if irradiance_scale is None else out * irradiance_scale

    def total_diffuse_reflectance(self) -> Tensor:
        """The integral of the profile over the plane, which is the albedo by construction."""
        return self.albedo

    def r_max(self, eps: float = 0.01) -> Tensor:
        """Radius per channel (mm) holding all but ``eps`` of the energy, :func:`~torchsss.physics.burley_r_max`."""
        return burley_r_max(self.s.detach(), eps)

    def cumulative(self, radius: Tensor) -> Tensor:
        """:math:`\\int_0^R R\\,2\\pi r\\,dr` of the evaluated profile, :math:`(..., 1)` mm -> :math:`(..., C)`."""
        a, s = self.albedo, self.s
        exact = burley_cumulative(radius, a, s)
        if self.core == 0:
            return exact
        rho = self.core / s
        inside = radius < rho
        r_in = torch.where(inside, radius, torch.zeros_like(radius))  # masked first: radius = inf has no NaN gradient
        core = burley_cumulative(rho, a, s) * (r_in / rho) ** 2  # the disk mean times the area within the core
        return torch.where(inside, core, exact)

    def spacing(self, eps: float = 0.01) -> Tensor:
        """Lattice spacing per channel (mm), no gradient: the dipole-matched rule, at most the core's radius.

        The profile's peak has a spectrum that decays like :math:`1/k` (like :math:`1/k^2` with the core), so the
        Poisson criterion of the dipole (:func:`~torchsss.physics.splat_spacing`) has no closed form here. The
        spacing is the dipole rule through Christensen & Burley's fit :math:`s = \\sigma_t' f(A)`,
        :math:`f(A) = 1.85 - A + 7|A - 0.8|^3` (:math:`h = 2\\pi f(A) / (s \\ln(4/\\epsilon))`, the spacing of
        the dipole this profile matches), capped at the core's radius ``core / s`` so that point sums resolve the
        core (measured on a 16 mm sphere: splat error against the reference 17% with the dipole rule alone at
        ``core=1``, see the class docstring).
        """
        if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not 0.0 < float(eps) < 1.0:
            raise ValueError(f"eps: expected a number in (0, 1), got {eps!r}")
        a, s = self.albedo.detach(), self.s.detach()
        fit = 1.85 - a + 7.0 * (a - 0.8).abs() ** 3
        h = 2.0 * math.pi * fit / (s * math.log(4.0 / float(eps)))
        return torch.minimum(h, self.core / s) if self.core > 0 else h

    def extra_repr(self) -> str:
        """The parameters, for ``repr``."""
        if is_tracing():
            return ""
        f = lambda t: [round(v, 6) for v in t.detach().reshape(-1).tolist()]  # noqa: E731
        return f"albedo={f(self.albedo)}, s={f(self.s)} (mm^-1), eta={f(self.eta)}"


class TabulatedMaterial(nn.Module):
    """A profile evaluated through a lookup table: the opt-in speed path of DESIGN.md §3.

    Each call samples the wrapped profile at ``size`` nodes over :math:`[0, r_{max}(\\epsilon)]` (the table
    keeps the autograd graph, so the wrapped material's parameters still receive gradients) and interpolates
    linearly (:func:`torchsss.physics.lookup_profile_table`); beyond :math:`r_{max}` the profile is 0, which
    drops a fraction ``eps`` of the energy. The rendering modules cache what they evaluate while the material is
    unchanged, so the table is rebuilt only after a material edit, where it replaces one profile evaluation per
    kernel tap and throughput entry by a gather and a lerp.

    ``eta``, ``r_max``, ``cumulative`` and ``total_diffuse_reflectance`` (and ``sigma_a``, ``sigma_s_prime`` of a
    dipole) are those of the wrapped material, so closed-form terms (the disk self term of the Lensch modules) stay
    exact. Gradients hold the table's nodes fixed (its range is a discrete budget): they are those of the
    interpolated profile and converge to the wrapped profile's as ``size`` grows (relative error 1.4e-3 at 64
    nodes, 3.7e-6 at 1024, 5e-8 at 8192 for the dipole; tested).

    Args:
        material: the profile module to tabulate (any module of the contract in the module docstring, e.g. a
            :class:`DipoleMaterial` or :class:`BurleyMaterial`; a submodule: its parameters are this module's).
        size: nodes per channel (>= 2).
        eps: tail fraction beyond the table's range, see :func:`torchsss.physics.r_max`.
        warp: node spacing, ``"sqrt"`` (default, dense near r = 0) or ``"linear"``.

    Examples:
        >>> m = TabulatedMaterial(DipoleMaterial.from_preset("skin1"), size=2048)
        >>> r = torch.tensor([[0.5], [2.0]])
        >>> bool(((m(r) - m.material(r)).abs() / m.material(r)).max() < 1e-3)
        True
    """

    def __init__(self, material: nn.Module, size: int = 1024, eps: float = 1e-4, warp: str = "sqrt") -> None:
        super().__init__()
        check_profile(material, "material")
        if isinstance(material, TabulatedMaterial):
            raise TypeError("material: expected a profile to tabulate, got a TabulatedMaterial (already tabulated)")
        if isinstance(size, bool) or not isinstance(size, int) or size < 2:
            raise ValueError(f"size: expected an int >= 2, got {size!r}")
        self.material = material
        self.size = size
        self.eps = float(eps)
        self.warp = warp
        self.table()  # validates eps and warp now rather than at the first call

    def __getattr__(self, name: str):
        # sigma_a / sigma_s_prime (dipole) or albedo / s (Burley) of the wrapped material
        if name in ("sigma_a", "sigma_s_prime", "albedo", "s"):
            return getattr(self._modules["material"], name)
        return super().__getattr__(name)

    @property
    def eta(self) -> Tensor:
        """Relative index of refraction of the wrapped material."""
        return self.material.eta

    @property
    def channels(self) -> int:
        """Number of colour channels C."""
        return self.material.channels

    def r_max(self, eps: float = 0.01) -> Tensor:
        """The wrapped material's radius (mm) at ``eps`` (no gradient)."""
        return self.material.r_max(eps)

    def cumulative(self, radius: Tensor) -> Tensor:
        """The wrapped material's closed-form :math:`\\int_0^R R_d\\,2\\pi r\\,dr`."""
        return self.material.cumulative(radius)

    def spacing(self, eps: float = 0.01) -> Tensor:
        """The wrapped material's lattice spacing (mm) at ``eps``."""
        return self.material.spacing(eps)

    def _work_dtype(self) -> torch.dtype:
        """The dtype of the table: the wrapped material's, float32 for float16/bfloat16 materials."""
        dtype = self.material.eta.dtype
        return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype

    def _table_range(self, work: torch.dtype) -> Tensor:
        """The table's :math:`(C,)` range :math:`r_{max}(\\epsilon)` in the dtype ``work``.

        For a reduced-precision dipole or Burley material it is computed from the parameters in float32 (a range
        beyond 65504 mm overflows float16).
        """
        material = self.material
        if material.eta.dtype != work and type(material).r_max in (DipoleMaterial.r_max, BurleyMaterial.r_max):
            if isinstance(material, DipoleMaterial):
                rm = _r_max(*(t.detach().to(work) for t in (material.sigma_a, material.sigma_s_prime, material.eta)),
                            self.eps)
            else:
                rm = burley_r_max(material.s.detach().to(work), self.eps)
        else:
            rm = material.r_max(self.eps)
        rm = rm.detach().to(work).reshape(-1)
        if not is_tracing() and not bool((torch.isfinite(rm) & (rm > 0)).all()):
            raise ValueError(f"eps: expected a tail fraction whose radius r_max(eps) is finite and > 0 for the "
                             f"wrapped {type(material).__name__} (the table's range), got eps={self.eps!r} with "
                             f"r_max {rm.tolist()} mm")
        return rm

    def table(self) -> ProfileTable:
        """The current table (per-channel ranges; values keep gradients).

        A float16/bfloat16 material is tabulated in float32 (its profile evaluated at float32 distances), so that
        values beyond the reduced format's range stay finite in the table and interpolation never meets inf.
        """
        rm = self._table_range(self._work_dtype())
        return build_profile_table(self.material, rm, self.size, self.warp, shared_range=False)

    def forward(
        self, r: Tensor, distance_scale: Tensor | None = None, irradiance_scale: Tensor | None = None
    ) -> Tensor:
        """:math:`M_i R_d(r M_d)` from the table; ``r`` :math:`(..., 1)` or :math:`(..., C)` mm -> :math:`(..., C)`.

        For a float16/bfloat16 material the result has the promoted dtype of ``r`` and the parameters, as the
        wrapped material's own forward: values beyond a reduced format's range overflow to inf in the final cast.
        """
        if distance_scale is not None:
            r = r * distance_scale
        table = self.table()
        out = lookup_profile_table(r, table)
        dtype = self.material.eta.dtype
        if table.values.dtype != dtype and isinstance(r, Tensor) and r.is_floating_point():
            out = out.to(torch.promote_types(r.dtype, dtype))
        if irradiance_scale is not None:
            out = out * irradiance_scale
        return out

    def total_diffuse_reflectance(self) -> Tensor:
        """Closed-form albedo of the wrapped material."""
        return self.material.total_diffuse_reflectance()


_CONTRACT = ("eta", "channels", "r_max", "cumulative", "spacing", "total_diffuse_reflectance")


def check_profile(material: object, name: str = "material") -> nn.Module:
    """Check that ``material`` is an ``nn.Module`` following the profile contract (module docstring); return it.

    Raises:
        TypeError: not an nn.Module, or a missing member (the message names it).

    Examples:
        >>> check_profile(DipoleMaterial.from_preset("marble")).channels
        3
    """
    if not isinstance(material, nn.Module):
        raise TypeError(f"{name}: expected a profile module (DipoleMaterial, BurleyMaterial, TabulatedMaterial or "
                        f"one with {', '.join(_CONTRACT)}), got {type(material).__name__}")
    missing = [a for a in _CONTRACT if not hasattr(type(material), a) and not hasattr(material, a)]
    if missing:
        raise TypeError(f"{name}: expected a profile module with {', '.join(_CONTRACT)}, got "
                        f"{type(material).__name__} without {', '.join(missing)}")
    return material


def material_module(
    material: Material | str | nn.Module,
    profile: str | None = None,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    table_size: int = 1024,
) -> nn.Module:
    """The one way from a material record to its nn.Module (the form every method renders and differentiates).

    Args:
        material: a :class:`~torchsss.physics.Material` record, a preset name, or a profile module (returned as
            it is, after :func:`check_profile`, moved to ``dtype``/``device`` when given).
        profile: ``"dipole"``, ``"burley"`` or ``"tabulated"`` (the dipole through a lookup table of
            ``table_size`` nodes); default the record's ``profile``.
        dtype: of the parameters (default float32).
        device: of the parameters.
        table_size: nodes of the ``"tabulated"`` profile's table.

    Returns:
        A :class:`DipoleMaterial`, :class:`BurleyMaterial` or :class:`TabulatedMaterial`.

    Raises:
        TypeError: ``material`` of another kind.
        ValueError: an unknown ``profile``.

    Examples:
        >>> type(material_module("skin1", "burley")).__name__
        'BurleyMaterial'
        >>> type(material_module(Material.from_json({"preset": "marble", "profile": "tabulated"}))).__name__
        'TabulatedMaterial'
    """
    if isinstance(material, nn.Module):
        check_profile(material)
        if profile is not None:
            raise ValueError(f"profile: expected None for a profile module (it is one already), got {profile!r}")
        return material if dtype is None and device is None else material.to(dtype=dtype, device=device)
    if isinstance(material, str):
        material = preset(material)
    if not isinstance(material, Material):
        raise TypeError(f"material: expected a Material record, a preset name or a profile module, got "
                        f"{type(material).__name__}")
    kind = material.profile if profile is None else profile
    if kind not in PROFILES:
        raise ValueError(f"profile: expected one of {list(PROFILES)}, got {kind!r}")
    dtype = dtype or torch.float32
    if kind == "burley":
        return BurleyMaterial.from_material(material, dtype=dtype, device=device)
    dipole = DipoleMaterial.from_material(material, dtype=dtype, device=device)
    return TabulatedMaterial(dipole, size=table_size) if kind == "tabulated" else dipole
