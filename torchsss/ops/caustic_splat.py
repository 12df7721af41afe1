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


def _shift(x: Tensor, axis: int, step: int) -> Tensor:
    """``x`` moved by ``step`` (+1 / -1) along ``axis``: out[i] = x[i + step], edge-replicated (masked later)."""
    n = x.shape[axis]
    if step > 0:
        return torch.cat([x.narrow(axis, 1, n - 1), x.narrow(axis, n - 1, 1)], axis)
    return torch.cat([x.narrow(axis, 0, 1), x.narrow(axis, 0, n - 1)], axis)


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
    mat = view_proj.to(work)
    clip = torch.einsum("bijcx,bkx->bijck", points.to(work), mat[:, :, :3]) + mat[:, None, None, None, :, 3]
    cw = clip[..., 3]
    front = cw > 0
    safe_w = torch.where(front, cw, torch.ones_like(cw))
    ndc_x, ndc_y = clip[..., 0] / safe_w, clip[..., 1] / safe_w
    uv = torch.stack([(ndc_x + 1.0) * (0.5 * w) - 0.5, (1.0 - ndc_y) * (0.5 * h) - 0.5], -1)  # (B, Hg, Wg, C, 2)
    ok = valid & front & torch.isfinite(uv).all(-1)
    uv = torch.where(ok[..., None], uv, torch.zeros_like(uv))
    f = torch.where(ok & torch.isfinite(flux), flux.to(work), torch.zeros_like(flux, dtype=work))
    limit2 = float(max_stretch_px) ** 2

    def side(axis: int, step: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        nb = _shift(uv, axis, step)
        nb_ok = _shift(ok, axis, step)
        n = uv.shape[axis]
        edge = torch.arange(n, device=uv.device) == (n - 1 if step > 0 else 0)
        edge = edge.view([-1 if d == axis else 1 for d in range(ok.dim())])
        d = (nb - uv) * step  # forward slope (texels per grid texel)
        use = ok & nb_ok & ~edge & ((d * d).sum(-1) <= limit2)
        return d, use, nb, nb_ok & ~edge

    # axis 2: grid columns (x); axis 1: grid rows
    dx_p, ux_p, nx_p, _ = side(2, 1)
    dx_m, ux_m, nx_m, _ = side(2, -1)
    dy_p, uy_p, ny_p, _ = side(1, 1)
    dy_m, uy_m, ny_m, _ = side(1, -1)
    zero = torch.zeros_like(dx_p)

    def slope(d_main: Tensor, u_main: Tensor, d_other: Tensor, u_other: Tensor) -> tuple[Tensor, Tensor]:
        sel = torch.where(u_main[..., None], d_main, torch.where(u_other[..., None], d_other, zero))
        return sel, u_main

    quads = []
    for sx in (1, -1):
        jx, nat_x = slope(dx_p, ux_p, dx_m, ux_m) if sx > 0 else slope(dx_m, ux_m, dx_p, ux_p)
        for sy in (1, -1):
            jy, nat_y = slope(dy_p, uy_p, dy_m, uy_m) if sy > 0 else slope(dy_m, uy_m, dy_p, uy_p)
            # the diagonal neighbour for the bilinear (twist) term of this quadrant's grid cell
            diag = _shift(_shift(uv, 2, sx), 1, sy)
            diag_ok = _shift(_shift(ok, 2, sx), 1, sy)
            nb_x = nx_p if sx > 0 else nx_m
            nb_y = ny_p if sy > 0 else ny_m
            twist = (diag - nb_x - nb_y + uv) * (sx * sy)
            use_t = nat_x & nat_y & diag_ok & ((twist * twist).sum(-1) <= limit2)
            # the diagonal exists only inside the grid: rows/cols at the edge already fail nat_x / nat_y
            twist = torch.where(use_t[..., None], twist, zero)
            quads.append((sx, sy, jx, jy, twist))

    if not is_tracing():
        # eager: only the grid points that carry flux (the shapes are data-dependent; tracing keeps them all)
        keep = ok.any(-1).reshape(-1)
        idx = keep.nonzero()[:, 0]

        def pick(x: Tensor) -> Tensor:
            return x.reshape(b * x.shape[1] * x.shape[2], *x.shape[3:]).index_select(0, idx)
        bidx = torch.arange(b, device=uv.device).view(b, 1, 1).expand(b, uv.shape[1], uv.shape[2]).reshape(-1)
        bidx = bidx.index_select(0, idx)
        uv_p, f_p, ok_p = pick(uv), pick(f), pick(ok)
        quads = [(sx, sy, pick(jx), pick(jy), pick(tw)) for sx, sy, jx, jy, tw in quads]
    else:
        bidx = torch.arange(b, device=uv.device).view(b, 1, 1).expand(b, uv.shape[1], uv.shape[2]).reshape(-1)
        uv_p, f_p, ok_p = (x.reshape(-1, *x.shape[3:]) for x in (uv, f, ok))
        quads = [(sx, sy, *(x.reshape(-1, *x.shape[3:]) for x in (jx, jy, tw))) for sx, sy, jx, jy, tw in quads]

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
    offsets = [(k + 0.5) / s - 0.5 for k in range(s)]
    groups = []  # per quadrant: its Jacobian, twist and the (ox, oy) offsets of its sub-points
    for sx, sy, jx, jy, twist in quads:
        sub = [(ox, oy) for ox in offsets if ox * sx > 0 for oy in offsets if oy * sy > 0]
        if sub:
            groups.append((jx, jy, twist, sub))
    # (K, P, C, 2) rows, one per sub-point: eager takes a quadrant at a time (bounding the (K, P, C, taps, taps)
    # temporaries); a traced graph takes every sub-point of every quadrant in one pass (one body, not 4 (s/2)^2)
    groups = [(*(x.expand(len(sub), *x.shape) for x in (jx, jy, tw)), sub) for jx, jy, tw, sub in groups]
    if is_tracing() and groups:
        groups = [(*(torch.cat([g[i] for g in groups]) for i in range(3)), [o for g in groups for o in g[3]])]
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
        wu = torch.where((iu >= 0) & (iu <= w - 1), wu, torch.zeros_like(wu))
        wv = torch.where((iv >= 0) & (iv <= h - 1), wv, torch.zeros_like(wv))
        wgt = wv[..., :, None] * wu[..., None, :]  # (K, P, C, T, T)
        index = (iv.clamp(0, h - 1)[..., :, None] * w + iu.clamp(0, w - 1)[..., None, :]).to(torch.int64)
        index = index + base[..., None, None]
        if coverage is not None:
            wgt = wgt * cover[index]
        tot = wgt.sum((-2, -1), keepdim=True)
        wgt = wgt / torch.where(tot > 0, tot, torch.ones_like(tot))
        wgt = wgt * (inside & (tot[..., 0, 0] > 0))[..., None, None]
        out = out.view(-1).scatter_add(0, index.reshape(-1), (wgt * sub_f[..., None, None]).reshape(-1))
    return out.reshape(b, c, h, w).to(out_dtype)
