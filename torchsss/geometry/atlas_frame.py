"""Per-frame quantities of a texture atlas: the irradiance atlas, and where each camera pixel reads the atlas.

Shared by every atlas method (Lensch, Chang's icdf and hybrid): the one home of the camera-to-atlas lookup.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchsss.geometry.atlas import Atlas
from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.lights import Light, surface_irradiance
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.raster import interpolate, rasterize
from torchsss.geometry.shadow import build_shadow_map, shadow_visibility

__all__ = ["camera_uv", "irradiance_atlas"]


def irradiance_atlas(mesh: Mesh, atlas: Atlas, lights: Sequence[Light], eta: float | Tensor, *,
                     shadow_resolution: int = 1024, fresnel: str = "exact",
                     texels: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor:
    """Irradiance at every valid atlas texel :math:`(1, 3, H, W)`, shadow-mapped per light.

    Args:
        mesh: the object (mm): the shadow maps are rendered from it.
        atlas: its texture atlas (or the atlas of a decimated copy of it, with ``texels``).
        lights: point, spot or directional lights.
        eta: relative index of refraction (a number, or the material module's ``eta`` tensor: gradients flow).
        shadow_resolution: size of each light's shadow map.
        fresnel: ``"exact"``, ``"schlick"`` or ``"none"``.
        texels: where the valid texels are lit, ``(index, position, normal)`` as
            :attr:`~torchsss.geometry.atlas.Atlas.valid_texels` (the default): an atlas built on a decimated copy
            of ``mesh`` lights its texels at their closest points on ``mesh``, with its normals
            (:meth:`~torchsss.pipelines.atlas_view.AtlasView.lit_texels`).

    Examples:
        >>> from torchsss.geometry import DirectionalLight, build_atlas, sphere
        >>> m = sphere(10.0, 2); a = build_atlas(m, 64, kernel_size=3)
        >>> irradiance_atlas(m, a, [DirectionalLight((0, 0, -1), 1.0)], 1.3).shape
        torch.Size([1, 3, 64, 64])
    """
    h, w = atlas.shape
    index, pts, nrm = atlas.valid_texels if texels is None else texels  # only valid texels are lit; the rest: 0
    pts, nrm = pts.unsqueeze(0), nrm.unsqueeze(0)
    vis = [shadow_visibility(build_shadow_map(mesh, light, shadow_resolution), pts, nrm, light) for light in lights]
    e = surface_irradiance(pts, nrm, list(lights), eta, visibility=vis, fresnel=fresnel)[0]
    image = torch.zeros(3, h * w, dtype=e.dtype, device=e.device).index_copy(1, index, e.T)
    return image.reshape(1, 3, h, w)


def camera_uv(mesh: Mesh, atlas: Atlas, camera: Camera) -> tuple[Tensor, Tensor]:
    """Atlas coordinates seen by every camera pixel: ``uv`` :math:`(1, 2, H, W)` in [0, 1] and the mask.

    Sample an atlas at them with :meth:`~torchsss.geometry.atlas.Atlas.sample`.

    Examples:
        >>> from torchsss.geometry import build_atlas, sphere
        >>> m = sphere(10.0, 2); a = build_atlas(m, 64, kernel_size=3)
        >>> uv, mask = camera_uv(m, a, Camera(eye=(0, 0, 60), target=(0, 0, 0), width=8, height=8))
        >>> tuple(uv.shape), tuple(mask.shape)
        ((1, 2, 8, 8), (1, 1, 8, 8))
    """
    dtype, device = mesh.vertices.dtype, mesh.vertices.device
    raster = rasterize(transform_points(mesh.vertices, camera.view_proj(dtype=dtype, device=device)), mesh.faces,
                       camera.resolution)
    corners = torch.arange(3 * mesh.num_faces, device=device).view(-1, 3)
    uv = interpolate(atlas.face_uvs.reshape(-1, 2).to(dtype), raster, corners)
    return uv, raster.mask
