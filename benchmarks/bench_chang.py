"""Chang et al. 2008 benchmark: error against N, unbiasedness, and the hybrid against pure importance sampling.

The ground truth is :func:`~torchsss.pipelines.reference.render_reference` with ``shadows="shadowmap"``, rendered
once per scene, so that both sides use the same visibility. Relative RMSE =
``sqrt(mean((L - L_ref)^2)) / sqrt(mean(L_ref^2))`` over the pixels (and channels) covered in both images.

(a) ``error_vs_n`` (Chang Tables 2-3): relative RMSE of ``render_icdf`` for N in {49, 100, 169, 256, 400, 900,
    1600, 2500}, mean and standard deviation over a few seeds (scrambled Sobol, one scramble per seed), on

    * ``spot40``: the default scene (spot, 40 mm, skin1, back-lit) at 64 x 64;
    * ``igea10``: the Igea head decimated to ~10k faces at 10 mm (bounding-box diagonal) in skin1, lights and
      camera of ``examples/scenes/igea.json`` scaled from 30 mm to 10 mm, at 96 x 96 (the head covers ~1/6 of
      the frame).

    Per N: the module time (``ImportanceSampledTranslucency.forward`` only, median over the seeds), the whole
    frame (``render_icdf(prebuilt=...)``: irradiance atlas with shadow maps, sampling, camera image; one call) and
    the precompute (atlas + module). ``rel_rmse_quadrature`` is the error of the estimator's *expectation* (the
    atlas quadrature over every chart texel, :func:`~torchsss.ops.reference.reference_radiosity`): the floor
    that no N goes below. The ``fit`` records hold the log-log slope of the mean error against N (expected
    ~ -0.5 while the noise dominates) and the slope of the noise part ``sqrt(err^2 - floor^2)``.
(b) ``unbiased``: the mean image over 32 seeds at N = 256 against the reference and against the quadrature: its
    relative RMSE (expected ~ 1/sqrt(32) of the single-seed error, or the quadrature floor), and the fraction of
    pixel values (pixel x channel) and of pixels (all channels) with ``|mean - target|`` within 3 standard errors
    of the mean (the per-value sample standard deviation over the seeds / sqrt(32)); against the quadrature an
    unbiased estimator gives ~ 0.99.
(c) ``hybrid`` (Chang Fig. 13): the same object at 10, 20 and 30 mm, pure importance sampling against the hybrid
    (``HybridTranslucency``, L = 4 rings x C = 8 + 1 local points) with its importance bound ``c`` at the
    default 0.01, at 0.03 and at 0.1, at equal N (256 and 1024), 2 seeds. Objects: the Igea head (~10k faces,
    size = bounding-box diagonal, 96 x 96) and a sphere (diameter = size, 64 x 64), lights and camera of
    ``examples/scenes/igea.json`` scaled by size / 30 mm. ``rel_rmse_expected`` is the error of the method's
    expectation (hybrid: local filter + global quadrature): the bias floor. ``local_mass_captured``: the local
    filter of a constant irradiance over its total weight, mean over the receivers (< 1: pattern points past a
    chart's gutter read 0). ``t_frame_ms`` here is the
    irradiance-atlas time of that scene (measured once) plus the module time.

All runs use atlas 256 (texel ~0.2 mm on the 40 mm spot; the quadrature floor shows where that stops being
sufficient), float32, Sobol uniforms, shadow maps of 1024^2.

Usage::

    python benchmarks/bench_chang.py                           # full run (~14 min on 2 loaded cores), results/chang.*
    python benchmarks/bench_chang.py --quick --out-dir /tmp/b  # spot 32x32, N in {49, 256}, one seed, < 60 s
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import time
from pathlib import Path

import torch

from torchsss.bench import write_results
from torchsss.geometry.atlas import build_atlas
from torchsss.geometry.atlas_frame import camera_uv, irradiance_atlas
from torchsss.geometry.gbuffer import camera_gbuffer
from torchsss.geometry.loading import load_mesh
from torchsss.geometry.procedural import sphere
from torchsss.modules.chang import HybridTranslucency, ImportanceSampledTranslucency
from torchsss.modules.material import DipoleMaterial
from torchsss.ops.reference import reference_radiosity
from torchsss.physics.fresnel import exit_radiance
from torchsss.pipelines.chang import ChangScene, render_icdf, sample_uniforms
from torchsss.pipelines.reference import render_reference
from torchsss.scene import Material, default_scene_path, load_scene

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"
IGEA = ROOT.parent / "shared" / "data" / "meshes" / "igea.ply"
IGEA_SCENE = ROOT / "examples" / "scenes" / "igea.json"
NS = [49, 100, 169, 256, 400, 900, 1600, 2500]
COLUMNS = {
    "error_vs_n": ["scene", "samples", "seeds", "rel_rmse_mean", "rel_rmse_std", "rel_rmse_quadrature",
                   "t_module_ms", "t_frame_s", "t_irradiance_s", "t_precompute_s", "receivers", "atlas"],
    "fit": ["scene", "slope", "slope_noise", "intercept", "rel_rmse_quadrature", "samples"],
    "unbiased": ["scene", "samples", "seeds", "rel_rmse_single_mean", "rel_rmse_of_mean", "expected_noise_only",
                 "rel_rmse_quadrature", "rel_rmse_of_mean_vs_quadrature", "within_3se_values",
                 "within_3se_pixels", "within_3se_values_vs_quadrature", "within_3se_pixels_vs_quadrature"],
    "hybrid": ["object", "size_mm", "method", "c", "r_p_mm", "local_bound_mm", "samples", "seeds",
               "rel_rmse_mean", "rel_rmse_std", "rel_rmse_expected", "local_mass_captured", "t_module_ms", "t_frame_ms",
               "t_precompute_s"],
}


def rel_rmse(image: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> float:
    """``sqrt(mean((L - L_ref)^2)) / sqrt(mean(L_ref^2))`` over ``mask`` (1, 1, H, W), all channels."""
    m = mask.expand_as(ref)
    d, r = (image - ref)[m].double(), ref[m].double()
    return float((d.square().mean() / r.square().mean()).sqrt())


@dataclasses.dataclass
class Prepared:
    """One scene: mesh, material, lights, camera, atlas, irradiance atlas, camera receivers and the reference."""

    label: str
    mesh: object
    material: Material
    lights: list
    camera: object
    atlas: object
    t_atlas_s: float
    irradiance: torch.Tensor
    t_irradiance_s: float
    mask: torch.Tensor  # (H, W) bool, G-buffer coverage
    receivers: torch.Tensor  # (1, M, 3)
    receivers_uv: torch.Tensor  # (1, M, 2)
    cos_o: torch.Tensor  # (1, 1, H, W)
    ref: object
    t_reference_s: float

    def dipole(self) -> DipoleMaterial:
        """The material as a :class:`DipoleMaterial` in the mesh's dtype."""
        sa, ss, eta = self.material.tensors(dtype=self.mesh.vertices.dtype)
        return DipoleMaterial(sa, ss, eta)

    def image(self, radiosity: torch.Tensor) -> torch.Tensor:
        """Camera radiance (1, 3, H, W) from receiver radiosity (1, M, 3), as ``render_icdf`` assembles it."""
        h, w = self.mask.shape
        b = torch.zeros(h, w, radiosity.shape[-1], dtype=radiosity.dtype)
        b[self.mask] = radiosity[0]
        b = b.permute(2, 0, 1).unsqueeze(0)
        return exit_radiance(b, self.cos_o, self.material.eta) * self.mask

    def error(self, radiance: torch.Tensor, target: torch.Tensor | None = None) -> float:
        """Relative RMSE of ``radiance`` against ``target`` (default the reference) over the covered pixels."""
        target = self.ref.radiance if target is None else target
        return rel_rmse(radiance, target, self.mask[None, None] & self.ref.mask)


def prepare(label, mesh, material, lights, camera, *, atlas_res, spacing_mm=None) -> Prepared:
    """Reference (shadow-mapped), atlas, irradiance atlas and camera receivers of one scene."""
    mesh = mesh.with_dtype(torch.float32)
    t0 = time.perf_counter()
    ref = render_reference(mesh, material, lights, camera, shadows="shadowmap", spacing_mm=spacing_mm)
    t_ref = time.perf_counter() - t0
    t0 = time.perf_counter()
    atlas = build_atlas(mesh, atlas_res, kernel_size=7)
    t_atlas = time.perf_counter() - t0
    t0 = time.perf_counter()
    e = irradiance_atlas(mesh, atlas, lights, material.eta).to(torch.float32)
    t_irr = time.perf_counter() - t0
    gbuf = camera_gbuffer(mesh, camera)
    mask = gbuf.mask[0, 0]
    receivers = gbuf.position[0].permute(1, 2, 0)[mask].unsqueeze(0)
    uv, _ = camera_uv(mesh, atlas, camera)
    rec_uv = uv[0].permute(1, 2, 0)[mask].unsqueeze(0)
    cos_o = (gbuf.normal * gbuf.view_dir).sum(1, keepdim=True).clamp(0.0, 1.0)
    print(f"[{label}] reference {camera.width}x{camera.height} {t_ref:.1f} s (spacing "
          f"{ref.stats.get('spacing_mm', float('nan')):.3f} mm), atlas {atlas_res} {t_atlas:.1f} s, irradiance "
          f"{t_irr:.2f} s, {int(mask.sum())} receivers", flush=True)
    return Prepared(label, mesh, material, list(lights), camera, atlas, t_atlas, e, t_irr, mask, receivers, rec_uv,
                    cos_o, ref, t_ref)


def run_module(prep: Prepared, module, samples: int, seed: int) -> tuple[torch.Tensor, float]:
    """Camera radiance of one seed and the module time (s)."""
    u = sample_uniforms(samples, seed=seed, dtype=torch.float32)
    t0 = time.perf_counter()
    with torch.no_grad():
        if isinstance(module, HybridTranslucency):
            b = module(prep.irradiance, u, prep.receivers, prep.receivers_uv)
        else:
            b = module(prep.irradiance, u, prep.receivers)
    return prep.image(b), time.perf_counter() - t0


def quadrature(prep: Prepared, module) -> torch.Tensor:
    """Camera radiance of the estimator's expectation.

    That is the atlas quadrature over every chart texel (plus the local filter for the hybrid).
    """
    glob = module.global_term if isinstance(module, HybridTranslucency) else module
    with torch.no_grad():
        ep = glob.weighted_irradiance(prep.irradiance)[0]  # (C, H, W)
        sel = ep.sum(0) > 0
        src_pos = glob.position[0].permute(1, 2, 0)[sel].unsqueeze(0).to(ep.dtype)
        src_e = ep.permute(1, 2, 0)[sel].unsqueeze(0)
        b = reference_radiosity(src_pos, src_e, torch.ones_like(src_e[..., 0]), prep.receivers, glob.material)
        if isinstance(module, HybridTranslucency) and module.bound > 0:
            b = b + module.local(prep.irradiance, prep.receivers_uv)
    return prep.image(b)


def local_mass_captured(prep: Prepared, module: HybridTranslucency) -> float | None:
    """The share of the local filter's weight that reads surface, mean over the receivers.

    The local filter of a constant irradiance (1 on every texel) over its total weight: < 1 where pattern points
    fall past a chart's gutter (they read 0).
    """
    if module.bound <= 0:
        return None
    with torch.no_grad():
        ones = torch.ones_like(prep.irradiance)
        got = module.local(ones, prep.receivers_uv)  # (1, M, C)
        total = module.point_weights().sum(0)  # (C,)
    return float((got / total).mean())


def icdf_module(prep: Prepared) -> tuple[ImportanceSampledTranslucency, float]:
    t0 = time.perf_counter()
    module = ImportanceSampledTranslucency.from_atlas(prep.atlas, prep.dipole())
    return module, prep.t_atlas_s + time.perf_counter() - t0


def hybrid_module(prep: Prepared, c: float) -> tuple[HybridTranslucency, float]:
    t0 = time.perf_counter()
    module = HybridTranslucency.from_atlas(prep.atlas, prep.dipole(), c=c)
    return module, prep.t_atlas_s + time.perf_counter() - t0


def _slope(xs, ys) -> tuple[float, float]:
    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = statistics.fmean(lx), statistics.fmean(ly)
    s = sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)
    return s, my - s * mx


def error_vs_n(prep: Prepared, ns, seeds: int, *, whole_frame: bool = True) -> list[dict]:
    """(a): error (mean, std over seeds) and times against N; a ``fit`` record with the log-log slope."""
    module, t_pre = icdf_module(prep)
    floor = prep.error(quadrature(prep, module))
    print(f"[{prep.label}] quadrature floor (expectation vs reference): {floor:.4f}", flush=True)
    built = ChangScene(prep.mesh, prep.atlas, module, {"t_precompute_s": t_pre})
    records = []
    for n in ns:
        errs, times = [], []
        for seed in range(seeds):
            img, t = run_module(prep, module, n, seed)
            errs.append(prep.error(img))
            times.append(t)
        rec = {"benchmark": "error_vs_n", "scene": prep.label, "samples": n, "seeds": seeds,
               "rel_rmse_mean": statistics.fmean(errs), "rel_rmse_std": statistics.stdev(errs) if seeds > 1 else 0.0,
               "rel_rmse": errs, "rel_rmse_quadrature": floor, "t_module_ms": 1e3 * statistics.median(times),
               "t_precompute_s": t_pre, "t_atlas_s": prep.t_atlas_s, "receivers": int(prep.receivers.shape[1]),
               "atlas": prep.atlas.resolution, "width": prep.camera.width, "height": prep.camera.height,
               "t_reference_s": prep.t_reference_s}
        if whole_frame:
            res = render_icdf(prep.mesh, prep.material, prep.lights, prep.camera, samples=n, seed=0, prebuilt=built)
            rec.update(t_frame_s=res.stats["t_frame_s"], t_irradiance_s=res.stats["t_irradiance_s"],
                       t_frame_module_s=res.stats["t_module_s"])
            # the fast path above reproduces render_icdf (same irradiance, same uniforms)
            img0, _ = run_module(prep, module, n, 0)
            rec["fast_path_max_rel_diff"] = float((res.radiance - img0).abs().max() / res.radiance.abs().max())
        records.append(rec)
        print(f"[{prep.label}] N {n:5d}: rel RMSE {rec['rel_rmse_mean']:.4f} +- {rec['rel_rmse_std']:.4f}  module "
              f"{rec['t_module_ms']:.0f} ms  frame {rec.get('t_frame_s', float('nan')):.2f} s", flush=True)
    means = [r["rel_rmse_mean"] for r in records]
    slope, icpt = _slope(ns, means)
    noise = [(n, math.sqrt(e * e - floor * floor)) for n, e in zip(ns, means) if e > floor]
    slope_noise = _slope(*zip(*noise))[0] if len(noise) >= 2 else None
    records.append({"benchmark": "fit", "scene": prep.label, "slope": slope, "slope_noise": slope_noise,
                    "intercept": icpt, "rel_rmse_quadrature": floor, "samples": f"{ns[0]}-{ns[-1]}"})
    print(f"[{prep.label}] log-log slope {slope:.3f} (noise part {slope_noise})", flush=True)
    return records


def unbiased(prep: Prepared, samples: int = 256, seeds: int = 32) -> dict:
    """(b): the mean image over ``seeds`` seeds against the reference and the quadrature."""
    module, _ = icdf_module(prep)
    quad = quadrature(prep, module)
    imgs = torch.stack([run_module(prep, module, samples, s)[0].double() for s in range(seeds)])
    mean = imgs.mean(0)
    se = imgs.std(0) / math.sqrt(seeds)
    single = [prep.error(img.float()) for img in imgs]
    m = (prep.mask[None, None] & prep.ref.mask).expand_as(mean)

    def within(target):
        ok = ((mean - target.double()).abs() <= 3.0 * se) | ((mean - target.double()).abs() == 0)
        values = float(ok[m].double().mean())
        pixels = float(ok.all(1, keepdim=True)[m[:, :1]].double().mean())
        return values, pixels

    v_ref, p_ref = within(prep.ref.radiance)
    v_q, p_q = within(quad)
    floor = prep.error(quad)
    single_mean = statistics.fmean(single)
    rec = {"benchmark": "unbiased", "scene": prep.label, "samples": samples, "seeds": seeds,
           "rel_rmse_single_mean": single_mean, "rel_rmse_of_mean": prep.error(mean.float()),
           "expected_noise_only": math.sqrt((single_mean ** 2 - floor ** 2) / seeds + floor ** 2)
           if single_mean > floor else floor,
           "rel_rmse_quadrature": floor, "rel_rmse_of_mean_vs_quadrature": prep.error(mean.float(), quad),
           "within_3se_values": v_ref, "within_3se_pixels": p_ref, "within_3se_values_vs_quadrature": v_q,
           "within_3se_pixels_vs_quadrature": p_q}
    print(f"[{prep.label}] unbiasedness: single {single_mean:.4f}, mean of {seeds} {rec['rel_rmse_of_mean']:.4f} "
          f"(expected {rec['expected_noise_only']:.4f}; floor {floor:.4f}); within 3 SE of ref {v_ref:.3f} values / "
          f"{p_ref:.3f} pixels, of the quadrature {v_q:.3f} / {p_q:.3f}", flush=True)
    return rec


def hybrid_vs_pure(prep: Prepared, obj: str, size: float, ns, cs, seeds: int) -> list[dict]:
    """(c): pure importance sampling and the hybrid at each ``c``, at equal N."""
    records = []
    methods = [("icdf", None)] + [("hybrid", c) for c in cs]
    for method, c in methods:
        module, t_pre = icdf_module(prep) if c is None else hybrid_module(prep, c)
        expected = prep.error(quadrature(prep, module))
        captured = local_mass_captured(prep, module) if c is not None else None
        for n in ns:
            errs, times = [], []
            for seed in range(seeds):
                img, t = run_module(prep, module, n, seed)
                errs.append(prep.error(img))
                times.append(t)
            t_mod = statistics.median(times)
            rec = {"benchmark": "hybrid", "object": obj, "size_mm": size, "method": method, "c": c,
                   "r_p_mm": getattr(module, "r_p", None), "local_bound_mm": getattr(module, "bound", None),
                   "samples": n, "seeds": seeds, "rel_rmse_mean": statistics.fmean(errs),
                   "rel_rmse_std": statistics.stdev(errs) if seeds > 1 else 0.0, "rel_rmse": errs,
                   "rel_rmse_expected": expected, "local_mass_captured": captured, "t_module_ms": 1e3 * t_mod,
                   "t_frame_ms": 1e3 * (prep.t_irradiance_s + t_mod), "t_irradiance_ms": 1e3 * prep.t_irradiance_s,
                   "t_precompute_s": t_pre, "receivers": int(prep.receivers.shape[1]),
                   "atlas": prep.atlas.resolution}
            records.append(rec)
            print(f"[{obj}{size:g}] {method:6s} c {c!s:5s} N {n:5d}: rel RMSE {rec['rel_rmse_mean']:.4f} +- "
                  f"{rec['rel_rmse_std']:.4f} (expectation {expected:.4f})  module {rec['t_module_ms']:.0f} ms",
                  flush=True)
    return records


def scaled_igea_setup(size_mm: float):
    """Lights and camera of ``examples/scenes/igea.json`` (30 mm) scaled to ``size_mm``; and its material."""
    scene = load_scene(IGEA_SCENE).rescaled(size_mm)
    lights, camera = list(scene.lights), scene.camera
    return scene.material, lights, camera


def igea_prepared(size_mm: float, res: int, atlas_res: int, faces: int = 10000) -> Prepared:
    material, lights, camera = scaled_igea_setup(size_mm)
    mesh = load_mesh(IGEA, size_mm, decimate_to=faces, warn_open=False)
    camera = dataclasses.replace(camera, width=res, height=res)
    return prepare(f"igea{size_mm:g}", mesh, material, lights, camera, atlas_res=atlas_res)


def sphere_prepared(size_mm: float, res: int, atlas_res: int) -> Prepared:
    material, lights, camera = scaled_igea_setup(size_mm)
    mesh = sphere(0.5 * size_mm, subdivisions=4)
    camera = dataclasses.replace(camera, width=res, height=res)
    return prepare(f"sphere{size_mm:g}", mesh, material, lights, camera, atlas_res=atlas_res)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="spot only, 32x32, N in {49, 256}, one seed, 2 mm reference spacing, one hybrid row")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (0: torch's default)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    ap.add_argument("--atlas", type=int, default=256, help="atlas resolution (default 256)")
    ap.add_argument("--seeds", type=int, default=4, help="seeds per N in (a) (default 4)")
    ap.add_argument("--parts", default="a,b,c", help="comma-separated parts to run (default a,b,c)")
    ap.add_argument("--append", action="store_true",
                    help="merge into the existing results file (re-measured records replace the old ones)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    name = "chang_quick" if args.quick else "chang"
    parts = set(args.parts.split(","))
    key_fields = ("benchmark", "scene", "samples", "object", "size_mm", "method", "c")
    previous: list[dict] = []
    if args.append and (args.out_dir / f"{name}.json").is_file():
        previous = json.loads((args.out_dir / f"{name}.json").read_text())["records"]
    records: list[dict] = []

    def save():
        fresh = {tuple(r.get(k) for k in key_fields) for r in records}
        kept = [r for r in previous if tuple(r.get(k) for k in key_fields) not in fresh]
        write_results(name, kept + records, args.out_dir, columns=COLUMNS)

    t_start = time.perf_counter()
    spot = load_scene(default_scene_path())
    if args.quick:
        cam = dataclasses.replace(spot.camera, width=32, height=32)
        prep = prepare("spot40", spot.load_mesh(), spot.material, spot.lights, cam, atlas_res=args.atlas,
                       spacing_mm=2.0)
        records += error_vs_n(prep, [49, 256], 1)
        records += hybrid_vs_pure(prep, "spot", 40.0, [256], [0.01], 1)
        save()
        print(f"wrote {args.out_dir / name}.json/.md in {time.perf_counter() - t_start:.1f} s", flush=True)
        return 0 if all(math.isfinite(r["rel_rmse_mean"]) for r in records if "rel_rmse_mean" in r) else 1

    preps = []
    if parts & {"a", "b"}:
        preps.append(prepare("spot40", spot.load_mesh(), spot.material, spot.lights,
                             dataclasses.replace(spot.camera, width=64, height=64), atlas_res=args.atlas))
        if IGEA.is_file():
            preps.append(igea_prepared(10.0, 96, args.atlas))
        else:
            print(f"warning: {IGEA} not found, Igea skipped", file=sys.stderr)
    for prep in preps:
        if "a" in parts:
            records += error_vs_n(prep, NS, args.seeds)
            save()
        if "b" in parts:
            records.append(unbiased(prep))
            save()
    if "c" in parts:
        for obj in ("igea", "sphere"):
            if obj == "igea" and not IGEA.is_file():
                continue
            for size in (10.0, 20.0, 30.0):
                prep = igea_prepared(size, 96, args.atlas) if obj == "igea" else sphere_prepared(size, 64, args.atlas)
                records += hybrid_vs_pure(prep, obj, size, [256, 1024], [0.01, 0.03, 0.1], 2)
                save()
    print(f"wrote {args.out_dir / name}.json/.md in {time.perf_counter() - t_start:.1f} s", flush=True)
    return 0 if all(math.isfinite(r["rel_rmse_mean"]) for r in records if "rel_rmse_mean" in r) else 1


if __name__ == "__main__":
    sys.exit(main())
