"""Profile evaluation benchmarks: analytic dipole vs lookup table, and reference-integrator throughput.

(a) ``dipole_rd`` against ``lookup_profile_table`` on random distances, for the marble and skin1 presets in
    float32: time per call of each (interleaved samples), speed-up analytic/LUT and the table's max relative
    error from ``profile_table_error``. The table covers [0, r_max(eps=0.01)] per channel, sizes 256/1024/4096,
    warps "sqrt" and "linear". Distances have shape (N, 1) (one distance for all channels, as the reference
    integrator passes them), uniform in [0, max over channels of r_max].
(b) ``reference_radiosity`` with N sources = M receivers at random points in a 30 mm box (marble, analytic
    dipole), float32 and float64: seconds per call and (source, receiver) pairs per second.

Usage::

    python benchmarks/bench_profile.py            # full run, writes benchmarks/results/profile.{json,md}
    python benchmarks/bench_profile.py --quick    # smoke run with small sizes (a few seconds)
"""

from __future__ import annotations

import functools
import itertools
import sys
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, compare, finish_benchmark, setup_benchmark, time_callable
from torchsss.ops import reference_radiosity
from torchsss.physics import (
    build_profile_table,
    dipole_rd,
    lookup_profile_table,
    preset,
    profile_table_error,
    r_max,
)

RESULTS_DIR = Path(__file__).resolve().parent / "results"
PRESETS = ("marble", "skin1")
SIZES = (256, 1024, 4096)
WARPS = ("sqrt", "linear")
LAYOUTS = (("per_channel", False), ("shared", True))
EPS = 0.01
BOX_MM = 30.0

# Markdown columns per benchmark (the JSON keeps every key, including r_max_mm and repeats).
MD_COLUMNS = {
    "lut_vs_analytic": ["preset", "layout", "warp", "size", "dtype", "n_distances", "analytic_ms", "lut_ms", "speedup",
                        "analytic_iqr_ms", "lut_iqr_ms", "max_rel_err", "rel_err_rgb"],
    "reference_radiosity": ["preset", "dtype", "n_sources", "n_receivers", "pairs", "median_s", "iqr_s",
                            "pairs_per_s"],
}

FULL = {
    "n_distances": 1_000_000,
    "lut_timing": {"repeats": 9, "warmup": 2, "min_time_s": 0.25},
    "ref_sizes": (1000, 4000),
    "ref_timing": {"repeats": 5, "warmup": 1, "min_time_s": 0.2},
}
QUICK = {
    "n_distances": 20_000,
    "lut_timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.005},
    "ref_sizes": (100, 200),
    "ref_timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.005},
}


def _coefficients(name: str, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, float]:
    sa, ss, _ = preset(name).tensors(dtype)
    return sa, ss, preset(name).eta


def bench_lut(n_distances: int, timing: dict, log=print) -> list[dict]:
    """Analytic dipole vs lookup table, float32, for every preset, size and warp."""
    records = []
    for name in PRESETS:
        sa, ss, eta = _coefficients(name, torch.float32)
        sa64, ss64 = sa.double(), ss.double()
        rm = r_max(sa, ss, eta, eps=EPS)  # (3,) float32
        r = torch.rand(n_distances, 1, dtype=torch.float32) * rm.max()

        def profile32(x, sa=sa, ss=ss, eta=eta):
            return dipole_rd(x, sa, ss, eta)

        def analytic(r=r, profile32=profile32):
            return profile32(r)

        def exact64(x, sa64=sa64, ss64=ss64, eta=eta):
            return dipole_rd(x, sa64, ss64, eta)

        for (layout, shared), warp in itertools.product(LAYOUTS, WARPS):
            for size in SIZES:
                table = build_profile_table(profile32, rm, size, warp, shared_range=shared)

                def lut(r=r, table=table):
                    return lookup_profile_table(r, table)

                err = profile_table_error(table, exact64)
                with torch.inference_mode():
                    c = compare(lut, analytic, name=f"{name}/{layout}/{warp}/{size}", **timing)
                rec = {
                    "benchmark": "lut_vs_analytic",
                    "preset": name,
                    "layout": layout,
                    "warp": warp,
                    "size": size,
                    "dtype": "float32",
                    "n_distances": n_distances,
                    "analytic_ms": 1e3 * c["baseline_median_s"],
                    "lut_ms": 1e3 * c["candidate_median_s"],
                    "speedup": c["speedup"],
                    "analytic_iqr_ms": 1e3 * c["baseline_iqr_s"],
                    "lut_iqr_ms": 1e3 * c["candidate_iqr_s"],
                    "max_rel_err": float(err.max()),
                    "rel_err_rgb": [float(e) for e in err],
                    "r_max_mm": [float(v) for v in rm],
                    "repeats": c["repeats"],
                }
                log(f"  {rec['preset']:7s} {layout:11s} {warp:6s} {size:5d}: analytic {rec['analytic_ms']:8.3f} ms, "
                    f"lut {rec['lut_ms']:8.3f} ms, speed-up {rec['speedup']:5.2f}x, "
                    f"max rel err {rec['max_rel_err']:.2e}")
                records.append(rec)
    return records


def bench_reference(sizes, timing: dict, log=print) -> list[dict]:
    """Throughput of the all-pairs reference integrator (marble, analytic dipole), float32 and float64."""
    records = []
    for dtype in (torch.float32, torch.float64):
        sa, ss, eta = _coefficients("marble", dtype)
        profile = functools.partial(dipole_rd, sigma_a=sa, sigma_s_prime=ss, eta=eta)
        for n in sizes:
            src = torch.rand(1, n, 3, dtype=dtype) * BOX_MM
            dst = torch.rand(1, n, 3, dtype=dtype) * BOX_MM
            irradiance = torch.rand(1, n, 3, dtype=dtype)
            area = torch.full((1, n), BOX_MM * BOX_MM / n, dtype=dtype)

            def run(src=src, dst=dst, irradiance=irradiance, area=area, profile=profile):
                return reference_radiosity(src, irradiance, area, dst, profile)

            with torch.inference_mode():
                out = run()
                if not bool(torch.isfinite(out).all()):
                    raise RuntimeError(f"reference_radiosity: non-finite output for N = {n}, {dtype}")
                t = time_callable(run, **timing)
            pairs = n * n
            rec = {
                "benchmark": "reference_radiosity",
                "preset": "marble",
                "dtype": str(dtype).removeprefix("torch."),
                "n_sources": n,
                "n_receivers": n,
                "pairs": pairs,
                "median_s": t["median_s"],
                "iqr_s": t["iqr_s"],
                "pairs_per_s": pairs / t["median_s"],
                "repeats": t["repeats"],
            }
            log(f"  {rec['dtype']:7s} N = M = {n:5d}: {rec['median_s']:.4f} s, {rec['pairs_per_s']:.3e} pairs/s")
            records.append(rec)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__.split("\n\n")[0], "profile", RESULTS_DIR,
                              seed_help="seed of the random distances and points")
    args = parser.parse_args(argv)
    setup_benchmark(parser, args)
    cfg = QUICK if args.quick else FULL

    start = time.perf_counter()
    print(f"(a) analytic dipole_rd vs lookup table, {cfg['n_distances']} distances, float32, "
          f"{torch.get_num_threads()} thread(s)")
    records = bench_lut(cfg["n_distances"], cfg["lut_timing"])
    print("(b) reference_radiosity throughput")
    records += bench_reference(cfg["ref_sizes"], cfg["ref_timing"])
    finish_benchmark(args.name, records, args.out_dir, columns=MD_COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
