"""Render with Shah's image-space splatting (ch. 6): light-view samples splatted onto the camera view.

Per frame and per light: the light-view G-buffer (:func:`~torchsss.geometry.gbuffer.light_view`, positions and
:math:`E\\,dA` with Fresnel, cosine and distance falloff) at a resolution from the splat budget, then
:class:`~torchsss.modules.splat.SplatTranslucency` onto the camera G-buffer, :math:`L = F_t/\\pi\\,B`. Nothing is
precomputed, so the mesh may change every frame.

Budget: the light view's pixels are the splats, so their spacing on the object, :math:`2R/n` for a light view
of :math:`n \\times n` pixels spanning the bounding sphere's diameter :math:`2R`, must not exceed the splat
spacing :math:`h(\\epsilon)` of :func:`~torchsss.physics.splat_spacing` (the sampling criterion that replaces the
literal eq. 6.17), oversampled by a factor ``oversample`` because the light view's pixels land farther apart on
surfaces inclined to the light: :math:`n = \\lceil s \\cdot 2R / h \\rceil`, capped at ``max_grid``. Measured on the
default scene (spot 40 mm, skin1, 64 x 64, eps 0.01) against the reference: relative RMSE 5.8% at s = 1
(grid 56), 2.6% at s = 2 (grid 112, the default), 2.1% at s = 4 and 2.2% at s = 8 (the floor of the r_max
truncation and the light-view sampling); 0.2 s, 0.2 s, 0.8 s and 3.1 s per frame. Under grazing light a pixel
stands for a strip :math:`1/\\cos\\theta` texels long; strips longer than ``max_stretch`` (4) texels are cut into
pieces along the surface (:func:`~torchsss.geometry.grazing.split_grazing`): a 25 mm cream slab whose front face the
light meets at 5.5° went from stripes ten texels apart, 10.4% against the reference at 128 x 128, to 2.7% (2.3x the
splats); on 17 other verification scenes the error moved by at most 0.1 point at 5-15% more splats.

Several objects of different materials (:func:`render_splat_objects`, Shah 6.4.3) are splatted in one pass: the
merged mesh (:func:`~torchsss.geometry.objects.merge_meshes`) is seen from every light (so the objects occlude
each other), every splat takes its object id and its row of the material table from the light view's face id,
every camera pixel its object id from the camera G-buffer's face id, and a splat lights only the pixels of its own
object (Shah's object-id clipping). The grid is the budget of the most demanding material over the merged
bounding sphere.

Environment lighting (Shah 6.4.2): an :class:`~torchsss.geometry.environment.EnvironmentLight` (order-2 SH) lights
every surface point, so its splats are the depth-peeled fragments of orthographic views along the three axes
(:func:`~torchsss.geometry.peel.environment_splats`, layers until empty or ``peel_layers``; each fragment's area
is weighted by :math:`n_k^2`, a partition of unity, so no grazing blow-up), with the unshadowed SH irradiance of
the Fresnel-cosine lobe. The view resolution is the same budget grid.

Heterogeneous materials (Shah eq. 7.4): per-vertex ``distance_scale`` :math:`M_d` and ``irradiance_scale``
:math:`M_i` are interpolated at every splat's source point (face id and barycentrics of the light view) and modify
its profile :math:`M_i R_d(r M_d)`.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor, nn

from torchsss.geometry.camera import Camera
from torchsss.geometry.coverage import coverage_scale
from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.gbuffer import camera_gbuffer, light_view, view_cosine
from torchsss.geometry.grazing import split_grazing
from torchsss.geometry.lights import Light, incident_light
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.objects import merge_meshes, object_ids, object_masks
from torchsss.geometry.peel import environment_splats
from torchsss.geometry.shading_flux import shading_flux_scale
from torchsss.geometry.shadow import bounding_sphere
from torchsss.modules.material import material_module
from torchsss.modules.splat import SplatTranslucency
from torchsss.physics.fresnel import exit_radiance
from torchsss.physics.materials import Material
from torchsss.pipelines.modifiers import at_sources, vertex_modifiers
from torchsss.pipelines.renderer import Renderer, RenderResult, check_lights, check_objects
from torchsss.pipelines.specular import shadow_mapped_specular

__all__ = ["SplatRenderer", "grid_for", "light_sources", "render_splat", "render_splat_objects", "splat_grid"]


@functools.lru_cache(maxsize=256)
def _record_spacing(material: Material, eps: float) -> float:
    """The smallest channel's spacing h(eps) in mm of a record, cached: the bisection costs 0.1-2 s."""
    return float(material_module(material, dtype=torch.float64).spacing(eps).min())


def _spacing(material: Material | nn.Module, eps: float) -> float:
    if isinstance(material, Material):
        return _record_spacing(material, float(eps))
    return float(material.spacing(eps).min())


#: The coarsest light view at ``oversample`` 1, in texels across the object (:func:`splat_grid` holds at least
#: ``oversample`` times this many): the irradiance (n.l, shadows) varies on the object's own scale however smooth the
#: profile is. A 5 mm chicken1 bunny (scattering length > the object) got 5-13 texels from the budget and measured
#: 5-14% against the reference at 128x128; 16 texels 1.1%, 32 0.86%. Where the profile's spacing asks for fewer
#: texels than this the light view samples the irradiance, not the profile, and ``oversample`` refines that as well
#: (since 2026-11-29; a fixed 32 had made the error of small or long-scattering objects a floor that no oversampling
#: moved): at eps 0.01, grid 32 / 64 / 128 / 256, a side-lit 8 mm potato torus measured 1.92 / 0.93 / 0.53 / 0.30%,
#: a side-lit 30 mm chicken1 teapot 1.78 / 0.59 / 0.49 / 0.33% and a front-lit 10 mm skin1 igea 0.94 / 0.50 / 0.34 /
#: 0.36% (``benchmarks/results/splat_calibration.md``).
MIN_GRID = 32

#: The longest light-view footprint (texels) one splat stands for (:func:`~torchsss.geometry.grazing.split_grazing`):
#: the budget's ``oversample`` 2 assumes 2; 4 keeps most of the gain under grazing light at a fraction of the splats.
MAX_STRETCH = 4.0
#: The coverage correction (``coverage=True``) rescales only faces the light meets at most 60 degrees from their
#: normal: at a smooth object's grazing silhouette it measured worse (the back-lit 15 mm apple torus 0.72% -> 1.32%),
#: where a rim lit face-on (the side-lit 25 mm cream slab) gains most.
COVERAGE_MIN_COS = 0.5
_LIGHT_VIEW_MIN_COS = 1e-2  # light_view's default min_cos: its area is footprint / max(cos, this)


def splat_grid(mesh: Mesh, material: Material | nn.Module | Sequence[Material | nn.Module], eps: float = 0.01,
               max_grid: int = 512, oversample: float = 2.0, min_grid: int = MIN_GRID) -> int:
    """Light-view resolution :math:`n = \\lceil s \\cdot \\max(2R / h(\\epsilon), n_0) \\rceil` (module docstring).

    ``s`` is ``oversample``, :math:`n_0` ``min_grid`` (:data:`MIN_GRID`: the texels across the object that sample
    the irradiance itself where the profile's spacing asks for fewer); at most ``max_grid``.

    With several materials (a multi-object scene, ``mesh`` the merged mesh), :math:`h` is the smallest splat
    spacing of all of them: the most demanding material sets the budget.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> m = sphere(10.0, 2)
        >>> a, b = Material.from_json("marble"), Material.from_json("skin1")
        >>> splat_grid(m, [a, b]) == max(splat_grid(m, a), splat_grid(m, b))
        True
    """
    if isinstance(max_grid, bool) or not isinstance(max_grid, int) or max_grid < 2:
        raise ValueError(f"max_grid: expected an int >= 2, got {max_grid!r}")
    if isinstance(min_grid, bool) or not isinstance(min_grid, int) or min_grid < 1:
        raise ValueError(f"min_grid: expected an int >= 1, got {min_grid!r}")
    if not (isinstance(oversample, (int, float)) and 0 < oversample < math.inf):
        raise ValueError(f"oversample: expected a positive number, got {oversample!r}")
    materials = [material] if isinstance(material, (Material, nn.Module)) else list(material)
    if not materials or not all(isinstance(m, (Material, nn.Module)) for m in materials):
        raise TypeError(f"material: expected a Material, a profile module or a non-empty list of them, got "
                        f"{material!r}")
    h = min(_spacing(mat, eps) for mat in materials)
    _, radius = bounding_sphere(mesh)
    return grid_for(2.0 * float(radius), h, oversample, max_grid, min_grid)


def grid_for(diameter_mm: float, spacing_mm: float, oversample: float = 2.0, max_grid: int = 512,
             min_grid: int = MIN_GRID) -> int:
    """:func:`splat_grid`'s rule from the numbers alone (the planner predicts with it).

    Texels across an object of ``diameter_mm`` for splats ``spacing_mm`` apart,
    :math:`\\lceil s \\max(D / h, n_0) \\rceil` in :math:`[2, \\text{max\\_grid}]`.
    Arguments are trusted (:func:`splat_grid` checks its own).

    Examples:
        >>> grid_for(10.0, 1.0, oversample=1.0), grid_for(10.0, 1.0), grid_for(100.0, 1.0), grid_for(1e4, 1.0)
        (32, 64, 200, 512)
    """
    return int(min(max_grid, max(2, math.ceil(oversample * max(diameter_mm / spacing_mm, float(min_grid))))))


def light_sources(mesh: Mesh, light: Light, n: int, eta: float, peel_layers: int,
                   max_stretch: float | None = MAX_STRETCH, coverage: bool = True,
                   flux: str = "shading") -> tuple[Tensor, ...]:
    """Splat sources of one light: position (S, 3), flux (S, 3), face id (S,), barycentrics (S, 3).

    A point, spot or directional light: the lit pixels of its light view (with ``flux="shading"`` their flux in the
    shading normals' convention, :func:`~torchsss.geometry.shading_flux.shading_flux_scale`; with ``coverage``, the
    silhouette pixels of each unoccluded run of faces the light meets within 60 degrees rescaled to the run's exact
    projected area, :func:`~torchsss.geometry.coverage.coverage_scale`), each cut into pieces no longer than
    ``max_stretch`` texels where the light grazes its face (:func:`~torchsss.geometry.grazing.split_grazing`; None:
    uncut). An environment: the depth-peeled fragments of
    the three axis views.
    """
    if isinstance(light, EnvironmentLight):
        es = environment_splats(mesh, light, n, eta, max_layers=peel_layers)
        return es.position[0], es.flux[0], es.face_id, es.bary
    lv = light_view(mesh, light, n, eta)
    if flux == "shading":
        lv = lv._replace(flux=lv.flux * shading_flux_scale(lv, mesh, light).to(lv.flux.dtype))
    if coverage:
        centroid = mesh.triangles().mean(1).unsqueeze(0)
        facing = (mesh.face_normals * incident_light(light, centroid)[0][0]).sum(-1) >= COVERAGE_MIN_COS
        scale = coverage_scale(mesh, lv.face_id, lv.camera.view_proj(dtype=torch.float64, device=lv.flux.device),
                               faces=facing)
        lv = lv._replace(flux=lv.flux * scale.to(lv.flux.dtype))
    sel = lv.mask[0, 0]
    fid, bary = lv.face_id[0, 0][sel], lv.bary[0].permute(1, 2, 0)[sel]
    if max_stretch is None:
        return lv.position[0].permute(1, 2, 0)[sel], lv.flux[0].permute(1, 2, 0)[sel], fid, bary
    h, w = sel.shape
    to_light = incident_light(light, lv.position.flatten(2).transpose(1, 2))[0]  # (1, HW, 3)
    to_light = to_light.transpose(1, 2).reshape(1, 3, h, w)
    cos = (lv.normal * to_light).sum(1, keepdim=True)
    texel = (lv.area * cos.clamp_min(_LIGHT_VIEW_MIN_COS)).clamp_min(0.0).sqrt()  # the footprint's side across the ray
    corners = mesh.triangles()[lv.face_id[0, 0].clamp_min(0)].reshape(h, w, 9).permute(2, 0, 1).unsqueeze(0)
    view_proj = lv.camera.view_proj(dtype=lv.position.dtype, device=lv.position.device)
    pos, flux, index = split_grazing(lv.position, lv.mask, lv.flux, corners.to(lv.position.dtype), to_light, texel,
                                     view_proj, max_stretch=max_stretch)
    return pos, flux, fid[index], bary[index]


class SplatRenderer(Renderer):
    """Shah's image-space splatting (module docstring): the budget and the module once, splat every frame.

    Setup: the light-view grid from the splat budget (:func:`splat_grid`) and the
    :class:`~torchsss.modules.splat.SplatTranslucency` module (its :math:`r_{max}`); nothing depends on the mesh's
    pose, so a deforming mesh may be given per frame (:meth:`render` takes an optional ``mesh``).

    Knobs:
        eps: splat budget tolerance (r_max and the splat spacing).
        grid: light-view resolution (None: :func:`splat_grid`).
        max_grid: cap of the automatic grid.
        oversample: factor on the budget's grid, and on its floor :data:`MIN_GRID` (texels across the object:
            a small or long-scattering object's light view refines with it too).
        max_stretch: the longest light-view footprint, in texels, one splat stands for (:data:`MAX_STRETCH`); longer
            ones (grazing light) are cut into pieces (:func:`~torchsss.geometry.grazing.split_grazing`). None: uncut,
            Shah's one splat per light-view pixel.
        coverage: rescale the light view's silhouette splats so that each unoccluded run of faces the light meets
            within 60 degrees carries its exact projected area (:func:`~torchsss.geometry.coverage.coverage_scale`):
            a thin lit feature is otherwise counted a light-view row too wide or too narrow (the rim-lit 25 mm cream
            slab 3.56% -> 1.53%). False: each pixel's own footprint, Shah's splats.
        flux: ``"shading"``: each light-view pixel carries the flux the reference's surface samples receive, the
            irradiance at the interpolated shading normal over the surface it covers
            (:func:`~torchsss.geometry.shading_flux.shading_flux_scale`; on the 30 scenes of the planner's splat
            calibration the median error at eps 0.003, oversample 4 fell from 1.02% to 0.56%, on the 40k-face igea
            scans from 1.2-1.5% to 0.5%). ``"facet"``: the light crossing its footprint, the face's own cosine
            (Shah's splats; flux-conserving on the flat mesh, 0.9% less light than the reference on a scan).
        splat_method: ``"auto"``, ``"window"`` or ``"tile"`` (:func:`~torchsss.ops.splat.splat_radiosity`).
        peel_layers: cap of the depth-peeling layers per axis for environment lights.
        specular: add the shadow-mapped GGX boundary reflection (point, spot and directional lights).
        roughness: GGX alpha of ``specular``.

    Per-vertex modifiers ``distance_scale`` :math:`M_d > 0` and ``irradiance_scale`` :math:`M_i \\ge 0`,
    :math:`(V,)` or :math:`(V, 3)` (Shah eq. 7.4), are constructor arguments.
    """

    method = "splat"
    defaults: ClassVar[dict] = dict(eps=0.01, grid=None, max_grid=512, oversample=2.0, max_stretch=MAX_STRETCH,
                                    coverage=True, flux="shading", splat_method="auto", peel_layers=8, specular=False,
                                    roughness=0.3)

    def __init__(self, mesh: Mesh, material, *, distance_scale: Tensor | None = None,
                 irradiance_scale: Tensor | None = None, **kwargs) -> None:
        self._modifiers = (distance_scale, irradiance_scale)
        super().__init__(mesh, material, **kwargs)

    def _build(self) -> None:
        k, mesh, dtype = self.knobs, self.mesh, self.dtype
        if not 0.0 < float(k["eps"]) < 1.0:
            raise ValueError(f"eps: expected a number in (0, 1), got {k['eps']!r}")
        ms = k["max_stretch"]
        if ms is not None and (isinstance(ms, bool) or not isinstance(ms, (int, float)) or not 1.0 <= ms < math.inf):
            raise ValueError(f"max_stretch: expected None or a finite number >= 1, got {ms!r}")
        if not isinstance(k["coverage"], bool):
            raise TypeError(f"coverage: expected a bool, got {type(k['coverage']).__name__}")
        if k["flux"] not in ("shading", "facet"):
            raise ValueError(f"flux: expected 'shading' or 'facet', got {k['flux']!r}")
        self.md, self.mi = vertex_modifiers(*self._modifiers, mesh, dtype)
        k["grid"] = splat_grid(mesh, self.material, k["eps"], k["max_grid"], k["oversample"]) if k["grid"] is None \
            else int(k["grid"])
        self.module = SplatTranslucency(self.material, eps=k["eps"], method=k["splat_method"])

    def render(self, lights, camera: Camera, mesh: Mesh | None = None, *, spp: int = 1,
               subpixel: str = "exact") -> RenderResult:
        """One frame (see :meth:`Renderer.render`); ``mesh`` replaces the built mesh's vertices (same topology)."""
        if mesh is not None:
            if not isinstance(mesh, Mesh) or mesh.faces.shape != self.mesh.faces.shape:
                raise ValueError("mesh: expected a Mesh with the built mesh's faces (a deformed pose), got another "
                                 "topology")
            self.mesh = mesh.with_dtype(self.dtype)
        return super().render(lights, camera, spp=spp, subpixel=subpixel)

    def _render(self, lights: list[Light], camera: Camera) -> RenderResult:
        k, mesh, dtype, eta = self.knobs, self.mesh, self.dtype, self.eta
        n = k["grid"]
        gbuf = camera_gbuffer(mesh, camera)
        view_proj = camera.view_proj(dtype=dtype, device=mesh.vertices.device)
        b = torch.zeros(1, 3, camera.height, camera.width, dtype=dtype, device=mesh.vertices.device)
        splats = 0
        sources, reused = self._per_lights(  # the splats depend on the lights and eta alone: kept while they stay
            "light_sources", lights,
            lambda: [light_sources(mesh, light, n, eta, k["peel_layers"], k["max_stretch"], k["coverage"],
                                         k["flux"])
                     for light in lights],
            (n, k["peel_layers"], k["max_stretch"], k["coverage"]))
        for pos, flux, fid, bary in sources:
            splats += int(pos.shape[0])
            b = b + self.module(pos.unsqueeze(0), flux.unsqueeze(0), gbuf.position, gbuf.mask, view_proj,
                                src_distance_scale=at_sources(self.md, mesh, fid, bary),
                                src_irradiance_scale=at_sources(self.mi, mesh, fid, bary))
        cos_o = view_cosine(gbuf)
        radiance = exit_radiance(b, cos_o, eta) * gbuf.mask
        if k["specular"]:
            radiance = radiance + shadow_mapped_specular(mesh, gbuf, lights, eta, roughness=k["roughness"])
        stats = {"grid": n, "splats": splats, "r_max_mm": float(self.module.r_max), "eps": k["eps"],
                 "relit": not reused}
        return RenderResult(radiance, b, gbuf.mask, stats)


def render_splat(mesh: Mesh, material: Material | nn.Module, lights: Sequence[Light], camera: Camera, *,
                 method: str = "auto", dtype: torch.dtype = torch.float32, progress: bool = False,
                 distance_scale: Tensor | None = None, irradiance_scale: Tensor | None = None,
                 **knobs) -> RenderResult:
    """Render one frame with Shah's splatting (:class:`SplatRenderer`); ``stats`` hold the grid, splat count, times.

    Args:
        mesh: the object (mm).
        material: its material (record, preset name or profile module).
        lights: point, spot, directional or environment lights.
        camera: the viewing camera.
        method: splat method of :func:`~torchsss.ops.splat.splat_radiosity` (the ``splat_method`` knob).
        dtype: float dtype of the computation.
        progress: unused (no step takes long enough); accepted for the shared render interface.
        distance_scale: per-vertex :math:`M_d > 0`, :math:`(V,)` or :math:`(V, 3)` (Shah eq. 7.4), or None.
        irradiance_scale: per-vertex :math:`M_i \\ge 0`, :math:`(V,)` or :math:`(V, 3)`, or None.
        **knobs: ``eps``, ``grid``, ``max_grid``, ``oversample``, ``peel_layers``, ``specular``, ``roughness`` of
            :class:`SplatRenderer`.

    Raises:
        ValueError: no lights, bad modifiers (shape, non-finite, out of range), a bad budget.
    """
    renderer = SplatRenderer(mesh, material, dtype=dtype, progress=progress, splat_method=method,
                             distance_scale=distance_scale, irradiance_scale=irradiance_scale, **knobs)
    res = renderer.render(lights, camera)
    res.stats["t_frame_s"] = res.stats["frame_s"]
    return res


def render_splat_objects(objects: Sequence[tuple[Mesh, Material | nn.Module]], lights: Sequence[Light],
                         camera: Camera, *,
                         eps: float = 0.01, grid: int | None = None, max_grid: int = 512, oversample: float = 2.0,
                         method: str = "auto", clip_objects: bool = True, dtype: torch.dtype = torch.float32,
                         progress: bool = False, specular: bool = False, roughness: float = 0.3,
                         peel_layers: int = 8) -> RenderResult:
    """Render several translucent objects of different materials with Shah's splatting in one pass (6.4.3).

    Per light, one light view of the merged mesh at ``grid`` (per distinct eta among the objects, for the Fresnel
    transmittance); every splat carries the object id of the face it sees, which is also its row of the material
    table; the camera G-buffer's face ids give the pixels' object ids; one
    :class:`~torchsss.modules.splat.SplatTranslucency` call with the material table (``r_max`` per material at
    ``eps``) and, with ``clip_objects``, the object-id clipping. :math:`L = F_t(\\eta_k)/\\pi\\,B` per object.

    Args:
        objects: :math:`K \\ge 1` ``(mesh, material)`` pairs, meshes in mm in the scene's frame.
        lights: point, spot or directional lights.
        camera: the viewing camera.
        eps: splat budget tolerance (r_max and the splat spacing).
        grid: light-view resolution (default: :func:`splat_grid` of the merged mesh and all materials).
        max_grid: cap of the automatic grid.
        oversample: factor on the budget's grid, and on its floor :data:`MIN_GRID` (texels across the object:
            a small or long-scattering object's light view refines with it too).
        method: splat method of :func:`~torchsss.ops.splat.splat_radiosity`.
        clip_objects: discard splats that land on another object (Shah's ID check); False lets light cross
            between objects (only for comparison).
        dtype: float dtype of the computation.
        progress: unused; accepted for the shared render interface.
        specular: add the shadow-mapped GGX boundary reflection (each object with its own eta).
        roughness: GGX alpha of ``specular``.
        peel_layers: cap of the depth-peeling layers per axis for environment lights.

    Returns:
        A :class:`~torchsss.pipelines.reference.RenderResult`; ``stats`` holds the grid, the splat count, the
        per-material ``r_max_mm`` and the time.

    Examples:
        >>> from torchsss.geometry.lights import DirectionalLight
        >>> from torchsss.geometry.procedural import sphere
        >>> import dataclasses
        >>> a = sphere(4.0, 2); b = dataclasses.replace(a, vertices=a.vertices + torch.tensor([8.0, 0, 0]))
        >>> cam = Camera(eye=(4, 0, 60), target=(4, 0, 0), width=16, height=16)
        >>> r = render_splat_objects([(a, Material.from_json("marble")), (b, Material.from_json("skin1"))],
        ...                          [DirectionalLight((0, 0, -1), 1.0)], cam, grid=32)
        >>> tuple(r.radiance.shape), len(r.stats["r_max_mm"])
        ((1, 3, 16, 16), 2)
    """
    del progress
    objects = check_objects(objects)
    if not 0.0 < float(eps) < 1.0:
        raise ValueError(f"eps: expected a number in (0, 1), got {eps!r}")
    lights = check_lights(lights)
    t0 = time.perf_counter()
    meshes = [m.with_dtype(dtype) for m, _ in objects]
    materials = [material_module(mat, dtype=None if isinstance(mat, nn.Module) else dtype) for _, mat in objects]
    merged, face_object = merge_meshes(meshes)
    device = merged.vertices.device
    n = splat_grid(merged, materials, eps, max_grid, oversample) if grid is None else int(grid)
    module = SplatTranslucency([m.to(device) for m in materials], eps=eps, method=method)
    gbuf = camera_gbuffer(merged, camera)
    dst_object = object_ids(gbuf.face_id, face_object)
    masks = object_masks(dst_object, len(objects))
    view_proj = camera.view_proj(dtype=dtype, device=device)
    etas = sorted({float(mat.eta.detach()) for mat in materials})
    obj_eta = torch.tensor([float(mat.eta.detach()) for mat in materials], dtype=dtype, device=device)
    pos, flux, obj = [], [], []
    for light in lights:
        views = [light_sources(merged, light, n, e, peel_layers) for e in etas]  # the same points, per eta
        p0, _, fid, _ = views[0]
        ids = face_object[fid]
        f = torch.zeros(ids.shape[0], 3, dtype=dtype, device=device)
        for e, v in zip(etas, views):
            pick = obj_eta[ids] == e
            f[pick] = v[1][pick]
        pos.append(p0)
        flux.append(f)
        obj.append(ids)
    src_pos = torch.cat(pos).unsqueeze(0)
    src_flux = torch.cat(flux).unsqueeze(0)
    src_obj = torch.cat(obj).unsqueeze(0)
    ids = {"src_object": src_obj, "dst_object": dst_object} if clip_objects else {}
    with torch.no_grad():
        b = module(src_pos, src_flux, gbuf.position, gbuf.mask, view_proj, src_material=src_obj, **ids)
    cos_o = view_cosine(gbuf)
    radiance = torch.zeros_like(b)
    for k, mat in enumerate(materials):
        radiance = radiance + exit_radiance(b, cos_o, mat.eta) * masks[:, k:k + 1]
        if specular:
            spec = shadow_mapped_specular(merged, gbuf, lights, mat.eta, roughness=roughness)
            radiance = radiance + spec * masks[:, k:k + 1]
    stats = {"grid": n, "splats": int(src_pos.shape[1]), "r_max_mm": [float(v) for v in module.r_max], "eps": eps,
             "objects": len(objects), "clip_objects": bool(clip_objects), "t_frame_s": time.perf_counter() - t0}
    return RenderResult(radiance, b, gbuf.mask, stats)
