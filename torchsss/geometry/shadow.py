"""Light-view cameras and shadow maps (hard shadows with a slope-scaled depth bias).

A shadow map stores, per light-view pixel, the distance along the light camera's axis (mm) of the first
surface the light sees. A point is lit when its own depth is not more than the stored depth plus a bias.
The bias is measured in millimetres: ``bias_texels`` shadow-map texel footprints at the point's depth, scaled
by :math:`1 + \\tan\\theta` (capped) when normals are given, :math:`\\theta` the angle between the normal and
the direction to the light, so that surfaces seen at grazing angles do not shadow themselves ("acne").

The light camera is fitted to a bounding sphere of the object: a perspective frustum from the position of a
point or spot light, an orthographic box along a directional light. A point light inside (or within 1% of)
the bounding sphere cannot see the whole object through one frustum; :func:`light_camera` raises ValueError
for it (cube maps are not implemented). Points outside the light's frustum are reported as lit.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsss._checks import check_shape, check_tensor
from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.lights import DirectionalLight, Light, PointLight, SpotLight
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.raster import interpolate, rasterize

__all__ = ["ShadowMap", "bounding_sphere", "build_shadow_map", "light_camera", "shadow_visibility"]


def bounding_sphere(mesh: Mesh) -> tuple[tuple[float, float, float], float]:
    """Centre (bounding-box centre) and radius (farthest vertex from it) in mm.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> c, r = bounding_sphere(sphere(5.0, 2))
        >>> round(r, 6)
        5.0
    """
    v = mesh.vertices.detach().double()
    centre = 0.5 * (v.min(0).values + v.max(0).values)
    radius = float((v - centre).norm(dim=-1).max())
    return tuple(float(c) for c in centre), radius  # type: ignore[return-value]


def _up_for(direction: tuple[float, float, float]) -> tuple[float, float, float]:
    return (0.0, 0.0, 1.0) if abs(direction[1]) > 0.9 * math.sqrt(sum(c * c for c in direction)) else (0.0, 1.0, 0.0)


def light_camera(light: Light, centre: tuple[float, float, float], radius: float, resolution: int) -> Camera:
    """A camera at the light that sees the whole bounding sphere ``(centre, radius)`` (mm).

    Point and spot lights get a perspective camera from the light's position towards the centre with the
    tightest field of view that holds the sphere (plus 2%); directional lights an orthographic camera along
    the light direction.

    Raises:
        ValueError: a point or spot light inside the bounding sphere (or within 1% of its radius outside it).

    Examples:
        >>> cam = light_camera(PointLight((0, 0, 100), 1.0), (0, 0, 0), 10.0, 64)
        >>> cam.projection, round(cam.fov_deg, 2)
        ('perspective', 11.71)
    """
    if not (radius > 0 and math.isfinite(radius)):
        raise ValueError(f"radius: expected a finite value > 0, got {radius!r}")
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1:
        raise ValueError(f"resolution: expected a positive int, got {resolution!r}")
    r = radius * 1.02
    if isinstance(light, DirectionalLight):
        d = light.direction
        eye = tuple(c - 2.0 * r * di for c, di in zip(centre, d))
        return Camera(eye=eye, target=tuple(centre), up=_up_for(d), width=resolution, height=resolution,
                      near=0.5 * r, far=3.5 * r, projection="orthographic", ortho_half_height=r)
    if not isinstance(light, (PointLight, SpotLight)):
        raise TypeError(f"light: expected PointLight, DirectionalLight or SpotLight, got {type(light).__name__}")
    offset = tuple(c - p for c, p in zip(centre, light.position))
    dist = math.sqrt(sum(o * o for o in offset))
    if dist <= r * 1.01:
        raise ValueError(
            f"light position {light.position}: expected a light outside the object's bounding sphere "
            f"(centre {tuple(round(c, 3) for c in centre)}, radius {radius:.3f} mm), got distance {dist:.3f} mm; "
            "one shadow frustum cannot see the whole object from inside it"
        )
    fov = 2.0 * math.degrees(math.asin(r / dist))
    return Camera(eye=tuple(light.position), target=tuple(centre), up=_up_for(offset), fov_deg=fov,
                  width=resolution, height=resolution, near=max(dist - r, 1e-3 * dist), far=dist + r)


class ShadowMap(NamedTuple):
    """Depth from the light's view.

    Attributes:
        depth: :math:`(1, 1, H, W)` distance along the light camera's axis in mm (+inf where no surface).
        view_proj: :math:`(4, 4)` world-to-clip matrix of the light camera.
        view: :math:`(4, 4)` world-to-view matrix.
        texel_mm: size in mm of one texel at unit distance along the axis (perspective) or absolute
            (orthographic).
        orthographic: whether the light camera is orthographic.
    """

    depth: Tensor
    view_proj: Tensor
    view: Tensor
    texel_mm: float
    orthographic: bool


def build_shadow_map(mesh: Mesh, light: Light, resolution: int = 1024) -> ShadowMap:
    """Rasterize the mesh from the light (camera from :func:`light_camera`) into a depth map.

    Args:
        mesh: the occluding geometry (mm).
        light: the light.
        resolution: shadow-map width and height in texels.

    Returns:
        A :class:`ShadowMap` in the mesh's dtype.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> sm = build_shadow_map(sphere(10.0, 2), PointLight((0, 0, 100), 1.0), 32)
        >>> bool(sm.depth.isfinite().any()), round(sm.depth.min().item())
        (True, 90)
    """
    centre, radius = bounding_sphere(mesh)
    cam = light_camera(light, centre, radius, resolution)
    dtype, device = mesh.vertices.dtype, mesh.vertices.device
    view = cam.view_matrix(dtype=dtype, device=device)
    vp = cam.view_proj(dtype=dtype, device=device)
    clip = transform_points(mesh.vertices, vp)
    raster = rasterize(clip, mesh.faces, (resolution, resolution))
    view_depth = -transform_points(mesh.vertices, view)[..., 2:3]
    depth = interpolate(view_depth, raster, mesh.faces)
    depth = torch.where(raster.mask, depth, torch.full_like(depth, math.inf))
    if cam.projection == "orthographic":
        texel = 2.0 * cam.ortho_half_height / resolution
    else:
        texel = 2.0 * math.tan(math.radians(cam.fov_deg) / 2.0) / resolution
    return ShadowMap(depth, vp, view, texel, cam.projection == "orthographic")


def shadow_visibility(
    shadow_map: ShadowMap,
    points: Tensor,
    normals: Tensor | None = None,
    light: Light | None = None,
    *,
    bias_texels: float = 1.5,
    max_slope: float = 8.0,
) -> Tensor:
    """Hard-shadow visibility of points: 1 where lit, 0 where an occluder is nearer to the light.

    Args:
        shadow_map: from :func:`build_shadow_map`.
        points: :math:`(B, N, 3)` positions in mm.
        normals: optional :math:`(B, N, 3)` unit normals for the slope-scaled bias (needs ``light``).
        light: the light the map was built for (only used with ``normals``).
        bias_texels: depth bias in texel footprints at the point's depth (>= 0).
        max_slope: cap of :math:`\\tan\\theta` in the slope-scaled bias.

    Returns:
        :math:`(B, N)` visibility in the points' dtype (0 or 1). Points outside the light frustum count as lit.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> sm = build_shadow_map(sphere(10.0, 3), PointLight((0, 0, 100), 1.0), 64)
        >>> shadow_visibility(sm, torch.tensor([[[0.0, 0.0, 10.0], [0.0, 0.0, -10.0]]])).tolist()
        [[1.0, 0.0]]
    """
    check_tensor(points, "points")
    dims = check_shape(points, "points", "B,N,3")
    if bias_texels < 0:
        raise ValueError(f"bias_texels: expected a value >= 0, got {bias_texels!r}")
    dmap = shadow_map.depth.to(points.dtype)
    h, w = dmap.shape[-2:]
    clip = transform_points(points, shadow_map.view_proj.to(points.dtype))
    wc = clip[..., 3]
    ok_w = wc > 0
    safe_w = torch.where(ok_w, wc, torch.ones_like(wc))
    ndc = clip[..., :3] / safe_w.unsqueeze(-1)
    col = torch.floor((ndc[..., 0] + 1.0) * 0.5 * w)
    row = torch.floor((1.0 - ndc[..., 1]) * 0.5 * h)
    inside = ok_w & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    idx = (row.clamp(0, h - 1) * w + col.clamp(0, w - 1)).long()
    stored = dmap.reshape(-1)[idx]
    depth = -transform_points(points, shadow_map.view.to(points.dtype))[..., 2]
    texel = shadow_map.texel_mm if shadow_map.orthographic else shadow_map.texel_mm * depth.abs()
    slope = torch.ones_like(depth)
    if normals is not None:
        check_tensor(normals, "normals")
        check_shape(normals, "normals", "B,N,3", **dims)
        if light is None:
            raise ValueError("light: expected the shadow map's light when normals are given, got None")
        if isinstance(light, DirectionalLight):
            to_light = -torch.tensor(light.direction, dtype=points.dtype, device=points.device)
        else:
            to_light = torch.tensor(light.position, dtype=points.dtype, device=points.device) - points
            to_light = to_light / to_light.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        cos = (normals * to_light).sum(-1).abs().clamp(1e-6, 1.0)
        slope = 1.0 + (torch.sqrt(1.0 - cos * cos) / cos).clamp_max(max_slope)
    lit = depth <= stored + bias_texels * texel * slope
    return torch.where(inside, lit, torch.ones_like(lit)).to(points.dtype)
