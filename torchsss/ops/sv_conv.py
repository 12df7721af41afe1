"""Spatially varying convolution: one :math:`k \\times k` kernel per output texel (Lensch's local response).

``out[b, c, y, x] = sum_{i,j} kernels[(b,) y, x, i, j] * image[b, c, y + i - k//2, x + j - k//2]`` with zeros
outside the image. This is a *gather*: the kernel stored at texel ``(y, x)`` says how much every neighbour
sends to ``(y, x)``, so the area of the *source* texel belongs inside the kernel weight (DESIGN.md §2).

:func:`sv_conv2d` is the fast path (pad once, then :math:`k^2` shifted-slice multiply-accumulates, compiled
into one loop over the texels for inference; it exports to ONNX at opset 18 and runs there exactly);
:func:`sv_conv2d_reference` is the readable ``unfold`` + ``einsum`` formulation it is tested against.
:func:`sv_conv2d_planes` takes the kernels already in the tap-major layout the fast path computes on
(:math:`(k^2, H, W)`): a caller that builds its kernels once (Lensch's local response) builds them in that layout
and holds one copy instead of two.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from torchsss._checks import check_devices, compute_dtype, is_tracing
from torchsss.ops import fused

__all__ = ["sv_conv2d", "sv_conv2d_planes", "sv_conv2d_reference"]

#: Bytes of kernels permuted per band of rows in the inference path (about an L2 cache).
_BAND_BYTES = 2 << 20
#: Images per compiled call that share one set of kernel planes: the fused loop reads each plane once for all
#: of them (more makes the unrolled kernel, and its compile, longer).
_GROUP = 4
#: Multiply-adds per unit of :func:`torchsss.ops.fused.use_compiled` work (eager: about 0.75 ns per
#: multiply-add on one core, a unit is about 0.1 us of eager work).
_MACS_PER_WORK = 128


def _image_dims(image: Tensor) -> tuple[int, int, int]:
    """``(B, H, W)`` of a :math:`(B, C, H, W)` image (ValueError naming ``image`` otherwise)."""
    if image.dim() != 4:
        raise ValueError(f"image: expected shape (B, C, H, W) (4 dims), got {tuple(image.shape)}")
    b, _, h, w = image.shape
    return b, h, w


def _check_inputs(image: object, kernels: object) -> tuple[int, bool]:
    """Validate ``image``/``kernels``; return ``(k, batched_kernels)``."""
    check_devices({"image": image, "kernels": kernels}, floating=True)  # first: before any host synchronisation
    b, h, w = _image_dims(image)
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

    (zero outside the image). The kernel is shared by the channels. Three implementations, one result:

    * **compiled** (inference, when :func:`torchsss.ops.fused.use_compiled` allows: ``TORCHSSS_COMPILE=1``, or
      ``auto`` once the frames of one size have spent about one compile's eager time): the kernels are permuted
      once to planes :math:`(k^2, H, W)` and kept while the same ``kernels`` tensor lives unchanged
      (:func:`torchsss.ops.fused.derived`; Lensch's kernels are built once per material and reused every
      frame), the image is padded, and one inductor loop (:func:`sv_conv2d_planes_eager`) computes up to 4
      images per read of the planes, vectorised along rows and parallel over rows (one parallel region per
      call, so 2 threads are not slower than 1). Measured at 512^2, C = 3, k = 7, float32
      (``benchmarks/bench_lensch_ops.py``, interleaved, shared 2-core machine): 5.6 ms on 1 thread (2.3x the
      memory floor of reading kernels and image once, 33x faster than ``unfold`` + ``einsum``, 6x faster than
      the eager path), 3.1 ms on 2 threads (2.1x the floor, 39x ``unfold`` + ``einsum``, 8.8x eager). The first
      call compiles (2-15 s at k = 7, up to a minute at k = 11, once per process, size and thread count) and
      builds the planes (one permuting copy). Rejected: the gather form reading each texel's :math:`k^2`
      contiguous weights (``(kern * patches).sum(-1)`` with patches from ``as_strided``: 6x the floor; with
      ``stack``ed slices inductor materialises the :math:`(B, C, H, W, k^2)` patches: 230x), one plane-sum per
      channel in the :math:`(B, C, H, W)` loop order (reads the planes C times: 3-4x the floor), the pad fused
      into the loop (masked loads: 1.7x slower than padding first).
    * **eager banded** (inference otherwise): the image is padded once by ``k // 2`` and the output accumulates
      :math:`k^2` products of a kernel plane with a shifted slice of the padded image, the kernels permuted to
      planes band by band of rows with in-place ``addcmul_``. Measured on 1 thread (512^2, C = 3, k = 7): the
      one-go permuting copy alone takes 62 ms against 19 ms for all the multiply-adds, so the banded path
      (29-34 ms) is 3.5x faster than the one-go path (102 ms); reading kernel planes straight from the strided
      :math:`(H, W, k, k)` layout is 1.4x slower than one copy; stacking a kernel row's :math:`k` slices and
      reducing is 1.1-1.9x slower; ``unfold`` + ``einsum`` (:func:`sv_conv2d_reference`) is slower still and
      materialises :math:`k^2` copies of the image. Its many small parallel regions make it slow on 2 threads
      of a loaded machine.
    * **functional** (autograd records, or a graph is traced/exported): the same shifted-slice sum out of
      place, the planes permuted in one go.

    Float16/bfloat16 inputs are computed in float32 and cast back.

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
    if needs_graph:
        out = _sv_conv2d_functional(x, kern, k)
    else:
        out = _sv_conv2d_fused(x, kern, kernels, k)
        if out is None:
            out = _sv_conv2d_tiled(x, kern, k)
    return out.to(out_dtype)


def sv_conv2d_planes_eager(xp: Tensor, planes: Tensor, threads: int) -> Tensor:
    """The fused kernel of :func:`sv_conv2d`: padded images x kernel planes, image ``g`` with kernel set ``n``.

    :math:`(N, G, H+2p, W+2p)` padded images and :math:`(N, k^2, H, W)` planes -> :math:`(N, G, H, W)`.

    Written as one unrolled sum of :math:`G k^2` products, which inductor compiles into one loop over the texels
    that loads each kernel plane value once for the :math:`G` images (vectorised along rows, parallel over rows).
    ``threads`` (the intra-op thread count) is a compile-time constant: inductor specialises the OpenMP loop on
    it, so a different thread count gets its own graph.
    """
    if threads < 1:  # read by dynamo, so that the graph is guarded (and recompiled) on the thread count
        raise ValueError(f"threads: expected an int >= 1, got {threads}")
    g = xp.shape[1]
    kk, h, w = planes.shape[1:]
    k = math.isqrt(kk)
    outs = []
    for gi in range(g):
        o = planes[:, 0] * xp[:, gi, 0:h, 0:w]
        for t in range(1, kk):
            i, j = divmod(t, k)
            o = o + planes[:, t] * xp[:, gi, i:i + h, j:j + w]
        outs.append(o)
    return torch.stack(outs, 1)


def _sv_conv2d_fused(x: Tensor, kern: Tensor, kernels: Tensor, k: int) -> Tensor | None:
    """The compiled inference path, or None where :func:`torchsss.ops.fused.use_compiled` says no."""
    b, _, h, w = x.shape
    batched = kern.dim() == 5
    n = b if batched else 1
    # the kernel planes (one permuting copy, 60 ms at 512^2 and k = 7) are kept while `kernels` lives unchanged:
    # Lensch's kernels are built once and applied to every frame
    return _fused_planes(x, lambda: fused.derived(("sv_conv2d.planes", kern.dtype), (kernels,),
                                                  lambda: _planes(kern, k).reshape(n, k * k, h, w)), k, batched, kern)


def _fused_planes(x: Tensor, planes, k: int, batched: bool, kern: Tensor) -> Tensor | None:
    """The compiled loop on ``planes()`` :math:`(N, k^2, H, W)` (a callable: made only when the loop runs)."""
    b, c, h, w = x.shape
    n, g = (b, c) if batched else (1, b * c)
    threads = torch.get_num_threads()
    variant = (x.device.type, x.dtype, n, g, h, w, k, threads)
    work = float(n) * g * h * w * k * k / _MACS_PER_WORK  # the frames of a variant add up (ski rental)
    if x.numel() == 0 or not fused.use_compiled("sv_conv2d", variant, work, (x, kern)):
        return None
    pl = planes()
    p = k // 2
    xs = x if batched else x.reshape(1, g, h, w)
    kernel = fused._compiled("sv_conv2d", sv_conv2d_planes_eager)
    outs = []
    for g0 in range(0, g, _GROUP):  # F.pad makes each group a fresh contiguous tensor (the graph guards strides)
        xp = F.pad(xs[:, g0:g0 + _GROUP], (p, p, p, p))
        outs.append(fused._call(kernel, variant, xp, pl, threads))
    out = outs[0] if len(outs) == 1 else torch.cat(outs, 1)
    return out.reshape(b, c, h, w)


def _planes(kern: Tensor, k: int) -> Tensor:
    """(H, W, k, k) -> (k*k, H, W) or (B, H, W, k, k) -> (B, k*k, 1, H, W), contiguous (one permuting copy)."""
    if kern.dim() == 5:
        b, h, w = kern.shape[:3]
        return kern.reshape(b, h, w, k * k).permute(0, 3, 1, 2).contiguous().unsqueeze(2)
    h, w = kern.shape[:2]
    return kern.reshape(h, w, k * k).permute(2, 0, 1).contiguous()


def _sv_conv2d_functional(x: Tensor, kern: Tensor, k: int) -> Tensor:
    """Out-of-place pad + k*k shifted slices over the whole image: autograd- and export-friendly."""
    return _planes_functional(x, _planes(kern, k), k)


def _planes_functional(x: Tensor, planes: Tensor, k: int) -> Tensor:
    """:func:`_sv_conv2d_functional` on planes ``(k*k, H, W)`` or ``(B, k*k, 1, H, W)``."""
    h, w = x.shape[-2:]
    p = k // 2
    at = (lambda t: planes[:, t]) if planes.dim() == 5 else (lambda t: planes[t])
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


def _check_planes(image: object, planes: object) -> tuple[int, bool]:
    """Validate ``image``/``planes`` of :func:`sv_conv2d_planes`; return ``(k, batched)``."""
    check_devices({"image": image, "planes": planes}, floating=True)
    b, h, w = _image_dims(image)
    if planes.dim() not in (3, 4):
        raise ValueError(f"planes: expected shape (k*k, H, W) or (B, k*k, H, W), got {tuple(planes.shape)}")
    batched = planes.dim() == 4
    kk = planes.shape[-3]
    k = math.isqrt(kk)
    if k * k != kk or k % 2 == 0:
        raise ValueError(f"planes: expected k*k taps with k odd (dim -3), got {kk} in {tuple(planes.shape)}")
    if tuple(planes.shape[-2:]) != (h, w):
        raise ValueError(f"planes: expected shape (..., k*k, H, W) with H={h}, W={w} (the image's), "
                         f"got {tuple(planes.shape)}")
    if batched and planes.shape[0] != b:
        raise ValueError(f"planes: expected shape (B, k*k, H, W) with B={b} (the image's batch), "
                         f"got {tuple(planes.shape)}")
    return k, batched


def sv_conv2d_planes(image: Tensor, planes: Tensor) -> Tensor:
    """:func:`sv_conv2d` with the kernels in tap-major layout: ``planes[t, y, x] = kernels[y, x, t // k, t % k]``.

    The layout every path of :func:`sv_conv2d` computes on, taken as given: no permuting copy is made or kept.
    For kernels built once and applied every frame (Lensch's local response at atlas 512 and k = 11 holds
    363 MB of kernels: :func:`sv_conv2d` keeps a second, permuted copy of them for its compiled loop).
    Same paths (compiled, eager, functional), same result, same gradients.

    Args:
        image: :math:`(B, C, H, W)` image or atlas.
        planes: :math:`(k^2, H, W)` shared by the batch or :math:`(B, k^2, H, W)` one set per batch element; tap
            ``t = i k + j`` weights the source at ``(y + i - k//2, x + j - k//2)``, ``k`` odd.

    Returns:
        :math:`(B, C, H, W)` in the promoted dtype of the inputs.

    Raises:
        TypeError: a non-tensor, non-floating or complex ``image``/``planes``.
        ValueError: different devices, wrong number of dims, a tap count that is not an odd square, ``H``/``W``
            or ``B`` that disagree.

    Examples:
        >>> img, kern = torch.rand(2, 3, 5, 4), torch.rand(5, 4, 3, 3)
        >>> planes = kern.reshape(5, 4, 9).permute(2, 0, 1)
        >>> torch.allclose(sv_conv2d_planes(img, planes), sv_conv2d(img, kern))
        True
    """
    k, batched = _check_planes(image, planes)
    out_dtype, dtype = compute_dtype(image, planes)
    x = image.to(dtype)
    pl = planes.to(dtype)
    if is_tracing() or (torch.is_grad_enabled() and (x.requires_grad or pl.requires_grad)):
        out = _planes_functional(x, pl.unsqueeze(2) if batched else pl, k)
    else:
        b, _, h, w = x.shape
        out = _fused_planes(x, lambda: pl.reshape(b if batched else 1, k * k, h, w).contiguous(), k, batched, pl)
        if out is None:
            out = _planes_eager(x, pl.unsqueeze(2) if batched else pl, k)
    return out.to(out_dtype)


def _planes_eager(x: Tensor, planes: Tensor, k: int) -> Tensor:
    """In-place multiply-accumulate over the taps of ready planes (``(k*k, H, W)`` or ``(B, k*k, 1, H, W)``)."""
    h, w = x.shape[-2:]
    p = k // 2
    xp = F.pad(x, (p, p, p, p)) if p > 0 else x
    at = (lambda t: planes[:, t]) if planes.dim() == 5 else (lambda t: planes[t])
    out = torch.mul(at(0), xp[:, :, 0:h, 0:w])
    for t in range(1, k * k):
        i, j = divmod(t, k)
        out.addcmul_(at(t), xp[:, :, i:i + h, j:j + w])
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
