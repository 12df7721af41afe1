"""examples/fit_material.py (issue 18): the log sigma_tr / albedo-ratio material, the orbit cameras, and a tiny fit
end to end (targets by the reference, fit through splat, JSON and PNGs written)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import fit_material

sys.path.pop(0)

from torchsss.geometry import Camera
from torchsss.modules import DipoleMaterial, check_profile
from torchsss.physics import total_diffuse_reflectance


def test_log_material_is_the_dipole_with_other_parameters():
    sa, ss = [0.0024, 0.009, 0.12], [0.68, 0.70, 0.55]
    m = fit_material.LogDipoleMaterial(sa, ss, 1.3, dtype=torch.float64)
    ref = DipoleMaterial(sa, ss, 1.3, dtype=torch.float64)
    check_profile(m)
    torch.testing.assert_close(m.sigma_a, ref.sigma_a, rtol=1e-12, atol=0)
    torch.testing.assert_close(m.sigma_s_prime, ref.sigma_s_prime, rtol=1e-12, atol=0)
    r = torch.linspace(0.0, 20.0, 50, dtype=torch.float64).unsqueeze(-1)
    torch.testing.assert_close(m(r), ref(r), rtol=1e-10, atol=0)
    # the parameters are log sigma_tr = log sqrt(3 sigma_a sigma_t') and log(sigma_s' / sigma_a)
    sa_t, ss_t = torch.tensor(sa, dtype=torch.float64), torch.tensor(ss, dtype=torch.float64)
    torch.testing.assert_close(m.log_sigma_tr, 0.5 * torch.log(3 * sa_t * (sa_t + ss_t)), rtol=1e-12, atol=0)
    torch.testing.assert_close(m.log_albedo_ratio, torch.log(ss_t / sa_t), rtol=1e-12, atol=0)
    # gradients reach them through the albedo
    (g,) = torch.autograd.grad(total_diffuse_reflectance(m.sigma_a, m.sigma_s_prime, m.eta).sum(),
                               [m.log_albedo_ratio])
    assert bool((g > 0).all())  # a higher albedo reflects more


def test_orbit_cameras_keep_distance_and_height():
    cam = Camera(eye=(75.0, 18.0, 45.0), target=(0.0, 0.0, 0.0), width=8, height=8)
    cams = fit_material.orbit_cameras(cam, 4)
    assert cams[0].eye == pytest.approx(cam.eye)
    for c in cams:
        assert math.dist(c.eye, c.target) == pytest.approx(math.dist(cam.eye, cam.target))
        assert c.eye[1] == pytest.approx(18.0)  # rotated about up = y
    assert cams[2].eye[0] == pytest.approx(-75.0) and cams[2].eye[2] == pytest.approx(-45.0)


def test_tiny_fit_end_to_end(tmp_path):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({
        "mesh": "sphere", "size_mm": 16.0, "material": "skin1",
        "lights": [{"type": "point", "position": [40, 20, 30], "intensity": 3000}],
        "camera": {"eye": [0, 10, 60], "target": [0, 0, 0], "fov_deg": 25, "width": 16, "height": 16}}))
    out = tmp_path / "fit.json"
    res = fit_material.main([str(scene), "--target-material", "potato", "--views", "2", "--size", "16", "--optimizer",
                             "adam", "--steps", "4", "--rebuild-every", "2", "--no-progress", "--json", str(out),
                             "--save-targets", "--sensitivity"])
    saved = json.loads(out.read_text())
    assert saved["fitted"] == res["fitted"] and saved["method"] == "splat" and saved["rebuilds"] == 2
    assert len(saved["loss"]) == 5 and saved["loss"][-1] < saved["loss"][0]
    assert set(saved["relative_error"]) == {"sigma_a", "sigma_s_prime", "eta"}
    assert saved["fitted"]["eta"] == pytest.approx(1.3, rel=1e-6)  # held
    sen = saved["sensitivity"]  # what the images tell apart: every coefficient moves its channel
    assert all(0 < x < 1 for x in sen["sigma_a"] + sen["sigma_s_prime"]) and len(sen["method_error"]) == 3
    assert sen["sigma_a"][2] > sen["sigma_a"][0]  # potato's blue absorbs 50x more than its red: more visible
    for name in ("fit_loss.png", "fit_side_by_side.png", "fit_target0.exr", "fit_target1.exr"):
        assert (tmp_path / name).is_file(), name
    # the EXR targets are accepted as input (the same views), and fit from there
    res2 = fit_material.main([str(scene), "--targets", str(tmp_path / "fit_target0.exr"),
                              str(tmp_path / "fit_target1.exr"), "--optimizer", "adam", "--steps", "1",
                              "--no-progress", "--out", str(tmp_path / "exr")])
    assert res2["views"] == 2 and res2["size"] == [16, 16]
    assert res2["loss"][0] == pytest.approx(saved["loss"][0], rel=1e-4)  # the same targets, the same start
