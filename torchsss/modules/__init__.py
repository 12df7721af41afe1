"""nn.Modules of torchsss: every ``forward()`` takes and returns tensors, so it trains, compiles and exports."""

from torchsss.modules.lensch import GlobalResponse, IrradianceAtlas, LenschTranslucency, LocalResponse
from torchsss.modules.material import POSITIVE_FLOOR, BurleyMaterial, DipoleMaterial
from torchsss.modules.profile import DipoleProfile

__all__ = [
    "POSITIVE_FLOOR",
    "BurleyMaterial",
    "DipoleMaterial",
    "DipoleProfile",
    "GlobalResponse",
    "IrradianceAtlas",
    "LenschTranslucency",
    "LocalResponse",
]
