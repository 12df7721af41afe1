"""The planned render of each shared mesh at 256x256 against the reference's own render of the same scene.

For the example scenes of the four shared meshes (spot: the default scene; bunny 69k faces, igea 268k faces,
teapot; ``examples/scenes``), at 256x256: ``render(scene, "auto", tolerance)`` end to end (as ``python -m torchsss
render SCENE --tolerance T``: mesh loading, planning, setup, one frame, files) and ``render(scene, "reference")``
(the reference at its default knobs on the full mesh), the planned image's relative RMSE against the reference's,
and both wall times. Writes ``results/shared_meshes.{json,md}``.

Usage::

    python benchmarks/bench_shared_meshes.py                  # 2% tolerance (about 40 minutes: igea's reference)
    python benchmarks/bench_shared_meshes.py --quick          # spot and teapot at 64x64
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark
from torchsss.cli import render
from torchsss.io import read_exr
from torchsss.plan import MODEL

RESULTS_DIR = Path(__file__).resolve().parent / "results"
SCENES = Path(__file__).resolve().parents[1] / "examples" / "scenes"


def main() -> None:
    parser = benchmark_parser(__doc__.splitlines()[0], "shared_meshes", RESULTS_DIR)
    parser.add_argument("--tolerance", type=float, default=0.02)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--skip-reference", nargs="*", default=[],
                        help="scenes whose reference is not run (its time is then estimated from its pair count)")
    args = parser.parse_args()
    setup_benchmark(parser, args)
    res = 64 if args.quick else args.resolution
    names = ["default", "teapot"] if args.quick else ["default", "teapot", "bunny", "igea"]
    start = time.perf_counter()
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            scene = "default" if name == "default" else str(SCENES / f"{name}.json")
            opts = {"progress": False}
            t0 = time.perf_counter()
            auto = render(scene, "auto", Path(tmp) / f"{name}_auto.exr", options=opts, resolution=(res, res),
                          tolerance=args.tolerance)
            auto_s = time.perf_counter() - t0
            rec = {"scene": name, "resolution": res, "tolerance": args.tolerance, "method": auto["method"],
                   "knobs": str(auto["plan"]["knobs"]), "decimate": auto["plan"]["decimate"],
                   "planned_setup_s": auto["setup_s"], "planned_frame_s": auto["frame_median_s"],
                   "planned_end_to_end_s": auto_s, "predicted_error": auto["plan"]["predicted_error"]}
            if name in args.skip_reference:
                # estimated: the reference's pair count (covered pixels x sources on the full mesh) at the rate
                # measured on the same machine (MODEL["ref_t_pair"], from the calibration trade)
                facts = auto["plan"]["facts"]
                pairs = auto["covered_pixels"] * facts["sources"][0]
                rec.update(reference_end_to_end_s=None, rel_rmse=None, reference_pairs=pairs,
                           reference_estimated_s=pairs * MODEL["ref_t_pair"])
            else:
                t0 = time.perf_counter()
                ref = render(scene, "reference", Path(tmp) / f"{name}_ref.exr", options=opts, resolution=(res, res))
                rec["reference_end_to_end_s"] = time.perf_counter() - t0
                a, b = read_exr(Path(auto["exr"])), read_exr(Path(ref["exr"]))
                both = (a.sum(0) > 0) & (b.sum(0) > 0)
                m = both.expand_as(b)
                rec["rel_rmse"] = float((a - b)[m].square().mean().sqrt() / b[m].square().mean().sqrt())
                rec["speedup"] = rec["reference_end_to_end_s"] / auto_s
                rec["reference_samples"] = ref["stats"].get("samples")
            records.append(rec)
            print(rec, flush=True)
    finish_benchmark(args.name, records, args.out_dir, start=start)


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
