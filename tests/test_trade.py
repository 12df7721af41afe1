"""The trade sweep (torchsss.trade): errors against closed forms, the Pareto front against brute force, a small
sweep end to end (JSON and plot) and the CLI."""

import json
import random

import pytest
import torch

from torchsss.cli import main
from torchsss.pipelines import RenderResult
from torchsss.scene import Scene
from torchsss.trade import PeakMemory, applicable_methods, image_error, pareto_front, sweep_configs, trade

SCENE = {"mesh": "sphere", "size_mm": 20.0, "material": "skin1",
         "lights": [{"type": "point", "position": [30, 20, 40], "intensity": 1e4}],
         "camera": {"eye": [0, 0, 50], "target": [0, 0, 0], "width": 12, "height": 12}}


def _result(img, mask):
    return RenderResult(radiance=img, radiosity=img, mask=mask)


def test_image_error_closed_form():
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(1, 3, 6, 7, generator=g) + 0.5
    mask = torch.ones(1, 1, 6, 7, dtype=torch.bool)
    mask[..., 0, :] = False
    out = image_error(_result(ref * 1.1, mask), _result(ref, mask))
    assert out["rel_rmse"] == pytest.approx(0.1, rel=1e-6)
    m = mask.expand_as(ref)
    assert out["max_error"] == pytest.approx(float(0.1 * ref[m].max() / ref[m].max()), rel=1e-6)
    # pixels outside either mask do not count
    bad = ref.clone()
    bad[..., 0, :] = 1e6
    assert image_error(_result(bad, mask), _result(ref, mask))["rel_rmse"] == 0.0
    with pytest.raises(ValueError, match="result"):
        image_error(_result(ref[..., :5], mask[..., :5]), _result(ref, mask))
    with pytest.raises(ValueError, match="covered"):
        image_error(_result(ref, ~mask & mask), _result(ref, mask))


def test_pareto_front_brute_force():
    rng = random.Random(1)
    for _ in range(20):
        rows = [{"frame_s": rng.random(), "rel_rmse": rng.random()} for _ in range(12)]
        dominated = {i for i, a in enumerate(rows)
                     if any(b["frame_s"] < a["frame_s"] and b["rel_rmse"] < a["rel_rmse"] for b in rows)}
        front = pareto_front(rows)
        assert set(front) == set(range(12)) - dominated
        assert [rows[i]["frame_s"] for i in front] == sorted(rows[i]["frame_s"] for i in front)
    assert pareto_front([]) == []


def test_sweep_configs_span_and_decimate():
    for method in ("reference", "splat", "icdf", "hybrid", "lensch"):
        full, quick = sweep_configs(method), sweep_configs(method, quick=True)
        assert len(quick) < len(full) or (method == "reference" and len(quick) == 1)
    assert all(c["source_faces"] == 20000 for c in sweep_configs("icdf", faces=70000))
    assert all("source_faces" not in c and "decimate" not in c for c in sweep_configs("splat", faces=70000))
    with pytest.raises(ValueError, match="method"):
        sweep_configs("caustics")
    glass = Scene.from_dict({**SCENE, "caustics": {"ior": 1.5}})
    assert applicable_methods(glass) == []
    with pytest.raises(ValueError, match="caustics"):
        trade(glass)


def test_peak_memory_sees_an_allocation():
    import mmap
    import time

    # Fresh pages from an anonymous map: a torch or numpy buffer may reuse heap pages that malloc kept resident
    # after an earlier test freed them, and then the resident set does not grow (this failed once in CI). The
    # sampler must see the resident set the buffer made: compared with that, not with the block's start, since the
    # rest of a test worker may release memory while the block runs (CI once saw no growth at all over 10 s with a
    # 64 MiB buffer measured against the start).
    size = 256 * 2**20
    with PeakMemory(interval=0.001) as pm:  # a transient allocation: the sampler thread sees it while it lives
        before = PeakMemory.rss_mib()
        buf = mmap.mmap(-1, size)
        buf.write(b"\x01" * size)  # touched: every page resident
        held = PeakMemory.rss_mib()
        deadline = time.monotonic() + 10.0  # on a loaded machine the sampler may wait well past 50 ms for a core
        while pm.available and pm._max < held - 1.0 and time.monotonic() < deadline:
            time.sleep(0.01)  # releases the GIL to the sampler
        buf.close()
    if pm.available:
        assert held - before > 128  # the buffer is resident (256 MiB)
        assert pm._max >= held - 1.0  # the sampler saw it while it lived
        assert pm.peak_mib == pytest.approx(max(0.0, pm._max - pm._start))
    else:
        assert pm.peak_mib == 0.0


def test_trade_small_sweep(tmp_path):
    scene = Scene.from_dict(SCENE)
    configs = {"reference": [{"eps": 0.3, "spacing_mm": 3.0}], "splat": [{"eps": 0.1}, {"eps": 0.01}]}
    result = trade(scene, methods=["reference", "splat"], frames=2, progress=False,
                   configs=lambda m: configs[m])
    rows = result["rows"]
    assert [r["method"] for r in rows] == ["reference", "splat", "splat"]
    for r in rows:
        assert r["setup_s"] >= 0 and r["frame_s"] > 0 and 0 <= r["rel_rmse"] < 1 and r["frames"] == 2
    # the splat budget's tolerance: a tighter eps is more accurate
    assert rows[2]["rel_rmse"] < rows[1]["rel_rmse"]
    assert set(result["pareto"]) <= set(range(3)) and result["pareto"]
    assert result["reference"]["covered_pixels"] > 0
    with pytest.raises(ValueError, match="methods"):
        trade(scene, methods=["caustics"])


def test_cli_trade_quick(tmp_path, capsys):
    path = tmp_path / "s.json"
    path.write_text(json.dumps({**SCENE, "camera": {**SCENE["camera"], "width": 8, "height": 8}}))
    out = tmp_path / "t"
    assert main(["trade", str(path), "--out", str(out), "--methods", "splat", "--quick", "--no-progress"]) == 0
    data = json.loads((out / "trade.json").read_text())
    assert {r["method"] for r in data["rows"]} == {"splat"} and len(data["rows"]) == 2
    assert (out / "trade.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = capsys.readouterr().out
    assert "Pareto" in text and "splat" in text
