"""Shah 2007 ch. 6 as an nn.Module: image-space subsurface scattering by splatting the dipole profile.

No precomputation: every frame takes light-view samples (positions, :math:`E\\,dA`) and a camera-view G-buffer,
and splats :math:`R_d(|x_o - x_i|)\\,E_i\\,dA_i` onto the camera pixels within :math:`r_{max}` of each sample
(:func:`torchsss.ops.splat.splat_radiosity`), so deforming objects work unchanged. Several objects of different
materials render in one pass through a material table and object ids (Shah 6.4.3), and heterogeneous materials
through per-splat distance and irradiance modifiers (Shah eq. 7.4). Lengths in mm.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchsss.modules.material import check_profile
from torchsss.ops.splat import _footprint, splat_radiosity

__all__ = ["SplatTranslucency"]


class SplatTranslucency(nn.Module):
    """Radiosity image :math:`B(x_o) = \\sum_i M_{i,i} R_d^{m_i}(|x_o - x_i| M_{d,i})\\,E_i\\,dA_i` from splats.

    Args:
        material: a profile module (:class:`~torchsss.DipoleMaterial`, :class:`~torchsss.BurleyMaterial`,
            :class:`~torchsss.modules.TabulatedMaterial`, or any module of the profile contract of
            :mod:`torchsss.modules.material`), or a sequence of them (the material table, one row per material;
            sources pick their row with ``src_material``). Their parameters receive gradients.
        eps: tail fraction beyond the splat radius :math:`r_{max}(\\epsilon)` (Shah eq. 6.16), per channel; the
            largest channel's radius of each material is used. Fixed when the module is built (a budget is not
            differentiable): rebuild the module after large material changes.
        method: ``"auto"`` (tile gather in eager mode, window scatter while exporting), ``"window"`` or ``"tile"``.
        window: fixed odd window size in pixels for the export path (see :func:`~torchsss.ops.splat.splat_radiosity`
            and :func:`~torchsss.ops.splat.splat_window_size`); required to export.

    Examples:
        >>> import torch
        >>> from torchsss import BurleyMaterial, DipoleMaterial
        >>> m = SplatTranslucency(DipoleMaterial.from_preset("skin1"))
        >>> src = torch.tensor([[[0.0, 0.0, 0.0]]]); flux = torch.ones(1, 1, 3)
        >>> pos = torch.zeros(1, 3, 4, 4); mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        >>> vp = torch.eye(4).unsqueeze(0)
        >>> m(src, flux, pos, mask, vp).shape
        torch.Size([1, 3, 4, 4])
        >>> two = SplatTranslucency([DipoleMaterial.from_preset("skin1"), BurleyMaterial.from_preset("marble")])
        >>> ids = torch.tensor([[1]])
        >>> two(src, flux, pos, mask, vp, src_material=ids).shape
        torch.Size([1, 3, 4, 4])
    """

    def __init__(self, material: nn.Module | Sequence[nn.Module], *, eps: float = 0.01,
                 method: str = "auto", window: int | None = None) -> None:
        super().__init__()
        materials = [material] if isinstance(material, nn.Module) else material
        if isinstance(materials, (str, bytes)) or not isinstance(materials, Sequence) or len(materials) == 0:
            raise TypeError(
                f"material: expected a profile module or a non-empty sequence of them, got {type(material).__name__}"
            )
        for i, m in enumerate(materials):
            check_profile(m, f"material[{i}]")
        channels = {m.channels for m in materials}
        if len(channels) != 1:
            raise ValueError(f"material: expected the same number of channels in every material, got {channels}")
        if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not 0.0 < float(eps) < 1.0:
            raise ValueError(f"eps: expected a number in (0, 1), got {eps!r}")
        self.materials = nn.ModuleList(materials)
        self.eps = float(eps)
        self.method = method
        self.window = window
        r_max = torch.stack([m.r_max(self.eps).amax() for m in materials]).detach().clone()
        self.register_buffer("r_max", r_max)

    @property
    def material(self) -> nn.Module:
        """The first (with one material, the only) row of the material table."""
        return self.materials[0]

    def forward(self, src_pos: Tensor, src_flux: Tensor, dst_pos: Tensor, dst_mask: Tensor, view_proj: Tensor,
                src_material: Tensor | None = None, src_object: Tensor | None = None,
                dst_object: Tensor | None = None, src_distance_scale: Tensor | None = None,
                src_irradiance_scale: Tensor | None = None) -> Tensor:
        """Splat the sources onto the camera view.

        Args:
            src_pos: :math:`(B, S, 3)` light-view sample positions, mm.
            src_flux: :math:`(B, S, C)` transmitted flux :math:`E_i\\,dA_i` of each sample.
            dst_pos: :math:`(B, 3, H, W)` camera-view positions, mm.
            dst_mask: :math:`(B, 1, H, W)` bool, pixels that see the object.
            view_proj: :math:`(B, 4, 4)` or :math:`(4, 4)` camera view-projection.
            src_material: :math:`(B, S)` integer row of the material table per source (required with several
                materials).
            src_object: :math:`(B, S)` integer object id per source; with ``dst_object``, light scatters only
                within an object (Shah 6.4.3).
            dst_object: :math:`(B, 1, H, W)` integer object id per pixel.
            src_distance_scale: :math:`(B, S, 1)` or :math:`(B, S, C)` distance multiplier :math:`M_d > 0` at the
                source (Shah eq. 7.4; below 1 the profile widens, the light spreads farther).
            src_irradiance_scale: :math:`(B, S, 1)` or :math:`(B, S, C)` irradiance modulation :math:`M_i \\ge 0`.

        Returns:
            :math:`(B, C, H, W)` radiosity (0 off the mask).
        """
        return splat_radiosity(src_pos, src_flux, dst_pos, dst_mask, view_proj, list(self.materials), self.r_max,
                               src_material=src_material, src_object=src_object, dst_object=dst_object,
                               src_distance_scale=src_distance_scale, src_irradiance_scale=src_irradiance_scale,
                               method=self.method, window=self.window)

    def count_truncated(self, src_pos: Tensor, dst_pos: Tensor, view_proj: Tensor, window: int | None = None,
                        src_material: Tensor | None = None, src_distance_scale: Tensor | None = None,
                        r_max: Tensor | None = None) -> Tensor:
        """Number of splats per batch element whose footprint may not fit a fixed ``window`` (exportable).

        A splat's footprint is the conservative pixel bound of its reach :math:`r_{max}/\\min M_d` projected with
        ``view_proj`` (the bound of :func:`~torchsss.ops.splat.splat_window_size`, perspective growth and one pixel
        of slack included). A visible splat counts when the odd window side its footprint needs exceeds
        ``window`` along an axis that the window does not already span. Zero means nothing was truncated; a
        positive count is an upper bound (the bound is conservative), so a deployed graph can flag a frame whose
        window is too small instead of losing light silently.

        Args:
            src_pos: :math:`(B, S, 3)` splat centres, mm.
            dst_pos: :math:`(B, 3, H, W)` camera-view positions (only the image size is read).
            view_proj: :math:`(B, 4, 4)` or :math:`(4, 4)` camera view-projection.
            window: odd window side :math:`K` (default: the module's ``window``).
            src_material: :math:`(B, S)` integer row of the material table (several materials).
            src_distance_scale: :math:`(B, S, 1)` or :math:`(B, S, C)` distance multiplier :math:`M_d`.
            r_max: :math:`(M,)` truncation radius per material in mm (default: the module's ``r_max`` buffer).

        Returns:
            :math:`(B,)` int64 counts.

        Raises:
            ValueError: no ``window`` (neither given nor the module's).
        """
        k = self.window if window is None else window
        if k is None:
            raise ValueError("window: expected an odd int (the module has none), got None")
        b, s = src_pos.shape[0], src_pos.shape[1]
        h, w = dst_pos.shape[-2], dst_pos.shape[-1]
        vp = view_proj if view_proj.dim() == 3 else view_proj.unsqueeze(0)
        dtype = src_pos.dtype
        rm = (self.r_max if r_max is None else r_max).to(dtype).reshape(-1)
        reach = rm[0].expand(b, s) if src_material is None else rm[src_material.long()]
        if src_distance_scale is not None:
            reach = reach / src_distance_scale.to(dtype).amin(-1)
        batch = torch.arange(b, device=src_pos.device).repeat_interleave(s)
        _, half, visible = _footprint(src_pos.reshape(-1, 3), reach.reshape(-1), vp.expand(b, 4, 4)[batch], h, w)
        need = 2.0 * torch.ceil(half) + 1.0  # (B*S, 2): the odd side each axis needs (inf when unbounded)
        # image sides as a tensor: a Python comparison of the (symbolic) sizes would freeze them into an export
        spans = torch.tensor([w, h], device=src_pos.device) <= k  # the window covers the whole axis
        short = ((need > k) & ~spans).any(-1)
        return (visible & short).reshape(b, s).sum(1)
