"""Smoke run of benchmarks/bench_chang.py --quick: it finishes and writes records with finite errors.

``--quick`` uses only the built-in default scene (spot), so this test needs no file from ../shared.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH_CHANG = ROOT / "benchmarks" / "bench_chang.py"


def _finite_nonneg(rec: dict, key: str) -> None:
    v = rec[key]
    assert isinstance(v, float) and math.isfinite(v) and v >= 0, (key, rec)


def test_bench_chang_quick_smoke(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.run(
        [sys.executable, str(BENCH_CHANG), "--quick", "--out-dir", str(out)],
        capture_output=True, text=True, timeout=240, cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    data = json.loads((out / "chang_quick.json").read_text(encoding="utf-8"))
    assert (out / "chang_quick.md").is_file()
    recs = data["records"]

    sweep = [r for r in recs if r["benchmark"] == "error_vs_n"]
    assert sorted(r["samples"] for r in sweep) == [49, 256]
    for r in sweep:
        assert r["scene"] == "spot40" and r["atlas"] == 256 and r["receivers"] > 0 and r["seeds"] == 1
        for key in ("rel_rmse_mean", "rel_rmse_quadrature", "t_module_ms", "t_frame_s", "t_irradiance_s",
                    "t_precompute_s"):
            _finite_nonneg(r, key)
        assert r["rel_rmse_quadrature"] < 0.2  # the expectation is close to the reference: a floor, not noise
        assert r["fast_path_max_rel_diff"] < 1e-4  # the benchmark's frames are render_icdf's frames
    by_n = {r["samples"]: r for r in sweep}
    assert by_n[256]["rel_rmse_mean"] < by_n[49]["rel_rmse_mean"]  # ~1/sqrt(N): 2.3x fewer errors expected
    assert by_n[256]["rel_rmse_mean"] < 1.0

    (fit,) = [r for r in recs if r["benchmark"] == "fit"]
    assert math.isfinite(fit["slope"]) and -1.0 < fit["slope"] < -0.2

    hyb = [r for r in recs if r["benchmark"] == "hybrid"]
    assert {r["method"] for r in hyb} == {"icdf", "hybrid"}
    for r in hyb:
        _finite_nonneg(r, "rel_rmse_mean")
        _finite_nonneg(r, "rel_rmse_expected")
        _finite_nonneg(r, "t_module_ms")
    (h,) = [r for r in hyb if r["method"] == "hybrid"]
    assert h["c"] == 0.01 and h["r_p_mm"] > 0 and h["local_bound_mm"] > h["r_p_mm"]
    assert 0.0 < h["local_mass_captured"] <= 1.0 + 1e-6
