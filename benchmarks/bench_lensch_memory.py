"""Lensch's memory: the peak resident set of the build and of the frames, stage by stage, in fresh processes.

Each configuration runs in its own process (a peak RSS is a process's high-water mark): the default scene
(spot, 40 mm, skin1, back-lit, 128 x 128, one thread) built with ``build_scene(scene, "lensch", ...)``, then three
frames. A thread samples ``VmRSS`` every 2 ms; the stages of the build (``build_lensch``'s atlas, kernel geometry,
throughput, blending) and of the first frame (irradiance atlas, throughput values, the local kernels' planes) are
timed by wrapping them, and each stage's peak is the highest sample within it. ``baseline_mb`` is the process
after ``import torch, torchsss`` (about 350 MB on this machine): the build's own share is peak minus baseline.

Usage::

    python benchmarks/bench_lensch_memory.py                 # atlas 512 (blended, k = 11) and 1024, ~2 min
    python benchmarks/bench_lensch_memory.py --quick         # atlas 256 only
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark

RESULTS_DIR = Path(__file__).resolve().parent / "results"

_CHILD = r"""
import json, sys, threading, time
import torch
torch.set_num_threads(1)
torch.set_grad_enabled(False)
import torchsss.geometry.lensch
import torchsss.modules.lensch as ML
import torchsss.pipelines.lensch as PL
from torchsss.registry import build_scene
from torchsss.scene import default_scene_path, load_scene

def rss():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024.0
    return 0.0

samples, marks, stop = [], [], []
def poll():
    while not stop:
        samples.append((time.perf_counter(), rss()))
        time.sleep(0.002)
threading.Thread(target=poll, daemon=True).start()

def wrap(owner, name, stage):
    fn = getattr(owner, name, None)
    if fn is None:  # an older layout of the code (the script also measures earlier commits)
        return
    def timed(*a, **k):
        t0 = time.perf_counter()
        out = fn(*a, **k)
        marks.append((stage, t0, time.perf_counter()))
        return out
    setattr(owner, name, timed)

for name in ("build_atlas", "local_kernel_geometry", "build_throughput", "build_dense_throughput", "blending_weights",
             "hat_quadrature"):
    wrap(PL, name, name)
wrap(PL, "irradiance_atlas", "frame: irradiance atlas")
wrap(ML.GlobalResponse, "throughput_values", "frame: throughput values")
wrap(ML.LocalResponse, "planes", "frame: local kernel planes")
wrap(ML.LocalResponse, "half_planes", "frame: local kernel planes")
time.sleep(0.05)
baseline = rss()
scene = load_scene(default_scene_path())
res = int(sys.argv[1])
t0 = time.perf_counter()
renderer = build_scene(scene, "lensch", atlas_resolution=res)
renderer.reuse_lights = False  # every frame relit (the same lights would reuse the radiosity atlas)
t1 = time.perf_counter()
after_build = rss()  # what the built renderer holds, before any frame
frames = []
for _ in range(3):
    f0 = time.perf_counter()
    renderer.render(scene.lights, scene.camera)
    frames.append((f0, time.perf_counter()))
time.sleep(0.02)
stop.append(1)
def peak(a, b):
    return max((m for t, m in samples if a <= t <= b), default=0.0)
out = {"atlas_resolution": res, "baseline_mb": baseline, "build_s": t1 - t0, "build_peak_mb": peak(t0, t1),
       "after_build_mb": after_build, "first_frame_s": frames[0][1] - frames[0][0],
       "first_frame_peak_mb": peak(*frames[0]), "frame_s": frames[-1][1] - frames[-1][0],
       "steady_mb": peak(*frames[-1]), "process_peak_mb": max(m for _, m in samples),
       "kernel_size": renderer.knobs["kernel_size"], "blend": renderer.knobs["blend"],
       "stages": [{"stage": s, "seconds": b - a, "peak_mb": peak(a, b)} for s, a, b in marks]}
print("RESULT " + json.dumps(out))
"""


def run_child(resolution: int) -> dict:
    """One configuration in a fresh process; its JSON result."""
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(resolution)], capture_output=True, text=True,
                          check=False)
    line = next((x for x in proc.stdout.splitlines() if x.startswith("RESULT ")), None)
    if line is None:
        raise RuntimeError(f"atlas {resolution}: the child failed:\n{proc.stderr[-2000:]}")
    return json.loads(line[len("RESULT "):])


def main() -> None:
    parser = benchmark_parser(__doc__.splitlines()[0], "lensch_memory", RESULTS_DIR)
    parser.add_argument("--resolutions", type=int, nargs="+", default=None, help="atlas sizes (512 1024)")
    args = parser.parse_args()
    setup_benchmark(parser, args)
    start = time.perf_counter()
    resolutions = args.resolutions or ([256] if args.quick else [512, 1024])
    records = []
    for res in resolutions:
        rec = run_child(res)
        stages = "; ".join(f"{s['stage']} {s['seconds']:.2f} s {s['peak_mb']:.0f} MB" for s in rec.pop("stages"))
        records.append({**rec, "stages": stages})
        print(f"atlas {res}: build {rec['build_s']:.1f} s, peak {rec['build_peak_mb']:.0f} MB "
              f"(baseline {rec['baseline_mb']:.0f}); first frame peak {rec['first_frame_peak_mb']:.0f} MB, "
              f"steady {rec['steady_mb']:.0f} MB", flush=True)
    finish_benchmark(args.name, records, args.out_dir, start=start,
                     columns=["atlas_resolution", "kernel_size", "blend", "baseline_mb", "build_s", "build_peak_mb",
                              "after_build_mb", "first_frame_s", "first_frame_peak_mb", "frame_s", "steady_mb",
                              "process_peak_mb", "stages"])


if __name__ == "__main__":
    main()
