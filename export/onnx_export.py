"""Export registered torchsss modules to ONNX and check them against eager PyTorch in onnxruntime.

Usage::

    python export/onnx_export.py NAME [--out DIR|FILE.onnx] [--opset 18] [--rtol R]
    python export/onnx_export.py --all [--out DIR] [--skip-slow]
    python export/onnx_export.py --list

Each model is exported at the registry's example size (``torchsss.export.EXPORTABLE``); ``export_onnx`` checks that
every declared dynamic dimension is symbolic in the written file. It is then run in onnxruntime (CPU, 1 thread) at
the export shapes *and* at the registry's test shapes (another batch, sample count, receiver count or image size),
and the maximum absolute and relative differences against eager PyTorch are printed. Exit status: 0 if every entry
is within its tolerance (relative difference over entries whose eager value is a normal float, or the entry's
absolute tolerance) with matching zero/underflow/non-finite patterns, 1 otherwise, 2 for usage errors.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from torchsss.export import EXPORTABLE, MIN_OPSET, compare_with_eager, export_case, export_onnx


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="onnx_export.py",
        description="Export torchsss modules to ONNX (dynamo exporter) and compare onnxruntime with eager PyTorch.",
    )
    p.add_argument("name", nargs="?", help=f"registry entry, one of: {', '.join(sorted(EXPORTABLE))}")
    p.add_argument("--all", action="store_true", help="export and check every registry entry")
    p.add_argument("--skip-slow", action="store_true", help="with --all: skip the entries marked slow")
    p.add_argument("--out", type=Path, default=None,
                   help="output directory (NAME.onnx inside) or, for one entry, a .onnx file (default: .)")
    p.add_argument("--opset", type=int, default=18, help=f"ONNX opset, >= {MIN_OPSET} (default: 18)")
    p.add_argument("--rtol", type=float, default=None, help="largest accepted relative difference (default: the "
                   "entry's own)")
    p.add_argument("--list", action="store_true", help="list the registry entries and exit")
    return p


def _ok(res: dict, rtol: float, atol: float | None) -> bool:
    close = res["max_abs_diff"] <= atol if atol is not None else res["max_rel_diff"] <= rtol
    return bool(close and res["zero_pattern_match"] and res["underflow_pattern_match"] and res["nonfinite_match"])


def run_entry(name: str, out: Path, opset: int = 18, rtol: float | None = None) -> dict:
    """Export one entry to ``out`` and compare it at the export and the test shapes; returns a summary dict."""
    case = export_case(name)
    tol = case.rtol if rtol is None else rtol
    print(f"{name}: {case.description}")
    t0 = time.perf_counter()
    path = export_onnx(case.module, case.example_args, out, dynamic_shapes=case.dynamic_shapes, opset=opset,
                       input_names=case.input_names)
    t_export = time.perf_counter() - t0
    shapes = ", ".join(str(tuple(a.shape)) for a in case.example_args)
    print(f"  exported {path} (opset {opset}) in {t_export:.2f} s at input shapes {shapes}; dynamic dims verified")
    ok = True
    results = {}
    for label, args in (("export shapes", case.example_args), ("test shapes", case.test_args)):
        with torch.no_grad():
            scale = None if case.scale is None else case.scale(*args)
        res = compare_with_eager(case.module, path, args, scale=scale)
        good = _ok(res, tol, case.atol)
        ok &= good
        results[label] = res
        shapes = ", ".join(str(tuple(a.shape)) for a in args)
        limit = f"atol {case.atol:g}" if case.atol is not None else f"rtol {tol:g}"
        print(f"  {label} {shapes} -> {res['shapes']}: max abs diff {res['max_abs_diff']:.3e}, max rel diff "
              f"{res['max_rel_diff']:.3e} ({limit}; patterns zero/underflow/non-finite "
              f"{res['zero_pattern_match']}/{res['underflow_pattern_match']}/{res['nonfinite_match']}) "
              f"{'ok' if good else 'FAIL'}")
    print("  PASS" if ok else "  FAIL")
    return {"name": name, "ok": ok, "export_s": t_export, "path": str(path), "results": results}


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    ns = parser.parse_args(argv)
    names = sorted(EXPORTABLE)
    if ns.list:
        for name in names:
            case = EXPORTABLE[name]()
            print(f"{name:18s} {'[slow] ' if case.slow else ''}{case.description}")
        return 0
    if ns.all and ns.name is not None:
        parser.error(f"NAME: expected either NAME or --all, got both ({ns.name!r} and --all)")
    if not ns.all and ns.name is None:
        parser.error(f"NAME: expected one of {', '.join(names)} (or --all, --list), got nothing")
    if ns.name is not None and ns.name not in EXPORTABLE:
        parser.error(f"NAME: expected one of {', '.join(names)}, got {ns.name!r}")
    if ns.opset < MIN_OPSET:
        parser.error(f"--opset: expected an int >= {MIN_OPSET}, got {ns.opset}")
    if ns.rtol is not None and not ns.rtol >= 0:
        parser.error(f"--rtol: expected a number >= 0, got {ns.rtol}")
    out = Path(".") if ns.out is None else ns.out
    if ns.all:
        todo = [n for n in names if not (ns.skip_slow and EXPORTABLE[n]().slow)]
        if out.suffix == ".onnx":
            parser.error(f"--out: expected a directory with --all, got {str(out)!r}")
    else:
        todo = [ns.name]
    summary = []
    for name in todo:
        path = out if (len(todo) == 1 and out.suffix == ".onnx") else out / f"{name}.onnx"
        try:
            summary.append(run_entry(name, path, ns.opset, ns.rtol))
        except Exception as err:  # report and go on with the other entries
            print(f"  FAIL: {type(err).__name__}: {err}")
            summary.append({"name": name, "ok": False, "export_s": float("nan")})
    if len(summary) > 1:
        print("\nentry              export s  result")
        for s in summary:
            print(f"{s['name']:18s} {s['export_s']:8.1f}  {'PASS' if s['ok'] else 'FAIL'}")
    return 0 if all(s["ok"] for s in summary) else 1


if __name__ == "__main__":
    sys.exit(main())
