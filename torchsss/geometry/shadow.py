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
import numbers
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsss._checks import check_shape, check_tensor
from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.lights import DirectionalLight, Light, PointLight, SpotLight
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.raster import rasterize_depth

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


def _positive(value: object, name: str, upper: float | None = None, closed: bool = True) -> float:
    """``value`` as a float in (0, upper] (``closed``) or (0, upper); TypeError / ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name}: expected a real number, got {type(value).__name__}")
    v = float(value)
    if not (math.isfinite(v) and v > 0 and (upper is None or v < upper or (closed and v == upper))):
        expected = "a finite number > 0" if upper is None else f"a number in (0, {upper:g}{']' if closed else ')'}"
        raise ValueError(f"{name}: expected {expected}, got {value!r}")
    return v


def light_camera(
    light: Light,
    centre: tuple[float, float, float],
    radius: float,
    resolution: int,
    *,
    margin: float = 1.02,
    points: Tensor | None = None,
    max_half_angle_deg: float | None = None,
    near_fraction: float | None = None,
) -> Camera:
    """A camera at the light that sees the whole bounding sphere ``(centre, radius)`` (mm).

    Point and spot lights get a perspective camera from the light's position towards the centre, directional lights
    an orthographic camera along the light direction, both sized on the sphere of radius :math:`R =` ``margin``
    :math:`\\cdot` ``radius``: the orthographic half-height is :math:`R`, the perspective half angle
    :math:`\\arcsin(\\min(1, R/d))` (d the light's distance to the centre), at most ``max_half_angle_deg``. The
    defaults are the shadow-map camera: the tightest view that holds the sphere plus 2%.

    Near and far planes: without ``points``, those of the sphere of radius :math:`R` (perspective
    :math:`\\max(d - R, 10^{-3} d)` and :math:`d + R`; orthographic, with the eye :math:`2R` before the centre,
    :math:`0.5 R` and :math:`3.5 R`). With ``points``, the planes enclose the points' distances along the axis
    (orthographic: their range padded by :math:`0.01\\,` ``radius`` :math:`+ 10^{-3}` mm on both sides;
    perspective: far at :math:`1.01 \\max(\\text{farthest point}, d + R) + 10^{-3}` mm), except that a perspective
    near plane stays at its own rule. ``near_fraction`` puts the perspective near plane at that fraction of the
    distance :math:`d - ` ``radius`` to the sphere (points nearer the light are clipped).

    The camera's up is +y, or +z when the view axis is within :math:`\\arccos 0.9` of the y axis.

    Args:
        light: a point, spot or directional light.
        centre: bounding-sphere centre (mm).
        radius: bounding-sphere radius (mm, > 0).
        resolution: image width and height in pixels.
        margin: half-extent of the view over ``radius`` (> 0; e.g. room for light bent outside the silhouette).
        points: optional :math:`(N, 3)` points (mm, any floating dtype and device) whose depth range near and far
            must enclose, e.g. every vertex of a scene.
        max_half_angle_deg: cap of the perspective half angle in degrees, in (0, 90) (default: no cap).
        near_fraction: perspective near plane at this fraction (in (0, 1]) of :math:`d -` ``radius``.

    Raises:
        TypeError: a wrong light or option type.
        ValueError: values out of range; a point or spot light inside the sphere of radius :math:`R` (within 1% of
            it) or, when ``max_half_angle_deg`` is given (the view need not hold all of that sphere), inside the
            bounding sphere itself (within 1%).

    Examples:
        >>> cam = light_camera(PointLight((0, 0, 100), 1.0), (0, 0, 0), 10.0, 64)
        >>> cam.projection, round(cam.fov_deg, 2)
        ('perspective', 11.71)
        >>> cam = light_camera(PointLight((0, 0, 12), 1.0), (0, 0, 0), 10.0, 64, margin=1.5, max_half_angle_deg=80.0,
        ...                    near_fraction=0.5)
        >>> round(cam.fov_deg, 1), round(cam.near, 3)
        (160.0, 1.0)
    """
    if not (radius > 0 and math.isfinite(radius)):
        raise ValueError(f"radius: expected a finite value > 0, got {radius!r}")
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1:
        raise ValueError(f"resolution: expected a positive int, got {resolution!r}")
    r = radius * _positive(margin, "margin")
    cap = None if max_half_angle_deg is None else _positive(max_half_angle_deg, "max_half_angle_deg", 90.0, False)
    near_frac = None if near_fraction is None else _positive(near_fraction, "near_fraction", 1.0)
    depth_pts = None
    if points is not None:
        check_tensor(points, "points")
        check_shape(points, "points", "N,3")
        if points.shape[0] == 0 or not bool(torch.isfinite(points).all()):
            raise ValueError(f"points: expected at least one point, all finite, got shape {tuple(points.shape)}")
        # float64 on the points' device (the CPU for MPS, which has no float64): only the extremes come back
        dev = points.device if points.device.type != "mps" else torch.device("cpu")
        depth_pts = points.detach().to(device=dev, dtype=torch.float64)

    def along(origin: Sequence[float], axis: Sequence[float]) -> Tensor:
        o = torch.tensor(origin, dtype=torch.float64, device=depth_pts.device)
        return (depth_pts - o) @ torch.tensor(axis, dtype=torch.float64, device=depth_pts.device)

    if isinstance(light, DirectionalLight):
        d = light.direction
        eye = tuple(c - 2.0 * r * di for c, di in zip(centre, d))
        if depth_pts is None:
            near, far = 0.5 * r, 3.5 * r
        else:
            depth, pad = along(eye, d), 0.01 * radius + 1e-3
            near, far = float(depth.min()) - pad, float(depth.max()) + pad
        return Camera(eye=eye, target=tuple(centre), up=_up_for(d), width=resolution, height=resolution,
                      near=near, far=far, projection="orthographic", ortho_half_height=r)
    if not isinstance(light, (PointLight, SpotLight)):
        raise TypeError(f"light: expected PointLight, DirectionalLight or SpotLight, got {type(light).__name__}")
    offset = tuple(c - p for c, p in zip(centre, light.position))
    dist = math.sqrt(sum(o * o for o in offset))
    inside = radius if cap is not None else r
    if dist <= inside * 1.01:
        kind = "spot" if isinstance(light, SpotLight) else "point"
        raise ValueError(
            f"light: expected a {kind} light outside the object's bounding sphere (centre "
            f"{tuple(round(c, 3) for c in centre)}, radius {radius:.3f} mm; a distance > {1.01 * inside:.3f} mm), "
            f"got light position {light.position} at distance {dist:.3f} mm; one frustum cannot see the whole "
            "object from inside it"
        )
    half = math.degrees(math.asin(min(1.0, r / dist)))
    if cap is not None:
        half = min(half, cap)
    near = max(dist - r, 1e-3 * dist) if near_frac is None else near_frac * (dist - radius)
    if depth_pts is None:
        far = dist + r
    else:
        axis = tuple(o / dist for o in offset)
        far = max(float(along(light.position, axis).max()), dist + r) * 1.01 + 1e-3
    return Camera(eye=tuple(light.position), target=tuple(centre), up=_up_for(offset), fov_deg=2.0 * half,
                  width=resolution, height=resolution, near=near, far=far)


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
    clip = transform_points(mesh.vertices.detach(), vp)
    # the depth pass alone (no barycentrics): NDC z back to the distance along the axis through the projection,
    # z_ndc = (a z + b) / (c z + e) with z = -d (perspective: c = -1, e = 0; orthographic: c = 0, e = 1)
    ndc = rasterize_depth(clip, mesh.faces, (resolution, resolution)).to(torch.float64)
    proj = cam.projection_matrix(dtype=torch.float64, device=device)
    a, b, c, e = proj[2, 2], proj[2, 3], proj[3, 2], proj[3, 3]
    z = (b - ndc * e) / (ndc * c - a)
    depth = torch.where(ndc.isfinite(), -z, torch.full_like(ndc, math.inf)).to(dtype)
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
