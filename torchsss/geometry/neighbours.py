"""Pairs of points within a radius in 3-D, for near-field sums that must not follow texture seams.

Two paths with one answer: a k-d tree (scipy, on the CPU) and a uniform grid of cells as wide as the radius, sorted
once, that lists each receiver's candidates from its 27 neighbouring cells with tensor ops on the points' own device
(no host round trip; the hybrid's per-frame near-field pairs on a GPU spent most of their frame in the tree).
"""

from __future__ import annotations

import itertools
import math
import numbers

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

__all__ = ["ball_pairs"]

#: Candidate pairs (before the distance test) per block of the grid path: bounds its temporaries (about 150 bytes
#: each in float64, 0.3 GB a block).
GRID_BLOCK = 1 << 21
#: Pairs per block of receivers of the k-d tree path (bounds its listing's temporaries, about 60 bytes a pair).
KDTREE_BLOCK = 1 << 20

_METHODS = ("auto", "kdtree", "grid")


def ball_pairs(receivers: Tensor, sources: Tensor, radius_mm: float, *,
               max_pairs: int = 50_000_000, method: str = "auto") -> tuple[Tensor, Tensor, Tensor]:
    """Every (receiver, source) pair within ``radius_mm`` in 3-D: ``rows``, ``cols``, ``distance``.

    A pair is in when its distance, computed in float64, is at most ``radius_mm``. Both paths return the same pairs
    (tested); within one receiver the order of the sources may differ between them.

    Args:
        receivers: :math:`(M, 3)` positions (mm).
        sources: :math:`(N, 3)` positions (mm), on the receivers' device.
        radius_mm: the radius (mm, >= 0).
        max_pairs: refuse (ValueError) more pairs than this. The tree counts them before listing; the grid stops
            listing as soon as its count passes this, so memory stays within ``max_pairs`` plus one block.
        method: ``"kdtree"`` (scipy's k-d tree on CPU copies), ``"grid"`` (a uniform grid, tensor ops on the
            points' device, blocks of :data:`GRID_BLOCK` candidates) or ``"auto"``: the tree for CPU points, the
            grid for points on an accelerator.

    Returns:
        ``rows`` :math:`(P,)` int64 receiver indices, sorted; ``cols`` :math:`(P,)` int64 source indices;
        ``distance`` :math:`(P,)` mm, in ``receivers``' dtype and device.

    Raises:
        TypeError: non-tensor or non-floating points.
        ValueError: shapes other than :math:`(\\cdot, 3)`, a negative or non-finite radius, too many pairs.

    Examples:
        >>> r = torch.tensor([[0.0, 0, 0], [5.0, 0, 0]])
        >>> s = torch.tensor([[0.5, 0, 0], [4.0, 0, 0], [9.0, 0, 0]])
        >>> rows, cols, d = ball_pairs(r, s, 1.5)
        >>> rows.tolist(), cols.tolist(), d.tolist()
        ([0, 1], [0, 1], [0.5, 1.0])
    """
    for name, x in (("receivers", receivers), ("sources", sources)):
        if not isinstance(x, Tensor) or not x.is_floating_point():
            raise TypeError(f"{name}: expected a floating tensor of shape (n, 3), got "
                            f"{x.dtype if isinstance(x, Tensor) else type(x).__name__}")
        if x.dim() != 2 or x.shape[1] != 3:
            raise ValueError(f"{name}: expected shape (n, 3), got {tuple(x.shape)}")
    if isinstance(radius_mm, bool) or not isinstance(radius_mm, numbers.Real) or not math.isfinite(radius_mm) \
            or radius_mm < 0:
        raise ValueError(f"radius_mm: expected a finite number >= 0, got {radius_mm!r}")
    if method not in _METHODS:
        raise ValueError(f"method: expected one of {_METHODS}, got {method!r}")
    if sources.device != receivers.device:
        raise ValueError(f"sources: expected the receivers' device {receivers.device}, got {sources.device}")
    if method == "grid" or (method == "auto" and receivers.device.type != "cpu"):
        return _grid_pairs(receivers, sources, float(radius_mm), max_pairs)
    rec = receivers.detach().to(torch.float64).cpu().numpy()
    src = sources.detach().to(torch.float64).cpu().numpy()
    tree_s = cKDTree(src)
    counts = np.asarray(tree_s.query_ball_point(rec, float(radius_mm), return_length=True), dtype=np.int64)
    count = int(counts.sum())
    if count > max_pairs:
        raise ValueError(f"max_pairs: expected at most {max_pairs} pairs within {radius_mm:.3g} mm, got {count} "
                         f"({rec.shape[0]} receivers, {src.shape[0]} sources); lower the radius or thin the sources")
    dev, dtype = receivers.device, receivers.dtype
    rows = torch.empty(count, dtype=torch.int64)
    cols = torch.empty(count, dtype=torch.int64)
    dist = torch.empty(count, dtype=dtype)
    # blocks of consecutive receivers with about KDTREE_BLOCK pairs each, listed, ordered by (receiver, source) and
    # written into the outputs (all pairs at once, their structured array, its sort and the copies took 0.6 GB
    # over the 8.4M pairs of the hybrid's frame on the shared bunny)
    ends = np.searchsorted(np.cumsum(counts), np.arange(KDTREE_BLOCK, count + KDTREE_BLOCK, KDTREE_BLOCK), "right")
    bounds = sorted({0, rec.shape[0], *(int(e) for e in ends if 0 < e < rec.shape[0])})
    at = 0
    for lo, hi in itertools.pairwise(bounds):
        sdm = cKDTree(rec[lo:hi]).sparse_distance_matrix(tree_s, float(radius_mm), output_type="ndarray")
        order = np.lexsort((sdm["j"], sdm["i"]))
        k = order.shape[0]
        if at + k > rows.shape[0]:  # a pair at the radius counted one way and listed the other: room for it
            extra = at + k - rows.shape[0]
            rows, cols = torch.cat([rows, rows.new_empty(extra)]), torch.cat([cols, cols.new_empty(extra)])
            dist = torch.cat([dist, dist.new_empty(extra)])
        rows[at:at + k] = torch.from_numpy(sdm["i"][order].astype(np.int64)) + lo
        cols[at:at + k] = torch.from_numpy(sdm["j"][order].astype(np.int64))
        dist[at:at + k] = torch.from_numpy(sdm["v"][order]).to(dtype)
        at += k
        del sdm, order
    return rows[:at].to(dev), cols[:at].to(dev), dist[:at].to(dev)


def _grid_pairs(receivers: Tensor, sources: Tensor, radius: float, max_pairs: int) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`ball_pairs` through a uniform grid of cells ``radius`` wide (module docstring), on the points' device."""
    dev, dtype = receivers.device, receivers.dtype
    rec = receivers.detach().to(torch.float64)
    src = sources.detach().to(torch.float64)
    empty = torch.zeros(0, dtype=torch.int64, device=dev)
    if rec.shape[0] == 0 or src.shape[0] == 0:
        return empty, empty.clone(), torch.zeros(0, dtype=dtype, device=dev)
    lo = torch.minimum(rec.amin(0), src.amin(0))
    extent = float((torch.maximum(rec.amax(0), src.amax(0)) - lo).max())
    # cells at least radius wide, and at most 2^20 per axis so that the linear keys fit in int64
    cell = max(radius, extent / (1 << 20), 1e-300)
    size = int(extent / cell) + 3  # a ring of empty cells around the points: the 27 neighbours stay in range
    strides = torch.tensor([size * size, size, 1], dtype=torch.int64, device=dev)

    def cells(x: Tensor) -> Tensor:
        return ((x - lo) / cell).floor().to(torch.int64).clamp_(0, size - 3) + 1

    src_key = (cells(src) * strides).sum(1)
    order = torch.argsort(src_key)
    key_sorted, src_sorted = src_key[order], src[order]
    steps = torch.tensor([-1, 0, 1], dtype=torch.int64, device=dev)
    offsets = (torch.cartesian_prod(steps, steps, steps) * strides).sum(1)  # (27,)
    rec_key = (cells(rec) * strides).sum(1)
    rows_out, cols_out, dist_out = [], [], []
    total = 0
    r2 = radius * radius
    m = rec.shape[0]
    i = 0
    while i < m:
        # receivers of one block: as many as fit GRID_BLOCK candidates (at least one)
        step = min(m - i, 4096)
        while True:
            keys = rec_key[i:i + step, None] + offsets  # (b, 27)
            start = torch.searchsorted(key_sorted, keys)
            count = torch.searchsorted(key_sorted, keys, right=True) - start
            n_cand = int(count.sum())
            if n_cand <= GRID_BLOCK or step == 1:
                break
            step = max(1, step // 2)
        if n_cand:
            flat = count.flatten()
            group = torch.repeat_interleave(torch.arange(flat.numel(), device=dev), flat)  # (n_cand,)
            first = torch.cumsum(flat, 0) - flat
            idx = start.flatten()[group] + torch.arange(n_cand, device=dev) - first[group]
            row = group // 27 + i
            d2 = (rec[row] - src_sorted[idx]).pow(2).sum(1)
            keep = d2 <= r2
            total += int(keep.sum())
            if total > max_pairs:
                raise ValueError(f"max_pairs: expected at most {max_pairs} pairs within {radius:.3g} mm, got more "
                                 f"({m} receivers, {src.shape[0]} sources); lower the radius or thin the sources")
            rows_out.append(row[keep])
            cols_out.append(order[idx[keep]])
            dist_out.append(d2[keep].sqrt().to(dtype))
        i += step
    if not rows_out:
        return empty, empty.clone(), torch.zeros(0, dtype=dtype, device=dev)
    return torch.cat(rows_out), torch.cat(cols_out), torch.cat(dist_out)
