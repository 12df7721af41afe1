"""benchmarks/bench_splat_scenes.py: its --quick run end to end (two touching objects, environment-lit sphere).

``--quick`` uses only files of this repository (examples/scenes/two_objects.json, a procedural sphere).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks" / "bench_splat_scenes.py"


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def test_bench_splat_scenes_quick(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.run([sys.executable, str(BENCH), "--quick", "--out-dir", str(out)],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    data = json.loads((out / "splat_scenes_quick.json").read_text(encoding="utf-8"))
    md = (out / "splat_scenes_quick.md").read_text(encoding="utf-8")
    assert md.count("What this shows") == 2
    recs = data["records"]

    refs = {r["scene"]: r for r in recs if r["benchmark"] == "reference"}
    assert set(refs) == {"two_objects", "env_sphere"}
    assert refs["two_objects"]["contact_pixels"] > 10 and refs["env_sphere"]["pixels"] > 50

    two = [r for r in recs if r["benchmark"] == "two_objects"]
    env = [r for r in recs if r["benchmark"] == "environment"]
    assert two and env
    for r in two + env:
        for key in ("rel_rmse", "patchiness", "frac_err_gt10", "t_frame_s"):
            assert _finite(r[key]) and r[key] >= 0, (key, r)
        assert r["finite"] and r["splats"] > 0 and r["repeats"] >= 1
    for r in two:
        assert _finite(r["rel_rmse_contact"]) and r["contact_pixels"] > 0

    # object-id clipping: at the budget grid the clipped frame is closer to the reference near the contact
    budget = {r["clip_objects"]: r for r in two if r["sweep"] == "grid" and r["grid_ratio"] == 1.0}
    assert set(budget) == {True, False}
    assert budget[True]["splats"] == budget[False]["splats"]
    assert budget[True]["rel_rmse_contact"] < 0.5 * budget[False]["rel_rmse_contact"]
    assert budget[True]["rel_rmse"] < budget[False]["rel_rmse"]
    assert budget[True]["rel_rmse"] < 0.05  # the budget grid against the ray-traced reference

    # Shah Fig. 6.10: the budget grid beats the 1/4x grid, with more splats
    (quarter,) = [r for r in two if r["sweep"] == "grid" and r["grid_ratio"] == 0.25]
    assert quarter["clip_objects"] and quarter["splats"] < budget[True]["splats"]
    assert budget[True]["rel_rmse"] < quarter["rel_rmse"]

    grid = sorted([r for r in env if r["sweep"] == "grid"], key=lambda r: r["grid_ratio"])
    assert len(grid) == 2 and grid[0]["grid_ratio"] < 0.3 and grid[1]["grid_ratio"] == 1.0
    assert grid[1]["rel_rmse"] < grid[0]["rel_rmse"] and grid[1]["splats"] > grid[0]["splats"]
    assert grid[1]["rel_rmse"] < 0.05
    peel = {r["peel_layers"]: r for r in env if r["sweep"] == "peel"}
    assert set(peel) == {1, 8}
    assert peel[1]["layers"] == "1/1/1" and peel[8]["layers"] == "2/2/2"  # a convex sphere: two layers per view
    assert peel[8]["rel_rmse"] == grid[1]["rel_rmse"]  # the same frame, measured once
    assert peel[1]["rel_rmse"] > 2.0 * peel[8]["rel_rmse"]  # one layer misses the far side
