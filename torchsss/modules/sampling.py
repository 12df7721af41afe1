"""Chang's texture-space importance sampler as an nn.Module with the pyramid depth fixed at build time.

:func:`~torchsss.ops.icdf.icdf_sample` picks its pyramid depth from the map size when ``levels`` is not given,
which is a Python decision on a tensor's shape: fine in eager mode, but a graph that is compiled or exported must
know the depth beforehand. :class:`IcdfSampler` fixes it when the module is built (from ``levels`` or from the
size of the maps it will sample), so ``forward(pdf, u)`` compiles and exports with the defaults.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence

from torch import Tensor, nn

from torchsss.ops.icdf import MAX_LEVELS, icdf_sample, pyramid_levels

__all__ = ["IcdfSampler"]


def _check_size(size: object) -> tuple[int, int]:
    """``size`` as a ``(H, W)`` pair of ints >= 1."""
    if isinstance(size, (str, bytes)) or not isinstance(size, Sequence):
        raise TypeError(f"size: expected a (H, W) pair of ints >= 1 or None, got {type(size).__name__}")
    if len(size) != 2 or any(isinstance(s, bool) or not isinstance(s, numbers.Integral) for s in size):
        raise TypeError(f"size: expected a (H, W) pair of ints >= 1 or None, got {tuple(size)!r}")
    h, w = int(size[0]), int(size[1])
    if h < 1 or w < 1:
        raise ValueError(f"size: expected a (H, W) pair of ints >= 1, got {(h, w)}")
    return h, w


class IcdfSampler(nn.Module):
    """Draw points with density proportional to a map (Chang Fig. 2b), with the pyramid depth fixed at build time.

    The module twin of :func:`~torchsss.ops.icdf.icdf_sample`: ``forward(pdf, u)`` returns exactly what
    ``icdf_sample(pdf, u, levels=self.levels)`` returns (see there for the descent, the conventions and the
    precision). The depth is fixed in the constructor, either directly (``levels``) or as the smallest that fits
    maps of ``size = (H, W)`` (:func:`~torchsss.ops.icdf.pyramid_levels`), so the module runs under
    ``torch.compile`` and exports to ONNX (dynamo) with the batch, the sample count and the map size dynamic (maps
    up to :math:`2^{levels}` square). For a map of exactly ``size`` the result is the same as the op's default.
    No parameters or buffers.

    Args:
        levels: pyramid depth in :math:`[0, 15]`; maps up to :math:`2^{levels}` square can be sampled. ``None``:
            computed from ``size``.
        size: ``(H, W)`` of the largest map to sample; required when ``levels`` is ``None``, and checked against
            it otherwise (:math:`2^{levels} \\ge \\max(H, W)`).

    Shapes:
        - pdf: :math:`(B, 1, H, W)` non-negative finite map, :math:`\\max(H, W) \\le 2^{levels}`.
        - u: :math:`(B, N, 2)` uniforms in :math:`[0, 1)`; ``u[..., 0]`` drives x (columns), ``u[..., 1]`` y.
        - output: ``(xy, p)``, :math:`(B, N, 2)` continuous pixel coordinates ``(x, y)`` in
          :math:`[0, W) \\times [0, H)` and :math:`(B, N)` density per unit pixel area,
          ``pdf[texel] / pdf.sum()``.

    Raises:
        TypeError: ``levels`` not an int or None, ``size`` not a pair of ints.
        ValueError: ``levels`` outside :math:`[0, 15]` or too small for ``size``; ``size`` with an entry < 1 or
            larger than :math:`2^{15}`; neither ``levels`` nor ``size`` given.

    Examples:
        >>> import torch
        >>> sampler = IcdfSampler(size=(2, 2))
        >>> sampler.levels
        1
        >>> pdf = torch.tensor([[[[0.0, 3.0], [1.0, 0.0]]]])
        >>> xy, p = sampler(pdf, torch.tensor([[[0.5, 0.5], [0.5, 0.875]]]))
        >>> xy
        tensor([[[1.5000, 0.6667],
                 [0.5000, 1.5000]]])
        >>> p
        tensor([[0.7500, 0.2500]])
    """

    def __init__(self, levels: int | None = None, size: Sequence[int] | None = None) -> None:
        super().__init__()
        hw = None if size is None else _check_size(size)
        if levels is None:
            if hw is None:
                raise ValueError("levels, size: expected levels (an int) or the map size (H, W), got neither")
            levels = pyramid_levels(*hw)
            if levels > MAX_LEVELS:
                raise ValueError(f"size: expected max(H, W) <= 2**{MAX_LEVELS} = {2**MAX_LEVELS}, got {hw}")
        elif isinstance(levels, bool) or not isinstance(levels, numbers.Integral):
            raise TypeError(f"levels: expected an int or None, got {type(levels).__name__}")
        elif not 0 <= levels <= MAX_LEVELS:
            raise ValueError(f"levels: expected an int in [0, {MAX_LEVELS}], got {levels}")
        elif hw is not None and max(hw) > 2**levels:
            raise ValueError(
                f"levels: expected 2**levels >= max(H, W) = {max(hw)} (size), got levels={levels} "
                f"({2**levels} x {2**levels})"
            )
        #: Pyramid depth: maps up to ``2**levels`` square.
        self.levels = int(levels)

    def forward(self, pdf: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Sample ``pdf`` :math:`(B, 1, H, W)` with the uniforms ``u`` :math:`(B, N, 2)`; returns ``(xy, p)``.

        Raises:
            TypeError, ValueError: as :func:`~torchsss.ops.icdf.icdf_sample` (e.g. a map larger than
                :math:`2^{levels}`).
        """
        return icdf_sample(pdf, u, self.levels)

    def extra_repr(self) -> str:
        """The pyramid depth, for ``repr``."""
        return f"levels={self.levels}"
