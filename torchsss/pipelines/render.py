"""Render a :class:`~torchsss.scene.Scene` with a named method.

This is the one entry point the CLI, tests and benchmarks share, so that every method is compared on exactly
the same input.

Methods register here as ``name -> function(scene, mesh, **options) -> RenderResult``. This issue ships
``"reference"``, ``"lensch"``, ``"icdf"``, ``"hybrid"``, ``"splat"`` and ``"caustics"``.

Scenes with several objects (``"objects"``, Shah 6.4.3) go to :data:`OBJECT_METHODS`
(``name -> function(scene, objects, **options)`` with ``objects`` the scene's ``(mesh, material)`` pairs):
``"reference"`` and ``"splat"``. The other methods render one object; a scene whose ``"objects"`` list has a single
entry still renders with them. Scenes with an environment light (``{"type": "environment", ...}`` in
``"lights"``) render with :data:`ENVIRONMENT_METHODS`: ``"reference"`` and ``"splat"``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch

from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.procedural import plane
from torchsss.pipelines.caustics import render_caustics
from torchsss.pipelines.chang import render_hybrid, render_icdf
from torchsss.pipelines.lensch import render_lensch
from torchsss.pipelines.reference import RenderResult, render_reference, render_reference_objects
from torchsss.pipelines.splat import render_splat, render_splat_objects
from torchsss.scene import Material, Scene

__all__ = ["ENVIRONMENT_METHODS", "METHODS", "OBJECT_METHODS", "render_scene"]


def _reference(scene: Scene, mesh: Mesh, **options) -> RenderResult:
    return render_reference(mesh, scene.material, scene.lights, scene.camera, **options)


def _lensch(scene: Scene, mesh: Mesh, **options) -> RenderResult:
    return render_lensch(mesh, scene.material, scene.lights, scene.camera, **options)


def _icdf(scene: Scene, mesh: Mesh, **options) -> RenderResult:
    return render_icdf(mesh, scene.material, scene.lights, scene.camera, **options)


def _hybrid(scene: Scene, mesh: Mesh, **options) -> RenderResult:
    return render_hybrid(mesh, scene.material, scene.lights, scene.camera, **options)


def _splat(scene: Scene, mesh: Mesh, **options) -> RenderResult:
    return render_splat(mesh, scene.material, scene.lights, scene.camera, **options)


def _caustics(scene: Scene, mesh: Mesh, *, dtype: torch.dtype = torch.float32, progress: bool = False,
              **options) -> RenderResult:
    """The scene's mesh refracts onto its ``"caustics"`` receiver plane (Shah ch. 5)."""
    c = scene.caustics
    if c is None:
        raise ValueError("scene.caustics: expected a \"caustics\" block in the scene for --method caustics, got none")
    if options.pop("specular", False):
        raise ValueError("specular: expected off for --method caustics (the refractor shows Fresnel reflection of "
                         "a uniform environment instead), got on")
    options.pop("roughness", None)
    size = c.receiver_size_mm
    receiver = plane(size, size, 1, dtype=dtype)
    receiver = dataclasses.replace(receiver, vertices=receiver.vertices + receiver.vertices.new_tensor(
        c.receiver_center))
    options.setdefault("resolution", c.grid)
    res = render_caustics(mesh, receiver, scene.lights, scene.camera, ior=c.ior, absorption=c.absorption,
                          mode=c.mode, albedo=c.albedo, **options)
    mask = res.receiver_mask | res.refractor_mask
    return RenderResult(res.radiance, res.direct + res.caustic, mask, dict(res.stats))


#: Rendering methods by name.
METHODS: dict[str, Callable[..., RenderResult]] = {"reference": _reference, "lensch": _lensch, "icdf": _icdf,
                                                   "hybrid": _hybrid, "caustics": _caustics, "splat": _splat}


def _reference_objects(scene: Scene, objects: list[tuple[Mesh, Material]], **options) -> RenderResult:
    return render_reference_objects(objects, scene.lights, scene.camera, **options)


def _splat_objects(scene: Scene, objects: list[tuple[Mesh, Material]], **options) -> RenderResult:
    return render_splat_objects(objects, scene.lights, scene.camera, **options)


#: Methods that render environment lights (Shah 6.4.2: order-2 SH, unshadowed, depth-peeled splat sources).
ENVIRONMENT_METHODS = frozenset({"reference", "splat"})

#: Methods that render a scene with several objects (``"objects"``), by name.
OBJECT_METHODS: dict[str, Callable[..., RenderResult]] = {"reference": _reference_objects, "splat": _splat_objects}


def render_scene(scene: Scene, method: str = "reference", *, dtype: torch.dtype = torch.float32,
                 **options) -> RenderResult:
    """Load the scene's mesh and render it with ``method`` (options go to the method).

    Examples:
        >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
        ...     "lights": [{"type": "directional", "direction": [0, 0, -1], "irradiance": 1.0}],
        ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 16, "height": 16}})
        >>> r = render_scene(s, "reference", spacing_mm=2.0)
        >>> tuple(r.radiance.shape), bool(r.radiance.max() > 0)
        ((1, 3, 16, 16), True)
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {sorted(METHODS)}, got {method!r}")
    if any(isinstance(light, EnvironmentLight) for light in scene.lights) and method not in ENVIRONMENT_METHODS:
        raise ValueError(f"method: expected one of {sorted(ENVIRONMENT_METHODS)} for a scene with an environment "
                         f"light, got {method!r}, which renders point, spot and directional lights only")
    if len(scene.objects) > 1:
        if method not in OBJECT_METHODS:
            raise ValueError(f"method: expected one of {sorted(OBJECT_METHODS)} for a scene with \"objects\" "
                             f"({len(scene.objects)} objects), got {method!r}, which renders one object")
        return OBJECT_METHODS[method](scene, scene.load_objects(dtype=dtype), dtype=dtype, **options)
    if scene.objects:
        (mesh, material), = scene.load_objects(dtype=dtype)
        return METHODS[method](dataclasses.replace(scene, material=material), mesh, dtype=dtype, **options)
    mesh = scene.load_mesh(dtype=dtype)
    return METHODS[method](scene, mesh, dtype=dtype, **options)
