"""Shah 2007 ch. 6 as an nn.Module: image-space subsurface scattering by splatting the dipole profile.

No precomputation: every frame takes light-view samples (positions, :math:`E\\,dA`) and a camera-view G-buffer,
and splats :math:`R_d(|x_o - x_i|)\\,E_i\\,dA_i` onto the camera pixels within :math:`r_{max}` of each sample
(:func:`torchsss.ops.splat.splat_radiosity`), so deforming objects work unchanged. Lengths in mm.
"""

from __future__ import annotations

from torch import Tensor, nn

from torchsss.modules.material import DipoleMaterial
from torchsss.ops.splat import splat_radiosity

__all__ = ["SplatTranslucency"]


class SplatTranslucency(nn.Module):
    """Radiosity image :math:`B(x_o) = \\sum_i R_d(|x_o - x_i|)\\,E_i\\,dA_i` from light-view splats.

    Args:
        material: the :class:`~torchsss.DipoleMaterial` (its parameters receive gradients).
        eps: tail fraction beyond the splat radius :math:`r_{max}(\\epsilon)` (Shah eq. 6.16), per channel; the
            largest channel's radius is used. Fixed when the module is built (a budget is not differentiable).
        method: ``"auto"`` (tile gather in eager mode, window scatter while exporting), ``"window"`` or ``"tile"``.
        window: fixed window size for the export path (see :func:`~torchsss.ops.splat.splat_radiosity`).

    Examples:
        >>> import torch
        >>> m = SplatTranslucency(DipoleMaterial.from_preset("skin1"))
        >>> src = torch.tensor([[[0.0, 0.0, 0.0]]]); flux = torch.ones(1, 1, 3)
        >>> pos = torch.zeros(1, 3, 4, 4); mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        >>> vp = torch.eye(4).unsqueeze(0)
        >>> m(src, flux, pos, mask, vp).shape
        torch.Size([1, 3, 4, 4])
    """

    def __init__(self, material: DipoleMaterial, *, eps: float = 0.01, method: str = "auto",
                 window: int | None = None) -> None:
        super().__init__()
        if not isinstance(material, DipoleMaterial):
            raise TypeError(f"material: expected a DipoleMaterial, got {type(material).__name__}")
        if not 0.0 < float(eps) < 1.0:
            raise ValueError(f"eps: expected a number in (0, 1), got {eps!r}")
        self.material = material
        self.eps = float(eps)
        self.method = method
        self.window = window
        self.register_buffer("r_max", material.r_max(self.eps).amax().reshape(1).detach().clone())

    def forward(self, src_pos: Tensor, src_flux: Tensor, dst_pos: Tensor, dst_mask: Tensor,
                view_proj: Tensor) -> Tensor:
        """Splat the sources onto the camera view.

        Args:
            src_pos: :math:`(B, S, 3)` light-view sample positions, mm.
            src_flux: :math:`(B, S, C)` transmitted flux :math:`E_i\\,dA_i` of each sample.
            dst_pos: :math:`(B, 3, H, W)` camera-view positions, mm.
            dst_mask: :math:`(B, 1, H, W)` bool, pixels that see the object.
            view_proj: :math:`(B, 4, 4)` or :math:`(4, 4)` camera view-projection.

        Returns:
            :math:`(B, C, H, W)` radiosity (0 off the mask).
        """
        m = self.material
        return splat_radiosity(src_pos, src_flux, dst_pos, dst_mask, view_proj, m.sigma_a, m.sigma_s_prime,
                               m.eta, self.r_max, method=self.method, window=self.window)
