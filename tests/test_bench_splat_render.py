"""benchmarks/bench_splat_render.py: its error measures on synthetic images, and its --quick run end to end.

``--quick`` uses only the built-in default scene (spot), so these tests need no file from ../shared.
"""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks" / "bench_splat_render.py"


def _load_bench():
    spec = importlib.util.spec_from_file_location("bench_splat_render", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass resolves annotations through sys.modules
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def bench():
    return _load_bench()


def _images(h: int = 24, w: int = 24):
    ref = torch.ones(1, 3, h, w)
    mask = torch.zeros(1, 1, h, w, dtype=torch.bool)
    mask[..., 4:20, 4:20] = True
    return ref, mask


def test_error_maps_separate_smooth_bias_from_patches(bench):
    ref, mask = _images()
    biased = ref * 1.2  # a smooth 20 % error: no high-frequency part
    m = bench.error_maps(biased, ref, mask)
    assert m["patchiness"] < 1e-6
    assert m["lowfreq_rms"] == pytest.approx(0.2, rel=1e-6)
    assert m["frac_err_gt10"] == 1.0 and m["error_pixels"] == 256
    yy, xx = torch.meshgrid(torch.arange(24), torch.arange(24), indexing="ij")
    checker = (((yy // 2) + (xx // 2)) % 2).to(torch.float32) * 2.0 - 1.0  # +-1 in 2-pixel squares
    patchy = ref * (1.0 + 0.2 * checker)
    p = bench.error_maps(patchy, ref, mask)
    assert p["patchiness"] > 0.1  # most of the +-20 % is high-frequency
    assert p["lowfreq_rms"] < 0.1
    assert bench.rel_rmse(patchy, ref, mask) == pytest.approx(0.2, rel=1e-5)


def test_error_maps_ignore_pixels_below_the_luminance_floor(bench):
    ref, mask = _images()
    ref[..., 4:8, :] = 1e-6  # a dark band: the relative error there is meaningless
    img = ref.clone()
    img[..., 4:8, :] = 1.0
    m = bench.error_maps(img, ref, mask)
    assert m["error_pixels"] == 12 * 16
    assert m["frac_err_gt10"] == 0.0 and m["patchiness"] < 1e-9


def test_materials_summary_ratios_come_from_the_rows(bench):
    rows = [{"preset": "a", "t_frame_s": 2.0, "t_splat_s": 1.0, "pairs": 100, "splats": 10, "footprint_px": 10.0,
             "ns_per_pair": 1.0, "capped": False},
            {"preset": "b", "t_frame_s": 8.0, "t_splat_s": 6.0, "pairs": 400, "splats": 40, "footprint_px": 10.0,
             "ns_per_pair": 1.0, "capped": True},
            {"preset": "c", "t_frame_s": 4.0, "t_splat_s": 3.0, "pairs": 200, "splats": 20, "footprint_px": 10.0,
             "ns_per_pair": 1.0, "capped": False}]
    s = bench.materials_summary(rows)
    assert s["t_ratio"] == 4.0 and s["t_max_preset"] == "b" and s["t_min_preset"] == "a"
    assert s["pairs_ratio"] == 4.0 and s["splats_ratio"] == 4.0 and s["t_splat_ratio"] == 6.0
    assert s["t_ratio_uncapped"] == 2.0 and s["pairs_ratio_uncapped"] == 2.0 and s["capped_presets"] == "b"
    assert s["slope_pairs_vs_splats"] == pytest.approx(1.0)  # pairs proportional to splats: no balance


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def test_bench_splat_render_quick(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.run([sys.executable, str(BENCH), "--quick", "--out-dir", str(out)],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    data = json.loads((out / "splat_render_quick.json").read_text(encoding="utf-8"))
    md = (out / "splat_render_quick.md").read_text(encoding="utf-8")
    assert md.count("What this shows") == 2
    recs = data["records"]

    mats = [r for r in recs if r["benchmark"] == "materials"]
    assert [r["preset"] for r in mats] == ["chicken1", "potato", "skin1"]
    for r in mats:
        for key in ("r_max_mm", "h_mm", "t_frame_s", "t_budget_s", "footprint_px", "reach_fraction", "sigma_tr",
                    "sigma_t_prime"):
            assert _finite(r[key]) and r[key] > 0, (key, r)
        assert r["finite"] and r["repeats"] >= 1 and r["splats"] > 0 and r["pairs"] > 0
        assert r["footprint_px"] == pytest.approx(r["pairs"] / r["splats"])
        assert r["footprint_px"] <= r["pixels"] and r["reach_fraction"] <= 1.0
        assert r["capped"] == (r["grid"] < r["grid_uncapped"])
    by = {r["preset"]: r for r in mats}
    # quick caps the grid at 64: skin1 asks for more and is undersampled; the others fit
    assert by["skin1"]["capped"] and by["skin1"]["grid"] == 64 and by["skin1"]["oversample_eff"] < 2.0
    assert not by["chicken1"]["capped"] and by["chicken1"]["oversample_eff"] == 2.0
    assert by["skin1"]["r_max_mm"] < by["chicken1"]["r_max_mm"]  # skin1 is the least translucent of the three
    (s,) = [r for r in recs if r["benchmark"] == "materials_summary"]
    times = [r["t_frame_s"] for r in mats]
    pairs = [r["pairs"] for r in mats]
    assert s["t_ratio"] == pytest.approx(max(times) / min(times))
    assert s["pairs_ratio"] == pytest.approx(max(pairs) / min(pairs))
    assert s["capped_presets"] == "skin1" and s["presets"] == 3

    (ref,) = [r for r in recs if r["benchmark"] == "reference"]
    assert ref["scene"] == "spot40" and ref["shadows"] == "raytrace" and ref["pixels"] > 100
    acc = [r for r in recs if r["benchmark"] == "accuracy"]
    for r in acc:
        for key in ("rel_rmse", "patchiness", "lowfreq_rms", "t_frame_s"):
            assert _finite(r[key]) and r[key] >= 0, (key, r)
    grid = sorted([r for r in acc if r["sweep"] == "grid"], key=lambda r: r["grid_ratio"])
    assert [r["oversample"] for r in grid] == [0.25, 2.0]
    under, budget = grid
    assert budget["grid_ratio"] == 1.0 and under["grid_ratio"] < 0.2 and under["splats"] < budget["splats"]
    assert budget["rel_rmse"] < 0.1  # the budget grid against the ray-traced reference
    assert under["rel_rmse"] > 2.0 * budget["rel_rmse"]  # Shah Fig. 6.10: too few splats
    assert under["patchiness"] > 2.0 * budget["patchiness"]
    assert under["frac_err_gt10"] > budget["frac_err_gt10"]
    eps = {r["eps"]: r for r in acc if r["sweep"] == "eps"}
    assert set(eps) == {0.1, 0.01}
    assert eps[0.1]["r_max_mm"] < eps[0.01]["r_max_mm"] and eps[0.1]["rel_rmse"] > eps[0.01]["rel_rmse"]
    assert eps[0.01]["rel_rmse"] == budget["rel_rmse"]  # the same frame (budget grid, eps 0.01), measured once
