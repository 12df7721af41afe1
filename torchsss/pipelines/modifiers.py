"""Per-vertex heterogeneous modifiers (Shah eq. 7.4) shared by the renderers that take them (splat, reference).

A renderer built with ``distance_scale`` :math:`M_d > 0` and/or ``irradiance_scale`` :math:`M_i \\ge 0`, each
:math:`(V,)` or :math:`(V, C)` per mesh vertex, interpolates them at every source point (face id and barycentrics)
and modifies that source's profile to :math:`M_i\\,R_d(r\\,M_d)`. The maps may require grad (a learned texture,
:class:`~torchsss.modules.HeterogeneousMaps`): they are validated once here and read every frame.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsss._checks import check_finite
from torchsss.geometry.mesh import Mesh

__all__ = ["at_sources", "vertex_modifiers"]


def _one(value: Tensor | None, name: str, mesh: Mesh, dtype: torch.dtype) -> Tensor | None:
    """Validate one per-vertex modifier: :math:`(V,)` or :math:`(V, C)` -> :math:`(V, 1 \\text{ or } C)`."""
    if value is None:
        return None
    if not isinstance(value, Tensor) or not value.is_floating_point():
        raise TypeError(f"{name}: expected a floating tensor of shape (V,) or (V, 3), got {type(value).__name__}")
    v = mesh.vertices.shape[0]
    if value.dim() not in (1, 2) or value.shape[0] != v or (value.dim() == 2 and value.shape[1] not in (1, 3)):
        raise ValueError(f"{name}: expected shape ({v},) or ({v}, 3) (one value per vertex), got "
                         f"{tuple(value.shape)}")
    check_finite(value, name)
    return value.to(device=mesh.vertices.device, dtype=dtype).reshape(v, -1)


def vertex_modifiers(distance_scale: Tensor | None, irradiance_scale: Tensor | None, mesh: Mesh,
                     dtype: torch.dtype) -> tuple[Tensor | None, Tensor | None]:
    """Validate :math:`M_d` and :math:`M_i` of a mesh; returns them as :math:`(V, 1 \\text{ or } 3)` (or None).

    Raises:
        TypeError: a modifier that is not a floating tensor.
        ValueError: a shape other than :math:`(V,)`, :math:`(V, 1)`, :math:`(V, 3)`; a non-finite value;
            :math:`M_d \\le 0` or :math:`M_i < 0`.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> m = sphere(5.0, 1)
        >>> md, mi = vertex_modifiers(torch.full((42,), 2.0), None, m, torch.float32)
        >>> tuple(md.shape), mi
        ((42, 1), None)
    """
    md = _one(distance_scale, "distance_scale", mesh, dtype)
    mi = _one(irradiance_scale, "irradiance_scale", mesh, dtype)
    if md is not None and not bool((md > 0).all()):
        raise ValueError(f"distance_scale: expected values > 0, got min {float(md.min())}")
    if mi is not None and not bool((mi >= 0).all()):
        raise ValueError(f"irradiance_scale: expected values >= 0, got min {float(mi.min())}")
    return md, mi


def at_sources(attr: Tensor | None, mesh: Mesh, face_id: Tensor, bary: Tensor) -> Tensor | None:
    """A per-vertex attribute :math:`(V, K)` at sources: :math:`(1, S, K)` (None for None).

    The sources are given by face ids :math:`(S,)` and barycentrics :math:`(S, 3)`.
    """
    if attr is None:
        return None
    corners = attr[mesh.faces[face_id]]  # (S, 3, K)
    return (corners * bary.unsqueeze(-1).to(attr.dtype)).sum(1).unsqueeze(0)
