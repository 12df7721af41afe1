"""Caustics pipeline (Shah 2007, ch. 5): meshes -> light-view G-buffers -> :class:`CausticMap` -> camera image.

:func:`caustic_gbuffers` renders, from one light camera, the refractor's nearest layer (front), its farthest layer
(back) and the receiver's positions texture. :func:`render_caustics` runs :class:`~torchsss.modules.caustics.
CausticMap` on them, converts the map's flux per texel to irradiance on the receiver, and shades a camera image of
the receiver (diffuse, albedo / pi) lit by the direct light (hard shadow of the refractor from a shadow map) plus
the caustic irradiance.

Conventions and choices:

- **Light camera.** :func:`~torchsss.geometry.shadow.light_camera` fitted to the refractor's bounding sphere (centre
  c, radius r): an orthographic box along a directional light of half-size ``margin * r`` (``margin`` > 1 leaves
  room for light bent outside the refractor's silhouette), or a perspective frustum from a point light towards c
  with the half-angle :math:`\\arcsin(\\min(1, margin\\, r / d))` (capped at 80 degrees). Near and far enclose
  every vertex of both meshes along the line of sight (a point light's near plane stays at 0.5 times the distance
  of the refractor's bounding sphere; receiver parts closer than that to the light are clipped). The camera's up
  is +y (+z when the light runs within 26 degrees of the y axis), the rule of the shadow-map cameras.
- **Back layer.** The refractor is rasterized a second time (:func:`~torchsss.geometry.gbuffer.layer_gbuffer`,
  ``farthest=True``) with its clip-space z negated, so that the z-buffer
  keeps the *farthest* surface along every light ray (the clip volume's z range is symmetric, and the
  perspective-correct barycentrics depend on x, y, w only). This needs no consistent face winding (the decimated
  bunny's winding is not guaranteed) and is exactly "the farthest layer" that Wyman's double-surface refraction
  reads. Normals are the interpolated outward vertex normals (CausticMap accepts either orientation), with Max's
  weights by default (:func:`refractor_normals`): a caustic focus amplifies the error of the normals' derivative,
  and the area-weighted normals of a 5120-face sphere (up to 6e-3 rad off) put its caustic 19.8% off the exact one
  at grid 256, against 1.6% with Max's (exact on a sphere; on an 11 x 9 x 8 mm ellipsoid of 5120 faces 15.6% ->
  8.6%, of 20480 faces 4.9% -> 2.4%).
- **Receiver texture.** The receiver alone (the refractor is not drawn into it); texels without receiver hold
  NaN. The receiver's normals are kept for the flux -> irradiance conversion.
- **Flux -> irradiance.** A light-view texel at a receiver point x covers the area :math:`A_\\perp(x) = (4/HW) /
  |\\nabla x_{ndc} \\times \\nabla y_{ndc}|` perpendicular to the light ray through x (the same footprint as in
  :class:`CausticMap`), so the receiver surface it covers is :math:`A_\\perp / \\cos\\theta` and the caustic
  irradiance is :math:`E = \\Phi \\cos\\theta / A_\\perp`, :math:`\\theta` between the receiver normal and the
  ray. Irradiance is set to 0 where :math:`\\cos\\theta < 10^{-3}`.
- **Camera image.** Receiver pixels: :math:`L = \\rho/\\pi\\,(V E_{direct} + E_{caustic})`, :math:`E_{direct} =
  E_\\perp \\max(0, n\\cdot l)` (point light: :math:`I \\max(0, n \\cdot l)/d^2`), V the shadow-map visibility of
  the refractor (the receiver does not shadow itself), :math:`E_{caustic}` the caustic irradiance map sampled
  bilinearly at the pixel's projection into the light view (no light-view occlusion test between receiver parts:
  meant for floors and walls).
- **Refractor pixels** (Shah §5.2, ``appearance=True``): :func:`refractor_paths` sends each pixel's view ray into
  a mirror ray (Fresnel reflectance :math:`F_r(\\cos\\theta_v)`, per channel) and one (``mode="single"``) or two
  (``"double"``) refractions; the exit point on the back surface is searched in the camera's farthest-layer
  positions texture with the caustic map's own back-surface search. Both rays then search the receiver with the
  caustic map's Newton-Raphson search in the receiver's positions texture of a *lookup camera* (the camera widened
  ``lookup_scale`` times, :func:`lookup_camera`, so rays bent out of the frame still find the floor). A ray that
  finds the receiver sees the receiver's radiance there (shaded like the receiver pixels: direct light with the
  refractor's shadow plus the caustic irradiance); one that misses sees the environment (:func:`sky_radiance`: a
  gradient from ``environment`` at the horizon to ``environment_zenith`` at +z). Pixel radiance:
  :math:`F_r L_{refl} + (1 - F_r)(1 - F_r^{back}) e^{-K_a d} L_{trans}`, each channel along its own refracted ray
  (dispersion). Not traced: the object seen in its own reflection, paths with more than two refractions (total
  internal reflection at the back is followed by one mirror step). ``appearance=False``: :math:`F_r L_{env}` only.
- **Background**: the environment (0 by default).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchsss._checks import check_int
from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.gbuffer import layer_gbuffer
from torchsss.geometry.lights import DirectionalLight, PointLight
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.shadow import bounding_sphere, build_shadow_map, light_camera, shadow_visibility
from torchsss.modules.caustics import CausticMap
from torchsss.ops.newton_raphson import lookup_positions
from torchsss.ops.refraction import reflect, refract
from torchsss.physics.fresnel import fresnel_reflectance

__all__ = ["CausticGBuffers", "CausticsResult", "RefractorPaths", "caustic_gbuffers", "caustic_irradiance",
           "caustic_light_camera", "lookup_camera", "refractor_normals", "refractor_paths", "render_caustics",
           "sky_radiance", "texel_footprint"]

_MAX_HALF_ANGLE_DEG = 80.0
_NORMALS = ("max", "area")


class CausticGBuffers(NamedTuple):
    """Light-view G-buffers of a refractor over a receiver (batch 1, the inputs of :class:`CausticMap`).

    Attributes:
        front_position, front_normal: :math:`(1, 3, H, W)` nearest layer of the refractor (NaN / 0 where empty).
        front_mask: :math:`(1, 1, H, W)` bool.
        back_position, back_normal: :math:`(1, 3, H, W)` farthest layer of the refractor.
        back_mask: :math:`(1, 1, H, W)` bool.
        receiver_position: :math:`(1, 3, H_r, W_r)` receiver positions, NaN where no receiver.
        receiver_normal: :math:`(1, 3, H_r, W_r)` unit receiver normals, 0 where no receiver.
        receiver_mask: :math:`(1, 1, H_r, W_r)` bool.
        light: :math:`(1, 4)` homogeneous light for :class:`CausticMap` (xyz towards the light, w = 0; or the
            point light's position, w = 1).
        intensity: :math:`(1, 3)` irradiance of a directional light, intensity of a point light.
        view_proj: :math:`(1, 4, 4)` the light camera's world-to-clip matrix.
        camera: the light :class:`~torchsss.geometry.camera.Camera` (grid resolution).
    """

    front_position: Tensor
    front_normal: Tensor
    front_mask: Tensor
    back_position: Tensor
    back_normal: Tensor
    back_mask: Tensor
    receiver_position: Tensor
    receiver_normal: Tensor
    receiver_mask: Tensor
    light: Tensor
    intensity: Tensor
    view_proj: Tensor
    camera: Camera

    def module_inputs(self) -> tuple[Tensor, ...]:
        """The ten positional inputs of :meth:`CausticMap.forward`, in order."""
        return (self.front_position, self.front_normal, self.front_mask, self.back_position, self.back_normal,
                self.back_mask, self.receiver_position, self.light, self.intensity, self.view_proj)


@dataclass
class CausticsResult:
    """A rendered caustics image and its intermediate maps.

    Attributes:
        radiance: :math:`(1, 3, H, W)` camera image (linear radiance; 0 on background).
        receiver_mask: :math:`(1, 1, H, W)` bool, pixels that see the receiver.
        refractor_mask: :math:`(1, 1, H, W)` bool, pixels that see the refractor.
        direct: :math:`(1, 3, H, W)` direct irradiance on the receiver pixels (shadowed).
        caustic: :math:`(1, 3, H, W)` caustic irradiance on the receiver pixels.
        caustic_maps: per light, the :math:`(1, 3, H_r, W_r)` light-view caustic flux per texel.
        irradiance_maps: per light, the light-view caustic irradiance maps.
        gbuffers: per light, the :class:`CausticGBuffers`.
        stats: timings in seconds.
        paths: the refractor pixels' :class:`RefractorPaths` (None with ``appearance=False``).
    """

    radiance: Tensor
    receiver_mask: Tensor
    refractor_mask: Tensor
    direct: Tensor
    caustic: Tensor
    caustic_maps: list = field(default_factory=list)
    irradiance_maps: list = field(default_factory=list)
    gbuffers: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    paths: RefractorPaths | None = None


# -- checks ------------------------------------------------------------------------------------------------------------
def _check_mesh(mesh: object, name: str) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{name}: expected a torchsss Mesh, got {type(mesh).__name__}")
    return mesh


def _check_light(light: object, name: str = "light") -> DirectionalLight | PointLight:
    if not isinstance(light, (DirectionalLight, PointLight)):
        raise TypeError(f"{name}: expected a DirectionalLight or PointLight, got {type(light).__name__}")
    return light



def _check_number(value: object, name: str, minimum: float, inclusive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name}: expected a real number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v) or v < minimum or (v == minimum and not inclusive):
        raise ValueError(f"{name}: expected a finite number {'>=' if inclusive else '>'} {minimum}, got {value!r}")
    return v


# -- light camera and G-buffers ----------------------------------------------------------------------------------
def caustic_light_camera(refractor: Mesh, receiver: Mesh, light: DirectionalLight | PointLight, resolution: int,
                         margin: float = 1.5) -> Camera:
    """The light camera of :func:`caustic_gbuffers` (see the module docstring).

    :func:`~torchsss.geometry.shadow.light_camera` on the refractor's bounding sphere with a half-extent of
    ``margin`` times its radius, near and far around every vertex of both meshes, the half angle capped at 80
    degrees and a point light's near plane at half the distance to the bounding sphere.

    Raises:
        TypeError, ValueError: bad arguments; a point light inside the refractor's bounding sphere.

    Examples:
        >>> from torchsss.geometry.procedural import plane, sphere
        >>> cam = caustic_light_camera(sphere(10.0, 3), plane(80.0, 80.0, 2), DirectionalLight((0, 0, -1), 1), 64)
        >>> cam.projection, round(cam.ortho_half_height, 3)
        ('orthographic', 15.0)
    """
    _check_mesh(refractor, "refractor")
    _check_mesh(receiver, "receiver")
    _check_light(light)
    resolution = check_int(resolution, "resolution", 1)
    margin = _check_number(margin, "margin", 0.0)
    centre, radius = bounding_sphere(refractor)
    if not radius > 0:
        raise ValueError(f"refractor: expected a mesh of non-zero extent, got bounding radius {radius}")
    points = torch.cat([refractor.vertices.detach().double(), receiver.vertices.detach().to(refractor.vertices.device,
                                                                                         torch.float64)])
    return light_camera(light, centre, radius, resolution, margin=margin, points=points,
                        max_half_angle_deg=_MAX_HALF_ANGLE_DEG, near_fraction=0.5)


def refractor_normals(refractor: Mesh, normals: str) -> Tensor:
    """The per-vertex normals the caustics pipeline interpolates on the refractor, :math:`(V, 3)`.

    ``"max"``: :attr:`~torchsss.geometry.mesh.Mesh.vertex_normals_max` (Max's weights: exact on a sphere; the glass
    sphere of 5120 faces at grid 256: caustic 1.6% relative RMSE against 19.8% with the area weights); ``"area"``:
    :attr:`~torchsss.geometry.mesh.Mesh.vertex_normals`.
    """
    if normals not in _NORMALS:
        raise ValueError(f"normals: expected one of {_NORMALS}, got {normals!r}")
    return refractor.vertex_normals_max if normals == "max" else refractor.vertex_normals


def caustic_gbuffers(refractor: Mesh, receiver: Mesh, light: DirectionalLight | PointLight, resolution: int = 256,
                     *, map_resolution: int | None = None, margin: float = 1.5,
                     normals: str = "max") -> CausticGBuffers:
    """Light-view G-buffers of ``refractor`` over ``receiver`` for :class:`CausticMap`.

    Args:
        refractor: the refractive object (mm).
        receiver: the surfaces that catch the caustic (mm), e.g. a floor plane.
        light: a :class:`DirectionalLight` (orthographic light camera) or :class:`PointLight` (perspective).
        resolution: refractive-grid size (front and back layers), an int >= 1.
        map_resolution: caustic-map size (the receiver texture); default ``resolution``.
        margin: light-camera half-extent over the refractor's bounding radius (> 0).
        normals: the refractor's vertex normals, ``"max"`` (default) or ``"area"`` (:func:`refractor_normals`).

    Returns:
        :class:`CausticGBuffers` in the refractor's dtype (front/back by z-buffering nearest / farthest, see the
        module docstring).

    Raises:
        TypeError: a mesh or light of the wrong type, non-int resolutions.
        ValueError: resolutions < 1, ``margin`` <= 0, a point light inside the refractor's bounding sphere.

    Examples:
        >>> from torchsss.geometry.procedural import plane, sphere
        >>> gb = caustic_gbuffers(sphere(10.0, 3), plane(80.0, 80.0, 2), DirectionalLight((0, 0, -1), 1), 32)
        >>> tuple(gb.front_position.shape), bool(gb.receiver_mask.all())
        ((1, 3, 32, 32), True)
    """
    _check_mesh(refractor, "refractor")
    _check_mesh(receiver, "receiver")
    _check_light(light)
    resolution = check_int(resolution, "resolution", 1)
    map_resolution = resolution if map_resolution is None else check_int(map_resolution, "map_resolution", 1)
    cam = caustic_light_camera(refractor, receiver, light, resolution, margin)
    dtype, device = refractor.vertices.dtype, refractor.vertices.device
    vp = cam.view_proj(dtype=dtype, device=device)
    nv = refractor_normals(refractor, normals)
    fp, fn, fm, *_ = layer_gbuffer(refractor, vp, resolution, normals=nv)
    bp, bn, bm, *_ = layer_gbuffer(refractor, vp, resolution, farthest=True, normals=nv)
    rec = receiver.with_dtype(dtype).with_device(device) if receiver.vertices.dtype != dtype or \
        receiver.vertices.device != device else receiver
    rp, rn, rm, *_ = layer_gbuffer(rec, vp, map_resolution)
    if isinstance(light, DirectionalLight):
        lt = torch.tensor([[-c for c in light.direction] + [0.0]], dtype=dtype, device=device)
        inten = torch.tensor([light.irradiance], dtype=dtype, device=device)
    else:
        lt = torch.tensor([[*light.position, 1.0]], dtype=dtype, device=device)
        inten = torch.tensor([light.intensity], dtype=dtype, device=device)
    return CausticGBuffers(fp, fn, fm, bp, bn, bm, rp, rn, rm, lt, inten, vp[None], cam)


# -- flux -> irradiance ------------------------------------------------------------------------------------------------
def texel_footprint(points: Tensor, view_proj: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Area :math:`A_\\perp` (mm^2) of one light-view texel at ``points``, and the unit light-ray direction there.

    :math:`A_\\perp` is measured perpendicular to the light ray; the direction points away from the light.

    Args:
        points: :math:`(B, N, 3)` finite positions.
        view_proj: :math:`(B, 4, 4)` or :math:`(4, 4)` world-to-clip matrix.
        size: ``(H, W)``.

    Returns:
        ``(area (B, N), direction (B, N, 3))``; area 0 where the Jacobian is degenerate.
    """
    vp = view_proj if view_proj.dim() == 3 else view_proj[None]
    vp = vp.to(points.dtype)
    clip = transform_points(points, vp)
    cw = clip[..., 3:4]
    cw = torch.where(cw != 0, cw, torch.ones_like(cw))
    a = vp[:, None, :, :3]
    gx = (a[:, :, 0] - clip[..., 0:1] / cw * a[:, :, 3]) / cw
    gy = (a[:, :, 1] - clip[..., 1:2] / cw * a[:, :, 3]) / cw
    cross = torch.linalg.cross(gx, gy)
    jac = cross.norm(dim=-1)
    area = torch.where(jac > 0, (4.0 / (size[0] * size[1])) / torch.where(jac > 0, jac, torch.ones_like(jac)),
                       torch.zeros_like(jac))
    # the ray direction is the null direction of the NDC Jacobian: along gx x gy; orient it away from the light
    ray = F.normalize(cross, dim=-1, eps=1e-30)
    depth_grad = (a[:, :, 2] - clip[..., 2:3] / cw * a[:, :, 3]) / cw  # NDC depth grows away from the light
    sign = torch.sign((ray * depth_grad).sum(-1, keepdim=True))
    return area, ray * torch.where(sign == 0, torch.ones_like(sign), sign)


def caustic_irradiance(flux: Tensor, gbuffers: CausticGBuffers, min_cos: float = 1e-3) -> Tensor:
    """Caustic irradiance (W/mm^2 per channel) on the receiver texels: :math:`\\Phi \\cos\\theta / A_\\perp`.

    Args:
        flux: :math:`(1, C, H_r, W_r)` caustic map (flux per texel) from :class:`CausticMap`.
        gbuffers: the G-buffers it was computed from.
        min_cos: below this :math:`\\cos\\theta` the irradiance is set to 0.

    Returns:
        :math:`(1, C, H_r, W_r)` irradiance, 0 where no receiver.
    """
    if not isinstance(flux, Tensor):
        raise TypeError(f"flux: expected a torch.Tensor, got {type(flux).__name__}")
    if flux.dim() != 4 or flux.shape[-2:] != gbuffers.receiver_position.shape[-2:]:
        raise ValueError(f"flux: expected shape (B, C, {gbuffers.receiver_position.shape[-2]}, "
                         f"{gbuffers.receiver_position.shape[-1]}), got {tuple(flux.shape)}")
    h, w = flux.shape[-2:]
    mask = gbuffers.receiver_mask.flatten(2).transpose(1, 2)[..., 0]
    pts = gbuffers.receiver_position.flatten(2).transpose(1, 2)
    pts = torch.where(mask[..., None], pts, torch.zeros_like(pts))
    area, ray = texel_footprint(pts, gbuffers.view_proj, (h, w))
    nrm = gbuffers.receiver_normal.flatten(2).transpose(1, 2)
    cos = (nrm * ray).sum(-1).abs()
    ok = mask & (cos >= min_cos) & (area > 0)
    scale = torch.where(ok, cos / torch.where(area > 0, area, torch.ones_like(area)), torch.zeros_like(area))
    return flux * scale.view(1, 1, h, w).to(flux.dtype)


def _sample_light_view(image: Tensor, points: Tensor, view_proj: Tensor) -> Tensor:
    """Bilinear lookup of a light-view image (1, C, H, W) at world points (1, N, 3): (1, N, C), 0 outside the view."""
    clip = transform_points(points, view_proj.to(points.dtype))
    wc = clip[..., 3:4]
    front = wc > 0
    ndc = clip[..., :2] / torch.where(front, wc, torch.ones_like(wc))
    grid = torch.stack([ndc[..., 0], -ndc[..., 1]], -1)  # grid_sample: y = -1 is row 0 (the top, NDC y = +1)
    grid = torch.where(front & torch.isfinite(grid), grid, torch.full_like(grid, 4.0))
    out = F.grid_sample(image.to(points.dtype), grid[:, None], mode="bilinear", padding_mode="zeros",
                        align_corners=False)  # (1, C, 1, N)
    return out[:, :, 0].transpose(1, 2)


# -- render ------------------------------------------------------------------------------------------------------------
def _rgb(value: object, name: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    if isinstance(value, bool):
        raise TypeError(f"{name}: expected a number or 3 numbers, got bool")
    try:
        t = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"{name}: expected a number or 3 numbers, got {value!r}") from err
    if t.numel() == 1:
        t = t.expand(3)
    if t.numel() != 3 or not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise ValueError(f"{name}: expected one or three finite values >= 0, got {value!r}")
    return t.to(dtype=dtype, device=device)


class RefractorPaths(NamedTuple):
    """The two paths of light that reach the eye from each refractor pixel (see :func:`refractor_paths`).

    Attributes:
        reflect_origin, reflect_direction: :math:`(M, 3)` the mirror ray off the front surface.
        reflect_hit: :math:`(M,)` bool, the mirror ray found a receiver; reflect_point :math:`(M, 3)` where.
        reflect_weight: :math:`(M, C)` Fresnel reflectance of the front surface (1 for ``mode="reflect"``).
        transmit_origin, transmit_direction: :math:`(M, C, 3)` the ray that leaves the object towards the scene
            behind it, per channel (zero weight for ``mode="reflect"``).
        transmit_hit: :math:`(M, C)` bool; transmit_point :math:`(M, C, 3)` the receiver point it sees.
        transmit_weight: :math:`(M, C)` Fresnel transmittance of both surfaces times :math:`e^{-K_a d}`.
    """

    reflect_origin: Tensor
    reflect_direction: Tensor
    reflect_hit: Tensor
    reflect_point: Tensor
    reflect_weight: Tensor
    transmit_origin: Tensor
    transmit_direction: Tensor
    transmit_hit: Tensor
    transmit_point: Tensor
    transmit_weight: Tensor


def lookup_camera(camera: Camera, scale: float) -> Camera:
    """The camera whose receiver positions texture the refractor's rays search: ``camera`` widened ``scale`` times.

    Same eye, target, up and resolution; the tangent of the half field of view (or the orthographic half height)
    times ``scale`` (the field capped at 170 degrees), so that rays bent out of the frame still find the receiver.
    """
    scale = _check_number(scale, "lookup_scale", 1.0, inclusive=True)
    if camera.projection == "orthographic":
        return dataclasses.replace(camera, ortho_half_height=camera.ortho_half_height * scale)
    half = math.atan(scale * math.tan(math.radians(camera.fov_deg) / 2.0))
    return dataclasses.replace(camera, fov_deg=min(170.0, math.degrees(2.0 * half)))


def sky_radiance(direction: Tensor, horizon: Tensor, zenith: Tensor) -> Tensor:
    """The simple environment of the caustics scenes: a sky gradient over +z, uniform below the horizon.

    :math:`L(\\omega) = L_h + (L_z - L_h) \\max(0, \\omega_z)` for unit :math:`\\omega`; :math:`L_h` at and below the
    horizon (a uniform environment when :math:`L_z = L_h`).

    Args:
        direction: :math:`(..., 3)` directions (any non-zero length).
        horizon: :math:`(3,)` RGB radiance at and below the horizon.
        zenith: :math:`(3,)` RGB radiance at the zenith.

    Returns:
        :math:`(..., 3)` radiance.
    """
    up = F.normalize(direction, dim=-1, eps=1e-30)[..., 2:3].clamp(0.0, 1.0)
    return horizon + (zenith - horizon) * up


def refractor_paths(module: CausticMap, position: Tensor, normal: Tensor, eye: Tensor, back_position: Tensor,
                    back_normal: Tensor, back_mask: Tensor, view_proj: Tensor, receiver_position: Tensor,
                    lookup_view_proj: Tensor) -> RefractorPaths:
    """Trace the refractor's pixels as Shah §5.2 does: reflection, and one or two refractions, by texture lookups.

    Every camera pixel on the refractor (front point ``position``, outward ``normal``) sends the view ray
    :math:`v = x - \\text{eye}` (or the orthographic view direction) into

    - the mirror ray :math:`\\text{reflect}(v, n)`, weighted by the exact Fresnel reflectance
      :math:`F_r(\\cos\\theta_v)` (1 for ``module.mode == "reflect"``, a mirror);
    - ``"double"``: the refracted ray :math:`t_1 = \\text{refract}(v, n, 1/\\eta_c)` (one per channel), whose exit
      point on the back layer (the camera's farthest layer) is found by ``module``'s back-surface search
      (:meth:`CausticMap.through_back`, the same Newton-Raphson/Shah search in the camera-view back positions
      texture; where the search loses the ray, Wyman's estimate: the back point behind the pixel, its distance and
      normal); it leaves along :math:`t_2 = \\text{refract}(t_1, n_b, \\eta_c)`, weighted by
      :math:`(1 - F_r)(1 - F_r^{back})\\, e^{-K_a d}`. Total internal reflection at the back is followed one step:
      the internally reflected ray leaves from the exit point (weight :math:`(1 - F_r) e^{-K_a d}`; the further
      bounces inside are not traced). ``"single"``: :math:`t_1` from the front point, weight :math:`1 - F_r`.

    Both rays then search the receiver in ``receiver_position`` (the receiver's positions texture from a camera
    at the eye, :func:`lookup_camera`) with ``module.search``, the Newton-Raphson search of the caustic map.

    Args:
        module: the :class:`CausticMap` (index, absorption, mode and searches).
        position: :math:`(M, 3)` front points of the refractor pixels.
        normal: :math:`(M, 3)` their normals (either orientation).
        eye: :math:`(3,)` the camera's eye (perspective) or :math:`(M, 3)` per-pixel view origins.
        back_position: :math:`(1, 3, H, W)` the camera's farthest layer of the refractor (NaN: none).
        back_normal: :math:`(1, 3, H, W)` its normals.
        back_mask: :math:`(1, 1, H, W)` its coverage.
        view_proj: :math:`(4, 4)` the camera's world-to-clip matrix.
        receiver_position: :math:`(1, 3, H_l, W_l)` receiver positions seen from the lookup camera (NaN: none).
        lookup_view_proj: :math:`(4, 4)` the lookup camera's matrix.

    Returns:
        :class:`RefractorPaths`.
    """
    dtype = position.dtype
    m = position.shape[0]
    ior = module.ior.to(dtype)
    c = ior.numel()
    k_a = module.absorption.to(dtype).expand(c) if module.absorption.numel() == 1 else module.absorption.to(dtype)
    vp = view_proj.to(dtype)[None]
    lvp = lookup_view_proj.to(dtype)[None]
    view = position - eye
    view = F.normalize(view, dim=-1, eps=1e-30)
    n = F.normalize(normal, dim=-1, eps=1e-30)
    n = torch.where(((n * view).sum(-1, keepdim=True) > 0), -n, n)  # face the viewer
    cos_v = (-(n * view).sum(-1)).clamp(0.0, 1.0)
    r_dir = reflect(view, n)
    if module.mode == "reflect":
        r_w = torch.ones(m, c, dtype=dtype, device=position.device)
    else:
        r_w = fresnel_reflectance(cos_v[:, None], ior)
    t1, tir1 = refract(view[:, None, :], n[:, None, :], 1.0 / ior)  # (M, C, 3)
    t_w = (1.0 - r_w) * ~tir1
    if module.mode == "double":
        x_b, t2, d, found, tir2, n_b = module.through_back(position[None], t1[None], back_position.to(dtype),
                                                           back_normal.to(dtype), back_mask, vp, ior)
        x_b, t2, d, found, tir2, n_b = x_b[0], t2[0], d[0], found[0], tir2[0], n_b[0]
        # where the search lost the exit (a ray leaving through another layer of a concave object, a silhouette),
        # Wyman's estimate: the back layer behind the pixel itself, its distance and its normal
        nan = torch.full_like(back_position, float("nan")).to(dtype)
        bm = back_mask != 0
        pb, ok_b = lookup_positions(position[None], torch.where(bm, back_position.to(dtype), nan), vp)
        nb, _ = lookup_positions(position[None], torch.where(bm, back_normal.to(dtype), nan), vp)
        d_v = (pb[0] - position).norm(dim=-1)[:, None].expand(m, c)
        x_v = position[:, None, :] + d_v[..., None] * t1
        n_v = F.normalize(nb[0], dim=-1, eps=1e-30)[:, None, :].expand(m, c, 3)
        t2_v, tir_v = refract(t1, n_v, ior)
        lost = ~found & ok_b[0][:, None]
        x_b = torch.where(lost[..., None], x_v, x_b)
        n_b = torch.where(lost[..., None], n_v, n_b)
        t2 = torch.where(lost[..., None], t2_v, t2)
        tir2 = torch.where(lost, tir_v, tir2)
        d = torch.where(lost, d_v, d)
        found = found | lost
        cos_b = (t1 * n_b).sum(-1).abs()
        f_back = fresnel_reflectance(cos_b, 1.0 / ior)  # from inside: relative index 1 / eta
        t_dir = torch.where(tir2[..., None], reflect(t1, n_b), t2)
        t_w = t_w * torch.where(tir2, torch.ones_like(f_back), 1.0 - f_back) * torch.exp(-k_a * d) * found
        t_org = x_b
    elif module.mode == "single":
        t_org, t_dir = position[:, None, :].expand(m, c, 3), t1
    else:
        t_org, t_dir = position[:, None, :].expand(m, c, 3), t1
        t_w = torch.zeros_like(t_w)
    t_dir = torch.where(torch.isfinite(t_dir), t_dir, torch.zeros_like(t_dir))
    t_org = torch.where(torch.isfinite(t_org), t_org, torch.zeros_like(t_org))

    origins = torch.cat([position, t_org.reshape(m * c, 3)])[None]
    dirs = torch.cat([r_dir, t_dir.reshape(m * c, 3)])[None]
    rec = receiver_position.to(dtype)
    dist, hit = module.search(origins, dirs, rec, lvp)
    pts = origins + dist[..., None] * F.normalize(dirs, dim=-1, eps=1e-30)
    pts = torch.where(hit[..., None], pts, torch.zeros_like(pts))[0]
    hit = hit[0]
    return RefractorPaths(position, r_dir, hit[:m], pts[:m], r_w, t_org, t_dir, hit[m:].reshape(m, c),
                          pts[m:].reshape(m, c, 3), t_w)


def render_caustics(
    refractor: Mesh,
    receiver: Mesh,
    lights: DirectionalLight | PointLight | Sequence[DirectionalLight | PointLight],
    camera: Camera,
    *,
    ior: float | Sequence[float] = 1.5,
    absorption: float | Sequence[float] = 0.0,
    resolution: int = 256,
    map_resolution: int | None = None,
    mode: str = "double",
    albedo: float | Sequence[float] = 0.8,
    environment: float | Sequence[float] = 0.0,
    environment_zenith: float | Sequence[float] | None = None,
    appearance: bool = True,
    lookup_scale: float = 2.0,
    shadow_resolution: int = 1024,
    margin: float = 1.5,
    normals: str = "max",
    module: CausticMap | None = None,
    **module_kwargs,
) -> CausticsResult:
    """Render the receiver lit directly and through the refractor's caustics, and the refractor, seen from ``camera``.

    Args:
        refractor: the refractive object (mm).
        receiver: the diffuse receiver (mm), e.g. ``plane(...)`` under the refractor.
        lights: one light or a sequence of :class:`DirectionalLight` / :class:`PointLight`.
        camera: the viewing camera.
        ior: refractor index (a number, or 3 values for dispersion).
        absorption: :math:`K_a` in mm^-1 (a number or 3 values).
        resolution: refractive-grid size of every light view.
        map_resolution: caustic-map size (default ``resolution``).
        mode: :class:`CausticMap` mode (``"double"``, ``"single"``, ``"reflect"``); also the refractor's look.
        albedo: receiver diffuse albedo (number or RGB).
        environment: radiance of the environment at (and below) the horizon (number or RGB); seen in the
            refractor's reflection and refraction and on the background pixels. 0 (default) is black.
        environment_zenith: radiance at the zenith (+z) of a sky gradient (:func:`sky_radiance`); None: uniform.
        appearance: draw the refractor with its reflection and refraction of the scene (:func:`refractor_paths`);
            False draws only the Fresnel reflection of the environment.
        lookup_scale: field of view of the receiver's lookup texture over the camera's (:func:`lookup_camera`).
        shadow_resolution: shadow-map size for the refractor's shadow.
        margin: light-camera half-extent over the refractor's bounding radius.
        normals: the refractor's vertex normals, ``"max"`` (default) or ``"area"`` (:func:`refractor_normals`), in
            the light views and the camera view.
        module: a ready :class:`CausticMap` (then ``ior``, ``absorption``, ``mode`` and ``module_kwargs`` are not
            used); otherwise one is built from them.
        **module_kwargs: more :class:`CausticMap` options (``splat``, ``subdivisions``, ``fresnel``, ...).

    Returns:
        :class:`CausticsResult` (image, masks, per-light maps, timings).

    Raises:
        TypeError, ValueError: bad meshes, lights, camera or options (naming the argument).
    """
    t_start = time.perf_counter()
    _check_mesh(refractor, "refractor")
    _check_mesh(receiver, "receiver")
    light_list = [lights] if isinstance(lights, (DirectionalLight, PointLight)) else lights
    if isinstance(light_list, (str, bytes)) or not isinstance(light_list, Sequence) or len(light_list) == 0:
        raise TypeError(f"lights: expected a light or a non-empty sequence of lights, got {type(lights).__name__}")
    for i, light in enumerate(light_list):
        _check_light(light, f"lights[{i}]")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a Camera, got {type(camera).__name__}")
    if module is not None and not isinstance(module, CausticMap):
        raise TypeError(f"module: expected a CausticMap or None, got {type(module).__name__}")
    if not isinstance(appearance, bool):
        raise TypeError(f"appearance: expected a bool, got {type(appearance).__name__}")
    shadow_resolution = check_int(shadow_resolution, "shadow_resolution", 1)
    dtype, device = refractor.vertices.dtype, refractor.vertices.device
    if receiver.vertices.dtype != dtype or receiver.vertices.device != device:
        receiver = receiver.with_dtype(dtype).with_device(device)
    rho = _rgb(albedo, "albedo", dtype, device)
    env = _rgb(environment, "environment", dtype, device)
    env_z = env if environment_zenith is None else _rgb(environment_zenith, "environment_zenith", dtype, device)
    look_cam = lookup_camera(camera, lookup_scale)
    if module is None:
        module = CausticMap(ior, absorption, mode=mode, **module_kwargs)
    module = module.to(device)
    eta = float(module.ior.mean())

    # camera view of both meshes
    t0 = time.perf_counter()
    vp_cam = camera.view_proj(dtype=dtype, device=device)
    res = camera.resolution
    h, w = res
    r_pos, r_nrm, r_mask, r_depth, *_ = layer_gbuffer(receiver, vp_cam, res, fill=0.0)
    nv = refractor_normals(refractor, normals)
    f_pos, f_nrm, f_mask, f_depth, *_ = layer_gbuffer(refractor, vp_cam, res, fill=0.0, normals=nv)
    rec_vis = r_mask & (~f_mask | (r_depth < f_depth))
    ref_vis = f_mask & ~rec_vis
    pts = r_pos.flatten(2).transpose(1, 2)
    nrm = r_nrm.flatten(2).transpose(1, 2)
    keep = rec_vis.flatten(1)
    pts = torch.where(keep[..., None], pts, torch.zeros_like(pts))
    eye = torch.tensor(camera.eye, dtype=dtype, device=device)
    # view rays of every pixel (origin far behind the image plane for an orthographic camera)
    if camera.projection == "orthographic":
        fwd = F.normalize(torch.tensor(camera.target, dtype=dtype, device=device) - eye, dim=0)
    ref_idx = ref_vis.flatten().nonzero()[:, 0]
    f_p = f_pos.flatten(2)[0].T.index_select(0, ref_idx)
    f_n = f_nrm.flatten(2)[0].T.index_select(0, ref_idx)
    origin = f_p - 1e3 * fwd if camera.projection == "orthographic" else eye
    paths = None
    n_extra = 0
    if appearance and ref_idx.numel():
        b_pos, b_nrm, b_mask, *_ = layer_gbuffer(refractor, vp_cam, res, farthest=True, normals=nv)
        vp_look = look_cam.view_proj(dtype=dtype, device=device)
        l_pos, l_nrm, l_mask, *_ = layer_gbuffer(receiver, vp_look, look_cam.resolution)
        with torch.no_grad():
            paths = refractor_paths(module, f_p, f_n, origin, b_pos, b_nrm, b_mask, vp_cam, l_pos, vp_look)
        hit_pts = torch.cat([paths.reflect_point, paths.transmit_point.reshape(-1, 3)])
        hit_ok = torch.cat([paths.reflect_hit, paths.transmit_hit.reshape(-1)])
        l_nrm_tex = torch.where(l_mask, l_nrm, torch.full_like(l_nrm, float("nan")))
        hit_n, _ = lookup_positions(hit_pts[None], l_nrm_tex, vp_look)
        hit_n = F.normalize(hit_n, dim=-1, eps=1e-30)
        n_extra = hit_pts.shape[0]
        pts = torch.cat([pts, torch.where(hit_ok[:, None], hit_pts, torch.zeros_like(hit_pts))[None]], 1)
        nrm = torch.cat([nrm, hit_n], 1)
        keep = torch.cat([keep, hit_ok[None]], 1)
    t_camera = time.perf_counter() - t0

    direct = torch.zeros(1, pts.shape[1], 3, dtype=dtype, device=device)
    caustic = torch.zeros_like(direct)
    maps, irr_maps, gbs = [], [], []
    t_gb = t_mod = t_shade = 0.0
    for light in light_list:
        t0 = time.perf_counter()
        gb = caustic_gbuffers(refractor, receiver, light, resolution, map_resolution=map_resolution, margin=margin,
                              normals=normals)
        t_gb += time.perf_counter() - t0
        t0 = time.perf_counter()
        with torch.no_grad():
            cmap = module(*gb.module_inputs())
        t_mod += time.perf_counter() - t0
        t0 = time.perf_counter()
        irr = caustic_irradiance(cmap, gb)
        if cmap.shape[1] == 1:
            irr = irr.expand(1, 3, *irr.shape[-2:])
        # direct light with the refractor's shadow
        if isinstance(light, DirectionalLight):
            to_light = -torch.tensor(light.direction, dtype=dtype, device=device).expand_as(pts)
            e0 = torch.tensor(light.irradiance, dtype=dtype, device=device).view(1, 1, 3)
        else:
            lp = torch.tensor(light.position, dtype=dtype, device=device)
            dv = lp - pts
            d2 = (dv * dv).sum(-1, keepdim=True).clamp_min(1e-12)
            to_light = dv / d2.sqrt()
            e0 = torch.tensor(light.intensity, dtype=dtype, device=device).view(1, 1, 3) / d2
        cos = (nrm * to_light).sum(-1, keepdim=True).clamp_min(0.0)
        sm = build_shadow_map(refractor, light, shadow_resolution)
        vis = shadow_visibility(sm, pts, nrm, light)[..., None]
        direct = direct + e0 * cos * vis * keep[..., None]
        caustic = caustic + _sample_light_view(irr, pts, gb.view_proj) * keep[..., None]
        t_shade += time.perf_counter() - t0
        maps.append(cmap)
        irr_maps.append(irr)
        gbs.append(gb)

    t0 = time.perf_counter()
    npx = h * w

    def img(x: Tensor) -> Tensor:
        return x[:, :npx].transpose(1, 2).reshape(1, -1, h, w)

    direct_img, caustic_img = img(direct), img(caustic)
    radiance = rho.view(1, 3, 1, 1) / math.pi * (direct_img + caustic_img) * rec_vis
    # the refractor's pixels
    if camera.projection == "orthographic":
        view_dir = fwd.expand(ref_idx.numel(), 3)
    else:
        view_dir = F.normalize(f_p - eye, dim=-1, eps=1e-30)
    if paths is not None:
        seen = rho / math.pi * (direct[0, npx:] + caustic[0, npx:])  # (n_extra, 3) receiver radiance at the hits
        m = ref_idx.numel()
        c = paths.transmit_hit.shape[1]
        l_r = torch.where(paths.reflect_hit[:, None], seen[:m], sky_radiance(paths.reflect_direction, env, env_z))
        l_t = seen[m:].reshape(m, c, 3)
        l_t = torch.where(paths.transmit_hit[..., None], l_t, sky_radiance(paths.transmit_direction, env, env_z))
        if c == 1:
            l_t = l_t[:, 0] * paths.transmit_weight
        else:  # channel k sees its own ray
            l_t = torch.diagonal(l_t, dim1=1, dim2=2) * paths.transmit_weight
        shade = paths.reflect_weight * l_r + l_t
    else:
        cos_v = (view_dir * F.normalize(f_n, dim=-1, eps=1e-30)).sum(-1, keepdim=True).abs()
        shade = fresnel_reflectance(cos_v, eta) * sky_radiance(-view_dir, env, env_z)
    ref_img = torch.zeros(3, npx, dtype=dtype, device=device)
    ref_img[:, ref_idx] = shade.T.to(dtype)
    radiance = radiance + ref_img.view(1, 3, h, w)
    # the background shows the environment
    if bool((env > 0).any() or (env_z > 0).any()):
        bg = ~(rec_vis | ref_vis)
        ndc_y = 1.0 - (torch.arange(h, dtype=dtype, device=device) + 0.5) * 2.0 / h
        ndc_x = (torch.arange(w, dtype=dtype, device=device) + 0.5) * 2.0 / w - 1.0
        inv = torch.linalg.inv(vp_cam)
        ny, nx = torch.meshgrid(ndc_y, ndc_x, indexing="ij")
        near = torch.stack([nx, ny, -torch.ones_like(nx), torch.ones_like(nx)], -1) @ inv.T
        far = torch.stack([nx, ny, torch.ones_like(nx), torch.ones_like(nx)], -1) @ inv.T
        ray = far[..., :3] / far[..., 3:] - near[..., :3] / near[..., 3:]
        sky = sky_radiance(ray, env, env_z).permute(2, 0, 1)[None]
        radiance = torch.where(bg, sky, radiance)
    radiance = torch.nan_to_num(radiance, nan=0.0, posinf=0.0, neginf=0.0)
    t_shade += time.perf_counter() - t0
    stats = {"t_camera_s": t_camera, "t_gbuffers_s": t_gb, "t_module_s": t_mod, "t_shade_s": t_shade,
             "t_frame_s": time.perf_counter() - t_start, "refractor_pixels": int(ref_idx.numel()),
             "refractor_lookups": n_extra}
    return CausticsResult(radiance, rec_vis, ref_vis, direct_img * rec_vis, caustic_img * rec_vis, maps, irr_maps,
                          gbs, stats, paths)
