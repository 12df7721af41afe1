"""Pipelines: mesh, material, lights, camera -> image, one renderer per method (build once, render frames).

``build(method, mesh, material, **knobs)`` makes a :class:`Renderer`; ``renderer.render(lights, camera)`` renders
a frame. Scene files map to them in :mod:`torchsss.registry` (beside :mod:`torchsss.scene` and the CLI).
"""

from torchsss.pipelines.build import RENDERERS, build
from torchsss.pipelines.caustics_renderer import CausticsRenderer
from torchsss.pipelines.chang import HybridRenderer, IcdfRenderer, render_hybrid, render_icdf
from torchsss.pipelines.lensch import LenschRenderer, build_lensch, render_lensch
from torchsss.pipelines.reference import (
    ReferenceRenderer,
    default_spacing,
    reference_radiosity_at,
    render_reference,
    render_reference_objects,
    sample_irradiance,
)
from torchsss.pipelines.renderer import Renderer, RenderResult
from torchsss.pipelines.splat import SplatRenderer, render_splat, render_splat_objects, splat_grid
from torchsss.pipelines.splat_sequence import render_splat_sequence

__all__ = [
    "RENDERERS",
    "CausticsRenderer",
    "HybridRenderer",
    "IcdfRenderer",
    "LenschRenderer",
    "ReferenceRenderer",
    "RenderResult",
    "Renderer",
    "SplatRenderer",
    "build",
    "build_lensch",
    "default_spacing",
    "reference_radiosity_at",
    "render_hybrid",
    "render_icdf",
    "render_lensch",
    "render_reference",
    "render_reference_objects",
    "render_splat",
    "render_splat_objects",
    "render_splat_sequence",
    "sample_irradiance",
    "splat_grid",
]
