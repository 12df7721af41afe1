"""Splat with and without the light view's coverage correction, on the spread and the planner's verification scenes.

Per scene: the reference (truth), then splat at the knobs the planner picks for it at 3% and at two fixed coarser
budgets (eps 0.03 / oversample 2, eps 0.01 / oversample 1), each with ``coverage=True`` (the light view's silhouette
pixels rescaled so that each run of faces there sums to its exact projected area,
:func:`torchsss.geometry.coverage.coverage_scale`) and
``coverage=False`` (each pixel's own footprint, as before 2026-11-27). Relative RMSE against the reference and the
ratio of the image means. Results: results/splat_coverage.{json,md}.

    python benchmarks/bench_splat_coverage.py              # about 20 minutes on 2 cores
    python benchmarks/bench_splat_coverage.py --quick      # the slab and the thin torus only
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_planner
import bench_spread

from torchsss.bench import finish_benchmark
from torchsss.plan import plan_method
from torchsss.registry import build_scene
from torchsss.trade import image_error

RESULTS_DIR = Path(__file__).resolve().parent / "results"
FIXED = [{"eps": 0.03, "oversample": 2.0}, {"eps": 0.01, "oversample": 1.0}]


def all_scenes(quick: bool, only: list[str] | None = None) -> list:
    spread = [n for n in bench_spread.SPREAD if n != "default-512"]
    verification = dict(bench_planner.VERIFICATION)
    if quick:
        spread, verification = ["slab-25-cream-side"], {"torus 12 mm wholemilk side": verification[
            "torus 12 mm wholemilk side"]}
    if only:
        spread = [n for n in spread if n in only]
        verification = {k: v for k, v in verification.items() if k in only}
    out = [(n, bench_spread.spread_scene(n)) for n in spread]
    out += [(n, bench_planner.make_scene(n, *args)) for n, args in verification.items()]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--scenes", nargs="*", default=None, help="only these scenes (names as in the table)")
    parser.add_argument("--name", default=None, help="results file stem (default splat_coverage)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    records = []
    for name, scene in all_scenes(args.quick, args.scenes):
        t = time.perf_counter()
        truth = build_scene(scene, "reference").render(scene.lights, scene.camera)
        print(f"{name}: reference {time.perf_counter() - t:.1f} s", flush=True)
        planned, _, _ = plan_method(scene, "splat", 0.03)
        for label, knobs in [("planned 3%", planned), *[("fixed", k) for k in FIXED]]:
            for coverage in (False, True):
                t = time.perf_counter()
                res = build_scene(scene, "splat", coverage=coverage, **knobs).render(scene.lights, scene.camera)
                err = image_error(res, truth)
                mean = float(res.radiance.sum() / truth.radiance.sum().clamp_min(1e-300))
                rec = {"scene": name, "knobs": label + " " + str(knobs), "coverage": coverage,
                       "rel_rmse": err["rel_rmse"], "max_error": err["max_error"], "mean_ratio": mean,
                       "grid": res.stats.get("grid"), "splats": res.stats.get("splats"),
                       "seconds": time.perf_counter() - t}
                records.append(rec)
                print(f"  {label} {knobs} coverage={coverage}: {100 * err['rel_rmse']:.2f}% mean x{mean:.4f}",
                      flush=True)
    name = args.name or ("splat_coverage_quick" if args.quick else "splat_coverage")
    finish_benchmark(name, records, args.out_dir, start=start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
