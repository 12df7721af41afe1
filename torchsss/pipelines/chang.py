"""Render with Chang et al. 2008: texture-space importance sampling (``icdf``) and the hybrid split (``hybrid``).

Build (timed as ``precompute``): the texture atlas and the module (:class:`~torchsss.modules.chang.
ImportanceSampledTranslucency`, or :class:`~torchsss.modules.chang.HybridTranslucency` with its split radius,
filter pattern and per-texel tangent frames). Per frame (timed as ``frame``): the shadow-mapped irradiance atlas
(:func:`~torchsss.pipelines.lensch.irradiance_atlas`), ``N`` uniforms (scrambled Sobol or pseudo-random), the
module evaluated at the camera pixels' surface positions (all pixels share the same samples, as in the paper),
:math:`L = F_t(\\eta, \\omega_o)/\\pi \\; B`.

The estimate is unbiased for the atlas quadrature of the surface integral (the irradiance is shadow-mapped and
piecewise constant per texel); its noise falls like :math:`1/\\sqrt{N}`.
"""

from __future__ import annotations

import math
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
from torchsss.geometry.lights import Light
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.neighbours import ball_pairs
from torchsss.geometry.sampling import faces_for_spacing, surface_samples
from torchsss.geometry.transfer import SurfaceLocator, transferred_uv
from torchsss.modules.chang import HybridTranslucency, ImportanceSampledTranslucency, SurfaceLocal
from torchsss.modules.material import material_module
from torchsss.ops.reference import DEFAULT_MAX_PAIRS
from torchsss.physics.budget import chang_rp
from torchsss.physics.fresnel import exit_radiance
from torchsss.physics.materials import Material
from torchsss.pipelines.atlas_view import AtlasView, source_mesh
from torchsss.pipelines.coarse import coarse_receivers
from torchsss.pipelines.reference import default_spacing
from torchsss.pipelines.renderer import Renderer, RenderResult
from torchsss.pipelines.specular import shadow_mapped_specular

__all__ = ["ChangScene", "HybridRenderer", "IcdfRenderer", "build_hybrid", "build_icdf", "profile_rp",
           "render_hybrid", "render_icdf", "sample_uniforms"]


@dataclass
class ChangScene:
    """What :func:`build_icdf` / :func:`build_hybrid` precompute for one mesh and material.

    ``local`` and ``sample_position`` (:math:`(N, 3)` mm): the hybrid's :class:`~torchsss.modules.chang.SurfaceLocal`
    and its surface samples (``local="surface"``); None otherwise.
    """

    mesh: Mesh
    atlas: Atlas
    module: nn.Module
    stats: dict
    local: SurfaceLocal | None = None
    sample_position: Tensor | None = None


def sample_uniforms(n: int, *, seed: int = 0, sobol: bool = True, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None) -> Tensor:
    """:math:`(1, N, 2)` uniforms in [0, 1): scrambled Sobol (default) or pseudo-random.

    Each seed scrambles the Sobol sequence differently, so every point is uniform and the estimator stays unbiased.

    Examples:
        >>> u = sample_uniforms(8, seed=1)
        >>> tuple(u.shape), bool((u >= 0).all() and (u < 1).all())
        ((1, 8, 2), True)
    """
    if isinstance(n, bool) or not isinstance(n, int):
        raise TypeError(f"samples: expected an int >= 1, got {type(n).__name__}")
    if n < 1:
        raise ValueError(f"samples: expected an int >= 1, got {n}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"seed: expected an int, got {type(seed).__name__}")
    if sobol:
        u = torch.quasirandom.SobolEngine(2, scramble=True, seed=seed).draw(n, dtype=torch.float64)
    else:
        u = torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    u = u.to(dtype).clamp(0.0, 1.0 - torch.finfo(dtype).eps / 2)  # rounding to float32 must not reach 1
    return u.unsqueeze(0).to(device)


def profile_rp(profile: nn.Module, c: float = 0.1, grid: int = 2048) -> float:
    """Chang's split radius :math:`R_p` of any profile: the largest r with :math:`\\max_c R_d(r)\\,2\\pi r \\ge c`.

    :func:`torchsss.physics.chang_rp` in closed form for the dipole; for any module of the profile contract the
    importance is evaluated on a log grid up to the module's ``r_max(1e-6)`` and the last crossing is bisected.
    0 where the importance never reaches ``c`` (everything global).

    Examples:
        >>> from torchsss.modules import BurleyMaterial
        >>> round(profile_rp(BurleyMaterial.from_preset("skin1"), 0.1), 2) > 0
        True
    """
    if isinstance(c, bool) or not isinstance(c, (int, float)) or not c > 0:
        raise ValueError(f"c: expected a number > 0, got {c!r}")
    hi = float(profile.r_max(1e-6).max())
    lo = hi * 1e-7

    def importance(r: Tensor) -> Tensor:
        with torch.no_grad():
            return 2.0 * math.pi * r[:, 0] * profile(r).detach().to(torch.float64).amax(-1)

    dev = profile.eta.device
    rs = torch.logspace(math.log10(lo), math.log10(hi), grid, dtype=torch.float64, device=dev).unsqueeze(-1)
    above = torch.nonzero(importance(rs) >= c).flatten()
    if above.numel() == 0:
        return 0.0
    i = int(above[-1])
    if i == grid - 1:
        return hi
    a, b = float(rs[i]), float(rs[i + 1])
    for _ in range(60):
        m = 0.5 * (a + b)
        if float(importance(torch.tensor([[m]], dtype=torch.float64, device=dev))[0]) >= c:
            a = m
        else:
            b = m
    return a


def build_icdf(mesh: Mesh, material: Material | nn.Module, *, atlas_resolution: int = 512, kernel_size: int = 7,
               levels: int | None = None, max_pairs: int = DEFAULT_MAX_PAIRS, progress: bool = False) -> ChangScene:
    """Atlas + :class:`~torchsss.modules.chang.ImportanceSampledTranslucency` for ``mesh`` in ``material``."""
    t0 = time.perf_counter()
    mat = material_module(material, dtype=None if isinstance(material, nn.Module) else mesh.vertices.dtype,
                          device=mesh.vertices.device)
    atlas = build_atlas(mesh, atlas_resolution, kernel_size=kernel_size, progress=progress)
    t1 = time.perf_counter()
    module = ImportanceSampledTranslucency.from_atlas(atlas, mat, levels=levels, max_pairs=max_pairs)
    stats = dict(t_atlas_s=t1 - t0, t_precompute_s=time.perf_counter() - t0)
    return ChangScene(mesh, atlas, module, stats)


def build_hybrid(mesh: Mesh, material: Material | nn.Module, *, atlas_resolution: int = 512, kernel_size: int = 7,
                 rings: int = 8, per_ring: int = 16, c: float = 0.1, k: float = 1.5, local_eps: float | None = None,
                 levels: int | None = None, max_pairs: int = DEFAULT_MAX_PAIRS, max_reach: float | None = 0.8,
                 local: str = "surface", local_spacing_mm: float | None = None, progress: bool = False) -> ChangScene:
    """Atlas + :class:`HybridTranslucency` for ``mesh`` in ``material``.

    ``kernel_size`` sets the atlas gutters (``kernel_size // 2`` texels). The split radius is Chang's closed form
    for a dipole and :func:`profile_rp` for other profiles.

    **The local term.** ``local="surface"`` (default): gathered in 3-D from surface samples at
    ``local_spacing_mm`` (default the reference's spacing of the material, :func:`~torchsss.pipelines.reference.
    default_spacing`) within the local bound of every receiver (:class:`~torchsss.modules.chang.SurfaceLocal`), and
    the global term takes :math:`R_d (1 - W_l^b)` for every pair; the default ``local_eps`` is then 1e-2 (the bound
    4.4 instead of 6.0 mm on the default scene, half the pairs, the same error). ``local="atlas"``: Chang's filter
    of ``rings`` x ``per_ring`` + 1 atlas lookups with the chart-aware global term (``local_eps`` 1e-3), which hands
    the near field across every chart seam to the sampled global term. Default scene at 128 x 128: N = 8192, 1.94%
    relative RMSE with the atlas filter (6.2% within 1 mm of a chart edge, 1.7% elsewhere: speckled seams), 0.53%
    gathered over the surface (0.8% and 0.7%); N = 2048, 6.6% and 2.3%.

    **Only where the scene allows it.** The local filter takes the surface as its tangent plane out to the local
    bound :math:`r_b`; on an object not much larger than :math:`r_b` that is false (measured: a 12 mm skin1 sphere,
    :math:`r_b` = 6 mm, blue 4% low; a 10 mm skin1 head scan 2-7% high). When :math:`r_b` exceeds ``max_reach``
    times the object's radius (the largest distance of a vertex from the bounding box's centre), the split is off
    (:math:`R_p = 0`: everything is importance-sampled, the icdf estimator) and ``stats["split"]`` says why;
    ``max_reach=None`` keeps the split whatever the size.
    """
    if max_reach is not None and (isinstance(max_reach, bool) or not isinstance(max_reach, (int, float))
                                  or not max_reach > 0):
        raise ValueError(f"max_reach: expected a number > 0 or None, got {max_reach!r}")
    if local not in ("surface", "atlas"):
        raise ValueError(f"local: expected 'surface' or 'atlas', got {local!r}")
    if local_eps is None:
        local_eps = 1e-2 if local == "surface" else 1e-3
    t0 = time.perf_counter()
    mat = material_module(material, dtype=None if isinstance(material, nn.Module) else mesh.vertices.dtype,
                          device=mesh.vertices.device)
    atlas = build_atlas(mesh, atlas_resolution, kernel_size=kernel_size, progress=progress)
    t1 = time.perf_counter()
    split = {} if hasattr(mat, "sigma_s_prime") else {"r_p": profile_rp(mat, c)}
    module = HybridTranslucency.from_atlas(atlas, mat, c=c, k=k, rings=rings, per_ring=per_ring,
                                           local_eps=local_eps, levels=levels, max_pairs=max_pairs, **split)
    centre = 0.5 * (mesh.vertices.amax(0) + mesh.vertices.amin(0))
    radius = float((mesh.vertices - centre).norm(dim=-1).amax())
    reason = f"on: local bound {module.bound:.2f} mm, object radius {radius:.2f} mm"
    if max_reach is not None and module.bound > max_reach * radius:
        why = "the filter's flat-surface assumption fails" if local == "atlas" else \
            "the local region would hold most of the object: the all-pairs sum, not a split"
        reason = (f"off: the local bound {module.bound:.2f} mm exceeds {max_reach} x the object's radius "
                  f"{radius:.2f} mm ({why}); every source is sampled")
        module = HybridTranslucency.from_atlas(atlas, mat, r_p=0.0, k=k, rings=rings, per_ring=per_ring,
                                               local_eps=local_eps, levels=levels, max_pairs=max_pairs)
    stats = dict(t_atlas_s=t1 - t0, r_p_mm=module.r_p, local_bound_mm=module.bound, rings=rings,
                 per_ring=per_ring, split=reason, local=local, local_eps=local_eps)
    surface = position = None
    if local == "surface" and module.bound > 0:
        spacing = default_spacing(mat, mesh) if local_spacing_mm is None else float(local_spacing_mm)
        if not (math.isfinite(spacing) and spacing > 0):
            raise ValueError(f"local_spacing_mm: expected a finite number > 0 or None, got {local_spacing_mm!r}")
        # a finely tessellated mesh holds a sample per face whatever the spacing: decimated to the spacing first
        sample_mesh = source_mesh(mesh, faces_for_spacing(mesh.area, spacing))
        samples = surface_samples(sample_mesh, spacing)
        if sample_mesh is mesh:
            uv = (samples.bary.unsqueeze(-1).to(atlas.face_uvs.dtype) * atlas.face_uvs[samples.face_id]).sum(1)
        else:  # samples on the decimated copy read the atlas at their closest points on the atlas's own mesh
            n = samples.position.shape[0]
            as_image = samples.position.T.reshape(1, 3, 1, n)
            covered = torch.ones(1, 1, 1, n, dtype=torch.bool, device=as_image.device)
            uv = transferred_uv(SurfaceLocator(mesh), atlas.face_uvs, as_image, covered)[0, :, 0].T
        surface = SurfaceLocal(uv, samples.area.to(mesh.vertices.dtype), atlas.valid_mask, mat, module.local_weight)
        position = samples.position
        stats.update(local_spacing_mm=spacing, local_samples=int(samples.area.shape[0]))
    stats["t_precompute_s"] = time.perf_counter() - t0
    return ChangScene(mesh, atlas, module, stats, surface, position)


class IcdfRenderer(Renderer):
    """Chang et al.'s texture-space importance sampling (module docstring): atlas once, ``samples`` per frame.

    Knobs:
        samples: importance samples N per frame (error ~ 1/sqrt(N)).
        atlas_resolution: texture atlas size (texels).
        seed: seed of the scrambled Sobol (or pseudo-random) uniforms.
        sobol: scrambled Sobol uniforms (True) or pseudo-random ones.
        levels: pyramid depth of the sampler (None: from the atlas size).
        max_pairs: pair budget of one chunk of the gather-sum.
        shadow_resolution: size of each light's shadow map for the irradiance atlas.
        specular: add the shadow-mapped GGX boundary reflection.
        roughness: GGX alpha of ``specular``.
        source_faces: build the atlas on the mesh decimated to about this many faces while the camera sees the
            full mesh (:mod:`torchsss.pipelines.atlas_view`); None: the mesh itself.
        stride: evaluate the sampled (global) term at every ``stride``-th pixel and interpolate it where the surface
            is smooth, exactly at edges (:mod:`torchsss.pipelines.coarse`, as the reference's ``stride``); None
            (default): the supersampling factor of ``render(..., spp=s * s, subpixel="exact")``, so a supersampled
            frame evaluates it about once per pixel where the surface is smooth and on every sub-pixel at edges;
            1: every pixel.
        refine: with ``stride`` > 1, an interpolated pixel whose grid corners differ by more than this (relative)
            is evaluated exactly.
    """

    method = "icdf"
    hybrid = False
    defaults: ClassVar[dict] = dict(samples=4096, atlas_resolution=512, seed=0, sobol=True, levels=None,
                                    max_pairs=DEFAULT_MAX_PAIRS, shadow_resolution=1024, specular=False,
                                    roughness=0.3, source_faces=None, stride=None, refine=0.2)

    def _build(self) -> None:
        k = self.knobs
        self.source_mesh = source_mesh(self.mesh, k["source_faces"])
        self.built = build_icdf(self.source_mesh, self.material, atlas_resolution=k["atlas_resolution"],
                                levels=k["levels"], max_pairs=k["max_pairs"], progress=self.progress)
        self.atlas, self.module = self.built.atlas, self.built.module
        self.view = AtlasView(self.mesh, self.source_mesh, self.atlas)
        self.view.lit_texels()  # built with the setup

    def _render(self, lights: list[Light], camera: Camera) -> RenderResult:
        k, mesh, eta = self.knobs, self.mesh, self.eta
        gbuf = camera_gbuffer(mesh, camera)
        dtype, device = mesh.vertices.dtype, mesh.vertices.device
        t0 = time.perf_counter()
        e, reused = self._per_lights(  # depends on the lights and eta alone: kept while they stay
            "irradiance_atlas", lights,
            lambda: irradiance_atlas(self.mesh, self.atlas, lights, eta, shadow_resolution=k["shadow_resolution"],
                                     texels=self.view.lit_texels()).to(dtype), (k["shadow_resolution"],))
        t1 = time.perf_counter()
        u = sample_uniforms(k["samples"], seed=k["seed"], sobol=k["sobol"], dtype=dtype, device=device)
        mask = gbuf.mask[0, 0]
        h, w = camera.resolution
        pos_img = gbuf.position[0].permute(1, 2, 0)
        stride = self._supersample if k["stride"] is None else k["stride"]
        coarse = coarse_receivers(pos_img, gbuf.normal[0].permute(1, 2, 0), mask, stride)
        pos_flat = pos_img.reshape(-1, 3)
        plan = self._local_plan(camera, gbuf) if self.hybrid and self.built.local is not None else None
        local_used = None
        if self.hybrid:
            local_used = getattr(self, "_local_reason", "atlas") if self.built.local is not None else \
                ("none (the split is off: everything is sampled)" if self.module.bound <= 0 else "atlas")
        if plan is not None:
            def sampled(index: Tensor) -> Tensor:
                return plan[3].global_everywhere(e, u, pos_flat[index].unsqueeze(0))[0]
        elif self.hybrid:
            uv_flat = self.view.uv(camera, gbuf.position, gbuf.mask)[0].permute(1, 2, 0).reshape(-1, 2)

            def sampled(index: Tensor) -> Tensor:
                return self.module(e, u, pos_flat[index].unsqueeze(0), uv_flat[index].unsqueeze(0))[0]
        else:
            def sampled(index: Tensor) -> Tensor:
                return self.module(e, u, pos_flat[index].unsqueeze(0))[0]
        b = sampled(coarse.evaluate)
        exact = coarse.refine(b, k["refine"])  # interpolated pixels whose corners disagree: evaluated exactly
        image = coarse.scatter(b, h, w, exact, sampled(coarse.fill[exact]) if exact.numel() else None)
        if plan is not None and plan[0] > 0:
            image[mask] = image[mask] + self._surface_local(e, gbuf, plan)
        t2 = time.perf_counter()
        radiosity = image.permute(2, 0, 1).unsqueeze(0)
        cos_o = view_cosine(gbuf)
        radiance = exit_radiance(radiosity, cos_o, eta) * gbuf.mask
        if k["specular"]:
            radiance = radiance + shadow_mapped_specular(mesh, gbuf, lights, eta, roughness=k["roughness"])
        stats = dict(self.built.stats)
        stats.update(t_irradiance_s=t1 - t0, t_module_s=t2 - t1, t_image_s=time.perf_counter() - t2,
                     atlas_resolution=self.atlas.resolution, samples=k["samples"],
                     receivers=int(coarse.evaluate.numel() + exact.numel()),
                     interpolated=int(coarse.fill.numel() - exact.numel()), sobol=k["sobol"], seed=k["seed"],
                     relit=not reused)
        if self.hybrid:
            stats["local_term"] = local_used
            if plan is not None:
                stats.update(local_stride=plan[0], local_pairs=int(plan[2][0].numel()) if plan[2] else 0,
                             local_exact=getattr(self, "_local_exact", 0), local_c=plan[5],
                             local_bound_mm=plan[3].bound, r_p_mm=plan[3].r_p)
        return RenderResult(radiance, radiosity, gbuf.mask, stats)


#: The pixel strides the hybrid's surface local term tries, finest first (:meth:`HybridRenderer._local_plan`).
LOCAL_STRIDES = (1, 2, 3, 4, 6, 8)


class HybridRenderer(IcdfRenderer):
    """Chang et al.'s hybrid: an ``rings x per_ring + 1`` local filter plus ``samples`` global samples per frame.

    Knobs: those of :class:`IcdfRenderer`, and ``local`` (``"surface"``: the local term gathered in 3-D from surface
    samples, default; ``"atlas"``: Chang's filter of ``rings`` x ``per_ring`` + 1 atlas lookups; see
    :func:`build_hybrid`), ``local_spacing_mm`` (the surface samples' spacing; None: the reference's),
    ``max_local_pairs`` (the local term is evaluated on a pixel grid coarse enough that its receivers have at most
    this many sample pairs within the local bound, and interpolated between; a view that would need a stride above
    8 narrows the split instead, ``stats["local_term"]`` says so; about 36 bytes a pair), ``c`` (the split's
    importance bound, mm^-1), ``k`` (the blend width of W_l, W_g), ``local_eps`` (the local term's truncation; None:
    1e-2 for the surface, 1e-3 for the atlas filter), ``max_reach`` (the split is turned off on objects whose
    bounding radius is below local bound / max_reach; see :func:`build_hybrid`). ``stats`` also hold the split
    radius ``r_p_mm``, the local bound ``local_bound_mm`` and ``split`` (on or off, and why).
    """

    method = "hybrid"
    hybrid = True
    defaults: ClassVar[dict] = dict(IcdfRenderer.defaults, rings=8, per_ring=16, c=0.1, k=1.5, local_eps=None,
                                    max_reach=0.8, local="surface", local_spacing_mm=None,
                                    max_local_pairs=8_000_000)

    def _build(self) -> None:
        k = self.knobs
        self.source_mesh = source_mesh(self.mesh, k["source_faces"])
        self.built = build_hybrid(self.source_mesh, self.material, atlas_resolution=k["atlas_resolution"],
                                  rings=k["rings"], per_ring=k["per_ring"], c=k["c"], k=k["k"],
                                  local_eps=k["local_eps"], levels=k["levels"], max_pairs=k["max_pairs"],
                                  max_reach=k["max_reach"], local=k["local"], local_spacing_mm=k["local_spacing_mm"],
                                  progress=self.progress)
        self.atlas, self.module = self.built.atlas, self.built.module
        self.view = AtlasView(self.mesh, self.source_mesh, self.atlas)
        self.view.lit_texels()  # built with the setup
        self._plan_cache: tuple | None = None

    def _local_plan(self, camera: Camera, gbuf) -> tuple | None:
        """The surface local term's plan for this view: ``(stride, CoarseReceivers, pairs, module, local, c)``.

        Cached while the view stays.
        The local term is evaluated at every ``stride``-th pixel and interpolated where the surface is smooth
        (:func:`~torchsss.pipelines.coarse.coarse_receivers`; gaps and, per frame, terminators sharper than the grid
        are evaluated exactly), with the smallest stride whose receivers have at most ``max_local_pairs`` sample
        pairs within the local bound (estimated on 256 of them, then counted). Where even a stride of 8 does not
        fit, the split is narrowed: Chang's importance bound ``c`` doubles (up to 16x), which moves :math:`R_p` and
        the local bound inwards and more of the near field to the sampled global term, noisier but, with the
        local term over the surface, without seams. None when nothing fits: the view takes Chang's atlas filter,
        and the stats say why.
        """
        cache = getattr(self, "_plan_cache", None)
        if cache is not None and cache[0] == camera:
            return cache[1]
        mask = gbuf.mask[0, 0]
        pos = gbuf.position[0].permute(1, 2, 0)
        nrm = gbuf.normal[0].permute(1, 2, 0)
        samples = self.built.sample_position.to(pos.device)
        budget = self.knobs["max_local_pairs"]
        covered = pos[mask]
        from scipy.spatial import cKDTree

        tree = cKDTree(samples.detach().double().cpu().numpy())
        pick = covered[torch.randperm(covered.shape[0], generator=torch.Generator().manual_seed(0))[:256]]
        result = None
        self._local_reason = "atlas (fallback: no covered pixel)"
        for scale in (1, 2, 4, 8, 16):
            c = self.knobs["c"] * scale
            module, local = self._split(c)
            if module.bound <= 0:  # the split narrowed away: everything sampled, still no seam
                result = (0, None, None, module, None, c)
                self._local_reason = f"none (split narrowed away at c = {c:g}: every source sampled)"
                break
            per = float(tree.query_ball_point(pick.detach().double().cpu().numpy(), module.bound,
                                              return_length=True).mean()) if pick.shape[0] else 0.0
            first = next((i for i, st in enumerate(LOCAL_STRIDES) if covered.shape[0] / st**2 * per <= budget),
                         len(LOCAL_STRIDES))
            for stride in LOCAL_STRIDES[first:]:  # the estimate misses the edges evaluated exactly: the count decides
                # a 3-D gather is continuous across creases: only gaps (silhouettes, other surfaces) are edges here
                plan = coarse_receivers(pos, nrm, mask, stride, max_angle_deg=180.0)
                try:
                    pairs = ball_pairs(pos.reshape(-1, 3)[plan.evaluate], samples, module.bound,
                                       max_pairs=int(1.5 * budget))
                except ValueError as err:
                    self._local_reason = f"atlas (fallback: at c = {c:g}, stride {stride}: {err})"
                    continue
                result = (stride, plan, pairs, module, local, c)
                self._local_reason = "surface" if scale == 1 else \
                    f"surface (split narrowed to c = {c:g}: local bound {module.bound:.2f} mm, to fit the pairs)"
                break
            if result is not None:
                break
        self._plan_cache = (camera, result)
        return result

    def _split(self, c: float) -> tuple:
        """The split at importance bound ``c``: ``(HybridTranslucency, SurfaceLocal)`` (the built ones at the knob)."""
        if c == self.knobs["c"]:
            return self.module, self.built.local
        splits = self.__dict__.setdefault("_splits", {})
        if c not in splits:
            k = self.knobs
            mat = self.material
            eps = self.built.stats["local_eps"]
            if hasattr(mat, "sigma_s_prime"):
                with torch.no_grad():
                    r_p = float(chang_rp(mat.sigma_a.detach(), mat.sigma_s_prime.detach(), mat.eta.detach(),
                                         c=c).amax())
            else:
                r_p = profile_rp(mat, c)
            # the weight's tail shrinks with R_p (at most 2 R_p past it; at Chang's K it is ln(0.5/eps)/K, 2.6 mm
            # at eps 1e-2, which would keep the bound wide however small R_p gets)
            blend = max(k["k"], math.log(0.5 / eps) / (2.0 * r_p)) if r_p > 0 else k["k"]
            module = HybridTranslucency.from_atlas(
                self.atlas, mat, r_p=r_p, k=blend, rings=k["rings"], per_ring=k["per_ring"], local_eps=eps,
                levels=k["levels"], max_pairs=k["max_pairs"])
            local = self.built.local.with_weight(module.local_weight) if module.bound > 0 else None
            splits[c] = (module, local)
        return splits[c]

    def _surface_local(self, irradiance: Tensor, gbuf, plan: tuple) -> Tensor:
        """:math:`(M, C)` the surface local term at the covered pixels (row-major), from the view's plan."""
        stride, coarse, (rows, cols, dist), module, local, _ = plan
        b_eval = local(irradiance, rows, cols, dist.to(irradiance.dtype), int(coarse.evaluate.numel()))[0]
        h, w = gbuf.mask.shape[-2:]
        exact = coarse.refine(b_eval, self.knobs.get("refine", 0.2)) if stride > 1 else coarse.fill[:0]
        b_exact = None
        if exact.numel():
            pos = gbuf.position[0].permute(1, 2, 0).reshape(-1, 3)[coarse.fill[exact]]
            r2, c2, d2 = ball_pairs(pos, self.built.sample_position.to(pos.device), module.bound)
            # this frame's pairs only: not cached (they would evict the coarse pairs' weights, 2.4 of the marble
            # torus's 6 s frame at 128 x 128 went to recomputing those every frame)
            b_exact = local(irradiance, r2, c2, d2.to(irradiance.dtype), int(pos.shape[0]), cache=False)[0]
        self._local_exact = int(exact.numel())
        image = coarse.scatter(b_eval, h, w, exact, b_exact)  # (H, W, C)
        return image[gbuf.mask[0, 0]]


def _frame(cls: type[IcdfRenderer], mesh: Mesh, material, lights, camera, *, samples: int, dtype: torch.dtype,
           progress: bool, prebuilt: IcdfRenderer | ChangScene | None, **knobs) -> RenderResult:
    if isinstance(prebuilt, ChangScene):
        prebuilt = cls.from_built(prebuilt, **knobs)
    renderer = prebuilt or cls(mesh, material, dtype=dtype, progress=progress, samples=samples, **knobs)
    if prebuilt is not None:
        renderer.knobs.update(samples=samples, **{k: v for k, v in knobs.items() if k in ("seed", "sobol")})
    res = renderer.render(lights, camera)
    res.stats.update(t_precompute_s=res.stats.get("t_precompute_s", renderer.setup_s), t_frame_s=res.stats["frame_s"])
    return res


def render_icdf(mesh: Mesh, material: Material | nn.Module, lights: Sequence[Light], camera: Camera, *,
                samples: int = 1024, dtype: torch.dtype = torch.float32, progress: bool = False,
                prebuilt: IcdfRenderer | ChangScene | None = None, **knobs) -> RenderResult:
    """Render one frame with Chang's texture-space importance sampling (``samples`` = N); see :class:`IcdfRenderer`.

    ``stats`` separate ``setup_s`` (atlas) from ``frame_s`` (irradiance atlas + sampling + sum). ``prebuilt``
    reuses an :class:`IcdfRenderer` or a :func:`build_icdf` result (relighting, new views, material edits on its
    ``material``; ``samples``, ``seed`` and ``sobol`` may change per frame).
    """
    return _frame(IcdfRenderer, mesh, material, lights, camera, samples=samples, dtype=dtype, progress=progress,
                  prebuilt=prebuilt, **knobs)


def render_hybrid(mesh: Mesh, material: Material | nn.Module, lights: Sequence[Light], camera: Camera, *,
                  samples: int = 1024, dtype: torch.dtype = torch.float32, progress: bool = False,
                  prebuilt: HybridRenderer | ChangScene | None = None, **knobs) -> RenderResult:
    """Render one frame with Chang's hybrid (see :class:`HybridRenderer`)."""
    return _frame(HybridRenderer, mesh, material, lights, camera, samples=samples, dtype=dtype, progress=progress,
                  prebuilt=prebuilt, **knobs)
