"""Lensch ops benchmarks: spatially varying convolution (local response) and sparse F^T x (global response).

(a) ``sv_conv2d`` against ``sv_conv2d_reference`` (unfold + einsum), interleaved ``compare``, for
    k in {5, 7, 9, 11} at 256^2, 512^2, 1024^2 (C = 3, B = 1, float32, inference mode), and against the
    "memory floor": reading the kernels and the image once (``kernels.sum()`` + ``image.sum()``). Two inference
    paths: the eager banded path (``fast``, ``TORCHSSS_COMPILE=0``) and the compiled fused path (``compiled``,
    ``TORCHSSS_COMPILE=1``; the kernels are the same tensor every frame, so their plane layout is built once,
    and the compile is done before timing: ``compile_s`` is the first call). Also the autograd/export path
    (``image.requires_grad``, forward only) and the max abs differences to the reference.
(b) ``sparse_apply_t`` with ``method="csr"`` and ``method="scatter"`` against scipy.sparse CSR (F^T @ x) on
    the same matrix: N = 10,000 points in a 3-D box, F_ij for pairs closer than a radius chosen for ~2e6
    nonzeros, C = 3, float32, shared values. ``csr`` reuses the CSR matrix built on the first call (same values
    tensor every frame); ``csr_first`` is the call that builds it (fresh values every call).

Usage::

    python benchmarks/bench_lensch_ops.py            # full run, writes benchmarks/results/lensch_ops.{json,md}
    python benchmarks/bench_lensch_ops.py --threads 2 --name lensch_ops_2threads
    python benchmarks/bench_lensch_ops.py --quick    # smoke run with small sizes (a few seconds)
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, compare, finish_benchmark, setup_benchmark, time_callable
from torchsss.ops import sparse_apply_t, sparse_pattern, sv_conv2d, sv_conv2d_reference

RESULTS_DIR = Path(__file__).resolve().parent / "results"

MD_COLUMNS = {
    "sv_conv2d": ["size", "k", "channels", "compiled_ms", "fast_ms", "reference_ms", "compiled_vs_reference",
                  "speedup_vs_reference", "graph_path_ms", "floor_ms", "compiled_over_floor", "fast_over_floor",
                  "compile_s", "max_abs_diff"],
    "sparse_apply_t": ["method", "n", "nnz", "channels", "torch_ms", "scipy_ms", "speedup_vs_scipy",
                       "max_abs_diff"],
}

FULL = {
    "sizes": (256, 512, 1024),
    "ks": (5, 7, 9, 11),
    "conv_timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.1},
    "sparse_n": 10_000,
    "sparse_nnz": 2_000_000,
    "sparse_timing": {"repeats": 7, "warmup": 2, "min_time_s": 0.2},
}
QUICK = {
    "sizes": (32, 64),
    "ks": (5, 7),
    "conv_timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.005},
    "sparse_n": 500,
    "sparse_nnz": 20_000,
    "sparse_timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.005},
}


def _mode(value: str, fn):
    """``fn`` run with ``TORCHSSS_COMPILE=value`` (set on every call: the calls of a comparison interleave)."""
    def run():
        os.environ["TORCHSSS_COMPILE"] = value
        return fn()
    return run


def bench_sv_conv(sizes, ks, timing: dict, log=print) -> list[dict]:
    torch._dynamo.config.recompile_limit = 64  # one graph per (size, k): more than dynamo's default of 8
    records = []
    for size in sizes:
        for k in ks:
            image = torch.rand(1, 3, size, size)
            kernels = torch.rand(size, size, k, k) / (k * k)
            with torch.inference_mode():
                fast = _mode("0", lambda image=image, kernels=kernels: sv_conv2d(image, kernels))
                compiled = _mode("1", lambda image=image, kernels=kernels: sv_conv2d(image, kernels))
                t0 = time.perf_counter()
                out_c = compiled()
                compile_s = time.perf_counter() - t0
                ref = sv_conv2d_reference(image, kernels)
                diff = float((fast() - ref).abs().max())
                diff_c = float((out_c - ref).abs().max())

                def reference(image=image, kernels=kernels):
                    return sv_conv2d_reference(image, kernels)

                def floor(image=image, kernels=kernels):
                    return kernels.sum(), image.sum()

                c = compare(fast, reference, name=f"sv_conv2d/{size}/{k}", **timing)
                cc = compare(compiled, reference, name=f"sv_conv2d_compiled/{size}/{k}", **timing)
                f = compare(fast, floor, name=f"sv_conv2d_floor/{size}/{k}", **timing)
                fc = compare(compiled, floor, name=f"sv_conv2d_compiled_floor/{size}/{k}", **timing)
            img_g = image.clone().requires_grad_()
            g = time_callable(lambda img_g=img_g, kernels=kernels: sv_conv2d(img_g, kernels), **timing)
            rec = {
                "benchmark": "sv_conv2d",
                "size": size,
                "k": k,
                "channels": 3,
                "dtype": "float32",
                "compiled_ms": 1e3 * cc["candidate_median_s"],
                "fast_ms": 1e3 * c["candidate_median_s"],
                "reference_ms": 1e3 * c["baseline_median_s"],
                "compiled_vs_reference": cc["speedup"],
                "speedup_vs_reference": c["speedup"],
                "graph_path_ms": 1e3 * g["median_s"],
                "floor_ms": 1e3 * f["baseline_median_s"],
                "compiled_over_floor": fc["candidate_median_s"] / fc["baseline_median_s"],
                "fast_over_floor": f["candidate_median_s"] / f["baseline_median_s"],
                "compile_s": compile_s,
                "max_abs_diff": max(diff, diff_c),
                "compiled_iqr_ms": 1e3 * cc["candidate_iqr_s"],
                "fast_iqr_ms": 1e3 * c["candidate_iqr_s"],
                "reference_iqr_ms": 1e3 * c["baseline_iqr_s"],
                "compiled_reference_ms": 1e3 * cc["baseline_median_s"],
                "compiled_floor_ms": 1e3 * fc["baseline_median_s"],
                "repeats": c["repeats"],
            }
            log(f"  {size:5d}^2 k={k:2d}: compiled {rec['compiled_ms']:7.2f} ms ({rec['compiled_vs_reference']:.1f}x "
                f"vs reference, x{rec['compiled_over_floor']:.1f} floor, compile {compile_s:.1f} s), fast "
                f"{rec['fast_ms']:8.2f} ms, reference {rec['reference_ms']:8.2f} ms "
                f"({rec['speedup_vs_reference']:.2f}x), graph path {rec['graph_path_ms']:8.2f} ms, floor "
                f"{rec['floor_ms']:6.2f} ms (x{rec['fast_over_floor']:.1f}), max abs diff {rec['max_abs_diff']:.1e}")
            records.append(rec)
    os.environ["TORCHSSS_COMPILE"] = "0"
    return records


def _point_cloud_pattern(n: int, nnz_target: int, seed: int = 0):
    """Points uniform in the unit cube; pairs (i, j) with |p_i - p_j| < r, r chosen for about nnz_target pairs."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 3, generator=g, dtype=torch.float64)
    # expected pairs ~ n^2 * (4/3 pi r^3) (ignoring the boundary): solve for r, then enlarge a little
    r = (nnz_target / (n * n) / (4.0 / 3.0 * math.pi)) ** (1.0 / 3.0) * 1.08
    rows, cols, dists = [], [], []
    for i0 in range(0, n, 1000):
        d = torch.cdist(pts[i0:i0 + 1000], pts)
        ii, jj = torch.nonzero(d < r, as_tuple=True)
        rows.append(ii + i0)
        cols.append(jj)
        dists.append(d[ii, jj])
    rows, cols, dist = torch.cat(rows), torch.cat(cols), torch.cat(dists)
    values = torch.exp(-dist / (0.3 * r)).float()  # a decaying profile stand-in
    return rows, cols, values, r


def bench_sparse(n: int, nnz_target: int, timing: dict, log=print) -> list[dict]:
    import numpy as np
    import scipy.sparse as sp

    rows, cols, values, radius = _point_cloud_pattern(n, nnz_target)
    nnz = int(rows.numel())
    pat = sparse_pattern(rows, cols, n, n)
    x = torch.rand(n, 3)
    ft = sp.csr_matrix((values.numpy(), (cols.numpy(), rows.numpy())), shape=(n, n))  # F^T
    xn = x.numpy()
    want = torch.from_numpy(np.asarray(ft @ xn))
    log(f"  point cloud: N = {n}, radius {radius:.4f}, nnz = {nnz}")
    records = []
    for method in ("csr", "csr_first", "scatter"):
        with torch.inference_mode():
            m = method.split("_")[0]
            if method == "csr_first":  # fresh values every call: the CSR matrix is built every call
                def candidate(m=m):
                    return sparse_apply_t(x, pat, values.clone(), method=m)
            else:
                def candidate(m=m):
                    return sparse_apply_t(x, pat, values, method=m)
            diff = float((candidate() - want).abs().max())
            c = compare(candidate, lambda: ft @ xn, name=f"sparse_apply_t/{method}", **timing)
        rec = {
            "benchmark": "sparse_apply_t",
            "method": method,
            "n": n,
            "nnz": nnz,
            "channels": 3,
            "dtype": "float32",
            "torch_ms": 1e3 * c["candidate_median_s"],
            "scipy_ms": 1e3 * c["baseline_median_s"],
            "speedup_vs_scipy": c["speedup"],
            "max_abs_diff": diff,
            "torch_iqr_ms": 1e3 * c["candidate_iqr_s"],
            "scipy_iqr_ms": 1e3 * c["baseline_iqr_s"],
            "repeats": c["repeats"],
        }
        log(f"  {method:9s}: torch {rec['torch_ms']:7.2f} ms, scipy {rec['scipy_ms']:7.2f} ms "
            f"({rec['speedup_vs_scipy']:.2f}x), max abs diff {diff:.1e}")
        records.append(rec)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__.split("\n\n")[0], "lensch_ops", RESULTS_DIR,
                              seed_help="seed of the random images and kernels")
    args = parser.parse_args(argv)
    setup_benchmark(parser, args)
    cfg = QUICK if args.quick else FULL

    start = time.perf_counter()
    print(f"(a) sv_conv2d vs unfold + einsum reference and the memory floor, {torch.get_num_threads()} thread(s)")
    records = bench_sv_conv(cfg["sizes"], cfg["ks"], cfg["conv_timing"])
    print("(b) sparse_apply_t vs scipy.sparse CSR")
    records += bench_sparse(cfg["sparse_n"], cfg["sparse_nnz"], cfg["sparse_timing"])
    finish_benchmark(args.name, records, args.out_dir, columns=MD_COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
