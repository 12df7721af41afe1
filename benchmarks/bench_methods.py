"""Setup and frame time of every method on the default scene, next to the reference's time in the same run.

Each method is built once (``torchsss.registry.render_scene``: ``setup_s``) and renders ``--frames`` frames with
the light orbiting the object (median ``frame_s``); the reference renders the scene's own lighting once (its setup
and frame are reported the same way). Error: relative RMSE of each method's first frame (the scene's lighting)
against the reference's, over the pixels both cover. All in one process and one run, so ratios are comparable;
absolute times drift 2x on the shared machine. Default knobs everywhere (the CLI's), float32.

Usage::

    python benchmarks/bench_methods.py                      # 96x96 and 256x256 (about 20 minutes on 2 cores)
    python benchmarks/bench_methods.py --quick              # 32x32, 2 frames
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark
from torchsss.registry import render_scene
from torchsss.scene import default_scene_path, load_scene

RESULTS_DIR = Path(__file__).resolve().parent / "results"
METHODS = ("splat", "icdf", "hybrid", "lensch")
COLUMNS = ["resolution", "method", "setup_s", "frame_median_s", "frames", "reference_s", "frame_speedup",
           "end_to_end_speedup", "rel_rmse", "knobs"]


def rel_rmse(a, ref) -> float:
    m = (a.mask & ref.mask).expand_as(ref.radiance)
    d = (a.radiance - ref.radiance)[m]
    return float(d.square().mean().sqrt() / ref.radiance[m].square().mean().sqrt())


def main() -> None:
    parser = benchmark_parser(__doc__.splitlines()[0], "methods", RESULTS_DIR)
    parser.add_argument("--frames", type=int, default=5, help="frames per method after the build (default 5)")
    parser.add_argument("--resolutions", type=int, nargs="+", default=[96, 256])
    args = parser.parse_args()
    setup_benchmark(parser, args)
    if args.quick:
        args.frames, args.resolutions = 2, [32]
    start = time.perf_counter()
    scene0 = load_scene(default_scene_path())
    records = []
    for res in args.resolutions:
        scene = dataclasses.replace(scene0, camera=dataclasses.replace(scene0.camera, width=res, height=res))
        ref = render_scene(scene, "reference")
        ref_s = ref.stats["setup_s"] + ref.stats["frame_median_s"]
        records.append({"resolution": res, "method": "reference", "setup_s": ref.stats["setup_s"],
                        "frame_median_s": ref.stats["frame_median_s"], "frames": 1, "reference_s": ref_s,
                        "frame_speedup": 1.0, "end_to_end_speedup": 1.0, "rel_rmse": 0.0,
                        "knobs": str(ref.stats["knobs"])})
        print(f"{res}x{res} reference: setup {ref.stats['setup_s']:.2f} s, frame {ref.stats['frame_median_s']:.2f} s",
              flush=True)
        for method in METHODS:
            out = render_scene(scene, method, frames=args.frames)
            st = out.stats
            rec = {"resolution": res, "method": method, "setup_s": st["setup_s"],
                   "frame_median_s": st["frame_median_s"], "frames": args.frames, "reference_s": ref_s,
                   "frame_speedup": ref_s / st["frame_median_s"],
                   "end_to_end_speedup": ref_s / (st["setup_s"] + st["frame_median_s"]),
                   "rel_rmse": rel_rmse(out, ref), "knobs": str(st["knobs"])}
            records.append(rec)
            print(f"{res}x{res} {method}: setup {rec['setup_s']:.2f} s, frame {rec['frame_median_s']:.3f} s, "
                  f"error {rec['rel_rmse']:.3%}", flush=True)
    finish_benchmark(args.name, records, args.out_dir, columns=COLUMNS, start=start)


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
