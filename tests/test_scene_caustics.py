"""Scene files: the "caustics" block, `render --method caustics` (Shah ch. 5), rescaling a scene to another size."""

from __future__ import annotations

import json

import pytest
import torch

from torchsss.cli import main
from torchsss.geometry.lights import surface_irradiance
from torchsss.registry import render_scene
from torchsss.scene import Caustics, Scene

BASE = {
    "mesh": "sphere", "size_mm": 34.64, "material": "marble",
    "lights": [{"type": "directional", "direction": [0.0, 0.0, -1.0], "irradiance": 1.0}],
    "camera": {"eye": [0.0, -70.0, 60.0], "target": [0.0, 0.0, -10.0], "up": [0, 0, 1], "fov_deg": 40.0,
               "width": 48, "height": 48},
}
CAUSTICS = {"ior": 1.5, "absorption": 0.0, "receiver": {"size_mm": 60, "center": [0, 0, -16]}, "grid": 64}


def test_caustics_block_parses_and_rejects_bad_values():
    s = Scene.from_dict({**BASE, "caustics": {**CAUSTICS, "ior": [1.45, 1.5, 1.55]}})
    assert s.caustics == Caustics(ior=(1.45, 1.5, 1.55), receiver_size_mm=60.0, receiver_center=(0.0, 0.0, -16.0),
                                  grid=64)
    assert Scene.from_dict(BASE).caustics is None
    bad = [({"ior": 0.0}, "ior"), ({"ior": [1.5, 1.5]}, "ior"), ({"absorption": -1.0}, "absorption"),
           ({"mode": "triple"}, "mode"), ({"grid": 4}, "grid"), ({"receiver": {"type": "sphere"}}, "type"),
           ({"receiver": {"center": [0, 0]}}, "center"), ({"receiver": {"size_mm": -5}}, "size_mm"),
           ({"colour": 1}, "unknown keys")]
    for change, match in bad:
        with pytest.raises(ValueError, match=match):
            Scene.from_dict({**BASE, "caustics": {**CAUSTICS, **change}})
    with pytest.raises(TypeError, match="caustics"):
        Scene.from_dict({**BASE, "caustics": 1.5})


def test_method_caustics_focuses_light_under_the_sphere():
    scene = Scene.from_dict({**BASE, "caustics": CAUSTICS})
    res = render_scene(scene, "caustics")
    img = res.radiance[0].sum(0)
    assert bool(torch.isfinite(res.radiance).all()) and bool(res.mask.any())
    # seen obliquely, the focus under the sphere is the brightest receiver pixel, far brighter than the directly
    # lit floor (irradiance 1, albedo 0.8: L = 0.8 / pi per channel)
    direct_level = 3 * 0.8 / torch.pi
    receiver = img[res.mask[0, 0]]
    assert float(receiver.max()) > 2.0 * direct_level, float(receiver.max())
    # most of the floor is directly lit at exactly that level (the plane is flat, the light uniform)
    lit = ((receiver - direct_level).abs() < 1e-3 * direct_level).float().mean()
    assert float(lit) > 0.5, float(lit)
    with pytest.raises(ValueError, match="caustics"):
        render_scene(Scene.from_dict(BASE), "caustics")


def test_cli_renders_a_caustics_scene(tmp_path):
    path = tmp_path / "glass.json"
    path.write_text(json.dumps({**BASE, "caustics": CAUSTICS}))
    assert main(["render", str(path), "--method", "caustics", "--out", str(tmp_path / "glass.exr"),
                 "--caustic-grid", "48"]) == 0
    assert (tmp_path / "glass.exr").is_file() and (tmp_path / "glass.png").is_file()
    summary = json.loads((tmp_path / "glass.json").read_text())
    assert summary["method"] == "caustics" and summary["options"]["grid"] == 48
    assert summary["knobs"]["grid"] == 48 and summary["setup_s"] >= 0 and len(summary["frame_s"]) == 1


def test_rescaled_scene_keeps_the_irradiance_at_corresponding_points():
    s = Scene.from_dict({**BASE, "lights": [{"type": "point", "position": [10.0, -20.0, 60.0], "intensity": 5e3},
                                            {"type": "directional", "direction": [0, 0, -1], "irradiance": 1.0}],
                         "caustics": CAUSTICS})
    t = s.rescaled(10.0)
    f = 10.0 / 34.64
    assert t.size_mm == 10.0 and t.camera.eye == pytest.approx(tuple(f * e for e in s.camera.eye))
    assert t.caustics.receiver_size_mm == pytest.approx(60 * f)
    assert t.lights[1] == s.lights[1]  # directional: unchanged
    pts = torch.tensor([[[1.0, 2.0, 3.0], [-4.0, 0.5, -2.0]]], dtype=torch.float64)
    nrm = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]]], dtype=torch.float64)
    e_s = surface_irradiance(pts, nrm, list(s.lights), 1.3)
    e_t = surface_irradiance(f * pts, nrm, list(t.lights), 1.3)
    torch.testing.assert_close(e_t, e_s, rtol=1e-10, atol=0.0)
    with pytest.raises(ValueError, match="size_mm"):
        s.rescaled(0.0)
    with pytest.raises(ValueError, match="size_mm"):
        Scene.from_dict({k: v for k, v in BASE.items() if k != "size_mm"}).rescaled(10.0)
