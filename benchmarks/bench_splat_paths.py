"""Where a splat frame's time goes: each path of ``splat_radiosity`` timed inside the render, against the planner.

For the scenes of a verification set (``bench_planner.SETS``), after the reference's plain pair sum has compiled (as
in ``bench_planner.py``, whose rows the planner's time constants are fitted to), splat at eps 0.03 / 0.01 / 0.003 and
oversample 1 / 2, one frame each: the light view's grid and splats, the covered pixels, the setup, the frame, the
seconds spent in the gather (compiled pair sum), tile and window paths of :func:`torchsss.ops.splat.splat_radiosity`
and the pairs each evaluated, next to :func:`torchsss.plan.predict`'s frame and the splats it counts
(``SceneFacts.light_fill`` x grid^2). The splat constants of ``torchsss.plan.MODEL`` (``splat_t``,
``splat_t_gather``, ``splat_t_texel``, ``splat_f0``, ``splat_s0``) were read from this table (2026-11-29). The first
scene's frames run eager until one frame is big enough to compile the truncated pair sum; later ones compile-warm.

Usage::

    python benchmarks/bench_splat_paths.py --set main     # 9 scenes x 6 configurations (about 5 minutes)
    python benchmarks/bench_splat_paths.py --quick        # 2 scenes at 48 x 48
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path

import torch

import torchsss.ops.splat as splat_op
from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark
from torchsss.ops.fused import block_shape
from torchsss.plan import SceneFacts, _Profile, predict, warm_kernels
from torchsss.trade import run_config

RESULTS_DIR = Path(__file__).resolve().parent / "results"
PATHS = ("gather", "tile", "window")


class _Timer:
    """Wraps splat_radiosity's path functions: seconds and pairs per path over one render."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.pairs: dict[str, int] = {}
        self._orig = {}

    def __enter__(self) -> _Timer:
        for name, count in (("gather", None), ("tile", None), ("window", None)):
            self._wrap(f"_splat_{name}", name, count)
        self._wrap("_accumulate", "window_pairs", lambda out, index, *a, **k: index.numel())
        self._wrap("_tile_block", "tile_pairs",
                   lambda tiles, idx, cand, *a, **k: idx.numel() * tiles.valid.shape[1] * cand.shape[1])
        return self

    def _wrap(self, attr: str, key: str, count) -> None:
        fn = getattr(splat_op, attr)
        self._orig[attr] = fn

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            self.seconds[key] = self.seconds.get(key, 0.0) + time.perf_counter() - t0
            if count is not None:
                self.pairs[key] = self.pairs.get(key, 0) + int(count(*args, **kwargs))
            return out

        setattr(splat_op, attr, timed)

    def __exit__(self, *exc) -> None:
        for attr, fn in self._orig.items():
            setattr(splat_op, attr, fn)


def main() -> None:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_planner import SETS, make_scene

    parser = benchmark_parser(__doc__.splitlines()[0], "splat_paths", RESULTS_DIR)
    parser.add_argument("--set", choices=tuple(SETS), default="main", help="the verification set's scenes")
    args = parser.parse_args()
    setup_benchmark(parser, args)
    start = time.perf_counter()
    if args.quick:
        scenes = [make_scene("sphere 10 mm apple front", "sphere", 10, "apple", "front", 48),
                  make_scene("torus 30 mm ketchup side", "torus", 30, "ketchup", "side", 48)]
        configs = [(0.01, 1.0), (0.01, 2.0)]
    else:
        scenes = [make_scene(name, *spec) for name, spec in SETS[args.set].items()]
        configs = [(e, s) for e in (0.03, 0.01, 0.003) for s in (1.0, 2.0)]
    rb, sb = block_shape("cpu")
    records = []
    for scene in scenes:
        facts = SceneFacts.from_scene(scene, throughput=False, spread=False)
        prof = _Profile.of(scene.material)
        run_config(scene, "reference", {"eps": 0.3}, 1, torch.float32)  # the plain pair sum compiled, as in the bench
        for eps, over in configs:
            knobs = {"eps": eps, "oversample": over}
            warm = warm_kernels()
            with _Timer() as t:
                out, _ = run_config(scene, "splat", knobs, 1, torch.float32)
            st = out.stats
            px, splats = int(out.mask.sum()), int(st["splats"])
            path = next((p for p in PATHS if p in t.seconds), "none")
            op_s = sum(t.seconds.get(p, 0.0) for p in PATHS)
            pred = predict("splat", knobs, facts, scene.material, warm=warm)
            footprint = min(px, math.pi * (prof.r_max(eps) / facts.pixel_mm) ** 2)
            blocked = math.ceil(px / rb) * rb * math.ceil(splats / sb) * sb
            per_pair = (op_s / blocked if path == "gather" else op_s / max(splats * footprint, 1.0))
            records.append({"benchmark": "frames", "scene": scene.name, "eps": eps, "oversample": over,
                            "grid": st["grid"], "splats": splats, "predicted_splats": round(facts.light_fill
                                                                                             * st["grid"] ** 2),
                            "covered_px": px, "path": path, "setup_s": st["setup_s"], "frame_s": st["frame_s"][0],
                            "path_s": op_s, "rest_s": st["frame_s"][0] - op_s,
                            "pairs_evaluated": t.pairs.get("window_pairs", t.pairs.get("tile_pairs", blocked
                                                                                         if path == "gather" else 0)),
                            "s_per_pair": per_pair, "predicted_frame_s": pred["frame_s"],
                            "predicted_setup_s": pred["setup_s"]})
            print(f"{scene.name} eps {eps} x{over:g}: {path} grid {st['grid']} splats {splats} "
                  f"frame {st['frame_s'][0]:.2f} s (path {op_s:.2f} s), predicted {pred['frame_s']:.2f} s", flush=True)
    summary = []
    for path in PATHS:
        mine = [r for r in records if r["path"] == path]
        if mine:
            summary.append({"benchmark": "summary", "path": path, "frames": len(mine),
                            "s_per_pair_median": statistics.median(r["s_per_pair"] for r in mine),
                            "frame_over_predicted_median": statistics.median(r["frame_s"] / r["predicted_frame_s"]
                                                                             for r in mine)})
    summary.append({"benchmark": "summary", "path": "all", "frames": len(records),
                    "rest_s_median": statistics.median(r["rest_s"] for r in records),
                    "setup_s_median": statistics.median(r["setup_s"] for r in records),
                    "frame_over_predicted_median": statistics.median(r["frame_s"] / r["predicted_frame_s"]
                                                                     for r in records)})
    finish_benchmark(args.name, records + summary, args.out_dir, start=start,
                     columns={"frames": ["scene", "eps", "oversample", "grid", "splats", "predicted_splats",
                                         "covered_px", "path", "setup_s", "frame_s", "path_s", "rest_s",
                                         "pairs_evaluated", "s_per_pair", "predicted_frame_s"],
                              "summary": ["path", "frames", "s_per_pair_median", "rest_s_median", "setup_s_median",
                                          "frame_over_predicted_median"]})


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
