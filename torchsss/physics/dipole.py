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
:math:`\\sigma_a = 0` even though :math:`d\\sigma_{tr}/d\\sigma_a` is not. The evaluation uses the series of
:math:`h` in :math:`u` where :math:`u < 10^{-4}`, which keeps autograd away from the :math:`0 \\cdot \\infty` of the
naive chain rule at :math:`\\sigma_a = 0` and from the cancellation of the closed form's derivative for tiny
:math:`\\sigma_a` (float32 gradients are accurate to ~1e-6 down to :math:`\\sigma_a = 0`).

:func:`dipole_rd` evaluates the profile in units of :math:`z_r = 1/\\sigma_t'`,

.. math::
    R_d = \\frac{\\sigma_s'\\sigma_t'}{4\\pi}\\left[\\frac{h(\\beta D_r)}{D_r^3}
          + \\zeta\\,\\frac{h(\\beta D_v)}{D_v^3}\\right], \\quad D_{r,v} = \\sqrt{(r\\sigma_t')^2 + \\{1, \\zeta\\}^2},
    \\quad \\zeta = 1 + \\tfrac43 A, \\quad \\beta = \\sqrt{3\\sigma_a/\\sigma_t'},

so no intermediate overflows unless the result does (the naive form overflows :math:`\\sigma_{tr}^2` in float32
from :math:`\\sigma_a \\approx 10^{19}` and underflows :math:`d^3` at :math:`r = 0` from
:math:`\\sigma_t' \\approx 10^{15}`; here only :math:`e^{-\\sigma_{tr} d}` can underflow, far below the peak).
:math:`r\\sigma_t'` is clamped to :math:`10^{19}` (float32) or :math:`10^{150}` (float64), where the profile is 0
to below the format's smallest number (for :math:`\\sigma_s'\\sigma_t' < 10^{11}` mm^-2 in float32), and
``r = inf`` is clamped to the largest finite number *before* any product, so ``r = inf`` gives 0 with a zero
gradient and no NaN reaches a batch's shared material gradient.
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
    skip_value_checks,
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

# Where u = (sigma_tr d)^2 is below this, h(sigma_tr d) and the cumulative's bracket are evaluated by their series
# in u (to u^3.5, next term ~ 1e-20): the closed forms lose their derivative in sigma_a to cancellation there
# (relative error ~ eps / (sigma_tr d), 1% in float32 at sigma_a = 1e-12 mm^-1) and divide 0 by 0 at sigma_a = 0.
_SERIES_U = 1e-4
# total_diffuse_reflectance: the derivative of sqrt(3 sigma_a / sigma_t') is clamped at this argument (see there).
_SQRT_FLOOR = 1e-12
# r / z_r is clamped to this (per compute dtype) so that its square cannot overflow: beyond it the profile is 0 to
# far below the format's smallest number (R_d ~ sigma_s' sigma_t' / rho^3), and its derivative is taken as 0.
_RHO_CAP = {torch.float32: 1e19, torch.float64: 1e150}


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

    def spectrum(self, k: Tensor) -> Tensor:
        """:func:`dipole_spectrum` at finite ``k >= 0`` (rad/mm) without its checks, for solvers' inner loops.

        :math:`\\hat R_d(k) = \\tfrac{\\alpha'}{2}(e^{-z_r q} + e^{-z_v q})`, :math:`q = \\sqrt{k^2 + \\sigma_{tr}^2}`;
        ``k`` broadcasts with the terms. Not for autograd (the square root's derivative is not guarded at
        :math:`k = \\sigma_a = 0`).
        """
        q = torch.sqrt(k * k + self.sigma_tr_sq)
        return 0.5 * self.alpha_prime * (torch.exp(-self.z_r * q) + torch.exp(-self.z_v * q))


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
    if not skip_value_checks(sa, ss):
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


def _safe_sqrt(x: Tensor, eps: float = _SQRT_FLOOR) -> Tensor:
    """:math:`\\sqrt{x}` (exact value) whose derivative is that of the square root clamped at ``eps``.

    For ``x >= eps`` this is ``torch.sqrt``; below, the value is still exactly :math:`\\sqrt{x}` but the
    derivative is held at :math:`1/(2\\sqrt{\\epsilon})` instead of growing to :math:`+\\infty` at 0.
    """
    big = x >= eps
    exact = torch.sqrt(torch.where(big, x, torch.full_like(x, eps)))
    low = torch.sqrt(x.detach().clamp_min(0.0)) + (x - x.detach()) * (0.5 / math.sqrt(eps))
    return torch.where(big, exact, low)


def _one_minus_exp(x: Tensor) -> Tensor:
    """:math:`1 - e^{-x}` for :math:`x \\ge 0` to full relative precision (a Taylor series below 0.1).

    ``torch.expm1`` would do in eager mode, but exporters lower it to ``exp(x) - 1``, which loses the precision this
    is for; the series (to :math:`x^9`, next term :math:`< 3 \\cdot 10^{-18}` relative) is plain arithmetic.
    """
    small = x < 0.1
    xs = torch.where(small, x, torch.zeros_like(x))
    poly = torch.ones_like(xs)
    for k in range(9, 1, -1):
        poly = 1.0 - xs / k * poly
    return torch.where(small, xs * poly, 1.0 - torch.exp(-x))


def _reduced_distance(r: Tensor, st: Tensor, md: Tensor | None, cap: float | None = None) -> Tensor:
    """:math:`\\rho = r M_d \\sigma_t'`, the distance in units of :math:`z_r`, clamped to ``cap``.

    ``cap`` defaults to ``_RHO_CAP``; :func:`dipole_rd` passes the format's largest number and forms
    :math:`\\sqrt{\\rho^2 + z^2}` with :func:`_source_distance`. ``r = inf`` is first clamped to the largest finite
    number (zero gradient), so no :math:`\\infty \\cdot 0` reaches the gradient of :math:`\\sigma_t'` or :math:`M_d`
    (the double-where trick, with clamps); a product that overflows or exceeds the cap is clamped to the cap, which
    passes a zero gradient to its (finite) factors. At the default cap the cumulative's tail is 0 to below the format's
    smallest number for any :math:`\\sigma_s'\\sigma_t' < 10^{11}` mm^-2 (float32; :math:`10^{126}` in float64).
    """
    r_c = r.clamp(max=torch.finfo(r.dtype).max)
    scale = st if md is None else md * st
    return (r_c * scale).clamp(max=_RHO_CAP.get(st.dtype, 1e19) if cap is None else cap)


def _source_distance(rho: Tensor, zz: Tensor | float) -> Tensor:
    """:math:`D = \\sqrt{\\rho^2 + z^2}` without overflow: :math:`D = \\rho` (to rounding) beyond ``_RHO_CAP``.

    The square is only taken of distances below the cap (double-where), so a :math:`\\rho` up to the format's
    largest number gives a finite :math:`D` and finite gradients.
    """
    big = _RHO_CAP.get(rho.dtype, 1e19)
    far = rho > big
    near = torch.where(far, torch.zeros_like(rho), rho)
    return torch.where(far, rho, torch.sqrt(near * near + zz * zz))


def _source_term(scale: Tensor, st: Tensor, b2: Tensor, dist: Tensor, any_small: bool, far: bool = True) -> Tensor:
    """One dipole source in units of :math:`z_r`: ``scale`` :math:`\\cdot\\, \\sigma_t'\\, h(\\beta D) / D^3`.

    ``scale`` is :math:`\\sigma_s'`, ``dist`` is :math:`D = d / z_r \\ge 1` and ``b2`` is
    :math:`\\beta^2 = 3\\sigma_a/\\sigma_t'`, so that :math:`\\beta D = \\sigma_{tr} d`. Written as
    :math:`(\\sigma_s'/D)(\\sigma_t'/D)(1/D + \\beta) e^{-\\beta D}`: every factor is bounded by a coefficient
    (:math:`D \\ge 1`, :math:`\\beta \\le \\sqrt 3`) and non-increasing in :math:`D`, so no intermediate overflows
    unless the result does, and rounding keeps the result monotone in r. Where :math:`u = \\beta^2 D^2 <`
    ``_SERIES_U`` (possible only if ``any_small``: some :math:`\\beta^2 <` ``_SERIES_U``), :math:`h` is its series
    in :math:`u`, whose derivative is exact and finite down to :math:`\\sigma_a = 0`.
    """
    inv = torch.reciprocal(dist)
    prefix = (scale * inv) * (st * inv)
    if not any_small:
        beta = torch.sqrt(b2)
        return prefix * (inv + beta) * torch.exp(-beta * dist)
    # beta^2 = 0 channels only ever take the series (u = 0); sqrt is masked there before the op (double-where)
    beta = torch.sqrt(torch.where(b2 > 0, b2, torch.ones_like(b2)))
    exact = prefix * (inv + beta) * torch.exp(-beta * dist)
    # u = (beta D)^2, squared only below the cap (double-where: b2 D D could overflow, and inf * 0 in the backward);
    # beyond it the exact form serves every beta > 0, and beta = 0 takes the series (u = 0) at any distance
    if far:  # some D may exceed the cap (``far``: unknown or known to): guard the square
        beyond = dist > _RHO_CAP.get(dist.dtype, 1e19)
        d_near = torch.where(beyond, torch.zeros_like(dist), dist)
        u = (b2 * d_near) * d_near
        tiny = (b2 <= 0) | (~beyond & (u < _SERIES_U))
    else:
        u = (b2 * dist) * dist
        tiny = u < _SERIES_U  # b2 = 0 gives u = 0: the series
    ut = torch.where(tiny, u, torch.zeros_like(u))
    # h(x) = (1 + x) e^{-x} = 1 - x^2/2 + x^3/3 - x^4/8 + x^5/30 - x^6/144 + x^7/840 - ..., x = sqrt(u)
    h = (1.0 + ut * (-0.5 + ut * (-0.125 - ut / 144.0))
         + torch.pow(ut, 1.5) * (1.0 / 3.0 + ut * (1.0 / 30.0 + ut / 840.0)))
    return torch.where(tiny, prefix * (h * inv), exact)


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
    sa_w, ss_w = sa.to(work), ss.to(work)
    st = sa_w + ss_w
    md = extra["distance_scale"].to(work) if "distance_scale" in extra else None
    # In units of z_r = 1/sigma_t' (module docstring); r = inf gives 0 with a zero gradient.
    # rho up to the format's largest number (not the cumulative's cap): R_d ~ sigma_s' sigma_t' / rho^3 stays exact
    # for huge coefficients at sigma_a = 0, where a cap on rho would leave a spurious floor
    rho = _reduced_distance(r_w, st, md, cap=torch.finfo(work).max)
    zeta = 1.0 + 4.0 / 3.0 * dipole_boundary_a(et.to(work))  # z_v / z_r
    b2 = 3.0 * (sa_w / st)  # (sigma_tr z_r)^2 = 3 (1 - alpha')
    # u = b2 D^2 >= b2: else no series anywhere (meta tensors hold no values: take both branches)
    any_small = is_tracing() or b2.device.type == "meta" or bool((b2 < _SERIES_U).any())
    # beyond _RHO_CAP the square would overflow: the guarded (double-where) forms; else the plain ones, cheaper
    far = is_tracing() or rho.device.type == "meta" or bool((rho > _RHO_CAP.get(rho.dtype, 1e19)).any())
    if far:
        d_r = _source_distance(rho, 1.0)
        d_v = _source_distance(rho, zeta)
    else:
        rho2 = rho * rho
        d_r = torch.sqrt(rho2 + 1.0)
        d_v = torch.sqrt(rho2 + zeta * zeta)
    rd = (_source_term(ss_w, st, b2, d_r, any_small, far) + zeta * _source_term(ss_w, st, b2, d_v, any_small, far)
          ) / (4.0 * math.pi)
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

    Note :math:`\\sqrt{3(1-\\alpha')} = \\sigma_{tr} z_r = \\sqrt{3\\sigma_a/\\sigma_t'}`, computed in that last form
    (no cancellation in :math:`1 - \\alpha'`).

    **Gradient at** :math:`\\sigma_a = 0`. Because of that square root the one-sided derivative with respect to
    :math:`\\sigma_a` is genuinely :math:`-\\infty` at :math:`\\sigma_a = 0` (a cusp: the first absorption
    removes light infinitely fast). For optimisation this function returns a finite surrogate instead (the usual
    safe-sqrt choice): the value is exact, but the derivative of the square root is clamped at the argument
    :math:`3\\sigma_a/\\sigma_t' = 10^{-12}` (to :math:`5 \\cdot 10^5`), so gradients are exact for
    :math:`\\sigma_a \\ge 3.3 \\cdot 10^{-13}\\,\\sigma_t'` and large but finite below. The derivative with
    respect to :math:`\\sigma_s'` (and :math:`\\eta`) at :math:`\\sigma_a = 0` is exactly 0, its true value
    (:math:`R_{total} = 1` for every :math:`\\sigma_s'` when nothing absorbs).

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
    sa_w, ss_w = sa.to(work), ss.to(work)
    st = sa_w + ss_w
    absorbed = sa_w / st  # 1 - alpha'
    # alpha' = 1 - sigma_a/sigma_t' where scattering dominates (its sigma_s' derivative is then exactly 0 at
    # sigma_a = 0), sigma_s'/sigma_t' elsewhere (accurate for tiny albedos). Both branches are finite.
    alpha = torch.where(sa_w <= ss_w, 1.0 - absorbed, ss_w / st)
    root = _safe_sqrt(3.0 * absorbed)
    a = dipole_boundary_a(et.to(work))
    return (0.5 * alpha * (1.0 + torch.exp(-4.0 / 3.0 * a * root)) * torch.exp(-root)).to(out_dtype)


def dipole_cumulative(
    radius: Tensor | float, sigma_a: Tensor | float, sigma_s_prime: Tensor | float, eta: Tensor | float = 1.3
) -> Tensor:
    """Closed-form :math:`\\int_0^{R} R_d(r)\\, 2\\pi r\\, dr`, the reflectance captured within radius ``R`` (mm).

    Substituting :math:`d = \\sqrt{r^2 + z^2}` turns each source term into an exact derivative:

    .. math::
        \\int_0^R R_d\\,2\\pi r\\,dr = \\frac{\\alpha'}{2}\\sum_{z \\in \\{z_r, z_v\\}}
        \\left(e^{-\\sigma_{tr} z} - \\frac{z}{d(R)} e^{-\\sigma_{tr} d(R)}\\right)

    It equals :func:`total_diffuse_reflectance` at :math:`R = \\infty`. Shapes as :func:`dipole_rd`.

    Gradients: at :math:`R = \\infty` the tail term is 0 with a zero gradient (masked before any product), and the
    :math:`\\sigma_a = 0` cusp is that of :func:`total_diffuse_reflectance` (the same clamped, finite surrogate).
    For finite :math:`R` the integral is smooth in :math:`\\sigma_a` at 0 (the linear terms of the two
    exponentials cancel), and its exact finite derivative there is computed from a series in
    :math:`\\sigma_{tr}`.

    Examples:
        >>> round(dipole_cumulative(float("inf"), 0.0, 1.0, 1.3).item(), 6)
        1.0
    """
    r_t = as_float_tensor(radius, "radius")
    sa, ss, et = _prepare_material(sigma_a, sigma_s_prime, eta, r_t)
    check_nonnegative(r_t, "radius", allow_inf=True)
    check_broadcastable(radius=r_t, sigma_a=sa, sigma_s_prime=ss, eta=et)
    out_dtype, work = compute_dtype(r_t, sa, ss, et)
    r_w, sa_w, ss_w = r_t.to(work), sa.to(work), ss.to(work)
    st = sa_w + ss_w
    absorbed = sa_w / st
    alpha = torch.where(sa_w <= ss_w, 1.0 - absorbed, ss_w / st)
    b2 = 3.0 * absorbed  # (sigma_tr z_r)^2
    zeta = 1.0 + 4.0 / 3.0 * dipole_boundary_a(et.to(work))
    # In units of z_r: each source contributes e^{-beta zz} - (zz / D) e^{-beta D}, D = sqrt(rho^2 + zz^2).
    far = torch.isinf(r_w)  # R = inf: no tail (masked before any product)
    rho = _reduced_distance(torch.where(far, torch.zeros_like(r_w), r_w), st, None)
    beta_cusp = _safe_sqrt(b2)  # R = inf: the head alone, with the cusp of total_diffuse_reflectance
    beta = torch.sqrt(torch.where(b2 > 0, b2, torch.ones_like(b2)))  # b2 = 0 only takes the series (u = 0)
    total = 0.0
    for zz in (torch.ones_like(zeta), zeta):
        dist = torch.sqrt(rho * rho + zz * zz)
        excess = rho * rho / (dist + zz)  # D - zz without cancellation (0 at R = 0)
        # e^{-beta zz} [excess / D + (zz / D)(1 - e^{-beta excess})]: no cancellation for small R
        exact = torch.exp(-beta * zz) * (excess / dist + zz / dist * _one_minus_exp(beta * excess))
        # series in beta where u = (beta D)^2 is small (the closed form's sigma_a derivative cancels there):
        # e^{-x zz} - (zz/D) e^{-x D} = (D - zz)/D + sum_{k>=2} (-1)^k / k! (zz^k b2^{k/2} - zz u^{k/2} / D), x = beta
        u = (b2 * dist) * dist
        small = ~far & (u < _SERIES_U)
        ut = torch.where(small, u, torch.zeros_like(u))
        bs = torch.where(small, b2, torch.zeros_like(b2))
        series = excess / dist
        for k in range(2, 8):
            b_k = bs ** (k // 2) if k % 2 == 0 else torch.pow(bs, 0.5 * k)
            u_k = ut ** (k // 2) if k % 2 == 0 else torch.pow(ut, 0.5 * k)
            series = series + (-1.0) ** k / math.factorial(k) * (zz**k * b_k - zz * u_k / dist)
        head = torch.exp(-beta_cusp * zz)
        total = total + torch.where(far, head, torch.where(small, series, exact))
    return (0.5 * alpha * total).to(out_dtype)


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
    Evaluated in units of :math:`z_r` (:math:`z_r q = \\sqrt{(k/\\sigma_t')^2 + 3\\sigma_a/\\sigma_t'}`); where
    :math:`k/\\sigma_t'` or its square is not finite the spectrum is 0 with a zero gradient, and the square root
    has the clamped derivative of :func:`total_diffuse_reflectance` below :math:`10^{-12}` (finite at
    :math:`k = \\sigma_a = 0`).
    """
    k_t = as_float_tensor(k, "k")
    sa, ss, et = _prepare_material(sigma_a, sigma_s_prime, eta, k_t)
    check_nonnegative(k_t, "k", allow_inf=True)
    check_broadcastable(k=k_t, sigma_a=sa, sigma_s_prime=ss, eta=et)
    out_dtype, work = compute_dtype(k_t, sa, ss, et)
    k_w, sa_w, ss_w = k_t.to(work), sa.to(work), ss.to(work)
    st = sa_w + ss_w
    absorbed = sa_w / st
    alpha = torch.where(sa_w <= ss_w, 1.0 - absorbed, ss_w / st)
    zeta = 1.0 + 4.0 / 3.0 * dipole_boundary_a(et.to(work))
    kappa_raw = k_w.detach() / st.detach()
    far = ~torch.isfinite(kappa_raw * kappa_raw)
    kappa = torch.where(far, torch.zeros_like(k_w), k_w) / st
    q = _safe_sqrt(kappa * kappa + 3.0 * absorbed)  # z_r q
    spec = 0.5 * alpha * (torch.exp(-q) + torch.exp(-zeta * q))
    return torch.where(far, torch.zeros_like(spec), spec).to(out_dtype)
