"""Render the Igea head with Chang et al.'s texture-space importance sampling at several N; plot error vs time.

The mesh (``../shared/data/meshes/igea.ply`` next to the repository by default) is decimated to ~10k faces and
scaled to 10 mm (bounding-box diagonal), in skin1; the lights and camera are those of ``examples/scenes/igea.json``
scaled from its 30 mm to 10 mm. The atlas is built once (precompute); then for every N (default 64, 256, 1024,
4096) one frame is rendered with ``render_icdf(prebuilt=...)`` and written as EXR + PNG (all PNGs share the
reference's exposure). The shadow-mapped reference (``render_reference(..., shadows="shadowmap")``, the same
visibility as the fast path) is rendered once; the relative RMSE of every frame against it and the frame time go
to ``error_vs_time.csv`` and, when matplotlib is installed (``pip install torchsss[plots]``), to
``error_vs_time.png``.

Usage::

    python examples/render_icdf_igea.py --out-dir out/icdf_igea --resolution 128 --samples 64 256 1024 4096
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import sys
import time
from pathlib import Path

import torch

from torchsss.geometry.loading import load_mesh
from torchsss.io import tonemap, write_exr, write_png
from torchsss.pipelines.chang import build_icdf, render_icdf
from torchsss.pipelines.reference import render_reference
from torchsss.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MESH = ROOT.parent / "shared" / "data" / "meshes" / "igea.ply"


def rel_rmse(image: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> float:
    """``sqrt(mean((L - L_ref)^2)) / sqrt(mean(L_ref^2))`` over the pixels in ``mask`` (all channels)."""
    m = mask.expand_as(ref)
    d, r = (image - ref)[m].double(), ref[m].double()
    return float((d.square().mean() / r.square().mean()).sqrt())


def plot(rows: list[dict], path: Path) -> Path | None:
    """Error against frame time (log-log), one labelled point per N; ``None`` without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, ax = plt.subplots(figsize=(5, 4))
    t = [r["t_frame_s"] * 1e3 for r in rows]
    e = [r["rel_rmse"] for r in rows]
    ax.loglog(t, e, "o-", label="render_icdf (whole frame)")
    tm = [r["t_module_s"] * 1e3 for r in rows]
    ax.loglog(tm, e, "s--", alpha=0.6, label="sampling module only")
    for r, x, y in zip(rows, t, e):
        ax.annotate(f"N={r['samples']}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xlabel("time per frame (ms)")
    ax.set_ylabel("relative RMSE vs reference")
    ax.set_title("Chang importance sampling: Igea, skin1", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    """Parse the options, render, write the images, the table and the plot, print the timings.

    Args:
        argv: command-line arguments (default ``sys.argv[1:]``).

    Returns:
        The exit status (0 on success, 1 when the mesh file is missing).
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, default=DEFAULT_MESH, help="Igea mesh file (default: %(default)s)")
    ap.add_argument("--out-dir", type=Path, default=Path("out/icdf_igea"), help="output folder")
    ap.add_argument("--resolution", type=int, default=128, help="image width and height in pixels")
    ap.add_argument("--atlas", type=int, default=512, help="texture atlas resolution")
    ap.add_argument("--faces", type=int, default=10000, help="decimate the mesh to about this many faces")
    ap.add_argument("--size-mm", type=float, default=10.0, help="object size (bounding-box diagonal) in mm")
    ap.add_argument("--samples", type=int, nargs="+", default=[64, 256, 1024, 4096], help="the N to render")
    ap.add_argument("--seed", type=int, default=0, help="scramble seed of the Sobol samples")
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if not args.mesh.is_file():
        print(f"error: mesh file not found: {args.mesh}\n(the Igea head is expected in ../shared/data/meshes/ "
              f"relative to the repository root; pass --mesh PATH)", file=sys.stderr)
        return 1

    scene = load_scene(ROOT / "examples" / "scenes" / "igea.json").rescaled(args.size_mm)
    lights = list(scene.lights)
    camera = dataclasses.replace(scene.camera, width=args.resolution, height=args.resolution)
    material = scene.material
    t0 = time.perf_counter()
    mesh = load_mesh(args.mesh, args.size_mm, decimate_to=args.faces, warn_open=False)
    print(f"mesh: {mesh.num_vertices} vertices, {mesh.num_faces} faces ({time.perf_counter() - t0:.1f} s to load)")

    t0 = time.perf_counter()
    ref = render_reference(mesh, material, lights, camera, shadows="shadowmap")
    print(f"reference (shadow-mapped): {time.perf_counter() - t0:.1f} s, spacing {ref.stats['spacing_mm']:.3f} mm")
    out = args.out_dir
    exposure = 1.0 / float(torch.quantile(ref.radiance[0].mean(0)[ref.mask[0, 0]], 0.99).clamp_min(1e-30))
    write_exr(out / "reference.exr", ref.radiance[0])
    write_png(out / "reference.png", tonemap(ref.radiance[0], exposure))

    built = build_icdf(mesh.with_dtype(torch.float32), material, atlas_resolution=args.atlas)
    print(f"precompute: {built.stats['t_precompute_s']:.1f} s (atlas {args.atlas}: {built.stats['t_atlas_s']:.1f} s)")
    # a warm-up frame (first-call allocations) so that the timed frames are steady
    render_icdf(mesh, material, lights, camera, samples=min(args.samples), prebuilt=built)
    rows = []
    for n in args.samples:
        res = render_icdf(mesh, material, lights, camera, samples=n, seed=args.seed, prebuilt=built)
        st = res.stats
        err = rel_rmse(res.radiance, ref.radiance, res.mask & ref.mask)
        rows.append({"samples": n, "rel_rmse": err, "t_frame_s": st["t_frame_s"],
                     "t_irradiance_s": st["t_irradiance_s"], "t_module_s": st["t_module_s"],
                     "t_image_s": st["t_image_s"]})
        exr = write_exr(out / f"icdf_N{n}.exr", res.radiance[0])
        write_png(out / f"icdf_N{n}.png", tonemap(res.radiance[0], exposure))
        print(f"N {n:5d}: rel RMSE {err:.4f}  frame {st['t_frame_s'] * 1e3:.0f} ms (irradiance atlas "
              f"{st['t_irradiance_s'] * 1e3:.0f} ms, sampling module {st['t_module_s'] * 1e3:.0f} ms, camera image "
              f"{st['t_image_s'] * 1e3:.0f} ms) -> {exr}")

    csv_path = out / "error_vs_time.csv"
    with csv_path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    png = plot(rows, out / "error_vs_time.png")
    if png is None:
        print(f"matplotlib not installed (pip install torchsss[plots]): the table is in {csv_path}, no plot")
    else:
        print(f"wrote {csv_path} and the plot {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
