"""Texture-space importance sampling (Chang et al., sections 2.2-3): draw points with density proportional to a map.

Chang et al. sample the texture atlas with density :math:`p(x) = E'(x) / E'_{avg}` by inverting its CDF. Their
Fig. 2b orders the CDF by the mipmap: each sample walks a *sum pyramid* from its 1x1 top down to the texels,
choosing one of the 2x2 children at every level. This module implements that walk with gathers only (no
``searchsorted``, no data-dependent Python control flow; the levels are unrolled), so it runs unchanged on any
device and exports to ONNX, and a row-major CDF + ``torch.searchsorted`` sampler (Fig. 2a) to test it against.

Both samplers return continuous pixel coordinates: texel ``(row i, column j)`` covers
:math:`[j, j+1) \\times [i, i+1)`, so ``xy.floor()`` is the texel and ``xy + 0.5`` would be a centre. The point
is uniform inside its texel, so the density per unit pixel area is piecewise constant and equals
``p = pdf[texel] / pdf.sum()``. An importance-sampled estimate of :math:`\\int f` over the map is therefore
``mean(f(xy) / p)`` (pixel units) and Chang's eq. 10 is ``E'_avg / N * sum R_d`` with ``E'_avg`` the top of
:func:`sum_pyramid` times the texel area.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from torchsss._checks import (
    _report,
    check_devices,
    check_nonnegative,
    check_tensor,
    compute_dtype,
    is_tracing,
    skip_value_checks,
)

__all__ = ["icdf_sample", "icdf_sample_reference", "pyramid_levels", "sum_pyramid"]

#: Largest accepted ``levels``: a 32768 x 32768 base (2^30 texels, 4 GiB in float32).
MAX_LEVELS = 15

#: Samples per chunk (all batch elements together) of the in-place descent on the CPU: its eight buffers stay in
#: the cache. Measured on the project's 2-core machine, 1e6 samples from a 1024^2 map: 2^12: 190 ms, 2^14: 107 ms,
#: 2^16: 96 ms, 2^18: 174 ms, one chunk: 238 ms (descent only).
_CHUNK = 1 << 16

#: Deepest pyramid whose texel indices (< 4^levels) a float type holds exactly; deeper ones track them in float64.
_FLOAT_INDEX_LEVELS = {torch.float32: 12, torch.float64: MAX_LEVELS}


# -- validation ---------------------------------------------------------------------------------------------------
def pyramid_levels(height: int, width: int) -> int:
    """Number of levels above the base of the smallest power-of-two square holding a ``height x width`` map.

    That is :math:`\\lceil \\log_2 \\max(H, W) \\rceil`; the pyramid then has ``levels + 1`` entries.

    Examples:
        >>> [pyramid_levels(1, 1), pyramid_levels(7, 13), pyramid_levels(512, 512), pyramid_levels(1, 513)]
        [0, 4, 9, 10]
    """
    return (max(int(height), int(width)) - 1).bit_length()


def _check_pdf(pdf: object, levels: object, values: bool = True) -> tuple[int, int, int, int]:
    """Validate ``pdf`` (B, 1, H, W), finite and >= 0 (unless ``values=False``), and ``levels``.

    Returns ``(B, H, W, levels)``.
    """
    check_tensor(pdf, "pdf")
    # not check_shape: its int() would freeze dynamic sizes while exporting
    if pdf.dim() != 4 or pdf.shape[1] != 1:
        raise ValueError(f"pdf: expected shape (B, 1, H, W), got {tuple(pdf.shape)}")
    b, _, h, w = pdf.shape
    if not is_tracing() and (h < 1 or w < 1):
        raise ValueError(f"pdf: expected H >= 1 and W >= 1, got shape {tuple(pdf.shape)}")
    if levels is None:
        if is_tracing():
            raise ValueError(
                "levels: expected an int while exporting (the pyramid depth is frozen into the graph), got None"
            )
        levels = pyramid_levels(h, w)
    elif isinstance(levels, bool) or not isinstance(levels, int):
        raise TypeError(f"levels: expected an int or None, got {type(levels).__name__}")
    elif not 0 <= levels <= MAX_LEVELS:
        raise ValueError(f"levels: expected an int in [0, {MAX_LEVELS}], got {levels}")
    elif h > 2**levels or w > 2**levels:
        raise ValueError(
            f"levels: expected 2**levels >= max(H, W) = {max(h, w)}, got levels={levels} ({2**levels} x {2**levels})"
        )
    if values:
        check_nonnegative(pdf, "pdf")
    return b, h, w, levels


def _check_u(u: object, b: int) -> None:
    """Validate ``u`` (B, N, 2) with the same ``B`` as ``pdf`` and values in [0, 1)."""
    check_tensor(u, "u")
    if u.dim() != 3 or u.shape[2] != 2:
        raise ValueError(f"u: expected shape (B, N, 2), got {tuple(u.shape)}")
    if u.shape[0] != b:
        raise ValueError(f"u: expected shape (B, N, 2) with B={b} (pdf's batch), got {tuple(u.shape)}")
    # fast check first (NaN propagates through amin/amax and fails both comparisons), then the detailed message
    if not skip_value_checks(u) and u.numel() and not (bool(u.amin() >= 0) and bool(u.amax() < 1)):
        _report(u, ~((u >= 0) & (u < 1)), "u", "values in [0, 1)")


# -- shared pieces ------------------------------------------------------------------------------------------------
def _one_minus(dtype: torch.dtype) -> float:
    """The largest float of ``dtype`` below 1 (1 - eps/2): the upper clamp of a rescaled uniform."""
    return 1.0 - torch.finfo(dtype).eps / 2


def _place(index: Tensor, frac: Tensor, dtype: torch.dtype) -> Tensor:
    """``index + frac`` in ``dtype``, kept strictly below ``index + 1`` so that ``floor`` gives back the texel.

    ``frac`` lies in [0, 1) but the rounded sum can reach ``index + 1`` (e.g. 62 + 0.99999994 in float32).
    ``n - n * eps/2`` with ``n = index + 1 >= 1`` (the product is exact) rounds to the float just below ``n``.
    Written as a subtraction, not as ``n * (1 - eps/2)``: the ONNX optimiser (onnxscript 0.7) drops a
    multiplication by a constant that close to 1 as if it were an identity.
    """
    i = index.to(dtype)
    n = i + 1.0
    return torch.minimum(i + frac.to(dtype), n - n * (torch.finfo(dtype).eps / 2))


def _children(cur: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Split a (B, s, s) level (s even) into 2x2 children; return ``(c00, c10, top, bottom, parent)``.

    ``top = c00 + c01``, ``bottom = c10 + c11`` and ``parent = top + bottom``, always in this order (strided
    slices and elementwise adds, no reduction kernel), so the sums are the same to the bit in eager mode and in
    onnxruntime.
    """
    c00, c10 = cur[:, 0::2, 0::2], cur[:, 1::2, 0::2]
    top = c00 + cur[:, 0::2, 1::2]
    bot = c10 + cur[:, 1::2, 1::2]
    return c00, c10, top, bot, top + bot


def _share(part: Tensor, whole: Tensor) -> Tensor:
    """``part / whole``, 0 where ``whole == 0`` (never visited); exact 1 where ``part == whole``.

    The base holds no subnormal numbers (see :func:`_normalised_base`), so every nonzero ``whole`` is at least
    ``tiny`` and the clamp changes nothing but zeros; no NaN in values or gradients.
    """
    return part / whole.clamp(min=torch.finfo(whole.dtype).tiny)


def _normalised_base(x: Tensor, amax: Tensor, empty: Tensor, size: int) -> Tensor:
    """(B, H, W) map -> (B, size, size) base: divided by its max, all-zero maps -> ones, subnormals -> 0, padded.

    Dividing by the max keeps the sums finite; flushing values below ``tiny`` (relative to the max: below
    1e-38 in float32) to zero makes ``x / x == 1`` hold for every nonzero sum, so a child whose sibling is empty
    gets a share of exactly 1.
    """
    x = x / (amax + empty) + empty
    tiny = torch.finfo(x.dtype).tiny
    x = F.threshold(x, tiny * (1.0 - torch.finfo(x.dtype).eps), 0.0)  # keeps x >= tiny
    h, w = x.shape[-2:]
    return F.pad(x, (0, size - w, 0, size - h))


def _split_tables(base: Tensor, levels: int) -> tuple[list[Tensor], list[Tensor], Tensor]:
    """Split probabilities of the sum pyramid of a (B, S, S) base, S = 2**levels, for the descent.

    Returns ``(rows, cols, total)``. For the ``M = (S / 2^{l+1})^2`` parents of level ``l`` (row-major index
    ``m = i * S/2^{l+1} + j``): ``rows[l][:, m]`` is the share of the upper pair of children,
    ``(c00 + c01) / parent``, and ``cols[l][:, m + M dy]`` the share of the left child in the upper (``dy = 0``)
    or lower (``dy = 1``) pair. A zero-mass child gets share exactly 0 and its sibling exactly 1, so it is never
    taken. ``total`` is the (B,) sum of the base.
    """
    rows, cols = [], []
    cur = base
    for _ in range(levels):
        c00, c10, top, bot, cur = _children(cur)
        rows.append(_share(top, cur).flatten(1))
        cols.append(torch.cat((_share(c00, top).flatten(1), _share(c10, bot).flatten(1)), dim=1))
    return rows, cols, cur.flatten(1)[:, 0]


def _warp(u: Tensor, share: Tensor, one_minus: float) -> tuple[Tensor, Tensor]:
    """Binary choice with a uniform: ``u >= share`` takes the second child; rescale ``u`` to [0, 1) given it.

    Returns ``(second, u')`` with ``second`` as 0/1 in ``u``'s dtype and ``u' = u / share`` (first child) or
    ``(u - share) / (1 - share)`` (second child): given the choice, ``u'`` is again uniform (sample warping), so
    one pair of uniforms drives the whole walk and what is left of it places the point inside the texel. The map
    is monotone and sends ``[0, share)`` and ``[share, 1)`` onto ``[0, 1)`` (half-open intervals to half-open
    intervals), so dyadic points such as Sobol's keep their strata exactly; a mirrored map (one subtraction
    fewer) would send the boundary points to the neighbouring stratum. ``u'`` is clamped to [0, 1) against
    rounding. The denominator is never 0: ``share = 0`` always takes the second child and ``share = 1`` the first
    (``u < 1``). Only multiply-adds, a divide and a compare: ``torch.where`` is several times slower on the CPU.
    """
    second = (u >= share).to(u.dtype)
    den = (second - share).abs()  # share or 1 - share
    return second, (torch.addcmul(u, second, share, value=-1.0) / den).clamp(max=one_minus)


def _descend(
    rows: list[Tensor], cols: list[Tensor], ux: Tensor, uy: Tensor, idt: torch.dtype, one_minus: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Functional descent (autograd, tracing, export). Returns ``(row, col, ux, uy)`` at the texel."""
    levels = len(rows)
    row = torch.zeros(ux.shape, dtype=idt, device=ux.device)
    col = torch.zeros_like(row)
    for level in range(levels - 1, -1, -1):
        half = 2 ** (levels - level - 1)  # parents per row at this level
        node = torch.add(col, row, alpha=half)  # row-major parent index
        down, uy = _warp(uy, torch.gather(rows[level], 1, node.long()), one_minus)
        pair = torch.add(node, down.to(idt), alpha=half * half)
        right, ux = _warp(ux, torch.gather(cols[level], 1, pair.long()), one_minus)
        row = torch.add(down.to(idt), row, alpha=2)
        col = torch.add(right.to(idt), col, alpha=2)
    return row, col, ux, uy


def _descend_inplace(
    rows: list[Tensor], cols: list[Tensor], ux: Tensor, uy: Tensor, idt: torch.dtype, one_minus: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`_descend` with preallocated buffers and in-place ops (inference only; same ops, same results).

    About 1.6x faster on the CPU for 1e6 samples (fewer allocations and memory passes). ``ux``/``uy`` must be
    private contiguous copies: they are overwritten.
    """
    levels = len(rows)
    row = torch.zeros(ux.shape, dtype=idt, device=ux.device)
    col = torch.zeros_like(row)
    node = torch.empty_like(row)
    second = torch.empty_like(ux)
    share = torch.empty_like(ux)
    den = torch.empty_like(ux)
    index = torch.empty(ux.shape, dtype=torch.long, device=ux.device)

    def warp(u: Tensor, table: Tensor) -> None:
        torch.gather(table, 1, index, out=share)
        torch.ge(u, share, out=second)
        torch.sub(second, share, out=den).abs_()
        u.addcmul_(second, share, value=-1.0).div_(den).clamp_(max=one_minus)

    for level in range(levels - 1, -1, -1):
        half = 2 ** (levels - level - 1)
        torch.add(col, row, alpha=half, out=node)
        index.copy_(node)
        warp(uy, rows[level])
        row.mul_(2).add_(second)
        index.copy_(node.add_(second, alpha=half * half))
        warp(ux, cols[level])
        col.mul_(2).add_(second)
    return row, col, ux, uy


# -- public API ---------------------------------------------------------------------------------------------------
def sum_pyramid(pdf: Tensor, levels: int | None = None) -> list[Tensor]:
    """Sum mip pyramid of a map: level 0 is the map zero-padded to a power-of-two square, each next level sums 2x2.

    Level ``l`` has shape :math:`(B, 1, S/2^l, S/2^l)` with :math:`S = 2^{levels}`; its texel ``(i, j)`` is
    the sum of the map over rows :math:`[2^l i, 2^l (i+1))` and columns :math:`[2^l j, 2^l (j+1))`. The last
    level is the :math:`(B, 1, 1, 1)` total (Chang's :math:`E'_{avg}` in texel units). Each 2x2 sum is
    ``(c00 + c01) + (c10 + c11)``, a pairwise summation: the relative error of any node is at most about
    ``levels`` ulps, float32 is accurate even for 4096^2 maps. Differentiable.

    Args:
        pdf: :math:`(B, 1, H, W)` non-negative finite map (any ``H, W >= 1``).
        levels: pyramid depth: the base is padded to :math:`2^{levels}` square. Default (``None``): the smallest
            that fits, :func:`pyramid_levels` ``(H, W)``. Required while exporting.

    Returns:
        ``levels + 1`` tensors, finest first, in ``pdf``'s dtype (float16/bfloat16 are summed in float32 and cast
        back, so sums can overflow the narrow type).

    Raises:
        TypeError: a non-tensor or non-floating ``pdf``; a non-int ``levels``.
        ValueError: ``pdf`` not :math:`(B, 1, H, W)`, empty, negative, NaN or infinite; ``levels`` out of
            :math:`[\\lceil \\log_2 \\max(H, W) \\rceil, 15]`.

    Examples:
        >>> pyr = sum_pyramid(torch.arange(1.0, 7.0).reshape(1, 1, 2, 3))
        >>> [tuple(t.shape) for t in pyr]
        [(1, 1, 4, 4), (1, 1, 2, 2), (1, 1, 1, 1)]
        >>> pyr[1][0, 0]
        tensor([[12.,  9.],
                [ 0.,  0.]])
        >>> pyr[-1].item()
        21.0
    """
    _, h, w, levels = _check_pdf(pdf, levels)
    out_dtype, dtype = compute_dtype(pdf)
    size = 2**levels
    cur = F.pad(pdf.to(dtype)[:, 0], (0, size - w, 0, size - h))
    out = [cur]
    for _ in range(levels):
        cur = _children(cur)[-1]
        out.append(cur)
    return [t.unsqueeze(1).to(out_dtype) for t in out]


def icdf_sample(pdf: Tensor, u: Tensor, levels: int | None = None) -> tuple[Tensor, Tensor]:
    """Draw points with density proportional to ``pdf`` by descending its sum pyramid (Chang Fig. 2b).

    Each sample starts at the pyramid's 1x1 top. At every level it picks the upper or lower pair of the 2x2
    children with ``u[..., 1]`` (probability = the pair's share of the node's sum), then the left or right child of
    that pair with ``u[..., 0]``, and rescales the uniform it used to [0, 1) given the choice (sample warping: no
    new random numbers, and stratified or low-discrepancy ``u`` stay well distributed). At the texel what is left
    of the two uniforms places the point uniformly inside it. The pyramid is stored as split probabilities (the
    upper pair's share of each node, the left child's share of each pair), so a level costs two gathers and about
    fifteen elementwise ops per sample, unrolled in Python over the (static) number of levels: no
    ``searchsorted``, no data-dependent control flow. It exports to ONNX (dynamo, opset 18 or 20) with ``B``,
    ``N``, ``H``, ``W`` dynamic when ``levels`` is given, and onnxruntime reproduces eager mode to the bit:
    every sum is a fixed sequence of elementwise adds (no pooling or reduction kernel whose order could differ).

    The map is divided by its maximum before the pyramid is built (no overflow in the sums) and texels below
    ``tiny`` times the maximum (1.2e-38 in float32, 2.2e-308 in float64) count as empty. An all-zero map (per
    batch element) has no density: its points are placed uniformly over :math:`[0, W) \\times [0, H)` and ``p``
    is 0. Computed in the promoted dtype of ``pdf`` and ``u`` (float16/bfloat16 in float32): the walk consumes
    about ``levels`` bits of each uniform, so float32 ``u`` leaves roughly :math:`24 - levels` bits for the
    position inside a texel, float64 ``u`` :math:`53 - levels`. Without autograd or tracing the descent runs
    in place, in chunks of 65,536 samples whose buffers stay in the CPU cache (same operations, same results as
    the autograd/export path; 2-3x faster for 1e6 samples). Memory: the padded :math:`2^{levels}` square base
    and the split tables (as much again), the outputs, and about eight buffers of one chunk (inference) or of
    :math:`(B, N)` (autograd/export). Gradients flow to ``pdf`` and ``u`` through ``p`` and the in-texel
    position (the texel index itself is piecewise constant).

    Args:
        pdf: :math:`(B, 1, H, W)` non-negative finite map, any ``H, W >= 1`` (e.g. Chang's :math:`E'`); it need
            not be normalised.
        u: :math:`(B, N, 2)` uniforms in :math:`[0, 1)` (values outside raise): pseudo-random, stratified or
            Sobol. ``u[..., 0]`` drives x (columns), ``u[..., 1]`` drives y (rows).
        levels: pyramid depth, :math:`2^{levels} \\ge \\max(H, W)`; default the smallest that fits. A fixed value
            (e.g. 10 for maps up to 1024^2) lets one exported graph serve every size up to :math:`2^{levels}`.
            Extra levels pass through zero-padding and do not change the distribution, but change which point a
            given ``u`` maps to (by rounding).

    Returns:
        ``(xy, p)``: ``xy`` :math:`(B, N, 2)` continuous pixel coordinates ``(x, y)`` in
        :math:`[0, W) \\times [0, H)` (texel = ``xy.floor()``); ``p`` :math:`(B, N)` the density of the sample per
        unit pixel area, ``pdf[texel] / pdf.sum()`` (0 for an all-zero map). Promoted dtype, ``pdf``'s device.

    Raises:
        TypeError: a non-tensor, non-floating or complex ``pdf``/``u``; a non-int ``levels``.
        ValueError: ``pdf`` and ``u`` on different devices; ``pdf`` not :math:`(B, 1, H, W)`, empty, negative,
            NaN or infinite; ``u`` not :math:`(B, N, 2)` with the same ``B`` or outside :math:`[0, 1)`;
            ``levels`` too small or above 15. Value checks are skipped while tracing/exporting and on the meta
            device (which gives the outputs' shapes).

    Examples:
        >>> pdf = torch.tensor([[[[0.0, 3.0], [1.0, 0.0]]]])
        >>> u = torch.tensor([[[0.5, 0.5], [0.5, 0.875]]])
        >>> xy, p = icdf_sample(pdf, u)
        >>> xy
        tensor([[[1.5000, 0.6667],
                 [0.5000, 1.5000]]])
        >>> p
        tensor([[0.7500, 0.2500]])
    """
    check_devices({"pdf": pdf, "u": u}, floating=True)  # first: before anything reads the data
    b, _, _, levels = _check_pdf(pdf, levels, values=False)
    _check_u(u, b)
    out_dtype, dtype = compute_dtype(pdf, u)
    size = 2**levels

    x = pdf.to(dtype)[:, 0]
    amax = x.amax(dim=(-2, -1), keepdim=True)
    # fast value check (NaN propagates through amax/amin); the detailed message comes from check_nonnegative
    if not skip_value_checks(x) and x.numel() and not (bool(x.amin() >= 0) and bool(torch.isfinite(amax).all())):
        check_nonnegative(pdf, "pdf")
    empty = (amax <= 0).to(dtype)  # (B, 1, 1): all-zero map -> uniform over the H x W region, p = 0
    base = _normalised_base(x, amax, empty, size)
    rows, cols, total = _split_tables(base, levels)

    # Texel indices are tracked as floats (exact below 2**24 in float32, hence float64 past 4096^2): the CPU is
    # several times faster at float than at int64 arithmetic; they are cast to int64 only to gather.
    idt = dtype if levels <= _FLOAT_INDEX_LEVELS[dtype] else torch.float64
    one_minus = _one_minus(dtype)

    def finish(row: Tensor, col: Tensor, ux: Tensor, uy: Tensor) -> tuple[Tensor, Tensor]:
        xy = torch.stack((_place(col, ux, out_dtype), _place(row, uy, out_dtype)), dim=-1)
        texel = torch.gather(base.flatten(1), 1, torch.add(col, row, alpha=size).long())
        return xy, (texel / total.unsqueeze(1) * (1.0 - empty.flatten(1))).to(out_dtype)

    if is_tracing() or (torch.is_grad_enabled() and (pdf.requires_grad or u.requires_grad)):
        return finish(*_descend(rows, cols, u[..., 0].to(dtype), u[..., 1].to(dtype), idt, one_minus))

    # inference: in place, on the CPU in chunks of about _CHUNK samples whose buffers stay in the cache (2-3x
    # faster for 1e6 samples); elsewhere (GPU) in one chunk, as kernel launches would dominate small chunks
    n = u.shape[1]
    xy = torch.empty((b, n, 2), dtype=out_dtype, device=pdf.device)
    p = torch.empty((b, n), dtype=out_dtype, device=pdf.device)
    step = max(1, _CHUNK // max(b, 1)) if pdf.device.type == "cpu" else max(n, 1)
    for start in range(0, n, step):
        part = slice(start, min(n, start + step))
        ux = u[:, part, 0].to(dtype=dtype, memory_format=torch.contiguous_format, copy=True)
        uy = u[:, part, 1].to(dtype=dtype, memory_format=torch.contiguous_format, copy=True)
        xy[:, part], p[:, part] = finish(*_descend_inplace(rows, cols, ux, uy, idt, one_minus))
    return xy, p


def icdf_sample_reference(pdf: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Reference sampler: row-major CDF (float64 ``cumsum``) inverted with ``torch.searchsorted`` (Chang Fig. 2a).

    The texel is the first one whose cumulative sum exceeds ``u[..., 0] * total`` in row-major order; the part of
    ``u[..., 0]`` left inside that texel's CDF step gives the x offset and ``u[..., 1]`` the y offset. Same
    contract and same distribution as :func:`icdf_sample` (the two map a given ``u`` to different points). The
    x offset reuses the bits of ``u[..., 0]`` that the search did not consume (:math:`24 - \\log_2(HW)` for
    float32 ``u``): pass float64 ``u`` for a fine placement in large maps. Eager mode only (``searchsorted``
    does not export to ONNX).

    Args:
        pdf: :math:`(B, 1, H, W)` non-negative finite map.
        u: :math:`(B, N, 2)` uniforms in :math:`[0, 1)`.

    Returns:
        ``(xy, p)`` as :func:`icdf_sample`.

    Raises:
        TypeError, ValueError: as :func:`icdf_sample`; also ValueError on the meta device (the search needs data).

    Examples:
        >>> pdf = torch.tensor([[[[0.0, 3.0], [1.0, 0.0]]]])
        >>> xy, p = icdf_sample_reference(pdf, torch.tensor([[[0.5, 0.5], [0.875, 0.25]]]))
        >>> xy
        tensor([[[1.6667, 0.5000],
                 [0.5000, 1.2500]]])
        >>> p
        tensor([[0.7500, 0.2500]])
    """
    check_devices({"pdf": pdf, "u": u}, floating=True, allow_meta=False)
    b, h, w, _ = _check_pdf(pdf, None)
    _check_u(u, b)
    out_dtype, _ = compute_dtype(pdf, u)
    f64 = torch.float64

    flat = pdf.to(f64).reshape(b, h * w)
    empty = flat.sum(dim=1, keepdim=True) <= 0
    flat = torch.where(empty, torch.ones_like(flat), flat)
    cdf = torch.cumsum(flat, dim=1)
    total = cdf[:, -1:]
    t = torch.minimum(u[..., 0].to(f64) * total, torch.nextafter(total, torch.zeros_like(total)))
    k = torch.searchsorted(cdf, t.contiguous(), right=True).clamp_(max=h * w - 1)  # cdf[k-1] <= t < cdf[k]
    hi = torch.gather(cdf, 1, k)
    lo = torch.where(k > 0, torch.gather(cdf, 1, (k - 1).clamp(min=0)), torch.zeros_like(hi))
    fx = ((t - lo) / (hi - lo)).clamp(0.0, _one_minus(f64))
    xy = torch.stack((_place(k % w, fx, out_dtype), _place(k // w, u[..., 1], out_dtype)), dim=-1)
    p = torch.where(empty, torch.zeros_like(t), torch.gather(flat, 1, k) / total)
    return xy, p.to(out_dtype)
