"""Texture-space importance sampling benchmark: sum-pyramid descent vs searchsorted vs torch.multinomial vs ORT.

For a 512^2 and a 1024^2 map and N in {1e4, 1e5, 1e6} samples (B = 1, float32, inference mode), each sampler
draws N points from the same map with the same uniforms and is timed against ``torch.multinomial`` (with
replacement, the flattened map as weights) in an interleaved ``compare``:

* ``descent``: ``icdf_sample`` in eager mode, the whole per-frame cost (validation, split tables, descent);
* ``reference``: ``icdf_sample_reference`` (float64 row-major ``cumsum`` + ``torch.searchsorted``);
* ``onnxruntime``: ``icdf_sample`` exported with the dynamo exporter (opset 18, pyramid depth frozen at
  log2(size), ``N`` dynamic) and run in an onnxruntime CPU session created once, with the same thread count.

``multinomial`` only returns texel indices; the samplers also return continuous positions and the density ``p``.
``*_x`` columns are time ratios to the multinomial run timed alongside (< 1: faster than multinomial).
``tables_ms`` is the descent with N = 1 (the per-frame cost of the split tables); ``ort_max_abs_diff`` the largest
difference between onnxruntime's and eager's outputs on the timed inputs.

The map imitates an irradiance atlas: a smooth lit lobe, a dark side and 30% of the texels empty (gutters).

Usage::

    python benchmarks/bench_icdf.py            # full run, writes benchmarks/results/icdf.{json,md}
    python benchmarks/bench_icdf.py --quick    # smoke run with small sizes, no ONNX export (a few seconds)
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, compare, finish_benchmark, setup_benchmark, time_callable
from torchsss.ops.icdf import icdf_sample, icdf_sample_reference, pyramid_levels

RESULTS_DIR = Path(__file__).resolve().parent / "results"

MD_COLUMNS = [
    "size",
    "n",
    "descent_ms",
    "reference_ms",
    "multinomial_ms",
    "onnxruntime_ms",
    "descent_x",
    "reference_x",
    "onnxruntime_x",
    "tables_ms",
    "ort_max_abs_diff",
]

FULL = {
    "sizes": (512, 1024),
    "ns": (10_000, 100_000, 1_000_000),
    "timing": {"repeats": 7, "warmup": 1, "min_time_s": 0.2},
    "onnx": True,
}
QUICK = {
    "sizes": (64,),
    "ns": (1_000, 10_000),
    "timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.005},
    "onnx": False,
}


def atlas_like_pdf(size: int, seed: int) -> torch.Tensor:
    """A (1, 1, size, size) float32 map: lit lobe + dark side + 30% empty texels in blocks of 8x8."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0.0, 1.0, size, dtype=torch.float64)
    yy, xx = torch.meshgrid(t, t, indexing="ij")
    lobe = torch.clamp(torch.cos(math.pi * (xx - 0.3)) * torch.cos(math.pi * (yy - 0.4)), min=0.0) ** 2
    pdf = lobe + 1e-3 * torch.rand(size, size, generator=g, dtype=torch.float64)
    blocks = torch.rand((size + 7) // 8, (size + 7) // 8, generator=g) < 0.3
    empty = blocks.repeat_interleave(8, 0).repeat_interleave(8, 1)[:size, :size]
    return pdf.masked_fill(empty, 0.0).float()[None, None]


class _Sampler(torch.nn.Module):
    """Export wrapper (ops/ holds no nn.Modules); the pyramid depth is frozen into the graph."""

    def __init__(self, levels: int):
        super().__init__()
        self.levels = levels

    def forward(self, pdf, u):
        return icdf_sample(pdf, u, levels=self.levels)


def ort_session(size: int, threads: int, directory: Path):
    """Export the descent for maps up to ``size``^2 (N dynamic) and open an onnxruntime session, or None."""
    try:
        import onnxruntime as ort

        from torchsss.export import export_onnx
    except ImportError:
        return None
    from torch.export import Dim

    levels = pyramid_levels(size, size)
    path = export_onnx(
        _Sampler(levels),
        (torch.rand(1, 1, size, size), torch.rand(1, 64, 2)),
        directory / f"icdf_{size}.onnx",
        dynamic_shapes=(None, {1: Dim("N")}),
    )
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(threads, 0)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


def bench(sizes, ns, timing: dict, use_onnx: bool, threads: int, seed: int, log=print) -> list[dict]:
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in sizes:
            pdf = atlas_like_pdf(size, seed)
            weights = pdf.flatten()
            session = ort_session(size, threads, Path(tmp)) if use_onnx else None
            with torch.inference_mode():
                tables = time_callable(lambda pdf=pdf: icdf_sample(pdf, torch.full((1, 1, 2), 0.5)), **timing)
            for n in ns:
                u = torch.rand(1, n, 2)
                methods = {
                    "descent": lambda pdf=pdf, u=u: icdf_sample(pdf, u),
                    "reference": lambda pdf=pdf, u=u: icdf_sample_reference(pdf, u),
                }
                rec = {"benchmark": "icdf", "size": size, "n": n, "dtype": "float32"}
                if session is not None:
                    feed = {"pdf": pdf.numpy(), "u": u.numpy()}
                    methods["onnxruntime"] = lambda session=session, feed=feed: session.run(None, feed)
                    with torch.inference_mode():
                        eager = icdf_sample(pdf, u)
                    ort_out = session.run(None, feed)
                    rec["ort_max_abs_diff"] = max(
                        float(abs(torch.from_numpy(o) - e).max()) for o, e in zip(ort_out, eager)
                    )

                def multinomial(weights=weights, n=n):
                    return torch.multinomial(weights, n, replacement=True)

                baselines = []
                with torch.inference_mode():
                    for name, fn in methods.items():
                        c = compare(fn, multinomial, name=f"{name}/{size}/{n}", **timing)
                        rec[f"{name}_ms"] = 1e3 * c["candidate_median_s"]
                        rec[f"{name}_x"] = 1.0 / c["speedup"]  # time ratio to multinomial
                        rec[f"{name}_iqr_ms"] = 1e3 * c["candidate_iqr_s"]
                        baselines.append(c["baseline_median_s"])
                rec["multinomial_ms"] = 1e3 * statistics.median(baselines)
                rec["tables_ms"] = 1e3 * tables["median_s"]
                rec["repeats"] = timing["repeats"]
                ort_text = (
                    f", ORT {rec['onnxruntime_ms']:8.2f} ms (x{rec['onnxruntime_x']:.2f})"
                    if "onnxruntime_ms" in rec
                    else ""
                )
                log(
                    f"  {size:5d}^2 N={n:8d}: descent {rec['descent_ms']:8.2f} ms (x{rec['descent_x']:.2f}), "
                    f"reference {rec['reference_ms']:8.2f} ms (x{rec['reference_x']:.2f}), multinomial "
                    f"{rec['multinomial_ms']:8.2f} ms{ort_text}"
                )
                records.append(rec)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__.split("\n\n")[0], "icdf", RESULTS_DIR, seed_help="seed of the map and uniforms")
    parser.add_argument(
        "--onnx",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="time onnxruntime too (default: yes for the full run, no with --quick)",
    )
    args = parser.parse_args(argv)
    setup_benchmark(parser, args)
    cfg = QUICK if args.quick else FULL
    use_onnx = cfg["onnx"] if args.onnx is None else args.onnx

    start = time.perf_counter()
    print(f"icdf samplers vs torch.multinomial, {torch.get_num_threads()} thread(s)")
    records = bench(cfg["sizes"], cfg["ns"], cfg["timing"], use_onnx, args.threads, args.seed)
    finish_benchmark(args.name, records, args.out_dir, columns=MD_COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
