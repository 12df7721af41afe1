"""Tone-mapped 8-bit PNG output with the standard library only (zlib), for previews next to the EXR."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import torch
from torch import Tensor

__all__ = ["tonemap", "write_png"]


def tonemap(image: Tensor, exposure: float | None = None) -> Tensor:
    """Map linear radiance to display values in [0, 1]: exposure, Reinhard :math:`x/(1+x)`, sRGB gamma.

    Args:
        image: :math:`(C, H, W)` linear values (>= 0).
        exposure: multiplier; default puts the 99th percentile of the non-zero luminance at 1.

    Returns:
        :math:`(C, H, W)` float tensor in [0, 1].
    """
    img = image.detach().to(torch.float32).clamp_min(0.0)
    if exposure is None:
        lum = img.mean(0).flatten()
        lum = lum[lum > 0]
        exposure = 1.0 / float(torch.quantile(lum[:1_000_000], 0.99)) if lum.numel() else 1.0
    x = img * exposure
    x = x / (1.0 + x) * 2.0  # Reinhard, rescaled so that the reference level 1 maps to 1
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1 / 2.4) - 0.055)


def write_png(path: str | Path, image: Tensor) -> Path:
    """Write display values in [0, 1] as an 8-bit RGB (or grey) PNG.

    Args:
        path: output file; parent directories are created.
        image: :math:`(C, H, W)` with C in {1, 3}, values in [0, 1] (clamped).

    Returns:
        The path written.
    """
    if not isinstance(image, Tensor):
        raise TypeError(f"image: expected a torch.Tensor, got {type(image).__name__}")
    if image.dim() != 3 or image.shape[0] not in (1, 3):
        raise ValueError(f"image: expected shape (C, H, W) with C in (1, 3), got {tuple(image.shape)}")
    c, h, w = image.shape
    data = (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).contiguous().numpy()
    raw = b"".join(b"\x00" + data[y].tobytes() for y in range(h))

    def chunk(tag: bytes, payload: bytes) -> bytes:
        return struct.pack(">I", len(payload)) + tag + payload + struct.pack(">I", zlib.crc32(tag + payload))

    colour = 2 if c == 3 else 0
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)
    return path
