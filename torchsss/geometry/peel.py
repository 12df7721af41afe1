"""Splat sources for environment lighting: every surface point, found by depth peeling (Shah 2007, 6.4.2).

Under an environment every surface point receives light, not only those a light sees first. Shah depth-peels the
object so that all its points become splats (:math:`n \\times n \\times l` splats for :math:`l` layers). Here the
sources are the depth-peeled fragments (:func:`~torchsss.geometry.raster.depth_peel`) of orthographic views along
coordinate axes through the mesh's bounding sphere (radius :math:`R`, the view spans :math:`2.04 R` over
``resolution`` pixels, pixel size :math:`s`). Peeling returns every crossing of a pixel's ray with the surface,
front and back faces alike, so one view per axis sees each point of the surface once (views along :math:`+k` and
:math:`-k` would see the same points twice).

Area of a fragment: a fragment of the view along axis :math:`k` stands for the surface area
:math:`s^2 / |n_k|` (:math:`n` the unit geometric normal of its face), which blows up at grazing angles. With
``axes=3`` the three views share every point through the partition of unity :math:`\\sum_k n_k^2 = 1`: the
fragment carries the weight :math:`n_k^2`, so its area is :math:`dA = s^2 |n_k| \\le s^2` (bounded at every angle)
and the weighted fragments of all layers of the three views sum to the surface area up to pixel coverage
(measured at 64, 128 and 256 pixels: within 0.04% on an icosphere of 5120 faces, 0.5% on the default torus,
0.07% on spot; the tests ask for 1%). ``axes=1`` is Shah's single view, along :math:`z` (looking from
:math:`+z`), with :math:`dA = s^2 / \\max(|n_z|, \\text{min\\_cos})`: surfaces seen edge-on are undersampled and
the clamp loses area there (measured: -1.7% on the sphere, -8.2% / -4.4% / +0.9% on spot at 64 / 128 / 256).

``layers`` reports the peeled layers per view; a count equal to ``max_layers`` means deeper surfaces may have been
cut off (spot needs 10 layers along x, 8 along y and z at 256 x 256; the 2 fragments past layer 8 are lost).

Irradiance: :math:`E` of :func:`~torchsss.geometry.environment.environment_irradiance` at the interpolated
(shading) vertex normal, unshadowed (environment occlusion is ignored, as in Shah); ``flux`` is :math:`E\\,dA`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchsss._checks import check_int
from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.environment import EnvironmentLight, environment_irradiance
from torchsss.geometry.mesh import Mesh, check_mesh
from torchsss.geometry.raster import depth_peel
from torchsss.geometry.shadow import bounding_sphere
from torchsss.physics.fresnel import check_fresnel

__all__ = ["EnvironmentSplats", "axis_camera", "environment_splats"]

_MARGIN = 1.02  # the views span the bounding sphere's diameter plus 2%, as the light cameras of shadow.py


class EnvironmentSplats(NamedTuple):
    """The splat sources of an environment: one entry per peeled fragment, over all layers of all views.

    Attributes:
        position: :math:`(1, S, 3)` surface points in mm.
        normal: :math:`(1, S, 3)` unit shading normals (interpolated vertex normals).
        irradiance: :math:`(1, S, 3)` transmitted irradiance :math:`E` (>= 0).
        area: :math:`(1, S, 1)` surface area :math:`dA` in mm^2 each fragment stands for (module docstring).
        flux: :math:`(1, S, 3)` :math:`E\\,dA`.
        face_id: :math:`(S,)` int64 face of each fragment.
        bary: :math:`(S, 3)` barycentric weights of the face's corners.
        layers: number of non-empty peeled layers of each view (one entry per axis).
    """

    position: Tensor
    normal: Tensor
    irradiance: Tensor
    area: Tensor
    flux: Tensor
    face_id: Tensor
    bary: Tensor
    layers: list[int]


def axis_camera(axis: int, centre: tuple[float, float, float], radius: float, resolution: int) -> Camera:
    """Orthographic camera looking along :math:`-e_{axis}` (from the :math:`+e_{axis}` side) at a bounding sphere.

    The view volume spans :math:`1.02` times the sphere's diameter in both image directions and in depth
    (eye at :math:`2.04 R` from the centre, near :math:`0.51 R`, far :math:`3.57 R`).

    Examples:
        >>> cam = axis_camera(2, (0.0, 0.0, 0.0), 10.0, 64)
        >>> cam.projection, cam.eye, cam.ortho_half_height
        ('orthographic', (0.0, 0.0, 20.4), 10.2)
    """
    if isinstance(axis, bool) or axis not in (0, 1, 2):
        raise ValueError(f"axis: expected 0, 1 or 2, got {axis!r}")
    if not (isinstance(radius, (int, float)) and 0 < radius < math.inf):
        raise ValueError(f"radius: expected a finite value > 0, got {radius!r}")
    r = radius * _MARGIN
    eye = tuple(c + (2.0 * r if i == axis else 0.0) for i, c in enumerate(centre))
    up = (0.0, 0.0, 1.0) if axis == 1 else (0.0, 1.0, 0.0)
    return Camera(eye=eye, target=tuple(centre), up=up, width=resolution, height=resolution, near=0.5 * r,
                  far=3.5 * r, projection="orthographic", ortho_half_height=r)



def environment_splats(mesh: Mesh, env: EnvironmentLight, resolution: int, eta: Tensor | float = 1.3, *,
                       max_layers: int = 8, axes: int = 3, fresnel: str = "exact", min_cos: float = 1e-2,
                       max_candidates: int = 2**22) -> EnvironmentSplats:
    """Depth-peeled splat sources of ``mesh`` lit by ``env`` (module docstring for the views and the areas).

    Args:
        mesh: the object (mm).
        env: the environment.
        resolution: width and height of each view in pixels (pixel size :math:`s = 2.04 R / \\text{resolution}`).
        eta: relative index of refraction (number, 0-dim or per-channel :math:`(3,)` tensor).
        max_layers: the most peeled layers per view.
        axes: 3 (views along x, y, z with the :math:`n_k^2` partition of unity) or 1 (Shah's single view along z).
        fresnel: ``"exact"``, ``"schlick"`` or ``"none"``.
        min_cos: lower bound of :math:`|n_z|` in the area of ``axes=1`` (0 < min_cos <= 1); unused for ``axes=3``.
        max_candidates: rasterizer memory bound (see :func:`~torchsss.geometry.raster.rasterize`).

    Returns:
        :class:`EnvironmentSplats` in the mesh's dtype and device; position and flux are differentiable w.r.t. the
        mesh vertices (inside each face) and ``eta``.

    Raises:
        TypeError: a non-mesh, non-environment or wrongly typed argument.
        ValueError: values out of range.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> m = sphere(5.0, 3)
        >>> sp = environment_splats(m, EnvironmentLight.uniform(1.0), 64, fresnel="none")
        >>> sp.layers, abs(sp.area.sum().item() / m.area - 1.0) < 0.01
        ([2, 2, 2], True)
    """
    mesh = check_mesh(mesh)
    if not isinstance(env, EnvironmentLight):
        raise TypeError(f"env: expected an EnvironmentLight, got {type(env).__name__}")
    resolution = check_int(resolution, "resolution", 1)
    max_layers = check_int(max_layers, "max_layers", 1)
    if isinstance(axes, bool) or axes not in (1, 3):
        raise ValueError(f"axes: expected 1 or 3, got {axes!r}")
    if not (isinstance(min_cos, (int, float)) and 0.0 < min_cos <= 1.0):
        raise ValueError(f"min_cos: expected a value in (0, 1], got {min_cos!r}")
    check_fresnel(fresnel)
    dtype, device = mesh.dtype, mesh.device
    view_axes = (0, 1, 2) if axes == 3 else (2,)
    fids, barys, areas, layer_counts = [], [], [], []
    centre, radius = bounding_sphere(mesh)
    if not radius > 0:
        raise ValueError(f"mesh: expected a mesh of non-zero extent, got a bounding radius of {radius!r}")
    geo_normals = mesh.face_normals.detach()
    for k in view_axes:
        cam = axis_camera(k, centre, radius, resolution)
        s = 2.0 * cam.ortho_half_height / resolution
        clip = transform_points(mesh.vertices, cam.view_proj(dtype=dtype, device=device))
        layers = depth_peel(clip, mesh.faces, (resolution, resolution), max_layers, max_candidates=max_candidates)
        layer_counts.append(len(layers))
        for lay in layers:
            idx = lay.mask.view(-1).nonzero().squeeze(1)
            fid = lay.face_id.view(-1).index_select(0, idx)
            bary = lay.bary.view(3, -1).index_select(1, idx).transpose(0, 1)
            nk = geo_normals.index_select(0, fid)[:, k].abs()
            area = s * s * nk if axes == 3 else s * s / nk.clamp_min(min_cos)
            fids.append(fid)
            barys.append(bary)
            areas.append(area)
    if fids:
        fid = torch.cat(fids)
        bary = torch.cat(barys)
        area = torch.cat(areas).to(dtype)
    else:
        fid = torch.zeros(0, dtype=torch.int64, device=device)
        bary = torch.zeros(0, 3, dtype=dtype, device=device)
        area = torch.zeros(0, dtype=dtype, device=device)
    corners = mesh.faces.index_select(0, fid)  # (S, 3)
    position = (bary[:, :, None] * mesh.vertices[corners]).sum(1)
    normal = F.normalize((bary[:, :, None] * mesh.corner_normals()[fid]).sum(1), dim=-1, eps=1e-12)
    irradiance = environment_irradiance(env, normal[None], eta, fresnel=fresnel)
    flux = irradiance * area[None, :, None]
    return EnvironmentSplats(position[None], normal[None], irradiance, area[None, :, None], flux, fid, bary,
                             layer_counts)
