"""Learned heterogeneous translucency: recover a painted stripe of denser material from multi-view images.

Shah ch. 7's editing turned around (issue 18): a sphere in one known material carries a stripe where the material is
denser, :math:`M_d = 2` (the profile :math:`R_d(r M_d)` is twice as narrow there), painted on the vertices with
``|y| < --stripe-mm / 2``. Targets are rendered with the all-pairs reference integrator
(:func:`~torchsss.ops.reference_radiosity` with the per-source ``src_distance_scale``, interpolated from the vertices
at every surface sample) from ``--views`` views orbiting the sphere's y axis, lit by two point lights. The fit
starts from a homogeneous map (:math:`M_d = 1` everywhere) and learns
:class:`~torchsss.modules.HeterogeneousMaps` (log :math:`M_d` per vertex, one channel) by Adam through splatting
(:class:`~torchsss.pipelines.splat.SplatRenderer`'s per-vertex ``distance_scale``), with the loss
:math:`\\frac{1}{V}\\sum_v \\sum (L - L^*)^2 / \\sum L^{*2} + \\lambda\\,` :func:`~torchsss.modules.edge_smoothness`
(``--smooth``). ``--learn-irradiance`` learns :math:`M_i` too (the targets have :math:`M_i = 1`).

Reported (and written to ``--json``): the map error, the RMS of :math:`M_d - M_d^*` over the vertices that some view
sees lit or shaded (a vertex no camera sees has no gradient and keeps its initial value), before and after; the
mean :math:`M_d` inside and outside the stripe; the loss history and the time. ``--out`` gets ``*_maps.png`` (the
fitted and the true :math:`M_d` against the height y of each vertex) and ``*_side_by_side.png`` (target, initial,
fitted per view) and ``*_loss.png``.

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
from torchsss.geometry.gbuffer import camera_gbuffer
from torchsss.geometry.sampling import surface_samples
from torchsss.modules import HeterogeneousMaps, material_module
from torchsss.ops import reference_radiosity
from torchsss.physics.fresnel import exit_radiance
from torchsss.pipelines import build
from torchsss.pipelines.reference import default_spacing, sample_irradiance

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit_material import _loss_png, _side_by_side, view_loss

__all__ = ["render_reference_modified", "stripe_scene"]


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


def _at(attr: Tensor, faces: Tensor, face_id: Tensor, bary: Tensor) -> Tensor:
    """A per-vertex attribute :math:`(V, K)` interpolated at points given by face ids and barycentrics."""
    return (attr[faces[face_id]] * bary.unsqueeze(-1).to(attr.dtype)).sum(1)


def render_reference_modified(mesh, material, lights, camera: Camera, distance_scale: Tensor | None = None,
                              irradiance_scale: Tensor | None = None, spacing_mm: float | None = None) -> Tensor:
    """Reference radiance :math:`(1, 3, H, W)` of a mesh with per-vertex :math:`M_d`, :math:`M_i` (Shah eq. 7.4).

    The reference renderer's steps (surface samples at the material's spacing, ray-traced irradiance, all pairs to
    the camera's pixels, the exit Fresnel term) with the modifiers interpolated at every sample and passed to
    :func:`~torchsss.ops.reference_radiosity` as ``src_distance_scale`` / ``src_irradiance_scale``.
    """
    profile = material_module(material, dtype=mesh.vertices.dtype)
    spacing = default_spacing(profile, mesh) if spacing_mm is None else spacing_mm
    samples = surface_samples(mesh, spacing)
    e = sample_irradiance(mesh, samples, lights, profile.eta)
    md = None if distance_scale is None else _at(distance_scale, mesh.faces, samples.face_id, samples.bary)[None]
    mi = None if irradiance_scale is None else _at(irradiance_scale, mesh.faces, samples.face_id, samples.bary)[None]
    gbuf = camera_gbuffer(mesh, camera)
    mask = gbuf.mask[0, 0]
    dst = gbuf.position[0].permute(1, 2, 0)[mask]
    b = reference_radiosity(samples.position[None], e[None], samples.area[None], dst[None], profile,
                            src_distance_scale=md, src_irradiance_scale=mi)[0]
    img = torch.zeros(camera.height, camera.width, 3, dtype=b.dtype)
    img[mask] = b
    b_img = img.permute(2, 0, 1).unsqueeze(0)
    cos_o = (gbuf.normal * gbuf.view_dir).sum(1, keepdim=True).clamp(0.0, 1.0)
    return exit_radiance(b_img, cos_o, profile.eta) * gbuf.mask


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--material", default="skin1", help="the known base material (preset)")
    p.add_argument("--radius", type=float, default=8.0, help="sphere radius (mm)")
    p.add_argument("--subdivisions", type=int, default=2, help="icosphere subdivisions (2: 162 vertices)")
    p.add_argument("--stripe-mm", type=float, default=5.0, help="stripe width (mm)")
    p.add_argument("--density", type=float, default=2.0, help="M_d inside the stripe")
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--size", type=int, default=32)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--lr", type=float, default=0.08)
    p.add_argument("--oversample", type=float, default=1.0, help="splat light-view oversampling")
    p.add_argument("--smooth", type=float, default=0.5, help="weight of the edge smoothness regulariser")
    p.add_argument("--learn-irradiance", action="store_true", help="learn M_i too")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    mesh, md_true, lights, cams = stripe_scene(args.radius, args.subdivisions, args.stripe_mm, args.density,
                                               args.views, args.size)
    print(f"rendering {len(cams)} reference targets ({args.size}x{args.size}, {mesh.vertices.shape[0]} vertices) ...")
    with torch.no_grad():
        targets = [render_reference_modified(mesh, args.material, lights, c, md_true) for c in cams]
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
    seen = torch.zeros(mesh.vertices.shape[0], dtype=torch.bool)
    opt = torch.optim.Adam(maps.parameters(), lr=args.lr)
    history = []
    bar = range(args.steps)
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(bar, desc="fit M_d (splat)", unit="step", file=sys.stdout)
    t0 = time.perf_counter()
    with torchsss.validation(False):
        for _ in bar:
            opt.zero_grad(set_to_none=True)
            data = sum(view_loss(render(c), t) for c, t in zip(cams, targets)) / len(cams)
            loss = data + args.smooth * maps.smoothness()
            loss.backward()
            seen |= maps.log_distance_scale.grad.abs().amax(-1) > 0
            opt.step()
            history.append(float(data.detach()))
            if not args.no_progress:
                bar.set_postfix(data=f"{history[-1]:.3e}")
    t_fit = time.perf_counter() - t0
    with torch.no_grad():
        fitted = [render(c) for c in cams]
        md_fit = maps()[0]
    stripe = (md_true[:, 0] > 1.0)

    def rms(a: Tensor, sel: Tensor) -> float:
        return float(((a - md_true)[sel] ** 2).mean().sqrt())

    out = {"material": args.material, "vertices": int(mesh.vertices.shape[0]), "views": len(cams),
           "size": args.size, "oversample": args.oversample, "steps": args.steps, "lr": args.lr,
           "smooth": args.smooth, "density": args.density,
           "stripe_mm": args.stripe_mm, "seen_vertices": int(seen.sum()),
           "map_rms_error": {"initial": rms(torch.ones_like(md_true), seen), "fitted": rms(md_fit, seen)},
           "mean_md": {"stripe": float(md_fit[stripe & seen].mean()), "outside": float(md_fit[~stripe & seen].mean()),
                       "true_stripe": args.density, "true_outside": 1.0},
           "loss": history, "time_s": {"targets": t_targets, "fit": t_fit, "per_step": t_fit / args.steps}}
    out_dir = args.out or (args.json.parent if args.json else Path("out/fit"))
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = args.json.stem if args.json else "heterogeneous"
    _loss_png(out_dir / f"{stem}_loss.png", history, "stripe of M_d: data term")
    _side_by_side(out_dir / f"{stem}_side_by_side.png", [[t, i, f] for t, i, f in zip(targets, initial, fitted)])
    _maps_png(out_dir / f"{stem}_maps.png", mesh.vertices[:, 1], md_true[:, 0], md_fit[:, 0], seen)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    print(f"map RMS error over {out['seen_vertices']} seen vertices: {out['map_rms_error']['initial']:.3f} -> "
          f"{out['map_rms_error']['fitted']:.3f}; mean M_d in the stripe {out['mean_md']['stripe']:.3f} "
          f"(true {args.density}), outside {out['mean_md']['outside']:.3f} (true 1); fit {t_fit:.0f} s")
    return out


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
