"""Frames: every method's setup and frame time on the shared meshes at 256x256, and each hot op against its floor.

Part (a), scenes: the example scenes of the four shared meshes (spot: the packaged default scene; teapot, bunny
69k faces, igea 268k faces: ``examples/scenes``) at ``--resolution`` (256). For each, in one run:

* the reference at its default knobs (the truth, ``eps`` 0.01, full mesh): setup, the first frame (cold: in a
  fresh process it includes the one-time compile of the fused integrator, :mod:`torchsss.ops.fused`), a second
  frame with the lights moved (warm), its pair count and pairs per second;
* splat, icdf, hybrid and Lensch at the knobs the planner picks for that method alone at ``--tolerance`` (3%;
  ``plan(scene, tolerance, frames, methods=[method])``; when no configuration of the method is predicted within
  the tolerance, its candidate with the smallest predicted error): setup (mesh loading and decimation included),
  the cold first frame, the median of ``--frames`` - 1 warm frames over a light orbit, the relative RMSE and max
  error of the first frame against the reference's first frame over the pixels both cover, the peak resident
  memory the build and frames added, and the warm frame's speed-up over the reference's warm frame; then
  ``--camera-frames`` frames with the camera orbiting under the scene's lights (``camera_frame_s``: the median of
  all but the first, which relights; a frame whose camera alone moved reuses what depends on the lights,
  ``Renderer.reuse_lights``) and their speed-up over the reference's warm frame (the reference keeps nothing).

Part (b), ops (``--ops``), each at 1 and 2 threads in the same process (CPU): the reference integrator's pairs
per second, eager chain against the fused kernel (M = 4096 receivers x N = 16384 sources, marble, float32);
``sv_conv2d`` 7x7 at 512^2 (C = 3) against its memory floor (reading kernels and image once) and against
``unfold`` + ``einsum``; ``sparse_apply_t`` against scipy's CSR product on the same matrix (10k points, ~2M
nonzeros); ``icdf_sample`` against ``torch.multinomial`` (one million draws from a 512^2 map; multinomial draws
texels only, icdf_sample also places each point in its texel and returns its pdf).

``--device cuda`` runs part (a) on the GPU (timings synchronised) and writes ``frames_cuda.{json,md}``; the CPU
run's Markdown includes the CUDA rows when that file exists, so both land in one table.

Usage::

    python benchmarks/bench_frames.py                       # CPU, scenes and ops (17-45 minutes on 2 cores)
    python benchmarks/bench_frames.py --quick               # default scene at 64x64 and small ops (a minute)
    python benchmarks/bench_frames.py --device cuda --skip-ops --name frames_cuda
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import torch

from torchsss import DipoleMaterial
from torchsss.bench import compare, environment, environment_line, finish_benchmark, markdown_table, time_callable
from torchsss.ops.fused import dipole_pair_sum
from torchsss.ops.icdf import icdf_sample
from torchsss.ops.reference import reference_radiosity
from torchsss.pipelines.build import build
from torchsss.plan import plan_method
from torchsss.registry import orbit_lights
from torchsss.scene import Scene, load_scene
from torchsss.trade import PeakMemory, image_error

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_lensch_ops import bench_sparse, bench_sv_conv

RESULTS_DIR = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]
SCENES = {"default": ROOT / "torchsss" / "data" / "scenes" / "default.json",
          "teapot": ROOT / "examples" / "scenes" / "teapot.json",
          "bunny": ROOT / "examples" / "scenes" / "bunny.json",
          "igea": ROOT / "examples" / "scenes" / "igea.json"}
METHODS = ("splat", "icdf", "hybrid", "lensch")

MD_COLUMNS = {
    "scene": ["device", "scene", "faces", "method", "knobs", "decimate", "setup_s", "cold_frame_s", "frame_s",
              "speedup_vs_reference", "camera_frame_s", "camera_speedup", "rel_rmse", "max_error", "peak_mib",
              "note"],
    "reference_pairs": ["device", "threads", "m", "n", "eager_mpairs_s", "fused_mpairs_s", "speedup",
                        "max_rel_diff"],
    "sv_conv2d": ["device", "threads", "size", "k", "fast_ms", "compiled_ms", "reference_ms", "speedup_vs_reference",
                  "compiled_vs_reference", "floor_ms", "fast_over_floor", "compiled_over_floor", "compile_s",
                  "max_abs_diff"],
    "sparse_apply_t": ["device", "threads", "method", "n", "nnz", "torch_ms", "scipy_ms", "speedup_vs_scipy",
                       "max_abs_diff"],
    "icdf_sample": ["device", "threads", "size", "draws", "icdf_ms", "multinomial_ms", "speedup_vs_multinomial"],
}


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _synced(fn, device: str):
    out = fn()
    _sync(device)
    return out


def _timed(fn, device: str):
    _sync(device)
    t0 = time.perf_counter()
    out = fn()
    _sync(device)
    return out, time.perf_counter() - t0


def _planned(scene: Scene, method: str, tolerance: float, frames: int) -> tuple[dict, int | None, str]:
    """The planner's knobs and decimation for ``method`` alone (what ``render --method M`` uses by default)."""
    return plan_method(scene, method, tolerance, frames)


def orbit_camera(camera, frame: int, frames: int, centre) -> object:
    """The camera of frame ``frame`` of ``frames``: eye and target turned by 2 pi frame / frames about its up axis.

    The axis runs through ``centre``; a camera orbit under fixed lights.
    """
    axis = torch.tensor(camera.up, dtype=torch.float64)
    axis = axis / axis.norm()
    a = 2.0 * math.pi * frame / frames
    c = torch.tensor(centre, dtype=torch.float64)

    def turn(p):
        v = torch.tensor(p, dtype=torch.float64) - c  # Rodrigues' rotation about the axis through the centre
        v = v * math.cos(a) + torch.linalg.cross(axis, v) * math.sin(a) + axis * (axis @ v) * (1.0 - math.cos(a))
        return tuple(float(x) for x in v + c)

    return dataclasses.replace(camera, eye=turn(camera.eye), target=turn(camera.target))


def _frames(renderer, scene: Scene, frames: int, device: str, camera_frames: int = 0) -> tuple:
    """The first frame (cold), ``frames`` - 1 light-orbit frames (warm), ``camera_frames`` camera-orbit frames.

    Returns (first, cold_s, warm median, camera median); the camera orbit runs under the scene's own lights.

    The camera orbit's first frame relights (the lights changed back from the light orbit's); the median is over
    the others, whose camera alone moved (a renderer keeps what depends on the lights alone, ``reuse_lights``).
    """
    mesh = renderer.mesh
    centre = tuple(float(v) for v in (mesh.vertices.amax(0) + mesh.vertices.amin(0)) / 2)
    first, cold = _timed(lambda: renderer.render(list(scene.lights), scene.camera), device)
    warm = []
    for i in range(1, frames):
        lights = orbit_lights(scene.lights, i, frames, centre=centre, axis=scene.camera.up)
        _, t = _timed(lambda lights=lights: renderer.render(lights, scene.camera), device)
        warm.append(t)
    moved = []
    for i in range(1, camera_frames + 1):
        cam = orbit_camera(scene.camera, i, 4 * max(camera_frames, 1), centre)
        _, t = _timed(lambda cam=cam: renderer.render(list(scene.lights), cam), device)
        moved.append(t)
    camera = statistics.median(moved[1:]) if len(moved) > 1 else None
    return first, cold, statistics.median(warm) if warm else cold, camera


def bench_scene(name: str, path: Path | Scene, args, log=print) -> list[dict]:
    """One scene (a file or a :class:`Scene`): the reference, then each method at its planned knobs."""
    device = args.device
    scene = path if isinstance(path, Scene) else load_scene(path)
    res = 64 if args.quick else args.resolution
    scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=res, height=res))
    records = []

    def load(decimate):
        s = scene if decimate is None else dataclasses.replace(scene, decimate=int(decimate))
        return s.load_mesh().with_device(device)

    # the reference: the truth and the baseline of every speed-up
    gc.collect()
    with PeakMemory() as pm:
        t0 = time.perf_counter()
        mesh = load(None)
        ref_r = build("reference", mesh, scene.material)
        setup = time.perf_counter() - t0
        ref, cold, warm, _ = _frames(ref_r, scene, 2 if args.reference_frames > 1 else 1, device)
    faces = mesh.num_faces
    pairs = ref.stats["pairs"]
    rec = {"benchmark": "scene", "device": device, "scene": name, "faces": faces, "resolution": res,
           "method": "reference", "knobs": "eps 0.01 (truth)", "decimate": None, "setup_s": setup,
           "cold_frame_s": cold, "frame_s": warm, "speedup_vs_reference": 1.0, "rel_rmse": 0.0, "max_error": 0.0,
           "peak_mib": pm.peak_mib, "pairs": pairs, "mpairs_per_s": pairs / warm / 1e6,
           "t_integrate_s": ref.stats.get("t_integrate_s"), "covered_pixels": int(ref.mask.sum()),
           "note": f"{pairs / 1e6:.0f} Mpairs, {pairs / warm / 1e6:.0f} Mpairs/s warm"}
    log(f"  {name} reference: setup {setup:.1f} s, cold {cold:.2f} s, warm {warm:.2f} s ({rec['note']})")
    records.append(rec)
    ref_frame = warm
    del ref_r
    for method in METHODS if args.methods is None else args.methods:
        try:
            knobs, decimate, note = _planned(scene, method, args.tolerance, args.frames)
        except ValueError as err:
            records.append({"benchmark": "scene", "device": device, "scene": name, "faces": faces,
                            "method": method, "note": f"not planned: {err}"})
            continue
        gc.collect()
        try:
            with PeakMemory() as pm:
                t0 = time.perf_counter()
                mesh = load(decimate)
                r = build(method, mesh, scene.material, **knobs)
                _sync(device)
                setup = time.perf_counter() - t0
                out, cold, warm, camera = _frames(r, scene, args.frames, device, args.camera_frames)
        except (ValueError, RuntimeError) as err:
            records.append({"benchmark": "scene", "device": device, "scene": name, "faces": faces,
                            "method": method, "knobs": json.dumps(knobs), "decimate": decimate,
                            "note": f"failed: {type(err).__name__}: {str(err)[:160]}"})
            log(f"  {name} {method}: FAILED {type(err).__name__}: {err}")
            continue
        err = image_error(out, ref)
        if out.stats.get("local_term"):  # the hybrid's local term: over the surface, or the atlas fallback (why)
            note = f"{note}; local term: {out.stats['local_term'][:60]}"
        rec = {"benchmark": "scene", "device": device, "scene": name, "faces": faces, "resolution": res,
               "method": method, "knobs": json.dumps(knobs, sort_keys=True), "decimate": decimate,
               "setup_s": setup, "cold_frame_s": cold, "frame_s": warm,
               "speedup_vs_reference": ref_frame / warm if warm > 0 else math.inf,
               "camera_frame_s": camera, "camera_speedup": None if not camera else ref_frame / camera, **err,
               "peak_mib": pm.peak_mib, "frames": args.frames, "note": note}
        log(f"  {name} {method} {knobs} dec {decimate}: setup {setup:.1f} s, cold {cold:.3f} s, warm {warm:.3f} s "
            f"({rec['speedup_vs_reference']:.0f}x the reference), rel RMSE {err['rel_rmse']:.2%}, "
            f"peak {pm.peak_mib:.0f} MiB")
        records.append(rec)
        del r, out
    return records


def bench_reference_pairs(threads: int | None, m: int, n: int, log=print, device: str = "cpu") -> dict:
    g = torch.Generator().manual_seed(0)
    dst, src = torch.rand(1, m, 3, generator=g) * 30, torch.rand(1, n, 3, generator=g) * 30
    e, area = torch.rand(1, n, 3, generator=g), torch.full((1, n), 0.05)
    dst, src, e, area = (t.to(device) for t in (dst, src, e, area))
    mat = DipoleMaterial.from_preset("marble", device=device)
    mat.requires_grad_(False)
    coeffs = tuple(t.detach() for t in mat.dipole_coefficients())

    old = os.environ.get("TORCHSSS_COMPILE")
    try:
        os.environ["TORCHSSS_COMPILE"] = "0"
        with torch.inference_mode():
            eager = reference_radiosity(src, e, area, dst, mat)
            t_eager = time_callable(lambda: _synced(lambda: reference_radiosity(src, e, area, dst, mat), device),
                                    repeats=3, warmup=0, min_time_s=0.0)["median_s"]
        os.environ["TORCHSSS_COMPILE"] = "1"
        w = e * area[..., None]
        with torch.inference_mode():
            fused = dipole_pair_sum(dst, src, w, *coeffs)
            t_fused = time_callable(lambda: _synced(lambda: dipole_pair_sum(dst, src, w, *coeffs), device),
                                    repeats=5, warmup=1, min_time_s=0.2)["median_s"]
    finally:
        if old is None:
            os.environ.pop("TORCHSSS_COMPILE", None)
        else:
            os.environ["TORCHSSS_COMPILE"] = old
    rec = {"benchmark": "reference_pairs", "device": device, "threads": threads, "m": m, "n": n,
           "eager_mpairs_s": m * n / t_eager / 1e6, "fused_mpairs_s": m * n / t_fused / 1e6,
           "speedup": t_eager / t_fused, "max_rel_diff": float((fused - eager).abs().max() / eager.abs().max())}
    log(f"  reference pairs, {threads} thread(s): eager {rec['eager_mpairs_s']:.1f} Mpairs/s, fused "
        f"{rec['fused_mpairs_s']:.1f} Mpairs/s ({rec['speedup']:.1f}x), max rel diff {rec['max_rel_diff']:.1e}")
    return rec


def bench_icdf(threads: int, size: int, draws: int, log=print) -> dict:
    g = torch.Generator().manual_seed(1)
    pdf = torch.rand(1, 1, size, size, generator=g) ** 4
    u = torch.rand(1, draws, 2, generator=g)
    flat = pdf.flatten()
    with torch.inference_mode():
        c = compare(lambda: icdf_sample(pdf, u), lambda: torch.multinomial(flat, draws, replacement=True),
                    name="icdf_sample", repeats=5, warmup=1, min_time_s=0.2)
    rec = {"benchmark": "icdf_sample", "device": "cpu", "threads": threads, "size": size, "draws": draws,
           "icdf_ms": 1e3 * c["candidate_median_s"], "multinomial_ms": 1e3 * c["baseline_median_s"],
           "speedup_vs_multinomial": c["speedup"]}
    log(f"  icdf_sample {size}^2, {draws} draws, {threads} thread(s): {rec['icdf_ms']:.1f} ms, multinomial "
        f"{rec['multinomial_ms']:.1f} ms ({rec['speedup_vs_multinomial']:.2f}x)")
    return rec


def bench_ops(args, log=print) -> list[dict]:
    records = []
    quick = args.quick
    for threads in (1, 2):
        torch.set_num_threads(threads)
        log(f"(b) ops at {threads} thread(s)")
        records.append(bench_reference_pairs(threads, 512 if quick else 4096, 2048 if quick else 16384, log))
        timing = {"repeats": 3, "warmup": 1, "min_time_s": 0.005 if quick else 0.2}
        for rec in bench_sv_conv((64,) if quick else (512,), (7,), timing, log=log):
            records.append({**rec, "device": "cpu", "threads": threads})
        sparse_timing = {"repeats": 3 if quick else 7, "warmup": 1, "min_time_s": 0.005 if quick else 0.2}
        for rec in bench_sparse(500 if quick else 10_000, 20_000 if quick else 2_000_000, sparse_timing, log=log):
            records.append({**rec, "device": "cpu", "threads": threads})
        records.append(bench_icdf(threads, 64 if quick else 512, 10_000 if quick else 1_000_000, log))
    return records


def make_parser() -> argparse.ArgumentParser:
    """The command line's options (also the defaults of :func:`bench_scene`'s ``args`` for other benchmarks)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the default scene at 64x64 and small ops")
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--name", default=None, help="file stem (default frames, or frames_cuda on CUDA)")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--threads", type=int, default=2, help="torch threads for part (a) (default 2)")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--tolerance", type=float, default=0.03)
    parser.add_argument("--frames", type=int, default=4, help="frames per method: 1 cold + the warm orbit")
    parser.add_argument("--reference-frames", type=int, default=2, help="1: the cold frame only (big meshes)")
    parser.add_argument("--camera-frames", type=int, default=3,
                        help="frames per method with the camera orbiting under the scene's lights (0: none)")
    parser.add_argument("--scenes", nargs="*", default=None, choices=sorted(SCENES))
    parser.add_argument("--methods", nargs="*", default=None, choices=METHODS)
    parser.add_argument("--skip-ops", action="store_true")
    parser.add_argument("--ops-only", action="store_true")
    parser.add_argument("--merge", action="append", default=[], type=Path,
                        help="results JSON of another run (e.g. frames_cuda.json) whose rows join the Markdown")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error("--frames: expected >= 2 (one cold frame and at least one warm frame)")
    name = args.name or ("frames_cuda" if args.device == "cuda" else "frames")
    torch.manual_seed(0)
    start = time.perf_counter()
    records: list[dict] = []
    if not args.ops_only:
        torch.set_num_threads(args.threads)
        names = ["default"] if args.quick else (args.scenes or list(SCENES))
        print(f"(a) scenes on {args.device}, {torch.get_num_threads()} thread(s), tolerance {args.tolerance:.0%}")
        for scene in names:
            records += bench_scene(scene, SCENES[scene], args)
            # written after every scene, so that a run cut short keeps what it measured
            (args.out_dir / f"{name}.partial.json").parent.mkdir(parents=True, exist_ok=True)
            (args.out_dir / f"{name}.partial.json").write_text(json.dumps(records, indent=1, default=str))
    if not args.skip_ops and args.device == "cpu":
        records += bench_ops(args)
    elif not args.skip_ops:
        print("(b) the reference integrator on CUDA")
        records.append(bench_reference_pairs(None, 16384, 65536, device=args.device))
    merged = []
    for path in args.merge:
        merged += json.loads(path.read_text()).get("records", [])
    columns = {k: v for k, v in MD_COLUMNS.items() if any(r.get("benchmark") == k for r in records + merged)}
    finish_benchmark(name, records + merged, args.out_dir, columns=columns, start=start)
    print(markdown_table([r for r in records if r.get("benchmark") == "scene"], MD_COLUMNS["scene"]))
    print(environment_line(environment()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
