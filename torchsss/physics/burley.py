"""Burley's normalized diffusion profile (Christensen & Burley 2015), an alternative to the dipole.

.. math::
    R(r) = \\frac{A\\, s\\, (e^{-s r} + e^{-s r / 3})}{8 \\pi r}, \\qquad \\int_0^\\infty R(r)\\, 2\\pi r\\, dr = A

``A`` is the surface albedo and ``s`` (mm^-1) the shape parameter (``1/d`` in Burley's notation). Shapes and
broadcasting follow :func:`torchsss.dipole_rd`: ``r`` is ``(..., C)`` or ``(..., 1)``, parameters ``(C,)``.
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
    skip_value_checks,
)
from torchsss.physics.dipole import total_diffuse_reflectance

__all__ = ["BURLEY_R_FLOOR", "burley_cumulative", "burley_params_from_dipole", "burley_r_max", "burley_rd"]

#: The profile is singular (1/r) at r = 0; distances are clamped to ``BURLEY_R_FLOOR / s`` so that a
#: receiver that coincides with a source gets a large finite value instead of inf (the integral is unaffected).
BURLEY_R_FLOOR = 1e-6


def _check_albedo(a: Tensor, name: str) -> None:
    """Raise ValueError unless every entry of ``a`` is in [0, 1] (skipped while tracing)."""
    if skip_value_checks(a):
        return
    bad = torch.isnan(a) | (a < 0) | (a > 1)
    if bool(bad.any()):
        first = a.detach()[bad].flatten()[0].item()
        raise ValueError(f"{name}: expected values in [0, 1], got {first!r} ({int(bad.sum())} of {a.numel()} "
                         f"entries bad)")


def burley_rd(
    r: Tensor | float,
    albedo: Tensor | float,
    s: Tensor | float,
    *,
    distance_scale: Tensor | float | None = None,
    irradiance_scale: Tensor | float | None = None,
) -> Tensor:
    """Burley's normalized diffusion profile (mm^-2), with the same optional modifiers as :func:`dipole_rd`.

    Args:
        r: distances in mm, :math:`(..., C)` or :math:`(..., 1)`, >= 0 (``inf`` gives 0 with a zero gradient).
        albedo: surface albedo :math:`A` in [0, 1], e.g. :math:`(C,)`.
        s: shape parameter in mm^-1 (> 0).
        distance_scale: optional :math:`M_d` (> 0) of the source.
        irradiance_scale: optional :math:`M_i` (>= 0) of the source.

    Returns:
        The profile, broadcast shape, promoted dtype (float16/bfloat16 computed in float32).

    Raises:
        TypeError: non-tensor, non-number or non-floating input.
        ValueError: negative/NaN distances, albedo outside [0, 1], ``s <= 0``, shapes that do not broadcast.

    Examples:
        >>> v = burley_rd(torch.tensor([1.0]), torch.tensor([0.8]), torch.tensor([2.0]))
        >>> round(v.item(), 6)
        0.041301
    """
    r_t = as_float_tensor(r, "r")
    a_t = as_float_tensor(albedo, "albedo", like=r_t)
    s_t = as_float_tensor(s, "s", like=r_t)
    check_nonnegative(r_t, "r", allow_inf=True)
    _check_albedo(a_t, "albedo")
    check_positive(s_t, "s")
    tensors = {"r": r_t, "albedo": a_t, "s": s_t}
    if distance_scale is not None:
        tensors["distance_scale"] = as_float_tensor(distance_scale, "distance_scale", like=r_t)
        check_positive(tensors["distance_scale"], "distance_scale")
    if irradiance_scale is not None:
        tensors["irradiance_scale"] = as_float_tensor(irradiance_scale, "irradiance_scale", like=r_t)
        check_nonnegative(tensors["irradiance_scale"], "irradiance_scale")
    check_broadcastable(**tensors)
    out_dtype, work = compute_dtype(*tensors.values())
    rr = r_t.to(work)
    sw = s_t.to(work)
    md = tensors["distance_scale"].to(work) if distance_scale is not None else None
    # Where s * r * M_d is infinite (r = inf) the profile and its derivatives are 0; r is masked before any
    # product (double-where trick) so that no inf * 0 reaches the gradient of s, M_d or the albedo. NaN stays NaN
    # (with validation off a NaN distance must not come out as a plausible 0).
    raw = rr.detach() * sw.detach()
    if md is not None:
        raw = raw * md.detach()
    far = torch.isinf(raw)
    rr = torch.where(far, torch.zeros_like(rr), rr)
    if md is not None:
        rr = rr * md
    rr = torch.maximum(rr, BURLEY_R_FLOOR / sw)
    sr = sw * rr
    val = a_t.to(work) * sw * (torch.exp(-sr) + torch.exp(-sr / 3.0)) / (8.0 * math.pi * rr)
    val = torch.where(far, torch.zeros_like(val), val)
    if irradiance_scale is not None:
        val = val * tensors["irradiance_scale"].to(work)
    return val.to(out_dtype)


def burley_params_from_dipole(
    sigma_a: Tensor | float, sigma_s_prime: Tensor | float, eta: Tensor | float = 1.3
) -> tuple[Tensor, Tensor]:
    """Burley parameters ``(albedo, s)`` matching a dipole material.

    ``albedo`` is the dipole's closed-form total diffuse reflectance, so both profiles carry the same energy;
    ``s = sigma_t' * (1.85 - A + 7 |A - 0.8|^3)`` is Christensen & Burley's fit for the searchlight
    configuration with the (reduced) mean free path :math:`1/\\sigma_t'` as length scale.

    Examples:
        >>> a, s = burley_params_from_dipole(0.0, 1.0)
        >>> round(a.item(), 6), round(s.item(), 6)
        (1.0, 0.906)
    """
    sa = as_float_tensor(sigma_a, "sigma_a")
    ss = as_float_tensor(sigma_s_prime, "sigma_s_prime", like=sa)
    a = total_diffuse_reflectance(sa, ss, eta)
    fit = 1.85 - a + 7.0 * (a - 0.8).abs() ** 3
    return a, (sa + ss) * fit


def burley_cumulative(radius: Tensor | float, albedo: Tensor | float, s: Tensor | float) -> Tensor:
    """Closed-form :math:`\\int_0^R R(r)\\,2\\pi r\\,dr` of Burley's profile: the reflectance within radius ``R`` (mm).

    .. math:: \\frac{A}{4}\\left[(1 - e^{-sR}) + 3\\,(1 - e^{-sR/3})\\right]

    It tends to the albedo :math:`A` as :math:`R \\to \\infty` (and is :math:`A` at ``inf``, with a zero derivative
    with respect to :math:`s`). Shapes broadcast; differentiable.

    Examples:
        >>> round(burley_cumulative(float("inf"), 0.8, 2.0).item(), 6)
        0.8
    """
    r_t = as_float_tensor(radius, "radius")
    a_t = as_float_tensor(albedo, "albedo", like=r_t)
    s_t = as_float_tensor(s, "s", like=r_t)
    check_nonnegative(r_t, "radius", allow_inf=True)
    check_positive(s_t, "s")
    out_dtype, work = compute_dtype(r_t, a_t, s_t)
    rw, sw = r_t.to(work), s_t.to(work)
    # R = inf (or s R beyond the format): the albedo, with a zero gradient for s (masked before the product)
    far = ~torch.isfinite(rw.detach() * sw.detach())
    sr = sw * torch.where(far, torch.zeros_like(rw), rw)
    inside = torch.where(far, torch.ones_like(sr), -torch.expm1(-sr) - 3.0 * torch.expm1(-sr / 3.0))
    return (a_t.to(work) * 0.25 * torch.where(far, torch.full_like(sr, 4.0), inside)).to(out_dtype)


def burley_r_max(s: Tensor | float, eps: float = 0.01) -> Tensor:
    """Radius (mm) beyond which Burley's profile holds a fraction ``eps`` of its energy (Shah eq. 6.16's r_max).

    The tail fraction :math:`(e^{-sR} + 3 e^{-sR/3})/4` is solved for :math:`\\epsilon` by bisection in float64
    (it does not depend on the albedo). No gradient.

    Examples:
        >>> round(burley_r_max(torch.tensor([1.0]), 0.01).item(), 4)
        12.9526
    """
    s_t = as_float_tensor(s, "s")
    check_positive(s_t, "s")
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not 0.0 < float(eps) < 1.0:
        raise ValueError(f"eps: expected a number in (0, 1), got {eps!r}")
    lo = torch.zeros(s_t.shape, dtype=torch.float64)
    hi = torch.full(s_t.shape, 3.0 * math.log(1.0 / float(eps)) + 1.0, dtype=torch.float64)  # x = s R
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        tail = 0.25 * (torch.exp(-mid) + 3.0 * torch.exp(-mid / 3.0))
        big = tail > eps
        lo = torch.where(big, mid, lo)
        hi = torch.where(big, hi, mid)
    return (hi.to(s_t.device) / s_t.detach().to(torch.float64)).to(s_t.dtype)
