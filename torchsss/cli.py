"""Command line: ``python -m torchsss <command>``.

Commands:
    profiles   evaluate the dipole profile of every Jensen 2001 preset and write EXR, PNG and JSON summaries.
    render     render a scene file (or the built-in default scene) with a method; write EXR, PNG and JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchsss.io import auto_exposure, tonemap, write_exr, write_png
from torchsss.physics import (
    chang_rp,
    dipole_rd,
    preset,
    preset_names,
    r_max,
    splat_overlap,
    splat_spacing,
    total_diffuse_reflectance,
)
from torchsss.physics.materials import PROFILES
from torchsss.registry import METHODS, render_scene
from torchsss.scene import default_scene_path, load_scene

__all__ = ["main", "profiles", "render"]


def _radial_quadrature(f, z_r: float, panels: int = 256, order: int = 16) -> torch.Tensor:
    """int_0^inf f(r) 2 pi r dr by composite Gauss-Legendre after r = z_r tan(theta) (float64)."""
    x, w = np.polynomial.legendre.leggauss(order)
    edges = np.linspace(0.0, math.pi / 2, panels + 1)
    a, b = edges[:-1, None], edges[1:, None]
    theta = torch.tensor((0.5 * (b - a) * x + 0.5 * (a + b)).ravel(), dtype=torch.float64)
    wts = torch.tensor((0.5 * (b - a) * w).ravel(), dtype=torch.float64)
    r = z_r * torch.tan(theta)
    jac = z_r / torch.cos(theta) ** 2
    return (f(r.unsqueeze(-1)) * (2 * math.pi * r * jac * wts).unsqueeze(-1)).sum(0)


def profiles(out: Path, eps: float = 0.01, width: int = 512, r_extent: float = 20.0, plot: bool = True) -> dict:
    """Evaluate every preset's profile; write ``profiles.exr``, ``profiles.png`` and ``profiles.json`` to ``out``.

    The EXR holds one 16-pixel band per preset (table order, top to bottom), column i at
    r = i * r_extent / (width - 1) mm, RGB = :math:`R_d(r)` in mm^-2. The JSON records, per preset and channel,
    the closed-form total diffuse reflectance, the numerical integral of :math:`R_d 2\\pi r`, their relative
    difference, Shah's :math:`r_{max}`, the splat spacing and overlap, and Chang's :math:`R_p` (c = 0.01).
    """
    out.mkdir(parents=True, exist_ok=True)
    names = preset_names()
    r = torch.linspace(0.0, r_extent, width, dtype=torch.float64).unsqueeze(-1)
    band = 16
    image = torch.zeros(3, band * len(names), width, dtype=torch.float64)
    records = {}
    curves = {}
    t0 = time.perf_counter()
    for row, name in enumerate(tqdm(names, desc="presets", unit="preset", disable=None)):
        p = preset(name)
        sa, ss, _ = p.tensors(torch.float64)
        rd = dipole_rd(r, sa, ss, p.eta)  # (width, 3)
        curves[name] = rd
        image[:, row * band:(row + 1) * band, :] = rd.T.unsqueeze(1)
        closed = total_diffuse_reflectance(sa, ss, p.eta)
        z_r = float((1.0 / (sa + ss)).min())
        numeric = _radial_quadrature(lambda x, sa=sa, ss=ss, eta=p.eta: dipole_rd(x, sa, ss, eta), z_r)
        records[name] = {
            "sigma_a_per_mm": list(p.sigma_a),
            "sigma_s_prime_per_mm": list(p.sigma_s_prime),
            "eta": p.eta,
            "total_diffuse_reflectance": closed.tolist(),
            "numerical_integral": numeric.tolist(),
            "integral_rel_error": ((numeric - closed).abs() / closed).tolist(),
            "r_max_mm": r_max(sa, ss, p.eta, eps).tolist(),
            "splat_spacing_mm": splat_spacing(sa, ss, p.eta, eps).tolist(),
            "splat_overlap": splat_overlap(sa, ss, p.eta, eps).tolist(),
            "splat_overlap_eq_6_17_literal": splat_overlap(sa, ss, p.eta, eps, rule="literal").tolist(),
            "chang_rp_mm_c0.01": chang_rp(sa, ss, p.eta, c=0.01).tolist(),
        }
    summary = {"eps": eps, "units": "mm, mm^-1, R_d in mm^-2", "seconds": time.perf_counter() - t0,
               "presets": records}
    write_exr(out / "profiles.exr", image.float())
    (out / "profiles.json").write_text(json.dumps(summary, indent=2))
    png = out / "profiles.png"
    if plot and _plot(curves, r.squeeze(-1), png):
        summary["png"] = "matplotlib plot"
    else:
        write_png(png, tonemap(torch.log1p(image / image[image > 0].min()).float()))
        summary["png"] = "tone-mapped EXR preview"
    return summary


def _plot(curves: dict, r: torch.Tensor, path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, axes = plt.subplots(3, 4, figsize=(14, 9), sharex=True)
    for ax, (name, rd) in zip(axes.flat, curves.items()):
        for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax.semilogy(r.numpy(), rd[:, c].clamp_min(1e-30).numpy(), color=colour)
        ax.set_title(name)
        ax.set_ylim(1e-8, None)
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("r (mm)")
    for ax in axes[:, 0]:
        ax.set_ylabel("R_d (mm$^{-2}$)")
    fig.suptitle("Jensen 2001 dipole profiles (RGB) of the 12 measured materials")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return True


def output_paths(out: Path) -> tuple[Path, Path, Path]:
    """The EXR, PNG and JSON paths of a render written to ``out`` (the three files share the stem).

    ``out`` may name the EXR (``x.exr``), the PNG (``x.png``: the EXR goes beside it as ``x.exr``) or just the stem
    (``x``); any other suffix is refused, so that no file is written under a name that says another format.

    Raises:
        ValueError: a suffix other than ``.exr`` or ``.png``.

    Examples:
        >>> [p.name for p in output_paths(Path("out/x.png"))]
        ['x.exr', 'x.png', 'x.json']
    """
    suffix = out.suffix.lower()
    if suffix not in ("", ".exr", ".png"):
        raise ValueError(f"out: expected a path ending in .exr or .png (the other image and the .json are written "
                         f"beside it with the same stem), got {str(out)!r}")
    stem = out.with_suffix("") if suffix else out
    exr = out if suffix == ".exr" else stem.with_suffix(".exr")
    png = out if suffix == ".png" else stem.with_suffix(".png")
    return exr, png, stem.with_suffix(".json")


def render(scene_arg: str, method: str, out: Path, *, options: dict, dtype: torch.dtype = torch.float32,
           resolution: tuple[int, int] | None = None, frames: int = 1, profile: str | None = None, spp: int = 1,
           exposure_ev: float = 0.0) -> dict:
    """Render ``scene_arg`` (a JSON path, or ``default`` for the shipped scene) and write EXR, PNG and JSON.

    ``out`` is the EXR or the PNG path (:func:`output_paths`); the other image (the PNG is tone-mapped) and the
    JSON (stats) go beside it with the same stem. The
    method is built once; ``frames`` > 1 renders that many frames with the light orbiting the object and the
    JSON gets every frame's time (``frame_s``), their median and the fps; the image is the first frame.
    ``profile`` renders the scene's material with another profile model (``dipole``, ``burley``, ``tabulated``).
    ``spp`` (a square) box-filters that many stratified sub-pixel samples per pixel. The PNG's exposure is automatic
    over the object's pixels (:func:`~torchsss.io.auto_exposure`) plus ``exposure_ev`` stops; the JSON records the
    multiplier (the EXR stays linear).
    """
    exr, png, json_path = output_paths(out)
    path = default_scene_path() if scene_arg == "default" and not Path(scene_arg).exists() else Path(scene_arg)
    scene = load_scene(path)
    if resolution is not None:
        scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, height=resolution[0],
                                                                      width=resolution[1]))
    if profile is not None:
        if scene.objects:
            scene = dataclasses.replace(scene, objects=tuple(
                dataclasses.replace(o, material=o.material.with_profile(profile)) for o in scene.objects))
        else:
            scene = dataclasses.replace(scene, material=scene.material.with_profile(profile))
    t0 = time.perf_counter()
    result = render_scene(scene, method, dtype=dtype, frames=frames, spp=spp, **options)
    seconds = time.perf_counter() - t0
    exr.parent.mkdir(parents=True, exist_ok=True)
    image = result.radiance[0].float()
    write_exr(exr, image)
    exposure = auto_exposure(image, result.mask[0]) * 2.0 ** float(exposure_ev)
    write_png(png, tonemap(image, exposure))
    if scene.objects:
        what = {"objects": [{"mesh": o.mesh, "size_mm": o.size_mm, "translate": list(o.translate),
                             "material": o.material.to_json()} for o in scene.objects]}
    else:
        what = {"mesh": scene.mesh, "size_mm": scene.size_mm, "material": scene.material.to_json()}
    st = result.stats
    summary = {"scene": str(path), "method": method, **what, "width": scene.camera.width,
               "height": scene.camera.height, "dtype": str(dtype).replace("torch.", ""), "seconds": seconds,
               "setup_s": st.get("setup_s"), "frame_s": st.get("frame_s"), "frame_median_s": st.get("frame_median_s"),
               "fps": st.get("fps"), "frames": frames, "knobs": _jsonable(st.get("knobs", {})),
               "options": {k: v for k, v in options.items() if k != "progress"},
               "covered_pixels": int(result.mask.sum()), "max_radiance": float(image.max()),
               "mean_radiance_covered": [float(v) for v in (image * result.mask[0]).flatten(1).sum(1)
                                         / max(1, int(result.mask.sum()))],
               "spp": spp, "exposure": exposure, "exposure_ev": exposure_ev,
               "stats": _jsonable(result.stats), "exr": str(exr), "png": str(png), "json": str(json_path)}
    json_path.write_text(json.dumps(summary, indent=2))
    return summary


def _jsonable(value: object) -> object:
    """Tuples, tensors and nested containers as JSON values."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, torch.Tensor):
        return value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 256x256, got {text!r}") from err
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"expected positive sizes, got {text!r}")
    return h, w


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m torchsss`` and the ``torchsss`` console script."""
    parser = argparse.ArgumentParser(prog="torchsss", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_prof = sub.add_parser("profiles", help="dipole profiles of all presets -> EXR, PNG, JSON")
    p_prof.add_argument("--out", type=Path, default=Path("out"), help="output directory (default: out)")
    p_prof.add_argument("--eps", type=float, default=0.01, help="truncation/sampling tolerance (default 0.01)")
    p_prof.add_argument("--no-plot", action="store_true", help="skip matplotlib; write a tone-mapped preview")
    p_ren = sub.add_parser("render", help="render a scene file with a method -> EXR, PNG, JSON")
    p_ren.add_argument("scene", help="scene JSON file, or 'default' for the built-in scene (spot, back-lit)")
    p_ren.add_argument("--method", default="reference", choices=sorted(METHODS), help="rendering method")
    p_ren.add_argument("--out", type=Path, default=Path("out/render.exr"),
                       help="output EXR or PNG (the other image and the JSON beside it)")
    p_ren.add_argument("--resolution", type=_resolution, default=None, help="override the camera, e.g. 128x128")
    p_ren.add_argument("--float64", action="store_true", help="integrate in float64")
    p_ren.add_argument("--spacing", type=float, default=None, help="reference: surface sample spacing in mm")
    p_ren.add_argument("--eps", type=float, default=0.01,
                       help="reference: tolerance of the default spacing; splat: the splat budget's tolerance")
    p_ren.add_argument("--shadows", default="raytrace", choices=["raytrace", "shadowmap", "none"],
                       help="reference: visibility of the lights")
    p_ren.add_argument("--atlas-resolution", type=int, default=512,
                       help="lensch/icdf/hybrid: texture atlas size (texels)")
    p_ren.add_argument("--kernel-size", type=int, default=None,
                       help="lensch: local kernel size k (odd); default: planned from the vertex spacing (5-11)")
    p_ren.add_argument("--threshold", type=float, default=1e-5,
                       help="lensch: throughput threshold relative to the largest entry")
    p_ren.add_argument("--blend", choices=["auto", "on", "off"], default="auto",
                       help="lensch: the local/global blending of §5.4 (auto: planned from the vertex spacing)")
    p_ren.add_argument("--no-blend", action="store_true", help="lensch: same as --blend off")
    p_ren.add_argument("--samples", type=int, default=4096,
                       help="icdf/hybrid: importance samples N per frame (default 4096)")
    p_ren.add_argument("--seed", type=int, default=0, help="icdf/hybrid: seed of the scrambled Sobol uniforms")
    p_ren.add_argument("--caustic-grid", type=int, default=None,
                       help="caustics: light-view grid size (default: the scene's caustics.grid)")
    p_ren.add_argument("--split-c", type=float, default=0.1,
                       help="hybrid: bound c of the split radius R_p (default 0.1; benchmarks/results/chang.md)")
    p_ren.add_argument("--specular", action="store_true",
                       help="add the boundary's GGX specular highlights (off: subsurface transport alone)")
    p_ren.add_argument("--roughness", type=float, default=0.3, help="GGX alpha of --specular (default 0.3)")
    p_ren.add_argument("--spp", type=int, default=1,
                       help="samples per pixel, a square (4 = 2x2 stratified sub-pixel grid, box filter; default 1)")
    p_ren.add_argument("--exposure", type=float, default=0.0,
                       help="PNG exposure compensation in stops on top of the automatic exposure over the object "
                            "(default 0; the EXR is linear)")
    p_ren.add_argument("--frames", type=int, default=1,
                       help="render N frames from one setup, the light orbiting the object; report the median frame "
                            "time and fps (default 1)")
    p_ren.add_argument("--profile", choices=list(PROFILES), default=None,
                       help="render the scene's material with this profile model (default: the scene's, dipole)")
    p_ren.add_argument("--no-progress", action="store_true", help="hide progress bars")
    args = parser.parse_args(argv)
    if args.command == "render":
        if not 0 < args.eps < 1:
            parser.error(f"--eps: expected a value in (0, 1), got {args.eps}")
        options = {"progress": not args.no_progress}
        if args.specular:
            options.update(specular=True, roughness=args.roughness)
        if args.frames < 1:
            parser.error(f"--frames: expected an int >= 1, got {args.frames}")
        if args.method == "reference":
            options.update(eps=args.eps, shadows=args.shadows)
            if args.spacing is not None:
                options["spacing_mm"] = args.spacing
        elif args.method == "lensch":
            options.update(atlas_resolution=args.atlas_resolution, kernel_size=args.kernel_size,
                           threshold=args.threshold,
                           blend=False if args.no_blend else {"auto": None, "on": True, "off": False}[args.blend])
        elif args.method == "splat":
            options["eps"] = args.eps
        elif args.method == "caustics":
            if args.specular:
                parser.exit(2, "torchsss render: error: specular: expected off for --method caustics (the refractor "
                               "shows Fresnel reflection of a uniform environment instead), got on\n")
            options = {"progress": options["progress"]}
            if args.caustic_grid is not None:
                options["grid"] = args.caustic_grid
        elif args.method in ("icdf", "hybrid"):
            options.update(atlas_resolution=args.atlas_resolution, samples=args.samples, seed=args.seed)
            if args.method == "hybrid":
                options["c"] = args.split_c
        try:
            summary = render(args.scene, args.method, args.out, options=options,
                             dtype=torch.float64 if args.float64 else torch.float32, resolution=args.resolution,
                             frames=args.frames, profile=args.profile, spp=args.spp, exposure_ev=args.exposure)
        except (ValueError, TypeError) as err:
            parser.exit(2, f"torchsss render: error: {err}\n")
        st = summary["stats"]
        print(f"wrote {summary['exr']}, {summary['png']}, {summary['json']}")
        head = (f"{summary['method']}: {summary['width']}x{summary['height']}, "
                f"{summary['covered_pixels']} covered pixels")
        if "spacing_mm" in st:
            head += f", {st['samples']} surface samples ({st['spacing_mm']:.3f} mm)"
        elif "samples" in st:
            head += f", {st['samples']} importance samples"
        if "nnz" in st:
            head += f", atlas {st['atlas_resolution']}², {st['nnz']} throughput entries"
        head += f", setup {summary['setup_s']:.2f} s, frame {1e3 * summary['frame_median_s']:.0f} ms"
        if args.frames > 1:
            head += f" (median of {args.frames}, {summary['fps']:.2f} fps)"
        print(f"{head}, {summary['seconds']:.1f} s in all")
    if args.command == "profiles":
        if not 0 < args.eps < 1:
            parser.error(f"--eps: expected a value in (0, 1), got {args.eps}")
        summary = profiles(args.out, eps=args.eps, plot=not args.no_plot)
        worst = max(max(v["integral_rel_error"]) for v in summary["presets"].values())
        print(f"wrote {args.out / 'profiles.exr'}, {args.out / 'profiles.png'} ({summary['png']}), "
              f"{args.out / 'profiles.json'}")
        print(f"{'preset':<11} {'R_total (r, g, b)':<26} {'r_max mm (eps=' + str(args.eps) + ')':<26}")
        for name, rec in summary["presets"].items():
            rt = ", ".join(f"{v:.4f}" for v in rec["total_diffuse_reflectance"])
            rm = ", ".join(f"{v:6.2f}" for v in rec["r_max_mm"])
            print(f"{name:<11} {rt:<26} {rm:<26}")
        print(f"max relative error, quadrature vs closed-form R_total: {worst:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
