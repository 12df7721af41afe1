"""Procedural test shapes in millimetres: icosphere, torus, thin slab (closed) and plane (open).

Every shape is centred at the origin, wound counter-clockwise seen from outside (outward normals), carries no
texture coordinates (``face_uvs=None``) and is built directly as index arrays (no clean-up pass needed: there
are no duplicated vertices or degenerate faces). The closed shapes are watertight with positive signed volume.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchsss.geometry.mesh import Mesh, _check_float_dtype, _check_int, _check_positive_number

__all__ = ["plane", "slab", "sphere", "torus"]

_MAX_SUBDIVISIONS = 10  # 20 * 4**10 = 21M faces


def _mesh(vertices: np.ndarray, faces: np.ndarray, name: str, dtype: torch.dtype) -> Mesh:
    return Mesh(
        torch.from_numpy(np.ascontiguousarray(vertices, dtype=np.float64)).to(dtype),
        torch.from_numpy(np.ascontiguousarray(faces, dtype=np.int64)),
        name=name,
    )


def _grid_faces(rows: int, cols: int, wrap_rows: bool = False, wrap_cols: bool = False) -> np.ndarray:
    """Two triangles per quad of a ``rows x cols`` vertex grid (index ``r * cols + c``), normal along d/dc x d/dr.

    With ``wrap_*`` the last row/column connects back to the first.
    """
    n_r = rows if wrap_rows else rows - 1
    n_c = cols if wrap_cols else cols - 1
    r, c = np.meshgrid(np.arange(n_r), np.arange(n_c), indexing="ij")
    r1, c1 = (r + 1) % rows, (c + 1) % cols
    a, b, cc, d = r * cols + c, r * cols + c1, r1 * cols + c1, r1 * cols + c
    tris = np.stack([np.stack([a, b, cc], -1), np.stack([a, cc, d], -1)], axis=-2)
    return tris.reshape(-1, 3)


def sphere(radius_mm: float = 10.0, subdivisions: int = 4, *, dtype: torch.dtype = torch.float32) -> Mesh:
    """An icosphere: an icosahedron subdivided ``subdivisions`` times, vertices projected onto the sphere.

    It has :math:`20 \\cdot 4^s` faces and :math:`10 \\cdot 4^s + 2` vertices; its area approaches
    :math:`4 \\pi r^2` from below (0.1 % short at ``subdivisions=4``).

    Args:
        radius_mm: Radius in mm, positive.
        subdivisions: Number of 1-to-4 subdivisions, 0 to 10.
        dtype: Floating dtype of the vertices.

    Returns:
        A watertight mesh named ``"sphere"``, centred at the origin.

    Raises:
        TypeError: Wrong argument types.
        ValueError: Non-positive radius or subdivisions out of range.

    Examples:
        >>> m = sphere(5.0, subdivisions=2)
        >>> m.num_vertices, m.num_faces, m.is_watertight
        (162, 320, True)
        >>> abs(m.vertices.norm(dim=1) - 5.0).max().item() < 1e-5
        True
    """
    radius = _check_positive_number(radius_mm, "radius_mm")
    subdivisions = _check_int(subdivisions, "subdivisions", 0, _MAX_SUBDIVISIONS)
    dtype = _check_float_dtype(dtype)
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
        dtype=np.float64,
    )  # fmt: skip
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
         [6, 2, 10], [8, 6, 7], [9, 8, 1]],
        dtype=np.int64,
    )  # fmt: skip
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):  # loop over levels, each level vectorised over all faces
        edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = v[unique].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = (len(v) + inverse.reshape(-1)).reshape(-1, 3)  # midpoints of edges 01, 12, 20
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate(
            [np.stack(x, axis=1) for x in ((a, m01, m20), (b, m12, m01), (c, m20, m12), (m01, m12, m20))]
        )
        v = np.concatenate([v, mid])
    return _mesh(v * radius, f, "sphere", dtype)


def torus(
    major_radius_mm: float = 10.0,
    minor_radius_mm: float = 4.0,
    major_segments: int = 48,
    minor_segments: int = 24,
    *,
    dtype: torch.dtype = torch.float32,
) -> Mesh:
    """A ring torus around the z axis: tube of radius ``minor_radius_mm`` around a circle of ``major_radius_mm``.

    The exact surface area is :math:`4 \\pi^2 R r`; the default tessellation is within 0.5 % of it.

    Args:
        major_radius_mm: Distance from the centre to the tube's centre line, mm.
        minor_radius_mm: Tube radius, mm, smaller than the major radius.
        major_segments: Segments around the z axis, >= 3.
        minor_segments: Segments around the tube, >= 3.
        dtype: Floating dtype of the vertices.

    Returns:
        A watertight mesh named ``"torus"`` with ``major_segments * minor_segments`` vertices.

    Raises:
        TypeError: Wrong argument types.
        ValueError: Non-positive radii, ``minor_radius_mm >= major_radius_mm`` or too few segments.

    Examples:
        >>> m = torus(10.0, 2.0, 32, 16)
        >>> m.num_vertices, m.num_faces, m.is_watertight
        (512, 1024, True)
    """
    big = _check_positive_number(major_radius_mm, "major_radius_mm")
    small = _check_positive_number(minor_radius_mm, "minor_radius_mm")
    if small >= big:
        raise ValueError(
            f"minor_radius_mm: expected a value < major_radius_mm = {big} (ring torus), got {minor_radius_mm!r}"
        )
    n_u = _check_int(major_segments, "major_segments", 3)
    n_v = _check_int(minor_segments, "minor_segments", 3)
    dtype = _check_float_dtype(dtype)
    u = np.arange(n_u) * (2.0 * math.pi / n_u)
    w = np.arange(n_v) * (2.0 * math.pi / n_v)
    uu, ww = np.meshgrid(u, w, indexing="ij")  # vertex index = i_u * n_v + i_v
    ring = big + small * np.cos(ww)
    v = np.stack([ring * np.cos(uu), ring * np.sin(uu), small * np.sin(ww)], axis=-1).reshape(-1, 3)
    # d/du x d/dv points away from the tube's centre line; _grid_faces' normal is d/dcol x d/drow = d/dv x d/du
    # for this layout (rows follow u, columns v), so flip the winding.
    f = _grid_faces(n_u, n_v, wrap_rows=True, wrap_cols=True)[:, [0, 2, 1]]
    return _mesh(v, f, "torus", dtype)


def slab(
    width_mm: float = 40.0,
    height_mm: float = 40.0,
    thickness_mm: float = 2.0,
    segments: int = 16,
    *,
    dtype: torch.dtype = torch.float32,
) -> Mesh:
    """A thin closed box centred at the origin: ``width`` along x, ``height`` along y, ``thickness`` along z.

    The two large faces (z = ±thickness/2) are regular grids of ``segments x segments`` quads; the four sides
    are one quad high and share the large faces' boundary vertices, so the mesh is watertight. Its area is
    exactly :math:`2wh + 2(w + h)t`.

    Args:
        width_mm: Extent along x, mm.
        height_mm: Extent along y, mm.
        thickness_mm: Extent along z, mm.
        segments: Quads per side of each large face, >= 1.
        dtype: Floating dtype of the vertices.

    Returns:
        A watertight mesh named ``"slab"`` with :math:`2 (s + 1)^2` vertices and :math:`4 s^2 + 8 s` faces.

    Raises:
        TypeError: Wrong argument types.
        ValueError: Non-positive sizes or ``segments`` < 1.

    Examples:
        >>> m = slab(10.0, 20.0, 1.0, segments=4)
        >>> m.num_vertices, m.num_faces, round(m.area, 4), m.is_watertight
        (50, 96, 460.0, True)
    """
    w = _check_positive_number(width_mm, "width_mm")
    h = _check_positive_number(height_mm, "height_mm")
    t = _check_positive_number(thickness_mm, "thickness_mm")
    s = _check_int(segments, "segments", 1)
    dtype = _check_float_dtype(dtype)
    n = s + 1
    x = np.linspace(-w / 2, w / 2, n)
    y = np.linspace(-h / 2, h / 2, n)
    yy, xx = np.meshgrid(y, x, indexing="ij")  # index = j * n + i, x varies along columns
    grid = np.stack([xx.reshape(-1), yy.reshape(-1)], axis=1)
    top = np.concatenate([grid, np.full((n * n, 1), t / 2)], axis=1)
    bottom = np.concatenate([grid, np.full((n * n, 1), -t / 2)], axis=1)
    v = np.concatenate([top, bottom])
    quads = _grid_faces(n, n)  # normal d/dx x d/dy = +z
    faces_top = quads
    faces_bottom = quads[:, [0, 2, 1]] + n * n
    # boundary loop of the grid, counter-clockwise seen from +z
    k = np.arange(s)
    loop = np.concatenate([k, s + k * n, n * n - 1 - k, (s - k) * n])
    nxt = np.roll(loop, -1)
    t0, t1, b0, b1 = loop, nxt, loop + n * n, nxt + n * n
    sides = np.concatenate([np.stack([t0, b0, b1], axis=1), np.stack([t0, b1, t1], axis=1)])
    f = np.concatenate([faces_top, faces_bottom, sides])
    return _mesh(v, f, "slab", dtype)


def plane(
    width_mm: float = 100.0, height_mm: float = 100.0, segments: int = 32, *, dtype: torch.dtype = torch.float32
) -> Mesh:
    """An open, single-sided square at z = 0 facing +z, centred at the origin, on a regular grid.

    Useful as a ground plane or receiver. It is not watertight (no warning is issued for it).

    Args:
        width_mm: Extent along x, mm.
        height_mm: Extent along y, mm.
        segments: Quads per side, >= 1.
        dtype: Floating dtype of the vertices.

    Returns:
        A mesh named ``"plane"`` with :math:`(s + 1)^2` vertices and :math:`2 s^2` faces, all normals +z.

    Raises:
        TypeError: Wrong argument types.
        ValueError: Non-positive sizes or ``segments`` < 1.

    Examples:
        >>> m = plane(10.0, 10.0, segments=2)
        >>> m.num_vertices, m.num_faces, m.area, m.is_watertight
        (9, 8, 100.0, False)
        >>> m.face_normals[:, 2].min().item()
        1.0
    """
    w = _check_positive_number(width_mm, "width_mm")
    h = _check_positive_number(height_mm, "height_mm")
    s = _check_int(segments, "segments", 1)
    dtype = _check_float_dtype(dtype)
    n = s + 1
    yy, xx = np.meshgrid(np.linspace(-h / 2, h / 2, n), np.linspace(-w / 2, w / 2, n), indexing="ij")
    v = np.stack([xx.reshape(-1), yy.reshape(-1), np.zeros(n * n)], axis=1)
    return _mesh(v, _grid_faces(n, n), "plane", dtype)
