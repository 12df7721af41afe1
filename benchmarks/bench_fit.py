"""Material fitting through the fast method against independent reference targets: parameter error and time.

Issue 18. For 4 presets (potato, skin1, ketchup, skim milk: a weak absorber, an average one, an albedo near 0 in
green and blue, the weakest absorber of the table) and two object sizes (the default scene's spot at 20 mm and at
40 mm, the scene rescaled so that the lights and the camera keep their places relative to the object),
``--views`` orbit views (back-, side- and front-lit) at ``--size`` x ``--size`` pixels are rendered with the
all-pairs reference at the independent target spacing (:func:`fit_material.target_spacing`: a finer quadrature than
the reference at its default spacing, which the correction renders). sigma_a and sigma_s' (per channel; eta held
at the target's) are then fitted from the same initial guess (sigma_a 0.05, sigma_s' 1.0 mm^-1) through splatting
(eps 0.01, oversample 1, window form) by three solvers, exactly as ``examples/fit_material.py`` runs them:

- ``lm``: Levenberg-Marquardt with the reference's defect correction (``fit_lm.py``; the example's default);
- ``lm-raw``: the same without the correction (fits splat's images as they are: its error moves the fit);
- ``adam``: Adam, ``--steps`` steps (lr 0.1, cosine decay), the renderer rebuilt every 10 steps.

Recorded per run: the per-channel relative errors of the fitted coefficients, the loss (relative squared error,
mean over the views) of the *reference* at the fitted material against the targets, the first iteration (and its
wall time) after which every coefficient stays within 10%, the wall and CPU time of the fit, the renders it took.

Writes ``benchmarks/results/fit.{json,md}`` (``--out-dir``, ``--name``), one row per run as soon as it finishes.

Usage::

    python benchmarks/bench_fit.py                  # 24 fits; ~15 min on the 2-core machine when it is quiet
    python benchmarks/bench_fit.py --quick          # 1 preset, 1 size, small images (smoke)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))

from fit_lm import fit_lm  # noqa: E402
from fit_material import (  # noqa: E402
    LogDipoleMaterial,
    _params,
    fit,
    load_fit_scene,
    orbit_cameras,
    relative_errors,
    render_targets,
    target_spacing,
    view_loss,
)

from torchsss.physics.materials import Material  # noqa: E402
from torchsss.pipelines import build  # noqa: E402

PRESETS = ("potato", "skin1", "ketchup", "skimmilk")
SIZES_MM = (20.0, 40.0)
SOLVERS = ("lm", "lm-raw", "adam")
TOL = 0.10


def _max_error(p: dict, target: Material) -> float:
    e = relative_errors(p, target)
    return max(max(e["sigma_a"]), max(e["sigma_s_prime"]))


def run_one(preset: str, size_mm: float, args) -> list[dict]:
    scene = load_fit_scene("default", args.size)
    scene = scene.rescaled(size_mm)
    mesh = scene.load_mesh()
    cameras = orbit_cameras(scene.camera, args.views)
    target = Material.from_json(preset)
    t0 = time.perf_counter()
    targets = render_targets(scene, mesh, target, cameras, spacing_mm=target_spacing(mesh, target))
    t_targets = time.perf_counter() - t0
    lights = list(scene.lights)
    knobs = {"eps": 0.01, "oversample": args.oversample, "splat_method": "window"}
    rows = []
    for solver in args.solvers:
        init = Material.from_json({"sigma_a": [0.05] * 3, "sigma_s_prime": [1.0] * 3, "eta": target.eta})
        material = LogDipoleMaterial.from_material(init)
        material.raw_eta.requires_grad_(False)
        make = lambda: build("splat", mesh, material, differentiable=True, **knobs)  # noqa: E731,B023
        reference_now = lambda: render_targets(scene, mesh, Material.from_json(_params(material)),  # noqa: E731,B023
                                               cameras)
        t0, c0 = time.perf_counter(), time.process_time()
        if solver == "adam":
            res = fit(make(), lights, cameras, targets, steps=args.steps, lr=args.lr, fit_eta=False, progress=False,
                      rebuild=make, rebuild_every=10)
            renders, outer = args.steps * len(cameras), None
        else:
            res = fit_lm(make, lights, cameras, targets, [material.log_sigma_tr, material.log_albedo_ratio],
                         [True, True], correct=reference_now if solver == "lm" else None,
                         record=lambda: _params(material), progress=False)  # noqa: B023
            res["params"] = _params(material)
            renders, outer = res["renders"], len(res["outer"])
        t_fit, cpu_fit = time.perf_counter() - t0, time.process_time() - c0
        with torch.no_grad():
            ref_loss = sum(float(view_loss(a, b)) for a, b in zip(reference_now(), targets)) / len(cameras)
        errs = relative_errors(res["params"], target)
        # the first iteration after which every coefficient stays within TOL
        within = [_max_error(p, target) <= TOL for p in res["trace"]]
        first = next((k for k in range(len(within)) if all(within[k:])), None)
        rows.append({
            "preset": preset, "size_mm": size_mm, "solver": solver, "faces": int(mesh.num_faces), "image": args.size,
            "views": args.views, "iterations": len(res["trace"]), "outer": outer, "renders": renders,
            "steps": args.steps if solver == "adam" else None, "lr": args.lr if solver == "adam" else None,
            "knobs": knobs, "target": {"sigma_a": list(target.sigma_a), "sigma_s_prime": list(target.sigma_s_prime)},
            "fitted": res["params"], "relative_error": errs,
            "max_error_sigma_a": max(errs["sigma_a"]), "max_error_sigma_s_prime": max(errs["sigma_s_prime"]),
            "loss_initial": res["loss"][0], "reference_loss_final": ref_loss,
            "iteration_within_10pct": None if first is None else first + 1,
            "time_to_10pct_s": None if first is None else res["trace"][first]["t_s"],
            "fit_s": t_fit, "fit_cpu_s": cpu_fit, "targets_s": t_targets})
    return rows


def _md(rows: list[dict], env: dict) -> str:
    fmt = lambda xs: " / ".join(f"{100 * x:.1f}%" for x in xs)  # noqa: E731
    r0 = rows[0] if rows else {}
    lines = [
        "# Material fitting through splatting against independent reference targets (`benchmarks/bench_fit.py`)",
        "",
        f"{env['date']}, torch {env['torch']}, {env['threads']} threads, {env['cpus']} CPUs (shared: wall times "
        "depend on the other jobs running; CPU time is this process's).",
        "Default scene (spot) rescaled to the object size; "
        f"{r0.get('views', '-')} orbit views (back-, side-, front-lit) at {r0.get('image', '-')}^2 px; targets by "
        "the all-pairs reference at the independent target spacing (`fit_material.target_spacing`); fit through "
        f"splat {r0.get('knobs', '-')} from sigma_a 0.05, sigma_s' 1.0 mm^-1, eta held. Solvers: `lm` = "
        "Levenberg-Marquardt with the reference's defect correction (the example's default), `lm-raw` = without "
        "the correction, `adam` = Adam (lr 0.1, cosine decay, renderer rebuilt every 10 steps). Errors are "
        "|fitted - target| / target per channel (R / G / B); 'reference loss' is the reference's relative squared "
        "error at the fitted material, mean over the views.",
        "",
        "| preset | size | solver | sigma_a error (R/G/B) | sigma_s' error (R/G/B) | reference loss start -> end | "
        "iterations (renders) | within 10% from (wall) | fit wall / CPU |",
        "|---|---:|---|---|---|---|---|---|---:|",
    ]
    for r in rows:
        reach = "never" if r["iteration_within_10pct"] is None else \
            f"{r['iteration_within_10pct']} ({r['time_to_10pct_s']:.0f} s)"
        lines.append(f"| {r['preset']} | {r['size_mm']:.0f} mm | {r['solver']} | {fmt(r['relative_error']['sigma_a'])}"
                     f" | {fmt(r['relative_error']['sigma_s_prime'])} | {r['loss_initial']:.2e} -> "
                     f"{r['reference_loss_final']:.2e} | {r['iterations']} ({r['renders']}) | {reach} | "
                     f"{r['fit_s']:.0f} s / {r['fit_cpu_s']:.0f} s |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--size", type=int, default=48)
    p.add_argument("--steps", type=int, default=60, help="adam steps")
    p.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=SOLVERS)
    p.add_argument("--oversample", type=float, default=1.0, help="splat light-view oversampling")
    p.add_argument("--lr", type=float, default=0.1)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--presets", nargs="+", default=list(PRESETS))
    p.add_argument("--sizes-mm", nargs="+", type=float, default=list(SIZES_MM))
    p.add_argument("--out-dir", type=Path, default=ROOT / "benchmarks" / "results")
    p.add_argument("--name", default="fit")
    args = p.parse_args(argv)
    if args.quick:
        args.presets, args.sizes_mm, args.steps, args.size, args.views = ["potato"], [20.0], 3, 16, 2
    torch.set_num_threads(args.threads)
    env = {"torch": torch.__version__, "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
           "platform": platform.platform(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    args.out_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    for size_mm in args.sizes_mm:
        for preset in args.presets:
            for r in run_one(preset, size_mm, args):
                rows.append(r)
                print(f"{preset} {size_mm:.0f} mm {r['solver']}: sigma_a err "
                      f"{[round(x, 3) for x in r['relative_error']['sigma_a']]}, sigma_s' err "
                      f"{[round(x, 3) for x in r['relative_error']['sigma_s_prime']]}, fit {r['fit_s']:.0f} s "
                      f"(cpu {r['fit_cpu_s']:.0f} s)", flush=True)
            (args.out_dir / f"{args.name}.json").write_text(json.dumps({"env": env, "rows": rows}, indent=1))
            (args.out_dir / f"{args.name}.md").write_text(_md(rows, env))
    return rows


if __name__ == "__main__":
    main()
