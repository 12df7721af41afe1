"""Scene files -> methods: the one entry point the CLI, tests and benchmarks share.

``build_scene(scene, method, **knobs)`` loads the scene's mesh and builds the method's renderer
(:func:`torchsss.pipelines.build`), with the knobs a scene implies (the ``"caustics"`` block for the caustics
method); ``render_scene(scene, method, frames=N)`` builds once and renders ``N`` frames with the light orbiting
the object (:func:`orbit_lights`), so that the setup and the per-frame cost are measured apart.

Scenes with several objects (``"objects"``, Shah 6.4.3) render with :data:`OBJECT_METHODS` (``"reference"`` and
``"splat"``, whose functions take the scene's ``(mesh, material)`` pairs; their setup is part of every frame);
scenes with an environment light with :data:`ENVIRONMENT_METHODS`.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from collections.abc import Callable, Sequence

import torch

from torchsss._checks import check_device
from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.lights import DirectionalLight, Light
from torchsss.geometry.mesh import Mesh
from torchsss.pipelines import (
    RENDERERS,
    Renderer,
    RenderResult,
    build,
    render_reference_objects,
    render_splat_objects,
)
from torchsss.pipelines.renderer import box_downsample, supersample_camera
from torchsss.scene import Scene

__all__ = ["ENVIRONMENT_METHODS", "METHODS", "OBJECT_METHODS", "build_scene", "orbit_lights",
           "render_scene", "scene_knobs"]

#: Every method, by name (the renderer classes of :func:`torchsss.pipelines.build`).
METHODS = RENDERERS

#: Methods that render environment lights (Shah 6.4.2: order-2 SH, unshadowed, depth-peeled splat sources).
ENVIRONMENT_METHODS = frozenset({"reference", "splat"})

#: Methods that render a scene with several objects (``"objects"``), by name.
OBJECT_METHODS: dict[str, Callable[..., RenderResult]] = {"reference": render_reference_objects,
                                                           "splat": render_splat_objects}


def scene_knobs(scene: Scene, method: str) -> dict:
    """The knobs a scene implies for ``method``: the ``"caustics"`` block for ``"caustics"``, none otherwise.

    Raises:
        ValueError: ``"caustics"`` for a scene without a caustics block.
    """
    if method != "caustics":
        return {}
    c = scene.caustics
    if c is None:
        raise ValueError("scene.caustics: expected a \"caustics\" block in the scene for --method caustics, got none")
    return dict(ior=c.ior, absorption=c.absorption, mode=c.mode, receiver_size_mm=c.receiver_size_mm,
                receiver_center=c.receiver_center, albedo=c.albedo, grid=c.grid)


def _check_method(scene: Scene, method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"method: expected one of {sorted(METHODS)}, got {method!r}")
    if any(isinstance(light, EnvironmentLight) for light in scene.lights) and method not in ENVIRONMENT_METHODS:
        raise ValueError(f"method: expected one of {sorted(ENVIRONMENT_METHODS)} for a scene with an environment "
                         f"light, got {method!r}, which renders point, spot and directional lights only")
    if len(scene.objects) > 1 and method not in OBJECT_METHODS:
        raise ValueError(f"method: expected one of {sorted(OBJECT_METHODS)} for a scene with \"objects\" "
                         f"({len(scene.objects)} objects), got {method!r}, which renders one object")


def _single(scene: Scene, dtype: torch.dtype) -> tuple[Mesh, object]:
    if scene.objects:
        (mesh, material), = scene.load_objects(dtype=dtype)
        return mesh, material
    return scene.load_mesh(dtype=dtype), scene.material


def build_scene(scene: Scene, method: str = "reference", *, dtype: torch.dtype = torch.float32,
                device: str | torch.device = "cpu", **knobs) -> Renderer:
    """Load a single-object scene's mesh and build ``method``'s renderer (knobs override the scene's).

    ``device``: where the renderer is built and renders (its mesh's device; the CPU-only setup steps, xatlas,
    embree and scipy, run on CPU copies); :func:`check_device`.

    Examples:
        >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
        ...     "lights": [{"type": "directional", "direction": [0, 0, -1], "irradiance": 1.0}],
        ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 16, "height": 16}})
        >>> r = build_scene(s, "reference", spacing_mm=2.0)
        >>> r.render(s.lights, s.camera).radiance.shape
        torch.Size([1, 3, 16, 16])
    """
    _check_method(scene, method)
    if len(scene.objects) > 1:
        raise ValueError(f"scene: expected a single-object scene for build_scene, got {len(scene.objects)} objects "
                         "(render it with render_scene)")
    dev = check_device(device)
    mesh, material = _single(scene, dtype)
    knobs = {**scene_knobs(scene, method), **knobs}
    return build(method, mesh.with_device(dev), None if method == "caustics" else material, dtype=dtype, **knobs)


def orbit_lights(lights: Sequence[Light], frame: int, frames: int, *, centre: Sequence[float] = (0.0, 0.0, 0.0),
                 axis: Sequence[float] = (0.0, 1.0, 0.0)) -> list[Light]:
    """The lights of frame ``frame`` of ``frames``, rotated by :math:`2\\pi \\cdot` frame / frames about ``axis``.

    Point and spot lights move on a circle around ``centre`` (mm); directional lights turn; environment lights
    stay. Frame 0 is the scene's own lighting.

    Examples:
        >>> from torchsss.geometry import PointLight
        >>> [tuple(round(v, 6) for v in orbit_lights([PointLight((10, 0, 0), 1.0)], i, 4)[0].position)
        ...  for i in range(2)]
        [(10.0, 0.0, 0.0), (0.0, 0.0, -10.0)]
    """
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ValueError(f"frames: expected an int >= 1, got {frames!r}")
    angle = 2.0 * math.pi * frame / frames
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    k = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=torch.float64)
    rot = torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)
    c = torch.tensor(centre, dtype=torch.float64)

    def turn(v: Sequence[float], about: torch.Tensor) -> tuple[float, ...]:
        return tuple(float(x) for x in rot @ (torch.tensor(v, dtype=torch.float64) - about) + about)

    out = []
    for light in lights:
        if isinstance(light, DirectionalLight):
            light = dataclasses.replace(light, direction=turn(light.direction, torch.zeros(3, dtype=torch.float64)))
        elif hasattr(light, "position"):
            changes = {"position": turn(light.position, c)}
            if hasattr(light, "direction"):
                changes["direction"] = turn(light.direction, torch.zeros(3, dtype=torch.float64))
            light = dataclasses.replace(light, **changes)
        out.append(light)
    return out


def render_scene(scene: Scene, method: str = "reference", *, dtype: torch.dtype = torch.float32, frames: int = 1,
                 progress: bool = False, spp: int = 1, subpixel: str = "exact", device: str | torch.device = "cpu",
                 **knobs) -> RenderResult:
    """Render ``scene`` with ``method``: build once, then ``frames`` frames with the lights orbiting the object.

    ``device`` (:func:`build_scene`): a single-object scene renders there and the result's tensors stay there;
    a scene of several objects renders on the CPU only.

    ``spp`` (a square) renders each frame on a finer pixel grid and box-filters it back
    (:meth:`~torchsss.pipelines.Renderer.render`, ``subpixel`` as there; several objects: ``"exact"`` only): the
    pixel-integrated image.

    Returns the first frame's result (the scene's own lighting); its ``stats`` hold ``setup_s``, ``frame_s`` (a list
    with one time per frame), ``frame_median_s``, ``fps`` and the ``knobs``.

    Examples:
        >>> s = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
        ...     "lights": [{"type": "directional", "direction": [0, 0, -1], "irradiance": 1.0}],
        ...     "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 16, "height": 16}})
        >>> r = render_scene(s, "reference", spacing_mm=2.0, frames=2)
        >>> tuple(r.radiance.shape), len(r.stats["frame_s"])
        ((1, 3, 16, 16), 2)
    """
    _check_method(scene, method)
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ValueError(f"frames: expected an int >= 1, got {frames!r}")
    fine, factor = supersample_camera(scene.camera, spp)
    if len(scene.objects) > 1 and subpixel != "exact" and factor > 1:
        raise ValueError(f"subpixel: expected 'exact' for a scene of several objects, got {subpixel!r}")
    first: RenderResult | None = None
    times: list[float] = []
    if len(scene.objects) > 1:
        if check_device(device).type != "cpu":
            raise ValueError(f"device: expected 'cpu' for a scene of several objects, got {device!r}")
        objects = scene.load_objects(dtype=dtype)
        setup_s = 0.0
        for i in range(frames):
            t0 = time.perf_counter()
            res = box_downsample(OBJECT_METHODS[method](objects, orbit_lights(scene.lights, i, frames), fine,
                                                        dtype=dtype, progress=progress, **knobs), factor)
            times.append(time.perf_counter() - t0)
            first = first or res
        assert first is not None
        first.stats.update(method=method, knobs=dict(knobs))
    else:
        t0 = time.perf_counter()
        renderer = build_scene(scene, method, dtype=dtype, progress=progress, device=device, **knobs)
        setup_s = time.perf_counter() - t0
        mesh = renderer.mesh
        centre = tuple(float(v) for v in (mesh.vertices.amax(0) + mesh.vertices.amin(0)) / 2)
        for i in range(frames):
            res = renderer.render(orbit_lights(scene.lights, i, frames, centre=centre, axis=scene.camera.up),
                                  scene.camera, spp=spp, subpixel=subpixel)
            times.append(res.stats["frame_s"])
            first = first or res
        assert first is not None
    median = statistics.median(times)
    first.stats.update(setup_s=setup_s, frame_s=times, frame_median_s=median, frames=frames, spp=factor * factor,
                       fps=1.0 / median if median > 0 else math.inf)
    return first
