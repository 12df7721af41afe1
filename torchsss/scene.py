"""Scene files: one JSON object that every method renders, so methods compare on exactly the same input.

The format is DESIGN.md §5::

    {
      "mesh": "spot",                 // a path (relative to the scene file) or a built-in name
      "size_mm": 40.0,                // bounding-box diagonal after centring (omit to keep the file's units)
      "material": "skin1",            // a Jensen 2001 preset, or
                                      // {"sigma_a": [r, g, b], "sigma_s_prime": [r, g, b], "eta": 1.3} (mm^-1)
      "lights": [{"type": "point", "position": [x, y, z], "intensity": [r, g, b]}],
                                      // "directional": direction, irradiance; "spot": position, direction,
                                      // intensity, cone_deg, inner_deg
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
from torch import Tensor

from torchsss.geometry.camera import Camera
from torchsss.geometry.lights import Light, light_from_dict
from torchsss.geometry.loading import builtin_mesh_names, load_mesh
from torchsss.geometry.mesh import Mesh
from torchsss.physics.materials import preset, preset_names

__all__ = ["Caustics", "Material", "Scene", "default_scene_path", "load_scene"]

_KEYS_REQUIRED = {"mesh", "material", "lights", "camera"}
_KEYS_OPTIONAL = {"size_mm", "decimate", "name", "caustics"}
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


@dataclass(frozen=True)
class Material:
    """Homogeneous dipole material: per-channel coefficients in mm^-1 and the relative index of refraction."""

    sigma_a: tuple[float, float, float]
    sigma_s_prime: tuple[float, float, float]
    eta: float = 1.3
    name: str = "custom"

    @classmethod
    def from_json(cls, value: object) -> Material:
        """A preset name or an object with ``sigma_a``, ``sigma_s_prime`` (3 numbers each, mm^-1) and ``eta``.

        Examples:
            >>> Material.from_json("marble").eta
            1.3
            >>> Material.from_json({"sigma_a": [0.1, 0.1, 0.1], "sigma_s_prime": [1, 1, 1]}).sigma_s_prime
            (1.0, 1.0, 1.0)
        """
        if isinstance(value, str):
            p = preset(value)
            return cls(p.sigma_a, p.sigma_s_prime, p.eta, p.name)
        if not isinstance(value, Mapping):
            raise TypeError(f"material: expected a preset name {preset_names()} or an object, got {value!r}")
        unknown = set(value) - {"sigma_a", "sigma_s_prime", "eta", "name"}
        if unknown or not {"sigma_a", "sigma_s_prime"} <= set(value):
            raise ValueError(
                f"material: expected keys sigma_a, sigma_s_prime and optional eta, name; got {sorted(value)}"
            )

        def rgb(key: str, positive: bool) -> tuple[float, float, float]:
            v = value[key]
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                v = [v] * 3
            if not isinstance(v, Sequence) or len(v) != 3:
                raise ValueError(f"material.{key}: expected 3 numbers (mm^-1), got {v!r}")
            out = tuple(float(x) for x in v)
            if not all(math.isfinite(x) and (x > 0 if positive else x >= 0) for x in out):
                raise ValueError(f"material.{key}: expected finite values {'> 0' if positive else '>= 0'}, got {v!r}")
            return out  # type: ignore[return-value]

        eta = float(value.get("eta", 1.3))
        if not (math.isfinite(eta) and eta > 0):
            raise ValueError(f"material.eta: expected a finite value > 0, got {value.get('eta')!r}")
        return cls(rgb("sigma_a", False), rgb("sigma_s_prime", True), eta, str(value.get("name", "custom")))

    def tensors(self, dtype: torch.dtype = torch.float64, device=None) -> tuple[Tensor, Tensor, Tensor]:
        """``(sigma_a (3,), sigma_s_prime (3,), eta ())`` tensors in mm^-1."""
        return (torch.tensor(self.sigma_a, dtype=dtype, device=device),
                torch.tensor(self.sigma_s_prime, dtype=dtype, device=device),
                torch.tensor(self.eta, dtype=dtype, device=device))


@dataclass(frozen=True)
class Scene:
    """A parsed scene file (see the module docstring for the format)."""

    mesh: str
    material: Material
    lights: tuple[Light, ...]
    camera: Camera
    size_mm: float | None = None
    decimate: int | None = None
    name: str = "scene"
    base_dir: Path = field(default_factory=Path.cwd)
    caustics: Caustics | None = None

    @classmethod
    def from_dict(cls, d: Mapping, base_dir: str | Path | None = None) -> Scene:
        """Validate and parse a scene object; relative mesh paths resolve against ``base_dir``.

        Examples:
            >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "marble",
            ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
            ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 32, "height": 32}})
            >>> s.material.name, s.camera.width, s.lights[0].kind
            ('marble', 32, 'point')
        """
        if not isinstance(d, Mapping):
            raise TypeError(f"scene: expected a JSON object, got {type(d).__name__}")
        keys = set(d)
        if missing := _KEYS_REQUIRED - keys:
            raise ValueError(f"scene: missing keys {sorted(missing)}")
        if unknown := keys - _KEYS_REQUIRED - _KEYS_OPTIONAL:
            allowed = sorted(_KEYS_REQUIRED | _KEYS_OPTIONAL)
            raise ValueError(f"scene: unknown keys {sorted(unknown)}; allowed {allowed}")
        if not isinstance(d["mesh"], str) or not d["mesh"]:
            raise TypeError(f"scene.mesh: expected a path or one of {builtin_mesh_names()}, got {d['mesh']!r}")
        size = d.get("size_mm")
        if size is not None:
            if isinstance(size, bool) or not isinstance(size, (int, float)) or not (math.isfinite(size) and size > 0):
                raise ValueError(f"scene.size_mm: expected a finite number > 0 (mm), got {size!r}")
            size = float(size)
        dec = d.get("decimate")
        if dec is not None and (isinstance(dec, bool) or not isinstance(dec, int) or dec < 4):
            raise ValueError(f"scene.decimate: expected an int >= 4 (target face count), got {dec!r}")
        lights = d["lights"]
        if not isinstance(lights, Sequence) or isinstance(lights, str) or len(lights) == 0:
            raise ValueError(f"scene.lights: expected a non-empty list of lights, got {lights!r}")
        if not isinstance(d["camera"], Mapping):
            raise TypeError(f"scene.camera: expected an object, got {d['camera']!r}")
        base = Path(base_dir) if base_dir is not None else Path.cwd()
        return cls(
            mesh=d["mesh"],
            material=Material.from_json(d["material"]),
            lights=tuple(light_from_dict(x) for x in lights),
            camera=Camera.from_dict(d["camera"]),
            size_mm=size,
            decimate=dec,
            name=str(d.get("name", "scene")),
            base_dir=base,
            caustics=None if d.get("caustics") is None else Caustics.from_dict(d["caustics"]),
        )

    def rescaled(self, size_mm: float) -> Scene:
        """The same scene for the object at another size (mm): what was at x is now at ``f x``.

        Positions (light positions, the camera's eye and target, the caustics receiver) scale by
        :math:`f = ` ``size_mm / self.size_mm``; point and spot intensities by :math:`f^2`, so the irradiance at
        corresponding points is unchanged; directional lights are unchanged. Only the object's size in mm (and so
        how translucent it looks) changes.

        Raises:
            ValueError: the scene has no ``size_mm`` or ``size_mm`` is not a positive finite number.

        Examples:
            >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
            ...     "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
            ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 8, "height": 8}})
            >>> t = s.rescaled(10.0)
            >>> t.size_mm, t.lights[0].position, t.lights[0].intensity, t.camera.eye
            (10.0, (0.0, 0.0, 50.0), (2500.0, 2500.0, 2500.0), (0.0, 0.0, 40.0))
        """
        if self.size_mm is None:
            raise ValueError("size_mm: expected a scene with size_mm to rescale, got a scene in the file's units")
        if isinstance(size_mm, bool) or not isinstance(size_mm, (int, float)) or not (
                math.isfinite(size_mm) and size_mm > 0):
            raise ValueError(f"size_mm: expected a finite number > 0 (mm), got {size_mm!r}")
        f = float(size_mm) / float(self.size_mm)
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
        return dataclasses.replace(self, size_mm=float(size_mm), lights=tuple(lights), camera=camera,
                                   caustics=caustics)

    def mesh_source(self) -> str:
        """The mesh argument for :func:`~torchsss.geometry.loading.load_mesh`: a built-in name or a resolved path."""
        if self.mesh in builtin_mesh_names():
            return self.mesh
        path = Path(self.mesh)
        if not path.is_absolute():
            path = self.base_dir / path
        if not path.is_file():
            raise ValueError(f"scene.mesh: expected an existing file or one of {builtin_mesh_names()}, got {path}")
        return str(path)

    def load_mesh(self, dtype: torch.dtype = torch.float32) -> Mesh:
        """Load, clean, scale (and decimate) the scene's mesh."""
        return load_mesh(self.mesh_source(), self.size_mm, decimate_to=self.decimate, dtype=dtype)


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
