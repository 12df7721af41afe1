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

import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchsss.geometry.atlas import Atlas, build_atlas
from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import camera_gbuffer
from torchsss.geometry.lights import Light
from torchsss.geometry.mesh import Mesh
from torchsss.modules.chang import HybridTranslucency, ImportanceSampledTranslucency
from torchsss.modules.lensch import LenschTranslucency
from torchsss.modules.material import DipoleMaterial
from torchsss.ops.reference import DEFAULT_MAX_PAIRS
from torchsss.pipelines.lensch import _camera_uv, irradiance_atlas
from torchsss.pipelines.reference import RenderResult
from torchsss.pipelines.specular import shadow_mapped_specular
from torchsss.scene import Material

__all__ = ["ChangScene", "build_hybrid", "build_icdf", "render_hybrid", "render_icdf", "sample_uniforms"]


@dataclass
class ChangScene:
    """What :func:`build_icdf` / :func:`build_hybrid` precompute for one mesh and material."""

    mesh: Mesh
    atlas: Atlas
    module: nn.Module
    stats: dict


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


def _check_dtype(dtype: object) -> None:
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")


def build_icdf(mesh: Mesh, material: Material, *, atlas_resolution: int = 512, kernel_size: int = 7,
               levels: int | None = None, max_pairs: int = DEFAULT_MAX_PAIRS, progress: bool = False) -> ChangScene:
    """Atlas + :class:`~torchsss.modules.chang.ImportanceSampledTranslucency` for ``mesh`` in ``material``."""
    t0 = time.perf_counter()
    atlas = build_atlas(mesh, atlas_resolution, kernel_size=kernel_size, progress=progress)
    t1 = time.perf_counter()
    sa, ss, eta = material.tensors(dtype=mesh.vertices.dtype)
    module = ImportanceSampledTranslucency.from_atlas(atlas, DipoleMaterial(sa, ss, eta), levels=levels,
                                                      max_pairs=max_pairs)
    stats = dict(t_atlas_s=t1 - t0, t_precompute_s=time.perf_counter() - t0)
    return ChangScene(mesh, atlas, module, stats)


def build_hybrid(mesh: Mesh, material: Material, *, atlas_resolution: int = 512, kernel_size: int = 7,
                 rings: int = 4, per_ring: int = 8, c: float = 0.1, k: float = 1.5, local_eps: float = 1e-3,
                 levels: int | None = None, max_pairs: int = DEFAULT_MAX_PAIRS, progress: bool = False) -> ChangScene:
    """Atlas + :class:`HybridTranslucency` for ``mesh`` in ``material``.

    ``kernel_size`` sets the atlas gutters (``kernel_size // 2`` texels) that the local filter reads across chart
    edges (wider gutters need a larger ``atlas_resolution``).
    """
    t0 = time.perf_counter()
    atlas = build_atlas(mesh, atlas_resolution, kernel_size=kernel_size, progress=progress)
    t1 = time.perf_counter()
    sa, ss, eta = material.tensors(dtype=mesh.vertices.dtype)
    module = HybridTranslucency.from_atlas(atlas, DipoleMaterial(sa, ss, eta), c=c, k=k, rings=rings,
                                           per_ring=per_ring, local_eps=local_eps, levels=levels, max_pairs=max_pairs)
    stats = dict(t_atlas_s=t1 - t0, t_precompute_s=time.perf_counter() - t0, r_p_mm=module.r_p,
                 local_bound_mm=module.bound, rings=rings, per_ring=per_ring)
    return ChangScene(mesh, atlas, module, stats)


def _render(built: ChangScene, mesh: Mesh, material: Material, lights: Sequence[Light], camera: Camera, *,
            samples: int, seed: int, sobol: bool, specular: bool, roughness: float, hybrid: bool,
            shadow_resolution: int) -> RenderResult:
    lights = list(lights)
    if not lights:
        raise ValueError("lights: expected at least one light, got none")
    gbuf = camera_gbuffer(mesh, camera)
    dtype, device = mesh.vertices.dtype, mesh.vertices.device
    t0 = time.perf_counter()
    e = irradiance_atlas(mesh, built.atlas, lights, material.eta, shadow_resolution=shadow_resolution).to(dtype)
    t1 = time.perf_counter()
    u = sample_uniforms(samples, seed=seed, sobol=sobol, dtype=dtype, device=device)
    mask = gbuf.mask[0, 0]
    receivers = gbuf.position[0].permute(1, 2, 0)[mask].unsqueeze(0)
    with torch.no_grad():
        if hybrid:
            uv, _ = _camera_uv(mesh, built.atlas, camera)
            rec_uv = uv[0].permute(1, 2, 0)[mask].unsqueeze(0)
            b = built.module(e, u, receivers, rec_uv)
        else:
            b = built.module(e, u, receivers)
    t2 = time.perf_counter()
    h, w = camera.resolution
    radiosity = torch.zeros(h, w, b.shape[-1], dtype=dtype, device=device)
    radiosity[mask] = b[0].to(dtype)
    radiosity = radiosity.permute(2, 0, 1).unsqueeze(0)
    cos_o = (gbuf.normal * gbuf.view_dir).sum(1, keepdim=True).clamp(0.0, 1.0)
    radiance = LenschTranslucency.radiance(radiosity, cos_o, material.eta) * gbuf.mask
    if specular:
        radiance = radiance + shadow_mapped_specular(mesh, gbuf, lights, material.eta, roughness=roughness)
    t3 = time.perf_counter()
    stats = dict(built.stats)
    stats.update(t_irradiance_s=t1 - t0, t_module_s=t2 - t1, t_image_s=t3 - t2, t_frame_s=t3 - t0,
                 atlas_resolution=built.atlas.resolution, samples=samples, receivers=int(receivers.shape[1]),
                 sobol=sobol, seed=seed)
    return RenderResult(radiance, radiosity, gbuf.mask, stats)


def render_icdf(mesh: Mesh, material: Material, lights: Sequence[Light], camera: Camera, *, samples: int = 1024,
                atlas_resolution: int = 512, seed: int = 0, sobol: bool = True, dtype: torch.dtype = torch.float32,
                levels: int | None = None, max_pairs: int = DEFAULT_MAX_PAIRS, progress: bool = False,
                prebuilt: ChangScene | None = None, shadow_resolution: int = 1024, specular: bool = False,
                roughness: float = 0.3) -> RenderResult:
    """Render a camera image with Chang's texture-space importance sampling (``samples`` = N).

    ``stats`` separates ``t_precompute_s`` (atlas) from ``t_frame_s`` (irradiance atlas + sampling + sum).
    ``shadow_resolution`` is that of the per-light shadow maps of the irradiance atlas. ``specular`` adds the
    opt-in GGX boundary reflection (shadow-mapped), as in the other renderers. ``prebuilt`` reuses a
    :func:`build_icdf` result (relighting, new views, material edits on ``prebuilt.module.material``).
    """
    _check_dtype(dtype)
    mesh = mesh.with_dtype(dtype)
    built = prebuilt or build_icdf(mesh, material, atlas_resolution=atlas_resolution, levels=levels,
                                   max_pairs=max_pairs, progress=progress)
    return _render(built, mesh, material, lights, camera, samples=samples, seed=seed, sobol=sobol,
                   specular=specular, roughness=roughness, hybrid=False, shadow_resolution=shadow_resolution)


def render_hybrid(mesh: Mesh, material: Material, lights: Sequence[Light], camera: Camera, *, samples: int = 1024,
                  atlas_resolution: int = 512, seed: int = 0, sobol: bool = True, dtype: torch.dtype = torch.float32,
                  rings: int = 4, per_ring: int = 8, c: float = 0.1, k: float = 1.5, local_eps: float = 1e-3,
                  levels: int | None = None, max_pairs: int = DEFAULT_MAX_PAIRS, progress: bool = False,
                  prebuilt: ChangScene | None = None, shadow_resolution: int = 1024, specular: bool = False,
                roughness: float = 0.3) -> RenderResult:
    """Render with Chang's hybrid: an ``rings x per_ring + 1`` local filter plus ``samples`` global samples.

    ``stats`` also holds the split radius ``r_p_mm`` and the local bound ``local_bound_mm``.
    """
    _check_dtype(dtype)
    mesh = mesh.with_dtype(dtype)
    built = prebuilt or build_hybrid(mesh, material, atlas_resolution=atlas_resolution, rings=rings,
                                     per_ring=per_ring, c=c, k=k, local_eps=local_eps, levels=levels,
                                     max_pairs=max_pairs, progress=progress)
    return _render(built, mesh, material, lights, camera, samples=samples, seed=seed, sobol=sobol,
                   specular=specular, roughness=roughness, hybrid=True, shadow_resolution=shadow_resolution)
