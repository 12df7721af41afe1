"""The reference renderer: ground truth that every fast method is measured against.

Steps (no approximation beyond the quadrature of the surface integral):

1. dense, deterministic surface samples (:func:`~torchsss.geometry.sampling.surface_samples`): every face is
   subdivided so that no sub-triangle edge exceeds ``spacing_mm``; each sample carries its exact area;
2. irradiance at every sample: :math:`E = \\sum_l I_l \\cos\\theta / d^2 \\, F_t(\\eta, \\cos\\theta)\\, V_l`
   with exact visibility :math:`V_l` by ray casting (or a shadow map, or none, on request);
3. radiosity at every receiver by the all-pairs integrator
   :func:`~torchsss.ops.reference.reference_radiosity`: :math:`B(x_o) = \\sum_i E_i A_i R_d(|x_i - x_o|)`;
4. outgoing radiance at every covered camera pixel: :math:`L = F_t(\\eta, n\\cdot\\omega_o)/\\pi \\; B`.

Several objects of different materials (:func:`render_reference_objects`, Shah 6.4.3): every object has its own
samples; their irradiance uses the visibility of the merged mesh (objects shadow each other); the pixels of each
object get :math:`B` from that object's samples with its material alone (no light crosses from one object into
another) and :math:`L = F_t(\\eta_k)/\\pi\\,B`.

The default sample spacing comes from the material: the splat spacing of
:func:`~torchsss.physics.splat_spacing` at ``eps`` (the largest lattice spacing whose aliasing error of the
sum stays below ``eps`` of the integral on a plane), the smallest over the channels. Cost is
receivers x samples profile evaluations; memory is bounded by ``max_pairs``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor, nn
from tqdm import tqdm

from torchsss.geometry.camera import Camera
from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.gbuffer import camera_gbuffer, view_cosine
from torchsss.geometry.lights import DirectionalLight, Light, incident_light, surface_irradiance
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.objects import merge_meshes, object_ids, object_masks
from torchsss.geometry.sampling import SurfaceSamples, refine_samples, surface_samples
from torchsss.geometry.shadow import build_shadow_map, shadow_visibility
from torchsss.geometry.transfer import SurfaceLocator, project_samples
from torchsss.geometry.visibility import point_inside, ray_visibility
from torchsss.modules.material import material_module
from torchsss.ops.fused import expected_work
from torchsss.ops.reference import reference_radiosity
from torchsss.physics.fresnel import check_fresnel, exit_radiance
from torchsss.physics.materials import Material
from torchsss.pipelines.atlas_view import source_mesh
from torchsss.pipelines.coarse import coarse_receivers
from torchsss.pipelines.modifiers import at_sources, vertex_modifiers
from torchsss.pipelines.renderer import Renderer, RenderResult, check_dtype, check_lights, check_objects
from torchsss.pipelines.specular import specular_radiance

__all__ = [
    "REFERENCE_MAX_PAIRS",
    "ReferenceRenderer",
    "RenderResult",
    "cast_shadow_faces",
    "check_objects",
    "default_spacing",
    "reference_radiosity_at",
    "render_reference",
    "render_reference_objects",
    "sample_irradiance",
]

_SHADOWS = ("raytrace", "shadowmap", "none")

#: The reference's pair budget: one integrator chunk, and its receiver blocks of ``8 * max_pairs / N`` receivers
#: for N samples. Larger than the integrator's own :data:`~torchsss.ops.reference.DEFAULT_MAX_PAIRS` (a chunk of
#: the eager chain that stays in cache) because the reference's frames run in the fused kernel, which takes a
#: receiver block whole: the default scene at 128x128 (102M pairs) took 4.6 s a warm frame at ``1 << 22`` and 7.2 s
#: at ``1 << 18`` (2026-11-28, 2 threads, both beside the same other job), its peak 509 and 547 MB.
REFERENCE_MAX_PAIRS = 1 << 22


def default_spacing(material: Material | nn.Module, mesh: Mesh | None = None, eps: float = 0.01) -> float:
    """Sample spacing (mm) for the reference: the finest per-channel lattice spacing of the profile at ``eps``.

    The profile module's ``spacing(eps)`` (:func:`~torchsss.physics.splat_spacing` for the dipole). With a mesh it
    is also kept above ``size_mm / 4000`` so that a thin material on a huge object cannot ask for billions of
    samples.

    Examples:
        >>> round(default_spacing(Material.from_json("skin1")), 3)
        0.608
    """
    module = material_module(material, dtype=None if isinstance(material, nn.Module) else torch.float64)
    s = float(module.spacing(eps).min())
    if mesh is not None:
        s = max(s, mesh.size_mm / 4000.0)
    return s


def _check_lights(mesh: Mesh, lights: Sequence[Light]) -> None:
    for light in lights:
        if isinstance(light, (DirectionalLight, EnvironmentLight)):
            continue
        if point_inside(mesh, light.position):
            raise ValueError(
                f"light position {light.position}: expected a light outside the mesh, got one inside it "
                "(it would light only the inside of the surface)"
            )


def _visibility(mesh: Mesh, lights: Sequence[Light], points: Tensor, normals: Tensor, shadows: str,
                shadow_resolution: int = 2048) -> list[Tensor | None]:
    """Per light, the :math:`(1, N)` visibility of points :math:`(N, 3)` by ``shadows``; None when unshadowed."""
    if shadows not in _SHADOWS:
        raise ValueError(f"shadows: expected one of {_SHADOWS}, got {shadows!r}")
    vis: list[Tensor | None] = []
    for light in lights:
        if isinstance(light, EnvironmentLight) or shadows == "none":
            vis.append(None)  # environments are unshadowed, as in Shah 6.4.2 and the splat renderer
        elif shadows == "raytrace":
            vis.append(ray_visibility(mesh, light, points, normals).unsqueeze(0))
        else:
            sm = build_shadow_map(mesh, light, shadow_resolution)
            vis.append(shadow_visibility(sm, points.unsqueeze(0), normals.unsqueeze(0), light))
    return vis


def cast_shadow_faces(mesh: Mesh, lights: Sequence[Light], shadows: str = "raytrace") -> Tensor:
    """The faces a cast shadow's edge crosses: :math:`(F,)` bool.

    Per light, each vertex that faces it (:math:`n \\cdot l > 0`) is lit or in a cast shadow (``shadows``'
    visibility at the vertex); a face with a lit and a shadowed corner holds a shadow edge, where the irradiance
    jumps within the face. Unshadowed lights (environments, ``shadows="none"``) cross no face. The attached
    terminator (:math:`n \\cdot l` through 0) is not an edge: the irradiance goes to zero continuously there.

    Examples:
        >>> from torchsss.geometry import PointLight, sphere
        >>> int(cast_shadow_faces(sphere(10.0, 2), [PointLight((0, 0, 50), 1.0)]).sum())  # convex: no cast shadow
        0
    """
    edge = torch.zeros(mesh.num_faces, dtype=torch.bool, device=mesh.faces.device)
    if shadows == "none" or mesh.num_faces == 0:
        return edge
    v, n = mesh.vertices.detach(), mesh.vertex_normals.detach()
    for light, vis in zip(lights, _visibility(mesh, lights, v, n, shadows)):
        if vis is None:
            continue
        facing = (n * incident_light(light, v.unsqueeze(0))[0][0]).sum(-1) > 0
        lit = (facing & (vis.reshape(-1) > 0.5))[mesh.faces]
        cast = (facing & (vis.reshape(-1) <= 0.5))[mesh.faces]
        edge |= lit.any(1) & cast.any(1)
    return edge


def _front_faces(mesh: Mesh, lights: Sequence[Light], samples: SurfaceSamples) -> list[Tensor | None]:
    """Per light, the :math:`(1, N)` visibility "the sample's face turns towards the light" (None: environments)."""
    normal = mesh.face_normals.detach().to(samples.position.dtype)[samples.face_id]
    out: list[Tensor | None] = []
    for light in lights:
        if isinstance(light, EnvironmentLight):
            out.append(None)
            continue
        to_light = incident_light(light, samples.position.detach().unsqueeze(0))[0][0]
        out.append(((normal * to_light).sum(-1) > 0).to(samples.position.dtype).unsqueeze(0))
    return out


def sample_irradiance(
    mesh: Mesh,
    samples: SurfaceSamples,
    lights: Sequence[Light],
    eta: float | Tensor,
    *,
    shadows: str = "raytrace",
    shadow_resolution: int = 2048,
    fresnel: str = "exact",
) -> Tensor:
    """Transmitted irradiance :math:`(N, 3)` at the samples, with the chosen visibility.

    ``shadows``: ``"raytrace"`` (exact, the reference), ``"shadowmap"`` (hard shadows from
    :func:`~torchsss.geometry.shadow.build_shadow_map`) or ``"none"``: no occlusion by other parts of the mesh,
    but no light through a face's back either (a sample whose face turns away from the light gets none, whatever
    its interpolated normal says: exact on a convex object, where vertex normals smoothed across a sharp edge
    would otherwise let light onto the faces turned away; a side-lit 25 mm cream slab was 5.8% off the
    ray-traced image at ``eps=0.1``). Environment lights
    (:class:`~torchsss.geometry.environment.EnvironmentLight`) are unshadowed: their order-2 SH irradiance with
    the Fresnel-cosine lobe is exact for the band-limited environment, and its occlusion is ignored (as in Shah).
    ``eta`` is a number or the material module's ``eta`` tensor.
    """
    if shadows == "none":
        vis = _front_faces(mesh, lights, samples)
    else:
        vis = _visibility(mesh, lights, samples.position, samples.normal, shadows, shadow_resolution)
    e = surface_irradiance(samples.position.unsqueeze(0), samples.normal.unsqueeze(0), list(lights), eta,
                           visibility=vis, fresnel=fresnel)
    return e.squeeze(0)


def reference_radiosity_at(
    points: Tensor,
    samples: SurfaceSamples,
    irradiance: Tensor,
    material: Material | nn.Module,
    *,
    max_pairs: int = REFERENCE_MAX_PAIRS,
    progress: bool = False,
    distance_scale: Tensor | None = None,
    irradiance_scale: Tensor | None = None,
) -> Tensor:
    """:math:`B` at receiver points :math:`(M, 3)` from samples with irradiance :math:`(N, 3)`; returns (M, 3).

    ``material`` is a profile module (or a record, made into one in the points' dtype). Receivers are processed
    in blocks (a tqdm bar over receivers when ``progress``); the dtype is the points' dtype. ``distance_scale``
    and ``irradiance_scale`` are the samples' :math:`M_d`, :math:`M_i` (Shah eq. 7.4), :math:`(N, 1)` or
    :math:`(N, 3)`, or None.
    """
    dtype = points.dtype
    record = not isinstance(material, nn.Module)
    profile = material_module(material, dtype=dtype if record else None, device=points.device if record else None)
    if record:  # a record's module is private here: nothing to differentiate
        profile.requires_grad_(False)
    src_pos = samples.position.to(dtype).unsqueeze(0)
    src_e = irradiance.to(dtype).unsqueeze(0)
    src_a = samples.area.to(dtype).unsqueeze(0)
    md = None if distance_scale is None else distance_scale.to(dtype).reshape(1, src_pos.shape[1], -1)
    mi = None if irradiance_scale is None else irradiance_scale.to(dtype).reshape(1, src_pos.shape[1], -1)
    n = max(1, src_pos.shape[1])
    block = max(64, min(points.shape[0], (max_pairs * 8) // n))
    out = []
    # the blocks add up to one frame's pairs: the fused kernel compiles at the first block when they pay for it
    with expected_work("dipole_pair_sum", float(points.shape[0]) * n), \
            tqdm(total=points.shape[0], desc="reference B(x_o)", unit="px", disable=not progress, leave=False) as bar:
        for start in range(0, points.shape[0], block):
            dst = points[start:start + block].unsqueeze(0)
            b = reference_radiosity(src_pos, src_e, src_a, dst, profile, max_pairs=max_pairs,
                                    src_distance_scale=md, src_irradiance_scale=mi).squeeze(0)
            out.append(b.to(dtype))
            bar.update(dst.shape[1])
    if not out:
        return points.new_zeros(0, 3)
    return torch.cat(out)


def _specular(mesh: Mesh, gbuf, lights: list[Light], eta, shadows: str, roughness: float) -> Tensor:
    pix = gbuf.position.flatten(2).transpose(1, 2)[0]
    pix_n = gbuf.normal.flatten(2).transpose(1, 2)[0]
    vis = _visibility(mesh, lights, pix, pix_n, shadows)
    return specular_radiance(gbuf, lights, eta, roughness=roughness, visibility=vis)


class ReferenceRenderer(Renderer):
    """The ground-truth renderer (module docstring), built once for a mesh and a material.

    Setup: the surface samples at the spacing (default :func:`default_spacing` of the material at ``eps``).
    Per frame: the camera G-buffer, the irradiance of every sample, all pairs, the exit radiance.

    Knobs:
        spacing_mm: surface sample spacing (mm); default from the material and ``eps``.
        eps: the tolerance that picks the default spacing.
        shadows: ``"raytrace"`` (exact, default), ``"shadowmap"`` or ``"none"``.
        fresnel: ``"exact"`` or ``"schlick"`` for the transmittance at entry and exit.
        max_pairs: pair budget of one integrator chunk (bounds memory).
        max_samples: refuse spacings that need more samples than this (ValueError).
        specular: add the boundary's GGX specular reflection with the same visibility (off by default so that
            images compare subsurface transport alone).
        roughness: GGX alpha of the specular term.
        source_faces: when set and the mesh has more faces, the sample sources (their positions, normals,
            irradiance and shadows) come from the mesh decimated to about this many faces
            (:func:`~torchsss.geometry.decimate`), while the camera still sees the full mesh: every face holds at
            least one sample, so a finely tessellated scan has far more samples than its spacing asks for
            (a 268k-face scan: 268k samples where the spacing needs ~10k). The planner sets it to the
            spacing's face count (:mod:`torchsss.plan`).
        project_sources: with ``source_faces``, move every sample to its closest point on the full mesh, with the
            full mesh's normal there, and shadow it against the full mesh
            (:func:`~torchsss.geometry.transfer.project_samples`; default True): the decimation then picks how many
            samples, not where they are. Measured against the full-source reference, a back-lit 25 mm apple igea
            (40k faces) at 128 x 128: sources from 11,484 faces at ``eps=0.05`` 1.53% -> 0.43%, from 5,625 at
            ``eps=0.2`` 2.95% -> 1.11%. False: the decimated surface's own samples.
        stride: evaluate :math:`B` at every ``stride``-th pixel in each direction and interpolate it where the
            surface is smooth, exactly at edges (:mod:`torchsss.pipelines.coarse`); 1: every pixel. None
            (default): the supersampling factor of ``render(..., spp=s * s)``, so that a supersampled frame
            evaluates :math:`B` about once per pixel where the surface is smooth and on every sub-pixel at
            silhouettes, creases and sharp shadow terminators (the pixel integral at little more than the cost
            of one sample per pixel: ``spp=16`` is within 0.3% of a fully evaluated 16-spp frame on a back-lit
            torus where 1 spp is 6.9% off; ``tests/test_coarse.py``).
        shadow_refine: the samples of the faces a cast shadow's edge crosses (:func:`cast_shadow_faces`, per
            frame) are subdivided this many times finer (1: off). A sample stands for its whole sub-triangle, so a
            shadow edge is quantised to the spacing, which the image shows where the near field of :math:`R_d` is
            narrower (against a reference refined 4x at ``eps=0.01``: a side-lit 12 mm wholemilk torus at 256 x 256,
            ``eps=0.1``, 1.82% relative RMSE unrefined (0.18% without shadows), 0.43% refined 2x (the default; 3%
            more samples), 0.29% 4x (13% more); a back-lit 40 mm skin1 spot at 128 x 128, ``eps=0.3``: 0.62%,
            0.30% (5% more), 0.19% (23% more)). The vertices' visibility costs a shadow ray per vertex and light.
        refine: with ``stride`` > 1, an interpolated pixel whose four grid corners differ by more than this
            (relative, any channel) is evaluated exactly too (shadow terminators sharper than the grid).

    Per-vertex modifiers ``distance_scale`` :math:`M_d > 0` and ``irradiance_scale`` :math:`M_i \\ge 0`,
    :math:`(V,)` or :math:`(V, 3)` (Shah eq. 7.4), are constructor arguments, as for
    :class:`~torchsss.pipelines.splat.SplatRenderer`: they are interpolated at every surface sample, whose profile
    becomes :math:`M_i R_d(r M_d)`, and may require grad (the integrator is differentiable in them). The default
    spacing is divided by the largest :math:`M_d` (the narrowest profile sets the quadrature). They need the
    samples on the mesh's own vertices, so they cannot be combined with ``source_faces`` (ValueError).

    Examples:
        >>> from torchsss.geometry import Camera, DirectionalLight, sphere
        >>> r = ReferenceRenderer(sphere(10.0, 2), "skin1", spacing_mm=2.0)
        >>> res = r.render([DirectionalLight((0, 0, -1), 1.0)], Camera(eye=(0, 0, 60), target=(0, 0, 0),
        ...                width=8, height=8))
        >>> tuple(res.radiance.shape), res.stats["method"], res.stats["knobs"]["spacing_mm"]
        ((1, 3, 8, 8), 'reference', 2.0)
    """

    method = "reference"
    defaults: ClassVar[dict] = dict(spacing_mm=None, eps=0.01, shadows="raytrace", fresnel="exact",
                                    max_pairs=REFERENCE_MAX_PAIRS, max_samples=2_000_000, specular=False,
                                    roughness=0.3, source_faces=None, stride=None, refine=0.2, shadow_refine=2,
                                    project_sources=True)

    def __init__(self, mesh: Mesh, material, *, distance_scale: Tensor | None = None,
                 irradiance_scale: Tensor | None = None, **kwargs) -> None:
        self._modifiers = (distance_scale, irradiance_scale)
        super().__init__(mesh, material, **kwargs)

    def _build(self) -> None:
        k = self.knobs
        self.md, self.mi = vertex_modifiers(*self._modifiers, self.mesh, self.dtype)
        if (self.md is not None or self.mi is not None) and k["source_faces"] is not None:
            raise ValueError(f"source_faces: expected None with per-vertex distance_scale / irradiance_scale (they "
                             f"live on the mesh's own vertices), got {k['source_faces']!r}")
        self.source_mesh = source_mesh(self.mesh, k["source_faces"])
        self.fresnel = check_fresnel(k["fresnel"], ("exact", "schlick"))
        refine = k["shadow_refine"]
        if isinstance(refine, bool) or not isinstance(refine, int) or refine < 1:
            raise ValueError(f"shadow_refine: expected an int >= 1, got {refine!r}")
        if k["shadows"] not in _SHADOWS:
            raise ValueError(f"shadows: expected one of {_SHADOWS}, got {k['shadows']!r}")
        if k["spacing_mm"] is None:
            spacing = default_spacing(self.material, self.mesh, k["eps"])
            if self.md is not None:  # R_d(r M_d): the largest M_d makes the narrowest profile
                spacing /= max(1.0, float(self.md.detach().max()))
        else:
            spacing = float(k["spacing_mm"])
        if not (math.isfinite(spacing) and spacing > 0):
            raise ValueError(f"spacing_mm: expected a finite value > 0, got {k['spacing_mm']!r}")
        k["spacing_mm"] = spacing
        self.samples = surface_samples(self.source_mesh, spacing, max_samples=k["max_samples"])
        if not isinstance(k["project_sources"], bool):
            raise ValueError(f"project_sources: expected a bool, got {k['project_sources']!r}")
        self._locator = None
        if k["project_sources"] and self.source_mesh is not self.mesh:
            self._locator = SurfaceLocator(self.mesh)
            self._projected = project_samples(self._locator, self.samples)

    def _render(self, lights: list[Light], camera: Camera) -> RenderResult:
        k, mesh = self.knobs, self.mesh
        stats: dict = {"spacing_mm": k["spacing_mm"], "samples": int(self.samples.area.shape[0])}
        _check_lights(mesh, lights)
        eta = self.eta
        gbuf = camera_gbuffer(mesh, camera)
        t1 = time.perf_counter()
        samples = self.samples
        projected = self._projected if self._locator is not None else None
        refine = k["shadow_refine"]
        if refine > 1:
            edge = cast_shadow_faces(self.source_mesh, lights, k["shadows"])
            samples, kept = refine_samples(self.source_mesh, samples, edge, k["spacing_mm"], refine)
            stats["shadow_edge_faces"] = int(edge.sum())
            stats["samples"] = int(samples.area.shape[0])
            if projected is not None and samples is not self.samples:  # refined: project the new samples too
                fine = SurfaceSamples(*(x[int(kept.sum()):] for x in samples))  # the refined faces' samples, last
                projected = SurfaceSamples(*(torch.cat([a[kept], b]) for a, b in
                                             zip(projected, project_samples(self._locator, fine))))
        if projected is not None:  # on the full mesh: its normals and its shadows
            samples = projected
        e = sample_irradiance(mesh if projected is not None else self.source_mesh, samples, lights, eta,
                              shadows=k["shadows"], fresnel=self.fresnel)
        stats["t_irradiance_s"] = time.perf_counter() - t1
        mask = gbuf.mask[0, 0]
        h, w = camera.resolution
        pos_img = gbuf.position[0].permute(1, 2, 0)
        stride = self._supersample if k["stride"] is None else k["stride"]
        plan = coarse_receivers(pos_img, gbuf.normal[0].permute(1, 2, 0), mask, stride)
        receivers = pos_img.reshape(-1, 3)[plan.evaluate]
        stats["receivers"] = int(receivers.shape[0])
        stats["interpolated"] = int(plan.fill.numel())
        stats["pairs"] = stats["receivers"] * stats["samples"]
        t2 = time.perf_counter()
        fid, bary = samples.face_id, samples.bary
        mods = {"distance_scale": at_sources(self.md, mesh, fid, bary),
                "irradiance_scale": at_sources(self.mi, mesh, fid, bary)}
        b = reference_radiosity_at(receivers, samples, e, self.material, max_pairs=k["max_pairs"],
                                   progress=self.progress, **mods)
        exact = plan.refine(b, k["refine"])  # interpolated pixels whose corners disagree: evaluated exactly
        b_exact = reference_radiosity_at(pos_img.reshape(-1, 3)[plan.fill[exact]], samples, e, self.material,
                                         max_pairs=k["max_pairs"], **mods) if exact.numel() else None
        stats["interpolated"] -= int(exact.numel())
        stats["receivers"] += int(exact.numel())
        stats["pairs"] = stats["receivers"] * stats["samples"]
        stats["t_integrate_s"] = time.perf_counter() - t2
        radiosity = plan.scatter(b, h, w, exact, b_exact).permute(2, 0, 1).unsqueeze(0)
        cos_o = view_cosine(gbuf)
        radiance = exit_radiance(radiosity, cos_o, eta, self.fresnel) * gbuf.mask
        if k["specular"]:
            radiance = radiance + _specular(mesh, gbuf, lights, eta, k["shadows"], k["roughness"])
        return RenderResult(radiance, radiosity, gbuf.mask, stats)


def render_reference(
    mesh: Mesh,
    material: Material | nn.Module,
    lights: Sequence[Light],
    camera: Camera,
    *,
    dtype: torch.dtype = torch.float32,
    progress: bool = False,
    **knobs,
) -> RenderResult:
    """Render the ground-truth image of a homogeneous translucent mesh: one frame of :class:`ReferenceRenderer`.

    Args:
        mesh: the object (mm).
        material: its material (a :class:`~torchsss.physics.Material` record, a preset name or a profile module).
        lights: the lights.
        camera: the camera.
        dtype: float32 (default) or float64 for the integration.
        progress: show tqdm bars.
        **knobs: the knobs of :class:`ReferenceRenderer` (``spacing_mm``, ``eps``, ``shadows``, ``fresnel``,
            ``max_pairs``, ``max_samples``, ``specular``, ``roughness``).

    Returns:
        A :class:`RenderResult`; ``stats`` holds the spacing, counts, ``setup_s``, ``frame_s`` and the stages.

    Raises:
        ValueError: a light inside a (watertight) mesh, a camera inside or too close to it, bad options.
    """
    renderer = ReferenceRenderer(mesh, material, dtype=dtype, progress=progress, **knobs)
    res = renderer.render(lights, camera)
    res.stats["t_setup_s"] = res.stats["setup_s"]
    res.stats["t_total_s"] = res.stats["setup_s"] + res.stats["frame_s"]
    return res


def render_reference_objects(
    objects: Sequence[tuple[Mesh, Material | nn.Module]],
    lights: Sequence[Light],
    camera: Camera,
    *,
    spacing_mm: float | None = None,
    eps: float = 0.01,
    shadows: str = "raytrace",
    fresnel: str = "exact",
    dtype: torch.dtype = torch.float32,
    max_pairs: int = REFERENCE_MAX_PAIRS,
    max_samples: int = 2_000_000,
    progress: bool = False,
    specular: bool = False,
    roughness: float = 0.3,
    differentiable: bool = False,
) -> RenderResult:
    """Ground truth for several translucent objects of different materials (module docstring).

    With one object the image equals :func:`render_reference`'s exactly.

    Args:
        objects: :math:`K \\ge 1` ``(mesh, material)`` pairs, meshes in mm in the scene's frame.
        lights: the lights.
        camera: the camera.
        spacing_mm: surface sample spacing of every object; default :func:`default_spacing` of each object's
            material and mesh at ``eps``.
        eps: the tolerance that picks the default spacings.
        shadows: ``"raytrace"`` (exact, default), ``"shadowmap"`` or ``"none"``, against all objects.
        fresnel: ``"exact"`` or ``"schlick"``.
        dtype: float32 (default) or float64.
        max_pairs: pair budget of one integrator chunk.
        max_samples: refuse spacings that need more samples than this, per object (ValueError).
        progress: show tqdm bars.
        specular: add the GGX specular reflection (each object with its own eta).
        roughness: GGX alpha of the specular term.
        differentiable: record the frame for autograd (gradients reach the materials' parameters when they are
            modules that require them), as :class:`~torchsss.pipelines.renderer.Renderer`'s ``differentiable``;
            False (default) renders without a graph. (Recorded, every chunk's temporaries stay alive until the
            backward pass: the two 20 mm spheres of ``examples/scenes/two_objects.json`` at 128 x 128 reached a
            15 GB peak when the frame was recorded by default, for 119M pairs.)

    Returns:
        A :class:`RenderResult`; ``mask`` covers every object; ``stats`` holds the per-object spacings and counts
        (lists), their totals and the timings.

    Raises:
        ValueError: bad ``objects``, a light inside an object, a camera inside or too close to one, bad options.

    Examples:
        >>> from torchsss.geometry.lights import DirectionalLight
        >>> from torchsss.geometry.procedural import sphere
        >>> import dataclasses
        >>> a = sphere(4.0, 2); b = dataclasses.replace(a, vertices=a.vertices + torch.tensor([8.0, 0, 0]))
        >>> cam = Camera(eye=(4, 0, 60), target=(4, 0, 0), width=16, height=16)
        >>> r = render_reference_objects([(a, Material.from_json("marble")), (b, Material.from_json("skin1"))],
        ...                              [DirectionalLight((0, 0, -1), 1.0)], cam, spacing_mm=1.0)
        >>> tuple(r.radiance.shape), r.stats["samples"] == sum(r.stats["samples_per_object"])
        ((1, 3, 16, 16), True)
    """
    objects = check_objects(objects)
    check_dtype(dtype)
    check_fresnel(fresnel, ("exact", "schlick"))
    if shadows not in _SHADOWS:
        raise ValueError(f"shadows: expected one of {_SHADOWS}, got {shadows!r}")
    if not isinstance(differentiable, bool):
        raise TypeError(f"differentiable: expected a bool, got {type(differentiable).__name__}")
    lights = check_lights(lights)
    with torch.set_grad_enabled(differentiable and torch.is_grad_enabled()):
        return _render_objects(objects, lights, camera, spacing_mm=spacing_mm, eps=eps, shadows=shadows,
                               fresnel=fresnel, dtype=dtype, max_pairs=max_pairs, max_samples=max_samples,
                               progress=progress, specular=specular, roughness=roughness)


def _render_objects(objects, lights, camera, *, spacing_mm, eps, shadows, fresnel, dtype, max_pairs, max_samples,
                    progress, specular, roughness) -> RenderResult:
    """:func:`render_reference_objects` after its checks, under its autograd mode."""
    stats: dict = {"objects": len(objects)}
    t0 = time.perf_counter()
    meshes = [m.with_dtype(dtype) for m, _ in objects]
    device = meshes[0].vertices.device
    materials = [material_module(mat, dtype=None if isinstance(mat, nn.Module) else dtype, device=device)
                 for _, mat in objects]
    for m in meshes:
        _check_lights(m, lights)
    merged, face_object = merge_meshes(meshes)
    gbuf = camera_gbuffer(merged, camera)
    masks = object_masks(object_ids(gbuf.face_id, face_object), len(objects))  # (1, K, H, W)
    h, w = camera.resolution
    radiosity = torch.zeros(h, w, 3, dtype=dtype, device=gbuf.position.device)
    pixels = gbuf.position[0].permute(1, 2, 0)
    stats.update(spacing_mm_per_object=[], samples_per_object=[], receivers_per_object=[],
                 t_setup_s=0.0, t_irradiance_s=0.0, t_integrate_s=0.0)
    for k, (mesh, material) in enumerate(zip(meshes, materials)):
        t1 = time.perf_counter()
        spacing = default_spacing(material, mesh, eps) if spacing_mm is None else float(spacing_mm)
        if not (math.isfinite(spacing) and spacing > 0):
            raise ValueError(f"spacing_mm: expected a finite value > 0, got {spacing_mm!r}")
        samples = surface_samples(mesh, spacing, max_samples=max_samples)
        t2 = time.perf_counter()
        e = sample_irradiance(merged, samples, lights, material.eta, shadows=shadows, fresnel=fresnel)
        t3 = time.perf_counter()
        mask_k = masks[0, k]
        b = reference_radiosity_at(pixels[mask_k], samples, e, material, max_pairs=max_pairs, progress=progress)
        radiosity[mask_k] = b
        stats["spacing_mm_per_object"].append(spacing)
        stats["samples_per_object"].append(int(samples.area.shape[0]))
        stats["receivers_per_object"].append(int(mask_k.sum()))
        stats["t_setup_s"] += t2 - t1
        stats["t_irradiance_s"] += t3 - t2
        stats["t_integrate_s"] += time.perf_counter() - t3
    stats["samples"] = sum(stats["samples_per_object"])
    stats["receivers"] = sum(stats["receivers_per_object"])
    stats["pairs"] = sum(a * b for a, b in zip(stats["samples_per_object"], stats["receivers_per_object"]))
    stats["spacing_mm"] = min(stats["spacing_mm_per_object"])
    radiosity = radiosity.permute(2, 0, 1).unsqueeze(0)
    cos_o = view_cosine(gbuf)
    radiance = torch.zeros_like(radiosity)
    for k, material in enumerate(materials):
        radiance = radiance + exit_radiance(radiosity, cos_o, material.eta, fresnel) * masks[:, k:k + 1]
    if specular:
        for k, material in enumerate(materials):
            spec = _specular(merged, gbuf, lights, material.eta, shadows, roughness)
            radiance = radiance + spec * masks[:, k:k + 1]
    stats["t_total_s"] = time.perf_counter() - t0
    return RenderResult(radiance, radiosity, gbuf.mask, stats)
