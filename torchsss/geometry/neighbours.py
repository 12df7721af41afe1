"""Pairs of points within a radius in 3-D (a k-d tree), for near-field sums that must not follow texture seams."""

from __future__ import annotations

import math
import numbers

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

__all__ = ["ball_pairs"]


def ball_pairs(receivers: Tensor, sources: Tensor, radius_mm: float, *,
               max_pairs: int = 50_000_000) -> tuple[Tensor, Tensor, Tensor]:
    """Every (receiver, source) pair closer than ``radius_mm`` in 3-D: ``rows``, ``cols``, ``distance``.

    Args:
        receivers: :math:`(M, 3)` positions (mm).
        sources: :math:`(N, 3)` positions (mm).
        radius_mm: the radius (mm, >= 0).
        max_pairs: refuse (ValueError) more pairs than this; counted before the pairs are listed.

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
    rec = receivers.detach().to(torch.float64).cpu().numpy()
    src = sources.detach().to(torch.float64).cpu().numpy()
    tree_r, tree_s = cKDTree(rec), cKDTree(src)
    count = int(tree_r.count_neighbors(tree_s, float(radius_mm)))
    if count > max_pairs:
        raise ValueError(f"max_pairs: expected at most {max_pairs} pairs within {radius_mm:.3g} mm, got {count} "
                         f"({rec.shape[0]} receivers, {src.shape[0]} sources); lower the radius or thin the sources")
    sdm = tree_r.sparse_distance_matrix(tree_s, float(radius_mm), output_type="ndarray")
    order = np.argsort(sdm["i"], kind="stable")
    dev, dtype = receivers.device, receivers.dtype
    rows = torch.from_numpy(sdm["i"][order].astype(np.int64)).to(dev)
    cols = torch.from_numpy(sdm["j"][order].astype(np.int64)).to(dev)
    dist = torch.from_numpy(sdm["v"][order]).to(device=dev, dtype=dtype)
    return rows, cols, dist
