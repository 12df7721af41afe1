"""The planned render of each shared mesh at 256x256 against the reference's own render of the same scene.

For the example scenes of the four shared meshes (spot: the default scene; bunny 69k faces, igea 268k faces,
teapot; ``examples/scenes``), at 256x256: ``render(scene, "auto", tolerance)`` end to end (as ``python -m torchsss
render SCENE --tolerance T``: mesh loading, planning, setup, one frame, files) and ``render(scene, "reference")``
(the reference at its default knobs on the full mesh), the planned image's relative RMSE against the reference's,
and both wall times. Each render is its own ``python -m torchsss render`` process with an empty inductor cache
directory (``TORCHINDUCTOR_CACHE_DIR``), so both pay what a user's first run pays: imports, mesh loading, planning,
the fused kernel's cold compile, setup, one frame and the files. Writes ``results/shared_meshes.{json,md}``.

Usage::

    python benchmarks/bench_shared_meshes.py                  # 2% tolerance (about 6 minutes: igea's reference)
    python benchmarks/bench_shared_meshes.py --quick          # spot and teapot at 64x64
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark
from torchsss.io import read_exr
from torchsss.plan import MODEL

RESULTS_DIR = Path(__file__).resolve().parent / "results"
SCENES = Path(__file__).resolve().parents[1] / "examples" / "scenes"


def _cli(scene: str, out: Path, res: int, threads: int, *extra: str) -> tuple[dict, float]:
    """Run ``python -m torchsss render`` in a fresh process (cold inductor cache); (its JSON, wall seconds)."""
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": tempfile.mkdtemp(prefix="inductor_"),
           "OMP_NUM_THREADS": str(threads)}
    cmd = [sys.executable, "-m", "torchsss", "render", scene, "--out", str(out), "--resolution", f"{res}x{res}",
           "--no-progress", *extra]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    shutil.rmtree(env["TORCHINDUCTOR_CACHE_DIR"], ignore_errors=True)
    return json.loads(out.with_suffix(".json").read_text()), wall


def main() -> None:
    parser = benchmark_parser(__doc__.splitlines()[0], "shared_meshes", RESULTS_DIR)
    parser.add_argument("--tolerance", type=float, default=0.02)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--skip-reference", nargs="*", default=[],
                        help="scenes whose reference is not run (its time is then estimated from its pair count)")
    args = parser.parse_args()
    setup_benchmark(parser, args)
    threads = torch.get_num_threads()
    res = 64 if args.quick else args.resolution
    names = ["default", "teapot"] if args.quick else ["default", "teapot", "bunny", "igea"]
    start = time.perf_counter()
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            scene = "default" if name == "default" else str(SCENES / f"{name}.json")
            auto, auto_s = _cli(scene, Path(tmp) / f"{name}_auto.exr", res, threads, "--tolerance",
                                str(args.tolerance))
            plan = auto["plan"]
            rec = {"scene": name, "resolution": res, "tolerance": args.tolerance, "method": auto["method"],
                   "knobs": str(plan["knobs"]), "decimate": plan["decimate"],
                   "planned_setup_s": auto["setup_s"], "planned_frame_s": auto["frame_median_s"],
                   "planned_end_to_end_s": auto_s, "predicted_error": plan["predicted_error"]}
            if name in args.skip_reference:
                # estimated: the reference's pair count (covered pixels x sources on the full mesh) at the fused
                # kernel's rate measured on the same machine (MODEL["fused_t_pair"])
                pairs = auto["covered_pixels"] * plan["facts"]["sources"][0]
                rec.update(reference_end_to_end_s=None, rel_rmse=None, reference_pairs=pairs,
                           reference_estimated_s=pairs * MODEL["fused_t_pair"])
            else:
                ref, ref_s = _cli(scene, Path(tmp) / f"{name}_ref.exr", res, threads, "--method", "reference")
                rec["reference_end_to_end_s"] = ref_s
                rec["reference_setup_s"], rec["reference_frame_s"] = ref["setup_s"], ref["frame_median_s"]
                a, b = read_exr(Path(auto["exr"])), read_exr(Path(ref["exr"]))
                both = (a.sum(0) > 0) & (b.sum(0) > 0)
                m = both.expand_as(b)
                rec["rel_rmse"] = float((a - b)[m].square().mean().sqrt() / b[m].square().mean().sqrt())
                rec["speedup"] = ref_s / auto_s
                rec["reference_samples"] = ref["stats"].get("samples")
            records.append(rec)
            print(rec, flush=True)
    finish_benchmark(args.name, records, args.out_dir, start=start)


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
