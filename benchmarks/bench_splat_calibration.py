"""Splat's calibration rows: every configuration the planner plans, on the scenes of its calibration.

The splat error model (``torchsss.plan.predict``) was fitted to the verification runs' sweeps
(``results/planner_v1_rows.json`` .. ``planner_v4_rows.json``), which render splat at oversample 1 and 2 only, while the
planner plans oversample 1, 2 and 4. Fitted to those rows alone, the model cannot tell a floor (error that no light
view removes) from aliasing that a finer light view removes: a side-lit 20 mm skin1 torus measured 6.0 / 3.0 / 1.0 /
0.71% at oversample 1 / 2 / 4 / 8 (eps 0.003), and the 1.48% floor the model charged was set by scans whose error
stayed at 1.2-1.5% at every oversampling (the light view's flux was the faces' projected area, the reference's the
shading normals' cosine: ``torchsss.geometry.shading_flux``). This benchmark renders, on every scene of those rows
files, the truth reference and splat at eps 0.03, 0.01, 0.003 with oversample 1, 2 and 4, and at eps 0.003 with
oversample 8, and writes the rows in the rows files' format (``results/<name>_rows.json``, which ``fit_planner.py``
reads for splat instead of the verification runs' splat rows) and a table (``results/<name>.{json,md}``).

Usage::

    python benchmarks/bench_splat_calibration.py                       # every scene (about 25 minutes, 1 thread)
    python benchmarks/bench_splat_calibration.py --shard 0/2 --name splat_calibration_0   # half the scenes
    python benchmarks/bench_splat_calibration.py --merge splat_calibration_0 splat_calibration_1
    python benchmarks/bench_splat_calibration.py --flux facet --name splat_calibration_facet   # Shah's flux
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark
from torchsss.trade import image_error, run_config

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_planner import make_scene  # noqa: E402
from bench_trade import calibration_scenes  # noqa: E402

RESULTS_DIR = HERE / "results"
#: The rows files whose scenes are rendered (the calibration scenes of the splat error model).
SOURCES = ("planner_v1_rows.json", "planner_v2_rows.json", "planner_v3_rows.json", "planner_v4_rows.json")
#: The configurations rendered on each scene.
CONFIGS = (*({"eps": e, "oversample": o} for o in (1.0, 2.0, 4.0) for e in (0.03, 0.01, 0.003)),
           {"eps": 0.003, "oversample": 8.0})


def specs() -> list[tuple[str, list]]:
    """``(name, spec)`` of every scene: :data:`SOURCES`' and the calibration trades'.

    ``spec`` is ``make_scene``'s arguments, or ``["trade", index, resolution]`` for the four scenes of
    ``bench_trade.calibration_scenes``.
    """
    out = []
    for name in SOURCES:
        path = RESULTS_DIR / name
        if path.exists():
            out += [(e["scene"], e["spec"]) for e in json.loads(path.read_text())["scenes"]]
    return out + [(s.name, ["trade", i, 96]) for i, s in enumerate(calibration_scenes(96))]


def scene_of(name: str, spec: list):
    """The scene of a rows entry (:func:`specs`)."""
    if spec and spec[0] == "trade":
        return calibration_scenes(int(spec[2]))[int(spec[1])]
    return make_scene(name, *spec)


def measure(name: str, spec: list, flux: str = "shading") -> dict:
    """The truth and :data:`CONFIGS` on one scene: ``{"scene", "spec", "rows"}`` (rows as the rows files')."""
    scene = scene_of(name, spec)
    t0 = time.perf_counter()
    truth, _ = run_config(scene, "reference", {}, 1, torch.float32)
    rows = [{"method": "reference", "knobs": {}, "time_s": time.perf_counter() - t0, "rel_rmse": 0.0,
             "kind": "truth"}]
    for knobs in CONFIGS:
        t0 = time.perf_counter()
        result, _ = run_config(scene, "splat", {**knobs, "flux": flux}, 1, torch.float32)
        err = image_error(result, truth)
        rows.append({"method": "splat", "knobs": dict(knobs), "kind": "sweep", "time_s": time.perf_counter() - t0,
                     "rel_rmse": err["rel_rmse"], "max_error": err["max_error"], "grid": result.stats.get("grid"),
                     "splats": result.stats.get("splats")})
    return {"scene": name, "spec": spec, "rows": rows}


def main() -> None:
    parser = benchmark_parser(__doc__.splitlines()[0], "splat_calibration", RESULTS_DIR)
    parser.add_argument("--flux", choices=("shading", "facet"), default="shading", help="the splat renderer's flux")
    parser.add_argument("--shard", default="0/1", help="K/N: the K-th of N interleaved parts of the scenes")
    parser.add_argument("--merge", nargs="+", default=None, help="merge these shards' rows (<name>_rows.json)")
    parser.add_argument("--only-trade", action="store_true", help="only the calibration trades' scenes")
    args = parser.parse_args()
    start = time.perf_counter()
    if args.merge:
        scenes = []
        for part in args.merge:
            scenes += json.loads((RESULTS_DIR / f"{part}_rows.json").read_text())["scenes"]
        order = [n for n, _ in specs()]
        scenes.sort(key=lambda s: order.index(s["scene"]) if s["scene"] in order else len(order))
    else:
        k, n = (int(x) for x in args.shard.split("/"))
        setup_benchmark(parser, args)
        scenes = []
        done = set()
        if args.only_trade:  # add the trades' scenes to existing rows
            done = {n_ for n_, sp in specs() if not (sp and sp[0] == "trade")}
        for i, (name, spec) in enumerate(specs()):
            if i % n != k or name in done:
                continue
            try:
                scenes.append(measure(name, spec, args.flux))
            except ValueError as e:  # a shared mesh that is not here
                print(f"skipped {name}: {e}")
                continue
            print(name, [f"{100 * r['rel_rmse']:.2f}%" for r in scenes[-1]["rows"][1:]], flush=True)
    (args.out_dir / f"{args.name}_rows.json").write_text(json.dumps({"scenes": scenes}, indent=1))
    records = [{"benchmark": "splat_calibration", "scene": s["scene"], **{
        f"eps {r['knobs']['eps']} x{r['knobs']['oversample']:g}": r["rel_rmse"] for r in s["rows"][1:]}}
        for s in scenes]
    finish_benchmark(args.name, records, args.out_dir, start=start)


if __name__ == "__main__":
    main()
