"""A batched, vectorised triangle rasterizer in pure PyTorch (CPU and CUDA), with attribute interpolation.

:func:`rasterize` turns triangles in homogeneous clip space (OpenGL conventions, see
:mod:`torchsss.geometry.camera`) into per-pixel G-buffer channels: the visible face, its perspective-correct
barycentric weights, NDC depth and a coverage mask. :func:`interpolate` uses them to gather vertex attributes
(positions, normals, UVs, ...) differentiably, and :func:`rasterize_uv` rasterizes triangles in texture space
(the texel-to-face map of an atlas) through the same code path.

Conventions:

* Images are :math:`(B, C, H, W)`, masks :math:`(B, 1, H, W)` bool; row 0 is the *top* of the image
  (NDC :math:`y = +1`), pixel (row :math:`r`, column :math:`c`) is sampled at its centre, NDC
  :math:`x = 2 (c + 0.5) / W - 1`, :math:`y = 1 - 2 (r + 0.5) / H`. One sample per pixel (no anti-aliasing).
* Coverage is decided by edge functions at the pixel centre, *inclusively*: a centre exactly on an edge belongs
  to both triangles and the depth test picks one. Each edge function is written so that the two triangles
  sharing an edge evaluate it from bitwise equal operands and get exactly opposite values (see ``_edges``):
  meshes rasterize without cracks, whatever the rounding.
* Visibility: a z-buffer on NDC :math:`z` (smaller is nearer), resolved without races by packing
  (depth quantised to 31 bits, face id) into one int64 key and taking the minimum per pixel
  (``scatter_reduce_(..., "amin")``). Depths equal after quantisation (steps of :math:`2^{-30}` in NDC z) go to
  the lower face id, so the result is exactly deterministic (also on CUDA, where the integer minimum does not
  depend on the order of the atomic updates) and independent of the order in which faces are processed.
* Clipping: a triangle with any vertex at :math:`w \\le 10^{-6}` (at or behind the camera's eye plane, where
  the perspective divide flips) is *dropped* whole. Other triangles are clipped per pixel against the near and
  far planes: a sample whose interpolated NDC :math:`z` is outside :math:`[-1, 1]` is discarded. So a triangle
  that crosses the near plane but lies entirely in front of the eye keeps its part beyond the near plane,
  while one reaching behind the eye disappears (split such triangles beforehand if that matters).
* Zero-area triangles (in screen space) cover nothing. With ``cull_backfaces=True`` triangles whose screen-space
  vertices run clockwise (NDC :math:`y` up; counter-clockwise is the front) are dropped.
* Precision: float64 inputs are rasterized in float64, everything else in float32 (float64 edge functions cost
  1.4-2.2x the time on CPU and changed 0-2 pixels of a 69k-face mesh at 1024 x 1024). In float32, vertices far
  outside the image (screen coordinates of :math:`10^6` pixels) lose sub-pixel accuracy near their edges.

Algorithm (no Python loop over faces or pixels): per face, the perspective divide, a pixel bounding box clipped
to the image, culling and the edge functions; faces are sorted into buckets by the size of their bounding box
(next powers of two of its height and width), and every face of a bucket is expanded into its candidate pixel
grid (in chunks of at most ``max_candidates`` candidates, tiling a single face's grid if needed, so memory stays
bounded even for a triangle covering the whole image). Inside candidates are depth-tested with one
``scatter_reduce_``; the winners' barycentrics are then recomputed once per covered pixel.
"""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsss._checks import is_tracing

__all__ = ["Raster", "depth_peel", "interpolate", "rasterize", "rasterize_depth", "rasterize_uv", "screen_coords"]

_W_EPS = 1e-6
_KEY_EMPTY = torch.iinfo(torch.int64).max
_DEPTH_SCALE = float(2**31 - 2) / 2.0  # NDC z in [-1, 1] -> [0, 2^31 - 2]
_Q_CLIPPED = 2**31 - 1  # quantised depth of a fragment clipped by the near/far planes: never "covered"
_KEY_LIMIT = _Q_CLIPPED << 32  # keys below this are visible fragments
_ID_MASK = 0xFFFFFFFF
_SETUP_FACES = 2**17  # faces (over the batch) per setup group
_PEEL_TOL_EPS = 16.0  # depth_peel: a pixel centre within 16 eps (H + W) pixels of an edge's line is on it
_BBOX_MARGIN = 1.0 / 64.0  # pixels; keeps the bounding box conservative against rounding in the edge functions


class Raster(NamedTuple):
    """Output of :func:`rasterize`: per-pixel visible face, barycentrics, depth and coverage.

    Attributes:
        face_id: :math:`(B, 1, H, W)` int64 index of the visible face, -1 on background.
        bary: :math:`(B, 3, H, W)` perspective-correct barycentric weights of the face's vertices 0, 1, 2
            (they sum to 1 on covered pixels; zeros on background).
        depth: :math:`(B, 1, H, W)` NDC :math:`z` of the visible surface (in :math:`[-1, 1]`, smaller is
            nearer; :math:`+\\infty` on background).
        mask: :math:`(B, 1, H, W)` bool, True where a face covers the pixel centre.
    """

    face_id: Tensor
    bary: Tensor
    depth: Tensor
    mask: Tensor


# -- validation -----------------------------------------------------------------------------------------------------
def _check_clip(clip_pos: object) -> Tensor:
    if not isinstance(clip_pos, Tensor):
        raise TypeError(f"clip_pos: expected a torch.Tensor, got {type(clip_pos).__name__}")
    if not clip_pos.is_floating_point():
        raise TypeError(f"clip_pos: expected a floating-point tensor, got dtype {clip_pos.dtype}")
    if clip_pos.dim() not in (2, 3) or clip_pos.shape[-1] != 4:
        raise ValueError(f"clip_pos: expected shape (V, 4) or (B, V, 4), got {tuple(clip_pos.shape)}")
    clip = clip_pos if clip_pos.dim() == 3 else clip_pos.unsqueeze(0)
    if clip.shape[0] < 1:
        raise ValueError(f"clip_pos: expected a batch size >= 1, got {tuple(clip_pos.shape)}")
    if not is_tracing() and clip.numel() and not bool(torch.isfinite(clip).all()):
        bad = ~torch.isfinite(clip.detach())
        first = clip.detach()[bad][0].item()
        raise ValueError(f"clip_pos: expected finite values, got {first!r} ({int(bad.sum())} of {clip.numel()} "
                         "entries bad)")
    return clip


def _check_faces(faces: object, num_vertices: int) -> Tensor:
    if not isinstance(faces, Tensor):
        raise TypeError(f"faces: expected a torch.Tensor, got {type(faces).__name__}")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise TypeError(f"faces: expected an integer tensor, got dtype {faces.dtype}")
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {tuple(faces.shape)}")
    if faces.shape[0] >= _ID_MASK:
        raise ValueError(f"faces: expected fewer than {_ID_MASK} faces, got {faces.shape[0]}")
    faces = faces.long()
    if not is_tracing() and faces.numel():
        lo, hi = (int(t) for t in torch.aminmax(faces))
        if lo < 0 or hi >= num_vertices:
            bad = lo if lo < 0 else hi
            raise ValueError(f"faces: expected vertex indices in [0, {num_vertices - 1}], got {bad}")
    return faces


def _check_resolution(resolution: object) -> tuple[int, int]:
    if isinstance(resolution, Tensor) or not isinstance(resolution, (tuple, list)) or len(resolution) != 2:
        raise TypeError(f"resolution: expected a pair of positive ints (H, W), got {resolution!r}")
    out = []
    for v in resolution:
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):
            raise TypeError(f"resolution: expected a pair of positive ints (H, W), got {resolution!r}")
        if v < 1:
            raise ValueError(f"resolution: expected a pair of positive ints (H, W), got {resolution!r}")
        out.append(int(v))
    return out[0], out[1]


def _check_max_candidates(value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"max_candidates: expected an int >= 1, got {type(value).__name__}")
    if value < 1:
        raise ValueError(f"max_candidates: expected an int >= 1, got {value!r}")
    return int(value)


# -- geometry helpers -----------------------------------------------------------------------------------------------
def screen_coords(x: Tensor, y: Tensor, z: Tensor, w: Tensor, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """Screen coordinates (x right, y *up*, in pixels) and NDC z of clip-space coordinates (any equal shapes).

    Elementwise, so the coverage pass and the barycentric pass get bitwise equal values for a vertex (and
    :mod:`torchsss.geometry.coverage` measures faces in the same pixels).

    Examples:
        >>> x, y, _ = screen_coords(torch.tensor(0.5), torch.tensor(-1.0), torch.tensor(0.0), torch.tensor(1.0), 4, 8)
        >>> float(x), float(y)
        (6.0, 0.0)
    """
    inv_w = 1.0 / w
    return (x * inv_w + 1.0) * (0.5 * width), (y * inv_w + 1.0) * (0.5 * height), z * inv_w


def _edges(xs: Sequence[Tensor], ys: Sequence[Tensor], orient: Tensor) -> list[tuple[Tensor, Tensor, Tensor, Tensor]]:
    """Edge data ``(xm, ym, ex, ey)`` of the three edges of triangles with corner coordinates ``xs, ys``.

    Edge ``i`` is the one opposite corner ``i``, from ``a = i + 1`` to ``b = i + 2``. Its edge function at a pixel
    centre ``p`` is ``E = ex (py - ym) - ey (px - xm)`` with the base point at the edge's midpoint
    ``(xa + xb) / 2`` and the direction ``(xb - xa) * orient``. Both are symmetric in ``a, b`` up to an exact sign
    flip (IEEE addition commutes, ``xa - xb == -(xb - xa)``), so the two triangles sharing an edge evaluate it
    with bitwise equal operands and get exactly opposite values at every pixel centre: a centre is never missed
    by both (no cracks), and one on the (rounded) edge line is covered by both. ``orient`` (+-1, the sign of the
    screen-space area) makes ``E >= 0`` inside for either winding; ``E_i`` is twice the area of the
    sub-triangle opposite corner ``i``, so ``E_i / sum(E)`` are the screen-space barycentrics.
    """
    out = []
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        out.append(((xs[a] + xs[b]) * 0.5, (ys[a] + ys[b]) * 0.5, (xs[b] - xs[a]) * orient,
                    (ys[b] - ys[a]) * orient))
    return out


# Rows of the packed per-face data built by _setup (a list of 1-D tensors, one entry per face, sorted by bucket).
_PXM, _PYM, _PEX, _PEY = (0, 1, 2), (3, 4, 5), (6, 7, 8), (9, 10, 11)  # edge data of edges 0, 1, 2
_PBW, _PBH, _PZC, _PGX, _PGY, _PCMIN, _PRMIN, _PFID, _PFIRST = range(12, 21)


def _candidate_pass(pf: list[Tensor], sh: int, sw: int, oy: int, ox: int, height: int, width: int,
                    clip_depth: bool, zbuf: Tensor, peel: tuple[Tensor, Tensor] | None = None) -> None:
    """Test the ``sh x sw`` pixel grid at offset ``(oy, ox)`` of each face's bounding box; update ``zbuf``.

    ``pf`` holds the packed per-face rows (``_PXM`` ... ``_PFIRST``) of one chunk of a bucket. ``peel`` (depth
    peeling only) is ``(floor, faces)``: flat per-pixel keys of the previous layer (``_KEY_EMPTY`` where it has
    none) and the :math:`(F, 3)` faces; a candidate then counts only if its key is greater than the floor and it is
    not an *edge duplicate* of the floor's face (see :func:`depth_peel`).
    """
    dev, cdt = zbuf.device, pf[0].dtype
    edge_vals: list[Tensor] = []
    ar_h = torch.arange(oy, oy + sh, device=dev, dtype=cdt)
    ar_w = torch.arange(ox, ox + sw, device=dev, dtype=cdt)
    px = (pf[_PCMIN][:, None] + ar_w) + 0.5  # (n, sw) pixel-centre x
    py = (height - 0.5) - (pf[_PRMIN][:, None] + ar_h)  # (n, sh) pixel-centre y (up)
    inside = None
    for i in range(3):  # E_i = U_i[:, :, None] - V_i[:, None, :]
        u = pf[_PEX[i]][:, None] * (py - pf[_PYM[i]][:, None])  # (n, sh)
        v = pf[_PEY[i]][:, None] * (px - pf[_PXM[i]][:, None])  # (n, sw)
        if i == 0:  # grid pixels outside the bounding box (the grid is a power of two) fail edge 0
            if sh > 1:
                u.masked_fill_(ar_h >= pf[_PBH][:, None], float("-inf"))
            if sw > 1:
                v.masked_fill_(ar_w >= pf[_PBW][:, None], float("inf"))
        e = u[:, :, None] - v[:, None, :]  # (n, sh, sw)
        inside = e >= 0 if inside is None else inside.logical_and_(e >= 0)
        if peel is not None:
            edge_vals.append(e.view(-1))
    idx = inside.view(-1).nonzero().squeeze(1)
    if idx.numel() == 0:
        return
    # depth (screen-space linear NDC z) and flat pixel index on the grid, read at the inside candidates
    zrow = pf[_PZC][:, None] + pf[_PGY][:, None] * py
    z = (zrow[:, :, None] + (pf[_PGX][:, None] * px)[:, None, :]).view(-1).index_select(0, idx)
    prow = pf[_PFIRST][:, None] + torch.arange(oy * width, (oy + sh) * width, width, device=dev)
    pix = (prow[:, :, None] + torch.arange(ox, ox + sw, device=dev)).view(-1).index_select(0, idx)
    per_face = sh * sw
    f = idx >> (per_face.bit_length() - 1) if per_face & (per_face - 1) == 0 else idx // per_face
    key = ((z.double() + 1.0) * _DEPTH_SCALE).long().clamp_(0, _Q_CLIPPED - 1)  # rounding may step past +-1
    if clip_depth:  # per-pixel near/far clipping; such keys never count as covered
        key.masked_fill_((z < -1.0) | (z > 1.0), _Q_CLIPPED)
    fid = pf[_PFID].index_select(0, f)
    key = (key << 32) | fid
    if peel is not None:
        floor, faces = peel
        prev = floor.index_select(0, pix)
        keep = key > prev
        # edge duplicates: a pixel centre on an edge (or a vertex) is covered by the faces around it (inclusive
        # coverage); skip those that share that edge (vertex) with the previous layer's face. "On" edge i: within
        # _PEEL_TOL_EPS * eps * (H + W) pixels of its line, |E_i| <= tol (|ex_i| + |ey_i|), which covers the
        # exact zeros of shared edges and the rounding of the edge functions near a vertex.
        tol = _PEEL_TOL_EPS * torch.finfo(cdt).eps * (height + width)
        zero = []
        for i in range(3):
            ev = edge_vals[i].index_select(0, idx).abs()
            scale = pf[_PEX[i]].index_select(0, f).abs() + pf[_PEY[i]].index_select(0, f).abs()
            zero.append(ev <= tol * scale)
        vert = faces.index_select(0, fid)  # (K, 3)
        pvert = faces.index_select(0, (prev & _ID_MASK).clamp_(max=faces.shape[0] - 1))
        shared = [(vert[:, j:j + 1] == pvert).any(1) for j in range(3)]  # corner j is a vertex of the floor face
        dup = torch.zeros_like(keep)
        for i in range(3):
            a, b = (i + 1) % 3, (i + 2) % 3
            dup |= zero[i] & shared[a] & shared[b]  # on edge (a, b), shared with the floor's face
            dup |= zero[a] & zero[b] & shared[i]  # on corner i (edges a and b meet there), a vertex of the floor's
        keep &= ~dup
        keep &= prev < _KEY_LIMIT
        pix, key = pix[keep], key[keep]
    zbuf.scatter_reduce_(0, pix, key, reduce="amin")


@functools.lru_cache(maxsize=64)
def _log2_table(limit: int, device: torch.device) -> Tensor:
    """The table of :func:`_ceil_log2` on ``device``: built on the CPU (float64 everywhere) once per size."""
    lut = torch.zeros(limit + 1, dtype=torch.int64)
    lut[2:] = torch.ceil(torch.log2(torch.arange(2, limit + 1, dtype=torch.float64) - 0.5)).long()
    return lut.to(device)


def _ceil_log2(n: Tensor, limit: int) -> Tensor:
    """ceil(log2(n)) for int64 ``0 <= n <= limit`` (0 for n <= 1), through a lookup table (cached per device)."""
    return _log2_table(int(limit), n.device).index_select(0, n)


def _setup(clip: Tensor, faces: Tensor, height: int, width: int, cull_backfaces: bool, cdt: torch.dtype,
           pix0: int = 0) -> tuple[list[Tensor], list[tuple[int, int, int]], bool] | None:
    """Per-face data of the faces that can cover a pixel centre (flattened over the batch), sorted by bucket.

    Returns ``(pf, buckets, clip_depth)``: the packed rows (``_PXM`` ... ``_PFIRST``: edge data, bounding box,
    depth plane, face id within its batch element, flat index of the bounding box's first pixel), 1-D tensors
    with one entry per kept face; the buckets as ``(sh, sw, count)`` in that order; and whether any vertex lies
    outside the near/far range. ``None`` if no face can cover a pixel centre. ``pix0`` is the flat index of the
    first pixel of ``clip``'s first batch element.
    """
    bsz, nv = clip.shape[:2]
    nf = faces.shape[0]
    dev = clip.device
    c = clip.to(cdt)
    xv, yv, zv = screen_coords(c[..., 0], c[..., 1], c[..., 2], c[..., 3], height, width)  # (B, V)
    clip_depth = bool(((zv < -1.0) | (zv > 1.0)).any())  # conservative: any vertex outside near/far
    sv = torch.stack([xv, yv, zv, c[..., 3]]).view(4, bsz * nv)
    vidx = faces.view(-1)
    if bsz > 1:
        vidx = (torch.arange(bsz, device=dev)[:, None] * nv + vidx).view(-1)
    g = sv.index_select(1, vidx).view(4, bsz * nf, 3)  # per face (N = B F) and corner
    x0, x1, x2 = g[0].unbind(1)
    y0, y1, y2 = g[1].unbind(1)
    w0, w1, w2 = g[3].unbind(1)
    area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    cmin = torch.ceil(torch.minimum(torch.minimum(x0, x1), x2) - (0.5 + _BBOX_MARGIN)).clamp_(0, width)
    cmax = torch.floor(torch.maximum(torch.maximum(x0, x1), x2) - (0.5 - _BBOX_MARGIN)).clamp_(-1, width - 1)
    rmin = torch.ceil((height - 0.5 - _BBOX_MARGIN) - torch.maximum(torch.maximum(y0, y1), y2)).clamp_(0, height)
    rmax = torch.floor((height - 0.5 + _BBOX_MARGIN) - torch.minimum(torch.minimum(y0, y1), y2)).clamp_(-1, height - 1)
    bw = (cmax - cmin + 1.0).clamp_(min=0.0)  # NaN for faces with non-finite coordinates
    bh = (rmax - rmin + 1.0).clamp_(min=0.0)
    keep = (torch.minimum(torch.minimum(w0, w1), w2) > _W_EPS) & (bw > 0) & (bh > 0)
    keep &= (area2 > 0) if cull_backfaces else (area2 != 0)
    # bucket key: ceil(log2) of the bounding-box height and width; all ones marks dropped faces
    bits = 4 if max(height, width) <= 2**14 else 5
    skip = (1 << (2 * bits)) - 1
    kdt = torch.uint8 if bits == 4 else torch.int16
    lw = _ceil_log2(bw.nan_to_num(0.0).long().clamp_(0, width), width)
    lh = _ceil_log2(bh.nan_to_num(0.0).long().clamp_(0, height), height)
    key = ((lh << bits) | lw).to(kdt) | ((~keep).to(kdt) * skip)
    key_sorted, order = torch.sort(key, stable=True)
    ukeys, counts = torch.unique_consecutive(key_sorted, return_counts=True)
    buckets = [(1 << (k >> bits), 1 << (k & ((1 << bits) - 1)), n)
               for k, n in zip(ukeys.tolist(), counts.tolist()) if k != skip]
    nkeep = sum(b[2] for b in buckets)
    if nkeep == 0:
        return None
    order = order[:nkeep]
    # compact the kept faces in bucket order
    g = g.index_select(1, order)
    bw, bh, area2, cmin, rmin = torch.stack([bw, bh, area2, cmin, rmin]).index_select(1, order)
    xs, ys, zs = g[0].unbind(1), g[1].unbind(1), g[2].unbind(1)
    edges = _edges(xs, ys, torch.sign(area2))
    # depth plane z = zc + gx px + gy py (NDC z is linear in screen space)
    dx1, dx2 = xs[1] - xs[0], xs[2] - xs[0]
    dy1, dy2 = ys[1] - ys[0], ys[2] - ys[0]
    dz1, dz2 = zs[1] - zs[0], zs[2] - zs[0]
    inv_area = 1.0 / area2
    gx = (dz1 * dy2 - dz2 * dy1) * inv_area
    gy = (dx1 * dz2 - dx2 * dz1) * inv_area
    zc = zs[0] - gx * xs[0] - gy * ys[0]
    fid = order % nf if bsz > 1 else order
    if height * width <= 2**24:  # exact in float32
        first = (rmin * width + cmin).long()
    else:
        first = rmin.long() * width + cmin.long()
    if bsz > 1:
        first += (order // nf) * (height * width)
    if pix0:
        first += pix0
    pf = [edges[i][k] for k in range(4) for i in range(3)] + [bw, bh, zc, gx, gy, cmin, rmin, fid, first]
    return pf, buckets, clip_depth


def _zbuffer(clip: Tensor, faces: Tensor, height: int, width: int, cull_backfaces: bool, max_candidates: int,
             cdt: torch.dtype, floor: Tensor | None = None) -> Tensor:
    """Flat ``(B H W,)`` int64 keys (quantised depth << 32 | face id) of the nearest face, ``_KEY_EMPTY`` if none.

    With ``floor`` (flat keys of the previous depth-peeling layer, ``_KEY_EMPTY`` where it has none) only fragments
    behind it count (see :func:`depth_peel`).
    """
    peel = None if floor is None else (floor, faces)
    bsz = clip.shape[0]
    zbuf = torch.full((bsz * height * width,), _KEY_EMPTY, dtype=torch.int64, device=clip.device)
    if faces.shape[0] == 0:
        return zbuf
    # batch elements are set up in groups of about _SETUP_FACES faces: the per-face gathers stay in cache (a
    # batch of 4 bunnies set up at once took 1.7x the time of 4 calls), small meshes still batch many views
    group = max(1, _SETUP_FACES // faces.shape[0])
    for b0 in range(0, bsz, group):
        setup = _setup(clip[b0:b0 + group], faces, height, width, cull_backfaces, cdt, b0 * height * width)
        if setup is None:
            continue
        pf, buckets, clip_depth = setup
        start = 0
        for sh, sw, n in buckets:
            sh, sw = min(sh, height), min(sw, width)
            # tile the grid if one face alone exceeds the budget, then chunk the faces
            tw = min(sw, max_candidates)
            th = max(1, min(sh, max_candidates // tw))
            per_chunk = max(1, max_candidates // (th * tw))
            for s in range(start, start + n, per_chunk):
                e = min(s + per_chunk, start + n)
                for oy in range(0, sh, th):
                    for ox in range(0, sw, tw):
                        _candidate_pass([row[s:e] for row in pf], min(th, sh - oy), min(tw, sw - ox), oy, ox,
                                        height, width, clip_depth, zbuf, peel)
            start += n
    return zbuf


# -- public API -----------------------------------------------------------------------------------------------------
def rasterize(clip_pos: Tensor, faces: Tensor, resolution: tuple[int, int], *, cull_backfaces: bool = False,
              max_candidates: int = 2**22) -> Raster:
    """Rasterize triangles given in homogeneous clip space (one sample at each pixel centre, z-buffered).

    See the module docstring for the conventions (row 0 at the top, pixel centres at :math:`i + 0.5`, inclusive
    crack-free coverage, deterministic depth ties to the lower face id, clipping). The result does not depend on
    the order of the faces except through face ids, and is bitwise reproducible.

    Args:
        clip_pos: :math:`(V, 4)` or :math:`(B, V, 4)` clip-space vertex positions (e.g.
            ``transform_points(vertices, camera.view_proj())``), float32 or float64, finite.
        faces: :math:`(F, 3)` integer vertex indices into ``clip_pos``'s :math:`V` (shared by the batch).
        resolution: ``(H, W)``, positive ints.
        cull_backfaces: drop triangles that are clockwise on screen (counter-clockwise with NDC y up is front).
        max_candidates: the most (face, pixel) candidates tested at once; bounds the temporary memory (roughly
            50 bytes per candidate in float32) at the price of more passes.

    Returns:
        :class:`Raster` with ``face_id`` :math:`(B, 1, H, W)` int64, ``bary`` :math:`(B, 3, H, W)`,
        ``depth`` :math:`(B, 1, H, W)` (float tensors in ``clip_pos``'s dtype) and ``mask``
        :math:`(B, 1, H, W)` bool, on ``clip_pos``'s device. ``bary`` and ``depth`` are differentiable
        w.r.t. ``clip_pos`` (inside each face; there are no silhouette gradients). No faces, or only
        clipped ones, give an all-background raster.

    Raises:
        TypeError: a non-tensor or non-floating ``clip_pos``, non-integer ``faces``, a bad ``resolution`` type.
        ValueError: wrong shapes, non-finite ``clip_pos`` (NaN, inf), face indices out of range, sizes < 1.

    Examples:
        >>> clip = torch.tensor([[-1.0, -1.0, 0.0, 1.0], [3.0, -1.0, 0.0, 1.0], [-1.0, 3.0, 0.0, 1.0]])
        >>> r = rasterize(clip, torch.tensor([[0, 1, 2]]), (2, 3))  # one triangle covering the whole image
        >>> r.face_id[0, 0].tolist(), bool(r.mask.all()), r.bary.shape
        ([[0, 0, 0], [0, 0, 0]], True, torch.Size([1, 3, 2, 3]))
    """
    clip, faces, height, width, cdt, zbuf = _checked_zbuffer(clip_pos, faces, resolution, cull_backfaces,
                                                             max_candidates)
    return _raster_from_zbuf(clip, faces, zbuf, height, width, cdt)


def _checked_zbuffer(clip_pos: object, faces: object, resolution: object, cull_backfaces: bool,
                     max_candidates: object) -> tuple[Tensor, Tensor, int, int, torch.dtype, Tensor]:
    """The arguments of :func:`rasterize` checked, and the depth pass's keys: ``(clip, faces, H, W, cdt, zbuf)``."""
    clip = _check_clip(clip_pos)
    faces = _check_faces(faces, clip.shape[1]).to(clip.device)
    height, width = _check_resolution(resolution)
    max_candidates = _check_max_candidates(max_candidates)
    cdt = torch.float64 if clip.dtype == torch.float64 else torch.float32
    with torch.no_grad():
        zbuf = _zbuffer(clip.detach(), faces, height, width, cull_backfaces, max_candidates, cdt)
    return clip, faces, height, width, cdt, zbuf


def rasterize_depth(clip_pos: Tensor, faces: Tensor, resolution: tuple[int, int], *, cull_backfaces: bool = False,
                    max_candidates: int = 2**22) -> Tensor:
    """The nearest NDC depth at every pixel centre, read from the z-buffer itself (no barycentrics resolved).

    The depth pass of :func:`rasterize` alone, for depth maps (shadow maps): the same coverage, clipping and
    depth test, so a pixel is covered exactly where :func:`rasterize`'s ``mask`` is, by the same face. The depth
    is the winner's NDC :math:`z` as the depth test quantised it (31 bits over :math:`[-1, 1]`), returned at the
    centre of its quantisation step: within :math:`2^{-31}` of the exact value (:func:`rasterize`'s ``depth``
    differs from it by that plus the rounding of the coverage pass's plane equation). Not differentiable.

    Args:
        clip_pos: :math:`(V, 4)` or :math:`(B, V, 4)` clip-space vertex positions, float32 or float64, finite.
        faces: :math:`(F, 3)` integer vertex indices.
        resolution: ``(H, W)``.
        cull_backfaces: as :func:`rasterize`.
        max_candidates: as :func:`rasterize`.

    Returns:
        :math:`(B, 1, H, W)` NDC :math:`z` in ``clip_pos``'s dtype, ``+inf`` where no face covers the centre.

    Raises:
        TypeError, ValueError: as :func:`rasterize`.

    Examples:
        >>> clip = torch.tensor([[-1.0, -1.0, 0.5, 1.0], [3.0, -1.0, 0.5, 1.0], [-1.0, 3.0, 0.5, 1.0]])
        >>> rasterize_depth(clip, torch.tensor([[0, 1, 2]]), (2, 2))[0, 0].tolist()
        [[0.5, 0.5], [0.5, 0.5]]
    """
    clip, _, height, width, _, zbuf = _checked_zbuffer(clip_pos, faces, resolution, cull_backfaces, max_candidates)
    with torch.no_grad():
        covered = zbuf < _KEY_LIMIT
        ndc = ((zbuf >> 32).to(torch.float64) + 0.5) / _DEPTH_SCALE - 1.0
        depth = torch.where(covered, ndc, torch.full_like(ndc, math.inf)).to(clip.dtype)
    return depth.view(clip.shape[0], 1, height, width)


def depth_peel(clip_pos: Tensor, faces: Tensor, resolution: tuple[int, int], max_layers: int, *,
               cull_backfaces: bool = False, max_candidates: int = 2**22) -> list[Raster]:
    """Depth peeling: the first, second, ... surface at every pixel centre, one :class:`Raster` per layer.

    Layer 0 is exactly :func:`rasterize`'s output. Layer :math:`k` holds at each pixel the nearest fragment strictly
    behind layer :math:`k - 1`'s: with the z-buffer keys (depth quantised to 31 bits << 32 | face id) it is the
    minimum key *greater than* the previous layer's key at that pixel. That ordering is total, so peeling is exact
    and needs no depth bias: coplanar faces (equal quantised depth) come out one per layer in face-id order, and
    no fragment is returned twice or skipped. Pixels where layer :math:`k - 1` is empty stay empty.

    Edge duplicates: coverage is inclusive, so a pixel centre that lies exactly on an edge (edge function == 0 in
    the rasterizer's arithmetic) is covered by both faces of the edge, and one at (or within rounding of) a vertex
    by several of the faces around it, all at the same surface point. A fragment of layer :math:`k \\ge 1` is
    skipped when it lies on an edge it shares with layer :math:`k - 1`'s face, or at a vertex it shares with that
    face ("on": within :math:`16\\,\\epsilon\\,(H + W)` pixels of the edge's line, :math:`\\epsilon` the compute
    dtype's machine epsilon; about :math:`10^{-3}` pixels in float32 at 256 x 256), so that a surface point is
    peeled once. Two fragments that pass this test share a point of the mesh, so nothing distinct is lost. (It
    compares vertex indices: faces that share positions but not indices count as distinct surfaces.)

    Peeling stops after ``max_layers`` layers or at the first layer in which no pixel (of any batch element) is
    covered; that empty layer is not returned. A mesh that covers no pixel gives ``[]``.

    Args:
        clip_pos: :math:`(V, 4)` or :math:`(B, V, 4)` clip-space positions, as for :func:`rasterize`.
        faces: :math:`(F, 3)` integer vertex indices.
        resolution: ``(H, W)``.
        max_layers: the most layers to return (>= 1).
        cull_backfaces: as for :func:`rasterize` (peels the front faces only).
        max_candidates: as for :func:`rasterize`.

    Returns:
        A list of at most ``max_layers`` :class:`Raster`, nearest first; each is differentiable as
        :func:`rasterize`'s. A layer's ``mask`` is False where the pixel has fewer surfaces.

    Raises:
        TypeError: as :func:`rasterize`, a non-int ``max_layers``.
        ValueError: as :func:`rasterize`, ``max_layers < 1``.

    Examples:
        >>> quad = torch.tensor([[-1.0, -1.0], [3.0, -1.0], [-1.0, 3.0]])  # a triangle covering the whole image
        >>> clip = torch.cat([torch.cat([quad, torch.full((3, 1), z), torch.ones(3, 1)], 1) for z in (0.5, -0.5)])
        >>> layers = depth_peel(clip, torch.tensor([[0, 1, 2], [3, 4, 5]]), (2, 2), max_layers=8)
        >>> len(layers), layers[0].face_id[0, 0, 0, 0].item(), layers[1].face_id[0, 0, 0, 0].item()
        (2, 1, 0)
    """
    clip = _check_clip(clip_pos)
    faces = _check_faces(faces, clip.shape[1]).to(clip.device)
    height, width = _check_resolution(resolution)
    max_candidates = _check_max_candidates(max_candidates)
    if isinstance(max_layers, bool) or not isinstance(max_layers, numbers.Integral):
        raise TypeError(f"max_layers: expected an int >= 1, got {type(max_layers).__name__}")
    if max_layers < 1:
        raise ValueError(f"max_layers: expected an int >= 1, got {max_layers!r}")
    cdt = torch.float64 if clip.dtype == torch.float64 else torch.float32
    layers: list[Raster] = []
    floor = None
    for _ in range(int(max_layers)):
        with torch.no_grad():
            zbuf = _zbuffer(clip.detach(), faces, height, width, cull_backfaces, max_candidates, cdt, floor)
            visible = zbuf < _KEY_LIMIT
            if not bool(visible.any()):
                break
            floor = torch.where(visible, zbuf, torch.full_like(zbuf, _KEY_EMPTY))
        layers.append(_raster_from_zbuf(clip, faces, zbuf, height, width, cdt))
    return layers


def _raster_from_zbuf(clip: Tensor, faces: Tensor, zbuf: Tensor, height: int, width: int,
                      cdt: torch.dtype) -> Raster:
    """The :class:`Raster` of the winning keys ``zbuf`` (flat, ``(B H W,)``)."""
    bsz, dev, dtype = clip.shape[0], clip.device, clip.dtype
    npix = height * width
    with torch.no_grad():
        pix = (zbuf < _KEY_LIMIT).nonzero().squeeze(1)
        fid = zbuf.index_select(0, pix) & _ID_MASK
        face_id = torch.full((bsz * npix,), -1, dtype=torch.int64, device=dev).index_put_((pix,), fid)
    bary_px, depth_px, b, hw = _resolve(clip, faces, pix, fid, height, width, cdt)
    # write (3, K) into the (B, 3, H W) layout through one flat index
    flat = (torch.arange(0, 3 * npix, npix, device=dev)[:, None] + (b * (3 * npix) + hw)).view(-1)
    bary = torch.zeros(bsz * 3 * npix, dtype=dtype, device=dev).index_put_((flat,), bary_px.to(dtype).view(-1))
    depth = torch.full((bsz * npix,), float("inf"), dtype=dtype, device=dev).index_put_((pix,), depth_px.to(dtype))
    return Raster(
        face_id=face_id.view(bsz, 1, height, width),
        bary=bary.view(bsz, 3, height, width),
        depth=depth.view(bsz, 1, height, width),
        mask=(face_id >= 0).view(bsz, 1, height, width),
    )


def _resolve(clip: Tensor, faces: Tensor, pix: Tensor, fid: Tensor, height: int, width: int,
             cdt: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Perspective-correct barycentrics ``(3, K)`` and NDC depth ``(K,)`` of face ``fid`` at flat pixel ``pix``.

    Also returns the batch index and the flat in-image pixel index of each entry. Differentiable w.r.t. ``clip``.
    """
    bsz, nv = clip.shape[:2]
    npix = height * width
    if bsz > 1:
        b = pix // npix
        hw = pix - b * npix
    else:
        b, hw = torch.zeros_like(pix), pix
    r = hw // width
    c = hw - r * width
    vidx = faces.index_select(0, fid)  # (K, 3)
    if bsz > 1:
        vidx = vidx + (b * nv)[:, None]
    tri = clip.reshape(bsz * nv, 4).index_select(0, vidx.view(-1)).to(cdt).view(-1, 3, 4).permute(2, 1, 0)
    xs, ys, zs = screen_coords(tri[0], tri[1], tri[2], tri[3], height, width)  # (3, K)
    area2 = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (xs[2] - xs[0]) * (ys[1] - ys[0])
    px = c.to(cdt) + 0.5
    py = (height - 0.5) - r.to(cdt)
    # the coverage pass's edge functions, bitwise: >= 0 at covered centres
    e = torch.stack([ex * (py - y0) - ey * (px - x0)
                     for x0, y0, ex, ey in _edges(xs.unbind(0), ys.unbind(0), torch.sign(area2.detach()))])
    e = e.clamp(min=0)
    total = e.sum(0)
    bs = torch.where(total > 0, e / total.clamp(min=torch.finfo(cdt).tiny), 1.0 / 3.0)
    depth = (bs * zs).sum(0)
    pw = bs / tri[3]
    return pw / pw.sum(0), depth, b, hw


def interpolate(attributes: Tensor, raster: Raster, faces: Tensor) -> Tensor:
    """Interpolate per-vertex attributes at every pixel with the raster's perspective-correct barycentrics.

    Args:
        attributes: :math:`(V, C)` (shared by the batch) or :math:`(B, V, C)` floating per-vertex values.
        raster: the :class:`Raster` from :func:`rasterize` (or :func:`rasterize_uv`) of the same ``faces``.
        faces: :math:`(F, 3)` integer vertex indices, as passed to :func:`rasterize`.

    Returns:
        :math:`(B, C, H, W)`, zeros on background; differentiable w.r.t. ``attributes`` (a gather and a weighted
        sum) and w.r.t. ``raster.bary``. The dtype is the promotion of ``attributes`` and ``raster.bary``.

    Raises:
        TypeError: a non-floating ``attributes`` or non-integer ``faces``.
        ValueError: shapes that do not match (vertex count, batch size).

    Examples:
        >>> clip = torch.tensor([[-1.0, -1.0, 0.0, 1.0], [3.0, -1.0, 0.0, 1.0], [-1.0, 3.0, 0.0, 1.0]])
        >>> faces = torch.tensor([[0, 1, 2]])
        >>> uv = interpolate(clip[:, :2], rasterize(clip, faces, (2, 2)), faces)  # NDC x, y at pixel centres
        >>> uv[0, :, 0, 0].tolist()
        [-0.5, 0.5]
    """
    if not isinstance(attributes, Tensor) or not attributes.is_floating_point():
        got = attributes.dtype if isinstance(attributes, Tensor) else type(attributes).__name__
        raise TypeError(f"attributes: expected a floating-point tensor, got {got}")
    if attributes.dim() not in (2, 3):
        raise ValueError(f"attributes: expected shape (V, C) or (B, V, C), got {tuple(attributes.shape)}")
    if not isinstance(raster, Raster):
        raise TypeError(f"raster: expected a Raster, got {type(raster).__name__}")
    bsz, _, height, width = raster.bary.shape
    faces = _check_faces(faces, attributes.shape[-2])
    if attributes.dim() == 3 and attributes.shape[0] not in (1, bsz):
        raise ValueError(f"attributes: expected batch size 1 or {bsz} (the raster's), got {tuple(attributes.shape)}")
    attr = attributes if attributes.dim() == 3 else attributes.unsqueeze(0)
    nv, nch = attr.shape[1:]
    dev = attr.device
    dtype = torch.promote_types(attr.dtype, raster.bary.dtype)
    npix = height * width
    fid_flat = raster.face_id.reshape(-1).to(dev)
    pix = (fid_flat >= 0).nonzero().squeeze(1)
    fid = fid_flat.index_select(0, pix)
    if not is_tracing() and fid.numel() and int(fid.max()) >= faces.shape[0]:
        raise ValueError(f"faces: expected at least {int(fid.max()) + 1} faces (the raster's face ids), "
                         f"got {faces.shape[0]}")
    if bsz > 1:
        b = pix // npix
        hw = pix - b * npix
    else:
        b, hw = torch.zeros_like(pix), pix
    vidx = faces.to(dev).index_select(0, fid)  # (K, 3)
    if attr.shape[0] > 1:
        vidx = vidx + (b * nv)[:, None]
    vals = attr.reshape(-1, nch).index_select(0, vidx.view(-1)).view(-1, 3, nch).to(dtype)  # (K, 3, C)
    wflat = torch.arange(0, 3 * npix, npix, device=dev)[:, None] + (b * (3 * npix) + hw)
    w = raster.bary.reshape(-1).to(dev).index_select(0, wflat.view(-1)).view(3, -1).to(dtype)  # (3, K)
    out_px = torch.einsum("kjc,jk->ck", vals, w)  # (C, K)
    # write (C, K) into the (B, C, H W) layout through one flat index
    flat = (torch.arange(0, nch * npix, npix, device=dev)[:, None] + (b * (nch * npix) + hw)).view(-1)
    out = torch.zeros(bsz * nch * npix, dtype=dtype, device=dev).index_put_((flat,), out_px.reshape(-1))
    return out.view(bsz, nch, height, width)


def rasterize_uv(face_uvs: Tensor, resolution: tuple[int, int], **kw) -> Raster:
    """Rasterize triangles in texture space: which face covers each texel centre of an atlas.

    Texel (row :math:`r`, column :math:`c`) of an :math:`H \\times W` atlas has its centre at
    :math:`(u, v) = ((c + 0.5) / W, 1 - (r + 0.5) / H)` (:math:`v` up, row 0 at the top). The triangles go
    through :func:`rasterize` with clip coordinates :math:`(2u - 1, 2v - 1, 0, 1)` per corner (so the same
    coverage rules apply; overlapping UV triangles resolve to the lower face id, all at depth 0).

    Args:
        face_uvs: :math:`(F, 3, 2)` (or :math:`(B, F, 3, 2)`) UV coordinates of each face's corners, in
            :math:`[0, 1]`.
        resolution: ``(H, W)`` of the atlas.
        **kw: ``cull_backfaces`` and ``max_candidates`` of :func:`rasterize`.

    Returns:
        :class:`Raster` whose ``face_id`` are indices into ``face_uvs``'s :math:`F`; ``bary`` weights the face's
        corners 0, 1, 2 (affine in texture space, as :math:`w = 1`). Interpolate per-corner attributes
        :math:`(F, 3, C)` with ``interpolate(attr.reshape(-1, C), raster, torch.arange(3 * F).view(F, 3))``.

    Raises:
        TypeError: a non-floating ``face_uvs``.
        ValueError: a shape other than :math:`(F, 3, 2)` / :math:`(B, F, 3, 2)`, non-finite values.

    Examples:
        >>> uv = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])  # lower-left half of the atlas
        >>> rasterize_uv(uv, (2, 2)).face_id[0, 0].tolist()
        [[0, -1], [0, 0]]
    """
    if not isinstance(face_uvs, Tensor) or not face_uvs.is_floating_point():
        got = face_uvs.dtype if isinstance(face_uvs, Tensor) else type(face_uvs).__name__
        raise TypeError(f"face_uvs: expected a floating-point tensor, got {got}")
    if face_uvs.dim() not in (3, 4) or face_uvs.shape[-2:] != (3, 2):
        raise ValueError(f"face_uvs: expected shape (F, 3, 2) or (B, F, 3, 2), got {tuple(face_uvs.shape)}")
    uv = face_uvs if face_uvs.dim() == 4 else face_uvs.unsqueeze(0)
    bsz, nf = uv.shape[:2]
    flat = uv.reshape(bsz, nf * 3, 2)
    clip = torch.cat([flat * 2.0 - 1.0, torch.zeros_like(flat[..., :1]), torch.ones_like(flat[..., :1])], dim=-1)
    faces = torch.arange(3 * nf, device=uv.device).view(nf, 3)
    try:
        return rasterize(clip, faces, resolution, **kw)
    except ValueError as err:
        if str(err).startswith("clip_pos"):
            raise ValueError("face_uvs" + str(err)[len("clip_pos"):]) from err
        raise
