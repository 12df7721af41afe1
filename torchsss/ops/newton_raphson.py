"""Ray / receiver intersection by iterative lookups in a light-view positions texture (Shah ch. 5.3.3-5.3.4).

Caustics mapping renders the receiver geometry from the light into a *positions texture* (world position per
texel) and then has to find where each refracted (or reflected) ray ``o + d r`` meets that geometry, without
ray tracing. Every step projects a point of the ray into the light's view, reads the receiver point seen
through that texel and updates the distance estimate :math:`d`. Two update rules are offered:

* ``method="shah"`` (Shah's estimator, §5.3.4, Fig. 5.4): :math:`d_{k+1} = |P(o + d_k r) - o|`, the distance
  from the ray origin to the receiver point looked up where the current estimate projects; one lookup per
  iteration, no derivative. It is a fixed-point iteration: exact at the root and linearly convergent, fast
  when the ray runs close to the light's lines of sight (refraction), slow for rays far from them.
* ``method="newton"`` (the Newton-Raphson iteration of Shah eq. 5.4-5.5 and the appendix) on the *signed*
  residual between the estimate :math:`x = o + d\\, r` and the receiver :math:`P(x)` seen through it,

  .. math:: f(d) = \\ell(x) \\cdot \\big(P(x) - x\\big),

  with :math:`\\ell(x)` the unit direction of the light's line of sight through :math:`x`, pointing away from the
  light (from the light's centre, the null vector of rows 0, 1 and 3 of ``view_proj``; constant for an
  orthographic light). :math:`P(x)` lies on that line, so :math:`|f| = |P(x) - x|` (Shah's eq. 5.3) and the sign
  is a shadow-map depth test: :math:`f > 0` while the estimate is in front of the receiver, :math:`f < 0` once it
  is past it, :math:`f = 0` exactly at the intersection. (Measuring the residual along the refracted ray
  instead, :math:`r \\cdot (P - x)`, multiplies it by :math:`r \\cdot \\ell`: spurious roots wherever the ray
  crosses a line of sight at a right angle, and a slope that vanishes for grazing rays.) :math:`f'` is a forward
  difference with step :math:`\\Delta = \\text{fd\\_step}\\,(|d| + |P - o|)`; two lookups per iteration.

Both start from :math:`d_0 = 0` unless ``initial_distance`` is given: the first lookup is the receiver seen
through the ray origin itself (Shah: "the distance of the surface geometry ... from the origin of the refracted
ray (i.e. :math:`d_0 = 0`)"), so :math:`d_1` of the Shah method is the origin's distance to that receiver point.

Safeguards. An iteration *oscillates* when it fails to reduce the residual, :math:`|f(d_k)| \\ge |f(d_{k-1})|`
(an overshoot across the root, a 2-cycle, divergence, or a stall at a kink of the interpolated texture). With
``fallback=True`` (the default, for either method), when such a step also ends on the other side of the root
(:math:`f(d_k)` and :math:`f(d_{k-1})` of opposite signs, so the last two estimates bracket it) the next
estimate is their midpoint instead of the Newton/Shah update (Shah §5.3.4: "storing the last two estimates and
then ... switching to ... the Bisection method"). Stalls on one side are reported but not bisected: a stale
bracket spanning most of the ray would throw a nearly converged estimate far away. Rays whose residual is
within ``tol`` of the distance count as converged and stop moving. Where the forward difference is unusable
(:math:`|f'| \\le 10^{-6}`, or the difference point missed the receivers) the Newton method takes Shah's update.

Lookups (:func:`lookup_positions`): ``view_proj`` maps world points to clip space; a point is looked up when it
lies in front of the light (:math:`w > 0`) and inside the frustum's sides (:math:`|x|, |y| \\le 1` in NDC; depth
is not clipped); NDC :math:`y` points up and texture row 0 is at the top; ``F.grid_sample`` (bilinear,
``align_corners=False``, pixel centres at :math:`i + 0.5`, border clamp in the outer half-texel). A texel whose
stored position is not finite holds no receiver. The texture is sanitised (zeros) before sampling and a
coverage channel (1 on receiver texels) is sampled with it: a lookup *hits* when more than half of the bilinear
weight lies on receiver texels, and the position is the bilinear average over those texels only. NaN never
reaches the sampler or the outputs.

A ray is **valid** when its origin and direction are finite with :math:`|r| > 0` (refract's zero TIR vector
gives an invalid ray), every lookup on its path hit (a ray that steps off the texture, behind the light or onto
an empty texel is dropped there, as in Shah: "some of the caustic splats would be lost"), the final estimate's
lookup hits as well, :math:`d > 0` and the receiver found lies ahead of the origin (:math:`r \\cdot (P - o) > 0`:
rays pointing away from every receiver are invalid), and, if ``max_residual`` is given, the final estimate lies
within ``max_residual`` mm of the receiver seen through it. The residual is not checked by default, yet a valid
ray is not necessarily converged: Shah's iterates approach the hit slowly for rays far from the light's lines of
sight (grazing rays), and either method can stall at a kink or an occlusion edge of the texture. Ask
``return_info=True`` for the residual or set ``max_residual`` (a texel or two) to drop such rays.

The iterations run a fixed number of times with tensor ops only (``torch.where`` for every branch), so the
function runs batched, differentiates (through ``grid_sample``'s bilinear weights, the finite difference and the
selected branches) and exports to ONNX with the sizes dynamic. Eagerly and under ``torch.compile`` it is a Python
loop; exported (``torch.export`` / ONNX) with four or more iterations it is one ``while_loop`` body, an ONNX
``Loop``, so the graph and the export time do not grow with ``iterations`` (the same step function, tested equal
to the Python loop).
"""

from __future__ import annotations

import itertools
import numbers

import torch
import torch.nn.functional as F
from torch import Tensor

from torchsss._checks import cast, check_shape, check_tensor, compute_dtype, is_exporting, is_tracing, skip_value_checks

__all__ = ["lookup_positions", "newton_raphson_intersect"]

_METHODS = ("shah", "newton")
#: Share of the bilinear weight that has to fall on receiver texels for a lookup to hit.
_MIN_COVERAGE = 0.5
#: Exported, this many iterations or more run as one ``while_loop`` body (an ONNX ``Loop``); fewer are unrolled (the
#: loop's own tracing costs about as much export time as three unrolled iterations).
_LOOP_MIN_ITERATIONS = 4
#: Forward-difference slopes smaller than this in magnitude are unusable (f' is dimensionless).
_MIN_SLOPE = 1e-6


def _shapes(checks: list[tuple[Tensor, str, str]]) -> None:
    """Shape checks (named dimensions shared across the list), skipped while tracing.

    ``check_shape`` turns sizes into Python ints, which would freeze dynamic sizes into an exported graph; the
    exporter checks the shapes itself.
    """
    if is_tracing():
        return
    sizes: dict[str, int] = {}
    for x, name, dims in checks:
        known = {k: v for k, v in sizes.items() if k in dims.split(",")}
        sizes.update(check_shape(x, name, dims, **known))


def _check_common(positions_texture: object, view_proj: object, rays: list[tuple[object, str]]) -> None:
    """Types, shapes and devices of the rays / points, the positions texture and the matrix; finite matrix."""
    for x, name in [*rays, (positions_texture, "positions_texture"), (view_proj, "view_proj")]:
        check_tensor(x, name)
    checks = [(x, name, "B,N,3") for x, name in rays]
    checks.append((positions_texture, "positions_texture", "B,3,H,W"))
    checks.append((view_proj, "view_proj", "4,4" if view_proj.dim() == 2 else "B,4,4"))
    _shapes(checks)
    for x, name in [*rays, (view_proj, "view_proj")]:
        if x.device != positions_texture.device:
            raise ValueError(
                f"{name}: expected a tensor on positions_texture's device {positions_texture.device}, got {x.device}"
            )
    if not skip_value_checks(view_proj) and not bool(torch.isfinite(view_proj).all()):
        raise ValueError("view_proj: expected finite values, got a non-finite entry")


def _prepare_texture(positions: Tensor) -> Tensor:
    """(B, 3, H, W) positions -> (B, 4, H, W): zeros where any channel is non-finite, plus a 0/1 coverage channel."""
    finite = torch.isfinite(positions).all(dim=1, keepdim=True)
    clean = torch.where(finite, positions, 0.0)
    return torch.cat([clean, finite.to(positions.dtype)], dim=1)


def _grid_matrix(mat: Tensor) -> tuple[Tensor, Tensor]:
    """(B, 3, 3) linear block and (B, 1, 3) offset mapping world points to (x, -y, w) clip coordinates.

    grid_sample's y runs from the top row (-1) to the bottom row (+1) while NDC y points up, so row 1 is negated
    here once rather than the NDC in every lookup (exact: a negation rounds nothing). Built outside any loop (a
    constant made inside a traced loop body does not export).
    """
    rows = torch.stack([mat[:, 0], -mat[:, 1], mat[:, 3]], 1)  # (B, 3, 4)
    # two separate tensors, not views of one (a loop body's inputs may not alias each other)
    return rows[:, :, :3].transpose(1, 2).contiguous(), rows[:, None, :, 3].clone()


def _lookup(points: Tensor, tex: Tensor, grid_mat: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    """Receiver positions (B, N, 3) seen through world ``points`` (B, N, 3), and the hit mask (B, N).

    ``grid_mat`` is :func:`_grid_matrix` of the light's ``view_proj``.
    """
    clip = torch.matmul(points, grid_mat[0]) + grid_mat[1]  # (B, N, 3): x, -y, w
    w = clip[..., 2]
    front = w > 0
    ndc = clip[..., :2] / torch.where(front, w, 1.0)[..., None]  # grid_sample's (x, y)
    inside = front & (ndc.abs() <= 1.0).all(-1)
    grid = torch.where(inside[..., None], ndc, 0.0)
    s = F.grid_sample(tex, grid.unsqueeze(2), mode="bilinear", padding_mode="border", align_corners=False)
    s = s[..., 0].transpose(1, 2)  # (B, N, 4)
    cover = s[..., 3]
    hit = inside & (cover > _MIN_COVERAGE)
    p = s[..., :3] / torch.where(hit, cover, 1.0)[..., None]
    return p, hit


def _levi_civita4_rows() -> list[list[float]]:
    """The 4-D Levi-Civita symbol as a 16 x 16 table: row ``4 j + k``, column ``4 i + l`` holds eps_ijkl."""
    table = [[0.0] * 16 for _ in range(16)]
    for perm in itertools.permutations(range(4)):
        i, j, k, m = perm
        inversions = sum(a > b for n, a in enumerate(perm) for b in perm[n + 1:])
        table[4 * j + k][4 * i + m] = -1.0 if inversions % 2 else 1.0
    return table


#: :func:`_levi_civita4_rows`, built once (a Python table, so a traced graph gets it as one constant).
_LEVI_CIVITA4 = _levi_civita4_rows()


def _sight_centre(mat: Tensor) -> Tensor:
    """(B, 4) homogeneous centre K of the light: the line of sight through x runs along ``K_w x - K_xyz``.

    The direction is oriented away from the light.
    Every line of sight keeps NDC x and y, i.e. the ratios of clip rows 0 and 1 to row 3, so all of them pass
    through the null vector C of those three rows (the eye; a point at infinity for an orthographic light). C is
    their generalised cross product, :math:`C_i = (-1)^i \\det` (the rows without column i). A perspective light
    (:math:`C_w \\ne 0`) uses :math:`K = C / C_w`, so the direction is :math:`x - \\text{eye}`; an orthographic one
    flips C so that the direction :math:`-C_{xyz}` makes clip depth (row 2) grow.
    """
    # C_i = eps_ijkl R0_j R1_k R3_l with R the rows 0, 1, 3: the Laplace expansion of det [e_i; R0; R1; R3], i.e.
    # (-1)^i times the 3 x 3 minor without column i; as two products (a handful of graph nodes, not ~100)
    b = mat.shape[0]
    outer = (mat[:, 0, :, None] * mat[:, 1, None, :]).reshape(b, 16)  # R0_j R1_k at 4 j + k
    eps = torch.tensor(_LEVI_CIVITA4, dtype=mat.dtype, device=mat.device)
    c = (torch.matmul(outer, eps).reshape(b, 4, 4) * mat[:, None, 3, :]).sum(-1)
    cw = c[:, 3:4]
    perspective = cw != 0
    k_persp = c / torch.where(perspective, cw, 1.0)
    depth_gain = -(c[:, :3] * mat[:, 2, :3]).sum(-1, keepdim=True)  # growth of clip z along -C_xyz
    k_ortho = torch.where(depth_gain < 0, -c, c)
    return torch.where(perspective, k_persp, k_ortho)


def _norm(v: Tensor) -> Tensor:
    """|v| over the last axis (size 3), with finite gradients at 0.

    ``torch.linalg.vector_norm`` over a last axis of 3 was 30x slower than this on 65,536 points (one CPU thread).
    """
    return torch.sqrt((v * v).sum(-1).clamp_min(torch.finfo(v.dtype).tiny))


def _batched_matrix(view_proj: Tensor, b: int, dtype: torch.dtype) -> Tensor:
    mat = cast(view_proj, dtype)
    return mat.unsqueeze(0).expand(b, 4, 4) if mat.dim() == 2 else mat


def lookup_positions(points: Tensor, positions_texture: Tensor, view_proj: Tensor) -> tuple[Tensor, Tensor]:
    """Receiver positions seen from the light through world points (one bilinear positions-texture lookup).

    Projects ``points`` with ``view_proj``, reads ``positions_texture`` at the projected NDC (row 0 at the top,
    bilinear, ``align_corners=False``) and reports where a receiver was found; see the module docstring for the
    rules (in front of the light, inside the frustum's sides, more than half of the bilinear weight on finite
    texels, averaged over the finite texels only).

    Args:
        points: :math:`(B, N, 3)` world points (mm).
        positions_texture: :math:`(B, 3, H, W)` world position per light texel; non-finite = no receiver.
        view_proj: :math:`(B, 4, 4)` or :math:`(4, 4)` world-to-clip matrix of the light (column vectors).

    Returns:
        ``(positions, hit)``: :math:`(B, N, 3)` receiver positions (zero where not hit) in the promoted dtype,
        and the :math:`(B, N)` bool mask of hits.

    Raises:
        TypeError: a non-tensor or non-floating input.
        ValueError: wrong shapes, batch sizes that differ, inputs on different devices, non-finite ``view_proj``.

    Examples:
        >>> tex = torch.tensor([0.0, 1.0]).reshape(1, 1, 2, 1).expand(1, 3, 2, 1)  # rows: (0,0,0) on top, (1,1,1)
        >>> p, hit = lookup_positions(torch.tensor([[[0.0, 0.5, 0.0], [0.0, -0.5, 0.0]]]), tex, torch.eye(4))
        >>> p[0, :, 0].tolist(), hit.tolist()  # NDC y = +0.5 is the top row's centre
        ([0.0, 1.0], [[True, True]])
    """
    _check_common(positions_texture, view_proj, [(points, "points")])
    out_dtype, work = compute_dtype(points, positions_texture, view_proj)
    pts = cast(points, work)  # a non-finite point fails the frustum test (comparisons with NaN are False)
    p, hit = _lookup(
        pts, _prepare_texture(cast(positions_texture, work)),
        _grid_matrix(_batched_matrix(view_proj, points.shape[0], work)),
    )
    p = torch.where(hit[..., None], p, 0.0)
    return cast(p, out_dtype), hit


def _check_options(
    iterations: object,
    method: object,
    fallback: object,
    fd_step: object,
    tol: object,
    max_residual: object,
    return_info: object,
) -> None:
    if isinstance(iterations, bool) or not isinstance(iterations, numbers.Integral):
        raise TypeError(f"iterations: expected an int >= 0, got {type(iterations).__name__}")
    if iterations < 0:
        raise ValueError(f"iterations: expected an int >= 0, got {iterations}")
    if not isinstance(method, str) or method not in _METHODS:
        raise ValueError(f"method: expected one of {_METHODS}, got {method!r}")
    for name, value in (("fallback", fallback), ("return_info", return_info)):
        if not isinstance(value, bool):
            raise TypeError(f"{name}: expected a bool, got {type(value).__name__}")
    for name, value, lo in (("fd_step", fd_step, "> 0"), ("tol", tol, ">= 0"), ("max_residual", max_residual, ">= 0")):
        if name == "max_residual" and value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise TypeError(f"{name}: expected a real number {lo}, got {type(value).__name__}")
        ok = value > 0 if lo == "> 0" else value >= 0
        if not (ok and float(value) < float("inf")):
            raise ValueError(f"{name}: expected a finite number {lo}, got {value!r}")


def newton_raphson_intersect(
    origins: Tensor,
    directions: Tensor,
    positions_texture: Tensor,
    view_proj: Tensor,
    iterations: int = 5,
    method: str = "shah",
    *,
    fallback: bool = True,
    initial_distance: Tensor | float | None = None,
    fd_step: float = 1e-3,
    tol: float = 1e-5,
    max_residual: float | None = None,
    return_info: bool = False,
) -> tuple[Tensor, Tensor] | tuple[Tensor, Tensor, dict[str, Tensor]]:
    """Distance along each ray to the receiver geometry stored in a light-view positions texture (Shah §5.3.4).

    See the module docstring for the two update rules, the safeguards, the lookup conventions and the validity
    rules. Cost: ``iterations + 1`` texture lookups per ray for ``"shah"`` and ``2 * iterations + 1`` for
    ``"newton"`` (the last one checks the final estimate and gives the residual).

    Args:
        origins: :math:`(B, N, 3)` ray origins in world space (mm), e.g. refractor points seen from the light.
        directions: :math:`(B, N, 3)` ray directions (any non-zero finite length, subnormal to near the float
            maximum; normalised scale-safely inside), e.g. from :func:`torchsss.ops.refraction.refract`. Zero
            vectors give invalid rays.
        positions_texture: :math:`(B, 3, H, W)` receiver world position per light texel (row 0 at the top);
            non-finite texels (NaN, inf) hold no receiver.
        view_proj: :math:`(B, 4, 4)` or :math:`(4, 4)` world-to-clip matrix of the light that rendered the texture.
        iterations: number of updates of the estimate (>= 0; 0 returns the initial estimate, checked).
        method: ``"shah"`` (Shah's estimator) or ``"newton"`` (Newton-Raphson with a finite-difference slope).
        fallback: bisect the last two estimates when they bracket the root and the last step did not reduce
            :math:`|f|` (both methods).
        initial_distance: :math:`d_0`, a number or a :math:`(B, N)` tensor (mm); default 0 (the receiver seen
            through the origin gives the first estimate).
        fd_step: relative step of the forward difference (``"newton"``), times :math:`|d| + |P - o|`.
        tol: rays with :math:`|f(d)| \\le` ``tol`` :math:`\\cdot (|d| + |P - o|)` count as converged and stop
            moving (both methods); oscillation is only flagged above it.
        max_residual: if given, rays whose final estimate lies farther than this (mm) from the receiver seen
            through it are invalid.
        return_info: also return a dict of per-ray diagnostics.

    Returns:
        ``(distance, valid)`` or ``(distance, valid, info)``: :math:`(B, N)` distances along the unit directions
        (mm; 0 where not valid) in the promoted dtype of the inputs, the :math:`(B, N)` bool validity mask, and
        ``info`` with :math:`(B, N)` entries

        - ``"oscillated"`` (bool): some iteration failed to reduce :math:`|f|` (above ``tol``);
        - ``"fallback"`` (bool): some step was replaced by bisection (always False without ``fallback``);
        - ``"residual"``: :math:`|P(o + d r) - (o + d r)|` at the final estimate (Shah eq. 5.3, mm; 0 where the
          ray left the receivers).

    Raises:
        TypeError: non-tensor or non-floating tensors, or options of the wrong type.
        ValueError: wrong shapes, batch sizes that differ, inputs on different devices, non-finite ``view_proj``,
            an unknown ``method`` or option values out of range.

    Examples:
        >>> # a light 10 mm above the plane z = 0, looking down (orthographic, 20 mm wide), 4 x 4 texels
        >>> ys, xs = torch.meshgrid(7.5 - 5.0 * torch.arange(4.0), -7.5 + 5.0 * torch.arange(4.0), indexing="ij")
        >>> tex = torch.stack([xs, ys, torch.zeros(4, 4)])[None]  # row 0 at the top (largest y)
        >>> view_proj = torch.tensor([[0.1, 0, 0, 0], [0, 0.1, 0, 0], [0, 0, -0.1, 0], [0, 0, 0, 1.0]])
        >>> o = torch.tensor([[[0.0, 0.0, 4.0]]])
        >>> r = torch.tensor([[[0.6, 0.0, -0.8]]])  # exact hit at d = 4 / 0.8 = 5
        >>> d, ok = newton_raphson_intersect(o, r, tex, view_proj, 2, method="newton")
        >>> round(d.item(), 4), ok.item()
        (5.0, True)
        >>> [round(newton_raphson_intersect(o, r, tex, view_proj, k, fallback=False)[0].item(), 4) for k in (1, 2)]
        [4.0, 4.6648]
    """
    _check_common(positions_texture, view_proj, [(origins, "origins"), (directions, "directions")])
    _check_options(iterations, method, fallback, fd_step, tol, max_residual, return_info)
    out_dtype, work = compute_dtype(origins, directions, positions_texture, view_proj)

    # -- rays: sanitise so that nothing non-finite enters the loop -------------------------------------------------
    o = cast(origins, work)
    r = cast(directions, work)
    # scale-safe normalisation: divide by the largest absolute component first, so that |r|^2 lies in [1, 3]
    # (summing squares directly underflows to 0 near 1e-20 and overflows to inf near 1e20 in float32)
    r_max = r.abs().amax(-1)
    ray_ok = torch.isfinite(o).all(-1) & torch.isfinite(r).all(-1) & (r_max > 0)
    r = r / torch.where(ray_ok, r_max, 1.0)[..., None]
    r2 = (r * r).sum(-1)
    o = torch.where(ray_ok[..., None], o, 0.0)
    r = r / torch.sqrt(torch.where(ray_ok, r2, 1.0))[..., None]
    r = torch.where(ray_ok[..., None], r, torch.full_like(r, 3.0**-0.5))

    if initial_distance is None:
        d = torch.zeros_like(r2)
    elif isinstance(initial_distance, Tensor):
        check_tensor(initial_distance, "initial_distance")
        _shapes([(origins, "origins", "B,N,3"), (initial_distance, "initial_distance", "B,N")])
        d0 = cast(initial_distance, work)
        alive_d0 = torch.isfinite(d0)
        ray_ok = ray_ok & alive_d0
        d = torch.where(alive_d0, d0, 0.0)
    elif isinstance(initial_distance, numbers.Real) and not isinstance(initial_distance, bool):
        if not abs(float(initial_distance)) < float("inf"):
            raise ValueError(f"initial_distance: expected a finite number, got {initial_distance!r}")
        d = torch.full_like(r2, float(initial_distance))
    else:
        raise TypeError(
            f"initial_distance: expected None, a number or a (B, N) tensor, got {type(initial_distance).__name__}"
        )

    tex = _prepare_texture(cast(positions_texture, work))
    mat = _batched_matrix(view_proj, origins.shape[0], work)
    centre = _sight_centre(mat)[:, None, :]  # (B, 1, 4)
    grid_mat = _grid_matrix(mat)
    newton = method == "newton"

    def evaluate(dist: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Receiver point, hit mask, residual f, distance origin-receiver (Shah's update), point x at ``dist``."""
        x = o + dist[..., None] * r
        p, hit = _lookup(x, tex, grid_mat)
        sight = centre[..., 3:] * x - centre[..., :3]
        f = ((p - x) * sight).sum(-1) / _norm(sight)
        return p, hit, f, _norm(p - o), x

    def step(d: Tensor, d_prev: Tensor, f_prev: Tensor, alive: Tensor, oscillated: Tensor,
             used_fallback: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """One update of the estimate; the state of the first one holds f_prev = NaN (no comparison fires)."""
        _p, hit, f, dist_po, _x = evaluate(d)
        alive = alive & hit
        scale = d.abs() + dist_po
        active = alive & (f.abs() > tol * scale)  # converged rays stop moving

        if newton:
            h = fd_step * scale
            h = torch.where(h > 0, h, 1.0)
            _pq, hit_q, f_q, _dq, _xq = evaluate(d + h)
            slope = (f_q - f) / h
            usable = hit_q & (slope.abs() > _MIN_SLOPE)
            slope = torch.where(usable, slope, 1.0)
            d_new = torch.where(usable, d - f / slope, dist_po)
        else:
            d_new = dist_po

        flag = active & (f.abs() >= f_prev.abs())  # False against the NaN of the first iteration
        oscillated = oscillated | flag
        if fallback:
            # the last two estimates bracket the root and the last step did not help: bisect them
            bisect = flag & ((f > 0) != (f_prev > 0)) & (f != 0) & (f_prev != 0)
            used_fallback = used_fallback | bisect
            d_new = torch.where(bisect, 0.5 * (d + d_prev), d_new)
        return torch.where(active, d_new, d), d, f, alive, oscillated, used_fallback

    state = (d, d.clone(), torch.full_like(d, float("nan")), ray_ok, torch.zeros_like(ray_ok),
             torch.zeros_like(ray_ok))
    if iterations >= _LOOP_MIN_ITERATIONS and is_exporting():
        # one loop body in the graph (an ONNX Loop), not `iterations` unrolled copies: the export time and the
        # file stay the same for any iteration count
        from torch._higher_order_ops.while_loop import while_loop

        def body(k: Tensor, *st: Tensor) -> tuple[Tensor, ...]:
            d = st[0]
            # a loop body traced for export sees the sizes of the tensors it closes over afresh: restate them
            b, n = d.shape
            for x, sizes in ((o, (b, n, 3)), (r, (b, n, 3)), (centre, (b, 1, 4)), (grid_mat[0], (b, 3, 3)),
                             (grid_mat[1], (b, 1, 3))):
                for have, want in zip(x.shape, sizes):
                    torch._check(have == want)
            torch._check(tex.shape[0] == b)
            torch._check(tex.shape[1] == 4)
            # a loop body may not hand an input back as an output (d becomes d_prev): copy those
            return (k + 1, *(x.clone() if any(x is y for y in st) else x for x in step(*st)))

        state = tuple(while_loop(lambda k, *st: k < iterations, body,
                                 (torch.zeros((), dtype=torch.int64, device=d.device), *state))[1:])
    else:
        for _ in range(iterations):
            state = step(*state)
    d, _d_prev, f_prev, alive, oscillated, used_fallback = state

    p, hit, f, dist_po, x = evaluate(d)
    alive = alive & hit
    oscillated = oscillated | (alive & (f.abs() > tol * (d.abs() + dist_po)) & (f.abs() >= f_prev.abs()))
    q = ((p - o) * r).sum(-1)  # the receiver's coordinate along the ray: > 0 when it lies ahead of the origin
    residual = _norm(p - x)
    residual = torch.where(alive, residual, 0.0)
    valid = alive & (d > 0) & (q > 0) & torch.isfinite(d)
    if max_residual is not None:
        valid = valid & (residual <= max_residual)
    distance = torch.where(valid, d, 0.0).to(out_dtype)
    if not return_info:
        return distance, valid
    info = {"oscillated": oscillated, "fallback": used_fallback, "residual": cast(residual, out_dtype)}
    return distance, valid, info
