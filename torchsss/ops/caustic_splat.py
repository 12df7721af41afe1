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

from torchsss._checks import cast, check_shape, check_tensor, compute_dtype, is_tracing

__all__ = ["default_kernel_size", "splat_caustic_beams", "splat_caustics"]


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

    pts = cast(points, work)
    if not per_channel:
        pts = pts.unsqueeze(2)  # (B, N, 1, 3)
        valid = valid.unsqueeze(2)
    mat = cast(view_proj, work)
    # clip = M [x, 1]^T for every point (B, N, c', 4)
    clip = torch.einsum("bnci,bji->bncj", pts, mat[:, :, :3]) + mat[:, None, None, :, 3]
    cw = clip[..., 3]
    front = cw > 0
    safe_w = torch.where(front, cw, 1.0)
    ndc_x = clip[..., 0] / safe_w
    ndc_y = clip[..., 1] / safe_w
    inside = front & (ndc_x.abs() <= 1.0) & (ndc_y.abs() <= 1.0) & valid
    ndc_x = torch.where(inside, ndc_x, 0.0)
    ndc_y = torch.where(inside, ndc_y, 0.0)
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
    d2_min = torch.where(torch.isfinite(d2_min), d2_min, 0.0)
    g = torch.exp(-(d2 - d2_min).clamp_min(0.0) / (2.0 * float(sigma_px) ** 2))
    g = torch.where(inside_tap, g, 0.0)
    total = g.sum(dim=(-2, -1), keepdim=True)
    weight = g / torch.where(total > 0, total, 1.0)
    weight = torch.where(inside[..., None, None], weight, 0.0)

    index = (rows.clamp(0, h - 1) * w + cols.clamp(0, w - 1)).to(torch.int64)  # (B, N, c', K, K)
    f = cast(torch.where(torch.isfinite(flux), flux, 0.0), work)  # (B, N, C); non-finite -> 0
    contrib = weight * f[..., None, None]  # (B, N, C, K, K)
    contrib = contrib.permute(0, 2, 1, 3, 4).reshape(b, c, -1)
    index = index.permute(0, 2, 1, 3, 4).reshape(b, index.shape[2], -1).expand(b, c, -1)
    out = torch.zeros(b, c, h * w, dtype=work, device=pts.device)
    out = out.scatter_add(2, index, contrib)
    return out.reshape(b, c, h, w).to(out_dtype)


# -- beam splats: flux spread over the receiver footprint of each grid texel -----------------------------------------
def _beam_inputs(points: object, flux: object, valid: object, view_proj: object, subdivisions: object,
                 taps: object, max_stretch_px: object) -> None:
    check_tensor(points, "points")
    check_tensor(flux, "flux")
    check_tensor(view_proj, "view_proj")
    if not isinstance(valid, Tensor):
        raise TypeError(f"valid: expected a bool torch.Tensor, got {type(valid).__name__}")
    if valid.dtype != torch.bool:
        raise TypeError(f"valid: expected a bool tensor, got dtype {valid.dtype}")
    for x, name in ((flux, "flux"), (valid, "valid"), (view_proj, "view_proj")):
        if x.device != points.device:
            raise ValueError(f"{name}: expected a tensor on points' device {points.device}, got {x.device}")
    for name, value, lo in (("subdivisions", subdivisions, 1), ("taps", taps, 2)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise TypeError(f"{name}: expected an int >= {lo}, got {type(value).__name__}")
        if value < lo:
            raise ValueError(f"{name}: expected an int >= {lo}, got {value}")
    if isinstance(max_stretch_px, bool) or not isinstance(max_stretch_px, numbers.Real):
        raise TypeError(f"max_stretch_px: expected a real number > 0, got {type(max_stretch_px).__name__}")
    if not (0.0 < float(max_stretch_px) < float("inf")):
        raise ValueError(f"max_stretch_px: expected a finite number > 0, got {max_stretch_px!r}")
    if is_tracing():
        return
    dims = check_shape(points, "points", "B,Hg,Wg,C,3")
    check_shape(flux, "flux", "B,Hg,Wg,C", **dims)
    check_shape(valid, "valid", "B,Hg,Wg,C", **dims)
    check_shape(view_proj, "view_proj", "B,4,4", B=dims["B"])
    if not bool(torch.isfinite(view_proj).all()):
        raise ValueError("view_proj: expected finite values, got a non-finite entry")


def _box_weights(c: Tensor, a: Tensor, first: Tensor, taps: int) -> tuple[Tensor, Tensor]:
    """Overlap of the box [c - a/2, c + a/2] with the texels first .. first + taps - 1 (centres at integers), / a."""
    idx = first[..., None] + torch.arange(taps, dtype=c.dtype, device=c.device)
    lo = torch.maximum((c - 0.5 * a)[..., None], idx - 0.5)
    hi = torch.minimum((c + 0.5 * a)[..., None], idx + 0.5)
    return (hi - lo).clamp_min(0.0) / a[..., None], idx


def splat_caustic_beams(
    points: Tensor,
    flux: Tensor,
    valid: Tensor,
    view_proj: Tensor,
    size: tuple[int, int],
    subdivisions: int = 4,
    taps: int = 3,
    max_stretch_px: float = 32.0,
    coverage: Tensor | None = None,
) -> Tensor:
    """Deposit the flux of every refractive-grid texel over its beam's footprint on the receiver (energy conserving).

    A grid point stands for the square texel around it, a pencil of parallel (or nearly parallel) rays; its
    neighbours' hit points give the footprint of that pencil on the receiver. The texel is cut into its four
    quadrants, each mapped bilinearly onto the grid cell it belongs to (the point, its two axis neighbours and the
    diagonal one: the piecewise-bilinear interpolation of the grid's hit points, so the footprints of neighbouring
    texels tile the receiver without gaps or overlaps). Each texel is sampled at ``subdivisions`` x ``subdivisions``
    stratified sub-points, each carrying ``flux / subdivisions^2``; a sub-point deposits its flux over an
    axis-aligned box of the size of its own sub-footprint (widths :math:`a_u = |J_{u\\cdot}| / s`, :math:`a_v =
    |J_{v\\cdot}| / s` from the local Jacobian :math:`J` in map texels per grid texel), with weights equal to the
    box's overlap with each map texel. For an axis-aligned magnification that is exactly the binned (box-filtered)
    irradiance of the interpolated beams; a tiny footprint (a focus) lands in the texel that contains it, not
    blurred. Boxes wider than ``taps - 1`` texels are clamped to it (a strongly spreading beam is then sampled
    by its sub-points only).

    Neighbours: a difference is used when both points are valid and their hit points lie within ``max_stretch_px``
    map texels of each other (farther apart means a discontinuity: another surface, a silhouette); otherwise the
    opposite side's difference is used, or none (a point deposit) when both are unusable. So texels at the
    refractor's rim keep their flux. Every sub-point whose centre projects inside the map deposits exactly its
    flux (weights renormalised over the taps inside the map, as :func:`splat_caustics`); one outside (or behind
    the light) is dropped.

    Args:
        points: :math:`(B, H_g, W_g, C, 3)` receiver hit point of each grid texel and channel (mm).
        flux: :math:`(B, H_g, W_g, C)` flux carried by each grid texel.
        valid: :math:`(B, H_g, W_g, C)` bool, False where the ray was lost (no flux, no neighbour).
        view_proj: :math:`(B, 4, 4)` world-to-clip matrix of the caustic map.
        size: ``(H, W)`` of the caustic map.
        subdivisions: sub-points per grid texel and axis (>= 1).
        taps: box window per axis and sub-point (>= 2): widths are clamped to ``taps - 1`` texels.
        max_stretch_px: largest distance (map texels) between neighbouring hit points still taken as one beam.
        coverage: optional :math:`(B, 1, H, W)` bool, the map texels that hold a receiver: a sub-point's box
            deposits on those only (renormalised over them), so a beam at a receiver's edge stays on it.

    Returns:
        :math:`(B, C, H, W)` flux per texel in the promoted dtype; its sum is the flux of the sub-points kept.

    Raises:
        TypeError: non-tensor or non-floating inputs, a non-bool ``valid``, bad option types.
        ValueError: wrong shapes, different devices, non-finite ``view_proj``, options out of range.

    Examples:
        >>> g = torch.linspace(-0.75, 0.75, 4)  # a 4 x 4 grid landing on a 4 x 4 map of the NDC square
        >>> y, x = torch.meshgrid(-g, g, indexing="ij")
        >>> pts = torch.stack([x, y, torch.zeros_like(x)], -1)[None, :, :, None, :]
        >>> m = splat_caustic_beams(pts, torch.ones(1, 4, 4, 1), torch.ones(1, 4, 4, 1, dtype=torch.bool),
        ...                         torch.eye(4)[None], (4, 4))
        >>> m[0, 0].tolist() == torch.ones(4, 4).tolist()  # a uniform beam: one texel of flux per texel
        True
    """
    _beam_inputs(points, flux, valid, view_proj, subdivisions, taps, max_stretch_px)
    h, w = _check_size(size)
    s, t = int(subdivisions), int(taps)
    out_dtype, work = compute_dtype(points, flux, view_proj)
    b, c = flux.shape[0], flux.shape[3]
    mat = cast(view_proj, work)
    clip = torch.einsum("bijcx,bkx->bijck", cast(points, work), mat[:, :, :3]) + mat[:, None, None, None, :, 3]
    cw = clip[..., 3]
    front = cw > 0
    safe_w = torch.where(front, cw, 1.0)
    ndc_x, ndc_y = clip[..., 0] / safe_w, clip[..., 1] / safe_w
    uv = torch.stack([(ndc_x + 1.0) * (0.5 * w) - 0.5, (1.0 - ndc_y) * (0.5 * h) - 0.5], -1)  # (B, Hg, Wg, C, 2)
    ok = valid & front & torch.isfinite(uv).all(-1)
    uv = torch.where(ok[..., None], uv, 0.0)
    f = torch.where(ok & torch.isfinite(flux), cast(flux, work), 0.0)
    limit2 = float(max_stretch_px) ** 2
    hg, wg = uv.shape[1], uv.shape[2]

    # the 3 x 3 neighbourhood of every grid point, (3 [dy], 3 [dx], B, Hg, Wg, C, 3): (u, v, valid), zero and invalid
    # outside the grid (a handful of graph nodes for any grid size)
    val = torch.cat([uv, ok[..., None].to(work)], -1)
    pad = torch.zeros_like(val.narrow(1, 0, 1))
    val = torch.cat([pad, val, pad], 1)
    pad = torch.zeros_like(val.narrow(2, 0, 1))
    val = torch.cat([pad, val, pad], 2)  # (B, Hg + 2, Wg + 2, C, 3)
    cols = torch.stack([val.narrow(2, k, wg) for k in range(3)])
    hood = torch.stack([cols.narrow(2, k, hg) for k in range(3)])
    # index 0 / 1 of a side axis: the step +1 / -1 (the neighbour at position 2 / 0 of the neighbourhood)
    side_index = torch.tensor([2, 0], device=uv.device)
    sign = torch.tensor([1.0, -1.0], dtype=work, device=uv.device).view(2, 1, 1, 1, 1, 1)
    nb_x = hood[1].index_select(0, side_index)  # (2 [sx], B, Hg, Wg, C, 3)
    nb_y = hood.index_select(0, side_index)[:, 1]  # (2 [sy], ...)
    diag = hood.index_select(0, side_index).index_select(1, side_index).transpose(0, 1)  # (2 [sx], 2 [sy], ...)

    def sides(nb: Tensor) -> tuple[Tensor, Tensor]:
        """Slopes (texels per grid texel) for both sides of one axis, and where the side's own neighbour serves."""
        d = (nb[..., :2] - uv) * sign
        nat = ok & (nb[..., 2] > 0.5) & ((d * d).sum(-1) <= limit2)
        # a quadrant takes its own side's difference, else the opposite side's, else none (a point deposit)
        jac = torch.where(nat[..., None], d, torch.where(nat.flip(0)[..., None], d.flip(0), torch.zeros_like(d)))
        return jac, nat

    jx, nat_x = sides(nb_x)
    jy, nat_y = sides(nb_y)
    # the diagonal neighbour gives the bilinear (twist) term of the quadrant's grid cell; it exists only inside the
    # grid (rows/cols at the edge already fail nat_x / nat_y)
    twist = diag[..., :2] - nb_x[:, None, ..., :2] - nb_y[None, ..., :2] + uv
    twist = twist * (sign * sign.view(1, 2, 1, 1, 1, 1))[..., None]
    use_t = nat_x[:, None] & nat_y[None] & (diag[..., 2] > 0.5) & ((twist * twist).sum(-1) <= limit2)
    twist = torch.where(use_t[..., None], twist, 0.0)
    # per quadrant q = 2 i_x + i_y (i = 0 on the + side): (4, B, Hg, Wg, C, 2)
    quad_x = jx[:, None].expand(2, 2, *uv.shape).reshape(4, *uv.shape)
    quad_y = jy[None].expand(2, 2, *uv.shape).reshape(4, *uv.shape)
    quad_t = twist.reshape(4, *uv.shape)

    bidx = torch.arange(b, device=uv.device).view(b, 1, 1).expand(b, hg, wg).reshape(-1)
    uv_p, f_p, ok_p = (x.reshape(-1, *x.shape[3:]) for x in (uv, f, ok))
    quad_x, quad_y, quad_t = (x.reshape(4, -1, c, 2) for x in (quad_x, quad_y, quad_t))
    if not is_tracing():
        # eager: only the grid points that carry flux (the shapes are data-dependent; tracing keeps them all)
        idx = ok.any(-1).reshape(-1).nonzero()[:, 0]
        bidx, uv_p, f_p, ok_p = (x.index_select(0, idx) for x in (bidx, uv_p, f_p, ok_p))
        quad_x, quad_y, quad_t = (x.index_select(1, idx) for x in (quad_x, quad_y, quad_t))

    out = torch.zeros(b, c, h * w, dtype=work, device=uv.device)
    if coverage is not None:
        if not isinstance(coverage, Tensor):
            raise TypeError(f"coverage: expected a bool torch.Tensor or None, got {type(coverage).__name__}")
        if not is_tracing():
            check_shape(coverage, "coverage", f"{b},1,{h},{w}")
        cover = (coverage != 0).to(work).reshape(b, h * w)
        cover = cover[:, None, :].expand(b, c, h * w).reshape(-1)
    sub_f = f_p / float(s * s)  # (P, C)
    chan = torch.arange(c, device=uv.device).view(1, c)
    base = (bidx.view(-1, 1) * c + chan) * (h * w)  # (P, C) offset of each (batch, channel) plane
    # the s x s sub-points, each in the quadrant its offset points into (an offset of 0, the middle row or column of
    # an odd s, goes to the + side)
    offsets = [(k + 0.5) / s - 0.5 for k in range(s)]
    subpoints = [(2 * (ox < 0) + (oy < 0), ox, oy) for ox in offsets for oy in offsets]
    # (K, P, C, 2) rows, one per sub-point: eager takes a quadrant at a time (bounding the (K, P, C, taps, taps)
    # temporaries); a traced graph takes all of them in one pass (one body in the graph)
    chunks = [subpoints] if is_tracing() else [[p for p in subpoints if p[0] == q] for q in range(4)]
    groups = []
    for chunk in chunks:
        if chunk:
            rows = torch.tensor([p[0] for p in chunk], device=uv.device)
            groups.append((*(x.index_select(0, rows) for x in (quad_x, quad_y, quad_t)), [p[1:] for p in chunk]))
    for jx, jy, twist, sub in groups:
        off = torch.tensor(sub, dtype=work, device=uv.device).view(-1, 1, 1, 2)
        ox, oy = off[..., :1], off[..., 1:]
        # the quadrant's Jacobian (map texels per grid texel) and its sub-footprint box: widths along u and v
        a = (torch.sqrt(jx * jx + jy * jy) / s).clamp(1e-6, float(t - 1))
        pos = uv_p + ox * jx + oy * jy + (ox * oy) * twist
        inside = ok_p & (pos[..., 0] >= -0.5) & (pos[..., 0] <= w - 0.5) & (pos[..., 1] >= -0.5) & (
            pos[..., 1] <= h - 0.5)
        first = torch.floor(pos - 0.5 * a + 0.5).detach()
        wu, iu = _box_weights(pos[..., 0], a[..., 0], first[..., 0], t)  # (K, P, C, T)
        wv, iv = _box_weights(pos[..., 1], a[..., 1], first[..., 1], t)
        wu = torch.where((iu >= 0) & (iu <= w - 1), wu, 0.0)
        wv = torch.where((iv >= 0) & (iv <= h - 1), wv, 0.0)
        wgt = wv[..., :, None] * wu[..., None, :]  # (K, P, C, T, T)
        index = (iv.clamp(0, h - 1)[..., :, None] * w + iu.clamp(0, w - 1)[..., None, :]).to(torch.int64)
        index = index + base[..., None, None]
        if coverage is not None:
            wgt = wgt * cover[index]
        tot = wgt.sum((-2, -1), keepdim=True)
        wgt = wgt / torch.where(tot > 0, tot, 1.0)
        wgt = wgt * (inside & (tot[..., 0, 0] > 0))[..., None, None]
        out = out.view(-1).scatter_add(0, index.reshape(-1), (wgt * sub_f[..., None, None]).reshape(-1))
    return out.reshape(b, c, h, w).to(out_dtype)
