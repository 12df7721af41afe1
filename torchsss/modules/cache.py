"""Caching of material-dependent tensors in the build-once modules (relighting a fixed material)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["ValueCache", "material_key"]


def material_key(material: nn.Module) -> tuple | None:
    """A key that changes whenever a parameter or buffer of ``material`` changes; None when caching is unsafe.

    Cached kernels and throughput values are only reused outside autograd and tracing (relighting a fixed
    material); whenever gradients are recorded the values are recomputed so that they flow to the material.

    Examples:
        >>> from torchsss.modules import DipoleMaterial
        >>> m = DipoleMaterial.from_preset("skin1")
        >>> with torch.no_grad():
        ...     a = material_key(m)
        ...     _ = m.raw_sigma_a.add_(0.1)
        ...     b = material_key(m)
        >>> a != b
        True
    """
    if torch.is_grad_enabled() or torch.jit.is_tracing() or torch.compiler.is_compiling() or \
            torch.onnx.is_in_onnx_export() or torch.compiler.is_exporting():
        return None
    tensors = list(material.parameters()) + list(material.buffers())
    return tuple((t.data_ptr(), t._version, t.dtype, t.device) for t in tensors)


class ValueCache:
    """One cached tensor per key (not a buffer: it never enters state_dict or an exported graph)."""

    def __init__(self):
        self.key: tuple | None = None
        self.value: Tensor | None = None

    def get(self, key: tuple | None, compute):
        """``compute()``'s value, reused while ``key`` (not None) stays the same."""
        if key is None:
            return compute()
        if key != self.key or self.value is None:
            self.value, self.key = compute(), key
        return self.value
