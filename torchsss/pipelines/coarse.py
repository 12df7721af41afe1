"""Evaluate the radiosity on a coarser pixel grid and interpolate it where the surface is smooth (issue 15).

Subsurface scattering blurs the irradiance over the material's scattering length, so :math:`B` varies slowly over
a smooth surface: away from object boundaries, depth and normal discontinuities it can be evaluated at every
``stride``-th pixel in each direction and interpolated bilinearly in between. Every covered pixel whose four
bracketing grid pixels are not all on the same smooth patch of surface (one is not covered, lies farther than
:math:`\\tau` in space, or turns its normal by more than ``max_angle_deg``) is evaluated exactly instead, so edges,
silhouettes and thin parts keep their exact values. The receivers a frame evaluates drop by up to
:math:`\\text{stride}^2`; the error this adds is measured against the reference in ``tests/test_coarse.py`` and
``benchmarks/bench_frames.py``.

:math:`\\tau` is ``gap`` times the grid spacing in mm at that pixel (``stride`` times the median distance between
neighbouring covered pixels), so a step in depth of more than a few pixels' footprint counts as an edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["CoarseReceivers", "coarse_receivers"]


@dataclass
class CoarseReceivers:
    """Which covered pixels to evaluate, and how to fill in the others.

    Attributes:
        evaluate: :math:`(K,)` flat pixel indices (row-major over :math:`H \\times W`) whose :math:`B` is computed.
        fill: :math:`(F,)` flat indices of the pixels that are interpolated.
        corners: :math:`(F, 4)` positions into ``evaluate`` of each filled pixel's four grid corners.
        weights: :math:`(F, 4)` bilinear weights (sum 1).
        covered: number of covered pixels.
    """

    evaluate: Tensor
    fill: Tensor
    corners: Tensor
    weights: Tensor
    covered: int

    def refine(self, values: Tensor, rel_tol: float) -> Tensor:
        """Positions into ``fill`` of the pixels whose corner values differ by more than ``rel_tol`` (relative).

        Geometry finds silhouettes and creases; this finds what the values themselves say is not smooth (shadow
        terminators sharper than the grid): the spread :math:`(\\max - \\min) / \\max` of the four corners in any
        channel. Those pixels should be evaluated exactly (:meth:`scatter`'s ``exact``).
        """
        if not self.fill.numel():
            return self.fill
        c = values[self.corners]                                            # (F, 4, C)
        hi, lo = c.amax(1), c.amin(1)
        spread = ((hi - lo) / hi.clamp_min(torch.finfo(values.dtype).tiny)).amax(-1)
        return torch.nonzero(spread > rel_tol).squeeze(1)

    def scatter(self, values: Tensor, height: int, width: int, exact: Tensor | None = None,
                exact_values: Tensor | None = None) -> Tensor:
        """:math:`(H, W, C)` image from the :math:`(K, C)` values at ``evaluate`` (zeros where not covered).

        ``exact`` (positions into ``fill``, from :meth:`refine`) with ``exact_values`` :math:`(E, C)` replace the
        interpolation at those pixels.
        """
        out = values.new_zeros(height * width, values.shape[-1])
        out[self.evaluate] = values
        if self.fill.numel():
            out[self.fill] = (values[self.corners] * self.weights.unsqueeze(-1).to(values.dtype)).sum(1)
        if exact is not None and exact.numel():
            out[self.fill[exact]] = exact_values.to(values.dtype)
        return out.reshape(height, width, -1)


def _grid(size: int, stride: int, device) -> Tensor:
    g = torch.arange(0, size, stride, device=device)
    if int(g[-1]) != size - 1:
        g = torch.cat([g, torch.tensor([size - 1], device=device)])
    return g


def coarse_receivers(position: Tensor, normal: Tensor, mask: Tensor, stride: int, *, gap: float = 2.0,
                     max_angle_deg: float = 30.0) -> CoarseReceivers:
    """Plan the coarse evaluation of a :math:`(H, W)` image (module docstring).

    Args:
        position: :math:`(H, W, 3)` surface points in mm.
        normal: :math:`(H, W, 3)` unit normals.
        mask: :math:`(H, W)` bool coverage.
        stride: grid step in pixels (1: every covered pixel is evaluated).
        gap: :math:`\\tau` in grid spacings (mm between grid pixels): a corner farther than this is another
            surface.
        max_angle_deg: a corner whose normal turns more than this is another surface.

    Returns:
        A :class:`CoarseReceivers`.

    Raises:
        ValueError: ``stride`` < 1, shapes that disagree.

    Examples:
        >>> yy, xx = torch.meshgrid(torch.arange(9.0), torch.arange(9.0), indexing="ij")
        >>> pos = torch.stack([xx, yy, torch.zeros_like(xx)], -1)      # a flat plane, 1 mm pixels
        >>> nrm = torch.zeros(9, 9, 3); nrm[..., 2] = 1.0
        >>> plan = coarse_receivers(pos, nrm, torch.ones(9, 9, dtype=torch.bool), 4)
        >>> plan.evaluate.numel(), plan.fill.numel()                     # a 3 x 3 grid, the rest interpolated
        (9, 72)
    """
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise ValueError(f"stride: expected an int >= 1, got {stride!r}")
    if position.dim() != 3 or position.shape[-1] != 3:
        raise ValueError(f"position: expected shape (H, W, 3), got {tuple(position.shape)}")
    h, w = position.shape[:2]
    if tuple(normal.shape) != (h, w, 3) or tuple(mask.shape) != (h, w):
        raise ValueError(f"normal, mask: expected shapes ({h}, {w}, 3) and ({h}, {w}), got "
                         f"{tuple(normal.shape)} and {tuple(mask.shape)}")
    device = position.device
    mask = mask.bool()
    flat_mask = mask.reshape(-1)
    covered = int(flat_mask.sum())
    all_idx = torch.nonzero(flat_mask).squeeze(1)
    empty = torch.zeros(0, dtype=torch.long, device=device)
    if stride == 1 or covered == 0:
        return CoarseReceivers(all_idx, empty, empty.reshape(0, 4), position.new_zeros(0, 4), covered)
    gy, gx = _grid(h, stride, device), _grid(w, stride, device)
    # the bracketing grid lines of every row and column, and the bilinear weights
    iy = torch.clamp(torch.searchsorted(gy, torch.arange(h, device=device), right=True) - 1, max=gy.numel() - 2)
    ix = torch.clamp(torch.searchsorted(gx, torch.arange(w, device=device), right=True) - 1, max=gx.numel() - 2)
    y0, y1, x0, x1 = gy[iy], gy[iy + 1], gx[ix], gx[ix + 1]
    ty = (torch.arange(h, device=device) - y0).to(position.dtype) / (y1 - y0).to(position.dtype)
    tx = (torch.arange(w, device=device) - x0).to(position.dtype) / (x1 - x0).to(position.dtype)
    cy = torch.stack([y0, y0, y1, y1], -1)[:, None, :].expand(h, w, 4)       # (H, W, 4): corner rows
    cx = torch.stack([x0, x1, x0, x1], -1)[None, :, :].expand(h, w, 4)       # corner columns
    wy = torch.stack([1 - ty, 1 - ty, ty, ty], -1)[:, None, :]
    wx = torch.stack([1 - tx, tx, 1 - tx, tx], -1)[None, :, :]
    weights = (wy * wx).expand(h, w, 4)
    corner = cy * w + cx                                                      # (H, W, 4) flat indices
    # the grid spacing in mm: stride x the median distance between horizontally neighbouring covered pixels
    both = mask[:, 1:] & mask[:, :-1]
    step = (position[:, 1:] - position[:, :-1]).norm(dim=-1)[both]
    pixel_mm = float(step.median()) if step.numel() else 0.0
    tau = gap * stride * pixel_mm
    pos_f = position.reshape(-1, 3)
    nrm_f = normal.reshape(-1, 3)
    cpos = pos_f[corner]                                                      # (H, W, 4, 3)
    ok = flat_mask[corner] & ((cpos - position.unsqueeze(2)).norm(dim=-1) <= tau)
    cos_max = torch.cos(torch.deg2rad(torch.tensor(float(max_angle_deg))))
    ok &= (nrm_f[corner] * normal.unsqueeze(2)).sum(-1) >= float(cos_max)
    smooth = ok.all(-1) & mask
    on_grid = torch.zeros(h, w, dtype=torch.bool, device=device)
    on_grid[gy[:, None], gx[None, :]] = True
    exact = mask & (on_grid | ~smooth)
    # every corner a filled pixel reads is covered, hence on the grid and in the evaluated set
    exact_flat = exact.reshape(-1)
    evaluate = torch.nonzero(exact_flat).squeeze(1)
    position_of = torch.full((h * w,), -1, dtype=torch.long, device=device)
    position_of[evaluate] = torch.arange(evaluate.numel(), device=device)
    fill_mask = (mask & ~exact).reshape(-1)
    fill = torch.nonzero(fill_mask).squeeze(1)
    corners = position_of[corner.reshape(-1, 4)[fill]]
    return CoarseReceivers(evaluate, fill, corners, weights.reshape(-1, 4)[fill], covered)
