"""``build(method, mesh, material, **knobs)``: the one entry point to every method's renderer (build once).

Examples:
    >>> from torchsss.geometry import Camera, DirectionalLight, sphere
    >>> r = build("splat", sphere(10.0, 2), "skin1", grid=16)
    >>> res = r.render(DirectionalLight((0, 0, -1), 1.0), Camera(eye=(0, 0, 60), target=(0, 0, 0), width=8,
    ...                height=8))
    >>> sorted(k for k in res.stats if k in ("setup_s", "frame_s", "knobs", "method"))
    ['frame_s', 'knobs', 'method', 'setup_s']
"""

from __future__ import annotations

from torch import nn

from torchsss.geometry.mesh import Mesh
from torchsss.physics.materials import Material
from torchsss.pipelines.caustics_renderer import CausticsRenderer
from torchsss.pipelines.chang import HybridRenderer, IcdfRenderer
from torchsss.pipelines.lensch import LenschRenderer
from torchsss.pipelines.reference import ReferenceRenderer
from torchsss.pipelines.renderer import Renderer
from torchsss.pipelines.splat import SplatRenderer

__all__ = ["RENDERERS", "build"]

#: Every method's renderer class, by name.
RENDERERS: dict[str, type[Renderer]] = {
    cls.method: cls
    for cls in (ReferenceRenderer, LenschRenderer, IcdfRenderer, HybridRenderer, SplatRenderer, CausticsRenderer)
}


def build(method: str, mesh: Mesh, material: Material | str | nn.Module | None, **knobs) -> Renderer:
    """Build ``method``'s renderer for ``mesh`` in ``material`` (all setup happens here); then ``.render(...)``.

    Args:
        method: one of :data:`RENDERERS` (``"reference"``, ``"lensch"``, ``"icdf"``, ``"hybrid"``, ``"splat"``,
            ``"caustics"``).
        mesh: the object (mm).
        material: a :class:`~torchsss.physics.Material` record, a preset name or a profile module (None for
            ``"caustics"``, whose glass is described by its knobs).
        **knobs: the method's knobs (its class's ``defaults``), and ``dtype``, ``differentiable``, ``progress``.

    Raises:
        ValueError: an unknown method or knob (the message lists the valid ones).
    """
    if method not in RENDERERS:
        raise ValueError(f"method: expected one of {sorted(RENDERERS)}, got {method!r}")
    return RENDERERS[method](mesh, material, **knobs)
