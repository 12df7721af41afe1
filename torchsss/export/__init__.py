"""ONNX export of torchsss modules: the dynamo exporter, verified dynamic shapes, onnxruntime parity, a registry.

- :mod:`torchsss.export.core`: :func:`export_onnx` (raises :class:`DynamicShapeError` when the exporter froze a
  declared dynamic dimension), :func:`run_onnxruntime`, :func:`compare_with_eager`;
- :mod:`torchsss.export.registry`: :data:`EXPORTABLE`, every per-frame module with inputs at two sizes;
- :mod:`torchsss.export.materials`: materials as graph inputs (:func:`with_material_inputs`);
- :mod:`torchsss.export.adapters`: the splat graph that reports truncated splats (:class:`SplatExport`).

``onnx``, ``onnxscript`` and ``onnxruntime`` are optional (``pip install torchsss[export]``) and imported only by
the functions that need them.
"""

from torchsss.export.adapters import OptionalArgs, SplatExport
from torchsss.export.core import (
    MIN_OPSET,
    DynamicShapeError,
    compare_with_eager,
    declared_dynamic_dims,
    export_onnx,
    rewrite_constant_pow,
    run_onnxruntime,
    verify_dynamic_dims,
)
from torchsss.export.materials import InputDipoleMaterial, MaterialInputs, with_material_inputs
from torchsss.export.registry import EXPORTABLE, MATERIAL_PRESETS, ExportCase, export_case, material_inputs

__all__ = [
    "EXPORTABLE",
    "MATERIAL_PRESETS",
    "MIN_OPSET",
    "DynamicShapeError",
    "ExportCase",
    "InputDipoleMaterial",
    "MaterialInputs",
    "OptionalArgs",
    "SplatExport",
    "compare_with_eager",
    "declared_dynamic_dims",
    "export_case",
    "export_onnx",
    "material_inputs",
    "rewrite_constant_pow",
    "run_onnxruntime",
    "verify_dynamic_dims",
    "with_material_inputs",
]
