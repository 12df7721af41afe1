"""ONNX export core: dynamo export with verified dynamic dimensions, onnxruntime, comparison with eager.

``onnx``, ``onnxscript`` and ``onnxruntime`` are optional dependencies (the ``export`` extra: ``pip install
torchsss[export]``); they are imported inside the functions that need them, so importing this module never
requires them.

The exporter is ``torch.onnx.export(..., dynamo=True)`` at opset 18 by default (see ``export/README.md`` for
why). Two rules follow from how it works:

- every dimension that must vary at run time has to be declared in ``dynamic_shapes`` (with
  :class:`torch.export.Dim`); a size that is not declared is frozen into the graph, and so is any Python int.
  :func:`export_onnx` reads the written file back and raises :class:`DynamicShapeError` (naming the dimension)
  when the exporter specialised a declared dimension to a constant;
- an exported model has to be checked at a size *different* from the one it was exported at, which is why
  every registry case (:mod:`torchsss.export.registry`) carries two sets of inputs.
"""

from __future__ import annotations

import importlib
import inspect
import math
import os
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

__all__ = [
    "MIN_OPSET",
    "DynamicShapeError",
    "compare_with_eager",
    "declared_dynamic_dims",
    "export_onnx",
    "rewrite_constant_pow",
    "run_onnxruntime",
    "verify_dynamic_dims",
]

#: Lowest opset accepted by :func:`export_onnx`. The dynamo exporter emits opset 18 natively; asking it for
#: less goes through a version converter that can silently leave the file at 18 (e.g. with ``Pad`` in the graph).
MIN_OPSET = 18


class DynamicShapeError(RuntimeError):
    """A dimension declared dynamic in ``dynamic_shapes`` is a constant in the exported file."""


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
    rewrite_pow: bool = True,
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
        rewrite_pow: replace ``Pow`` by a constant exponent 2, 3, 0.5 or 1.5 with ``Mul``/``Sqrt``
            (:func:`rewrite_constant_pow`): onnxruntime's ``Pow`` calls ``std::pow`` per element, several times
            slower than a multiplication (the square in a distance, :math:`x^{3/2}` in the dipole).

    Returns:
        The path written, as a :class:`pathlib.Path`.

    Raises:
        TypeError: ``module`` is not an ``nn.Module``, ``args`` is not a tuple of tensors, ``path``, ``opset``
            or the names have the wrong type.
        ValueError: ``opset`` below 18, names of the wrong count, sparse tensors in ``args``, or
            ``dynamic_shapes`` of the wrong length.
        ImportError: ``onnx``/``onnxscript`` are missing (the ``torchsss[export]`` extra).
        RuntimeError: the written file does not carry the requested opset.
        DynamicShapeError: a dimension declared in ``dynamic_shapes`` was specialised to a constant by the
            exporter (the file is left on disk for inspection).
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
        program = torch.onnx.export(
            module,
            args,
            None,
            dynamo=True,
            opset_version=opset,
            dynamic_shapes=_nest_varargs(module, dynamic_shapes),
            input_names=in_names,
            output_names=out_names,
            verbose=False,
            custom_translation_table=_translations(),
            optimize=False,
        )
    _optimize(program.model)
    program.save(path, external_data=False)
    model = onnx.load(str(path), load_external_data=False)
    if rewrite_pow and rewrite_constant_pow(model):
        onnx.save(model, str(path))
    written = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), None)
    if written != opset:
        raise RuntimeError(f"{path}: expected default-domain opset {opset} in the exported file, got {written}")
    if dynamic_shapes is not None:
        verify_dynamic_dims(model, declared_dynamic_dims(module, args, dynamic_shapes, in_names), path)
    return path


def _optimize(model: Any) -> None:
    """The exporter's optimizer (``onnxscript.optimizer.optimize_ir``) without its pattern rewriter, in place.

    Inlining, constant folding (with ONNX shape inference) and removal of unused nodes, twice or until nothing
    changes, then constants lifted to initializers, duplicates and common subexpressions merged. The rewriter's
    ~46 rules (Cast/Reshape/Transpose cleanups, Conv/BatchNorm fusions, ...) were most of the optimizer's time
    (``CausticMap``: 4.5 s of 4.5 s against 0.7 s without them; 1,225 against 1,251 nodes; onnxruntime ran the
    file without them no slower, 17.1 against 18.2 ms), and onnxruntime's own graph optimizer makes the same
    cleanups when it loads the file.
    """
    import onnx_ir as ir
    from onnx_ir.passes import common
    from onnxscript import optimizer

    optimizer.inline(model)
    for _ in range(2):
        folded = optimizer.fold_constants_ir(model, onnx_shape_inference=True)
        before = len(list(model.graph))
        optimizer.remove_unused_nodes(model)
        if not folded.modified and len(list(model.graph)) == before:
            break
    ir.passes.Sequential(
        common.RemoveUnusedFunctionsPass(),
        common.RemoveUnusedOpsetsPass(),
        common.LiftConstantsToInitializersPass(lift_all_constants=True, size_limit=0),
        common.LiftSubgraphInitializersToMainGraphPass(),
        common.DeduplicateInitializersPass(),
        common.CommonSubexpressionEliminationPass(),
        common.OutputFixPass(),
        common.NameFixPass(),
    )(model)


def _translations() -> dict[Any, Any]:
    """ONNX translations for aten ops the exporter's library lacks.

    ``aten.sym_stride.int``: the exporter leaves stride checks of a traced ``while_loop`` body (the Newton
    searches' ONNX ``Loop``) in the graph; an ONNX tensor is dense, so the stride of ``dim`` is the product of the
    sizes after it.
    """
    from onnxscript import opset18 as op

    def sym_stride(self: Any, dim: int = 0) -> Any:
        return op.ReduceProd(op.Shape(self, start=dim + 1), keepdims=0)

    return {torch.ops.aten.sym_stride.int: sym_stride}


def _nest_varargs(module: nn.Module, dynamic_shapes: Any) -> Any:
    """A flat per-argument spec for ``forward(a, *rest)`` as torch.export wants it: ``{a: .., rest: (..)}``."""
    if not isinstance(dynamic_shapes, (tuple, list)):
        return dynamic_shapes
    params = list(inspect.signature(module.forward).parameters.values())
    if not any(p.kind == p.VAR_POSITIONAL for p in params):
        return dynamic_shapes
    named = [p.name for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    var = next(p.name for p in params if p.kind == p.VAR_POSITIONAL)
    k = len(named)
    if len(dynamic_shapes) <= k:
        return dynamic_shapes
    # keyed by parameter name: the exporter turns a nested tuple spec into a list that no longer matches the args
    return {**dict(zip(named, dynamic_shapes[:k])), var: tuple(dynamic_shapes[k:])}


def _constant_values(graph: Any) -> dict[str, np.ndarray]:
    from onnx import numpy_helper

    values = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    for node in graph.node:
        if node.op_type == "Constant":
            for a in node.attribute:
                if a.name == "value":
                    values[node.output[0]] = numpy_helper.to_array(a.t)
    return values


def rewrite_constant_pow(model: Any) -> int:
    """Replace ``Pow(x, c)`` with a scalar constant ``c`` in {1, 2, 3, 0.5, 1.5} by ``Mul``/``Sqrt`` nodes, in place.

    The results agree with ``Pow`` to a few ulps (``x * sqrt(x)`` for :math:`x^{3/2}`); a ``Pow`` whose exponent is
    not such a constant is left alone. Returns the number of nodes replaced (top-level graph only).
    """
    from onnx import helper

    graph = model.graph
    consts = _constant_values(graph)
    new_nodes = []
    count = 0
    for node in graph.node:
        c = consts.get(node.input[1]) if node.op_type == "Pow" and len(node.input) == 2 else None
        value = float(c.reshape(-1)[0]) if c is not None and c.size == 1 else None
        if value not in (1.0, 2.0, 3.0, 0.5, 1.5):
            new_nodes.append(node)
            continue
        x, y, stem = node.input[0], node.output[0], node.name or f"pow_{count}"
        if value == 1.0:
            new_nodes.append(helper.make_node("Identity", [x], [y], name=f"{stem}_id"))
        elif value == 2.0:
            new_nodes.append(helper.make_node("Mul", [x, x], [y], name=f"{stem}_sq"))
        elif value == 3.0:
            new_nodes += [helper.make_node("Mul", [x, x], [f"{stem}_x2"], name=f"{stem}_sq"),
                          helper.make_node("Mul", [f"{stem}_x2", x], [y], name=f"{stem}_cube")]
        elif value == 0.5:
            new_nodes.append(helper.make_node("Sqrt", [x], [y], name=f"{stem}_sqrt"))
        else:
            new_nodes += [helper.make_node("Sqrt", [x], [f"{stem}_sqrt"], name=f"{stem}_sqrt"),
                          helper.make_node("Mul", [x, f"{stem}_sqrt"], [y], name=f"{stem}_x15")]
        count += 1
    if count:
        del graph.node[:]
        graph.node.extend(new_nodes)
        used = {i for n in graph.node for i in n.input}
        keep = [t for t in graph.initializer if t.name in used or t.name in {v.name for v in graph.output}]
        del graph.initializer[:]
        graph.initializer.extend(keep)
    return count


def _dim_name(dim: object) -> str:
    """The name of a :class:`torch.export.Dim` (or the repr of a ``Dim.AUTO``/``Dim.DYNAMIC`` hint)."""
    return str(getattr(dim, "__name__", None) or dim)


def declared_dynamic_dims(
    module: nn.Module, args: tuple[Tensor, ...], dynamic_shapes: dict[str, Any] | tuple[Any, ...] | list[Any],
    input_names: Sequence[str] | None = None,
) -> list[tuple[int, str, int, str]]:
    """The dynamic dimensions declared in ``dynamic_shapes``, one ``(arg index, input name, dim, Dim name)`` each.

    ``dynamic_shapes`` as for :func:`export_onnx`: a tuple/list in argument order or a dict keyed by ``forward``'s
    parameter names; each entry None, a dict ``{dim: Dim}`` or a tuple/list with one Dim (or None) per dimension.
    The input names are ``input_names`` or ``forward``'s parameter names (the names the exporter gives the graph
    inputs).

    Raises:
        TypeError: an entry of ``dynamic_shapes`` of another type.
        ValueError: a dict key that is not a parameter of ``forward``.
    """
    params = [p.name for p in inspect.signature(module.forward).parameters.values()
              if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    names = list(input_names) if input_names is not None else (params + [f"input_{i}" for i in range(len(args))])
    if isinstance(dynamic_shapes, dict):
        unknown = sorted(set(dynamic_shapes) - set(params[:len(args)]))
        if unknown:
            raise ValueError(f"dynamic_shapes: expected keys among forward's parameters {params[:len(args)]}, "
                             f"got {unknown}")
        per_arg = [dynamic_shapes.get(p) for p in params[:len(args)]]
    else:
        per_arg = list(dynamic_shapes)
    out = []
    for i, spec in enumerate(per_arg):
        if spec is None:
            continue
        if isinstance(spec, dict):
            items = spec.items()
        elif isinstance(spec, (tuple, list)):
            items = enumerate(spec)
        else:
            raise TypeError(f"dynamic_shapes[{i}]: expected None, a dict or a tuple/list, got {type(spec).__name__}")
        for d, dim in items:
            if dim is not None:
                out.append((i, names[i], int(d) % max(args[i].dim(), 1), _dim_name(dim)))
    return out


def verify_dynamic_dims(model: Any, declared: list[tuple[int, str, int, str]], where: object = "model") -> None:
    """Check that every declared dynamic dimension is symbolic among the graph inputs of an ONNX ``model``.

    Graph inputs are matched by name (the exporter names them after ``forward``'s parameters or
    ``input_names``), else by position among the non-initializer inputs.

    Raises:
        DynamicShapeError: a declared dimension is a constant (or missing) in the file; the message names the
            Dim, the input, the axis and the constant the exporter put there.
    """
    inits = {t.name for t in model.graph.initializer}
    graph_inputs = [v for v in model.graph.input if v.name not in inits]
    by_name = {v.name: v for v in graph_inputs}
    bad = []
    for i, name, d, dim_name in declared:
        v = by_name.get(name, graph_inputs[i] if i < len(graph_inputs) else None)
        if v is None:
            bad.append(f"{dim_name} (input {name!r}, axis {d}): the input is not in the graph")
            continue
        dims = v.type.tensor_type.shape.dim
        if d >= len(dims):
            bad.append(f"{dim_name} (input {v.name!r}, axis {d}): the input has rank {len(dims)}")
        elif not dims[d].dim_param:
            got = dims[d].dim_value if dims[d].HasField("dim_value") else "unknown"
            bad.append(f"{dim_name} (input {v.name!r}, axis {d}): specialised to {got}")
    if bad:
        raise DynamicShapeError(
            f"{where}: expected the declared dynamic dimensions to stay symbolic in the exported graph, but the "
            "exporter froze " + "; ".join(bad) + " (a Python int or a size comparison in forward() specialises "
            "it: see export/README.md)"
        )


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
    if isinstance(out, dict):  # the exporter flattens a dict output in key order
        out = list(out.values())
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


