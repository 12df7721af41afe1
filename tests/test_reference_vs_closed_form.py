"""The reference renderer: closed-form plane, rotational symmetry, convergence, bad input, the CLI."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys

import pytest
import torch

from torchsss.cli import main, output_paths
from torchsss.geometry.camera import Camera
from torchsss.geometry.lights import DirectionalLight, PointLight
from torchsss.geometry.procedural import plane, sphere
from torchsss.geometry.sampling import surface_samples
from torchsss.io import read_exr
from torchsss.physics import fresnel_transmittance, profile_tail_fraction, total_diffuse_reflectance
from torchsss.pipelines import default_spacing, reference_radiosity_at, render_reference, sample_irradiance
from torchsss.scene import Material


def _plane_b(material: Material, spacing: float, size: float = 100.0) -> tuple[torch.Tensor, torch.Tensor]:
    mesh = plane(size, size, 32, dtype=torch.float64)
    light = DirectionalLight((0.0, 0.0, -1.0), 1.0)
    s = surface_samples(mesh, spacing)
    e = sample_irradiance(mesh, s, [light], material.eta)
    g = torch.linspace(-4.0, 4.0, 5, dtype=torch.float64) + 0.123  # off-lattice receivers near the centre
    x, y = torch.meshgrid(g, g, indexing="ij")
    rx = torch.stack([x.flatten(), y.flatten(), torch.zeros(x.numel(), dtype=torch.float64)], -1)
    b = reference_radiosity_at(rx, s, e, material)
    sa, ss, eta = material.tensors()
    want = fresnel_transmittance(torch.tensor(1.0, dtype=torch.float64), eta) * total_diffuse_reflectance(sa, ss, eta)
    return b, want


@pytest.mark.parametrize("name", ["skin1", "ketchup"])
def test_plane_gives_e_times_r_total(name):
    material = Material.from_json(name)
    sa, ss, eta = material.tensors()
    assert float(profile_tail_fraction(torch.tensor(45.0, dtype=torch.float64), sa, ss, eta).max()) < 1e-3
    b, want = _plane_b(material, default_spacing(material))
    rel = ((b - want) / want).abs().max()
    assert float(rel) < 0.01, f"plane test: max relative error {float(rel):.2e}"


def test_plane_convergence_with_sample_density():
    material = Material.from_json("skin1")
    errors = []
    for spacing in (4.0, 2.0, 1.0, 0.5):
        b, want = _plane_b(material, spacing)
        errors.append(float(((b - want) / want).abs().max()))
    print("plane test, skin1: spacing 4, 2, 1, 0.5 mm -> max rel. error", [f"{e:.2e}" for e in errors])
    assert errors[-1] < 0.005
    assert errors[0] > 2 * errors[-1], "the error must shrink with the sample density"
    assert all(b <= a * 1.05 for a, b in itertools.pairwise(errors))


def test_sphere_lit_along_an_axis_is_rotationally_symmetric():
    mesh = sphere(8.0, 5, dtype=torch.float64)  # level 4 facets alone give a 4% spread at the terminator
    material = Material.from_json("skin1")
    light = DirectionalLight((0.0, 0.0, -1.0), 1.0)
    # receivers on rings of constant polar angle (lit side, terminator, far side)
    samples = surface_samples(mesh, 0.6)
    e = sample_irradiance(mesh, samples, [light], material.eta)
    phi = torch.linspace(0, 2 * math.pi, 13, dtype=torch.float64)[:-1] + 0.1
    for theta in (0.6, 1.57, 2.5):
        pts = 8.0 * torch.stack([math.sin(theta) * torch.cos(phi), math.sin(theta) * torch.sin(phi),
                                 torch.full_like(phi, math.cos(theta))], -1)
        b = reference_radiosity_at(pts, samples, e, material)
        spread = (b.amax(0) - b.amin(0)) / b.mean(0)
        assert float(spread.max()) < 0.02, f"theta={theta}: azimuthal spread {spread.tolist()}"
    # the image seen along the axis is invariant under a quarter turn
    cam = Camera(eye=(0.0, 0.0, -60.0), target=(0.0, 0.0, 0.0), fov_deg=20.0, width=33, height=33)
    r = render_reference(mesh, material, [light], cam, spacing_mm=0.6, dtype=torch.float64)
    img, m = r.radiance[0, 0], r.mask[0, 0]
    rot, mrot = torch.rot90(img, 1), torch.rot90(m, 1)
    both = m & mrot & (img > 0.02 * img.max())
    rel = ((img - rot).abs() / img.clamp_min(1e-30))[both]
    assert int(both.sum()) > 200 and float(rel.max()) < 0.05


def test_float32_matches_float64():
    mesh = sphere(8.0, 3)
    material = Material.from_json("marble")
    light = PointLight((30.0, 40.0, 50.0), 1e4)
    cam = Camera(eye=(0.0, 10.0, 50.0), target=(0.0, 0.0, 0.0), width=16, height=16)
    a = render_reference(mesh, material, [light], cam, spacing_mm=1.0, dtype=torch.float32)
    b = render_reference(mesh, material, [light], cam, spacing_mm=1.0, dtype=torch.float64)
    assert torch.equal(a.mask, b.mask)
    torch.testing.assert_close(a.radiance.double(), b.radiance, rtol=1e-4, atol=1e-6 * float(b.radiance.max()))
    assert a.stats["samples"] > 0 and a.stats["receivers"] == int(a.mask.sum())


def test_bad_scenes():
    mesh = sphere(10.0, 3)
    material = Material.from_json("skin1")
    cam = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0), width=8, height=8)
    with pytest.raises(ValueError, match="got one inside it"):
        render_reference(mesh, material, [PointLight((0.0, 0.0, 1.0), 1.0)], cam, spacing_mm=2.0)
    inside = Camera(eye=(0.0, 0.0, 1.0), target=(0.0, 0.0, -5.0), width=8, height=8)
    with pytest.raises(ValueError, match="near plane"):
        render_reference(mesh, material, [DirectionalLight((0, 0, -1), 1.0)], inside, spacing_mm=2.0)
    with pytest.raises(ValueError, match="lights"):
        render_reference(mesh, material, [], cam)
    with pytest.raises(ValueError, match="shadows"):
        render_reference(mesh, material, [DirectionalLight((0, 0, -1), 1.0)], cam, spacing_mm=2.0, shadows="soft")
    with pytest.raises(TypeError, match="dtype"):
        render_reference(mesh, material, [DirectionalLight((0, 0, -1), 1.0)], cam, dtype=torch.float16)


def test_unlit_object_renders_zero():
    mesh = plane(20.0, 20.0, 4)
    cam = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0), width=8, height=8)
    r = render_reference(mesh, Material.from_json("skin1"), [DirectionalLight((0, 0, 1), 1.0)], cam, spacing_mm=2.0)
    assert int(r.mask.sum()) > 0 and bool(torch.isfinite(r.radiance).all()) and float(r.radiance.abs().max()) == 0.0


def test_shadowmap_option_close_to_raytrace():
    mesh = sphere(8.0, 3)
    material = Material.from_json("skin1")
    light = PointLight((40.0, 30.0, 20.0), 1e4)
    cam = Camera(eye=(-30.0, 0.0, 50.0), target=(0.0, 0.0, 0.0), width=16, height=16)
    a = render_reference(mesh, material, [light], cam, spacing_mm=1.0, shadows="raytrace")
    b = render_reference(mesh, material, [light], cam, spacing_mm=1.0, shadows="shadowmap")
    rel = float((a.radiance - b.radiance).abs().sum() / a.radiance.abs().sum())
    assert rel < 0.02


def test_cli_renders_default_scene(tmp_path):
    out = tmp_path / "img.exr"
    assert main(["render", "default", "--out", str(out), "--resolution", "24x20", "--spacing", "2.0",
                 "--no-progress"]) == 0
    img = read_exr(out)
    assert img.shape == (3, 20, 24) and float(img.max()) > 0 and bool(torch.isfinite(img).all())
    assert out.with_suffix(".png").stat().st_size > 0
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["method"] == "reference" and summary["covered_pixels"] > 0


def test_cli_out_png_keeps_the_linear_exr_beside_it(tmp_path, capsys):
    """``--out x.png`` writes the PNG there and the EXR as x.exr (before: the EXR went to x.png, then the PNG
    overwrote it, and the path was printed twice); another suffix is refused before anything renders."""
    out = tmp_path / "shot.png"
    assert main(["render", "default", "--out", str(out), "--resolution", "12x12", "--spacing", "3.0",
                 "--no-progress"]) == 0
    printed = capsys.readouterr().out
    exr = out.with_suffix(".exr")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = read_exr(exr)
    assert img.shape == (3, 12, 12) and float(img.max()) > 0
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["exr"] == str(exr) and summary["png"] == str(out)
    assert f"wrote {exr}, {out}, {out.with_suffix('.json')}" in printed
    stem = tmp_path / "plain"
    assert [p.name for p in output_paths(stem)] == ["plain.exr", "plain.png", "plain.json"]
    with pytest.raises(SystemExit) as err:
        main(["render", "default", "--out", str(tmp_path / "x.jpg"), "--resolution", "8x8", "--no-progress"])
    assert err.value.code == 2
    assert "out: expected a path ending in .exr or .png" in capsys.readouterr().err
    assert not list(tmp_path.glob("x.*"))


@pytest.mark.filterwarnings("ignore:.*mesh is not watertight")  # bunny and teapot are open (as the CLI says)
@pytest.mark.parametrize("name", ["stanford-bunny.obj", "teapot.obj", "igea.ply"])
def test_cli_renders_shared_meshes(shared_dir, tmp_path, name):
    scene = {"mesh": str(shared_dir / "data" / "meshes" / name), "size_mm": 30.0, "material": "marble",
             "lights": [{"type": "point", "position": [-40, 30, -60], "intensity": 1e4}],
             "camera": {"eye": [0, 10, 70], "target": [0, 0, 0], "width": 16, "height": 16}}
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    out = tmp_path / "img.exr"
    # in process (the `python -m torchsss` entry point itself runs in test_cli_errors): no interpreter start-up
    assert main(["render", str(path), "--out", str(out), "--spacing", "3.0", "--no-progress"]) == 0
    img = read_exr(out)
    assert img.shape == (3, 16, 16) and float(img.max()) > 0


def test_cli_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"mesh": "sphere"}))
    proc = subprocess.run([sys.executable, "-m", "torchsss", "render", str(bad), "--out", str(tmp_path / "x.exr")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "missing keys" in proc.stderr
    with pytest.raises(SystemExit):
        main(["render", "default", "--method", "magic"])
