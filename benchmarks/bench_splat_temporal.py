"""Temporal coherence of Shah's light-view splat samples (sec. 6.5.2): flicker of a rotating object, reuse or not.

Scene: the spot mesh at 40 mm (bounding-box diagonal), skin1, a point light, a 64 x 64 camera; the mesh turns about
the vertical axis by ``deg`` degrees per frame (its vertices rotated, a new Mesh per frame). Per light-view grid n
(0.25x, 0.5x and 1x the budget of :func:`torchsss.pipelines.splat.splat_grid`) several source sets are splatted with
:class:`torchsss.modules.splat.SplatTranslucency`, exactly as :func:`torchsss.pipelines.splat.render_splat` does:

* ``plain``: the lit pixels of a fresh light view each frame (what ``render_splat`` does);
* ``carry``: :func:`torchsss.geometry.coherence.coherent_light_samples` with ``mode="carry"``: samples attached
  to the surface and reused while the light still sees them, each carrying the area it was taken with;
* ``partition``: ``mode="partition"`` (the default): the same reused positions, but every lit pixel of the current
  light view splits its flux among the kept samples within 1 light-view pixel by normalised tent weights (a new
  sample where none is), so the total flux is the light view's exactly;
* ``partition_nearest``: as ``partition`` with all of a pixel's flux given to the nearest kept sample;
* ``partition_r1.5``: as ``partition`` with a tent radius of 1.5 pixels.

The reference is a fresh light view at ``fine`` x the budget's grid, rendered the same way. Columns:

* ``flicker``: mean over frames of :math:`\\sum|L_{t+1} - L_t| / \\sum|L_t|` (all pixels); ``flicker_ref`` the same
  for the reference (the true motion); ``excess`` = flicker - flicker_ref;
* ``jitter``: mean over frames of :math:`\\sum|e_{t+1} - e_t| / \\sum|R_t|` with :math:`e = L - R` the error
  against the reference: the frame-to-frame change that the true motion does not explain (the flicker proper);
* ``rmse_mean`` / ``rmse_max``: relative RMSE :math:`\\|L - R\\|_2 / \\|R\\|_2` per frame, mean and max over
  frames (reuse must not add bias);
* ``flux_dev``: largest relative deviation over frames of the total source flux from the reference light view's;
* ``samples``: mean number of splats per frame; ``reused``: mean fraction of them taken over from the previous
  frame; ``ms_frame``: mean time to build the sources (light view, reuse) per frame.

Usage::

    python benchmarks/bench_splat_temporal.py            # 24 frames, reference at 2x the budget (~5 min)
    python benchmarks/bench_splat_temporal.py --quick    # 6 frames, reference at 1x the budget (< 1 min)
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import torch

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark
from torchsss.geometry.camera import Camera
from torchsss.geometry.coherence import coherent_light_samples
from torchsss.geometry.gbuffer import camera_gbuffer, light_view
from torchsss.geometry.lights import PointLight
from torchsss.geometry.loading import load_mesh
from torchsss.geometry.mesh import Mesh
from torchsss.modules.material import DipoleMaterial
from torchsss.modules.splat import SplatTranslucency
from torchsss.physics.fresnel import exit_radiance
from torchsss.pipelines.splat import splat_grid
from torchsss.scene import Material

RESULTS_DIR = Path(__file__).resolve().parent / "results"

MD_COLUMNS = {
    "temporal": ["grid_scale", "n", "mode", "frames", "deg_per_frame", "flicker", "flicker_ref", "excess", "jitter",
                 "rmse_mean", "rmse_max", "flux_dev", "samples", "reused", "ms_frame"],
}

FULL = {"frames": 24, "deg": 0.5, "scales": (0.25, 0.5, 1.0), "fine": 2.0}
QUICK = {"frames": 6, "deg": 0.5, "scales": (0.25, 0.5), "fine": 1.0}

EPS = 0.01
MODES = {
    "plain": None,
    "carry": {"mode": "carry"},
    "partition": {"mode": "partition"},
    "partition_nearest": {"mode": "partition", "weights": "nearest"},
    "partition_r1.5": {"mode": "partition", "radius_px": 1.5},
}
LIGHT = PointLight((-60.0, 50.0, 40.0), (8000.0, 8000.0, 8000.0))
CAMERA = Camera(eye=(55.0, 15.0, 45.0), target=(0.0, 0.0, 0.0), fov_deg=40.0, width=64, height=64)


def rotated(mesh: Mesh, deg: float) -> Mesh:
    """The mesh turned by ``deg`` degrees about the vertical (y) axis through the origin."""
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    rot = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=mesh.vertices.dtype)
    return Mesh(mesh.vertices @ rot.T, mesh.faces, name=mesh.name)


class Renderer:
    """Splat a set of sources onto a frame's camera G-buffer (render_splat's steps, sources supplied)."""

    def __init__(self, material: Material) -> None:
        sa, ss, eta = material.tensors(dtype=torch.float32)
        self.eta = material.eta
        self.module = SplatTranslucency(DipoleMaterial(sa, ss, eta), eps=EPS)

    def __call__(self, mesh: Mesh, pos: torch.Tensor, flux: torch.Tensor) -> torch.Tensor:
        """Radiance (1, 3, H, W) of ``mesh`` lit by sources ``pos``, ``flux`` (1, S, 3)."""
        g = camera_gbuffer(mesh, CAMERA)
        with torch.no_grad():
            b = self.module(pos, flux, g.position, g.mask, CAMERA.view_proj())
        cos_o = (g.normal * g.view_dir).sum(1, keepdim=True).clamp(0.0, 1.0)
        return exit_radiance(b, cos_o, self.eta) * g.mask


def plain_sources(mesh: Mesh, n: int, eta: float) -> tuple[torch.Tensor, torch.Tensor]:
    lv = light_view(mesh, LIGHT, n, eta)
    sel = lv.mask[0, 0]
    return lv.position[0].permute(1, 2, 0)[sel].unsqueeze(0), lv.flux[0].permute(1, 2, 0)[sel].unsqueeze(0)


def sequence_stats(images: list[torch.Tensor], refs: list[torch.Tensor]) -> dict:
    flick, flick_ref, jitter, rmse = [], [], [], []
    for t in range(len(images)):
        err, ref = images[t] - refs[t], refs[t]
        rmse.append(float(err.square().sum().sqrt() / ref.square().sum().sqrt()))
        if t + 1 < len(images):
            flick.append(float((images[t + 1] - images[t]).abs().sum() / images[t].abs().sum()))
            flick_ref.append(float((refs[t + 1] - refs[t]).abs().sum() / ref.abs().sum()))
            jitter.append(float(((images[t + 1] - refs[t + 1]) - err).abs().sum() / ref.abs().sum()))

    def mean(x: list[float]) -> float:
        return sum(x) / len(x)

    return {"flicker": mean(flick), "flicker_ref": mean(flick_ref), "excess": mean(flick) - mean(flick_ref),
            "jitter": mean(jitter), "rmse_mean": mean(rmse), "rmse_max": max(rmse)}


def run(cfg: dict, log=print) -> list[dict]:
    mesh0 = load_mesh("spot", 40.0)
    material = Material.from_json("skin1")
    eta = material.eta
    render = Renderer(material)
    base = splat_grid(mesh0, material, EPS)
    frames = [rotated(mesh0, cfg["deg"] * t) for t in range(cfg["frames"])]
    n_fine = max(2, round(cfg["fine"] * base))
    refs, ref_flux = [], []
    for m in frames:
        pos, flux = plain_sources(m, n_fine, eta)
        refs.append(render(m, pos, flux))
        ref_flux.append(float(flux.sum()))
    log(f"reference: grid {n_fine} ({cfg['fine']}x the budget's {base}), {cfg['frames']} frames")
    records = []
    for scale in cfg["scales"]:
        n = max(2, round(scale * base))
        for mode, kwargs in MODES.items():
            images, counts, reused, dev, t_src = [], [], [], [], 0.0
            prev = None
            for t, m in enumerate(frames):
                t0 = time.perf_counter()
                if mode == "plain":
                    pos, flux = plain_sources(m, n, eta)
                    st = {"reused": 0}
                else:
                    prev, pos, flux, st = coherent_light_samples(m, LIGHT, n, eta, prev, **kwargs)
                t_src += time.perf_counter() - t0
                images.append(render(m, pos, flux))
                counts.append(int(pos.shape[1]))
                reused.append(st["reused"] / max(1, int(pos.shape[1])))
                dev.append(abs(float(flux.sum()) / ref_flux[t] - 1.0))
            rec = {"benchmark": "temporal", "grid_scale": scale, "n": n, "n_ref": n_fine, "mode": mode,
                   "frames": cfg["frames"], "deg_per_frame": cfg["deg"], **sequence_stats(images, refs),
                   "flux_dev": max(dev), "samples": sum(counts) / len(counts),
                   "reused": sum(reused[1:]) / max(1, len(reused) - 1), "ms_frame": 1e3 * t_src / len(frames),
                   "material": "skin1", "mesh": "spot 40 mm", "image": "64x64"}
            log(f"  n={n:4d} {mode:17s}: flicker {rec['flicker']:.4f} (ref {rec['flicker_ref']:.4f}), jitter "
                f"{rec['jitter']:.4f}, rmse {rec['rmse_mean']:.4f} (max {rec['rmse_max']:.4f}), flux dev "
                f"{rec['flux_dev']:.3f}, {rec['samples']:.0f} splats, {100 * rec['reused']:.0f}% reused, "
                f"{rec['ms_frame']:.0f} ms")
            records.append(rec)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__.split("\n\n")[0], "splat_temporal", RESULTS_DIR,
                              seed_help="unused (the scene is fixed)")
    args = parser.parse_args(argv)
    setup_benchmark(parser, args)
    cfg = QUICK if args.quick else FULL
    start = time.perf_counter()
    records = run(cfg)
    finish_benchmark(args.name, records, args.out_dir, columns=MD_COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
