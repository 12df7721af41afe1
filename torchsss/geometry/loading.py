"""Reading meshes: files through trimesh, and the built-in meshes (procedural shapes and the shipped spot).

Kept apart from :mod:`torchsss.geometry.mesh` so that imports run one way: ``mesh`` <- ``procedural`` <-
``loading``.
"""

from __future__ import annotations

import os
import pathlib
from importlib import resources

import numpy as np
import torch
import trimesh

from torchsss.geometry import procedural
from torchsss.geometry.mesh import (
    Mesh,
    _build,
    _check_float_dtype,
    _check_int,
    _check_positive_number,
    _warn_open,
    decimate,
    normalize_to_size,
)

__all__ = ["builtin_mesh_names", "builtin_mesh_path", "load_mesh"]

_BUILTIN_NAMES = ("slab", "sphere", "spot", "torus")
_PROCEDURAL = ("slab", "sphere", "torus")


def builtin_mesh_names() -> tuple[str, ...]:
    """Names :func:`load_mesh` accepts instead of a path: procedural shapes and the shipped "spot" model.

    Examples:
        >>> builtin_mesh_names()
        ('slab', 'sphere', 'spot', 'torus')
    """
    return _BUILTIN_NAMES


def builtin_mesh_path(name: str) -> pathlib.Path:
    """Path of a built-in mesh file shipped with the package (only ``"spot"`` is a file).

    Args:
        name: A name from :func:`builtin_mesh_names` that has a file.

    Returns:
        The file's path (``torchsss/data/spot.obj``, "Spot" by Keenan Crane, CC0).

    Raises:
        TypeError: ``name`` is not a string.
        ValueError: Unknown name, or a procedural shape (no file; use :func:`load_mesh`).

    Examples:
        >>> builtin_mesh_path("spot").name
        'spot.obj'
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a str, got {type(name).__name__}")
    if name in _PROCEDURAL:
        raise ValueError(f"name: expected a built-in mesh with a file ('spot'), got {name!r} (procedural, no file)")
    if name != "spot":
        raise ValueError(f"name: expected one of {_BUILTIN_NAMES}, got {name!r}")
    return pathlib.Path(str(resources.files("torchsss").joinpath("data", "spot.obj")))


def _procedural(name: str, dtype: torch.dtype) -> Mesh:
    return getattr(procedural, name)(dtype=dtype)


def _read(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many kinds (KeyError, ValueError, ImportError of a codec, ...)
        raise ValueError(f"source: expected a readable mesh file (OBJ, PLY, STL, GLB, OFF), got {path} that "
                         f"trimesh cannot read: {type(err).__name__}: {err}") from err
    if not isinstance(loaded, trimesh.Trimesh):
        raise ValueError(f"source: expected a file holding triangle geometry, got {type(loaded).__name__} ({path})")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    face_uvs = None
    visual = loaded.visual
    uv = getattr(visual, "uv", None) if isinstance(visual, trimesh.visual.TextureVisuals) else None
    if uv is not None and len(uv) == len(vertices) and len(faces):
        face_uvs = np.asarray(uv, dtype=np.float64)[:, :2][faces]  # per corner, before any welding
    return vertices, faces, face_uvs


def load_mesh(
    source: str | os.PathLike,
    size_mm: float | None = None,
    *,
    decimate_to: int | None = None,
    dtype: torch.dtype = torch.float32,
    warn_open: bool = True,
) -> Mesh:
    """Load a mesh file or a built-in mesh, clean it up, optionally decimate it and scale it to millimetres.

    Files are read with ``trimesh.load(path, force="mesh", process=False)`` (OBJ, PLY, STL, GLB/GLTF, OFF, ...);
    scenes with several geometries are concatenated (with their scene transforms) into one mesh. Per-corner
    texture coordinates are kept in ``face_uvs`` when the file has them. The arrays then go through the
    clean-up of :func:`mesh_from_arrays`. A string equal to a built-in name (:func:`builtin_mesh_names`) selects
    the built-in mesh even if a file of that name exists: ``"sphere"``, ``"torus"``, ``"slab"`` are the
    procedural defaults (in mm), ``"spot"`` the shipped model.

    Args:
        source: Path to a mesh file, or a built-in name.
        size_mm: If given, centre on the bounding-box centre and scale so that the bounding-box diagonal is
            ``size_mm`` mm; otherwise the file's units are taken as mm (``mm_per_unit`` = 1).
        decimate_to: If given, decimate to about this many faces (see :func:`decimate`; drops ``face_uvs``),
            before scaling.
        dtype: Floating dtype of the vertices and face_uvs.
        warn_open: Warn (:class:`MeshWarning`, once) when the final mesh is not watertight.

    Returns:
        The mesh, named after the file stem or the built-in name.

    Raises:
        TypeError: ``source`` is not a string or path, or another argument has the wrong type.
        FileNotFoundError: ``source`` is neither a built-in name nor an existing file.
        ValueError: The file holds no usable triangles, or a bad ``size_mm`` / ``decimate_to``.

    Examples:
        >>> m = load_mesh("spot", size_mm=30.0)
        >>> m.num_faces, tuple(m.face_uvs.shape), round(m.size_mm, 3), m.is_watertight
        (5856, (5856, 3, 2), 30.0, True)
        >>> load_mesh("torus").name
        'torus'
    """
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"source: expected a path or a built-in mesh name, got {type(source).__name__}")
    if size_mm is not None:
        size_mm = _check_positive_number(size_mm, "size_mm")
    if decimate_to is not None:
        decimate_to = _check_int(decimate_to, "decimate_to", 4)
    dtype = _check_float_dtype(dtype)

    if isinstance(source, str) and source in _PROCEDURAL:
        mesh = _procedural(source, dtype)
    else:
        path = builtin_mesh_path("spot") if (isinstance(source, str) and source == "spot") else pathlib.Path(source)
        if not path.is_file():
            raise FileNotFoundError(
                f"source: expected an existing mesh file or a built-in name {_BUILTIN_NAMES}, got {str(source)!r}"
            )
        vertices, faces, face_uvs = _read(path)
        if len(vertices) == 0 or len(faces) == 0:
            raise ValueError(f"source: expected a file with triangles, got {len(faces)} faces in {path}")
        mesh = _build(
            torch.from_numpy(vertices), torch.from_numpy(faces), face_uvs, dtype=dtype, merge=True, name=path.stem
        )
    if decimate_to is not None:
        mesh = decimate(mesh, decimate_to)
    if size_mm is not None:
        mesh = normalize_to_size(mesh, size_mm)
    if warn_open:
        _warn_open(mesh, stacklevel=2)
    return mesh
