"""What a user waits for and what it costs: ``python -m torchsss render`` per example scene and method, fresh processes.

Each run is one ``python -m torchsss render SCENE [--method M] --resolution RxR --out ...`` in its own process, as a
user types it (planning, loading, setup, the frame, writing the images): its wall time and its peak resident set
(``ru_maxrss`` of that process alone, from ``os.wait4``; about 0.35 GB of it is the interpreter with torch and
torchsss imported). Scenes: the packaged default scene and ``examples/scenes`` (the shared meshes' scenes only where
``../shared`` is beside the checkout); methods: the planner's choice (``auto``) and, on the single-object scenes
without caustics, each fast method at its planned default knobs (the multi-object and environment-light scenes:
``auto`` and ``splat``). The brief's bound: nothing past a few GB on the shared meshes.

Usage::

    python benchmarks/bench_cli_memory.py                  # 128 x 128, about 5 minutes on 2 cores
    python benchmarks/bench_cli_memory.py --resolution 256 --scenes igea --methods auto splat
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from torchsss.bench import finish_benchmark

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"
SCENES = {"default": ROOT / "torchsss" / "data" / "scenes" / "default.json",
          **{p.stem: p for p in sorted((ROOT / "examples" / "scenes").glob("*.json"))}}
METHODS = ("auto", "splat", "icdf", "hybrid", "lensch")
#: Scenes that take only some methods: several objects and the environment light (auto, splat), caustics (auto).
ONLY = {"two_objects": ("auto", "splat"), "spot_sky": ("auto", "splat"), "glass_sphere": ("auto",)}


def run_one(scene: Path, method: str, resolution: int, out_dir: Path) -> dict:
    """One CLI render in a fresh process: wall time, peak RSS, exit status and the CLI's summary line."""
    out = out_dir / f"{scene.stem}_{method}.png"
    cmd = [sys.executable, "-m", "torchsss", "render", str(scene), "--resolution", f"{resolution}x{resolution}",
           "--out", str(out), "--no-progress"]
    if method != "auto":
        cmd += ["--method", method]
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        log.seek(0)
        text = log.read().decode(errors="replace")
    lines = [x for x in text.splitlines() if x.startswith(("reference:", "splat:", "icdf:", "hybrid:", "lensch:",
                                                            "caustics:"))]
    rec = {"scene": scene.stem, "method": method, "resolution": resolution, "exit": proc.returncode,
           "wall_s": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0, "summary": lines[-1] if lines else ""}
    summary = out.with_suffix(".json")
    if summary.exists():
        data = json.loads(summary.read_text())
        rec["rendered_with"] = data.get("method", "")
    if proc.returncode != 0:
        rec["summary"] = text.strip().splitlines()[-1] if text.strip() else "(no output)"
    return rec


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--scenes", nargs="*", default=None, choices=sorted(SCENES))
    parser.add_argument("--methods", nargs="*", default=None, choices=METHODS)
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--name", default="cli_memory")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes or list(SCENES):
            scene = SCENES[name]
            text = scene.read_text()
            if "../../../shared" in text and not (ROOT.parent / "shared" / "data" / "meshes").is_dir():
                continue
            for method in args.methods or METHODS:
                if method not in ONLY.get(name, METHODS):
                    continue
                rec = run_one(scene, method, args.resolution, Path(tmp))
                records.append(rec)
                print(f"{name:14s} {method:7s} exit {rec['exit']}  {rec['wall_s']:6.1f} s  "
                      f"{rec['peak_rss_mb']:7.0f} MB  {rec['summary']}", flush=True)
    finish_benchmark(args.name, records, args.out_dir, start=start,
                     columns=["scene", "method", "resolution", "exit", "wall_s", "peak_rss_mb", "summary"])
    return 0 if all(r["exit"] == 0 for r in records) else 1


if __name__ == "__main__":
    raise SystemExit(main())
