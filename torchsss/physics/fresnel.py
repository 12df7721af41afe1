"""Fresnel terms of a smooth dielectric boundary, and the diffuse Fresnel reflectance of the dipole model.

``eta`` is the relative index of refraction of the material over the outside medium (1.3 for the Jensen 2001
measurements). ``cos_theta`` is the cosine between the surface normal and the direction on the *outside* of the
boundary (the light direction for :math:`F_t(\\eta, \\omega_i)`, the view direction for :math:`F_t(\\eta,
\\omega_o)`); it is clamped to [0, 1]. All functions broadcast their arguments and are differentiable.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsss._checks import as_float_tensor, check_broadcastable, check_positive, compute_dtype

__all__ = [
    "FRESNEL_MODES",
    "check_fresnel",
    "diffuse_fresnel_reflectance",
    "dipole_boundary_a",
    "exit_radiance",
    "fresnel_reflectance",
    "fresnel_transmittance",
    "schlick_reflectance",
    "schlick_transmittance",
    "transmittance",
]

#: The Fresnel transmittance models every renderer accepts: the exact unpolarised dielectric, Schlick's
#: approximation, or none (:math:`F_t \\equiv 1`).
FRESNEL_MODES = ("exact", "schlick", "none")


def _prepare(cos_theta: Tensor | float, eta: Tensor | float) -> tuple[Tensor, Tensor, torch.dtype]:
    cos_t = as_float_tensor(cos_theta, "cos_theta")
    eta_t = as_float_tensor(eta, "eta", like=cos_t)
    check_broadcastable(cos_theta=cos_t, eta=eta_t)
    check_positive(eta_t, "eta")
    out_dtype, work = compute_dtype(cos_t, eta_t)
    return cos_t.to(work).clamp(0.0, 1.0), eta_t.to(work), out_dtype


def _sin2_transmitted(cos_i: Tensor, eta: Tensor) -> Tensor:
    return (1.0 - cos_i * cos_i) / (eta * eta)


def fresnel_reflectance(cos_theta: Tensor | float, eta: Tensor | float) -> Tensor:
    """Exact unpolarised Fresnel reflectance of a dielectric boundary (average of s and p).

    Light arrives from the outside (index 1) onto a material of relative index ``eta``. For ``eta < 1`` total
    internal reflection gives 1. ``eta == 1`` gives exactly 0 at every angle.

    Args:
        cos_theta: cosine of the angle of incidence, any shape; clamped to [0, 1].
        eta: relative index of refraction (> 0), broadcastable with ``cos_theta``.

    Returns:
        Reflectance in [0, 1], the broadcast shape, dtype promoted from the inputs.

    Examples:
        >>> r = fresnel_reflectance(torch.tensor([1.0, 0.0]), 1.5)
        >>> [round(v, 4) for v in r.tolist()]
        [0.04, 1.0]
    """
    cos_i, eta_t, out_dtype = _prepare(cos_theta, eta)
    sin2_t = _sin2_transmitted(cos_i, eta_t)
    tir = sin2_t >= 1.0
    # Safe square root: the TIR branch never differentiates through sqrt(<= 0).
    cos_t = torch.sqrt(torch.where(tir, torch.ones_like(sin2_t), 1.0 - sin2_t))
    rs_num = cos_i - eta_t * cos_t
    rs_den = cos_i + eta_t * cos_t
    rp_num = eta_t * cos_i - cos_t
    rp_den = eta_t * cos_i + cos_t
    # Both denominators vanish only at grazing incidence with cos_t = 0 (eta == 1); that case is handled below.
    degenerate = (rs_den <= 0) | (rp_den <= 0)
    one = torch.ones_like(rs_den)
    rs = rs_num / torch.where(degenerate, one, rs_den)
    rp = rp_num / torch.where(degenerate, one, rp_den)
    f = 0.5 * (rs * rs + rp * rp)
    f = torch.where(degenerate, one, f)
    f = torch.where(tir, one, f)
    f = torch.where(eta_t == 1.0, torch.zeros_like(f), f)
    return f.clamp(0.0, 1.0).to(out_dtype)


def fresnel_transmittance(cos_theta: Tensor | float, eta: Tensor | float) -> Tensor:
    """Exact unpolarised Fresnel transmittance :math:`F_t = 1 - F_r` (see :func:`fresnel_reflectance`).

    Examples:
        >>> round(fresnel_transmittance(torch.tensor(1.0), 1.3).item(), 5)
        0.98299
    """
    return 1.0 - fresnel_reflectance(cos_theta, eta)


def schlick_reflectance(cos_theta: Tensor | float, eta: Tensor | float) -> Tensor:
    """Schlick's approximation :math:`R_0 + (1 - R_0)(1 - \\cos)^5`, :math:`R_0 = ((\\eta-1)/(\\eta+1))^2`.

    For ``eta < 1`` the cosine on the denser side (the transmitted one) is used, and total internal reflection
    gives 1. Shapes and dtypes as :func:`fresnel_reflectance`. Against the exact reflectance (measured, tested):
    max absolute error 0.068 at eta = 1.3 and 0.036 at eta = 1.5 (both near grazing incidence), cosine-weighted
    hemispherical mean error below 0.011 for 1.3 <= eta <= 2.5. It is poor close to eta = 1, where it
    returns :math:`(1 - \\cos)^5` instead of 0.

    Examples:
        >>> round(schlick_reflectance(torch.tensor(1.0), 1.5).item(), 4)
        0.04
    """
    cos_i, eta_t, out_dtype = _prepare(cos_theta, eta)
    r0 = ((eta_t - 1.0) / (eta_t + 1.0)) ** 2
    sin2_t = _sin2_transmitted(cos_i, eta_t)
    tir = sin2_t >= 1.0
    cos_t = torch.sqrt(torch.where(tir, torch.ones_like(sin2_t), 1.0 - sin2_t))
    c = torch.where(eta_t < 1.0, cos_t, cos_i)
    f = r0 + (1.0 - r0) * (1.0 - c) ** 5
    f = torch.where(tir, torch.ones_like(f), f)
    return f.clamp(0.0, 1.0).to(out_dtype)


def schlick_transmittance(cos_theta: Tensor | float, eta: Tensor | float) -> Tensor:
    """:math:`1 -` :func:`schlick_reflectance`."""
    return 1.0 - schlick_reflectance(cos_theta, eta)


def check_fresnel(fresnel: object, modes: tuple[str, ...] = FRESNEL_MODES) -> str:
    """Validate a Fresnel model name (one of ``modes``); returns it.

    Raises:
        ValueError: not one of ``modes`` (the message lists them).

    Examples:
        >>> check_fresnel("schlick")
        'schlick'
    """
    if not isinstance(fresnel, str) or fresnel not in modes:
        raise ValueError(f"fresnel: expected one of {', '.join(repr(m) for m in modes)}, got {fresnel!r}")
    return fresnel


def transmittance(cos_theta: Tensor | float, eta: Tensor | float, fresnel: str = "exact") -> Tensor:
    """Fresnel transmittance by the chosen model: the one place where the exact/Schlick choice is made.

    Args:
        cos_theta: cosines on the outside of the boundary (broadcast with ``eta``).
        eta: relative index of refraction.
        fresnel: ``"exact"`` (:func:`fresnel_transmittance`), ``"schlick"`` (:func:`schlick_transmittance`) or
            ``"none"`` (1 everywhere, in the broadcast shape).

    Examples:
        >>> [round(transmittance(torch.tensor(1.0), 1.3, m).item(), 4) for m in FRESNEL_MODES]
        [0.983, 0.983, 1.0]
    """
    check_fresnel(fresnel)
    if fresnel == "exact":
        return fresnel_transmittance(cos_theta, eta)
    if fresnel == "schlick":
        return schlick_transmittance(cos_theta, eta)
    cos_t = as_float_tensor(cos_theta, "cos_theta")
    eta_t = as_float_tensor(eta, "eta", like=cos_t)
    return torch.ones(torch.broadcast_shapes(cos_t.shape, eta_t.shape), dtype=compute_dtype(cos_t, eta_t)[0],
                      device=cos_t.device)


def exit_radiance(radiosity: Tensor, cos_out: Tensor, eta: Tensor | float, fresnel: str = "exact") -> Tensor:
    """Outgoing radiance :math:`L = F_t(\\eta, \\cos\\theta_o)/\\pi \\; B` of every method (DESIGN.md §1).

    The one exit-radiance function: every renderer turns its radiosity into radiance here, with the ``eta`` of its
    material module, so an edit of that eta (or a gradient step on it) reaches the exit Fresnel term.

    Args:
        radiosity: :math:`(B, C, H, W)` radiosity :math:`B` (or any shape that broadcasts with ``cos_out``).
        cos_out: :math:`(B, 1, H, W)` cosine between the normal and the direction to the viewer (clamped to [0, 1]).
        eta: a number, :math:`()`, :math:`(1,)` or :math:`(C,)` (per channel) relative index of refraction.
        fresnel: ``"exact"``, ``"schlick"`` or ``"none"`` (see :func:`transmittance`).

    Returns:
        :math:`(B, C, H, W)` radiance, differentiable in ``radiosity`` and ``eta``.

    Examples:
        >>> b = torch.ones(1, 3, 2, 2); cos = torch.ones(1, 1, 2, 2)
        >>> round(exit_radiance(b, cos, 1.3)[0, 0, 0, 0].item() * math.pi, 4)
        0.983
        >>> exit_radiance(b, cos, torch.tensor([1.3, 1.4, 1.5])).shape
        torch.Size([1, 3, 2, 2])
    """
    if isinstance(eta, Tensor) and eta.dim() == 1 and eta.numel() > 1 and radiosity.dim() == 4:
        eta = eta.view(1, -1, 1, 1)
    return transmittance(cos_out, eta, fresnel) / math.pi * radiosity


def diffuse_fresnel_reflectance(eta: Tensor | float) -> Tensor:
    """Diffuse Fresnel reflectance :math:`F_{dr}(\\eta)`, the rational fits used by Jensen et al. 2001.

    .. math::
        F_{dr} = -1.440/\\eta^2 + 0.710/\\eta + 0.668 + 0.0636\\,\\eta \\quad (\\eta \\ge 1)

        F_{dr} = -0.4399 + 0.7099/\\eta - 0.3319/\\eta^2 + 0.0636/\\eta^3 \\quad (\\eta < 1)

    Shah (2007) eq. 6.12 prints the constant as 0.0668; that is a typo (Lensch Fig. 2 and Chang Table 1 print
    0.668, and only 0.668 gives F_dr ~ 0 at eta = 1).

    Args:
        eta: relative index of refraction (> 0), any shape.

    Returns:
        :math:`F_{dr}`, same shape.

    Examples:
        >>> round(diffuse_fresnel_reflectance(1.3).item(), 4)
        0.4448
    """
    eta_t = as_float_tensor(eta, "eta")
    check_positive(eta_t, "eta")
    out_dtype, work = compute_dtype(eta_t)
    e = eta_t.to(work)
    inv = 1.0 / e
    above = -1.440 * inv * inv + 0.710 * inv + 0.668 + 0.0636 * e
    below = -0.4399 + 0.7099 * inv - 0.3319 * inv * inv + 0.0636 * inv * inv * inv
    return torch.where(e >= 1.0, above, below).to(out_dtype)


def dipole_boundary_a(eta: Tensor | float) -> Tensor:
    """Boundary mismatch term :math:`A = (1 + F_{dr}) / (1 - F_{dr})` of the dipole model.

    Examples:
        >>> round(dipole_boundary_a(1.0).item(), 4)
        1.0032
    """
    fdr = diffuse_fresnel_reflectance(eta)
    return (1.0 + fdr) / (1.0 - fdr)
