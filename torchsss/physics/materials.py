"""The measured materials of Jensen et al. 2001 (Figure 5), shipped with the library.

Coefficients are in mm^-1 per RGB channel; eta = 1.3 for all. The table is ``torchsss/data/
materials_jensen2001.csv``, a copy of the project's shared data file.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cache
from importlib import resources

import torch
from torch import Tensor

__all__ = ["PROFILES", "Material", "MaterialPreset", "preset", "preset_names"]

#: The profile models a :class:`Material` can be rendered with (``torchsss.modules.material_module`` makes the
#: module): the Jensen 2001 dipole, Burley's normalized diffusion fitted to the same total reflectance, and the
#: dipole through a lookup table (the speed path).
PROFILES = ("dipole", "burley", "tabulated")


def _rgb(value: object, name: str, positive: bool) -> tuple[float, ...]:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 3:
        raise ValueError(f"{name}: expected 3 numbers (mm^-1), got {value!r}")
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
        raise TypeError(f"{name}: expected 3 numbers (mm^-1), got {value!r}")
    out = tuple(float(x) for x in value)
    if not all(math.isfinite(x) and (x > 0 if positive else x >= 0) for x in out):
        raise ValueError(f"{name}: expected finite values {'> 0' if positive else '>= 0'}, got {list(value)!r}")
    return out


@dataclass(frozen=True)
class Material:
    """A homogeneous translucent material: the one record of a material's coefficients, eta and profile model.

    Every method renders a material given as this record (or as the nn.Module that
    ``torchsss.modules.material_module`` makes from it, the form that carries gradients).

    Attributes:
        sigma_a: absorption coefficient per RGB channel, mm^-1 (>= 0).
        sigma_s_prime: reduced scattering coefficient per channel, mm^-1 (> 0).
        eta: relative index of refraction (> 0).
        name: a label (the preset's name, or ``"custom"``).
        profile: the profile model, one of :data:`PROFILES` (default ``"dipole"``).

    Examples:
        >>> m = Material.from_json("marble")
        >>> m.name, m.eta, m.profile
        ('marble', 1.3, 'dipole')
        >>> Material.from_json({"sigma_a": [0.1, 0.1, 0.1], "sigma_s_prime": [1, 1, 1]}).sigma_s_prime
        (1.0, 1.0, 1.0)
        >>> Material.from_json({"preset": "skin1", "profile": "burley"}).profile
        'burley'
    """

    sigma_a: tuple[float, ...]
    sigma_s_prime: tuple[float, ...]
    eta: float = 1.3
    name: str = "custom"
    profile: str = "dipole"

    def __post_init__(self) -> None:
        object.__setattr__(self, "sigma_a", _rgb(self.sigma_a, "material.sigma_a", positive=False))
        object.__setattr__(self, "sigma_s_prime", _rgb(self.sigma_s_prime, "material.sigma_s_prime", positive=True))
        eta = self.eta
        if isinstance(eta, bool) or not isinstance(eta, (int, float)) or not (math.isfinite(eta) and eta > 0):
            raise ValueError(f"material.eta: expected a finite number > 0, got {eta!r}")
        object.__setattr__(self, "eta", float(eta))
        if self.profile not in PROFILES:
            raise ValueError(f"material.profile: expected one of {list(PROFILES)}, got {self.profile!r}")

    @classmethod
    def from_preset(cls, name: str, profile: str = "dipole") -> Material:
        """One of the 12 Jensen 2001 measurements (case-insensitive), see :func:`preset`."""
        p = preset(name)
        return p if profile == p.profile else replace(p, profile=profile)

    @classmethod
    def from_json(cls, value: object) -> Material:
        """Parse a scene file's ``"material"``: a preset name, a coefficients object, or a preset with a profile.

        An object holds ``sigma_a``, ``sigma_s_prime`` (3 numbers or one, mm^-1) and optional ``eta``, ``name`` and
        ``profile``; ``{"preset": NAME, "profile": ...}`` picks a preset with another profile model.

        Raises:
            TypeError: not a string or an object.
            ValueError: unknown preset or keys, bad values (the message names the key).
        """
        if isinstance(value, str):
            return cls.from_preset(value)
        if isinstance(value, Material):
            return value
        if not isinstance(value, Mapping):
            raise TypeError(f"material: expected a preset name {preset_names()} or an object, got {value!r}")
        keys = set(value)
        if "preset" in keys:
            if unknown := keys - {"preset", "profile"}:
                raise ValueError(f"material: expected keys preset and optional profile, got extra {sorted(unknown)}")
            return cls.from_preset(value["preset"], value.get("profile", "dipole"))
        unknown = keys - {"sigma_a", "sigma_s_prime", "eta", "name", "profile"}
        if unknown or not {"sigma_a", "sigma_s_prime"} <= keys:
            raise ValueError(
                "material: expected keys sigma_a, sigma_s_prime and optional eta, name, profile (or preset); "
                f"got {sorted(keys)}"
            )
        return cls(value["sigma_a"], value["sigma_s_prime"], value.get("eta", 1.3), str(value.get("name", "custom")),
                   value.get("profile", "dipole"))

    def to_json(self) -> dict:
        """The record as a JSON object (the inverse of :meth:`from_json`)."""
        return {"name": self.name, "sigma_a": list(self.sigma_a), "sigma_s_prime": list(self.sigma_s_prime),
                "eta": self.eta, "profile": self.profile}

    def with_profile(self, profile: str) -> Material:
        """The same coefficients rendered with another profile model (one of :data:`PROFILES`)."""
        return replace(self, profile=profile)

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


#: The former name of :class:`Material` (the presets are Material records).
MaterialPreset = Material


@cache
def _table() -> dict[str, Material]:
    text = resources.files("torchsss").joinpath("data/materials_jensen2001.csv").read_text(encoding="utf-8")
    rows = [line for line in text.splitlines() if line and not line.startswith("#")]
    table = {}
    for row in csv.DictReader(io.StringIO("\n".join(rows))):
        name = row["name"].strip().lower()
        table[name] = Material(
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


def preset(name: str) -> Material:
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
