"""torchsss: subsurface scattering and caustics as batched, differentiable PyTorch ops and modules.

Lengths are in millimetres and coefficients per millimetre throughout.
"""

from torchsss import ops, physics
from torchsss._checks import set_validation, validation, validation_enabled
from torchsss.modules import BurleyMaterial, DipoleMaterial, DipoleProfile, TabulatedMaterial, material_module
from torchsss.ops import reference_radiosity
from torchsss.physics import (
    Material,
    burley_rd,
    dipole_rd,
    exit_radiance,
    fresnel_reflectance,
    fresnel_transmittance,
    preset_names,
    schlick_reflectance,
    total_diffuse_reflectance,
)
from torchsss.pipelines import Renderer, RenderResult, build

__version__ = "0.1.0"

__all__ = [
    "BurleyMaterial",
    "DipoleMaterial",
    "DipoleProfile",
    "Material",
    "RenderResult",
    "Renderer",
    "TabulatedMaterial",
    "__version__",
    "build",
    "burley_rd",
    "dipole_rd",
    "exit_radiance",
    "fresnel_reflectance",
    "fresnel_transmittance",
    "material_module",
    "ops",
    "physics",
    "preset_names",
    "reference_radiosity",
    "schlick_reflectance",
    "set_validation",
    "total_diffuse_reflectance",
    "validation",
    "validation_enabled",
]
