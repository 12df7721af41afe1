"""Command line: ``python -m torchsss <command>``.

Commands:
    profiles   evaluate the dipole profile of every Jensen 2001 preset and write EXR, PNG and JSON summaries.
    render     render a scene file (or the built-in default scene) with a method; write EXR, PNG and JSON.
    plan       print the planner's choice (method, knobs, modelling, predicted error and time) for a tolerance.
    trade      measure a scene's speed/accuracy trade: every method over a knob sweep; write JSON and a plot.
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

from torchsss._checks import check_device
from torchsss._json import jsonable
from torchsss.geometry.lensch import THROUGHPUT_THRESHOLD
from torchsss.io import auto_exposure, key_exposure, tonemap, write_exr, write_png
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
from torchsss.plan import Plan, plan, plan_method
from torchsss.registry import METHODS, render_scene
from torchsss.scene import Scene, default_scene_path, load_scene
from torchsss.trade import trade, write_trade

__all__ = ["main", "plan_command", "profiles", "render", "trade_command"]


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
           resolution: tuple[int, int] | None = None, frames: int = 1, profile: str | None = None,
           spp: int | None = None, subpixel: str | None = None, exposure_ev: float = 0.0, tolerance: float = 0.02,
           explicit: dict | None = None, save_gbuffers: Path | None = None, device: str = "cpu") -> dict:
    """Render ``scene_arg`` (a JSON path, or ``default`` for the shipped scene) and write EXR, PNG and JSON.

    ``out`` is the EXR or the PNG path (:func:`output_paths`); the other image (the PNG is tone-mapped) and the
    JSON (stats) go beside it with the same stem. The
    method is built once; ``frames`` > 1 renders that many frames with the light orbiting the object and the
    JSON gets every frame's time (``frame_s``), their median and the fps; the image is the first frame.
    ``profile`` renders the scene's material with another profile model (``dipole``, ``burley``, ``tabulated``).
    ``spp`` (a square) box-filters that many stratified sub-pixel samples per pixel, rendered as ``subpixel`` says
    (:meth:`~torchsss.pipelines.Renderer.render`). By default (None) the image is the pixel integral:
    :data:`DEFAULT_SPP` sub-pixels with the radiosity upsampled edge-aware (``"upsample"``, about the cost of one
    sub-pixel G-buffer) for a single translucent object without ``specular``; one sample per pixel where upsampling
    does not apply (caustics, several objects, specular, ``save_gbuffers``: pass ``spp`` with ``subpixel="exact"``
    to integrate those). The PNG's exposure is automatic
    over the object's pixels (:func:`~torchsss.io.auto_exposure`) plus ``exposure_ev`` stops; the JSON records the
    multiplier (the EXR stays linear). Caustics scenes use :func:`~torchsss.io.key_exposure` and the extended tone
    curve instead (the floor's median at 0.5, the brightest caustic pixel at white), so neither is lost.

    ``method`` splat, icdf, hybrid or lensch (:data:`PLANNED_METHODS`) gets the planner's knobs for that method
    alone at ``tolerance`` (:func:`~torchsss.plan.plan_method`; the JSON's ``"method_plan"``), with ``explicit``
    flags on top. ``method="auto"`` plans the render (:func:`torchsss.plan.plan` with ``tolerance`` and
    ``frames``; a caustics scene renders with ``caustics``): the plan's method, knobs and mesh decimation, with
    ``explicit`` knob flags (:data:`KNOB_FLAGS` dests) on top; the JSON gets the plan (``"plan"``).

    ``save_gbuffers`` (splat and lensch): also write the first frame's G-buffers and its exported ONNX frame graph to
    that ``.npz`` (:func:`torchsss.export.frames.save_scene_gbuffers`; ``export/ort_render.py`` renders it).

    ``device`` (``"cpu"`` or ``"cuda"``; :func:`~torchsss._checks.check_device`): where the method is built and the
    frames render, for a single-object scene. The planner's times are the CPU's (its calibration); on a GPU the
    ranking of methods differs (the README's GPU table).
    """
    exr, png, json_path = output_paths(out)
    dev = check_device(device)
    path, scene = _scene(scene_arg, resolution)
    if dev.type != "cpu" and (scene.objects or save_gbuffers is not None):
        raise ValueError(f"device: expected 'cpu' for a scene of several objects or with --save-gbuffers, got "
                         f"{device!r}")
    upsampling = (not scene.objects and scene.caustics is None and method != "caustics" and save_gbuffers is None
                  and not options.get("specular"))
    if subpixel is None:
        subpixel = "upsample" if upsampling else "exact"
    if spp is None:
        spp = DEFAULT_SPP if upsampling or subpixel == "upsample" else 1
    if save_gbuffers is not None:
        from torchsss.export.frames import check_gbuffer_request

        check_gbuffer_request(method, spp, scene)
    if profile is not None:
        if scene.objects:
            scene = dataclasses.replace(scene, objects=tuple(
                dataclasses.replace(o, material=o.material.with_profile(profile)) for o in scene.objects))
        else:
            scene = dataclasses.replace(scene, material=scene.material.with_profile(profile))
    t0 = time.perf_counter()
    planned = method_note = None
    if method == "auto":
        explicit = dict(explicit or {})
        if scene.caustics is not None:
            method = "caustics"
            options = {**options, **method_knobs(method, explicit, {})}
        else:
            planned = plan(scene, tolerance, frames, methods=_methods_for(explicit))
            scene = planned.scene(scene)
            method = planned.method
            options = {**options, **method_knobs(method, explicit, planned.knobs)}
    elif method in PLANNED_METHODS:
        # the method's default knobs: the planner's choice for it alone (given flags override them)
        explicit = dict(explicit or {})
        if scene.objects or scene.caustics is not None:
            method_note = {"knobs": None, "note": "multi-object scene: the method's fixed defaults"}
            options = {**options, **method_knobs(method, explicit)}
        else:
            knobs, decimate, note = plan_method(scene, method, tolerance, frames)
            if decimate:
                scene = dataclasses.replace(scene, decimate=int(decimate))
            method_note = {"knobs": knobs, "note": note}
            options = {**options, **method_knobs(method, explicit, knobs)}
    result = render_scene(scene, method, dtype=dtype, frames=frames, spp=spp, subpixel=subpixel, device=dev,
                          **options)
    result = dataclasses.replace(result, radiance=result.radiance.detach().cpu(),  # a CUDA render: write from the host
                                 radiosity=result.radiosity.detach().cpu(), mask=result.mask.cpu())
    seconds = time.perf_counter() - t0
    exr.parent.mkdir(parents=True, exist_ok=True)
    image = result.radiance[0].float()
    write_exr(exr, image)
    white = None
    if method == "caustics":  # high dynamic range: floor at the key, the caustic up to the white point
        exposure, white = key_exposure(image, result.mask[0])
        exposure *= 2.0 ** float(exposure_ev)
    else:
        exposure = auto_exposure(image, result.mask[0]) * 2.0 ** float(exposure_ev)
    write_png(png, tonemap(image, exposure, white=white))
    if scene.objects:
        what = {"objects": [{"mesh": o.mesh, "size_mm": o.size_mm, "translate": list(o.translate),
                             "material": o.material.to_json()} for o in scene.objects]}
    else:
        what = {"mesh": scene.mesh, "size_mm": scene.size_mm, "material": scene.material.to_json()}
    st = result.stats
    summary = {"scene": str(path), "method": method, **what, "width": scene.camera.width,
               "height": scene.camera.height, "dtype": str(dtype).replace("torch.", ""), "device": str(dev),
               "seconds": seconds,
               "setup_s": st.get("setup_s"), "frame_s": st.get("frame_s"), "frame_median_s": st.get("frame_median_s"),
               "fps": st.get("fps"), "frames": frames, "knobs": jsonable(st.get("knobs", {})),
               "options": {k: v for k, v in options.items() if k != "progress"},
               "covered_pixels": int(result.mask.sum()), "max_radiance": float(image.max()),
               "mean_radiance_covered": [float(v) for v in (image * result.mask[0]).flatten(1).sum(1)
                                         / max(1, int(result.mask.sum()))],
               "spp": spp, "subpixel": subpixel if spp > 1 else "none", "exposure": exposure,
               "exposure_ev": exposure_ev, "white": white,
               "stats": jsonable(result.stats), "exr": str(exr), "png": str(png), "json": str(json_path)}
    if method_note is not None:
        summary["method_plan"] = jsonable(method_note)
    if planned is not None:
        p = planned.to_json()
        p["candidates"] = p["candidates"][:10]
        summary["plan"] = jsonable(p)
    if save_gbuffers is not None:
        from torchsss.export.frames import save_scene_gbuffers

        summary["gbuffers"] = str(save_scene_gbuffers(save_gbuffers, scene, method, dtype=dtype, frames=frames,
                                                      spp=spp, options=options, radiance=result.radiance))
    json_path.write_text(json.dumps(summary, indent=2))
    return summary


def _scene(scene_arg: str, resolution: tuple[int, int] | None) -> tuple[Path, Scene]:
    """The scene file (``default``: the shipped scene) and its scene, with the camera resized if asked."""
    path = default_scene_path() if scene_arg == "default" and not Path(scene_arg).exists() else Path(scene_arg)
    scene = load_scene(path)
    if resolution is not None:
        scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, height=resolution[0],
                                                                      width=resolution[1]))
    return path, scene


def plan_command(scene_arg: str, *, tolerance: float, frames: int, resolution: tuple[int, int] | None = None,
                 json_out: Path | None = None) -> Plan:
    """``python -m torchsss plan``: plan the scene's render (no rendering); optionally write the plan's JSON."""
    _, scene = _scene(scene_arg, resolution)
    p = plan(scene, tolerance, frames)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(jsonable(p.to_json()), indent=2))
    return p


def trade_command(scene_arg: str, out: Path, *, quick: bool = False, resolution: tuple[int, int] | None = None,
                  methods: Sequence[str] | None = None, frames: int | None = None, progress: bool = True) -> dict:
    """``python -m torchsss trade``: measure the scene's trade (:func:`torchsss.trade.trade`) into ``out``."""
    _, scene = _scene(scene_arg, resolution)
    result = trade(scene, methods=methods, quick=quick, frames=frames, progress=progress)
    js, png = write_trade(result, out)
    result["json"], result["png"] = str(js), None if png is None else str(png)
    return result


#: Methods whose default knobs are planned from the scene (:func:`torchsss.plan.plan_method`) at ``--tolerance``.
PLANNED_METHODS = ("splat", "icdf", "hybrid", "lensch")
#: the render command's default samples per pixel (4 x 4, upsampled): within 0.6% of the pixel integral on the
#: back-lit 15 mm torus and 30 mm bunny where one sample per pixel is 3.4% and 5.0% off (tests/test_subpixel.py)
DEFAULT_SPP = 16

#: Per-method knob flags of ``render``: argparse dest -> (knob, the methods that take it). An unset flag leaves the
#: knob to the plan or to the renderer's own default (``Renderer.defaults``, the one home of every default).
KNOB_FLAGS: dict[str, tuple[str, frozenset[str]]] = {
    "spacing": ("spacing_mm", frozenset({"reference"})),
    "shadows": ("shadows", frozenset({"reference"})),
    "eps": ("eps", frozenset({"reference", "splat"})),
    "atlas_resolution": ("atlas_resolution", frozenset({"lensch", "icdf", "hybrid"})),
    "kernel_size": ("kernel_size", frozenset({"lensch"})),
    "threshold": ("threshold", frozenset({"lensch"})),
    "blend": ("blend", frozenset({"lensch"})),
    "samples": ("samples", frozenset({"icdf", "hybrid"})),
    "seed": ("seed", frozenset({"icdf", "hybrid"})),
    "split_c": ("c", frozenset({"hybrid"})),
    "caustic_grid": ("grid", frozenset({"caustics"})),
}


def _knob_arguments(p: argparse.ArgumentParser) -> None:
    """The per-method knob flags (:data:`KNOB_FLAGS`); unset flags are None (the method's or the plan's value)."""
    p.add_argument("--spacing", type=float, default=None, help="reference: surface sample spacing in mm")
    p.add_argument("--eps", type=float, default=None,
                   help="reference: tolerance of the default spacing; splat: the splat budget's tolerance (0.01)")
    p.add_argument("--shadows", default=None, choices=["raytrace", "shadowmap", "none"],
                   help="reference: visibility of the lights (default raytrace)")
    p.add_argument("--atlas-resolution", type=int, default=None,
                   help="lensch/icdf/hybrid: texture atlas size (texels; default 512)")
    p.add_argument("--kernel-size", type=int, default=None,
                   help="lensch: local kernel size k (odd); default: planned from the vertex spacing (5-11)")
    p.add_argument("--threshold", type=float, default=None,
                   help="lensch: throughput threshold relative to the largest self throughput (default "
                        f"{THROUGHPUT_THRESHOLD:g})")
    p.add_argument("--blend", choices=["auto", "on", "off"], default=None,
                   help="lensch: the local/global blending of §5.4 (auto: planned from the vertex spacing)")
    p.add_argument("--no-blend", action="store_true", help="lensch: same as --blend off")
    p.add_argument("--samples", type=int, default=None,
                   help="icdf/hybrid: importance samples N per frame (default 4096)")
    p.add_argument("--seed", type=int, default=None, help="icdf/hybrid: seed of the scrambled Sobol uniforms (0)")
    p.add_argument("--caustic-grid", type=int, default=None,
                   help="caustics: light-view grid size (default: the scene's caustics.grid)")
    p.add_argument("--split-c", type=float, default=None,
                   help="hybrid: bound c of the split radius R_p (default 0.1; benchmarks/results/chang.md)")


def _explicit_knobs(args: argparse.Namespace) -> dict[str, object]:
    """The knob flags the user gave, by argparse dest (validated)."""
    if args.no_blend:
        args.blend = "off"
    explicit = {dest: getattr(args, dest) for dest in KNOB_FLAGS if getattr(args, dest) is not None}
    if "blend" in explicit:
        explicit["blend"] = {"auto": None, "on": True, "off": False}[explicit["blend"]]
    if "eps" in explicit and not 0 < explicit["eps"] < 1:
        raise ValueError(f"eps: expected a value in (0, 1), got {explicit['eps']}")
    return explicit


def method_knobs(method: str, explicit: dict[str, object], planned: dict | None = None) -> dict:
    """``method``'s knobs: the plan's (or none: the renderer's defaults), overridden by the flags the user gave.

    Raises:
        ValueError: a flag that ``method`` does not take (naming the methods that do).
    """
    for dest in explicit:
        methods = KNOB_FLAGS[dest][1]
        if method not in methods:
            raise ValueError(f"--{dest.replace('_', '-')}: applies to {', '.join(sorted(methods))}, got --method "
                             f"{method}")
    knobs = dict(planned) if planned is not None else {}
    knobs.update({KNOB_FLAGS[dest][0]: v for dest, v in explicit.items()})
    return knobs


def _methods_for(explicit: dict[str, object]) -> list[str] | None:
    """The methods that take every given flag (None: no flag given)."""
    if not explicit:
        return None
    common = frozenset.intersection(*(KNOB_FLAGS[d][1] for d in explicit))
    if not common:
        raise ValueError(f"knobs: expected flags that one method takes together, got "
                         f"{', '.join('--' + d.replace('_', '-') for d in explicit)}")
    return sorted(common)



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
    p_ren.add_argument("--method", default="auto", choices=["auto", *sorted(METHODS)],
                       help="rendering method (default auto: the planner's choice for --tolerance)")
    p_ren.add_argument("--tolerance", type=float, default=None,
                       help="auto, splat, icdf, hybrid, lensch: relative RMSE against the reference that the "
                            "planned knobs meet at least cost (default 0.02)")
    p_ren.add_argument("--out", type=Path, default=Path("out/render.exr"),
                       help="output EXR or PNG (the other image and the JSON beside it)")
    p_ren.add_argument("--resolution", type=_resolution, default=None, help="override the camera, e.g. 128x128")
    p_ren.add_argument("--float64", action="store_true", help="integrate in float64")
    p_ren.add_argument("--device", default="cpu",
                       help="torch device of the build and the frames, e.g. cuda (default cpu; single-object scenes; "
                            "the planner's times are the CPU's)")
    _knob_arguments(p_ren)
    p_ren.add_argument("--specular", action="store_true",
                       help="add the boundary's GGX specular highlights (off: subsurface transport alone)")
    p_ren.add_argument("--roughness", type=float, default=0.3, help="GGX alpha of --specular (default 0.3)")
    p_ren.add_argument("--spp", type=int, default=None,
                       help=f"samples per pixel, a square (4 = 2x2 stratified sub-pixel grid, box filter; default "
                            f"{DEFAULT_SPP}, the pixel integral, for one translucent object; else 1)")
    p_ren.add_argument("--subpixel", choices=("upsample", "exact"), default=None,
                       help="how sub-pixels are rendered: 'upsample' (default where it applies: the radiosity once per "
                            "pixel, upsampled edge-aware with each sub-pixel's coverage and exit cosine) or 'exact' "
                            "(the method on the finer grid, up to spp times the cost)")
    p_ren.add_argument("--exposure", type=float, default=0.0,
                       help="PNG exposure compensation in stops on top of the automatic exposure over the object "
                            "(default 0; the EXR is linear)")
    p_ren.add_argument("--frames", type=int, default=1,
                       help="render N frames from one setup, the light orbiting the object; report the median frame "
                            "time and fps (default 1)")
    p_ren.add_argument("--profile", choices=list(PROFILES), default=None,
                       help="render the scene's material with this profile model (default: the scene's, dipole)")
    p_ren.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p_ren.add_argument("--save-gbuffers", type=Path, default=None, metavar="GBUFFERS.npz",
                       help="splat/lensch: also save the first frame's G-buffers and its ONNX frame graph "
                            "(render them without torch: python export/ort_render.py GBUFFERS.npz)")
    p_plan = sub.add_parser("plan", help="print the planned method and knobs for a tolerance (no rendering)")
    p_plan.add_argument("scene", help="scene JSON file, or 'default'")
    p_plan.add_argument("--tolerance", type=float, default=0.02, help="relative RMSE to meet (default 0.02)")
    p_plan.add_argument("--frames", type=int, default=1, help="frames that follow one setup (default 1)")
    p_plan.add_argument("--resolution", type=_resolution, default=None, help="override the camera, e.g. 256x256")
    p_plan.add_argument("--json", type=Path, default=None, help="also write the plan (all candidates) as JSON")
    p_trade = sub.add_parser("trade", help="measure the speed/accuracy trade of a scene -> trade.json, trade.png")
    p_trade.add_argument("scene", help="scene JSON file, or 'default'")
    p_trade.add_argument("--out", type=Path, default=Path("out/trade"), help="output directory (default out/trade)")
    p_trade.add_argument("--quick", action="store_true", help="a small sweep (about a minute at 64x64)")
    p_trade.add_argument("--resolution", type=_resolution, default=None, help="override the camera, e.g. 64x64")
    p_trade.add_argument("--methods", nargs="+", default=None, help="methods to sweep (default: all applicable)")
    p_trade.add_argument("--frames", type=int, default=None, help="frames per configuration (default 3, quick 2)")
    p_trade.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    args = parser.parse_args(argv)
    if args.command == "plan":
        if not 0 < args.tolerance < 1:
            parser.error(f"--tolerance: expected a value in (0, 1), got {args.tolerance}")
        if args.frames < 1:
            parser.error(f"--frames: expected an int >= 1, got {args.frames}")
        try:
            p = plan_command(args.scene, tolerance=args.tolerance, frames=args.frames, resolution=args.resolution,
                             json_out=args.json)
        except (ValueError, TypeError) as err:
            parser.exit(2, f"torchsss plan: error: {err}\n")
        print(p)
    if args.command == "trade":
        try:
            result = trade_command(args.scene, args.out, quick=args.quick, resolution=args.resolution,
                                   methods=args.methods, frames=args.frames, progress=not args.no_progress)
        except (ValueError, TypeError) as err:
            parser.exit(2, f"torchsss trade: error: {err}\n")
        print(f"wrote {result['json']}" + (f", {result['png']}" if result["png"] else " (no matplotlib: no plot)"))
        ref = result["reference"]
        print(f"reference: setup {ref['setup_s']:.2f} s, frame {ref['frame_s']:.2f} s")
        print(f"{'method':<10} {'knobs':<40} {'setup s':>8} {'frame s':>8} {'rel RMSE':>9} {'max err':>8} {'MiB':>6}")
        for i, row in enumerate(result["rows"]):
            if "refused" in row:
                print(f"{row['method']:<10} {json.dumps(row['knobs']):<40} refused: {row['refused']}")
                continue
            mark = " *" if i in result["pareto"] else ""
            print(f"{row['method']:<10} {json.dumps(row['knobs']):<40} {row['setup_s']:8.2f} {row['frame_s']:8.3f} "
                  f"{row['rel_rmse']:9.2%} {row['max_error']:8.2%} {row['peak_mib']:6.0f}{mark}")
        print("* on the Pareto front (error vs frame time)")
    if args.command == "render":
        if args.frames < 1:
            parser.error(f"--frames: expected an int >= 1, got {args.frames}")
        if args.tolerance is not None and not 0 < args.tolerance < 1:
            parser.error(f"--tolerance: expected a value in (0, 1), got {args.tolerance}")
        if args.tolerance is not None and args.method not in ("auto", *PLANNED_METHODS):
            parser.error(f"--tolerance: applies to --method auto and to the planned methods "
                         f"({', '.join(PLANNED_METHODS)}), got --method {args.method}")
        try:
            explicit = _explicit_knobs(args)
            options = {"progress": not args.no_progress}
            if args.specular:
                if args.method == "caustics":
                    raise ValueError("specular: expected off for --method caustics (the refractor shows Fresnel "
                                     "reflection of a uniform environment instead), got on")
                options.update(specular=True, roughness=args.roughness)
            if args.method not in ("auto", *PLANNED_METHODS):
                options.update(method_knobs(args.method, explicit))
            summary = render(args.scene, args.method, args.out, options=options,
                             dtype=torch.float64 if args.float64 else torch.float32, resolution=args.resolution,
                             frames=args.frames, profile=args.profile, spp=args.spp, subpixel=args.subpixel,
                             exposure_ev=args.exposure,
                             tolerance=0.02 if args.tolerance is None else args.tolerance, explicit=explicit,
                             save_gbuffers=args.save_gbuffers, device=args.device)
        except (ValueError, TypeError) as err:
            parser.exit(2, f"torchsss render: error: {err}\n")
        st = summary["stats"]
        print(f"wrote {summary['exr']}, {summary['png']}, {summary['json']}"
              + (f", {summary['gbuffers']}" if "gbuffers" in summary else ""))
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
        if "plan" in summary:
            pl = summary["plan"]
            print(f"planned for {pl['tolerance']:.2%} over {pl['frames']} frame(s): predicted error "
                  f"{pl['predicted_error']:.2%}; {pl['reasons'].get('method', '')}")
        note = (summary.get("method_plan") or {}).get("note") or ""
        if note.startswith("no configuration predicted"):
            # the method cannot be planned within the tolerance on this scene: say so, not only in the JSON
            print(f"warning: {summary['method']}: {note}; --method auto plans a method that meets it",
                  file=sys.stderr)
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
