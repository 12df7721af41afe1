"""Caustics mapping (Shah 2007, ch. 5) as an nn.Module: refract a light-view grid, find the receivers, splat.

Every texel of the refractor's light-view G-buffer is one vertex of Shah's *refractive grid* (§5.3.2). For each
covered grid point :math:`x_f` (front surface, the layer nearest to the light) :class:`CausticMap`

1. takes the incident direction of the light, :math:`i = x_f - x_L` for a point light and :math:`i = -\\omega_L`
   for a directional one (``light`` is homogeneous, see :meth:`CausticMap.forward`);
2. refracts it at the front normal, :math:`t_1 = \\text{refract}(i, n_f, 1/\\eta_c)`, with one index of refraction
   per channel (dispersion, Shah Fig. 5.13: every channel follows its own ray);
3. ``mode="double"`` (double-surface refraction, Wyman 2005): finds where :math:`t_1` leaves the object through
   the back surface (the farthest layer seen from the light): ``back="search"`` iterates
   :func:`~torchsss.ops.newton_raphson.newton_raphson_intersect` in the back-positions texture (starting from
   :math:`d_0 = 0`, whose first update is the distance to the back point of the same texel); ``back="wyman"``
   takes Wyman's cheap estimate :math:`d_V = |x_b - x_f|` at the same texel. The back normal at
   :math:`x_b = x_f + d\\, t_1` is read from the back-normal texture (bilinear, renormalised) and the ray refracts
   out, :math:`t_2 = \\text{refract}(t_1, n_b, \\eta_c)`. Rays that are totally internally reflected at the back
   surface are **dropped** (their light is not followed further; with ``fresnel=True`` the partial internal
   reflections are dropped as well, so the map holds the light transmitted through both surfaces only).
   Absorption: :math:`I = I_0 e^{-K_a d}` (Shah eq. 5.7) with :math:`d` the path inside the object.
   ``mode="single"`` (one refracting surface, e.g. water): :math:`t_1` goes straight to the receivers and the
   absorption acts over the distance from the surface to the receiver (Shah §5.3.5).
   ``mode="reflect"`` (reflective caustics, Shah Fig. 5.12): one specular bounce, :math:`r = \\text{reflect}(i,
   n_f)`, the same for all channels, no absorption;
4. intersects the outgoing ray with the receivers' light-view positions texture (Newton-Raphson / Shah's
   estimator, :func:`~torchsss.ops.newton_raphson.newton_raphson_intersect`; rays that leave the texture or miss
   every receiver are lost, as in Shah; so is a ray whose search *starts* over an empty texel, since the first
   lookup is the receiver seen through the ray's origin: a receiver with holes under the refractor loses the
   rays that leave the refractor above a hole, wherever they would land);
5. deposits the flux of the grid point into the caustic map, which shares the receivers' texture resolution and
   the light's ``view_proj``: ``splat="beam"`` (default) spreads it over the footprint of the grid texel's beam,
   interpolated between the hit points of the neighbouring grid points
   (:func:`~torchsss.ops.caustic_splat.splat_caustic_beams`: the binned irradiance, smooth where beams spread and
   sharp at a focus; glass sphere at grid 256: 0.7-2.6% relative RMSE against the binned exact irradiance);
   ``splat="gaussian"`` splats a fixed Gaussian at the hit point (:func:`~torchsss.ops.caustic_splat.
   splat_caustics`, Shah §5.3.6; gaps and moire where beams spread, blurred foci: 5-45% on the same sphere). Both
   conserve energy. In eager mode with batch 1 only the covered grid points are traced (traced graphs keep all).

**Flux per grid point** (``flux="texel"``, the default, physical): a grid texel is a pencil of light of
cross-section :math:`A_\\perp` (the texel's footprint on the plane perpendicular to the light's line of sight
through :math:`x_f`, from ``view_proj``: :math:`A_\\perp = (4 / H W) / |\\nabla x_{ndc} \\times \\nabla y_{ndc}|`),
so it carries the power :math:`\\Phi = E_\\perp A_\\perp` of a directional light of irradiance :math:`E_\\perp`
(W/mm² perpendicular to the light) or :math:`\\Phi = I A_\\perp / |x_f - x_L|^2` of a point light of intensity
:math:`I` (W/sr). The surface's :math:`N \\cdot L` does not appear: the texel's surface area is
:math:`A_\\perp / (N \\cdot L)`, and its irradiance :math:`E_\\perp (N \\cdot L)`, whose product is
:math:`\\Phi`. With ``fresnel=True`` the flux is multiplied by the exact unpolarised Fresnel transmittance of
each interface (reflectance of the mirror for ``mode="reflect"``). The sum of the caustic map is then the power
that reaches the receivers (within the map), in the unit of ``intensity`` times mm² (or sr).
``flux="shah"`` is Shah's eq. 5.6 literally: :math:`\\Phi_i = I_0 (N_i \\cdot L_i) / V`, :math:`V` the number of
covered grid points, a brightness normalised against the grid resolution whose total is :math:`I_0` times the
mean :math:`N \\cdot L` over the refractor (not a power: a texel seen at a grazing angle carries the same power
through the grid as one seen head-on, so the :math:`N \\cdot L` factor undercounts the rim).

**Output**: the caustic map :math:`(B, C, H, W)` holds *flux per texel* of the light-view map (not irradiance).
The irradiance on a receiver at texel :math:`k` is :math:`\\Phi_k \\cos\\theta_k / A_{\\perp,k}`, with
:math:`\\theta_k` the angle between the receiver normal and the light's line of sight (the receiver normal is
not an input here).
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import torch
from kornia.filters import gaussian_blur2d
from torch import Tensor, nn

from torchsss._checks import (
    as_float_tensor,
    cast,
    check_devices,
    check_finite,
    check_finite_inputs,
    check_positive,
    check_shape,
    check_tensor,
    is_tracing,
    skip_value_checks,
)
from torchsss.modules.search import NewtonRaphsonSearch
from torchsss.ops.caustic_splat import default_kernel_size, splat_caustic_beams, splat_caustics
from torchsss.ops.newton_raphson import lookup_positions
from torchsss.ops.refraction import reflect, refract
from torchsss.physics.fresnel import fresnel_reflectance, fresnel_transmittance

__all__ = ["CausticMap"]

_MODES = ("double", "single", "reflect")
_BACK = ("search", "wyman")
_FLUX = ("texel", "shah")
_METHODS = ("shah", "newton")
_SPLATS = ("beam", "gaussian")


def _channels(value: object, name: str, positive: bool) -> Tensor:
    t = as_float_tensor(value, name).detach().clone()
    t = t.reshape(-1) if t.dim() <= 1 else t
    if t.dim() != 1 or t.numel() < 1:
        raise ValueError(f"{name}: expected a number or a 1-D sequence of C >= 1 values, got shape {tuple(t.shape)}")
    bad = ~torch.isfinite(t) | ((t <= 0) if positive else (t < 0))
    if bool(bad.any()):
        raise ValueError(f"{name}: expected finite values {'> 0' if positive else '>= 0'}, got {t.tolist()}")
    return t


def _unit(v: Tensor) -> Tensor:
    """Unit vectors over the last axis; zero vectors stay zero (finite gradients).

    Scale-safe, as :func:`~torchsss.ops.refraction.refract`: divided by the largest absolute component before the
    norm, so normals of any non-zero length work (``sum(v * v)`` underflows near 1e-20 in float32).
    """
    m = v.abs().amax(-1, keepdim=True)
    v = v / torch.where(m > 0, m, 1.0)
    n2 = (v * v).sum(-1, keepdim=True)
    return v / torch.sqrt(torch.where(n2 > 0, n2, 1.0))


def _flat(img: Tensor) -> Tensor:
    """(B, C, H, W) -> (B, H*W, C)."""
    return img.flatten(2).transpose(1, 2)


class CausticMap(nn.Module):
    """Light-view caustic map of a refractive (or reflective) object over receivers (Shah 2007, ch. 5).

    See the module docstring for the algorithm, the flux per grid point and the output's unit.

    Args:
        ior: index of refraction of the object over the outside, a number or one per channel :math:`(C,)`
            (dispersion). Used for refraction and Fresnel (and the mirror's Fresnel reflectance).
        absorption: :math:`K_a` in mm^-1 (>= 0), a number or :math:`(C,)`; Shah eq. 5.7.
        mode: ``"double"`` (front and back surface), ``"single"`` (front surface only) or ``"reflect"``.
        back: ``"search"`` (iterated search in the back-positions texture) or ``"wyman"`` (:math:`d_V`).
        iterations: updates of the receiver search, >= 0.
        method: ``"shah"`` or ``"newton"`` for the receiver search (see
            :func:`~torchsss.ops.newton_raphson.newton_raphson_intersect`); Newton solves a planar receiver in one
            step.
        back_iterations: updates of the back-surface search (``back="search"``), >= 0.
        back_method: method of the back-surface search. The default ``"shah"`` stays on the object: Newton's
            tangent steps on the steep rim of a curved back surface overshoot past the silhouette, where the
            lookup misses and the ray is dropped (measured on a glass sphere: Newton loses every grid point
            beyond 0.875 R, a quarter of them; Shah's estimator with 12 updates finds all of them within 0.1 mm).
        sigma_px: standard deviation of the Gaussian splats, in caustic-map texels (``splat="gaussian"``).
        kernel_size: fixed splat window (default :math:`2 \\lceil 3\\sigma \\rceil + 1`; ``splat="gaussian"``).
        fresnel: weight by the exact Fresnel transmittance of each interface (reflectance for ``"reflect"``).
        flux: ``"texel"`` (power through each grid texel, default) or ``"shah"`` (eq. 5.6).
        lowpass_sigma_px: optional Gaussian low-pass of the caustic map (texels, kornia ``gaussian_blur2d`` with
            reflected borders; 0 = off), the smoothing Shah applies against splat gaps.
        splat: ``"beam"`` (default): every grid texel's flux is spread over its beam's footprint on the receiver
            (:func:`~torchsss.ops.caustic_splat.splat_caustic_beams`: the piecewise-bilinear interpolation of the
            neighbouring grid points' hit points, ``subdivisions``:sup:`2` sub-points per texel with box splats of
            their own footprint): the binned irradiance, smooth at the default grid and sharp at a focus.
            ``"gaussian"``: Shah's fixed Gaussian point splats (``sigma_px``, ``kernel_size``).
        subdivisions: sub-points per grid texel and axis of the beam splats (>= 1).
        max_stretch_px: neighbouring grid points whose hit points lie farther apart than this (caustic-map
            texels) are not one beam (beam splats).

    Raises:
        TypeError, ValueError: options of the wrong type or out of range (naming the option). ``forward`` raises
            TypeError/ValueError naming the input for non-tensor, non-floating or complex inputs, inputs on
            different devices, wrong shapes, and (in eager mode) a non-finite ``light`` or ``intensity``.

    Examples:
        >>> m = CausticMap(ior=[1.50, 1.52, 1.54], absorption=0.01)
        >>> tuple(m.ior.shape), tuple(m.absorption.shape), m.mode, m.kernel_size
        ((3,), (1,), 'double', 7)
    """

    def __init__(
        self,
        ior: float | Sequence[float] | Tensor = 1.5,
        absorption: float | Sequence[float] | Tensor = 0.0,
        *,
        mode: str = "double",
        back: str = "search",
        iterations: int = 5,
        method: str = "newton",
        back_iterations: int = 12,
        back_method: str = "shah",
        sigma_px: float = 1.0,
        kernel_size: int | None = None,
        fresnel: bool = False,
        flux: str = "texel",
        lowpass_sigma_px: float = 0.0,
        splat: str = "beam",
        subdivisions: int = 4,
        max_stretch_px: float = 32.0,
    ) -> None:
        super().__init__()
        for name, value, allowed in (("mode", mode, _MODES), ("back", back, _BACK), ("method", method, _METHODS),
                                     ("back_method", back_method, _METHODS), ("flux", flux, _FLUX),
                                     ("splat", splat, _SPLATS)):
            if not isinstance(value, str) or value not in allowed:
                raise ValueError(f"{name}: expected one of {allowed}, got {value!r}")
        for name, value, lo in (("iterations", iterations, 0), ("back_iterations", back_iterations, 0),
                                ("subdivisions", subdivisions, 1)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise TypeError(f"{name}: expected an int >= {lo}, got {type(value).__name__}")
            if value < lo:
                raise ValueError(f"{name}: expected an int >= {lo}, got {value}")
        if isinstance(max_stretch_px, bool) or not isinstance(max_stretch_px, numbers.Real):
            raise TypeError(f"max_stretch_px: expected a real number > 0, got {type(max_stretch_px).__name__}")
        if not 0.0 < float(max_stretch_px) < float("inf"):
            raise ValueError(f"max_stretch_px: expected a finite number > 0, got {max_stretch_px!r}")
        if not isinstance(fresnel, bool):
            raise TypeError(f"fresnel: expected a bool, got {type(fresnel).__name__}")
        k_default = default_kernel_size(sigma_px)  # validates sigma_px
        if kernel_size is not None:
            if isinstance(kernel_size, bool) or not isinstance(kernel_size, numbers.Integral):
                raise TypeError(f"kernel_size: expected an int >= 1 or None, got {type(kernel_size).__name__}")
            if kernel_size < 1:
                raise ValueError(f"kernel_size: expected an int >= 1 or None, got {kernel_size}")
        self.mode, self.back, self.flux, self.splat = mode, back, flux, splat
        self.subdivisions, self.max_stretch_px = int(subdivisions), float(max_stretch_px)
        #: The receiver search (:class:`~torchsss.modules.NewtonRaphsonSearch`, ``iterations`` x ``method``).
        self.search = NewtonRaphsonSearch(int(iterations), method)
        #: The back-surface search (``back="search"``; ``back_iterations`` x ``back_method``).
        self.back_search = NewtonRaphsonSearch(int(back_iterations), back_method)
        self.sigma_px = float(sigma_px)
        self.kernel_size = int(kernel_size) if kernel_size is not None else k_default
        self.fresnel = fresnel
        lp = float(lowpass_sigma_px) if isinstance(lowpass_sigma_px, (int, float)) and not isinstance(
            lowpass_sigma_px, bool) else None
        if lp is None or not (lp >= 0 and lp < float("inf")):
            raise ValueError(f"lowpass_sigma_px: expected a finite number >= 0, got {lowpass_sigma_px!r}")
        self.lowpass_sigma_px = lp
        self.register_buffer("ior", _channels(ior, "ior", positive=True))
        self.register_buffer("absorption", _channels(absorption, "absorption", positive=False))

    @property
    def iterations(self) -> int:
        """Updates of the receiver search (held by :attr:`search`)."""
        return self.search.iterations

    @property
    def method(self) -> str:
        """Method of the receiver search (held by :attr:`search`)."""
        return self.search.method

    @property
    def back_iterations(self) -> int:
        """Updates of the back-surface search (held by :attr:`back_search`)."""
        return self.back_search.iterations

    @property
    def back_method(self) -> str:
        """Method of the back-surface search (held by :attr:`back_search`)."""
        return self.back_search.method

    # -- validation ----------------------------------------------------------------------------------------------
    def _check(self, front_position, front_normal, front_mask, back_position, back_normal, back_mask,
               receiver_position, light, intensity, view_proj) -> None:
        named = (("front_position", front_position), ("front_normal", front_normal),
                 ("back_position", back_position), ("back_normal", back_normal),
                 ("receiver_position", receiver_position), ("light", light), ("intensity", intensity),
                 ("view_proj", view_proj))
        for name, x in named:
            check_tensor(x, name)
        for name, x in (("front_mask", front_mask), ("back_mask", back_mask)):
            if not isinstance(x, Tensor):
                raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
            if x.is_complex():
                raise TypeError(f"{name}: expected a bool or real tensor, got dtype {x.dtype}")
        # devices before anything reads tensor data (the masks included)
        check_devices({**dict(named), "front_mask": front_mask, "back_mask": back_mask})
        if is_tracing():
            return
        dims = check_shape(front_position, "front_position", "B,3,H,W")
        check_shape(front_normal, "front_normal", "B,3,H,W", **dims)
        check_shape(front_mask, "front_mask", "B,1,H,W", **dims)
        check_shape(back_position, "back_position", "B,3,H,W", **dims)
        check_shape(back_normal, "back_normal", "B,3,H,W", **dims)
        check_shape(back_mask, "back_mask", "B,1,H,W", **dims)
        check_shape(receiver_position, "receiver_position", "B,3,Hr,Wr", B=dims["B"])
        check_shape(light, "light", "B,4", B=dims["B"])
        c = check_shape(intensity, "intensity", "B,C", B=dims["B"])["C"]
        check_shape(view_proj, "view_proj", "B,4,4", B=dims["B"])
        for name, buf in (("ior", self.ior), ("absorption", self.absorption)):
            if buf.numel() not in (1, c):
                raise ValueError(f"intensity: expected C = 1 or C = {name}'s {buf.numel()} channels, got C = {c}")
        if skip_value_checks(light, intensity, view_proj):
            return
        if not bool(torch.isfinite(light).all()):
            raise ValueError("light: expected finite values, got a non-finite entry")
        if not bool(((light[:, 3] == 0) | (light[:, 3] == 1)).all()):
            raise ValueError(f"light: expected w = 0 (directional) or 1 (point), got {light[:, 3].tolist()}")
        check_positive(view_proj.abs().sum((-2, -1)), "view_proj")
        # a NaN intensity would silently give an all-zero map (the splat drops non-finite flux)
        check_finite(intensity, "intensity")
        # a covered texel with a NaN position or normal would silently drop out of the map
        check_finite_inputs({"front_position": front_position, "front_normal": front_normal}, where=front_mask != 0)
        if self.mode == "double":
            check_finite_inputs({"back_position": back_position, "back_normal": back_normal}, where=back_mask != 0)

    # -- forward -------------------------------------------------------------------------------------------------
    def forward(
        self,
        front_position: Tensor,
        front_normal: Tensor,
        front_mask: Tensor,
        back_position: Tensor,
        back_normal: Tensor,
        back_mask: Tensor,
        receiver_position: Tensor,
        light: Tensor,
        intensity: Tensor,
        view_proj: Tensor,
    ) -> Tensor:
        """Caustic map :math:`(B, C, H_r, W_r)` of flux per texel in the light's view.

        Args:
            front_position: :math:`(B, 3, H, W)` light-view positions of the refractor's nearest layer (mm).
            front_normal: :math:`(B, 3, H, W)` its normals (any length, either orientation).
            front_mask: :math:`(B, 1, H, W)` bool (or 0/1) grid points covered by the refractor.
            back_position: :math:`(B, 3, H, W)` positions of the farthest layer (``mode="double"``; ignored
                otherwise but shape-checked).
            back_normal: :math:`(B, 3, H, W)` normals of the farthest layer.
            back_mask: :math:`(B, 1, H, W)` coverage of the farthest layer.
            receiver_position: :math:`(B, 3, H_r, W_r)` light-view positions texture of the receivers (the
                refractor not rendered into it); non-finite texels hold no receiver. Sets the map's size.
            light: :math:`(B, 4)` homogeneous light: ``(x, y, z, 1)`` a point light at xyz (mm), ``(dx, dy, dz,
                0)`` a directional light, xyz the unit direction *towards* the light.
            intensity: :math:`(B, C)` finite radiant intensity of a point light or perpendicular irradiance of a
                directional one (``flux="shah"``: Shah's :math:`I_0`).
            view_proj: :math:`(B, 4, 4)` world-to-clip matrix of the light view that rendered all the textures
                (its lines of sight must pass through the point light / run along the directional light).

        Returns:
            :math:`(B, C, H_r, W_r)` flux per caustic-map texel, in the dtype of ``front_position``.
        """
        self._check(front_position, front_normal, front_mask, back_position, back_normal, back_mask,
                    receiver_position, light, intensity, view_proj)
        dtype = front_position.dtype
        b = front_position.shape[0]
        hg, wg = front_position.shape[-2], front_position.shape[-1]
        c = intensity.shape[1]
        ior = cast(self.ior, dtype).expand(c) if self.ior.numel() == 1 else cast(self.ior, dtype)
        k_a = cast(self.absorption, dtype).expand(c) if self.absorption.numel() == 1 else cast(self.absorption, dtype)
        view_proj = cast(view_proj, dtype)

        mask = _flat(front_mask)[..., 0] != 0  # (B, N)
        p = _flat(front_position)
        n_f = _flat(cast(front_normal, dtype))
        ok = mask & torch.isfinite(p).all(-1) & torch.isfinite(n_f).all(-1)
        p = torch.where(ok[..., None], p, 0.0)
        n_f = torch.where(ok[..., None], n_f, 1.0)
        n = p.shape[1]

        # incident direction and power through each grid texel
        w_l = light[:, 3].to(dtype).view(b, 1, 1)
        xyz = light[:, :3].to(dtype).view(b, 1, 3)
        inc = w_l * p - xyz  # point: x - x_L; directional: -omega
        dist2 = (inc * inc).sum(-1)
        inc_u = _unit(inc)
        cos_i = -(inc_u * _unit(n_f)).sum(-1)
        n_f = torch.where((cos_i < 0)[..., None], -n_f, n_f)  # face the light
        cos_i = cos_i.abs()
        if self.flux == "texel":
            clip = torch.matmul(p, view_proj[:, :, :3].transpose(1, 2)) + view_proj[:, None, :, 3]
            cw = clip[..., 3:4]
            cw = torch.where(cw != 0, cw, 1.0)
            a = view_proj[:, None, :, :3]  # (B, 1, 4, 3)
            gx = (a[:, :, 0] - clip[..., 0:1] / cw * a[:, :, 3]) / cw
            gy = (a[:, :, 1] - clip[..., 1:2] / cw * a[:, :, 3]) / cw
            cross = torch.linalg.cross(gx, gy)
            jac = torch.sqrt((cross * cross).sum(-1))
            area = (4.0 / (hg * wg)) / torch.where(jac > 0, jac, 1.0)
            falloff = torch.where(w_l[..., 0] > 0, 1.0 / torch.where(dist2 > 0, dist2, 1.0),
                                  torch.ones_like(dist2))
            power = (area * falloff * (jac > 0))[..., None] * cast(intensity, dtype)[:, None, :]  # (B, N, C)
        else:
            count = cast(ok, dtype).sum(-1).clamp_min(1.0).view(b, 1, 1)
            power = cos_i[..., None] / count * cast(intensity, dtype)[:, None, :]
        power = power * ok[..., None]
        n_grid = n
        compact = None
        if b == 1 and not is_tracing():
            # eager: trace the covered grid points only (data-dependent size; traced graphs keep every point)
            compact = ok[0].nonzero()[:, 0]
            p, n_f, inc_u, cos_i, power, ok = (x.index_select(1, compact) for x in (p, n_f, inc_u, cos_i, power, ok))
            n = int(compact.numel())

        # ---- the outgoing rays, one per (grid point, channel) -------------------------------------------------
        exp_c = (b, n, c, 3)
        if self.mode == "reflect":
            out_dir = reflect(inc_u, n_f)[:, :, None, :].expand(exp_c)
            origin = p[:, :, None, :].expand(exp_c)
            weight = fresnel_reflectance(cos_i[..., None], ior) if self.fresnel else torch.ones_like(power)
            alive = ok[..., None].expand(b, n, c)
            inside_len = torch.zeros_like(power)
        else:
            t1, tir1 = refract(inc_u[:, :, None, :], n_f[:, :, None, :], 1.0 / ior)  # (B, N, C, 3)
            weight = fresnel_transmittance(cos_i[..., None], ior) if self.fresnel else torch.ones_like(power)
            alive = ok[..., None] & ~tir1
            if self.mode == "single":
                origin, out_dir = p[:, :, None, :].expand(exp_c), t1
                inside_len = torch.zeros_like(power)
            else:
                origin, out_dir, d_in, found, tir2, n_b = self.through_back(
                    p, t1, back_position, back_normal, back_mask, view_proj, ior
                )
                alive = alive & found & ~tir2
                if self.fresnel:
                    w2 = fresnel_transmittance((t1 * n_b).sum(-1).abs(), 1.0 / ior)
                else:
                    w2 = torch.ones_like(d_in)
                inside_len = d_in
                weight = weight * w2

        d_r, hit = self.search(
            origin.reshape(b, n * c, 3), out_dir.reshape(b, n * c, 3), cast(receiver_position, dtype), view_proj
        )
        d_r = d_r.reshape(b, n, c)
        alive = alive & hit.reshape(b, n, c)
        if self.mode == "single":
            inside_len = d_r  # Shah: a single surface (water) attenuates over the way to the receiver
        q = origin + d_r[..., None] * out_dir
        q = torch.where(alive[..., None], q, 0.0)
        flux = power * weight * torch.exp(-k_a * inside_len)
        flux = torch.where(alive, flux, 0.0)
        if compact is not None:
            q = q.new_zeros(b, n_grid, c, 3).index_copy(1, compact, q)
            flux = flux.new_zeros(b, n_grid, c).index_copy(1, compact, flux)
            alive = alive.new_zeros(b, n_grid, c).index_copy(1, compact, alive)
            n = n_grid
        size = (receiver_position.shape[-2], receiver_position.shape[-1])
        if self.splat == "beam":
            out = splat_caustic_beams(q.reshape(b, hg, wg, c, 3), flux.reshape(b, hg, wg, c),
                                      alive.reshape(b, hg, wg, c), view_proj, size, self.subdivisions,
                                      max_stretch_px=self.max_stretch_px,
                                      coverage=torch.isfinite(receiver_position).all(1, keepdim=True))
        else:
            out = splat_caustics(q, flux, alive, view_proj, size, self.sigma_px, self.kernel_size)
        if self.lowpass_sigma_px > 0:
            # Shah's optional low-pass of the caustic map (kornia; reflected borders keep the flux on the map, up to
            # the mirrored texels at the edge)
            k = default_kernel_size(self.lowpass_sigma_px)
            out = gaussian_blur2d(out, (k, k), (self.lowpass_sigma_px, self.lowpass_sigma_px), border_type="reflect")
        return out

    def through_back(
        self, p: Tensor, t1: Tensor, back_position: Tensor, back_normal: Tensor, back_mask: Tensor,
        view_proj: Tensor, ior: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Where rays refracted into the object leave it through the back layer (double-surface refraction).

        The back-surface step of :meth:`forward` (``back="search"`` or ``"wyman"``), also used for the camera view
        of the refractor (:func:`~torchsss.pipelines.caustics.render_caustics`).

        Args:
            p: :math:`(B, N, 3)` entry points on the front layer (mm).
            t1: :math:`(B, N, C, 3)` unit directions inside the object, one per channel.
            back_position: :math:`(B, 3, H, W)` the back layer seen through ``view_proj`` (whose lines of sight pass
                through the rays' source).
            back_normal: :math:`(B, 3, H, W)` its normals.
            back_mask: :math:`(B, 1, H, W)` its coverage.
            view_proj: :math:`(B, 4, 4)` world-to-clip matrix of that view.
            ior: :math:`(C,)` index of the object over the outside.

        Returns:
            ``(x_b, t2, d, found, tir, n_b)``: exit points :math:`(B, N, C, 3)`, exit directions (zero where
            ``tir``), path lengths inside :math:`(B, N, C)`, the mask of rays whose exit point was found on the back
            layer, the mask of total internal reflection there, and the unit back normals :math:`(B, N, C, 3)`.
        """
        b, n, c = t1.shape[0], t1.shape[1], t1.shape[2]
        exp_c = (b, n, c, 3)
        dtype = p.dtype
        bmask = back_mask != 0
        nan = torch.full_like(back_position, float("nan"))
        back_tex = torch.where(bmask, cast(back_position, dtype), cast(nan, dtype))
        origin = p[:, :, None, :].expand(exp_c)
        if self.back == "search":
            d, found = self.back_search(origin.reshape(b, n * c, 3), t1.reshape(b, n * c, 3), back_tex, view_proj)
            d, found = d.reshape(b, n, c), found.reshape(b, n, c)
        else:
            # the back point of the same texel: the lookup at the front point's own projection (its texel centre;
            # the points may be a compacted subset of the grid)
            pb, found = lookup_positions(p, back_tex, view_proj)
            dv = pb - p
            d = torch.sqrt((dv * dv).sum(-1).clamp_min(0.0))
            d = torch.where(found, d, 0.0)[..., None].expand(b, n, c)
            found = found[..., None].expand(b, n, c)
        x_b = origin + d[..., None] * t1
        normal_tex = torch.where(bmask, cast(back_normal, dtype), cast(nan, dtype))
        n_b, hit = lookup_positions(x_b.reshape(b, n * c, 3), normal_tex, view_proj)
        n_b = _unit(n_b.reshape(exp_c))
        hit = hit.reshape(b, n, c) & ((n_b * n_b).sum(-1) > 0)
        t2, tir2 = refract(t1, n_b, ior)
        return x_b, t2, d, found & hit, tir2 & found & hit, n_b
