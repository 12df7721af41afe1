"""Shah image-space splatting benchmark: ``splat_radiosity`` window vs tile vs the all-pairs reference; ONNX Runtime.

Scene: the spot mesh at 30 mm (bounding-box diagonal), seen by a 256 x 256 perspective camera (about 15,000
covered pixels), lit by a point light; the sources are the lit texels of an n x n light view (Shah's n x n splats,
n in {32, 64, 128}: the light camera frames the bounding sphere, so about 28 % of its texels see the cow),
carrying ``E dA`` (:func:`torchsss.geometry.gbuffer.light_view`). Materials: skin1, marble, ketchup, each truncated
at its ``r_max`` (Shah eq. 6.16, eps = 0.01, largest channel): 13.7, 17.7 and 20.6 mm.

(a) ``splat``: time per call (float32, inference mode) of ``method="window"`` (automatic window) and
    ``method="tile"`` (16 x 16 tiles), interleaved with ``bench.compare``, and of
    :func:`torchsss.ops.reference.reference_radiosity` (all pairs of sources and covered pixels, same truncated
    profile). ``err`` = max |method - reference| / max |reference| over the covered pixels.
    ``reach_fraction`` is the fraction of (source, pixel) pairs within ``r_max``: the share of the all-pairs work
    that splatting cannot avoid.
(b) ``onnx``: the window path with a fixed K x K window (K in {31, 63, 127}; what an exported graph needs),
    eager against the ONNX file in onnxruntime (1 thread), skin1, exported once per K with the splat count and
    image size dynamic; combinations with more than 1.2e7 taps (S K^2: the graph is one dense chunk) are skipped.
    ``ort_vs_eager`` = max |ORT - eager| / max |eager|; ``window_err`` = the truncation error of the fixed window
    against the reference (max over covered pixels, relative to the largest reference value).

Usage::

    python benchmarks/bench_splat.py            # full run (~10 min on 2 busy cores), writes results/splat.{json,md}
    python benchmarks/bench_splat.py --quick    # 64 x 64 image, n in {8, 16}, a few seconds
"""

from __future__ import annotations

import functools
import sys
import tempfile
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, compare, finish_benchmark, setup_benchmark, time_callable
from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import camera_gbuffer, light_view
from torchsss.geometry.lights import PointLight
from torchsss.geometry.loading import load_mesh
from torchsss.ops.reference import reference_radiosity
from torchsss.ops.splat import splat_radiosity, splat_window_size
from torchsss.physics import dipole_rd, preset, r_max

RESULTS_DIR = Path(__file__).resolve().parent / "results"

MD_COLUMNS = {
    "splat": [
        "material",
        "r_max_mm",
        "n",
        "sources",
        "pixels",
        "window_k",
        "reach_fraction",
        "window_ms",
        "tile_ms",
        "reference_ms",
        "window_speedup",
        "tile_speedup",
        "window_err",
        "tile_err",
    ],
    "onnx": [
        "material",
        "n",
        "sources",
        "pixels",
        "window",
        "eager_ms",
        "ort_ms",
        "ort_over_eager",
        "ort_vs_eager",
        "window_err",
    ],
}

FULL = {
    "size": 256,
    "ns": (32, 64, 128),
    "materials": ("skin1", "marble", "ketchup"),
    "timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.0},
    "ref_timing": {"repeats": 2, "warmup": 0, "min_time_s": 0.0},
    "onnx_windows": (31, 63, 127),
    "onnx_max_taps": 12_000_000,
}
QUICK = {
    "size": 64,
    "ns": (8, 16),
    "materials": ("skin1", "ketchup"),
    "timing": {"repeats": 2, "warmup": 0, "min_time_s": 0.0},
    "ref_timing": {"repeats": 1, "warmup": 0, "min_time_s": 0.0},
    "onnx_windows": (9, 17),
    "onnx_max_taps": 12_000_000,
}

EPS = 0.01
LIGHT = PointLight((-50.0, 40.0, 30.0), (5000.0, 5000.0, 5000.0))


class Scene:
    """Camera G-buffer of the 30 mm spot and the lit texels of its n x n light views (cached per n)."""

    def __init__(self, size: int) -> None:
        self.mesh = load_mesh("spot", size_mm=30.0)
        self.camera = Camera(eye=(45.0, 12.0, 30.0), target=(0.0, 0.0, 0.0), fov_deg=30.0, width=size, height=size)
        g = camera_gbuffer(self.mesh, self.camera)
        self.dst, self.mask = g.position, g.mask
        self.view_proj = self.camera.view_proj()
        self.pixels = self.dst.flatten(2).transpose(1, 2)[:, self.mask.flatten()]  # (1, M, 3) covered pixels

    def sources(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions (1, S, 3) and flux E dA (1, S, 3) of the lit texels of an n x n light view."""
        lv = light_view(self.mesh, LIGHT, n, 1.3)
        flux = lv.flux.flatten(2).transpose(1, 2)
        lit = flux.sum(-1)[0] > 0
        return lv.position.flatten(2).transpose(1, 2)[:, lit].contiguous(), flux[:, lit].contiguous()


def material(name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    sa, ss, eta = preset(name).tensors(torch.float32)
    return sa, ss, eta, float(r_max(sa, ss, eta, EPS).max())


def reference_image(scene: Scene, pos, flux, sa, ss, eta, rmax) -> torch.Tensor:
    """reference_radiosity at the covered pixels with the profile truncated at r_max: (1, M, C)."""

    def profile(r):
        return torch.where(r <= rmax, dipole_rd(r, sa, ss, eta), torch.zeros((), dtype=r.dtype))

    return reference_radiosity(pos, flux, torch.ones(pos.shape[:2]), scene.pixels, profile)


def reach_fraction(pos: torch.Tensor, pixels: torch.Tensor, rmax: float) -> float:
    inside = 0
    for i in range(0, pixels.shape[1], 4096):
        d = torch.cdist(pixels[0, i : i + 4096], pos[0], compute_mode="donot_use_mm_for_euclid_dist")
        inside += int((d <= rmax).sum())
    return inside / (pixels.shape[1] * pos.shape[1])


def _dipole(sa, ss, eta):
    """The op's profile callable from coefficient tensors (materials as graph inputs in the export wrapper)."""
    return functools.partial(dipole_rd, sigma_a=sa, sigma_s_prime=ss, eta=eta)


def rel_err(image: torch.Tensor, scene: Scene, ref: torch.Tensor) -> float:
    got = image.flatten(2).transpose(1, 2)[:, scene.mask.flatten()]
    return float((got - ref).abs().max() / ref.abs().max())


def bench_splat(scene: Scene, cfg: dict, log=print) -> list[dict]:
    records = []
    for name in cfg["materials"]:
        sa, ss, eta, rmax = material(name)
        for n in cfg["ns"]:
            pos, flux = scene.sources(n)
            args = (pos, flux, scene.dst, scene.mask, scene.view_proj, _dipole(sa, ss, eta), rmax)
            with torch.inference_mode():
                ref = reference_image(scene, pos, flux, sa, ss, eta, rmax)
                errs = {m: rel_err(splat_radiosity(*args, method=m), scene, ref) for m in ("window", "tile")}
                c = compare(
                    lambda args=args: splat_radiosity(*args, method="window"),
                    lambda args=args: splat_radiosity(*args, method="tile"),
                    name=f"splat/{name}/{n}",
                    **cfg["timing"],
                )
                mat = (sa, ss, eta, rmax)
                t_ref = time_callable(
                    lambda pos=pos, flux=flux, mat=mat: reference_image(scene, pos, flux, *mat), **cfg["ref_timing"]
                )
            rec = {
                "benchmark": "splat",
                "material": name,
                "r_max_mm": rmax,
                "n": n,
                "sources": int(pos.shape[1]),
                "pixels": int(scene.pixels.shape[1]),
                "window_k": splat_window_size(pos, scene.view_proj, rmax, *scene.camera.resolution),
                "reach_fraction": reach_fraction(pos, scene.pixels, rmax),
                "window_ms": 1e3 * c["candidate_median_s"],
                "tile_ms": 1e3 * c["baseline_median_s"],
                "reference_ms": 1e3 * t_ref["median_s"],
                "window_speedup": t_ref["median_s"] / c["candidate_median_s"],
                "tile_speedup": t_ref["median_s"] / c["baseline_median_s"],
                "window_err": errs["window"],
                "tile_err": errs["tile"],
                "window_iqr_ms": 1e3 * c["candidate_iqr_s"],
                "tile_iqr_ms": 1e3 * c["baseline_iqr_s"],
                "reference_iqr_ms": 1e3 * t_ref["iqr_s"],
                "repeats": c["repeats"],
                "dtype": "float32",
            }
            log(
                f"  {name:8s} n={n:4d} S={rec['sources']:5d} K={rec['window_k']:4d} reach {rec['reach_fraction']:.2f}: "
                f"window {rec['window_ms']:9.1f} ms, tile {rec['tile_ms']:9.1f} ms, "
                f"reference {rec['reference_ms']:9.1f} ms; err {errs['window']:.1e} / {errs['tile']:.1e}"
            )
            records.append(rec)
    return records


class _SplatWindow(torch.nn.Module):
    """Export wrapper (nn.Modules stay out of torchsss.ops): one material, a fixed window."""

    def __init__(self, window: int) -> None:
        super().__init__()
        self.window = window

    def forward(self, src_pos, src_flux, dst_pos, dst_mask, view_proj, sigma_a, sigma_s_prime, eta, r_max):
        return splat_radiosity(
            src_pos,
            src_flux,
            dst_pos,
            dst_mask,
            view_proj,
            _dipole(sigma_a, sigma_s_prime, eta),
            r_max,
            method="window",
            window=self.window,
        )


def bench_onnx(scene: Scene, cfg: dict, log=print) -> list[dict]:
    try:
        import onnxruntime as ort
    except ImportError:
        log("  onnxruntime missing: skipped")
        return []
    from torch.export import Dim

    from torchsss.export import export_onnx

    sa, ss, eta, rmax = material("skin1")
    rm = torch.tensor([rmax])
    sources = {n: scene.sources(n) for n in cfg["ns"]}
    refs = {n: reference_image(scene, *sources[n], sa, ss, eta, rmax) for n in cfg["ns"]}
    records = []
    for window in cfg["onnx_windows"]:
        module = _SplatWindow(window)
        with tempfile.TemporaryDirectory() as tmp:
            pos0, flux0 = sources[cfg["ns"][0]]
            sd, hd, wd = Dim("S"), Dim("H"), Dim("W")
            dyn = ({1: sd}, {1: sd}, {2: hd, 3: wd}, {2: hd, 3: wd}, None, None, None, None, None)
            # exported at another image size than it runs at
            small = (pos0, flux0, scene.dst[..., :-1, :-1], scene.mask[..., :-1, :-1], scene.view_proj, sa, ss,
                     eta.reshape(1), rm)  # fmt: skip
            t0 = time.perf_counter()
            path = export_onnx(module, small, Path(tmp) / "splat.onnx", dynamic_shapes=dyn)
            log(f"  window {window}: exported in {time.perf_counter() - t0:.1f} s")
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1
            opts.inter_op_num_threads = 1
            sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
            names = [i.name for i in sess.get_inputs()]
            for n in cfg["ns"]:
                pos, flux = sources[n]
                if pos.shape[1] * window * window > cfg["onnx_max_taps"]:
                    continue  # the exported graph is one dense chunk of S * K^2 taps
                args = (pos, flux, scene.dst, scene.mask, scene.view_proj, sa, ss, eta.reshape(1), rm)
                feed = {k: a.numpy() for k, a in zip(names, args)}
                with torch.inference_mode():
                    eager = module(*args)
                    (out,) = sess.run(None, feed)
                    c = compare(
                        lambda feed=feed, sess=sess: sess.run(None, feed),
                        lambda args=args, module=module: module(*args),
                        name=f"onnx/{window}/{n}",
                        **cfg["timing"],
                    )
                rec = {
                    "benchmark": "onnx",
                    "material": "skin1",
                    "n": n,
                    "sources": int(pos.shape[1]),
                    "pixels": int(scene.pixels.shape[1]),
                    "window": window,
                    "eager_ms": 1e3 * c["baseline_median_s"],
                    "ort_ms": 1e3 * c["candidate_median_s"],
                    "ort_over_eager": c["candidate_median_s"] / c["baseline_median_s"],
                    "ort_vs_eager": float((torch.from_numpy(out) - eager).abs().max() / eager.abs().max()),
                    "window_err": rel_err(eager, scene, refs[n]),
                    "eager_iqr_ms": 1e3 * c["baseline_iqr_s"],
                    "ort_iqr_ms": 1e3 * c["candidate_iqr_s"],
                    "repeats": c["repeats"],
                }
                log(
                    f"  K={window:3d} n={n:4d} S={rec['sources']:5d}: eager {rec['eager_ms']:8.1f} ms, ORT "
                    f"{rec['ort_ms']:8.1f} ms (x{rec['ort_over_eager']:.2f}), ORT vs eager {rec['ort_vs_eager']:.1e}, "
                    f"window truncation {rec['window_err']:.1e}"
                )
                records.append(rec)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__.split("\n\n")[0], "splat", RESULTS_DIR, seed_help="unused (the scene is fixed)")
    args = parser.parse_args(argv)
    setup_benchmark(parser, args)
    cfg = QUICK if args.quick else FULL

    start = time.perf_counter()
    scene = Scene(cfg["size"])
    print(
        f"(a) window vs tile vs all-pairs reference, {cfg['size']}^2 image, {int(scene.pixels.shape[1])} covered "
        f"pixels, {torch.get_num_threads()} thread(s)"
    )
    records = bench_splat(scene, cfg)
    print(f"(b) window path, fixed windows {cfg['onnx_windows']}: onnxruntime vs eager")
    records += bench_onnx(scene, cfg)
    finish_benchmark(args.name, records, args.out_dir, columns=MD_COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
