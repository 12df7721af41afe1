"""OpenEXR input/output for linear radiance images (float32, channel-first tensors)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import torch
from torch import Tensor

__all__ = ["read_exr", "write_exr"]

_NAMES = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


def write_exr(path: str | Path, image: Tensor) -> Path:
    """Write a linear image as a float32 OpenEXR file (ZIP compression).

    Args:
        path: output file; parent directories are created.
        image: :math:`(C, H, W)` or :math:`(1, C, H, W)` tensor with C in {1, 3, 4} (Y, RGB, RGBA). Row 0 is the
            top of the image.

    Returns:
        The path written.

    Examples:
        >>> import tempfile, os
        >>> p = write_exr(os.path.join(tempfile.mkdtemp(), "x.exr"), torch.ones(3, 2, 4))
        >>> read_exr(p).shape
        torch.Size([3, 2, 4])
    """
    if not isinstance(image, Tensor):
        raise TypeError(f"image: expected a torch.Tensor, got {type(image).__name__}")
    if image.dim() == 4 and image.shape[0] == 1:
        image = image[0]
    if image.dim() != 3 or image.shape[0] not in _NAMES:
        raise ValueError(f"image: expected shape (C, H, W) or (1, C, H, W) with C in (1, 3, 4), "
                         f"got {tuple(image.shape)}")
    arr = image.detach().to(torch.float32).cpu().numpy()
    channels = {name: np.ascontiguousarray(arr[i]) for i, name in enumerate(_NAMES[image.shape[0]])}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))
    return path


def read_exr(path: str | Path) -> Tensor:
    """Read an OpenEXR file written by :func:`write_exr` (or any Y/RGB/RGBA scanline file) as :math:`(C, H, W)`.

    Raises:
        FileNotFoundError: ``path`` does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no such file {str(path)!r}")
    with OpenEXR.File(str(path), separate_channels=True) as f:
        chans = f.channels()
        for names in (("R", "G", "B", "A"), ("R", "G", "B"), ("Y",)):
            if all(n in chans for n in names):
                return torch.from_numpy(np.stack([np.asarray(chans[n].pixels, dtype=np.float32) for n in names]))
    raise ValueError(f"path: expected Y, RGB or RGBA channels in {str(path)!r}, got {sorted(chans)}")
