"""Chang et al. 2008 as nn.Modules: texture-space importance sampling (§2.2-3) and the hybrid local/global split (§4).

**The estimator (Chang eq. 7-11).** The radiosity :math:`B(x_o) = \\int_S E(x) R_d(|x - x_o|) dA` is written over
the texture atlas as :math:`\\int_T E'(t) R_d dt` with :math:`E' = E\\,A_S/A_T`. On the texel grid this is the
midpoint quadrature :math:`F(x_o) = \\sum_t E(t)\\,A(t)\\,R_d(|x_t - x_o|)` (``A(t)`` the surface area of texel
``t``, chart texels only: gutter texels duplicate surface). Drawing ``N`` texels :math:`t_i` with probability
:math:`P(t) = \\mathrm{pdf}(t) / \\sum \\mathrm{pdf}` (:func:`~torchsss.ops.icdf.icdf_sample`, Chang's mip-pyramid
ICDF), every channel ``c`` is estimated by

.. math::
    \\hat B_c(x_o) = \\frac{1}{N} \\sum_{i=1}^N \\frac{E_c(t_i)\\,A(t_i)}{P(t_i)}\\, R_{d,c}(|x_{t_i} - x_o|),

which is unbiased for :math:`F_c` whenever :math:`P > 0` wherever :math:`E_c A > 0`. Chang's eq. 10 is the
special case :math:`\\mathrm{pdf} = E'` of a single channel, where the ratio is the constant
:math:`E'_{avg}` (the *integral* of :math:`E'`, not its mean). With colour, one shared pdf serves all channels
(the samples are shared between channels and receivers, as in the paper); it is the channel **sum** of
:math:`E' = E\\,M_i\\,A` (positive wherever any channel is, so every channel stays unbiased; for grey light the
ratio is again constant). The sample point is the texel's stored surface position (nearest texel: the
in-texel offset that the sampler also returns is not used), so the estimator's expectation is exactly the atlas
quadrature that :func:`~torchsss.ops.reference.reference_radiosity` computes over all chart texels. The sum
over samples and receivers *is* that all-pairs integrator with per-sample area :math:`1/(N P(t_i))`, so memory
stays bounded by ``max_pairs``.

**Gradients.** The sampling density is treated as a constant (detached): the estimator is then linear in
:math:`E` and smooth in the material, and its gradients are unbiased estimates of the gradients of :math:`F`
(differentiating through the texel choice would be biased: the texel index is piecewise constant in the pdf).
The material is a submodule evaluated in every ``forward()``, so its parameters get gradients and can change
from frame to frame without any recomputation (Chang's "dynamic materials").

**Heterogeneous materials (Shah eq. 7.4).** Optional atlases at the *source* texel: an irradiance modulation
:math:`M_i` (multiplies :math:`E` and so also the pdf), a distance multiplier :math:`M_d`
(:math:`R_d(|x_i - x_o|\\,M_d(x_i))`, as in :func:`~torchsss.ops.reference.reference_radiosity`) and a
translucency mask (0 = not translucent: the texel sends no subsurface light). Receivers are points; masking
receivers is left to the caller (e.g. by looking the mask up at the receivers' texture coordinates).

**The hybrid (Chang §4).** :math:`R_d = R_d W_l + R_d W_g` (weights of :func:`~torchsss.physics.chang_weights`,
with its sign correction of the paper's :math:`W_l`). The global part is the estimator above with the profile
:math:`R_d W_g`; the local part is a filter of :math:`L \\cdot C + 1` irradiance lookups around each receiver
(:class:`HybridTranslucency` documents its approximations).
"""

from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

import torchsss.modules.material as material_mod
from torchsss._checks import (
    check_finite,
    check_int,
    check_nonnegative,
    check_positive,
    check_shape,
    check_tensor,
    is_tracing,
    skip_value_checks,
)
from torchsss.modules.blocks import in_blocks
from torchsss.modules.cache import ValueCache, material_key
from torchsss.modules.material import bulk_profile
from torchsss.modules.sampling import IcdfSampler
from torchsss.ops.icdf import MAX_LEVELS
from torchsss.ops.reference import DEFAULT_MAX_PAIRS, reference_radiosity
from torchsss.physics.budget import chang_rp, chang_weights

__all__ = ["ChangLocalProfile", "HybridTranslucency", "ImportanceSampledTranslucency", "SplitProfile", "SurfaceLocal"]



def _check_number(value: object, name: str, *, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name}: expected a number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v) or (v <= 0 if positive else v < 0):
        raise ValueError(f"{name}: expected a finite number {'> 0' if positive else '>= 0'}, got {value!r}")
    return v


def _check_map(x: object, name: str, h: int, w: int, channels: tuple[int, ...]) -> Tensor:
    """A (1, k, H, W) atlas with k in ``channels``."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.dim() != 4 or x.shape[0] != 1 or x.shape[1] not in channels or tuple(x.shape[-2:]) != (h, w):
        want = " or ".join(f"(1, {k}, {h}, {w})" for k in channels)
        raise ValueError(f"{name}: expected shape {want}, got {tuple(x.shape)}")
    return x


def _material_channels(material: nn.Module) -> int | None:
    ch = getattr(material, "channels", None)
    return ch if isinstance(ch, int) else None


class ImportanceSampledTranslucency(nn.Module):
    """Chang's texture-space importance-sampled radiosity at arbitrary receiver points (see the module notes).

    Args:
        position: :math:`(1, 3, H, W)` surface position of every texel (mm).
        area: :math:`(1, 1, H, W)` surface area of every texel (mm^2, >= 0).
        mask: :math:`(1, 1, H, W)` bool, the texels that are sources: the atlas's ``chart_mask`` (gutter texels
            duplicate surface and must not be counted twice).
        material: profile module, ``forward(r (..., 1)) -> (..., C)`` in mm^-2 (e.g.
            :class:`~torchsss.modules.DipoleMaterial`); any ``nn.Module`` profile works, its parameters get
            gradients.
        distance_scale: optional :math:`(1, 1|C, H, W)` distance multiplier :math:`M_d > 0` (Shah eq. 7.4).
        irradiance_scale: optional :math:`(1, 1|C, H, W)` irradiance modulation :math:`M_i \\ge 0`.
        translucency_mask: optional :math:`(1, 1, H, W)` bool or weights in [0, 1]; 0 = the texel is not
            translucent and sends no subsurface light.
        levels: pyramid depth of the sampler, fixed at construction (default: the smallest that fits the
            atlas, :func:`~torchsss.ops.icdf.pyramid_levels` ``(H, W)``), so ``torch.compile`` and ONNX export work
            with the defaults.
        max_pairs: (receiver, sample) pairs evaluated at once per batch element (bounds memory).

    Shapes:
        ``forward(irradiance (B, C, H, W), u (B, N, 2), receivers (B, M, 3), pdf=None) -> (B, M, C)``.

    Examples:
        >>> from torchsss.modules import DipoleMaterial
        >>> pos = torch.stack(torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="xy")
        ...                   + (torch.zeros(8, 8),)).unsqueeze(0)           # a plane, 1 mm texels
        >>> mod = ImportanceSampledTranslucency(pos, torch.ones(1, 1, 8, 8), torch.ones(1, 1, 8, 8, dtype=torch.bool),
        ...                                     DipoleMaterial.from_preset("marble"))
        >>> b = mod(torch.ones(1, 3, 8, 8), torch.rand(1, 256, 2), torch.tensor([[[3.5, 3.5, 0.0]]]))
        >>> b.shape
        torch.Size([1, 1, 3])
    """

    def __init__(
        self,
        position: Tensor,
        area: Tensor,
        mask: Tensor,
        material: nn.Module,
        *,
        distance_scale: Tensor | None = None,
        irradiance_scale: Tensor | None = None,
        translucency_mask: Tensor | None = None,
        levels: int | None = None,
        max_pairs: int = DEFAULT_MAX_PAIRS,
    ) -> None:
        super().__init__()
        check_tensor(position, "position")
        dims = check_shape(position, "position", "1,3,H,W")
        check_tensor(area, "area")
        check_shape(area, "area", "1,1,H,W", **dims)
        if not isinstance(mask, Tensor):
            raise TypeError(f"mask: expected a torch.Tensor, got {type(mask).__name__}")
        check_shape(mask, "mask", "1,1,H,W", **dims)
        check_nonnegative(area, "area")
        if not isinstance(material, nn.Module):
            raise TypeError(f"material: expected an nn.Module profile, got {type(material).__name__}")
        if levels is not None:
            if isinstance(levels, bool) or not isinstance(levels, int):
                raise TypeError(f"levels: expected an int or None, got {type(levels).__name__}")
            if not 0 <= levels <= MAX_LEVELS or 2**levels < max(dims["H"], dims["W"]):
                raise ValueError(f"levels: expected an int in [0, {MAX_LEVELS}] with 2**levels >= "
                                 f"{max(dims['H'], dims['W'])}, got {levels}")
        check_int(max_pairs, "max_pairs", 1)
        h, w = dims["H"], dims["W"]
        ch = _material_channels(material)
        chans = (1,) if ch in (None, 1) else (1, ch)
        dtype = position.dtype
        weight = area.detach() * mask.to(dtype)
        if translucency_mask is not None:
            tm = _check_map(translucency_mask, "translucency_mask", h, w, (1,)).to(dtype)
            if not is_tracing() and bool(((tm < 0) | (tm > 1) | torch.isnan(tm)).any()):
                raise ValueError("translucency_mask: expected values in [0, 1], got values outside")
            weight = weight * tm
        self.material = material
        #: The texel sampler, its pyramid depth fixed for this atlas's (H, W).
        self.sampler = IcdfSampler(levels, size=(h, w))
        self.max_pairs = max_pairs
        self.register_buffer("position", position.detach().clone())
        #: Source weight of every texel: area x chart mask x translucency mask (mm^2).
        self.register_buffer("source_area", weight.clone())
        ds = ms = None
        if distance_scale is not None:
            ds = _check_map(distance_scale, "distance_scale", h, w, chans).detach().to(dtype).clone()
            check_positive(ds, "distance_scale")
        if irradiance_scale is not None:
            ms = _check_map(irradiance_scale, "irradiance_scale", h, w, chans).detach().to(dtype).clone()
            check_nonnegative(ms, "irradiance_scale")
        self.register_buffer("distance_scale", ds)
        self.register_buffer("irradiance_scale", ms)

    @classmethod
    def from_atlas(cls, atlas, material: nn.Module, **kwargs) -> ImportanceSampledTranslucency:
        """Build from a :class:`~torchsss.geometry.atlas.Atlas` (positions, areas, ``chart_mask`` as sources)."""
        return cls(atlas.position, atlas.area, atlas.chart_mask, material, **kwargs)

    @property
    def shape(self) -> tuple[int, int]:
        """Atlas ``(H, W)``."""
        return int(self.position.shape[-2]), int(self.position.shape[-1])

    @property
    def levels(self) -> int:
        """Pyramid depth of the sampler (fixed at construction)."""
        return self.sampler.levels

    def weighted_irradiance(self, irradiance: Tensor) -> Tensor:
        """:math:`E' = E\\,M_i\\,A` per texel :math:`(B, C, H, W)` (mm^2 x irradiance): 0 outside the sources."""
        e = irradiance * self.source_area
        if self.irradiance_scale is not None:
            e = e * self.irradiance_scale
        return e

    def density(self, irradiance: Tensor) -> Tensor:
        """The default sampling map :math:`(B, 1, H, W)`: the channel sum of :math:`E'`, detached."""
        return self.weighted_irradiance(irradiance).sum(1, keepdim=True).detach()

    def _check_inputs(self, irradiance: Tensor, u: Tensor, receivers: Tensor) -> dict:
        check_tensor(irradiance, "irradiance")
        h, w = self.shape
        dims = check_shape(irradiance, "irradiance", "B,C,H,W", H=h, W=w)
        ch = _material_channels(self.material)
        if ch not in (None, 1) and dims["C"] not in (1, ch):
            raise ValueError(f"irradiance: expected 1 or {ch} channels (the material's), got {dims['C']}")
        check_nonnegative(irradiance, "irradiance")
        check_tensor(u, "u")
        dims = check_shape(u, "u", "B,N,2", **dims)
        if not is_tracing() and dims["N"] < 1:
            raise ValueError(f"u: expected at least one sample (N >= 1), got shape {tuple(u.shape)}")
        check_tensor(receivers, "receivers")
        dims = check_shape(receivers, "receivers", "B,M,3", **dims)
        check_finite(receivers, "receivers")
        return dims

    def forward(self, irradiance: Tensor, u: Tensor, receivers: Tensor, pdf: Tensor | None = None) -> Tensor:
        """Radiosity :math:`(B, M, C)` at ``receivers`` from ``N`` importance samples (see the module notes).

        Args:
            irradiance: :math:`(B, C, H, W)` transmitted irradiance atlas :math:`E` (>= 0).
            u: :math:`(B, N, 2)` uniforms in [0, 1) (random, stratified or Sobol), one pair per sample.
            receivers: :math:`(B, M, 3)` receiver positions (mm).
            pdf: optional :math:`(B, 1, H, W)` sampling map (detached; default the channel sum of
                :math:`E'`). It must be > 0 wherever :math:`E' > 0` for the estimate to stay unbiased.

        Returns:
            :math:`(B, M, C)` radiosity (multiply by :math:`F_t/\\pi` for radiance). All-zero irradiance gives
            exact zeros.

        Raises:
            TypeError: non-tensor or non-floating inputs.
            ValueError: shapes that disagree with the atlas or each other, negative or non-finite irradiance,
                ``u`` outside [0, 1), no samples.
        """
        dims = self._check_inputs(irradiance, u, receivers)
        return self.estimate(irradiance, u, receivers, dims, pdf)

    def estimate(self, irradiance: Tensor, u: Tensor, receivers: Tensor, dims: dict, pdf: Tensor | None = None,
                 profile: nn.Module | None = None) -> Tensor:
        """:meth:`forward` on checked inputs (``dims`` from the checks), with ``profile`` in place of the material."""
        profile = self.material if profile is None else profile
        src_pos, src_e, inv, ds, _ = self._draw(irradiance, u, dims, pdf)
        if not is_tracing() and dims["M"] == 0:
            c = max(dims["C"], _material_channels(profile) or 1)
            return src_e.new_zeros(dims["B"], 0, c)
        return reference_radiosity(src_pos, src_e, inv.to(src_e.dtype), receivers.to(src_e.dtype), profile,
                                   src_distance_scale=ds, max_pairs=self.max_pairs)

    def _draw(self, irradiance: Tensor, u: Tensor, dims: dict, pdf: Tensor | None = None):
        """The N samples of the estimator: positions, weighted irradiance, 1 / (N p), M_d and flat texel index."""
        b, n = dims["B"], dims["N"]
        h, w = self.shape
        ep = self.weighted_irradiance(irradiance)
        if not skip_value_checks(ep) and not bool(torch.isfinite(ep.sum())):
            raise ValueError(f"irradiance: expected values whose area-weighted sum is finite in {ep.dtype}, got an "
                             f"overflow (max irradiance {float(irradiance.max()):.3g}); rescale the light intensity "
                             "or use float64")
        if pdf is None:
            pdf = ep.sum(1, keepdim=True)
        else:
            check_tensor(pdf, "pdf")
            check_shape(pdf, "pdf", "B,1,H,W", B=b, H=h, W=w)
        xy, p = self.sampler(pdf.detach(), u)
        col = xy[..., 0].detach().floor().long().clamp(0, w - 1)
        row = xy[..., 1].detach().floor().long().clamp(0, h - 1)
        idx = row * w + col  # (B, N)

        def gather(img: Tensor) -> Tensor:  # (1|B, k, H, W) -> (B, N, k)
            flat = img.flatten(2).expand(b, -1, -1)
            return torch.gather(flat, 2, idx.unsqueeze(1).expand(-1, flat.shape[1], -1)).transpose(1, 2)

        src_e = gather(ep)
        src_pos = gather(self.position).to(src_e.dtype)
        pos_p = p > 0
        inv = torch.where(pos_p, 1.0 / (n * torch.where(pos_p, p, torch.ones_like(p))), torch.zeros_like(p))
        ds = None if self.distance_scale is None else gather(self.distance_scale)
        return src_pos, src_e, inv, ds, idx


class ChangLocalProfile(nn.Module):
    """The local weight of Chang §4.1 truncated at ``bound``: :math:`W_l^b(r) = W_l(r)\\,[r \\le b]`.

    ``forward(r)`` returns the weight (same shape as ``r``); no parameters. :math:`W_l` uses the corrected sign of
    :func:`~torchsss.physics.chang_weights`. Truncating the local weight (instead of the profile) keeps the split
    exact: :class:`SplitProfile` gives the global part :math:`R_d (1 - W_l^b)`.
    """

    def __init__(self, r_p: float, k: float = 1.5, bound: float | None = None) -> None:
        super().__init__()
        self.r_p = _check_number(r_p, "r_p", positive=False)
        self.k = _check_number(k, "k")
        self.bound = math.inf if bound is None else _check_number(bound, "bound", positive=False)

    def forward(self, r: Tensor) -> Tensor:
        """:math:`W_l^b(r)`."""
        w_l, _ = chang_weights(r, self.r_p, self.k)
        return torch.where(r <= self.bound, w_l, torch.zeros_like(w_l))


class SplitProfile(nn.Module):
    """:math:`R_d(r)\\,(1 - W_l^b(r))` or :math:`R_d(r)\\,W_l^b(r)`: one part of Chang's split as a profile module.

    Args:
        material: the full profile module (its parameters stay live).
        weight: a :class:`ChangLocalProfile`.
        part: ``"global"`` or ``"local"``.
    """

    def __init__(self, material: nn.Module, weight: ChangLocalProfile, part: str = "global") -> None:
        super().__init__()
        if part not in ("global", "local"):
            raise ValueError(f"part: expected 'global' or 'local', got {part!r}")
        self.material = material
        self.weight = weight
        self.part = part

    def forward(self, r: Tensor) -> Tensor:
        """The weighted profile, ``(..., C)`` in mm^-2."""
        w_l = self.weight(r)
        return self.material(r) * (w_l if self.part == "local" else 1.0 - w_l)


class SurfaceLocal(nn.Module):
    """The hybrid's local term gathered in 3-D from surface samples: no texture seam can cut it.

    :math:`B_l(x_o) = \\sum_s A_s\\,R_d(d_{os})\\,W_l^b(d_{os})\\,E(s)` over the surface samples ``s`` within the
    local bound of the receiver (``rows``, ``cols``, ``distance`` of :func:`~torchsss.geometry.neighbours.ball_pairs`),
    :math:`d` the 3-D distance. :math:`E(s)` is the irradiance atlas read bilinearly at the sample's uv over the
    atlas's valid texels (renormalised: a sample beside a chart edge reads its chart and the gutter's
    continuation, not the empty texels beyond), times :math:`M_i` and the translucency mask when given. Chang's
    filter (:class:`HybridTranslucency`'s atlas pattern) reads the near field in the texture instead, and near a
    chart edge it must hand the part across the seam to the sampled global term, which shows as speckle along the
    seams (default scene at 128 x 128, N = 8192: relative RMSE 6.2% within 1 mm of a chart edge against 1.7%
    elsewhere); gathered here over the surface, the split is the same everywhere (0.8% against 0.7%) and the
    global term takes :math:`R_d (1 - W_l^b)` for every pair (:class:`SplitProfile`).

    Args:
        sample_uv: :math:`(N, 2)` atlas uv of the samples (u right, v up).
        sample_area: :math:`(N,)` mm^2.
        valid: :math:`(1, 1, H, W)` the atlas's valid texels.
        material: the profile module (shared with the global term).
        weight: the :class:`ChangLocalProfile` of the split.
        irradiance_scale: optional :math:`(1, 1 | C, H, W)` atlas :math:`M_i`.
        translucency_mask: optional :math:`(1, 1, H, W)` atlas (0: the texel sends no subsurface light).

    Shapes:
        ``forward(irradiance (B, C, H, W), rows (P,), cols (P,), distance (P,), receivers)`` -> :math:`(B, M, C)`;
        ``receivers`` is M, or the :math:`(M, 3)` receiver positions (only their count is used: the form that
        keeps M dynamic in an exported graph).

    Examples:
        >>> from torchsss.modules import DipoleMaterial
        >>> mat = DipoleMaterial.from_preset("skin1")
        >>> valid = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        >>> w_l = ChangLocalProfile(1.0, 1.5, 3.0)
        >>> loc = SurfaceLocal(torch.tensor([[0.5, 0.5]]), torch.tensor([0.2]), valid, mat, w_l)
        >>> b = loc(torch.ones(1, 3, 4, 4), torch.tensor([0]), torch.tensor([0]), torch.tensor([0.1]), 1)
        >>> tuple(b.shape), bool((b > 0).all())
        ((1, 1, 3), True)
    """

    #: Pairs whose weights are evaluated at a time outside autograd (:meth:`pair_weights`).
    weight_block = 1 << 20

    def __init__(self, sample_uv: Tensor, sample_area: Tensor, valid: Tensor, material: nn.Module,
                 weight: ChangLocalProfile, *, irradiance_scale: Tensor | None = None,
                 translucency_mask: Tensor | None = None) -> None:
        super().__init__()
        check_tensor(sample_uv, "sample_uv")
        check_tensor(sample_area, "sample_area")
        n = check_shape(sample_uv, "sample_uv", "N,2")["N"]
        check_shape(sample_area, "sample_area", "N", N=n)
        if not isinstance(valid, Tensor):
            raise TypeError(f"valid: expected a torch.Tensor, got {type(valid).__name__}")
        dims = check_shape(valid, "valid", "1,1,H,W")
        if not isinstance(weight, ChangLocalProfile):
            raise TypeError(f"weight: expected a ChangLocalProfile, got {type(weight).__name__}")
        check_finite(sample_uv, "sample_uv")
        check_nonnegative(sample_area, "sample_area")
        dtype = sample_area.dtype
        self.material = material
        self.weight = weight
        uv = sample_uv.detach().to(dtype)
        grid = torch.stack([2.0 * uv[:, 0] - 1.0, 1.0 - 2.0 * uv[:, 1]], -1)  # grid_sample: y down, v up
        self.register_buffer("grid", grid.reshape(1, 1, n, 2))
        self.register_buffer("area", sample_area.detach().clone())
        mask = valid.to(dtype)
        if translucency_mask is not None:
            check_shape(translucency_mask, "translucency_mask", "1,1,H,W", H=dims["H"], W=dims["W"])
            mask = mask * translucency_mask.to(dtype)
        self.register_buffer("valid", valid.to(dtype))
        self.register_buffer("lookup", mask)
        if irradiance_scale is not None:
            check_shape(irradiance_scale, "irradiance_scale", "1,C,H,W", H=dims["H"], W=dims["W"])
        self.register_buffer("irradiance_scale", None if irradiance_scale is None else irradiance_scale.clone())
        self._cache = ValueCache()

    def with_weight(self, weight: ChangLocalProfile) -> SurfaceLocal:
        """The same samples and atlas with another local weight (a narrower split): buffers are shared."""
        if not isinstance(weight, ChangLocalProfile):
            raise TypeError(f"weight: expected a ChangLocalProfile, got {type(weight).__name__}")
        other = copy.copy(self)
        other._modules = dict(self._modules)
        other._modules["weight"] = weight
        other._cache = ValueCache()
        return other

    def sample_irradiance(self, irradiance: Tensor) -> Tensor:
        """:math:`(B, C, H, W)` atlas -> :math:`(B, N, C)` irradiance at the samples (valid texels only)."""
        e = irradiance * self.lookup
        if self.irradiance_scale is not None:
            e = e * self.irradiance_scale
        b = e.shape[0]
        grid = self.grid.to(e.dtype).expand(b, -1, -1, -1)
        num = F.grid_sample(e, grid, mode="bilinear", padding_mode="zeros", align_corners=False)[:, :, 0]
        den = F.grid_sample(self.valid.to(e.dtype).expand(b, -1, -1, -1), grid, mode="bilinear",
                            padding_mode="zeros", align_corners=False)[:, :, 0]
        return (num / den.clamp_min(1e-6)).transpose(1, 2)

    def pair_weights(self, cols: Tensor, distance: Tensor) -> Tensor:
        """:math:`(P, C)` :math:`A_s R_d(d) W_l^b(d)` for the current material.

        Outside autograd, for at least :data:`~torchsss.modules.material.BULK_MIN_VALUES` pairs, the profile is
        evaluated through a table (:func:`~torchsss.modules.material.bulk_profile`); fewer are evaluated directly.
        """
        d = distance.unsqueeze(-1)
        if torch.is_grad_enabled() or is_tracing():
            return self.area[cols].unsqueeze(-1).to(d.dtype) * self.material(d) * self.weight(d)
        profile = self.material
        if distance.numel() >= material_mod.BULK_MIN_VALUES:
            profile = bulk_profile(self.material, float(distance.max()), d.dtype, d.device)
        # in blocks written into the output (every pair's profile temporaries at once took 0.5 GB over the 8.4M
        # pairs of the hybrid's frame on the shared bunny)
        return in_blocks(lambda lo, hi: self.area[cols[lo:hi]].unsqueeze(-1).to(d.dtype) * profile(d[lo:hi])
                         * self.weight(d[lo:hi]), distance.numel(), self.weight_block)

    def forward(self, irradiance: Tensor, rows: Tensor, cols: Tensor, distance: Tensor,
                receivers: int | Tensor, *, cache: bool = True) -> Tensor:
        """:math:`B_l` at ``receivers`` points, :math:`(B, M, C)` (see the class docstring).

        ``cache``: keep the pairs' weights :math:`A_s R_d W_l^b` for the next call with the same pairs and material
        (outside autograd; one set is kept). ``False`` for pairs used once (a frame's refined pixels): they neither
        evict the kept set nor can a later tensor at the same address be mistaken for them.

        Raises:
            TypeError, ValueError: bad tensors or shapes (named), a NaN or infinite irradiance texel.
        """
        check_tensor(irradiance, "irradiance")
        check_shape(irradiance, "irradiance", "B,C,H,W", H=self.valid.shape[-2], W=self.valid.shape[-1])
        check_finite(irradiance, "irradiance")
        p = check_shape(distance, "distance", "P")["P"]
        check_shape(rows, "rows", "P", P=p)
        check_shape(cols, "cols", "P", P=p)
        if isinstance(receivers, Tensor):
            receivers = check_shape(receivers, "receivers", "M,3")["M"]
        else:
            receivers = check_int(receivers, "receivers", 0)
        es = self.sample_irradiance(irradiance)  # (B, N, C)
        if not isinstance(cache, bool):
            raise TypeError(f"cache: expected a bool, got {type(cache).__name__}")
        key = material_key(self.material) if cache else None
        w = self._cache.get(None if key is None else (*key, distance.data_ptr(), p),
                            lambda: self.pair_weights(cols, distance))
        out = es.new_zeros(es.shape[0], receivers, es.shape[-1])
        if torch.is_grad_enabled() or is_tracing():
            return out.index_add(1, rows, w.to(es.dtype).unsqueeze(0) * es.index_select(1, cols))
        block = 1 << 22  # (B, 4M, C) temporaries at a time: memory stays bounded whatever the pair count
        for lo in range(0, p, block):
            hi = min(p, lo + block)
            out.index_add_(1, rows[lo:hi], w[lo:hi].to(es.dtype).unsqueeze(0) * es[:, cols[lo:hi]])
        return out


def _texel_frames(position: Tensor, valid: Tensor) -> Tensor:
    """Per texel :math:`(1, 4, H, W)`: the 2x2 map from mm in a local orthonormal tangent frame to texel offsets.

    The atlas's Jacobian :math:`J = [\\partial P/\\partial x, \\partial P/\\partial y]` (mm per texel, x = column,
    y = row) comes from central differences of the texel positions (one-sided where a neighbour is not valid,
    zero where both are missing). With :math:`J = Q R` (Gram-Schmidt, :math:`Q = [e_1, e_2]` orthonormal) an
    offset :math:`a e_1 + b e_2` in the tangent plane maps to the texel offset :math:`R^{-1} (a, b)`. Degenerate
    texels (rank-deficient :math:`J`) get the zero map: every pattern point then falls on the receiver's texel.
    Entries: ``(R^-1)_00, (R^-1)_01, (R^-1)_10, (R^-1)_11``.
    """
    pos = position.to(torch.float64)
    v = valid.to(torch.float64)

    def diff(dim: int) -> Tensor:
        fwd_p = torch.roll(pos, -1, dim)
        bwd_p = torch.roll(pos, 1, dim)
        fwd_v = torch.roll(v, -1, dim)
        bwd_v = torch.roll(v, 1, dim)
        size = pos.shape[dim]
        idx = torch.arange(size, device=pos.device)
        shape = [1, 1, 1, 1]
        shape[dim] = size
        fwd_v = fwd_v * (idx < size - 1).view(shape)
        bwd_v = bwd_v * (idx > 0).view(shape)
        central = (fwd_p - bwd_p) / 2.0
        d = torch.where((fwd_v * bwd_v) > 0, central,
                        torch.where(fwd_v > 0, fwd_p - pos, torch.where(bwd_v > 0, pos - bwd_p, torch.zeros_like(pos))))
        return d * v

    jx, jy = diff(3), diff(2)
    nx = jx.norm(dim=1, keepdim=True)
    ok_x = nx > 0
    e1 = jx / torch.where(ok_x, nx, torch.ones_like(nx))
    r01 = (e1 * jy).sum(1, keepdim=True)
    perp = jy - r01 * e1
    r11 = perp.norm(dim=1, keepdim=True)
    ok = ok_x & (r11 > 1e-9 * nx)
    r00 = torch.where(ok, nx, torch.ones_like(nx))
    r11s = torch.where(ok, r11, torch.ones_like(r11))
    # R = [[r00, r01], [0, r11]] -> R^-1 = [[1/r00, -r01/(r00 r11)], [0, 1/r11]]
    inv = torch.cat([1.0 / r00, -r01 / (r00 * r11s), torch.zeros_like(r00), 1.0 / r11s], dim=1)
    return (inv * ok).to(position.dtype)


class HybridTranslucency(nn.Module):
    """Chang §4: local filter + importance-sampled global term, :math:`B = B_l + B_g`.

    **Split.** :math:`R_p` is :func:`~torchsss.physics.chang_rp` at importance bound ``c`` for the build material,
    the largest over the channels (one split for all channels, as in the paper), ``K = k``. The local weight is
    truncated at :math:`r_b = R_p + \\ln(0.5/\\epsilon_l)/K` (where :math:`W_l = \\epsilon_l`, ``local_eps``);
    the global profile is :math:`R_d (1 - W_l [r \\le r_b])`, so the two parts add up to :math:`R_d` exactly
    whatever the truncation. With :math:`R_p = 0` (no local peak, :func:`chang_rp`) everything is global.
    :math:`R_p`, :math:`r_b` and the pattern are fixed at construction; the material may change afterwards
    (gradients, per-frame edits): the ring weights are recomputed from it in every ``forward()``.

    **Local term (Chang §4.2, translucent-shadow-map filter) and its approximations.**

    1. The pattern has ``rings`` (L) rings of ``per_ring`` (C) points plus the centre. The radial importance
       :math:`q(r) = 2\\pi r\\,\\overline{R_d}(r)\\,W_l^b(r)` (channel mean, build material) is cut into L + 1 pieces
       of equal mass: the disk :math:`[0, \\rho_1]` goes to the centre point, the annulus
       :math:`[\\rho_l, \\rho_{l+1}]` to ring ``l`` placed at the piece's median radius (importance-sampled radii
       as in Mertens et al.), its C points at equal angles, staggered by half a step on odd rings.
    2. Every point carries its piece's mass per channel :math:`\\int_{piece} 2\\pi r R_{d,c} W_l^b dr` (trapezoid
       rule on a fixed grid of ``grid`` radii, quadratic spacing), divided by the piece's point count; so a
       constant :math:`E` on a plane is filtered exactly (for any material), and a varying one is a
       deterministic quadrature with L + 1 radial and C angular nodes (its error is a bias, not noise).
    3. The pattern lies in the receiver's tangent plane, in mm. It is mapped into the atlas with the local
       Jacobian of the parameterization at the receiver's texel (:func:`_texel_frames`), i.e. the surface is
       taken as its tangent plane over :math:`r \\le r_b` and the atlas as locally affine.
    4. **With chart ids** (``chart_id``, the default from an atlas): :math:`E` is read with bilinear
       ``grid_sample`` from the chart texels, and a point counts only if its texel lies in the receiver's chart.
       Each point's weight is rescaled from the pattern's planar radius :math:`r_p` to the 3-D distance
       :math:`d` between the surface points the atlas holds at the centre and at the point:
       :math:`w_p f(d) / f(r_p)` with :math:`f = R_d W_l^b`; on a curved surface :math:`d < r_p`, and the
       rescaled weight is what the global term leaves out (below).
       **Without** (``chart_id=None``, the earlier approximation): gutters are read too, a point past a chart's
       gutter reads 0 and the weights stay planar, which loses energy on curved surfaces and at seams (6-9%
       on a 20 mm sphere, up to a third on scanned meshes: ``tests/test_hybrid_vs_reference.py``).

    **Global term.** Importance-sampled as :class:`ImportanceSampledTranslucency`. With chart ids each sample
    contributes :math:`R_d (1 - W_l^b\\,[\\text{same chart}])`: sources in another chart than the receiver
    (across a seam, the far side of a thin part) are entirely global, so the two terms add up to :math:`R_d`
    over every pair, up to the local quadrature. Near a seam the global estimator then carries the profile's
    peak from across the seam, which shows as noise along chart boundaries that falls with ``N`` (default scene,
    128x128: 3.8% at N = 4096, 1.6% at 16384). Without chart ids the profile is :class:`SplitProfile`
    ("global"), :math:`R_d (1 - W_l^b)` for every pair.

    Args:
        position, area, mask: as :class:`ImportanceSampledTranslucency` (``mask`` = chart texels).
        valid: :math:`(1, 1, H, W)` bool, texels with surface (charts and filled gutters) for the Jacobian.
        material: a dipole-like profile module with ``sigma_a``, ``sigma_s_prime``, ``eta`` (or give ``r_p``).
        r_p: split radius in mm (default: from the material with ``c``).
        c: Chang's importance lower bound (mm^-1); default 0.1, not 0.01: the local filter assumes a flat surface
            within its reach, and c = 0.01 gave 13-44% bias on a back-lit Igea and sphere at 10-30 mm against 3-21%
            at 0.1 (benchmarks/results/chang.md).
        k: Chang's K (mm^-1).
        rings, per_ring: L and C of the pattern.
        local_eps: truncation of the local weight.
        grid: radii of the quadrature grid for the ring weights.
        irradiance_scale, translucency_mask: as :class:`ImportanceSampledTranslucency` (applied to both terms).
        levels, max_pairs: of the global sampler (``levels`` default: the smallest that fits the atlas, fixed at
            construction).
        chart_id: :math:`(1, 1, H, W)` integer chart of every valid texel (``Atlas.chart_id``); None keeps the
            chart-less split (see 4.).

    Shapes:
        ``forward(irradiance (B, C, H, W), u (B, N, 2), receivers (B, M, 3), receivers_uv (B, M, 2))``
        -> :math:`(B, M, C)`; ``receivers_uv`` in the atlas convention (u right, v up, [0, 1]).
    """

    def __init__(
        self,
        position: Tensor,
        area: Tensor,
        mask: Tensor,
        valid: Tensor,
        material: nn.Module,
        *,
        r_p: float | None = None,
        c: float = 0.1,
        k: float = 1.5,
        rings: int = 8,
        per_ring: int = 16,
        local_eps: float = 1e-3,
        grid: int = 1024,
        irradiance_scale: Tensor | None = None,
        translucency_mask: Tensor | None = None,
        levels: int | None = None,
        max_pairs: int = DEFAULT_MAX_PAIRS,
        chart_id: Tensor | None = None,
    ) -> None:
        super().__init__()
        rings = check_int(rings, "rings", 1)
        per_ring = check_int(per_ring, "per_ring", 1)
        grid = check_int(grid, "grid", 8)
        k = _check_number(k, "k")
        local_eps = _check_number(local_eps, "local_eps")
        if local_eps >= 0.5:
            raise ValueError(f"local_eps: expected a number in (0, 0.5), got {local_eps!r}")
        if r_p is None:
            if not all(hasattr(material, a) for a in ("sigma_a", "sigma_s_prime", "eta")):
                raise TypeError(f"material: expected a dipole material (sigma_a, sigma_s_prime, eta) when r_p is "
                                f"not given, got {type(material).__name__}")
            with torch.no_grad():
                r_p = float(chang_rp(material.sigma_a.detach(), material.sigma_s_prime.detach(),
                                     material.eta.detach(), c=_check_number(c, "c")).amax())
        r_p = _check_number(r_p, "r_p", positive=False)
        bound = r_p + math.log(0.5 / local_eps) / k if r_p > 0 else 0.0
        self.r_p, self.k, self.bound = r_p, k, bound
        self.rings, self.per_ring = rings, per_ring
        weight = ChangLocalProfile(r_p, k, bound)
        self.global_term = ImportanceSampledTranslucency(
            position, area, mask, SplitProfile(material, weight, "global"), irradiance_scale=irradiance_scale,
            translucency_mask=translucency_mask, levels=levels, max_pairs=max_pairs)
        h, w = self.global_term.shape
        if not isinstance(valid, Tensor):
            raise TypeError(f"valid: expected a torch.Tensor, got {type(valid).__name__}")
        check_shape(valid, "valid", "1,1,H,W", H=h, W=w)
        dtype = position.dtype
        self.local_weight = weight
        self.register_buffer("frames", _texel_frames(position.detach(), valid))
        if chart_id is not None:
            if not isinstance(chart_id, Tensor) or chart_id.is_floating_point() or chart_id.is_complex() or \
                    chart_id.dtype == torch.bool:
                got = chart_id.dtype if isinstance(chart_id, Tensor) else type(chart_id).__name__
                raise TypeError(f"chart_id: expected an integer tensor, got {got}")
            check_shape(chart_id, "chart_id", "1,1,H,W", H=h, W=w)
            chart_id = chart_id.to(torch.int64)
        self.register_buffer("chart_id", chart_id)
        # with charts the local filter reads chart texels of the receiver's own chart only (the global term takes
        # every other source); without, it reads gutters too (the previous, seam-darkening approximation)
        lookup = (mask if chart_id is not None else valid).to(dtype)
        if translucency_mask is not None:
            lookup = lookup * translucency_mask.to(dtype)
        self.register_buffer("lookup_mask", lookup)
        # radial quadrature grid and the pattern (build material, no gradient)
        dev = position.device  # the buffers live with the atlas (the material is there too)
        t = torch.linspace(0.0, 1.0, grid + 1, dtype=torch.float64, device=dev)
        radii = bound * t * t
        self.register_buffer("radii", radii.to(dtype))
        pieces = rings + 1
        with torch.no_grad():
            if bound > 0:
                q = self._interval_mass(radii.to(dtype)).to(torch.float64).mean(-1)  # (grid,)
            else:
                q = torch.zeros(grid, dtype=torch.float64, device=dev)
            cum = torch.cat([q.new_zeros(1), torch.cumsum(q, 0)])
            total = float(cum[-1])
            if total > 0:
                mid = 0.5 * (cum[:-1] + cum[1:]) / total
                piece = (mid * pieces).floor().clamp(0, pieces - 1).long()
                targets = (torch.arange(1, rings + 1, dtype=torch.float64, device=dev) + 0.5) / pieces * total
                j = torch.searchsorted(cum, targets).clamp(1, grid)
                frac = (targets - cum[j - 1]) / (cum[j] - cum[j - 1]).clamp_min(1e-300)
                ring_r = radii[j - 1] + frac * (radii[j] - radii[j - 1])
            else:
                piece = torch.zeros(grid, dtype=torch.long, device=dev)
                ring_r = torch.zeros(rings, dtype=torch.float64, device=dev)
        member = F.one_hot(piece, pieces).to(torch.float64).T  # (pieces, grid)
        self.register_buffer("membership", member.to(dtype))
        # pattern points (P, 2) in mm in the tangent frame, and their share of each piece (P, pieces)
        pts = [torch.zeros(1, 2, dtype=torch.float64, device=dev)]
        share = torch.zeros(1 + rings * per_ring, pieces, dtype=torch.float64, device=dev)
        share[0, 0] = 1.0
        for li in range(rings):
            ang = 2.0 * math.pi * (torch.arange(per_ring, dtype=torch.float64, device=dev) + 0.5 * (li % 2)) / per_ring
            pts.append(ring_r[li] * torch.stack([torch.cos(ang), torch.sin(ang)], -1))
            share[1 + li * per_ring: 1 + (li + 1) * per_ring, li + 1] = 1.0 / per_ring
        self.register_buffer("pattern", torch.cat(pts).to(dtype))
        self.register_buffer("point_share", share.to(dtype))

    @classmethod
    def from_atlas(cls, atlas, material: nn.Module, **kwargs) -> HybridTranslucency:
        """Build from a :class:`~torchsss.geometry.atlas.Atlas` (with its chart ids: the chart-aware split)."""
        kwargs.setdefault("chart_id", getattr(atlas, "chart_id", None))
        return cls(atlas.position, atlas.area, atlas.chart_mask, atlas.valid_mask, material, **kwargs)

    @property
    def material(self) -> nn.Module:
        """The full profile module (shared by both terms)."""
        return self.global_term.material.material

    @property
    def ring_radii(self) -> Tensor:
        """The L ring radii (mm)."""
        return self.pattern[1::self.per_ring].norm(dim=-1)

    def _interval_mass(self, radii: Tensor) -> Tensor:
        """Trapezoid integrals of :math:`2\\pi r R_d W_l^b` over the grid intervals: :math:`(grid, C)`."""
        r = radii.unsqueeze(-1)
        q = 2.0 * math.pi * r * self.material(r) * self.local_weight(r)
        return 0.5 * (q[1:] + q[:-1]) * (r[1:] - r[:-1])

    def point_weights(self) -> Tensor:
        """:math:`(P, C)` weight (mm^2 x mm^-2) of every pattern point for the current material."""
        mass = self.membership @ self._interval_mass(self.radii)  # (pieces, C)
        return self.point_share.to(mass.dtype) @ mass

    def _receiver_texels(self, receivers_uv: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Continuous pixel coordinates ``(px, py)`` of atlas uvs (v up) and their texel ``(row, col)``."""
        h, w = self.global_term.shape
        px = receivers_uv[..., 0] * w
        py = (1.0 - receivers_uv[..., 1]) * h
        return px, py, py.detach().floor().long().clamp(0, h - 1), px.detach().floor().long().clamp(0, w - 1)

    def local(self, irradiance: Tensor, receivers_uv: Tensor) -> Tensor:
        r"""Local term :math:`(B, M, C)` at receivers given by atlas uv :math:`(B, M, 2)`.

        With chart ids, a pattern point counts only if its texel lies in the receiver's chart, and its weight is
        rescaled from the planar radius of the pattern to the 3-D distance :math:`d` between the surface points the
        atlas holds at the centre and at the point: :math:`w_p\,f(d)/f(r_p)`, :math:`f = R_d W_l^b`, the integrand
        the global term leaves out for sources of the same chart.
        """
        b, _, h, w = irradiance.shape
        e = irradiance * self.lookup_mask
        if self.global_term.irradiance_scale is not None:
            e = e * self.global_term.irradiance_scale
        px, py, row, col = self._receiver_texels(receivers_uv)
        idx = (row * w + col).unsqueeze(1).expand(-1, 4, -1)
        fr = torch.gather(self.frames.flatten(2).expand(b, -1, -1), 2, idx).to(e.dtype)  # (B, 4, M)
        a, bb = self.pattern[:, 0].to(e.dtype), self.pattern[:, 1].to(e.dtype)  # (P,)
        dx = fr[:, 0, :, None] * a + fr[:, 1, :, None] * bb  # (B, M, P)
        dy = fr[:, 2, :, None] * a + fr[:, 3, :, None] * bb
        gx = 2.0 * (px.unsqueeze(-1) + dx) / w - 1.0
        gy = 2.0 * (py.unsqueeze(-1) + dy) / h - 1.0
        grid = torch.stack([gx, gy], -1)
        vals = F.grid_sample(e, grid, mode="bilinear", padding_mode="zeros", align_corners=False)  # (B, C, M, P)
        wts = self.point_weights().to(e.dtype)  # (P, C)
        if self.chart_id is None:
            return torch.einsum("bcmp,pc->bmc", vals, wts)
        # the pattern point's texel must lie in the receiver's chart
        qx = (px.unsqueeze(-1) + dx).detach().floor().long()
        qy = (py.unsqueeze(-1) + dy).detach().floor().long()
        inside = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
        charts = self.chart_id.reshape(-1)
        q_chart = charts[(qy.clamp(0, h - 1) * w + qx.clamp(0, w - 1))]  # (B, M, P)
        same = inside & (q_chart == charts[row * w + col].unsqueeze(-1))
        # the planar radius of the pattern -> the 3-D distance to the surface point read
        pos = self.global_term.position.to(e.dtype).expand(b, -1, -1, -1)
        q_pos = F.grid_sample(pos, grid, mode="bilinear", padding_mode="border", align_corners=False)
        # measured from the atlas's own point at the receiver's uv (pattern point 0, the centre), so that the
        # centre keeps its weight whatever the gap between the atlas and the receiver's G-buffer position
        q_pos = q_pos.permute(0, 2, 3, 1)  # (B, M, P, 3)
        d = (q_pos - q_pos[:, :, :1]).norm(dim=-1, keepdim=True)  # (B, M, P, 1)
        planar = self.pattern.to(e.dtype).norm(dim=-1, keepdim=True)  # (P, 1)
        f_planar = self.material(planar) * self.local_weight(planar)  # (P, C)
        f_d = self.material(d) * self.local_weight(d)  # (B, M, P, C)
        tiny = torch.finfo(e.dtype).tiny
        ratio = f_d / f_planar.clamp_min(tiny)
        return torch.einsum("bcmp,bmpc,pc->bmc", vals * same.unsqueeze(1).to(e.dtype), ratio, wts)

    def global_split(self, irradiance: Tensor, u: Tensor, receivers: Tensor, receivers_uv: Tensor | None,
                     dims: dict) -> Tensor:
        """The global term :math:`(B, M, C)` of the split.

        Every sample contributes :math:`R_d`, less :math:`R_d W_l^b` where sample and receiver lie in one chart (the
        part the local filter takes): sources on another chart (across a seam, the far side of a thin part) are
        entirely global. With ``receivers_uv`` None every pair counts as one chart: :math:`R_d (1 - W_l^b)` for all
        (the split of :class:`SurfaceLocal`, whose local term is gathered over the surface), in the same fused
        kernel.
        """
        g = self.global_term
        src_pos, src_e, inv, ds, idx = g._draw(irradiance, u, dims)
        if not is_tracing() and dims["M"] == 0:
            return src_e.new_zeros(dims["B"], 0, max(dims["C"], _material_channels(self.material) or 1))
        w = g.shape[1]
        if receivers_uv is None:
            charts = torch.zeros(self.global_term.shape[0] * w, dtype=torch.int64, device=src_e.device)
            row = col = torch.zeros(dims["B"], dims["M"], dtype=torch.int64, device=src_e.device)
        else:
            charts = self.chart_id.reshape(-1)
            _, _, row, col = self._receiver_texels(receivers_uv)

        def id_weight(r: Tensor, same: Tensor) -> Tensor:
            return 1.0 - self.local_weight(r) * same.to(r.dtype)

        # exactly 1 - W_l^b(r) [same]: the fused integrator (torchsss.ops.fused) may evaluate it in its kernel
        lw = self.local_weight
        id_weight.chang_split = (lw.r_p, lw.k, lw.bound)

        return reference_radiosity(src_pos, src_e, inv.to(src_e.dtype), receivers.to(src_e.dtype), self.material,
                                   src_distance_scale=ds, src_ids=charts[idx], dst_ids=charts[row * w + col],
                                   id_weight=id_weight, max_pairs=g.max_pairs)

    def global_everywhere(self, irradiance: Tensor, u: Tensor, receivers: Tensor) -> Tensor:
        """The global term :math:`(B, M, C)` with :math:`R_d (1 - W_l^b)` for every pair.

        The part a :class:`SurfaceLocal` leaves (the plain profile without a split); arguments as
        :meth:`ImportanceSampledTranslucency.forward`.
        """
        dims = self.global_term._check_inputs(irradiance, u, receivers)
        if self.bound <= 0:
            return self.global_term.estimate(irradiance, u, receivers, dims, profile=self.material)
        return self.global_split(irradiance, u, receivers, None, dims)

    def forward(self, irradiance: Tensor, u: Tensor, receivers: Tensor, receivers_uv: Tensor) -> Tensor:
        """:math:`B_l + B_g` :math:`(B, M, C)`; arguments as :meth:`ImportanceSampledTranslucency.forward` plus uv.

        Raises:
            TypeError, ValueError: as :meth:`ImportanceSampledTranslucency.forward`; ``receivers_uv`` not
                :math:`(B, M, 2)`.
        """
        check_tensor(receivers_uv, "receivers_uv")
        dims = self.global_term._check_inputs(irradiance, u, receivers)
        check_shape(receivers_uv, "receivers_uv", "B,M,2", B=dims["B"], M=dims["M"])
        check_finite(receivers_uv, "receivers_uv")
        if self.bound <= 0:  # no split (W_l = 0): the plain profile, which the fused kernel evaluates
            return self.global_term.estimate(irradiance, u, receivers, dims, profile=self.material)
        uv = receivers_uv.to(irradiance.dtype)
        if self.chart_id is None:
            return self.global_term(irradiance, u, receivers) + self.local(irradiance, uv)
        return self.global_split(irradiance, u, receivers, uv, dims) + self.local(irradiance, uv)
