"""Per-channel lookup tables of a radial profile over [0, r_max], linearly interpolated: an opt-in speed path.

The nodes are spaced uniformly in :math:`t = \\sqrt{r / r_{max}}` by default (``warp="sqrt"``), which puts more
nodes near r = 0 where the dipole bends on the scale of :math:`z_r`; ``warp="linear"`` spaces them uniformly in r.
Beyond :math:`r_{max}` the table returns 0 (the profile is truncated there, as splats are). The lookup is a
gather plus a lerp, differentiable with respect to the table values (so material gradients flow through a
table built from a differentiable profile) and exportable to ONNX.

Two layouts: per-channel ranges (each channel's nodes span its own :math:`r_{max}`), or a shared range (all
channels span the largest :math:`r_{max}`, ``shared_range=True``). With a shared range and distances of shape
:math:`(..., 1)` one index serves all channels and the lookup gathers whole rows, about 3-4x faster; channels
with a short range then get fewer nodes inside it (measured in ``benchmarks/``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsss._checks import as_float_tensor, check_nonnegative, check_positive, check_tensor, is_tracing

__all__ = ["BULK_MIN_VALUES", "BULK_TOLERANCE", "ProfileTable", "build_profile_table", "bulk_profile",
           "fitted_profile_table", "lookup_profile_table", "profile_table_error"]

_WARPS = ("sqrt", "linear")


@dataclass
class ProfileTable:
    """A sampled radial profile.

    Attributes:
        values: :math:`(N, C)` profile values at the nodes (mm^-2).
        r_max: :math:`(C,)` table range per channel (mm).
        warp: ``"sqrt"`` or ``"linear"`` node spacing.
        shared_range: all channels share one range (``r_max`` is constant), enabling the row-gather lookup.
    """

    values: Tensor
    r_max: Tensor
    warp: str
    shared_range: bool = False

    @property
    def size(self) -> int:
        """Number of nodes N."""
        return int(self.values.shape[0])


def _check_warp(warp: str) -> None:
    if warp not in _WARPS:
        raise ValueError(f"warp: expected one of {_WARPS}, got {warp!r}")


def _node_radii(r_max: Tensor, size: int, warp: str) -> Tensor:
    t = torch.linspace(0.0, 1.0, size, dtype=r_max.dtype, device=r_max.device).unsqueeze(-1)
    return r_max * (t * t if warp == "sqrt" else t)


def build_profile_table(
    profile: Callable[[Tensor], Tensor],
    r_max: Tensor,
    size: int = 1024,
    warp: str = "sqrt",
    shared_range: bool = False,
) -> ProfileTable:
    """Sample ``profile`` at ``size`` nodes per channel over :math:`[0, r_{max}]`.

    Args:
        profile: maps distances :math:`(N, C)` in mm to values :math:`(N, C)`, e.g.
            ``lambda r: dipole_rd(r, sigma_a, sigma_s_prime, eta)`` or a :class:`~torchsss.DipoleMaterial`.
        r_max: :math:`(C,)` range per channel in mm (> 0), e.g. from :func:`~torchsss.physics.r_max`.
        size: number of nodes N (>= 2).
        warp: node spacing, ``"sqrt"`` (default) or ``"linear"``.
        shared_range: span every channel over ``r_max.max()`` (faster lookup of :math:`(..., 1)` distances).

    Returns:
        A :class:`ProfileTable`; its values keep the autograd graph of ``profile``.

    Examples:
        >>> from torchsss.physics import dipole_rd
        >>> tab = build_profile_table(lambda r: dipole_rd(r, 0.01, 1.0), torch.tensor([20.0]), size=256)
        >>> tab.values.shape
        torch.Size([256, 1])
    """
    r_max = check_tensor(r_max, "r_max")
    if r_max.dim() != 1:
        raise ValueError(f"r_max: expected shape (C,), got {tuple(r_max.shape)}")
    check_positive(r_max, "r_max")
    if isinstance(size, bool) or not isinstance(size, int) or size < 2:
        raise ValueError(f"size: expected an int >= 2, got {size!r}")
    _check_warp(warp)
    if shared_range:
        r_max = r_max.amax().expand(r_max.shape).clone()
    nodes = _node_radii(r_max, size, warp)
    values = profile(nodes)
    if values.shape != nodes.shape:
        raise ValueError(f"profile: expected output shape {tuple(nodes.shape)} for input {tuple(nodes.shape)}, "
                         f"got {tuple(values.shape)}")
    return ProfileTable(values=values, r_max=r_max, warp=warp, shared_range=shared_range)


def lookup_profile_table(r: Tensor, table: ProfileTable) -> Tensor:
    """Linearly interpolate ``table`` at distances ``r``.

    Args:
        r: distances in mm, :math:`(..., C)` or :math:`(..., 1)` (>= 0).
        table: from :func:`build_profile_table`, with C channels.

    With ``warp="sqrt"`` the first segment :math:`[0, r_{max}/(N-1)^2]` is interpolated linearly in
    :math:`r^2` (the other segments linearly in :math:`\\sqrt{r}`), so the slope at r = 0 is 0, as for any
    radial profile smooth at the origin, instead of :math:`-\\infty`. float16/bfloat16 tables are interpolated
    in float32 and the result cast back.

    Returns:
        :math:`(..., C)`, 0 beyond each channel's :math:`r_{max}`; dtype of ``table.values``.

    Examples:
        >>> tab = ProfileTable(torch.tensor([[2.0], [1.0], [0.0]]), torch.tensor([2.0]), "linear")
        >>> lookup_profile_table(torch.tensor([[0.5], [1.5], [3.0]]), tab).flatten().tolist()
        [1.5, 0.5, 0.0]
    """
    r = as_float_tensor(r, "r")
    check_nonnegative(r, "r", allow_inf=True)
    values = table.values
    n, c = values.shape
    if r.dim() == 0 or r.shape[-1] not in (1, c):
        raise ValueError(f"r: expected shape (..., {c}) or (..., 1) for a {c}-channel table, got {tuple(r.shape)}")
    # float16/bfloat16 tables are interpolated in float32: node indices above 2048 (256 for bfloat16) are not
    # representable in the reduced formats, and neither are the positions between them.
    work = torch.float32 if values.dtype in (torch.float16, torch.bfloat16) else values.dtype
    vals = values.to(work)
    r = r.to(work)
    r_max = table.r_max.to(work)
    if table.shared_range and r.shape[-1] == 1:
        r_max = r_max[:1]  # one index per distance, whole rows gathered
        if not (torch.is_grad_enabled() and (r.requires_grad or vals.requires_grad)) and not is_tracing():
            return _lookup_rows(r, vals, float(r_max[0]), table.warp).to(values.dtype)
    x = (r / r_max).clamp(0.0, 1.0)
    if table.warp == "sqrt":
        # First segment [0, r_max/(n-1)^2]: linear in r^2 rather than in sqrt(r). A radial profile that is smooth
        # on the plane is even in r, so this is exact to second order and has the true slope 0 at r = 0 (linear
        # in sqrt(r) would have slope -inf there). sqrt is masked before the op (double-where trick).
        q = x * float((n - 1) ** 2)  # r / r_1, r_1 the first node after 0
        first = q < 1.0
        root = torch.sqrt(torch.where(first, torch.ones_like(x), x))
        pos = torch.where(first, torch.zeros_like(x), root * (n - 1))
        i0 = torch.floor(pos).clamp(max=n - 2)
        frac = torch.where(first, q * q, pos - i0)
    else:
        pos = x * (n - 1)
        i0 = torch.floor(pos).clamp(max=n - 2)
        frac = pos - i0
    if table.shared_range and r.shape[-1] == 1:
        rows = i0.to(torch.int64).reshape(-1)
        shape = (*r.shape[:-1], c)
        v0 = vals.index_select(0, rows).reshape(shape)
        v1 = vals.index_select(0, rows + 1).reshape(shape)
    else:
        channel = torch.arange(c, device=values.device)
        idx0 = i0.to(torch.int64) * c + channel  # (..., C) flat index of the left node
        flat = vals.reshape(-1)
        v0 = flat.index_select(0, idx0.reshape(-1)).reshape(idx0.shape)
        v1 = flat.index_select(0, (idx0 + c).reshape(-1)).reshape(idx0.shape)
    out = v0 + frac * (v1 - v0)
    return torch.where(r <= r_max, out, torch.zeros_like(out)).to(values.dtype)


def _lookup_rows(r: Tensor, vals: Tensor, r_max: float, warp: str) -> Tensor:
    """:func:`lookup_profile_table`'s shared-range row lookup of :math:`(..., 1)` distances, outside autograd.

    The same interpolation in fewer passes (3x faster): with :math:`p = (N - 1)\\sqrt{r / r_{max}}` the first
    segment's weight :math:`q^2` is :math:`p^4` (:math:`q = p^2`), so no masked square root is needed when no
    gradient flows through ``r``.
    """
    n, c = vals.shape
    x = (r * (1.0 / r_max)).clamp_(0.0, 1.0)
    pos = (x.sqrt_() if warp == "sqrt" else x).mul_(n - 1)
    i0 = pos.floor().clamp_(max=n - 2)
    frac = pos - i0
    if warp == "sqrt":
        first = pos < 1.0
        frac = torch.where(first, frac.square().square(), frac)
    rows = i0.to(torch.int64).reshape(-1)
    shape = (*r.shape[:-1], c)
    v0 = vals.index_select(0, rows).reshape(shape)
    v1 = vals.index_select(0, rows + 1).reshape(shape)
    out = v0.addcmul_(frac, v1.sub_(v0))
    return out.masked_fill_(r > r_max, 0.0)


def profile_table_error(
    table: ProfileTable, profile: Callable[[Tensor], Tensor], samples: int = 65536, floor: float = 0.0
) -> Tensor:
    """Max relative error :math:`\\max |T(r) - R(r)| / \\max(|R(r)|, f \\max_r |R|)` of a table against the profile.

    The profile is evaluated in float64 at ``samples`` points per channel spread over :math:`[0, r_{max}]`
    (uniform in the table's warped coordinate, offset so that node midpoints, where linear interpolation is
    worst, are included). ``floor`` :math:`f` (>= 0) measures the error where the profile has fallen below that
    fraction of its channel's largest value against that level instead (0: purely relative).

    Returns:
        :math:`(C,)` maximum relative error per channel.
    """
    n = table.size
    k = max(int(samples), 4 * n)
    # points at every node, every midpoint and in between (k is a multiple of 2 (n - 1) plus one)
    k = 2 * (n - 1) * max(1, k // (2 * (n - 1))) + 1
    t = torch.linspace(0.0, 1.0, k, dtype=torch.float64, device=table.values.device).unsqueeze(-1)
    r_max = table.r_max.detach().to(torch.float64)
    r = r_max * (t * t if table.warp == "sqrt" else t)
    r = torch.minimum(r, r_max)
    with torch.no_grad():
        exact = profile(r).to(torch.float64)
        approx = lookup_profile_table(r, ProfileTable(table.values.detach().to(torch.float64), r_max, table.warp,
                                                      table.shared_range))
    level = torch.maximum(exact.abs(), float(floor) * exact.abs().amax(0))
    return ((approx - exact).abs() / level.clamp_min(torch.finfo(torch.float64).tiny)).amax(0)


def fitted_profile_table(profile: Callable[[Tensor], Tensor], r_max: float, *, tolerance: float = 2e-5,
                         floor: float = 1e-6, sizes: tuple[int, ...] = (4096, 16384, 65536),
                         dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
                         ) -> ProfileTable | None:
    """The smallest shared-range table of ``profile`` over :math:`[0, r_{max}]` within ``tolerance``, or None.

    For evaluating a fixed profile at many distances at once (a precompute's millions of distances): a gather and a
    lerp instead of the profile's formula. Each size of ``sizes`` is tried in turn (``warp="sqrt"``) and checked by
    :func:`profile_table_error` at every node midpoint, in float64, against the profile itself (relative error,
    with ``floor``); None when none meets ``tolerance`` (a profile with a kink or a range too wide for the
    largest size: evaluate it directly then). Distances beyond ``r_max`` look up 0: give the largest distance.

    Args:
        profile: maps distances :math:`(N, C)` mm to :math:`(N, C)` (e.g. a :class:`~torchsss.DipoleMaterial`).
        r_max: the largest distance to be looked up (mm, > 0).
        tolerance: the largest relative error accepted (> 0).
        floor: see :func:`profile_table_error`.
        sizes: node counts to try, ascending.
        dtype: of the distances the table's range is made in (the profile's own dtype sets the values').
        device: of those distances.

    Returns:
        A :class:`ProfileTable` (``shared_range``, values without autograd history), or None.

    Examples:
        >>> from torchsss.physics import dipole_rd
        >>> tab = fitted_profile_table(lambda r: dipole_rd(r, torch.tensor([0.01]), torch.tensor([1.0])), 30.0)
        >>> tab.size, tab.warp
        (4096, 'sqrt')
    """
    if isinstance(r_max, bool) or not isinstance(r_max, (int, float)) or not 0.0 < float(r_max) < float("inf"):
        raise ValueError(f"r_max: expected a finite number > 0 (mm), got {r_max!r}")
    if not isinstance(tolerance, (int, float)) or not tolerance > 0:
        raise ValueError(f"tolerance: expected a number > 0, got {tolerance!r}")
    probe = profile(torch.zeros(1, 1, dtype=dtype, device=device))
    rm = torch.full((int(probe.shape[-1]),), float(r_max), dtype=dtype, device=device)
    with torch.no_grad():
        for size in sizes:
            table = build_profile_table(profile, rm, int(size), "sqrt", shared_range=True)
            if bool((profile_table_error(table, profile, 4 * int(size), floor) <= tolerance).all()):
                return table
    return None


#: Largest relative error of the tables :func:`bulk_profile` evaluates a profile with (below the profile's millionth
#: part: against that level), about 100x below the smallest error any method of this library is planned for.
BULK_TOLERANCE = 2e-5
#: The fewest distances worth a table: fitting one evaluates the profile at 20k-330k nodes and midpoints (5-30 ms),
#: more than evaluating fewer distances directly.
BULK_MIN_VALUES = 1 << 18


def bulk_profile(material: Callable[[Tensor], Tensor], r_max_mm: float, dtype: torch.dtype = torch.float32,
                 device: torch.device | str | None = None) -> Callable[[Tensor], Tensor]:
    """``material`` for evaluating millions of distances in :math:`[0, r_{max}]` mm at once, without autograd.

    A precompute that evaluates a fixed profile at every kernel tap or throughput entry (the Lensch modules' first
    frame after a material change: 20-40M distances) spends most of its time in the profile's formula. Where the
    evaluation is in float32 (or a reduced format), this returns a lookup of a table of the profile over
    :math:`[0, r_{max}]` (:func:`~torchsss.physics.fitted_profile_table`: 4,096-65,536 nodes, each size checked at
    every node midpoint against the profile itself in float64, within :data:`BULK_TOLERANCE`), 2-6x faster than the
    dipole's formula. It returns ``material`` itself for float64 (exact evaluation asked for), for a range that is
    not finite and positive, under autograd or tracing (the table would hold no gradient), or when no table meets
    the tolerance.

    Args:
        material: a profile: distances :math:`(..., 1)` mm to :math:`(..., C)` (a material module, e.g.
            :class:`~torchsss.DipoleMaterial`).
        r_max_mm: the largest distance that will be evaluated (mm); larger ones would look up 0.
        dtype: the distances' dtype.
        device: the distances' device.

    Returns:
        A callable mapping :math:`(..., 1)` distances (mm) to :math:`(..., C)` profile values (mm^-2).

    Examples:
        >>> from torchsss.modules import DipoleMaterial
        >>> m = DipoleMaterial.from_preset("skin1")
        >>> r = torch.tensor([[0.3], [4.0]])
        >>> with torch.no_grad():
        ...     fast = bulk_profile(m, 5.0)
        ...     bool(((fast(r) - m(r)).abs() / m(r)).max() < BULK_TOLERANCE)
        True
    """
    if torch.is_grad_enabled() or is_tracing() or dtype not in (torch.float32, torch.float16, torch.bfloat16):
        return material
    r_max = float(r_max_mm)
    if not 0.0 < r_max < math.inf:
        return material
    probe = material(torch.zeros(1, 1, dtype=dtype, device=device))
    if probe.dtype == torch.float64:
        return material
    table = fitted_profile_table(material, r_max * (1.0 + 1e-6), tolerance=BULK_TOLERANCE, dtype=dtype,
                                 device=device)
    if table is None:
        return material
    return lambda r: lookup_profile_table(r, table)
