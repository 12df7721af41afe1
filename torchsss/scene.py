"""Scene files: one JSON object that every method renders, so methods compare on exactly the same input.

The format is DESIGN.md §5::

    {
      "mesh": "spot",                 // a path (relative to the scene file) or a built-in name
      "size_mm": 40.0,                // bounding-box diagonal after centring (omit to keep the file's units)
      "material": "skin1",            // a Jensen 2001 preset, or
                                      // {"sigma_a": [r, g, b], "sigma_s_prime": [r, g, b], "eta": 1.3} (mm^-1),
                                      // optional "profile": "dipole" | "burley" | "tabulated"; or
                                      // {"preset": "skin1", "profile": "burley"}
      "lights": [{"type": "point", "position": [x, y, z], "intensity": [r, g, b]}],
                                      // "directional": direction, irradiance; "spot": position, direction,
                                      // intensity, cone_deg, inner_deg; "environment" (Shah 6.4.2,
                                      // order-2 SH radiance, unshadowed): "sh": 9 x [r, g, b], or
                                      // "uniform": [r, g, b], or "sky", "ground" ([r, g, b]) and "up"
      "camera": {"eye": [x, y, z], "target": [x, y, z], "up": [0, 1, 0],
                 "fov_deg": 40.0, "width": 256, "height": 256}
    }

Optional keys: ``"decimate"`` (target face count, quadric decimation at load), ``"name"``, ``"caustics"``.
Positions are in millimetres in the centred, scaled frame. Unknown keys are an error (a typo must not be
silently ignored).

``"caustics"`` makes the scene's mesh a refractive (or reflective) object above a diffuse receiver, rendered
with ``--method caustics`` (Shah ch. 5)::

    "caustics": {
      "ior": 1.5,                     // or [r, g, b] for dispersion
      "absorption": [0, 0.02, 0.05],  // K_a in mm^-1 (I = I0 exp(-K_a d)), number or [r, g, b]
      "mode": "double",               // "double" (front and back refraction), "single", "reflect"
      "receiver": {"type": "plane", "size_mm": 120, "center": [0, 0, -16], "albedo": 0.8},
      "grid": 256                     // light-view grid (texels per side)
    }

The receiver plane faces +z; the lights must be point or directional lights.

Several objects of different materials (Shah 6.4.3) replace ``"mesh"``, ``"size_mm"``, ``"material"`` and
``"decimate"`` by an ``"objects"`` list (exactly one of ``"mesh"`` or ``"objects"``)::

    "objects": [
      {"mesh": "sphere", "size_mm": 20, "material": "marble", "translate": [-5.8, 0, 0]},
      {"mesh": "sphere", "size_mm": 20, "material": "skin1", "translate": [5.8, 0, 0], "decimate": 2000}
    ]

Each object's mesh is loaded, centred and scaled exactly as a single ``"mesh"`` (``"size_mm"`` and
``"decimate"`` optional, as above), then moved by ``"translate"`` (mm, default ``[0, 0, 0]``); ``"mesh"`` and
``"material"`` are required. Light never scatters from one object into another, but the objects shadow each
other. Such a scene has ``Scene.mesh``, ``Scene.material`` and ``Scene.size_mm`` None and its objects in
``Scene.objects``; :meth:`Scene.load_objects` loads ``(mesh, material)`` pairs for either form. Only the
``"reference"`` and ``"splat"`` methods render several objects; ``"caustics"`` is not allowed with
``"objects"``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import torch

from torchsss.geometry.camera import Camera
from torchsss.geometry.lights import Light, light_from_dict
from torchsss.geometry.loading import builtin_mesh_names, load_mesh
from torchsss.geometry.mesh import Mesh
from torchsss.physics.materials import Material

__all__ = ["Caustics", "Material", "Scene", "SceneObject", "default_scene_path", "load_scene"]

_KEYS_REQUIRED = {"mesh", "material", "lights", "camera"}
_KEYS_OPTIONAL = {"size_mm", "decimate", "name", "caustics"}
_KEYS_OBJECTS_REQUIRED = {"objects", "lights", "camera"}
_KEYS_OBJECTS_OPTIONAL = {"name"}
_OBJECT_KEYS_REQUIRED = {"mesh", "material"}
_OBJECT_KEYS_OPTIONAL = {"size_mm", "translate", "decimate"}
_CAUSTIC_KEYS = {"ior", "absorption", "mode", "receiver", "grid"}
_RECEIVER_KEYS = {"type", "size_mm", "center", "albedo"}


def _rgb_or_number(value: object, name: str, positive: bool) -> float | tuple[float, ...]:
    vals = [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else value
    if not isinstance(vals, Sequence) or isinstance(vals, str) or len(vals) not in (1, 3) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in vals):
        raise ValueError(f"{name}: expected a number or [r, g, b], got {value!r}")
    if any((v <= 0) if positive else (v < 0) for v in vals):
        raise ValueError(f"{name}: expected values {'> 0' if positive else '>= 0'}, got {value!r}")
    return float(vals[0]) if len(vals) == 1 else tuple(float(v) for v in vals)


@dataclass(frozen=True)
class Caustics:
    """The ``"caustics"`` block of a scene: refraction parameters and the receiver plane (mm)."""

    ior: float | tuple[float, ...] = 1.5
    absorption: float | tuple[float, ...] = 0.0
    mode: str = "double"
    receiver_size_mm: float = 120.0
    receiver_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    albedo: float | tuple[float, ...] = 0.8
    grid: int = 256

    @classmethod
    def from_dict(cls, d: object) -> Caustics:
        """Validate and parse the block (see the module docstring)."""
        if not isinstance(d, Mapping):
            raise TypeError(f"scene.caustics: expected an object, got {type(d).__name__}")
        if unknown := set(d) - _CAUSTIC_KEYS:
            raise ValueError(f"scene.caustics: unknown keys {sorted(unknown)}; allowed {sorted(_CAUSTIC_KEYS)}")
        mode = d.get("mode", "double")
        if mode not in ("double", "single", "reflect"):
            raise ValueError(f"scene.caustics.mode: expected 'double', 'single' or 'reflect', got {mode!r}")
        rec = d.get("receiver", {})
        if not isinstance(rec, Mapping):
            raise TypeError(f"scene.caustics.receiver: expected an object, got {type(rec).__name__}")
        if unknown := set(rec) - _RECEIVER_KEYS:
            raise ValueError(f"scene.caustics.receiver: unknown keys {sorted(unknown)}; "
                             f"allowed {sorted(_RECEIVER_KEYS)}")
        if rec.get("type", "plane") != "plane":
            raise ValueError(f"scene.caustics.receiver.type: expected 'plane', got {rec.get('type')!r}")
        size = rec.get("size_mm", 120.0)
        if isinstance(size, bool) or not isinstance(size, (int, float)) or not (math.isfinite(size) and size > 0):
            raise ValueError(f"scene.caustics.receiver.size_mm: expected a finite number > 0 (mm), got {size!r}")
        center = rec.get("center", [0.0, 0.0, 0.0])
        if not isinstance(center, Sequence) or len(center) != 3 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in center):
            raise ValueError(f"scene.caustics.receiver.center: expected [x, y, z] in mm, got {center!r}")
        grid = d.get("grid", 256)
        if isinstance(grid, bool) or not isinstance(grid, int) or not 8 <= grid <= 4096:
            raise ValueError(f"scene.caustics.grid: expected an int in [8, 4096], got {grid!r}")
        return cls(ior=_rgb_or_number(d.get("ior", 1.5), "scene.caustics.ior", positive=True),
                   absorption=_rgb_or_number(d.get("absorption", 0.0), "scene.caustics.absorption", positive=False),
                   mode=mode, receiver_size_mm=float(size), receiver_center=tuple(float(v) for v in center),
                   albedo=_rgb_or_number(rec.get("albedo", 0.8), "scene.caustics.receiver.albedo", positive=False),
                   grid=grid)


def _mesh_name(value: object, name: str) -> str:
    if not isinstance(value, str) or not value:
        raise TypeError(f"{name}: expected a path or one of {builtin_mesh_names()}, got {value!r}")
    return value


def _size(value: object, name: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name}: expected a finite number > 0 (mm), got {value!r}")
    return float(value)


def _decimate(value: object, name: str) -> int | None:
    if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 4):
        raise ValueError(f"{name}: expected an int >= 4 (target face count), got {value!r}")
    return value


def _resolve_mesh(mesh: str, base_dir: Path, name: str) -> str:
    if mesh in builtin_mesh_names():
        return mesh
    path = Path(mesh)
    if not path.is_absolute():
        path = base_dir / path
    if not path.is_file():
        raise ValueError(f"{name}: expected an existing file or one of {builtin_mesh_names()}, got {path}")
    return str(path)


#: The last few meshes loaded, by (file, its modification time, size, decimation, dtype): planning and rendering a
#: scene load its mesh twice (a 268k-face scan takes seconds); meshes are not modified in place.
_MESHES: dict[tuple, Mesh] = {}
_MESH_CACHE_SIZE = 4


def _load(source: str, key: str, size_mm: float | None, decimate: int | None, dtype: torch.dtype) -> Mesh:
    """load_mesh with its errors prefixed by the scene key that named the file (``scene.mesh``, ...), cached."""
    path = Path(source)
    stamp = path.stat().st_mtime_ns if path.is_file() else None
    cache_key = (str(path.resolve()) if stamp is not None else source, stamp, size_mm, decimate, dtype)
    if cache_key in _MESHES:
        return _MESHES[cache_key]
    try:
        mesh = load_mesh(source, size_mm, decimate_to=decimate, dtype=dtype)
    except (ValueError, FileNotFoundError) as err:
        raise ValueError(f"{key}: {err}") from err
    if len(_MESHES) >= _MESH_CACHE_SIZE:
        _MESHES.pop(next(iter(_MESHES)))
    _MESHES[cache_key] = mesh
    return mesh


@dataclass(frozen=True)
class SceneObject:
    """One entry of a scene's ``"objects"`` list: a mesh, its size and material, and a translation (mm)."""

    mesh: str
    material: Material
    size_mm: float | None = None
    translate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    decimate: int | None = None

    @classmethod
    def from_dict(cls, d: object, name: str = "scene.objects[0]") -> SceneObject:
        """Validate and parse one object (see the module docstring); ``name`` prefixes the error messages.

        Examples:
            >>> o = SceneObject.from_dict({"mesh": "sphere", "material": "marble", "translate": [5, 0, 0]})
            >>> o.material.name, o.translate, o.size_mm
            ('marble', (5.0, 0.0, 0.0), None)
        """
        if not isinstance(d, Mapping):
            raise TypeError(f"{name}: expected an object, got {type(d).__name__}")
        if missing := _OBJECT_KEYS_REQUIRED - set(d):
            raise ValueError(f"{name}: missing keys {sorted(missing)}")
        if unknown := set(d) - _OBJECT_KEYS_REQUIRED - _OBJECT_KEYS_OPTIONAL:
            allowed = sorted(_OBJECT_KEYS_REQUIRED | _OBJECT_KEYS_OPTIONAL)
            raise ValueError(f"{name}: unknown keys {sorted(unknown)}; allowed {allowed}")
        t = d.get("translate", [0.0, 0.0, 0.0])
        if not isinstance(t, Sequence) or isinstance(t, str) or len(t) != 3 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in t):
            raise ValueError(f"{name}.translate: expected [x, y, z] in mm, got {t!r}")
        return cls(mesh=_mesh_name(d["mesh"], f"{name}.mesh"), material=Material.from_json(d["material"]),
                   size_mm=_size(d.get("size_mm"), f"{name}.size_mm"), translate=tuple(float(v) for v in t),
                   decimate=_decimate(d.get("decimate"), f"{name}.decimate"))

    def load(self, base_dir: str | Path | None = None, dtype: torch.dtype = torch.float32, *,
             name: str = "scene.objects[0]") -> Mesh:
        """Load, clean, scale (and decimate) the mesh as a single-object scene does, then translate it.

        Relative paths resolve against ``base_dir`` (default: the working directory); ``name`` prefixes errors.

        Examples:
            >>> o = SceneObject(mesh="sphere", material=Material.from_json("marble"), size_mm=20.0,
            ...                 translate=(10.0, 0.0, 0.0))
            >>> m = o.load()
            >>> round(float(m.vertices[:, 0].min()), 3), round(float(m.vertices[:, 0].max()), 3)
            (4.226, 15.774)
        """
        base = Path(base_dir) if base_dir is not None else Path.cwd()
        mesh = _load(_resolve_mesh(self.mesh, base, f"{name}.mesh"), f"{name}.mesh", self.size_mm, self.decimate,
                     dtype)
        if any(self.translate):
            mesh = dataclasses.replace(mesh, vertices=mesh.vertices + mesh.vertices.new_tensor(self.translate))
        return mesh


@dataclass(frozen=True)
class Scene:
    """A parsed scene file (see the module docstring for the format).

    A single-object scene has ``mesh`` and ``material`` (and optional ``size_mm``, ``decimate``) and empty
    ``objects``; a multi-object scene has ``mesh``, ``material`` and ``size_mm`` None and its entries in
    ``objects``.
    """

    mesh: str | None
    material: Material | None
    lights: tuple[Light, ...]
    camera: Camera
    size_mm: float | None = None
    decimate: int | None = None
    name: str = "scene"
    base_dir: Path = field(default_factory=Path.cwd)
    caustics: Caustics | None = None
    objects: tuple[SceneObject, ...] = ()

    @classmethod
    def from_dict(cls, d: Mapping, base_dir: str | Path | None = None) -> Scene:
        """Validate and parse a scene object; relative mesh paths resolve against ``base_dir``.

        Examples:
            >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "marble",
            ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
            ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 32, "height": 32}})
            >>> s.material.name, s.camera.width, s.lights[0].kind
            ('marble', 32, 'point')
            >>> t = Scene.from_dict({"objects": [{"mesh": "sphere", "size_mm": 20, "material": "marble"},
            ...     {"mesh": "sphere", "size_mm": 10, "material": "skin1", "translate": [8.7, 0, 0]}],
            ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
            ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 32, "height": 32}})
            >>> [o.material.name for o in t.objects], t.mesh
            (['marble', 'skin1'], None)
        """
        if not isinstance(d, Mapping):
            raise TypeError(f"scene: expected a JSON object, got {type(d).__name__}")
        keys = set(d)
        multi = "objects" in keys
        if multi and "mesh" in keys:
            raise ValueError('scene: expected exactly one of "mesh" or "objects", got both')
        if not multi and "mesh" not in keys:
            raise ValueError('scene: expected exactly one of "mesh" or "objects", got neither')
        required = _KEYS_OBJECTS_REQUIRED if multi else _KEYS_REQUIRED
        optional = _KEYS_OBJECTS_OPTIONAL if multi else _KEYS_OPTIONAL
        if missing := required - keys:
            raise ValueError(f"scene: missing keys {sorted(missing)}")
        if unknown := keys - required - optional:
            allowed = sorted(required | optional)
            extra = ' (with "objects", mesh, material, size_mm and decimate go in each object)' if multi else ""
            raise ValueError(f"scene: unknown keys {sorted(unknown)}; allowed {allowed}{extra}")
        lights = d["lights"]
        if not isinstance(lights, Sequence) or isinstance(lights, str) or len(lights) == 0:
            raise ValueError(f"scene.lights: expected a non-empty list of lights, got {lights!r}")
        if not isinstance(d["camera"], Mapping):
            raise TypeError(f"scene.camera: expected an object, got {d['camera']!r}")
        base = Path(base_dir) if base_dir is not None else Path.cwd()
        common = dict(lights=tuple(light_from_dict(x) for x in lights), camera=Camera.from_dict(d["camera"]),
                      name=str(d.get("name", "scene")), base_dir=base)
        if multi:
            objs = d["objects"]
            if not isinstance(objs, Sequence) or isinstance(objs, str) or len(objs) == 0:
                raise ValueError(f"scene.objects: expected a non-empty list of objects, got {objs!r}")
            objects = tuple(SceneObject.from_dict(o, f"scene.objects[{i}]") for i, o in enumerate(objs))
            return cls(mesh=None, material=None, objects=objects, **common)
        return cls(
            mesh=_mesh_name(d["mesh"], "scene.mesh"),
            material=Material.from_json(d["material"]),
            size_mm=_size(d.get("size_mm"), "scene.size_mm"),
            decimate=_decimate(d.get("decimate"), "scene.decimate"),
            caustics=None if d.get("caustics") is None else Caustics.from_dict(d["caustics"]),
            **common,
        )

    def rescaled(self, size_mm: float) -> Scene:
        """The same scene for the object at another size (mm): what was at x is now at ``f x``.

        Positions (light positions, the camera's eye and target, the caustics receiver) scale by
        :math:`f = ` ``size_mm / self.size_mm``; point and spot intensities by :math:`f^2`, so the irradiance at
        corresponding points is unchanged; directional lights are unchanged. Only the object's size in mm (and so
        how translucent it looks) changes. A multi-object scene scales as a whole so that its largest object gets
        ``size_mm``: :math:`f` = ``size_mm`` / (the largest object's ``size_mm``), and every object's size and
        translation scale by :math:`f`.

        Raises:
            ValueError: the scene (or one of its objects) has no ``size_mm``, or ``size_mm`` is not a positive
                finite number.

        Examples:
            >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
            ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
            ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 8, "height": 8}})
            >>> t = s.rescaled(10.0)
            >>> t.size_mm, t.lights[0].position, t.lights[0].intensity, t.camera.eye
            (10.0, (0.0, 0.0, 50.0), (2500.0, 2500.0, 2500.0), (0.0, 0.0, 40.0))
        """
        if self.objects:
            if any(o.size_mm is None for o in self.objects):
                raise ValueError("size_mm: expected every object of the scene to have size_mm to rescale, got an "
                                 "object in its file's units")
            current = max(float(o.size_mm) for o in self.objects)  # type: ignore[arg-type]
        elif self.size_mm is None:
            raise ValueError("size_mm: expected a scene with size_mm to rescale, got a scene in the file's units")
        else:
            current = float(self.size_mm)
        if isinstance(size_mm, bool) or not isinstance(size_mm, (int, float)) or not (
                math.isfinite(size_mm) and size_mm > 0):
            raise ValueError(f"size_mm: expected a finite number > 0 (mm), got {size_mm!r}")
        f = float(size_mm) / current
        lights = []
        for light in self.lights:
            if hasattr(light, "position"):
                light = dataclasses.replace(light, position=tuple(f * p for p in light.position),
                                            intensity=tuple(f * f * i for i in light.intensity))
            lights.append(light)
        camera = dataclasses.replace(self.camera, eye=tuple(f * e for e in self.camera.eye),
                                     target=tuple(f * t for t in self.camera.target))
        caustics = self.caustics
        if caustics is not None:
            caustics = dataclasses.replace(caustics, receiver_size_mm=f * caustics.receiver_size_mm,
                                           receiver_center=tuple(f * c for c in caustics.receiver_center))
        objects = tuple(dataclasses.replace(o, size_mm=f * o.size_mm, translate=tuple(f * t for t in o.translate))
                        for o in self.objects)
        return dataclasses.replace(self, size_mm=None if self.objects else float(size_mm), lights=tuple(lights),
                                   camera=camera, caustics=caustics, objects=objects)

    def mesh_source(self) -> str:
        """The mesh argument for :func:`~torchsss.geometry.loading.load_mesh`: a built-in name or a resolved path.

        For a scene with ``"objects"`` every object's mesh is resolved (an error names the first missing one) and
        the first object's source is returned; :meth:`mesh_sources` gives all of them.
        """
        if self.mesh is None:
            return self.mesh_sources()[0]
        return _resolve_mesh(self.mesh, self.base_dir, "scene.mesh")

    def mesh_sources(self) -> list[str]:
        """The resolved mesh source of every object (one entry for a single-object scene).

        Examples:
            >>> s = Scene.from_dict({"objects": [{"mesh": "sphere", "material": "marble"},
            ...     {"mesh": "torus", "material": "skin1"}],
            ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
            ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 8, "height": 8}})
            >>> s.mesh_sources()
            ['sphere', 'torus']
        """
        if self.mesh is not None:
            return [self.mesh_source()]
        return [_resolve_mesh(o.mesh, self.base_dir, f"scene.objects[{i}].mesh") for i, o in enumerate(self.objects)]

    def load_mesh(self, dtype: torch.dtype = torch.float32) -> Mesh:
        """Load, clean, scale (and decimate) the scene's mesh (single-object scenes; see :meth:`load_objects`)."""
        if self.mesh is None:
            raise ValueError('scene: expected a single-object scene ("mesh") for load_mesh, got one with "objects" '
                             "(use Scene.load_objects)")
        return _load(self.mesh_source(), "scene.mesh", self.size_mm, self.decimate, dtype)

    def load_objects(self, dtype: torch.dtype = torch.float32) -> list[tuple[Mesh, Material]]:
        """``(mesh, material)`` of every object, translated into place (one entry for a single-object scene).

        Examples:
            >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
            ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
            ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 8, "height": 8}})
            >>> [(m.name, mat.name) for m, mat in s.load_objects()]
            [('sphere', 'skin1')]
        """
        if not self.objects:
            return [(self.load_mesh(dtype=dtype), self.material)]  # type: ignore[list-item]
        return [(o.load(self.base_dir, dtype=dtype, name=f"scene.objects[{i}]"), o.material)
                for i, o in enumerate(self.objects)]


def load_scene(path: str | Path) -> Scene:
    """Read a scene JSON file (relative mesh paths resolve against the file's folder).

    Examples:
        >>> load_scene(default_scene_path()).mesh
        'spot'
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"scene: expected an existing JSON file, got {path}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise ValueError(f"scene: {path} is not valid JSON: {err}") from err
    return Scene.from_dict(data, base_dir=path.parent)


def default_scene_path() -> Path:
    """The shipped default scene: the embedded spot mesh, back-lit, in a Jensen preset."""
    return Path(str(resources.files("torchsss").joinpath("data/scenes/default.json")))
