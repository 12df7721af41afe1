"""Graded refinement of a mesh towards its creases and open boundaries (the receivers' side of vertex hats).

A function carried by vertex hats (Lensch's vertex radiosity, interpolated barycentrically) can follow a variation
only as fine as the hats. Beside a crease lit on its other side - a slab's rim in the light, the face beside it in
view - the radiosity falls within a few tenths of a millimetre of the edge and then over a few millimetres, while
the hats are one edge length wide; beside an open boundary or an unlit crease it rises from half its plane value
over the same lengths. :func:`refine_creases` inserts rows of vertices along such *feature* edges at graded
distances, :math:`g_k = g_0 q^k` up to a reach, so that the hats there shrink with their distance from the edge and
the mesh elsewhere is left alone. The rows are level sets of the distance to the feature edges, cut into every face
they cross (a face's band between two levels is convex and fanned into triangles), so the result is conforming:
every new vertex on an edge is shared by both faces of that edge. Edges that run between two feature vertices but
are not features themselves (across a slab's rim) are bisected first, so that the distance is not zero on both ends.

The refined surface is the original one (every new vertex is a fixed combination of the original vertices, gathered
differentiably), its faces keep their winding, and ``face_uvs`` are interpolated. All lengths are millimetres.
"""

from __future__ import annotations

import itertools
import math
import numbers
from dataclasses import replace

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from torchsss.geometry.mesh import CREASE_DEG, Mesh, check_mesh

__all__ = ["feature_edges", "refine_creases"]

#: the grading ratio of the rows' distances, :math:`g_{k+1} / g_k`
REFINE_RATIO = 1.6
#: the rows reach this many times the median length of the edges at the feature vertices
REFINE_REACH = 3.0


def _edges(faces: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges: ``(lo, hi)`` per edge, and each face corner's edge id (corner k: k -> k + 1)."""
    a, b = faces, np.roll(faces, -1, axis=1)
    lo, hi = np.minimum(a, b).reshape(-1), np.maximum(a, b).reshape(-1)
    uniq, inverse = np.unique(lo.astype(np.int64) * n + hi, return_inverse=True)
    return uniq // n, uniq % n, inverse.reshape(-1, 3)


def _feature_mask(faces: np.ndarray, normals: np.ndarray, corner_edge: np.ndarray, num_edges: int,
                  cos_crease: float) -> np.ndarray:
    """Per unique edge: True where it is an open boundary, non-manifold, or a crease (normals turn > crease)."""
    count = np.bincount(corner_edge.reshape(-1), minlength=num_edges)
    feature = count != 2
    flat = corner_edge.reshape(-1)
    order = np.argsort(flat, kind="stable")
    two = np.flatnonzero(count == 2)
    start = np.searchsorted(flat[order], two)
    fa, fb = order[start] // 3, order[start + 1] // 3
    feature[two] = (normals[fa] * normals[fb]).sum(-1) < cos_crease
    return feature


def _check_crease(crease_deg: object) -> float:
    if isinstance(crease_deg, bool) or not isinstance(crease_deg, numbers.Real):
        raise TypeError(f"crease_deg: expected an angle in degrees, got {type(crease_deg).__name__}")
    c = float(crease_deg)
    if not (0.0 < c <= 180.0):
        raise ValueError(f"crease_deg: expected an angle in (0, 180] degrees, got {crease_deg!r}")
    return c


def _check_length(x: object, name: str, *, allow_none: bool = False) -> float | None:
    if x is None and allow_none:
        return None
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        kind = "a positive length in mm or None" if allow_none else "a positive length in mm"
        raise TypeError(f"{name}: expected {kind}, got {type(x).__name__}")
    v = float(x)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name}: expected a positive finite length in mm, got {x!r}")
    return v


def feature_edges(mesh: Mesh, crease_deg: float = CREASE_DEG) -> Tensor:
    """The mesh's feature edges: open boundaries, non-manifold edges and creases.

    An edge is a crease where its two faces' normals turn by more than ``crease_deg`` (the rule of
    :meth:`~torchsss.geometry.mesh.Mesh.corner_normals` and :func:`~torchsss.geometry.mesh.split_creases`).

    Args:
        mesh: the mesh (mm).
        crease_deg: dihedral angle in degrees, in (0, 180].

    Returns:
        :math:`(E, 2)` int64 vertex indices of the feature edges (``lo < hi``), on the mesh's device.

    Raises:
        TypeError: ``mesh`` not a :class:`~torchsss.geometry.mesh.Mesh`, or a non-numeric ``crease_deg``.
        ValueError: ``crease_deg`` outside (0, 180].

    Examples:
        >>> from torchsss.geometry.procedural import slab, sphere
        >>> feature_edges(slab(10.0, 10.0, 1.0, segments=2)).shape[0]  # 8 rim lines of 2 edges, 4 corner edges
        20
        >>> feature_edges(sphere(5.0, subdivisions=2)).shape[0]
        0
    """
    mesh = check_mesh(mesh)
    crease = _check_crease(crease_deg)
    faces = mesh.faces.detach().cpu().numpy()
    if faces.shape[0] == 0:
        return torch.zeros(0, 2, dtype=torch.int64, device=mesh.device)
    lo, hi, corner_edge = _edges(faces, mesh.num_vertices)
    normals = mesh.face_normals.detach().to(torch.float64).cpu().numpy()
    feature = _feature_mask(faces, normals, corner_edge, lo.size, math.cos(math.radians(crease)))
    return torch.from_numpy(np.stack([lo[feature], hi[feature]], 1)).to(mesh.device)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances from points ``p`` (N, 3) to segments ``a``-``b`` (N, 3) each."""
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=-1)


def _distance_to_features(points: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray, reach: float) -> np.ndarray:
    """Distance from each point to the nearest segment, exact up to ``reach`` (``inf`` beyond it)."""
    out = np.full(points.shape[0], np.inf)
    if seg_a.shape[0] == 0 or points.shape[0] == 0:
        return out
    length = np.linalg.norm(seg_b - seg_a, axis=-1)
    step = max(reach / 4.0, 1e-9)
    # probes along every segment at most ``step`` apart: a point within ``reach`` of a segment lies within
    # ``reach + step / 2`` of one of its probes
    pieces = np.maximum(1, np.ceil(length / step).astype(np.int64))
    seg = np.repeat(np.arange(seg_a.shape[0]), pieces + 1)
    offset = np.arange(seg.size) - np.repeat(np.cumsum(pieces + 1) - (pieces + 1), pieces + 1)
    t = offset / pieces[seg]
    probes = seg_a[seg] + t[:, None] * (seg_b[seg] - seg_a[seg])
    tree = cKDTree(probes)
    hits = tree.query_ball_point(points, reach + 0.5 * step + 1e-12)
    counts = np.fromiter((len(h) for h in hits), dtype=np.int64, count=len(hits))
    if counts.sum() == 0:
        return out
    pt = np.repeat(np.arange(points.shape[0]), counts)
    sg = seg[np.fromiter((j for h in hits for j in h), dtype=np.int64, count=int(counts.sum()))]
    d = _segment_distance(points[pt], seg_a[sg], seg_b[sg])
    np.minimum.at(out, pt, d)
    out[out > reach] = np.inf
    return out


class _Combos:
    """Vertices as fixed combinations of the original vertices: ``(rows, cols, weights)`` in COO form."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.terms: list[dict[int, float]] = []

    def add(self, parts: list[tuple[int, float]]) -> int:
        acc: dict[int, float] = {}
        for v, w in parts:
            if w == 0.0:
                continue
            if v < self.n:
                acc[v] = acc.get(v, 0.0) + w
            else:
                for c, cw in self.terms[v - self.n].items():
                    acc[c] = acc.get(c, 0.0) + w * cw
        self.terms.append(acc)
        return self.n + len(self.terms) - 1

    def weights(self, v: int) -> dict[int, float]:
        return {v: 1.0} if v < self.n else self.terms[v - self.n]


def _bisect_bridges(faces: np.ndarray, lo: np.ndarray, hi: np.ndarray, corner_edge: np.ndarray,
                    feature: np.ndarray, is_feature_vertex: np.ndarray, combos: _Combos,
                    parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bisect every non-feature edge between two feature vertices; the faces split 1-to-2, 1-to-3 or 1-to-4."""
    bridge = ~feature & is_feature_vertex[lo] & is_feature_vertex[hi]
    if not bridge.any():
        return faces, parent
    mid = np.full(lo.size, -1, dtype=np.int64)
    for e in np.flatnonzero(bridge):
        mid[e] = combos.add([(int(lo[e]), 0.5), (int(hi[e]), 0.5)])
    out, out_parent = [], []
    for f in range(faces.shape[0]):
        a = faces[f]
        m = mid[corner_edge[f]]  # the midpoint of edge k (corner k -> k + 1), or -1
        k = np.flatnonzero(m >= 0)
        if k.size == 0:
            tris = [a]
        elif k.size == 1:
            i = int(k[0])
            tris = [[a[i], m[i], a[(i + 2) % 3]], [m[i], a[(i + 1) % 3], a[(i + 2) % 3]]]
        elif k.size == 2:
            i = int(({0, 1, 2} - set(k.tolist())).pop())  # the unsplit edge i -> i + 1; the others split
            j, q = (i + 1) % 3, (i + 2) % 3
            tris = [[a[i], a[j], m[j]], [a[i], m[j], m[q]], [m[j], a[q], m[q]]]
        else:
            tris = [[a[0], m[0], m[2]], [m[0], a[1], m[1]], [m[2], m[1], a[2]], [m[0], m[1], m[2]]]
        out += [list(map(int, t)) for t in tris]
        out_parent += [parent[f]] * len(tris)
    return np.asarray(out, dtype=np.int64), np.asarray(out_parent, dtype=np.int64)


def _slice(faces: np.ndarray, d: np.ndarray, levels: np.ndarray, combos: _Combos,
           parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cut every face along the level sets ``d = levels`` (``d`` linear on the faces); bands fanned into triangles."""
    crossing: dict[tuple[int, int, int], int] = {}

    def cross(u: int, v: int, k: int) -> int:
        a, b = (u, v) if u < v else (v, u)
        key = (a, b, k)
        if key not in crossing:
            t = (levels[k] - d[a]) / (d[b] - d[a])
            crossing[key] = combos.add([(a, 1.0 - t), (b, t)])
        return crossing[key]

    out, out_parent = [], []
    for f in range(faces.shape[0]):
        tri = [int(x) for x in faces[f]]
        dv = [d[x] for x in tri]
        lo_d, hi_d = min(dv), max(dv)
        inside = np.flatnonzero((levels > lo_d) & (levels < hi_d))
        if inside.size == 0 or not math.isfinite(lo_d):
            out.append(tri)
            out_parent.append(parent[f])
            continue
        if not math.isfinite(hi_d):  # not met: the distances are exact one edge beyond the reach
            raise RuntimeError("refine_creases: a face straddles the distance field's range")
        cuts = [lo_d] + [float(levels[k]) for k in inside] + [hi_d]  # bands between levels (convex)
        kof = {float(levels[k]): int(k) for k in inside}
        for l0, l1 in itertools.pairwise(cuts):
            poly: list[int] = []
            for i in range(3):
                p, q = tri[i], tri[(i + 1) % 3]
                dp, dq = dv[i], dv[(i + 1) % 3]
                if l0 <= dp <= l1:
                    poly.append(p)
                ends = [lv for lv in (l0, l1) if lv in kof and min(dp, dq) < lv < max(dp, dq)]
                ends.sort(key=lambda lv: (lv - dp) / (dq - dp))
                poly += [cross(p, q, kof[lv]) for lv in ends]
            for j in range(1, len(poly) - 1):
                out.append([poly[0], poly[j], poly[j + 1]])
                out_parent.append(parent[f])
    return np.asarray(out, dtype=np.int64), np.asarray(out_parent, dtype=np.int64)


def _median_at_features(pos: np.ndarray, lo: np.ndarray, hi: np.ndarray, is_fv: np.ndarray) -> float:
    at = is_fv[lo] | is_fv[hi]
    return float(np.median(np.linalg.norm(pos[lo[at]] - pos[hi[at]], axis=-1)))


def _median_feature_edge(mesh: Mesh, crease_deg: float = CREASE_DEG) -> float:
    """The median length of the edges at the feature vertices (mm; 0 without features): the reach's unit."""
    faces = mesh.faces.detach().cpu().numpy().astype(np.int64)
    pos = mesh.vertices.detach().to(torch.float64).cpu().numpy()
    lo, hi, corner_edge = _edges(faces, mesh.num_vertices)
    normals = mesh.face_normals.detach().to(torch.float64).cpu().numpy()
    feature = _feature_mask(faces, normals, corner_edge, lo.size, math.cos(math.radians(crease_deg)))
    if not feature.any():
        return 0.0
    is_fv = np.zeros(mesh.num_vertices, dtype=bool)
    is_fv[lo[feature]] = True
    is_fv[hi[feature]] = True
    return _median_at_features(pos, lo, hi, is_fv)


def refine_creases(mesh: Mesh, first_mm: float, *, ratio: float = REFINE_RATIO, reach_mm: float | None = None,
                   crease_deg: float = CREASE_DEG) -> tuple[Mesh, Tensor]:
    """The mesh with rows of vertices along its feature edges at graded distances (see the module docstring).

    Rows lie at the distances :math:`g_k = g_0 q^k < r` from the nearest feature edge (an open boundary or a crease,
    :func:`feature_edges`), :math:`g_0` = ``first_mm``, :math:`q` = ``ratio``, :math:`r` = ``reach_mm``, measured in
    3-D to the edge segments and taken linear on each face. The faces beyond the reach, and every face of a mesh
    without features, are kept as they are.

    Args:
        mesh: the mesh (mm).
        first_mm: the first row's distance from the feature edges (mm), > 0.
        ratio: the grading ratio q > 1 (default 1.6).
        reach_mm: the rows' reach (mm); default 3 median lengths of the edges at the feature vertices. Rows at
            ``first_mm`` or beyond the reach are not made (nothing changes when ``first_mm >= reach_mm``).
        crease_deg: dihedral angle in degrees above which an edge is a crease, in (0, 180].

    Returns:
        ``(refined, parent)``: the refined mesh (``mesh`` itself where nothing changes) and :math:`(F',)` int64, the
        original face of each new face. The new vertices are fixed combinations of the original ones (gradients flow
        to ``mesh.vertices``); ``face_uvs`` are interpolated.

    Raises:
        TypeError: a wrong argument type.
        ValueError: non-positive lengths, ``ratio <= 1`` or ``crease_deg`` outside (0, 180].

    Examples:
        >>> from torchsss.geometry.procedural import slab
        >>> m = slab(10.0, 10.0, 1.0, segments=2)
        >>> r, parent = refine_creases(m, 0.1, reach_mm=1.0)
        >>> r.num_vertices > m.num_vertices, abs(r.area - m.area) < 1e-5 * m.area, r.is_watertight
        (True, True, True)
        >>> bool((parent.bincount(minlength=m.num_faces) >= 1).all())
        True
    """
    mesh = check_mesh(mesh)
    first = _check_length(first_mm, "first_mm")
    reach = _check_length(reach_mm, "reach_mm", allow_none=True)
    if isinstance(ratio, bool) or not isinstance(ratio, numbers.Real):
        raise TypeError(f"ratio: expected a number > 1, got {type(ratio).__name__}")
    q = float(ratio)
    if not (math.isfinite(q) and q > 1.0):
        raise ValueError(f"ratio: expected a finite number > 1, got {ratio!r}")
    crease = _check_crease(crease_deg)
    device = mesh.device
    same = (mesh, torch.arange(mesh.num_faces, device=device))
    faces = mesh.faces.detach().cpu().numpy().astype(np.int64)
    n = mesh.num_vertices
    if faces.shape[0] == 0:
        return same
    pos = mesh.vertices.detach().to(torch.float64).cpu().numpy()
    lo, hi, corner_edge = _edges(faces, n)
    normals = mesh.face_normals.detach().to(torch.float64).cpu().numpy()
    feature = _feature_mask(faces, normals, corner_edge, lo.size, math.cos(math.radians(crease)))
    if not feature.any():
        return same
    is_fv = np.zeros(n, dtype=bool)
    is_fv[lo[feature]] = True
    is_fv[hi[feature]] = True
    if reach is None:
        reach = REFINE_REACH * _median_at_features(pos, lo, hi, is_fv)
    levels = first * q ** np.arange(max(0, math.ceil(math.log(reach / first) / math.log(q))) + 1)
    levels = levels[levels < reach]
    if levels.size == 0:
        return same
    combos = _Combos(n)
    parent = np.arange(faces.shape[0], dtype=np.int64)
    faces, parent = _bisect_bridges(faces, lo, hi, corner_edge, feature, is_fv, combos, parent)

    def positions() -> np.ndarray:
        extra = np.zeros((len(combos.terms), 3))
        for i, t in enumerate(combos.terms):
            for c, w in t.items():
                extra[i] += w * pos[c]
        return np.concatenate([pos, extra])

    points = positions()
    seg_a, seg_b = pos[lo[feature]], pos[hi[feature]]
    # exact one edge beyond the reach, so that every face with a vertex within it has finite distances
    near = np.isfinite(_distance_to_features(points, seg_a, seg_b, reach))
    e_lo, e_hi = faces.reshape(-1), np.roll(faces, -1, axis=1).reshape(-1)
    touch = near[e_lo] | near[e_hi]
    longest = float(np.linalg.norm(points[e_lo[touch]] - points[e_hi[touch]], axis=-1).max()) if touch.any() else 0.0
    d = _distance_to_features(points, seg_a, seg_b, reach + longest)
    d[:n][is_fv] = 0.0
    faces, parent = _slice(faces, d, levels, combos, parent)
    if len(combos.terms) == 0:
        return same
    # the new vertices gathered from the originals (differentiable), in the mesh's dtype
    rows = np.concatenate([np.arange(n)] + [np.full(len(t), n + i) for i, t in enumerate(combos.terms)])
    cols = np.concatenate([np.arange(n)] + [np.fromiter(t.keys(), dtype=np.int64, count=len(t))
                                            for t in combos.terms])
    wts = np.concatenate([np.ones(n)] + [np.fromiter(t.values(), dtype=np.float64, count=len(t))
                                         for t in combos.terms])
    total = n + len(combos.terms)
    v = mesh.vertices
    r_t, c_t = torch.from_numpy(rows).to(device), torch.from_numpy(cols).to(device)
    w_t = torch.from_numpy(wts).to(device=device, dtype=v.dtype)
    vertices = torch.zeros(total, 3, dtype=v.dtype, device=device).index_add(0, r_t, v[c_t] * w_t[:, None])
    face_uvs = None
    if mesh.face_uvs is not None:
        # every corner's barycentrics in its parent face, from its combination of the parent's vertices
        par = faces.shape[0]
        bary = np.zeros((par, 3, 3))
        orig = mesh.faces.detach().cpu().numpy()
        for f in range(par):
            pf = orig[parent[f]]
            for k in range(3):
                for c, w in combos.weights(int(faces[f, k])).items():
                    bary[f, k, int(np.flatnonzero(pf == c)[0])] += w
        b_t = torch.from_numpy(bary).to(device=device, dtype=mesh.face_uvs.dtype)
        face_uvs = torch.einsum("fkj,fjc->fkc", b_t, mesh.face_uvs[torch.from_numpy(parent).to(device)])
    refined = replace(mesh, vertices=vertices, faces=torch.from_numpy(faces).to(device), face_uvs=face_uvs)
    return refined, torch.from_numpy(parent).to(device)
