"""Reference renderer benchmarks: convergence with sample density, and render times of real scenes.

(a) plane convergence: a 100 mm plane under uniform normal irradiance; B at 25 off-lattice receivers near the
    centre against the closed form :math:`E F_t(0) R_{total}`; max relative error and time against the sample
    spacing, for skin1, marble and ketchup, float64. The default spacing (:func:`default_spacing`, eps = 0.01)
    is one of the rows.
(b) render times: the default scene (spot, 40 mm, skin1, back-lit, 160 x 160), and the Stanford bunny
    (50 mm, skin1, back-lit) at 256 x 256 with the default spacing, float32 - stage times, samples, receivers,
    pairs per second.

Usage::

    python benchmarks/bench_reference.py                # full run (several minutes), writes results/reference.*
    python benchmarks/bench_reference.py --quick        # small sizes, a few seconds
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch

from torchsss.bench import write_results
from torchsss.geometry.camera import Camera
from torchsss.geometry.lights import DirectionalLight, PointLight
from torchsss.geometry.loading import load_mesh
from torchsss.geometry.procedural import plane
from torchsss.geometry.sampling import surface_samples
from torchsss.physics import fresnel_transmittance, total_diffuse_reflectance
from torchsss.pipelines import default_spacing, reference_radiosity_at, render_reference, sample_irradiance
from torchsss.scene import Material, default_scene_path, load_scene

RESULTS_DIR = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"


def plane_convergence(names, spacings) -> list[dict]:
    records = []
    mesh = plane(100.0, 100.0, 32, dtype=torch.float64)
    g = torch.linspace(-4.0, 4.0, 5, dtype=torch.float64) + 0.123
    x, y = torch.meshgrid(g, g, indexing="ij")
    rx = torch.stack([x.flatten(), y.flatten(), torch.zeros(x.numel(), dtype=torch.float64)], -1)
    for name in names:
        mat = Material.from_json(name)
        sa, ss, eta = mat.tensors()
        want = fresnel_transmittance(torch.tensor(1.0, dtype=torch.float64), eta) * total_diffuse_reflectance(
            sa, ss, eta)
        default = default_spacing(mat)
        for spacing in sorted({*spacings, round(default, 4)}, reverse=True):
            t0 = time.perf_counter()
            s = surface_samples(mesh, spacing)
            e = sample_irradiance(mesh, s, [DirectionalLight((0, 0, -1), 1.0)], mat.eta)
            b = reference_radiosity_at(rx, s, e, mat)
            secs = time.perf_counter() - t0
            err = ((b - want) / want).abs().amax(0)
            records.append({"benchmark": "plane_convergence", "material": name, "spacing_mm": spacing,
                            "default": abs(spacing - default) < 1e-3, "samples": int(s.area.shape[0]),
                            "max_rel_error": float(err.max()), "rel_error_rgb": [float(v) for v in err],
                            "seconds": secs})
            print(f"plane {name:8s} spacing {spacing:6.3f} mm  samples {s.area.shape[0]:7d}  "
                  f"max rel err {float(err.max()):.2e}  {secs:.2f} s", flush=True)
    return records


def render_record(label, mesh, material, lights, camera) -> dict:
    r = render_reference(mesh, material, lights, camera, progress=True)
    st = r.stats
    rec = {"benchmark": "render", "scene": label, "resolution": f"{camera.width}x{camera.height}",
           "faces": mesh.num_faces, "size_mm": round(mesh.size_mm, 3), "material": material.name,
           "spacing_mm": st["spacing_mm"], "samples": st["samples"], "receivers": st["receivers"],
           "pairs": st["pairs"], "t_irradiance_s": st["t_irradiance_s"], "t_integrate_s": st["t_integrate_s"],
           "t_total_s": st["t_total_s"], "pairs_per_s": st["pairs"] / max(st["t_integrate_s"], 1e-9)}
    print(f"render {label}: {rec['resolution']}, {rec['samples']} samples, {rec['receivers']} receivers, "
          f"{rec['t_total_s']:.1f} s", flush=True)
    return rec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.quick:
        records = plane_convergence(["skin1"], [4.0, 1.0])
    else:
        records = plane_convergence(["skin1", "marble", "ketchup"], [4.0, 2.0, 1.0, 0.5, 0.25])
    scene = load_scene(default_scene_path())
    if args.quick:
        scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=32, height=32))
    records.append(render_record("default scene (spot)", scene.load_mesh(), scene.material, scene.lights,
                                 scene.camera))
    bunny_path = SHARED / "stanford-bunny.obj"
    if bunny_path.is_file() and not args.quick:
        bunny = load_mesh(bunny_path, 50.0, warn_open=False)
        cam = Camera(eye=(0.0, 8.0, 95.0), target=(0.0, 0.0, 0.0), fov_deg=32.0, width=256, height=256)
        lights = [PointLight((-40.0, 40.0, -80.0), 1e4), PointLight((60.0, 20.0, 80.0), 1e3)]
        records.append(render_record("stanford bunny", bunny, Material.from_json("skin1"), lights, cam))
    name = "reference_quick" if args.quick else "reference"
    write_results(name, records, args.out_dir, columns={
        "plane_convergence": ["material", "spacing_mm", "default", "samples", "max_rel_error", "seconds"],
        "render": ["scene", "resolution", "faces", "size_mm", "material", "spacing_mm", "samples", "receivers",
                   "pairs", "t_irradiance_s", "t_integrate_s", "t_total_s", "pairs_per_s"],
    })
    print(f"wrote {args.out_dir / name}.json/.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
