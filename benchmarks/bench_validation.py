"""Cost of the value checks (``torchsss.set_validation``): frame time with validation on and off, every method.

Each method is built once on the default scene (``torchsss.registry.build_scene``) and then renders the scene's
lighting with validation on and off, alternating (on, off, on, off, ...) so that drift on the shared machine hits
both alike; the cost is the ratio of the two medians minus one. The checks are one ``isfinite`` reduction and one
host synchronisation per module input (irradiance atlas, splat sources, receivers), so their cost is expected to
be a small fraction of a frame. A second number isolates it: the time of the checks alone, measured by timing
``check_finite`` on the same inputs the frame checks (the module inputs recorded during one frame), as a
fraction of the median frame.

Usage::

    python benchmarks/bench_validation.py            # 96x96 and 256x256, 7 frames per setting (about 5 minutes)
    python benchmarks/bench_validation.py --quick    # 32x32, 3 frames per setting
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from pathlib import Path

import torch

import torchsss._checks as checks
from torchsss import validation
from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark, time_callable
from torchsss.registry import build_scene
from torchsss.scene import default_scene_path, load_scene

RESULTS_DIR = Path(__file__).resolve().parent / "results"
METHODS = ("splat", "icdf", "hybrid", "lensch", "reference")
COLUMNS = ["resolution", "method", "frame_on_s", "frame_off_s", "ab_cost", "checks_s", "checks_fraction",
           "checked_inputs", "checked_mb", "frames"]


class _Recorder:
    """Wrap ``_report`` (called by every finite check with the input and its bad-entry mask) to record inputs."""

    def __init__(self) -> None:
        self.inputs: list[tuple[torch.Tensor, str]] = []
        self._orig = checks._report

    def __enter__(self):
        def spy(x, bad, name, expected):
            self.inputs.append((x.detach(), name))
            return self._orig(x, bad, name, expected)

        checks._report = spy
        return self

    def __exit__(self, *exc):
        checks._report = self._orig


def main() -> None:
    parser = benchmark_parser(__doc__.splitlines()[0], "validation", RESULTS_DIR)
    parser.add_argument("--frames", type=int, default=7, help="frames per setting (default 7)")
    parser.add_argument("--resolutions", type=int, nargs="+", default=[96, 256])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    args = parser.parse_args()
    setup_benchmark(parser, args)
    if args.quick:
        args.frames, args.resolutions = 3, [32]
    start = time.perf_counter()
    scene0 = load_scene(default_scene_path())
    records = []
    torch.set_grad_enabled(False)
    for res in args.resolutions:
        scene = dataclasses.replace(scene0, camera=dataclasses.replace(scene0.camera, width=res, height=res))
        for method in args.methods:
            renderer = build_scene(scene, method)
            renderer.reuse_lights = False  # every frame relit: its checks run on every frame
            frames = 1 if method == "reference" and not args.quick else args.frames
            renderer.render(scene.lights, scene.camera)  # warm (first-call costs out of the comparison)
            on, off = [], []
            for _ in range(frames):
                for enabled, times in ((True, on), (False, off)):
                    with validation(enabled):
                        t0 = time.perf_counter()
                        renderer.render(scene.lights, scene.camera)
                        times.append(time.perf_counter() - t0)
            with _Recorder() as rec:
                renderer.render(scene.lights, scene.camera)
            inputs = rec.inputs

            def run_checks(inputs=inputs):
                for x, name in inputs:
                    checks._report(x, ~torch.isfinite(x), name, "finite values")

            t_checks = time_callable(run_checks, repeats=5, warmup=1, min_time_s=0.05)["median_s"] if inputs else 0.0
            f_on, f_off = statistics.median(on), statistics.median(off)
            record = {"resolution": res, "method": method, "frame_on_s": f_on, "frame_off_s": f_off,
                      "ab_cost": f_on / f_off - 1.0, "checks_s": t_checks, "checks_fraction": t_checks / f_off,
                      "checked_inputs": len(inputs),
                      "checked_mb": sum(x.numel() * x.element_size() for x, _ in inputs) / 2**20, "frames": frames}
            records.append(record)
            print(f"{res}x{res} {method}: frame {f_on:.3f} s on / {f_off:.3f} s off ({record['ab_cost']:+.1%}); "
                  f"checks alone {t_checks * 1e3:.2f} ms = {record['checks_fraction']:.2%} of a frame "
                  f"({len(inputs)} inputs)", flush=True)
    finish_benchmark(args.name, records, args.out_dir, columns=COLUMNS, start=start)


if __name__ == "__main__":
    main()
