"""Pipelines: Scene -> G-buffers -> method -> image. The reference renderer and the method registry."""

from torchsss.pipelines.reference import (
    RenderResult,
    default_spacing,
    reference_radiosity_at,
    render_reference,
    sample_irradiance,
)
from torchsss.pipelines.render import METHODS, render_scene

__all__ = [
    "METHODS",
    "RenderResult",
    "default_spacing",
    "reference_radiosity_at",
    "render_reference",
    "render_scene",
    "sample_irradiance",
]
