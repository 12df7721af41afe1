"""torchsss: subsurface scattering and caustics as batched, differentiable PyTorch ops and modules.

Lengths are in millimetres and coefficients per millimetre throughout.
"""

from torchsss import ops, physics
from torchsss.modules import BurleyMaterial, DipoleMaterial, DipoleProfile
from torchsss.ops import reference_radiosity
from torchsss.physics import (
    burley_rd,
    dipole_rd,
    fresnel_reflectance,
    fresnel_transmittance,
    preset_names,
    schlick_reflectance,
    total_diffuse_reflectance,
)

__version__ = "0.1.0"

__all__ = [
    "BurleyMaterial",
    "DipoleMaterial",
    "DipoleProfile",
    "__version__",
    "burley_rd",
    "dipole_rd",
    "fresnel_reflectance",
    "fresnel_transmittance",
    "ops",
    "physics",
    "preset_names",
    "reference_radiosity",
    "schlick_reflectance",
    "total_diffuse_reflectance",
]
