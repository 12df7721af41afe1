"""ONNX export scaffolding: export a module with the dynamo exporter, run it in onnxruntime, compare with eager.

``onnx``, ``onnxscript`` and ``onnxruntime`` are optional dependencies (the ``export`` extra: ``pip install
torchsss[export]``); they are imported inside the functions that need them, so importing this module never
requires them.

The exporter is ``torch.onnx.export(..., dynamo=True)`` at opset 18 by default (see ``export/README.md`` for
why). Two rules follow from how it works:

- every dimension that must vary at run time has to be declared in ``dynamic_shapes`` (with
  :class:`torch.export.Dim`); a size that is not declared is frozen into the graph, and so is any Python int;
- an exported model has to be checked at a size *different* from the one it was exported at, which is why
  every :class:`ExportCase` carries two sets of inputs.

:data:`EXPORTABLE` lists the modules that are known to export and to match eager PyTorch in onnxruntime.

Examples:
    >>> sorted(EXPORTABLE)
    ['lensch', 'material', 'profile']
    >>> case = export_case("profile")
    >>> tuple(case.example_args[0].shape), tuple(case.test_args[0].shape)
    ((4, 48, 1), (3, 101, 1))
"""

from __future__ import annotations

import importlib
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from torchsss.geometry import build_atlas, build_throughput, local_kernel_geometry, sphere, vertex_weights
from torchsss.modules import DipoleMaterial, DipoleProfile, GlobalResponse, LenschTranslucency, LocalResponse
from torchsss.physics.materials import preset

__all__ = [
    "EXPORTABLE",
    "MIN_OPSET",
    "ExportCase",
    "compare_with_eager",
    "export_case",
    "export_onnx",
    "run_onnxruntime",
]

#: Lowest opset accepted by :func:`export_onnx`. The dynamo exporter emits opset 18 natively; asking it for
#: less goes through a version converter that can silently leave the file at 18 (e.g. with ``Pad`` in the graph).
MIN_OPSET = 18

_EXTRA_HINT = "install the optional dependencies with `pip install torchsss[export]`"

# ONNX tensor element types (as onnxruntime reports them) -> numpy dtypes, for input checks.
_ORT_DTYPES = {
    "tensor(float)": np.float32,
    "tensor(double)": np.float64,
    "tensor(float16)": np.float16,
    "tensor(int64)": np.int64,
    "tensor(int32)": np.int32,
    "tensor(bool)": np.bool_,
}


def _require(module_name: str) -> ModuleType:
    """Import an optional dependency or raise ImportError naming the ``torchsss[export]`` extra."""
    try:
        return importlib.import_module(module_name)
    except ImportError as err:
        raise ImportError(f"torchsss.export needs the optional dependency {module_name!r}; {_EXTRA_HINT}") from err


def _check_module(module: object, name: str = "module") -> nn.Module:
    if not isinstance(module, nn.Module):
        raise TypeError(f"{name}: expected a torch.nn.Module, got {type(module).__name__}")
    return module


def _check_tensor_tuple(args: object, name: str) -> tuple[Tensor, ...]:
    if isinstance(args, Tensor):
        raise TypeError(f"{name}: expected a tuple of tensors, got a single Tensor (pass a 1-tuple `(x,)`)")
    if not isinstance(args, tuple):
        raise TypeError(f"{name}: expected a tuple of tensors, got {type(args).__name__}")
    for i, a in enumerate(args):
        if not isinstance(a, Tensor):
            raise TypeError(f"{name}[{i}]: expected a torch.Tensor, got {type(a).__name__}")
        if a.is_sparse or a.layout != torch.strided:
            raise ValueError(f"{name}[{i}]: expected a dense (strided) tensor, got layout {a.layout}")
    return args


def _check_names(names: object, name: str, count: int | None) -> list[str] | None:
    if names is None:
        return None
    if isinstance(names, str) or not isinstance(names, Sequence):
        raise TypeError(f"{name}: expected a sequence of str, got {type(names).__name__}")
    for i, n in enumerate(names):
        if not isinstance(n, str) or not n:
            raise TypeError(f"{name}[{i}]: expected a non-empty str, got {n!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"{name}: expected unique names, got {list(names)}")
    if count is not None and len(names) != count:
        raise ValueError(f"{name}: expected {count} names (one per input tensor), got {len(names)}")
    return list(names)


class _EvalMode:
    """Put a module tree in eval mode for the duration of a ``with`` block, restoring each submodule's flag."""

    def __init__(self, module: nn.Module) -> None:
        self.module = module
        self.flags: list[tuple[nn.Module, bool]] = []

    def __enter__(self) -> nn.Module:
        self.flags = [(m, m.training) for m in self.module.modules()]
        self.module.eval()
        return self.module

    def __exit__(self, *exc: object) -> None:
        for m, flag in self.flags:
            m.training = flag


def export_onnx(
    module: nn.Module,
    args: tuple[Tensor, ...],
    path: str | os.PathLike,
    *,
    dynamic_shapes: dict[str, Any] | tuple[Any, ...] | list[Any] | None = None,
    opset: int = 18,
    input_names: Sequence[str] | None = None,
    output_names: Sequence[str] | None = None,
) -> Path:
    """Export ``module`` to an ONNX file with the dynamo exporter (``torch.onnx.export(..., dynamo=True)``).

    The module is traced in eval mode (each submodule's training flag is restored afterwards) without
    autograd. Weights are stored inside the file (no external data). The exporter's optimizer folds arithmetic
    that depends only on parameters and buffers into constants (e.g. :class:`DipoleMaterial`'s softplus), so
    such parameters do not appear under their own names; folding is evaluated by ONNX, not by torch, and can
    differ from eager by a few ulps.

    Args:
        module: the module to export; ``forward`` is called as ``module(*args)``.
        args: example inputs, a tuple of dense tensors, e.g. ``(r,)`` with ``r`` of shape :math:`(N, 1)` in mm.
            Their sizes are frozen into the graph unless declared in ``dynamic_shapes``.
        path: file to write (parent directories are created).
        dynamic_shapes: as for :func:`torch.export.export`: one entry per argument (``None`` = static, or a
            dict ``{dim: torch.export.Dim("N")}``), as a tuple/list in argument order or a dict keyed by the
            ``forward`` parameter names.
        opset: default-domain ONNX opset, >= :data:`MIN_OPSET` (18).
        input_names: optional names of the graph inputs, one per tensor in ``args`` (default: the ``forward``
            parameter names).
        output_names: optional names of the graph outputs.

    Returns:
        The path written, as a :class:`pathlib.Path`.

    Raises:
        TypeError: ``module`` is not an ``nn.Module``, ``args`` is not a tuple of tensors, ``path``, ``opset``
            or the names have the wrong type.
        ValueError: ``opset`` below 18, names of the wrong count, sparse tensors in ``args``, or
            ``dynamic_shapes`` of the wrong length.
        ImportError: ``onnx``/``onnxscript`` are missing (the ``torchsss[export]`` extra).
        RuntimeError: the written file does not carry the requested opset.
    """
    _check_module(module)
    args = _check_tensor_tuple(args, "args")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
    if isinstance(opset, bool) or not isinstance(opset, int):
        raise TypeError(f"opset: expected an int, got {type(opset).__name__}")
    if opset < MIN_OPSET:
        raise ValueError(f"opset: expected an int >= {MIN_OPSET} (the dynamo exporter's native opset), got {opset}")
    if dynamic_shapes is not None:
        if not isinstance(dynamic_shapes, (dict, tuple, list)):
            raise TypeError(f"dynamic_shapes: expected a dict, tuple or list, got {type(dynamic_shapes).__name__}")
        if isinstance(dynamic_shapes, (tuple, list)) and len(dynamic_shapes) != len(args):
            raise ValueError(f"dynamic_shapes: expected {len(args)} entries (one per argument), "
                             f"got {len(dynamic_shapes)}")
    in_names = _check_names(input_names, "input_names", len(args))
    out_names = _check_names(output_names, "output_names", None)
    onnx = _require("onnx")
    _require("onnxscript")

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with _EvalMode(module), torch.no_grad():
        torch.onnx.export(
            module,
            args,
            path,
            dynamo=True,
            opset_version=opset,
            dynamic_shapes=dynamic_shapes,
            input_names=in_names,
            output_names=out_names,
            external_data=False,
        )
    model = onnx.load(str(path), load_external_data=False)
    written = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), None)
    if written != opset:
        raise RuntimeError(f"{path}: expected default-domain opset {opset} in the exported file, got {written}")
    return path


def run_onnxruntime(
    path: str | os.PathLike, inputs: tuple[Tensor, ...], *, intra_op_threads: int = 1
) -> list[np.ndarray]:
    """Run an ONNX file in onnxruntime on the CPU and return its outputs.

    Args:
        path: the ONNX file.
        inputs: one tensor per graph input, in graph order (the order of ``forward``'s arguments); they are
            detached and copied to the CPU.
        intra_op_threads: onnxruntime's intra-op thread count; 1 (the default) makes reductions and scatters
            deterministic, 0 lets onnxruntime choose.

    Returns:
        The graph outputs as numpy arrays, in graph order.

    Raises:
        TypeError: ``inputs`` is not a tuple of tensors, a tensor's dtype differs from the graph input's,
            or ``intra_op_threads`` is not an int.
        ValueError: wrong number of inputs, ``intra_op_threads < 0``, or ``path`` does not exist.
        ImportError: ``onnxruntime`` is missing (the ``torchsss[export]`` extra).
    """
    inputs = _check_tensor_tuple(inputs, "inputs")
    if isinstance(intra_op_threads, bool) or not isinstance(intra_op_threads, int):
        raise TypeError(f"intra_op_threads: expected an int, got {type(intra_op_threads).__name__}")
    if intra_op_threads < 0:
        raise ValueError(f"intra_op_threads: expected an int >= 0, got {intra_op_threads}")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
    if not Path(path).is_file():
        raise ValueError(f"path: expected an existing ONNX file, got {str(path)!r}")
    ort = _require("onnxruntime")

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = intra_op_threads
    opts.inter_op_num_threads = 1 if intra_op_threads == 1 else 0
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    session = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    graph_inputs = session.get_inputs()
    if len(graph_inputs) != len(inputs):
        names = ", ".join(i.name for i in graph_inputs)
        raise ValueError(f"inputs: expected {len(graph_inputs)} tensors ({names}), got {len(inputs)}")
    feed = {}
    for i, (spec, t) in enumerate(zip(graph_inputs, inputs)):
        arr = t.detach().cpu().contiguous().numpy()
        want = _ORT_DTYPES.get(spec.type)
        if want is not None and arr.dtype != want:
            raise TypeError(f"inputs[{i}] ({spec.name}): expected dtype {np.dtype(want).name}, got {arr.dtype.name}")
        feed[spec.name] = arr
    return list(session.run(None, feed))


def _flatten_outputs(out: object) -> list[Tensor]:
    if isinstance(out, Tensor):
        return [out]
    if isinstance(out, (tuple, list)):
        flat: list[Tensor] = []
        for o in out:
            flat.extend(_flatten_outputs(o))
        return flat
    raise TypeError(f"module output: expected a tensor or a tuple/list of tensors, got {type(out).__name__}")


def compare_with_eager(
    module: nn.Module, path: str | os.PathLike, inputs: tuple[Tensor, ...], *, intra_op_threads: int = 1,
    scale: Tensor | Sequence[Tensor] | None = None,
) -> dict[str, Any]:
    """Run ``module`` eagerly (eval mode, no grad) and the ONNX file in onnxruntime on ``inputs``; compare.

    Differences are computed in float64 over entries that are finite in both results. The relative difference
    ``|onnx - eager| / |eager|`` only counts entries where ``|eager|`` is a normal number of its dtype
    (``> finfo.tiny``): below that, values are zero or subnormal and only their pattern is compared.

    Args:
        module: the eager module the file was exported from.
        path: the ONNX file.
        inputs: a tuple of tensors, ideally of a different size than the export size.
        intra_op_threads: passed to :func:`run_onnxruntime`.
        scale: optional per-entry magnitude of what each output entry sums (one tensor per output, the output's
            shape), for outputs that are sums of terms of both signs: the relative difference is then
            ``|onnx - eager| / max(|eager|, scale)``, the error relative to the size of the summands (a sum that
            cancels to ~0 carries the rounding of its terms, which no runtime reproduces bit for bit).

    Returns:
        A dict with

        - ``max_abs_diff``: largest absolute difference (``inf`` if the non-finite entries differ);
        - ``max_rel_diff``: largest relative difference over normal eager entries (``inf`` likewise);
        - ``shapes``: list of output shapes (tuples), equal in both runtimes;
        - ``zero_pattern_match``: whether exact zeros are in the same places;
        - ``underflow_pattern_match``: whether the entries below ``finfo.tiny`` in magnitude (zeros and
          subnormals) are in the same places;
        - ``nonfinite_match``: whether inf/NaN entries agree;
        - ``compared``: number of entries that entered ``max_rel_diff``.

    Raises:
        TypeError, ValueError: bad arguments (see :func:`run_onnxruntime`).
        RuntimeError: the two runtimes return a different number of outputs or different shapes.
    """
    _check_module(module)
    inputs = _check_tensor_tuple(inputs, "inputs")
    onnx_out = run_onnxruntime(path, inputs, intra_op_threads=intra_op_threads)
    with _EvalMode(module), torch.no_grad():
        eager_out = _flatten_outputs(module(*inputs))
    if len(eager_out) != len(onnx_out):
        raise RuntimeError(f"outputs: expected {len(eager_out)} from eager, got {len(onnx_out)} from onnxruntime")

    scales: list[Tensor | None] = [None] * len(eager_out)
    if scale is not None:
        scales = [scale] if isinstance(scale, Tensor) else list(scale)
        if len(scales) != len(eager_out):
            raise ValueError(f"scale: expected one tensor per output ({len(eager_out)}), got {len(scales)}")
    max_abs = max_rel = 0.0
    zero_ok = under_ok = finite_ok = True
    compared = 0
    shapes = []
    for k, (e_t, o) in enumerate(zip(eager_out, onnx_out)):
        e = e_t.detach().cpu().numpy()
        if e.shape != o.shape:
            raise RuntimeError(f"output {k}: expected shape {e.shape} (eager), got {o.shape} (onnxruntime)")
        shapes.append(tuple(e.shape))
        e64, o64 = e.astype(np.float64), o.astype(np.float64)
        tiny = float(np.finfo(e.dtype).tiny) if np.issubdtype(e.dtype, np.floating) else 0.0
        both = np.isfinite(e64) & np.isfinite(o64)
        inf_e, inf_o = np.isinf(e64), np.isinf(o64)
        nonfinite_same = (np.array_equal(np.isnan(e64), np.isnan(o64)) and np.array_equal(inf_e, inf_o)
                          and np.array_equal(e64[inf_e], o64[inf_o]))
        finite_ok &= nonfinite_same
        zero_ok &= np.array_equal(e64 == 0, o64 == 0)
        under_ok &= np.array_equal(both & (np.abs(e64) < tiny), both & (np.abs(o64) < tiny))
        if not nonfinite_same:
            max_abs = max_rel = math.inf
            continue
        diff = np.abs(o64[both] - e64[both])
        if diff.size:
            max_abs = max(max_abs, float(diff.max()))
        normal = both & (np.abs(e64) > tiny)
        compared += int(normal.sum())
        if normal.any():
            den = np.abs(e64)
            if scales[k] is not None:
                den = np.maximum(den, np.abs(scales[k].detach().cpu().numpy().astype(np.float64)))
            max_rel = max(max_rel, float((np.abs(o64[normal] - e64[normal]) / den[normal]).max()))
    return {
        "max_abs_diff": max_abs,
        "max_rel_diff": max_rel,
        "shapes": shapes,
        "zero_pattern_match": bool(zero_ok),
        "underflow_pattern_match": bool(under_ok),
        "nonfinite_match": bool(finite_ok),
        "compared": compared,
    }


# -- registry -----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExportCase:
    """A module with inputs at two sizes, ready for :func:`export_onnx` and :func:`compare_with_eager`.

    Attributes:
        module: the module to export.
        example_args: inputs at the export size.
        test_args: inputs at a different size (other dynamic dims), to check that no size was frozen.
        dynamic_shapes: the ``dynamic_shapes`` spec for :func:`export_onnx` (uses :class:`torch.export.Dim`).
        description: one line saying what the graph computes, with shapes and units.
        rtol: the largest elementwise relative difference onnxruntime vs eager that the entry accepts.
        scale: for outputs that sum terms of both signs, ``scale(*test_args)`` gives the magnitude of the summands
            per entry; the relative difference is taken against it where the sum cancels.
    """

    module: nn.Module
    example_args: tuple[Tensor, ...]
    test_args: tuple[Tensor, ...]
    dynamic_shapes: dict[str, Any] | tuple[Any, ...] | None
    description: str
    rtol: float = 1e-5
    #: optional: test inputs -> per-entry magnitude of the summands of each output (see :func:`compare_with_eager`)
    scale: Callable[..., Tensor] | None = None


def _distances(shape: tuple[int, ...], r_max_mm: float) -> Tensor:
    """Evenly spaced distances 0..r_max_mm (mm, float32, both ends included) reshaped to ``shape``."""
    return torch.linspace(0.0, r_max_mm, math.prod(shape), dtype=torch.float32).reshape(shape)


def _profile_case() -> ExportCase:
    p = preset("marble")
    material = (
        torch.tensor(p.sigma_a, dtype=torch.float32),
        torch.tensor(p.sigma_s_prime, dtype=torch.float32),
        torch.tensor([p.eta], dtype=torch.float32),
    )
    n, m = torch.export.Dim("N"), torch.export.Dim("M")
    return ExportCase(
        module=DipoleProfile(),
        example_args=(_distances((4, 48, 1), 30.0), *material),
        test_args=(_distances((3, 101, 1), 30.0), *material),
        dynamic_shapes=({0: n, 1: m}, None, None, None),
        description="DipoleProfile: r (N, M, 1) mm, sigma_a/sigma_s_prime (3,) mm^-1, eta (1,) -> R_d (N, M, 3) "
                    "mm^-2; example material: marble",
    )


def _material_case() -> ExportCase:
    n = torch.export.Dim("N")
    return ExportCase(
        module=DipoleMaterial.from_preset("skin1"),
        example_args=(_distances((64, 1), 30.0),),
        test_args=(_distances((257, 1), 30.0),),
        dynamic_shapes=({0: n},),
        description="DipoleMaterial('skin1'), parameters folded into the graph: r (N, 1) mm -> R_d (N, 3) mm^-2",
    )


def _lensch_case() -> ExportCase:
    mesh = sphere(6.0, 2)
    atlas = build_atlas(mesh, 64, kernel_size=5)
    sa, ss, eta = preset("skin1").tensors(torch.float32)
    mat = DipoleMaterial(sa, ss, eta)
    module = LenschTranslucency(
        LocalResponse(local_kernel_geometry(atlas, 5), mat),
        GlobalResponse(vertex_weights(mesh, atlas), build_throughput(mesh, mat), mat, atlas.valid_mask,
                       method="scatter"),  # the exported graph's summation order, so eager and ORT compare tightly
    )
    gen = torch.Generator().manual_seed(0)
    e1 = torch.rand(1, 3, 64, 64, generator=gen) * atlas.valid_mask
    e2 = torch.rand(3, 3, 64, 64, generator=gen) * atlas.valid_mask
    return ExportCase(
        module=module,
        example_args=(e1,),
        test_args=(e2,),
        dynamic_shapes=({0: torch.export.Dim("B")},),
        description="LenschTranslucency per frame (skin1, 10k-texel sphere atlas, 5x5 kernels, 162 vertices): "
                    "irradiance atlas (B, 3, 64, 64) -> radiosity atlas (B, 3, 64, 64)",
        # float32 sums of 25 kernel taps and ~160 vertex terms, in a different order than eager's in-place
        # accumulation: measured 1.3e-5 elementwise (2.4e-7 absolute at values up to ~0.1). The dual-basis vertex
        # irradiance of random texels is signed, so local + global can cancel to ~1e-6 at values of ~0.04: the
        # difference is taken relative to |local| + |global| (one float32 rounding of a summand is 0.4% of such
        # a sum).
        rtol=5e-5,
        scale=lambda e: module.local(e).abs() + module.global_response(e).abs(),
    )


#: Exportable modules by name; each value builds a fresh :class:`ExportCase`.
EXPORTABLE: dict[str, Callable[[], ExportCase]] = {
    "profile": _profile_case,
    "material": _material_case,
    "lensch": _lensch_case,
}


def export_case(name: str) -> ExportCase:
    """Build the :class:`ExportCase` registered under ``name`` in :data:`EXPORTABLE`.

    Raises:
        TypeError: ``name`` is not a str.
        ValueError: unknown name; the message lists the valid ones.
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a str, got {type(name).__name__}")
    if name not in EXPORTABLE:
        raise ValueError(f"name: expected one of {', '.join(sorted(EXPORTABLE))}, got {name!r}")
    return EXPORTABLE[name]()
