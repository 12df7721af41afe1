"""The measured trade on calibration scenes: ``torchsss.trade`` over several scenes, one JSON with every row.

The planner's (``torchsss.plan``) error and cost constants are fitted to these rows (see ``torchsss/plan.py``);
the planner is then verified on other scenes (``bench_planner.py``). Each scene: the reference (the truth) and
every applicable method over its knob sweep, ``--frames`` frames per configuration (light orbit), 1 thread by
default (on this shared 2-core machine two OpenMP threads of two processes slow each other down 5-10x).

Usage::

    python benchmarks/bench_trade.py                 # the calibration scenes at 96x96 (about 20 min)
    python benchmarks/bench_trade.py --quick         # one scene at 48x48, the quick sweep
    python benchmarks/bench_trade.py --methods lensch   # re-measure Lensch only: its rows replace the old ones
        # in each scene's trade.json, the other methods' rows are kept
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark
from torchsss.scene import Scene, default_scene_path, load_scene
from torchsss.trade import pareto_front, trade, write_trade

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def _scene(mesh: str, size: float, material: str, light: list[float], res: int, name: str) -> Scene:
    d = 2.2 * size
    return Scene.from_dict({
        "name": name, "mesh": mesh, "size_mm": size, "material": material,
        "lights": [{"type": "point", "position": [v * d for v in light], "intensity": [float(d * d * 4)] * 3}],
        "camera": {"eye": [0.0, 0.0, d], "target": [0.0, 0.0, 0.0], "fov_deg": 30.0, "width": res, "height": res}})


def calibration_scenes(res: int) -> list[Scene]:
    """The scenes the planner's constants are fitted on.

    The default scene (back-lit skin1 spot), a side-lit marble torus, a front-lit skin2 sphere, a cream spot lit
    from the side and behind.
    """
    import dataclasses

    s0 = load_scene(default_scene_path())
    default = dataclasses.replace(s0, camera=dataclasses.replace(s0.camera, width=res, height=res))
    return [default, _scene("torus", 30.0, "marble", [1.0, 0.3, 0.2], res, "torus 30 mm marble, side-lit"),
            _scene("sphere", 15.0, "skin2", [0.3, 0.5, 1.0], res, "sphere 15 mm skin2, front-lit"),
            _scene("spot", 25.0, "cream", [-1.0, 0.2, -0.4], res, "spot 25 mm cream, side/back-lit")]


def scene_key(scene: Scene) -> str:
    """The folder of a scene's trade.json and trade.png under ``results/trade``."""
    return "_".join(scene.name.translate({ord(c): None for c in ",:()"}).split()[:4])


def merge_rows(path: Path, result: dict, methods: list[str]) -> dict:
    """``result`` with the rows of the other methods of ``path``'s earlier trade (when there is one) kept."""
    if not path.exists():
        return result
    old = json.loads(path.read_text())
    rows = [r for r in old["rows"] if r["method"] not in methods] + result["rows"]
    live = [r if "refused" not in r else {"frame_s": math.inf, "rel_rmse": math.inf} for r in rows]
    return {**result, "rows": rows, "pareto": [i for i in pareto_front(live) if "refused" not in rows[i]],
            "seconds": result["seconds"] + old.get("seconds", 0.0)}


def main() -> None:
    parser = benchmark_parser(__doc__.splitlines()[0], "trade_calibration", RESULTS_DIR)
    parser.add_argument("--resolution", type=int, default=96)
    parser.add_argument("--scenes", type=int, nargs="+", default=None, help="indices of the scenes to run (all)")
    parser.add_argument("--methods", nargs="+", default=None,
                        help="re-measure only these methods; their rows replace those of the scene's trade.json")
    args = parser.parse_args()
    setup_benchmark(parser, args)
    start = time.perf_counter()
    scenes = calibration_scenes(48 if args.quick else args.resolution)
    scenes = scenes[:1] if args.quick else [scenes[i] for i in args.scenes] if args.scenes else scenes
    records = []
    for scene in scenes:
        result = trade(scene, quick=args.quick, methods=args.methods)
        if args.methods:
            result = merge_rows(Path(args.out_dir) / "trade" / scene_key(scene) / "trade.json", result, args.methods)
        write_trade(result, Path(args.out_dir) / "trade" / scene_key(scene))
        ref = result["reference"]
        for row in result["rows"]:
            if "refused" in row:
                continue
            records.append({"scene": scene.name, "resolution": scene.camera.width, "method": row["method"],
                            "knobs": row["knobs"], "setup_s": row["setup_s"], "frame_s": row["frame_s"],
                            "rel_rmse": row["rel_rmse"], "max_error": row["max_error"], "peak_mib": row["peak_mib"],
                            "reference_setup_s": ref["setup_s"], "reference_frame_s": ref["frame_s"],
                            "covered_pixels": ref["covered_pixels"], "stats_knobs": row["stats_knobs"]})
        print(f"{scene.name}: {len(result['rows'])} runs, {result['seconds']:.0f} s", flush=True)
    finish_benchmark(args.name, records, args.out_dir, start=start,
                     columns=["scene", "resolution", "method", "knobs", "setup_s", "frame_s", "rel_rmse",
                              "max_error", "peak_mib", "reference_frame_s"])


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
