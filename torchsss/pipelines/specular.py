"""Opt-in specular highlights (DESIGN.md §5): the light the dielectric boundary reflects before any enters.

Off by default so that rendered images compare methods on subsurface transport alone. The boundary is a GGX
microfacet surface (Trowbridge-Reitz distribution, Smith-Schlick masking, exact unpolarised Fresnel
reflectance at the half vector):

.. math::

    L_s = \\frac{F_r(\\eta, h\\cdot\\omega_i)\\, D(n\\cdot h)\\, G}{4\\, (n\\cdot\\omega_i)(n\\cdot\\omega_o)}
          \\; E_\\perp\\, (n\\cdot\\omega_i)\\; V

with :math:`E_\\perp` the light's irradiance on a surface facing it (mm^-2 units of the lights) and V the
visibility.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.gbuffer import GBuffer
from torchsss.geometry.lights import Light, incident_light
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.shadow import build_shadow_map, shadow_visibility
from torchsss.physics.fresnel import fresnel_reflectance

__all__ = ["shadow_mapped_specular", "specular_radiance"]


def specular_radiance(gbuffer: GBuffer, lights: Sequence[Light], eta: float, *, roughness: float = 0.3,
                      visibility: Sequence[Tensor | None] | None = None) -> Tensor:
    """GGX specular radiance :math:`(B, 3, H, W)` at the camera G-buffer's pixels (0 on the background).

    Args:
        gbuffer: camera G-buffer (positions, unit normals, unit view directions, mask).
        lights: the lights.
        eta: relative index of refraction of the boundary.
        roughness: GGX alpha in (0, 1] (perceptual roughness squared is a common choice).
        visibility: per light an optional :math:`(B, H \\cdot W)` visibility, None for unshadowed.

    Environment lights (:class:`~torchsss.geometry.environment.EnvironmentLight`) add no specular term here (their
    entries are skipped): the glossy reflection of an environment is outside this library's subsurface scope.

    Examples:
        >>> from torchsss.geometry import Camera, PointLight, camera_gbuffer, sphere
        >>> g = camera_gbuffer(sphere(10.0, 3), Camera(eye=(0, 0, 60), target=(0, 0, 0), width=16, height=16))
        >>> s = specular_radiance(g, [PointLight((0, 0, 60), 1e3)], 1.3)
        >>> bool(s.max() > 0), bool((s[:, :, ~g.mask[0, 0]] == 0).all())
        (True, True)
    """
    if not 0.0 < roughness <= 1.0:
        raise ValueError(f"roughness: expected a value in (0, 1], got {roughness!r}")
    b, _, h, w = gbuffer.position.shape
    pts = gbuffer.position.flatten(2).transpose(1, 2)
    n = gbuffer.normal.flatten(2).transpose(1, 2)
    v = gbuffer.view_dir.flatten(2).transpose(1, 2)
    vis_list = list(visibility) if visibility is not None else [None] * len(lights)
    if len(vis_list) != len(lights):
        raise ValueError(f"visibility: expected one entry per light ({len(lights)}), got {len(vis_list)}")
    a2 = roughness * roughness
    k = roughness / 2.0
    total = torch.zeros(b, h * w, 3, dtype=pts.dtype, device=pts.device)
    n_o = (n * v).sum(-1).clamp_min(0.0)
    for light, vis in zip(lights, vis_list):
        if isinstance(light, EnvironmentLight):
            continue
        to_l, _, e_perp = incident_light(light, pts)
        n_i = (n * to_l).sum(-1).clamp_min(0.0)
        half = torch.nn.functional.normalize(to_l + v, dim=-1, eps=1e-12)
        n_h = (n * half).sum(-1).clamp(0.0, 1.0)
        h_i = (half * to_l).sum(-1).clamp(0.0, 1.0)
        d = a2 / (math.pi * (n_h * n_h * (a2 - 1.0) + 1.0) ** 2)
        g = (n_i / (n_i * (1.0 - k) + k)) * (n_o / (n_o * (1.0 - k) + k))
        lit = (n_i > 0) & (n_o > 0)
        denom = torch.where(lit, 4.0 * n_i * n_o, torch.ones_like(n_i))
        f = fresnel_reflectance(h_i, eta) * d * g / denom * lit
        term = e_perp * (f * n_i).unsqueeze(-1)
        if vis is not None:
            term = term * vis.unsqueeze(-1)
        total = total + term
    return total.transpose(1, 2).reshape(b, 3, h, w) * gbuffer.mask


def shadow_mapped_specular(mesh: Mesh, gbuffer: GBuffer, lights: Sequence[Light], eta: float, *,
                           roughness: float = 0.3, shadow_resolution: int = 1024) -> Tensor:
    """:func:`specular_radiance` at the camera pixels with shadow-mapped visibility (the fast renderers' choice).

    Returns:
        :math:`(1, 3, H, W)` specular radiance.
    """
    lights = [light for light in lights if not isinstance(light, EnvironmentLight)]
    pix = gbuffer.position.flatten(2).transpose(1, 2)
    pix_n = gbuffer.normal.flatten(2).transpose(1, 2)
    vis = [shadow_visibility(build_shadow_map(mesh, light, shadow_resolution), pix, pix_n, light) for light in lights]
    return specular_radiance(gbuffer, lights, eta, roughness=roughness, visibility=vis)
