"""benchmarks/bench_splat_paths.py --quick end to end: every splat frame timed on the path splat_radiosity took, the
planner's splat count (SceneFacts.light_fill x grid^2) against the renderer's, and the summary rows."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks" / "bench_splat_paths.py"


def test_bench_splat_paths_quick(tmp_path):
    out = tmp_path / "res"
    proc = subprocess.run([sys.executable, str(BENCH), "--quick", "--out-dir", str(out), "--name", "paths"],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    recs = json.loads((out / "paths.json").read_text(encoding="utf-8"))["records"]
    frames = [r for r in recs if r["benchmark"] == "frames"]
    assert len(frames) == 4
    for r in frames:
        assert r["path"] in ("gather", "tile", "window")
        assert r["splats"] > 0 and r["covered_px"] > 0 and r["pairs_evaluated"] > 0
        assert 0 < r["path_s"] <= r["frame_s"] and r["rest_s"] == pytest.approx(r["frame_s"] - r["path_s"])
        assert r["predicted_splats"] == pytest.approx(r["splats"], rel=0.25)
        assert r["predicted_frame_s"] > 0 and r["s_per_pair"] > 0
    summary = [r for r in recs if r["benchmark"] == "summary"]
    assert summary[-1]["path"] == "all" and summary[-1]["frames"] == 4
    assert {s["path"] for s in summary[:-1]} == {r["path"] for r in frames}
