"""Several objects in one scene: merging meshes, object ids, the "objects" scene format, render dispatch."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import pytest
import torch

from torchsss.cli import main
from torchsss.geometry.loading import load_mesh
from torchsss.geometry.objects import merge_meshes, object_ids, object_masks
from torchsss.geometry.procedural import sphere, torus
from torchsss.pipelines.splat import render_splat
from torchsss.registry import OBJECT_METHODS, render_scene
from torchsss.scene import Material, Scene, SceneObject, load_scene

ROOT = Path(__file__).resolve().parents[1]
TWO = ROOT / "examples" / "scenes" / "two_objects.json"

BASE = {
    "objects": [
        {"mesh": "sphere", "size_mm": 20, "material": "marble", "translate": [-5.7, 0, 0]},
        {"mesh": "torus", "size_mm": 10, "material": "skin1", "translate": [8, 1, -2], "decimate": 200},
    ],
    "lights": [{"type": "point", "position": [-50, 15, -45], "intensity": 6000}],
    "camera": {"eye": [0, 5, 70], "target": [0, 0, 0], "width": 16, "height": 16},
}


# -- merge_meshes / object ids ---------------------------------------------------------------------------------------
def test_merge_meshes_offsets_and_ids():
    a, b, c = sphere(5.0, 1), torus(), sphere(2.0, 0)
    m, ids = merge_meshes([a, b, c])
    assert m.num_vertices == a.num_vertices + b.num_vertices + c.num_vertices
    assert m.num_faces == a.num_faces + b.num_faces + c.num_faces
    assert ids.dtype == torch.int64 and ids.shape == (m.num_faces,)
    counts = torch.bincount(ids).tolist()
    assert counts == [a.num_faces, b.num_faces, c.num_faces]
    # every face of the merged mesh is the same triangle (positions, winding) as the original's
    originals = torch.cat([a.triangles(), b.triangles(), c.triangles()])
    assert torch.equal(m.triangles(), originals)
    fa, fb = a.num_faces, a.num_faces + b.num_faces
    assert int(m.faces[:fa].max()) < a.num_vertices
    assert int(m.faces[fa:fb].min()) == a.num_vertices
    assert int(m.faces[fb:].min()) == a.num_vertices + b.num_vertices
    assert m.area == pytest.approx(a.area + b.area + c.area, rel=1e-6)


def test_merge_meshes_single_and_errors():
    a = sphere(5.0, 1)
    m, ids = merge_meshes([a])
    assert torch.equal(m.vertices, a.vertices) and torch.equal(m.faces, a.faces)
    assert bool((ids == 0).all()) and ids.shape == (a.num_faces,)
    with pytest.raises(ValueError, match="meshes"):
        merge_meshes([])
    with pytest.raises(TypeError, match="meshes"):
        merge_meshes(a)
    with pytest.raises(TypeError, match=r"meshes\[1\]"):
        merge_meshes([a, "sphere"])
    with pytest.raises(TypeError, match=r"meshes\[1\].*dtype"):
        merge_meshes([a, a.with_dtype(torch.float64)])


def test_object_ids_and_masks():
    face_object = torch.tensor([0, 0, 1, 2, 1])
    face_id = torch.tensor([[-1, 0, 1], [2, 3, 4]]).view(1, 1, 2, 3)
    ids = object_ids(face_id, face_object)
    expected = [[-1 if f < 0 else int(face_object[f]) for f in row] for row in face_id[0, 0].tolist()]
    assert ids.dtype == torch.int64 and ids[0, 0].tolist() == expected
    masks = object_masks(ids, 3)
    assert masks.shape == (1, 3, 2, 3)
    assert masks.sum(1)[0].tolist() == [[0, 1, 1], [1, 1, 1]]  # background in no mask, others in one
    for k in range(3):
        assert torch.equal(masks[0, k], ids[0, 0] == k)
    with pytest.raises(ValueError, match="face_id"):
        object_ids(torch.tensor([[[[5]]]]), face_object)
    with pytest.raises(ValueError, match="face_id"):
        object_ids(torch.tensor([[[[-2]]]]), face_object)
    with pytest.raises(TypeError, match="face_id"):
        object_ids(torch.zeros(1, 1, 2, 2), face_object)
    with pytest.raises(ValueError, match="face_id"):
        object_ids(torch.zeros(2, 2, dtype=torch.int64), face_object)
    with pytest.raises(ValueError, match="num_objects"):
        object_masks(ids, 0)


# -- the scene format ------------------------------------------------------------------------------------------------
def test_objects_scene_parses_and_loads():
    s = Scene.from_dict(BASE)
    assert s.mesh is None and s.material is None and s.size_mm is None
    assert [o.material.name for o in s.objects] == ["marble", "skin1"]
    assert s.objects[0].translate == (-5.7, 0.0, 0.0) and s.objects[1].decimate == 200
    loaded = s.load_objects(dtype=torch.float64)
    assert [mat.name for _, mat in loaded] == ["marble", "skin1"]
    # each mesh is the single-object load (centred, scaled), moved by its translation
    for (mesh, _), obj in zip(loaded, s.objects):
        alone = load_mesh(obj.mesh, obj.size_mm, decimate_to=obj.decimate, dtype=torch.float64)
        torch.testing.assert_close(mesh.vertices, alone.vertices + torch.tensor(obj.translate, dtype=torch.float64))
        assert torch.equal(mesh.faces, alone.faces)
    lo, hi = loaded[0][0].vertices.min(0).values, loaded[0][0].vertices.max(0).values
    torch.testing.assert_close((lo + hi) / 2, torch.tensor([-5.7, 0.0, 0.0], dtype=torch.float64))
    assert float((hi - lo).norm()) == pytest.approx(20.0, rel=1e-9)
    with pytest.raises(ValueError, match="objects"):
        s.load_mesh()
    assert s.mesh_sources() == ["sphere", "torus"] and s.mesh_source() == "sphere"


def test_single_object_scene_load_objects():
    d = {"mesh": "sphere", "size_mm": 20, "material": "skin1", "lights": BASE["lights"], "camera": BASE["camera"]}
    s = Scene.from_dict(d)
    assert s.objects == () and s.mesh == "sphere"
    ((mesh, mat),) = s.load_objects()
    assert mat.name == "skin1" and torch.equal(mesh.vertices, s.load_mesh().vertices)


def test_objects_in_a_file_resolve_relative_paths(tmp_path):
    load_mesh("sphere", 10.0).to_trimesh().export(tmp_path / "ball.obj")
    d = copy.deepcopy(BASE)
    d["objects"][1] = {"mesh": "ball.obj", "material": "ketchup", "translate": [20, 0, 0]}
    (tmp_path / "s.json").write_text(json.dumps(d))
    s = load_scene(tmp_path / "s.json")
    mesh, _ = s.load_objects()[1]
    assert float(mesh.vertices[:, 0].mean()) == pytest.approx(20.0, abs=0.1)
    d["objects"][1]["mesh"] = "missing.obj"
    (tmp_path / "t.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"objects\[1\]\.mesh"):
        load_scene(tmp_path / "t.json").load_objects()
    with pytest.raises(ValueError, match=r"objects\[1\]\.mesh"):
        load_scene(tmp_path / "t.json").mesh_sources()


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(mesh="sphere"), "exactly one of"),
    (lambda d: d.pop("objects"), "exactly one of"),
    (lambda d: d.update(material="marble"), "unknown keys.*material"),
    (lambda d: d.update(size_mm=20), "unknown keys.*size_mm"),
    (lambda d: d.update(caustics={}), "unknown keys.*caustics"),
    (lambda d: d.update(objects=[]), "scene.objects"),
    (lambda d: d.update(objects="sphere"), "scene.objects"),
    (lambda d: d["objects"][1].update(color=1), r"objects\[1\]: unknown keys.*color"),
    (lambda d: d["objects"][0].pop("material"), r"objects\[0\]: missing keys.*material"),
    (lambda d: d["objects"][0].update(translate=[1, 2]), r"objects\[0\].translate"),
    (lambda d: d["objects"][0].update(translate=[1, 2, float("nan")]), r"objects\[0\].translate"),
    (lambda d: d["objects"][0].update(size_mm=-1), r"objects\[0\].size_mm"),
    (lambda d: d["objects"][1].update(decimate=2), r"objects\[1\].decimate"),
    (lambda d: d["objects"][0].update(material="jelly"), "jelly"),
])
def test_objects_scene_errors(edit, match):
    d = copy.deepcopy(BASE)
    edit(d)
    with pytest.raises((ValueError, TypeError), match=match):
        Scene.from_dict(d)


def test_object_type_errors():
    with pytest.raises(TypeError, match=r"objects\[0\]"):
        Scene.from_dict({**BASE, "objects": [5]})
    with pytest.raises(TypeError, match=r"objects\[0\].mesh"):
        SceneObject.from_dict({"mesh": 3, "material": "marble"}, "scene.objects[0]")


def test_rescaled_objects():
    s = Scene.from_dict(BASE)
    t = s.rescaled(10.0)  # the largest object (20 mm) becomes 10 mm: f = 0.5
    assert [o.size_mm for o in t.objects] == [10.0, 5.0]
    assert t.objects[0].translate == (-2.85, 0.0, 0.0) and t.objects[1].translate == (4.0, 0.5, -1.0)
    assert t.lights[0].position == (-25.0, 7.5, -22.5) and t.lights[0].intensity == (1500.0, 1500.0, 1500.0)
    assert t.camera.eye == (0.0, 2.5, 35.0) and t.size_mm is None
    assert [o.material for o in t.objects] == [o.material for o in s.objects]
    # the loaded geometry is the original scaled about the origin
    a, b = s.load_objects(torch.float64), t.load_objects(torch.float64)
    for (ma, _), (mb, _) in zip(a, b):
        torch.testing.assert_close(mb.vertices, 0.5 * ma.vertices)
    d = copy.deepcopy(BASE)
    del d["objects"][1]["size_mm"]
    with pytest.raises(ValueError, match="size_mm"):
        Scene.from_dict(d).rescaled(10.0)
    with pytest.raises(ValueError, match="size_mm"):
        s.rescaled(0.0)


def test_example_scene_touches():
    s = load_scene(TWO)
    assert len(s.objects) == 2 and s.objects[0].material != s.objects[1].material
    (ma, _), (mb, _) = s.load_objects(torch.float64)
    gap = torch.cdist(ma.vertices, mb.vertices).min()
    assert float(gap) < 0.5  # the objects touch (within half a millimetre)


# -- dispatch --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["lensch", "icdf", "hybrid", "caustics"])
def test_single_object_methods_refuse_objects(method):
    s = Scene.from_dict(BASE)
    with pytest.raises(ValueError, match=r"renders one object.*|reference.*splat") as err:
        render_scene(s, method)
    assert "objects" in str(err.value) and all(m in str(err.value) for m in OBJECT_METHODS)


def test_single_entry_objects_renders_with_any_method():
    d = copy.deepcopy(BASE)
    d["objects"] = [{"mesh": "sphere", "size_mm": 20, "material": "skin1", "translate": [3, 0, 0]}]
    s = Scene.from_dict(d)
    got = render_scene(s, "splat", grid=32)
    mesh = load_mesh("sphere", 20.0)
    mesh = dataclasses.replace(mesh, vertices=mesh.vertices + torch.tensor([3.0, 0.0, 0.0]))
    want = render_splat(mesh, Material.from_json("skin1"), s.lights, s.camera, grid=32)
    assert bool(want.radiance.max() > 0)
    torch.testing.assert_close(got.radiance, want.radiance)


def test_cli_renders_objects(tmp_path, capsys):
    out = tmp_path / "o.exr"
    assert main(["render", str(TWO), "--method", "splat", "--resolution", "16x16", "--out", str(out),
                 "--no-progress"]) == 0
    summary = json.loads(out.with_suffix(".json").read_text())
    assert [o["material"]["name"] for o in summary["objects"]] == ["marble", "skin1"]
    assert summary["covered_pixels"] > 0 and summary["max_radiance"] > 0
    with pytest.raises(SystemExit) as ex:
        main(["render", str(TWO), "--method", "lensch", "--resolution", "16x16", "--out", str(out)])
    assert ex.value.code == 2
    assert "renders one object" in capsys.readouterr().err
