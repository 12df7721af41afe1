"""Shah's image-space splatting (Shah 2007, ch. 6.4): accumulate dipole-weighted splats into the camera image.

Every source :math:`x_i` (a light-view sample: position, transmitted irradiance times area, material) sends light
to the camera pixels whose surface point :math:`x_o` lies within the truncation radius :math:`r_{max}` of its
material,

.. math::
    B(x_o) = \\sum_i [\\xi_i = \\xi_o]\\; [\\,|x_o - x_i| M_{d,i} \\le r_{max}(m_i)\\,]\\;
             R_d^{m_i}(|x_o - x_i|\\, M_{d,i})\\; E_i\\, dA_i\\, M_{i,i},

with :math:`m_i` the source's material (one row of a material table: several materials in one pass, Shah 6.4.3),
:math:`\\xi` object ids (a splat never lights another object, Shah 6.4.3's clipping), :math:`M_d, M_i` the
optional distance and irradiance modifiers of Shah eq. 7.4. Distances are in mm, coefficients in mm^-1,
:math:`R_d` in mm^-2, so :math:`B` has the units of :math:`E\\,dA` per mm^2 (the outgoing radiance is
:math:`F_t/\\pi \\cdot B`). The truncation is a *disk* of radius :math:`r_{max}` in world space around the source
(:func:`torchsss.physics.r_max` solves Shah eq. 6.16 for it); it is applied to the scaled distance
:math:`|x_o - x_i| M_d`, so a source's world-space reach is :math:`r_{max} / \\min_c M_{d,i,c}`.

Three implementations compute the same sum:

* ``"window"`` (Shah's splat, scatter form): each splat centre is projected with ``view_proj``; a
  :math:`K_y \\times K_x` pixel window around it is tested and its weights are accumulated with
  ``scatter_add`` (the only accumulation that exports to ONNX exactly, see ONNX_NOTES.md). The automatic
  window is conservative (:func:`splat_window_size`); a fixed ``window`` (needed for ONNX export) misses the
  pixels of a footprint that does not fit in it.
* ``"tile"`` (gather form): the covered pixels are grouped in tiles of :math:`T \\times T` (tile-major order);
  each tile sums over the splats whose world-space reach touches the tile's bounding box (per-tile candidate
  lists, tiles sorted by candidate count and processed in chunks). No projection, no window, no truncation error;
  eager only (the candidate lists have data-dependent sizes).

* ``"gather"`` (plain dipole profiles): every covered pixel against every splat of its image in the fused,
  compiled pair sum (:func:`torchsss.ops.fused.dipole_pair_sum` with ``r_max``): no candidate lists, all pairs at
  30-70 Mpairs/s (one thread) instead of the pairs in reach at 0.2-10 M/s. ``"auto"`` picks it (inference, where
  the pair sum runs compiled) when at least :data:`GATHER_REACH` of the pairs are in reach: wherever r_max spans a
  good part of the object, and down to a hundredth of it.

All are checked against the all-pairs :func:`torchsss.ops.reference.reference_radiosity` with a truncated
profile; ``benchmarks/bench_splat.py`` measures them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchsss._checks import (
    as_float_tensor,
    check_devices,
    check_finite_inputs,
    check_nonnegative,
    check_positive,
    check_shape,
    check_tensor,
    compute_dtype,
    is_exporting,
    is_tracing,
    skip_value_checks,
)
from torchsss.ops.fused import dipole_pair_sum, dipole_params, dipole_taps, use_compiled, would_compile
from torchsss.physics.lut import BULK_MIN_VALUES, bulk_profile

#: A profile: distances :math:`(..., 1)` or :math:`(..., C)` in mm -> :math:`R_d` :math:`(..., C)` in mm^-2.
Profile = Callable[[Tensor], Tensor]

__all__ = ["splat_radiosity", "splat_window_size"]

_METHODS = ("auto", "window", "tile", "gather")
#: Pixels of slack added to every projected half extent (absorbs rounding of the projection).
_MARGIN_PX = 1.0
#: Upper bound of the (pixel, splat) candidate taps formed per chunk (indices, masks, distances); each call has
#: a fixed cost of a few dozen tensor ops, so chunks are large; ``max_memory_mb`` can lower the bound.
_MAX_CHUNK_TAPS = 1 << 20
#: Upper bound of the (pixel, splat) pairs per evaluation of the profile (~25 elementwise passes of C channels).
_EVAL_PAIRS = 1 << 18


# -- validation ------------------------------------------------------------------------------------------------------
def _shape(x: Tensor, name: str, pattern: str, **known: int) -> dict[str, int]:
    """:func:`check_shape`, skipped while tracing.

    ``check_shape`` binds sizes with ``int()``, which would freeze symbolic sizes (the splat count, the image size)
    into an exported graph.
    """
    return dict(known) if is_tracing() else check_shape(x, name, pattern, **known)


def _check_int_tensor(x: object, name: str) -> Tensor:
    if not isinstance(x, Tensor) or x.is_floating_point() or x.is_complex() or x.dtype == torch.bool:
        got = x.dtype if isinstance(x, Tensor) else type(x).__name__
        raise TypeError(f"{name}: expected an integer tensor, got {got}")
    return x


def _check_modifier(x: object, name: str, dims: dict[str, int]) -> Tensor:
    check_tensor(x, name)
    c = dims["C"]
    if x.dim() != 3 or x.shape[-1] not in (1, c):
        raise ValueError(f"{name}: expected shape (B, S, 1) or (B, S, {c}), got {tuple(x.shape)}")
    _shape(x, name, f"B,S,{x.shape[-1]}", **dims)
    return x


def _profiles(profile: object) -> list[Profile]:
    """The material table as a list of profile callables (one material: a list of one)."""
    rows = list(profile) if isinstance(profile, (list, tuple)) else [profile]
    if not rows:
        raise ValueError("profile: expected a profile or a non-empty sequence of profiles, got an empty sequence")
    for i, p in enumerate(rows):
        if not callable(p):
            name = "profile" if len(rows) == 1 and not isinstance(profile, (list, tuple)) else f"profile[{i}]"
            raise TypeError(f"{name}: expected a callable from distances (mm) to R_d (a material module), "
                            f"got {type(p).__name__}")
    return rows


def _check_profile_channels(profiles: list[Profile], c: int, like: Tensor) -> None:
    """Every profile must give C channels (those of ``src_flux``): one evaluation at r = 1 mm each."""
    probe = torch.ones(1, 1, dtype=like.dtype if like.is_floating_point() else torch.float32, device=like.device)
    for i, p in enumerate(profiles):
        with torch.no_grad():
            got = p(probe)
        if not isinstance(got, Tensor) or got.dim() < 1 or got.shape[-1] != c:
            shape = tuple(got.shape) if isinstance(got, Tensor) else type(got).__name__
            raise ValueError(f"profile[{i}]: expected R_d of shape (..., {c}) (the channels of src_flux) for "
                             f"distances (..., 1), got {shape}")


def _per_material(x: object, name: str, m: int, like: Tensor) -> Tensor:
    t = as_float_tensor(x, name, like=like)
    if t.dim() > 1 or (t.dim() == 1 and t.shape[0] not in (1, m)):
        raise ValueError(f"{name}: expected a number or a tensor of shape () or (M,) with M={m}, got {tuple(t.shape)}")
    return t.reshape(-1).expand(m)


def _check_positive_int(value: object, name: str, *, odd: bool = False) -> int:
    what = "an odd int >= 1" if odd else "an int >= 1"
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name}: expected {what}, got {type(value).__name__}")
    if value < 1 or (odd and value % 2 == 0):
        raise ValueError(f"{name}: expected {what}, got {value!r}")
    return value


def _check_view_proj(view_proj: object, b: int) -> Tensor:
    check_tensor(view_proj, "view_proj")
    if view_proj.dim() == 2:
        view_proj = view_proj.unsqueeze(0)
    if view_proj.dim() != 3 or view_proj.shape[-2:] != (4, 4) or view_proj.shape[0] not in (1, b):
        raise ValueError(f"view_proj: expected shape (4, 4) or (B, 4, 4) with B={b}, got {tuple(view_proj.shape)}")
    return view_proj


# -- footprint -------------------------------------------------------------------------------------------------------
def _footprint(pos: Tensor, reach: Tensor, vp: Tensor, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """Conservative pixel footprint of the world-space balls ``|p - pos| <= reach`` under ``vp``.

    With clip coordinates affine in the point, :math:`a = g_a \\cdot p + a_0` (x or y) and
    :math:`w = g_w \\cdot p + w_0`, a displacement :math:`\\delta`, :math:`|\\delta| \\le R`, moves NDC by
    :math:`(g_a - n\\, g_w)\\cdot\\delta / (w_c + g_w\\cdot\\delta)`, hence at most
    :math:`R\\,|g_a - n\\,g_w| / (w_c - R\\,|g_w|)` while the denominator is positive. This covers the near side of
    the ball (perspective), whatever the surface's slope. A ball that reaches the camera plane is unbounded (inf).

    Args:
        pos: (n, 3) ball centres in mm.
        reach: (n,) ball radii in mm.
        vp: (n, 4, 4) or (1, 4, 4) world-to-clip matrices.
        height: image height in pixels.
        width: image width in pixels.

    Returns:
        ``centre`` (n, 2) continuous pixel coordinates (column, row; pixel centres at integers), ``half`` (n, 2)
        half extents in pixels (inf when unbounded, margin included), ``visible`` (n,) whether the ball can reach a
        pixel centre of the image.
    """
    clip = torch.matmul(vp[:, :, :3], pos.unsqueeze(-1)).squeeze(-1) + vp[:, :, 3]  # (n, 4)
    g = vp[:, :, :3]  # (n|1, 4, 3) gradients of x, y, z, w
    w_c = clip[:, 3]
    front = w_c > 0
    w_safe = torch.where(front, w_c, torch.ones_like(w_c))
    ndc = clip[:, :2] / w_safe.unsqueeze(-1)  # (n, 2)
    ndc = torch.where(front.unsqueeze(-1), ndc, torch.zeros_like(ndc))
    gw_norm = torch.linalg.vector_norm(g[:, 3], dim=-1)  # (n|1,)
    den = w_c - reach * gw_norm
    bounded = den > 0
    den_safe = torch.where(bounded, den, torch.ones_like(den))
    num = torch.linalg.vector_norm(g[:, :2] - ndc.unsqueeze(-1) * g[:, 3:4], dim=-1)  # (n, 2)
    half_ndc = reach.unsqueeze(-1) * num / den_safe.unsqueeze(-1)
    scale = torch.tensor([0.5 * width, 0.5 * height], dtype=pos.dtype, device=pos.device)
    half = torch.where(bounded.unsqueeze(-1), half_ndc * scale + _MARGIN_PX, torch.full_like(half_ndc, math.inf))
    centre = torch.stack([(ndc[:, 0] + 1.0) * (0.5 * width) - 0.5, (1.0 - ndc[:, 1]) * (0.5 * height) - 0.5], -1)
    size = torch.tensor([width - 1.0, height - 1.0], dtype=pos.dtype, device=pos.device)
    on_image = ((centre + half >= 0) & (centre - half <= size)).all(-1)
    # a ball entirely behind the camera plane (w <= 0 everywhere in it) sees nothing
    visible = (w_c + reach * gw_norm > 0) & (~bounded | on_image)
    return centre, half, visible


def _window_extent(half: Tensor, size: int) -> int:
    """Smallest odd window side covering ``half`` pixels around a rounded centre, capped at ``size``."""
    if half.numel() == 0:
        return 1
    h = float(half.max())
    if not math.isfinite(h) or 2 * math.ceil(h) + 1 >= size:
        return size
    return 2 * math.ceil(h) + 1


def splat_window_size(src_pos: Tensor, view_proj: Tensor, radius: Tensor | float, height: int, width: int) -> int:
    """Side :math:`K` of a square window that holds every visible splat's footprint (for ``window=`` of the op).

    The footprint of a splat is the projection of the world-space ball of ``radius`` around its centre; its
    half extent is bounded in closed form, including the perspective growth of the ball's near side (see the
    module docstring of :mod:`torchsss.ops.splat`), plus one pixel of slack. Splats whose ball cannot reach the
    image (off-screen, behind the camera) are ignored; a ball that reaches the camera plane needs the whole image.
    The result is at most ``max(height, width)`` rounded up to odd (such a window covers the image from any
    centre).

    Args:
        src_pos: :math:`(B, S, 3)` splat centres in mm.
        view_proj: :math:`(4, 4)` or :math:`(B, 4, 4)` world-to-clip matrix of the camera (OpenGL conventions).
        radius: world-space reach in mm, a number or :math:`(B, S)` (e.g. ``r_max[src_material]``).
        height: image height :math:`H` in pixels.
        width: image width :math:`W` in pixels.

    Returns:
        An odd int :math:`K \\ge 1`.

    Raises:
        TypeError: non-tensor or non-floating inputs, non-int sizes.
        ValueError: wrong shapes, non-positive radius or sizes.

    Examples:
        >>> vp = torch.eye(4)  # orthographic: NDC = world x, y
        >>> splat_window_size(torch.zeros(1, 1, 3), vp, 0.25, 16, 16)  # 0.25 NDC = 2 px, +1 px slack
        7
    """
    check_tensor(src_pos, "src_pos")
    dims = check_shape(src_pos, "src_pos", "B,S,3")
    vp = _check_view_proj(view_proj, dims["B"])
    h = _check_positive_int(height, "height")
    w = _check_positive_int(width, "width")
    rad = as_float_tensor(radius, "radius", like=src_pos)
    if rad.dim() != 0:
        check_shape(rad, "radius", "B,S", **dims)
    check_positive(rad, "radius")
    b, s = dims["B"], dims["S"]
    _, dtype = compute_dtype(src_pos, vp, rad)
    pos = src_pos.detach().to(dtype).reshape(b * s, 3)
    reach = rad.detach().to(dtype).expand(b, s).reshape(b * s)
    sb = torch.arange(b * s, device=pos.device) // max(s, 1)
    vps = vp.detach().to(dtype)
    _, half, visible = _footprint(pos, reach, vps if vps.shape[0] == 1 else vps[sb], h, w)
    ky = _window_extent(half[visible, 1], h)
    kx = _window_extent(half[visible, 0], w)
    k = max(kx, ky)
    return k if k % 2 == 1 else k + 1


# -- shared pieces -----------------------------------------------------------------------------------------------------
def _profile(r: Tensor, valid: Tensor | None, md: Tensor | None, rmax: Tensor, profile: Profile) -> Tensor:
    """Truncated, masked :math:`R_d(r M_d)`: zero where ``valid`` is False or :math:`r M_d > r_{max}`.

    Channels first: ``r`` is :math:`(1, ...)`, ``md`` :math:`(1 \\text{ or } C, ...)`, the result
    :math:`(C, ...)`; the profile itself is called channels-last (the contract of every profile: distances
    :math:`(..., 1 \\text{ or } C)` in mm to :math:`(..., C)`).
    """
    r_eff = r if md is None else r * md
    keep = r_eff <= rmax
    if valid is not None:
        keep = keep & valid
    rd = profile(r_eff.movedim(0, -1)).movedim(-1, 0).to(r.dtype)
    return torch.where(keep, rd, torch.zeros_like(rd))


def _material_row(profile: Profile, r_max: Tensor, pairs: float, dtype: torch.dtype, device: torch.device) -> tuple:
    """``(profile, r_max (1, 1), evaluation)`` of one material for the eager per-pair paths.

    The evaluation is the profile's table (:func:`~torchsss.physics.lut.bulk_profile`, within its
    :data:`~torchsss.physics.lut.BULK_TOLERANCE`) when a frame may evaluate at least
    :data:`~torchsss.physics.lut.BULK_MIN_VALUES` pairs (``pairs``: covered pixels x splats, the most it can) outside
    autograd; else the profile itself (bulk_profile also keeps it for float64, under autograd and while tracing).
    A gather and a lerp per pair instead of the dipole's formula: a splat frame whose reach spans the object 1.4-1.5x
    faster (a back-lit 20 mm potato sphere at 128 x 128, oversample 1 and 2: 0.63 -> 0.42 s and 4.6 -> 3.1 s).
    """
    evaluate = profile
    if pairs >= BULK_MIN_VALUES and not torch.is_grad_enabled():
        evaluate = bulk_profile(profile, float(r_max), dtype, device)
    return profile, r_max.reshape(1, 1), evaluate


def _sqrt0(x: Tensor) -> Tensor:
    """:math:`\\sqrt{x}` with gradient 0 at :math:`x = 0` (coincident points)."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


def _accumulate(out: Tensor, index: Tensor, r: Tensor, splat: Tensor, src: dict, mat: tuple, step: int) -> Tensor:
    """Add :math:`R_d(r)\\,E\\,dA` of a list of pairs to ``out`` :math:`(C, N)` (``index`` into its columns).

    ``r`` are the pairs' distances (mm), ``splat`` their sources in ``src``; ``mat`` = (profile, r_max (1, 1),
    evaluation) of the one material of ``src`` (the eager paths handle one material at a time, so no per-pair
    material gather; the evaluation is the profile or its table, :func:`_material_row`). The pairs are evaluated
    ``step`` at a time.
    """
    c = out.shape[0]
    profile, rmax, evaluate = mat
    dipole = dipole_params(profile, r.dtype, r.device, c)  # the plain dipole: the fused kernel may run
    coeffs = None if dipole is None else dipole[1]
    fused = dipole is not None and use_compiled(
        "dipole_taps", (r.device.type, r.dtype, c, None if src["md"] is None else src["md"].shape[-1]),
        float(index.numel()), (r, src["flux"], *dipole[0], *coeffs))
    for i in range(0, index.numel(), step):
        sl = slice(i, i + step)
        sp = splat[sl]
        md = None if src["md"] is None else src["md"][sp].T
        flux = src["flux"][sp].T
        if fused:
            contrib = dipole_taps(r[sl], flux, rmax.to(r.dtype), *coeffs, md, compiled=True)
        else:
            contrib = _profile(r[sl].unsqueeze(0), None, md, rmax, evaluate) * flux  # (C, P)
        out = out.scatter_add(1, index[sl].expand(c, -1), contrib)
    return out


def _take(src: dict, sel: Tensor | slice) -> dict:
    return {k: (v if v is None else v[sel]) for k, v in src.items()}


def _chunk(budget_bytes: int, per_item_taps: int, dtype: torch.dtype, c: int, cap: int = _MAX_CHUNK_TAPS) -> int:
    """Items (splats, tiles, pairs) per chunk: at most ``cap`` (pixel, splat) pairs and about ``budget_bytes``."""
    e = torch.empty((), dtype=dtype).element_size()
    per_tap = 24 + (4 + 6 * c) * e  # indices, masks, distances and the live profile temporaries of one pair
    taps = max(1, min(cap, budget_bytes // per_tap))
    return max(1, taps // max(1, per_item_taps))


# -- window (scatter) --------------------------------------------------------------------------------------------------
def _window_taps(
    src: dict,
    x0: Tensor,
    y0: Tensor,
    kx: int,
    ky: int,
    dst_valid: Tensor,
    dst_obj: Tensor | None,
    h: int,
    w: int,
    box: tuple[int, int, int, int] | None = None,
) -> tuple[Tensor, Tensor]:
    """Flat pixel index (s, ky*kx) of every window tap and whether it is a valid receiver of its splat.

    ``box`` = (row0, col0, rows, cols) is the part of the image that holds receivers (default: all of it); the
    window origins ``x0``, ``y0`` are relative to it.
    """
    oy, ox, bh, bw = (0, 0, h, w) if box is None else box
    dev = x0.device
    xs = x0.unsqueeze(-1) + torch.arange(kx, device=dev)  # (s, kx)
    ys = y0.unsqueeze(-1) + torch.arange(ky, device=dev)  # (s, ky)
    inside = ((ys >= 0) & (ys < bh)).unsqueeze(-1) & ((xs >= 0) & (xs < bw)).unsqueeze(-2)  # (s, ky, kx)
    pix = (
        src["batch"][:, None, None] * (h * w)
        + (ys.clamp(0, bh - 1) + oy).unsqueeze(-1) * w
        + (xs.clamp(0, bw - 1) + ox).unsqueeze(-2)
    ).flatten(1)
    valid = inside.flatten(1) & dst_valid[pix]
    if dst_obj is not None:
        valid = valid & (dst_obj[pix] == src["obj"].unsqueeze(-1))
    return pix, valid


def _window_origin(centre: Tensor, kx: int, ky: int, h: int, w: int) -> tuple[Tensor, Tensor]:
    """Top-left tap of each window: centred on the rounded splat centre, then shifted to lie inside the image."""
    cxy = torch.round(centre.clamp(-4.0 * (h + w), 4.0 * (h + w))).to(torch.int64)  # (n, 2) column, row
    x0 = torch.clamp(cxy[:, 0] - kx // 2, min=0, max=w - kx)
    y0 = torch.clamp(cxy[:, 1] - ky // 2, min=0, max=h - ky)
    return x0, y0


def _splat_window_traced(
    src: dict, dst: Tensor, dst_valid: Tensor, dst_obj: Tensor | None, vp: Tensor, b: int, h: int, w: int, window: int
) -> Tensor:
    """Exportable window path: one dense chunk, per-splat material rows in ``src``; returns (C, B*H*W)."""
    c = src["flux"].shape[-1]
    centre, _, _ = _footprint(src["pos"], src["reach"], vp if vp.shape[0] == 1 else vp[src["batch"]], h, w)
    x0, y0 = _window_origin(centre, window, window, h, w)
    pix, valid = _window_taps(src, x0, y0, window, window, dst_valid, dst_obj, h, w)  # (S, K)
    d = dst[:, pix] - src["pos"].T.unsqueeze(-1)  # (3, S, K)
    r = _sqrt0(d[0:1].square() + d[1:2].square() + d[2:3].square())  # (1, S, K)
    md = None if src["md"] is None else src["md"].T.unsqueeze(-1)
    rmax = src["rmax"][None, :, None]
    profiles = src["profiles"]
    if len(profiles) == 1:
        wgt = _profile(r, valid.unsqueeze(0), md, rmax, profiles[0])  # (C, S, K)
    else:  # one evaluation per row of the material table, each kept on the splats of that row
        row = src["mat"][None, :, None]
        wgt = sum(_profile(r, valid.unsqueeze(0) & (row == k), md, rmax, p) for k, p in enumerate(profiles))
    contrib = (wgt * src["flux"].T.unsqueeze(-1)).reshape(c, -1)
    out = torch.zeros(c, b * h * w, dtype=dst.dtype, device=dst.device)
    return out.scatter_add(1, pix.reshape(1, -1).expand(c, -1), contrib)


def _splat_window(
    out: Tensor,
    src: dict,
    mat: tuple,
    dst: Tensor,
    dst_valid: Tensor,
    dst_obj: Tensor | None,
    vp: Tensor,
    h: int,
    w: int,
    window: int | None,
    budget: int,
) -> Tensor:
    """Eager window path for the splats of one material; adds to ``out`` (C, B*H*W).

    Off-screen splats are dropped. Without a fixed window, splats are grouped by footprint size (powers of two)
    so that small footprints do not pay for the largest one. The taps are compacted to the receivers within
    reach before the profile is evaluated.
    """
    centre, half, visible = _footprint(src["pos"], src["reach"], vp if vp.shape[0] == 1 else vp[src["batch"]], h, w)
    eval_pairs = _chunk(budget, 1, dst.dtype, out.shape[0], cap=_EVAL_PAIRS)
    # automatic windows only need to cover the bounding box of the receivers (over the batch): crop to it. A
    # fixed window is placed in the whole image, as in the traced path, so that both truncate alike.
    rows = torch.nonzero(dst_valid.reshape(-1, h, w).any(0).any(1)).squeeze(-1)
    cols = torch.nonzero(dst_valid.reshape(-1, h, w).any(0).any(0)).squeeze(-1)
    if rows.numel() == 0:
        return out
    oy, ox, bh, bw = 0, 0, h, w
    if window is None:
        oy, ox = int(rows[0]), int(cols[0])
        bh, bw = int(rows[-1]) - oy + 1, int(cols[-1]) - ox + 1
    offset = torch.tensor([ox, oy], dtype=centre.dtype, device=centre.device)
    lo, hi = offset, offset + torch.tensor([bw - 1, bh - 1], dtype=centre.dtype, device=centre.device)
    visible = visible & ((centre + half >= lo) & (centre - half <= hi)).all(-1)
    keep = torch.nonzero(visible).squeeze(-1)
    src, centre, half = _take(src, keep), centre[keep] - offset, half[keep]
    if keep.numel() == 0:
        return out
    if window is not None:
        groups = [(torch.arange(keep.numel(), device=keep.device), min(window, bw), min(window, bh))]
    else:
        need = half.clamp(max=4.0 * (h + w)).ceil()  # (n, 2) half extents in whole pixels
        level = torch.log2(need.amax(-1).clamp_min(1.0)).ceil().to(torch.int64)
        groups = []
        for lv in torch.unique(level).tolist():
            idx = torch.nonzero(level == lv).squeeze(-1)
            hx, hy = need[idx].amax(0).tolist()
            groups.append((idx, min(bw, 2 * int(hx) + 1), min(bh, 2 * int(hy) + 1)))
    for idx, kx, ky in groups:
        g = _take(src, idx)
        x0, y0 = _window_origin(centre[idx], kx, ky, bh, bw)
        step = _chunk(budget, kx * ky, dst.dtype, out.shape[0])
        for i0 in range(0, idx.numel(), step):
            sub = _take(g, slice(i0, i0 + step))
            pix, valid = _window_taps(
                sub, x0[i0 : i0 + step], y0[i0 : i0 + step], kx, ky, dst_valid, dst_obj, h, w, (oy, ox, bh, bw)
            )
            si, ki = torch.nonzero(valid, as_tuple=True)  # receivers first: most window taps are background
            pq = pix[si, ki]
            d = dst[:, pq] - sub["pos"][si].T  # (3, P)
            r = _sqrt0(d[0].square() + d[1].square() + d[2].square())
            near = torch.nonzero(r <= sub["reach"][si]).squeeze(-1)
            if near.numel():
                out = _accumulate(out, pq[near], r[near], si[near], sub, mat, eval_pairs)
    return out


# -- tile (gather) -----------------------------------------------------------------------------------------------------
def _to_tiles(x: Tensor, t: int) -> Tensor:
    """(H, W, ...) -> (nty * ntx, t*t, ...) after zero-padding H, W to multiples of ``t``."""
    h, w = x.shape[:2]
    hp, wp = -(-h // t) * t, -(-w // t) * t
    if (hp, wp) != (h, w):
        pad = torch.zeros((hp, wp, *x.shape[2:]), dtype=x.dtype, device=x.device)
        pad[:h, :w] = x
        x = pad
    rest = x.shape[2:]
    x = x.reshape(hp // t, t, wp // t, t, *rest).transpose(1, 2)
    return x.reshape((hp // t) * (wp // t), t * t, *rest)


class _Tiles:
    """The covered pixels of one image, in tile-major order, cut into groups of ``t*t`` pixels (the "tiles").

    Taking only covered pixels (rather than the whole ``t x t`` squares) means no background pixel is ever paired
    with a splat; a group is a tile of the image, or the pieces of two neighbouring tiles where the covered pixels
    do not fill one. Attributes: ``pix`` (ng, G) flat pixel index, ``valid`` (ng, G) (False on the padding of
    the last group), ``pos`` (ng, G, 3), ``obj`` (ng, G) or None, ``lo``/``hi`` (ng, 3) bounding boxes,
    ``omin``/``omax`` (ng,) object-id ranges.
    """

    def __init__(self, dst: Tensor, valid: Tensor, obj: Tensor | None, t: int) -> None:
        h, w = valid.shape
        dev = dst.device
        order = _to_tiles(torch.arange(h * w, device=dev).reshape(h, w), t).flatten()
        pix = order[_to_tiles(valid, t).flatten()]  # covered pixels, tile by tile
        g = t * t
        ng = max(1, -(-pix.numel() // g))
        self.valid = (torch.arange(ng * g, device=dev) < pix.numel()).reshape(ng, g)
        self.pix = torch.cat([pix, pix.new_zeros(ng * g - pix.numel())]).reshape(ng, g)
        self.pos = dst.reshape(h * w, 3)[self.pix]
        inf = torch.tensor(math.inf, dtype=dst.dtype, device=dev)
        vm = self.valid.unsqueeze(-1)
        self.lo = torch.where(vm, self.pos, inf).amin(1)  # (ng, 3); +inf for a group without receivers
        self.hi = torch.where(vm, self.pos, -inf).amax(1)
        self.obj = None if obj is None else obj.reshape(h * w)[self.pix]
        if self.obj is not None:
            big = torch.iinfo(self.obj.dtype)
            self.omin = torch.where(self.valid, self.obj, big.max).amin(1)
            self.omax = torch.where(self.valid, self.obj, big.min).amax(1)

    def cull(self, idx: Tensor | slice, src: dict) -> Tensor:
        """(tiles, splats) bool: the splat's reach touches the tile's box (and the tile holds its object id)."""
        p = src["pos"]
        gap = (self.lo[idx].unsqueeze(1) - p).clamp_min(0) + (p - self.hi[idx].unsqueeze(1)).clamp_min(0)
        hit = (gap * gap).sum(-1) <= src["reach"] * src["reach"]
        if self.obj is not None:
            o = src["obj"]
            hit = hit & (o >= self.omin[idx].unsqueeze(1)) & (o <= self.omax[idx].unsqueeze(1))
        return hit


def _tile_block(tiles: _Tiles, idx: Tensor, cand: Tensor, ok: Tensor, src: dict, mat: tuple) -> Tensor:
    """Dense gather for tiles ``idx`` and their padded candidate lists ``cand`` (ntc, L): (C, ntc, T2)."""
    d = tiles.pos[idx].unsqueeze(2) - src["pos"][cand].unsqueeze(1)  # (ntc, T2, L, 3), exact differences
    r = _sqrt0(d[..., 0].square() + d[..., 1].square() + d[..., 2].square())  # (ntc, T2, L)
    valid = tiles.valid[idx].unsqueeze(-1) & ok.unsqueeze(1)
    if tiles.obj is not None:
        valid = valid & (tiles.obj[idx].unsqueeze(-1) == src["obj"][cand].unsqueeze(1))
    md = None if src["md"] is None else src["md"][cand].permute(2, 0, 1).unsqueeze(2)  # (1|C, ntc, 1, L)
    rd = _profile(r.unsqueeze(0), valid.unsqueeze(0), md, mat[1].reshape(1, 1, 1, 1), mat[2])  # (C, ntc, T2, L)
    flux = src["flux"][cand].permute(2, 0, 1).unsqueeze(2)  # (C, ntc, 1, L)
    return (rd * flux).sum(-1)


def _splat_tile_one(src: dict, mat: tuple, tiles: _Tiles, c: int, budget: int) -> Tensor:
    """Gather form for one image and one material: (C, nt, T2) radiosity per tile pixel.

    Pass 1 counts each tile's candidates; pass 2 takes the tiles by decreasing count, so that a chunk's padded
    candidate length is close to the counts of its tiles, and evaluates every (pixel, candidate) pair densely
    (masked), summing over the candidates. Long candidate lists are cut into pieces.
    """
    n = src["pos"].shape[0]
    nt, t2 = tiles.valid.shape
    dev, dtype = tiles.pos.device, tiles.pos.dtype
    rows = max(1, budget // max(1, 32 * n))  # tiles per culling chunk (the (tiles, splats, 3) temporaries)
    counts = torch.cat([tiles.cull(slice(i, i + rows), src).sum(1) for i in range(0, nt, rows)])
    order = torch.argsort(counts, descending=True, stable=True)
    sorted_counts = counts[order].tolist()
    ar = torch.arange(n, device=dev)
    done_idx, done_val = [], []
    i = 0
    while i < nt and sorted_counts[i] > 0:
        length = sorted_counts[i]
        idx = order[i : i + _chunk(budget, t2 * length, dtype, c, cap=_EVAL_PAIRS)]
        i += idx.numel()
        hit = tiles.cull(idx, src)  # (ntc, n)
        slot = torch.where(hit, hit.cumsum(1) - 1, torch.full_like(hit, length, dtype=torch.int64))
        cand = torch.zeros(idx.numel(), length + 1, dtype=torch.int64, device=dev)
        cand = cand.scatter_(1, slot, ar.expand(idx.numel(), n))[:, :length]  # (ntc, L), padded
        ok = torch.arange(length, device=dev) < counts[idx].unsqueeze(-1)
        piece = _chunk(budget, idx.numel() * t2, dtype, c, cap=_EVAL_PAIRS)  # candidates per dense block
        acc = None
        for l0 in range(0, length, piece):
            part = _tile_block(tiles, idx, cand[:, l0 : l0 + piece], ok[:, l0 : l0 + piece], src, mat)
            acc = part if acc is None else acc + part
        done_idx.append(idx)
        done_val.append(acc)
    out = torch.zeros(nt, c, t2, dtype=dtype, device=dev)
    if done_idx:
        out = out.index_put((torch.cat(done_idx),), torch.cat(done_val, 1).transpose(0, 1))
    return out.transpose(0, 1)


def _splat_tile(out: Tensor, src: dict, mat: tuple, tiles: list[_Tiles], h: int, w: int, budget: int) -> Tensor:
    """Eager tile path for the splats of one material over the batch; adds to ``out`` (C, B*H*W)."""
    b, c = len(tiles), out.shape[0]
    bounds = torch.searchsorted(src["batch"], torch.arange(b + 1, device=out.device)).tolist()
    acc = torch.zeros(b * h * w, c, dtype=out.dtype, device=out.device)
    for bi in range(b):
        if bounds[bi + 1] == bounds[bi]:
            continue
        res = _splat_tile_one(_take(src, slice(bounds[bi], bounds[bi + 1])), mat, tiles[bi], c, budget)
        tl = tiles[bi]
        acc = acc.index_put((tl.pix[tl.valid] + bi * h * w,), res.permute(1, 2, 0)[tl.valid])
    return out + acc.T


# -- gather (fused all pairs) -----------------------------------------------------------------------------------------
#: The share of (pixel, splat) pairs within reach above which the fused gather of all pairs beats the per-pair
#: paths. Measured 2026-11-29 (1 thread, the compiled pair sum warm): the gather runs 30-70 Mpairs/s over all pairs
#: (5-20 where a frame has under 3M, its blocks of 2,048 splats mostly padding); the window path 0.2-5 M/s over the
#: pairs in reach in a frame's first evaluation (eager, through the profile's table) and the tile path about 9. On a
#: back-lit 60 mm whole-milk sphere at 128 x 128, where 1% of the pairs are in reach (eps 0.03, 7,835 splats), the
#: gather took 0.55 s a frame, the window path 2.55 s on the first frame and 0.65 s on the next (its taps compiled);
#: at 7% (eps 0.01, 11,873 and 46,672 splats) 0.86 s against 4.58 / 0.95 s and 3.29 s against 17.4 / 3.35 s. It had
#: been 0.2 (from rates of 100-150 against 20 Mpairs/s).
GATHER_REACH = 0.01


def _reach_share(src: dict, dst: Tensor, mask_flat: Tensor, probe: int = 256) -> float:
    """The share of (covered pixel, splat) pairs within the splats' world-space reach.

    Estimated on ``probe`` evenly spaced covered pixels (fewer, at least 16, when there are over 16k splats).
    """
    covered = torch.nonzero(mask_flat).squeeze(-1)
    if covered.numel() == 0 or src["pos"].shape[0] == 0:
        return 0.0
    probe = max(16, min(probe, (1 << 22) // src["pos"].shape[0]))  # the (probe, S) distances stay under 32 MB
    pick = covered[torch.linspace(0, covered.numel() - 1, min(probe, covered.numel()),
                                  device=covered.device).long()]
    d = torch.cdist(dst[pick].to(src["pos"].dtype), src["pos"])  # (probe, S)
    return float((d <= src["reach"].reshape(1, -1)).to(torch.float64).mean())


def _gather_ok(dipole: tuple | None, src: dict, dst: Tensor, pairs: float) -> bool:
    """The gather form pays: a plain dipole, nothing recorded by autograd, and the pairs run compiled.

    ``dipole``: the material's :func:`~torchsss.ops.fused.dipole_params` (None: another profile). ``pairs``
    (covered pixels x splats) run compiled when :func:`~torchsss.ops.fused.would_compile` says so (the truncated
    pair sum is warm, or the frame pays for its compile); eager, the pair sum is slower than the per-pair paths
    over the pairs in reach.
    """
    if dipole is None:
        return False
    tensors = (src["pos"], src["flux"], dst, *dipole[0]) + (() if src["md"] is None else (src["md"],))
    return would_compile("dipole_pair_sum", pairs, tensors, device=dst.device.type, dtype=dipole[1][0].dtype,
                         truncated=True)


def _splat_gather(out: Tensor, src: dict, coeffs: tuple, rmax: Tensor, dst: Tensor, mask_flat: Tensor,
                  dst_obj: Tensor | None, b: int, hw: int) -> Tensor:
    """Gather form for the splats of one plain-dipole material; adds to ``out`` :math:`(C, B H W)`.

    Every covered pixel against every splat of its image in the fused pair sum
    (:func:`~torchsss.ops.fused.dipole_pair_sum` with ``r_max``); ``coeffs``: the material's dipole coefficients
    (the second item of :func:`~torchsss.ops.fused.dipole_params`).
    """
    bounds = torch.searchsorted(src["batch"], torch.arange(b + 1, device=out.device)).tolist()
    for bi in range(b):
        lo, hi = bounds[bi], bounds[bi + 1]
        pix = torch.nonzero(mask_flat[bi * hw:(bi + 1) * hw]).squeeze(-1) + bi * hw
        if hi == lo or pix.numel() == 0:
            continue
        ids = {} if src["obj"] is None else {"src_ids": src["obj"][lo:hi].unsqueeze(0),
                                             "dst_ids": dst_obj[pix].unsqueeze(0)}
        work = coeffs[0].dtype  # the profile's dtype promoted with the positions'
        md = None if src["md"] is None else src["md"][lo:hi].unsqueeze(0).to(work)
        val = dipole_pair_sum(dst[pix].unsqueeze(0).to(work), src["pos"][lo:hi].unsqueeze(0).to(work),
                              src["flux"][lo:hi].unsqueeze(0).to(work), *coeffs, md, r_max=float(rmax), **ids)[0]
        out = out.index_add(1, pix, val.T.to(out.dtype))
    return out


# -- public op -------------------------------------------------------------------------------------------------------
def splat_radiosity(
    src_pos: Tensor,
    src_flux: Tensor,
    dst_pos: Tensor,
    dst_mask: Tensor,
    view_proj: Tensor,
    profile: Profile | Sequence[Profile],
    r_max: Tensor | float,
    *,
    src_material: Tensor | None = None,
    src_object: Tensor | None = None,
    dst_object: Tensor | None = None,
    src_distance_scale: Tensor | None = None,
    src_irradiance_scale: Tensor | None = None,
    method: str = "auto",
    window: int | None = None,
    tile_size: int = 16,
    max_memory_mb: float = 256.0,
) -> Tensor:
    """Radiosity image of Shah's splatting: :math:`B(x_o) = \\sum_i R_d^{m_i}(|x_o - x_i| M_{d,i}) E_i dA_i M_{i,i}`.

    The sum runs over the sources whose scaled distance to the pixel's surface point is at most the
    :math:`r_{max}` of their material (a world-space disk, zero beyond), and, when object ids are given, over the
    sources of the pixel's object only (Shah 6.4.3). Several materials are splatted in one pass: each source
    picks its row of the material table with ``src_material``.

    ``method="window"`` is Shah's splat (scatter form): each splat centre is projected with ``view_proj`` and the
    pixels of a window around it are tested and accumulated with ``scatter_add``. With ``window=None`` (eager) the
    window of each splat holds its whole footprint: a closed-form bound of the projected :math:`r_{max}` ball
    (:func:`splat_window_size`) that includes the perspective growth of the ball's near side, whatever the
    surface's slope. Nothing within reach is missed as long as ``dst_pos`` is the G-buffer of ``view_proj`` (each
    pixel's point projects into that pixel); splats are grouped by footprint size (powers of two) and the windows
    are cropped to the bounding box of the covered pixels; a ball that reaches the camera plane gets the whole
    image. A fixed ``window`` :math:`K` (required to trace/export, where it is frozen into the graph) misses the
    pixels of a footprint wider than :math:`K`: splats close to the camera or with a large :math:`r_{max}` in
    pixels (check with :func:`splat_window_size`), and any pixel whose ``dst_pos`` does not project into its own
    pixel. ``method="tile"`` is the gather form: the covered pixels in tiles of ``tile_size`` :math:`^2`, each
    summing over the splats whose reach touches the tile's world-space bounding box; it needs neither
    ``view_proj`` nor a window and misses nothing, but cannot be exported. ``method="gather"`` (plain dipole
    profiles only) sums every covered pixel against every splat of its image in the fused pair sum with the
    truncation (:func:`~torchsss.ops.fused.dipole_pair_sum`, compiled where :func:`~torchsss.ops.fused.use_compiled`
    allows). ``"auto"`` picks ``"window"`` while tracing/exporting; in eager mode ``"gather"`` for plain dipoles when
    nothing is recorded by autograd, the pair sum runs compiled (:func:`~torchsss.ops.fused.would_compile`) and at
    least :data:`GATHER_REACH` of the (pixel, splat) pairs are within reach (estimated on 256 pixels), else
    ``"tile"`` when the covered pixels outnumber the splats (with flux) and ``"window"`` otherwise (the faster form
    in each regime in ``benchmarks/bench_splat.py`` and ``benchmarks/bench_splat_render.py``).

    In eager mode, splats that cannot reach a pixel (off-screen or behind the camera for the window path; sources
    with zero flux unless ``src_flux``/``src_irradiance_scale`` require gradients) are dropped first, materials are
    processed one after the other, and the work is chunked over splats (window) or tiles (tile) so that the
    temporaries stay below about ``max_memory_mb``. Outside autograd, in float32, a frame of at least
    :data:`~torchsss.physics.lut.BULK_MIN_VALUES` (pixel, splat) pairs evaluates the profile of those two paths
    through a table of it (:func:`~torchsss.physics.lut.bulk_profile`, within
    :data:`~torchsss.physics.lut.BULK_TOLERANCE` of the formula). While tracing/exporting, the window path is one
    dense chunk (:math:`S K^2` taps) with per-splat material rows, and the data-dependent checks are skipped.

    Differentiable with respect to ``src_flux``, the parameters the profiles close over (a material module's
    :math:`\\sigma_a`, :math:`\\sigma_s'`, ...) and the modifiers (the truncation is a step: ``r_max`` gets no
    gradient). Gradients also reach the positions
    through the distances (the truncation edge and the window placement contribute none).

    Args:
        src_pos: :math:`(B, S, 3)` source positions :math:`x_i` in mm (light-view samples).
        src_flux: :math:`(B, S, C)` transmitted irradiance times area, :math:`E_i\\,dA_i`.
        dst_pos: :math:`(B, 3, H, W)` camera G-buffer positions :math:`x_o` in mm; ignored (may be NaN/inf) where
            ``dst_mask`` is False.
        dst_mask: :math:`(B, 1, H, W)` bool, pixels that see a surface.
        view_proj: :math:`(4, 4)` or :math:`(B, 4, 4)` world-to-clip matrix of the camera that produced
            ``dst_pos`` (OpenGL conventions, row 0 at the top, :mod:`torchsss.geometry.camera`); used by the
            window path only.
        profile: the material table: one profile, or a sequence of :math:`M` of them, each a callable from
            distances :math:`(..., 1)` or :math:`(..., C)` in mm to :math:`R_d` :math:`(..., C)` in mm^-2 (a
            material module such as :class:`~torchsss.DipoleMaterial`, :class:`~torchsss.BurleyMaterial`,
            :class:`~torchsss.modules.TabulatedMaterial`, or ``functools.partial(dipole_rd, sigma_a=..., ...)``).
        r_max: truncation radius per material in mm (> 0), a number, :math:`()` or :math:`(M,)`, e.g.
            ``material.r_max(eps).amax()``.
        src_material: :math:`(B, S)` integer row of the material table of each source, in ``[0, M)``; required
            when :math:`M > 1`.
        src_object: :math:`(B, S)` integer object id of each source; give both ids or neither.
        dst_object: :math:`(B, 1, H, W)` integer object id of each pixel.
        src_distance_scale: :math:`(B, S, 1)` or :math:`(B, S, C)` distance multiplier :math:`M_d > 0` (Shah eq.
            7.4); the truncation applies to the scaled distance, so the reach is :math:`r_{max}/\\min_c M_d`.
        src_irradiance_scale: :math:`(B, S, 1)` or :math:`(B, S, C)` irradiance modulation :math:`M_i \\ge 0`.
        method: ``"auto"``, ``"window"``, ``"tile"`` or ``"gather"``.
        window: odd window side :math:`K` in pixels for ``"window"``, or None to compute it (eager only).
        tile_size: tile side :math:`T` in pixels for ``"tile"``.
        max_memory_mb: soft bound of the temporaries of one chunk, in MiB (> 0).

    Returns:
        :math:`(B, C, H, W)` radiosity (zero where ``dst_mask`` is False), in the promoted floating dtype of the
        inputs (float16/bfloat16 computed in float32), on their device.

    Raises:
        TypeError: non-tensor, non-floating or complex inputs, non-bool ``dst_mask``, non-integer ids or
            materials, a non-int ``window``/``tile_size``, a non-str ``method``.
        ValueError: tensors on different devices (naming the first one off ``src_pos``'s device) or on the meta
            device, shapes that disagree (the message names the argument), material indices out of range, a
            missing ``src_material`` with several materials, only one of the object ids, non-positive ``r_max``,
            modifiers out of range, a NaN or infinite ``src_pos``, ``src_flux``, ``view_proj`` or ``dst_pos`` under
            the mask (naming the input and the first bad index; see :func:`torchsss.set_validation`), an unknown
            ``method``, an even ``window``, ``"tile"`` or ``window=None`` while tracing/exporting.

    Examples:
        >>> from torchsss.modules import DipoleMaterial
        >>> skin = DipoleMaterial.from_preset("skin1")
        >>> ys, xs = torch.meshgrid(torch.linspace(-3.5, 3.5, 8), torch.linspace(-3.5, 3.5, 8), indexing="ij")
        >>> dst = torch.stack([xs, -ys, torch.zeros_like(xs)])[None]           # a plane z = 0, 1 mm pixels
        >>> vp = torch.diag(torch.tensor([0.25, 0.25, 1.0, 1.0]))              # orthographic, 8 mm wide
        >>> src = torch.tensor([[[0.0, 0.0, 0.0]]])
        >>> out = splat_radiosity(src, torch.ones(1, 1, 3), dst, torch.ones(1, 1, 8, 8, dtype=torch.bool), vp,
        ...                       skin, r_max=2.0, method="window")
        >>> out.shape, bool((out[0, :, 0, 0] == 0).all()), bool((out[0, :, 3, 3] > 0).all())  # corner beyond r_max
        (torch.Size([1, 3, 8, 8]), True, True)
        >>> torch.allclose(out, splat_radiosity(src, torch.ones(1, 1, 3), dst, torch.ones(1, 1, 8, 8,
        ...                dtype=torch.bool), vp, skin, r_max=2.0, method="tile"))
        True
    """
    tracing = is_exporting()  # under plain torch.compile the eager path runs (dynamo breaks the graph)
    # -- validation --
    # devices first, before anything below reads tensor data; the eager path needs data (no meta tensors)
    check_devices(
        {"src_pos": src_pos, "src_flux": src_flux, "dst_pos": dst_pos, "dst_mask": dst_mask, "view_proj": view_proj,
         "r_max": r_max, "src_material": src_material, "src_object": src_object, "dst_object": dst_object,
         "src_distance_scale": src_distance_scale, "src_irradiance_scale": src_irradiance_scale},
        floating=("src_pos", "src_flux", "dst_pos"),
        allow_meta=False,
    )
    dims = _shape(src_pos, "src_pos", "B,S,3")
    dims = _shape(src_flux, "src_flux", "B,S,C", **dims)
    dims = _shape(dst_pos, "dst_pos", "B,3,H,W", **dims)
    b, s, c = src_flux.shape
    h, w = dst_pos.shape[-2:]
    dims = {"B": b, "S": s, "C": c, "H": h, "W": w}
    if not isinstance(dst_mask, Tensor) or dst_mask.dtype != torch.bool:
        got = dst_mask.dtype if isinstance(dst_mask, Tensor) else type(dst_mask).__name__
        raise TypeError(f"dst_mask: expected a bool tensor, got {got}")
    _shape(dst_mask, "dst_mask", "B,1,H,W", **dims)
    vp = _check_view_proj(view_proj, b)
    profiles = _profiles(profile)
    m = len(profiles)
    rm = _per_material(r_max, "r_max", m, src_flux)
    if not isinstance(method, str):
        raise TypeError(f"method: expected a str, got {type(method).__name__}")
    if method not in _METHODS:
        raise ValueError(f"method: expected one of {_METHODS}, got {method!r}")
    if window is not None:
        window = _check_positive_int(window, "window", odd=True)
    tile_size = _check_positive_int(tile_size, "tile_size")
    if isinstance(max_memory_mb, bool) or not isinstance(max_memory_mb, (int, float)):
        raise TypeError(f"max_memory_mb: expected a number > 0, got {type(max_memory_mb).__name__}")
    if not (math.isfinite(max_memory_mb) and max_memory_mb > 0):
        raise ValueError(f"max_memory_mb: expected a finite number > 0, got {max_memory_mb!r}")
    if src_material is None:
        if m != 1:
            raise ValueError(f"src_material: expected a (B, S) integer tensor with M={m} materials, got None")
    else:
        _check_int_tensor(src_material, "src_material")
        _shape(src_material, "src_material", "B,S", **dims)
    if (src_object is None) != (dst_object is None):
        raise ValueError(
            "src_object, dst_object: expected both or neither, got only "
            f"{'src_object' if dst_object is None else 'dst_object'}"
        )
    if src_object is not None:
        _check_int_tensor(src_object, "src_object")
        _check_int_tensor(dst_object, "dst_object")
        _shape(src_object, "src_object", "B,S", **dims)
        _shape(dst_object, "dst_object", "B,1,H,W", **dims)
    md = None if src_distance_scale is None else _check_modifier(src_distance_scale, "src_distance_scale", dims)
    mi = None if src_irradiance_scale is None else _check_modifier(src_irradiance_scale, "src_irradiance_scale", dims)
    auto = method == "auto"
    if auto:
        method = "window"  # eager: refined below, once the sources without flux are dropped
    if tracing and method in ("tile", "gather"):
        raise ValueError(
            "method: expected 'window' while tracing/exporting (the tile path builds candidate lists of "
            f"data-dependent size; the gather runs the compiled pair sum in blocks), got {method!r}"
        )
    if tracing and method == "window" and window is None:
        raise ValueError(
            "window: expected an odd int while tracing/exporting (a window computed from the data "
            "would be frozen into the graph), got None"
        )
    if not tracing:
        _check_profile_channels(profiles, c, src_flux)
        check_positive(rm, "r_max")
        if md is not None:
            check_positive(md, "src_distance_scale")
        if mi is not None:
            check_nonnegative(mi, "src_irradiance_scale")
        check_finite_inputs({"src_pos": src_pos, "src_flux": src_flux, "view_proj": vp})
        check_finite_inputs({"dst_pos": dst_pos}, where=dst_mask)  # off the mask a position may hold anything
        if src_material is not None and src_material.numel() > 0 and not skip_value_checks(src_material):
            lo, hi = int(src_material.min()), int(src_material.max())
            if lo < 0 or hi >= m:
                raise ValueError(
                    f"src_material: expected indices in [0, {m}) (rows of the material table), "
                    f"got {lo if lo < 0 else hi}"
                )

    tensors = [src_pos, src_flux, dst_pos, rm] + [x for x in (md, mi) if x is not None]
    out_dtype, dtype = compute_dtype(*tensors)
    if h * w == 0 or b == 0:
        return torch.zeros(b, c, h, w, dtype=out_dtype, device=dst_pos.device)

    # -- flat per-splat arrays (rows sorted by batch element) --
    n = b * s
    rm = rm.to(dtype)
    mat = (
        torch.zeros(n, dtype=torch.int64, device=src_pos.device)
        if src_material is None
        else src_material.reshape(n).to(torch.int64)
    )
    flux = src_flux.to(dtype).reshape(n, c)
    if mi is not None:
        flux = flux * mi.to(dtype).reshape(n, -1)
    md_flat = None if md is None else md.to(dtype).reshape(n, -1)
    reach = rm[mat] if md_flat is None else rm[mat] / md_flat.amin(-1)
    src = {
        "pos": src_pos.to(dtype).reshape(n, 3),
        "flux": flux,
        "batch": torch.arange(n, device=src_pos.device) // (s if tracing else max(s, 1)),
        "reach": reach,
        "md": md_flat,
        "obj": None if src_object is None else src_object.reshape(n),
    }
    # -- receivers: sanitised (masked-out entries may be NaN), flattened channels-first --
    mask_flat = dst_mask.reshape(b * h * w)
    dst = torch.where(dst_mask, dst_pos.to(dtype), torch.zeros((), dtype=dtype, device=dst_pos.device))
    dst_obj = None if dst_object is None else dst_object.reshape(b * h * w)

    if tracing:
        src.update(profiles=profiles, mat=mat, rmax=rm[mat])
        dst_flat = dst.permute(1, 0, 2, 3).reshape(3, b * h * w)
        out = _splat_window_traced(src, dst_flat, mask_flat, dst_obj, vp.to(dtype), b, h, w, window)
        return out.reshape(c, b, h, w).transpose(0, 1).contiguous().to(out_dtype)

    # eager: drop sources without flux (unless their flux needs a gradient), then one material at a time
    if not (torch.is_grad_enabled() and (src_flux.requires_grad or (mi is not None and mi.requires_grad))):
        keep = torch.nonzero((flux != 0).any(-1)).squeeze(-1)
        if keep.numel() < n:
            src, mat = _take(src, keep), mat[keep]
    dst_points = dst.permute(0, 2, 3, 1).reshape(b * h * w, 3)
    dipoles = [dipole_params(p, dtype, dst.device, c) for p in profiles] if method == "gather" or auto else []
    if method == "gather" and any(d is None for d in dipoles):
        raise ValueError("method: expected a plain dipole profile for 'gather' (the fused pair sum evaluates the "
                         "analytic dipole), got another profile")
    pairs = float(mask_flat.sum()) * src["pos"].shape[0] / max(b, 1) ** 2  # per image: its pixels x its splats
    gather = method == "gather" or (auto and all(_gather_ok(d, src, dst_points, pairs) for d in dipoles)
                                    and _reach_share(src, dst_points, mask_flat) >= GATHER_REACH)
    if auto and not gather:
        # measured rule (benchmarks/results/splat*.md): the gather form wins when receivers outnumber the sources
        # (2-3x with 15k pixels and 0.3k-4.7k splats), the scatter form when the sources outnumber the receivers
        # (1.3-7.7x with 2k pixels and 7k-19k splats, render_splat on the default scene)
        method = "tile" if int(mask_flat.sum()) > src["pos"].shape[0] else "window"
    budget = int(max_memory_mb * (1 << 20))
    out = torch.zeros(c, b * h * w, dtype=dtype, device=dst_pos.device)
    if gather:
        pass
    elif method == "window":
        dst_flat = dst.permute(1, 0, 2, 3).reshape(3, b * h * w)
    else:
        grid = dst.permute(0, 2, 3, 1)
        obj = None if dst_object is None else dst_object[:, 0]
        tiles = [_Tiles(grid[i], dst_mask[i, 0], None if obj is None else obj[i], tile_size) for i in range(b)]
    for k in torch.unique(mat).tolist() if m > 1 else ([0] if mat.numel() else []):
        sub = src if m == 1 else _take(src, torch.nonzero(mat == k).squeeze(-1))
        row = _material_row(profiles[k], rm[k], pairs, dtype, dst_pos.device)
        if gather:
            out = _splat_gather(out, sub, dipoles[k][1], rm[k], dst_points, mask_flat, dst_obj, b, h * w)
        elif method == "window":
            out = _splat_window(out, sub, row, dst_flat, mask_flat, dst_obj, vp.to(dtype), h, w, window, budget)
        else:
            out = _splat_tile(out, sub, row, tiles, h, w, budget)
    return out.reshape(c, b, h, w).transpose(0, 1).contiguous().to(out_dtype)
