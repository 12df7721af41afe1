"""JSON values of results: tuples, tensors and nested containers (non-finite floats as strings)."""

from __future__ import annotations

import math

import torch

__all__ = ["jsonable"]


def jsonable(value: object) -> object:
    """``value`` with tensors as lists, tuples as lists, dict keys as str and inf/nan as strings.

    Examples:
        >>> jsonable({"a": (1, torch.tensor([2.0])), 3: float("inf")})
        {'a': [1, [2.0]], '3': 'inf'}
    """
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, torch.Tensor):
        return value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value
