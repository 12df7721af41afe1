"""The spine every method shares: one material record, one profile contract, one exit radiance, build / render."""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path

import pytest
import torch

import torchsss
from torchsss.cli import main
from torchsss.geometry import Camera, DirectionalLight, PointLight, sphere
from torchsss.modules import BurleyMaterial, DipoleMaterial, TabulatedMaterial, check_profile, material_module
from torchsss.physics import Material, preset
from torchsss.pipelines import RENDERERS, build
from torchsss.registry import orbit_lights, render_scene
from torchsss.scene import Scene

PACKAGE = Path(torchsss.__file__).resolve().parent


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_pipelines_do_not_import_the_scene_module():
    for path in (PACKAGE / "pipelines").glob("*.py"):
        bad = {m for m in _imports(path) if m == "torchsss.scene" or m.startswith("torchsss.registry")}
        assert not bad, (path.name, bad)


def test_one_material_record_and_one_exit_radiance_function():
    classes, exits = [], []
    for path in PACKAGE.rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and node.name in ("Material", "MaterialPreset"):
                classes.append(path.name)
            if isinstance(node, ast.FunctionDef) and node.name in ("exit_radiance", "radiance"):
                exits.append((path.name, node.name))
    assert classes == ["materials.py"], classes
    assert exits == [("fresnel.py", "exit_radiance")], exits
    assert torchsss.scene.Material is Material and torchsss.physics.MaterialPreset is Material
    assert preset("marble") == Material.from_json("marble")


def test_material_record_json_round_trip_and_errors():
    m = Material.from_json({"sigma_a": [0.1, 0.2, 0.3], "sigma_s_prime": 1.0, "eta": 1.4, "profile": "burley"})
    assert Material.from_json(m.to_json()) == m and m.sigma_s_prime == (1.0, 1.0, 1.0)
    assert Material.from_json({"preset": "skin1", "profile": "tabulated"}).profile == "tabulated"
    with pytest.raises(ValueError, match=r"material\.profile: expected one of"):
        Material.from_json({"preset": "skin1", "profile": "gaussian"})
    with pytest.raises(ValueError, match=r"material\.sigma_s_prime: expected finite values > 0"):
        Material.from_json({"sigma_a": 0.1, "sigma_s_prime": 0.0})
    with pytest.raises(ValueError, match=r"material\.eta"):
        Material((0.1,) * 3, (1.0,) * 3, eta=-1.0)
    with pytest.raises(TypeError, match="material: expected a preset name"):
        Material.from_json(3)


@pytest.mark.parametrize("profile,cls", [("dipole", DipoleMaterial), ("burley", BurleyMaterial),
                                         ("tabulated", TabulatedMaterial)])
def test_material_module_follows_the_contract(profile, cls):
    m = material_module(Material.from_json("skin1"), profile, dtype=torch.float64)
    assert isinstance(m, cls) and check_profile(m) is m
    r = torch.linspace(0.0, 20.0, 64, dtype=torch.float64).unsqueeze(-1)
    assert m(r).shape == (64, 3) and bool(torch.isfinite(m(r)).all())
    assert m.eta.shape == () and abs(float(m.eta) - 1.3) < 1e-9 and m.channels == 3
    rm, h = m.r_max(0.01), m.spacing(0.01)
    assert rm.shape == (3,) and h.shape == (3,) and bool((h > 0).all()) and bool((h < rm).all())
    # r_max(eps) holds all but eps of the energy (closed-form cumulative; tabulated: the wrapped dipole's)
    total = m.total_diffuse_reflectance()
    inside = m.cumulative(rm.unsqueeze(-1)).diagonal()
    torch.testing.assert_close(1.0 - inside / total, torch.full((3,), 0.01, dtype=torch.float64), rtol=0.05, atol=0)


def test_check_profile_and_material_module_errors():
    with pytest.raises(TypeError, match="material: expected a profile module"):
        check_profile(lambda r: r)
    with pytest.raises(TypeError, match=r"without .*spacing"):
        check_profile(torch.nn.Linear(1, 3))
    with pytest.raises(ValueError, match="profile: expected one of"):
        material_module("skin1", "gaussian")
    with pytest.raises(ValueError, match="profile: expected None for a profile module"):
        material_module(DipoleMaterial.from_preset("skin1"), "burley")
    with pytest.raises(TypeError, match="material: expected a Material record"):
        material_module(3.0)


def test_build_rejects_unknown_methods_and_knobs():
    mesh = sphere(5.0, 1)
    with pytest.raises(ValueError, match="method: expected one of"):
        build("pathtrace", mesh, "skin1")
    with pytest.raises(ValueError, match="spacing: expected a knob of method 'reference'"):
        build("reference", mesh, "skin1", spacing=1.0)
    with pytest.raises(TypeError, match="mesh: expected a torchsss Mesh"):
        build("splat", "sphere", "skin1")
    assert set(RENDERERS) == {"reference", "lensch", "splat", "icdf", "hybrid", "caustics"}


def test_frames_reuse_one_setup_and_report_the_knobs():
    mesh = sphere(8.0, 2)
    cam = Camera(eye=(0.0, 0.0, 45.0), target=(0.0, 0.0, 0.0), width=12, height=12)
    r = build("splat", mesh, "skin1", grid=24)
    module = r.module
    a = r.render([PointLight((30.0, 0.0, 10.0), 1e3)], cam)
    b = r.render([PointLight((-30.0, 0.0, 10.0), 1e3)], cam)
    assert r.module is module and a.stats["setup_s"] == b.stats["setup_s"] and a.stats["knobs"]["grid"] == 24
    assert not torch.equal(a.radiance, b.radiance)
    # the orbit turns point lights about the axis through the centre and directional lights alike
    p = orbit_lights([PointLight((10.0, 0.0, 0.0), 1.0), DirectionalLight((1.0, 0.0, 0.0), 1.0)], 1, 2)
    assert all(abs(x - y) < 1e-9 for x, y in zip(p[0].position, (-10.0, 0.0, 0.0)))
    assert all(abs(x - y) < 1e-9 for x, y in zip(p[1].direction, (-1.0, 0.0, 0.0)))


SCENE = {"mesh": "sphere", "size_mm": 16.0, "material": {"preset": "skin1", "profile": "burley"},
         "lights": [{"type": "point", "position": [40.0, 5.0, -20.0], "intensity": 1500.0}],
         "camera": {"eye": [0.0, 0.0, 45.0], "target": [0.0, 0.0, 0.0], "width": 16, "height": 16}}


def test_render_scene_frames_and_a_burley_scene():
    scene = Scene.from_dict(SCENE)
    assert scene.material.profile == "burley"
    res = render_scene(scene, "splat", frames=3)
    st = res.stats
    assert len(st["frame_s"]) == 3 and st["frame_median_s"] > 0 and st["fps"] > 0 and st["setup_s"] >= 0
    assert st["method"] == "splat" and "eps" in st["knobs"]


def test_cli_frames_and_profile(tmp_path):
    path = tmp_path / "s.json"
    path.write_text(json.dumps({**SCENE, "material": "skin1"}))
    out = tmp_path / "a.exr"
    assert main(["render", str(path), "--method", "splat", "--frames", "2", "--profile", "burley", "--out",
                 str(out), "--no-progress"]) == 0
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["material"]["profile"] == "burley" and len(summary["frame_s"]) == 2
    assert summary["setup_s"] >= 0 and summary["fps"] > 0
    assert summary["knobs"]["eps"] == summary["method_plan"]["knobs"]["eps"]  # planned for the scene
    with pytest.raises(SystemExit):
        main(["render", str(path), "--frames", "0", "--out", str(out)])


def test_irradiance_atlas_module_reads_eta_from_the_material():
    from torchsss.geometry import build_atlas
    from torchsss.modules import IrradianceAtlas

    mesh = sphere(10.0, 2)
    atlas = build_atlas(mesh, 64, kernel_size=3)
    mat = DipoleMaterial.from_preset("skin1", dtype=torch.float64)
    module = IrradianceAtlas.from_atlas(dataclasses.replace(atlas), mat)
    light = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float32)
    e13 = module(light, torch.ones(1, 3))
    with torch.no_grad():
        mat.raw_eta.copy_(DipoleMaterial(0.1, 1.0, 1.6).raw_eta)
    e16 = module(light, torch.ones(1, 3))
    fixed = IrradianceAtlas.from_atlas(atlas, 1.6)(light, torch.ones(1, 3))
    torch.testing.assert_close(e16, fixed.to(e16.dtype), rtol=1e-6, atol=1e-9)
    assert float((e13 - e16).abs().max()) > 1e-3


def test_render_device_is_checked_and_followed(tmp_path, capsys):
    """``device``: the CPU renders as before; an unknown or absent device is a typed error naming the argument."""
    from torchsss._checks import check_device
    from torchsss.registry import build_scene

    scene = Scene.from_dict(SCENE)
    assert check_device("cpu") == torch.device("cpu") and check_device(torch.device("cpu")).type == "cpu"
    with pytest.raises(TypeError, match=r"device: expected a str or torch\.device"):
        check_device(0)
    with pytest.raises(ValueError, match="device: expected a torch device"):
        check_device("gpu7")
    with pytest.raises(ValueError, match="device: expected 'cpu' or 'cuda'"):
        check_device("meta")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"device: expected an available device, got 'cuda'"):
            build_scene(scene, "splat", device="cuda")
    a = render_scene(scene, "splat", device="cpu", grid=24)
    b = render_scene(scene, "splat", grid=24)
    assert a.radiance.device.type == "cpu" and torch.equal(a.radiance, b.radiance)
    path = tmp_path / "s.json"
    path.write_text(json.dumps({**SCENE, "material": "skin1"}))
    out = tmp_path / "a.exr"
    assert main(["render", str(path), "--method", "splat", "--device", "cpu", "--out", str(out), "--no-progress"]) == 0
    assert json.loads(out.with_suffix(".json").read_text())["device"] == "cpu"
    with pytest.raises(SystemExit) as exc:
        main(["render", str(path), "--method", "splat", "--device", "gpu7", "--out", str(out), "--no-progress"])
    assert exc.value.code == 2 and "device: expected a torch device" in capsys.readouterr().err


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
def test_cli_renders_on_cuda_like_the_cpu(tmp_path):
    path = tmp_path / "s.json"
    path.write_text(json.dumps({**SCENE, "material": "skin1"}))
    outs = {}
    for dev in ("cpu", "cuda"):
        out = tmp_path / f"{dev}.exr"
        assert main(["render", str(path), "--method", "splat", "--eps", "0.03", "--device", dev, "--out", str(out),
                     "--no-progress"]) == 0
        outs[dev] = json.loads(out.with_suffix(".json").read_text())
    assert outs["cuda"]["device"].startswith("cuda")
    for a, b in zip(outs["cpu"]["mean_radiance_covered"], outs["cuda"]["mean_radiance_covered"]):
        assert abs(a - b) <= 1e-4 * abs(a)
