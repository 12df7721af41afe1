"""Precomputation for Lensch et al. 2002 (local kernels, dual-basis vertex weights, vertex throughput, blending).

Everything here is build-once geometry (DESIGN.md §3): plain tensors in named tuples, no nn.Modules. The
modules store these tensors as buffers and evaluate the profile on the stored *distances*, so that material
edits and gradients stay live.

- :func:`local_kernel_geometry` (Lensch §5.3, §6.3): for every receiver texel ``o`` and every offset of its
  ``k x k`` window, the distance to the source texel ``s`` and the source's area. Gather form (DESIGN.md §1):
  :math:`B^l(o) = \\sum_s A(s) R_d(|x_o - x_s|) E(s)`, i.e. ``kernel = area * R_d(distance)`` weighting
  ``image[y + i - k//2, x + j - k//2]``.
- :func:`vertex_weights` (Lensch §5.2, §6.1 eq. 10): the dual hat basis
  :math:`\\tilde\\psi_\\nu = 3/A_\\nu (4\\beta_\\nu - 1)` times the texel area, so that
  :math:`E^g_i = \\sum_{texels} \\mathrm{dual} \\cdot E`, and the barycentrics to interpolate vertex values back.
- :func:`build_throughput` (Lensch §5.2, §6.2): the sparse pattern of
  :math:`F_{ij} = A_i/3\\, R_d(|v_i - v_j|)` (source ``i``, receiver ``j``, :math:`B^g_j = \\sum_i E^g_i F_{ij}`),
  built blockwise; :func:`throughput_values` evaluates it for any profile.
- :func:`blending_weights` (Lensch §5.4): the per-texel direct-radiosity weights :math:`w_\\nu(u, v)` fitted on
  the ring of the ``(k+2) x (k+2)`` window and the matching kernel corrections.
"""

from __future__ import annotations

import itertools
import math
import numbers
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import Tensor
from tqdm.auto import tqdm

from torchsss._checks import validation
from torchsss.geometry.atlas import Atlas
from torchsss.geometry.lights import incident_light
from torchsss.geometry.mesh import Mesh, check_mesh
from torchsss.geometry.sampling import subdivision_barycentrics
from torchsss.geometry.transfer import closest_point_on_triangle

__all__ = [
    "MAX_THROUGHPUT_ENTRIES",
    "THROUGHPUT_THRESHOLD",
    "BlendWeights",
    "DenseThroughput",
    "HatMoments",
    "HatQuadrature",
    "LocalKernelGeometry",
    "Throughput",
    "VertexWeights",
    "blending_weights",
    "build_dense_throughput",
    "build_throughput",
    "check_entries",
    "entry_moments",
    "estimate_throughput_entries",
    "hat_quadrature",
    "kernel_reach",
    "local_kernel_geometry",
    "median_edge",
    "plan_kernel_size",
    "plan_lensch",
    "throughput_cut",
    "throughput_layout",
    "throughput_values",
    "vertex_weights",
]

_MAX_KERNEL = 63
_RIDGE = 1e-12  # relative ridge of the 3 x 3 blending normal equations
_TINY = 1e-300  # absolute ridge (rings that see none of the three vertices get w = 0)


# --------------------------------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------------------------------


def _check_atlas(atlas: object) -> Atlas:
    if not isinstance(atlas, Atlas):
        raise TypeError(f"atlas: expected a torchsss.geometry.Atlas, got {type(atlas).__name__}")
    return atlas


def _check_kernel_size(kernel_size: object) -> int:
    if isinstance(kernel_size, bool) or not isinstance(kernel_size, numbers.Integral):
        raise TypeError(f"kernel_size: expected an odd int, got {type(kernel_size).__name__}")
    k = int(kernel_size)
    if k < 1 or k % 2 == 0 or k > _MAX_KERNEL:
        raise ValueError(f"kernel_size: expected an odd int in [1, {_MAX_KERNEL}] (7 in Lensch et al.), got {k}")
    return k


def _check_threshold(threshold: object, relative: object) -> tuple[float, bool]:
    if not isinstance(relative, bool):
        raise TypeError(f"relative: expected a bool, got {type(relative).__name__}")
    if isinstance(threshold, bool) or not isinstance(threshold, numbers.Real):
        raise TypeError(f"threshold: expected a non-negative number, got {type(threshold).__name__}")
    t = float(threshold)
    if not math.isfinite(t) or t < 0 or (relative and t > 1):
        expected = "a number in [0, 1] (relative to max F)" if relative else "a finite number >= 0"
        raise ValueError(f"threshold: expected {expected}, got {threshold!r}")
    return t, relative


def _check_bool(x: object, name: str) -> bool:
    if not isinstance(x, bool):
        raise TypeError(f"{name}: expected a bool, got {type(x).__name__}")
    return x


def _profile64(profile: object, device: torch.device) -> tuple[Callable[[Tensor], Tensor], int]:
    """The profile as a float64, gradient-free callable ``(..., 1) mm -> (..., C)``, and its channel count C.

    Validated by a probe evaluation at r = 1 mm.
    """
    if not callable(profile):
        raise TypeError(f"profile: expected a callable from distances (..., 1) in mm to R_d (..., C) (a material "
                        f"module such as DipoleMaterial), got {type(profile).__name__}")

    def f(r: Tensor) -> Tensor:
        with torch.no_grad():
            return profile(r).detach().to(torch.float64)

    probe = f(torch.ones(1, 1, dtype=torch.float64, device=device))
    if probe.dim() != 2 or probe.shape[0] != 1:
        raise ValueError(f"profile: expected R_d of shape (N, C) for distances (N, 1), got {tuple(probe.shape)}")
    return f, int(probe.shape[-1])


def _disk_mean_peak(profile: Callable[[Tensor], Tensor], area: float, device: torch.device) -> float:
    """:math:`\\max_c \\int_{disk(A)} R\\,dA` (the self throughput of an element of area A), by Gauss-Legendre.

    The reference of the relative throughput threshold: an element's throughput to itself is the integral of the
    profile over its own disk (as the modules' self terms), not :math:`A R(0)`, which grows without bound for
    profiles narrower than the element (and is infinite for Burley's).
    """
    rho = math.sqrt(max(area, 0.0) / math.pi)
    if rho == 0.0:
        return 0.0
    x, w = np.polynomial.legendre.leggauss(64)
    r = torch.tensor(0.5 * rho * (x + 1.0), dtype=torch.float64, device=device)
    wt = torch.tensor(0.5 * rho * w, dtype=torch.float64, device=device)
    vals = profile(r.unsqueeze(-1)) * (2.0 * math.pi * r * wt).unsqueeze(-1)
    return float(vals.sum(0).amax())


def _distance(a: Tensor, b: Tensor) -> Tensor:
    """Euclidean distance over the last dimension, written out so that every caller rounds the same way."""
    diff = a - b
    return torch.sqrt((diff * diff).sum(-1))


# --------------------------------------------------------------------------------------------------------------
# local kernels
# --------------------------------------------------------------------------------------------------------------


class LocalKernelGeometry(NamedTuple):
    """Geometry of the per-texel ``k x k`` local kernels in gather form (see :func:`local_kernel_geometry`).

    Attributes:
        distance: :math:`(H, W, k, k)` mm, :math:`|x_o - x_s|` for receiver ``o = (y, x)`` and source
            ``s = (y + i - k//2, x + j - k//2)``; 0 wherever ``area`` is 0. Compact: :math:`(N, k, k)`, the
            receivers ``index``.
        area: :math:`(H, W, k, k)` mm^2, the source texel's ``atlas.area``; 0 where the receiver or the source
            is not valid or the source lies outside the image. Compact: :math:`(N, k, k)`.
        kernel_size: ``k``.
        index: None (full), or compact: :math:`(N,)` int64 flat texel ``y * W + x`` of each receiver (the
            atlas's valid texels, ascending); every other receiver's kernel is 0.
        shape: ``(H, W)`` of the atlas.
    """

    distance: Tensor
    area: Tensor
    kernel_size: int
    index: Tensor | None = None
    shape: tuple[int, int] | None = None


def local_kernel_geometry(atlas: Atlas, kernel_size: int = 7, *, compact: bool = False) -> LocalKernelGeometry:
    """Distances and source areas of the spatially varying local kernels (Lensch §5.3, gather form).

    The kernel of receiver texel ``o = (y, x)`` is ``area[y, x] * R_d(distance[y, x])`` and weights
    ``E[y + i - k//2, x + j - k//2]``, i.e. :math:`B^l(o) = \\sum_s A(s) R_d(|x_o - x_s|) E(s)`: Lensch writes
    the kernel as a scatter with the *source* area :math:`A(u, v)`; in gather form that is the area of the
    texel read, not of the receiver. Gutter texels (``valid_mask`` but not ``chart_mask``) are kept as sources
    and receivers: they are what lets a kernel read across a chart edge. Built from ``k^2`` shifted slices of
    the padded buffers (no loop over texels), in the atlas's dtype and device.

    ``compact=True`` keeps only the receivers that have kernels, the valid texels (xatlas fills 36-52% of the
    square): at atlas 512 and k = 11 the two full tensors take 242 MB, the compact ones about 110 MB.

    Args:
        atlas: The texture atlas; its ``padding`` should be at least ``k // 2`` (``build_atlas(..., kernel_size=k)``).
        kernel_size: Odd ``k`` in [1, 63]; Lensch uses 7.
        compact: Return :math:`(N, k, k)` tensors over the valid receivers (``index``) instead of
            :math:`(H, W, k, k)`.

    Returns:
        :class:`LocalKernelGeometry` with ``distance`` and ``area`` of shape :math:`(H, W, k, k)` (compact:
        :math:`(N, k, k)` and ``index``).

    Raises:
        TypeError: ``atlas`` is not an :class:`~torchsss.geometry.Atlas`, ``kernel_size`` not an int or
            ``compact`` not a bool.
        ValueError: ``kernel_size`` even or out of range.

    Examples:
        >>> from torchsss.geometry import build_atlas, sphere
        >>> atlas = build_atlas(sphere(5.0, 2), 64, kernel_size=3)
        >>> geo = local_kernel_geometry(atlas, 3)
        >>> tuple(geo.distance.shape), geo.kernel_size
        ((64, 64, 3, 3), 3)
        >>> bool((geo.area[..., 1, 1] == atlas.area[0, 0] * atlas.valid_mask[0, 0]).all())  # centre tap: itself
        True
        >>> small = local_kernel_geometry(atlas, 3, compact=True)
        >>> bool((small.distance == geo.distance.reshape(-1, 3, 3)[small.index]).all())
        True
    """
    atlas = _check_atlas(atlas)
    k = _check_kernel_size(kernel_size)
    compact = _check_bool(compact, "compact")
    r = k // 2
    height, width = atlas.shape
    pos = atlas.position[0]  # (3, H, W)
    valid = atlas.valid_mask[0, 0]
    area = atlas.area[0, 0] * valid
    pos_p = F.pad(pos, (r, r, r, r))
    area_p = F.pad(area, (r, r, r, r))
    valid_p = F.pad(valid.to(pos.dtype), (r, r, r, r)) > 0
    if compact:
        index = valid.reshape(-1).nonzero(as_tuple=True)[0]
        wp = width + 2 * r
        base = (index // width) * wp + index % width  # the window's top-left in the padded buffers
        pos_f, area_f, valid_f = pos_p.reshape(3, -1), area_p.reshape(-1), valid_p.reshape(-1)
        x_o = pos.reshape(3, -1)[:, index].T  # (N, 3)
        distance = torch.zeros(index.numel(), k, k, dtype=pos.dtype, device=pos.device)
        source_area = torch.zeros_like(distance)
        for i in range(k):
            for j in range(k):
                src = base + (i * wp + j)
                keep = valid_f[src]
                d = _distance(x_o, pos_f[:, src].T)
                distance[:, i, j] = torch.where(keep, d, torch.zeros_like(d))
                source_area[:, i, j] = torch.where(keep, area_f[src], torch.zeros_like(d))
        return LocalKernelGeometry(distance, source_area, k, index, (height, width))
    # written tap by tap into the outputs (a list of k^2 slices and a stack would hold both at once)
    distance = torch.zeros(height, width, k, k, dtype=pos.dtype, device=pos.device)
    source_area = torch.zeros(height, width, k, k, dtype=pos.dtype, device=pos.device)
    for i in range(k):
        for j in range(k):
            keep = valid & valid_p[i:i + height, j:j + width]
            d = _distance(pos.permute(1, 2, 0), pos_p[:, i:i + height, j:j + width].permute(1, 2, 0))
            distance[:, :, i, j] = torch.where(keep, d, torch.zeros_like(d))
            source_area[:, :, i, j] = torch.where(keep, area_p[i:i + height, j:j + width], torch.zeros_like(d))
    return LocalKernelGeometry(distance, source_area, k, None, (height, width))


# --------------------------------------------------------------------------------------------------------------
# dual-basis vertex weights
# --------------------------------------------------------------------------------------------------------------


class VertexWeights(NamedTuple):
    """Per-texel weights linking the atlas to the mesh vertices (see :func:`vertex_weights`).

    Attributes:
        vertex_ids: :math:`(1, 3, H, W)` int64, the three vertices of the texel's face; 0 where not valid.
        dual: :math:`(1, 3, H, W)` :math:`\\tilde\\psi_\\nu(x) A(x) = 3/A_\\nu (M_f \\beta(x))_\\nu A(x)` on chart
            texels, 0 elsewhere (gutters would count their surface twice); :math:`M_f \\beta = 4\\beta - 1` in the
            continuum, the discrete dual of the face's texels otherwise (:func:`vertex_weights`).
        bary: :math:`(1, 3, H, W)` barycentrics :math:`\\beta_\\nu` on valid texels (extrapolated in gutters),
            0 elsewhere.
    """

    vertex_ids: Tensor
    dual: Tensor
    bary: Tensor


def vertex_weights(mesh: Mesh, atlas: Atlas, *, discrete: bool = True) -> VertexWeights:
    """Dual hat-basis weights (Lensch eq. 10) and interpolation weights of every atlas texel.

    Projection to vertices: :math:`E^g_i = \\sum_{texels} \\mathrm{dual}_\\nu E` summed over the texels whose
    face has ``vertex_ids_nu == i`` (e.g. ``index_add`` / ``scatter_add`` over ``vertex_ids``), with
    :math:`A_\\nu = 3\\,` ``mesh.vertex_areas`` (sum of the areas of the faces around the vertex). Because
    :math:`\\int \\tilde\\psi_i \\psi_j = \\delta_{ij}`, the projection reproduces any function that is linear on
    every face (e.g. linear in position) up to texel quadrature, and since :math:`\\sum_\\nu (4\\beta_\\nu - 1)
    = 1`, :math:`\\sum_i E^g_i\\,` ``vertex_areas_i`` equals :math:`\\sum E\\,` ``area * chart_mask`` exactly.
    Reconstruction on texels: :math:`v(x) = \\sum_\\nu` ``bary_nu`` :math:`\\cdot v_{\\mathrm{vertex\\_ids}_\\nu}`.

    The continuum dual :math:`4\\beta - 1` is biorthogonal to the hats only under exact integration; over a face's
    few texels the sum :math:`\\sum_{texels} A (4\\beta_a - 1) \\beta_b` misses :math:`\\delta_{ab} A_f / 3` (a face
    of 30 texels: the projection of a constant irradiance came out 0.91-1.06 per vertex at atlas 128 on a 6 mm
    sphere). Every face with at least 3 chart texels therefore takes a discrete dual: texel weights
    :math:`w = A + \\beta^T \\lambda_f` that integrate the face's three hats exactly (:math:`\\sum w \\beta = A_f/3`
    each, so they sum to :math:`A_f`), and the shape :math:`M_f \\beta` with :math:`M_f = (A_f / 3)\\, G_f^{-1}`,
    :math:`G_f = \\sum_{texels \\in f} w\\, \\beta \\beta^T` (the continuum :math:`G_f` gives :math:`4\\beta - 1`
    back). The projection then reproduces every function linear on the faces exactly at the texels, and conserves
    the weighted flux (:math:`M_f^T 1 = 1` because :math:`G_f 1 = A_f/3\\, 1`): a constant is that constant at
    every vertex. Faces with fewer texels (or a near-singular :math:`G_f`: a sliver 1-3 texels across) project
    their mean instead, :math:`A_f/3` times the texels' area-weighted mean for each of their hats (exact for a
    constant; until 2026-12-07 the continuum :math:`(4\\beta - 1) A`, 5-10% low on a graded slab's thin rows).

    Args:
        mesh: The mesh the atlas was built from (same face order).
        atlas: Its texture atlas.
        discrete: the discrete dual (default); False: the continuum :math:`(4\\beta - 1) A` everywhere (what
            :func:`blending_weights` fits against).

    Returns:
        :class:`VertexWeights`, buffers :math:`(1, 3, H, W)` in the atlas's dtype (``vertex_ids`` int64).

    Raises:
        TypeError: wrong argument types.
        ValueError: the atlas's faces do not belong to the mesh.

    Examples:
        >>> from torchsss.geometry import build_atlas, sphere
        >>> mesh = sphere(5.0, 2)
        >>> atlas = build_atlas(mesh, 64, kernel_size=3)
        >>> vw = vertex_weights(mesh, atlas)
        >>> e_g = torch.zeros(mesh.num_vertices).index_add_(0, vw.vertex_ids.flatten(), vw.dual.flatten())
        >>> round(float((e_g * mesh.vertex_areas).sum() / mesh.area), 5)   # E = 1 integrates to the area
        1.0
    """
    mesh = check_mesh(mesh)
    atlas = _check_atlas(atlas)
    if atlas.face_uvs.shape[0] != mesh.num_faces:
        raise ValueError(f"atlas: expected an atlas of this mesh ({mesh.num_faces} faces), "
                         f"got one of {atlas.face_uvs.shape[0]} faces")
    valid = atlas.valid_mask[0, 0]
    chart = atlas.chart_mask[0, 0]
    face = torch.where(valid, atlas.face_id[0, 0], torch.zeros_like(atlas.face_id[0, 0]))
    faces = mesh.faces.to(face.device)
    ids = faces[face].permute(2, 0, 1)  # (3, H, W)
    ids = torch.where(valid, ids, torch.zeros_like(ids))
    vertex_area = mesh.vertex_areas.detach().to(device=face.device, dtype=atlas.area.dtype)
    big_a = 3.0 * vertex_area[ids]  # A_nu: sum of the adjacent face areas
    bary = atlas.bary[0] * valid
    area = atlas.area[0] * chart
    if not isinstance(discrete, bool):
        raise TypeError(f"discrete: expected a bool, got {type(discrete).__name__}")
    if discrete:
        weighted = _discrete_dual(bary, area[0], face, chart, mesh.face_areas.detach().to(device=face.device,
                                                                                         dtype=torch.float64))
    else:
        weighted = (4.0 * bary - 1.0) * area
    dual = torch.where(chart & (big_a > 0), 3.0 / big_a.clamp_min(torch.finfo(big_a.dtype).tiny)
                       * weighted.to(bary.dtype), torch.zeros_like(bary))
    return VertexWeights(ids.unsqueeze(0), dual.unsqueeze(0), bary.unsqueeze(0))


def _discrete_dual(bary: Tensor, area: Tensor, face: Tensor, chart: Tensor, face_area: Tensor) -> Tensor:
    """:math:`(3, H, W)` mm^2 the dual shape times the texel weight, :math:`(M_f \\beta)\\, w`, per chart texel.

    See :func:`vertex_weights`: the texel weights :math:`w = A + \\beta^T\\lambda_f` integrate the face's three hats
    exactly (:math:`\\sum w \\beta = A_f/3\\,1`), and :math:`M_f = (A_f/3)\\,G_f^{-1}` with :math:`G_f = \\sum w
    \\beta\\beta^T`. A face with fewer than 3 texels or a near-singular Gram matrix (a graded mesh's row beside a
    crease, 1-3 texels across) projects its mean instead: each of its hats gets :math:`A_f/3` times the face's
    area-weighted texel mean (a constant stays that constant at every vertex).
    """
    b = bary.to(torch.float64).permute(1, 2, 0)[chart]  # (n, 3)
    a = area.to(torch.float64)[chart]
    f = face[chart]
    nf = face_area.shape[0]
    outer = b[:, :, None] * b[:, None, :]
    gram = torch.zeros(nf, 3, 3, dtype=torch.float64, device=b.device).index_add_(0, f, a[:, None, None] * outer)
    first = torch.zeros(nf, 3, dtype=torch.float64, device=b.device).index_add_(0, f, a[:, None] * b)
    count = torch.bincount(f, minlength=nf)
    scale = face_area[:, None, None] / 12.0  # the continuum Gram matrix is A_f / 12 (I + 1 1^T)
    eye = torch.eye(3, dtype=torch.float64, device=b.device)
    tiny = torch.finfo(torch.float64).tiny
    ok = (count >= 3) & (torch.linalg.eigvalsh(gram / scale.clamp_min(tiny))[:, 0] > 0.05)
    gram = torch.where(ok[:, None, None], gram, scale * (eye + 1.0))
    # sum_t (a_t + beta_t . lam) beta_t = A_f / 3: the correction is solved with the texels' unweighted Gram matrix
    plain = torch.zeros(nf, 3, 3, dtype=torch.float64, device=b.device).index_add_(0, f, outer)
    plain = torch.where(ok[:, None, None], plain, eye + 1.0)
    lam = torch.linalg.solve(plain, face_area[:, None] / 3.0 - first)  # (nf, 3)
    w = a + (b * lam[f]).sum(-1)  # texel weights that integrate the hats exactly
    gram_w = torch.zeros(nf, 3, 3, dtype=torch.float64, device=b.device).index_add_(0, f, w[:, None, None] * outer)
    gram_w = torch.where(ok[:, None, None], gram_w, scale * (eye + 1.0))
    m = (face_area[:, None, None] / 3.0) * torch.linalg.inv(gram_w)  # continuum: 4 I - 1 1^T
    shape = torch.einsum("nab,nb->na", m[f], b) * w[:, None]
    # a face too thin or small for the discrete dual (a graded mesh's row beside a crease, 1-3 texels across)
    # projects its mean instead: each hat gets A_f / 3 times the face's area-weighted texel mean, so that a constant
    # is that constant at every vertex; the continuum dual (4 beta - 1) A on so few texels came out 5-10% low on the
    # rim-lit slab's rows at atlas 1024
    total = torch.zeros(nf, dtype=torch.float64, device=b.device).index_add_(0, f, a)
    fallback = (a * (face_area / 3.0)[f] / total[f].clamp_min(tiny))[:, None].expand(-1, 3)
    out = torch.zeros(*bary.shape[1:], 3, dtype=torch.float64, device=b.device)
    out[chart] = torch.where(ok[f][:, None], shape, fallback)
    return out.permute(2, 0, 1)


# --------------------------------------------------------------------------------------------------------------
# vertex-to-vertex throughput
# --------------------------------------------------------------------------------------------------------------


class Throughput(NamedTuple):
    """Sparse pattern of the vertex throughput :math:`F_{ij} = A_i/3\\, R_d(|v_i - v_j|)` (row-major order).

    Attributes:
        rows: :math:`(nnz,)` int64 source vertex ``i``.
        cols: :math:`(nnz,)` int64 receiver vertex ``j``.
        distance: :math:`(nnz,)` mm :math:`|v_i - v_j|` (computed in float64, stored in the mesh's dtype).
        source_area: :math:`(nnz,)` mm^2 :math:`A_i / 3` = ``mesh.vertex_areas[rows]``.
        num_vertices: ``N``.
        threshold: The threshold as given.
        relative: Whether it was relative to :math:`\\max_{ij} F_{ij}`.
        cutoff_mm: Largest kept distance (0 if nothing was kept).
        build_seconds: Wall-clock time of the build.
    """

    rows: Tensor
    cols: Tensor
    distance: Tensor
    source_area: Tensor
    num_vertices: int
    threshold: float
    relative: bool
    cutoff_mm: float
    build_seconds: float


def _max_rd(r: Tensor, profile: Callable[[Tensor], Tensor]) -> Tensor:
    """:math:`\\max_c R_d(r)` for ``r`` of any shape (float64)."""
    return profile(r.unsqueeze(-1)).amax(-1)


def _absolute_threshold(vertex_area64: Tensor, profile: Callable[[Tensor], Tensor], threshold: float,
                        relative: bool) -> float:
    """Absolute threshold on :math:`\\max_c F_{ij}`: relative to the largest self throughput.

    The largest entry of F is an element's throughput to itself, the integral of the profile over its own disk
    (:func:`_disk_mean_peak`), largest for the largest vertex area (the integral grows with the disk).
    """
    if not relative:
        return threshold
    return threshold * _disk_mean_peak(profile, float(vertex_area64.max()), vertex_area64.device)


def _cut_weight(va: Tensor, cut_area: float | None) -> Tensor:
    """The areas the threshold is applied with: :math:`\\max(A_i/3, a)` (``cut_area`` a; None: the areas)."""
    if cut_area is None:
        return va
    if isinstance(cut_area, bool) or not isinstance(cut_area, numbers.Real) or not math.isfinite(cut_area) \
            or cut_area < 0:
        raise ValueError(f"cut_area: expected a finite number >= 0 (mm^2) or None, got {cut_area!r}")
    return va.clamp_min(float(cut_area))


def _keep_radius(area: float, profile: Callable[[Tensor], Tensor], thr: float, device: torch.device) -> float:
    """Smallest r with ``area * max_c R_d(r) < thr`` (a bound on the kept distances), inf when thr <= 0."""
    if thr <= 0:
        return math.inf
    zero = torch.zeros((), dtype=torch.float64, device=device)
    hi = 1.0
    while area * float(_max_rd(zero + hi, profile)) >= thr:
        hi *= 2.0
        if hi > 1e12:
            return math.inf
    lo = 0.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if area * float(_max_rd(zero + mid, profile)) >= thr:
            lo = mid
        else:
            hi = mid
    return hi * (1.0 + 1e-9) + 1e-12


#: Default cap on the throughput's kept entries: each costs about 100-200 bytes at build and per frame (indices,
#: distances, the profile's float temporaries), so 1e7 entries stay within 1-2 GB. A 30 mm marble bunny decimated
#: to 20k faces asks for ~1e8 (every vertex pair) and was killed at 24 GB before this cap.
MAX_THROUGHPUT_ENTRIES = 10_000_000
#: Default throughput threshold, relative to the largest self throughput (:func:`build_throughput`). A limit: a
#: back-lit 60 mm whole-milk sphere loses 14% of the light that crosses it at 1e-5 (its seen side is lit only by
#: entries past the cut: 7.4% against the reference; 1.96% at 1e-6, the same at 0). 1e-6 as the default kept 23%
#: more entries on the default scene for the same frame time and error, but under :data:`MAX_THROUGHPUT_ENTRIES`
#: it decimated the long-scattering scans further (the 50 mm marble bunny 6,744 -> 5,831 source faces, 2.92% ->
#: 3.13%), so the default stays 1e-5; :func:`throughput_cut` estimates what it cuts from a scene's image, and the
#: planner offers a finer threshold where that matters (the sphere: 1e-6).
THROUGHPUT_THRESHOLD = 1e-5


def estimate_throughput_entries(mesh: Mesh, profile: Callable[[Tensor], Tensor], *,
                                threshold: float = THROUGHPUT_THRESHOLD, relative: bool = True, rows: int = 128,
                                seed: int = 0, cut_area: float | None = None) -> int:
    """The number of entries :func:`build_throughput` keeps, estimated from ``rows`` random source vertices.

    Counts exactly which receivers each sampled source keeps (the same test as the build, ``cut_area`` as there) and
    scales by the vertex count; costs ``rows x N`` distances. Use it to refuse or re-plan before an atlas and a
    throughput are built.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> from torchsss.modules import DipoleMaterial
        >>> m, mat = sphere(10.0, 2), DipoleMaterial.from_preset("marble")
        >>> est, exact = estimate_throughput_entries(m, mat), build_throughput(m, mat).rows.numel()
        >>> 0.8 < est / exact < 1.25
        True
    """
    mesh = check_mesh(mesh)
    threshold, relative = _check_threshold(threshold, relative)
    prof, _ = _profile64(profile, mesh.vertices.device)
    v = mesh.vertices.detach().to(torch.float64)
    va = mesh.vertex_areas.detach().to(torch.float64)
    n = v.shape[0]
    thr = _absolute_threshold(va, prof, threshold, relative)
    g = torch.Generator().manual_seed(seed)
    idx = torch.randperm(n, generator=g)[:rows].to(v.device) if n > rows else torch.arange(n, device=v.device)
    kept = 0
    # sources a block: about 1M distances, each with the profile's float64 temporaries per channel (blocks of 32 rows
    # of the shared igea's 134k vertices took 1.1 GB, in every plan of it)
    step = max(1, min(32, (1 << 20) // max(n, 1)))
    with validation(False):  # the profile was validated by _profile64's probe
        for lo in range(0, idx.numel(), step):
            i = idx[lo:lo + step]
            d = _distance(v[i, None, :], v[None, :, :])
            kept += int((_cut_weight(va[i], cut_area)[:, None] * _max_rd(d, prof) >= thr).sum())
    return round(kept * n / idx.numel())


def throughput_cut(mesh: Mesh, profile: Callable[[Tensor], Tensor], lights, eye, thresholds=(THROUGHPUT_THRESHOLD,),
                   *, receivers: int = 256, max_sources: int = 40_000, seed: int = 0) -> tuple[float, ...]:
    """The share of the seen radiosity that :func:`build_throughput`'s threshold cuts, per threshold (relative).

    The vertex throughput keeps an entry only while :math:`A_i \\max_c R_d(d_{ij})` reaches ``threshold`` times the
    largest self throughput. Light that reaches the side the camera sees only along longer paths (a large back-lit
    object of a long-scattering material) is cut. Estimated in float64 from the unshadowed irradiance
    :math:`E_i` of the vertices (point, spot and directional lights; others are skipped) and ``receivers`` random
    vertices facing ``eye``: per receiver and channel the radiosity of all sources
    :math:`B_j = \\sum_i A_i E_i R_d(d_{ij})` and of the kept ones, and over the receivers the relative RMS of the
    difference weighted by each receiver's share of the image (its area times its cosine to the eye over its squared
    distance); the largest channel's. Sources beyond ``max_sources`` are a random subset with their areas scaled.

    Args:
        mesh: the mesh Lensch builds on.
        profile: the material (distances :math:`(..., 1)` mm to :math:`(..., C)`).
        lights: the scene's lights.
        eye: the camera's position (mm).
        thresholds: relative thresholds (as :func:`build_throughput`'s with ``relative=True``).
        receivers: vertices sampled among those facing the eye.
        max_sources: the most sources summed.
        seed: of the random subsets.

    Returns:
        One share per threshold, in [0, 1]; 0 where no vertex faces the eye or nothing is lit.

    Examples:
        >>> from torchsss.geometry import PointLight, sphere
        >>> from torchsss.modules import DipoleMaterial
        >>> mat = DipoleMaterial.from_preset("wholemilk")
        >>> back = throughput_cut(sphere(30.0, 3), mat, [PointLight((0, 0, -150), 1e4)], (0, 0, 130), (1e-5, 1e-7))
        >>> [round(c, 2) for c in back]  # lit from straight behind: the seen side only along long paths
        [0.56, 0.0]
        >>> front = throughput_cut(sphere(30.0, 3), mat, [PointLight((0, 0, 150), 1e4)], (0, 0, 130), (1e-5,))
        >>> front[0] < 1e-3
        True
    """
    mesh = check_mesh(mesh)
    prof, channels = _profile64(profile, mesh.vertices.device)
    v = mesh.vertices.detach().to(torch.float64)
    normal = mesh.vertex_normals.detach().to(torch.float64)
    va = mesh.vertex_areas.detach().to(torch.float64)
    e = torch.zeros(v.shape[0], channels, dtype=torch.float64, device=v.device)
    for light in lights:
        try:
            to_light, _, e_perp = incident_light(light, v.unsqueeze(0))
        except TypeError:  # an environment: smooth, lights every side
            continue
        cos = (normal * to_light[0]).sum(-1).clamp_min(0.0).unsqueeze(-1)
        e = e + cos * e_perp[0].to(torch.float64)[:, :channels]
    eye64 = torch.as_tensor(eye, dtype=torch.float64, device=v.device)
    view = eye64 - v
    dist = view.norm(dim=-1)
    cos_v = (view * normal).sum(-1) / dist.clamp_min(1e-300)
    g = torch.Generator().manual_seed(seed)
    facing = (cos_v > 0).nonzero()[:, 0]
    rec = facing[torch.randperm(facing.numel(), generator=g)[:receivers].to(v.device)]
    src = (e.amax(-1) > 0).nonzero()[:, 0]
    if rec.numel() == 0 or src.numel() == 0:
        return tuple(0.0 for _ in thresholds)
    scale = 1.0
    if src.numel() > max_sources:
        scale = src.numel() / max_sources
        src = src[torch.randperm(src.numel(), generator=g)[:max_sources].to(v.device)]
    weight = (va[rec] * cos_v[rec] / dist[rec].square()).unsqueeze(-1)  # the receiver's share of the image
    cuts = [_absolute_threshold(va, prof, float(t), True) for t in thresholds]
    total = torch.zeros(rec.numel(), channels, dtype=torch.float64, device=v.device)
    kept = [torch.zeros_like(total) for _ in thresholds]
    flux = va[src].unsqueeze(-1) * e[src] * scale
    with validation(False):
        for lo in range(0, rec.numel(), 16):
            hi = min(rec.numel(), lo + 16)
            rd = prof(_distance(v[rec[lo:hi], None, :], v[None, src, :]).unsqueeze(-1))  # (r, S, C)
            b = flux.unsqueeze(0) * rd
            total[lo:hi] = b.sum(1)
            peak = va[src].unsqueeze(0) * rd.amax(-1)
            for k, thr in enumerate(cuts):
                kept[k][lo:hi] = (b * (peak >= thr).unsqueeze(-1)).sum(1)
    den = (weight * total.square()).sum(0)
    out = []
    for part in kept:
        num = (weight * (total - part).square()).sum(0)
        share = torch.where(den > 0, num / den.clamp_min(1e-300), torch.zeros_like(den)).sqrt()
        out.append(float(share.max()))
    return tuple(out)


def check_entries(mesh: Mesh, profile: Callable[[Tensor], Tensor], *, threshold: float, relative: bool,
                  max_entries: int | None, cut_area: float | None = None) -> int | None:
    """Raise a ValueError naming the way out when the throughput would keep more than ``max_entries`` entries.

    Returns the estimate (None when ``max_entries`` is None).
    """
    if max_entries is None:
        return None
    if isinstance(max_entries, bool) or not isinstance(max_entries, numbers.Integral) or max_entries < 1:
        raise ValueError(f"max_entries: expected a positive int or None, got {max_entries!r}")
    est = estimate_throughput_entries(mesh, profile, threshold=threshold, relative=relative, cut_area=cut_area)
    if est > max_entries:
        # entries grow like the square of the vertex count where the profile reaches across the object
        faces = max(4, int(mesh.num_faces * math.sqrt(max_entries / est)))
        raise ValueError(
            f"throughput: expected at most max_entries={max_entries} vertex pairs (about 1-2 GB), got an estimated "
            f"{est:.3g} for {mesh.num_vertices} vertices (the profile reaches across the object); decimate the mesh "
            f"to about {faces} faces (a scene's \"decimate\"), raise the threshold (now {threshold}) or raise "
            "max_entries")
    return est


def build_throughput(
    mesh: Mesh,
    profile: Callable[[Tensor], Tensor],
    *,
    threshold: float = THROUGHPUT_THRESHOLD,
    relative: bool = True,
    zero_diagonal: bool = False,
    block_rows: int | None = None,
    max_memory_mb: float = 64.0,
    max_entries: int | None = MAX_THROUGHPUT_ENTRIES,
    progress: bool = False,
    cut_area: float | None = None,
) -> Throughput:
    """Sparse vertex-to-vertex throughput pattern of Lensch §5.2 / §6.2.

    :math:`F_{ij} = A_i/3\\, R_d(|v_i - v_j|)` (``i`` source, ``j`` receiver, :math:`B^g_j = \\sum_i E^g_i
    F_{ij}`); an entry is kept when :math:`\\max_c F_{ij} \\ge` the threshold. The default is **relative**
    (``threshold * max_i max_c F_ii``, the self throughput :math:`F_{ii} = \\int_{disk(A_i/3)} R_d\\,dA` of the
    largest vertex, the integral of the profile over its own disk as in the modules' self terms): F is
    dimensionless but its scale depends on the mesh's resolution (vertex areas) and on the material, so an
    absolute 1e-5 (Lensch's value, for their meshes and units) keeps very different fractions of the matrix on
    different meshes; the relative rule keeps the same dynamic range everywhere. ``relative=False`` applies the
    threshold to F directly.

    The pattern stores distances and source areas, not values: evaluate it with :func:`throughput_values` for
    any (learnable) profile. Entries beyond ``cutoff_mm`` (the largest kept distance) were dropped for the
    material given here, so a pattern reused with a wider profile misses that tail. Built blockwise over source
    rows (never an ``N x N`` matrix when N is large), distances in float64. When the largest kept distance is
    short against the mesh, the candidate pairs come from a k-d tree (scipy) and the build is O(nnz).

    Args:
        mesh: Vertices in mm.
        profile: The material's profile: distances :math:`(..., 1)` mm -> :math:`R_d` :math:`(..., C)` mm^-2 (a
            material module of the profile contract, e.g. :class:`~torchsss.DipoleMaterial`, evaluated without
            gradient in float64).
        threshold: Keep :math:`\\max_c F_{ij} \\ge` threshold (relative: in [0, 1], times max F).
        relative: See above; default True.
        zero_diagonal: Drop ``i == j`` (Lensch's :math:`F^0` for blending).
        block_rows: Source rows per block; default from ``max_memory_mb``.
        max_memory_mb: Memory budget of one block's temporaries.
        max_entries: Refuse (ValueError, before allocating) when :func:`estimate_throughput_entries` predicts more
            kept entries than this (default :data:`MAX_THROUGHPUT_ENTRIES`, about 1-2 GB); None: no cap.
        progress: Show a tqdm bar over the blocks.
        cut_area: the threshold tests :math:`\\max(A_i/3, a)\\,\\max_c R_d` instead of :math:`\\max_c F_{ij}`
            (mm^2; None: a = 0): a source smaller than ``a`` keeps the reach of one of area ``a``. A mesh graded
            towards its creases (:func:`~torchsss.geometry.refine.refine_creases`) passes its coarse hats' median
            area, so that its fine hats beside a crease do not lose the far field the coarse ones keep (without it,
            the rim-lit cream slab's far side got none of the rim's light).

    Returns:
        :class:`Throughput` with entries sorted by (row, col).

    Raises:
        TypeError: wrong argument types.
        ValueError: negative threshold, bad material or sizes, or more entries than ``max_entries``.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> from torchsss.modules import DipoleMaterial
        >>> tp = build_throughput(sphere(10.0, 2), DipoleMaterial.from_preset("marble"))
        >>> tp.num_vertices, tp.rows.shape == tp.distance.shape, tp.relative
        (162, True, True)
        >>> values = throughput_values(tp, lambda r: r.new_ones(r.shape[0], 3))   # any profile (nnz, 1) -> (nnz, C)
        >>> tuple(values.shape) == (tp.rows.numel(), 3)
        True
    """
    start = time.perf_counter()
    mesh = check_mesh(mesh)
    threshold, relative = _check_threshold(threshold, relative)
    zero_diagonal = _check_bool(zero_diagonal, "zero_diagonal")
    progress = _check_bool(progress, "progress")
    if isinstance(max_memory_mb, bool) or not isinstance(max_memory_mb, numbers.Real):
        raise TypeError(f"max_memory_mb: expected a positive number, got {type(max_memory_mb).__name__}")
    if not math.isfinite(float(max_memory_mb)) or max_memory_mb <= 0:
        raise ValueError(f"max_memory_mb: expected a positive finite number, got {max_memory_mb!r}")
    check_entries(mesh, profile, threshold=threshold, relative=relative, max_entries=max_entries, cut_area=cut_area)
    prof, channels = _profile64(profile, mesh.vertices.device)
    n = mesh.num_vertices
    if block_rows is None:
        per_row = 8.0 * n * (8 + 2 * channels)  # bytes of the float64 temporaries of one row
        block_rows = max(1, min(n, int(float(max_memory_mb) * 2**20 / per_row)))
    elif isinstance(block_rows, bool) or not isinstance(block_rows, numbers.Integral):
        raise TypeError(f"block_rows: expected a positive int or None, got {type(block_rows).__name__}")
    elif block_rows < 1:
        raise ValueError(f"block_rows: expected a positive int or None, got {block_rows}")
    block_rows = int(block_rows)

    v = mesh.vertices.detach().to(torch.float64)
    va = mesh.vertex_areas.detach().to(torch.float64)
    thr = _absolute_threshold(va, prof, threshold, relative)
    va_cut = _cut_weight(va, cut_area)
    radius = _keep_radius(float(va_cut.max()), prof, thr, v.device)
    diagonal = float((v.amax(0) - v.amin(0)).norm())
    rows, cols, dists = [], [], []
    if radius < 0.5 * diagonal:
        # R_d decreases with r: every kept pair lies within ``radius`` (set by the largest vertex area), so a
        # k-d tree lists the candidates in O(nnz) instead of testing all N^2 pairs; the test below is the same.
        # Blocks of consecutive source rows (about max_memory_mb of candidates each) against the whole mesh: the
        # rows come out in order, so the entries are sorted block by block and written into the outputs without
        # a global sort (the pairs of the whole mesh, both directions, and their sort peaked at about 600 MB on
        # the default scene's 6.4M entries; now the outputs and one block's temporaries).
        vn = v.cpu().numpy()
        tree = cKDTree(vn)
        counts = np.asarray(tree.query_ball_point(vn, radius, return_length=True), dtype=np.int64)
        # candidates a block: the profile of one candidate holds about 2 channels x 8 float64 temporaries
        budget = max(1, int(float(max_memory_mb) * 2**20 / (8.0 * (16 + 16 * channels))))
        ends = np.searchsorted(np.cumsum(counts), np.arange(budget, int(counts.sum()) + budget, budget), "right")
        bounds = sorted({0, n, *(int(e) for e in ends if 0 < e < n)})
        dtype = mesh.vertices.dtype
        # the outputs sized for every candidate (an upper bound on the kept entries) and filled block by block:
        # per-block lists of kept entries interleaved with the blocks' temporaries fragmented the heap
        cap = int(counts.sum())
        cols_t = torch.empty(cap, dtype=torch.int64, device=v.device)
        dist_t = torch.empty(cap, dtype=dtype, device=v.device)
        at = 0
        row_counts = torch.zeros(n, dtype=torch.int64, device=v.device)
        cutoff64 = 0.0
        for lo, hi in tqdm(list(itertools.pairwise(bounds)), desc="throughput", unit="block",
                           disable=not progress):
            if hi <= lo:
                continue
            cand = cKDTree(vn[lo:hi]).sparse_distance_matrix(tree, radius, output_type="ndarray")
            r_idx = torch.from_numpy(cand["i"].astype(np.int64)).to(v.device) + lo
            c_idx = torch.from_numpy(cand["j"].astype(np.int64)).to(v.device)
            del cand
            order = torch.argsort(r_idx * n + c_idx)
            r_idx, c_idx = r_idx[order], c_idx[order]
            d = _distance(v[r_idx], v[c_idx])
            keep = va_cut[r_idx] * _max_rd(d, prof) >= thr
            if zero_diagonal:
                keep &= r_idx != c_idx
            if bool(keep.any()):
                cutoff64 = max(cutoff64, float(d[keep].max()))
            row_counts += torch.bincount(r_idx[keep], minlength=n)
            kept = int(keep.sum())
            cols_t[at:at + kept] = c_idx[keep]
            dist_t[at:at + kept] = d[keep]
            at += kept
        if at < cap:
            cols_t, dist_t = cols_t[:at].clone(), dist_t[:at].clone()
        rows_t = torch.repeat_interleave(torch.arange(n, device=v.device), row_counts)
        return Throughput(rows_t, cols_t, dist_t, mesh.vertex_areas.detach()[rows_t].to(dtype), n,
                          threshold, relative, cutoff64, time.perf_counter() - start)
    all_cols = torch.arange(n, device=v.device)
    for lo in tqdm(range(0, n, block_rows), desc="throughput", unit="block", disable=not progress):
        hi = min(n, lo + block_rows)
        d = _distance(v[lo:hi, None, :], v[None, :, :])  # (b, N)
        f = va_cut[lo:hi, None] * _max_rd(d, prof)
        keep = f >= thr
        if zero_diagonal:
            keep &= torch.arange(lo, hi, device=v.device)[:, None] != all_cols[None, :]
        r_idx, c_idx = keep.nonzero(as_tuple=True)
        rows.append(r_idx + lo)
        cols.append(c_idx)
        dists.append(d[r_idx, c_idx])
    rows_t = torch.cat(rows)
    cols_t = torch.cat(cols)
    dist_t = torch.cat(dists)
    cutoff = float(dist_t.max()) if dist_t.numel() else 0.0
    dtype = mesh.vertices.dtype
    return Throughput(rows_t, cols_t, dist_t.to(dtype), mesh.vertex_areas.detach()[rows_t].to(dtype), n,
                      threshold, relative, cutoff, time.perf_counter() - start)


class DenseThroughput(NamedTuple):
    """The vertex throughput as a dense :math:`N \\times N` matrix (row ``i`` source, column ``j`` receiver).

    The same entries as :class:`Throughput` (:func:`build_dense_throughput` applies :func:`build_throughput`'s
    test), for the meshes whose profile reaches across most of the object: there a sparse pattern's indices cost
    more than the matrix (:func:`throughput_layout`).

    Attributes:
        distance: :math:`(N, N)` mm :math:`|v_i - v_j|` of every pair (computed in float64, stored in the mesh's
            dtype), kept or not.
        keep: :math:`(N, N)` bool, the kept entries.
        source_area: :math:`(N,)` mm^2 :math:`A_i / 3` = ``mesh.vertex_areas``.
        num_vertices: ``N``.
        threshold: The threshold as given.
        relative: Whether it was relative to :math:`\\max_{ij} F_{ij}`.
        cutoff_mm: Largest kept distance (0 if nothing was kept).
        build_seconds: Wall-clock time of the build.
    """

    distance: Tensor
    keep: Tensor
    source_area: Tensor
    num_vertices: int
    threshold: float
    relative: bool
    cutoff_mm: float
    build_seconds: float


#: Bytes a kept entry of a sparse throughput costs in a built Lensch module, besides its values: the distance and
#: source area (float32) and the pattern's three int32 index arrays (rows, cols and the permutation into column
#: order, :class:`~torchsss.modules.lensch.GlobalResponse`); the CSR product's cached matrix adds another int32
#: index per entry and its values.
_SPARSE_ENTRY_BYTES = 4 + 4 + 3 * 4 + 4
#: Bytes a vertex pair of a dense throughput costs besides its values: the distance (float32) and the keep flag.
_DENSE_PAIR_BYTES = 4 + 1


def throughput_layout(num_vertices: int, entries: int, channels: int = 3) -> str:
    """``"dense"`` or ``"sparse"``: the throughput's layout that holds ``entries`` kept pairs in fewer bytes.

    A sparse entry costs its distance, source area and three int32 pattern indices plus an int32 index of the cached
    CSR matrix (24 bytes) and its values twice (the values and the CSR copy, :math:`2 \\cdot 4C`); a dense pair its
    distance and keep flag (5 bytes) and its values once (:math:`4C`). At :math:`C = 3` dense is smaller from a
    density of about 0.35; the default scene's spot (2,930 vertices, 6.4M entries, 74% dense) holds 0.31 GB sparse and
    0.15 GB dense.

    Examples:
        >>> throughput_layout(2930, 6_358_446), throughput_layout(20000, 6_000_000)
        ('dense', 'sparse')
    """
    for name, x in (("num_vertices", num_vertices), ("entries", entries), ("channels", channels)):
        if isinstance(x, bool) or not isinstance(x, numbers.Integral) or x < 0:
            raise ValueError(f"{name}: expected a non-negative int, got {x!r}")
    sparse = int(entries) * (_SPARSE_ENTRY_BYTES + 8 * int(channels))
    dense = int(num_vertices) ** 2 * (_DENSE_PAIR_BYTES + 4 * int(channels))
    return "dense" if dense <= sparse else "sparse"


def build_dense_throughput(
    mesh: Mesh,
    profile: Callable[[Tensor], Tensor],
    *,
    threshold: float = THROUGHPUT_THRESHOLD,
    relative: bool = True,
    zero_diagonal: bool = False,
    max_memory_mb: float = 64.0,
    max_pairs: int | None = MAX_THROUGHPUT_ENTRIES * 4,
) -> DenseThroughput:
    """The throughput of :func:`build_throughput` (same test, same threshold) as a dense matrix.

    Distances in float64, row blocks of about ``max_memory_mb`` of temporaries, stored in the mesh's dtype; the
    output is :math:`N^2` distances and keep flags (5 bytes a pair in float32; 43 MB for the default scene's 2,930
    vertices, where the sparse throughput's buffers in :class:`~torchsss.modules.lensch.GlobalResponse`, distances,
    source areas and four index arrays of its 6.4M entries, held 243 MB). See :func:`throughput_layout` for when it
    is the smaller one.

    Args:
        mesh: Vertices in mm.
        profile: The material's profile, as in :func:`build_throughput`.
        threshold: As in :func:`build_throughput`.
        relative: As in :func:`build_throughput`.
        zero_diagonal: Drop ``i == j`` (Lensch's :math:`F^0` for blending).
        max_memory_mb: Memory budget of one block's temporaries.
        max_pairs: Refuse (ValueError, before allocating) a mesh of more than this many vertex pairs :math:`N^2`
            (default 4e7, about 200 MB of distances and flags in float32); None: no cap.

    Returns:
        :class:`DenseThroughput`.

    Raises:
        TypeError: wrong argument types.
        ValueError: negative threshold, bad material or sizes, more pairs than ``max_pairs``.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> from torchsss.modules import DipoleMaterial
        >>> mesh, mat = sphere(10.0, 2), DipoleMaterial.from_preset("marble")
        >>> dense, sparse = build_dense_throughput(mesh, mat), build_throughput(mesh, mat)
        >>> tuple(dense.distance.shape), int(dense.keep.sum()) == sparse.rows.numel()
        ((162, 162), True)
    """
    start = time.perf_counter()
    mesh = check_mesh(mesh)
    threshold, relative = _check_threshold(threshold, relative)
    zero_diagonal = _check_bool(zero_diagonal, "zero_diagonal")
    if isinstance(max_memory_mb, bool) or not isinstance(max_memory_mb, numbers.Real):
        raise TypeError(f"max_memory_mb: expected a positive number, got {type(max_memory_mb).__name__}")
    if not math.isfinite(float(max_memory_mb)) or max_memory_mb <= 0:
        raise ValueError(f"max_memory_mb: expected a positive finite number, got {max_memory_mb!r}")
    n = mesh.num_vertices
    if max_pairs is not None:
        if isinstance(max_pairs, bool) or not isinstance(max_pairs, numbers.Integral) or max_pairs < 1:
            raise ValueError(f"max_pairs: expected a positive int or None, got {max_pairs!r}")
        if n * n > max_pairs:
            raise ValueError(f"max_pairs: expected a mesh of at most {max_pairs} vertex pairs for a dense "
                             f"throughput, got {n} vertices ({n * n} pairs); use build_throughput (sparse) or "
                             "decimate the mesh")
    prof, channels = _profile64(profile, mesh.vertices.device)
    v = mesh.vertices.detach().to(torch.float64)
    va = mesh.vertex_areas.detach().to(torch.float64)
    thr = _absolute_threshold(va, prof, threshold, relative)
    dtype = mesh.vertices.dtype
    distance = torch.empty(n, n, dtype=dtype, device=v.device)
    keep = torch.empty(n, n, dtype=torch.bool, device=v.device)
    # float64 temporaries of one row: its distances and the profile's channels (about 4 arrays each)
    block = max(1, min(n, int(float(max_memory_mb) * 2**20 / (8.0 * max(n, 1) * (4 + 4 * channels)))))
    cutoff = 0.0
    with validation(False):  # the profile was validated by _profile64's probe
        for lo in range(0, n, block):
            hi = min(n, lo + block)
            d = _distance(v[lo:hi, None, :], v[None, :, :])  # (b, N)
            k = va[lo:hi, None] * _max_rd(d, prof) >= thr
            if zero_diagonal:
                k[torch.arange(hi - lo, device=v.device), torch.arange(lo, hi, device=v.device)] = False
            if bool(k.any()):
                cutoff = max(cutoff, float(d[k].max()))
            distance[lo:hi] = d
            keep[lo:hi] = k
    return DenseThroughput(distance, keep, mesh.vertex_areas.detach().to(dtype).clone(), n, threshold, relative,
                           cutoff, time.perf_counter() - start)


def throughput_values(tp: Throughput, profile: Callable[[Tensor], Tensor]) -> Tensor:
    """Values :math:`F_{ij} = A_i/3\\, R(|v_i - v_j|)` of a throughput pattern for a profile.

    Args:
        tp: Pattern from :func:`build_throughput`.
        profile: Maps distances :math:`(nnz, 1)` mm to :math:`(nnz, C)` mm^-2, e.g.
            ``lambda r: dipole_rd(r, sigma_a, sigma_s_prime, eta)``.

    Returns:
        :math:`(nnz, C)`; :math:`B^g_j = \\sum_i E^g_i F_{ij}` is then ``index_add`` over ``tp.cols``.

    Raises:
        TypeError: ``tp`` is not a :class:`Throughput` or ``profile`` not callable.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> from torchsss.physics import dipole_rd
        >>> profile = lambda r: dipole_rd(r, torch.tensor([0.01]), 1.0)
        >>> tp = build_throughput(sphere(10.0, 1), profile)
        >>> throughput_values(tp, profile).shape[1]
        1
    """
    if not isinstance(tp, Throughput):
        raise TypeError(f"tp: expected a Throughput, got {type(tp).__name__}")
    if not callable(profile):
        raise TypeError(f"profile: expected a callable (nnz, 1) -> (nnz, C), got {type(profile).__name__}")
    return tp.source_area[:, None] * profile(tp.distance[:, None])


class HatMoments(NamedTuple):
    r"""Every vertex hat's centroid and covariance: what the moment rule of :class:`HatQuadrature` needs per entry.

    Per vertex, not per entry (:func:`entry_moments` derives an entry's from its row and column), so that a module
    keeps :math:`O(N)` numbers for the rule instead of three per entry (73 MB on the default scene's 6.4M entries).

    Attributes:
        vertices: :math:`(N, 3)` mm, the mesh's vertices (the receivers).
        centroid: :math:`(N, 3)` mm, the centroid of each vertex's hat :math:`\psi_i`.
        covariance: :math:`(N, 3, 3)` mm^2, the hat's covariance about its centroid.
    """

    vertices: Tensor
    centroid: Tensor
    covariance: Tensor


def entry_moments(moments: HatMoments, rows: Tensor, cols: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""The moment rule's distance and variances of the entries ``(rows, cols)`` (source hat ``i``, receiver ``j``).

    :math:`r = |v_j - c_i|`, :math:`\sigma_r^2 = u^T C_i u` along :math:`u = (v_j - c_i)/r` and
    :math:`\sigma_t^2 = \mathrm{tr}\,C_i - \sigma_r^2` across it (both clamped at 0; :math:`u = 0` where
    :math:`r = 0`), in the moments' dtype.

    Args:
        moments: :class:`HatMoments`.
        rows: :math:`(E,)` int source vertices.
        cols: :math:`(E,)` int receiver vertices.

    Returns:
        ``(r, radial_var, transverse_var)``, each :math:`(E,)`.

    Raises:
        TypeError: ``moments`` not a :class:`HatMoments`, or ``rows``/``cols`` not integer tensors.
        ValueError: shapes other than :math:`(N, 3)`, :math:`(N, 3)`, :math:`(N, 3, 3)` and two equal :math:`(E,)`.

    Examples:
        >>> m = HatMoments(torch.tensor([[0.0, 0, 0], [3.0, 4, 0]]), torch.zeros(2, 3),
        ...                torch.diag(torch.tensor([1.0, 2.0, 0.0])).expand(2, 3, 3))
        >>> r, sr2, st2 = entry_moments(m, torch.tensor([0]), torch.tensor([1]))
        >>> round(float(r), 4), round(float(sr2), 4), round(float(st2), 4)  # u = (0.6, 0.8, 0)
        (5.0, 1.64, 1.36)
    """
    if not isinstance(moments, HatMoments):
        raise TypeError(f"moments: expected a HatMoments, got {type(moments).__name__}")
    n = moments.vertices.shape[0]
    for name, t, shape in (("moments.vertices", moments.vertices, (n, 3)),
                           ("moments.centroid", moments.centroid, (n, 3)),
                           ("moments.covariance", moments.covariance, (n, 3, 3))):
        if tuple(t.shape) != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {tuple(t.shape)}")
    for name, t in (("rows", rows), ("cols", cols)):
        if not isinstance(t, Tensor) or t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
            raise TypeError(f"{name}: expected an integer tensor, got "
                            f"{t.dtype if isinstance(t, Tensor) else type(t).__name__}")
    if rows.dim() != 1 or rows.shape != cols.shape:
        raise ValueError(f"rows, cols: expected two equal (E,) shapes, got {tuple(rows.shape)} and {tuple(cols.shape)}")
    dvec = moments.vertices[cols] - moments.centroid[rows]
    r = dvec.norm(dim=-1)
    u = dvec / r.clamp_min(torch.finfo(r.dtype).tiny).unsqueeze(-1)
    cov = moments.covariance[rows]
    radial = torch.einsum("ea,eab,eb->e", u, cov, u).clamp_min(0.0)
    transverse = (cov.diagonal(dim1=-2, dim2=-1).sum(-1) - radial).clamp_min(0.0)
    return r, radial, transverse


class HatQuadrature(NamedTuple):
    r"""The throughput's entries integrated over their source's hat (see :func:`hat_quadrature`).

    Every entry: the moment rule :math:`F_{ij} \approx \frac{A_i}{3}\,[\tfrac12 R(r + \sigma_r) + \tfrac12
    R(|r - \sigma_r|) + R(\sqrt{r^2 + \sigma_t^2}) - R(r)]`, with :math:`r` the distance from the hat's centroid
    to the receiver and :math:`\sigma_r^2`, :math:`\sigma_t^2` the hat's variance along and across that
    direction. The near entries (within ``radius_mm``, the self entries among them): :math:`F_{ij} = \sum_t w_t
    R(d_t)` over quadrature terms instead.

    Attributes:
        centroid_distance: :math:`(nnz,)` mm, :math:`r` of every entry.
        radial_var: :math:`(nnz,)` mm^2, :math:`\sigma_r^2`.
        transverse_var: :math:`(nnz,)` mm^2, :math:`\sigma_t^2`.
        entries: :math:`(E,)` int64 positions (in the throughput's row-major entries) of the near entries, sorted.
        term_entry: :math:`(T,)` int32 position in ``entries`` of every quadrature term (sorted).
        distance: :math:`(T,)` mm from the term's point on the hat of ``i`` to the receiver vertex ``j``.
        weight: :math:`(T,)` mm^2 the hat's value at the point times the point's area (they sum to :math:`A_i/3`
            per entry).
        radius_mm: the largest vertex distance :math:`|v_i - v_j|` of a near entry.
        moments: :class:`HatMoments` of the mesh, from which :func:`entry_moments` gives any entry's
            ``centroid_distance``, ``radial_var`` and ``transverse_var`` (in the mesh's dtype; the three columns
            above are computed in float64).
    """

    centroid_distance: Tensor
    radial_var: Tensor
    transverse_var: Tensor
    entries: Tensor
    term_entry: Tensor
    distance: Tensor
    weight: Tensor
    radius_mm: float
    moments: HatMoments | None = None


def _edge_lengths(tri: Tensor) -> Tensor:
    """:math:`(F, 3)` the lengths of edge k (corner k -> k + 1) of triangles :math:`(F, 3, 3)`."""
    return torch.stack([(tri[:, (k + 1) % 3] - tri[:, k]).norm(dim=-1) for k in range(3)], 1)


def _gauss_grid(u: tuple[Tensor, Tensor], v: tuple[Tensor, Tensor], device) -> tuple[Tensor, Tensor, Tensor]:
    """The tensor product of two 1-D rules ``(points, weights)`` on [0, 1]^2: flat ``(uu, vv, ww)`` on ``device``."""
    (gu, wu), (gv, wv) = u, v
    uu = gu[:, None].expand(gu.numel(), gv.numel()).reshape(-1).to(device)
    vv = gv[None, :].expand(gu.numel(), gv.numel()).reshape(-1).to(device)
    return uu, vv, (wu[:, None] * wv[None, :]).reshape(-1).to(device)


def _gauss01(n: int, levels: int = 0) -> tuple[Tensor, Tensor]:
    """Gauss-Legendre on [0, 1]: ``n`` points on each of ``levels + 1`` intervals graded by 4 towards 0.

    ``[0, 4^-levels], ..., [1/16, 1/4], [1/4, 1]`` (one interval for ``levels = 0``): a peak at 0 of width down to
    ``4^-levels`` is resolved.
    """
    x, w = np.polynomial.legendre.leggauss(n)
    edges = [0.0] + [4.0 ** -k for k in range(levels, -1, -1)]
    xs, ws = [], []
    for lo, hi in itertools.pairwise(edges):
        xs.append(lo + 0.5 * (x + 1.0) * (hi - lo))
        ws.append(0.5 * w * (hi - lo))
    return torch.from_numpy(np.concatenate(xs)), torch.from_numpy(np.concatenate(ws))


def hat_quadrature(mesh: Mesh, throughput: Throughput, *, radius_mm: float | None = None, subdivisions: int = 4,
                   duffy: tuple[int, int] = (6, 4), scale_mm: float | None = None,
                   max_terms: int = 50_000_000) -> HatQuadrature:
    r"""Quadrature of the near throughput entries over the source's hat.

    :math:`F_{ij} = \int \psi_i(s) R_d(|v_j - s|)\,ds` for the entries whose vertices lie within ``radius_mm``.

    Lensch's :math:`F_{ij} = A_i/3\,R_d(|v_i - v_j|)` samples the profile at the source vertex, which is a fine
    quadrature of the hat only while :math:`R_d` varies little across it: measured on a 30 mm marble torus (2304
    faces) against a converged quadrature, it is 16% low on average within 1.5 edges (the self term and the first
    ring, where the dipole's near field peaks), 6% at 1.5-3 edges, 2.8% at 3-5 and 1.6% at 5-8, in a pattern that
    follows the vertex layout (blotches at the vertex spacing, and an image 1-2% dark). With the irradiance
    represented on the hats (:math:`E \approx \sum_i E^g_i \psi_i`, the dual projection of
    :func:`vertex_weights`), the integral is what the vertex radiosity :math:`B^g_j = \sum_i E^g_i F_{ij}` means.

    Every entry gets the second-order moment rule of :class:`HatQuadrature` (the hat's centroid, its variance along
    and across the direction to the receiver, from a ``subdivisions``-fold rule on its faces): on that torus
    within 0.1% on average beyond 1.5 edges (rms 1.7% at 1.5-3 edges, 0.12% at 3-5, 0.03% at 5-8). The near
    entries, within ``radius_mm``, are integrated term by term, for every face ``f`` of the one-ring of ``i``:

    - ``f`` holds the receiver ``j`` (the self entry, and the first ring's shared faces): a Duffy rule with its apex
      at :math:`v_j`, ``duffy = (n_u, n_v)`` Gauss-Legendre points, :math:`s = v_j + u\,(e_1 + v\,(e_2 - e_1))`,
      :math:`ds = 2 A_f u\,du\,dv`: the profile's peak at :math:`v_j` is resolved at any width;
    - otherwise the centroids of the ``subdivisions``-fold subdivision of ``f``, weighted by their area
      :math:`A_f / n^2` and the hat's value (the barycentric of ``i``).

    The pattern stores distances and weights, not values (as :class:`Throughput`): any profile is evaluated on it
    (:class:`~torchsss.modules.lensch.GlobalResponse`).

    Args:
        mesh: the throughput's mesh (mm).
        throughput: :func:`build_throughput` of it.
        radius_mm: integrate the entries with :math:`|v_i - v_j|` up to this term by term (mm); default (None) per
            source: 2 median lengths of the edges at :math:`v_i` (on a uniform mesh about 2 median edges), or twice
            the longest edge of a sliver at :math:`v_i` (a row of :func:`~torchsss.geometry.refine.refine_creases`:
            a hat as long as its distance to the receiver is beyond the moment rule).
        subdivisions: n of the regular rule (>= 1).
        duffy: the Duffy rule's Gauss points along and across (each >= 1).
        scale_mm: the profile's shortest length (e.g. its spacing at 1%, :meth:`DipoleMaterial.spacing`), or
            None. Given, each pair's rule grows where its face is large against it: the Duffy rule's radial points
            are repeated on :math:`\lceil \log_4(4L/s)\rceil` (at most 10) intervals graded by 4 towards its apex
            (a peak far narrower than a face is resolved), its angular points grow to :math:`\lceil 1.5L/s\rceil`
            (at most 12), the regular rule to :math:`\lceil L/\max(s, g/5)\rceil` (at most 8), with L the face's
            middle edge (on a uniform mesh about the median edge, the single L of every face until 2026-12-07) and g
            the receiver's distance from the sphere around the face, never below ``duffy`` and ``subdivisions``. A
            sliver (its longest edge over 3 times its shortest: the rows of
            :func:`~torchsss.geometry.refine.refine_creases`) takes a collapsed Gauss rule instead, its apex
            opposite the shortest edge, :math:`\lceil 2L_{max}/g\rceil` points along (at most 24; at least
            ``subdivisions`` within half its length of the receiver, 2 beyond) and :math:`\lceil 2L_{min}/g\rceil`
            across (1-8), g the larger of s and the receiver's distance from the face. The regular rule takes at
            least 2 (not ``subdivisions``) on a face farther than its middle edge from the receiver.
        max_terms: refuse (ValueError) more quadrature terms than this (memory: 12 bytes a term in float32).

    Returns:
        :class:`HatQuadrature` in the mesh's dtype.

    Raises:
        TypeError, ValueError: bad arguments, a throughput of another mesh, too many terms.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> from torchsss.modules import DipoleMaterial
        >>> mesh = sphere(5.0, 2)
        >>> tp = build_throughput(mesh, DipoleMaterial.from_preset("marble"))
        >>> hq = hat_quadrature(mesh, tp)
        >>> per_entry = torch.zeros(hq.entries.numel()).index_add_(0, hq.term_entry, hq.weight)  # the hat's area
        >>> bool(torch.allclose(per_entry, mesh.vertex_areas[tp.rows[hq.entries]], rtol=1e-5))
        True
    """
    mesh = check_mesh(mesh)
    if not isinstance(throughput, Throughput):
        raise TypeError(f"throughput: expected a torchsss.geometry.lensch.Throughput, got {type(throughput).__name__}")
    if throughput.num_vertices != mesh.num_vertices:
        raise ValueError(f"throughput: expected one of this mesh ({mesh.num_vertices} vertices), got one of "
                         f"{throughput.num_vertices}")
    n = _check_int_arg(subdivisions, "subdivisions", 1)
    if not (isinstance(duffy, tuple) and len(duffy) == 2):
        raise TypeError(f"duffy: expected a tuple of two ints, got {duffy!r}")
    nu, nv = (_check_int_arg(x, "duffy", 1) for x in duffy)
    max_terms = _check_int_arg(max_terms, "max_terms", 1)
    scale = None
    if scale_mm is not None:
        if isinstance(scale_mm, bool) or not isinstance(scale_mm, numbers.Real) or not math.isfinite(scale_mm) \
                or scale_mm <= 0:
            raise ValueError(f"scale_mm: expected a finite number > 0 or None, got {scale_mm!r}")
        scale = float(scale_mm)
    v = mesh.vertices.detach().to(torch.float64)
    faces = mesh.faces
    device = v.device
    tri_all = v[faces]
    edge_len = _edge_lengths(tri_all)  # (F, 3)
    if radius_mm is None:
        reach = 2.0 * _vertex_median_edge(mesh)  # per source vertex
        # a hat with a sliver (a graded mesh's row beside a crease) reaches as far as its longest edge: the moment
        # rule of a hat as long as its distance to the receiver was 13% off on the rim-lit slab
        el = edge_len
        sliver_face = el.max(1).values > 3.0 * el.min(1).values
        if bool(sliver_face.any()):
            longest_at = torch.zeros(mesh.num_vertices, dtype=torch.float64, device=mesh.vertices.device)
            fl = torch.where(sliver_face, el.max(1).values, torch.zeros_like(el[:, 0]))
            for k in range(3):
                longest_at.scatter_reduce_(0, mesh.faces[:, k], fl, "amax")
            reach = torch.maximum(reach, 2.0 * longest_at)
        near = (throughput.distance.to(torch.float64) <= reach[throughput.rows]).nonzero()[:, 0]
        radius_mm = float(reach.max()) if reach.numel() else 0.0
    else:
        if isinstance(radius_mm, bool) or not isinstance(radius_mm, numbers.Real) or not math.isfinite(radius_mm) \
                or radius_mm < 0:
            raise ValueError(f"radius_mm: expected a finite number >= 0, got {radius_mm!r}")
        near = (throughput.distance.to(torch.float64) <= float(radius_mm)).nonzero()[:, 0]
    rows, cols = throughput.rows[near], throughput.cols[near]
    # the one-ring of every vertex as (face, corner) pairs, grouped by vertex (CSR)
    corner_vertex = faces.reshape(-1)
    order = torch.argsort(corner_vertex, stable=True)
    ring_face = torch.div(order, 3, rounding_mode="floor")
    ring_corner = order % 3
    offsets = torch.zeros(mesh.num_vertices + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(torch.bincount(corner_vertex, minlength=mesh.num_vertices), 0)
    counts = offsets[rows + 1] - offsets[rows]  # faces in the hat of each entry's source
    pair_entry = torch.arange(near.numel(), device=device).repeat_interleave(counts)
    start = torch.repeat_interleave(offsets[rows], counts)
    local = torch.arange(pair_entry.numel(), device=device) - torch.repeat_interleave(
        torch.cumsum(counts, 0) - counts, counts)
    slot = start + local
    pf, pc = ring_face[slot], ring_corner[slot]  # (pairs,) face and the corner of i in it
    fv = faces[pf]  # (pairs, 3)
    j = cols[pair_entry]
    # vertices by position: on a mesh split at creases (:func:`~torchsss.geometry.mesh.split_creases`) a copy of
    # ``j`` on the other side of the crease is the profile's peak as much as ``j`` itself
    same = torch.unique(v, dim=0, return_inverse=True)[1]
    has_j = (same[fv] == same[j][:, None]).any(1)
    area = mesh.face_areas.detach().to(torch.float64)[pf]
    # regular rule where the face does not hold j
    reg = (~has_j).nonzero()[:, 0]
    # the hat moments of every vertex in closed form (the monomials of the barycentrics integrate exactly: the hat
    # lambda_k times lambda_k^2, lambda_k lambda_m, lambda_a lambda_b over a face give A/10, A/30, A/60), in
    # coordinates relative to the hat's own vertex (q_k = 0)
    farea = mesh.face_areas.detach().to(torch.float64)
    mass = torch.zeros(mesh.num_vertices, dtype=torch.float64, device=device)
    first = torch.zeros_like(v)
    second = torch.zeros(mesh.num_vertices, 3, 3, dtype=torch.float64, device=device)
    for k in range(3):
        qa = v[faces[:, (k + 1) % 3]] - v[faces[:, k]]
        qb = v[faces[:, (k + 2) % 3]] - v[faces[:, k]]
        a = farea[:, None]
        mass.index_add_(0, faces[:, k], farea / 3.0)
        first.index_add_(0, faces[:, k], a / 12.0 * (qa + qb))
        outer = (qa[:, :, None] * qa[:, None, :] + qb[:, :, None] * qb[:, None, :]) / 30.0 + \
            (qa[:, :, None] * qb[:, None, :] + qb[:, :, None] * qa[:, None, :]) / 60.0
        second.index_add_(0, faces[:, k], a[:, :, None] * outer)
    tiny = torch.finfo(torch.float64).tiny
    offset = first / mass.clamp_min(tiny)[:, None]  # centroid - vertex
    centroid = v + offset
    cov = second / mass.clamp_min(tiny)[:, None, None] - offset[:, :, None] * offset[:, None, :]
    dtype = mesh.vertices.dtype
    nnz = throughput.rows.numel()
    # written block by block into the outputs (lists and a cat held every entry's moments twice)
    c_dist, r_var, t_var = (torch.empty(nnz, dtype=dtype, device=device) for _ in range(3))
    step = 1 << 18
    moments64 = HatMoments(v, centroid, cov)
    for lo in range(0, nnz, step):
        parts = entry_moments(moments64, throughput.rows[lo:lo + step], throughput.cols[lo:lo + step])
        for out, part in zip((c_dist, r_var, t_var), parts):
            out[lo:lo + step] = part.to(dtype)
        del parts
    has_j_rows = has_j.nonzero()[:, 0]
    # every pair's rule, from its face's size against the profile's shortest length (``scale_mm``) or, for the
    # regular rule, a fifth of the receiver's distance from the face if that is longer (on the coarse marble sphere of
    # tests/test_lensch_detail.py within 0.22% of a 576-point rule with 25% fewer terms than the uniform order; half
    # the distance was 1.1% off): the regular rule's order and the Duffy rule's grading and angular points from the
    # face's middle edge; without ``scale_mm`` the given orders everywhere
    n_reg = torch.full((reg.numel(),), n, dtype=torch.int64, device=device)
    # a sliver (a face of a mesh graded towards its creases, longest edge over 3x its shortest) takes a collapsed
    # Gauss rule instead: the apex opposite its shortest edge, n_u points along it and n_v across
    sliver = torch.zeros(reg.numel(), dtype=torch.bool, device=device)
    nu_sl = torch.zeros(reg.numel(), dtype=torch.int64, device=device)
    nv_sl = torch.zeros(reg.numel(), dtype=torch.int64, device=device)
    lev_duf = torch.zeros(has_j_rows.numel(), dtype=torch.int64, device=device)
    nv_duf = torch.full((has_j_rows.numel(),), nv, dtype=torch.int64, device=device)
    if scale is not None:
        longest = edge_len.max(1).values
        shortest = edge_len.min(1).values
        middle = edge_len.median(1).values
        fr = pf[reg]
        cen = tri_all.mean(1)
        rad = (tri_all - cen[:, None]).norm(dim=-1).max(1).values
        gap = ((v[j[reg]] - cen[fr]).norm(dim=-1) - rad[fr]).clamp_min(0.0)
        n_reg = torch.ceil(middle[fr] / torch.maximum(gap / 5.0, torch.full_like(gap, scale))).to(torch.int64)
        # at least the given order next to the receiver, 2 beyond a face's size from it
        floor = torch.where(gap < middle[fr], torch.full_like(n_reg, n), torch.full_like(n_reg, min(n, 2)))
        n_reg = torch.maximum(n_reg, floor).clamp_max(max(n, 8))
        sliver = longest[fr] > 3.0 * shortest[fr]
        if bool(sliver.any()):
            t = tri_all[fr[sliver]]
            bc = closest_point_on_triangle(v[j[reg[sliver]]], t[:, 0], t[:, 1], t[:, 2])
            near_gap = (v[j[reg[sliver]]] - torch.einsum("pk,pkd->pd", bc, t)).norm(dim=-1).clamp_min(scale)
            long_sl = longest[fr[sliver]]
            nu_sl[sliver] = torch.maximum(torch.ceil(2.0 * long_sl / near_gap).to(torch.int64),
                                          torch.where(near_gap < 0.5 * long_sl, n, 2)).clamp_max(24)
            nv_sl[sliver] = torch.ceil(2.0 * shortest[fr[sliver]] / near_gap).to(torch.int64).clamp(1, 8)
        ratio = middle[pf[has_j_rows]] / scale
        lev_duf = torch.ceil(torch.log(torch.clamp(4.0 * ratio, min=1.0)) / math.log(4.0)).to(torch.int64).clamp(0, 10)
        nv_duf = torch.ceil(1.5 * ratio).to(torch.int64).clamp(nv, max(nv, 12))
    pair_terms = torch.zeros(pair_entry.numel(), dtype=torch.int64, device=device)
    pair_terms[reg] = torch.where(sliver, nu_sl * nv_sl, n_reg * n_reg)
    pair_terms[has_j_rows] = nu * (lev_duf + 1) * nv_duf
    terms = int(pair_terms.sum())
    if terms > max_terms:
        raise ValueError(f"max_terms: expected at most {max_terms} quadrature terms, got {terms} ({near.numel()} "
                         f"entries within {radius_mm:.3g} mm); lower radius_mm or subdivisions")
    # the terms are written straight into their place in the output, in the order of the pairs (sorted by entry: the
    # terms are too); the parts, their concatenation, a sort and the sorted copies peaked at 4-5 times the output
    pair_start = torch.cumsum(pair_terms, 0) - pair_terms
    term_entry = torch.repeat_interleave(pair_entry.to(torch.int32), pair_terms)
    distance = torch.empty(terms, dtype=dtype, device=device)
    weight = torch.empty(terms, dtype=dtype, device=device)
    plain = ~sliver
    for order in torch.unique(n_reg[plain]).tolist():  # regular rule on faces without j, by order
        sel = reg[plain & (n_reg == order)]
        bary = subdivision_barycentrics(order, dtype=torch.float64, device=device)  # (n^2, 3)
        q = order * order
        block = max(1, (1 << 21) // q)  # pairs per block: about 2M terms of float64 at a time
        for lo in range(0, sel.numel(), block):
            rb = sel[lo:lo + block]
            tri = v[fv[rb]]  # (r, 3, 3)
            pts = torch.einsum("qk,rkd->rqd", bary, tri)
            hat = bary[:, pc[rb]].T  # (r, q): the barycentric of i
            d_reg = (pts - v[j[rb]][:, None, :]).norm(dim=-1)
            w_reg = area[rb][:, None] / q * hat
            at = (pair_start[rb][:, None] + torch.arange(q, device=device)).reshape(-1)
            distance[at] = d_reg.reshape(-1).to(dtype)
            weight[at] = w_reg.reshape(-1).to(dtype)
    if bool(sliver.any()):  # collapsed rule on slivers, by (n_u, n_v)
        key_sl = nu_sl * 64 + nv_sl
        for key in torch.unique(key_sl[sliver]).tolist():
            sel = reg[sliver & (key_sl == key)]
            uu, vv, ww = _gauss_grid(_gauss01(key // 64), _gauss01(key % 64), device)
            q = uu.numel()
            block = max(1, (1 << 21) // q)
            for lo in range(0, sel.numel(), block):
                rb = sel[lo:lo + block]
                tri = v[fv[rb]]  # (r, 3, 3)
                apex = (edge_len[pf[rb]].argmin(1) + 2) % 3  # opposite the shortest edge
                ca, cb = (apex + 1) % 3, (apex + 2) % 3
                x0 = tri.gather(1, apex[:, None, None].expand(-1, 1, 3))[:, 0]
                xa = tri.gather(1, ca[:, None, None].expand(-1, 1, 3))[:, 0]
                xb = tri.gather(1, cb[:, None, None].expand(-1, 1, 3))[:, 0]
                pts = x0[:, None] + uu[None, :, None] * ((xa - x0)[:, None] + vv[None, :, None] * (xb - xa)[:, None])
                d_sl = (pts - v[j[rb]][:, None, :]).norm(dim=-1)
                ic = pc[rb]
                hat = torch.where((ic == apex)[:, None], 1.0 - uu[None, :],
                                  torch.where((ic == ca)[:, None], uu[None, :] * (1.0 - vv[None, :]),
                                              uu[None, :] * vv[None, :]))
                w_sl = 2.0 * area[rb][:, None] * uu[None, :] * ww[None, :] * hat
                at = (pair_start[rb][:, None] + torch.arange(q, device=device)).reshape(-1)
                distance[at] = d_sl.reshape(-1).to(dtype)
                weight[at] = w_sl.reshape(-1).to(dtype)
    # Duffy rule with the apex at v_j where the face holds j, by (grading, angular points)
    rule = lev_duf * 64 + nv_duf
    for key in torch.unique(rule).tolist():
        pick = rule == key
        sel = has_j_rows[pick]
        uu, vv, ww = _gauss_grid(_gauss01(nu, key // 64), _gauss01(key % 64), device)
        nq = uu.numel()
        block = max(1, (1 << 21) // nq)
        for lo in range(0, sel.numel(), block):
            dj = sel[lo:lo + block]
            fvd = fv[dj]
            jj = j[dj]
            apex_corner = (same[fvd] == same[jj][:, None]).to(torch.int64).argmax(1)
            a_corner, b_corner = (apex_corner + 1) % 3, (apex_corner + 2) % 3
            x0 = v[jj]
            xa = v[fvd.gather(1, a_corner[:, None])[:, 0]]
            xb = v[fvd.gather(1, b_corner[:, None])[:, 0]]
            e1, e2 = xa - x0, xb - x0
            direction = e1[:, None, :] + vv[None, :, None] * (e2 - e1)[:, None, :]  # (p, q, 3)
            d_duf = uu[None, :] * direction.norm(dim=-1)
            # the hat of i at s: barycentrics (1 - u, u (1 - v), u v) of (apex, a, b)
            i_corner = pc[dj]
            hat_duf = torch.where((i_corner == apex_corner)[:, None], 1.0 - uu[None, :],
                                  torch.where((i_corner == a_corner)[:, None], uu[None, :] * (1.0 - vv[None, :]),
                                              uu[None, :] * vv[None, :]))
            w_duf = 2.0 * area[dj][:, None] * uu[None, :] * ww[None, :] * hat_duf
            at = (pair_start[dj][:, None] + torch.arange(nq, device=device)).reshape(-1)
            distance[at] = d_duf.reshape(-1).to(dtype)
            weight[at] = w_duf.reshape(-1).to(dtype)
    moments = HatMoments(v.to(dtype), centroid.to(dtype), cov.to(dtype))
    return HatQuadrature(c_dist, r_var, t_var, near, term_entry, distance, weight, float(radius_mm), moments)


def _check_int_arg(x: object, name: str, minimum: int) -> int:
    if isinstance(x, bool) or not isinstance(x, numbers.Integral):
        raise TypeError(f"{name}: expected an int >= {minimum}, got {type(x).__name__}")
    if x < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, got {x}")
    return int(x)


# --------------------------------------------------------------------------------------------------------------
# blending of the local and the global response
# --------------------------------------------------------------------------------------------------------------


class BlendWeights(NamedTuple):
    """Lensch §5.4 blending: direct-radiosity weights and kernel corrections (see :func:`blending_weights`).

    Attributes:
        weights: :math:`(C, 3, H, W)` :math:`w_\\nu(u, v)`, the contribution per unit irradiance of texel
            ``(u, v)`` to the direct radiosity :math:`B^d` of the three vertices ``vertex_ids`` of its face
            (:math:`B^d_i = \\sum_{texels} w E`, scattered like the dual weights); 0 off chart texels.
        kernel_correction: :math:`(C, H, W, k, k)` to add to the gather-form kernels ``area * R_d(distance)`` of
            :func:`local_kernel_geometry`: minus the interpolated :math:`B^{g0} + B^d` response of the source
            ``s = (y + i - k//2, x + j - k//2)`` at the receiver ``(y, x)``. With ``index``: :math:`(C, N, k, k)`,
            the receivers of a compact :class:`LocalKernelGeometry`.
    """

    weights: Tensor
    kernel_correction: Tensor


def blending_weights(
    mesh: Mesh,
    atlas: Atlas,
    profile: Callable[[Tensor], Tensor],
    *,
    kernel_size: int = 7,
    threshold: float = THROUGHPUT_THRESHOLD,
    relative: bool = True,
    chunk_texels: int = 1024,
    fit_radius: int | None = None,
    index: Tensor | None = None,
    progress: bool = False,
) -> BlendWeights:
    """Blend the local kernels with the global vertex response (Lensch §5.4), per chart texel, per channel.

    The combined response is :math:`B = B^l + B^{g0} + B^d` (Lensch eq. 9) with :math:`F^0` the throughput of
    :func:`build_throughput` with ``zero_diagonal=True`` and the same ``threshold``/``relative``. For a unit
    impulse of irradiance at a chart texel ``o`` (scatter view): :math:`E^g_\\nu` = its dual weights,
    :math:`B^{g0}_j = \\sum_\\nu E^g_\\nu F^0_{\\nu j}` (the 9 pairs source-face x receiver-face vertices are
    evaluated directly from the vertex positions), interpolated at a receiver ``s`` with its barycentrics. The
    weights minimise, on the ring :math:`\\Gamma` = valid texels on the border of the ``(k+2) x (k+2)`` window,

    .. math::
        \\sum_{s \\in \\Gamma} \\Big[A(o) R_d(|x_o - x_s|) - B^{g0}(x_s)
        - \\sum_\\nu w_\\nu \\hat\\psi_\\nu(x_s)\\Big]^2,

    :math:`\\hat\\psi_\\nu(x_s)` the barycentric of vertex :math:`\\nu` in the face of ``s`` (0 if it is not a
    vertex of that face); a tiny ridge makes the 3 x 3 normal equations regular (``w = 0`` for a ring that sees
    none of the three vertices). The kernel correction then subtracts the impulse's :math:`B^{g0} + B^d` inside
    the ``k x k`` window, so that local + global reproduces :math:`A(o) R_d(|x_o - x_s|)` there exactly; far
    from ``o`` the response is the global one without its diagonal.

    Only chart texels are impulses here (gutter texels carry no dual weight, so they feed no global response;
    their weights and corrections are 0). Computed in float64, chunked over texels.

    Args:
        mesh: The mesh of the atlas, mm.
        atlas: Its texture atlas (``padding >= k//2 + 1`` so that the ring reads filled texels).
        profile: The material's profile, as in :func:`build_throughput`.
        kernel_size: Odd ``k`` of the local kernels.
        threshold: Throughput threshold, as in :func:`build_throughput`.
        relative: As in :func:`build_throughput`.
        chunk_texels: Source texels per chunk (working memory ~ 60 kB each at k = 11).
        fit_radius: Fit the weights on the band of texels with ``k//2 < Chebyshev distance <= fit_radius``
            instead of Lensch's single ring (``None``: ``k//2 + 1``, the ring).
        index: None, or the :math:`(N,)` receivers of a compact geometry (``local_kernel_geometry(...,
            compact=True).index``, every valid texel among them): the correction is then :math:`(C, N, k, k)`,
            never the full :math:`(C, H, W, k, k)` (363 MB at atlas 512 and k = 11).
        progress: Show a tqdm bar over the chunks.

    Returns:
        :class:`BlendWeights`, in the atlas's dtype and device.

    Raises:
        TypeError: wrong argument types.
        ValueError: bad kernel size, threshold, material, mismatched mesh and atlas, or an ``index`` that misses a
            valid texel.

    Examples:
        >>> from torchsss.geometry import build_atlas, sphere
        >>> mesh = sphere(5.0, 1)
        >>> atlas = build_atlas(mesh, 32, kernel_size=3)
        >>> from torchsss.modules import DipoleMaterial
        >>> bw = blending_weights(mesh, atlas, DipoleMaterial.from_preset("marble"), kernel_size=3)
        >>> tuple(bw.weights.shape), tuple(bw.kernel_correction.shape)
        ((3, 3, 32, 32), (3, 32, 32, 3, 3))
    """
    mesh = check_mesh(mesh)
    atlas = _check_atlas(atlas)
    k = _check_kernel_size(kernel_size)
    threshold, relative = _check_threshold(threshold, relative)
    progress = _check_bool(progress, "progress")
    if isinstance(chunk_texels, bool) or not isinstance(chunk_texels, numbers.Integral):
        raise TypeError(f"chunk_texels: expected a positive int, got {type(chunk_texels).__name__}")
    if chunk_texels < 1:
        raise ValueError(f"chunk_texels: expected a positive int, got {chunk_texels}")
    vw = vertex_weights(mesh, atlas, discrete=False)
    device = atlas.position.device
    prof, channels = _profile64(profile, device)
    f64 = torch.float64
    v = mesh.vertices.detach().to(device=device, dtype=f64)
    va = mesh.vertex_areas.detach().to(device=device, dtype=f64)
    thr = _absolute_threshold(va, prof, threshold, relative)

    height, width = atlas.shape
    r = k // 2
    if fit_radius is None:
        ring_r = r + 1
    elif isinstance(fit_radius, bool) or not isinstance(fit_radius, numbers.Integral):
        raise TypeError(f"fit_radius: expected an int or None, got {type(fit_radius).__name__}")
    elif fit_radius < r + 1:
        raise ValueError(f"fit_radius: expected an int >= kernel_size // 2 + 1 = {r + 1}, got {fit_radius}")
    else:
        ring_r = int(fit_radius)
    ids = vw.vertex_ids[0].permute(1, 2, 0).reshape(-1, 3)  # (HW, 3)
    bary = vw.bary[0].permute(1, 2, 0).reshape(-1, 3).to(f64)
    dual = vw.dual[0].permute(1, 2, 0).reshape(-1, 3).to(f64)
    pos = atlas.position[0].permute(1, 2, 0).reshape(-1, 3).to(f64)
    area = (atlas.area[0, 0] * atlas.valid_mask[0, 0]).reshape(-1).to(f64)
    valid = atlas.valid_mask[0, 0].reshape(-1)
    face = atlas.face_id[0, 0].reshape(-1).clamp_min(0)
    faces = mesh.faces.to(device)
    num_faces = faces.shape[0]
    sources = atlas.chart_mask[0, 0].reshape(-1).nonzero(as_tuple=True)[0]

    span = torch.arange(-ring_r, ring_r + 1, device=device)
    dy, dx = torch.meshgrid(span, span, indexing="ij")
    dy, dx = dy.reshape(-1), dx.reshape(-1)  # (P,), P = (2 ring_r + 1)^2
    cheb = torch.maximum(dy.abs(), dx.abs())
    # the ring (Lensch) or, with fit_radius, the band from the ring out to fit_radius
    ring_at = (cheb > r).nonzero(as_tuple=True)[0]
    inner_at = (cheb <= r).nonzero(as_tuple=True)[0]  # row-major over the k x k window

    dtype = atlas.position.dtype
    receivers = height * width
    slot = None
    if index is not None:
        if not isinstance(index, Tensor) or index.dtype != torch.int64 or index.dim() != 1:
            got = (f"{index.dtype} of shape {tuple(index.shape)}" if isinstance(index, Tensor)
                   else type(index).__name__)
            raise TypeError(f"index: expected a (N,) int64 tensor or None, got {got}")
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= receivers):
            raise ValueError(f"index: expected flat texels in [0, {receivers}), got [{int(index.min())}, "
                             f"{int(index.max())}]")
        slot = torch.full((receivers,), -1, dtype=torch.int64, device=device)
        slot[index.to(device)] = torch.arange(index.numel(), device=device)
        if bool((slot[valid.nonzero(as_tuple=True)[0]] < 0).any()):
            raise ValueError("index: expected every valid texel of the atlas among the receivers, some are missing")
        receivers = index.numel()
    weights = torch.zeros(height * width, 3, channels, dtype=f64, device=device)
    # gather form: correction[c, y, x, i, j] = the impulse response of the source at (y + i - r, x + j - r) at offset
    # (r - i, r - j); each (receiver, tap) has exactly one source, so every chunk writes its sources' responses
    # straight into the output layout (no per-source scatter buffer)
    correction = torch.zeros(channels, receivers * k * k, dtype=dtype, device=device)
    tap = (r - dy[inner_at]) * k + (r - dx[inner_at])  # (k*k,) the receiver's tap that reads offset (dy, dx)
    eye = torch.eye(3, dtype=f64, device=device)
    for lo in tqdm(range(0, sources.numel(), chunk_texels), desc="blending", unit="chunk", disable=not progress):
        o = sources[lo:lo + chunk_texels]
        oy, ox = o // width, o % width
        ys, xs = oy[:, None] + dy, ox[:, None] + dx  # (M, P)
        inside = (ys >= 0) & (ys < height) & (xs >= 0) & (xs < width)
        s = torch.where(inside, ys * width + xs, torch.zeros_like(ys))
        ok = inside & valid[s]
        ids_o, ids_s = ids[o], ids[s]  # (M, 3), (M, P, 3)
        bary_s = bary[s] * ok[..., None]
        # F^0 between the 3 source-face vertices (nu) and the 3 receiver-face vertices (m), per channel: it depends
        # on the pair of faces only, and a window holds few faces, so the profile is evaluated once per distinct
        # face pair of the chunk (~100x fewer evaluations than per texel pair) and gathered back
        pair, inverse = torch.unique(face[o][:, None] * num_faces + face[s], return_inverse=True)  # (U,), (M, P)
        fv_o, fv_s = faces[pair // num_faces], faces[pair % num_faces]  # (U, 3)
        rd = prof(_distance(v[fv_o][:, :, None, :], v[fv_s][:, None, :, :]).unsqueeze(-1))  # (U, 3, 3, C)
        f0 = va[fv_o][:, :, None, None] * rd
        keep = (f0.amax(-1) >= thr) & (fv_o[:, :, None] != fv_s[:, None, :])
        f0 = (f0 * keep[..., None])[inverse]  # (M, P, 3, 3, C)
        b_g0 = torch.einsum("mn,mpnqc,mpq->mpc", dual[o], f0, bary_s)  # (M, P, C)
        hat = torch.einsum("mpq,mpnq->mpn", bary_s, (ids_s[:, :, None, :] == ids_o[:, None, :, None]).to(f64))
        # the fit reads the ring only: the target profile is evaluated there
        s_ring = s[:, ring_at]
        target = area[o][:, None, None] * prof(_distance(pos[o][:, None, :], pos[s_ring])[..., None])  # (M, R, C)
        ring = ok[:, ring_at].to(f64)[..., None]
        h_ring = hat[:, ring_at] * ring  # (M, R, 3)
        gram = h_ring.transpose(1, 2) @ h_ring  # (M, 3, 3)
        rhs = h_ring.transpose(1, 2) @ ((target - b_g0[:, ring_at]) * ring)  # (M, 3, C)
        trace = gram.diagonal(dim1=1, dim2=2).sum(-1)
        ridge = torch.where(trace > 0, _RIDGE * trace / 3.0, torch.ones_like(trace))
        w = torch.linalg.solve(gram + ridge[:, None, None] * eye, rhs)
        weights[o] = w
        b_d = hat[:, inner_at] @ w  # (M, k*k, C)
        hit = ok[:, inner_at]  # (M, k*k): valid receivers inside the image
        rec = s[:, inner_at] if slot is None else slot[s[:, inner_at]]
        flat = (rec * (k * k) + tap)[hit]
        correction[:, flat] = (-(b_g0[:, inner_at] + b_d))[hit].T.to(dtype)
    weights_img = weights.view(height, width, 3, channels).permute(3, 2, 0, 1).to(dtype).contiguous()
    if slot is not None:
        return BlendWeights(weights_img, correction.view(channels, receivers, k, k))
    return BlendWeights(weights_img, correction.view(channels, height, width, k, k))


#: Fraction of the atlas square that charts cover, used by :func:`plan_kernel_size` to estimate the texel size
#: before the atlas exists (xatlas packs 0.36-0.52 of the square for the meshes measured in benchmarks/).
ATLAS_UTILIZATION = 0.45


def plan_kernel_size(mesh: Mesh, resolution: int, *, reach: float = 0.7, k_min: int = 5, k_max: int = 11,
                     utilization: float = ATLAS_UTILIZATION) -> int:
    r"""Local kernel size for Lensch's blending: the kernel must reach towards the neighbouring vertices.

    The blended method hands the near field to the k x k texel kernel and everything beyond to the vertex
    throughput; the §5.4 least-squares fit on the kernel's ring joins the two. When the kernel's half-width is
    small against the vertex spacing the global term has to carry the near field it cannot resolve, and the
    error grows with the profile's sharpness (benchmarks/results/lensch.md: spot, skin1, 0.74 mm edges,
    atlas 512: 4.6% at k = 7, 3.0% at k = 9, 2.6% at k = 11). The rule: the smallest odd k whose half-width
    ``(k // 2) * texel`` is about ``reach`` times the median edge length, clamped to ``[k_min, k_max]``; the
    texel size is estimated from the mesh area as :math:`\sqrt{A / (u\,\mathrm{resolution}^2)}`.

    Args:
        mesh: the surface (mm).
        resolution: atlas resolution (texels per side).
        reach: kernel half-width over the median edge length.
        k_min: smallest kernel (odd).
        k_max: largest kernel (odd); the blending precompute grows with :math:`k^2`.
        utilization: assumed fraction of the atlas covered by charts.

    Returns:
        An odd kernel size.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> plan_kernel_size(sphere(10.0, 3), 512) in (5, 7, 9, 11)
        True
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh: expected a torchsss.geometry.Mesh, got {type(mesh).__name__}")
    if isinstance(resolution, bool) or not isinstance(resolution, numbers.Integral) or resolution < 1:
        raise ValueError(f"resolution: expected an int >= 1, got {resolution!r}")
    k_min, k_max = _check_kernel_size(k_min), _check_kernel_size(k_max)
    if k_min > k_max:
        raise ValueError(f"k_min, k_max: expected k_min <= k_max, got {k_min} > {k_max}")
    if not (0.0 < float(reach) < math.inf):
        raise ValueError(f"reach: expected a positive number, got {reach!r}")
    if not (0.0 < float(utilization) <= 1.0):
        raise ValueError(f"utilization: expected a number in (0, 1], got {utilization!r}")
    edge = median_edge(mesh)
    texel = math.sqrt(float(mesh.area) / (float(utilization) * resolution * resolution))
    half = round(float(reach) * edge / texel) if texel > 0 else k_min // 2
    return int(min(max(2 * half + 1, k_min), k_max))


#: Smallest kernel reach (half-width over the median edge) at which blending pays off; measured in
#: benchmarks/results/lensch.md: blending won at reach 0.55-0.72 (bunny 9.4% -> 2.3%, spot 2.6%) and lost at
#: 0.21-0.41 (checker plane 4.6% -> 30%, spot k 7 3.4% -> 4.6%).
BLEND_MIN_REACH = 0.5


def _vertex_median_edge(mesh: Mesh) -> Tensor:
    """:math:`(V,)` float64: the median length of the edges at every vertex (each edge counted once per face)."""
    f = mesh.faces
    v = mesh.vertices.detach().to(torch.float64)
    a = torch.cat([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    b = torch.cat([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    length = (v[a] - v[b]).norm(dim=1)
    order = torch.argsort(a * (length.max() + 1.0 if length.numel() else 1.0) + length)  # by vertex, then length
    a, length = a[order], length[order]
    counts = torch.bincount(a, minlength=mesh.num_vertices)
    start = torch.cumsum(counts, 0) - counts
    mid = (start + torch.div(counts - 1, 2, rounding_mode="floor")).clamp_min(0)
    out = length[mid.clamp_max(max(length.numel() - 1, 0))] if length.numel() else v.new_zeros(mesh.num_vertices)
    return torch.where(counts > 0, out, torch.zeros_like(out))


def median_edge(mesh: Mesh) -> float:
    """The median edge length of ``mesh`` (mm; every face's three edges)."""
    f = mesh.faces
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    v = mesh.vertices.detach().to(torch.float64)
    return float((v[edges[:, 0]] - v[edges[:, 1]]).norm(dim=1).median())


def plan_lensch(mesh: Mesh, resolution: int, *, utilization: float = ATLAS_UTILIZATION) -> tuple[int, bool]:
    """Kernel size and whether to blend, for a mesh and an atlas resolution (the pipeline's defaults).

    The kernel comes from :func:`plan_kernel_size`. Blending (Lensch §5.4) fits the direct term on the kernel's
    ring and spreads it over the vertex hats; when even the planned kernel reaches less than
    :data:`BLEND_MIN_REACH` median edges the fitted level is that of the profile's peak and the blended
    response overshoots badly, so the unblended sum with Lensch's 7 x 7 kernel is returned instead.

    Returns:
        ``(kernel_size, blend)``.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> k, blend = plan_lensch(sphere(10.0, 3), 512)
        >>> k % 2, isinstance(blend, bool)
        (1, True)
    """
    k = plan_kernel_size(mesh, resolution, utilization=utilization)
    if kernel_reach(mesh, resolution, k, utilization=utilization) >= BLEND_MIN_REACH:
        return k, True
    return 7, False


def kernel_reach(mesh: Mesh, resolution: int, kernel_size: int, *, utilization: float = ATLAS_UTILIZATION) -> float:
    """A ``kernel_size`` kernel's half-width over the median edge at atlas ``resolution`` (inf on a degenerate mesh).

    Examples:
        >>> from torchsss.geometry import sphere
        >>> kernel_reach(sphere(10.0, 3), 1024, 7) < kernel_reach(sphere(10.0, 3), 512, 7)
        True
    """
    texel = math.sqrt(float(mesh.area) / (float(utilization) * resolution * resolution))
    edge = median_edge(mesh)
    return (kernel_size // 2) * texel / edge if edge > 0 else math.inf
