"""Rasterizer benchmarks: frames per second of ``rasterize`` on real meshes, where the time goes, and variants.

(a) ``rasterize``: the Stanford bunny (69,451 faces) and spot (5,856 faces), each centred and scaled to a 100 mm
    bounding-box diagonal, seen from 250 mm with a 40 degree vertical field of view, float32, at 256^2, 512^2
    and 1024^2, with 1 and 2 torch threads: median and IQR of the time per frame, frames per second, covered
    pixels, the number of (face, pixel) candidates tested and of size buckets. Each configuration is first
    called until its time per call is steady (``settle``); the first call's time and the settling time are
    recorded too.
(b) ``stages`` (bunny, 1 thread): the same frame split into per-face setup and bucketing, candidate passes
    (edge functions, depth, ``scatter_reduce_``), winner extraction, barycentric recomputation and the rest
    (validation, output tensors), each timed on its own.
(c) ``variants`` (bunny, 1 thread): interleaved comparisons against the default call: float64 inputs (edge
    functions in float64), back-face culling, a small ``max_candidates`` (many chunks), a batch of 4 views
    (against 4 separate calls) and the cost of ``interpolate`` for 3 channels.

Usage::

    python benchmarks/bench_raster.py            # full run, writes benchmarks/results/raster.{json,md}
    python benchmarks/bench_raster.py --quick    # smoke run (small images, an icosphere if the meshes are missing)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchsss.bench import compare, finish_benchmark, time_callable
from torchsss.geometry import raster as R
from torchsss.geometry.camera import Camera, transform_points

RESULTS_DIR = Path(__file__).resolve().parent / "results"
MESH_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"
MESHES = {"bunny": "stanford-bunny.obj", "spot": "spot.obj"}
SIZE_MM = 100.0
DISTANCE_MM = 250.0
EYE_DIR = (0.3, 0.2, 1.0)
CDT = torch.float32  # internal dtype of the float32 rasterizer

MD_COLUMNS = {
    "rasterize": ["mesh", "faces", "resolution", "threads", "median_ms", "iqr_ms", "fps", "covered_px",
                  "candidates", "buckets", "first_call_ms", "settle_s"],
    "stages": ["mesh", "resolution", "threads", "setup_ms", "passes_ms", "winners_ms", "resolve_ms", "other_ms",
               "total_ms"],
    "variants": ["mesh", "resolution", "variant", "default_ms", "variant_ms", "ratio", "note"],
}

FULL = {
    "sizes": (256, 512, 1024),
    "threads": (1, 2),
    "timing": {"repeats": 9, "warmup": 2, "min_time_s": 0.3},
    "stage_timing": {"repeats": 7, "warmup": 1, "min_time_s": 0.2},
    "variant_sizes": (512, 1024),
    "settle_s": 30.0,
}
QUICK = {
    "sizes": (64, 128),
    "threads": (1,),
    "timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.005},
    "stage_timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.005},
    "variant_sizes": (128,),
    "settle_s": 1.0,
}


def load_mesh(name: str, mesh_dir: Path, quick: bool) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Vertices (V, 3) float32 in mm (bounding box centred, diagonal SIZE_MM) and faces (F, 3) int64."""
    import trimesh

    path = mesh_dir / MESHES[name] if name in MESHES else None
    if path is not None and path.is_file():
        mesh = trimesh.load(str(path), force="mesh")
    elif quick or name == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=4)
    else:
        return None
    v = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    v = (v - (lo + hi) / 2) * (SIZE_MM / np.linalg.norm(hi - lo))
    return torch.tensor(v, dtype=torch.float32), torch.tensor(np.asarray(mesh.faces), dtype=torch.int64)


def camera(size: int) -> Camera:
    d = np.asarray(EYE_DIR) / np.linalg.norm(EYE_DIR) * DISTANCE_MM
    return Camera(eye=tuple(d.tolist()), target=(0.0, 0.0, 0.0), fov_deg=40.0, width=size, height=size)


def settle(fn, max_s: float = 30.0, min_s: float = 0.5) -> dict:
    """Call ``fn`` until its call time is steady (3 consecutive calls within 1.5x), at most ``max_s`` seconds.

    On the project's VM the first seconds after a process starts using a second thread can cost ~800 ms per
    frame (every call, then never again in that process; see the README), which a fixed warm-up of a few calls
    does not absorb. The first call's time and the settling time are recorded next to the steady timings.
    """
    times = []
    start = time.perf_counter()
    while True:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        elapsed = time.perf_counter() - start
        last = times[-3:]
        if (len(last) == 3 and max(last) < 1.5 * min(last) and elapsed >= min_s) or elapsed >= max_s:
            return {"first_call_ms": 1e3 * times[0], "settle_s": elapsed, "settle_calls": len(times)}


def candidate_stats(clip: torch.Tensor, faces: torch.Tensor, size: int) -> tuple[int, int]:
    """(face, pixel) candidates tested and number of buckets of the default call."""
    setup = R._setup(clip.detach(), faces, size, size, False, torch.float32)
    if setup is None:
        return 0, 0
    _, buckets, _ = setup
    return sum(min(sh, size) * min(sw, size) * n for sh, sw, n in buckets), len(buckets)


def bench_rasterize(meshes: dict, cfg: dict, log=print) -> list[dict]:
    records = []
    for threads in cfg["threads"]:
        torch.set_num_threads(threads)
        for name, (verts, faces) in meshes.items():
            for size in cfg["sizes"]:
                cam = camera(size)
                clip = transform_points(verts, cam.view_proj())

                def run(clip=clip, faces=faces, size=size):
                    return R.rasterize(clip, faces, (size, size))

                with torch.inference_mode():
                    warm = settle(run, max_s=cfg["settle_s"])
                    ras = run()
                    t = time_callable(run, **cfg["timing"])
                    cand, nb = candidate_stats(clip, faces, size)
                rec = {
                    "benchmark": "rasterize", "mesh": name, "faces": int(faces.shape[0]), "resolution": size,
                    "threads": threads, "median_ms": 1e3 * t["median_s"], "iqr_ms": 1e3 * t["iqr_s"],
                    "min_ms": 1e3 * t["min_s"], "fps": 1.0 / t["median_s"], "covered_px": int(ras.mask.sum()),
                    "candidates": cand, "buckets": nb, "repeats": t["repeats"], "loops": t["loops"], **warm,
                }
                log(f"  {name:6s} {size:5d}^2 {threads} thr: {rec['median_ms']:8.2f} ms (IQR {rec['iqr_ms']:.2f}), "
                    f"{rec['fps']:7.1f} fps, {rec['covered_px']} px, {cand} candidates; first call "
                    f"{warm['first_call_ms']:.1f} ms, settled after {warm['settle_s']:.1f} s")
                records.append(rec)
    return records


def bench_stages(verts: torch.Tensor, faces: torch.Tensor, name: str, cfg: dict, log=print) -> list[dict]:
    torch.set_num_threads(1)
    records = []
    for size in cfg["sizes"]:
        cam = camera(size)
        clip = transform_points(verts, cam.view_proj())
        with torch.inference_mode():
            zbuf = R._zbuffer(clip, faces, size, size, False, 2**22, CDT)

            def winners(zbuf=zbuf):
                pix = (zbuf < R._KEY_LIMIT).nonzero().squeeze(1)
                return pix, zbuf.index_select(0, pix) & R._ID_MASK

            pix, fid = winners()
            stages = {
                "setup": lambda clip=clip, size=size: R._setup(clip, faces, size, size, False, CDT),
                "zbuffer": lambda clip=clip, size=size: R._zbuffer(clip, faces, size, size, False, 2**22, CDT),
                "winners": winners,
                "resolve": lambda clip=clip, size=size, pix=pix, fid=fid: R._resolve(clip, faces, pix, fid, size,
                                                                                     size, CDT),
                "total": lambda clip=clip, size=size: R.rasterize(clip, faces, (size, size)),
            }
            ms = {k: 1e3 * time_callable(fn, **cfg["stage_timing"])["median_s"] for k, fn in stages.items()}
        rec = {
            "benchmark": "stages", "mesh": name, "resolution": size, "threads": 1,
            "setup_ms": ms["setup"], "passes_ms": ms["zbuffer"] - ms["setup"], "winners_ms": ms["winners"],
            "resolve_ms": ms["resolve"],
            "other_ms": ms["total"] - ms["zbuffer"] - ms["winners"] - ms["resolve"], "total_ms": ms["total"],
        }
        log(f"  {size:5d}^2: setup {rec['setup_ms']:.2f}, passes {rec['passes_ms']:.2f}, winners "
            f"{rec['winners_ms']:.2f}, resolve {rec['resolve_ms']:.2f}, other {rec['other_ms']:.2f}, total "
            f"{rec['total_ms']:.2f} ms")
        records.append(rec)
    return records


def bench_variants(verts: torch.Tensor, faces: torch.Tensor, name: str, cfg: dict, log=print) -> list[dict]:
    torch.set_num_threads(1)
    records = []
    timing = cfg["stage_timing"]
    for size in cfg["variant_sizes"]:
        res = (size, size)
        cam = camera(size)
        clip = transform_points(verts, cam.view_proj())
        clip64 = clip.double()
        cams = [Camera(eye=tuple((np.asarray(camera(size).eye) @ _rot_y(a)).tolist()), target=(0.0, 0.0, 0.0),
                       fov_deg=40.0, width=size, height=size) for a in (0.0, 90.0, 180.0, 270.0)]
        clip4 = transform_points(verts, torch.stack([c.view_proj() for c in cams]))
        with torch.inference_mode():
            ref = R.rasterize(clip, faces, res)
            n_pix = int(ref.mask.sum())
            diff64 = int((R.rasterize(clip64, faces, res).face_id != ref.face_id).sum())
            culled = int(R.rasterize(clip, faces, res, cull_backfaces=True).mask.sum())
            variants = [
                ("float64 inputs", lambda clip64=clip64, res=res: R.rasterize(clip64, faces, res), 1,
                 f"face ids differ on {diff64} of {n_pix} covered px"),
                ("cull_backfaces=True", lambda clip=clip, res=res: R.rasterize(clip, faces, res, cull_backfaces=True),
                 1, f"{culled} covered px (default {n_pix})"),
                ("max_candidates=2**14", lambda clip=clip, res=res: R.rasterize(clip, faces, res,
                                                                                max_candidates=2**14), 1,
                 "identical output, many chunks"),
                ("batch of 4 views", lambda clip4=clip4, res=res: R.rasterize(clip4, faces, res), 1,
                 "B = 4 cameras around the mesh, against 4 calls"),
                ("+ interpolate 3 channels", lambda clip=clip, res=res: R.interpolate(
                    verts, R.rasterize(clip, faces, res), faces), 1, "rasterize + interpolate(positions)"),
            ]
            for label, fn, per, note in variants:
                if label.startswith("batch"):
                    def baseline(clip4=clip4, res=res):
                        return [R.rasterize(clip4[i], faces, res) for i in range(4)]
                else:
                    def baseline(clip=clip, res=res):
                        return R.rasterize(clip, faces, res)
                rec = compare(fn, baseline, name=label, **timing)
                out = {
                    "benchmark": "variants", "mesh": name, "resolution": size, "variant": label,
                    "default_ms": 1e3 * rec["baseline_median_s"], "variant_ms": 1e3 * rec["candidate_median_s"] / per,
                    "ratio": rec["candidate_median_s"] / per / rec["baseline_median_s"], "note": note,
                    "variant_iqr_ms": 1e3 * rec["candidate_iqr_s"] / per, "default_iqr_ms": 1e3 * rec["baseline_iqr_s"],
                }
                log(f"  {size:5d}^2 {label:28s}: {out['variant_ms']:8.2f} ms vs {out['default_ms']:8.2f} ms "
                    f"(x{out['ratio']:.2f}); {note}")
                records.append(out)
    return records


def _rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small images for a smoke run")
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR, help=f"output folder (default {RESULTS_DIR})")
    parser.add_argument("--name", default="raster", help="file stem of the results (default 'raster')")
    parser.add_argument("--mesh-dir", type=Path, default=MESH_DIR, help=f"folder of the meshes (default {MESH_DIR})")
    parser.add_argument("--threads", type=int, nargs="+", default=None,
                        help="thread counts of the (a) runs (default: 1 2; --quick: 1)")
    args = parser.parse_args(argv)
    cfg = dict(QUICK if args.quick else FULL)
    if args.threads is not None:
        if any(t < 1 for t in args.threads):
            parser.error(f"--threads: expected ints >= 1, got {args.threads}")
        cfg["threads"] = tuple(args.threads)

    start = time.perf_counter()
    meshes = {}
    for name in ("bunny", "spot"):
        loaded = load_mesh(name, args.mesh_dir, args.quick)
        if loaded is None:
            print(f"warning: {name} not found in {args.mesh_dir}, skipped", file=sys.stderr)
        else:
            meshes[name] = loaded
    if not meshes:
        meshes["sphere"] = load_mesh("sphere", args.mesh_dir, True)
    main_name = next(iter(meshes))
    print(f"(a) rasterize, float32, threads {cfg['threads']}")
    records = bench_rasterize(meshes, cfg)
    print(f"(b) stages of one {main_name} frame, 1 thread")
    records += bench_stages(*meshes[main_name], main_name, cfg)
    print(f"(c) variants against the default call, {main_name}, 1 thread")
    records += bench_variants(*meshes[main_name], main_name, cfg)
    finish_benchmark(args.name, records, args.out_dir, columns=MD_COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
