"""The reference integrator: all pairs of source and receiver points, chunked. Ground truth for every method."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from torchsss._checks import (
    check_devices,
    check_finite,
    check_nonnegative,
    check_shape,
    check_tensor,
    compute_dtype,
    is_exporting,
    is_tracing,
)
from torchsss.ops.fused import dipole_pair_sum, dipole_params, use_compiled

__all__ = ["pairwise_distance", "reference_radiosity"]

#: Default number of (source, receiver) pairs evaluated at once (per batch element) by the eager chain. Smaller
#: chunks stay in cache: 4,096 sources against 3,906 receivers (skin1, 2 threads) took 1.3-2.1 s and 0.2-0.4 GB of
#: temporaries at 2M pairs a chunk, 0.9-1.0 s and under 0.1 GB at 256k; the hybrid's frame on the default scene at
#: 128 x 128 peaked at 1.03-1.12 GB with 2M, 0.77 GB with 256k (its global split 1.25-1.33 -> 0.99-1.06 s).
DEFAULT_MAX_PAIRS = 1 << 18


def pairwise_distance(a: Tensor, b: Tensor) -> Tensor:
    """Exact Euclidean distances :math:`|a_m - b_n|` from coordinate differences (no Gram-matrix cancellation).

    The gradient is defined as 0 where two points coincide (the norm is not differentiable there). NaN in gives
    NaN out: a pair with a NaN coordinate (or an infinite one on both sides) has a NaN distance, never a
    plausible 0.

    Args:
        a: :math:`(B, M, 3)` points.
        b: :math:`(B, N, 3)` points.

    Returns:
        :math:`(B, M, N, 1)` distances.

    Examples:
        >>> pairwise_distance(torch.zeros(1, 1, 3), torch.tensor([[[3.0, 4.0, 0.0]]])).flatten().tolist()
        [5.0]
        >>> pairwise_distance(torch.zeros(1, 1, 3), torch.tensor([[[float("nan"), 0.0, 0.0]]])).flatten().tolist()
        [nan]
    """
    diff = a.unsqueeze(2) - b.unsqueeze(1)
    sq = (diff * diff).sum(-1, keepdim=True)
    pos = sq > 0
    # not-positive entries are 0 (coincident points, zero gradient) or NaN: sq * 0 keeps the NaN (a comparison
    # with NaN is False, so a zeros_like here would turn a NaN distance into 0)
    return torch.where(pos, torch.sqrt(torch.where(pos, sq, torch.ones_like(sq))), sq * 0)


def reference_radiosity(
    src_pos: Tensor,
    src_irradiance: Tensor,
    src_area: Tensor,
    dst_pos: Tensor,
    profile: Callable[..., Tensor],
    *,
    src_distance_scale: Tensor | None = None,
    src_irradiance_scale: Tensor | None = None,
    src_ids: Tensor | None = None,
    dst_ids: Tensor | None = None,
    id_weight: Callable[[Tensor, Tensor], Tensor] | None = None,
    max_pairs: int = DEFAULT_MAX_PAIRS,
) -> Tensor:
    """Radiosity :math:`B(x_o) = \\sum_i E_i\\, A_i\\, M_{i,i}\\, R(|x_i - x_o| M_{d,i})` over all pairs.

    This is the brute-force quadrature of :math:`B(x_o) = \\int E(x_i) R_d(|x_i - x_o|) dA(x_i)` that every fast
    method is measured against. Memory stays bounded: at most ``max_pairs`` pairs per batch element are formed
    at once (receivers and sources are both chunked). When ``profile`` is the plain dipole (it offers
    ``dipole_coefficients()``, as :class:`~torchsss.DipoleMaterial` does), ``id_weight`` is absent or Chang's
    split (``chang_split``, below), nothing is recorded for autograd and compilation pays
    (:func:`torchsss.ops.fused.use_compiled`), the sum runs in the fused compiled
    kernel :func:`torchsss.ops.fused.dipole_pair_sum` instead (same values to float rounding; 100-150 Mpairs/s
    on the 2-core CPU machine in float32 against 7 for this chunked chain). Differentiable with respect to the
    irradiance, the areas, the positions, the modifiers and any parameters ``profile`` closes over.

    Args:
        src_pos: :math:`(B, N, 3)` source positions in mm.
        src_irradiance: :math:`(B, N, C)` transmitted irradiance :math:`E_i`.
        src_area: :math:`(B, N)` or :math:`(B, N, 1)` surface area :math:`A_i` of each source in mm^2 (>= 0).
        dst_pos: :math:`(B, M, 3)` receiver positions in mm.
        profile: maps distances :math:`(B, m, n, 1)` (or :math:`(B, m, n, C)` with a distance scale) in mm to
            :math:`(B, m, n, C)` in mm^-2, e.g. a :class:`~torchsss.DipoleMaterial` or
            ``functools.partial(dipole_rd, sigma_a=..., sigma_s_prime=..., eta=...)``.
        src_distance_scale: optional :math:`(B, N, 1)` or :math:`(B, N, C)` distance multiplier :math:`M_d` of
            each source (Shah eq. 7.4).
        src_irradiance_scale: optional :math:`(B, N, 1)` or :math:`(B, N, C)` irradiance modulation :math:`M_i`.
        src_ids: optional :math:`(B, N)` integer object ids of the sources; a pair whose ids differ does not
            interact (Shah 6.4.3). Give both ``src_ids`` and ``dst_ids`` or neither.
        dst_ids: optional :math:`(B, M)` integer object ids of the receivers.
        id_weight: optional ``(r, same) -> factor`` that replaces the ids' all-or-nothing rule: the kernel of a
            pair is ``profile(r) * id_weight(r, same)``, ``same`` :math:`(B, m, n, 1)` bool (the ids agree), e.g.
            the hybrid's global part :math:`1 - W_l(r)\\,[same]` (sources in another chart stay whole). A callable
            with the attribute ``chang_split = (r_p, k, bound)`` says it is exactly that factor with Chang's
            truncated local weight, which the fused kernel then evaluates itself.
        max_pairs: pair budget per chunk (>= 1); ignored while exporting (ONNX, ``torch.export``), where all
            pairs form one block so that N and M stay dynamic in the graph.

    Returns:
        :math:`(B, M, C)` radiosity :math:`B(x_o)` (multiply by :math:`F_t/\\pi` for radiance), in the promoted
        dtype of the inputs and the profile's output; float16/bfloat16 inputs are computed in float32 and, unless
        the profile's output is wider, cast back.

    Raises:
        TypeError: non-tensor, non-floating or complex inputs, non-integer ids.
        ValueError: inputs on different devices, shapes that disagree (the message names the argument), NaN or
            infinite positions, irradiances, areas or modifiers (naming the input and the first bad index),
            negative areas, bad ``max_pairs``. The value checks are skipped while tracing and on the meta device
            (which gives the output's shape).

    Examples:
        >>> from functools import partial
        >>> from torchsss import dipole_rd
        >>> prof = partial(dipole_rd, sigma_a=torch.tensor([0.01]), sigma_s_prime=torch.tensor([1.0]), eta=1.3)
        >>> x = torch.rand(1, 100, 3)
        >>> b = reference_radiosity(x, torch.ones(1, 100, 1), torch.full((1, 100), 0.01), x[:, :10], prof)
        >>> b.shape
        torch.Size([1, 10, 1])
    """
    check_devices(
        {"src_pos": src_pos, "src_irradiance": src_irradiance, "src_area": src_area, "dst_pos": dst_pos,
         "src_distance_scale": src_distance_scale, "src_irradiance_scale": src_irradiance_scale,
         "src_ids": src_ids, "dst_ids": dst_ids},
        floating=("src_pos", "src_irradiance", "src_area", "dst_pos", "src_distance_scale", "src_irradiance_scale"),
    )
    dims = check_shape(src_pos, "src_pos", "B,N,3")
    dims = check_shape(src_irradiance, "src_irradiance", "B,N,C", **dims)
    area_in = src_area
    if src_area.dim() == 2:
        src_area = src_area.unsqueeze(-1)
    check_shape(src_area, "src_area", "B,N,1", **dims)
    dims = check_shape(dst_pos, "dst_pos", "B,M,3", **dims)
    check_finite(src_pos, "src_pos")
    check_finite(src_irradiance, "src_irradiance")
    check_nonnegative(area_in, "src_area")
    check_finite(dst_pos, "dst_pos")
    c = dims["C"]
    # float16/bfloat16 are computed in float32 (E dA of small values underflows in float16) and cast back
    out_dtype, work = compute_dtype(src_pos, src_irradiance, src_area, dst_pos)
    src_pos, dst_pos = src_pos.to(work), dst_pos.to(work)
    weight = src_irradiance.to(work) * src_area.to(work)
    if src_irradiance_scale is not None:
        check_tensor(src_irradiance_scale, "src_irradiance_scale")
        if src_irradiance_scale.dim() != 3 or src_irradiance_scale.shape[-1] not in (1, c):
            raise ValueError(f"src_irradiance_scale: expected shape (B, N, 1) or (B, N, {c}), "
                             f"got {tuple(src_irradiance_scale.shape)}")
        check_shape(src_irradiance_scale, "src_irradiance_scale", f"B,N,{src_irradiance_scale.shape[-1]}", **dims)
        check_finite(src_irradiance_scale, "src_irradiance_scale")
        weight = weight * src_irradiance_scale.to(work)
    if src_distance_scale is not None:
        check_tensor(src_distance_scale, "src_distance_scale")
        if src_distance_scale.dim() != 3 or src_distance_scale.shape[-1] not in (1, c):
            raise ValueError(f"src_distance_scale: expected shape (B, N, 1) or (B, N, {c}), "
                             f"got {tuple(src_distance_scale.shape)}")
        check_shape(src_distance_scale, "src_distance_scale", f"B,N,{src_distance_scale.shape[-1]}", **dims)
        check_finite(src_distance_scale, "src_distance_scale")
    if (src_ids is None) != (dst_ids is None):
        raise ValueError("src_ids, dst_ids: expected both or neither, got only one")
    if id_weight is not None and (src_ids is None or not callable(id_weight)):
        raise ValueError("id_weight: expected a callable (r, same) -> factor together with src_ids and dst_ids")
    if src_ids is not None:
        for name, ids, pattern in (("src_ids", src_ids, "B,N"), ("dst_ids", dst_ids, "B,M")):
            if not isinstance(ids, Tensor) or ids.is_floating_point() or ids.is_complex():
                raise TypeError(f"{name}: expected an integer tensor, got "
                                f"{ids.dtype if isinstance(ids, Tensor) else type(ids).__name__}")
            check_shape(ids, name, pattern, **dims)
    if isinstance(max_pairs, bool) or not isinstance(max_pairs, int) or max_pairs < 1:
        raise ValueError(f"max_pairs: expected an int >= 1, got {max_pairs!r}")

    b, n, m = dims["B"], dims["N"], dims["M"]
    dtype = torch.promote_types(torch.promote_types(src_pos.dtype, dst_pos.dtype), weight.dtype)
    split = getattr(id_weight, "chang_split", None) if id_weight is not None else None
    # (never while tracing: the work estimate below would specialise symbolic sizes)
    dipole = None if is_tracing() or not (id_weight is None or split is not None) else \
        dipole_params(profile, dtype, dst_pos.device, c)
    if dipole is not None:
        # the plain dipole: one fused kernel (torchsss.ops.fused) when compilation pays and nothing is recorded
        params, coeffs = dipole
        fused = coeffs[0].dtype
        scale = None if src_distance_scale is None else src_distance_scale.to(fused)
        pos = (dst_pos.to(fused), src_pos.to(fused), weight.to(fused))
        if use_compiled(
                "dipole_pair_sum", (dst_pos.device.type, fused, scale is not None, src_ids is not None,
                                    split is not None), float(b) * m * n,
                (*pos, *coeffs, *params, *(() if scale is None else (scale,)))):
            result = dipole_pair_sum(*pos, *coeffs, scale, src_ids=src_ids, dst_ids=dst_ids, split=split,
                                     compiled=True)
            return result if out_dtype in (torch.float32, torch.float64) or result.dtype != work \
                else result.to(out_dtype)
    if is_exporting():
        # an exported graph: one block of all (receiver, source) pairs. The chunk loops below compare the sizes
        # with Python ints (min, range), which would freeze N and M into the graph; memory is then the caller's
        # to bound (B x M x N x C temporaries).
        blocks = [(slice(None), [slice(None)])]
    else:
        m_chunk = max(1, min(m, 4096, max_pairs))
        n_chunk = max(1, min(n, max_pairs // m_chunk))
        blocks = [(slice(m0, min(m, m0 + m_chunk)), [slice(n0, min(n, n0 + n_chunk)) for n0 in range(0, n, n_chunk)])
                  for m0 in range(0, m, m_chunk)]
    out = []
    for ms, n_slices in blocks:
        dst = dst_pos[:, ms]
        acc = torch.zeros(b, dst.shape[1], c, dtype=dtype, device=dst_pos.device)
        for ns in n_slices:
            r = pairwise_distance(dst, src_pos[:, ns])  # (B, m, n, 1)
            if src_distance_scale is not None:
                r = r * src_distance_scale[:, None, ns].to(work)
            kern = profile(r)  # (B, m, n, C)
            if src_ids is not None:
                same = (dst_ids[:, ms, None] == src_ids[:, None, ns]).unsqueeze(-1)
                kern = kern * (same.to(kern.dtype) if id_weight is None else id_weight(r, same))
            acc = acc + (kern * weight[:, None, ns]).sum(2)
        out.append(acc)
    result = torch.cat(out, dim=1)
    return result if out_dtype in (torch.float32, torch.float64) or result.dtype != work else result.to(out_dtype)
