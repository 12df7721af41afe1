"""Render with Lensch et al. 2002: build once (atlas, kernels, throughput), then relight per frame.

Build (timed as ``precompute``): texture atlas with gutters, per-texel k x k kernel geometry, vertex dual-basis
weights, the sparse vertex-to-vertex throughput (threshold relative to the largest entry), and - when
``blend`` - Lensch's §5.4 blending weights and kernel correction. Per frame (timed as ``frame``): irradiance
atlas with shadow-mapped visibility, :class:`~torchsss.modules.lensch.LenschTranslucency`, the atlas sampled
at the camera pixels' texture coordinates, :math:`L = F_t(\\eta, \\omega_o)/\\pi \\; B`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsss.geometry.atlas import Atlas, build_atlas
from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.gbuffer import camera_gbuffer
from torchsss.geometry.lensch import (
    blending_weights,
    build_throughput,
    local_kernel_geometry,
    plan_kernel_size,
    plan_lensch,
    vertex_weights,
)
from torchsss.geometry.lights import Light, surface_irradiance
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.raster import interpolate, rasterize
from torchsss.geometry.shadow import build_shadow_map, shadow_visibility
from torchsss.modules.lensch import GlobalResponse, LenschTranslucency, LocalResponse
from torchsss.modules.material import DipoleMaterial
from torchsss.pipelines.reference import RenderResult
from torchsss.pipelines.specular import shadow_mapped_specular
from torchsss.scene import Material

__all__ = ["LenschScene", "build_lensch", "irradiance_atlas", "render_lensch"]


@dataclass
class LenschScene:
    """What :func:`build_lensch` precomputes for one mesh and material."""

    mesh: Mesh
    atlas: Atlas
    module: LenschTranslucency
    stats: dict


def build_lensch(mesh: Mesh, material: Material, *, resolution: int = 512, kernel_size: int | None = None,
                 threshold: float = 1e-5, relative: bool = True, blend: bool | None = None,
                 progress: bool = False) -> LenschScene:
    """Precompute everything the per-frame Lensch module needs (see the module docstring).

    ``kernel_size=None`` and ``blend=None`` (defaults) are planned from the vertex spacing and the texel size
    (:func:`~torchsss.geometry.lensch.plan_lensch`: blending with a kernel that reaches ~0.7 median edges, 7 for
    Lensch's meshes and up to 11 for coarse ones; no blending, k = 7, when no kernel up to 11 reaches half an
    edge). Without blending the kernel only has to hold the near field and 7 is used.
    """
    stats: dict = {}
    if blend is None:
        planned_k, blend = plan_lensch(mesh, resolution)
        if kernel_size is None:
            kernel_size = planned_k
    if kernel_size is None:
        kernel_size = plan_kernel_size(mesh, resolution) if blend else 7
    stats.update(kernel_size=kernel_size, blend=blend)
    t0 = time.perf_counter()
    atlas = build_atlas(mesh, resolution, kernel_size=kernel_size, progress=progress)
    stats["t_atlas_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    sa, ss, eta = material.tensors(dtype=mesh.vertices.dtype)
    geom = local_kernel_geometry(atlas, kernel_size)
    weights = vertex_weights(mesh, atlas)
    tp = build_throughput(mesh, sa, ss, eta, threshold=threshold, relative=relative, zero_diagonal=blend,
                          progress=progress)
    stats.update(t_kernels_throughput_s=time.perf_counter() - t1, nnz=int(tp.rows.shape[0]),
                 vertices=mesh.num_vertices, cutoff_mm=tp.cutoff_mm)
    mat = DipoleMaterial(sa, ss, eta)
    direct = correction = None
    if blend:
        t2 = time.perf_counter()
        bw = blending_weights(mesh, atlas, sa, ss, eta, kernel_size=kernel_size, threshold=threshold,
                              relative=relative, progress=progress)
        direct, correction = bw.weights, bw.kernel_correction
        stats["t_blending_s"] = time.perf_counter() - t2
    local = LocalResponse(geom, mat, correction=correction)
    glob = GlobalResponse(weights, tp, mat, atlas.valid_mask)
    module = LenschTranslucency(local, glob, direct=direct)
    stats["t_precompute_s"] = time.perf_counter() - t0
    return LenschScene(mesh, atlas, module, stats)


def irradiance_atlas(mesh: Mesh, atlas: Atlas, lights: Sequence[Light], eta: float, *,
                     shadow_resolution: int = 1024, fresnel: str = "exact") -> Tensor:
    """Irradiance at every valid atlas texel :math:`(1, 3, H, W)`, shadow-mapped per light."""
    h, w = atlas.shape
    pts = atlas.position.flatten(2).transpose(1, 2)
    nrm = atlas.normal.flatten(2).transpose(1, 2)
    vis = [shadow_visibility(build_shadow_map(mesh, light, shadow_resolution), pts, nrm, light) for light in lights]
    e = surface_irradiance(pts, nrm, list(lights), eta, visibility=vis, fresnel=fresnel)
    return e.transpose(1, 2).reshape(1, 3, h, w) * atlas.valid_mask


def _camera_uv(mesh: Mesh, atlas: Atlas, camera: Camera) -> tuple[Tensor, Tensor]:
    dtype, device = mesh.vertices.dtype, mesh.vertices.device
    raster = rasterize(transform_points(mesh.vertices, camera.view_proj(dtype=dtype, device=device)), mesh.faces,
                       camera.resolution)
    corners = torch.arange(3 * mesh.num_faces, device=device).view(-1, 3)
    uv = interpolate(atlas.face_uvs.reshape(-1, 2).to(dtype), raster, corners)
    return uv, raster.mask


def render_lensch(mesh: Mesh, material: Material, lights: Sequence[Light], camera: Camera, *,
                  resolution: int = 512, kernel_size: int | None = None, threshold: float = 1e-5, relative: bool = True,
                  blend: bool | None = None, dtype: torch.dtype = torch.float32, progress: bool = False,
                  prebuilt: LenschScene | None = None, specular: bool = False,
                  roughness: float = 0.3) -> RenderResult:
    """Render a camera image with the Lensch method; ``stats`` separates precompute and per-frame time.

    ``specular`` adds the opt-in GGX boundary reflection (shadow-mapped), as in the reference renderer.
    """
    mesh = mesh.with_dtype(dtype)
    built = prebuilt or build_lensch(mesh, material, resolution=resolution, kernel_size=kernel_size,
                                     threshold=threshold, relative=relative, blend=blend, progress=progress)
    gbuf = camera_gbuffer(mesh, camera)
    t0 = time.perf_counter()
    e = irradiance_atlas(mesh, built.atlas, lights, material.eta)
    t1 = time.perf_counter()
    with torch.no_grad():
        b_atlas = built.module(e)
    t2 = time.perf_counter()
    uv, mask = _camera_uv(mesh, built.atlas, camera)
    b = built.atlas.sample(b_atlas, uv) * mask
    cos_o = (gbuf.normal * gbuf.view_dir).sum(1, keepdim=True).clamp(0.0, 1.0)
    radiance = LenschTranslucency.radiance(b, cos_o, material.eta) * mask
    if specular:
        radiance = radiance + shadow_mapped_specular(mesh, gbuf, lights, material.eta, roughness=roughness)
    t3 = time.perf_counter()
    stats = dict(built.stats)
    stats.update(t_irradiance_s=t1 - t0, t_module_s=t2 - t1, t_image_s=t3 - t2, t_frame_s=t3 - t0,
                 atlas_resolution=built.atlas.resolution, kernel_size=built.module.local.kernel_size,
                 threshold=threshold, blend=built.module.direct is not None)
    return RenderResult(radiance, b, mask, stats)
