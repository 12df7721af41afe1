"""Image input/output: linear EXR and tone-mapped PNG previews."""

from torchsss.io.exr import read_exr, write_exr
from torchsss.io.png import auto_exposure, key_exposure, tonemap, write_png

__all__ = ["auto_exposure", "key_exposure", "read_exr", "tonemap", "write_exr", "write_png"]
