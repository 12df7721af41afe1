"""Input validation shared by every public function.

Every check raises :class:`TypeError` (wrong kind of object or dtype) or :class:`ValueError` (wrong shape or
value) with a message that names the argument and says what was expected and what was got. Value checks that
need to look at tensor data are skipped while a graph is being traced, compiled or exported, so that
``forward()`` stays exportable.
"""

from __future__ import annotations

import contextlib
import numbers
import os
from collections.abc import Collection, Iterator, Mapping, Sequence

import torch
from torch import Tensor

__all__ = [
    "as_float_tensor",
    "cast",
    "check_broadcastable",
    "check_device",
    "check_devices",
    "check_finite",
    "check_finite_inputs",
    "check_nonnegative",
    "check_positive",
    "check_shape",
    "check_tensor",
    "compute_dtype",
    "is_exporting",
    "is_tracing",
    "set_validation",
    "skip_value_checks",
    "validation",
    "validation_enabled",
]

_REDUCED = (torch.float16, torch.bfloat16)


def is_tracing() -> bool:
    """True while torch.jit, torch.compile, torch.export or the ONNX exporter is tracing the current call."""
    return bool(
        torch.jit.is_tracing()
        or torch.compiler.is_compiling()
        or torch.compiler.is_exporting()
        or torch.onnx.is_in_onnx_export()
    )


def is_exporting() -> bool:
    """True while torch.jit, torch.export or the ONNX exporter traces the call (not plain ``torch.compile``).

    Under ``torch.compile`` alone, data-dependent Python code still runs (dynamo breaks the graph around it), so
    an op may keep its eager path there; an exported graph cannot.
    """
    return bool(torch.jit.is_tracing() or torch.compiler.is_exporting() or torch.onnx.is_in_onnx_export())


_VALIDATE = os.environ.get("TORCHSSS_VALIDATE", "1").strip().lower() not in ("0", "false", "off", "no")


def validation_enabled() -> bool:
    """Whether value checks run (non-finite inputs, ranges); True by default.

    The environment variable ``TORCHSSS_VALIDATE=0`` turns them off for a whole process; :func:`set_validation`
    and :func:`validation` switch them at run time. Type, shape and device checks always run (they read no
    tensor data and cost nothing).

    Examples:
        >>> validation_enabled()
        True
    """
    return _VALIDATE


def set_validation(enabled: bool) -> bool:
    """Switch the value checks of every op and module on or off; return the previous setting.

    With validation on (the default), a module given a NaN or infinite input raises ValueError naming the input
    and the first bad index, instead of returning NaN or a plausible wrong value. The checks read tensor data
    (one reduction per input and a host synchronisation); switch them off in a tight loop once the inputs are
    known to be good (``benchmarks/bench_validation.py`` measures their cost). They never run while tracing,
    compiling or exporting.

    Raises:
        TypeError: ``enabled`` is not a bool.

    Examples:
        >>> previous = set_validation(False)
        >>> validation_enabled()
        False
        >>> _ = set_validation(previous)
    """
    global _VALIDATE
    if not isinstance(enabled, bool):
        raise TypeError(f"enabled: expected a bool, got {type(enabled).__name__}")
    previous, _VALIDATE = _VALIDATE, enabled
    return previous


@contextlib.contextmanager
def validation(enabled: bool) -> Iterator[None]:
    """Context manager: value checks on or off inside the ``with`` block (see :func:`set_validation`).

    Examples:
        >>> with validation(False):
        ...     validation_enabled()
        False
    """
    previous = set_validation(enabled)
    try:
        yield
    finally:
        set_validation(previous)


def skip_value_checks(*tensors: object) -> bool:
    """True where checks that read tensor data must not run.

    That is while tracing, compiling or exporting, when validation is switched off (:func:`set_validation`), or
    when one of ``tensors`` lives on the meta device (shapes and dtypes only, no data: ``.item()`` would raise).
    """
    return (not _VALIDATE) or is_tracing() or any(isinstance(t, Tensor) and t.device.type == "meta" for t in tensors)


def check_tensor(x: object, name: str) -> Tensor:
    """Return ``x`` if it is a real floating-point tensor, else raise TypeError naming ``name``."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.is_complex():
        raise TypeError(f"{name}: expected a real floating-point tensor, got complex dtype {x.dtype}")
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")
    return x


def check_devices(
    tensors: Mapping[str, object], *, floating: bool | Collection[str] = (), allow_meta: bool = True
) -> torch.device | None:
    """Check that the tensors of one call share one device; return it (None without tensors).

    Call it first, before anything reads tensor data (host synchronisation), so that mixed devices fail with a
    clear message instead of inside torch. ``tensors`` maps argument names to the arguments, in the order they
    are checked; ``None`` and non-tensor entries are skipped (unless named in ``floating``). Names in
    ``floating`` (``True``: every entry) must be real floating-point tensors (:func:`check_tensor`). Tensors on
    the meta device carry no data: with ``allow_meta=False`` (ops whose eager path reads values) they raise;
    otherwise the caller skips its value checks (:func:`skip_value_checks`).

    Raises:
        TypeError: a ``floating`` entry that is not a real floating-point tensor (named).
        ValueError: a tensor on another device than the first tensor (both named, both devices), or on the
            meta device when ``allow_meta`` is False.

    Examples:
        >>> check_devices({"a": torch.zeros(2), "b": None, "c": torch.ones(1)}, floating=True)
        device(type='cpu')
        >>> check_devices({"a": torch.zeros(2), "b": torch.zeros(2, device="meta")})
        Traceback (most recent call last):
        ...
        ValueError: b: expected a tensor on a's device cpu, got one on meta
    """
    first: tuple[str, torch.device] | None = None
    for name, x in tensors.items():
        if floating is True or (not isinstance(floating, bool) and name in floating):
            if x is not None:
                check_tensor(x, name)
        if not isinstance(x, Tensor):
            continue
        if first is None:
            first = (name, x.device)
        elif x.device != first[1]:
            raise ValueError(f"{name}: expected a tensor on {first[0]}'s device {first[1]}, got one on {x.device}")
        if not allow_meta and x.device.type == "meta":
            raise ValueError(
                f"{name}: expected a tensor with data (cpu, cuda, ...), got one on the meta device "
                "(this op reads tensor values)"
            )
    return None if first is None else first[1]


def as_float_tensor(x: object, name: str, like: Tensor | None = None) -> Tensor:
    """Convert a Python number, sequence or tensor to a floating tensor on ``like``'s device.

    Tensors keep their own dtype (promotion happens later, never a silent downcast); Python numbers and
    sequences take ``like``'s dtype (float32 without ``like``).
    """
    if isinstance(x, Tensor):
        return check_tensor(x, name)
    if isinstance(x, bool) or not isinstance(x, (int, float, Sequence)):
        raise TypeError(f"{name}: expected a tensor, a number or a sequence of numbers, got {type(x).__name__}")
    dtype = like.dtype if like is not None and like.is_floating_point() else torch.get_default_dtype()
    device = like.device if like is not None else None
    try:
        return torch.as_tensor(x, dtype=dtype, device=device)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name}: expected numbers, got {x!r}") from err


def compute_dtype(*tensors: Tensor) -> tuple[torch.dtype, torch.dtype]:
    """Return ``(out_dtype, compute_dtype)`` for a set of floating inputs.

    The output dtype is the promotion of all inputs. float16 and bfloat16 are computed in float32 (the dipole
    spans too many orders of magnitude for 5- or 8-bit mantissas and exponents) and cast back.
    """
    out = tensors[0].dtype
    for t in tensors[1:]:
        out = torch.promote_types(out, t.dtype)
    return out, (torch.float32 if out in _REDUCED else out)


def cast(x: Tensor, dtype: torch.dtype) -> Tensor:
    """``x.to(dtype)``, or ``x`` itself when it already has that dtype.

    The same values either way; a traced graph (``torch.export`` / ONNX) gets no node for the no-op (``x.to`` of
    the same dtype records two, and every node costs export time).
    """
    return x if x.dtype == dtype else x.to(dtype)


def check_broadcastable(**tensors: Tensor) -> torch.Size:
    """Return the broadcast shape of the named tensors, or raise ValueError listing every shape."""
    try:
        return torch.broadcast_shapes(*(t.shape for t in tensors.values()))
    except RuntimeError as err:
        shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in tensors.items())
        raise ValueError(f"shapes do not broadcast (trailing dimension = channels): {shapes}") from err


def _report(x: Tensor, bad: Tensor, name: str, expected: str) -> None:
    """Raise ValueError naming ``name``, the first bad value, its index and the count, if ``bad`` has a True entry."""
    if bool(bad.any()):
        first = x.detach()[bad].flatten()[0].item()
        where = ""
        if bad.dim() > 0:
            flat = int(bad.flatten().nonzero()[0, 0])
            index = tuple(int(i) for i in torch.unravel_index(torch.tensor(flat), tuple(bad.shape)))
            where = f", the first at index {index}"
        raise ValueError(
            f"{name}: expected {expected}, got {first!r} ({int(bad.sum())} of {x.numel()} entries bad{where})"
        )


def check_finite(x: Tensor, name: str) -> None:
    """Raise ValueError if ``x`` holds a NaN or infinite entry (naming the first and its index).

    Skipped while tracing and on the meta device.

    Examples:
        >>> check_finite(torch.tensor([[1.0, float("nan")]]), "src_pos")
        Traceback (most recent call last):
        ...
        ValueError: src_pos: expected finite values, got nan (1 of 2 entries bad, the first at index (0, 1))
    """
    if skip_value_checks(x):
        return
    _report(x, ~torch.isfinite(x), name, "finite values")


def check_finite_inputs(inputs: Mapping[str, Tensor | None], where: Tensor | None = None) -> None:
    """Run :func:`check_finite` on each named input (``None`` entries skipped), in order.

    ``where`` (bool, expandable to each input's shape) restricts the check to entries that are used, e.g. the pixels
    of a mask (positions off the mask may hold anything).

    Examples:
        >>> check_finite_inputs({"light": torch.zeros(1, 4), "intensity": torch.tensor([[1.0, float("inf")]])})
        Traceback (most recent call last):
        ...
        ValueError: intensity: expected finite values, got inf (1 of 2 entries bad, the first at index (0, 1))
    """
    if skip_value_checks(*inputs.values(), where):
        return
    for name, x in inputs.items():
        if x is None:
            continue
        bad = ~torch.isfinite(x)
        if where is not None:
            bad = bad & where.expand_as(bad)
        _report(x, bad, name, "finite values")


def check_nonnegative(x: Tensor, name: str, allow_inf: bool = False) -> None:
    """Raise ValueError if ``x`` holds a negative, NaN (or, unless allowed, infinite) entry.

    Skipped while tracing and on the meta device.
    """
    if skip_value_checks(x):
        return
    bad = torch.isnan(x) | (x < 0)
    if not allow_inf:
        bad |= torch.isinf(x)
    _report(x, bad, name, "finite values >= 0" if not allow_inf else "values >= 0")


def check_positive(x: Tensor, name: str) -> None:
    """Raise ValueError if ``x`` holds an entry that is <= 0, NaN or infinite.

    Skipped while tracing and on the meta device.
    """
    if skip_value_checks(x):
        return
    _report(x, ~torch.isfinite(x) | (x <= 0), name, "finite values > 0")



def check_int(value: object, name: str, minimum: int, maximum: int | None = None) -> int:
    """Return ``value`` as an int, or raise TypeError (not an integer; bools are refused) / ValueError (out of range).

    Examples:
        >>> check_int(3, "layers", 1)
        3
    """
    expected = f"an int >= {minimum}" if maximum is None else f"an int in [{minimum}, {maximum}]"
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name}: expected {expected}, got {type(value).__name__}")
    if value < minimum or (maximum is not None and value > maximum):
        raise ValueError(f"{name}: expected {expected}, got {value!r}")
    return int(value)

def check_shape(x: Tensor, name: str, dims: str, **known: int) -> dict[str, int]:
    """Check ``x`` against a named-dimension pattern such as ``"B,N,3"`` and return the sizes found.

    Letters are free dimensions (bound on first use, also across calls through ``known``); integers must match
    exactly. Raises ValueError ``"<name>: expected shape (B, N, 3), got (2, 5, 4)"``.
    """
    names = [d.strip() for d in dims.split(",")]
    sizes = dict(known)
    pattern = "(" + ", ".join(names) + ")"
    if x.dim() != len(names):
        raise ValueError(f"{name}: expected shape {pattern} ({len(names)} dims), got {tuple(x.shape)}")
    for dim_name, size in zip(names, x.shape):
        if dim_name.isdigit():
            if size != int(dim_name):
                raise ValueError(f"{name}: expected shape {pattern}, got {tuple(x.shape)}")
        elif dim_name in sizes and sizes[dim_name] != size:
            raise ValueError(
                f"{name}: expected shape {pattern} with {dim_name}={sizes[dim_name]}, got {tuple(x.shape)}"
            )
        else:
            # int() would specialise a dynamic dimension to a constant while exporting: keep the symbol then
            sizes[dim_name] = size if is_tracing() else int(size)
    return sizes


def check_device(device: str | torch.device) -> torch.device:
    """``device`` as a :class:`torch.device` that this process can use (the renderers follow their mesh's device).

    Raises:
        TypeError: not a string or a device.
        ValueError: an unknown device, or an accelerator this process does not have (named).

    Examples:
        >>> check_device("cpu")
        device(type='cpu')
    """
    if not isinstance(device, (str, torch.device)):
        raise TypeError(f"device: expected a str or torch.device, got {type(device).__name__}")
    try:
        dev = torch.device(device)
    except RuntimeError as err:
        raise ValueError(f"device: expected a torch device such as 'cpu' or 'cuda', got {device!r}") from err
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device: expected an available device, got {device!r} (torch.cuda.is_available() is "
                         f"False in this process)")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device: expected 'cpu' or 'cuda', got {device!r}")
    return dev
