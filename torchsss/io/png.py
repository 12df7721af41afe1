"""Tone-mapped 8-bit PNG output with the standard library only (zlib), for previews next to the EXR."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import torch
from torch import Tensor

__all__ = ["auto_exposure", "key_exposure", "tonemap", "write_png"]


def auto_exposure(image: Tensor, subject: Tensor | None = None, percentile: float = 0.99) -> float:
    """The exposure multiplier that puts the ``percentile`` of the subject's luminance at 1 (display white).

    Args:
        image: :math:`(C, H, W)` linear values.
        subject: optional :math:`(H, W)` or :math:`(1, H, W)` bool mask of the pixels that matter (e.g. the
            render's object mask): a bright floor or a caustic outside it neither darkens nor brightens the subject.
            Default: every pixel with non-zero luminance.
        percentile: in (0, 1].

    Returns:
        The multiplier (1.0 for an all-black subject).

    Examples:
        >>> img = torch.ones(3, 2, 2)
        >>> img[:, 0, 0] = 100.0                                   # a highlight outside the subject
        >>> auto_exposure(img, torch.tensor([[False, True], [True, True]]))
        1.0
    """
    if not 0.0 < percentile <= 1.0:
        raise ValueError(f"percentile: expected a number in (0, 1], got {percentile!r}")
    lum = image.detach().to(torch.float32).clamp_min(0.0).mean(0)
    if subject is not None:
        mask = subject.reshape(lum.shape).bool()
        lum = lum[mask]
    lum = lum.flatten()
    lum = lum[lum > 0]
    if not lum.numel():
        return 1.0
    return 1.0 / float(torch.quantile(lum[:1_000_000], percentile))


def key_exposure(image: Tensor, subject: Tensor | None = None, key: float = 0.5) -> tuple[float, float]:
    """Exposure and white point for a high-dynamic-range subject (a caustic ~100x brighter than its floor).

    :func:`auto_exposure` puts the 99th percentile at display white, which loses either a small bright caustic
    (clipped with the floor) or the floor (black under a large caustic). Here the subject's *median* luminance
    (its typical surface, e.g. the lit floor) goes to ``key`` and the subject's brightest pixel to the white point
    of :func:`tonemap`'s extended curve, so the floor sits in the mid-tones and the caustic rises towards white
    without clipping.

    Args:
        image: :math:`(C, H, W)` linear values.
        subject: optional :math:`(H, W)` or :math:`(1, H, W)` bool mask (default: every non-zero pixel).
        key: the display level (before the curve) of the median, in (0, 1].

    Returns:
        ``(exposure, white)``: the multiplier and the white point in exposed units (>= 1); ``(1.0, 1.0)`` for an
        all-black subject.

    Examples:
        >>> img = torch.full((3, 4, 4), 0.25)
        >>> img[:, 0, 0] = 25.0                                    # a caustic 100x brighter than the floor
        >>> e, w = key_exposure(img)
        >>> round(e * 0.25, 3), round(w, 1)                        # the floor at 0.5, the caustic at white
        (0.5, 50.0)
    """
    if not 0.0 < key <= 1.0:
        raise ValueError(f"key: expected a number in (0, 1], got {key!r}")
    lum = image.detach().to(torch.float32).clamp_min(0.0).mean(0)
    if subject is not None:
        lum = lum[subject.reshape(lum.shape).bool()]
    lum = lum.flatten()
    lum = lum[lum > 0]
    if not lum.numel():
        return 1.0, 1.0
    exposure = key / float(lum.median())
    return exposure, max(1.0, exposure * float(lum.max()))


def tonemap(image: Tensor, exposure: float | None = None, *, ev: float = 0.0,
            subject: Tensor | None = None, white: float | None = None) -> Tensor:
    """Map linear radiance to display values in [0, 1]: exposure, a soft shoulder, sRGB gamma.

    The documented tone map: :math:`x = E \\cdot 2^{ev} \\cdot L` per channel, then :math:`2x/(1+x)` (Reinhard's
    curve scaled so that :math:`x = 1` is display white; linear with slope 2 near black, values above 1 clip), then
    the sRGB transfer function. With a ``white`` point :math:`W` the curve is Reinhard's extended one,
    :math:`x (1 + x / W^2) / (1 + x)` (slope 1 near black, :math:`x = W` at display white): for high-dynamic-range
    images such as caustics, with :func:`key_exposure`.

    Args:
        image: :math:`(C, H, W)` linear values (>= 0).
        exposure: multiplier :math:`E`; default :func:`auto_exposure` over ``subject`` (the 99th percentile of its
            non-zero luminance at 1).
        ev: exposure compensation in stops (+1 doubles the exposure), applied on top of ``exposure``.
        subject: :math:`(H, W)` bool mask for the automatic exposure (see :func:`auto_exposure`).
        white: optional white point (exposed units, >= 1) of the extended curve; None: the default curve.

    Returns:
        :math:`(C, H, W)` float tensor in [0, 1].
    """
    img = image.detach().to(torch.float32).clamp_min(0.0)
    if exposure is None:
        exposure = auto_exposure(img, subject)
    x = img * (exposure * 2.0 ** float(ev))
    if white is None:
        x = x / (1.0 + x) * 2.0  # Reinhard, rescaled so that the reference level 1 maps to 1
    else:
        if not float(white) >= 1.0:
            raise ValueError(f"white: expected a number >= 1 or None, got {white!r}")
        x = x * (1.0 + x / float(white) ** 2) / (1.0 + x)  # Reinhard's extended curve: W maps to 1
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
