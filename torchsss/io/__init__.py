"""Image input/output: linear EXR and tone-mapped PNG previews."""

from torchsss.io.exr import read_exr, write_exr
from torchsss.io.png import tonemap, write_png

__all__ = ["read_exr", "tonemap", "write_exr", "write_png"]
