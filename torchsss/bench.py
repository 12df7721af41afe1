"""Benchmark harness: robust timing of callables, interleaved A/B comparisons and result files.

The scripts in ``benchmarks/`` build on three functions:

* :func:`time_callable` times one callable: each sample loops the callable enough times to last at least
  ``min_time_s`` (so timer resolution and per-sample overhead do not matter), and the per-call seconds of
  ``repeats`` samples are summarised by their median, min, max and interquartile range.
* :func:`compare` times a candidate against a baseline *in the same process*, alternating their samples
  (candidate, baseline, baseline, candidate, ...) so that slow drift of a shared, noisy machine (thermal
  throttling, other jobs) affects both alike; the speed-up is ``baseline / candidate`` of the medians.
* :func:`write_results` writes ``<name>.json`` (records plus the environment: torch version, threads,
  platform, CPU count, date) and ``<name>.md`` (the same records as Markdown tables).

Timings are wall-clock (:func:`time.perf_counter`); the garbage collector is paused while a sample runs, as
:mod:`timeit` does. Work queued asynchronously (CUDA kernels) must be synchronised inside the callable.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import gc
import json
import math
import numbers
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from torchsss._checks import check_int

__all__ = [
    "benchmark_parser",
    "compare",
    "environment",
    "finish_benchmark",
    "format_value",
    "markdown_table",
    "setup_benchmark",
    "time_callable",
    "write_results",
]

_TIMING_KEYS = ("repeats", "warmup", "min_time_s")
_COMPARE_KEYS = ("name", "candidate_median_s", "baseline_median_s", "speedup", "candidate_iqr_s", "baseline_iqr_s",
                 "candidate_min_s", "baseline_min_s", "candidate_loops", "baseline_loops", "repeats")
# Growth cap of one calibration step, so that one fast outlier call does not make the loop count explode.
_MAX_GROWTH = 100.0


# -- validation ---------------------------------------------------------------------------------------------------
def _check_callable(fn: object, name: str) -> None:
    if not callable(fn):
        raise TypeError(f"{name}: expected a callable, got {type(fn).__name__}")



def _check_seconds(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name}: expected a number of seconds >= 0, got {type(value).__name__}")
    if not math.isfinite(float(value)) or value < 0:
        raise ValueError(f"{name}: expected a finite number of seconds >= 0, got {value!r}")
    return float(value)


def _check_name(value: object, name: str) -> str:
    if not isinstance(value, str):
        raise TypeError(f"{name}: expected a non-empty str, got {type(value).__name__}")
    if not value.strip():
        raise ValueError(f"{name}: expected a non-empty str, got {value!r}")
    return value


def _timing_args(repeats: object, warmup: object, min_time_s: object) -> tuple[int, int, float]:
    return (check_int(repeats, "repeats", 1), check_int(warmup, "warmup", 0),
            _check_seconds(min_time_s, "min_time_s"))


# -- timing -------------------------------------------------------------------------------------------------------
def _run(fn: Callable[[], object], loops: int) -> float:
    """Seconds taken by ``loops`` back-to-back calls of ``fn``, with the garbage collector paused."""
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        start = time.perf_counter()
        for _ in range(loops):
            fn()
        return time.perf_counter() - start
    finally:
        if gc_was_enabled:
            gc.enable()


def _calibrate(fn: Callable[[], object], warmup: int, min_time_s: float) -> int:
    """Run ``warmup`` untimed calls, then find a loop count whose sample lasts at least ``min_time_s``."""
    for _ in range(warmup):
        fn()
    loops = 1
    while True:
        elapsed = _run(fn, loops)
        if elapsed >= min_time_s:
            return loops
        # aim 20% above the target so that a sample does not fall just short of it
        growth = 1.2 * min_time_s / elapsed if elapsed > 0 else _MAX_GROWTH
        loops = max(loops + 1, math.ceil(loops * min(growth, _MAX_GROWTH)))


def _summary(samples: Sequence[float]) -> dict[str, float]:
    if len(samples) >= 2:
        q1, _, q3 = statistics.quantiles(samples, n=4, method="inclusive")
    else:
        q1 = q3 = samples[0]
    return {
        "median_s": statistics.median(samples),
        "min_s": min(samples),
        "max_s": max(samples),
        "iqr_s": q3 - q1,
        "q1_s": q1,
        "q3_s": q3,
    }


def time_callable(
    fn: Callable[[], object], *, repeats: int = 7, warmup: int = 2, min_time_s: float = 0.05
) -> dict[str, Any]:
    """Time a zero-argument callable: median, min, max and interquartile range of the seconds per call.

    After ``warmup`` untimed calls the loop count is calibrated so that one sample (``loops`` back-to-back
    calls) lasts at least ``min_time_s``; then ``repeats`` samples are taken and each is divided by ``loops``.

    Args:
        fn: the work to time, called with no arguments (wrap arguments in a closure or ``functools.partial``).
        repeats: number of timed samples (>= 1).
        warmup: untimed calls before calibration (>= 0); the calibration runs also warm up.
        min_time_s: minimum duration of one sample in seconds (>= 0; 0 means one call per sample).

    Returns:
        A dict with ``median_s``, ``min_s``, ``max_s``, ``iqr_s``, ``q1_s``, ``q3_s`` (seconds per call),
        ``repeats``, ``loops`` (calls per sample) and ``samples_s`` (the per-call seconds of every sample).

    Raises:
        TypeError: ``fn`` is not callable, or a count/duration is not a number.
        ValueError: ``repeats < 1``, ``warmup < 0`` or a negative/non-finite ``min_time_s``.

    Examples:
        >>> t = time_callable(lambda: sum(range(100)), repeats=3, warmup=1, min_time_s=0.001)
        >>> t["min_s"] <= t["median_s"] <= t["max_s"], t["repeats"], len(t["samples_s"])
        (True, 3, 3)
    """
    _check_callable(fn, "fn")
    repeats, warmup, min_time_s = _timing_args(repeats, warmup, min_time_s)
    loops = _calibrate(fn, warmup, min_time_s)
    samples = [_run(fn, loops) / loops for _ in range(repeats)]
    return {**_summary(samples), "repeats": repeats, "loops": loops, "samples_s": samples}


def compare(
    candidate: Callable[[], object],
    baseline: Callable[[], object],
    *,
    name: str,
    extra: Mapping[str, Any] | None = None,
    **timing_kw: Any,
) -> dict[str, Any]:
    """Time ``candidate`` against ``baseline`` with interleaved samples and report the speed-up.

    Both are warmed up and calibrated separately (each gets its own loop count), then their samples alternate
    in the order candidate, baseline, baseline, candidate, candidate, ... so that a linear drift in machine
    speed biases neither.

    Args:
        candidate: the (presumably faster) implementation, a zero-argument callable.
        baseline: the implementation it is measured against, a zero-argument callable.
        name: label of the comparison, stored as ``record["name"]``.
        extra: more metrics to store in the record (e.g. an error measure); keys must not clash with the
            timing keys.
        **timing_kw: ``repeats``, ``warmup``, ``min_time_s`` as in :func:`time_callable`.

    Returns:
        A flat record: ``name``, ``candidate_median_s``, ``baseline_median_s``, ``speedup`` (baseline median /
        candidate median; > 1 means the candidate is faster), ``candidate_iqr_s``, ``baseline_iqr_s``,
        ``candidate_min_s``, ``baseline_min_s``, ``candidate_loops``, ``baseline_loops``, ``repeats``, then
        the items of ``extra``.

    Raises:
        TypeError: a non-callable, a non-str ``name``, an unknown timing keyword, a non-mapping ``extra``.
        ValueError: an empty ``name``, bad timing values, ``extra`` keys that clash with the timing keys.

    Examples:
        >>> rec = compare(lambda: None, lambda: sum(range(1000)), name="noop", repeats=3, min_time_s=0.001,
        ...               extra={"note": "demo"})
        >>> rec["name"], rec["speedup"] > 0, rec["note"]
        ('noop', True, 'demo')
    """
    _check_callable(candidate, "candidate")
    _check_callable(baseline, "baseline")
    name = _check_name(name, "name")
    unknown = sorted(set(timing_kw) - set(_TIMING_KEYS))
    if unknown:
        raise TypeError(f"timing_kw: expected keywords among {_TIMING_KEYS}, got {unknown}")
    defaults = {"repeats": 7, "warmup": 2, "min_time_s": 0.05}
    repeats, warmup, min_time_s = _timing_args(*({**defaults, **timing_kw}[k] for k in _TIMING_KEYS))
    if extra is None:
        extra = {}
    if not isinstance(extra, Mapping):
        raise TypeError(f"extra: expected a mapping of metric name to value, got {type(extra).__name__}")
    for key in extra:
        if not isinstance(key, str):
            raise TypeError(f"extra: expected str keys, got {type(key).__name__} key {key!r}")
        if key in _COMPARE_KEYS:
            raise ValueError(f"extra: expected keys other than the timing keys {_COMPARE_KEYS}, got {key!r}")

    loops_c = _calibrate(candidate, warmup, min_time_s)
    loops_b = _calibrate(baseline, warmup, min_time_s)
    cand: list[float] = []
    base: list[float] = []
    for i in range(repeats):
        order = ((candidate, loops_c, cand), (baseline, loops_b, base))
        for fn, loops, out in (order if i % 2 == 0 else order[::-1]):
            out.append(_run(fn, loops) / loops)
    sc, sb = _summary(cand), _summary(base)
    record: dict[str, Any] = {
        "name": name,
        "candidate_median_s": sc["median_s"],
        "baseline_median_s": sb["median_s"],
        "speedup": sb["median_s"] / sc["median_s"] if sc["median_s"] > 0 else math.inf,
        "candidate_iqr_s": sc["iqr_s"],
        "baseline_iqr_s": sb["iqr_s"],
        "candidate_min_s": sc["min_s"],
        "baseline_min_s": sb["min_s"],
        "candidate_loops": loops_c,
        "baseline_loops": loops_b,
        "repeats": repeats,
    }
    record.update(extra)
    return record


# -- results ------------------------------------------------------------------------------------------------------
def environment() -> dict[str, Any]:
    """Where the numbers were measured: torch and Python versions, threads, platform, CPU count, date (UTC).

    Examples:
        >>> env = environment()
        >>> env["torch"] == torch.__version__, env["threads"] == torch.get_num_threads()
        (True, True)
    """
    env: dict[str, Any] = {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "threads": torch.get_num_threads(),
        "interop_threads": torch.get_num_interop_threads(),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or None,
        "cpu_count": os.cpu_count(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    try:
        env["cpu_affinity"] = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on every platform
        pass
    return env


def _jsonable(value: Any) -> Any:
    """Convert tensors, numpy scalars, dtypes and paths to JSON types; non-finite floats become ``None``."""
    if isinstance(value, torch.Tensor):
        return _jsonable(value.detach().cpu().tolist())
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        v = float(value)
        return v if math.isfinite(v) else None
    if hasattr(value, "item") and callable(value.item):  # numpy scalars and 0-d arrays
        return _jsonable(value.item())
    if hasattr(value, "tolist") and callable(value.tolist):  # numpy arrays
        return _jsonable(value.tolist())
    return str(value)  # dtypes, devices, paths, ...


def format_value(value: Any) -> str:
    """Format one table cell: 4 significant digits, scientific notation outside [1e-3, 1e5).

    Examples:
        >>> [format_value(v) for v in (0.012345, 123456.0, 3.2e-7, 0.0, 7, True, None, [1.0, 2.5])]
        ['0.01235', '1.235e+05', '3.200e-07', '0', '7', 'True', '', '1, 2.5']
    """
    if value is None:
        return ""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().tolist()
    if isinstance(value, (bool, str)):
        text = str(value)
    elif isinstance(value, numbers.Integral):
        text = str(int(value))
    elif isinstance(value, numbers.Real):
        v = float(value)
        if not math.isfinite(v):
            text = str(v)
        elif v == 0.0:
            text = "0"
        elif 1e-3 <= abs(v) < 1e5:
            text = f"{v:.4g}"
        else:
            text = f"{v:.3e}"
    elif isinstance(value, (list, tuple)):
        text = ", ".join(format_value(v) for v in value)
    else:
        text = str(value)
    return text.replace("|", "\\|").replace("\n", " ")


def environment_line(env: Mapping[str, Any]) -> str:
    """The ``Environment: k=v, ...`` line that closes every results Markdown (None values left out).

    Examples:
        >>> environment_line({"torch": "2.13.0", "threads": 2, "gpu": None})
        'Environment: torch=2.13.0, threads=2.'
    """
    return "Environment: " + ", ".join(f"{k}={format_value(v)}" for k, v in env.items() if v is not None) + "."


def _columns(records: Sequence[Mapping[str, Any]]) -> list[str]:
    seen: dict[str, None] = {}
    for rec in records:
        for key in rec:
            seen.setdefault(key, None)
    return list(seen)


def _is_numeric_column(records: Sequence[Mapping[str, Any]], column: str) -> bool:
    vals = [rec[column] for rec in records if rec.get(column) is not None]
    return bool(vals) and all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in vals)


def markdown_table(records: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None) -> str:
    """A GitHub-flavoured Markdown table of ``records``; missing cells are empty, numbers right-aligned.

    Args:
        records: the rows, dicts of column name to value.
        columns: which columns, in order (default: the union of the records' keys, in first-seen order).

    Examples:
        >>> print(markdown_table([{"size": 256, "err": 1.5e-6}, {"size": 1024, "note": "x"}]))
        | size | err | note |
        |---:|---:|---|
        | 256 | 1.500e-06 |  |
        | 1024 |  | x |
    """
    cols = list(columns) if columns is not None else _columns(records)
    lines = ["| " + " | ".join(format_value(c) for c in cols) + " |",
             "|" + "|".join("---:" if _is_numeric_column(records, c) else "---" for c in cols) + "|"]
    lines += ["| " + " | ".join(format_value(rec.get(c)) for c in cols) + " |" for rec in records]
    return "\n".join(lines)


def _check_records(records: object) -> list[dict[str, Any]]:
    if not isinstance(records, (list, tuple)):
        raise TypeError(f"records: expected a list of dicts, got {type(records).__name__}")
    for i, rec in enumerate(records):
        if not isinstance(rec, Mapping):
            raise TypeError(f"records[{i}]: expected a dict, got {type(rec).__name__}")
        bad = [k for k in rec if not isinstance(k, str)]
        if bad:
            raise TypeError(f"records[{i}]: expected str keys, got {type(bad[0]).__name__} key {bad[0]!r}")
    return [dict(rec) for rec in records]


def write_results(
    name: str,
    records: list[dict[str, Any]],
    directory: str | os.PathLike[str] = "benchmarks/results",
    *,
    columns: Sequence[str] | Mapping[Any, Sequence[str]] | None = None,
    group_key: str | None = "benchmark",
) -> tuple[Path, Path]:
    """Write ``<directory>/<name>.json`` and ``<directory>/<name>.md`` (the directory is created if needed).

    The JSON holds ``{"name", "environment", "records"}`` (see :func:`environment`); tensors, numpy values and
    dtypes are converted, and non-finite floats are written as ``null`` so that the file is strict JSON. The
    Markdown file has a heading, one table per group (records sharing the value of ``group_key``; one table if
    no record has that key) and the environment.

    Args:
        name: file stem, e.g. ``"profile"``; letters, digits, ``-``, ``_`` and ``.`` only.
        records: the results, one dict per row.
        directory: output folder (relative paths are relative to the current working directory).
        columns: Markdown columns, in order: one list for every table, or a mapping from group value to list
            (groups not in the mapping get the default). Default: the union of the keys of the group's records,
            in first-seen order, without ``group_key``. The JSON always holds every key.
        group_key: record key that splits the Markdown into sections, or ``None`` for a single table.

    Returns:
        ``(json_path, md_path)``.

    Raises:
        TypeError: ``name`` not a str, ``records`` not a list of dicts with str keys, a bad ``directory``.
        ValueError: an empty ``name`` or one with other characters (e.g. a path separator).
    """
    name = _check_name(name, "name")
    if not all(ch.isalnum() or ch in "-_." for ch in name) or name.startswith("."):
        raise ValueError(f"name: expected a file stem of letters, digits, '-', '_', '.', got {name!r}")
    recs = _check_records(records)
    if not isinstance(directory, (str, os.PathLike)):
        raise TypeError(f"directory: expected a str or path, got {type(directory).__name__}")
    column_map = columns if isinstance(columns, Mapping) else {None: columns} if columns is not None else {}
    for cols in column_map.values():
        if isinstance(cols, str) or not isinstance(cols, Sequence) or not all(isinstance(c, str) for c in cols):
            raise TypeError(f"columns: expected a sequence of str (or a mapping to such), got {cols!r}")
    if group_key is not None and not isinstance(group_key, str):
        raise TypeError(f"group_key: expected a str or None, got {type(group_key).__name__}")

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    env = environment()
    json_path = out / f"{name}.json"
    md_path = out / f"{name}.md"
    payload = {"name": name, "environment": _jsonable(env), "records": _jsonable(recs)}
    json_path.write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n", encoding="utf-8")

    groups: dict[Any, list[dict[str, Any]]] = {}
    for rec in recs:
        groups.setdefault(rec.get(group_key) if group_key else None, []).append(rec)
    parts = [f"# {name}", ""]
    for group, rows in groups.items():
        if group is not None:
            parts += [f"## {format_value(group)}", ""]
        chosen = column_map.get(group) if isinstance(columns, Mapping) else columns
        cols = list(chosen) if chosen is not None else _columns(rows)
        if group is not None:
            cols = [c for c in cols if c != group_key]
        parts += [markdown_table(rows, cols), ""]
    parts += [environment_line(env), ""]
    md_path.write_text("\n".join(parts), encoding="utf-8")
    return json_path, md_path


def benchmark_parser(description: str, name: str, results_dir: Path, *, seed_help: str = "seed of the random inputs"):
    """The command line every benchmark script shares: --quick, --out-dir, --name, --threads, --seed.

    Scripts add their own options to the returned :class:`argparse.ArgumentParser`, then call
    :func:`setup_benchmark` on the parsed arguments.
    """
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true", help="small sizes for a smoke run")
    parser.add_argument("--out-dir", type=Path, default=results_dir, help=f"output folder (default {results_dir})")
    parser.add_argument("--name", default=name, help=f"file stem of the results (default {name!r})")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: stable on a shared machine; 0 = torch default)")
    parser.add_argument("--seed", type=int, default=0, help=seed_help)
    return parser


def setup_benchmark(parser, args) -> None:
    """Validate ``--threads``, set torch's thread count and seed (for parsers from :func:`benchmark_parser`)."""
    if args.threads < 0:
        parser.error(f"--threads: expected an int >= 0, got {args.threads}")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)


def finish_benchmark(name: str, records: list[dict[str, Any]], directory: str | os.PathLike[str], *,
                     columns: Sequence[str] | Mapping[Any, Sequence[str]] | None = None,
                     start: float | None = None) -> tuple[Path, Path]:
    """Warn on stderr about non-finite numbers in ``records``, write them (:func:`write_results`), say where.

    ``start`` is the :func:`time.perf_counter` value at the beginning of the run, for the elapsed time.
    """
    for rec in records:
        bad = [k for k, v in rec.items() if isinstance(v, float) and not math.isfinite(v)]
        if bad:
            print(f"warning: non-finite {bad} in {rec}", file=sys.stderr)
    json_path, md_path = write_results(name, records, directory, columns=columns)
    took = "" if start is None else f" in {time.perf_counter() - start:.1f} s"
    print(f"wrote {json_path} and {md_path}{took}")
    return json_path, md_path
