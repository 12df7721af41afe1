"""Where the hybrid's frame goes: each part's wall time (device-synchronised) per frame, k-d tree against grid.

The default scene and the shared bunny at 256x256, the hybrid at the knobs the planner picks for 3%, three frames
under lights moved 5% a frame. The parts: the irradiance atlas, the per-view local plan (first frame only), the
sampled global term, the surface local term and, inside it, the neighbour search (`ball_pairs`, the k-d tree on
the host or the uniform grid on the points' device) and the pairs' weights. Results: results/hybrid_parts_<device>.

    python benchmarks/bench_hybrid_parts.py --device cuda      # about 2 minutes on an H200
    python benchmarks/bench_hybrid_parts.py --scenes default   # the CPU, the default scene only
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time
from pathlib import Path

import torch

import torchsss.modules.chang as mc
import torchsss.pipelines.chang as pc
import torchsss.pipelines.coarse as co
from torchsss.bench import environment, finish_benchmark
from torchsss.pipelines.build import build
from torchsss.plan import plan_method
from torchsss.registry import _single
from torchsss.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
SCENES = {"default": ROOT / "torchsss" / "data" / "scenes" / "default.json",
          "bunny": ROOT / "examples" / "scenes" / "bunny.json"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--search", nargs="*", default=["kdtree", "grid"], choices=("kdtree", "grid", "auto"))
    parser.add_argument("--scenes", nargs="*", default=sorted(SCENES), choices=sorted(SCENES))
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out-dir", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    start = time.perf_counter()

    def sync() -> None:
        if args.device == "cuda":
            torch.cuda.synchronize()

    parts: dict[str, float] = {}
    search = {"method": "auto"}

    def timed(name, fn, **bound):
        @functools.wraps(fn)
        def wrapper(*a, **k):
            sync()
            t = time.perf_counter()
            out = fn(*a, **bound, **k)
            sync()
            parts[name] = parts.get(name, 0.0) + time.perf_counter() - t
            return out
        return wrapper

    ball_pairs = pc.ball_pairs
    pc.ball_pairs = timed("ball_pairs_s", lambda *a, **k: ball_pairs(*a, method=search["method"], **k))
    pc.irradiance_atlas = timed("irradiance_atlas_s", pc.irradiance_atlas)
    pc.HybridRenderer._surface_local = timed("surface_local_s", pc.HybridRenderer._surface_local)
    pc.HybridRenderer._local_plan = timed("local_plan_s", pc.HybridRenderer._local_plan)
    mc.SurfaceLocal.pair_weights = timed("pair_weights_s", mc.SurfaceLocal.pair_weights)
    mc.HybridTranslucency.global_everywhere = timed("global_s", mc.HybridTranslucency.global_everywhere)
    co.CoarseReceivers.refine = timed("refine_s", co.CoarseReceivers.refine)
    records = []
    for name in args.scenes:
        scene = load_scene(SCENES[name])
        scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=256, height=256))
        knobs, _, note = plan_method(scene, "hybrid", 0.03)
        mesh, material = _single(scene, torch.float32)
        for method in args.search:
            search["method"] = method
            renderer = build("hybrid", mesh.with_device(args.device), material, **knobs)
            for i in range(args.frames):
                lights = [dataclasses.replace(lt, position=tuple(p * (1 + 0.05 * i) for p in lt.position))
                          if hasattr(lt, "position") else lt for lt in scene.lights]
                parts.clear()
                sync()
                t = time.perf_counter()
                out = renderer.render(lights, scene.camera)
                sync()
                rec = {"device": args.device, "scene": name, "search": method, "knobs": knobs, "frame": i,
                       "frame_s": time.perf_counter() - t, **parts, "exact": out.stats.get("local_exact"),
                       "pairs": out.stats.get("local_pairs"), "note": note}
                records.append(rec)
                print({k: round(v, 3) if isinstance(v, float) else v for k, v in rec.items() if k != "note"},
                      flush=True)
    finish_benchmark(f"hybrid_parts_{args.device}", records, args.out_dir, start=start)
    print(environment())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
