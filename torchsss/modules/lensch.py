"""Lensch et al. 2002 as nn.Modules: irradiance atlas, local response, global response, their sum.

Everything here works on atlas-space tensors :math:`(B, C, H, W)`; the precomputation (kernel geometry,
vertex dual-basis weights, the sparse vertex-to-vertex throughput pattern) comes from
:mod:`torchsss.geometry.lensch` and is stored as buffers. The material is a submodule: the kernels
:math:`K = A_s R_d(|x_o - x_s|)` and the throughput values :math:`F_{ij} = A_i/3\\, R_d(|v_i - v_j|)` are
re-evaluated from stored distances and areas in every ``forward()``, so material parameters receive gradients
and can change per frame without a rebuild (the sparsity pattern, chosen at build time for the build
material, stays).

Heterogeneous materials (Shah eq. 7.4) enter on the source side: an irradiance modulation :math:`M_i`
multiplies the irradiance atlas, a distance multiplier :math:`M_d` (atlas) scales the distances from each
source texel (and, projected onto the vertices with the dual basis, from each source vertex), and a
translucency mask removes non-translucent texels as sources and receivers.
"""

from __future__ import annotations

import math
import warnings

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchsss._checks import check_finite, check_finite_inputs, check_shape, check_tensor, compute_dtype, is_tracing
from torchsss.geometry.lensch import (
    DenseThroughput,
    HatMoments,
    HatQuadrature,
    LocalKernelGeometry,
    Throughput,
    VertexWeights,
    _check_atlas,
    _check_kernel_size,
    _distance,
    entry_moments,
)
from torchsss.modules.blocks import in_blocks
from torchsss.modules.cache import ValueCache, material_key
from torchsss.modules.material import bulk_profile
from torchsss.ops.sparse import SparsePattern, sparse_apply_t, sparse_pattern
from torchsss.ops.sv_conv import sv_conv2d_planes
from torchsss.physics.fresnel import check_fresnel, transmittance

__all__ = ["GlobalResponse", "IrradianceAtlas", "LenschTranslucency", "LocalResponse"]


def _disk_integral(material: nn.Module, area: Tensor, scale: Tensor | None = None) -> Tensor | None:
    """:math:`\\int_{disk(A)} R_d(r M_d) dA` (mm^-2 x mm^2) for areas ``(...)`` -> ``(..., C)``.

    The self term of a texel or vertex, from the material's closed-form ``cumulative`` (the profile contract of
    :mod:`torchsss.modules.material`; None for a bare profile callable without one): sampling :math:`A R_d(0)`
    overestimates it without bound once the profile is narrower than the element (:math:`R_d(0) \\propto
    z_r^{-2}` for the dipole, infinite for Burley's), while the disk integral tends to :math:`R_{total}`, which is
    what the element really sends to itself.
    """
    cumulative = getattr(material, "cumulative", None)
    if cumulative is None:
        return None
    radius = torch.sqrt(area / math.pi).unsqueeze(-1)
    if scale is None:
        return cumulative(radius)
    md = scale.unsqueeze(-1)
    return cumulative(radius * md) / (md * md)


def _window_at(image: Tensor, k: int, index: Tensor) -> Tensor:
    """(1, 1, H, W) -> (N, k, k): the values at the sources of the windows of receivers ``index`` (0 outside)."""
    w = image.shape[-1]
    r = k // 2
    wp = w + 2 * r
    flat = F.pad(image[0, 0], (r, r, r, r)).reshape(-1)
    base = (index // w) * wp + index % w  # the window's top-left in the padded image
    cols = torch.arange(k, device=index.device)
    return torch.stack([flat[base[:, None] + (i * wp + cols)] for i in range(k)], 1)  # a kernel row at a time


class IrradianceAtlas(nn.Module):
    """Transmitted irradiance at every atlas texel from point or directional lights.

    Lights come in as tensors so that ``forward()`` exports: ``light`` :math:`(B, 4)` homogeneous positions in
    mm (w = 1: a point light at xyz; w = 0: a directional light, xyz the unit direction *towards* the light)
    and ``intensity`` :math:`(B, C)` (radiant intensity of a point light, irradiance of a directional one).

    .. math:: E = I \\max(0, n\\cdot\\omega) / d^2 \\; F_t(\\eta, n\\cdot\\omega) \\; V

    Args:
        position: :math:`(1, 3, H, W)` texel positions (mm).
        normal: :math:`(1, 3, H, W)` unit texel normals.
        valid: :math:`(1, 1, H, W)` bool, texels that carry surface (chart and filled gutter texels).
        eta: the material module (its ``eta`` is read at every call, so an edit or a gradient step on it reaches
            the Fresnel term: the one home of eta), or a fixed relative index of refraction (a number).
        fresnel: ``"exact"`` or ``"schlick"`` (Lensch uses Schlick).
    """

    def __init__(self, position: Tensor, normal: Tensor, valid: Tensor, eta: float | nn.Module = 1.3,
                 fresnel: str = "exact"):
        super().__init__()
        check_tensor(position, "position")
        dims = check_shape(position, "position", "1,3,H,W")
        check_shape(normal, "normal", "1,3,H,W", **dims)
        check_shape(valid, "valid", "1,1,H,W", **dims)
        self.fresnel = check_fresnel(fresnel, ("exact", "schlick"))
        if isinstance(eta, nn.Module):
            self.material = eta
            self._eta = None
        else:
            self.material = None
            self._eta = float(eta)
        self.register_buffer("position", position.detach().clone(), persistent=False)
        self.register_buffer("normal", normal.detach().clone(), persistent=False)
        self.register_buffer("valid", valid.to(position.dtype), persistent=False)

    @classmethod
    def from_atlas(cls, atlas, eta: float | nn.Module = 1.3, fresnel: str = "exact") -> IrradianceAtlas:
        """Build from a :class:`~torchsss.geometry.atlas.Atlas` (``eta``: the material module or a number)."""
        return cls(atlas.position, atlas.normal, atlas.valid_mask, eta, fresnel)

    @property
    def eta(self) -> Tensor | float:
        """The relative index of refraction: the material module's, or the fixed number."""
        return self._eta if self.material is None else self.material.eta

    def forward(self, light: Tensor, intensity: Tensor, visibility: Tensor | None = None) -> Tensor:
        """Irradiance atlas :math:`(B, C, H, W)`; ``visibility`` optional :math:`(B, 1, H, W)` in [0, 1]."""
        check_shape(light, "light", "B,4")
        dims = check_shape(intensity, "intensity", "B,C", B=light.shape[0])
        check_finite_inputs({"light": light, "intensity": intensity, "visibility": visibility})
        w = light[:, 3:4].view(-1, 1, 1, 1)
        xyz = light[:, :3].view(-1, 3, 1, 1)
        delta = xyz - w * self.position  # point: light - x; directional: the direction itself
        d2 = (delta * delta).sum(1, keepdim=True)
        safe = torch.where(d2 > 0, d2, torch.ones_like(d2))
        to_light = delta / torch.sqrt(safe)
        falloff = torch.where(w > 0, 1.0 / safe, torch.ones_like(safe)) * (d2 > 0)
        cos = (to_light * self.normal).sum(1, keepdim=True).clamp_min(0.0)
        eta = self.eta
        if isinstance(eta, Tensor) and eta.dim() == 1 and eta.numel() > 1:
            eta = eta.view(1, -1, 1, 1)
        ft = transmittance(cos, eta, self.fresnel)
        e = intensity.view(dims["B"], dims["C"], 1, 1) * (falloff * cos * ft * self.valid)
        if visibility is not None:
            check_shape(visibility, "visibility", "B,1,H,W", B=dims["B"], H=e.shape[-2], W=e.shape[-1])
            e = e * visibility
        return e


class LocalResponse(nn.Module):
    """Local response :math:`B^l(o) = \\sum_s K_o(s) E(s)` with :math:`K_o(s) = A_s M_i R_d(|x_o - x_s| M_d)`.

    The kernels are held for the receivers that have them only (the atlas's valid texels, 36-52% of the square:
    :class:`~torchsss.geometry.lensch.LocalKernelGeometry`'s compact form; a full geometry is compacted to the
    receivers with a source or a correction) and evaluated into the one full tap-major copy that
    :func:`~torchsss.ops.sv_conv2d_planes` reads, cached while the material is unchanged. At atlas 512 and
    k = 11 on the default scene that is 634 MB where full buffers, full kernels and the convolution's permuted
    copy of them took 1.33 GB. A module :meth:`from_atlas` without a correction, distance multiplier or mask
    relights with half of that instead (:meth:`half_planes`: the kernels are the source area times a profile of a
    symmetric distance, so one plane serves a tap and its mirror): at atlas 1024 and k = 7, 0.32 GB instead of
    0.62 GB, the frame's local response about 1.4x slower (eager), the same values up to float rounding.

    Args:
        geometry: :class:`~torchsss.geometry.lensch.LocalKernelGeometry` (distances and source areas), full or
            compact.
        material: a module mapping distances :math:`(\\ldots, 1)` mm to :math:`(\\ldots, C)` mm^-2 (e.g.
            :class:`~torchsss.DipoleMaterial`); its parameters receive gradients.
        correction: optional kernel correction added after evaluation (blending): :math:`(C, H, W, k, k)`, or
            :math:`(C, N, k, k)` on the receivers of a compact ``geometry``.
        distance_scale: optional :math:`(1, 1, H, W)` distance multiplier atlas :math:`M_d` (> 0).
        irradiance_scale: optional :math:`(1, C, H, W)` or :math:`(1, 1, H, W)` irradiance modulation :math:`M_i`.
        mask: optional :math:`(1, 1, H, W)` translucency mask (1 translucent, 0 not).
        self_term: ``"disk"`` (default) replaces the centre tap :math:`A_o R_d(0)` by the closed-form integral
            of :math:`R_d` over a disk of the texel's area (needs a dipole material; finite and -> R_total when
            the profile is far narrower than a texel); ``"point"`` keeps Lensch's point sample.
        copy: copy a compact ``geometry`` and ``correction`` into the buffers (default); ``False`` takes them as
            they are (no second copy; the caller must not change them afterwards). A full geometry is always
            compacted into new buffers.
    """

    #: Bytes of profile temporaries per block of receivers in the eager evaluation of :meth:`planes`.
    block_bytes = 8 << 20
    #: Bytes of outputs per band of rows in the frames' accumulation over the symmetric planes (:meth:`forward`).
    band_bytes = 512 << 10

    def __init__(self, geometry: LocalKernelGeometry, material: nn.Module, *, correction: Tensor | None = None,
                 distance_scale: Tensor | None = None, irradiance_scale: Tensor | None = None,
                 mask: Tensor | None = None, self_term: str = "disk", copy: bool = True):
        super().__init__()
        if not isinstance(copy, bool):
            raise TypeError(f"copy: expected a bool, got {type(copy).__name__}")
        k = self.kernel_size = int(geometry.kernel_size)
        self.material = material
        if geometry.index is None:
            dims = check_shape(geometry.distance, "geometry.distance", "H,W,k,k", k=k)
            h, w = dims["H"], dims["W"]
            live = (geometry.area != 0).flatten(2).any(-1)
            if correction is not None:
                check_shape(correction, "correction", "C,H,W,k,k", H=h, W=w, k=k)
                live = live | (correction != 0).flatten(3).any(-1).any(0)
            index = live.reshape(-1).nonzero(as_tuple=True)[0]
            dist = geometry.distance.detach().reshape(h * w, k, k)[index]
            area = geometry.area.detach().reshape(h * w, k, k)[index]
            if correction is not None:
                correction = correction.detach().reshape(correction.shape[0], h * w, k, k)[:, index]
        else:
            if geometry.shape is None:
                raise ValueError("geometry: a compact LocalKernelGeometry (index given) needs its shape (H, W)")
            h, w = (int(v) for v in geometry.shape)
            dims = check_shape(geometry.distance, "geometry.distance", "N,k,k", k=k)
            check_shape(geometry.area, "geometry.area", "N,k,k", N=dims["N"], k=k)
            check_shape(geometry.index, "geometry.index", "N", N=dims["N"])
            index = geometry.index
            dist = geometry.distance.detach().clone() if copy else geometry.distance.detach()
            area = geometry.area.detach().clone() if copy else geometry.area.detach()
            if correction is not None:
                check_shape(correction, "correction", "C,N,k,k", N=dims["N"], k=k)
                correction = correction.detach().clone() if copy else correction.detach()
        self._finish(index, h, w, dist, area, correction, distance_scale, irradiance_scale, mask, self_term)

    def _finish(self, index: Tensor, h: int, w: int, dist: Tensor | None, area: Tensor | None,
                correction: Tensor | None, distance_scale: Tensor | None, irradiance_scale: Tensor | None,
                mask: Tensor | None, self_term: str, sources: dict | None = None) -> None:
        """The buffers of both constructions: stored taps (``dist``/``area``) or ``sources`` maps to derive them."""
        k = self.kernel_size
        self.height, self.width = int(h), int(w)
        if self_term not in ("disk", "point"):
            raise ValueError(f"self_term: expected 'disk' or 'point', got {self_term!r}")
        self.self_term = self_term
        if distance_scale is not None:
            check_shape(distance_scale, "distance_scale", "1,1,H,W", H=h, W=w)
        if mask is not None:
            check_shape(mask, "mask", "1,1,H,W", H=h, W=w)
        if irradiance_scale is not None:
            check_shape(irradiance_scale, "irradiance_scale", "1,C,H,W", H=h, W=w)
        # where each texel's kernel sits in the compact list (N: none; the planes read a zero column there)
        slot = torch.full((h * w,), index.numel(), dtype=torch.int64, device=index.device)
        slot[index] = torch.arange(index.numel(), device=index.device)
        self.register_buffer("index", index)
        self.register_buffer("slot", slot, persistent=False)
        r = k // 2
        if sources is None:
            if distance_scale is not None:
                dist = dist * _window_at(distance_scale.to(dist.dtype), k, index)
            if mask is not None:
                m = mask.to(area.dtype)
                area = area * _window_at(m, k, index) * m.reshape(-1)[index][:, None, None]
            dtype = dist.dtype
            self_area = area[:, r, r].clone()
            for name in ("src_position", "src_area", "src_scale", "rec_position", "rec_mask", "offsets"):
                self.register_buffer(name, None, persistent=False)
        else:
            dtype = sources["position"].dtype
            pad = (r, r, r, r)
            self.register_buffer("src_position", F.pad(sources["position"], pad).reshape(3, -1), persistent=False)
            # the source area, 0 where the source is not valid (as local_kernel_geometry's taps)
            src_area = F.pad(sources["area"] * sources["valid"], pad).reshape(-1)
            rec_mask = None
            if mask is not None:
                m = mask[0, 0].to(dtype)
                src_area = src_area * F.pad(m, pad).reshape(-1)
                rec_mask = m.reshape(-1)[index].clone()
            self.register_buffer("src_area", src_area, persistent=False)
            self.register_buffer("src_scale", None if distance_scale is None else
                                 F.pad(distance_scale[0, 0].to(dtype), pad).reshape(-1), persistent=False)
            self.register_buffer("rec_position", sources["position"].reshape(3, -1)[:, index].T.contiguous(),
                                 persistent=False)
            self.register_buffer("rec_mask", rec_mask, persistent=False)
            wp = w + 2 * r
            ar = torch.arange(k, device=index.device)
            self.register_buffer("offsets", (ar[:, None] * wp + ar[None, :]).reshape(-1), persistent=False)
            self.register_buffer("base", (index // w) * wp + index % w, persistent=False)
            centre = self.base + (r * wp + r)
            self_area = src_area[centre] * (1.0 if rec_mask is None else rec_mask)
        self.register_buffer("distance", dist)
        self.register_buffer("area", area)
        self.register_buffer("self_scale", None if distance_scale is None else
                             distance_scale.reshape(-1)[index].to(dtype).clone())
        self.register_buffer("self_area", self_area)
        self.register_buffer("correction", correction)
        self._cache = ValueCache()
        self.register_buffer("irradiance_scale", None if irradiance_scale is None else irradiance_scale.clone())

    @classmethod
    def from_atlas(cls, atlas, kernel_size: int, material: nn.Module, *, correction: Tensor | None = None,
                   distance_scale: Tensor | None = None, irradiance_scale: Tensor | None = None,
                   mask: Tensor | None = None, self_term: str = "disk") -> LocalResponse:
        """The local response of ``atlas``'s valid texels with taps derived from the atlas's maps, not stored.

        The same kernels as ``LocalResponse(local_kernel_geometry(atlas, k, compact=True), ...)``, bit for bit
        (the same distance formula on the same positions; outside autograd each evaluates the profile through a
        table of its own range, :func:`~torchsss.modules.material.bulk_profile`, so there they agree within its
        tolerance), but the :math:`(N, k, k)` distances and areas (234 MB at atlas 1024 and k = 7) are not kept:
        every evaluation of the kernels (once per material) gathers the taps' positions and areas from the atlas's
        padded maps, block by block.

        Args:
            atlas: The :class:`~torchsss.geometry.Atlas` (its ``padding`` at least ``k // 2``).
            kernel_size: Odd ``k``.
            material: The profile module, as the constructor's.
            correction: Optional :math:`(C, N, k, k)` on the valid texels in ascending order (``blending_weights(...,
                index=...)``).
            distance_scale: Optional :math:`(1, 1, H, W)` :math:`M_d`, as the constructor's.
            irradiance_scale: Optional :math:`M_i`, as the constructor's.
            mask: Optional :math:`(1, 1, H, W)` translucency mask, as the constructor's.
            self_term: ``"disk"`` or ``"point"``, as the constructor's.

        Returns:
            The module; ``distance`` and ``area`` are None (derived when needed).

        Examples:
            >>> from torchsss.geometry import build_atlas, sphere
            >>> from torchsss.geometry.lensch import local_kernel_geometry
            >>> from torchsss.modules import DipoleMaterial
            >>> atlas = build_atlas(sphere(5.0, 2), 32, kernel_size=3)
            >>> mat = DipoleMaterial.from_preset("marble")
            >>> derived = LocalResponse.from_atlas(atlas, 3, mat)
            >>> stored = LocalResponse(local_kernel_geometry(atlas, 3, compact=True), mat)
            >>> with torch.enable_grad():  # the profile's formula (outside autograd: tables of each one's range)
            ...     bool((derived.planes() == stored.planes()).all()), derived.distance is None
            (True, True)
        """
        empty = _check_atlas(atlas)
        k = _check_kernel_size(kernel_size)
        self = cls.__new__(cls)
        nn.Module.__init__(self)
        self.kernel_size = k
        self.material = material
        h, w = empty.shape
        valid = empty.valid_mask[0, 0]
        index = valid.reshape(-1).nonzero(as_tuple=True)[0]
        if correction is not None:
            check_shape(correction, "correction", "C,N,k,k", N=index.numel(), k=k)
            correction = correction.detach()
        sources = {"position": empty.position[0].detach(), "area": empty.area[0, 0].detach(),
                   "valid": valid.to(empty.position.dtype)}
        self._finish(index, h, w, None, None, correction, distance_scale, irradiance_scale, mask, self_term,
                     sources=sources)
        return self

    def _taps(self, lo: int, hi: int) -> tuple[Tensor, Tensor]:
        """Distances (M_d applied) and source areas (mask applied) of receivers ``lo:hi``: :math:`(n, k, k)` each."""
        k = self.kernel_size
        if self.src_position is None:
            return self.distance[lo:hi], self.area[lo:hi]
        idx = self.base[lo:hi, None] + self.offsets  # (n, k*k) in the padded maps
        src = self.src_position[:, idx].permute(1, 2, 0)  # (n, k*k, 3)
        d = _distance(self.rec_position[lo:hi, None, :], src)
        area = self.src_area[idx]
        d = torch.where(area != 0, d, torch.zeros_like(d))
        if self.src_scale is not None:
            d = d * self.src_scale[idx]
        if self.rec_mask is not None:
            area = area * self.rec_mask[lo:hi, None]
        return d.reshape(-1, k, k), area.reshape(-1, k, k)

    def planes(self) -> Tensor:
        """Per-channel kernels in tap-major layout :math:`(C, k^2, H, W)` (:func:`~torchsss.ops.sv_conv2d_planes`).

        Outside autograd and tracing the compact kernels are evaluated in blocks of receivers (about 32 MB of
        profile temporaries at a time) and written into the planes; under autograd or export in one expression
        and gathered into place (a zero column for the receivers without a kernel).
        """
        k2 = self.kernel_size ** 2
        n = self.index.shape[0]
        if torch.is_grad_enabled() or is_tracing():
            comp = self._kernel_rows(0, n)
            c = comp.shape[0]
            cols = torch.cat([comp.reshape(c, n, k2), comp.new_zeros(c, 1, k2)], 1).transpose(1, 2)  # (C, k2, N+1)
            return cols.index_select(2, self.slot).reshape(c, k2, self.height, self.width)
        block = max(1, self.block_bytes // (k2 * 4 * self.self_area.element_size()))
        out = None
        profile = self._bulk_profile()
        for lo in range(0, max(n, 1), block):
            rows = self._kernel_rows(lo, min(n, lo + block), profile)
            c = rows.shape[0]
            if out is None:
                out = rows.new_zeros(c, k2, self.height * self.width)
            out[:, :, self.index[lo:lo + block]] = rows.reshape(c, -1, k2).transpose(1, 2)
        return out.view(-1, k2, self.height, self.width)

    def kernels(self) -> Tensor:
        """Per-channel kernels :math:`(C, H, W, k, k)` in gather form (:func:`~torchsss.ops.sv_conv2d`).

        The layout of :meth:`planes` turned around (a copy: for tests and inspection; frames use the planes).
        """
        k = self.kernel_size
        p = self.planes()
        return p.reshape(p.shape[0], k, k, self.height, self.width).permute(0, 3, 4, 1, 2).contiguous()

    def _bulk_profile(self):
        """The material for a no-grad evaluation of every tap (:func:`~torchsss.modules.material.bulk_profile`).

        Its range: the largest tap distance (stored taps), or the extent of the receivers, which are every texel a
        tap can read (derived taps), times the largest distance multiplier.
        """
        if torch.is_grad_enabled() or is_tracing() or self.index.numel() == 0:
            return self.material
        if self.src_position is None:
            d_max = float(self.distance.max())
        else:
            pos = self.rec_position
            d_max = float((pos.amax(0) - pos.amin(0)).norm())
            if self.src_scale is not None:
                d_max *= float(self.src_scale.max())
        return bulk_profile(self.material, d_max, self.self_area.dtype, self.index.device)

    def _kernel_rows(self, lo: int, hi: int, profile=None) -> Tensor:
        """The compact kernels of receivers ``index[lo:hi]``: :math:`(C, hi - lo, k, k)`.

        ``profile``: the material's evaluation to use (:meth:`_bulk_profile`); default the material itself.
        """
        dist, area = self._taps(lo, hi)
        k = area.unsqueeze(-1) * (self.material if profile is None else profile)(dist.unsqueeze(-1))  # (n, k, k, C)
        scale = None if self.self_scale is None else self.self_scale[lo:hi]
        disk = _disk_integral(self.material, self.self_area[lo:hi], scale) if self.self_term == "disk" else None
        if disk is not None:
            c = self.kernel_size // 2
            centre = torch.zeros_like(area)
            centre[:, c, c] = 1.0
            k = k + centre.unsqueeze(-1) * (disk - k[:, c, c]).unsqueeze(1).unsqueeze(1)
        k = k.permute(3, 0, 1, 2)
        if self.correction is not None:
            k = k + self.correction[:, lo:hi]
        return k

    def forward(self, irradiance: Tensor) -> Tensor:
        """:math:`(B, C, H, W)` irradiance atlas -> :math:`(B, C, H, W)` local radiosity.

        Raises:
            ValueError: a NaN or infinite irradiance texel (named with its index; see
                :func:`torchsss.set_validation`).
        """
        check_finite(irradiance, "irradiance")
        e = irradiance if self.irradiance_scale is None else irradiance * self.irradiance_scale
        key = material_key(self.material)
        if key is not None and self._symmetric():
            half, centre = self._cache.get((*key, self.index.device, "half"), self.half_planes)
            return self._apply_half(e, half, centre)
        planes = self._cache.get(None if key is None else (*key, self.index.device), self.planes)
        out = sv_conv2d_planes(e.transpose(0, 1), planes)  # channels as the kernel batch, the batch as channels
        return out.transpose(0, 1)

    def _symmetric(self) -> bool:
        """Whether the kernels factor as :math:`A_s P(o, s)` with a symmetric :math:`P` (taps derived from the atlas).

        True for :meth:`from_atlas` modules without a correction, a distance multiplier or a mask: there
        :math:`K_o(s) = A_s R_d(|x_o - x_s|)` and the distance is the same bits either way round.
        """
        return self.src_position is not None and self.correction is None and self.src_scale is None and \
            self.rec_mask is None

    def half_planes(self) -> tuple[Tensor, Tensor]:
        """The symmetric factor of the kernels on half the taps, and the centre taps (:meth:`forward`'s cache).

        :math:`P_t(o) = R_d(|x_o - x_{o + \\delta_t}|)` for the :math:`(k^2 - 1)/2` taps ``t`` before the centre
        (row-major), 0 unless both texels are valid, :math:`(C, (k^2 - 1)/2, H, W)`; the tap opposite ``t`` of
        receiver ``o`` is :math:`P_t(o - \\delta_t)`, so these planes hold every off-centre kernel
        :math:`K_o(s) = A_s P(o, s)` (less than half of :meth:`planes`: 0.32 GB instead of 0.62 GB at atlas 1024
        and k = 7). The centre taps (the self term) :math:`(C, H, W)`. Only for :meth:`_symmetric` modules,
        evaluated in blocks of receivers outside autograd.
        """
        k = self.kernel_size
        r = k // 2
        nh = (k * k - 1) // 2
        n = self.index.shape[0]
        hw = self.height * self.width
        wp = self.width + 2 * r
        valid = F.pad((self.slot < n).reshape(self.height, self.width), (r, r, r, r)).reshape(-1)
        ar = torch.arange(k, device=self.index.device)
        offsets = (ar[:, None] * wp + ar[None, :]).reshape(-1)[:nh]
        zero = torch.zeros(1, 1, dtype=self.self_area.dtype, device=self.index.device)
        probe = self.material(zero)
        channels, dtype = int(probe.shape[-1]), torch.promote_types(probe.dtype, self.self_area.dtype)
        half = torch.zeros(channels, nh, hw, dtype=dtype, device=self.index.device)
        centre = torch.zeros(channels, hw, dtype=dtype, device=self.index.device)
        block = max(1, self.block_bytes // (max(nh, 1) * 4 * self.self_area.element_size()))
        profile = self._bulk_profile()
        for lo in range(0, n, block):
            hi = min(n, lo + block)
            idx = self.base[lo:hi, None] + offsets  # (m, nh) in the padded maps
            d = _distance(self.rec_position[lo:hi, None, :], self.src_position[:, idx].permute(1, 2, 0))
            rd = profile(d.unsqueeze(-1))  # (m, nh, C)
            rd = torch.where(valid[idx].unsqueeze(-1), rd, torch.zeros_like(rd))
            at = self.index[lo:hi]
            half[:, :, at] = rd.permute(2, 1, 0).to(dtype)
            # the centre tap as _kernel_rows makes it: A_o R_d(0), replaced by the disk integral
            area = self.self_area[lo:hi]
            kc = area.unsqueeze(-1) * self.material(torch.zeros_like(area).unsqueeze(-1))
            disk = _disk_integral(self.material, area) if self.self_term == "disk" else None
            if disk is not None:
                kc = kc + (disk - kc)
            centre[:, at] = kc.T.to(dtype)
        return half.view(channels, nh, self.height, self.width), centre.view(channels, self.height, self.width)

    def _apply_half(self, e: Tensor, half: Tensor, centre: Tensor) -> Tensor:
        """:math:`(B, C, H, W)` -> :math:`(B, C, H, W)` with :meth:`half_planes`: every tap pair from one plane.

        :math:`B^l(o) = K_o(o) E(o) + \\sum_t P_t(o) (AE)(o + \\delta_t) + P_t(o - \\delta_t) (AE)(o - \\delta_t)`,
        :math:`AE` the irradiance times the source area; in-place multiply-accumulates over shifted slices.
        """
        check_tensor(e, "irradiance")
        out_dtype, dtype = compute_dtype(e, half)
        k = self.kernel_size
        r = k // 2
        h, w = self.height, self.width
        x = e.transpose(0, 1).to(dtype)  # (C, B, H, W): channel c of the irradiance meets channel c's kernels
        half, centre = half.to(dtype), centre.to(dtype)
        wp = w + 2 * r
        area = self.src_area.view(h + 2 * r, wp)[r:r + h, r:r + w].to(dtype)
        ae = x * area
        aep = F.pad(ae, (r, r, r, r))
        out = centre.unsqueeze(1) * x
        # bands of rows whose outputs stay in the cache over the k^2 - 1 passes (1.4x faster than whole planes)
        band = max(1, self.band_bytes // max(1, out[:, :, :1].numel() * out.element_size()))
        for y0 in range(0, h, band):
            y1 = min(h, y0 + band)
            for t in range(half.shape[1]):
                i, j = divmod(t, k)
                p = half[:, t].unsqueeze(1)
                out[:, :, y0:y1].addcmul_(p[:, :, y0:y1], aep[:, :, y0 + i:y1 + i, j:j + w])  # source o + delta_t
                dy, dx = r - i, r - j  # the source at o - delta_t = o + (dy, dx), dy >= 0
                x0, x1 = max(0, -dx), w - max(0, dx)
                z1 = min(y1, h - dy)
                if z1 > y0:
                    out[:, :, y0:z1, x0:x1].addcmul_(p[:, :, y0 + dy:z1 + dy, x0 + dx:x1 + dx],
                                                     ae[:, :, y0 + dy:z1 + dy, x0 + dx:x1 + dx])
        return out.transpose(0, 1).to(out_dtype)


class GlobalResponse(nn.Module):
    """Global response through the sparse vertex-to-vertex throughput (Lensch eq. 10-12).

    :math:`E^g_i = \\sum_{texels} \\tilde\\psi_i A E`; :math:`B^g_j = \\sum_i E^g_i F_{ij}`;
    :math:`B^g(x) = \\sum_\\nu \\beta_\\nu(x) B^g_\\nu`, with :math:`F_{ij} = A_i/3\\, R_d(|v_i - v_j| M_{d,i})`.

    Args:
        weights: :class:`~torchsss.geometry.lensch.VertexWeights` (vertex ids, dual weights, barycentrics).
        throughput: :class:`~torchsss.geometry.lensch.Throughput` (pattern, distances, source areas), or a
            :class:`~torchsss.geometry.lensch.DenseThroughput` (an :math:`(N, N)` matrix: the product per frame is
            one batched matrix product per channel; see :func:`~torchsss.geometry.lensch.throughput_layout`).
        material: the profile module (shared with the local response).
        valid: :math:`(1, 1, H, W)` texels to reconstruct on.
        distance_scale: optional :math:`(1, 1, H, W)` :math:`M_d` atlas, projected onto the source vertices.
        method: ``"auto"``, ``"csr"`` or ``"scatter"`` (see :func:`torchsss.ops.sparse.sparse_apply_t`).
        hat: optional :class:`~torchsss.geometry.lensch.HatQuadrature` of a sparse throughput: every entry is
            integrated over the source's hat (its moment rule, and the near entries, the self entries among them,
            term by term, :math:`F_{ij} = \\sum_t w_t R_d(d_t M_{d,i})`) instead of sampled at the source vertex
            (and the self entries' disk integral); see :func:`~torchsss.geometry.lensch.hat_quadrature`. The
            module keeps the hats' moments per vertex (:class:`~torchsss.geometry.lensch.HatMoments`) and derives
            each entry's rule when the values are evaluated; ``distance`` and ``source_area`` are then None.
        copy: copy the throughput's distances and source areas into the buffers (default); ``False`` takes them
            as they are (the caller must not change them afterwards: :func:`~torchsss.pipelines.build_lensch`
            hands its throughput over).
    """

    #: vertex pairs of a dense throughput whose values are evaluated at once outside autograd (about 100 MB of the
    #: profile's temporaries)
    value_block = 1 << 20

    def __init__(self, weights: VertexWeights, throughput: Throughput | DenseThroughput, material: nn.Module,
                 valid: Tensor, *, distance_scale: Tensor | None = None, method: str = "auto",
                 hat: HatQuadrature | None = None, copy: bool = True):
        super().__init__()
        if not isinstance(copy, bool):
            raise TypeError(f"copy: expected a bool, got {type(copy).__name__}")
        if not isinstance(throughput, (Throughput, DenseThroughput)):
            raise TypeError("throughput: expected a torchsss.geometry.lensch.Throughput or DenseThroughput, got "
                            f"{type(throughput).__name__}")
        self.dense = isinstance(throughput, DenseThroughput)
        if self.dense and hat is not None:
            raise ValueError("hat: expected None with a DenseThroughput (the hat quadrature indexes a sparse "
                             "throughput's entries), got a HatQuadrature")
        dims = check_shape(weights.vertex_ids, "weights.vertex_ids", "1,3,H,W")
        check_shape(valid, "valid", "1,1,H,W", H=dims["H"], W=dims["W"])
        self.material = material
        self.method = method
        self.num_vertices = int(throughput.num_vertices)
        n = self.num_vertices
        if self.dense:
            check_shape(throughput.distance, "throughput.distance", "N,N", N=n)
            check_shape(throughput.keep, "throughput.keep", "N,N", N=n)
            check_shape(throughput.source_area, "throughput.source_area", "N", N=n)
        self.register_buffer("vertex_ids", weights.vertex_ids.reshape(1, 1, -1).clone(), persistent=False)
        self.register_buffer("dual", weights.dual.reshape(1, 1, -1).clone(), persistent=False)
        self.register_buffer("bary", weights.bary.clone(), persistent=False)
        self.register_buffer("valid", valid.to(weights.bary.dtype), persistent=False)
        # the texels that carry anything, for the per-frame gathers and scatters outside tracing (the traced and
        # exported graph keeps the whole-image form): texels with a dual weight (vertex_irradiance) and valid
        # texels (reconstruct); int32 vertex ids, (3, T)
        ids3 = weights.vertex_ids.reshape(3, -1)
        gather = self.valid.reshape(-1).nonzero().squeeze(1)
        scatter = (weights.dual.reshape(3, -1) != 0).any(0).nonzero().squeeze(1)
        self.register_buffer("_gather_texels", gather, persistent=False)
        self.register_buffer("_gather_ids", ids3.index_select(1, gather).to(torch.int32), persistent=False)
        self.register_buffer("_gather_bary", weights.bary.reshape(3, -1).index_select(1, gather), persistent=False)
        self.register_buffer("_scatter_texels", scatter, persistent=False)
        self.register_buffer("_scatter_ids", ids3.index_select(1, scatter).reshape(-1), persistent=False)
        self.register_buffer("_scatter_dual", weights.dual.reshape(3, -1).index_select(1, scatter), persistent=False)
        dist = throughput.distance.clone() if copy else throughput.distance
        vertex_md = None
        if distance_scale is not None:
            check_shape(distance_scale, "distance_scale", "1,1,H,W", H=dims["H"], W=dims["W"])
            num = torch.zeros(self.num_vertices, dtype=dist.dtype, device=dist.device)
            den = torch.zeros_like(num)
            flat = self.dual.reshape(3, -1)  # (3, H*W) after the reshape of (1, 3, H, W)
            ids = weights.vertex_ids.reshape(3, -1)
            md = distance_scale.reshape(1, -1).to(dist.dtype).expand_as(flat)
            num.scatter_add_(0, ids.reshape(-1), (flat * md).reshape(-1))
            den.scatter_add_(0, ids.reshape(-1), flat.reshape(-1))
            vertex_md = torch.where(den > 0, num / torch.where(den > 0, den, torch.ones_like(den)),
                                    torch.ones_like(den)).clamp_min(1e-6)
            if self.dense:
                dist = dist * vertex_md[:, None]
            else:
                dist = dist * vertex_md[throughput.rows]
        self.register_buffer("source_area", throughput.source_area.clone() if copy else throughput.source_area)
        self._cache = ValueCache()
        if self.dense:
            self.register_buffer("distance", dist)
            self.register_buffer("keep", throughput.keep.clone() if copy else throughput.keep, persistent=False)
            # the kept diagonal entries (vertex ids): their disk integrals replace A_i/3 R_d(0)
            self.register_buffer("diagonal_index", throughput.keep.diagonal().nonzero()[:, 0], persistent=False)
            for name in ("hat_entries", "hat_term_entry", "hat_distance", "hat_weight", "_h_vertices", "_h_centroid",
                         "_h_covariance", "_h_area", "_h_scale"):
                self.register_buffer(name, None, persistent=False)
            self._hat_d_max = 0.0
            self.pattern = None
            return
        geometry = {"_h_vertices": None, "_h_centroid": None, "_h_covariance": None, "_h_area": None,
                    "_h_scale": None}
        self._hat_d_max = 0.0
        if hat is not None:
            if not isinstance(hat, HatQuadrature):
                raise TypeError(f"hat: expected a torchsss.geometry.lensch.HatQuadrature, got {type(hat).__name__}")
            nnz = throughput.rows.numel()
            if hat.centroid_distance.shape != (nnz,) or (hat.entries.numel() and int(hat.entries.max()) >= nnz):
                raise ValueError(f"hat: expected the quadrature of this throughput ({nnz} entries), got one of "
                                 f"{hat.centroid_distance.shape[0]}")
            if not isinstance(hat.moments, HatMoments) or hat.moments.vertices.shape != (n, 3):
                raise ValueError(f"hat: expected the HatMoments of this throughput's {n} vertices (hat_quadrature's "
                                 f"moments), got {type(hat.moments).__name__}")
            dt, dev = dist.dtype, dist.device
            scale = None if vertex_md is None else vertex_md.to(dt)
            # the moment rule's distance and variances are derived per block of entries from the hats' centroids and
            # covariances (:func:`entry_moments`) whenever the values are evaluated: three numbers per vertex kept
            # instead of four per entry (the distance, the two variances, the source area: 97 MB on the default
            # scene's 6.4M entries at atlas 1024, 135 MB on the 40 mm teapot's 8.4M)
            area = torch.zeros(n, dtype=dt, device=dev)
            area[throughput.rows] = throughput.source_area.to(dt)  # every entry of row i holds A_i / 3
            geometry = {"_h_vertices": hat.moments.vertices.to(dt).clone(),
                        "_h_centroid": hat.moments.centroid.to(dt).clone(),
                        "_h_covariance": hat.moments.covariance.to(dt).clone(), "_h_area": area, "_h_scale": scale}
            # the largest distance the rule evaluates: the range of the profile's table outside autograd
            moments = HatMoments(geometry["_h_vertices"], geometry["_h_centroid"], geometry["_h_covariance"])
            for lo in range(0, nnz, 1 << 18):
                rows_b = throughput.rows[lo:lo + (1 << 18)]
                r, rv, tv = entry_moments(moments, rows_b, throughput.cols[lo:lo + (1 << 18)])
                far = torch.maximum(r + rv.sqrt(), (r * r + tv).sqrt())
                if scale is not None:
                    far = far * scale[rows_b]
                self._hat_d_max = max(self._hat_d_max, float(far.max()))
                del r, rv, tv, far
            dist = None  # the entries' distances are the rule's (derived)
            hd = hat.distance.to(dt)
            if scale is not None:  # the source's M_d, as for the sampled entries
                hd = hd * scale[throughput.rows[hat.entries][hat.term_entry]]
            self.source_area = None  # per vertex in _h_area
        for name, value in geometry.items():
            self.register_buffer(name, value, persistent=False)
        self.register_buffer("distance", dist)
        self.register_buffer("hat_entries", None if hat is None else hat.entries.clone(), persistent=False)
        # int32 (index_add takes it; 43 MB less on the default scene's 10.7M terms at atlas 1024), int64 in graphs
        self.register_buffer("hat_term_entry", None if hat is None else hat.term_entry.to(torch.int32),
                             persistent=False)
        self.register_buffer("hat_distance", None if hat is None else hd, persistent=False)
        hw = None if hat is None else hat.weight.to(hd.dtype)
        self.register_buffer("hat_weight", hw.clone() if copy and hw is not None and hw is hat.weight else hw,
                             persistent=False)
        # the positions of the diagonal entries: their disk integrals are evaluated there only (one per vertex,
        # not per nonzero: on 6M nonzeros the closed-form cumulative for all of them took 8 s of a first frame)
        self.register_buffer("diagonal_index", (throughput.rows == throughput.cols).nonzero()[:, 0],
                             persistent=False)
        # the pattern in int32 (the entries' rows and columns, the CSR row pointers of F^T and the permutation that
        # sorts the entries by column): 97 MB for the default scene's 6.4M entries where the int64 SparsePattern,
        # with F^T's column indices, held 194 MB; F^T's CSR matrix (the frames' product) is built from them once
        # per material (:meth:`vertex_radiosity`), the int64 pattern only for the differentiable and exported paths
        rows, cols = throughput.rows, throughput.cols
        if n >= 2**31 or rows.numel() >= 2**31:
            raise ValueError(f"throughput: expected fewer than 2^31 vertices and entries, got {n} and {rows.numel()}")
        sparse_pattern(rows[:0], cols[:0], n, n)  # the index checks of the pattern (types, shapes, devices)
        if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= n or int(cols.min()) < 0
                             or int(cols.max()) >= n):
            raise ValueError(f"throughput: expected rows and cols in [0, {n}), got rows in [{int(rows.min())}, "
                             f"{int(rows.max())}] and cols in [{int(cols.min())}, {int(cols.max())}]")
        counts = torch.bincount(cols, minlength=n) if cols.numel() else cols.new_zeros(n)
        cols32 = cols.to(torch.int32)
        self.register_buffer("_p_t_perm", torch.argsort(cols32, stable=True).to(torch.int32), persistent=False)
        self.register_buffer("_p_rows", rows.to(torch.int32), persistent=False)
        self.register_buffer("_p_cols", cols32, persistent=False)
        self.register_buffer("_p_t_crow", torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)]).to(torch.int32),
                             persistent=False)
        self.pattern = None
        self._csr_cache = ValueCache()

    @property
    def nnz(self) -> int:
        """The throughput's kept entries (a dense throughput's kept pairs)."""
        return int(self.keep.sum()) if self.dense else int(self._p_rows.shape[0])

    def _pattern(self) -> SparsePattern:
        """The throughput's :class:`~torchsss.ops.sparse.SparsePattern` (int64, made from the int32 buffers)."""
        rows, perm = self._p_rows.long(), self._p_t_perm.long()
        n = self.num_vertices
        return SparsePattern(rows, self._p_cols.long(), n, n, self._p_t_crow.long(), rows.index_select(0, perm), perm)

    def _csr(self, x_dtype: torch.dtype) -> tuple[list[Tensor], torch.dtype, torch.dtype]:
        """The CSR matrices of :math:`F^T`, one per channel, from the current values; the output and compute dtypes.

        As :func:`~torchsss.ops.sparse.sparse_apply_t`'s cached CSR product for a vertex irradiance of ``x_dtype``:
        the values in the compute dtype permuted into column order, int32 indices (F^T's column indices, the
        entries' rows in that order, made here); the values themselves are not kept.
        """
        values = self.throughput_values()
        out_dtype, dtype = compute_dtype(torch.empty(0, dtype=x_dtype), values)
        vals = values.to(dtype).index_select(0, self._p_t_perm)
        del values
        col = self._p_rows.index_select(0, self._p_t_perm)
        n = self.num_vertices

        def csr(v: Tensor) -> Tensor:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)
                return torch.sparse_csr_tensor(self._p_t_crow, col, v, size=(n, n), check_invariants=False)

        if vals.dim() == 1:
            return [csr(vals)], out_dtype, dtype
        return [csr(vals[:, ch].contiguous()) for ch in range(vals.shape[1])], out_dtype, dtype

    def vertex_irradiance(self, irradiance: Tensor) -> Tensor:
        """:math:`(B, C, H, W)` -> :math:`(B, N, C)` vertex irradiance :math:`E^g` (Lensch eq. 10), scatter_add."""
        b, c = irradiance.shape[:2]
        if not is_tracing():  # only the texels with a dual weight: (B, C, T) gathered, (B, C, 3 T) added
            e = irradiance.reshape(b, c, -1).index_select(2, self._scatter_texels)
            src = (e.unsqueeze(2) * self._scatter_dual).reshape(b, c, -1)
            idx = self._scatter_ids.reshape(1, 1, -1).expand(b, c, -1)
        else:
            src = (irradiance.reshape(b, c, 1, -1) * self.dual.reshape(1, 1, 3, -1)).reshape(b, c, -1)
            idx = self.vertex_ids.reshape(1, 1, -1).expand(b, c, -1)
        out = torch.zeros(b, c, self.num_vertices, dtype=src.dtype, device=src.device)
        return out.scatter_add(2, idx, src).transpose(1, 2)

    def throughput_values(self) -> Tensor:
        """:math:`(nnz, C)` values :math:`A_i/3\\, R_d(d_{ij})` from the current material (dense: :math:`(C, N, N)`).

        With a hat quadrature (``hat``) every entry is its moment rule and its near entries are
        :math:`\\sum_t w_t R_d(d_t)` (:class:`~torchsss.geometry.lensch.HatQuadrature`); otherwise the diagonal
        entries (present unless the throughput was built with ``zero_diagonal``) use the disk integral of
        :math:`R_d` over the vertex area instead of :math:`A_i/3\\, R_d(0)` (see :class:`LocalResponse`).
        """
        if self.dense:
            return self._dense_values()
        if self.hat_entries is not None:
            profile = self.material
            if not (torch.is_grad_enabled() or is_tracing() or self.nnz == 0):
                profile = bulk_profile(self.material, self._hat_d_max, self._h_area.dtype, self._h_area.device)
            vals = self._blocks(lambda lo, hi: self._moment_rule(lo, hi, profile), self.nnz)
            near = self.hat_values(vals.shape[-1], vals.dtype)
            if vals.requires_grad or near.requires_grad or is_tracing():
                return vals.index_copy(0, self.hat_entries, near)
            return vals.index_copy_(0, self.hat_entries, near)  # in place: no second copy of every value
        profile = self._bulk_profile(self.distance)
        vals = self._blocks(lambda lo, hi: self._sampled(lo, hi, profile), self.distance.shape[0])
        disk = _disk_integral(self.material, self.source_area.index_select(0, self.diagonal_index))
        if disk is None:
            return vals
        return vals.index_copy(0, self.diagonal_index, disk)

    def _dense_values(self) -> Tensor:
        """The dense throughput's values :math:`(C, N, N)`, 0 where an entry was not kept.

        Outside autograd and tracing in blocks of source rows (``value_block`` pairs, 1M), written into one output.
        """
        n = self.num_vertices
        profile = self._bulk_profile(self.distance)

        def rows(lo: int, hi: int) -> Tensor:
            f = self.source_area[lo:hi, None, None] * profile(self.distance[lo:hi].unsqueeze(-1))
            return torch.where(self.keep[lo:hi].unsqueeze(-1), f, torch.zeros_like(f)).permute(2, 0, 1)

        if torch.is_grad_enabled() or is_tracing():
            vals = rows(0, n)
        else:
            vals = in_blocks(rows, n, max(1, self.value_block // max(n, 1)), dim=1)
        if self.diagonal_index.numel():
            disk = _disk_integral(self.material, self.source_area.index_select(0, self.diagonal_index))
            if disk is not None:
                c = vals.shape[0]
                flat = self.diagonal_index * (n + 1)
                vals = vals.reshape(c, n * n).index_copy(1, flat, disk.transpose(0, 1).to(vals.dtype)).reshape(c, n, n)
        return vals

    def _bulk_profile(self, *distances: Tensor):
        """The material for a no-grad evaluation of ``distances`` (:func:`~torchsss.modules.material.bulk_profile`)."""
        if torch.is_grad_enabled() or is_tracing() or not all(d.numel() for d in distances):
            return self.material
        d_max = max(float(d.max()) for d in distances)
        return bulk_profile(self.material, d_max, distances[0].dtype, distances[0].device)

    def _sampled(self, lo: int, hi: int, profile=None) -> Tensor:
        """The entries ``lo:hi`` sampled at the source vertex, :math:`A_i/3\\, R_d(d_{ij})`: :math:`(hi - lo, C)`."""
        profile = self.material if profile is None else profile
        return self.source_area[lo:hi].unsqueeze(-1) * profile(self.distance[lo:hi].unsqueeze(-1))

    def _moment_rule(self, lo: int, hi: int, profile=None) -> Tensor:
        """The moment rule of the entries ``lo:hi``, :math:`(hi - lo, C)`.

        :math:`A_i/3\\,[\\tfrac12 R(r + \\sigma_r) + \\tfrac12 R(|r - \\sigma_r|) + R(\\sqrt{r^2 + \\sigma_t^2})
        - R(r)]`, with :math:`r`, :math:`\\sigma_r^2`, :math:`\\sigma_t^2` derived from the hats' moments
        (:func:`~torchsss.geometry.lensch.entry_moments`) and times the source's :math:`M_d`.
        """
        profile = self.material if profile is None else profile
        rows = self._p_rows[lo:hi].long()
        moments = HatMoments(self._h_vertices, self._h_centroid, self._h_covariance)
        r, radial, transverse = entry_moments(moments, rows, self._p_cols[lo:hi].long())
        sr = radial.sqrt()
        d = torch.stack([r, r + sr, (r - sr).abs(), (r * r + transverse).sqrt()])
        if self._h_scale is not None:  # the source's M_d
            d = d * self._h_scale[rows]
        f = profile(d.unsqueeze(-1))
        return self._h_area[rows].unsqueeze(-1) * (0.5 * (f[1] + f[2]) + f[3] - f[0])

    @staticmethod
    def _blocks(fn, n: int) -> Tensor:
        """``fn(lo, hi)`` over ``0:n``: one call under autograd, tracing or export, blocks of 256k rows otherwise.

        (The profile's temporaries of every entry at once reached 1-2 GB on a 7M-entry throughput; blocks of 1M
        rows of the moment rule, four profile evaluations a row, still took 0.3 GB.)
        """
        if torch.is_grad_enabled() or is_tracing():
            return fn(0, n)
        return in_blocks(fn, n, 1 << 18)

    def hat_values(self, channels: int, dtype: torch.dtype) -> Tensor:
        """:math:`(E, C)` the near entries of the hat quadrature, :math:`\\sum_t w_t R_d(d_t)`.

        Outside autograd and tracing the terms are evaluated in blocks (256k terms, ~15 MB of profile
        temporaries, at a time); under autograd or export in one expression.
        """
        n = self.hat_entries.shape[0]
        total = self.hat_distance.shape[0]
        if torch.is_grad_enabled() or is_tracing():
            terms = self.hat_weight.unsqueeze(-1) * self.material(self.hat_distance.unsqueeze(-1))
            out = torch.zeros(n, terms.shape[-1], dtype=terms.dtype, device=terms.device)
            return out.index_add(0, self.hat_term_entry.long(), terms)  # the exported ScatterND takes int64
        out = torch.zeros(n, channels, dtype=dtype, device=self.hat_distance.device)
        profile = self._bulk_profile(self.hat_distance)
        block = 1 << 18
        for lo in range(0, total, block):
            hi = min(total, lo + block)
            terms = self.hat_weight[lo:hi].unsqueeze(-1) * profile(self.hat_distance[lo:hi].unsqueeze(-1))
            out.index_add_(0, self.hat_term_entry[lo:hi], terms.to(dtype))
        return out

    def vertex_radiosity(self, irradiance: Tensor, vertex_irradiance: Tensor | None = None) -> Tensor:
        """:math:`(B, C, H, W)` irradiance atlas -> :math:`(B, N, C)` vertex radiosity :math:`B^g`.

        ``vertex_irradiance``: :meth:`vertex_irradiance` of ``irradiance`` when the caller has it already.
        """
        eg = self.vertex_irradiance(irradiance) if vertex_irradiance is None else vertex_irradiance
        key = material_key(self.material)
        if key is not None and not self.dense and self.method in ("auto", "csr") and eg.device.type != "meta":
            # relighting a fixed material: only F^T's CSR matrices are kept (sparse_apply_t's csr path, its values)
            check_tensor(eg, "vertex_irradiance")
            mats, out_dtype, dtype = self._csr_cache.get((*key, self.vertex_ids.device, eg.dtype),
                                                         lambda: self._csr(eg.dtype))
            if eg.dim() == 3 and eg.shape[1] == self.num_vertices and eg.shape[2] == len(mats):
                x = eg.to(dtype)
                y = torch.stack([mats[ch] @ x[:, :, ch].t() for ch in range(x.shape[-1])], dim=-1)
                return y.permute(1, 0, 2).to(out_dtype)
        values = self._cache.get(None if key is None else (*key, self.vertex_ids.device), self.throughput_values)
        if self.dense:  # B_j = sum_i E_i F_ij per channel: (C, B, N) @ (C, N, N)
            dtype = torch.promote_types(eg.dtype, values.dtype)
            out = torch.bmm(eg.permute(2, 0, 1).to(dtype), values.to(dtype))
            return out.permute(1, 2, 0)
        return sparse_apply_t(eg, self._pattern(), values, method=self.method)

    def reconstruct(self, vertex_values: Tensor) -> Tensor:
        """:math:`(B, N, C)` vertex values -> :math:`(B, C, H, W)` atlas by barycentric interpolation."""
        b, _, c = vertex_values.shape
        h, w = self.bary.shape[-2:]
        if not is_tracing():  # only the valid texels, scattered into the image
            vals = vertex_values.index_select(1, self._gather_ids.reshape(-1)).reshape(b, 3, -1, c)
            texel = (vals * self._gather_bary.unsqueeze(-1)).sum(1).transpose(1, 2)  # (B, C, T)
            out = texel.new_zeros(b, c, h * w).index_copy(2, self._gather_texels, texel)
            return out.view(b, c, h, w)
        idx = self.vertex_ids.reshape(1, -1, 1).expand(b, -1, c)
        vals = torch.gather(vertex_values, 1, idx)  # (B, 3*H*W, C)
        vals = vals.transpose(1, 2).reshape(b, c, 3, h, w)
        return (vals * self.bary.unsqueeze(1)).sum(2) * self.valid

    def forward(self, irradiance: Tensor) -> Tensor:
        """:math:`(B, C, H, W)` irradiance atlas -> :math:`(B, C, H, W)` global radiosity atlas.

        Raises:
            ValueError: a NaN or infinite irradiance texel (named with its index; see
                :func:`torchsss.set_validation`).
        """
        check_finite(irradiance, "irradiance")
        return self.reconstruct(self.vertex_radiosity(irradiance))


class LenschTranslucency(nn.Module):
    """The composed method: radiosity atlas :math:`B = B^l + B^d + B^{g0}` and, on request, the camera image.

    With blending (``direct`` given) the throughput must have been built with a zero diagonal and the local
    kernels carry the blending correction. Without it, ``detail=True`` (the unblended default of
    :func:`~torchsss.pipelines.lensch.build_lensch`) splits the irradiance into the part the vertex hats carry,
    :math:`\\tilde E = \\sum_i E^g_i \\psi_i` (the dual projection, reconstructed on the atlas), and the detail
    :math:`E - \\tilde E`: the throughput (with its near entries integrated over the hats,
    :class:`GlobalResponse`'s ``hat``) answers :math:`\\tilde E` at every distance, the local kernels answer the
    detail (a shadow edge, a texture) within their window, :math:`B = B^g + B^l(E - \\tilde E)`, so that no part of
    the near field is counted twice whatever the window's size (a smooth irradiance has no detail: the local term
    vanishes). ``detail=False`` returns :math:`B^l(E) + B^g` as given (Lensch's plain sum, which counts the window's
    near field in both terms; kept so that what the split buys is measurable).

    Args:
        local: :class:`LocalResponse`.
        global_response: :class:`GlobalResponse` (shares ``local.material``).
        direct: optional :math:`(C, 3, H, W)` blending weights :math:`w_\\nu` of Lensch §5.4.
        albedo: optional :math:`(1, C, H, W)` surface texture :math:`T_\\rho` (Lensch eq. 13-14), > 0.
        albedo_at_vertices: :math:`(N, C)` :math:`T_\\rho(v_i)`, required with ``albedo``.
        detail: the local kernels act on the irradiance's detail :math:`E - \\tilde E` (unblended only).
    """

    def __init__(self, local: LocalResponse, global_response: GlobalResponse, *, direct: Tensor | None = None,
                 albedo: Tensor | None = None, albedo_at_vertices: Tensor | None = None, detail: bool = False):
        super().__init__()
        if not isinstance(detail, bool):
            raise TypeError(f"detail: expected a bool, got {type(detail).__name__}")
        if detail and direct is not None:
            raise ValueError("detail: expected False with blending (direct given): the blending weights already "
                             "split the near field, got True")
        self.detail = detail
        self.local = local
        self.global_response = global_response
        self.register_buffer("direct", None if direct is None else direct.detach().clone())
        if (albedo is None) != (albedo_at_vertices is None):
            raise ValueError("albedo: expected both albedo and albedo_at_vertices or neither")
        self.register_buffer("albedo", albedo)
        self.register_buffer("albedo_at_vertices", albedo_at_vertices)

    @property
    def material(self) -> nn.Module:
        """The shared material module."""
        return self.local.material

    def split(self, irradiance: Tensor) -> tuple[Tensor, Tensor]:
        """The radiosity in its two parts: ``(atlas, vertex)``, :math:`(B, C, H, W)` and :math:`(B, N, C)`.

        :meth:`forward` is ``atlas + global_response.reconstruct(vertex)``: the local kernels' part (and nothing
        else) on the atlas, the vertex radiosity (with blending's direct part) on the vertices, so that a caller can
        interpolate the vertex part at any surface point of the hat mesh instead of through the atlas's texels
        (:class:`~torchsss.pipelines.lensch.LenschRenderer` does, at every pixel). Without a surface texture only.

        Raises:
            ValueError: the module has a surface texture (``albedo``), and as :meth:`forward`.
        """
        if self.albedo is not None:
            raise ValueError("split: expected a module without albedo (the textured radiosity is an atlas product), "
                             "got one with albedo")
        check_tensor(irradiance, "irradiance")
        check_shape(irradiance, "irradiance", "B,C,H,W", H=self.local.height, W=self.local.width)
        check_finite(irradiance, "irradiance")
        g = self.global_response
        eg = g.vertex_irradiance(irradiance)
        vert = self._vertex(irradiance, eg)
        local = self.local(irradiance - g.reconstruct(eg)) if self.detail else self.local(irradiance)
        return local, vert

    def _vertex(self, irradiance: Tensor, eg: Tensor) -> Tensor:
        """:math:`(B, N, C)` vertex radiosity, with blending's direct part."""
        g = self.global_response
        vert = g.vertex_radiosity(irradiance, eg)
        if self.direct is not None:
            b, c = irradiance.shape[:2]
            src = (irradiance.reshape(b, c, 1, -1) * self.direct.reshape(1, c, 3, -1)).reshape(b, c, -1)
            idx = g.vertex_ids.reshape(1, 1, -1).expand(b, c, -1)
            bd = torch.zeros(b, c, g.num_vertices, dtype=src.dtype, device=src.device).scatter_add(2, idx, src)
            vert = vert + bd.transpose(1, 2)
        return vert

    def forward(self, irradiance: Tensor) -> Tensor:
        """:math:`(B, C, H, W)` irradiance atlas -> :math:`(B, C, H, W)` radiosity atlas.

        Raises:
            TypeError: a non-floating ``irradiance``.
            ValueError: an atlas of another size, a NaN or infinite texel (named with its index; see
                :func:`torchsss.set_validation`).
        """
        check_tensor(irradiance, "irradiance")
        h, w = self.local.height, self.local.width
        check_shape(irradiance, "irradiance", "B,C,H,W", H=h, W=w)
        check_finite(irradiance, "irradiance")
        g = self.global_response
        eg = g.vertex_irradiance(irradiance)
        vert = self._vertex(irradiance, eg)
        if self.albedo is not None:
            vert = vert / self.albedo_at_vertices.unsqueeze(0)
            glob = g.reconstruct(vert) * self.albedo
        else:
            glob = g.reconstruct(vert)
        if self.detail:
            return self.local(irradiance - g.reconstruct(eg)) + glob
        return self.local(irradiance) + glob
