"""Pixel integration: each method's default image against an exact 4x4-supersampled reference (issue 16).

An independent reference or a path tracer integrates every pixel; one ray per pixel is all or nothing at
silhouettes and at back-lit terminators. For each scene the truth is the reference at a finer spacing (``eps``
0.003) rendered on the 4x4 sub-pixel grid (``subpixel="exact"``; B on every sub-pixel where it is not smooth,
``tests/test_coarse.py``) and box-filtered. Every method, at the knobs ``render --method M`` plans for it
(``plan_method`` at ``--tolerance``), renders one frame at 1 spp and at the render command's default
(:data:`torchsss.cli.DEFAULT_SPP` sub-pixels, the radiosity upsampled, ``torchsss.pipelines.subpixel``); the
reference also with 2x2 and 3x3 rendered exactly. Reported: relative RMSE against the truth over the pixels both
cover, the frame time and the sub-pixel G-buffer's share of it.

Usage::

    python benchmarks/bench_subpixel.py                       # the back-lit torus and bunny at 256x256 (~15 min)
    python benchmarks/bench_subpixel.py --scenes torus-15-apple-back --methods reference lensch
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from torchsss.bench import finish_benchmark
from torchsss.cli import DEFAULT_SPP
from torchsss.plan import plan_method
from torchsss.registry import build_scene
from torchsss.trade import image_error

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_spread import SPREAD, spread_scene

RESULTS_DIR = Path(__file__).resolve().parent / "results"
METHODS = ("reference", "splat", "icdf", "hybrid", "lensch")
COLUMNS = ["scene", "method", "spp", "subpixel", "rel_rmse", "frame_s", "t_subpixel_s", "knobs"]


def run(name: str, methods, tolerance: float, log=print) -> list[dict]:
    scene = spread_scene(name)
    t0 = time.perf_counter()
    truth = build_scene(scene, "reference", eps=0.003).render(scene.lights, scene.camera, spp=16)
    rows = [{"scene": name, "method": "truth", "spp": 16, "subpixel": "exact", "frame_s": time.perf_counter() - t0,
             "knobs": "eps 0.003"}]
    for method in methods:
        knobs = {} if method == "reference" else plan_method(scene, method, tolerance)[0]
        r = build_scene(scene, method, **knobs)
        runs = [(1, "exact"), (DEFAULT_SPP, "upsample")]
        if method == "reference":
            runs += [(4, "exact"), (9, "exact")]
        for spp, sub in runs:
            t = time.perf_counter()
            res = r.render(scene.lights, scene.camera, spp=spp, subpixel=sub)
            row = {"scene": name, "method": method, "spp": spp, "subpixel": sub if spp > 1 else "none",
                   "rel_rmse": image_error(res, truth)["rel_rmse"], "frame_s": time.perf_counter() - t,
                   "t_subpixel_s": res.stats.get("t_subpixel_s"),
                   "knobs": ", ".join(f"{k} {v}" for k, v in sorted(knobs.items()))}
            rows.append(row)
            log(f"{name} {method} spp {spp} {row['subpixel']}: {row['rel_rmse']:.2%} ({row['frame_s']:.1f} s)")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=["torus-15-apple-back", "bunny-30-marble-back"],
                        choices=sorted(SPREAD))
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS)
    parser.add_argument("--tolerance", type=float, default=0.03)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--name", default="subpixel")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    rows: list[dict] = []
    for name in args.scenes:
        rows += run(name, args.methods, args.tolerance, log=lambda s: print(s, flush=True))
    finish_benchmark(args.name, rows, args.out_dir, columns=COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
