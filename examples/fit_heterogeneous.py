"""Learned heterogeneous translucency: recover a painted stripe of denser material from multi-view images.

Shah ch. 7's editing turned around (issue 18): a sphere in one known material carries a stripe where the material is
denser, :math:`M_d = 2` (the profile :math:`R_d(r M_d)` is twice as narrow there), painted on the vertices with ``|y| <
--stripe-mm / 2``. Targets are rendered with the reference renderer (:class:`~torchsss.pipelines.ReferenceRenderer` with
the per-vertex ``distance_scale``, at a finer sample spacing than the correction's renders below, so the fit does not
share the targets' quadrature) from ``--views`` views orbiting the sphere's y axis, lit by two point lights. The fit
starts from a homogeneous map (:math:`M_d = 1` everywhere) and learns :class:`~torchsss.modules.HeterogeneousMaps` (log
:math:`M_d` per vertex, one channel) through splatting (:class:`~torchsss.pipelines.splat.SplatRenderer`'s per-vertex
``distance_scale``) with :func:`fit_maps`: each outer iteration renders the reference once at the current map and fits
splat + that defect (``fit_lm.py``'s defect correction) by L-BFGS, with the loss :math:`\\frac{1}{V}\\sum_v \\sum (L -
L^*)^2 / \\sum L^{*2} + \\lambda\\,` :func:`~torchsss.modules.edge_smoothness` (``--smooth``). ``--solver adam`` and
``--no-correct`` give the plain Adam fit of the splat images. ``--learn-irradiance`` learns :math:`M_i` too (the targets
have :math:`M_i = 1`).

Reported (and written to ``--json``): the map error, the RMS of :math:`M_d - M_d^*` over the vertices the data term
reaches ("seen": a gradient at the first evaluation) and over the *well-lit* ones (the light flux entering around
the vertex, :func:`vertex_flux`, at least 20% of the median vertex's: a vertex that little light enters around
hardly changes any image), before and after; the mean :math:`M_d` inside and outside the stripe; the loss history,
the per-vertex maps and the time. ``--out`` gets ``*_maps.png`` (the fitted and the true :math:`M_d` against the
height y of each vertex), ``*_side_by_side.png`` (target, initial, fitted per view) and ``*_loss.png``.

Usage::

    python examples/fit_heterogeneous.py --json out/fit/stripe.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
from torch import Tensor

import torchsss
from torchsss.geometry import Camera, PointLight, sphere
from torchsss.geometry.sampling import surface_samples
from torchsss.modules import HeterogeneousMaps
from torchsss.pipelines import build
from torchsss.pipelines.reference import sample_irradiance

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit_material import _loss_png, _side_by_side, target_spacing, view_loss

__all__ = ["fit_maps", "render_reference_maps", "stripe_scene", "vertex_flux"]


def stripe_scene(radius_mm: float = 8.0, subdivisions: int = 3, stripe_mm: float = 5.0, density: float = 2.0,
                 views: int = 4, size: int = 40):
    """The sphere, its true per-vertex :math:`M_d` :math:`(V, 1)`, the lights and the orbit cameras."""
    mesh = sphere(radius_mm, subdivisions)
    y = mesh.vertices[:, 1]
    md = torch.where(y.abs() < stripe_mm / 2, torch.full_like(y, density), torch.ones_like(y)).unsqueeze(-1)
    lights = [PointLight((40.0, 25.0, 30.0), 4e3), PointLight((-35.0, -15.0, -40.0), 3e3)]
    d = 6.0 * radius_mm
    cams = [Camera(eye=(d * math.sin(2 * math.pi * k / views), 0.3 * d, d * math.cos(2 * math.pi * k / views)),
                   target=(0.0, 0.0, 0.0), fov_deg=30.0, width=size, height=size) for k in range(views)]
    return mesh, md, lights, cams


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--material", default="skin1", help="the known base material (preset)")
    p.add_argument("--radius", type=float, default=8.0, help="sphere radius (mm)")
    p.add_argument("--subdivisions", type=int, default=2, help="icosphere subdivisions (2: 162 vertices)")
    p.add_argument("--stripe-mm", type=float, default=5.0, help="stripe width (mm)")
    p.add_argument("--density", type=float, default=2.0, help="M_d inside the stripe")
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--size", type=int, default=32)
    p.add_argument("--solver", default="lbfgs", choices=("lbfgs", "adam"),
                   help="lbfgs: L-BFGS with the strong Wolfe line search (default); adam: Adam")
    p.add_argument("--no-correct", action="store_true",
                   help="fit the splat images as they are (no reference defect correction)")
    p.add_argument("--outer", type=int, default=4, help="outer iterations (reference correction) at most")
    p.add_argument("--steps", type=int, default=40,
                   help="per outer iteration: L-BFGS iterations, or Adam steps, at most")
    p.add_argument("--lr", type=float, default=0.08, help="adam: learning rate (log space)")
    p.add_argument("--oversample", type=float, default=1.0, help="splat light-view oversampling")
    p.add_argument("--smooth", type=float, default=1e-4, help="weight of the edge smoothness regulariser")
    p.add_argument("--learn-irradiance", action="store_true", help="learn M_i too")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    for name in ("views", "size", "steps", "outer"):
        if getattr(args, name) < 1:
            p.error(f"--{name}: expected a positive int, got {getattr(args, name)}")
    return args


def render_reference_maps(mesh, material, lights, cameras, distance_scale: Tensor | None = None,
                          irradiance_scale: Tensor | None = None, spacing_mm: float | None = None) -> list[Tensor]:
    """Reference images :math:`(1, 3, H, W)` of a mesh with per-vertex :math:`M_d`, :math:`M_i` (forward only).

    The reference renderer (:class:`~torchsss.pipelines.ReferenceRenderer`) with the maps as its per-vertex
    ``distance_scale`` / ``irradiance_scale``; ``spacing_mm`` None: its default (the material's spacing over the
    largest :math:`M_d`).
    """
    md = None if distance_scale is None else distance_scale.detach()
    mi = None if irradiance_scale is None else irradiance_scale.detach()
    knobs = {} if spacing_mm is None else {"spacing_mm": spacing_mm}
    ref = build("reference", mesh, material, distance_scale=md, irradiance_scale=mi, **knobs)
    with torch.no_grad():
        return [ref.render(lights, c).radiance for c in cameras]


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    mesh, md_true, lights, cams = stripe_scene(args.radius, args.subdivisions, args.stripe_mm, args.density,
                                               args.views, args.size)
    # independent targets: a finer quadrature than the correction's reference at its default spacing
    spacing = target_spacing(mesh, args.material) / args.density
    print(f"rendering {len(cams)} reference targets ({args.size}x{args.size}, {mesh.vertices.shape[0]} vertices, "
          f"spacing {spacing:.3g} mm) ...")
    targets = render_reference_maps(mesh, args.material, lights, cams, md_true, spacing_mm=spacing)
    t_targets = time.perf_counter() - t_start
    maps = HeterogeneousMaps(mesh, 1, learn_irradiance=args.learn_irradiance)
    renderer = build("splat", mesh, args.material, differentiable=True, splat_method="window",
                     oversample=args.oversample, distance_scale=torch.ones(mesh.vertices.shape[0]))
    renderer.material.requires_grad_(False)  # the base material is known; only the maps are learned

    def render(c: Camera) -> Tensor:
        md, mi = maps()
        # the renderer's per-vertex modifiers, (V, K), set every step (SplatRenderer keeps them as tensors)
        renderer.md, renderer.mi = md, (mi if args.learn_irradiance else None)
        return renderer.render(lights, c).radiance

    with torch.no_grad():
        initial = [render(c) for c in cams]
    correct = not args.no_correct
    t0 = time.perf_counter()
    result = fit_maps(maps, render, cams, targets, smooth=args.smooth, solver=args.solver, outer=args.outer,
                      steps=args.steps, lr=args.lr, progress=not args.no_progress,
                      correct=(lambda: render_reference_maps(mesh, args.material, lights, cams, *maps())) if correct
                      else None)
    t_fit = time.perf_counter() - t0
    seen = result["seen"]
    flux = vertex_flux(mesh, lights, spacing)
    lit = flux > 0.2 * float(flux[flux > 0].median())  # well lit: their M_d shapes a visible share of the light
    with torch.no_grad():
        fitted = render_reference_maps(mesh, args.material, lights, cams, *maps()) if correct else \
            [render(c) for c in cams]
        md_fit = maps()[0]
    stripe = (md_true[:, 0] > 1.0)

    def rms(a: Tensor, sel: Tensor) -> float:
        return float(((a - md_true)[sel] ** 2).mean().sqrt())

    final_loss = float(sum(view_loss(a, b) for a, b in zip(fitted, targets)) / len(cams))
    out = {"material": args.material, "vertices": int(mesh.vertices.shape[0]), "views": len(cams),
           "size": args.size, "oversample": args.oversample, "solver": args.solver, "corrected": correct,
           "fitted_render": "reference" if correct else "splat", "outer": result["outer"],
           "steps": args.steps, "lr": args.lr if args.solver == "adam" else None,
           "smooth": args.smooth, "density": args.density, "target_spacing_mm": spacing,
           "stripe_mm": args.stripe_mm, "seen_vertices": int(seen.sum()),
           "map_rms_error": {"initial": rms(torch.ones_like(md_true), seen), "fitted": rms(md_fit, seen)},
           "map_max_error": float((md_fit - md_true)[seen].abs().max()),
           "lit_vertices": int(lit.sum()),
           "map_rms_error_lit": {"initial": rms(torch.ones_like(md_true), lit), "fitted": rms(md_fit, lit)},
           "map_max_error_lit": float((md_fit - md_true)[lit].abs().max()),
           "per_vertex": {"y": mesh.vertices[:, 1].tolist(), "true": md_true[:, 0].tolist(),
                          "fitted": md_fit[:, 0].tolist(), "lit_flux": flux.tolist()},
           "mean_md": {"stripe": float(md_fit[stripe & seen].mean()), "outside": float(md_fit[~stripe & seen].mean()),
                       "true_stripe": args.density, "true_outside": 1.0},
           "final_loss": final_loss, "loss": result["loss"], "evaluations": result["evaluations"],
           "time_s": {"targets": t_targets, "fit": t_fit, "total": time.perf_counter() - t_start}}
    out_dir = args.out or (args.json.parent if args.json else Path("out/fit"))
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = args.json.stem if args.json else "heterogeneous"
    _loss_png(out_dir / f"{stem}_loss.png", result["loss"], "stripe of M_d: data term")
    _side_by_side(out_dir / f"{stem}_side_by_side.png", [[t, i, f] for t, i, f in zip(targets, initial, fitted)])
    _maps_png(out_dir / f"{stem}_maps.png", mesh.vertices[:, 1], md_true[:, 0], md_fit[:, 0], seen)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    print(f"map RMS error over {out['seen_vertices']} seen vertices: {out['map_rms_error']['initial']:.3f} -> "
          f"{out['map_rms_error']['fitted']:.3f} (max {out['map_max_error']:.3f}); over the {out['lit_vertices']} "
          f"lit ones {out['map_rms_error_lit']['initial']:.3f} -> {out['map_rms_error_lit']['fitted']:.3f} (max "
          f"{out['map_max_error_lit']:.3f}); mean M_d in the stripe "
          f"{out['mean_md']['stripe']:.3f} (true {args.density}), outside {out['mean_md']['outside']:.3f} (true 1); "
          f"{out['fitted_render']} loss {final_loss:.2e}; fit {t_fit:.0f} s")
    return out


def vertex_flux(mesh, lights, spacing_mm: float) -> Tensor:
    """The light flux :math:`(V,)` (summed over channels) that enters the surface around each vertex.

    The transmitted irradiance times the area of the surface samples, shared among their face's corners by their
    barycentrics. A vertex's :math:`M_d` shapes only the light that enters around it, so a vertex with no flux
    cannot be recovered from any image (the data term's gradient there is 0).
    """
    samples = surface_samples(mesh, spacing_mm)
    e = sample_irradiance(mesh, samples, lights, 1.0).sum(-1)  # eta 1: the geometric share, no Fresnel weighting
    w = (e * samples.area)[:, None] * samples.bary.to(e.dtype)
    return torch.zeros(mesh.vertices.shape[0], dtype=e.dtype).index_add_(0, mesh.faces[samples.face_id].reshape(-1),
                                                                         w.reshape(-1))


def fit_maps(maps: HeterogeneousMaps, render, cameras, targets: list[Tensor], *, smooth: float, solver: str = "lbfgs",
             outer: int = 4, steps: int = 40, lr: float = 0.08, correct=None, tol: float = 1e-3,
             progress: bool = True) -> dict:
    """Fit the maps' parameters so that ``render(camera)`` (+ the reference's defect) matches the targets.

    Each outer iteration measures the defect :math:`D_v = L^{ref}_v(m_k) - L_v(m_k)` of the fast render at the
    current maps with ``correct()`` (the reference images; None: :math:`D = 0`), then minimises
    :math:`\\frac{1}{V}\\sum_v` ``view_loss`` :math:`(L_v(m) + D_v, L^*_v) + \\lambda\\,` ``maps.smoothness()``
    by L-BFGS (strong Wolfe line search, ``steps`` iterations at most) or by ``steps`` Adam steps. At a fixed
    point the reference at the maps matches the targets as well as the fast method's gradient can tell
    (``fit_lm.py``'s defect correction, for a map instead of a material). Stops after ``outer`` iterations, or
    when one moves no log-map entry by more than ``tol``.

    Returns:
        ``{"loss": the data term at every evaluation, "outer": per outer iteration the reference loss at its
        start (None without ``correct``) and the largest log change, "evaluations": n, "seen": (V,) bool, the
        vertices that received a gradient}``.
    """
    params = [p for p in maps.parameters() if p.requires_grad]
    views = len(cameras)
    history: list[float] = []
    outers: list[dict] = []
    seen = torch.zeros(maps.num_vertices, dtype=torch.bool)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=outer * steps, desc=f"fit M_d (splat, {solver})", unit="it", file=sys.stdout)
    with torchsss.validation(False):
        for k in range(outer):
            start = [p.detach().clone() for p in params]
            with torch.no_grad():
                if correct is not None:
                    ref = correct()
                    offsets = [r - render(c) for r, c in zip(ref, cameras)]
                    ref_loss = float(sum(view_loss(r, t) for r, t in zip(ref, targets)) / views)
                else:
                    offsets, ref_loss = [torch.zeros_like(t) for t in targets], None

            def objective():
                for p in params:
                    p.grad = None
                data = sum(view_loss(render(c) + d, t) for c, d, t in zip(cameras, offsets, targets)) / views  # noqa: B023
                nonlocal seen
                if not seen.any():  # the vertices the data term reaches (the regulariser reaches all)
                    (g,) = torch.autograd.grad(data, maps.log_distance_scale, retain_graph=True)
                    seen = g.abs().amax(-1) > 0
                loss = data + smooth * maps.smoothness()
                loss.backward()
                history.append(float(data.detach()))
                if bar is not None:
                    bar.set_postfix(data=f"{history[-1]:.3e}", outer=len(outers))
                return loss

            if solver == "lbfgs":
                opt = torch.optim.LBFGS(params, lr=1.0, max_iter=steps, history_size=20,
                                        line_search_fn="strong_wolfe", tolerance_grad=1e-10, tolerance_change=1e-12)
                opt.step(objective)
                iters = opt.state[opt._params[0]].get("n_iter", steps)
            else:
                opt = torch.optim.Adam(params, lr=lr)
                for _ in range(steps):
                    objective()
                    opt.step()
                iters = steps
            if bar is not None:
                bar.update(steps)
            moved = max(float((p.detach() - s).abs().max()) for p, s in zip(params, start))
            outers.append({"outer": k, "reference_loss": ref_loss, "iterations": int(iters), "max_change": moved})
            if correct is None or moved < tol:
                break
    if bar is not None:
        bar.close()
    return {"loss": history, "outer": outers, "evaluations": len(history), "seen": seen}


def _maps_png(path: Path, y: Tensor, true: Tensor, fit: Tensor, seen: Tensor) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    order = torch.argsort(y)
    ax.plot(y[order], true[order], "k-", lw=1, label="true M_d")
    ax.scatter(y[seen], fit[seen], s=4, label="fitted (seen vertices)")
    ax.scatter(y[~seen], fit[~seen], s=4, c="0.7", label="not seen")
    ax.set_xlabel("vertex height y (mm)")
    ax.set_ylabel("M_d")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    main()
