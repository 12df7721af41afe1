"""Caustic receiver search: accuracy of Shah's estimator and Newton-Raphson vs iterations, and eager vs ONNX speed.

Scenes (Shah ch. 5). A perspective light 100 mm above the origin looks down (fov 40 degrees, S x S texels; 0.28 mm
per texel at z = 0 for S = 256) at a receiver, which it renders into the positions texture:

* ``plane``: z = 0;
* ``sphere_cap``: the plane plus the part above it of a sphere (radius 12 mm, centre 3 mm above the plane), whose
  overhang hides some of the plane from the light: depth discontinuities in the positions texture;
* ``heightfield``: a rugged floor, a sum of sines (slopes up to ~0.8).

Two sets of queries per receiver: ``water``, the light's S x S pixel rays refracted into a wavy water surface
around z = 40 mm (amplitude 2 mm; single refraction, eta = 1 / 1.33, Shah Figs. 5.5 and 5.8; within 17 degrees
of the light's lines of sight), and ``glass_ball``, the pixel
rays that pass through a glass ball (radius 15 mm, centre 45 mm up, eta = 1.5; double refraction, Shah Figs. 5.6
and 5.9; up to ~80 degrees from the lines of sight). Queries whose exact hit is hidden from the light (under the
sphere's overhang) or projects outside the light image cannot be found in the texture and are left out.

The positions texture holds the exact first hit of every light pixel ray (closed form, or march + 60 bisections
for the heightfield, float64); the reference distance of every query is its exact intersection with the same
surface, computed the same way. The search runs in float32 (what a renderer feeds it).

(a) ``accuracy``: for each scene, method (``shah``, ``newton``), fallback (off/on) and iterations 1..10:
    ``valid_frac`` (share of the queries whose exact hit projects into the light image that come back valid),
    median and p90 of the error |d - d_exact| over the valid ones in texels (of the light camera at the hit) and
    mm, ``bad_frac`` (valid with an error above 1 texel), ``wrong_root_frac`` (of those, the ones whose residual is
    below 0.1 texel: converged onto a later intersection of the ray with the receiver, e.g. the far side of the
    dome or the plane behind it, instead of the first one), ``osc_frac`` (share flagged as oscillating),
    ``fallback_frac`` (share bisected at least once) and ``rescued_frac`` (share that oscillate without the
    fallback and end more than half a texel off or invalid, but within half a texel with it; fallback rows only).
(b) ``timing``: time for the S x S queries at 5 iterations, eager PyTorch (inference mode) against the same graph
    exported to ONNX (dynamo, opset 18) in onnxruntime (CPU, 1 thread), interleaved samples; max abs difference.

Usage::

    python benchmarks/bench_caustic_search.py            # full run (S = 256), writes results/caustic_search.*
    python benchmarks/bench_caustic_search.py --quick    # smoke run (S = 48, iterations 1..3)
"""

from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from torchsss.bench import benchmark_parser, compare, finish_benchmark, setup_benchmark
from torchsss.geometry.camera import Camera
from torchsss.ops.newton_raphson import newton_raphson_intersect
from torchsss.ops.refraction import refract

RESULTS_DIR = Path(__file__).resolve().parent / "results"
F64 = torch.float64
EYE = (0.0, 0.0, 100.0)
WATER_ETA = 1.0 / 1.33
SPHERE_C = (6.0, -4.0, 3.0)
SPHERE_R = 12.0
BALL_C = (0.0, 0.0, 45.0)
BALL_R = 15.0
BALL_ETA = 1.5

MD_COLUMNS = {
    "accuracy": [
        "scene",
        "queries",
        "method",
        "fallback",
        "iterations",
        "valid_frac",
        "median_texel",
        "p90_texel",
        "median_mm",
        "p90_mm",
        "bad_frac",
        "wrong_root_frac",
        "osc_frac",
        "fallback_frac",
        "rescued_frac",
    ],
    "timing": [
        "scene",
        "method",
        "iterations",
        "rays",
        "texture",
        "eager_ms",
        "onnx_ms",
        "onnx_over_eager",
        "max_abs_diff_mm",
        "export_s",
    ],
}

FULL = {
    "size": 256,
    "iterations": tuple(range(1, 11)),
    "onnx_iterations": 5,
    "timing": {"repeats": 5, "warmup": 1, "min_time_s": 0.2},
}
QUICK = {
    "size": 48,
    "iterations": (1, 2, 3),
    "onnx_iterations": 2,
    "timing": {"repeats": 3, "warmup": 1, "min_time_s": 0.01},
}


# -- scene geometry (float64, exact) ------------------------------------------------------------------------------
def floor_height(x, y):
    return (
        -2.0
        + 1.5 * torch.sin(0.25 * x + 0.3) * torch.sin(0.2 * y)
        + 0.8 * torch.sin(0.13 * x - 0.21 * y + 1.0)
        + 0.3 * torch.sin(0.6 * x + 0.4 * y)
    )


def water_height(x, y):
    return 40.0 + 1.4 * torch.sin(0.3 * x + 0.2 * y) + 0.7 * torch.sin(-0.25 * x + 0.45 * y + 0.5)


def water_normal(x, y):
    a, b = torch.cos(0.3 * x + 0.2 * y), torch.cos(-0.25 * x + 0.45 * y + 0.5)
    dx, dy = 1.4 * 0.3 * a - 0.7 * 0.25 * b, 1.4 * 0.2 * a + 0.7 * 0.45 * b
    return torch.stack([-dx, -dy, torch.ones_like(dx)], -1)


def march(o, d, height, t0, t1, steps, chunk=8192):
    """First t in [t0, t1] where o + t d (N, 3) goes below z = height(x, y): grid sign change, then 60 bisections."""
    out = []
    ts = torch.linspace(0.0, 1.0, steps + 1, dtype=F64)
    for i in range(0, o.shape[0], chunk):
        oc, dc = o[i : i + chunk], d[i : i + chunk]
        t = t0 + (t1 - t0) * ts
        x = oc[:, None, :] + t[None, :, None] * dc[:, None, :]
        below = (x[..., 2] - height(x[..., 0], x[..., 1])) <= 0
        first = below.to(torch.int8).argmax(1)
        ok = below.any(1) & (first > 0)
        j = first.clamp_min(1)
        a, b = t[j - 1], t[j]
        for _ in range(60):
            m = 0.5 * (a + b)
            xm = oc + m[:, None] * dc
            above = xm[:, 2] - height(xm[:, 0], xm[:, 1]) > 0
            a, b = torch.where(above, m, a), torch.where(above, b, m)
        out.append(torch.where(ok, 0.5 * (a + b), torch.full_like(a, math.nan)))
    return torch.cat(out)


def hit_plane(o, d):
    t = -o[:, 2] / d[:, 2]
    return torch.where(t > 0, t, torch.full_like(t, math.nan))


def hit_sphere_cap(o, d):
    """First hit of the union of the plane z = 0 and the part above it of the sphere (SPHERE_C, SPHERE_R)."""
    c = torch.tensor(SPHERE_C, dtype=F64)
    oc = o - c
    b = (oc * d).sum(1)
    disc = b * b - ((oc * oc).sum(1) - SPHERE_R**2)
    root = torch.sqrt(disc.clamp_min(0.0))
    t_near = -b - root
    on_dome = (disc > 0) & (t_near > 0) & ((o[:, 2] + t_near * d[:, 2]) >= 0)
    t_plane = hit_plane(o, d)
    return torch.where(on_dome & ~(t_plane < t_near), t_near, t_plane)


def exact_hit(name):
    """Exact first-hit distance function (origins (N, 3), unit directions (N, 3)) -> (N,) of a receiver."""
    if name == "plane":
        return hit_plane
    if name == "sphere_cap":
        return hit_sphere_cap

    def heightfield(o, d):
        return march(o, d, floor_height, 0.0, 130.0, 650)

    return heightfield


def water_queries(ol, dl):
    """Light rays refracted into a wavy water surface (single refraction, Shah Figs. 5.5 and 5.8)."""
    t_w = march(ol, dl, water_height, 50.0, 70.0, 100)
    origins = ol + t_w[:, None] * dl
    directions, tir = refract(dl, water_normal(origins[:, 0], origins[:, 1]), WATER_ETA)
    return origins[~tir], directions[~tir]


def glass_ball_queries(ol, dl):
    """Light rays refracted into and out of a glass ball (double refraction, Shah Figs. 5.6 and 5.9)."""
    c = torch.tensor(BALL_C, dtype=F64)
    oc = ol - c
    b = (oc * dl).sum(1)
    disc = b * b - ((oc * oc).sum(1) - BALL_R**2)
    hit = disc > 0
    p1 = ol + (-b - torch.sqrt(disc.clamp_min(0.0)))[:, None] * dl
    d1, tir1 = refract(dl, p1 - c, 1.0 / BALL_ETA)
    p2 = p1 - 2.0 * ((p1 - c) * d1).sum(1, keepdim=True) * d1  # the other end of the chord
    d2, tir2 = refract(d1, p2 - c, BALL_ETA)
    keep = hit & ~tir1 & ~tir2
    return p2[keep], d2[keep]


QUERIES = {"water": water_queries, "glass_ball": glass_ball_queries}


def build_scene(name, size):
    """Light camera, (1, 3, S, S) positions texture and the exact-hit function of a receiver."""
    cam = Camera(eye=EYE, target=(0.0, 0.0, 0.0), fov_deg=40.0, width=size, height=size, near=1.0, far=500.0)
    o_l, d_l = cam.rays(dtype=F64)
    ol, dl = o_l[0].reshape(3, -1).T, d_l[0].reshape(3, -1).T
    exact = exact_hit(name)
    tex = (ol + exact(ol, dl)[:, None] * dl).T.reshape(1, 3, size, size)  # NaN where a pixel sees no receiver
    return cam, tex, exact, (ol, dl)


def texel_mm(cam, points):
    vp = cam.view_proj(dtype=F64)
    w = points @ vp[3, :3] + vp[3, 3]
    return 2.0 * w * math.tan(math.radians(cam.fov_deg) / 2) / cam.height


def visible_from_light(exact, points):
    """Points (N, 3) that the light sees: its ray toward them meets the receiver there first (within 1e-6 mm)."""
    eye = torch.tensor(EYE, dtype=F64).expand_as(points)
    dist = torch.linalg.vector_norm(points - eye, dim=1)
    first = exact(eye, (points - eye) / dist[:, None])
    return (first - dist).abs() <= 1e-6


def inside_image(cam, points, margin_texels=1.0):
    vp = cam.view_proj(dtype=F64)
    c = points @ vp[:, :3].T + vp[:, 3]
    ndc = c[:, :2] / c[:, 3:]
    return (c[:, 3] > 0) & (ndc.abs() <= 1.0 - 2.0 * margin_texels / cam.height).all(1)


# -- (a) accuracy -------------------------------------------------------------------------------------------------
def bench_accuracy(scenes, iterations, log=print):
    records = []
    for name, (cam, tex, exact, light_rays) in scenes.items():
        for qname, make_queries in QUERIES.items():
            o, r = make_queries(*light_rays)
            d_exact = exact(o, r)
            hit = torch.nan_to_num(o + d_exact[:, None] * r)
            lit = visible_from_light(exact, hit)  # a hit hidden from the light is not in the positions texture
            expected = torch.isfinite(d_exact) & inside_image(cam, hit) & lit
            n_exp = max(1, int(expected.sum()))
            texel = texel_mm(cam, hit)
            sight = (o - torch.tensor(EYE, dtype=F64)) / torch.linalg.vector_norm(
                o - torch.tensor(EYE, dtype=F64), dim=1, keepdim=True
            )
            dev = torch.rad2deg(torch.acos((r * sight).sum(1).clamp(-1.0, 1.0)))
            args = (o[None].float(), r[None].float(), tex.float(), cam.view_proj(dtype=torch.float32))
            hidden = int((~lit & torch.isfinite(d_exact)).sum())
            log(
                f"  {name} / {qname}: {o.shape[0]} queries, {int(expected.sum())} with the exact hit lit and in the "
                f"light image ({hidden} hidden from the light); angle to the light's line of sight: median "
                f"{float(dev.median()):.1f}, max {float(dev.max()):.1f} deg; "
                f"texel {float(texel[expected].median()):.3f} mm"
            )
            for method in ("shah", "newton"):
                for k in iterations:
                    runs = {}
                    for fallback in (False, True):
                        with torch.inference_mode():
                            d, valid, info = newton_raphson_intersect(
                                *args, k, method, fallback=fallback, return_info=True
                            )
                        d, valid = d[0].double(), valid[0] & expected
                        err_mm = (d - d_exact).abs()
                        err_tx = err_mm / texel
                        runs[fallback] = (valid, err_tx, info)
                        ok = err_tx[valid]
                        rec = {
                            "benchmark": "accuracy",
                            "scene": name,
                            "queries": qname,
                            "method": method,
                            "fallback": fallback,
                            "iterations": k,
                            "n_queries": int(expected.sum()),
                            "hidden": hidden,
                            "valid_frac": float(valid.sum()) / n_exp,
                            "median_texel": float(ok.median()),
                            "p90_texel": float(ok.quantile(0.9)),
                            "median_mm": float(err_mm[valid].median()),
                            "p90_mm": float(err_mm[valid].quantile(0.9)),
                            "max_texel": float(ok.max()),
                            "bad_frac": float((ok > 1.0).sum()) / n_exp,
                            "wrong_root_frac": float(
                                (valid & (err_tx > 1.0) & (info["residual"][0].double() < 0.1 * texel)).sum()
                            )
                            / n_exp,
                            "osc_frac": float((info["oscillated"][0] & expected).sum()) / n_exp,
                            "fallback_frac": float((info["fallback"][0] & expected).sum()) / n_exp,
                            "rescued_frac": None,
                        }
                        if fallback:
                            v0, e0, i0 = runs[False]
                            bad_without = ~v0 | (e0 > 0.5)
                            good_with = valid & (err_tx <= 0.5)
                            rescued = expected & i0["oscillated"][0] & bad_without & good_with
                            rec["rescued_frac"] = float(rescued.sum()) / n_exp
                        records.append(rec)
                    a, b = records[-2], records[-1]
                    log(
                        f"    {method:6s} k={k:2d}: valid {a['valid_frac']:.4f}/{b['valid_frac']:.4f}, median "
                        f"{a['median_texel']:.4f}/{b['median_texel']:.4f} texel, p90 {a['p90_texel']:.4f}/"
                        f"{b['p90_texel']:.4f}, bad {a['bad_frac']:.4f}/{b['bad_frac']:.4f}, oscillating "
                        f"{a['osc_frac']:.4f}, bisected {b['fallback_frac']:.4f}, rescued {b['rescued_frac']:.4f} "
                        f"(fallback off/on)"
                    )
    return records


# -- (b) eager vs onnxruntime -------------------------------------------------------------------------------------
class _Search(torch.nn.Module):
    """Exportable wrapper (benchmark only: ops/ holds no modules)."""

    def __init__(self, iterations, method):
        super().__init__()
        self.iterations, self.method = iterations, method

    def forward(self, origins, directions, positions, view_proj):
        return newton_raphson_intersect(origins, directions, positions, view_proj, self.iterations, self.method)


def bench_timing(scene_name, scene, iterations, timing, log=print):
    import onnxruntime as ort
    from torch.export import Dim

    from torchsss.export import export_onnx

    cam, tex, _, light_rays = scene
    o, r = water_queries(*light_rays)
    args = (o[None].float(), r[None].float(), tex.float(), cam.view_proj(dtype=torch.float32)[None])
    small = (args[0][:, :500], args[1][:, :500], args[2][:, :, :40, :36], args[3])  # export at another size
    bd, nd, hd, wd = Dim("B", min=1, max=64), Dim("N"), Dim("H"), Dim("W")
    dyn = ({0: bd, 1: nd}, {0: bd, 1: nd}, {0: bd, 2: hd, 3: wd}, {0: bd})
    records = []
    for method in ("shah", "newton"):
        module = _Search(iterations, method)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            path = export_onnx(module, small, Path(tmp) / "search.onnx", dynamic_shapes=dyn)
            export_s = time.perf_counter() - t0
            opts = ort.SessionOptions()
            opts.intra_op_num_threads, opts.inter_op_num_threads = 1, 1
            session = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
        feed = {i.name: a.numpy() for i, a in zip(session.get_inputs(), args)}

        def eager(module=module):
            with torch.inference_mode():
                return module(*args)

        def onnx(session=session, feed=feed):
            return session.run(None, feed)

        d_e, v_e = eager()
        d_o, v_o = onnx()
        both = v_e[0].numpy() & v_o[0]
        diff = float(np.abs(d_o[0][both] - d_e[0].numpy()[both]).max())
        c = compare(onnx, eager, name=f"caustic_search/{scene_name}/{method}", **timing)
        rec = {
            "benchmark": "timing",
            "scene": scene_name,
            "method": method,
            "iterations": iterations,
            "rays": int(o.shape[0]),
            "texture": f"{tex.shape[-2]}x{tex.shape[-1]}",
            "dtype": "float32",
            "eager_ms": 1e3 * c["baseline_median_s"],
            "onnx_ms": 1e3 * c["candidate_median_s"],
            "onnx_over_eager": c["candidate_median_s"] / c["baseline_median_s"],
            "eager_iqr_ms": 1e3 * c["baseline_iqr_s"],
            "onnx_iqr_ms": 1e3 * c["candidate_iqr_s"],
            "max_abs_diff_mm": diff,
            "valid_mismatch": int((v_e[0].numpy() != v_o[0]).sum()),
            "export_s": export_s,
            "repeats": c["repeats"],
        }
        log(
            f"  {method:6s}: eager {rec['eager_ms']:8.2f} ms, onnxruntime {rec['onnx_ms']:8.2f} ms "
            f"(x{rec['onnx_over_eager']:.2f}), max abs diff {diff:.1e} mm, {rec['valid_mismatch']} validity "
            f"mismatches, export {export_s:.1f} s"
        )
        records.append(rec)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(
        __doc__.split("\n\n")[0], "caustic_search", RESULTS_DIR, seed_help="unused (the scenes are deterministic)"
    )
    parser.add_argument("--skip-onnx", action="store_true", help="skip the onnxruntime timing (b)")
    args = parser.parse_args(argv)
    setup_benchmark(parser, args)
    cfg = QUICK if args.quick else FULL

    start = time.perf_counter()
    print(f"building scenes at {cfg['size']}^2 (exact float64 intersections)")
    scenes = {name: build_scene(name, cfg["size"]) for name in ("plane", "sphere_cap", "heightfield")}
    print(f"(a) accuracy vs iterations, float32, {torch.get_num_threads()} thread(s)")
    records = bench_accuracy(scenes, cfg["iterations"])
    if not args.skip_onnx:
        print(f"(b) eager vs onnxruntime, {cfg['size']}^2 queries, {cfg['onnx_iterations']} iterations")
        records += bench_timing("heightfield", scenes["heightfield"], cfg["onnx_iterations"], cfg["timing"])
    finish_benchmark(args.name, records, args.out_dir, columns=MD_COLUMNS, start=start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
