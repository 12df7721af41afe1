"""Surface samples for the reference, and scene files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from torchsss.geometry.loading import builtin_mesh_names
from torchsss.geometry.procedural import plane, sphere, torus
from torchsss.geometry.sampling import subdivision_barycentrics, surface_samples
from torchsss.scene import Material, Scene, default_scene_path, load_scene


@pytest.mark.parametrize("n", [1, 2, 3, 7])
def test_subdivision_centroids(n):
    b = subdivision_barycentrics(n)
    assert b.shape == (n * n, 3)
    torch.testing.assert_close(b.sum(-1), torch.ones(n * n, dtype=torch.float64))
    assert bool((b > 0).all())
    # centroids of a regular subdivision average to the triangle's centroid
    torch.testing.assert_close(b.mean(0), torch.full((3,), 1 / 3, dtype=torch.float64))
    assert len({tuple(round(v, 9) for v in row) for row in b.tolist()}) == n * n


@pytest.mark.parametrize("mesh_fn", [lambda: sphere(10.0, 3), lambda: torus(), lambda: plane(20.0, 10.0, 4)])
def test_samples_area_and_spacing(mesh_fn):
    mesh = mesh_fn().with_dtype(torch.float64)
    s = surface_samples(mesh, 0.5)
    assert s.area.sum().item() == pytest.approx(mesh.area, rel=1e-12)
    # every sample lies on its face: reconstruct from barycentrics
    tri = mesh.triangles()[s.face_id]
    torch.testing.assert_close(torch.einsum("nk,nkc->nc", s.bary, tri), s.position)
    torch.testing.assert_close(s.normal.norm(dim=-1), torch.ones_like(s.area))
    # sub-triangle edge bound: per-face sample area <= equilateral area of the spacing (or the face is tiny)
    assert float(s.area.max()) <= 0.5**2 * 3**0.5 / 4 * 1.0001 or float(s.area.max()) <= mesh.face_areas.max()


def test_samples_guard():
    with pytest.raises(ValueError, match="max_samples"):
        surface_samples(sphere(10.0, 2), 0.01, max_samples=1000)
    with pytest.raises(ValueError, match="spacing_mm"):
        surface_samples(sphere(10.0, 2), 0.0)


def test_default_scene_parses():
    s = load_scene(default_scene_path())
    assert s.mesh == "spot" and s.size_mm == 40.0 and s.material.name == "skin1"
    assert len(s.lights) >= 1 and s.camera.width > 0
    mesh = s.load_mesh()
    assert mesh.size_mm == pytest.approx(40.0, rel=1e-5)


def _scene(**over):
    d = {"mesh": "sphere", "size_mm": 20, "material": "marble",
         "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
         "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 32, "height": 32}}
    d.update(over)
    return d


def test_scene_relative_mesh_path(tmp_path):
    sphere(5.0, 2).to_trimesh().export(tmp_path / "ball.obj")
    (tmp_path / "s.json").write_text(json.dumps(_scene(mesh="ball.obj", size_mm=None)))
    s = load_scene(tmp_path / "s.json")
    assert s.load_mesh().size_mm == pytest.approx(sphere(5.0, 2).size_mm, rel=1e-5)


@pytest.mark.parametrize(("over", "exc", "match"), [
    ({"colour": 1}, ValueError, "unknown keys"),
    ({"size_mm": -3}, ValueError, "size_mm"),
    ({"size_mm": "big"}, ValueError, "size_mm"),
    ({"material": "jade"}, ValueError, "jade"),
    ({"material": {"sigma_a": [1, 1], "sigma_s_prime": [1, 1, 1]}}, ValueError, "sigma_a"),
    ({"material": {"sigma_a": [0, 0, 0], "sigma_s_prime": [0, 1, 1]}}, ValueError, "sigma_s_prime"),
    ({"material": 3}, TypeError, "material"),
    ({"lights": []}, ValueError, "lights"),
    ({"camera": [1, 2]}, TypeError, "camera"),
    ({"mesh": 5}, TypeError, "mesh"),
    ({"decimate": 2}, ValueError, "decimate"),
])
def test_scene_errors(over, exc, match):
    with pytest.raises(exc, match=match):
        Scene.from_dict(_scene(**over))


def test_scene_missing_file_and_bad_json(tmp_path):
    with pytest.raises(ValueError, match="mesh"):
        Scene.from_dict(_scene(mesh="nope.obj"), base_dir=tmp_path).load_mesh()
    with pytest.raises(ValueError, match="scene"):
        load_scene(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_scene(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="missing keys"):
        Scene.from_dict({"mesh": "sphere"})


def test_material_custom_tensors():
    m = Material.from_json({"sigma_a": 0.1, "sigma_s_prime": [1.0, 2.0, 3.0], "eta": 1.5})
    sa, ss, eta = m.tensors(torch.float32)
    assert sa.tolist() == pytest.approx([0.1] * 3) and ss.tolist() == [1.0, 2.0, 3.0] and eta.item() == 1.5


def test_example_scenes_resolve(shared_dir):
    scenes = sorted((Path(__file__).resolve().parents[1] / "examples" / "scenes").glob("*.json"))
    assert len(scenes) >= 3
    for path in scenes:
        s = load_scene(path)
        source = s.mesh_source()
        # A scene names either a built-in procedural mesh or a mesh file that must exist.
        assert source in builtin_mesh_names() or Path(source).is_file(), path
