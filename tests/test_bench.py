"""The benchmark harness (torchsss.bench) and a smoke run of benchmarks/bench_profile.py."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torchsss.bench import compare, format_value, markdown_table, time_callable, write_results

ROOT = Path(__file__).resolve().parents[1]
BENCH_PROFILE = ROOT / "benchmarks" / "bench_profile.py"

FAST = {"repeats": 3, "warmup": 0, "min_time_s": 0.0}


class Counter:
    """A callable that counts its calls."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self) -> None:
        self.calls += 1


# -- time_callable ------------------------------------------------------------------------------------------------
def test_time_callable_summary_is_consistent():
    t = time_callable(lambda: sum(range(200)), repeats=5, warmup=1, min_time_s=0.001)
    assert set(t) >= {"median_s", "min_s", "max_s", "iqr_s", "q1_s", "q3_s", "repeats", "loops", "samples_s"}
    assert t["repeats"] == 5 and len(t["samples_s"]) == 5
    assert 0 < t["min_s"] <= t["q1_s"] <= t["median_s"] <= t["q3_s"] <= t["max_s"]
    assert t["iqr_s"] == pytest.approx(t["q3_s"] - t["q1_s"])
    assert t["min_s"] == min(t["samples_s"]) and t["max_s"] == max(t["samples_s"])


def test_time_callable_loops_each_sample_past_min_time():
    t = time_callable(lambda: time.sleep(0.001), repeats=2, warmup=0, min_time_s=0.02)
    assert t["loops"] >= 2
    # every sample lasted at least min_time_s in total (per-call time x loops)
    assert min(t["samples_s"]) * t["loops"] >= 0.02


def test_time_callable_call_count():
    fn = Counter()
    t = time_callable(fn, repeats=4, warmup=3, min_time_s=0.0)
    assert t["loops"] == 1
    # 3 warmup calls, 1 calibration call, 4 samples of one call
    assert fn.calls == 3 + 1 + 4


def test_time_callable_single_repeat_has_zero_iqr():
    t = time_callable(lambda: None, repeats=1, warmup=0, min_time_s=0.0)
    assert t["iqr_s"] == 0.0 and t["median_s"] == t["min_s"] == t["max_s"]


@pytest.mark.parametrize(
    ("kwargs", "exc", "match"),
    [
        ({"repeats": 0}, ValueError, "repeats"),
        ({"repeats": 2.0}, TypeError, "repeats"),
        ({"repeats": True}, TypeError, "repeats"),
        ({"warmup": -1}, ValueError, "warmup"),
        ({"warmup": "2"}, TypeError, "warmup"),
        ({"min_time_s": -0.1}, ValueError, "min_time_s"),
        ({"min_time_s": math.nan}, ValueError, "min_time_s"),
        ({"min_time_s": "fast"}, TypeError, "min_time_s"),
    ],
)
def test_time_callable_bad_arguments(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        time_callable(lambda: None, **{**FAST, **kwargs})


def test_time_callable_rejects_non_callable():
    with pytest.raises(TypeError, match=r"fn: expected a callable, got int"):
        time_callable(3)


def test_time_callable_propagates_errors():
    def boom():
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        time_callable(boom, **FAST)


# -- compare ------------------------------------------------------------------------------------------------------
def test_compare_sleep_ratio():
    short = 0.002
    rec = compare(lambda: time.sleep(short), lambda: time.sleep(3 * short), name="sleep",
                  repeats=5, warmup=1, min_time_s=0.01)
    assert rec["name"] == "sleep"
    assert rec["speedup"] == pytest.approx(rec["baseline_median_s"] / rec["candidate_median_s"])
    assert 1.5 < rec["speedup"] < 6.0
    assert rec["candidate_median_s"] >= short and rec["baseline_median_s"] >= 3 * short


def test_compare_interleaves_and_adds_extra_metrics():
    order: list[str] = []
    rec = compare(lambda: order.append("c"), lambda: order.append("b"), name="order",
                  extra={"max_rel_err": 1e-5, "size": 256}, **{**FAST, "repeats": 4})
    # calibration: one call each, then samples alternate c b | b c | c b | b c
    assert order == ["c", "b", "c", "b", "b", "c", "c", "b", "b", "c"]
    assert rec["max_rel_err"] == 1e-5 and rec["size"] == 256
    assert rec["repeats"] == 4 and rec["candidate_loops"] == rec["baseline_loops"] == 1
    for key in ("candidate_median_s", "baseline_median_s", "speedup", "candidate_iqr_s", "baseline_iqr_s"):
        assert math.isfinite(rec[key]) and rec[key] >= 0


@pytest.mark.parametrize(
    ("kwargs", "exc", "match"),
    [
        ({"candidate": None}, TypeError, "candidate: expected a callable"),
        ({"baseline": 1.0}, TypeError, "baseline: expected a callable"),
        ({"name": 3}, TypeError, "name: expected a non-empty str"),
        ({"name": "  "}, ValueError, "name: expected a non-empty str"),
        ({"repeat": 3}, TypeError, "timing_kw"),
        ({"repeats": 0}, ValueError, "repeats"),
        ({"extra": [("a", 1)]}, TypeError, "extra: expected a mapping"),
        ({"extra": {"speedup": 2.0}}, ValueError, "extra: expected keys other than"),
        ({"extra": {1: 2.0}}, TypeError, "extra: expected str keys"),
    ],
)
def test_compare_bad_arguments(kwargs, exc, match):
    calls = Counter()
    args = {"candidate": calls, "baseline": calls, "name": "x", **FAST, **kwargs}
    with pytest.raises(exc, match=match):
        compare(**args)
    assert calls.calls == 0  # arguments are validated before anything runs


# -- write_results ------------------------------------------------------------------------------------------------
def test_write_results_round_trip(tmp_path):
    records = [
        {"benchmark": "lut", "preset": "marble", "size": 256, "speedup": 1.23456, "err": 3.2e-7,
         "rgb": torch.tensor([1.0, 2.0, 3.0]), "dtype": torch.float32},
        {"benchmark": "lut", "preset": "skin1", "size": 1024, "speedup": 0.5, "note": "a|b"},
        {"benchmark": "ref", "pairs": 1_000_000, "pairs_per_s": 2.5e7, "bad": math.inf},
    ]
    json_path, md_path = write_results("demo", records, tmp_path / "out")
    assert json_path == tmp_path / "out" / "demo.json" and md_path == tmp_path / "out" / "demo.md"

    data = json.loads(json_path.read_text(encoding="utf-8"))
    assert data["name"] == "demo"
    env = data["environment"]
    assert env["torch"] == torch.__version__ and env["threads"] == torch.get_num_threads()
    assert {"platform", "cpu_count", "date", "python"} <= set(env)
    assert len(data["records"]) == 3
    first = data["records"][0]
    assert first["rgb"] == [1.0, 2.0, 3.0] and first["dtype"] == "torch.float32"
    assert first["speedup"] == pytest.approx(1.23456)
    assert data["records"][2]["bad"] is None  # strict JSON: no Infinity

    md = md_path.read_text(encoding="utf-8")
    assert md.startswith("# demo")
    assert "## lut" in md and "## ref" in md
    tables = _parse_md_tables(md)
    assert len(tables) == 2
    header, rows = tables[0]
    assert header == ["preset", "size", "speedup", "err", "rgb", "dtype", "note"]  # union, first-seen order
    assert rows[0][:5] == ["marble", "256", "1.235", "3.200e-07", "1, 2, 3"]
    assert rows[1][header.index("note")] == "a\\|b" and rows[1][header.index("err")] == ""
    header, rows = tables[1]
    assert header == ["pairs", "pairs_per_s", "bad"]
    assert rows == [["1000000", "2.500e+07", "inf"]]
    assert "Environment:" in md and f"torch={torch.__version__}" in md


def test_write_results_columns_and_no_groups(tmp_path):
    records = [{"a": 1, "b": 2.0, "c": "x"}, {"a": 2, "b": 4.0}]
    _, md_path = write_results("cols", records, tmp_path, columns=["c", "a"])
    (header, rows), = _parse_md_tables(md_path.read_text(encoding="utf-8"))
    assert header == ["c", "a"] and rows == [["x", "1"], ["", "2"]]
    _, md_path = write_results("cols", [{"benchmark": "g", "a": 1, "b": 2}], tmp_path, columns={"g": ["b"]})
    (header, rows), = _parse_md_tables(md_path.read_text(encoding="utf-8"))
    assert header == ["b"] and rows == [["2"]]


def test_write_results_empty_records(tmp_path):
    json_path, md_path = write_results("empty", [], tmp_path)
    assert json.loads(json_path.read_text(encoding="utf-8"))["records"] == []
    assert md_path.read_text(encoding="utf-8").startswith("# empty")


@pytest.mark.parametrize(
    ("name", "records", "directory", "exc", "match"),
    [
        (3, [], ".", TypeError, "name: expected a non-empty str, got int"),
        ("", [], ".", ValueError, "name: expected a non-empty str"),
        ("../evil", [], ".", ValueError, "name: expected a file stem"),
        ("ok", {"a": 1}, ".", TypeError, "records: expected a list of dicts, got dict"),
        ("ok", [1.0], ".", TypeError, r"records\[0\]: expected a dict, got float"),
        ("ok", [{1: 2}], ".", TypeError, r"records\[0\]: expected str keys"),
        ("ok", [], 5, TypeError, "directory: expected a str or path, got int"),
    ],
)
def test_write_results_bad_arguments(tmp_path, monkeypatch, name, records, directory, exc, match):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(exc, match=match):
        write_results(name, records, directory)
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_write_results_bad_columns(tmp_path):
    with pytest.raises(TypeError, match="columns"):
        write_results("x", [{"a": 1}], tmp_path, columns="a")


def test_format_value_and_markdown_table():
    assert format_value(float("nan")) == "nan"
    assert format_value(12345.678) == "1.235e+04"
    assert format_value(123456.0) == "1.235e+05"
    assert format_value(-0.5) == "-0.5"
    table = markdown_table([{"x": 1.0, "s": "a"}])
    assert table.splitlines()[1] == "|---:|---|"


def _parse_md_tables(md: str) -> list[tuple[list[str], list[list[str]]]]:
    """(header, rows) of every Markdown table, cells stripped (escaped pipes kept as written)."""
    tables: list[tuple[list[str], list[list[str]]]] = []
    block: list[str] = []
    for line in [*md.splitlines(), ""]:
        if line.startswith("|"):
            block.append(line)
        elif block:
            cells = [_split_row(row) for row in block]
            tables.append((cells[0], cells[2:]))
            block = []
    return tables


def _split_row(row: str) -> list[str]:
    parts, cur, i = [], "", 1
    body = row.strip()
    while i < len(body) - 1:
        if body[i] == "\\" and body[i + 1] == "|":
            cur += "\\|"
            i += 2
            continue
        if body[i] == "|":
            parts.append(cur.strip())
            cur = ""
        else:
            cur += body[i]
        i += 1
    parts.append(cur.strip())
    return parts


# -- benchmarks/bench_profile.py ----------------------------------------------------------------------------------
def test_bench_profile_quick_smoke(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.run(
        [sys.executable, str(BENCH_PROFILE), "--quick", "--out-dir", str(out)],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    data = json.loads((out / "profile.json").read_text(encoding="utf-8"))
    assert (out / "profile.md").is_file()
    records = data["records"]

    lut = [r for r in records if r["benchmark"] == "lut_vs_analytic"]
    combos = {(r["preset"], r["layout"], r["warp"], r["size"]) for r in lut}
    assert combos == {(p, lay, w, s) for p in ("marble", "skin1") for lay in ("per_channel", "shared")
                      for w in ("sqrt", "linear") for s in (256, 1024, 4096)}
    for r in lut:
        assert r["dtype"] == "float32"
        for key in ("analytic_ms", "lut_ms", "speedup", "max_rel_err"):
            assert isinstance(r[key], float) and math.isfinite(r[key]) and r[key] > 0, (key, r)
        assert r["max_rel_err"] < 0.05  # a linear-interpolation table of >= 256 nodes
        assert len(r["rel_err_rgb"]) == 3
    # more nodes, smaller error
    for p in ("marble", "skin1"):
        for lay in ("per_channel", "shared"):
            for w in ("sqrt", "linear"):
                errs = [next(r["max_rel_err"] for r in lut
                             if (r["preset"], r["layout"], r["warp"], r["size"]) == (p, lay, w, s))
                        for s in (256, 1024, 4096)]
                assert errs[0] > errs[1] > errs[2]

    ref = [r for r in records if r["benchmark"] == "reference_radiosity"]
    assert {r["dtype"] for r in ref} == {"float32", "float64"}
    assert len(ref) == 4
    for r in ref:
        assert r["n_sources"] == r["n_receivers"] and r["pairs"] == r["n_sources"] ** 2
        for key in ("median_s", "pairs_per_s"):
            assert isinstance(r[key], float) and math.isfinite(r[key]) and r[key] > 0, (key, r)
    assert data["environment"]["torch"] == torch.__version__


BENCH_ICDF = ROOT / "benchmarks" / "bench_icdf.py"


def test_bench_icdf_quick_smoke(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.run([sys.executable, str(BENCH_ICDF), "--quick", "--out-dir", str(out)],
                          capture_output=True, text=True, timeout=180, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    records = json.loads((out / "icdf.json").read_text(encoding="utf-8"))["records"]
    assert {r["n"] for r in records} == {1000, 10000}
    for r in records:
        for key in ("descent_ms", "reference_ms", "multinomial_ms", "descent_x", "tables_ms"):
            assert math.isfinite(r[key]) and r[key] > 0, (key, r)
