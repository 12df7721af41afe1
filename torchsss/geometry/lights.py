"""Point, directional and spot lights, and the transmitted irradiance they deliver to a surface.

All positions are in millimetres. A point or spot light has a per-channel radiant ``intensity`` I (power per
steradian); at distance d (mm) it gives the irradiance :math:`I \\cos\\theta / d^2` on a surface whose normal
makes the angle :math:`\\theta` with the direction to the light. A directional light has a per-channel
``irradiance`` E_0 on a surface facing it, so :math:`E = E_0 \\cos\\theta`. The irradiance that enters a
translucent material is multiplied by the Fresnel transmittance :math:`F_t(\\eta, \\cos\\theta)` (exact
unpolarised by default, Schlick optional) and by the light's visibility (1 lit, 0 shadowed).

Lights are small frozen dataclasses of Python floats (they come from scene files); an intensity (or a directional
irradiance) may also be a tensor, the differentiable route to fitting a light. The functions take tensors and follow
their dtype and device. Point sets are :math:`(B, N, 3)`, channels last.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsss._checks import check_shape, check_tensor
from torchsss.geometry.environment import EnvironmentLight, environment_irradiance
from torchsss.physics.fresnel import check_fresnel, transmittance

__all__ = [
    "DirectionalLight",
    "Light",
    "PointLight",
    "SpotLight",
    "incident_light",
    "light_from_dict",
    "surface_irradiance",
]


def _vec3(value: object, name: str) -> tuple[float, float, float]:
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 3:
        raise ValueError(f"{name}: expected 3 numbers, got {value!r}")
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name}: expected 3 numbers, got {value!r}") from err
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name}: expected finite numbers, got {value!r}")
    return out  # type: ignore[return-value]


def _rgb(value: object, name: str) -> tuple[float, float, float] | Tensor:
    if isinstance(value, Tensor):
        return _rgb_tensor(value, name)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = (value, value, value)
    out = _vec3(value, name)
    if min(out) < 0:
        raise ValueError(f"{name}: expected values >= 0, got {value!r}")
    return out


def _rgb_tensor(value: Tensor, name: str) -> Tensor:
    """A tensor intensity (the differentiable route): :math:`()`, :math:`(1,)` or :math:`(3,)` -> :math:`(3,)`.

    The tensor stays in the autograd graph (a leaf with ``requires_grad`` receives the gradient of a render's loss).
    """
    if not value.is_floating_point():
        raise TypeError(f"{name}: expected a floating tensor, got dtype {value.dtype}")
    if value.dim() > 1 or (value.dim() == 1 and value.shape[0] not in (1, 3)):
        raise ValueError(f"{name}: expected a tensor of shape (), (1,) or (3,), got {tuple(value.shape)}")
    v = value.detach()
    if not bool(torch.isfinite(v).all()) or bool((v < 0).any()):
        raise ValueError(f"{name}: expected finite values >= 0, got {v.tolist()}")
    return value.reshape(-1).expand(3)


def _rgb_value(value: tuple[float, float, float] | Tensor, like: Tensor) -> Tensor:
    """A light's intensity or irradiance as a :math:`(3,)` tensor in ``like``'s dtype and device.

    A tensor keeps its autograd graph.
    """
    if isinstance(value, Tensor):
        return value.to(dtype=like.dtype, device=like.device)
    return torch.tensor(value, dtype=like.dtype, device=like.device)


def _unit(value: object, name: str) -> tuple[float, float, float]:
    v = _vec3(value, name)
    n = math.sqrt(sum(c * c for c in v))
    if n == 0:
        raise ValueError(f"{name}: expected a non-zero direction, got {value!r}")
    return (v[0] / n, v[1] / n, v[2] / n)


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light.

    Args:
        position: (x, y, z) in mm.
        intensity: per-channel radiant intensity (a number is used for all three channels), or a floating tensor of
            shape :math:`()`, :math:`(1,)` or :math:`(3,)`: the differentiable route (a tensor with
            ``requires_grad`` receives the gradient of a render's loss through every method's irradiance; a light
            holding a tensor cannot be compared with ``==``).

    Examples:
        >>> PointLight(position=(0, 0, 100), intensity=(1e4, 1e4, 1e4)).kind
        'point'
    """

    position: tuple[float, float, float]
    intensity: tuple[float, float, float]
    kind = "point"

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3(self.position, "position"))
        object.__setattr__(self, "intensity", _rgb(self.intensity, "intensity"))


@dataclass(frozen=True)
class DirectionalLight:
    """A light at infinity.

    Args:
        direction: the direction the light travels (from the light towards the scene); normalised.
        irradiance: per-channel irradiance on a surface facing the light (numbers, or a tensor as a point light's
            ``intensity``: the differentiable route).
    """

    direction: tuple[float, float, float]
    irradiance: tuple[float, float, float]
    kind = "directional"

    def __post_init__(self) -> None:
        object.__setattr__(self, "direction", _unit(self.direction, "direction"))
        object.__setattr__(self, "irradiance", _rgb(self.irradiance, "irradiance"))


@dataclass(frozen=True)
class SpotLight:
    """A point light restricted to a cone, with a smooth edge.

    The intensity is full inside ``inner_deg`` of the axis, falls off as a smoothstep of the angle between
    ``inner_deg`` and ``cone_deg`` and is zero beyond ``cone_deg`` (both are half-angles).

    Args:
        position: (x, y, z) in mm.
        direction: cone axis, pointing away from the light; normalised.
        intensity: per-channel radiant intensity on the axis (numbers, or a tensor as :class:`PointLight`'s).
        cone_deg: outer half-angle in degrees, in (0, 90].
        inner_deg: inner half-angle in degrees, in [0, cone_deg]; defaults to 0.8 * cone_deg.
    """

    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    intensity: tuple[float, float, float]
    cone_deg: float = 30.0
    inner_deg: float | None = None
    kind = "spot"

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3(self.position, "position"))
        object.__setattr__(self, "direction", _unit(self.direction, "direction"))
        object.__setattr__(self, "intensity", _rgb(self.intensity, "intensity"))
        cone = float(self.cone_deg)
        if not 0.0 < cone <= 90.0:
            raise ValueError(f"cone_deg: expected a half-angle in (0, 90] degrees, got {self.cone_deg!r}")
        inner = 0.8 * cone if self.inner_deg is None else float(self.inner_deg)
        if not 0.0 <= inner <= cone:
            raise ValueError(f"inner_deg: expected a value in [0, cone_deg={cone}], got {self.inner_deg!r}")
        object.__setattr__(self, "cone_deg", cone)
        object.__setattr__(self, "inner_deg", inner)


Light = PointLight | DirectionalLight | SpotLight | EnvironmentLight

_LIGHT_KEYS = {
    "point": ({"position", "intensity"}, set()),
    "directional": ({"direction", "irradiance"}, set()),
    "spot": ({"position", "direction", "intensity"}, {"cone_deg", "inner_deg"}),
}


def light_from_dict(d: Mapping) -> Light:
    """Build a light from its scene-JSON block (DESIGN.md §5).

    Examples:
        >>> light_from_dict({"type": "directional", "direction": [0, 0, -2], "irradiance": 1.0}).direction
        (0.0, 0.0, -1.0)
    """
    if not isinstance(d, Mapping):
        raise TypeError(f"light: expected a JSON object, got {type(d).__name__}")
    kind = d.get("type")
    if kind == "environment":
        return EnvironmentLight.from_dict(d)
    if kind not in _LIGHT_KEYS:
        raise ValueError(f"light type: expected one of {[*sorted(_LIGHT_KEYS), 'environment']}, got {kind!r}")
    required, optional = _LIGHT_KEYS[kind]
    keys = set(d) - {"type"}
    if missing := required - keys:
        raise ValueError(f"{kind} light: missing keys {sorted(missing)}")
    if unknown := keys - required - optional:
        raise ValueError(f"{kind} light: unknown keys {sorted(unknown)}; allowed {sorted(required | optional)}")
    cls = {"point": PointLight, "directional": DirectionalLight, "spot": SpotLight}[kind]
    return cls(**{k: d[k] for k in keys})


def _smoothstep(edge0: float, edge1: float, x: Tensor) -> Tensor:
    if edge1 <= edge0:
        return (x >= edge1).to(x.dtype)
    t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _channel_eta(eta: Tensor | float, like: Tensor) -> Tensor | float:
    """``eta`` ready to broadcast against channels-last :math:`(..., 1)` cosines (a number stays a number).

    A :math:`()` or :math:`(1,)` tensor applies to every channel, a :math:`(3,)` tensor is per channel; a tensor is
    moved to ``like``'s device (differentiably: the autograd graph to ``eta`` is kept).
    """
    if not isinstance(eta, Tensor):
        return eta
    if eta.dim() > 1 or (eta.dim() == 1 and eta.shape[0] not in (1, 3)):
        raise ValueError(f"eta: expected a number, a 0-dim tensor or shape (1,) or (3,), got {tuple(eta.shape)}")
    return eta.to(device=like.device)


def incident_light(light: Light, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Direction to the light, distance and the normal-incidence irradiance at every point.

    Args:
        light: a :class:`PointLight`, :class:`DirectionalLight` or :class:`SpotLight`.
        points: :math:`(B, N, 3)` positions in mm.

    Returns:
        ``(to_light, distance, e_normal)``: :math:`(B, N, 3)` unit vectors towards the light, :math:`(B, N)`
        distances in mm (``inf`` for a directional light) and :math:`(B, N, 3)` irradiance on a surface facing
        the light (:math:`I/d^2` times the spot falloff, or the directional irradiance). A point exactly at
        the light's position gets direction 0 and irradiance 0 (never NaN).

    Examples:
        >>> _, d, e = incident_light(PointLight((0, 0, 10), 100.0), torch.zeros(1, 1, 3))
        >>> d.item(), e[0, 0].tolist()
        (10.0, [1.0, 1.0, 1.0])
    """
    check_tensor(points, "points")
    check_shape(points, "points", "B,N,3")
    dtype, device = points.dtype, points.device
    if isinstance(light, DirectionalLight):
        to_light = -torch.tensor(light.direction, dtype=dtype, device=device).expand_as(points)
        dist = torch.full(points.shape[:-1], math.inf, dtype=dtype, device=device)
        e = _rgb_value(light.irradiance, points).expand(*points.shape[:-1], 3)
        return to_light, dist, e
    if not isinstance(light, (PointLight, SpotLight)):
        raise TypeError(f"light: expected PointLight, DirectionalLight or SpotLight, got {type(light).__name__}")
    delta = torch.tensor(light.position, dtype=dtype, device=device) - points
    d2 = (delta * delta).sum(-1)
    pos = d2 > 0
    safe = torch.where(pos, d2, torch.ones_like(d2))
    dist = torch.sqrt(safe) * pos
    to_light = delta / torch.sqrt(safe).unsqueeze(-1) * pos.unsqueeze(-1)
    falloff = pos.to(dtype) / safe
    if isinstance(light, SpotLight):
        axis = torch.tensor(light.direction, dtype=dtype, device=device)
        cos_axis = -(to_light * axis).sum(-1)
        falloff = falloff * _smoothstep(
            math.cos(math.radians(light.cone_deg)), math.cos(math.radians(light.inner_deg)), cos_axis
        )
    e = _rgb_value(light.intensity, points) * falloff.unsqueeze(-1)
    return to_light, dist, e


def surface_irradiance(
    points: Tensor,
    normals: Tensor,
    lights: Light | Sequence[Light],
    eta: Tensor | float = 1.3,
    *,
    visibility: Tensor | Sequence[Tensor | None] | None = None,
    fresnel: str = "exact",
) -> Tensor:
    """Irradiance transmitted into the material, :math:`E = \\sum_l E_l \\max(0, n\\cdot\\omega_l) F_t V_l`.

    Args:
        points: :math:`(B, N, 3)` positions in mm.
        normals: :math:`(B, N, 3)` unit outward normals.
        lights: one light or a sequence of lights (their contributions add up).
        eta: relative index of refraction of the material: a number, a :math:`()` or :math:`(1,)` tensor, or a
            per-channel :math:`(3,)` tensor; gradients flow to a tensor ``eta``.
        visibility: per light a :math:`(B, N)` tensor in [0, 1] (1 = lit) or None (unshadowed); a single
            tensor is accepted when there is one light. An :class:`~torchsss.geometry.environment.EnvironmentLight`
            is always unshadowed (its entry must be None), see
            :func:`~torchsss.geometry.environment.environment_irradiance`.
        fresnel: ``"exact"`` (unpolarised dielectric, the default), ``"schlick"`` or ``"none"``.

    Returns:
        :math:`(B, N, 3)` transmitted irradiance (same units as the lights' intensity per mm^2).

    Examples:
        >>> pts, nrm = torch.zeros(1, 1, 3), torch.tensor([[[0.0, 0.0, 1.0]]])
        >>> e = surface_irradiance(pts, nrm, PointLight((0, 0, 10), 100.0), fresnel="none")
        >>> e[0, 0].tolist()
        [1.0, 1.0, 1.0]
    """
    check_tensor(normals, "normals")
    dims = check_shape(points, "points", "B,N,3")
    check_shape(normals, "normals", "B,N,3", **dims)
    check_fresnel(fresnel)
    eta_c = _channel_eta(eta, points)
    single = (PointLight, DirectionalLight, SpotLight, EnvironmentLight)
    light_list = [lights] if isinstance(lights, single) else list(lights)
    if isinstance(visibility, Tensor) or visibility is None:
        vis_list = [visibility] * len(light_list) if visibility is None else [visibility]
    else:
        vis_list = list(visibility)
    if len(vis_list) != len(light_list):
        raise ValueError(f"visibility: expected one entry per light ({len(light_list)}), got {len(vis_list)}")
    total = torch.zeros(*points.shape[:-1], 3, dtype=points.dtype, device=points.device)
    for light, vis in zip(light_list, vis_list):
        if isinstance(light, EnvironmentLight):
            if vis is not None:
                raise ValueError("visibility: expected None for an environment light (it is unshadowed), got a tensor")
            total = total + environment_irradiance(light, normals, eta, fresnel=fresnel)
            continue
        to_light, _, e = incident_light(light, points)
        cos = (normals * to_light).sum(-1, keepdim=True).clamp_min(0.0)
        term = e * (cos * transmittance(cos, eta_c, fresnel))
        if vis is not None:
            check_tensor(vis, "visibility")
            check_shape(vis, "visibility", "B,N", **dims)
            term = term * vis.unsqueeze(-1)
        total = total + term
    return total
