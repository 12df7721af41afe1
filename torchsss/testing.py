"""Test helpers shared by the test suite and by downstream users' tests."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["DEFAULT_TOLERANCES", "assert_close", "tolerance"]

#: (rtol, atol) per dtype, for results that went through a few dozen floating-point operations.
DEFAULT_TOLERANCES: dict[torch.dtype, tuple[float, float]] = {
    torch.float64: (1e-10, 1e-12),
    torch.float32: (1e-5, 1e-7),
    torch.float16: (2e-3, 1e-4),
    torch.bfloat16: (1.6e-2, 1e-3),
}


def tolerance(dtype: torch.dtype) -> tuple[float, float]:
    """``(rtol, atol)`` for ``dtype`` from :data:`DEFAULT_TOLERANCES`."""
    if dtype not in DEFAULT_TOLERANCES:
        raise ValueError(f"dtype: expected one of {list(DEFAULT_TOLERANCES)}, got {dtype}")
    return DEFAULT_TOLERANCES[dtype]


def assert_close(
    actual: Tensor,
    expected: Tensor,
    *,
    rtol: float | None = None,
    atol: float | None = None,
    msg: str = "",
) -> None:
    """Assert ``|actual - expected| <= atol + rtol |expected|`` elementwise, with per-dtype default tolerances.

    Shapes must match exactly (no broadcasting); NaNs must coincide. On failure the message gives the number
    of mismatches, the largest absolute and relative differences and the index where each occurs.

    Examples:
        >>> assert_close(torch.tensor([1.0, 2.0]), torch.tensor([1.0, 2.0 + 1e-7]))
    """
    if not isinstance(actual, Tensor) or not isinstance(expected, Tensor):
        raise TypeError(f"expected two tensors, got {type(actual).__name__} and {type(expected).__name__}")
    if actual.shape != expected.shape:
        raise AssertionError(f"{msg} shape mismatch: actual {tuple(actual.shape)} vs expected {tuple(expected.shape)}")
    d_rtol, d_atol = tolerance(actual.dtype) if actual.dtype in DEFAULT_TOLERANCES else (0.0, 0.0)
    rtol = d_rtol if rtol is None else rtol
    atol = d_atol if atol is None else atol
    a = actual.detach().to(torch.float64).cpu()
    e = expected.detach().to(torch.float64).cpu()
    nan_a, nan_e = torch.isnan(a), torch.isnan(e)
    if not torch.equal(nan_a, nan_e):
        idx = torch.nonzero(nan_a ^ nan_e)[0].tolist()
        raise AssertionError(f"{msg} NaN pattern differs, first at index {idx}: actual {a[tuple(idx)].item()} "
                             f"vs expected {e[tuple(idx)].item()}")
    same_inf = torch.isinf(a) & (a == e)
    diff = (a - e).abs().masked_fill(nan_a | same_inf, 0.0)
    bad = diff > atol + rtol * e.abs().masked_fill(nan_e, 0.0)
    if bool(bad.any()):
        rel = diff / e.abs().clamp_min(torch.finfo(torch.float64).tiny)
        i_abs = tuple(torch.nonzero(diff == diff.max())[0].tolist())
        i_rel = tuple(torch.nonzero(rel == rel.max())[0].tolist())
        raise AssertionError(
            f"{msg} {int(bad.sum())} of {a.numel()} elements differ (rtol={rtol:g}, atol={atol:g}); "
            f"max abs diff {diff.max().item():.3e} at {i_abs} (actual {a[i_abs].item():.9g}, expected "
            f"{e[i_abs].item():.9g}); max rel diff {rel.max().item():.3e} at {i_rel}"
        )
