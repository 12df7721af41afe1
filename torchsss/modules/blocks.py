"""Evaluation in blocks written into one output (bounded temporaries for the build-once modules' large tables)."""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from torchsss._checks import check_int

__all__ = ["in_blocks"]


def in_blocks(fn: Callable[[int, int], Tensor], n: int, block: int, *, dim: int = 0) -> Tensor:
    """``fn(lo, hi)`` over ``0:n`` in blocks of ``block`` along ``dim``, written into one output.

    ``fn(lo, hi)`` returns the slice ``lo:hi`` of the result along ``dim`` (``hi - lo`` long there). One block is
    returned as it is; several are copied into an output allocated after the first (a list and a ``cat`` would
    hold every block and the result at once). ``n = 0`` calls ``fn(0, 0)``. The caller decides when to block:
    under autograd one call records one graph (the copies into a preallocated output do too, but keep every block's
    temporaries alive for the backward pass).

    Args:
        fn: ``(lo, hi) -> Tensor``, the rows ``lo:hi`` of the result along ``dim``.
        n: the result's length along ``dim`` (>= 0).
        block: rows per call (>= 1).
        dim: the dimension the blocks run along.

    Returns:
        The result, of length ``n`` along ``dim``.

    Raises:
        ValueError: a negative ``n``, a ``block`` below 1, or a block of the wrong length (named).

    Examples:
        >>> import torch
        >>> x = torch.arange(10.0)
        >>> in_blocks(lambda lo, hi: x[lo:hi] * 2, 10, 4).tolist() == (x * 2).tolist()
        True
        >>> in_blocks(lambda lo, hi: x[lo:hi].expand(2, -1), 10, 3, dim=1).shape
        torch.Size([2, 10])
    """
    n = check_int(n, "n", 0)
    block = check_int(block, "block", 1)
    out = None
    for lo in range(0, n, block):
        hi = min(n, lo + block)
        part = fn(lo, hi)
        if part.shape[dim] != hi - lo:
            raise ValueError(f"fn: expected {hi - lo} rows along dim {dim} for the block {lo}:{hi}, got "
                             f"{part.shape[dim]}")
        if hi - lo == n:
            return part
        if out is None:
            shape = list(part.shape)
            shape[dim] = n
            out = part.new_empty(shape)
        out.narrow(dim, lo, hi - lo).copy_(part)
        del part
    return fn(0, 0) if out is None else out
