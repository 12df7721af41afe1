"""The measured materials of Jensen et al. 2001 (Figure 5), shipped with the library.

Coefficients are in mm^-1 per RGB channel; eta = 1.3 for all. The table is ``torchsss/data/
materials_jensen2001.csv``, a copy of the project's shared data file.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from functools import cache
from importlib import resources

import torch
from torch import Tensor

__all__ = ["MaterialPreset", "preset", "preset_names"]


@dataclass(frozen=True)
class MaterialPreset:
    """One measured material: name, per-channel coefficients (mm^-1) and relative index of refraction."""

    name: str
    sigma_a: tuple[float, float, float]
    sigma_s_prime: tuple[float, float, float]
    eta: float

    def tensors(
        self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``(sigma_a, sigma_s_prime, eta)`` as tensors of shape ``(3,)``, ``(3,)``, ``()`` (mm^-1).

        Examples:
            >>> sa, ss, eta = preset("marble").tensors()
            >>> sa.dtype, tuple(ss.shape), eta.item()
            (torch.float64, (3,), 1.3)
        """
        return (torch.tensor(self.sigma_a, dtype=dtype, device=device),
                torch.tensor(self.sigma_s_prime, dtype=dtype, device=device),
                torch.tensor(self.eta, dtype=dtype, device=device))


@cache
def _table() -> dict[str, MaterialPreset]:
    text = resources.files("torchsss").joinpath("data/materials_jensen2001.csv").read_text(encoding="utf-8")
    rows = [line for line in text.splitlines() if line and not line.startswith("#")]
    table = {}
    for row in csv.DictReader(io.StringIO("\n".join(rows))):
        name = row["name"].strip().lower()
        table[name] = MaterialPreset(
            name=name,
            sigma_a=tuple(float(row[f"sigma_a_{c}"]) for c in "rgb"),
            sigma_s_prime=tuple(float(row[f"sigma_s_prime_{c}"]) for c in "rgb"),
            eta=float(row["eta"]),
        )
    return table


def preset_names() -> list[str]:
    """Names of the 12 Jensen 2001 presets, in table order.

    Examples:
        >>> preset_names()[:3]
        ['apple', 'chicken1', 'chicken2']
    """
    return list(_table())


def preset(name: str) -> MaterialPreset:
    """Look up a preset by name (case-insensitive).

    Raises:
        TypeError: ``name`` is not a string.
        ValueError: unknown name; the message lists the valid ones.

    Examples:
        >>> preset("Marble").sigma_s_prime
        (2.19, 2.62, 3.0)
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a str, got {type(name).__name__}")
    key = name.strip().lower()
    table = _table()
    if key not in table:
        raise ValueError(f"name: unknown material {name!r}; expected one of {', '.join(table)}")
    return table[key]
