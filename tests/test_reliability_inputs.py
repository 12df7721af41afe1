"""Reliability of the user-facing boundaries: unreadable meshes, a camera looking away, wrong atlas sizes, overflow."""

from __future__ import annotations

import pytest
import torch

from torchsss.geometry import Camera, PointLight, build_atlas, camera_gbuffer, sphere
from torchsss.geometry.loading import load_mesh
from torchsss.modules import DipoleMaterial
from torchsss.modules.chang import ImportanceSampledTranslucency
from torchsss.pipelines import build
from torchsss.scene import Scene


def _scene(mesh: str) -> Scene:
    return Scene.from_dict({"mesh": mesh, "material": "skin1",
                            "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
                            "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 8, "height": 8}})


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl"])
def test_unreadable_mesh_files_name_the_file_and_the_scene_key(tmp_path, suffix):
    path = tmp_path / f"noise{suffix}"
    path.write_bytes(bytes(range(256)) * 3)
    with pytest.raises(ValueError, match=r"scene\.mesh: source: expected a .*noise") as err:
        _scene(str(path)).load_mesh()
    assert str(path) in str(err.value)
    with pytest.raises(ValueError, match=str(path).replace("\\", "\\\\")):
        load_mesh(path)


def test_a_camera_looking_away_is_told_so():
    mesh = sphere(10.0, 2)
    away = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 120.0), width=8, height=8)
    with pytest.raises(ValueError, match="camera looks away from the object"):
        camera_gbuffer(mesh, away)
    close = Camera(eye=(0.0, 0.0, 9.0), target=(0.0, 0.0, 0.0), width=8, height=8)
    with pytest.raises(ValueError, match="inside or too close"):
        camera_gbuffer(mesh, close)


def test_lensch_module_names_an_irradiance_of_the_wrong_atlas_size():
    r = build("lensch", sphere(8.0, 2), "skin1", atlas_resolution=64, blend=False)
    with pytest.raises(ValueError, match=r"irradiance: expected shape \(B, C, H, W\) with H=64"):
        r.module(torch.ones(1, 3, 32, 32))
    out = r.module(torch.zeros(1, 3, 64, 64))
    assert out.shape == (1, 3, 64, 64) and bool((out == 0).all())


def test_icdf_module_names_an_overflowing_irradiance():
    mesh = sphere(10.0, 2)
    atlas = build_atlas(mesh, 64, kernel_size=3)
    module = ImportanceSampledTranslucency.from_atlas(atlas, DipoleMaterial.from_preset("skin1"))
    e = torch.full((1, 3, 64, 64), 3e38) * atlas.valid_mask
    u = torch.rand(1, 16, 2)
    rec = atlas.position[0, :, 32, 32].view(1, 1, 3)
    with pytest.raises(ValueError, match="irradiance: expected values whose area-weighted sum is finite"):
        module(e, u, rec)
    assert bool(torch.isfinite(module(e * 1e-30, u, rec)).all())


def test_a_light_looking_at_the_object_still_renders():
    r = build("splat", sphere(8.0, 2), "skin1", grid=16)
    res = r.render([PointLight((0.0, 0.0, 40.0), 1e3)], Camera(eye=(0, 0, 45), target=(0, 0, 0), width=8, height=8))
    assert bool(torch.isfinite(res.radiance).all()) and float(res.radiance.max()) > 0
