"""The sampled estimators' error against N, before and after the better estimator (issue 16).

Chang et al.'s texture-space estimator (``icdf``: every source importance-sampled by the irradiance atlas, N
scrambled-Sobol samples shared by all pixels) is the "before". The "after" is the hybrid with the local term
gathered exactly over the surface (``hybrid``, ``local="surface"``: :class:`~torchsss.modules.chang.SurfaceLocal`),
i.e. the near field, where most of the variance of the icdf estimator comes from (R_d peaks at r = 0), taken out of
the sampled sum and integrated deterministically; only :math:`R_d (1 - W_l^b)` is sampled. For each scene, N and
seed the script renders one frame with each and reports the relative RMSE against the reference (eps 0.01, same
pixels) and the frame time, so the two can be compared at equal N and at equal time.

Usage::

    python benchmarks/bench_estimators.py            # 3 scenes x N in {1024, 4096, 16384} x 2 seeds, 128 x 128
    python benchmarks/bench_estimators.py --quick    # one small scene, two N (about a minute)
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark
from torchsss.registry import build_scene
from torchsss.trade import image_error

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_spread import spread_scene

RESULTS_DIR = Path(__file__).resolve().parent / "results"
SCENES = ("default-128", "bunny-30-marble-side", "spot-20-skin2-back")
COLUMNS = ["scene", "method", "samples", "seeds", "rel_rmse_mean", "rel_rmse_std", "frame_s_median", "setup_s"]


def _scene(name: str, resolution: int):
    scene = spread_scene(name)
    cam = dataclasses.replace(scene.camera, width=resolution, height=resolution)
    return dataclasses.replace(scene, camera=cam)


def run(scenes, samples, seeds: int, resolution: int) -> list[dict]:
    rows = []
    for name in scenes:
        scene = _scene(name, resolution)
        truth = build_scene(scene, "reference").render(scene.lights, scene.camera)
        for method in ("icdf", "hybrid"):
            t0 = time.perf_counter()
            r = build_scene(scene, method, samples=samples[0])
            r.reuse_lights = False  # every frame relit, as a frame with new lights
            setup = time.perf_counter() - t0
            r.render(scene.lights, scene.camera)  # warm-up (compile, caches)
            for n in samples:
                errs, times = [], []
                for seed in range(seeds):
                    r.knobs.update(samples=n, seed=seed)
                    res = r.render(scene.lights, scene.camera)
                    errs.append(image_error(res, truth)["rel_rmse"])
                    times.append(res.stats["frame_s"])
                row = {"scene": name, "method": method, "samples": n, "seeds": seeds,
                       "rel_rmse_mean": statistics.fmean(errs),
                       "rel_rmse_std": statistics.stdev(errs) if len(errs) > 1 else 0.0,
                       "frame_s_median": statistics.median(times), "setup_s": setup}
                rows.append(row)
                print(f"{name} {method} N={n}: {row['rel_rmse_mean']:.2%} ({row['frame_s_median']:.2f} s)",
                      flush=True)
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Per scene and N: the icdf/hybrid error ratio, and the N^-a slope of each method (log-log fit)."""
    out = []
    for name in dict.fromkeys(r["scene"] for r in rows):
        for n in sorted({r["samples"] for r in rows if r["scene"] == name}):
            pair = {r["method"]: r for r in rows if r["scene"] == name and r["samples"] == n}
            if {"icdf", "hybrid"} <= set(pair):
                out.append({"scene": name, "samples": n,
                            "icdf_rel_rmse": pair["icdf"]["rel_rmse_mean"],
                            "hybrid_rel_rmse": pair["hybrid"]["rel_rmse_mean"],
                            "error_ratio": pair["icdf"]["rel_rmse_mean"] / pair["hybrid"]["rel_rmse_mean"],
                            "time_ratio": pair["hybrid"]["frame_s_median"] / pair["icdf"]["frame_s_median"]})
    return out


def main() -> None:
    parser = benchmark_parser(__doc__.splitlines()[0], "estimators", RESULTS_DIR)
    parser.add_argument("--resolution", type=int, default=128, help="image size (default 128)")
    args = parser.parse_args()
    setup_benchmark(parser, args)
    start = time.perf_counter()
    if args.quick:
        rows = run(("sphere-5-skimmilk-side",), (256, 1024), 1, 48)
    else:
        rows = run(SCENES, (1024, 4096, 16384), 2, args.resolution)
    for row in summary(rows):
        rows.append({"benchmark": "ratio", **row})
    for r in rows:
        for k, v in r.items():
            if isinstance(v, float) and not math.isfinite(v):
                r[k] = None
    finish_benchmark(args.name, rows, args.out_dir, start=start)


if __name__ == "__main__":
    main()
