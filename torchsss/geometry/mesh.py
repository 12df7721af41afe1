"""Triangle meshes in millimetres: validation and clean-up, size normalisation, decimation (files: ``loading``).

A :class:`Mesh` holds vertex positions in millimetres, int64 triangle indices wound counter-clockwise seen
from outside (so that ``cross(v1 - v0, v2 - v0)`` points outward) and optional per-corner texture
coordinates. Meshes are immutable: every operation returns a new mesh. Files are read (in ``loading``) with ``trimesh``
(OBJ, PLY, STL, GLB/GLTF, OFF, ...); scenes with several geometries are concatenated into one mesh.

Clean-up (:func:`mesh_from_arrays`, used by :func:`~torchsss.geometry.loading.load_mesh`) welds duplicated
positions, drops degenerate faces and unreferenced vertices and warns (:class:`MeshWarning`) about open meshes:
the subsurface-scattering methods assume a closed surface, so light that should stay inside leaks out through holes.
"""

from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from torch import Tensor

from torchsss._checks import check_shape

__all__ = [
    "Mesh",
    "MeshWarning",
    "check_mesh",
    "decimate",
    "mesh_from_arrays",
    "normalize_to_size",
    "split_creases",
    "surface_deviation",
]

_WELD_REL_TOL = 1e-8  # weld tolerance, relative to the bounding-box diagonal
_DEGENERATE_REL_AREA = 1e-12  # faces with area <= this x diagonal^2 are dropped
_NORMAL_EPS = 1e-12
CREASE_DEG = 60.0  # dihedral angle (degrees) above which :meth:`Mesh.corner_normals` splits the shading normal


class MeshWarning(UserWarning):
    """A mesh was accepted but is not ideal for subsurface scattering (open surface, dropped faces)."""


# --------------------------------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------------------------------


def _check_positive_number(x: object, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise TypeError(f"{name}: expected a positive finite number, got {type(x).__name__}")
    value = float(x)
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name}: expected a positive finite number, got {x!r}")
    return value


def _check_int(x: object, name: str, minimum: int, maximum: int | None = None) -> int:
    expected = f"an integer >= {minimum}" if maximum is None else f"an integer in [{minimum}, {maximum}]"
    if isinstance(x, bool) or not isinstance(x, numbers.Integral):
        raise TypeError(f"{name}: expected {expected}, got {type(x).__name__}")
    value = int(x)
    if value < minimum or (maximum is not None and value > maximum):
        raise ValueError(f"{name}: expected {expected}, got {value}")
    return value


def _check_float_dtype(dtype: object, name: str = "dtype") -> torch.dtype:
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"{name}: expected a floating torch.dtype (e.g. torch.float32), got {dtype!r}")
    return dtype


def _as_tensor(x: object, name: str, kind: str) -> Tensor:
    """Convert a tensor or numpy array to a tensor; ``kind`` is "real" or "int"."""
    if isinstance(x, np.ndarray):
        if x.dtype.kind not in "iuf":
            raise TypeError(f"{name}: expected a numeric array, got dtype {x.dtype}")
        x = np.ascontiguousarray(x)
        x = torch.from_numpy(x if x.flags.writeable else x.copy())  # from_numpy warns on read-only arrays
    elif not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor or numpy.ndarray, got {type(x).__name__}")
    if x.dtype == torch.bool or x.is_complex():
        raise TypeError(f"{name}: expected a real-valued tensor, got dtype {x.dtype}")
    if kind == "int" and x.is_floating_point():
        raise TypeError(f"{name}: expected an integer tensor of vertex indices, got dtype {x.dtype}")
    return x


# --------------------------------------------------------------------------------------------------------------
# numpy helpers (clean-up runs on CPU in float64; results gather from the original tensor)
# --------------------------------------------------------------------------------------------------------------


def _weld(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Group points closer than ``tol`` (grid quantisation): ``(first index of each group, inverse map)``."""
    origin = points.min(axis=0)
    key = np.round((points - origin) / tol).astype(np.int64)
    order = np.lexsort(key.T[::-1])
    sorted_key = key[order]
    new_group = np.ones(len(order), dtype=bool)
    new_group[1:] = np.any(sorted_key[1:] != sorted_key[:-1], axis=1)
    group_of_sorted = np.cumsum(new_group) - 1
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = group_of_sorted
    first = np.full(int(group_of_sorted[-1]) + 1, len(order), dtype=np.int64)
    np.minimum.at(first, inverse, np.arange(len(order), dtype=np.int64))
    return first, inverse


def _diagonal(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def _edge_counts(faces: np.ndarray) -> tuple[int, int]:
    """Number of boundary edges (one face) and non-manifold edges (more than two faces)."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts == 1).sum()), int((counts > 2).sum())


def _watertight(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Trimesh's watertightness (every edge shared by exactly two faces) after welding equal positions."""
    diag = _diagonal(vertices)
    _, inverse = _weld(vertices, max(_WELD_REL_TOL * diag, np.finfo(np.float64).tiny))
    welded = inverse[faces]
    edges = welded[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    watertight, _ = trimesh.graph.is_watertight(edges=edges, edges_sorted=np.sort(edges, axis=1))
    return bool(watertight)


def _warn_open(mesh: Mesh, stacklevel: int) -> None:
    if mesh.is_watertight:
        return
    boundary, nonmanifold = _edge_counts(mesh.faces.detach().cpu().numpy())
    label = f"{mesh.name!r}: " if mesh.name else ""
    warnings.warn(
        f"{label}mesh is not watertight: {boundary} boundary edges, {nonmanifold} non-manifold edges; translucency "
        "through holes and open boundaries is not modelled (subsurface light leaks out where the surface is "
        "open). Pass warn_open=False to silence this warning.",
        MeshWarning,
        stacklevel=stacklevel + 1,
    )


# --------------------------------------------------------------------------------------------------------------
# Mesh
# --------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Mesh:
    """An immutable triangle mesh in millimetres.

    Build meshes with :func:`~torchsss.geometry.loading.load_mesh`, :func:`mesh_from_arrays` (which validate and
    clean up) or the procedural shapes of :mod:`torchsss.geometry.procedural`. The constructor itself only checks
    types and shapes. Derived quantities (normals, areas, bounds) are computed on first use and cached, except when the
    vertices require grad (then they are recomputed so that gradients flow to the current graph). Do not modify
    the tensors in place.

    Attributes:
        vertices: Vertex positions in mm, :math:`(V, 3)`, floating.
        faces: Vertex indices, :math:`(F, 3)`, int64, on the vertices' device, counter-clockwise seen from outside
            (outward normals).
        face_uvs: Per-corner texture coordinates, :math:`(F, 3, 2)`, same dtype as the vertices, ``u`` right and
            ``v`` up, nominally in :math:`[0, 1]` (values outside wrap), or ``None``.
        mm_per_unit: Scale applied to the source file's units to get millimetres.
        name: Free-form name (file stem or built-in name).

    Examples:
        >>> import torch
        >>> v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> f = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> m = Mesh(v, f, name="tetra")
        >>> m.num_vertices, m.num_faces, m.is_watertight
        (4, 4, True)
        >>> round(m.area, 4), tuple(m.face_normals.shape)
        (2.366, (4, 3))
        >>> m.face_normals[0].tolist()
        [0.0, 0.0, -1.0]
    """

    vertices: Tensor
    faces: Tensor
    face_uvs: Tensor | None = None
    mm_per_unit: float = 1.0
    name: str = ""

    def __post_init__(self) -> None:
        v = self.vertices
        if not isinstance(v, Tensor):
            raise TypeError(f"vertices: expected a torch.Tensor, got {type(v).__name__}")
        if not v.is_floating_point():
            raise TypeError(f"vertices: expected a floating-point tensor, got dtype {v.dtype}")
        check_shape(v, "vertices", "V,3")
        f = self.faces
        if not isinstance(f, Tensor):
            raise TypeError(f"faces: expected a torch.Tensor, got {type(f).__name__}")
        if f.is_floating_point() or f.is_complex() or f.dtype == torch.bool:
            raise TypeError(f"faces: expected an int64 tensor, got dtype {f.dtype}")
        check_shape(f, "faces", "F,3")
        if f.device != v.device:
            raise ValueError(f"faces: expected a tensor on the vertices' device {v.device}, got {f.device}")
        if f.dtype != torch.int64:
            object.__setattr__(self, "faces", f.long())
        uv = self.face_uvs
        if uv is not None:
            if not isinstance(uv, Tensor):
                raise TypeError(f"face_uvs: expected a torch.Tensor or None, got {type(uv).__name__}")
            if not uv.is_floating_point():
                raise TypeError(f"face_uvs: expected a floating-point tensor, got dtype {uv.dtype}")
            check_shape(uv, "face_uvs", "F,3,2", F=f.shape[0])
            if uv.device != v.device:
                raise ValueError(f"face_uvs: expected a tensor on the vertices' device {v.device}, got {uv.device}")
            if uv.dtype != v.dtype:
                object.__setattr__(self, "face_uvs", uv.to(v.dtype))
        object.__setattr__(self, "mm_per_unit", _check_positive_number(self.mm_per_unit, "mm_per_unit"))
        if not isinstance(self.name, str):
            raise TypeError(f"name: expected a str, got {type(self.name).__name__}")
        object.__setattr__(self, "_cache", {})

    def __repr__(self) -> str:
        return (
            f"Mesh(name={self.name!r}, num_vertices={self.num_vertices}, num_faces={self.num_faces}, "
            f"uvs={self.face_uvs is not None}, mm_per_unit={self.mm_per_unit:g}, dtype={self.vertices.dtype}, "
            f"device={self.vertices.device})"
        )

    def _cached(self, key: str, compute: Any) -> Any:
        if self.vertices.requires_grad:
            return compute()
        cache = self._cache  # type: ignore[attr-defined]
        if key not in cache:
            cache[key] = compute()
        return cache[key]

    # ---- sizes -------------------------------------------------------------------------------------------------

    @property
    def num_vertices(self) -> int:
        """Number of vertices :math:`V`."""
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        """Number of triangles :math:`F`."""
        return int(self.faces.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the vertices (and face_uvs)."""
        return self.vertices.dtype

    @property
    def device(self) -> torch.device:
        """Device of the vertices, faces and face_uvs."""
        return self.vertices.device

    # ---- derived geometry --------------------------------------------------------------------------------------

    def triangles(self) -> Tensor:
        """Corner positions of every face, :math:`(F, 3, 3)` in mm (corner, xyz).

        Examples:
            >>> from torchsss.geometry.procedural import sphere
            >>> tuple(sphere(subdivisions=1).triangles().shape)
            (80, 3, 3)
        """
        return self.vertices[self.faces]

    def _cross(self) -> Tensor:
        def compute() -> Tensor:
            tri = self.triangles()
            return torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)

        return self._cached("cross", compute)

    @property
    def face_normals(self) -> Tensor:
        """Unit outward face normals, :math:`(F, 3)` (zero for degenerate faces)."""
        return self._cached("face_normals", lambda: F.normalize(self._cross(), dim=-1, eps=_NORMAL_EPS))

    @property
    def face_areas(self) -> Tensor:
        """Face areas in mm², :math:`(F,)`."""
        return self._cached("face_areas", lambda: 0.5 * torch.linalg.vector_norm(self._cross(), dim=-1))

    @property
    def vertex_normals(self) -> Tensor:
        """Unit vertex normals, :math:`(V, 3)`: area-weighted average of the adjacent face normals."""

        def compute() -> Tensor:
            cross = self._cross()  # length = twice the area: the sum is area-weighted
            acc = torch.zeros_like(self.vertices)
            acc = acc.index_add(0, self.faces.reshape(-1), cross.repeat_interleave(3, dim=0))
            return F.normalize(acc, dim=-1, eps=_NORMAL_EPS)

        return self._cached("vertex_normals", compute)

    @property
    def vertex_normals_max(self) -> Tensor:
        """Unit vertex normals, :math:`(V, 3)`, with Max's weights for curved surfaces.

        N. Max, "Weights for computing vertex normals from facet normals" (JGT 1999): each corner adds :math:`(e_1
        \\times e_2) / (|e_1|^2 |e_2|^2)` of its two edges. Exact when a vertex's one-ring lies on a sphere (any
        tessellation), and closer to a smooth surface's normal than the area weights of :attr:`vertex_normals` elsewhere
        (an ellipsoid of 5120 faces: worst angle 1.8e-3 against 7.9e-3 rad). Refraction differentiates the normal field
        (a caustic's focus amplifies its errors), so the caustics pipeline interpolates these
        (:func:`~torchsss.geometry.gbuffer.layer_gbuffer`'s ``normals``); shading keeps the area weights, which a sliver
        with tiny edges cannot dominate. A vertex whose corners are all degenerate (or whose weights cancel) keeps its
        area-weighted normal.

        Examples:
            >>> from torchsss.geometry.procedural import sphere
            >>> m = sphere(10.0, 2, dtype=torch.float64)
            >>> exact = m.vertices / m.vertices.norm(dim=-1, keepdim=True)
            >>> float((m.vertex_normals_max - exact).abs().max()) < 1e-12
            True
        """

        def compute() -> Tensor:
            v, f = self.vertices, self.faces
            acc = torch.zeros_like(v)
            for k in range(3):
                e1 = v[f[:, (k + 1) % 3]] - v[f[:, k]]
                e2 = v[f[:, (k + 2) % 3]] - v[f[:, k]]
                den = (e1 * e1).sum(-1, keepdim=True) * (e2 * e2).sum(-1, keepdim=True)
                w = torch.linalg.cross(e1, e2) / den.clamp_min(torch.finfo(v.dtype).tiny)
                acc = acc.index_add(0, f[:, k], torch.where(den > 0, w, torch.zeros_like(w)))
            norm = torch.linalg.vector_norm(acc, dim=-1, keepdim=True)
            ok = torch.isfinite(norm) & (norm > 0)
            unit = acc / torch.where(ok, norm, torch.ones_like(norm))
            return torch.where(ok, unit, self.vertex_normals)

        return self._cached("vertex_normals_max", compute)

    def corner_normals(self, crease_deg: float = CREASE_DEG) -> Tensor:
        """Unit shading normals per face corner, :math:`(F, 3, 3)`: smooth across soft edges, split at creases.

        A corner's normal is the area-weighted average of the faces around its vertex whose normals lie within
        ``crease_deg`` of its own face's (three.js's ``toCreasedNormals`` rule). Where no two faces around a vertex
        differ by more than ``crease_deg`` this is :attr:`vertex_normals` (on a scan, almost every vertex); at a box's
        right-angled edge each side keeps its own flat normal instead of one smoothed over the edge at 45°, which
        tilts the irradiance of every pixel on the bevel it fakes (a 40 mm slab lit from the front: splat 5.2% off
        with the smoothed normals, 0.3% with face normals). Shading (G-buffers, surface samples, atlas texels)
        interpolates these.

        Args:
            crease_deg: dihedral angle in degrees above which an edge is a crease, in (0, 180].

        Returns:
            :math:`(F, 3, 3)` unit normals (face, corner, xyz), differentiable w.r.t. the vertices.

        Raises:
            TypeError: a non-numeric ``crease_deg``.
            ValueError: ``crease_deg`` outside (0, 180].

        Examples:
            >>> from torchsss.geometry.procedural import slab
            >>> m = slab(10.0, 10.0, 2.0, segments=2, dtype=torch.float64)
            >>> bool(torch.allclose(m.corner_normals(), m.face_normals[:, None].expand(-1, 3, -1)))  # all flat
            True
            >>> bool(torch.allclose(m.corner_normals(180.0), m.vertex_normals[m.faces]))  # no crease: smooth
            True
        """
        crease = _check_positive_number(crease_deg, "crease_deg")
        if crease > 180.0:
            raise ValueError(f"crease_deg: expected an angle in (0, 180] degrees, got {crease_deg!r}")
        return self._cached(f"corner_normals_{crease!r}", lambda: self._corner_normals(math.cos(math.radians(crease))))

    def _corner_normals(self, cos_crease: float) -> Tensor:
        faces, cross, fn = self.faces, self._cross(), self.face_normals
        smooth = self.vertex_normals[faces]  # (F, 3, 3)
        if faces.shape[0] == 0:
            return smooth
        corner_vertex = faces.reshape(-1)
        # A vertex needs splitting only if two of its faces differ by more than the crease; all faces within half the
        # crease of the vertex normal is a sufficient test that none do, so only the others are paired exactly.
        cos_half = math.cos(0.5 * math.acos(max(-1.0, min(1.0, cos_crease))))
        dev = (fn.detach()[:, None, :] * smooth.detach()).sum(-1).reshape(-1)  # (3F,)
        suspect = torch.zeros(self.num_vertices, dtype=torch.bool, device=faces.device)
        suspect[corner_vertex[dev < cos_half]] = True
        corners = torch.nonzero(suspect[corner_vertex]).squeeze(1)
        if corners.numel() == 0:
            return smooth
        order = torch.argsort(corner_vertex[corners], stable=True)
        corners = corners[order]
        _, counts = torch.unique_consecutive(corner_vertex[corners], return_counts=True)
        starts = torch.cumsum(counts, 0) - counts
        degree = counts.repeat_interleave(counts)  # per sorted corner: how many corners share its vertex
        first = starts.repeat_interleave(counts)
        total = int(degree.sum())
        offset = torch.arange(total, device=faces.device) - (torch.cumsum(degree, 0) - degree).repeat_interleave(degree)
        a = corners.repeat_interleave(degree)  # every ordered pair of corners around one vertex
        b = corners[first.repeat_interleave(degree) + offset]
        fa, fb = a // 3, b // 3
        keep = (fn.detach()[fa] * fn.detach()[fb]).sum(-1) >= cos_crease
        acc = torch.zeros(corner_vertex.shape[0], 3, dtype=cross.dtype, device=cross.device)
        acc = acc.index_add(0, a[keep], cross[fb[keep]])[corners]
        flat = smooth.reshape(-1, 3)
        split = torch.where(acc.detach().abs().amax(-1, keepdim=True) > 0, F.normalize(acc, dim=-1, eps=_NORMAL_EPS),
                            flat[corners])
        return flat.index_copy(0, corners, split).reshape(smooth.shape)

    @property
    def vertex_areas(self) -> Tensor:
        """Area per vertex in mm², :math:`(V,)`: a third of the adjacent faces' areas (sums to :attr:`area`)."""

        def compute() -> Tensor:
            third = self.face_areas / 3.0
            acc = torch.zeros(self.num_vertices, dtype=third.dtype, device=third.device)
            return acc.index_add(0, self.faces.reshape(-1), third.repeat_interleave(3))

        return self._cached("vertex_areas", compute)

    @property
    def bounds(self) -> Tensor:
        """Bounding box in mm, :math:`(2, 3)`: minimum corner, maximum corner."""
        return self._cached("bounds", lambda: torch.stack([self.vertices.amin(0), self.vertices.amax(0)]))

    @property
    def size_mm(self) -> float:
        """Bounding-box diagonal in mm."""
        b = self.bounds.detach()
        return float(torch.linalg.vector_norm(b[1] - b[0]))

    @property
    def area(self) -> float:
        """Total surface area in mm²."""
        return float(self.face_areas.detach().sum())

    @property
    def is_watertight(self) -> bool:
        """True when every edge is shared by exactly two faces after welding equal positions (trimesh's notion)."""
        cache = self._cache  # type: ignore[attr-defined]
        if "is_watertight" not in cache:
            cache["is_watertight"] = _watertight(
                self.vertices.detach().cpu().double().numpy(), self.faces.detach().cpu().numpy()
            )
        return cache["is_watertight"]

    # ---- conversions -------------------------------------------------------------------------------------------

    def with_dtype(self, dtype: torch.dtype) -> Mesh:
        """The same mesh with vertices and face_uvs cast to a floating ``dtype`` (faces stay int64).

        Args:
            dtype: Floating dtype, e.g. ``torch.float64``.

        Returns:
            A new mesh (``self`` if the dtype is already right).

        Raises:
            TypeError: ``dtype`` is not a floating torch dtype.

        Examples:
            >>> import torch
            >>> from torchsss.geometry.procedural import sphere
            >>> sphere(subdivisions=1).with_dtype(torch.float64).vertices.dtype
            torch.float64
        """
        dtype = _check_float_dtype(dtype)
        if dtype == self.vertices.dtype:
            return self
        uv = None if self.face_uvs is None else self.face_uvs.to(dtype)
        return replace(self, vertices=self.vertices.to(dtype), face_uvs=uv)

    def with_device(self, device: torch.device | str) -> Mesh:
        """The same mesh with every tensor on ``device``.

        Examples:
            >>> from torchsss.geometry.procedural import sphere
            >>> sphere(subdivisions=1).with_device("cpu").faces.device
            device(type='cpu')
        """
        device = torch.device(device)
        uv = None if self.face_uvs is None else self.face_uvs.to(device)
        return replace(self, vertices=self.vertices.to(device), faces=self.faces.to(device), face_uvs=uv)

    def to_trimesh(self) -> trimesh.Trimesh:
        """Geometry as a ``trimesh.Trimesh`` (float64, ``process=False``, same vertex order; UVs not included).

        Examples:
            >>> from torchsss.geometry.procedural import sphere
            >>> tm = sphere(subdivisions=2).to_trimesh()
            >>> tm.faces.shape, tm.is_watertight
            ((320, 3), True)
        """
        return trimesh.Trimesh(
            vertices=self.vertices.detach().cpu().double().numpy(),
            faces=self.faces.detach().cpu().numpy(),
            process=False,
        )


# --------------------------------------------------------------------------------------------------------------
# construction and clean-up
# --------------------------------------------------------------------------------------------------------------


def _build(
    vertices: object,
    faces: object,
    face_uvs: object,
    *,
    dtype: torch.dtype | None,
    merge: bool,
    name: str,
    mm_per_unit: float = 1.0,
    warn_dropped: bool = True,
    stacklevel: int = 3,
) -> Mesh:
    """Validate and clean up arrays; see :func:`mesh_from_arrays`."""
    v = _as_tensor(vertices, "vertices", "real")
    check_shape(v, "vertices", "V,3")
    f = _as_tensor(faces, "faces", "int")
    check_shape(f, "faces", "F,3")
    if v.shape[0] == 0:
        raise ValueError("vertices: expected at least one vertex, got 0 (empty mesh)")
    if f.shape[0] == 0:
        raise ValueError("faces: expected at least one face, got 0 (mesh has no faces)")
    if dtype is None:
        dtype = v.dtype if (isinstance(vertices, Tensor) and v.is_floating_point()) else torch.get_default_dtype()
    dtype = _check_float_dtype(dtype)
    device = v.device
    uv = None
    if face_uvs is not None:
        uv = _as_tensor(face_uvs, "face_uvs", "real")
        check_shape(uv, "face_uvs", "F,3,2", F=f.shape[0])
        uv = uv.to(device=device, dtype=dtype)
        bad = ~torch.isfinite(uv)
        if bool(bad.any()):
            raise ValueError(
                f"face_uvs: expected finite values, got {uv[bad][0].item()!r} ({int(bad.sum())} of {uv.numel()} bad)"
            )

    v64 = v.detach().cpu().to(torch.float64).numpy()
    bad = ~np.isfinite(v64)
    if bad.any():
        raise ValueError(
            f"vertices: expected finite values, got {v64[bad][0]!r} ({int(bad.sum())} of {v64.size} entries bad)"
        )
    f64 = f.detach().cpu().to(torch.int64).numpy()
    n_vertices = v64.shape[0]
    out_of_range = (f64 < 0) | (f64 >= n_vertices)
    if out_of_range.any():
        raise ValueError(
            f"faces: expected vertex indices in [0, {n_vertices}), got {int(f64[out_of_range][0])} "
            f"({int(out_of_range.sum())} of {f64.size} indices out of range)"
        )

    used = np.unique(f64)
    diag = _diagonal(v64[used])
    source = np.arange(n_vertices, dtype=np.int64)  # output vertex -> input vertex
    if merge:
        first, inverse = _weld(v64[used], max(_WELD_REL_TOL * diag, np.finfo(np.float64).tiny))
        remap = np.zeros(n_vertices, dtype=np.int64)
        remap[used] = inverse
        f64 = remap[f64]
        source = used[first]

    # degenerate faces: repeated indices or (almost) zero area
    p = v64[source]
    tri = p[f64]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    repeated = (f64[:, 0] == f64[:, 1]) | (f64[:, 1] == f64[:, 2]) | (f64[:, 2] == f64[:, 0])
    degenerate = repeated | (areas <= _DEGENERATE_REL_AREA * diag**2)
    n_bad = int(degenerate.sum())
    if n_bad == len(f64):
        raise ValueError(f"faces: expected at least one non-degenerate face, got {n_bad} degenerate faces")
    if n_bad:
        f64 = f64[~degenerate]
        if uv is not None:
            uv = uv[torch.from_numpy(~degenerate).to(device)]
        if warn_dropped:
            label = f"{name!r}: " if name else ""
            warnings.warn(
                f"{label}dropped {n_bad} degenerate faces (zero area or repeated vertex indices)",
                MeshWarning,
                stacklevel=stacklevel,
            )

    # unreferenced vertices
    kept, f64 = np.unique(f64, return_inverse=True)
    f64 = f64.reshape(-1, 3)
    source = source[kept]

    index = torch.from_numpy(source).to(device)
    out_v = v.to(dtype)[index]
    out_f = torch.from_numpy(np.ascontiguousarray(f64, dtype=np.int64)).to(device)
    return Mesh(out_v, out_f, uv, mm_per_unit=mm_per_unit, name=name)


def check_mesh(mesh: object, name: str = "mesh") -> Mesh:
    """Return ``mesh`` if it is a :class:`Mesh` with at least one face, else raise TypeError / ValueError."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{name}: expected a torchsss.geometry.Mesh, got {type(mesh).__name__}")
    if mesh.num_faces == 0:
        raise ValueError(f"{name}: expected at least one face, got 0")
    return mesh


def mesh_from_arrays(
    vertices: Tensor | np.ndarray,
    faces: Tensor | np.ndarray,
    *,
    face_uvs: Tensor | np.ndarray | None = None,
    size_mm: float | None = None,
    name: str = "",
    dtype: torch.dtype | None = None,
    merge: bool = True,
    warn_open: bool = True,
) -> Mesh:
    """Build a clean :class:`Mesh` from vertex and face arrays.

    Clean-up, in order: positions closer than :math:`10^{-8}` times the bounding-box diagonal are welded (by
    position only; ``face_uvs`` are per corner, so welding never loses texture coordinates); faces with repeated
    indices or an area :math:`\\le 10^{-12}\\,d^2` (:math:`d` the bounding-box diagonal) are dropped with one
    :class:`MeshWarning`; unreferenced vertices are removed (so every vertex has a face). The result keeps the
    input's winding (counter-clockwise seen from outside is expected) and its device; gradients flow from the
    output vertices to the input tensor (the clean-up only gathers rows).

    Args:
        vertices: Positions, :math:`(V, 3)`, tensor or numpy array (mm, or source units if ``size_mm`` is given).
        faces: Vertex indices, :math:`(F, 3)`, integer tensor or array, all in :math:`[0, V)`.
        face_uvs: Optional per-corner texture coordinates, :math:`(F, 3, 2)`, finite.
        size_mm: If given, centre the mesh on its bounding-box centre and scale it so that the bounding-box
            diagonal is ``size_mm`` mm (see :func:`normalize_to_size`); ``mm_per_unit`` records the scale.
        name: Name stored on the mesh.
        dtype: Floating dtype of the result. ``None`` keeps a floating tensor's dtype and uses the default dtype
            (float32) for numpy arrays and integer inputs.
        merge: Weld duplicated positions (turn it off to keep the vertex layout, e.g. for per-vertex data).
        warn_open: Warn (:class:`MeshWarning`) when the result is not watertight.

    Returns:
        The cleaned mesh, faces int64 on the vertices' device.

    Raises:
        TypeError: An argument is not a tensor/array, has a non-numeric dtype, or faces are not integers.
        ValueError: Wrong shapes, no vertices ("empty mesh"), no faces ("mesh has no faces"), non-finite values,
            indices out of range, nothing left after dropping degenerate faces, or a bad ``size_mm``.

    Examples:
        >>> import torch
        >>> v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> f = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> soup = v[f].reshape(-1, 3)  # 12 unshared corners
        >>> m = mesh_from_arrays(soup, torch.arange(12).reshape(4, 3), size_mm=10.0)
        >>> m.num_vertices, m.num_faces, round(m.size_mm, 4), round(m.mm_per_unit, 4)
        (4, 4, 10.0, 5.7735)
    """
    if not isinstance(merge, bool):
        raise TypeError(f"merge: expected a bool, got {type(merge).__name__}")
    if not isinstance(name, str):
        raise TypeError(f"name: expected a str, got {type(name).__name__}")
    if size_mm is not None:
        size_mm = _check_positive_number(size_mm, "size_mm")
    mesh = _build(vertices, faces, face_uvs, dtype=dtype, merge=merge, name=name)
    if size_mm is not None:
        mesh = normalize_to_size(mesh, size_mm)
    if warn_open:
        _warn_open(mesh, stacklevel=2)
    return mesh


def normalize_to_size(mesh: Mesh, size_mm: float) -> Mesh:
    """Centre a mesh on its bounding-box centre and scale it uniformly to a bounding-box diagonal of ``size_mm``.

    Args:
        mesh: The mesh.
        size_mm: Target bounding-box diagonal in mm, positive and finite.

    Returns:
        A new mesh; ``mm_per_unit`` is multiplied by the scale factor. UVs and faces are unchanged.

    Raises:
        TypeError: ``mesh`` is not a :class:`Mesh` or ``size_mm`` not a number.
        ValueError: ``size_mm`` is not positive and finite, or the mesh has a zero-size bounding box.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> m = normalize_to_size(sphere(radius_mm=1.0, subdivisions=1), 30.0)
        >>> round(m.size_mm, 4), round(m.mm_per_unit, 4), m.bounds.mean(0).abs().max().item() < 1e-6
        (30.0, 8.6603, True)
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh: expected a Mesh, got {type(mesh).__name__}")
    size_mm = _check_positive_number(size_mm, "size_mm")
    v = mesh.vertices
    # compute the bounding box in float64 so that float32 meshes hit the target size to ~1e-7
    v64 = v.detach().to(torch.float64)
    lo, hi = v64.amin(0), v64.amax(0)
    diag = float(torch.linalg.vector_norm(hi - lo))
    if not diag > 0:
        raise ValueError(f"mesh: expected a mesh with a non-zero bounding box, got diagonal {diag}")
    scale = size_mm / diag
    centre = (0.5 * (lo + hi)).to(v.dtype)
    return replace(mesh, vertices=(v - centre) * scale, mm_per_unit=mesh.mm_per_unit * scale)


def decimate(mesh: Mesh, target_faces: int) -> Mesh:
    """Reduce a mesh to about ``target_faces`` triangles by quadric edge collapse.

    Uses ``trimesh.Trimesh.simplify_quadric_decimation`` (the ``fast_simplification`` package). The result is
    cleaned up like :func:`mesh_from_arrays` (silently: collapsed faces are expected) and keeps the name, dtype,
    device and ``mm_per_unit``. **Texture coordinates are dropped** (``face_uvs`` is ``None``): the decimator
    does not carry them.

    Args:
        mesh: The mesh.
        target_faces: Wanted number of faces, an integer >= 4. The decimator lands close to it, not exactly.

    Returns:
        The decimated mesh, or ``mesh`` itself when it already has at most ``target_faces`` faces.

    Raises:
        TypeError: ``mesh`` is not a :class:`Mesh` or ``target_faces`` is not an integer.
        ValueError: ``target_faces`` < 4.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> m = decimate(sphere(subdivisions=3), 320)
        >>> 280 <= m.num_faces <= 340, m.face_uvs is None
        (True, True)
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh: expected a Mesh, got {type(mesh).__name__}")
    target_faces = _check_int(target_faces, "target_faces", 4)
    if target_faces >= mesh.num_faces:
        return mesh
    simple = mesh.to_trimesh().simplify_quadric_decimation(face_count=target_faces)
    vertices = torch.from_numpy(np.asarray(simple.vertices, dtype=np.float64)).to(mesh.device)
    faces = torch.from_numpy(np.asarray(simple.faces, dtype=np.int64)).to(mesh.device)
    return _build(
        vertices,
        faces,
        None,
        dtype=mesh.dtype,
        merge=True,
        name=mesh.name,
        mm_per_unit=mesh.mm_per_unit,
        warn_dropped=False,
    )


def split_creases(mesh: Mesh, crease_deg: float = CREASE_DEG) -> tuple[Mesh, Tensor]:
    """The mesh with every vertex split into one copy per smooth fan of its faces, parted at creases.

    Around each vertex, two faces that share an edge through it stay on one copy unless the edge is a crease (its
    faces' normals turn by more than ``crease_deg``, the rule of :meth:`Mesh.corner_normals`) or is not shared by
    exactly two faces. A box's corner becomes three copies, a vertex on its edge two, a vertex of a scan with no
    crease one. The faces keep their order (each corner points at its copy), so anything indexed by face (an atlas,
    ``face_uvs``) still fits; the copies sit at their original's position (gathered, differentiable). Hat functions
    on the result do not reach across a crease: a function carried by them may jump there (the light that enters a
    slab's rim stays on the rim's hats).

    Args:
        mesh: The mesh.
        crease_deg: Dihedral angle in degrees above which an edge parts the fans, in (0, 180].

    Returns:
        ``(split, origin)``: the split mesh (``mesh`` itself where nothing is split) and :math:`(V',)` int64, the
        original vertex of every copy.

    Raises:
        TypeError: ``mesh`` not a :class:`Mesh`, or a non-numeric ``crease_deg``.
        ValueError: ``crease_deg`` outside (0, 180].

    Examples:
        >>> from torchsss.geometry.procedural import slab
        >>> m = slab(10.0, 10.0, 1.0, segments=2)
        >>> split, origin = split_creases(m)
        >>> m.num_vertices, split.num_vertices, split.num_faces == m.num_faces  # corners 8 x 3, rim points 8 x 2, 2
        (18, 42, True)
        >>> bool((split.vertices == m.vertices[origin]).all())
        True
    """
    mesh = check_mesh(mesh)
    crease = _check_positive_number(crease_deg, "crease_deg")
    if crease > 180.0:
        raise ValueError(f"crease_deg: expected an angle in (0, 180] degrees, got {crease_deg!r}")
    faces = mesh.faces.detach().cpu().numpy()
    nf = faces.shape[0]
    if nf == 0:
        return mesh, torch.arange(mesh.num_vertices, device=mesh.device)
    normal = mesh.face_normals.detach().to(torch.float64).cpu().numpy()
    # every edge as (face, corner k): the edge from corner k to corner k + 1
    a, b = faces, np.roll(faces, -1, axis=1)
    lo, hi = np.minimum(a, b).reshape(-1), np.maximum(a, b).reshape(-1)
    key = lo * mesh.num_vertices + hi
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.r_[True, ks[1:] != ks[:-1]]
    count = np.diff(np.r_[np.flatnonzero(start), ks.size])
    first = order[np.flatnonzero(start)[count == 2]]  # edges shared by exactly two faces
    second = order[np.flatnonzero(start)[count == 2] + 1]
    fa, ka = first // 3, first % 3
    fb, kb = second // 3, second % 3
    smooth = (normal[fa] * normal[fb]).sum(-1) >= math.cos(math.radians(crease))
    fa, ka, fb, kb = fa[smooth], ka[smooth], fb[smooth], kb[smooth]
    # join the corners of the shared edge's two ends across the two faces (a corner is face * 3 + k)
    va = faces[fa, ka]
    kb_same = np.where(faces[fb, kb] == va, kb, (kb + 1) % 3)  # fb's corner at va
    ends_a = np.stack([fa * 3 + ka, fa * 3 + (ka + 1) % 3])
    ends_b = np.stack([fb * 3 + kb_same, fb * 3 + np.where(kb_same == kb, (kb + 1) % 3, kb)])
    n = 3 * nf
    graph = coo_matrix((np.ones(ends_a.size), (ends_a.reshape(-1), ends_b.reshape(-1))), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    corner_vertex = faces.reshape(-1)
    # one copy per (vertex, fan); the copies of an unsplit vertex keep its index, the others follow
    pair = corner_vertex.astype(np.int64) * n + label
    uniq, inverse = np.unique(pair, return_inverse=True)
    if uniq.size == mesh.num_vertices:
        return mesh, torch.arange(mesh.num_vertices, device=mesh.device)
    owner = uniq // n
    is_first = np.r_[True, owner[1:] != owner[:-1]]
    new_id = np.where(is_first, owner, 0)
    extra = np.flatnonzero(~is_first)
    new_id[extra] = mesh.num_vertices + np.arange(extra.size)
    origin = np.empty(mesh.num_vertices + extra.size, dtype=np.int64)
    origin[new_id] = owner
    device = mesh.device
    origin_t = torch.from_numpy(origin).to(device)
    split_faces = torch.from_numpy(new_id[inverse].reshape(nf, 3)).to(device)
    return replace(mesh, vertices=mesh.vertices[origin_t], faces=split_faces), origin_t


#: The fine mesh's vertices :func:`surface_deviation` measures at most (a seeded sample beyond).
_DEVIATION_SAMPLES = 8192


def surface_deviation(mesh: Mesh, coarse: Mesh, quantile: float = 0.9) -> float:
    """How far (mm) ``coarse`` (e.g. a :func:`decimate` of ``mesh``) strays from ``mesh``'s surface.

    The ``quantile`` of the distances from ``mesh``'s vertices (a seeded sample of 8,192 where it has more: within
    1% of all of them on the shared igea's and bunny's decimations) to the plane of the ``coarse`` face whose centroid
    is nearest (a cheap stand-in for the point-to-surface distance: exact on faces much larger than the offset, an
    overestimate where the nearest centroid belongs to a neighbouring face). Sources sampled on a coarse
    surface sit this far off the true one; the dipole between two points changes by about that length over
    :math:`1/\\sigma_{tr}` in relative terms (:func:`torchsss.plan.predict`).

    Args:
        mesh: the fine mesh (mm).
        coarse: the coarse mesh in the same frame.
        quantile: in (0, 1].

    Returns:
        The distance in mm (0 when ``coarse`` is ``mesh``).

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> m = sphere(10.0, 4)
        >>> 0.0 < surface_deviation(m, decimate(m, 320)) < 0.2, surface_deviation(m, m)
        (True, 0.0)
    """
    if not isinstance(mesh, Mesh) or not isinstance(coarse, Mesh):
        raise TypeError(f"mesh, coarse: expected two Mesh, got {type(mesh).__name__}, {type(coarse).__name__}")
    if not (isinstance(quantile, numbers.Real) and 0.0 < float(quantile) <= 1.0):
        raise ValueError(f"quantile: expected a number in (0, 1], got {quantile!r}")
    if coarse is mesh:
        return 0.0
    tri = coarse.vertices.detach().double().cpu().numpy()[coarse.faces.cpu().numpy()]
    centre = tri.mean(1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-300
    v = mesh.vertices.detach().double().cpu().numpy()
    if len(v) > _DEVIATION_SAMPLES:  # a quantile: a seeded sample of the vertices holds it within about 1%
        v = v[np.random.default_rng(0).choice(len(v), _DEVIATION_SAMPLES, replace=False)]
    _, idx = cKDTree(centre).query(v, k=1)
    dist = np.abs(((v - centre[idx]) * normal[idx]).sum(1))
    return float(np.quantile(dist, float(quantile)))
