"""Sampling budgets derived from the profile: Shah's splat radius, overlap and count; Chang's local/global split.

All distances are in mm, coefficients in mm^-1. The solvers run in float64 without gradients (a budget is a
discrete decision, not a differentiable quantity) and return tensors of the material's broadcast shape in the
promoted input dtype, so a per-channel material ``(C,)`` gives one value per channel.

Shah (2007) eq. 6.16 writes the truncated area as :math:`A' = r_{max}^2`. This library truncates the profile
to the *disk* of radius :math:`r_{max}` (:math:`A' = \\pi r_{max}^2`; the splat quad of side :math:`2 r_{max}`
is its bounding square), so that the tail fraction has the closed form of :func:`dipole_cumulative`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsss._checks import as_float_tensor, check_positive, compute_dtype
from torchsss.physics.dipole import dipole_rd, dipole_spectrum, dipole_terms

__all__ = [
    "chang_local_weight",
    "chang_rp",
    "chang_weights",
    "profile_tail_fraction",
    "r_max",
    "splat_alias_error",
    "splat_count",
    "splat_overlap",
    "splat_spacing",
]

#: Bisection steps: geometric steps over a bracket of at most ~1e6 reach float64's 2e-16 relative precision in 56
#: (100 were spent before: the planner's first plan of a material ran ~800 profile evaluations, 1.2 s).
_BISECT_STEPS = 60
_MAX_DOUBLINGS = 200


def _material64(sigma_a, sigma_s_prime, eta) -> tuple[Tensor, Tensor, Tensor, torch.dtype]:
    terms = dipole_terms(sigma_a, sigma_s_prime, eta)  # validates
    sa = as_float_tensor(sigma_a, "sigma_a")
    ss = as_float_tensor(sigma_s_prime, "sigma_s_prime")
    et = as_float_tensor(eta, "eta")
    out_dtype, _ = compute_dtype(sa, ss, et)
    shape = terms.z_v.shape
    conv = [t.detach().to(torch.float64).expand(shape) for t in (sa, ss, et)]
    return conv[0], conv[1], conv[2], out_dtype


def _material_like(sigma_a, sigma_s_prime, eta, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Python numbers take ``like``'s dtype (so a float64 radius is never evaluated with float32 material terms)."""
    return (as_float_tensor(sigma_a, "sigma_a", like=like), as_float_tensor(sigma_s_prime, "sigma_s_prime", like=like),
            as_float_tensor(eta, "eta", like=like))


def _check_eps(eps: float, name: str = "eps") -> float:
    if isinstance(eps, bool) or not isinstance(eps, (int, float)):
        raise TypeError(f"{name}: expected a float in (0, 1), got {type(eps).__name__}")
    if not 0.0 < float(eps) < 1.0:
        raise ValueError(f"{name}: expected a value in (0, 1), got {eps!r}")
    return float(eps)


def _bisect_increasing(f, lo: Tensor, hi: Tensor, target: float | Tensor, rtol: float = 0.0) -> Tensor:
    """Smallest x in [lo, hi] (elementwise) with f(x) >= target, for f non-decreasing; geometric steps when lo > 0.

    ``rtol`` > 0 stops once every bracket with lo > 0 is within that relative width (and none has lo = 0).
    """
    for _ in range(_BISECT_STEPS):
        if rtol > 0.0 and bool((lo > 0).all()) and bool((hi <= lo * (1.0 + rtol)).all()):
            break
        mid = torch.where(lo > 0, torch.sqrt(lo * hi), 0.5 * (lo + hi))
        above = f(mid) >= target
        hi = torch.where(above, mid, hi)
        lo = torch.where(above, lo, mid)
    return hi


def profile_tail_fraction(radius, sigma_a, sigma_s_prime, eta=1.3) -> Tensor:
    """Fraction of the total diffuse reflectance that falls outside the disk of ``radius`` mm (closed form).

    .. math::
        T(R) = \\frac{\\sum_z \\frac{z}{d_z(R)} e^{-\\sigma_{tr} d_z(R)}}{\\sum_z e^{-\\sigma_{tr} z}},
        \\quad z \\in \\{z_r, z_v\\}

    This is the left side of Shah eq. 6.16 with the disk area. Shapes broadcast as :func:`dipole_rd`.

    Examples:
        >>> round(profile_tail_fraction(0.0, 0.01, 1.0).item(), 6)
        1.0
    """
    r = as_float_tensor(radius, "radius")
    return _tail_fraction(r, dipole_terms(*_material_like(sigma_a, sigma_s_prime, eta, r)))


def _tail_fraction(r: Tensor, terms) -> Tensor:
    """:func:`profile_tail_fraction` of a validated material's :func:`dipole_terms` (the bisections' inner loop)."""
    sig = terms.sigma_tr
    num = 0.0
    den = 0.0
    for z in (terms.z_r, terms.z_v):
        d = torch.sqrt(r * r + z * z)
        num = num + z / d * torch.exp(-sig * d)
        den = den + torch.exp(-sig * z)
    return num / den


def r_max(sigma_a, sigma_s_prime, eta=1.3, eps: float = 0.01) -> Tensor:
    """Splat radius of Shah eq. 6.16: the smallest :math:`r_{max}` (mm) with tail fraction :math:`\\le \\epsilon`.

    Solved numerically per channel by bisection on the closed-form tail (:func:`profile_tail_fraction`), to a
    relative precision of about 1e-12.

    Args:
        sigma_a: absorption coefficient (mm^-1), e.g. ``(C,)``.
        sigma_s_prime: reduced scattering coefficient (mm^-1), broadcastable with ``sigma_a``.
        eta: relative index of refraction.
        eps: allowed fraction of the total diffuse reflectance lost by truncation, in (0, 1).

    Returns:
        :math:`r_{max}` in mm, the material's broadcast shape.

    Examples:
        >>> rm = r_max(torch.tensor([0.0021, 0.0041, 0.0071]), torch.tensor([2.19, 2.62, 3.00]), 1.3, eps=0.01)
        >>> rm.shape
        torch.Size([3])
    """
    eps = _check_eps(eps)
    sa, ss, et, out_dtype = _material64(sigma_a, sigma_s_prime, eta)

    terms = dipole_terms(sa, ss, et)  # validated once: the bisection evaluates the tail ~250 times

    def tail(x: Tensor) -> Tensor:
        return _tail_fraction(x, terms)

    hi = terms.z_v.clone()
    for _ in range(_MAX_DOUBLINGS):
        grow = tail(hi) > eps
        if not bool(grow.any()):
            break
        hi = torch.where(grow, 2.0 * hi, hi)
    lo = torch.zeros_like(hi)
    # tail is decreasing: find the smallest R with -tail(R) >= -eps.
    return _bisect_increasing(lambda x: -tail(x), lo, hi, -eps).to(out_dtype)


def splat_alias_error(spacing, sigma_a, sigma_s_prime, eta=1.3, shells: int = 4) -> Tensor:
    """Relative error of a uniform lattice sum of the profile, predicted by the Poisson summation formula.

    Summing :math:`R_d(|x_o - x_{ij}|)\\,h^2` over sources on a square lattice of spacing :math:`h` around any
    receiver :math:`x_o` estimates :math:`R_{total}`; by Poisson summation the relative error is bounded by

    .. math::
        \\epsilon_{alias}(h) = \\sum_{m \\in \\mathbb{Z}^2 \\setminus 0} \\hat R_d(2\\pi |m| / h) / \\hat R_d(0),

    with :math:`\\hat R_d` the closed-form spectrum (:func:`dipole_spectrum`). The sum runs over
    :math:`|m|_\\infty \\le` ``shells`` (the rest is negligible: :math:`\\hat R_d` decays like
    :math:`e^{-z_r k}`). Shapes broadcast as :func:`dipole_rd`.
    """
    h = as_float_tensor(spacing, "spacing")
    check_positive(h, "spacing")
    sigma_a, sigma_s_prime, eta = _material_like(sigma_a, sigma_s_prime, eta, h)
    terms = dipole_terms(sigma_a, sigma_s_prime, eta)
    k = 2.0 * math.pi * _lattice_norms(shells, h.device).to(terms.z_r.dtype) / h.unsqueeze(-1)
    expand = [s.unsqueeze(-1) for s in (as_float_tensor(sigma_a, "sigma_a", like=h),
                                        as_float_tensor(sigma_s_prime, "sigma_s_prime", like=h),
                                        as_float_tensor(eta, "eta", like=h))]
    spec = dipole_spectrum(k, *expand)
    return spec.sum(-1) / dipole_spectrum(0.0, sigma_a, sigma_s_prime, eta)


def _lattice_norms(shells: int, device) -> Tensor:
    """:math:`|m|` over the lattice's nonzero points with :math:`|m|_\\infty \\le` ``shells`` (float64)."""
    rng = torch.arange(-shells, shells + 1, dtype=torch.float64, device=device)
    mx, my = torch.meshgrid(rng, rng, indexing="ij")
    norms = torch.sqrt(mx * mx + my * my).flatten()
    return norms[norms > 0]


def _alias_solver(sa: Tensor, ss: Tensor, et: Tensor, shells: int = 4):
    """:func:`splat_alias_error` of one validated float64 material as a function of the spacing alone.

    The bisection's inner loop: the material's terms and the lattice are built once and each call evaluates the
    closed-form spectrum without checks (:meth:`~torchsss.physics.dipole.DipoleTerms.spectrum`). splat_spacing's
    bisection for the planner's nine eps x three channels took 0.12 s with a checked call per step, 0.011 s with
    this. ``h`` broadcasts with the material's shape.
    """
    terms = dipole_terms(sa.unsqueeze(-1), ss.unsqueeze(-1), et.unsqueeze(-1))
    k_unit = 2.0 * math.pi * _lattice_norms(shells, sa.device)
    zero = terms.spectrum(torch.zeros((), dtype=torch.float64, device=sa.device)).squeeze(-1)

    def alias(h: Tensor) -> Tensor:
        return terms.spectrum(k_unit / h.unsqueeze(-1)).sum(-1) / zero

    return alias


def splat_spacing(sigma_a, sigma_s_prime, eta=1.3, eps: float = 0.01) -> Tensor:
    """Largest splat spacing :math:`h` (mm) whose predicted lattice-sum error is :math:`\\le \\epsilon`.

    This is the sampling criterion used in place of the literal Shah eq. 6.17 (which asks for 1e4-3e7
    overlapping splats for the Jensen materials): splat centres must resolve the profile's narrowest feature,
    whose width is set by the depth :math:`z_r = 1/\\sigma_t'` of the real source. Roughly
    :math:`h \\approx 2\\pi z_r / \\ln(4/\\epsilon)`; see :func:`splat_alias_error` for the exact criterion.

    ``eps`` may also be a sequence of :math:`E` values (one bisection for all of them: the planner asks for nine).

    Returns:
        :math:`h` in mm, the material's broadcast shape; :math:`(E, *)` for a sequence of ``eps``.

    Examples:
        >>> h = splat_spacing(0.0021, 2.19, 1.3, eps=0.01)      # marble, red
        >>> 0.4 < h.item() < 0.8
        True
        >>> splat_spacing(0.0021, 2.19, 1.3, eps=[0.01, 0.1]).shape
        torch.Size([2])
    """
    many = isinstance(eps, (list, tuple))
    if many:
        if not eps:
            raise ValueError("eps: expected at least one value in (0, 1), got an empty sequence")
        values = [_check_eps(e) for e in eps]
    else:
        values = [_check_eps(eps)]
    sa, ss, et, out_dtype = _material64(sigma_a, sigma_s_prime, eta)
    terms = dipole_terms(sa, ss, et)
    target = torch.tensor(values, dtype=torch.float64, device=sa.device).reshape(-1, *([1] * sa.dim()))

    alias = _alias_solver(sa, ss, et)
    lo = (terms.z_r * 1e-3).expand(target.shape[:1] + terms.z_r.shape)
    hi = terms.z_r.expand_as(lo).clone()
    for _ in range(_MAX_DOUBLINGS):
        grow = alias(hi) < target
        if not bool(grow.any()):
            break
        hi = torch.where(grow, 2.0 * hi, hi)
    # alias error increases with h: the largest h with alias <= eps is the boundary of {alias >= eps}.
    h = _bisect_increasing(alias, lo, hi, target).to(out_dtype)
    return h if many else h[0]


def splat_overlap(sigma_a, sigma_s_prime, eta=1.3, eps: float = 0.01, rule: str = "spacing") -> Tensor:
    """Splat overlap :math:`n_o` (Shah eq. 6.17): splats that overlap along one splat diameter.

    Args:
        sigma_a: absorption coefficient (mm^-1), e.g. ``(C,)``.
        sigma_s_prime: reduced scattering coefficient (mm^-1), broadcastable with ``sigma_a``.
        eta: relative index of refraction.
        eps: threshold, as in :func:`r_max`.
        rule: ``"spacing"`` (default): :math:`n_o = 2 r_{max} / h` with :math:`h` from :func:`splat_spacing`,
            so that eq. 6.18 gives a lattice of spacing :math:`h`. ``"literal"``: eq. 6.17 as printed,
            :math:`n_o = R_d(0) / (\\epsilon R_d(r_{max}))`, which yields 1e4-3e7 for the Jensen presets
            and is kept for comparison.

    Returns:
        :math:`n_o` (real-valued, >= 1), the material's broadcast shape.
    """
    eps = _check_eps(eps)
    if rule not in ("spacing", "literal"):
        raise ValueError(f"rule: expected 'spacing' or 'literal', got {rule!r}")
    sa, ss, et, out_dtype = _material64(sigma_a, sigma_s_prime, eta)
    rm = r_max(sa, ss, et, eps)
    if rule == "literal":
        n_o = dipole_rd(torch.zeros_like(rm), sa, ss, et) / (eps * dipole_rd(rm, sa, ss, et))
    else:
        n_o = 2.0 * rm / splat_spacing(sa, ss, et, eps)
    return n_o.clamp_min(1.0).to(out_dtype)


def splat_count(width_mm, r_max_mm, n_o) -> Tensor:
    """Splats per side of the light view, Shah eq. 6.18: :math:`n = \\lceil \\tfrac12 n_o W / r_{max} \\rceil`.

    Args:
        width_mm: width :math:`W` of the light's view frustum at the object, mm.
        r_max_mm: splat radius, mm.
        n_o: overlap from :func:`splat_overlap`.

    Returns:
        :math:`n` as an integer tensor (int64); the light view holds :math:`n \\times n` splats.

    Examples:
        >>> splat_count(30.0, 3.0, 4.0).item()
        20
    """
    w = as_float_tensor(width_mm, "width_mm")
    rm = as_float_tensor(r_max_mm, "r_max_mm", like=w)
    no = as_float_tensor(n_o, "n_o", like=w)
    check_positive(w, "width_mm")
    check_positive(rm, "r_max_mm")
    check_positive(no, "n_o")
    return torch.ceil(0.5 * no * w / rm - 1e-9).to(torch.int64)


def chang_rp(sigma_a, sigma_s_prime, eta=1.3, c: float = 0.01, grid: int = 4096) -> Tensor:
    """Chang et al. §4.1 split radius :math:`R_p`: the largest r with :math:`R_d(r)\\,2\\pi r = c`.

    Where the importance function :math:`2\\pi r R_d(r)` never reaches ``c`` there is no local peak worth
    separating and :math:`R_p = 0` is returned (everything is global). Chang takes one :math:`R_p` for all
    three channels, the largest: call ``chang_rp(...).amax(-1)`` for that.

    Args:
        sigma_a: absorption coefficient (mm^-1), e.g. ``(C,)``.
        sigma_s_prime: reduced scattering coefficient (mm^-1), broadcastable with ``sigma_a``.
        eta: relative index of refraction.
        c: importance lower bound in mm^-1 (> 0).
        grid: points of the log-spaced bracketing grid before bisection.

    Returns:
        :math:`R_p` in mm, the material's broadcast shape.

    Examples:
        >>> rp = chang_rp(0.0024, 0.70, 1.3, c=0.01)            # Chang's Fig. 3 skimmilk red channel
        >>> 2.0 < rp.item() < 30.0
        True
    """
    if isinstance(c, bool) or not isinstance(c, (int, float)) or not c > 0:
        raise ValueError(f"c: expected a number > 0, got {c!r}")
    sa, ss, et, out_dtype = _material64(sigma_a, sigma_s_prime, eta)
    terms = dipole_terms(sa, ss, et)

    def importance(r: Tensor) -> Tensor:
        return 2.0 * math.pi * r * dipole_rd(r, sa.unsqueeze(-1), ss.unsqueeze(-1), et.unsqueeze(-1))

    hi = terms.z_v.clone()
    for _ in range(_MAX_DOUBLINGS):  # beyond the peak and below c
        val = importance(hi.unsqueeze(-1)).squeeze(-1)
        grow = (val >= c) | (hi < 10.0 * terms.z_v)
        if not bool(grow.any()):
            break
        hi = torch.where(grow, 2.0 * hi, hi)
    t = torch.linspace(0.0, 1.0, grid, dtype=torch.float64, device=hi.device)
    lo_r = terms.z_r * 1e-6
    rs = lo_r.unsqueeze(-1) * (hi / lo_r).unsqueeze(-1) ** t  # (..., grid)
    vals = importance(rs)
    above = vals >= c
    idx = torch.arange(grid, device=above.device).expand_as(above)
    last = torch.where(above, idx, torch.full_like(idx, -1)).amax(-1)
    found = last >= 0
    i0 = last.clamp(0, grid - 2).unsqueeze(-1)
    lo = torch.gather(rs, -1, i0).squeeze(-1)
    up = torch.gather(rs, -1, i0 + 1).squeeze(-1)
    # importance is decreasing on [lo, up] past the last crossing: bisect -importance.
    # (the grid's bracket is 0.1-1% wide: 1e-12 in 30 steps, not 60)
    root = _bisect_increasing(lambda x: -importance(x.unsqueeze(-1)).squeeze(-1), lo, up, -c, rtol=1e-12)
    return torch.where(found, root, torch.zeros_like(root)).to(out_dtype)


def chang_weights(r, r_p, k: float = 1.5) -> tuple[Tensor, Tensor]:
    """Chang et al. §4.1 local/global weights :math:`(W_l, W_g)` with :math:`W_l + W_g = 1`.

    .. math::
        W_l(r) = 1 - \\tfrac12 e^{(r - R_p) K} \\; (r \\le R_p), \\qquad
        W_l(r) = \\tfrac12 e^{-(r - R_p) K} \\; (r > R_p)

    The paper prints the first branch as :math:`1 - 0.5 e^{-(r-R_p)K}`, which is negative near r = 0 for any
    :math:`R_p K > \\ln 2` (W_l(0) = -17.5 for its own skimmilk example, R_p = 2.41, K = 1.5) and contradicts
    "the function value of small distance r is retained in the local term". The sign is corrected here: the
    weights are then in [0, 1], continuous and C^1 at :math:`R_p` (both slopes are :math:`-K/2`).

    Args:
        r: distances in mm, any shape.
        r_p: split radius in mm, broadcastable with ``r``.
        k: steepness K in mm^-1 (Chang: 1.5).

    Returns:
        ``(w_local, w_global)``, the broadcast shape.

    Examples:
        >>> wl, wg = chang_weights(torch.tensor([0.0, 2.0, 50.0]), 2.0)
        >>> [round(v, 4) for v in wl.tolist()]
        [0.9751, 0.5, 0.0]
    """
    r_t = as_float_tensor(r, "r")
    rp = as_float_tensor(r_p, "r_p", like=r_t)
    if isinstance(k, bool) or not isinstance(k, (int, float)) or not k > 0:
        raise ValueError(f"k: expected a number > 0, got {k!r}")
    w_l = chang_local_weight(r_t, rp, k)
    return w_l, 1.0 - w_l


def chang_local_weight(r: Tensor, r_p: Tensor | float, k: Tensor | float) -> Tensor:
    """:math:`W_l(r)` of :func:`chang_weights` without validation (for compiled kernels; tensors or numbers).

    Both branches' exponents are clamped to <= 0 before ``exp`` (double-where), so no branch overflows or
    passes a NaN gradient.
    """
    x = (r - r_p) * k
    inside = x <= 0
    x_in = torch.where(inside, x, torch.zeros_like(x))
    x_out = torch.where(inside, torch.zeros_like(x), x)
    return torch.where(inside, 1.0 - 0.5 * torch.exp(x_in), 0.5 * torch.exp(-x_out))
