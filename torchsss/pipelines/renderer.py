"""The one shape every method shares: build once (:class:`Renderer`), render frames (:meth:`Renderer.render`).

A renderer is built for one mesh and one material with its knobs; the constructor does all the setup that does
not depend on the lights or the camera (atlas, kernels, throughput, tables, budgets, surface samples) and
records its time as ``setup_s``; :meth:`Renderer.render` renders one frame for given lights and camera and
returns a :class:`RenderResult` whose ``stats`` hold ``setup_s``, ``frame_s`` (this frame), ``method`` and the
``knobs``. The material is held as a profile module (:func:`~torchsss.modules.material_module`): its ``eta`` is
read every frame for the Fresnel terms of the irradiance and of the exit radiance, so editing it (or a gradient
step on it) changes the whole image consistently, and its other parameters change ``R_d`` without a rebuild
(rebuild after large material changes, where the knobs planned from the material, such as the splat budget,
the throughput pattern or the reference's sample spacing, no longer fit).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import camera_gbuffer, view_cosine
from torchsss.geometry.lights import DirectionalLight, Light, PointLight, SpotLight
from torchsss.geometry.mesh import Mesh
from torchsss.modules.cache import material_key
from torchsss.modules.material import material_module
from torchsss.physics.fresnel import exit_radiance
from torchsss.physics.materials import Material
from torchsss.pipelines.atlas_view import AtlasView
from torchsss.pipelines.subpixel import upsample_radiosity

__all__ = ["RenderResult", "Renderer", "box_downsample", "check_dtype", "check_lights", "check_objects",
           "supersample_camera"]


@dataclass
class RenderResult:
    """A rendered image and what it took.

    Attributes:
        radiance: :math:`(1, 3, H, W)` linear outgoing radiance :math:`L = F_t/\\pi \\, B` (0 on background).
        radiosity: :math:`(1, 3, H, W)` :math:`B` at the covered pixels.
        mask: :math:`(1, 1, H, W)` bool, pixels that see the object.
        stats: timings (s) and sizes; from a :class:`Renderer` also ``method``, ``setup_s``, ``frame_s``, ``knobs``.
    """

    radiance: Tensor
    radiosity: Tensor
    mask: Tensor
    stats: dict = field(default_factory=dict)


def _plain_light(light: object) -> bool:
    """A point, spot or directional light whose fields hold numbers only (values that cannot change in place)."""
    if not isinstance(light, (PointLight, DirectionalLight, SpotLight)):
        return False
    for f in dataclasses.fields(light):
        value = getattr(light, f.name)
        items = value if isinstance(value, (tuple, list)) else (value,)
        if not all(isinstance(x, (int, float, str, bool)) or x is None for x in items):
            return False
    return True


def supersample_camera(camera: Camera, spp: object) -> tuple[Camera, int]:
    """The camera on a :math:`\\sqrt{spp}`-times finer pixel grid (same view) and the factor :math:`s`.

    Raises:
        TypeError: ``spp`` not an int.
        ValueError: ``spp`` not a perfect square >= 1.

    Examples:
        >>> cam = Camera(eye=(0, 0, 50), target=(0, 0, 0), width=8, height=6)
        >>> fine, s = supersample_camera(cam, 4)
        >>> (fine.width, fine.height, s)
        (16, 12, 2)
    """
    if isinstance(spp, bool) or not isinstance(spp, int):
        raise TypeError(f"spp: expected an int (a square: 1, 4, 9, 16, ...), got {type(spp).__name__}")
    s = math.isqrt(spp) if spp >= 1 else 0
    if spp < 1 or s * s != spp:
        raise ValueError(f"spp: expected a square >= 1 (1, 4, 9, 16, ...: an s x s grid per pixel), got {spp}")
    if s == 1:
        return camera, 1
    return dataclasses.replace(camera, width=camera.width * s, height=camera.height * s), s


def box_downsample(result: RenderResult, factor: int) -> RenderResult:
    """Box-filter a render on a ``factor``-times finer grid back to the camera's pixels.

    Radiance and radiosity are averaged over the :math:`s \\times s` sub-pixels (uncovered ones count as 0, so an
    edge pixel holds the covered fraction of the light, the pixel integral); the mask is True where any sub-pixel
    sees the object.
    """
    if factor == 1:
        return result
    down = {k: F.avg_pool2d(getattr(result, k), factor) for k in ("radiance", "radiosity")}
    mask = F.max_pool2d(result.mask.to(down["radiance"].dtype), factor) > 0
    return RenderResult(radiance=down["radiance"], radiosity=down["radiosity"], mask=mask, stats=dict(result.stats))


def check_dtype(dtype: object) -> torch.dtype:
    """float32 or float64, else TypeError naming ``dtype``."""
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
    return dtype  # type: ignore[return-value]


def check_lights(lights: object) -> list[Light]:
    """A non-empty list of lights (a single light is wrapped), else ValueError naming ``lights``."""
    if isinstance(lights, Sequence) and not isinstance(lights, (str, bytes)):
        out = list(lights)
    else:
        out = [lights]
    if not out:
        raise ValueError("lights: expected at least one light, got none")
    return out  # type: ignore[return-value]


def check_objects(objects: object) -> list[tuple[Mesh, Material | nn.Module]]:
    """Validate a list of ``(mesh, material)`` pairs (the multi-object renderers' input); returns it as a list.

    A material is a :class:`~torchsss.physics.Material` record or a profile module.
    """
    if not isinstance(objects, Sequence) or isinstance(objects, (str, Mesh)) or len(objects) == 0:
        raise ValueError(f"objects: expected a non-empty list of (Mesh, Material) pairs, got {objects!r}")
    out = []
    for i, item in enumerate(objects):
        if not (isinstance(item, Sequence) and len(item) == 2 and isinstance(item[0], Mesh)
                and isinstance(item[1], (Material, nn.Module))):
            raise TypeError(f"objects[{i}]: expected a (Mesh, Material) pair, got {type(item).__name__}")
        out.append((item[0], item[1]))
    return out


class Renderer:
    """Base of every method's renderer: build once in the constructor, then :meth:`render` frames.

    Subclasses set :attr:`method`, implement :meth:`_build` (the setup, may use ``self.mesh``,
    ``self.material``, ``self.knobs``) and :meth:`_render` (one frame), and list their knobs with defaults in
    :attr:`defaults`. Unknown knobs are an error (a typo must not be silently ignored).

    Attributes:
        method: the method's name (``"reference"``, ``"lensch"``, ...).
        mesh: the object (mm), in the renderer's dtype.
        device: the mesh's device, where the material module, the built buffers and every frame's tensors live
            (setup steps that only exist on the CPU, such as the xatlas atlas, the embree ray casts or the
            decimation, run on CPU copies and move their results here).
        material: the profile module (its parameters receive gradients when ``differentiable``), on ``device``
            (a given module is moved there, as ``nn.Module.to`` does).
        knobs: every knob's value (the defaults completed by what was given), JSON-serialisable.
        setup_s: seconds the constructor took.
    """

    method = "base"
    #: whether the method renders a translucent material (caustics' glass is described by its knobs instead).
    needs_material = True
    #: knob -> default; subclasses extend it.
    defaults: ClassVar[dict] = {}
    #: the Fresnel model of the exit radiance (the reference's ``fresnel`` knob sets its own).
    fresnel: str = "exact"
    #: keep what depends on the lights and the material alone for the next frame with the same lights
    #: (:meth:`_per_lights`: a frame whose camera alone moved skips it); False recomputes it every frame (benchmarks
    #: that time relit frames by rendering the same lights again).
    reuse_lights: bool = True

    def __init__(self, mesh: Mesh, material: Material | str | nn.Module | None, *, dtype: torch.dtype = torch.float32,
                 differentiable: bool = False, progress: bool = False, **knobs) -> None:
        t0 = time.perf_counter()
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh: expected a torchsss Mesh, got {type(mesh).__name__}")
        unknown = set(knobs) - set(self.defaults)
        if unknown:
            raise ValueError(f"{sorted(unknown)[0]}: expected a knob of method {self.method!r} "
                             f"({', '.join(sorted(self.defaults))}), got an unknown one")
        self.dtype = check_dtype(dtype)
        self.differentiable = bool(differentiable)
        self.progress = bool(progress)
        self.knobs = {**self.defaults, **knobs}
        self.mesh = mesh.with_dtype(self.dtype)
        self.device = self.mesh.vertices.device
        self.material = None if material is None and not self.needs_material else \
            material_module(material, dtype=None if isinstance(material, nn.Module) else self.dtype,
                            device=self.device)
        self._supersample = 1
        self._build()
        self.setup_s = time.perf_counter() - t0

    @classmethod
    def from_built(cls, built, **knobs) -> Renderer:
        """A renderer around an existing build result (``mesh``, ``atlas``, ``module``, ``stats``): no new setup.

        For the atlas methods' ``build_*`` functions (``build_lensch``, ``build_icdf``, ``build_hybrid``).
        """
        self = cls.__new__(cls)
        self.dtype = built.mesh.vertices.dtype
        self.differentiable = False
        self.progress = False
        self.knobs = {**cls.defaults, **knobs}
        self.mesh, self.built, self.atlas, self.module = built.mesh, built, built.atlas, built.module
        self.source_mesh = built.mesh
        self._supersample = 1
        self.view = AtlasView(built.mesh, built.mesh, built.atlas)
        self.device = built.mesh.vertices.device
        self.material = built.module.material
        self.setup_s = float(built.stats.get("t_precompute_s", 0.0))
        return self

    @property
    def eta(self) -> Tensor:
        """The material module's relative index of refraction (the one home of eta), read every frame."""
        if self.material is None:
            raise ValueError(f"material: expected a translucent material for eta, got None (method {self.method!r})")
        return self.material.eta

    def _build(self) -> None:
        """The setup (subclasses)."""

    def _per_lights(self, name: str, lights: Sequence[Light], compute: Callable[[], object],
                    extra: tuple = ()) -> tuple[object, bool]:
        """``compute()``, kept for the last lights it was computed for: ``(value, reused)``.

        For what depends on the lights, the material and the build alone (the atlas methods' irradiance atlas,
        Lensch's radiosity atlas, the splats of the light views), so that a frame whose camera alone moved skips
        it. Reused only for the same point, spot and directional lights given by numbers (equal values; a light
        holding a tensor, e.g. a differentiable intensity, can change in place and is never reused), the same
        material (:func:`material_key`: its parameters' storage and versions, so an in-place edit or an optimiser
        step counts as a change), the same ``extra`` (knobs the value depends on), and never while autograd records
        (there ``material_key`` is None).
        """
        if not self.reuse_lights or not all(_plain_light(light) for light in lights):
            self.__dict__.pop("_lights_cache", None)
            return compute(), False
        mat = () if self.material is None else material_key(self.material)
        if mat is None:
            return compute(), False
        try:
            key = (tuple(lights), mat, extra)
            hash(key)
        except TypeError:  # a light given with list-valued fields: not reused
            return compute(), False
        cache = self.__dict__.setdefault("_lights_cache", {})
        hit = cache.get(name)
        if hit is not None and hit[0] == key:
            return hit[1], True
        cache.pop(name, None)  # the old value is released before the new one is computed
        value = compute()
        cache[name] = (key, value)
        return value, False

    def _render(self, lights: list[Light], camera: Camera) -> RenderResult:
        raise NotImplementedError

    def render(self, lights: Light | Sequence[Light], camera: Camera, *, spp: int = 1,
               subpixel: str = "exact") -> RenderResult:
        """Render one frame; ``stats`` gain ``method``, ``setup_s``, ``frame_s``, ``knobs`` and ``spp``.

        Args:
            lights: one light or a sequence of them (point, spot, directional; environment where supported).
            camera: the viewing camera (its resolution is the image's).
            spp: samples per pixel, a square (1, 4, 9, 16, ...): the frame is rendered on an
                :math:`\\sqrt{spp}`-times finer pixel grid (a stratified sub-pixel grid) and box-filtered back
                (:func:`supersample_camera`, :func:`box_downsample`), so edges and shadow terminators are
                pixel-integrated, as an independent reference or a path tracer produces them.
            subpixel: with ``spp`` > 1, ``"exact"`` (default) renders the method on the finer grid (up to ``spp``
                times the cost; the reference and the Chang methods evaluate :math:`B` about once per pixel where
                the surface is smooth); ``"upsample"`` renders :math:`B` once per pixel and upsamples it to the
                sub-pixels edge-aware, with each sub-pixel's own coverage and exit cosine
                (:mod:`torchsss.pipelines.subpixel`: the cost of one sub-pixel G-buffer; translucent methods without
                ``specular``).

        Returns:
            A :class:`RenderResult` (tensors of shape :math:`(1, 3, H, W)` and a :math:`(1, 1, H, W)` mask).
        """
        if not isinstance(camera, Camera):
            raise TypeError(f"camera: expected a Camera, got {type(camera).__name__}")
        lights = check_lights(lights)
        fine, factor = supersample_camera(camera, spp)
        if subpixel not in ("exact", "upsample"):
            raise ValueError(f"subpixel: expected 'exact' or 'upsample', got {subpixel!r}")
        upsample = subpixel == "upsample" and factor > 1
        if upsample and (not self.needs_material or self.knobs.get("specular")):
            raise ValueError(f"subpixel: expected 'exact' for {self.method!r}"
                             f"{' with specular' if self.needs_material else ''} (upsampling forms the exit "
                             f"radiance from the translucent radiosity alone), got 'upsample'")
        # a method may evaluate smooth parts of the fine grid more coarsely
        self._supersample = 1 if upsample else factor
        t0 = time.perf_counter()
        with torch.set_grad_enabled(self.differentiable and torch.is_grad_enabled()):
            if upsample:
                result = box_downsample(self._upsampled(lights, camera, fine, factor), factor)
            else:
                result = box_downsample(self._render(lights, fine), factor)
        frame_s = time.perf_counter() - t0
        result.stats.update(method=self.method, setup_s=self.setup_s, frame_s=frame_s, knobs=dict(self.knobs),
                            spp=factor * factor, subpixel=subpixel if factor > 1 else "none")
        return result

    def _upsampled(self, lights: list[Light], camera: Camera, fine: Camera, factor: int) -> RenderResult:
        """One frame at the pixels, its radiosity upsampled to the ``fine`` grid (:mod:`~.subpixel`)."""
        pixel = self._render(lights, camera)
        t0 = time.perf_counter()
        subpixels = camera_gbuffer(self.mesh, fine)
        b = upsample_radiosity(pixel.radiosity, camera_gbuffer(self.mesh, camera), subpixels, factor)
        radiance = exit_radiance(b, view_cosine(subpixels), self.eta, self.fresnel)
        stats = dict(pixel.stats, t_subpixel_s=time.perf_counter() - t0)
        return RenderResult(radiance * subpixels.mask, b, subpixels.mask, stats)

    def __repr__(self) -> str:
        knobs = ", ".join(f"{k}={v!r}" for k, v in self.knobs.items())
        return f"{type(self).__name__}({self.mesh.num_faces} faces, {knobs}; setup {self.setup_s:.2f} s)"
