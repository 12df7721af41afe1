"""Export a registered torchsss module to ONNX and check it against eager PyTorch in onnxruntime.

Usage::

    python export/onnx_export.py NAME [--out PATH] [--opset 18]
    python export/onnx_export.py --list

The model is exported at the registry's example size and run at its (different) test size, so a size frozen
into the graph shows up as an error. Exit status: 0 if the maximum relative difference (over entries whose
eager value is a normal float) is <= --rtol and the zero/underflow patterns agree, 1 otherwise, 2 for usage
errors.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from torchsss.export import EXPORTABLE, MIN_OPSET, compare_with_eager, export_case, export_onnx

DEFAULT_RTOL = 1e-5


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="onnx_export.py",
        description="Export a torchsss module to ONNX (dynamo exporter) and compare onnxruntime with eager PyTorch.",
    )
    p.add_argument("name", nargs="?", help=f"registry entry, one of: {', '.join(sorted(EXPORTABLE))}")
    p.add_argument("--out", type=Path, default=None, help="output file (default: ./NAME.onnx)")
    p.add_argument("--opset", type=int, default=18, help=f"ONNX opset, >= {MIN_OPSET} (default: 18)")
    p.add_argument("--rtol", type=float, default=None,
                   help=f"largest accepted relative difference (default: the entry's own, {DEFAULT_RTOL:g} for most)")
    p.add_argument("--list", action="store_true", help="list the registry entries and exit")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    ns = parser.parse_args(argv)
    if ns.list:
        for name in sorted(EXPORTABLE):
            print(f"{name:10s} {EXPORTABLE[name]().description}")
        return 0
    if ns.name is None:
        parser.error(f"NAME: expected one of {', '.join(sorted(EXPORTABLE))} (or --list), got nothing")
    if ns.name not in EXPORTABLE:
        parser.error(f"NAME: expected one of {', '.join(sorted(EXPORTABLE))}, got {ns.name!r}")
    if ns.opset < MIN_OPSET:
        parser.error(f"--opset: expected an int >= {MIN_OPSET}, got {ns.opset}")
    if ns.rtol is not None and not ns.rtol >= 0:
        parser.error(f"--rtol: expected a number >= 0, got {ns.rtol}")

    case = export_case(ns.name)
    if ns.rtol is None:
        ns.rtol = case.rtol
    out = ns.out if ns.out is not None else Path(f"{ns.name}.onnx")
    print(f"{ns.name}: {case.description}")
    t0 = time.perf_counter()
    path = export_onnx(case.module, case.example_args, out, dynamic_shapes=case.dynamic_shapes, opset=ns.opset)
    t_export = time.perf_counter() - t0
    example = ", ".join(str(tuple(a.shape)) for a in case.example_args)
    test = ", ".join(str(tuple(a.shape)) for a in case.test_args)
    print(f"exported {path} (opset {ns.opset}) in {t_export:.2f} s at input shapes {example}")

    with torch.no_grad():
        scale = None if case.scale is None else case.scale(*case.test_args)
    res = compare_with_eager(case.module, path, case.test_args, scale=scale)
    print(f"onnxruntime vs eager at input shapes {test} -> output shapes {res['shapes']}:")
    print(f"  max abs diff = {res['max_abs_diff']:.3e}")
    print(f"  max rel diff = {res['max_rel_diff']:.3e} (over {res['compared']} normal entries; rtol {ns.rtol:g})")
    print(f"  zero pattern match = {res['zero_pattern_match']}, underflow pattern match = "
          f"{res['underflow_pattern_match']}, non-finite match = {res['nonfinite_match']}")
    ok = (res["max_rel_diff"] <= ns.rtol and res["zero_pattern_match"] and res["underflow_pattern_match"]
          and res["nonfinite_match"])
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
