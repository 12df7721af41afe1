"""The Jensen et al. 2001 dipole diffusion profile :math:`R_d(r)` and its closed-form integrals.

Units: distances in millimetres, coefficients in mm^-1, R_d in mm^-2. Every function broadcasts its arguments
over a trailing channel dimension: ``r`` is ``(..., C)`` or ``(..., 1)`` and the coefficients ``(C,)`` (or any
shape broadcastable with ``r``).

The profile is written as

.. math::
    R_d(r) = \\frac{\\alpha'}{4\\pi}\\left[z_r\\,\\frac{h(\\sigma_{tr} d_r)}{d_r^3}
             + z_v\\,\\frac{h(\\sigma_{tr} d_v)}{d_v^3}\\right], \\qquad h(x) = (1 + x) e^{-x},

which is Lensch Fig. 2 / Chang Table 1; Shah eq. 6.5 writes :math:`z (\\sigma_{tr} + 1/d) e^{-\\sigma_{tr} d}/d^2`,
algebraically the same. Because :math:`dh/dx = -x e^{-x}` vanishes at 0, :math:`h` is smooth in
:math:`u = x^2 = 3\\sigma_a\\sigma_t' d^2`, so the gradient with respect to :math:`\\sigma_a` is finite at
:math:`\\sigma_a = 0` even though :math:`d\\sigma_{tr}/d\\sigma_a` is not. The evaluation uses a series in
:math:`u` below a tiny threshold to keep autograd away from the :math:`0 \\cdot \\infty` of the naive chain rule.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsss._checks import (
    as_float_tensor,
    check_broadcastable,
    check_nonnegative,
    check_positive,
    compute_dtype,
    is_tracing,
)
from torchsss.physics.fresnel import dipole_boundary_a

__all__ = [
    "DipoleTerms",
    "dipole_cumulative",
    "dipole_rd",
    "dipole_rd_shah",
    "dipole_spectrum",
    "dipole_terms",
    "total_diffuse_reflectance",
]

# Below this value of u = sigma_tr^2 (in mm^-2) the series branch is used. sqrt(1e-20) = 1e-10 mm^-1: an
# extinction length of 1e10 mm, far outside anything rendered, and the series is exact there to rounding.
_SERIES_BELOW = 1e-20


class DipoleTerms:
    """Derived dipole quantities for one material, all broadcast to a common shape.

    Attributes:
        alpha_prime: reduced albedo :math:`\\alpha' = \\sigma_s'/\\sigma_t'`.
        sigma_t_prime: reduced extinction :math:`\\sigma_t' = \\sigma_a + \\sigma_s'` (mm^-1).
        sigma_tr_sq: :math:`\\sigma_{tr}^2 = 3 \\sigma_a \\sigma_t'` (mm^-2).
        z_r: depth of the real source, :math:`1/\\sigma_t'` (mm).
        z_v: height of the virtual source, :math:`z_r (1 + 4A/3)` (mm).
        a: boundary term :math:`A`.
    """

    __slots__ = ("a", "alpha_prime", "sigma_t_prime", "sigma_tr_sq", "z_r", "z_v")

    def __init__(self, sigma_a: Tensor, sigma_s_prime: Tensor, eta: Tensor) -> None:
        self.sigma_t_prime = sigma_a + sigma_s_prime
        self.alpha_prime = sigma_s_prime / self.sigma_t_prime
        self.sigma_tr_sq = 3.0 * sigma_a * self.sigma_t_prime
        self.a = dipole_boundary_a(eta)
        self.z_r = 1.0 / self.sigma_t_prime
        self.z_v = self.z_r * (1.0 + 4.0 / 3.0 * self.a)

    @property
    def sigma_tr(self) -> Tensor:
        """Effective extinction :math:`\\sigma_{tr} = \\sqrt{3\\sigma_a\\sigma_t'}` in mm^-1.

        Not safe to differentiate at :math:`\\sigma_a = 0`; :func:`dipole_rd` does not use it.
        """
        return torch.sqrt(self.sigma_tr_sq)


def _prepare_material(
    sigma_a: Tensor | float, sigma_s_prime: Tensor | float, eta: Tensor | float, like: Tensor | None
) -> tuple[Tensor, Tensor, Tensor]:
    if like is None:  # Python numbers take the dtype of whichever coefficient is a tensor
        like = next((t for t in (sigma_a, sigma_s_prime, eta) if isinstance(t, Tensor) and t.is_floating_point()),
                    None)
    sa = as_float_tensor(sigma_a, "sigma_a", like=like)
    ss = as_float_tensor(sigma_s_prime, "sigma_s_prime", like=like)
    et = as_float_tensor(eta, "eta", like=like)
    check_nonnegative(sa, "sigma_a")
    check_nonnegative(ss, "sigma_s_prime")
    check_positive(et, "eta")
    if not is_tracing():
        st = sa.detach() + ss.detach()
        if bool((st <= 0).any()):
            raise ValueError("sigma_a + sigma_s_prime: expected > 0 (a medium that neither absorbs nor scatters "
                             "has no dipole profile), got 0")
    return sa, ss, et


def dipole_terms(sigma_a: Tensor | float, sigma_s_prime: Tensor | float, eta: Tensor | float) -> DipoleTerms:
    """Validate a material and return its derived dipole quantities (see :class:`DipoleTerms`).

    Examples:
        >>> t = dipole_terms(0.0, 1.0, 1.0)
        >>> round(t.z_r.item(), 6), round(t.alpha_prime.item(), 6)
        (1.0, 1.0)
    """
    sa, ss, et = _prepare_material(sigma_a, sigma_s_prime, eta, None)
    check_broadcastable(sigma_a=sa, sigma_s_prime=ss, eta=et)
    return DipoleTerms(sa, ss, et)


def _h_over_d3(u_scale: Tensor, d: Tensor) -> Tensor:
    """:math:`h(\\sigma_{tr} d)/d^3` with :math:`h(x) = (1+x)e^{-x}`, safe to differentiate at :math:`\\sigma_{tr}=0`.

    ``u_scale`` is :math:`\\sigma_{tr}^2`.
    """
    small = u_scale < _SERIES_BELOW
    if not is_tracing() and not bool(small.any()):  # eager fast path: every channel absorbs
        sigma_tr = torch.sqrt(u_scale)
        return (sigma_tr + 1.0 / d) * torch.exp(-sigma_tr * d) / (d * d)
    # Exact branch, evaluated at a safe value where the series branch is selected (double-where trick).
    s_safe = torch.where(small, torch.ones_like(u_scale), u_scale)
    sigma_tr = torch.sqrt(s_safe)
    exact = (sigma_tr + 1.0 / d) * torch.exp(-sigma_tr * d) / (d * d)
    # Series of h in u = x^2: 1 - u/2 + u^{3/2}/3 - u^2/8; |u| <= 1e-20 * d^2 keeps the next term negligible.
    d_fin = torch.where(torch.isinf(d), torch.zeros_like(d), d)  # r = inf: u = 0, the value is 1/d^3 = 0
    u = torch.where(small, u_scale, torch.zeros_like(u_scale)) * d_fin * d_fin
    series = (1.0 - 0.5 * u + torch.pow(u, 1.5) / 3.0 - 0.125 * u * u) / (d * d * d)
    return torch.where(small, series, exact)


def dipole_rd(
    r: Tensor | float,
    sigma_a: Tensor | float,
    sigma_s_prime: Tensor | float,
    eta: Tensor | float = 1.3,
    *,
    distance_scale: Tensor | float | None = None,
    irradiance_scale: Tensor | float | None = None,
) -> Tensor:
    """Dipole diffuse reflectance profile :math:`R_d(r)` of Jensen et al. 2001 (mm^-2).

    With the heterogeneous modifiers of Shah (2007) eq. 7.4 the result is
    :math:`M_i \\cdot R_d(r \\cdot M_d)`, where :math:`M_d` (``distance_scale``) and :math:`M_i`
    (``irradiance_scale``) belong to the *source* point :math:`x_i`.

    Args:
        r: distances :math:`|x_i - x_o|` in mm, shape :math:`(..., C)` or :math:`(..., 1)`; >= 0.
        sigma_a: absorption coefficient in mm^-1, e.g. :math:`(C,)`; >= 0.
        sigma_s_prime: reduced scattering coefficient in mm^-1, broadcastable; >= 0, with
            ``sigma_a + sigma_s_prime > 0``.
        eta: relative index of refraction (> 0); :math:`F_{dr}` switches fit at 1.
        distance_scale: optional :math:`M_d` (> 0), broadcastable with ``r``.
        irradiance_scale: optional :math:`M_i` (>= 0), broadcastable with ``r``.

    Returns:
        :math:`R_d` of the broadcast shape; dtype is the promotion of the inputs (float16/bfloat16 inputs are
        computed in float32 and cast back, so values beyond the reduced format's range overflow to inf or
        flush to 0 in the cast).

    Raises:
        TypeError: non-tensor, non-number or non-floating input.
        ValueError: negative/NaN coefficients or distances, ``eta <= 0``, shapes that do not broadcast.

    Examples:
        >>> r = torch.tensor([[0.0], [1.0], [10.0]])            # (3, 1) distances in mm
        >>> m = dict(sigma_a=torch.tensor([0.0021, 0.0041, 0.0071]),
        ...          sigma_s_prime=torch.tensor([2.19, 2.62, 3.00]), eta=1.3)   # marble, mm^-1
        >>> dipole_rd(r, **m).shape
        torch.Size([3, 3])
    """
    r_t = as_float_tensor(r, "r")
    sa, ss, et = _prepare_material(sigma_a, sigma_s_prime, eta, r_t)
    check_nonnegative(r_t, "r", allow_inf=True)
    extra = {}
    if distance_scale is not None:
        md = as_float_tensor(distance_scale, "distance_scale", like=r_t)
        check_positive(md, "distance_scale")
        extra["distance_scale"] = md
    if irradiance_scale is not None:
        mi = as_float_tensor(irradiance_scale, "irradiance_scale", like=r_t)
        check_nonnegative(mi, "irradiance_scale")
        extra["irradiance_scale"] = mi
    check_broadcastable(r=r_t, sigma_a=sa, sigma_s_prime=ss, eta=et, **extra)
    out_dtype, work = compute_dtype(r_t, sa, ss, et, *extra.values())

    r_w = r_t.to(work)
    if "distance_scale" in extra:
        r_w = r_w * extra["distance_scale"].to(work)
    t = DipoleTerms(sa.to(work), ss.to(work), et.to(work))
    d_r = torch.sqrt(r_w * r_w + t.z_r * t.z_r)
    d_v = torch.sqrt(r_w * r_w + t.z_v * t.z_v)
    rd = t.alpha_prime / (4.0 * math.pi) * (
        t.z_r * _h_over_d3(t.sigma_tr_sq, d_r) + t.z_v * _h_over_d3(t.sigma_tr_sq, d_v)
    )
    if "irradiance_scale" in extra:
        rd = rd * extra["irradiance_scale"].to(work)
    return rd.to(out_dtype)


def dipole_rd_shah(
    r: Tensor | float, sigma_a: Tensor | float, sigma_s_prime: Tensor | float, eta: Tensor | float = 1.3
) -> Tensor:
    """The dipole exactly as printed in Shah (2007) eq. 6.5-6.11 (with F_dr's constant 0.668, not the typo).

    A literal transcription kept as an independent cross-check of :func:`dipole_rd`; it is not safe to
    differentiate at :math:`\\sigma_a = 0`. Shapes as :func:`dipole_rd`.
    """
    r_t = as_float_tensor(r, "r")
    sa, ss, et = _prepare_material(sigma_a, sigma_s_prime, eta, r_t)
    sigma_t = sa + ss
    alpha = ss / sigma_t
    sigma_tr = torch.sqrt(3.0 * sa * sigma_t)
    fdr = -1.440 / et**2 + 0.710 / et + 0.668 + 0.0636 * et
    a = (1.0 + fdr) / (1.0 - fdr)
    z_r = 1.0 / sigma_t
    z_v = z_r * (1.0 + 4.0 * a / 3.0)
    d_r = torch.sqrt(r_t**2 + z_r**2)
    d_v = torch.sqrt(r_t**2 + z_v**2)
    return alpha / (4.0 * math.pi) * (
        z_r * (sigma_tr + 1.0 / d_r) * torch.exp(-sigma_tr * d_r) / d_r**2
        + z_v * (sigma_tr + 1.0 / d_v) * torch.exp(-sigma_tr * d_v) / d_v**2
    )


def total_diffuse_reflectance(
    sigma_a: Tensor | float, sigma_s_prime: Tensor | float, eta: Tensor | float = 1.3
) -> Tensor:
    """Closed-form total diffuse reflectance :math:`R_{total} = \\int_0^\\infty R_d(r)\\, 2\\pi r\\, dr`.

    .. math::
        R_{total} = \\frac{\\alpha'}{2}\\left(1 + e^{-\\frac{4}{3} A \\sqrt{3(1-\\alpha')}}\\right)
                    e^{-\\sqrt{3(1-\\alpha')}}

    Note :math:`\\sqrt{3(1-\\alpha')} = \\sigma_{tr} z_r`. Its derivative with respect to :math:`\\sigma_a` is
    genuinely :math:`-\\infty` at :math:`\\sigma_a = 0` (a square-root cusp); this function does not hide that.

    Args:
        sigma_a: absorption coefficient in mm^-1 (any shape broadcastable with the others).
        sigma_s_prime: reduced scattering coefficient in mm^-1.
        eta: relative index of refraction.

    Returns:
        Albedo in [0, 1], broadcast shape.

    Examples:
        >>> total_diffuse_reflectance(0.0, 1.0, 1.3).item()   # no absorption: all light comes back
        1.0
    """
    sa, ss, et = _prepare_material(sigma_a, sigma_s_prime, eta, None)
    check_broadcastable(sigma_a=sa, sigma_s_prime=ss, eta=et)
    out_dtype, work = compute_dtype(sa, ss, et)
    t = DipoleTerms(sa.to(work), ss.to(work), et.to(work))
    root = torch.sqrt(3.0 * (1.0 - t.alpha_prime).clamp_min(0.0))
    return (0.5 * t.alpha_prime * (1.0 + torch.exp(-4.0 / 3.0 * t.a * root)) * torch.exp(-root)).to(out_dtype)


def dipole_cumulative(
    radius: Tensor | float, sigma_a: Tensor | float, sigma_s_prime: Tensor | float, eta: Tensor | float = 1.3
) -> Tensor:
    """Closed-form :math:`\\int_0^{R} R_d(r)\\, 2\\pi r\\, dr`, the reflectance captured within radius ``R`` (mm).

    Substituting :math:`d = \\sqrt{r^2 + z^2}` turns each source term into an exact derivative:

    .. math::
        \\int_0^R R_d\\,2\\pi r\\,dr = \\frac{\\alpha'}{2}\\sum_{z \\in \\{z_r, z_v\\}}
        \\left(e^{-\\sigma_{tr} z} - \\frac{z}{d(R)} e^{-\\sigma_{tr} d(R)}\\right)

    It equals :func:`total_diffuse_reflectance` at :math:`R = \\infty`. Shapes as :func:`dipole_rd`.

    Examples:
        >>> round(dipole_cumulative(float("inf"), 0.0, 1.0, 1.3).item(), 6)
        1.0
    """
    r_t = as_float_tensor(radius, "radius")
    sa, ss, et = _prepare_material(sigma_a, sigma_s_prime, eta, r_t)
    check_nonnegative(r_t, "radius", allow_inf=True)
    check_broadcastable(radius=r_t, sigma_a=sa, sigma_s_prime=ss, eta=et)
    out_dtype, work = compute_dtype(r_t, sa, ss, et)
    t = DipoleTerms(sa.to(work), ss.to(work), et.to(work))
    r_w = r_t.to(work)
    sig = t.sigma_tr
    total = 0.0
    for z in (t.z_r, t.z_v):
        d = torch.sqrt(r_w * r_w + z * z)
        tail = torch.where(torch.isinf(d), torch.zeros_like(d), z / d * torch.exp(-sig * d))
        total = total + torch.exp(-sig * z) - tail
    return (0.5 * t.alpha_prime * total).to(out_dtype)


def dipole_spectrum(
    k: Tensor | float, sigma_a: Tensor | float, sigma_s_prime: Tensor | float, eta: Tensor | float = 1.3
) -> Tensor:
    """Radial 2-D Fourier transform :math:`\\hat R_d(k) = \\int R_d(|x|) e^{-i k\\cdot x} dx` (k in rad/mm).

    Each dipole term is a Poisson-like kernel with a closed-form Hankel transform:

    .. math::
        \\int_0^\\infty z(1+\\sigma_{tr}d)e^{-\\sigma_{tr}d}/d^3\\,J_0(kr)\\,r\\,dr = e^{-z q},
        \\quad q = \\sqrt{k^2+\\sigma_{tr}^2},

    so that

    .. math::
        \\hat R_d(k) = \\frac{\\alpha'}{2}\\left(e^{-z_r q} + e^{-z_v q}\\right).

    :math:`\\hat R_d(0)` is :func:`total_diffuse_reflectance`. Used for the sampling criterion of splats.
    """
    k_t = as_float_tensor(k, "k")
    sa, ss, et = _prepare_material(sigma_a, sigma_s_prime, eta, k_t)
    check_nonnegative(k_t, "k", allow_inf=True)
    check_broadcastable(k=k_t, sigma_a=sa, sigma_s_prime=ss, eta=et)
    out_dtype, work = compute_dtype(k_t, sa, ss, et)
    t = DipoleTerms(sa.to(work), ss.to(work), et.to(work))
    k_w = k_t.to(work)
    q = torch.sqrt(k_w * k_w + t.sigma_tr_sq)
    return (0.5 * t.alpha_prime * (torch.exp(-t.z_r * q) + torch.exp(-t.z_v * q))).to(out_dtype)
