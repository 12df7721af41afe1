"""The README's gallery: every method on the default scene (and the caustics scene), with its error and time.

Each translucent method is built with the knobs ``python -m torchsss render default --method M`` uses by default
(the planner's choice for that method alone at ``--tolerance``, :func:`torchsss.plan.plan_method`), renders one
frame at the render command's default pixel integration (``--spp``, :data:`torchsss.cli.DEFAULT_SPP` sub-pixels,
upsampled) and is compared with the reference (its default knobs, the full mesh, the same sub-pixels) over the
pixels both cover. All images
share the reference's exposure, so brightness differences are real. Writes ``OUT/<method>.png``, an error image
``OUT/<method>_error.png`` (|L - L_ref| / max L_ref, x10, red), ``OUT/caustics.png`` and ``OUT/gallery.md`` (the
table the README embeds).

Usage::

    python examples/gallery.py --out docs/gallery            # 128x128 (about 10-20 minutes on 2 cores)
    python examples/gallery.py --out /tmp/g --resolution 64 --methods icdf
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import torch

from torchsss.cli import DEFAULT_SPP
from torchsss.cli import render as cli_render
from torchsss.io import auto_exposure, tonemap, write_png
from torchsss.pipelines.build import build
from torchsss.plan import plan_method
from torchsss.scene import default_scene_path, load_scene
from torchsss.trade import image_error

METHODS = ("splat", "icdf", "hybrid", "lensch")
CAUSTICS = Path(__file__).resolve().parent / "scenes" / "glass_sphere.json"


def _render(method: str, scene, knobs: dict, spp: int):
    mesh = scene.load_mesh()
    t0 = time.perf_counter()
    renderer = build(method, mesh, scene.material, **knobs)
    setup = time.perf_counter() - t0
    t1 = time.perf_counter()
    result = renderer.render(list(scene.lights), scene.camera, spp=spp, subpixel="upsample")
    return result, setup, time.perf_counter() - t1


def _keep_other_rows(path: Path, rows: list[str]) -> list[str]:
    """The table's rows: this run's, and the rows of methods it did not render kept from an existing ``path``.

    A run of some methods (``--methods icdf``) must not drop the others' rows; rows stay in the order of
    :data:`METHODS` (reference first, caustics last).
    """
    def key(row: str) -> str:
        return row.split("|")[1].strip().split(" ")[0]

    mine = {key(r): r for r in rows}
    if path.exists():
        for line in path.read_text().splitlines():
            if line.startswith("| ") and not line.startswith("| method") and key(line) not in mine:
                mine[key(line)] = line
    order = ["reference", *METHODS, "caustics"]
    return [mine[k] for k in order if k in mine] + [r for k, r in mine.items() if k not in order]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/gallery"))
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--tolerance", type=float, default=0.02)
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS)
    parser.add_argument("--no-caustics", action="store_true")
    parser.add_argument("--spp", type=int, default=DEFAULT_SPP, help=f"sub-pixels, upsampled (default {DEFAULT_SPP})")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(default_scene_path())
    scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=args.resolution,
                                                                  height=args.resolution))
    ref, ref_setup, ref_frame = _render("reference", scene, {}, args.spp)
    image = ref.radiance[0].detach().float()
    exposure = auto_exposure(image, ref.mask[0])
    write_png(args.out / "reference.png", tonemap(image, exposure))
    peak = float(image.max())
    rows = [f"| reference (truth) | eps 0.01, full mesh | {ref_setup:.1f} s | {ref_frame:.2f} s | - | "
            f"![reference](reference.png) | |"]
    print(rows[-1], flush=True)
    for method in args.methods:
        knobs, _, note = plan_method(scene, method, args.tolerance)
        out, setup, frame = _render(method, scene, knobs, args.spp)
        err = image_error(out, ref)
        img = out.radiance[0].detach().float()
        write_png(args.out / f"{method}.png", tonemap(img, exposure))
        diff = ((img - image).abs().amax(0) / peak * 10.0).clamp(0, 1)
        write_png(args.out / f"{method}_error.png", torch.stack([diff, torch.zeros_like(diff), torch.zeros_like(diff)]))
        shown = ", ".join(f"{k} {v}" for k, v in sorted(knobs.items()))
        rows.append(f"| {method} | {shown} | {setup:.1f} s | {frame:.2f} s | {err['rel_rmse']:.2%} | "
                    f"![{method}]({method}.png) | ![{method} error]({method}_error.png) |")
        print(rows[-1], f"({note})", flush=True)
    if not args.no_caustics:
        summary = cli_render(str(CAUSTICS), "caustics", args.out / "caustics.png", options={"progress": False},
                             resolution=(args.resolution, args.resolution))
        frame = summary["stats"].get("frame_s", 0.0)
        frame = frame[0] if isinstance(frame, list) else frame
        setup = float(summary.get("setup_s", summary["stats"].get("setup_s", 0.0)))
        rows.append(f"| caustics (glass sphere) | the scene's | {setup:.1f} s | "
                    f"{float(frame):.2f} s | benchmarks/results/caustics.md | ![caustics](caustics.png) | |")
        print(rows[-1], flush=True)
    rows = _keep_other_rows(args.out / "gallery.md", rows)
    table = ["| method | knobs (planned at the tolerance) | setup | frame | rel. RMSE vs reference | image | "
             "error x10 |", "|---|---|---:|---:|---:|---|---|", *rows]
    head = (f"Default scene at {args.resolution}x{args.resolution}, {args.spp} sub-pixels per pixel (upsampled), "
            f"tolerance {args.tolerance:.0%}, one frame each (2-core CPU; `python examples/gallery.py --out "
            f"{args.out}`).")
    (args.out / "gallery.md").write_text(head + "\n\n" + "\n".join(table) + "\n")
    print(f"wrote {args.out / 'gallery.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
