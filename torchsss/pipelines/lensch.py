"""Render with Lensch et al. 2002: build once (atlas, kernels, throughput), then relight per frame.

Build (timed as ``precompute``): texture atlas with gutters, per-texel k x k kernel geometry, vertex dual-basis
weights, the sparse vertex-to-vertex throughput (threshold relative to the largest entry), and - when
``blend`` - Lensch's §5.4 blending weights and kernel correction. Per frame (timed as ``frame``): irradiance
atlas with shadow-mapped visibility, :class:`~torchsss.modules.lensch.LenschTranslucency`, the atlas sampled
at the camera pixels' texture coordinates, :math:`L = F_t(\\eta, \\omega_o)/\\pi \\; B`.
"""

from __future__ import annotations

import numbers
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor, nn

from torchsss.geometry.atlas import Atlas, build_atlas
from torchsss.geometry.atlas_frame import irradiance_atlas
from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import camera_gbuffer, view_cosine
from torchsss.geometry.lensch import (
    MAX_THROUGHPUT_ENTRIES,
    THROUGHPUT_THRESHOLD,
    blending_weights,
    build_dense_throughput,
    build_throughput,
    check_entries,
    estimate_throughput_entries,
    hat_quadrature,
    plan_kernel_size,
    plan_lensch,
    throughput_layout,
    vertex_weights,
)
from torchsss.geometry.lights import Light
from torchsss.geometry.mesh import CREASE_DEG, Mesh, split_creases
from torchsss.geometry.refine import REFINE_RATIO, feature_edges, refine_creases
from torchsss.modules.lensch import GlobalResponse, LenschTranslucency, LocalResponse
from torchsss.modules.material import material_module
from torchsss.ops.interp import barycentric_interpolate
from torchsss.physics.fresnel import exit_radiance
from torchsss.physics.materials import Material
from torchsss.pipelines.atlas_view import AtlasView, source_mesh
from torchsss.pipelines.renderer import Renderer, RenderResult
from torchsss.pipelines.specular import shadow_mapped_specular

__all__ = ["LenschRenderer", "LenschScene", "build_lensch", "irradiance_atlas", "refine_first_mm", "render_lensch"]


def refine_first_mm(mesh: Mesh, material: nn.Module, crease_deg: float | None = CREASE_DEG) -> float | None:
    """``refine_mm="auto"``: half the profile's shortest length (its 1% spacing), or None without features.

    None where the mesh has no crease or open boundary (:func:`~torchsss.geometry.refine.feature_edges`) or the
    profile has no ``spacing``; the rows then start at about half the shortest mean free path (cream 0.08 mm,
    marble 0.19 mm, ketchup 0.28 mm), where the radiosity beside a lit crease varies fastest.
    """
    spacing = getattr(material, "spacing", None)
    if not callable(spacing):
        return None
    if feature_edges(mesh, CREASE_DEG if crease_deg is None else crease_deg).shape[0] == 0:
        return None
    with torch.no_grad():
        return 0.5 * float(spacing(0.01).min())


@dataclass
class LenschScene:
    """What :func:`build_lensch` precomputes for one mesh and material."""

    mesh: Mesh
    atlas: Atlas
    module: LenschTranslucency
    stats: dict
    #: :math:`(F, 3)` the vertex (hat) of every face corner: ``mesh``'s faces on the copies parted at creases
    hat_faces: Tensor | None = None
    #: :math:`(F,)` with ``refine_mm``: the face of the mesh given to :func:`build_lensch` each face lies in
    parent_faces: Tensor | None = None


def build_lensch(mesh: Mesh, material: Material | nn.Module, *, resolution: int = 512, kernel_size: int | None = None,
                 threshold: float = THROUGHPUT_THRESHOLD, relative: bool = True, blend: bool | None = None,
                 max_entries: int | None = MAX_THROUGHPUT_ENTRIES, progress: bool = False,
                 detail: bool = True, layout: str = "auto", crease_deg: float | None = CREASE_DEG,
                 refine_mm: float | str | None = None) -> LenschScene:
    """Precompute everything the per-frame Lensch module needs (see the module docstring).

    ``material`` is a :class:`~torchsss.physics.Material` record, a preset name or a profile module (shared by the
    module: its parameters receive gradients). ``kernel_size=None`` and ``blend=None`` (defaults) are planned from
    the vertex spacing and the texel size (:func:`~torchsss.geometry.lensch.plan_lensch`: blending with a kernel
    that reaches ~0.7 median edges, 7 for Lensch's meshes and up to 11 for coarse ones; no blending, k = 7, when no
    kernel up to 11 reaches half an edge). Without blending the kernel only has to hold the near field and 7 is
    used. ``max_entries`` caps the throughput's size
    (:func:`~torchsss.geometry.lensch.check_entries`; None: no cap). ``detail`` (unblended only, default): the
    throughput's near entries are integrated over the source hats
    (:func:`~torchsss.geometry.lensch.hat_quadrature`) and the local kernels answer only the irradiance's detail
    beyond what the hats carry (:class:`~torchsss.modules.lensch.LenschTranslucency`), so the near field is counted
    once; False keeps Lensch's plain sum :math:`B^l + B^g` with point-sampled entries (measurable, as ``blend``).
    Measured against the reference at 256 x 256, atlas 1024, from the earlier first-order window overlap to this: a
    side-lit 30 mm marble sphere 2.61% -> 0.30% (image mean within 0.1%), a side-lit 30 mm marble torus 1.68% ->
    1.36%, the default scene at 128 x 128 1.62% -> 0.87%, the back-lit 20 mm skin2 spot 1.53% -> 0.62%, the
    side-lit 30 mm marble bunny 4.32% -> 2.70% (built on 5,907 of its 69k faces, as the throughput's cap allows:
    the reference with its sources on 5,360 faces is itself 2.7% off the full mesh's).

    ``crease_deg`` (default :data:`~torchsss.geometry.mesh.CREASE_DEG`, 60): the vertex hats are parted at edges whose
    faces turn by more than this (:func:`~torchsss.geometry.mesh.split_creases`: one copy of a vertex per smooth fan
    of its faces), so the irradiance may jump there and the light that enters a slab's rim stays on the rim's hats
    instead of spreading a hat's width into the face beside it; the atlas is built on ``mesh`` itself (the same
    faces). None: one hat per vertex, as Lensch. A scan has few such edges (the shared bunny 66 copies among 34,834
    vertices, the default scene 7: its image unchanged, 0.87% at 128 x 128); the spread's rim-lit 25 mm cream slab
    at 128 x 128 goes from 20.8% to 18.8% (largest error 40% -> 22%), the rest being the receivers' side: its
    radiosity varies within a few tenths of a millimetre of the lit edge, inside one hat of 1.1 mm, and the vertex
    values interpolated over the hats cannot follow it.

    ``refine_mm``: rows of vertices along the mesh's creases and open boundaries at graded distances from
    ``refine_mm`` on (:func:`~torchsss.geometry.refine.refine_creases`: ratio 1.6, reach 3 edges), built before
    everything else (the returned scene's ``mesh`` is the refined one; blending is not planned on it, and its hat
    quadrature keeps the rules of the coarse edges). ``"auto"``: half the profile's shortest length
    (:func:`refine_first_mm`) where the mesh has such edges, the grading coarsened (its ratio's excess over 1 grown
    by 1.5x a step) until the throughput's estimate fits ``max_entries`` (none if nothing does); None (default here,
    ``"auto"`` in :class:`LenschRenderer`): the mesh as it is. Beside a crease lit on its other side the radiosity
    varies within tenths of a millimetre, inside one hat (see ``crease_deg``): on the spread's rim-lit 25 mm cream
    slab at 256 x 256 (atlas 1024) the rows (578 -> 3,126 vertices at ratio 2.35, 9.2M entries) take Lensch from
    18.8% to 3.06% (4.1% with the rows interpolated linearly), ``benchmarks/results/spread_lensch_refine.md``.

    ``layout``: the throughput's storage, ``"sparse"`` (:func:`~torchsss.geometry.lensch.build_throughput`),
    ``"dense"`` (:func:`~torchsss.geometry.lensch.build_dense_throughput`, without ``detail``'s hat quadrature, which
    indexes sparse entries) or ``"auto"`` (default): dense where it is the smaller one
    (:func:`~torchsss.geometry.lensch.throughput_layout`, from the estimated entries) and no hat quadrature is
    built. The default scene (2,930 vertices, 74% of the pairs kept) builds dense at atlas 512 (blended): the same
    values, the build's peak resident set 1.25 -> 0.94 GB, the first frame's 1.66 -> 1.36 GB, a relit frame 0.50 ->
    0.38 s (``benchmarks/bench_lensch_memory.py``).
    """
    if not isinstance(detail, bool):
        raise TypeError(f"detail: expected a bool, got {type(detail).__name__}")
    mat = material_module(material, dtype=None if isinstance(material, nn.Module) else mesh.vertices.dtype,
                          device=mesh.vertices.device)
    coarse, parent = mesh, None
    crease_split = CREASE_DEG if crease_deg is None else crease_deg
    auto = isinstance(refine_mm, str)
    if auto:
        if refine_mm != "auto":
            raise ValueError(f"refine_mm: expected a length in mm, 'auto' or None, got {refine_mm!r}")
        refine_mm = refine_first_mm(mesh, mat, crease_deg) if detail and not blend else None
    elif refine_mm is not None and (isinstance(refine_mm, bool) or not isinstance(refine_mm, numbers.Real)):
        raise TypeError(f"refine_mm: expected a length in mm, 'auto' or None, got {type(refine_mm).__name__}")
    ratio = REFINE_RATIO
    cut_area = None
    if refine_mm is not None:
        if not detail:
            raise ValueError("refine_mm: expected None with detail=False (a graded mesh needs the hat quadrature), "
                             f"got {refine_mm!r}")
        if blend:
            raise ValueError("blend: expected False or None with refine_mm (the blending fit is not made on a graded "
                             "mesh), got True")
        # a refined mesh's fine hats keep the coarse hats' reach (build_throughput's cut_area)
        cut_area = float((coarse if crease_deg is None else split_creases(coarse, crease_deg)[0])
                         .vertex_areas.detach().median())
        while True:
            mesh, parent = refine_creases(coarse, refine_mm, ratio=ratio, crease_deg=crease_split)
            if not auto or max_entries is None or mesh is coarse:
                break
            # "auto" plans rows that fit the throughput's cap: coarser grading until they do, none if nothing fits
            fine = mesh if crease_deg is None else split_creases(mesh, crease_deg)[0]
            if estimate_throughput_entries(fine, mat, threshold=threshold, relative=relative,
                                           cut_area=cut_area) <= max_entries:
                break
            ratio = 1.0 + 1.5 * (ratio - 1.0)
            if ratio > 4.0:
                mesh, parent = coarse, None
                break
        if mesh is coarse:
            refine_mm, cut_area = None, None
    blend = False if refine_mm is not None else blend
    # the vertex hats parted at creases: the atlas stays on ``mesh`` (same faces), everything per vertex on the copies
    hat_mesh = mesh if crease_deg is None else split_creases(mesh, crease_deg)[0]
    if layout not in ("auto", "dense", "sparse"):
        raise ValueError(f"layout: expected 'auto', 'dense' or 'sparse', got {layout!r}")
    stats: dict = {"refine_mm": refine_mm, "refine_ratio": None if refine_mm is None else ratio,
                   "refined_vertices": mesh.num_vertices - coarse.num_vertices}
    # the throughput's size first, before the atlas: a ValueError that says how far to decimate
    stats["throughput_estimate"] = check_entries(hat_mesh, mat, threshold=threshold, relative=relative,
                                                 max_entries=max_entries, cut_area=cut_area)
    if blend is None:
        planned_k, blend = plan_lensch(mesh, resolution)
        if kernel_size is None:
            kernel_size = planned_k
    if kernel_size is None:
        kernel_size = plan_kernel_size(mesh, resolution) if blend else 7
    stats.update(kernel_size=kernel_size, blend=blend)
    if layout == "dense" and detail and not blend:
        raise ValueError("layout: expected 'sparse' or 'auto' with detail=True and no blending (the hat quadrature "
                         "indexes a sparse throughput's entries), got 'dense'")
    t0 = time.perf_counter()
    atlas = build_atlas(mesh, resolution, kernel_size=kernel_size, progress=progress)
    stats["t_atlas_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    receivers = atlas.valid_mask[0, 0].reshape(-1).nonzero(as_tuple=True)[0]  # the texels that hold kernels
    weights = vertex_weights(hat_mesh, atlas, discrete=not blend)  # the blending fit is made against the continuum
    detail = detail and not blend
    if layout == "auto":
        entries = stats["throughput_estimate"]
        if entries is None:
            entries = estimate_throughput_entries(hat_mesh, mat, threshold=threshold, relative=relative,
                                                  cut_area=cut_area)
        channels = int(mat(mesh.vertices.new_ones(1, 1)).shape[-1])
        layout = "sparse" if detail else throughput_layout(hat_mesh.num_vertices, entries, channels)
    if layout == "dense":
        tp = build_dense_throughput(hat_mesh, mat, threshold=threshold, relative=relative, zero_diagonal=blend,
                                    max_pairs=None)
        nnz = int(tp.keep.sum())
    else:
        tp = build_throughput(hat_mesh, mat, threshold=threshold, relative=relative, zero_diagonal=blend,
                              max_entries=None, progress=progress, cut_area=cut_area)
        nnz = int(tp.rows.shape[0])
    stats.update(t_kernels_throughput_s=time.perf_counter() - t1, nnz=nnz, layout=layout,
                 vertices=hat_mesh.num_vertices, split_vertices=hat_mesh.num_vertices - mesh.num_vertices,
                 cutoff_mm=tp.cutoff_mm)
    direct = correction = None
    if blend:
        t2 = time.perf_counter()
        bw = blending_weights(hat_mesh, atlas, mat, kernel_size=kernel_size, threshold=threshold, relative=relative,
                              index=receivers, progress=progress)
        direct, correction = bw.weights, bw.kernel_correction
        stats["t_blending_s"] = time.perf_counter() - t2
    hat = None
    if detail:
        t3 = time.perf_counter()
        spacing = getattr(mat, "spacing", None)
        hat = hat_quadrature(hat_mesh, tp, scale_mm=float(spacing(0.01).min()) if callable(spacing) else None)
        stats.update(t_hat_s=time.perf_counter() - t3, hat_entries=int(hat.entries.numel()),
                     hat_terms=int(hat.term_entry.numel()))
    stats["detail"] = detail
    stats["crease_deg"] = crease_deg
    # the kernels' taps derived from the atlas's maps whenever the kernels are evaluated (not stored)
    local = LocalResponse.from_atlas(atlas, kernel_size, mat, correction=correction)
    glob = GlobalResponse(weights, tp, mat, atlas.valid_mask, hat=hat, copy=False)  # the throughput handed over
    module = LenschTranslucency(local, glob, direct=direct, detail=detail)
    stats["t_precompute_s"] = time.perf_counter() - t0
    return LenschScene(mesh, atlas, module, stats, hat_faces=hat_mesh.faces,
                       parent_faces=None if mesh is coarse else parent)


class LenschRenderer(Renderer):
    """Lensch et al. 2002 (module docstring): build atlas, kernels, throughput (and blending) once; relight frames.

    Knobs:
        atlas_resolution: texture atlas size (texels).
        kernel_size: local kernel size k (odd); None plans it from the vertex spacing (5-11).
        threshold: throughput threshold (relative to the largest self throughput unless ``relative`` is False).
        relative: see ``threshold``.
        blend: the local/global blending of §5.4 (None: planned from the vertex spacing).
        shadow_resolution: size of each light's shadow map for the irradiance atlas.
        specular: add the shadow-mapped GGX boundary reflection.
        roughness: GGX alpha of ``specular``.
        max_entries: cap of the vertex throughput's entries (ValueError beyond it).
        detail: unblended only: the throughput's near entries integrated over the source hats and the local
            kernels on the irradiance's detail (no near field counted twice; :func:`build_lensch`).
        source_faces: build the atlas, kernels and throughput on the mesh decimated to about this many faces
            while the camera sees the full mesh (:mod:`torchsss.pipelines.atlas_view`); None: the mesh itself.
        layout: the throughput's storage, ``"auto"``, ``"dense"`` or ``"sparse"`` (:func:`build_lensch`).
        crease_deg: the vertex hats are parted at edges whose faces turn by more than this (degrees; None: never;
            :func:`build_lensch`).
        refine_mm: rows of vertices graded towards the creases and open boundaries from this distance (mm) on;
            ``"auto"`` (default): from the profile's shortest length where the mesh has such edges; None: none
            (:func:`build_lensch`).
        interpolation: how the vertex radiosity is read at a pixel (:func:`~torchsss.ops.interp.
            barycentric_interpolate`): ``"adaptive"`` (default: linear where a face's corners agree, their geometric
            mean where they differ by 2x or more, exact for the exponential fall-off beside a lit crease),
            ``"geometric"`` or ``"linear"``. Unblended scenes only; a blended one reads the whole radiosity from the
            atlas.
    """

    method = "lensch"
    defaults: ClassVar[dict] = dict(atlas_resolution=512, kernel_size=None, threshold=THROUGHPUT_THRESHOLD,
                                    relative=True, blend=None, shadow_resolution=1024, specular=False, roughness=0.3,
                                    max_entries=MAX_THROUGHPUT_ENTRIES, source_faces=None, detail=True,
                                    layout="auto", crease_deg=CREASE_DEG, refine_mm="auto",
                                    interpolation="adaptive")

    @classmethod
    def from_built(cls, built: LenschScene, **knobs) -> LenschRenderer:
        """A renderer around an existing :func:`build_lensch` result (no new setup)."""
        fixed = {"kernel_size": int(built.module.local.kernel_size), "blend": built.module.direct is not None,
                 "detail": built.module.detail, "layout": "dense" if built.module.global_response.dense else "sparse",
                 "crease_deg": built.stats.get("crease_deg", CREASE_DEG), "refine_mm": built.stats.get("refine_mm")}
        return super().from_built(built, **{**knobs, **fixed})

    def _build(self) -> None:
        k = self.knobs
        if k["interpolation"] not in ("linear", "geometric", "adaptive"):
            raise ValueError(f"interpolation: expected 'linear', 'geometric' or 'adaptive', got "
                             f"{k['interpolation']!r}")
        self.source_mesh = source_mesh(self.mesh, k["source_faces"])
        self.built = build_lensch(self.source_mesh, self.material, resolution=k["atlas_resolution"],
                                  kernel_size=k["kernel_size"], threshold=k["threshold"], relative=k["relative"],
                                  blend=k["blend"], max_entries=k["max_entries"], progress=self.progress,
                                  detail=k["detail"], layout=k["layout"], crease_deg=k["crease_deg"],
                                  refine_mm=k["refine_mm"])
        k["refine_mm"] = self.built.stats["refine_mm"]
        self.source_mesh = self.built.mesh  # the refined mesh the atlas is built on
        k["kernel_size"] = int(self.built.module.local.kernel_size)
        k["blend"] = self.built.module.direct is not None
        k["layout"] = self.built.stats["layout"]
        self.module = self.built.module
        self.atlas = self.built.atlas
        refined = self.built.parent_faces is not None
        # a refinement of the mesh in view maps by its faces' parents; of a decimated copy, by closest points
        self.view = AtlasView(self.mesh, self.source_mesh, self.atlas,
                              parent=self.built.parent_faces if refined and k["source_faces"] is None else None)
        self.view.lit_texels()  # built with the setup

    def _render(self, lights: list[Light], camera: Camera) -> RenderResult:
        k, mesh, eta = self.knobs, self.mesh, self.eta
        gbuf = camera_gbuffer(mesh, camera)
        t0 = time.perf_counter()
        times = {}

        hat_faces = self.built.hat_faces
        pixel_exact = hat_faces is not None and self.module.albedo is None

        def radiosity_atlas() -> Tensor | tuple[Tensor, Tensor]:  # depends on the lights and the material alone
            e = irradiance_atlas(self.mesh, self.atlas, lights, eta, shadow_resolution=k["shadow_resolution"],
                                 texels=self.view.lit_texels())
            times["t1"] = time.perf_counter()
            return self.module.split(e) if pixel_exact else self.module(e)

        b_atlas, reused = self._per_lights("radiosity_atlas", lights, radiosity_atlas, (k["shadow_resolution"],))
        t2 = time.perf_counter()
        t1 = times.get("t1", t0)
        mask = gbuf.mask
        uv = self.view.uv(camera, gbuf.position, mask, gbuf.face_id)
        if pixel_exact:
            # the local kernels' part read from the atlas, the vertex radiosity interpolated at each pixel's own
            # point of the hat mesh (no texel between it and the pixel: beside a lit crease the radiosity changes
            # by half within a tenth of a millimetre, a few texels)
            local, vert = b_atlas
            face, bary = self.view.source_points(camera, gbuf.face_id, gbuf.position, mask)
            glob = barycentric_interpolate(vert, hat_faces[face], bary, k["interpolation"])  # (B, P, C)
            b = self.atlas.sample(local, uv)
            where = mask[0, 0].reshape(-1).nonzero().squeeze(1)  # row-major, as source_points
            n_b, n_c, h, w = b.shape
            glob_img = b.new_zeros(n_b, n_c, h * w).index_copy(2, where, glob.transpose(1, 2).to(b.dtype))
            b = (b + glob_img.view(n_b, n_c, h, w)) * mask
        else:
            b = self.atlas.sample(b_atlas, uv) * mask
        cos_o = view_cosine(gbuf)
        radiance = exit_radiance(b, cos_o, eta) * mask
        if k["specular"]:
            radiance = radiance + shadow_mapped_specular(mesh, gbuf, lights, eta, roughness=k["roughness"])
        stats = dict(self.built.stats)
        stats.update(t_irradiance_s=t1 - t0, t_module_s=t2 - t1, t_image_s=time.perf_counter() - t2,
                     atlas_resolution=self.atlas.resolution, kernel_size=k["kernel_size"],
                     threshold=k["threshold"], blend=k["blend"], relit=not reused)
        return RenderResult(radiance, b, mask, stats)


def render_lensch(mesh: Mesh, material: Material | nn.Module, lights: Sequence[Light], camera: Camera, *,
                  resolution: int = 512, dtype: torch.dtype = torch.float32, progress: bool = False,
                  prebuilt: LenschRenderer | LenschScene | None = None, **knobs) -> RenderResult:
    """Render one frame with the Lensch method; ``stats`` separate ``setup_s`` and ``frame_s``.

    ``resolution`` is the atlas resolution (the ``atlas_resolution`` knob of :class:`LenschRenderer`); other knobs
    as there. ``prebuilt`` reuses a :class:`LenschRenderer` (relighting, new views, material edits on its
    ``material``).
    """
    if isinstance(prebuilt, LenschScene):
        prebuilt = LenschRenderer.from_built(prebuilt, **knobs)
    renderer = prebuilt or LenschRenderer(mesh, material, dtype=dtype, progress=progress,
                                          atlas_resolution=resolution, **knobs)
    res = renderer.render(lights, camera)
    res.stats.update(t_precompute_s=res.stats.get("t_precompute_s", renderer.setup_s), t_frame_s=res.stats["frame_s"])
    return res
