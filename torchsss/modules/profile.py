"""Stateless profile evaluation as a module: the first exportable building block."""

from __future__ import annotations

from torch import Tensor, nn

from torchsss.physics.dipole import dipole_rd

__all__ = ["DipoleProfile"]


class DipoleProfile(nn.Module):
    """Distances and material in, :math:`R_d` out: ``forward(r, sigma_a, sigma_s_prime, eta)``.

    The material enters as tensors (not parameters), so one exported graph serves any material, as Chang's
    dynamic materials need. See :func:`torchsss.dipole_rd` for the formula and the safe-gradient formulation.

    Shapes:
        - r: :math:`(..., C)` or :math:`(..., 1)` distances in mm.
        - sigma_a, sigma_s_prime: :math:`(C,)` in mm^-1.
        - eta: :math:`(1,)` or :math:`(C,)`.
        - output: :math:`(..., C)` in mm^-2.

    Examples:
        >>> import torch
        >>> DipoleProfile()(torch.rand(4, 5, 1), torch.full((3,), 0.01), torch.ones(3), torch.tensor([1.3])).shape
        torch.Size([4, 5, 3])
    """

    def forward(self, r: Tensor, sigma_a: Tensor, sigma_s_prime: Tensor, eta: Tensor) -> Tensor:
        """Evaluate :math:`R_d` (mm^-2) at distances ``r`` (mm); see the class docstring for shapes."""
        return dipole_rd(r, sigma_a, sigma_s_prime, eta)
