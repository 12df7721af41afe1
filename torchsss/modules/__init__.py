"""nn.Modules of torchsss: every ``forward()`` takes and returns tensors, so it trains, compiles and exports."""

from torchsss.modules.caustics import CausticMap
from torchsss.modules.chang import HybridTranslucency, ImportanceSampledTranslucency, SurfaceLocal
from torchsss.modules.heterogeneous import HeterogeneousMaps, edge_smoothness
from torchsss.modules.lensch import GlobalResponse, IrradianceAtlas, LenschTranslucency, LocalResponse
from torchsss.modules.material import (
    POSITIVE_FLOOR,
    BurleyMaterial,
    DipoleMaterial,
    TabulatedMaterial,
    check_profile,
    material_module,
)
from torchsss.modules.profile import DipoleProfile
from torchsss.modules.sampling import IcdfSampler
from torchsss.modules.search import NewtonRaphsonSearch
from torchsss.modules.splat import SplatTranslucency

__all__ = [
    "POSITIVE_FLOOR",
    "BurleyMaterial",
    "CausticMap",
    "DipoleMaterial",
    "DipoleProfile",
    "GlobalResponse",
    "HeterogeneousMaps",
    "HybridTranslucency",
    "IcdfSampler",
    "ImportanceSampledTranslucency",
    "IrradianceAtlas",
    "LenschTranslucency",
    "LocalResponse",
    "NewtonRaphsonSearch",
    "SplatTranslucency",
    "SurfaceLocal",
    "TabulatedMaterial",
    "check_profile",
    "edge_smoothness",
    "material_module",
]
