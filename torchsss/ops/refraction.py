"""Specular refraction and reflection of direction vectors (vector Snell's law), as caustics mapping needs them.

Conventions shared by :func:`refract` and :func:`reflect`:

* ``incident`` is the direction the light *travels*: it points *toward* the surface (a light straight above a
  horizontal surface gives ``incident = (0, 0, -1)``). Neither ``incident`` nor ``normal`` needs unit length;
  both are normalised, and the returned directions have unit length.
* ``normal`` may face either side of the surface: :func:`refract` flips it to face the incoming light
  (:math:`n \\cdot i \\le 0`), so the same call refracts a ray entering or leaving an object; only ``eta``
  says which side the light comes from. :func:`reflect` does not depend on the normal's sign.
* ``eta`` is :math:`n_1 / n_2`, the index of refraction on the *incident* side over the index on the
  *transmitted* side: light entering water from air has ``eta = 1 / 1.33``, light leaving glass into air
  ``eta = 1.5``. (This is the reciprocal of the material-over-outside ``eta`` of :mod:`torchsss.physics.fresnel`
  for light entering a material.)
* Any non-zero length works, from subnormal to near the float maximum: vectors are divided by their largest
  absolute component before the norm is taken, so :math:`|v|^2` neither underflows to 0 nor overflows to inf.
* Zero-length ``incident`` or ``normal`` vectors have no direction: they give the zero direction (never NaN)
  with ``tir`` False, which no real result has (a refracted direction has unit length, a TIR one is flagged),
  so ``~tir & (direction == 0).all(-1)`` finds them. Non-finite vectors give NaN directions.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsss._checks import as_float_tensor, cast, check_positive, check_tensor, compute_dtype

__all__ = ["reflect", "refract"]


def _check_vectors(x: object, name: str) -> Tensor:
    check_tensor(x, name)
    if x.dim() < 1 or x.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (..., 3), got {tuple(x.shape)}")
    return x


def _normalize(v: Tensor) -> tuple[Tensor, Tensor]:
    """Unit vectors along ``v`` (zero where ``|v| = 0``, with finite gradients) and the mask of zero vectors.

    Scale-safe: ``v`` is first divided by its largest absolute component, so the squared norm lies in [1, 3] for
    every non-zero finite vector (``(v * v).sum()`` underflows to 0 for components near 1e-20 in float32 and
    overflows to inf near 1e20).
    """
    m = v.abs().amax(-1, keepdim=True)
    zero = m == 0
    s = v / torch.where(zero, torch.ones_like(m), m)
    n2 = (s * s).sum(-1, keepdim=True)
    return s / torch.sqrt(torch.where(zero, torch.ones_like(n2), n2)), zero[..., 0]


def refract(incident: Tensor, normal: Tensor, eta: Tensor | float) -> tuple[Tensor, Tensor]:
    """Refract directions at a smooth interface: vector Snell's law :math:`n_1 \\sin\\theta_1 = n_2 \\sin\\theta_2`.

    With unit :math:`i` (toward the surface), unit :math:`n` flipped to face the light (:math:`c = -n \\cdot i
    \\ge 0`) and :math:`\\eta = n_1/n_2`:

    .. math:: k = 1 - \\eta^2 (1 - c^2), \\qquad t = \\eta\\, i + (\\eta c - \\sqrt{k})\\, n

    (normalised once more against rounding). Where :math:`k \\le 0` (incidence at or beyond the critical angle
    :math:`\\arcsin(1/\\eta)`, only possible for :math:`\\eta > 1`, and grazing incidence at :math:`\\eta = 1`)
    the light is totally internally reflected: ``direction`` is the zero vector and ``tir`` is True, as
    :func:`torchsss.physics.fresnel.fresnel_reflectance` returns 1 there. At the critical angle itself the
    transmitted ray would run along the surface and carry no energy, so it counts as TIR.

    Per-channel indices (dispersion, Shah Fig. 5.13): ``eta`` broadcasts against the *leading* dimensions of
    ``incident`` and ``normal`` (everything but the last axis). Give the vectors a channel axis before the
    vector axis, e.g. ``incident[..., None, :]`` with ``eta`` of shape :math:`(C,)`, to get :math:`(..., C, 3)`
    directions.

    Differentiable with respect to ``incident``, ``normal`` and ``eta`` (the square root is only taken of
    :math:`k > 0`, so TIR entries get zero gradients, never NaN). Exports to ONNX (elementwise ops only).

    Args:
        incident: :math:`(..., 3)` directions of travel, pointing toward the surface (any non-zero length).
        normal: :math:`(..., 3)` surface normals, either orientation, any non-zero length, broadcastable with
            ``incident``.
        eta: :math:`n_1 / n_2` (> 0), a number or a tensor broadcastable with the leading dimensions.

    Returns:
        ``(direction, tir)``: :math:`(..., 3)` unit refracted directions in the promoted dtype of the inputs, and
        the :math:`(...)` bool mask of total internal reflection. ``direction`` is the zero vector where ``tir``
        is True and where ``incident`` or ``normal`` has zero length (``tir`` False there: no direction to
        refract).

    Raises:
        TypeError: a non-tensor or non-floating ``incident``/``normal``, or an ``eta`` that is not a number or
            floating tensor.
        ValueError: a last dimension other than 3, shapes that do not broadcast, or ``eta <= 0`` / non-finite.

    Examples:
        >>> s = 0.5  # 30 degrees from the normal, from air (1.0) into glass (1.5)
        >>> i = torch.tensor([s, 0.0, -(1 - s * s) ** 0.5], dtype=torch.float64)
        >>> t, tir = refract(i, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 1.0 / 1.5)
        >>> round(t[0].item(), 6), tir.item()  # sin(theta_t) = sin(theta_i) / 1.5
        (0.333333, False)
        >>> refract(i, torch.tensor([0.0, 0.0, 1.0]), 2.5)[1].item()  # glass to air beyond the critical angle
        True
        >>> rgb = refract(i[None, :], torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.74, 0.75, 0.76]))[0]
        >>> tuple(rgb.shape)  # one direction per channel
        (3, 3)
        >>> round(refract(i.float() * 1e-30, torch.tensor([0.0, 0.0, 1e30]), 1.0 / 1.5)[0][0].item(), 6)  # any length
        0.333333
        >>> refract(torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]), 1.0 / 1.5)  # no direction: zero, not TIR
        (tensor([0., 0., 0.]), tensor(False))
    """
    _check_vectors(incident, "incident")
    _check_vectors(normal, "normal")
    eta_t = as_float_tensor(eta, "eta", like=incident)
    lead = (tuple(incident.shape[:-1]), tuple(normal.shape[:-1]))
    try:
        torch.broadcast_shapes(*lead, eta_t.shape)
    except RuntimeError as err:
        raise ValueError(
            f"incident, normal, eta: expected leading shapes that broadcast, got incident {lead[0]} "
            f"(+3), normal {lead[1]} (+3), eta {tuple(eta_t.shape)}"
        ) from err
    check_positive(eta_t, "eta")
    out_dtype, work = compute_dtype(incident, normal, eta_t)
    i, zero_i = _normalize(cast(incident, work))
    n, zero_n = _normalize(cast(normal, work))
    e = cast(eta_t, work)
    cos_i = -(i * n).sum(-1)
    flip = cos_i < 0
    n = torch.where(flip[..., None], -n, n)
    cos_i = torch.where(flip, -cos_i, cos_i)
    sin2_i = (1.0 - cos_i * cos_i).clamp_min(0.0)
    k = 1.0 - e * e * sin2_i
    degenerate = zero_i | zero_n
    tir = (k <= 0) & ~degenerate
    sqrt_k = torch.sqrt(torch.where(k > 0, k, 1.0))
    t = e[..., None] * i + (e * cos_i - sqrt_k)[..., None] * n
    t, _ = _normalize(t)
    t = torch.where((tir | degenerate)[..., None], torch.zeros_like(t), t)
    return cast(t, out_dtype), tir


def reflect(incident: Tensor, normal: Tensor) -> Tensor:
    """Mirror directions about the surface normal: :math:`r = i - 2 (n \\cdot i)\\, n` (unit :math:`i, n`).

    The result does not depend on the normal's orientation. A direction travelling toward the surface
    (:math:`n \\cdot i < 0` for an outward :math:`n`) leaves it (:math:`n \\cdot r = -n \\cdot i`); the tangential
    part is kept. Differentiable; exports to ONNX.

    Args:
        incident: :math:`(..., 3)` directions of travel, pointing toward the surface (any non-zero length).
        normal: :math:`(..., 3)` surface normals (either orientation, any non-zero length), broadcastable with
            ``incident``.

    Returns:
        :math:`(..., 3)` unit reflected directions (zero where an input has zero length), promoted dtype.

    Raises:
        TypeError: a non-tensor or non-floating input.
        ValueError: a last dimension other than 3, or shapes that do not broadcast.

    Examples:
        >>> reflect(torch.tensor([1.0, 0.0, -1.0]), torch.tensor([0.0, 0.0, 2.0])) * 2**0.5
        tensor([1.0000, 0.0000, 1.0000])
    """
    _check_vectors(incident, "incident")
    _check_vectors(normal, "normal")
    try:
        torch.broadcast_shapes(incident.shape, normal.shape)
    except RuntimeError as err:
        raise ValueError(
            f"incident, normal: expected shapes that broadcast, got incident {tuple(incident.shape)}, "
            f"normal {tuple(normal.shape)}"
        ) from err
    out_dtype, work = compute_dtype(incident, normal)
    i, zero_i = _normalize(cast(incident, work))
    n, zero_n = _normalize(cast(normal, work))
    r = i - 2.0 * (n * i).sum(-1, keepdim=True) * n
    r, _ = _normalize(r)
    r = torch.where((zero_i | zero_n)[..., None], torch.zeros_like(r), r)
    return cast(r, out_dtype)
