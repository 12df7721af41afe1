"""nn.Modules of torchsss: every ``forward()`` takes and returns tensors, so it trains, compiles and exports."""

from torchsss.modules.caustics import CausticMap
from torchsss.modules.chang import HybridTranslucency, ImportanceSampledTranslucency
from torchsss.modules.lensch import GlobalResponse, IrradianceAtlas, LenschTranslucency, LocalResponse
from torchsss.modules.material import POSITIVE_FLOOR, BurleyMaterial, DipoleMaterial, TabulatedMaterial
from torchsss.modules.profile import DipoleProfile
from torchsss.modules.splat import SplatTranslucency

__all__ = [
    "POSITIVE_FLOOR",
    "BurleyMaterial",
    "CausticMap",
    "DipoleMaterial",
    "DipoleProfile",
    "GlobalResponse",
    "HybridTranslucency",
    "ImportanceSampledTranslucency",
    "IrradianceAtlas",
    "LenschTranslucency",
    "LocalResponse",
    "SplatTranslucency",
    "TabulatedMaterial",
]
