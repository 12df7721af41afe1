"""Gaussian splatting of caustic photons into a light-view caustic map (Shah 2007, §5.3.3, §5.3.6).

Caustics mapping moves every vertex of the refractive grid to the receiver point its refracted ray reaches and
accumulates the light it carries there ("additive alpha blending"); point splats leave gaps, so Shah uses
"textured point primitives with a gaussian fall-off" (§5.3.6, Fig. 5.11). :func:`splat_caustics` does that on
tensors: each receiver hit point is projected into the caustic map (the light's view), and its flux is spread
over a fixed :math:`K \\times K` window of texels around the projected point with Gaussian weights

.. math:: w_k = \\frac{g_k}{\\sum_{j \\in \\text{image}} g_j}, \\qquad
          g_k = \\exp\\!\\Big(-\\frac{|u_k - u|^2}{2 \\sigma^2}\\Big),

:math:`u` the projected point and :math:`u_k` the texel centres (in pixels, centres at :math:`i + 0.5`). The
weights of one splat sum to exactly 1 over the texels *inside the map*, so every splat deposits exactly its flux
(energy conserving): a splat near the border loses no energy, its share that would fall outside is redistributed
over its texels inside (the map's border texels are slightly brighter than a larger map would show there, the
total is exact). A splat whose centre projects outside the map (beyond the frustum's sides, :math:`|x|` or
:math:`|y| > 1` in NDC) or behind the light (:math:`w \\le 0`) is dropped, like Shah's lost splats; so are
points marked invalid and non-finite points.

The window is fixed (:math:`K` a Python int, by default :math:`2 \\lceil 3 \\sigma \\rceil + 1`), so the op has
no data-dependent shapes: the weights are accumulated with ``scatter_add`` (the only accumulation that
onnxruntime reproduces exactly, see ONNX_NOTES.md) and the op exports to ONNX with the point count dynamic.
The Gaussian is truncated to the window (for :math:`K \\ge 2\\lceil 3\\sigma\\rceil + 1` the truncation drops
less than :math:`1.2 \\cdot 10^{-8}` of the unnormalised mass, which the normalisation then redistributes).

Channels: ``flux`` carries :math:`C` channels. ``points`` is either shared by all channels :math:`(B, N, 3)` or
given per channel :math:`(B, N, C, 3)` (dispersion: each wavelength refracts to its own point); ``valid``
follows (:math:`(B, N)` or :math:`(B, N, C)`).
"""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from torchsss._checks import check_shape, check_tensor, compute_dtype, is_tracing

__all__ = ["default_kernel_size", "splat_caustics"]


def default_kernel_size(sigma_px: float) -> int:
    """The default window :math:`K = 2 \\lceil 3 \\sigma \\rceil + 1` texels for a Gaussian of ``sigma_px`` texels.

    Examples:
        >>> default_kernel_size(1.0), default_kernel_size(0.3)
        (7, 3)
    """
    _check_sigma(sigma_px)
    return 2 * math.ceil(3.0 * float(sigma_px)) + 1


def _check_sigma(sigma_px: object) -> None:
    if isinstance(sigma_px, bool) or not isinstance(sigma_px, numbers.Real):
        raise TypeError(f"sigma_px: expected a real number > 0, got {type(sigma_px).__name__}")
    if not (0.0 < float(sigma_px) < float("inf")):
        raise ValueError(f"sigma_px: expected a finite number > 0, got {sigma_px!r}")


def _check_size(size: object) -> tuple:
    if not isinstance(size, (tuple, list, torch.Size)) or len(size) != 2:
        raise TypeError(f"size: expected a (H, W) pair of ints, got {size!r}")
    if is_tracing():
        return tuple(size)
    for v in size:
        if isinstance(v, bool) or not isinstance(v, (numbers.Integral, torch.SymInt)):
            raise TypeError(f"size: expected a (H, W) pair of ints, got {size!r}")
        if int(v) < 1:
            raise ValueError(f"size: expected a (H, W) pair of ints >= 1, got {tuple(size)}")
    return tuple(size)


def _check_inputs(points: object, flux: object, valid: object, view_proj: object) -> bool:
    """Validate; return True when the points are given per channel (B, N, C, 3)."""
    check_tensor(points, "points")
    check_tensor(flux, "flux")
    check_tensor(view_proj, "view_proj")
    if not isinstance(valid, Tensor):
        raise TypeError(f"valid: expected a bool torch.Tensor, got {type(valid).__name__}")
    if valid.dtype != torch.bool:
        raise TypeError(f"valid: expected a bool tensor, got dtype {valid.dtype}")
    per_channel = points.dim() == 4
    for x, name in ((flux, "flux"), (valid, "valid"), (view_proj, "view_proj")):
        if x.device != points.device:
            raise ValueError(f"{name}: expected a tensor on points' device {points.device}, got {x.device}")
    if is_tracing():
        return per_channel
    if points.dim() not in (3, 4) or points.shape[-1] != 3:
        raise ValueError(f"points: expected shape (B, N, 3) or (B, N, C, 3), got {tuple(points.shape)}")
    dims = check_shape(flux, "flux", "B,N,C", B=points.shape[0], N=points.shape[1])
    if per_channel:
        check_shape(points, "points", "B,N,C,3", **dims)
        check_shape(valid, "valid", "B,N,C", **dims)
    else:
        check_shape(valid, "valid", "B,N", B=dims["B"], N=dims["N"])
    check_shape(view_proj, "view_proj", "B,4,4", B=dims["B"])
    if not bool(torch.isfinite(view_proj).all()):
        raise ValueError("view_proj: expected finite values, got a non-finite entry")
    return per_channel


def splat_caustics(
    points: Tensor,
    flux: Tensor,
    valid: Tensor,
    view_proj: Tensor,
    size: tuple[int, int],
    sigma_px: float = 1.0,
    kernel_size: int | None = None,
) -> Tensor:
    """Accumulate energy-conserving Gaussian splats of caustic flux into a light-view map (see the module docstring).

    Args:
        points: :math:`(B, N, 3)` receiver hit points in world space (mm), or :math:`(B, N, C, 3)` one point per
            channel (dispersion).
        flux: :math:`(B, N, C)` flux carried by each point (any unit; the map holds the same unit per texel).
        valid: :math:`(B, N)` (or :math:`(B, N, C)` with per-channel points) bool; False drops the splat.
        view_proj: :math:`(B, 4, 4)` world-to-clip matrix of the caustic map (the light's view; NDC y up, texture
            row 0 at the top).
        size: ``(H, W)`` of the caustic map.
        sigma_px: standard deviation of the Gaussian in texels (> 0).
        kernel_size: the fixed window :math:`K` (odd or even, >= 1); default :func:`default_kernel_size`.

    Returns:
        :math:`(B, C, H, W)` flux per texel, in the promoted dtype of ``points``, ``flux`` and ``view_proj``.
        Its sum over the texels is the sum of the flux of the splats kept (exactly, up to rounding).

    Raises:
        TypeError: non-tensor inputs, non-floating ``points``/``flux``/``view_proj``, a non-bool ``valid``, a bad
            ``size``, ``sigma_px`` or ``kernel_size`` type.
        ValueError: wrong shapes, different devices, non-finite ``view_proj``, ``sigma_px <= 0``, ``kernel_size``
            or sizes < 1.

    Examples:
        >>> vp = torch.eye(4)[None]  # the map spans [-1, 1]^2 in x and y
        >>> m = splat_caustics(torch.zeros(1, 1, 3), torch.ones(1, 1, 1), torch.ones(1, 1, dtype=torch.bool),
        ...                    vp, (4, 4), sigma_px=0.5, kernel_size=2)
        >>> m[0, 0].tolist()  # the centre of the map, between four texels: a quarter each
        [[0.0, 0.0, 0.0, 0.0], [0.0, 0.25, 0.25, 0.0], [0.0, 0.25, 0.25, 0.0], [0.0, 0.0, 0.0, 0.0]]
    """
    per_channel = _check_inputs(points, flux, valid, view_proj)
    _check_sigma(sigma_px)
    h, w = _check_size(size)
    if kernel_size is None:
        kernel_size = default_kernel_size(sigma_px)
    if isinstance(kernel_size, bool) or not isinstance(kernel_size, numbers.Integral):
        raise TypeError(f"kernel_size: expected an int >= 1 or None, got {type(kernel_size).__name__}")
    if kernel_size < 1:
        raise ValueError(f"kernel_size: expected an int >= 1 or None, got {kernel_size}")
    k = int(kernel_size)
    out_dtype, work = compute_dtype(points, flux, view_proj)
    b = flux.shape[0]
    c = flux.shape[2]

    pts = points.to(work)
    if not per_channel:
        pts = pts.unsqueeze(2)  # (B, N, 1, 3)
        valid = valid.unsqueeze(2)
    mat = view_proj.to(work)
    # clip = M [x, 1]^T for every point (B, N, c', 4)
    clip = torch.einsum("bnci,bji->bncj", pts, mat[:, :, :3]) + mat[:, None, None, :, 3]
    cw = clip[..., 3]
    front = cw > 0
    safe_w = torch.where(front, cw, torch.ones_like(cw))
    ndc_x = clip[..., 0] / safe_w
    ndc_y = clip[..., 1] / safe_w
    inside = front & (ndc_x.abs() <= 1.0) & (ndc_y.abs() <= 1.0) & valid
    ndc_x = torch.where(inside, ndc_x, torch.zeros_like(ndc_x))
    ndc_y = torch.where(inside, ndc_y, torch.zeros_like(ndc_y))
    # continuous pixel coordinates with texel centres at integers (column from the left, row from the top)
    u = (ndc_x + 1.0) * (0.5 * w) - 0.5
    v = (1.0 - ndc_y) * (0.5 * h) - 0.5
    shift = 1.0 - 0.5 * k
    u0 = torch.floor(u + shift).detach()
    v0 = torch.floor(v + shift).detach()

    offs = torch.arange(k, device=pts.device, dtype=work)
    cols = u0[..., None, None] + offs[None, :]  # (B, N, c', 1, K)
    rows = v0[..., None, None] + offs[:, None]  # (B, N, c', K, 1)
    inside_tap = (cols >= 0) & (cols <= w - 1) & (rows >= 0) & (rows <= h - 1)  # (B, N, c', K, K)
    d2 = (cols - u[..., None, None]) ** 2 + (rows - v[..., None, None]) ** 2
    # relative to the nearest tap in the map (within 0.5 sqrt(2) px of the centre), so the largest weight is 1
    # and tiny sigmas cannot underflow every tap
    big = torch.full_like(d2, float("inf"))
    d2_min = torch.where(inside_tap, d2, big).amin(dim=(-2, -1), keepdim=True)
    d2_min = torch.where(torch.isfinite(d2_min), d2_min, torch.zeros_like(d2_min))
    g = torch.exp(-(d2 - d2_min).clamp_min(0.0) / (2.0 * float(sigma_px) ** 2))
    g = torch.where(inside_tap, g, torch.zeros_like(g))
    total = g.sum(dim=(-2, -1), keepdim=True)
    weight = g / torch.where(total > 0, total, torch.ones_like(total))
    weight = torch.where(inside[..., None, None], weight, torch.zeros_like(weight))

    index = (rows.clamp(0, h - 1) * w + cols.clamp(0, w - 1)).to(torch.int64)  # (B, N, c', K, K)
    f = torch.where(torch.isfinite(flux), flux, torch.zeros_like(flux)).to(work)  # (B, N, C); non-finite -> 0
    contrib = weight * f[..., None, None]  # (B, N, C, K, K)
    contrib = contrib.permute(0, 2, 1, 3, 4).reshape(b, c, -1)
    index = index.permute(0, 2, 1, 3, 4).reshape(b, index.shape[2], -1).expand(b, c, -1)
    out = torch.zeros(b, c, h * w, dtype=work, device=pts.device)
    out = out.scatter_add(2, index, contrib)
    return out.reshape(b, c, h, w).to(out_dtype)
