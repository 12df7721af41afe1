"""Spatially varying convolution: one :math:`k \\times k` kernel per output texel (Lensch's local response).

``out[b, c, y, x] = sum_{i,j} kernels[(b,) y, x, i, j] * image[b, c, y + i - k//2, x + j - k//2]`` with zeros
outside the image. This is a *gather*: the kernel stored at texel ``(y, x)`` says how much every neighbour
sends to ``(y, x)``, so the area of the *source* texel belongs inside the kernel weight (DESIGN.md §2).

:func:`sv_conv2d` is the fast path (pad once, then :math:`k^2` shifted-slice multiply-accumulates; it exports
to ONNX at opset 18 and runs there exactly); :func:`sv_conv2d_reference` is the readable ``unfold`` + ``einsum``
formulation it is tested against.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from torchsss._checks import check_devices, compute_dtype, is_tracing

__all__ = ["sv_conv2d", "sv_conv2d_reference"]

#: Bytes of kernels permuted per band of rows in the inference path (about an L2 cache).
_BAND_BYTES = 2 << 20


def _check_inputs(image: object, kernels: object) -> tuple[int, bool]:
    """Validate ``image``/``kernels``; return ``(k, batched_kernels)``."""
    check_devices({"image": image, "kernels": kernels}, floating=True)  # first: before any host synchronisation
    if image.dim() != 4:
        raise ValueError(f"image: expected shape (B, C, H, W) (4 dims), got {tuple(image.shape)}")
    b, _, h, w = image.shape
    if kernels.dim() not in (4, 5):
        raise ValueError(f"kernels: expected shape (H, W, k, k) or (B, H, W, k, k), got {tuple(kernels.shape)}")
    batched = kernels.dim() == 5
    k, k2 = kernels.shape[-2:]
    if k != k2 or k % 2 == 0:
        raise ValueError(f"kernels: expected square kernels of odd size k (last two dims), got {tuple(kernels.shape)}")
    if tuple(kernels.shape[-4:-2]) != (h, w):
        raise ValueError(f"kernels: expected shape (..., H, W, k, k) with H={h}, W={w} (the image's), "
                         f"got {tuple(kernels.shape)}")
    if batched and kernels.shape[0] != b:
        raise ValueError(f"kernels: expected shape (B, H, W, k, k) with B={b} (the image's batch), "
                         f"got {tuple(kernels.shape)}")
    return int(k), batched


def sv_conv2d(image: Tensor, kernels: Tensor) -> Tensor:
    """Spatially varying 2-D convolution (correlation) with a per-texel :math:`k \\times k` kernel.

    .. math:: out_{b,c,y,x} = \\sum_{i,j} K_{(b,)y,x,i,j}\\, I_{b,c,\\,y+i-k/2,\\,x+j-k/2}

    (zero outside the image). The kernel is shared by the channels. Implementation: the image is padded once
    by ``k // 2`` and the output accumulates :math:`k^2` products of a kernel plane with a shifted slice of the
    padded image. The kernels are permuted to planes :math:`(k^2, H, W)` (or :math:`(B, k^2, 1, H, W)`): in one
    go when autograd records or a graph is traced/exported (out-of-place, exportable), band by band of rows
    with in-place ``addcmul_`` otherwise (same summation order). Measured on 1 thread (512^2, C = 3, k = 7;
    ``benchmarks/bench_lensch_ops.py`` and the README section "Lensch ops"): the one-go permuting copy alone
    takes 62 ms against 19 ms for all the multiply-adds, so the banded path (29 ms) is 3.5x faster than the
    one-go path (102 ms); reading kernel planes straight from the strided :math:`(H, W, k, k)` layout is 1.4x
    slower than one copy; stacking a kernel row's :math:`k` slices and reducing is 1.1-1.9x slower;
    ``unfold`` + ``einsum`` (:func:`sv_conv2d_reference`) is slower still and materialises :math:`k^2`
    copies of the image. Float16/bfloat16 inputs are computed in float32 and cast back.

    Differentiable with respect to ``image`` and ``kernels``; exports to ONNX (dynamo, opset 18) with the image
    size dynamic.

    Args:
        image: :math:`(B, C, H, W)` image or atlas, e.g. irradiance.
        kernels: :math:`(H, W, k, k)` kernels shared by the batch, or :math:`(B, H, W, k, k)` one set per batch
            element; ``k`` odd. ``kernels[y, x, k//2, k//2]`` weights the texel itself.

    Returns:
        :math:`(B, C, H, W)` tensor in the promoted dtype of the inputs, on their device.

    Raises:
        TypeError: a non-tensor, non-floating or complex ``image``/``kernels``.
        ValueError: ``image`` and ``kernels`` on different devices, wrong number of dims, even or non-square
            ``k``, ``H``/``W`` or ``B`` that disagree.

    Examples:
        >>> img = torch.arange(9.0).reshape(1, 1, 3, 3)
        >>> shift = torch.zeros(3, 3, 3, 3)
        >>> shift[..., 1, 2] = 1.0  # every texel reads its right-hand neighbour
        >>> sv_conv2d(img, shift)[0, 0]
        tensor([[1., 2., 0.],
                [4., 5., 0.],
                [7., 8., 0.]])
    """
    k, _ = _check_inputs(image, kernels)
    out_dtype, dtype = compute_dtype(image, kernels)
    x = image.to(dtype)
    kern = kernels.to(dtype)
    needs_graph = is_tracing() or (torch.is_grad_enabled() and (x.requires_grad or kern.requires_grad))
    out = _sv_conv2d_functional(x, kern, k) if needs_graph else _sv_conv2d_tiled(x, kern, k)
    return out.to(out_dtype)


def _planes(kern: Tensor, k: int) -> Tensor:
    """(H, W, k, k) -> (k*k, H, W) or (B, H, W, k, k) -> (B, k*k, 1, H, W), contiguous (one permuting copy)."""
    if kern.dim() == 5:
        b, h, w = kern.shape[:3]
        return kern.reshape(b, h, w, k * k).permute(0, 3, 1, 2).contiguous().unsqueeze(2)
    h, w = kern.shape[:2]
    return kern.reshape(h, w, k * k).permute(2, 0, 1).contiguous()


def _sv_conv2d_functional(x: Tensor, kern: Tensor, k: int) -> Tensor:
    """Out-of-place pad + k*k shifted slices over the whole image: autograd- and export-friendly."""
    h, w = x.shape[-2:]
    p = k // 2
    planes = _planes(kern, k)
    at = (lambda t: planes[:, t]) if kern.dim() == 5 else (lambda t: planes[t])
    xp = F.pad(x, (p, p, p, p)) if p > 0 else x
    out = at(0) * xp[:, :, 0:h, 0:w]
    for t in range(1, k * k):
        i, j = divmod(t, k)
        out = out + at(t) * xp[:, :, i:i + h, j:j + w]
    return out


def _sv_conv2d_tiled(x: Tensor, kern: Tensor, k: int) -> Tensor:
    """In-place variant for inference: bands of rows whose kernels (about 2 MB) are permuted while in cache.

    The (H*W, k*k) -> (k*k, H*W) permuting copy costs more than all the multiply-adds when done in one go
    (62 ms against 19 ms at 512^2, k = 7, 1 thread); permuting band by band and accumulating the band's output
    while it is in cache is 3-4x faster overall. Same summation order as the functional path.
    """
    h, w = x.shape[-2:]
    p = k // 2
    kk = k * k
    rows = int(min(h, max(8, _BAND_BYTES // max(1, w * kk * kern.element_size()))))
    xp = F.pad(x, (p, p, p, p)) if p > 0 else x
    shape = torch.broadcast_shapes(x.shape, (kern.shape[0], 1, h, w) if kern.dim() == 5 else (h, w))
    out = torch.empty(shape, dtype=x.dtype, device=x.device)
    batched = kern.dim() == 5
    for y0 in range(0, h, rows):
        y1 = min(h, y0 + rows)
        band = _planes(kern[:, y0:y1] if batched else kern[y0:y1], k)
        o = out[:, :, y0:y1]
        at = (lambda t, band=band: band[:, t]) if batched else (lambda t, band=band: band[t])
        torch.mul(at(0), xp[:, :, y0:y1, 0:w], out=o)
        for t in range(1, kk):
            i, j = divmod(t, k)
            o.addcmul_(at(t), xp[:, :, y0 + i:y1 + i, j:j + w])
    return out


def sv_conv2d_reference(image: Tensor, kernels: Tensor) -> Tensor:
    """Readable reference of :func:`sv_conv2d`: ``F.unfold`` the image into patches, ``einsum`` with the kernels.

    Materialises :math:`B\\,C\\,k^2 H W` patch values: use it for tests and small images only.

    Args:
        image: :math:`(B, C, H, W)`.
        kernels: :math:`(H, W, k, k)` or :math:`(B, H, W, k, k)`, ``k`` odd.

    Returns:
        :math:`(B, C, H, W)`, as :func:`sv_conv2d`.

    Raises:
        TypeError, ValueError: as :func:`sv_conv2d`.

    Examples:
        >>> img, kern = torch.rand(2, 3, 5, 4), torch.rand(5, 4, 3, 3)
        >>> torch.allclose(sv_conv2d_reference(img, kern), sv_conv2d(img, kern))
        True
    """
    k, batched = _check_inputs(image, kernels)
    out_dtype, dtype = compute_dtype(image, kernels)
    b, c, h, w = image.shape
    patches = F.unfold(image.to(dtype), kernel_size=k, padding=k // 2)  # (B, C*k*k, H*W), taps row-major
    patches = patches.reshape(b, c, k * k, h, w)
    if batched:
        out = torch.einsum("bcthw,bhwt->bchw", patches, kernels.to(dtype).reshape(b, h, w, k * k))
    else:
        out = torch.einsum("bcthw,hwt->bchw", patches, kernels.to(dtype).reshape(h, w, k * k))
    return out.to(out_dtype)
