"""Caustics mapping (Shah 2007, ch. 5) benchmark: a glass sphere over a plane against an exact photon tracer.

Scene: a sphere of radius R = 10 mm centred 16 mm over the floor z = 0 (just past the paraxial focus of n = 1.5),
a directional light straight down (irradiance 1), an orthographic light view of half-width 15 mm, caustic map
128 x 128 (and 256 x 256 at grid 256, the default knobs, in the full run), beam splats (the default) and Gaussian
splats of sigma 1 texel, ``mode="double"``, ``back="search"``, no Fresnel, no absorption, float64.

Two sources of the light-view G-buffers, one row each:

- ``mesh``: built by :func:`torchsss.pipelines.caustics.caustic_gbuffers` from a procedural icosphere
  (``subdivisions=6``, 81920 faces; 5 with ``--quick``) over a ``plane`` receiver — the whole pipeline, with the
  default Max vertex normals; at the default knobs (grid = map = 256) also the 5120-face icosphere of the shipped
  scene ``examples/scenes/glass_sphere.json`` and an 11 x 9 x 8 mm ellipsoid (the icosphere scaled, against its
  own exact tracer), each with Max's and with the area-weighted normals (column ``normals``);
- ``analytic``: the closed-form sphere (exact positions and normals at the texel centres), as in
  ``tests/test_caustics.py``.

Reference: rays on a jittered grid over the light view (``m x m``, 2000 full / 800 quick), refracted twice through
the exact sphere with Snell's law in numpy, intersected with the floor, histogrammed in the map's texels (the binned
exact irradiance: the reference of the beam splats) and, for the Gaussian splats, blurred by their Gaussian
(scipy). Errors: relative RMSE (|map - ref|_2 / |ref|_2 over the map; ``rel_rmse_binned`` against the binned
exact irradiance for both splats), relative L1 over the whole map, and over
the focused spot (texels where the reference exceeds 10 % of its peak). Energy ratio: total caustic flux / flux
transmitted through the sphere that reaches the floor inside the map (the histogram's total). Time per frame:
median of ``CausticMap.forward`` (and of ``caustic_gbuffers`` for the mesh rows).

Usage::

    python benchmarks/bench_caustics.py                 # grids 64/128/256, results/caustics.*
    python benchmarks/bench_caustics.py --quick --out-dir /tmp/b   # < 60 s
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from torchsss.bench import benchmark_parser, finish_benchmark, setup_benchmark, time_callable
from torchsss.geometry.lights import DirectionalLight
from torchsss.geometry.mesh import mesh_from_arrays
from torchsss.geometry.procedural import plane, sphere
from torchsss.geometry.shadow import bounding_sphere
from torchsss.modules.caustics import CausticMap
from torchsss.pipelines.caustics import caustic_gbuffers

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"
R, ZC, HALF, IOR, MAP, SIGMA = 10.0, 16.0, 15.0, 1.5, 128, 1.0
ELLIPSOID = (11.0, 9.0, 8.0)  # semi-axes (mm) of the non-spherical check
F64 = torch.float64
COLUMNS = ["source", "splat", "grid", "map", "faces", "normals", "rel_rmse", "rel_rmse_binned", "rel_l1",
           "focus_rel_l1", "energy_ratio", "peak_ratio", "t_module_ms", "t_gbuffers_ms", "t_frame_ms"]


def photon_histogram(h: int, m: int, seed: int = 0, axes: tuple[float, float, float] = (R, R, R)) -> np.ndarray:
    """Flux (irradiance 1) reaching the floor per texel of an (h, h) map of half-width HALF, exact ellipsoid.

    The ellipsoid has the semi-axes ``axes`` and is centred ZC over the floor (a sphere of radius R by default).
    """
    rng = np.random.default_rng(seed)
    cell = 2 * HALF / m
    x = (-HALF + (np.arange(m)[None, :] + rng.random((m, m))) * cell).ravel()
    y = (-HALF + (np.arange(m)[:, None] + rng.random((m, m))) * cell).ravel()
    ax = np.asarray(axes, dtype=float)
    c = np.array([0.0, 0.0, ZC])

    def hit(o, d, far):  # ray-ellipsoid intersection in the unit sphere's frame; the gradient normal
        q, e = (o - c) / ax, d / ax
        a2, b2, c2 = (e * e).sum(-1), 2 * (q * e).sum(-1), (q * q).sum(-1) - 1.0
        disc = b2 * b2 - 4 * a2 * c2
        t = (-b2 + (1 if far else -1) * np.sqrt(np.clip(disc, 0.0, None))) / (2 * a2)
        p = o + t[:, None] * d
        n = (p - c) / ax**2
        return p, n / np.linalg.norm(n, axis=-1, keepdims=True), disc > 0

    def snell(i, n, eta):
        cc = -(i * n).sum(-1, keepdims=True)
        k = 1.0 - eta**2 * (1.0 - cc**2)
        t = eta * i + (eta * cc - np.sqrt(np.clip(k, 0.0, None))) * n
        return t / np.linalg.norm(t, axis=-1, keepdims=True), k[..., 0] > 0

    down0 = np.broadcast_to([0.0, 0.0, -1.0], (x.size, 3))
    p, n, s = hit(np.stack([x, y, np.full_like(x, ZC + 2 * ax[2])], -1), down0, far=False)
    t1, _ = snell(down0[s], n[s], 1.0 / IOR)
    q, nb, _ = hit(p[s], t1, far=True)
    t2, ok = snell(t1, -nb, IOR)
    down = ok & (t2[:, 2] < 0)
    q, t2 = q[down], t2[down]
    hit = q - (q[:, 2] / t2[:, 2])[:, None] * t2
    col = np.floor((hit[:, 0] + HALF) / (2 * HALF) * h).astype(int)
    row = np.floor((HALF - hit[:, 1]) / (2 * HALF) * h).astype(int)
    inside = (col >= 0) & (col < h) & (row >= 0) & (row < h)
    hist = np.zeros((h, h))
    np.add.at(hist, (row[inside], col[inside]), cell * cell)
    return hist


def analytic_inputs(g: int, map_size: int) -> tuple:
    """Closed-form G-buffers of the sphere (as tests/test_caustics.py), the floor texture and the light view."""
    xs = -HALF + (np.arange(g) + 0.5) * 2 * HALF / g
    x, y = np.meshgrid(xs, xs[::-1])
    r2 = x * x + y * y
    mask = r2 < R * R
    hh = np.sqrt(np.clip(R * R - r2, 0.0, None))
    nan = np.where(mask, 1.0, np.nan)

    def t(a):
        return torch.tensor(a, dtype=F64)[None]

    m = t(mask[None])
    xm = -HALF + (np.arange(map_size) + 0.5) * 2 * HALF / map_size
    fx, fy = np.meshgrid(xm, xm[::-1])
    floor = t(np.stack([fx, fy, np.zeros_like(fx)]))
    vp = torch.zeros(1, 4, 4, dtype=F64)
    vp[0, 0, 0] = vp[0, 1, 1] = 1.0 / HALF
    vp[0, 2, 2] = -0.01
    vp[0, 3, 3] = 1.0
    return (t(np.stack([x, y, ZC + hh]) * nan), t(np.stack([x, y, hh]) / R), m,
            t(np.stack([x, y, ZC - hh]) * nan), t(np.stack([x, y, -hh]) / R), m.clone(), floor,
            torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=F64), torch.ones(1, 1, dtype=F64), vp)


def scene_meshes(subdivisions: int, axes: tuple[float, float, float] = (R, R, R)):
    s = sphere(1.0, subdivisions, dtype=F64)
    v = s.vertices * torch.tensor(axes, dtype=F64) + torch.tensor([0.0, 0.0, ZC], dtype=F64)
    s = mesh_from_arrays(v, s.faces, dtype=F64, name="sphere" if len(set(axes)) == 1 else "ellipsoid")
    return s, plane(120.0, 120.0, 4, dtype=F64)


def measure(source: str, grid: int, inputs: tuple, refs: dict, hist_total: float, extra: dict,
            repeats: int, splat: str) -> dict:
    map_size = inputs[6].shape[-1]
    module = CausticMap(IOR, 0.0, mode="double", sigma_px=SIGMA, splat=splat)
    ref = refs[splat]
    with torch.no_grad():
        cmap = module(*inputs)[0, 0].numpy()
        t = time_callable(lambda: module(*inputs), repeats=repeats, warmup=1, min_time_s=0.0)
    focus = ref > 0.1 * ref.max()
    rec = {
        "benchmark": "sphere", "source": source, "splat": splat, "grid": grid, "map": map_size, **extra,
        "rel_rmse": float(np.sqrt(((cmap - ref) ** 2).sum() / (ref**2).sum())),
        "rel_rmse_binned": float(np.sqrt(((cmap - refs["beam"]) ** 2).sum() / (refs["beam"] ** 2).sum())),
        "rel_l1": float(np.abs(cmap - ref).sum() / ref.sum()),
        "focus_rel_l1": float(np.abs(cmap - ref)[focus].sum() / ref[focus].sum()),
        "energy_ratio": float(cmap.sum() / hist_total),
        "peak_ratio": float(cmap.max() / ref.max()),
        "t_module_ms": 1e3 * t["median_s"],
    }
    rec["t_frame_ms"] = rec["t_module_ms"] + (rec.get("t_gbuffers_ms") or 0.0)
    print(f"{source:8s} {splat:8s} grid {grid:4d} map {map_size:4d}: rel RMSE {rec['rel_rmse']:.4f}, "
          f"rel L1 {rec['rel_l1']:.4f}, focus {rec['focus_rel_l1']:.4f}, energy "
          f"{rec['energy_ratio']:.4f}, module {rec['t_module_ms']:.1f} ms, frame {rec['t_frame_ms']:.1f} ms",
          flush=True)
    return rec


def main(argv=None) -> int:
    parser = benchmark_parser(__doc__.splitlines()[0], "caustics", RESULTS_DIR)
    args = parser.parse_args(argv)
    setup_benchmark(parser, args)
    start = time.perf_counter()
    grids = (64, 128) if args.quick else (64, 128, 256)
    subdiv = 5 if args.quick else 6
    repeats = 2 if args.quick else 5
    refractor, receiver = scene_meshes(subdiv)
    light = DirectionalLight((0.0, 0.0, -1.0), 1.0)
    records = []
    # map 128 at every grid; the default knobs (grid = map = 256) in the full run
    runs = [(g, MAP) for g in grids] + ([] if args.quick else [(256, 256)])
    hists = {}
    for g, map_size in runs:
        if map_size not in hists:
            hists[map_size] = photon_histogram(map_size, 800 if args.quick else 2000, args.seed)
        hist = hists[map_size]
        # beam splats are compared with the binned exact irradiance, Gaussian splats with it blurred by their sigma
        refs = {"beam": hist, "gaussian": ndimage.gaussian_filter(hist, SIGMA, mode="constant", truncate=3.0)}
        total = float(hist.sum())
        for splat in ("beam", "gaussian"):
            records.append(measure("analytic", g, analytic_inputs(g, map_size), refs, total, {"faces": None},
                                   repeats, splat))
        meshes = [("mesh", refractor, hist, "max")]
        if not args.quick and (g, map_size) == (256, 256):  # the default knobs: the scene's mesh and an ellipsoid
            ell = photon_histogram(map_size, 2000, args.seed, ELLIPSOID)
            for normals in ("max", "area"):
                meshes += [("mesh", scene_meshes(4)[0], hist, normals),
                           ("ellipsoid", scene_meshes(4, ELLIPSOID)[0], ell, normals),
                           ("ellipsoid", scene_meshes(5, ELLIPSOID)[0], ell, normals)]
        for source, mesh, ref_hist, normals in meshes:
            t0 = time.perf_counter()
            radius = float(bounding_sphere(mesh)[1])  # the light view spans +-HALF, as the reference's map
            gb = caustic_gbuffers(mesh, receiver, light, g, map_resolution=map_size, margin=HALF / radius,
                                  normals=normals)
            t_gb = time.perf_counter() - t0
            inputs = list(gb.module_inputs())
            inputs[8] = inputs[8][:, :1]  # one channel: the light is white
            mesh_refs = refs if ref_hist is hist else {
                "beam": ref_hist, "gaussian": ndimage.gaussian_filter(ref_hist, SIGMA, mode="constant", truncate=3.0)}
            both = source == "mesh" and normals == "max" and mesh is refractor
            for splat in ("beam", "gaussian") if both else ("beam",):
                records.append(measure(source, g, tuple(inputs), mesh_refs, float(ref_hist.sum()),
                                       {"faces": mesh.num_faces, "normals": normals, "t_gbuffers_ms": 1e3 * t_gb},
                                       repeats, splat))
    print(f"reference: {total:.3f} mm^2 of the sphere's {np.pi * R * R:.3f} reach the map", flush=True)
    name = args.name + ("_quick" if args.quick and args.name == "caustics" else "")
    finish_benchmark(name, records, args.out_dir, columns=COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
