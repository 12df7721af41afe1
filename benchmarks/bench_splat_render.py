"""Render-level benchmark of Shah's image-space splatting (``render_splat``): cost across materials, accuracy.

Everything here is a whole frame of :func:`~torchsss.pipelines.splat.render_splat` (camera G-buffer, one light
view per light, splatting, ``L = F_t / pi B``), float32, default method (``"auto"``: the window scatter when the
splats outnumber the covered pixels, as here).

(a) ``materials`` (Shah Table 6.2: "fewer, larger splats balance more, smaller ones", so the frame rate stays
    roughly constant across materials): the 12 Jensen presets on the default scene (spot, 40 mm, back-lit, two
    point lights) at 32 x 32 (235 covered pixels), eps = 0.01, the budget grid (``splat_grid``, oversample 2,
    ``max_grid`` 512). 64 x 64 (938 covered pixels) was the plan, but on the shared 2-core machine a splat-pixel
    pair cost ~4 us (apple: 7.3M pairs, 31 s a frame), so spectralon's capped frame (~1.3e8 pairs) alone would
    have taken ~9 min; the pair counts scale with the covered pixels, their ratios hardly change.
    Per preset: ``sigma_t_prime`` (largest channel; it sets the splat spacing ``h_mm``), ``sigma_tr`` (smallest
    channel; it sets ``r_max_mm``), the grid and the grid the budget asks for without the cap
    (``grid_uncapped``), the number of splats (lit light-view texels over both lights), ``pairs`` = the
    (splat, covered camera pixel) pairs within ``r_max`` (world distance, the work splatting cannot skip; the
    machine-independent cost), ``footprint_px`` = pairs / splats (mean footprint in camera pixels),
    ``reach_fraction`` = pairs / (splats x covered pixels), ``t_frame_s`` (median of the timed frames, see
    below), ``t_budget_s`` (the part of a frame spent solving the budget: ``splat_grid`` and ``r_max`` by
    bisection, per frame since nothing is precomputed) and ``ns_per_pair`` (frame minus budget time, per pair).
    Where the grid is capped, ``oversample_eff`` = 2 x grid / grid_uncapped is the
    oversampling actually delivered (< 1 is below the sampling criterion: see (b) for the error that costs).
    The ``materials_summary`` record holds max/min of the time, pairs, splats and footprint over the presets
    (and without the capped ones), and the log-log slopes of pairs and time against the splat count (0 if the
    cost balanced as Shah says, 1 if it grew like the splat count).
(b) ``accuracy`` (Shah Fig. 6.10 undersampling): relative RMSE of the camera radiance against
    :func:`~torchsss.pipelines.reference.render_reference` on the same scene, over the pixels covered in both,
    ``sqrt(mean((L - L_ref)^2)) / sqrt(mean(L_ref^2))``, one reference per scene. Sweeps: ``grid``: oversample
    in {0.25, 0.5, 1, 2} at eps 0.01, i.e. 1/8, 1/4, 1/2 and 1 x the budget grid (``grid_ratio``; 2 x the budget,
    4x the frame cost, is left out for time: the ``render_splat`` docstring has it for the spot, 2.1-2.2 %);
    ``eps``: eps in {0.1, 0.03, 0.01, 0.003} at the budget grid of that eps (eps changes both r_max and the
    splat spacing). Patchiness isolates the high-frequency part of the error: with ``q = lum(L)/lum(L_ref) - 1``
    per pixel (luminance = channel mean) over the covered pixels whose reference luminance is >= 1 % of its
    maximum, ``patchiness`` = RMS of ``q - G*q`` (G: normalised Gaussian of sigma 1.5 px restricted to those
    pixels), ``lowfreq_rms`` = RMS of ``G*q`` (smooth bias: truncation, light-view edges), ``frac_err_gt10`` =
    the fraction of those pixels with ``|q| > 0.1``. Scenes: ``bunny30``: the Stanford bunny decimated to 20k
    faces at 30 mm in marble, back-lit (``examples/scenes/bunny.json`` scaled from 50 mm), at 64 x 64 (739
    covered pixels; at 96 x 96 the reference and every frame cost 2.25x more, too slow for this machine);
    ``spot40``: the default scene (skin1) at 64 x 64. The reference uses ray-traced shadows: ``render_splat``'s
    light view is a first-hit visibility (only the surface the light sees first gets irradiance), i.e. exact
    shadows for a point light up to the light view's resolution, so the ray-traced reference is the like-for-like
    one. Its sample spacing is ``default_spacing`` at eps 0.003 (the smallest eps of the sweep: a predicted
    lattice-sum error <= 0.3 % on a plane), so its own quadrature error stays below the splat errors measured.

Timing: one untimed warm-up frame per process (``render_splat`` keeps no state between calls, so this pays the
one-off costs), then per row up to ``repeats`` (3) timed frames, stopping early once the row has used
``row_budget_s`` (20 s) so that the slowest presets (tens of seconds a frame on the loaded 2-core machine) fit
the run; ``repeats`` in each record says how many were taken and ``t_frame_s`` is their median. But
the machine is shared with other jobs: compare times within one table, and prefer ``pairs``.

Usage::

    python benchmarks/bench_splat_render.py            # full run (~15 min on 2 loaded cores), results/splat_render.*
    python benchmarks/bench_splat_render.py --parts accuracy --append   # one part, merged into the results
    python benchmarks/bench_splat_render.py --rewrite-md                # the Markdown again from the JSON
    python benchmarks/bench_splat_render.py --quick --out-dir /tmp/b   # spot 32 x 32, 3 presets, < 1 min
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import math
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from torchsss.bench import environment, environment_line, format_value, markdown_table, write_results
from torchsss.geometry.gbuffer import camera_gbuffer
from torchsss.geometry.loading import load_mesh
from torchsss.modules.material import DipoleMaterial
from torchsss.modules.splat import SplatTranslucency
from torchsss.physics import splat_spacing
from torchsss.physics.dipole import dipole_terms
from torchsss.physics.materials import preset_names
from torchsss.pipelines.reference import default_spacing, render_reference
from torchsss.pipelines.splat import light_sources, render_splat, splat_grid
from torchsss.scene import Material, default_scene_path, load_scene

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"
BUNNY = ROOT.parent / "shared" / "data" / "meshes" / "stanford-bunny.obj"
BUNNY_SCENE = ROOT / "examples" / "scenes" / "bunny.json"

FULL = {
    "presets": tuple(preset_names()),
    "size": 32,  # (a) image side (64 planned: see the module docstring)
    "max_grid": 512,
    "scenes": {"bunny30": 64, "spot40": 64},  # (b) image side per scene
    "oversample": (0.25, 0.5, 1.0, 2.0),
    "eps": (0.1, 0.03, 0.01, 0.003),
    "ref_eps": 0.003,
    "ref_spacing_mm": None,
    "repeats": 3,
    "row_budget_s": 20.0,
}
QUICK = {
    "presets": ("chicken1", "potato", "skin1"),
    "size": 32,
    "max_grid": 64,  # skin1 asks for 111: exercises the cap
    "scenes": {"spot40": 32},
    "oversample": (0.25, 2.0),
    "eps": (0.1, 0.01),
    "ref_eps": 0.01,
    "ref_spacing_mm": 0.6,
    "repeats": 1,
    "row_budget_s": 5.0,
}
EPS = 0.01
OVERSAMPLE = 2.0  # render_splat's default: the "budget grid"
BLUR_SIGMA_PX = 1.5
LUM_FLOOR = 0.01
CHUNK_PAIRS = 1 << 24

COLUMNS = {
    "materials": ["preset", "sigma_t_prime", "sigma_tr", "r_max_mm", "h_mm", "grid", "grid_uncapped", "capped",
                  "oversample_eff", "splats", "pixels", "pairs", "footprint_px", "reach_fraction", "t_frame_s",
                  "repeats", "t_budget_s", "ns_per_pair"],
    "materials_summary": ["presets", "t_ratio", "t_max_preset", "t_min_preset", "pairs_ratio", "pairs_max_preset",
                          "pairs_min_preset", "t_splat_ratio", "splats_ratio", "footprint_ratio", "t_ratio_uncapped",
                          "pairs_ratio_uncapped", "slope_pairs_vs_splats", "slope_time_vs_splats",
                          "ns_per_pair_ratio", "capped_presets"],
    "reference": ["scene", "material", "width", "height", "pixels", "shadows", "spacing_mm", "samples",
                  "t_reference_s"],
    "accuracy": ["scene", "sweep", "eps", "oversample", "grid", "grid_ratio", "splats", "r_max_mm", "pairs",
                 "rel_rmse", "patchiness", "lowfreq_rms", "frac_err_gt10", "t_frame_s", "repeats"],
}


# -- scenes ---------------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class SceneSetup:
    """One scene: label, mesh, material, lights, camera."""

    label: str
    mesh: object
    material: Material
    lights: list
    camera: object


def spot_scene(size: int) -> SceneSetup:
    """The default scene (spot 40 mm, skin1, back-lit) at ``size`` x ``size``."""
    s = load_scene(default_scene_path())
    cam = dataclasses.replace(s.camera, width=size, height=size)
    return SceneSetup("spot40", s.load_mesh(), s.material, list(s.lights), cam)


def bunny_scene(size: int, faces: int = 20000) -> SceneSetup:
    """``examples/scenes/bunny.json`` (marble, back-lit) scaled from 50 mm to 30 mm, mesh decimated to ``faces``."""
    s = load_scene(BUNNY_SCENE).rescaled(30.0)
    cam = dataclasses.replace(s.camera, width=size, height=size)
    mesh = load_mesh(BUNNY, 30.0, decimate_to=faces, warn_open=False)
    return SceneSetup("bunny30", mesh, s.material, list(s.lights), cam)


# -- measures -------------------------------------------------------------------------------------------------------
def timed_frames(fn, repeats: int, budget_s: float):
    """Up to ``repeats`` calls of ``fn`` (at least one; stop once ``budget_s`` is used): (first result, seconds)."""
    first, times = None, []
    while len(times) < repeats:
        gc.collect()
        gc.disable()
        try:
            t0 = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - t0)
        finally:
            gc.enable()
        if first is None:
            first = out
        if sum(times) >= budget_s:
            break
    return first, times


def budget_seconds(mesh, material: Material, eps: float, max_grid: int, oversample: float) -> float:
    """Seconds of the per-frame budget solve inside ``render_splat``: ``splat_grid`` and the module's ``r_max``."""
    t0 = time.perf_counter()
    splat_grid(mesh, material, eps, max_grid, oversample, min_grid=2)
    SplatTranslucency(DipoleMaterial(*material.tensors(dtype=torch.float32)), eps=eps)
    return time.perf_counter() - t0


def covered_pixels(setup: SceneSetup) -> torch.Tensor:
    """World positions (M, 3) of the pixels that see the object."""
    g = camera_gbuffer(setup.mesh, setup.camera)
    return g.position[0].permute(1, 2, 0)[g.mask[0, 0]]


def reach_pairs(setup: SceneSetup, material: Material, grid: int, radius: float, pixels: torch.Tensor) -> tuple:
    """(splats, pairs within ``radius``) of ``render_splat``'s light views at ``grid`` (same selection)."""
    splats = pairs = 0
    for light in setup.lights:
        src = light_sources(setup.mesh, light, grid, material.eta, 0)[0]  # the renderer's own sources
        splats += int(src.shape[0])
        step = max(1, CHUNK_PAIRS // max(1, pixels.shape[0]))
        for i in range(0, src.shape[0], step):
            d = torch.cdist(src[i:i + step], pixels, compute_mode="donot_use_mm_for_euclid_dist")
            pairs += int((d <= radius).sum())
    return splats, pairs


def rel_rmse(image: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> float:
    """``sqrt(mean((L - L_ref)^2)) / sqrt(mean(L_ref^2))`` over ``mask`` (1, 1, H, W), all channels."""
    m = mask.expand_as(ref)
    d, r = (image - ref)[m].double(), ref[m].double()
    return float((d.square().mean() / r.square().mean()).sqrt())


def _gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian of ``sigma`` px on (1, 1, H, W), zero padding."""
    half = max(1, math.ceil(3.0 * sigma))
    t = torch.arange(-half, half + 1, dtype=x.dtype)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    x = F.conv2d(x, k.view(1, 1, 1, -1), padding=(0, half))
    return F.conv2d(x, k.view(1, 1, -1, 1), padding=(half, 0))


def error_maps(image: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor, sigma: float = BLUR_SIGMA_PX,
               floor: float = LUM_FLOOR) -> dict:
    """Patchiness measures of ``q = lum(image)/lum(ref) - 1`` (module docstring); ``mask`` (1, 1, H, W)."""
    lum, lum_ref = image.double().mean(1, keepdim=True), ref.double().mean(1, keepdim=True)
    m = mask & (lum_ref > floor * lum_ref[mask].max())
    w = m.double()
    q = torch.where(m, lum / lum_ref.clamp_min(1e-300) - 1.0, torch.zeros_like(lum))
    low = _gaussian_blur(q * w, sigma) / _gaussian_blur(w, sigma).clamp_min(1e-12)
    hp = q - low
    return {"patchiness": float(hp[m].square().mean().sqrt()), "lowfreq_rms": float(low[m].square().mean().sqrt()),
            "ratio_rms": float(q[m].square().mean().sqrt()), "frac_err_gt10": float((q[m].abs() > 0.1).double().mean()),
            "error_pixels": int(m.sum())}


def _loglog_slope(xs, ys) -> float | None:
    if len(xs) < 2:
        return None
    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = statistics.fmean(lx), statistics.fmean(ly)
    den = sum((a - mx) ** 2 for a in lx)
    return None if den == 0 else sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / den


# -- (a) materials --------------------------------------------------------------------------------------------------
def bench_materials(setup: SceneSetup, cfg: dict) -> list[dict]:
    pixels = covered_pixels(setup)
    records = []
    for name in cfg["presets"]:
        material = Material.from_json(name)
        sa, ss, eta = material.tensors()
        terms = dipole_terms(sa, ss, eta)
        grid = splat_grid(setup.mesh, material, EPS, cfg["max_grid"], OVERSAMPLE)  # as render_splat builds it
        grid_free = splat_grid(setup.mesh, material, EPS, 1 << 30, OVERSAMPLE)  # the same, uncapped
        res, times = timed_frames(lambda material=material: render_splat(
            setup.mesh, material, setup.lights, setup.camera, eps=EPS, max_grid=cfg["max_grid"]),
            cfg["repeats"], cfg["row_budget_s"])
        assert res.stats["grid"] == grid
        splats, pairs = reach_pairs(setup, material, grid, res.stats["r_max_mm"], pixels)
        assert splats == res.stats["splats"], (splats, res.stats)
        t = statistics.median(times)
        t_budget = min(budget_seconds(setup.mesh, material, EPS, cfg["max_grid"], OVERSAMPLE) for _ in range(2))
        rec = {"benchmark": "materials", "scene": setup.label, "preset": name,
               "sigma_t_prime": float((sa + ss).max()), "sigma_tr": float(terms.sigma_tr.min()),
               "r_max_mm": res.stats["r_max_mm"], "h_mm": float(splat_spacing(sa, ss, eta, EPS).min()),
               "grid": grid, "grid_uncapped": grid_free, "capped": grid < grid_free,
               "oversample_eff": OVERSAMPLE * grid / grid_free, "splats": splats, "pixels": int(pixels.shape[0]),
               "pairs": pairs, "footprint_px": pairs / max(1, splats),
               "reach_fraction": pairs / max(1, splats * pixels.shape[0]), "t_frame_s": t,
               "t_frames_s": times, "repeats": len(times), "t_budget_s": t_budget,
               "t_splat_s": max(t - t_budget, 0.0), "ns_per_pair": 1e9 * max(t - t_budget, 0.0) / max(1, pairs),
               "width": setup.camera.width, "height": setup.camera.height, "eps": EPS, "max_grid": cfg["max_grid"],
               "finite": bool(torch.isfinite(res.radiance).all())}
        records.append(rec)
        print(f"[materials] {name:10s} r_max {rec['r_max_mm']:5.1f} mm  h {rec['h_mm']:.3f} mm  grid {grid:4d}"
              f"{f' (cap; needs {grid_free})' if rec['capped'] else '':16s} splats {splats:7d}  pairs {pairs:11d}"
              f"  footprint {rec['footprint_px']:7.1f} px  {t:7.2f} s x{len(times)}", flush=True)
    return records


def materials_summary(rows: list[dict]) -> dict:
    """Max/min ratios over the preset rows (and over the uncapped ones), and log-log slopes against splats."""
    def ratio(key, rs):
        vals = [r[key] for r in rs]
        return max(vals) / min(vals) if rs and min(vals) > 0 else None

    def arg(key, fn):
        return fn(rows, key=lambda r: r[key])["preset"]

    free = [r for r in rows if not r["capped"]]
    splats = [r["splats"] for r in rows]
    return {"benchmark": "materials_summary", "presets": len(rows),
            "t_ratio": ratio("t_frame_s", rows), "t_max_preset": arg("t_frame_s", max),
            "t_min_preset": arg("t_frame_s", min), "pairs_ratio": ratio("pairs", rows),
            "pairs_max_preset": arg("pairs", max), "pairs_min_preset": arg("pairs", min),
            "splats_ratio": ratio("splats", rows), "footprint_ratio": ratio("footprint_px", rows),
            "t_splat_ratio": ratio("t_splat_s", rows), "t_ratio_uncapped": ratio("t_frame_s", free),
            "pairs_ratio_uncapped": ratio("pairs", free),
            "slope_pairs_vs_splats": _loglog_slope(splats, [r["pairs"] for r in rows]),
            "slope_time_vs_splats": _loglog_slope(splats, [r["t_frame_s"] for r in rows]),
            "slope_footprint_vs_splats": _loglog_slope(splats, [r["footprint_px"] for r in rows]),
            "ns_per_pair_ratio": ratio("ns_per_pair", [r for r in rows if r["ns_per_pair"] > 0]),
            "capped_presets": ", ".join(r["preset"] for r in rows if r["capped"]) or "none"}


# -- (b) accuracy ---------------------------------------------------------------------------------------------------
def bench_accuracy(setup: SceneSetup, cfg: dict) -> list[dict]:
    mat = setup.material
    spacing = cfg["ref_spacing_mm"] or default_spacing(mat, setup.mesh, cfg["ref_eps"])
    t0 = time.perf_counter()
    ref = render_reference(setup.mesh, mat, setup.lights, setup.camera, spacing_mm=spacing, shadows="raytrace")
    t_ref = time.perf_counter() - t0
    records = [{"benchmark": "reference", "scene": setup.label, "material": mat.name, "width": setup.camera.width,
                "height": setup.camera.height, "pixels": int(ref.mask.sum()), "shadows": "raytrace",
                "spacing_mm": spacing, "samples": ref.stats["samples"], "t_reference_s": t_ref}]
    print(f"[{setup.label}] reference {setup.camera.width}x{setup.camera.height}: {t_ref:.1f} s, spacing "
          f"{spacing:.3f} mm, {ref.stats['samples']} samples, {int(ref.mask.sum())} pixels", flush=True)
    pixels = covered_pixels(setup)
    budget = {eps: splat_grid(setup.mesh, mat, eps, 1 << 30, OVERSAMPLE, min_grid=2) for eps in {EPS, *cfg["eps"]}}
    rows = [("grid", EPS, s) for s in cfg["oversample"]] + [("eps", e, OVERSAMPLE) for e in cfg["eps"]]
    done: dict = {}
    for sweep, eps, over in rows:
        grid = splat_grid(setup.mesh, mat, eps, 1 << 30, over, min_grid=2)
        key = (eps, grid)
        if key in done:  # the budget row of the grid sweep is the eps = 0.01 row of the eps sweep
            records.append({**done[key], "sweep": sweep})
            continue
        res, times = timed_frames(lambda eps=eps, grid=grid: render_splat(
            setup.mesh, mat, setup.lights, setup.camera, eps=eps, grid=grid), cfg["repeats"], cfg["row_budget_s"])
        mask = res.mask & ref.mask
        _, pairs = reach_pairs(setup, mat, grid, res.stats["r_max_mm"], pixels)
        rec = {"benchmark": "accuracy", "scene": setup.label, "material": mat.name, "sweep": sweep, "eps": eps,
               "oversample": over, "grid": grid, "grid_ratio": grid / budget[eps], "budget_grid": budget[eps],
               "splats": res.stats["splats"], "r_max_mm": res.stats["r_max_mm"], "pairs": pairs,
               "rel_rmse": rel_rmse(res.radiance, ref.radiance, mask), **error_maps(res.radiance, ref.radiance, mask),
               "t_frame_s": statistics.median(times), "t_frames_s": times, "repeats": len(times),
               "width": setup.camera.width, "height": setup.camera.height}
        done[key] = rec
        records.append(rec)
        print(f"[{setup.label}] {sweep:4s} eps {eps:<5g} oversample {over:<4g} grid {grid:4d} "
              f"({rec['grid_ratio']:.3g}x) splats {rec['splats']:6d}: rel RMSE {rec['rel_rmse']:.4f}"
              f"  patchiness {rec['patchiness']:.4f}"
              f"  low-freq {rec['lowfreq_rms']:.4f}  |err|>10% {rec['frac_err_gt10']:.3f}  {rec['t_frame_s']:.2f} s"
              f" x{len(times)}", flush=True)
    return records


# -- markdown -------------------------------------------------------------------------------------------------------
def _f(v, digits=3) -> str:
    return format_value(round(v, digits) if isinstance(v, float) else v)


def _materials_text(rows: list[dict], summ: dict) -> str:
    fp = sorted(rows, key=lambda r: r["footprint_px"])
    sp = sorted(rows, key=lambda r: r["splats"])
    rm = sorted(r["r_max_mm"] for r in rows)
    capped = [r for r in rows if r["capped"]]
    slope = summ["slope_pairs_vs_splats"]
    verdict = ("does not hold here: the cost grows almost like the splat count" if slope is not None and slope > 0.6
               else "holds only partly here" if slope is not None and slope > 0.25 else "holds here")
    text = (
        f"Shah (Table 6.2) reports 33, 27 and 24 fps (a 1.4x spread) for sigma_t 0.27, 1.47 and 3.27 mm^-1 because "
        f"the splat count and the splat size move in opposite directions. Over {summ['presets']} presets at "
        f"{rows[0]['width']} x {rows[0]['height']} the splat count spans {_f(summ['splats_ratio'], 1)}x "
        f"({sp[0]['preset']} {sp[0]['splats']} to {sp[-1]['preset']} {sp[-1]['splats']}) but the footprint only "
        f"{_f(summ['footprint_ratio'], 2)}x ({fp[0]['footprint_px']:.0f} px for {fp[0]['preset']} to "
        f"{fp[-1]['footprint_px']:.0f} px for {fp[-1]['preset']}, of {rows[0]['pixels']} covered pixels), so the "
        f"splat-pixel pairs, the machine-independent cost, span {_f(summ['pairs_ratio'], 1)}x "
        f"({summ['pairs_min_preset']} to {summ['pairs_max_preset']}; log-log slope against the splat count "
        f"{_f(slope, 2)}, where 0 is Shah's balance and 1 none) and the frame time {_f(summ['t_ratio'], 1)}x "
        f"({summ['t_min_preset']} fastest, {summ['t_max_preset']} slowest; slope "
        f"{_f(summ['slope_time_vs_splats'], 2)}). The claim {verdict}"
        + (", for two reasons" if slope is not None and slope > 0.25 else " (about these presets; in general") +
        f": (1) r_max at eps 0.01 ({rm[0]:.1f}-{rm[-1]:.1f} mm) is comparable to "
        f"the 40 mm object, so most splats reach most of the object and the footprint is clipped by the object, "
        f"not set by r_max, and cannot shrink to compensate; (2) the splat spacing h follows the real-source depth "
        f"1/sigma_t' while r_max follows the diffusion length 1/sigma_tr, so the splats per footprint, "
        f"(r_max/h)^2, differs from material to material instead of staying fixed"
        + ("." if slope is not None and slope > 0.25 else ").") +
        f" Time tracks pairs only roughly: "
        f"the time per pair (frame minus the per-frame budget solve, `t_budget_s`, where the frame took longer) "
        f"varies {_f(summ['ns_per_pair_ratio'], 2)}x over the presets, and the budget solve itself "
        f"({min(r['t_budget_s'] for r in rows):.2f}-{max(r['t_budget_s'] for r in rows):.2f} s: `render_splat` "
        f"builds its module, solving r_max by bisection, every frame; the spacing is cached) dominates the small "
        f"frames; both move with "
        f"the load of the shared machine, so one lucky or unlucky frame moves the time ratio a lot (here the "
        f"fastest frame, {summ['t_min_preset']}, took {min(r['t_frame_s'] for r in rows):.2f} s while frames with "
        f"fewer pairs took {sorted(r['t_frame_s'] for r in rows)[1]:.2f} s or more). The pairs ratio is the "
        f"number to trust."
    )
    if capped:
        names = ", ".join(f"{r['preset']} (needs {r['grid_uncapped']}, effective oversample "
                          f"{r['oversample_eff']:.2f})" for r in capped)
        text += (
            f" The grid hits max_grid {capped[0]['max_grid']} for {names}: the cap bounds the cost (without it "
            f"the splats, and so the pairs, would grow by (grid_uncapped/grid)^2) but puts the splat spacing above "
            f"the sampling criterion, so that frame is undersampled; the accuracy table's rows at a grid_ratio near "
            f"oversample_eff/2 show what that costs in error and patchiness. Without the capped presets the time "
            f"ratio is {_f(summ['t_ratio_uncapped'], 1)}x and the pairs ratio {_f(summ['pairs_ratio_uncapped'], 1)}x."
        )
    return text


def _accuracy_text(rows: list[dict], label: str) -> str:
    grid = sorted([r for r in rows if r["sweep"] == "grid"], key=lambda r: r["grid_ratio"])
    eps = sorted([r for r in rows if r["sweep"] == "eps"], key=lambda r: -r["eps"])
    parts = []
    if grid:
        budget = min(grid, key=lambda r: abs(r["grid_ratio"] - 1.0))
        low = grid[0]
        pieces = ", ".join(f"{r['grid_ratio']:.3g}x ({r['grid']}): {r['rel_rmse']:.3f} / {r['patchiness']:.3f} / "
                           f"{r['frac_err_gt10']:.2f}" for r in grid)
        parts.append(
            f"Grid sweep at eps 0.01 (grid relative to the budget grid {budget['grid']}: rel RMSE / patchiness / "
            f"fraction of pixels off by > 10 %): {pieces}. From the budget grid down to {low['grid_ratio']:.3g}x "
            f"({low['grid']} x {low['grid']} per light) the relative RMSE grows "
            f"{low['rel_rmse'] / budget['rel_rmse']:.1f}x and the patchiness (the high-pass part of the relative "
            f"error) {low['patchiness'] / budget['patchiness']:.1f}x, while the splats drop "
            f"{budget['splats'] / low['splats']:.0f}x and the frame time {budget['t_frame_s'] / low['t_frame_s']:.1f}x."
            + (f" At {low['grid_ratio']:.3g}x the error is mostly patchiness (high-pass {low['patchiness']:.3f} > "
               f"low-pass {low['lowfreq_rms']:.3f}): Fig. 6.10's patchy artifacts."
               if low["patchiness"] > low["lowfreq_rms"] else
               f" At {low['grid_ratio']:.3g}x the high-pass part is {low['patchiness']:.3f} and the low-pass part "
               f"{low['lowfreq_rms']:.3f}.") +
            (f" At the budget grid what is left is mostly smooth (low-pass {budget['lowfreq_rms']:.3f} vs high-pass "
             f"{budget['patchiness']:.3f}): the r_max truncation and the light view's sampling of silhouettes."
             if budget["lowfreq_rms"] > budget["patchiness"] else
             f" At the budget grid the high-pass part is {budget['patchiness']:.3f} and the low-pass part "
             f"{budget['lowfreq_rms']:.3f}."))
        above = [r for r in grid if r["grid_ratio"] > 1.0]
        if above:
            parts.append("Above the budget grid: " + ", ".join(
                f"{r['grid_ratio']:.3g}x: {r['rel_rmse']:.3f}" for r in above) + ".")
    if eps:
        pieces = ", ".join(f"eps {r['eps']:g}: grid {r['grid']}, r_max {r['r_max_mm']:.1f} mm, rel RMSE "
                           f"{r['rel_rmse']:.3f} (low-pass {r['lowfreq_rms']:.3f}, high-pass {r['patchiness']:.3f}), "
                           f"{r['t_frame_s']:.2f} s" for r in eps)
        big = eps[0]
        parts.append(f"Eps sweep, each at its own budget grid: {pieces}." + (
            f" A large eps costs a smooth bias, not patches (eps {big['eps']:g}: low-pass {big['lowfreq_rms']:.3f} > "
            f"high-pass {big['patchiness']:.3f}): the profile truncated at a short r_max drops the light that travels "
            f"far, which is what a back-lit object shows; the splat spacing follows eps too, so the grid stays "
            f"adequate." if big["lowfreq_rms"] > big["patchiness"] else ""))
    return f"**{label}.** " + " ".join(parts)


def write_markdown(name: str, records: list[dict], out_dir: Path, env: dict | None = None) -> Path:
    """Write ``<out_dir>/<name>.md``: the tables and a "what this shows" paragraph for each."""
    env = env or environment()
    lines = [f"# {name}", "",
             "Shah 2007 ch. 6 image-space splatting, whole frames of `render_splat` (float32, method `auto`, "
             f"{env['threads']} thread(s)). See `benchmarks/bench_splat_render.py` for the definitions. Times are "
             "the median of the timed frames (`repeats`, at most 3, fewer where a frame exceeds the row budget) "
             "on a shared machine: compare within this file, and prefer the machine-independent `pairs`.", ""]
    mats = [r for r in records if r["benchmark"] == "materials"]
    summ = [r for r in records if r["benchmark"] == "materials_summary"]
    if mats:
        lines += ["## materials: cost across the 12 Jensen presets (Shah Table 6.2)", "",
                  f"Spot 40 mm, default lights and camera at {mats[0]['width']} x {mats[0]['height']}, eps "
                  f"{mats[0]['eps']}, budget grid (oversample 2), max_grid {mats[0]['max_grid']}.", "",
                  markdown_table(mats, COLUMNS["materials"]), ""]
        if summ:
            lines += [markdown_table(summ, COLUMNS["materials_summary"]), "",
                      "**What this shows.** " + _materials_text(mats, summ[0]), ""]
    refs = [r for r in records if r["benchmark"] == "reference"]
    acc = [r for r in records if r["benchmark"] == "accuracy"]
    if refs:
        lines += ["## reference: the ground truth of the accuracy table", "",
                  "`render_reference` with ray-traced shadows (like-for-like with the light view's first-hit "
                  "visibility), computed once per scene.", "", markdown_table(refs, COLUMNS["reference"]), ""]
    if acc:
        lines += ["## accuracy: error and patchiness against the number of splats and eps (Shah Fig. 6.10)", "",
                  "`grid_ratio` = grid / budget grid of that eps; `patchiness` = RMS of the high-pass "
                  f"(sigma {BLUR_SIGMA_PX} px) relative luminance error, `lowfreq_rms` its smooth part, "
                  "`frac_err_gt10` the fraction of pixels off by more than 10 %.", "",
                  markdown_table(acc, COLUMNS["accuracy"]), "", "**What this shows.**", ""]
        for ref in refs:
            rows = [r for r in acc if r["scene"] == ref["scene"]]
            if rows:
                lines += [_accuracy_text(rows, f"{ref['scene']} ({ref['material']}, {ref['width']} x "
                                               f"{ref['height']})"), ""]
    lines += [environment_line(env), ""]
    path = out_dir / f"{name}.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


# -- main -----------------------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="spot 32x32: presets chicken1/potato/skin1 with max_grid 64, oversample {0.25, 2}, eps "
                         "{0.1, 0.01}, reference spacing 0.6 mm, one frame per row")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (0: torch's default)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    ap.add_argument("--parts", default="materials,accuracy", help="comma-separated: materials, accuracy")
    ap.add_argument("--presets", default=None, help="comma-separated preset names for (a) (default: the config's)")
    ap.add_argument("--scenes", default=None, help="comma-separated scenes for (b): bunny30, spot40")
    ap.add_argument("--rewrite-md", action="store_true",
                    help="only rewrite the Markdown file from the existing JSON results (no measurement)")
    ap.add_argument("--append", action="store_true",
                    help="merge into the existing results file (re-measured records replace the old ones)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    cfg = dict(QUICK if args.quick else FULL)
    if args.presets:
        cfg["presets"] = tuple(p.strip() for p in args.presets.split(","))
        unknown = set(cfg["presets"]) - set(preset_names())
        if unknown:
            ap.error(f"--presets: unknown {sorted(unknown)}; expected among {preset_names()}")
    if args.scenes:
        wanted = [s.strip() for s in args.scenes.split(",")]
        sizes = {**FULL["scenes"], **cfg["scenes"]}
        if set(wanted) - set(sizes):
            ap.error(f"--scenes: expected among {sorted(sizes)}, got {wanted}")
        cfg["scenes"] = {s: sizes[s] for s in wanted}
    parts = set(args.parts.split(","))
    name = "splat_render_quick" if args.quick else "splat_render"
    key_fields = ("benchmark", "scene", "preset", "sweep", "eps", "oversample")
    previous: list[dict] = []
    if args.append and (args.out_dir / f"{name}.json").is_file():
        previous = json.loads((args.out_dir / f"{name}.json").read_text())["records"]
    records: list[dict] = []
    if args.rewrite_md:
        path = args.out_dir / f"{name}.json"
        data = json.loads(path.read_text())
        rows = [r for r in data["records"] if r["benchmark"] == "materials"]
        if rows:  # the summary is a function of the rows: recompute it
            data["records"] = [materials_summary(rows) if r["benchmark"] == "materials_summary" else r
                               for r in data["records"]]
            path.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        print(f"wrote {write_markdown(name, data['records'], args.out_dir, data['environment'])}")
        return 0

    def save():
        fresh = {tuple(r.get(k) for k in key_fields) for r in records}
        kept = [r for r in previous if tuple(r.get(k) for k in key_fields) not in fresh]
        order = list(COLUMNS)
        allrec = sorted(kept + records, key=lambda r: order.index(r["benchmark"]))
        write_results(name, allrec, args.out_dir, columns=COLUMNS)
        write_markdown(name, allrec, args.out_dir)

    t_start = time.perf_counter()
    spot = spot_scene(cfg["size"])
    # one warm-up frame per process: render_splat keeps no state, this pays the one-off costs
    render_splat(spot.mesh, spot.material, spot.lights, spot.camera, grid=16)
    if "materials" in parts:
        print(f"(a) materials: spot 40 mm at {cfg['size']}x{cfg['size']}, {torch.get_num_threads()} thread(s)",
              flush=True)
        rows = bench_materials(spot, cfg)
        records += [*rows, materials_summary(rows)]
        s = records[-1]
        print(f"[materials] time max/min {s['t_ratio']:.1f}x, pairs max/min {s['pairs_ratio']:.1f}x, splats "
              f"{s['splats_ratio']:.1f}x, footprint {s['footprint_ratio']:.2f}x; capped: {s['capped_presets']}",
              flush=True)
        save()
    if "accuracy" in parts:
        for label, size in cfg["scenes"].items():
            if label == "bunny30":
                if not BUNNY.is_file():
                    print(f"warning: {BUNNY} not found, bunny skipped", file=sys.stderr)
                    continue
                setup = bunny_scene(size)
            else:
                setup = spot_scene(size)
            records += bench_accuracy(setup, cfg)
            save()
    print(f"wrote {args.out_dir / name}.json/.md in {time.perf_counter() - t_start:.1f} s", flush=True)
    finite = all(math.isfinite(v) for r in records for k, v in r.items()
                 if k in ("t_frame_s", "rel_rmse", "patchiness", "pairs") and isinstance(v, (int, float)))
    return 0 if finite and all(r.get("finite", True) for r in records) else 1


if __name__ == "__main__":
    sys.exit(main())
