"""Smoke run of benchmarks/bench_cli_memory.py on one scene and method: it runs the CLI and records its cost."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks" / "bench_cli_memory.py"


def test_bench_cli_memory_smoke(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.run(
        [sys.executable, str(BENCH), "--scenes", "default", "--methods", "splat", "--resolution", "24",
         "--out-dir", str(out), "--name", "cli"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (rec,) = json.loads((out / "cli.json").read_text(encoding="utf-8"))["records"]
    assert (out / "cli.md").is_file()
    assert rec["scene"] == "default" and rec["method"] == "splat" and rec["exit"] == 0
    assert rec["summary"].startswith("splat: 24x24")
    # a process with torch imported holds well over 100 MB; the render of a 24 x 24 image well under 4 GB
    assert 100.0 < rec["peak_rss_mb"] < 4096.0 and rec["wall_s"] > 0.0
