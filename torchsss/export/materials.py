"""Materials as graph inputs: one exported file renders any dipole material.

:func:`with_material_inputs` copies a built module and swaps its :class:`~torchsss.DipoleMaterial` (wherever the
module tree holds it: a splat's material table, Lensch's local and global responses, the irradiance atlas's Fresnel
term, Chang's estimators) for an :class:`InputDipoleMaterial`, whose :math:`\\sigma_a`, :math:`\\sigma_s'` and
:math:`\\eta` are set from the last three arguments of every ``forward()``. Everything the module fixed at build
time from the build material stays fixed (Lensch's throughput sparsity pattern, the hybrid's split radius and ring
pattern, a splat window); for the splat, whose truncation radius :math:`r_{max}` depends on the material,
:class:`torchsss.export.adapters.SplatExport` takes :math:`r_{max}` as a fourth material input
(:func:`torchsss.physics.r_max`, computed outside the graph: it is a bisection).
"""

from __future__ import annotations

import copy
import inspect
import keyword

import torch
from torch import Tensor, nn

from torchsss._checks import is_tracing
from torchsss.modules.material import DipoleMaterial

__all__ = ["InputDipoleMaterial", "MaterialInputs", "find_dipole_material", "swap_material", "with_material_inputs"]


class InputDipoleMaterial(DipoleMaterial):
    """A :class:`~torchsss.DipoleMaterial` whose coefficients come from :meth:`bind` (graph inputs) at each call.

    Until :meth:`bind` is called it is the material it was built from. Its own parameters only carry the channel
    count; a ``_stamp`` buffer changes at every eager :meth:`bind`, so that the kernel and throughput caches of the
    Lensch modules (keyed on the material's tensors) are never reused across materials.

    Args:
        like: the material to stand in for (its coefficients are the defaults).
    """

    def __init__(self, like: DipoleMaterial) -> None:
        super().__init__(like.sigma_a.detach(), like.sigma_s_prime.detach(), like.eta.detach())
        self.register_buffer("_stamp", torch.zeros((), dtype=torch.int64), persistent=False)
        self._bound: tuple[Tensor, Tensor, Tensor] | None = None

    def bind(self, sigma_a: Tensor, sigma_s_prime: Tensor, eta: Tensor) -> None:
        """Set the coefficients for the next calls: ``(C,)`` mm^-1, ``(C,)`` mm^-1, ``(1,)`` or ``(C,)``."""
        self._bound = (sigma_a, sigma_s_prime, eta)
        if not is_tracing():
            self._stamp.add_(1)

    @property
    def sigma_a(self) -> Tensor:
        """Absorption coefficient (mm^-1): the bound input."""
        return DipoleMaterial.sigma_a.fget(self) if self._bound is None else self._bound[0]

    @property
    def sigma_s_prime(self) -> Tensor:
        """Reduced scattering coefficient (mm^-1): the bound input."""
        return DipoleMaterial.sigma_s_prime.fget(self) if self._bound is None else self._bound[1]

    @property
    def eta(self) -> Tensor:
        """Relative index of refraction: the bound input."""
        return DipoleMaterial.eta.fget(self) if self._bound is None else self._bound[2]


def find_dipole_material(module: nn.Module) -> DipoleMaterial:
    """The one :class:`~torchsss.DipoleMaterial` of a module tree.

    Raises:
        ValueError: none, or several distinct ones (a material table: not supported as inputs).
    """
    found = {id(m): m for m in module.modules() if isinstance(m, DipoleMaterial)}
    if len(found) != 1:
        raise ValueError(f"module: expected exactly one DipoleMaterial in the module tree to make an input, "
                         f"got {len(found)}")
    return next(iter(found.values()))


def swap_material(module: nn.Module, old: nn.Module, new: nn.Module) -> int:
    """Replace every reference to the submodule ``old`` in ``module``'s tree by ``new``; returns the count."""
    count = 0
    for parent in module.modules():
        for name, child in list(parent._modules.items()):
            if child is old:
                parent._modules[name] = new
                count += 1
    return count


class MaterialInputs(nn.Module):
    """``forward(<module inputs>, sigma_a, sigma_s_prime, eta)``: the module with its material bound to the inputs.

    Built by :func:`with_material_inputs`, which gives ``forward`` an explicit signature (the exporter names the
    graph inputs after it and cannot take ``*args`` with dynamic dimensions).

    Args:
        module: a module whose tree holds one :class:`InputDipoleMaterial`.
    """

    def __init__(self, module: nn.Module) -> None:
        super().__init__()
        self.module = module
        self.material = find_dipole_material(module)
        if not isinstance(self.material, InputDipoleMaterial):
            raise TypeError(f"module: expected an InputDipoleMaterial in the tree, got "
                            f"{type(self.material).__name__} (use with_material_inputs)")

    def _call(self, *args: Tensor):
        *inputs, sigma_a, sigma_s_prime, eta = args
        self.material.bind(sigma_a, sigma_s_prime, eta)
        return self.module(*inputs)

    def forward(self, *args: Tensor):
        """The module's inputs followed by ``sigma_a (C,)``, ``sigma_s_prime (C,)``, ``eta (1,)``."""
        return self._call(*args)


def _required_inputs(module: nn.Module) -> list[str]:
    params = inspect.signature(module.forward).parameters.values()
    return [p.name for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty]


def with_material_inputs(module: nn.Module, inputs: tuple[str, ...] | None = None) -> MaterialInputs:
    """A copy of ``module`` whose dipole material is taken from three extra trailing inputs.

    Args:
        module: a module whose tree holds one :class:`~torchsss.DipoleMaterial` (shared or not between submodules).
        inputs: names of the module inputs that the graph takes before the material (default: ``forward``'s
            required positional parameters).

    Raises:
        ValueError: the module tree holds no :class:`~torchsss.DipoleMaterial` or several distinct ones.
    """
    clone = copy.deepcopy(module)
    old = find_dipole_material(clone)
    names = list(_required_inputs(module) if inputs is None else inputs)
    names += ["sigma_a", "sigma_s_prime", "eta"]
    if any(not n.isidentifier() or keyword.iskeyword(n) for n in names) or len(set(names)) != len(names):
        raise ValueError(f"inputs: expected distinct identifiers, got {names}")
    new = InputDipoleMaterial(old)
    if clone is old:  # the module is the material itself
        clone = new
    else:
        swap_material(clone, old, new)
    ns: dict = {}
    exec(f"def forward(self, {', '.join(names)}):\n    return self._call({', '.join(names)})\n", ns)
    ns["forward"].__doc__ = MaterialInputs.forward.__doc__
    cls = type(f"MaterialInputs_{type(module).__name__}", (MaterialInputs,), {"forward": ns["forward"]})
    return cls(clone)
