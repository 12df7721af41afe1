"""Spread: every method at its default (planned) knobs on scenes nobody tuned on, against the reference.

Issue 16's yardstick for "defaults that generalise": the default scene at 128x128, 256x256 and 512x512 and a spread of
other scenes at 256x256 (shared meshes and procedural shapes; object sizes 5-80 mm; materials from ketchup to skim
milk; the key light in front of, beside or behind the object). Every scene is built here from a few numbers
(:func:`spread_scene`): the camera looks at the object from 1.6 bounding-box diagonals with a 30 degree field of
view, the key light stands 2.5 diagonals from the centre (intensity (2.5 d)^2, so the irradiance at the object is
about 1) and a fill light of 5% sits beside the camera.

For each scene and method (splat, icdf, hybrid, lensch) the knobs are the ones ``python -m torchsss render --method
M`` uses by default: the planner's choice for that method alone at ``--tolerance`` (3%); the error is the relative
RMSE of one frame against the reference (``eps`` 0.01, full mesh) over the pixels both cover. The table reports
each method's worst case over the spread.

Usage::

    python benchmarks/bench_spread.py                 # all scenes (about 30-60 minutes on 2 cores)
    python benchmarks/bench_spread.py --scenes sphere-5-skimmilk-side --methods hybrid
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import torch

from torchsss.bench import environment, environment_line, finish_benchmark, markdown_table
from torchsss.scene import Scene, default_scene_path, load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_frames import METHODS, bench_scene, make_parser

RESULTS_DIR = Path(__file__).resolve().parent / "results"
MESHES = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"

#: name -> (mesh, size_mm, material, key light side, resolution, decimate); mesh "default" is the packaged scene
SPREAD = {
    "default-128": ("default", None, None, None, 128, None),
    "default-256": ("default", None, None, None, 256, None),
    "default-512": ("default", None, None, None, 512, None),
    "bunny-30-marble-side": (str(MESHES / "stanford-bunny.obj"), 30.0, "marble", "side", 256, None),
    "bunny-30-marble-back": (str(MESHES / "stanford-bunny.obj"), 30.0, "marble", "back", 256, None),
    "igea-10-skin1-side": (str(MESHES / "igea.ply"), 10.0, "skin1", "side", 256, 60000),  # seen from -z: the face
    "spot-20-skin2-back": ("spot", 20.0, "skin2", "back", 256, None),
    "teapot-80-ketchup-front": (str(MESHES / "teapot.obj"), 80.0, "ketchup", "front", 256, None),
    "sphere-5-skimmilk-side": ("sphere", 5.0, "skimmilk", "side", 256, None),
    "torus-15-apple-back": ("torus", 15.0, "apple", "back", 256, None),
    "bunny-5-chicken1-front": (str(MESHES / "stanford-bunny.obj"), 5.0, "chicken1", "front", 256, None),
    # a thin slab (25 mm its diagonal: 17.7 x 17.7 x 0.88 mm) lit on its rim: the seen face's light enters beside
    # it, across a crease (added 2026-11-27)
    "slab-25-cream-side": ("slab", 25.0, "cream", "side", 256, None),
}

MD_COLUMNS = ["scene", "faces", "method", "knobs", "decimate", "setup_s", "cold_frame_s", "rel_rmse", "max_error",
              "peak_mib", "note"]


def spread_scene(name: str) -> Scene:
    """The spread's scene ``name`` (see :data:`SPREAD`) as a :class:`Scene`."""
    mesh, size, material, side, res, decimate = SPREAD[name]
    if mesh == "default":
        scene = load_scene(default_scene_path())
        return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=res, height=res))
    d = float(size)
    eye = (0.0, 0.25 * d, 1.6 * d)
    key = {"front": (0.4 * d, 0.8 * d, 2.3 * d), "side": (2.5 * d, 0.5 * d, 0.0),
           "back": (-0.6 * d, 0.6 * d, -2.35 * d)}[side]
    fill = (1.2 * d, 0.6 * d, 1.6 * d)
    if name.startswith("igea"):  # the scan's face looks down -z
        eye, key, fill = ((x, y, -z) for x, y, z in (eye, key, fill))
    i_key = (2.5 * d) ** 2
    i_fill = 0.05 * sum(c * c for c in fill)  # 5% of the key's irradiance
    spec = {"name": name, "mesh": mesh, "size_mm": d, "material": material,
            "lights": [{"type": "point", "position": list(key), "intensity": [i_key] * 3},
                       {"type": "point", "position": list(fill), "intensity": [i_fill] * 3}],
            "camera": {"eye": list(eye), "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov_deg": 30.0,
                       "width": res, "height": res}}
    if decimate is not None:
        spec["decimate"] = decimate
    return Scene.from_dict(spec, base_dir=Path.cwd())


def worst_cases(records: list[dict]) -> list[dict]:
    """Per method: the worst relative RMSE over the scenes (and which scene)."""
    rows = []
    for method in METHODS:
        mine = [r for r in records if r.get("method") == method and math.isfinite(r.get("rel_rmse", math.nan))]
        failed = [r for r in records if r.get("method") == method and "rel_rmse" not in r]
        if not mine:
            continue
        worst = max(mine, key=lambda r: r["rel_rmse"])
        rows.append({"benchmark": "worst", "method": method, "scenes": len(mine), "failed": len(failed),
                     "worst_rel_rmse": worst["rel_rmse"], "worst_scene": worst["scene"],
                     "median_rel_rmse": sorted(r["rel_rmse"] for r in mine)[len(mine) // 2],
                     "within_3pct": sum(r["rel_rmse"] <= 0.03 for r in mine)})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=None, choices=sorted(SPREAD))
    parser.add_argument("--methods", nargs="*", default=None, choices=METHODS)
    parser.add_argument("--tolerance", type=float, default=0.03)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--name", default="spread")
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    records: list[dict] = []
    for name in args.scenes or list(SPREAD):
        scene = spread_scene(name)
        # bench_frames' own defaults for every option not set here (one cold frame each, no camera orbit)
        ns = make_parser().parse_args(["--resolution", str(scene.camera.width), "--tolerance", str(args.tolerance),
                                       "--frames", "1", "--reference-frames", "1", "--camera-frames", "0",
                                       *(["--methods", *args.methods] if args.methods else [])])
        print(f"{name}: {scene.mesh} {scene.size_mm} mm {scene.material.name} at {scene.camera.width}^2", flush=True)
        records += bench_scene(name, scene, ns, log=lambda s: print(s, flush=True))
        args.out_dir.mkdir(parents=True, exist_ok=True)
        (args.out_dir / f"{args.name}.partial.json").write_text(json.dumps(records, indent=1, default=str))
    records += worst_cases(records)
    finish_benchmark(args.name, records, args.out_dir,
                     columns={"scene": MD_COLUMNS, "worst": ["method", "scenes", "failed", "worst_rel_rmse",
                                                             "worst_scene", "median_rel_rmse", "within_3pct"]},
                     start=start)
    print(markdown_table([r for r in records if r.get("benchmark") == "worst"],
                         ["method", "scenes", "worst_rel_rmse", "worst_scene", "within_3pct"]))
    print(environment_line(environment()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
