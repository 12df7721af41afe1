"""Image-space G-buffers: what the camera sees and what the light sees.

The camera G-buffer gives the receivers :math:`x_o` of every method (positions, shading normals, the unit
direction towards the eye). The light-view G-buffer gives the sources of the splatting and caustics methods:
the first surface the light sees at every light-view pixel, its transmitted irradiance and the surface area
the pixel covers,

.. math::

    dA = \\frac{\\text{pixel footprint}}{\\cos\\theta}, \\qquad
    \\text{footprint} = \\Omega_{pix}\\, d^2 \\text{ (perspective)}, \\quad s^2 \\text{ (orthographic)},

with :math:`\\Omega_{pix} = s^2 \\cos^3\\alpha` the solid angle of a pixel of size s on the unit image plane
whose ray makes the angle :math:`\\alpha` with the axis, d the distance to the light and :math:`\\theta` the
angle between the normal and the direction to the light. At grazing incidence :math:`dA` grows without bound;
it is clamped through :math:`\\cos\\theta \\ge` ``min_cos``. The product that the methods actually need, the
flux :math:`E\\,dA = E_\\perp\\,\\text{footprint}\\,F_t`, is computed without the division and stays exact and
bounded at every angle (it is 0 where :math:`\\cos\\theta \\le 0`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.lights import Light, _channel_eta, incident_light
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.raster import Raster, interpolate, rasterize
from torchsss.geometry.shadow import bounding_sphere, light_camera
from torchsss.physics.fresnel import check_fresnel, transmittance

__all__ = ["GBuffer", "LayerGBuffer", "LightView", "bend_towards_viewer", "camera_gbuffer", "interpolate_normals",
           "layer_gbuffer", "light_view", "view_cosine"]


class GBuffer(NamedTuple):
    """Camera-view surface data; every tensor :math:`(B, C, H, W)`, zeros on the background.

    Attributes:
        position: :math:`(B, 3, H, W)` mm.
        normal: :math:`(B, 3, H, W)` unit shading normals (interpolated vertex normals).
        view_dir: :math:`(B, 3, H, W)` unit direction from the surface towards the eye.
        face_id: :math:`(B, 1, H, W)` int64, -1 on background.
        mask: :math:`(B, 1, H, W)` bool.
    """

    position: Tensor
    normal: Tensor
    view_dir: Tensor
    face_id: Tensor
    mask: Tensor


def _normalize(v: Tensor, dim: int = 1) -> Tensor:
    return F.normalize(v, dim=dim, eps=1e-12)


class LayerGBuffer(NamedTuple):
    """One depth layer of a mesh seen through a world-to-clip matrix (:func:`layer_gbuffer`).

    Attributes:
        position: :math:`(B, 3, H, W)` mm, ``fill`` where ``mask`` is False.
        normal: :math:`(B, 3, H, W)` unit shading normals (interpolated vertex normals), 0 where ``mask`` is False.
        mask: :math:`(B, 1, H, W)` bool, a face covers the pixel centre.
        depth: :math:`(B, 1, H, W)` NDC :math:`z` of the kept surface (in [-1, 1], smaller is nearer the
            camera, for the farthest layer too), :math:`+\\infty` where ``mask`` is False.
        face_id: :math:`(B, 1, H, W)` int64 face of the kept surface, -1 where ``mask`` is False.
        bary: :math:`(B, 3, H, W)` its perspective-correct barycentric weights, zeros where ``mask`` is False.
    """

    position: Tensor
    normal: Tensor
    mask: Tensor
    depth: Tensor
    face_id: Tensor
    bary: Tensor


def interpolate_normals(mesh: Mesh, raster: Raster, normals: Tensor | None = None) -> Tensor:
    """Interpolate shading normals (not normalised) at a raster of ``mesh``, :math:`(B, 3, H, W)`.

    Args:
        mesh: the rasterized mesh, :math:`F` faces and :math:`V` vertices.
        raster: :func:`~torchsss.geometry.raster.rasterize` (or ``rasterize_uv``) of ``mesh.faces``.
        normals: :math:`(V, 3)` per-vertex or :math:`(F, 3, 3)` per-corner normals; default
            :meth:`Mesh.corner_normals` (split at creases).

    Raises:
        ValueError: ``normals`` of another shape.
    """
    if normals is None:
        normals = mesh.corner_normals()
    if isinstance(normals, Tensor) and normals.shape == mesh.vertices.shape:
        return interpolate(normals, raster, mesh.faces)
    if isinstance(normals, Tensor) and normals.shape == (mesh.num_faces, 3, 3):
        corners = torch.arange(3 * mesh.num_faces, device=mesh.faces.device).view(-1, 3)
        return interpolate(normals.reshape(-1, 3), raster, corners)
    got = tuple(normals.shape) if isinstance(normals, Tensor) else type(normals).__name__
    raise ValueError(f"normals: expected a tensor of shape {tuple(mesh.vertices.shape)} (one per vertex) or "
                     f"{(mesh.num_faces, 3, 3)} (one per face corner), got {got}")


def layer_gbuffer(mesh: Mesh, view_proj: Tensor, resolution: int | tuple[int, int], *, farthest: bool = False,
                  fill: float = math.nan, normals: Tensor | None = None) -> LayerGBuffer:
    """Rasterize ``mesh`` through ``view_proj`` and interpolate positions and unit normals of one depth layer.

    The nearest layer is the z-buffer's; the farthest (``farthest=True``) is found by negating clip-space z, so
    that the z-buffer keeps the farthest surface along every pixel's ray (the clip volume's z range is symmetric,
    and the perspective-correct barycentrics depend on x, y, w only). This needs no consistent face winding.

    Args:
        mesh: the geometry (mm), :math:`V` vertices.
        view_proj: :math:`(4, 4)` world-to-clip matrix (e.g. :meth:`Camera.view_proj`), in the mesh's dtype.
        resolution: ``(H, W)``, or one int for a square image.
        farthest: keep the farthest surface instead of the nearest.
        fill: position value where nothing is seen (NaN by default; 0 for the zero-background G-buffers).
        normals: :math:`(V, 3)` per-vertex or :math:`(F, 3, 3)` per-corner normals to interpolate (default
            :meth:`Mesh.corner_normals`: smooth, split at creases; the caustics pipeline passes
            :attr:`Mesh.vertex_normals_max`).

    Returns:
        :class:`LayerGBuffer` with batch 1, in the mesh's dtype and device; position and normal are differentiable
        w.r.t. the mesh vertices (inside each face).

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> cam = Camera(eye=(0, 0, 60), target=(0, 0, 0), width=32, height=32)
        >>> m = sphere(10.0, 3)
        >>> near = layer_gbuffer(m, cam.view_proj(), 32)
        >>> far = layer_gbuffer(m, cam.view_proj(), 32, farthest=True)
        >>> round(near.position[0, 2, 16, 16].item(), 1), round(far.position[0, 2, 16, 16].item(), 1)
        (10.0, -10.0)
        >>> bool(near.position[0, 0, 0, 0].isnan()), bool(near.depth[0, 0, 16, 16] < far.depth[0, 0, 16, 16])
        (True, True)
    """
    size = (resolution, resolution) if isinstance(resolution, int) and not isinstance(resolution, bool) else resolution
    clip = transform_points(mesh.vertices, view_proj)
    if farthest:
        clip = clip * torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=clip.dtype, device=clip.device)
    raster = rasterize(clip, mesh.faces, size)
    mask = raster.mask
    position = interpolate(mesh.vertices, raster, mesh.faces)
    if fill != 0.0:  # interpolate already gives zeros on the background (NaN != 0 too)
        position = torch.where(mask, position, torch.full_like(position, fill))
    normal = _normalize(interpolate_normals(mesh, raster, normals)) * mask
    depth = torch.where(mask, -raster.depth, raster.depth) if farthest else raster.depth
    return LayerGBuffer(position, normal, mask, depth, raster.face_id, raster.bary)


def _check_in_front(mesh: Mesh, cam: Camera) -> None:
    view = cam.view_matrix(dtype=torch.float64, device=mesh.vertices.device)
    depth = -transform_points(mesh.vertices.double(), view)[..., 2]
    if float(depth.max()) <= 0.0:
        raise ValueError(
            f"camera: expected the mesh in front of the camera, got every vertex behind it (view depths "
            f"{float(depth.min()):.3f} to {float(depth.max()):.3f} mm: the camera looks away from the object); point "
            f"'target' at the object (eye {cam.eye}, target {cam.target})"
        )
    if float(depth.min()) < cam.near:
        raise ValueError(
            f"camera: expected the mesh entirely beyond the near plane ({cam.near} mm), got a vertex at view depth "
            f"{float(depth.min()):.3f} mm (the camera is inside or too close to the mesh); move the eye back or "
            "lower 'near'"
        )


def camera_gbuffer(mesh: Mesh, camera: Camera) -> GBuffer:
    """Rasterize ``mesh`` from ``camera`` and interpolate positions and normals.

    Raises:
        ValueError: a vertex lies in front of the near plane (camera inside or too close to the mesh).

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> g = camera_gbuffer(sphere(10.0, 3), Camera(eye=(0, 0, 60), target=(0, 0, 0), width=32, height=32))
        >>> tuple(g.position.shape), round(g.position[0, 2, 16, 16].item(), 1)
        ((1, 3, 32, 32), 10.0)
    """
    _check_in_front(mesh, camera)
    dtype, device = mesh.vertices.dtype, mesh.vertices.device
    layer = layer_gbuffer(mesh, camera.view_proj(dtype=dtype, device=device), camera.resolution, fill=0.0)
    position, normal, mask = layer.position, layer.normal, layer.mask
    eye = torch.tensor(camera.eye, dtype=dtype, device=device).view(1, 3, 1, 1)
    if camera.projection == "orthographic":
        fwd = torch.tensor(camera.target, dtype=dtype, device=device).view(1, 3, 1, 1) - eye
        view_dir = (-_normalize(fwd)).expand_as(position)
    else:
        view_dir = _normalize(eye - position)
    face = layer.face_id.clamp_min(0)[:, 0]                                        # (B, H, W)
    face_normal = mesh.face_normals[face].permute(0, 3, 1, 2)                      # (B, 3, H, W)
    normal = bend_towards_viewer(normal, view_dir, face_normal) * mask
    return GBuffer(position, normal, view_dir * mask, layer.face_id, mask)


def bend_towards_viewer(normal: Tensor, view_dir: Tensor, face_normal: Tensor) -> Tensor:
    """Shading normals turned no more away from the viewer than the face the camera sees.

    Interpolated vertex normals can turn away from the eye on a face the camera sees (inner silhouettes: between a
    cow's legs, along a bunny's ears), where the exit Fresnel term :math:`F_t(\\cos\\theta_o)` then drops to 0 and
    leaves isolated black pixels. Where :math:`\\cos_s = n_s \\cdot v` is smaller than the face's
    :math:`\\cos_g = |n_g \\cdot v|`, the normal is rotated in the plane of :math:`n_s` and :math:`v` until
    :math:`n \\cdot v = \\cos_g`: :math:`n = \\cos_g v + \\sqrt{1 - \\cos_g^2}\\, w` with
    :math:`w = (n_s - \\cos_s v) / |n_s - \\cos_s v|` (the face normal where :math:`n_s = \\pm v`). Elsewhere the
    shading normal is kept. So the exit cosine is :math:`\\max(\\cos_s, \\cos_g)`: never more grazing than the
    visible face.

    Args:
        normal: :math:`(B, 3, H, W)` unit shading normals.
        view_dir: :math:`(B, 3, H, W)` unit directions towards the eye.
        face_normal: :math:`(B, 3, H, W)` unit normals of the faces seen (either orientation).

    Returns:
        :math:`(B, 3, H, W)` unit normals.

    Examples:
        >>> v = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
        >>> n = bend_towards_viewer(torch.tensor([1.0, 0.0, -0.1]).view(1, 3, 1, 1) / 1.005, v,
        ...                         torch.tensor([0.6, 0.0, 0.8]).view(1, 3, 1, 1))
        >>> [round(x, 3) for x in n.flatten().tolist()]
        [0.6, 0.0, 0.8]
    """
    cos_s = (normal * view_dir).sum(1, keepdim=True)
    cos_g = (face_normal * view_dir).sum(1, keepdim=True).abs().clamp(max=1.0)
    tangent = normal - cos_s * view_dir
    length = tangent.norm(dim=1, keepdim=True)
    tiny = 1e-6
    w = tangent / length.clamp_min(tiny)
    bent = cos_g * view_dir + (1.0 - cos_g.square()).clamp_min(0.0).sqrt() * w
    oriented = torch.where((face_normal * view_dir).sum(1, keepdim=True) < 0, -face_normal, face_normal)
    bent = torch.where(length > tiny, bent, oriented)
    return torch.where(cos_s < cos_g, bent, normal)


def view_cosine(gbuf: GBuffer) -> Tensor:
    """:math:`(B, 1, H, W)` exit cosine :math:`n \\cdot v` of a camera G-buffer, clamped to [0, 1] (0 off the object).

    The one place every method takes :math:`\\cos\\theta_o` for :func:`~torchsss.physics.exit_radiance`.
    """
    return (gbuf.normal * gbuf.view_dir).sum(1, keepdim=True).clamp(0.0, 1.0)


class LightView(NamedTuple):
    """The first surface seen from a light; every tensor :math:`(1, C, H, W)`, zeros where nothing is seen.

    Attributes:
        position: :math:`(1, 3, H, W)` mm.
        normal: :math:`(1, 3, H, W)` unit shading normals.
        irradiance: :math:`(1, 3, H, W)` transmitted irradiance :math:`E = E_\\perp \\cos\\theta F_t`.
        area: :math:`(1, 1, H, W)` surface area dA in mm^2 the pixel covers (clamped at grazing angles).
        flux: :math:`(1, 3, H, W)` :math:`E\\,dA`, exact at every angle.
        mask: :math:`(1, 1, H, W)` bool, pixel sees the object (and receives light).
        face_id: :math:`(1, 1, H, W)` int64, -1 where nothing is seen.
        camera: the light camera (:func:`~torchsss.geometry.shadow.light_camera`).
        bary: :math:`(1, 3, H, W)` the raster's barycentric weights of ``face_id``'s vertices (zeros where
            nothing is seen); with ``face_id`` they attach a pixel's sample to the surface
            (:mod:`torchsss.geometry.coherence`).
    """

    position: Tensor
    normal: Tensor
    irradiance: Tensor
    area: Tensor
    flux: Tensor
    mask: Tensor
    face_id: Tensor
    camera: Camera
    bary: Tensor


def light_view(
    mesh: Mesh,
    light: Light,
    resolution: int = 256,
    eta: Tensor | float = 1.3,
    *,
    fresnel: str = "exact",
    min_cos: float = 1e-2,
) -> LightView:
    """Light-view G-buffer of ``mesh`` seen from ``light`` (the sources of image-space methods).

    Every pixel that sees the object is lit by construction (it is the first surface along the light's ray),
    so no shadow test is needed here.

    Args:
        mesh: the object (mm).
        light: a point, spot or directional light.
        resolution: light-view width and height in pixels.
        eta: relative index of refraction for the Fresnel transmittance: a number, a :math:`()` or :math:`(1,)`
            tensor or a per-channel :math:`(3,)` tensor; gradients flow to a tensor ``eta`` (through ``irradiance``
            and ``flux``).
        fresnel: ``"exact"``, ``"schlick"`` or ``"none"``.
        min_cos: lower bound of :math:`\\cos\\theta` in :math:`dA` (0 < min_cos <= 1); ``flux`` is not clamped.

    Examples:
        >>> from torchsss.geometry.lights import DirectionalLight
        >>> from torchsss.geometry.procedural import plane
        >>> lv = light_view(plane(10.0, 10.0, 2), DirectionalLight((0, 0, -1), 1.0), 64, fresnel="none")
        >>> abs((lv.area * lv.mask).sum().item() - 100.0) < 2.0  # the plane's 100 mm^2, up to pixel coverage
        True
    """
    if not 0.0 < min_cos <= 1.0:
        raise ValueError(f"min_cos: expected a value in (0, 1], got {min_cos!r}")
    check_fresnel(fresnel)
    centre, radius = bounding_sphere(mesh)
    cam = light_camera(light, centre, radius, resolution)
    dtype, device = mesh.vertices.dtype, mesh.vertices.device
    layer = layer_gbuffer(mesh, cam.view_proj(dtype=dtype, device=device), resolution, fill=0.0)
    position, normal, mask = layer.position, layer.normal, layer.mask
    pts = position.flatten(2).transpose(1, 2)
    to_light, dist, e_perp = incident_light(light, pts)
    cos = (normal.flatten(2).transpose(1, 2) * to_light).sum(-1)
    lit = (cos > 0) & mask.flatten(1)
    cos_c = cos.clamp_min(0.0)
    ft = transmittance(cos_c.unsqueeze(-1), _channel_eta(eta, cos_c), fresnel)  # (1, HW, 1) or per channel (1, HW, 3)
    if cam.projection == "orthographic":
        s = 2.0 * cam.ortho_half_height / resolution
        footprint = torch.full_like(cos, s * s)
    else:
        s = 2.0 * math.tan(math.radians(cam.fov_deg) / 2.0) / resolution
        view = cam.view_matrix(dtype=dtype, device=device)
        v = transform_points(pts, view)[..., :3]
        cos_alpha = (-v[..., 2]) / v.norm(dim=-1).clamp_min(1e-12)
        footprint = s * s * cos_alpha**3 * torch.where(lit, dist, torch.zeros_like(dist)) ** 2
    area = torch.where(mask.flatten(1), footprint / cos_c.clamp_min(min_cos), torch.zeros_like(footprint))
    flux = e_perp * (footprint.unsqueeze(-1) * ft * lit.unsqueeze(-1))
    irradiance = e_perp * (cos_c.unsqueeze(-1) * ft * lit.unsqueeze(-1))
    h = w = resolution

    def _img(x: Tensor) -> Tensor:
        return x.transpose(1, 2).reshape(x.shape[0], -1, h, w)

    return LightView(position, normal, _img(irradiance), _img(area.unsqueeze(-1)), _img(flux), mask,
                     layer.face_id, cam, layer.bary)
