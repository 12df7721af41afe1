"""Fused kernels for the per-frame hot loops, compiled once per process with ``torch.compile``.

Each kernel here is written once, as a plain tensor expression (the *eager* form), and compiled with
``torch.compile``: inductor turns it into one C++/OpenMP loop nest on the CPU (a Triton kernel on
CUDA) that never materialises the full-size temporaries the eager form builds. The eager chains stay the
reference the compiled paths are tested against and the fallback where compilation is unavailable.

When compilation is used (:func:`use_compiled`):

* ``TORCHSSS_COMPILE=0`` (or ``off``/``false``/``no``) never compiles; ``TORCHSSS_COMPILE=1`` always compiles
  (tests); the default (``auto``) compiles a kernel variant once the eager work spent on it in this process
  reaches about one compile's time (:data:`COLD_WORK`; a compile takes 5-15 s cold on the 2-core CPU machine,
  1-3 s when inductor's on-disk cache already holds the kernel), and uses an already compiled variant for every
  call above :data:`WARM_WORK`. The test suite runs with ``TORCHSSS_COMPILE=0`` (``tests/conftest.py``) except
  where a test switches it on, so results do not depend on test order.
* Never while autograd records through the inputs (the compiled kernels are inference paths), while tracing or
  exporting, or on devices other than CPU and CUDA.
* A compile that fails (no C++ compiler, an unsupported platform) warns once and falls back to eager for the rest
  of the process.

Every call of a compiled kernel has the same static shapes (inputs are cut into fixed blocks, the last one
padded) and materials are tensor inputs, so a new light, camera, sample count or material does not recompile:
only a new dtype, device or variant (e.g. with or without a distance scale) does (tested with ``torch._dynamo``
counters).

The kernels:

* :func:`dipole_pair_sum`: the all-pairs sum of the reference integrator with the analytic dipole of
  :func:`torchsss.dipole_rd` inlined, channel-major so the reduction over sources vectorises (about 54 Mpairs/s on
  one core in float32, against 6-7 for the eager chunked chain; :func:`reference_radiosity` dispatches to it).
"""

from __future__ import annotations

import contextlib
import math
import os
import warnings
import weakref
from collections.abc import Callable, Iterator

import torch
from torch import Tensor

from torchsss._checks import is_tracing
from torchsss.physics.budget import chang_local_weight
from torchsss.physics.fresnel import dipole_boundary_a

__all__ = [
    "COLD_WORK",
    "WARM_WORK",
    "block_shape",
    "compile_mode",
    "compile_policy",
    "derived",
    "dipole_pair_sum",
    "dipole_pair_sum_eager",
    "dipole_taps",
    "dipole_taps_eager",
    "eligible",
    "expected_work",
    "is_warm",
    "use_compiled",
    "would_compile",
]

#: Eager work (e.g. source-receiver pairs) spent on a variant in this process after which it is compiled
#: (``auto`` mode): at the eager path's 6-10 Mpairs/s this is 3.5-6 s, about one cold compile (5-7 s on the 2-core
#: CPU machine with an empty inductor cache, :func:`_compile_config`).
COLD_WORK = 1 << 25
#: Work above which an already compiled variant is used (``auto`` mode); below it the call overhead dominates.
WARM_WORK = 1 << 14

#: Receivers x sources per compiled call, by device. Inductor stores the call's :math:`(B, C, m, n)` block of
#: squared reduced distances once (both dipole sources read it); 512 x 2048 keeps it in cache on the CPU (55-61
#: Mpairs/s per core measured; recomputing it instead costs 2.5x). On CUDA, larger calls fill the GPU.
_BLOCKS = {"cpu": (512, 2048), "cuda": (8192, 8192)}
#: Pairs per compiled call of :func:`dipole_taps`.
_TAPS = 1 << 18  # the eager splat paths' chunk (torchsss.ops.splat._EVAL_PAIRS): full chunks need no padding
#: Pairs per eager block (each holds several (B, C, m, n) temporaries).
_EAGER_PAIRS = 1 << 20

_COMPILED: dict[str, Callable] = {}
_WARM: set[tuple] = set()
_EAGER_WORK: dict[tuple, float] = {}
_BROKEN: dict[str, str] = {}
_EXPECTED: dict[str, float] = {}
_RAN: set[tuple] = set()  # variants whose compiled form has run (compiled: no ISA setting needed any more)


def block_shape(device: str = "cpu") -> tuple[int, int]:
    """(receivers, sources) of one static block of the compiled :func:`dipole_pair_sum` on a device type.

    A compiled call pads its receivers and sources to whole blocks, so it evaluates whole blocks of pairs.

    Examples:
        >>> block_shape("cpu")
        (512, 2048)
    """
    return _BLOCKS.get(device, _BLOCKS["cpu"])


def compile_mode() -> str:
    """``"off"``, ``"on"`` or ``"auto"`` from the ``TORCHSSS_COMPILE`` environment variable (read on every call)."""
    v = os.environ.get("TORCHSSS_COMPILE", "auto").strip().lower()
    if v in ("0", "off", "false", "no"):
        return "off"
    if v in ("1", "on", "true", "yes", "always"):
        return "on"
    return "auto"


def compile_policy(work: float, *, warm: bool, mode: str | None = None) -> bool:
    """The compile rule as a pure function: whether a call of ``work`` units runs compiled.

    ``mode`` (default :func:`compile_mode`): ``off``: never; ``on``: always; ``auto``: a variant already compiled in
    this process (``warm``) serves every call of :data:`WARM_WORK` or more, a cold one compiles when ``work`` (the
    eager work spent on it so far, this call's included, or the announced :func:`expected_work`) reaches
    :data:`COLD_WORK`. :func:`use_compiled` and :func:`would_compile` apply it to this process's accounts; the
    planner (:mod:`torchsss.plan`) applies it to the kernels it assumes warm.

    Examples:
        >>> compile_policy(COLD_WORK, warm=False, mode="auto"), compile_policy(1, warm=True, mode="auto")
        (True, False)
    """
    mode = compile_mode() if mode is None else mode
    if mode not in ("off", "on", "auto"):
        raise ValueError(f"mode: expected 'off', 'on', 'auto' or None, got {mode!r}")
    if mode == "off":
        return False
    if mode == "on":
        return True
    return work >= (WARM_WORK if warm else COLD_WORK)


def eligible(name: str, tensors: tuple[Tensor, ...]) -> bool:
    """Whether kernel ``name`` may run compiled on ``tensors`` at all, whatever the work.

    Not switched off (``TORCHSSS_COMPILE=0``), not broken in this process, nothing traced or exported, a CPU or
    CUDA device, and nothing recorded by autograd through ``tensors``.

    Examples:
        >>> eligible("dipole_pair_sum", (torch.zeros(2, requires_grad=True),)) and torch.is_grad_enabled()
        False
    """
    if compile_mode() == "off" or name in _BROKEN or is_tracing():
        return False
    if any(t.device.type not in ("cpu", "cuda") for t in tensors):
        return False
    return not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))


def use_compiled(name: str, variant: tuple, work: float, tensors: tuple[Tensor, ...]) -> bool:
    """Whether kernel ``name``'s ``variant`` runs compiled for a call of ``work`` units on ``tensors``.

    :func:`eligible` and then :func:`compile_policy`: in ``auto`` mode a variant not yet compiled in this process
    stays eager until the eager work spent on it (this call's included) reaches :data:`COLD_WORK`, about one
    compile's time (the ski-rental rule: at most twice the cost of the better choice in hindsight); a compiled
    variant serves every call of :data:`WARM_WORK` or more. A call answered False is counted as eager work. Inside
    :func:`expected_work` the call counts as the whole announced work (a caller that cuts one frame into blocks
    compiles at its first block when the frame pays for a compile, instead of spending :data:`COLD_WORK` eagerly
    first).
    """
    if not eligible(name, tensors):
        return False
    if compile_mode() == "on":
        return True  # no accounts kept (the tests' mode)
    key = (name, *variant)
    if key in _WARM:
        return compile_policy(work, warm=True)
    spent = _EAGER_WORK.get(key, 0.0) + float(work)
    if compile_policy(max(spent, _EXPECTED.get(name, 0.0)), warm=False):
        _WARM.add(key)  # the caller compiles now: later calls of this variant find it warm
        return True
    _EAGER_WORK[key] = spent
    return False


def would_compile(name: str, work: float, tensors: tuple[Tensor, ...] = (), **variant: object) -> bool:
    """Whether a call of kernel ``name`` with ``work`` units on ``tensors`` would run compiled now (no side effects).

    As :func:`use_compiled`: :func:`eligible` on ``tensors`` (none given: only the mode and a broken kernel are
    checked), then :func:`compile_policy` with the variant warm when a matching one is (``variant``: the filters of
    :func:`is_warm`, e.g. ``truncated=True``) and, for a cold one, the work or the announced :func:`expected_work`.
    A caller that chooses between a compiled form and another path asks this first.

    Examples:
        >>> would_compile("dipole_pair_sum", 0) in (True, False)
        True
    """
    if not eligible(name, tensors):
        return False
    if is_warm(name, **variant):
        return compile_policy(work, warm=True)
    return compile_policy(max(float(work), _EXPECTED.get(name, 0.0)), warm=False)


@contextlib.contextmanager
def expected_work(name: str, work: float) -> Iterator[None]:
    """Announce that the calls of kernel ``name`` inside this block add up to about ``work`` units.

    :func:`use_compiled` then decides at the first call as if the whole work came at once (``auto`` mode: compile
    at once when ``work`` reaches :data:`COLD_WORK`), so a frame cut into blocks does not spend a compile's worth
    of eager work before it compiles. Nested blocks: the innermost announcement counts.

    Examples:
        >>> with expected_work("dipole_pair_sum", 1e9):
        ...     pass
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a kernel name (str), got {type(name).__name__}")
    if not (isinstance(work, (int, float)) and not isinstance(work, bool) and math.isfinite(work) and work >= 0):
        raise ValueError(f"work: expected a finite number >= 0, got {work!r}")
    before = _EXPECTED.get(name)
    _EXPECTED[name] = float(work)
    try:
        yield
    finally:
        if before is None:
            _EXPECTED.pop(name, None)
        else:
            _EXPECTED[name] = before


def is_warm(name: str, *, device: str = "cpu", dtype: torch.dtype = torch.float32, split: bool | None = None,
            truncated: bool | None = None) -> bool:
    """Whether this process has already compiled a variant of kernel ``name`` on ``device`` in ``dtype``.

    The planner (:func:`torchsss.plan.plan`) charges no compile to a method whose kernel is warm. ``split`` (for
    ``dipole_pair_sum``): only variants with (True) or without (False) the local/global split count; None: any.
    ``truncated`` likewise for the splat's truncated gather (a variant of its own). Every variant key starts with
    (device type, dtype); those of ``dipole_pair_sum`` end with the split flag, after ``"truncated"`` if truncated.

    Examples:
        >>> is_warm("no_such_kernel")
        False
    """
    return any(k[0] == name and k[1] == device and k[2] == dtype and (split is None or k[-1] is split)
               and (truncated is None or ("truncated" in k) is truncated) for k in _WARM)


def _compiled(name: str, eager: Callable) -> Callable:
    """The compiled twin of ``eager`` (one per process), tagged with ``name`` and ``eager`` for :func:`_call`."""
    fn = _COMPILED.get(name)
    if fn is None:
        fn = _COMPILED[name] = torch.compile(eager, dynamic=False)
        fn.torchsss_name, fn.torchsss_eager = name, eager
    return fn


def _compile_config() -> contextlib.AbstractContextManager:
    """Inductor settings for our compiles: trust the CPU's ISA flags instead of building a probe per ISA.

    With an empty inductor cache, inductor's first CPU compile in a process builds and loads a probe program for
    every vector ISA the CPU reports (AMX, AVX512-VNNI, AVX512, AVX2: 6-8 s of a 12-13 s cold compile on the 2-core
    CPU machine); ``cpp.vec_isa_ok = True`` takes the CPU's flags for it (the same ISA is picked here; a cold
    compile of :func:`dipole_pair_sum` then takes 5-6 s). Left alone when the user set ``vec_isa_ok``
    (``TORCHINDUCTOR_VEC_ISA_OK``); :func:`_call` retries with inductor's own probes if a compile fails this way.
    """
    try:
        from torch._inductor import config
    except Exception:  # no inductor: the compile fails and falls back as usual
        return contextlib.nullcontext()
    if getattr(config.cpp, "vec_isa_ok", False) is not None:
        return contextlib.nullcontext()
    return config.patch({"cpp.vec_isa_ok": True})


def _reset_isa() -> None:
    """Forget inductor's ISA list (computed with trusted flags) so that a retry probes the compiler."""
    try:
        from torch._inductor import cpu_vec_isa
        cpu_vec_isa.valid_vec_isa_list.cache_clear()
    except Exception:
        pass


def _call(kernel: Callable, variant: tuple, *args: Tensor | None) -> Tensor:
    """``kernel(*args)``; a compiled kernel that fails warns once and falls back to its eager form for good."""
    name = getattr(kernel, "torchsss_name", None)
    if name is None:
        return kernel(*args)
    if name in _BROKEN:
        return kernel.torchsss_eager(*args)
    # the ISA setting matters when inductor compiles: on a variant's first call (its shapes are static), not on the
    # hundreds of block calls of a frame after it (the patch costs about 0.1 ms a call)
    config = _compile_config() if (name, *variant) not in _RAN else contextlib.nullcontext()
    try:
        try:
            with config:
                out = kernel(*args)
        except Exception:
            if isinstance(config, contextlib.nullcontext):
                raise
            _reset_isa()  # perhaps the compiler cannot build a reported ISA: inductor's own probes decide
            out = kernel(*args)
    except Exception as err:  # a missing compiler or an unsupported platform: fall back to eager for good
        _BROKEN[name] = f"{type(err).__name__}: {err}"
        warnings.warn(f"torchsss: compiling {name} failed ({_BROKEN[name][:200]}); using the eager path",
                      RuntimeWarning, stacklevel=3)
        return kernel.torchsss_eager(*args)
    _WARM.add((name, *variant))
    _RAN.add((name, *variant))
    return out


def dipole_params(profile: object, dtype: torch.dtype, device: torch.device, channels: int
                  ) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]] | None:
    """``(coefficients as given, coefficients on device in dtype promoted with theirs)`` of a plain dipole, or None.

    A profile is the plain dipole of :func:`torchsss.dipole_rd` when its class offers ``dipole_coefficients()``
    (``(sigma_a, sigma_s_prime, eta)``, as :class:`~torchsss.DipoleMaterial` does; a wrapper that forwards attribute
    lookups, such as a tabulated profile, does not count) and it has ``channels`` channels. The first tuple is for
    :func:`use_compiled`'s autograd check, the second for the kernels.
    """
    if not callable(getattr(type(profile), "dipole_coefficients", None)):
        return None
    params = tuple(profile.dipole_coefficients())
    if params[0].numel() != channels:
        return None
    dtype = torch.promote_types(dtype, params[0].dtype)  # as the eager sum: a float64 profile widens
    return params, tuple(t.to(device=device, dtype=dtype) for t in params)


def _dipole_rd(rho2: Tensor, sigma_a: Tensor, sigma_s_prime: Tensor, eta: Tensor, view: tuple[int, ...]) -> Tensor:
    """:math:`R_d` from squared reduced distances :math:`\\rho^2 = (r M_d \\sigma_t')^2`.

    The :math:`(C,)` coefficients are viewed as ``view`` (e.g. ``(C, 1)`` channels-first columns, or
    ``(1, C, 1, 1)``) to broadcast with ``rho2``; the bounded-factor form of :func:`torchsss.dipole_rd`:
    :math:`\\sigma_s' \\sigma_t' (1/D + \\beta) e^{-\\beta D} / D^2` per source.
    """
    st = (sigma_a + sigma_s_prime).reshape(view)
    beta = torch.sqrt(3.0 * sigma_a.reshape(view) / st)          # sigma_tr z_r
    zeta = (1.0 + 4.0 / 3.0 * dipole_boundary_a(eta)).reshape(view)  # z_v / z_r
    ss = sigma_s_prime.reshape(view)

    def source(dist: Tensor) -> Tensor:
        inv = torch.reciprocal(dist)
        return (ss * inv) * (st * inv) * (inv + beta) * torch.exp(-beta * dist)

    return (source(torch.sqrt(rho2 + 1.0)) + zeta * source(torch.sqrt(rho2 + zeta * zeta))) * (0.25 / math.pi)


def dipole_taps_eager(r: Tensor, flux: Tensor, r_max: Tensor, sigma_a: Tensor, sigma_s_prime: Tensor, eta: Tensor,
                      distance_scale: Tensor | None = None) -> Tensor:
    """The eager form of :func:`dipole_taps` (same arguments and result, no validation)."""
    r_eff = r[None] if distance_scale is None else r[None] * distance_scale     # (1 | C, P)
    st = (sigma_a + sigma_s_prime)[:, None]
    rd = _dipole_rd((r_eff * st) ** 2, sigma_a, sigma_s_prime, eta, (-1, 1))    # (C, P)
    return torch.where(r_eff <= r_max, rd * flux, torch.zeros_like(rd))


def dipole_taps(r: Tensor, flux: Tensor, r_max: Tensor, sigma_a: Tensor, sigma_s_prime: Tensor, eta: Tensor,
                distance_scale: Tensor | None = None, *, compiled: bool | None = None) -> Tensor:
    """Truncated splat weights :math:`R_d(r M_d)\\,[r M_d \\le r_{max}]\\, E\\,dA` of a list of pairs, fused.

    The per-pair work of Shah's splatting (:func:`~torchsss.ops.splat.splat_radiosity`'s eager window and tile
    paths) for the plain dipole: one compiled pointwise kernel (:func:`use_compiled` decides) over fixed blocks of
    :data:`_TAPS` pairs (the last padded), so that no pair count recompiles. Inputs are trusted (validated by the
    caller).

    Args:
        r: :math:`(P,)` distances in mm.
        flux: :math:`(C, P)` the source's :math:`E\\,dA\\,M_i` per pair.
        r_max: scalar or :math:`(1, 1)` truncation radius in mm (of the scaled distance).
        sigma_a: :math:`(C,)` absorption in mm^-1.
        sigma_s_prime: :math:`(C,)` reduced scattering in mm^-1.
        eta: scalar or :math:`(C,)`.
        distance_scale: optional :math:`(1 \\text{ or } C, P)` :math:`M_d` per pair.
        compiled: as :func:`dipole_pair_sum`.

    Returns:
        :math:`(C, P)` weights.
    """
    c, p = flux.shape
    eta = eta.reshape(-1).expand(c).contiguous()
    r_max = r_max.reshape(1, 1)
    tensors = tuple(t for t in (r, flux, r_max, sigma_a, sigma_s_prime, eta, distance_scale) if t is not None)
    variant = (r.device.type, r.dtype, c, None if distance_scale is None else distance_scale.shape[0])
    if compiled is None:
        compiled = use_compiled("dipole_taps", variant, float(p), tensors)
    if not (compiled and eligible("dipole_taps", tensors)) or p == 0:
        return dipole_taps_eager(r, flux, r_max, sigma_a, sigma_s_prime, eta, distance_scale)
    kernel = _compiled("dipole_taps", dipole_taps_eager)
    args = tuple(_fresh(t) for t in (r_max, sigma_a, sigma_s_prime, eta))
    out = []
    for p0 in range(0, p, _TAPS):
        n = min(_TAPS, p - p0)
        pad = _TAPS - n

        def block(x: Tensor, fill: float, n=n, p0=p0, pad=pad) -> Tensor:
            x = x if (p0, n) == (0, x.shape[-1]) else x[..., p0:p0 + n]
            return _fresh(torch.cat([x, x.new_full((*x.shape[:-1], pad), fill)], -1) if pad else x)

        ds = None if distance_scale is None else block(distance_scale, 1.0)
        part = _call(kernel, variant, block(r, 0.0), block(flux, 0.0), *args, ds)
        out.append(part[:, :n])
    return torch.cat(out, 1)


def dipole_pair_sum_eager(dst_pos: Tensor, src_pos: Tensor, weight: Tensor, sigma_a: Tensor, sigma_s_prime: Tensor,
                          eta: Tensor, distance_scale: Tensor | None = None, src_ids: Tensor | None = None,
                          dst_ids: Tensor | None = None, split: Tensor | None = None,
                          r_max: Tensor | None = None) -> Tensor:
    """The eager form of :func:`dipole_pair_sum` (materialises :math:`(B, C, M, N)`: small inputs only).

    Same arguments and result as :func:`dipole_pair_sum` (``split`` and ``r_max`` as tensors), no validation.
    """
    st4 = (sigma_a + sigma_s_prime)[None, :, None, None]
    r2 = sum((dst_pos[:, :, None, k] - src_pos[:, None, :, k]) ** 2 for k in range(3))[:, None]  # (B, 1, M, N)
    if distance_scale is not None:                               # M_d of the source: rho = r M_d sigma_t'
        md = distance_scale.transpose(1, 2)[:, :, None, :]       # (B, 1|C, 1, N)
        r2 = r2 * (md * md)
    rd = _dipole_rd(r2 * (st4 * st4), sigma_a, sigma_s_prime, eta, (1, -1, 1, 1))  # (B, C, M, N)
    if r_max is not None:  # Shah's truncation of the scaled distance (the splat's disk)
        rd = torch.where(r2 <= r_max * r_max, rd, torch.zeros_like(rd))
    if src_ids is not None:
        same = (dst_ids[:, None, :, None] == src_ids[:, None, None, :]).to(rd.dtype)  # (B, 1, M, N)
        if split is None:
            rd = rd * same
        else:  # Chang's global part: 1 - W_l^b(r M_d) where the pair shares a chart (chang_weights' corrected sign)
            r = torch.sqrt(r2)
            w_l = torch.where(r <= split[2], chang_local_weight(r, split[0], split[1]), torch.zeros_like(r))
            rd = rd * (1.0 - w_l * same)
    return (rd * weight.transpose(1, 2)[:, :, None, :]).sum(-1).transpose(1, 2)


def dipole_pair_sum(dst_pos: Tensor, src_pos: Tensor, weight: Tensor, sigma_a: Tensor, sigma_s_prime: Tensor,
                    eta: Tensor, distance_scale: Tensor | None = None, *, src_ids: Tensor | None = None,
                    dst_ids: Tensor | None = None, split: tuple[float, float, float] | None = None,
                    r_max: float | None = None, compiled: bool | None = None) -> Tensor:
    """:math:`B_{b,m,c} = \\sum_n w_{b,n,c}\\, R_{d,c}(|x_{b,m} - y_{b,n}|\\, M_{d,b,n})`: the dipole pair sum, fused.

    The analytic dipole of :func:`torchsss.dipole_rd` (Jensen et al. 2001, with the same bounded-factor form in
    units of :math:`z_r = 1/\\sigma_t'`), evaluated and summed in one compiled kernel when
    :func:`use_compiled` allows (else the eager form, in blocks of receivers that bound its memory). Inputs are
    trusted (validated by the caller, :func:`~torchsss.ops.reference.reference_radiosity`): finite, one dtype
    and device, ``sigma_a >= 0``, ``sigma_a + sigma_s_prime > 0``, ``eta > 0``. Not differentiable through the
    compiled path (the caller uses it for inference only).

    Args:
        dst_pos: :math:`(B, M, 3)` receivers in mm.
        src_pos: :math:`(B, N, 3)` sources in mm.
        weight: :math:`(B, N, C)` :math:`E_i A_i M_i` of each source.
        sigma_a: :math:`(C,)` absorption in mm^-1.
        sigma_s_prime: :math:`(C,)` reduced scattering in mm^-1.
        eta: scalar, :math:`(1,)` or :math:`(C,)` relative index of refraction.
        distance_scale: optional :math:`(B, N, 1)` or :math:`(B, N, C)` distance multiplier :math:`M_d`.
        src_ids: optional :math:`(B, N)` integer ids (objects or atlas charts) of the sources; with ``dst_ids``
            :math:`(B, M)`, a pair whose ids differ does not interact.
        dst_ids: the receivers' ids, with ``src_ids``.
        split: optional ``(r_p, k, bound)`` of Chang's split (:class:`~torchsss.modules.chang.ChangLocalProfile`):
            with ids, a pair's kernel is :math:`R_d (1 - W_l^b(r M_d)\\,[\\xi_i = \\xi_o])` (the hybrid's global
            part: sources in another chart stay whole) instead of :math:`R_d [\\xi_i = \\xi_o]`.
        r_max: optional truncation radius in mm: a pair contributes only where :math:`|x - y| M_d \\le r_{max}`
            (Shah's splat disk; :func:`~torchsss.ops.splat.splat_radiosity`'s gather form).
        compiled: None: :func:`use_compiled` decides; True: compiled wherever compilation is allowed at all (the
            caller decided, e.g. from the work of a whole frame); False: eager.

    Returns:
        :math:`(B, M, C)` radiosity in the inputs' dtype.

    Examples:
        >>> x = torch.rand(1, 50, 3) * 10
        >>> sa, ss = torch.tensor([0.01, 0.02, 0.03]), torch.tensor([1.0, 1.2, 1.5])
        >>> dipole_pair_sum(x[:, :5], x, torch.full((1, 50, 3), 0.1), sa, ss, torch.tensor(1.3)).shape
        torch.Size([1, 5, 3])
    """
    b, m = dst_pos.shape[:2]
    n, c = weight.shape[1:]
    eta = eta.reshape(-1).expand(c).contiguous()  # one rank and stride for every caller (else another graph)
    args = (sigma_a, sigma_s_prime, eta)
    if (src_ids is None) != (dst_ids is None) or (split is not None and src_ids is None):
        raise ValueError("src_ids, dst_ids, split: expected both ids or neither, and ids with split")
    window = None if split is None else torch.tensor([float(v) for v in split], dtype=weight.dtype,
                                                     device=weight.device)
    trunc = None if r_max is None else torch.tensor(float(r_max), dtype=weight.dtype, device=weight.device)
    tensors = tuple(t for t in (dst_pos, src_pos, weight, *args, distance_scale) if t is not None)
    # (the split flag stays last: is_warm reads it there)
    variant = (dst_pos.device.type, dst_pos.dtype, b, c, None if distance_scale is None else distance_scale.shape[-1],
               src_ids is not None) + (("truncated",) if trunc is not None else ()) + (split is not None,)
    if m == 0 or n == 0:
        return weight.new_zeros(b, m, c)
    if compiled is None:
        compiled = use_compiled("dipole_pair_sum", variant, float(b) * m * n, tensors)
    extra = (distance_scale, src_ids, dst_ids, window, trunc)
    if not (compiled and eligible("dipole_pair_sum", tensors)):
        m_step = max(1, min(m, _EAGER_PAIRS // 1024))
        n_step = max(1, _EAGER_PAIRS // m_step)
        return _blocks(dipole_pair_sum_eager, variant, dst_pos, src_pos, weight, args, extra, m_step, n_step)
    # static blocks: every call has the same shapes (the inputs are padded to whole blocks with zero-weight
    # sources and repeated receivers), so one graph serves every sample and receiver count
    m_step, n_step = block_shape(dst_pos.device.type)
    m_pad, n_pad = -m % m_step, -n % n_step
    if m_pad:
        dst_pos = torch.cat([dst_pos, dst_pos[:, :1].expand(b, m_pad, 3)], 1)
        if dst_ids is not None:
            dst_ids = torch.cat([dst_ids, dst_ids[:, :1].expand(b, m_pad)], 1)
    if n_pad:
        src_pos = torch.cat([src_pos, src_pos[:, :1].expand(b, n_pad, 3)], 1)
        weight = torch.cat([weight, weight.new_zeros(b, n_pad, c)], 1)
        if distance_scale is not None:
            distance_scale = torch.cat([distance_scale, distance_scale.new_ones(b, n_pad, distance_scale.shape[-1])], 1)
        if src_ids is not None:
            src_ids = torch.cat([src_ids, src_ids[:, :1].expand(b, n_pad)], 1)
    kernel = _compiled("dipole_pair_sum", dipole_pair_sum_eager)
    out = _blocks(kernel, variant, dst_pos, src_pos, weight, args, (distance_scale, src_ids, dst_ids, window, trunc),
                  m_step, n_step)
    return out[:, :m]


def _fresh(x: Tensor) -> Tensor:
    """``x`` with the standard contiguous strides (a copy unless it has them already).

    A compiled graph guards on strides, and a sliced size-1 dimension keeps its parent's stride through
    ``.contiguous()`` and ``.clone()``.
    """
    stride, step = [], 1
    for size in reversed(x.shape):
        stride.append(step)
        step *= size
    if tuple(reversed(stride)) == tuple(x.stride()):
        return x
    return torch.empty(x.shape, dtype=x.dtype, device=x.device).copy_(x)


def _blocks(kernel: Callable, variant: tuple, dst_pos: Tensor, src_pos: Tensor, weight: Tensor,
            args: tuple[Tensor, ...], extra: tuple[Tensor | None, ...], m_step: int, n_step: int) -> Tensor:
    """``kernel`` over blocks of ``m_step`` receivers x ``n_step`` sources, summed over the source blocks.

    ``extra`` is ``(distance_scale, src_ids, dst_ids, split, r_max)``: per-source, per-source, per-receiver, whole,
    whole.
    """
    m, n = dst_pos.shape[1], src_pos.shape[1]
    distance_scale, src_ids, dst_ids, split, r_max = extra
    blocks = []
    args = tuple(_fresh(a) for a in args)
    split = None if split is None else _fresh(split)
    for m0 in range(0, m, m_step):
        acc = None
        # fresh blocks with the standard strides (a sliced size-1 batch keeps its parent's stride through
        # .contiguous() and .clone()): the compiled graph guards on strides
        dst = _fresh(dst_pos[:, m0:m0 + m_step])
        did = None if dst_ids is None else _fresh(dst_ids[:, m0:m0 + m_step])
        for n0 in range(0, n, n_step):
            sl = slice(n0, n0 + n_step)
            ds = None if distance_scale is None else _fresh(distance_scale[:, sl])
            sid = None if src_ids is None else _fresh(src_ids[:, sl])
            part = _call(kernel, variant, dst, _fresh(src_pos[:, sl]), _fresh(weight[:, sl]), *args, ds, sid, did,
                         split, r_max)
            acc = part if acc is None else acc + part
        blocks.append(acc)
    return torch.cat(blocks, 1)


# -- helpers for kernels called once per frame ---------------------------------------------------------------------
#: Most tensors :func:`derived` keeps at a time (the oldest is dropped first).
_DERIVED_MAX = 8
_DERIVED: dict[tuple, tuple] = {}


def _version(t: Tensor) -> int | None:
    return None if t.is_inference() else t._version


def derived(tag: tuple, tensors: tuple[Tensor, ...], compute: Callable[[], object]) -> object:
    """``compute()``, cached while ``tensors`` are the same objects with the same data (a constant re-layout).

    For data that is constant across frames (Lensch's kernels and throughput values, built once) and that a fast
    path wants in another layout: the re-layout is computed on the first call and reused while every tensor of
    ``tensors`` is the same live object at the same address with the same version counter. Inference tensors
    (made under ``torch.inference_mode``) have no version counter: an in-place change to one of them *inside*
    inference mode is not seen (outside inference mode torch forbids it). The entry goes when a tensor is freed;
    at most :data:`_DERIVED_MAX` entries are kept. ``tag`` names the re-layout (and whatever else ``compute``
    depends on, e.g. a dtype). Not for tensors that autograd records through (the result would be detached from
    later graphs): callers use it on inference paths only.
    """
    key = (tag, *(id(t) for t in tensors))
    state = tuple((t.data_ptr(), _version(t), t.shape, t.stride(), t.dtype, t.device) for t in tensors)
    hit = _DERIVED.get(key)
    if hit is not None:
        refs, old_state, value = hit
        if all(r() is t for r, t in zip(refs, tensors)) and old_state == state:
            return value
    value = compute()

    def forget(ref, key=key):  # drop the entry of a freed tensor (not a newer entry that reuses its id)
        entry = _DERIVED.get(key)
        if entry is not None and any(r is ref for r in entry[0]):
            del _DERIVED[key]

    refs = tuple(weakref.ref(t, forget) for t in tensors)
    _DERIVED.pop(key, None)
    while len(_DERIVED) >= _DERIVED_MAX:
        _DERIVED.pop(next(iter(_DERIVED)))
    _DERIVED[key] = (refs, state, value)
    return value
