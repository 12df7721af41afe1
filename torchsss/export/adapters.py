"""Export adapters: thin modules that give a per-frame module the graph signature a deployment needs.

- :class:`SplatExport`: :class:`~torchsss.modules.SplatTranslucency` with a fixed window that also returns the
  number of splats whose footprint may exceed the window (no silent truncation), optionally with the material
  (and its truncation radius) as graph inputs.
- :class:`OptionalArgs`: binds keyword arguments of a module to positional graph inputs (the exporter only sees
  positional tensors).
"""

from __future__ import annotations

import copy

from torch import Tensor, nn

from torchsss.export.materials import InputDipoleMaterial, find_dipole_material, swap_material
from torchsss.modules.splat import SplatTranslucency
from torchsss.ops.splat import splat_radiosity

__all__ = ["OptionalArgs", "SplatExport"]


class SplatExport(nn.Module):
    """``forward(src_pos, src_flux, dst_pos, dst_mask, view_proj[, sigma_a, sigma_s_prime, eta, r_max])``.

    Returns ``(radiosity (B, C, H, W), truncated (B,) int64)``: the splat radiosity in the module's fixed window
    and :meth:`~torchsss.modules.SplatTranslucency.count_truncated` of the same splats, so that a deployed graph
    reports a window too small for a frame (a larger image, a closer camera) instead of losing light silently.

    Args:
        module: a one-material :class:`~torchsss.modules.SplatTranslucency` built with ``window=K``.
        material_inputs: take the dipole material (``sigma_a (C,)``, ``sigma_s_prime (C,)`` in mm^-1, ``eta
            (1,)``) and its truncation radius ``r_max (1,)`` in mm (e.g. ``material.r_max(eps).amax()``) as four
            trailing inputs; the module is copied, not changed.

    Raises:
        TypeError: not a SplatTranslucency.
        ValueError: no fixed window, or a material table (several materials).
    """

    def __init__(self, module: SplatTranslucency, material_inputs: bool = False) -> None:
        super().__init__()
        if not isinstance(module, SplatTranslucency):
            raise TypeError(f"module: expected a SplatTranslucency, got {type(module).__name__}")
        if module.window is None:
            raise ValueError("module: expected a SplatTranslucency built with window=K (odd) to export, got None")
        if len(module.materials) != 1:
            raise ValueError(f"module: expected one material, got a table of {len(module.materials)}")
        self.material_inputs = bool(material_inputs)
        if self.material_inputs:
            module = copy.deepcopy(module)
            old = find_dipole_material(module)
            swap_material(module, old, InputDipoleMaterial(old))
        self.splat = module

    def forward(self, src_pos: Tensor, src_flux: Tensor, dst_pos: Tensor, dst_mask: Tensor, view_proj: Tensor,
                sigma_a: Tensor | None = None, sigma_s_prime: Tensor | None = None, eta: Tensor | None = None,
                r_max: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Radiosity :math:`(B, C, H, W)` and truncated-splat counts :math:`(B,)`."""
        m = self.splat
        if self.material_inputs:
            if sigma_a is None or sigma_s_prime is None or eta is None or r_max is None:
                raise ValueError("sigma_a, sigma_s_prime, eta, r_max: expected tensors (material_inputs=True), "
                                 "got None")
            m.material.bind(sigma_a, sigma_s_prime, eta)
        else:
            r_max = m.r_max
        out = splat_radiosity(src_pos, src_flux, dst_pos, dst_mask, view_proj, list(m.materials), r_max,
                              method="window", window=m.window)
        return out, m.count_truncated(src_pos, dst_pos, view_proj, r_max=r_max)


class OptionalArgs(nn.Module):
    """``forward(*positional, *keyword_values)``: calls ``module(*positional, **dict(zip(keywords, values)))``.

    Args:
        module: the module.
        positional: how many leading inputs are positional.
        keywords: the names of the keyword arguments fed by the remaining inputs, in order.
    """

    def __init__(self, module: nn.Module, positional: int, keywords: tuple[str, ...]) -> None:
        super().__init__()
        self.module = module
        self.positional = int(positional)
        self.keywords = tuple(keywords)

    def forward(self, *args: Tensor):
        """The wrapped module's output."""
        pos, kw = args[:self.positional], args[self.positional:]
        return self.module(*pos, **dict(zip(self.keywords, kw)))
