"""Pipelines: Scene -> G-buffers -> method -> image. The reference renderer and the method registry."""

from torchsss.pipelines.reference import (
    RenderResult,
    default_spacing,
    reference_radiosity_at,
    render_reference,
    render_reference_objects,
    sample_irradiance,
)
from torchsss.pipelines.render import METHODS, OBJECT_METHODS, render_scene
from torchsss.pipelines.splat import render_splat, render_splat_objects, splat_grid
from torchsss.pipelines.splat_sequence import render_splat_sequence

__all__ = [
    "METHODS",
    "OBJECT_METHODS",
    "RenderResult",
    "default_spacing",
    "reference_radiosity_at",
    "render_reference",
    "render_reference_objects",
    "render_scene",
    "render_splat",
    "render_splat_objects",
    "render_splat_sequence",
    "sample_irradiance",
    "splat_grid",
]
