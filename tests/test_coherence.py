"""Tests of torchsss.geometry.coherence: light-view samples attached to the surface and reused across frames."""

from __future__ import annotations

import math

import pytest
import torch

from torchsss.geometry.coherence import AttachedSamples, _near_any, attach_light_view, coherent_light_samples
from torchsss.geometry.gbuffer import light_view
from torchsss.geometry.lights import DirectionalLight, PointLight
from torchsss.geometry.mesh import Mesh
from torchsss.geometry.procedural import plane, sphere, torus
from torchsss.geometry.shadow import bounding_sphere

LIGHT = PointLight((10.0, 20.0, 90.0), (1e4, 2e4, 3e4))


def _lit(lv):
    sel = lv.mask[0, 0] & (lv.irradiance[0].amax(0) > 0)
    return lv.position[0].permute(1, 2, 0)[sel], lv.flux[0].permute(1, 2, 0)[sel]


def _rot_y(deg: float, dtype=torch.float32) -> torch.Tensor:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=dtype)


def _moved(mesh: Mesh, vertices: torch.Tensor) -> Mesh:
    return Mesh(vertices, mesh.faces, name=mesh.name)


def test_light_view_bary_reproduces_positions():
    mesh = sphere(10.0, 3)
    lv = light_view(mesh, LIGHT, 32)
    m = lv.mask[0, 0]
    assert lv.bary.shape == (1, 3, 32, 32)
    bary = lv.bary[0].permute(1, 2, 0)[m]
    torch.testing.assert_close(bary.sum(-1), torch.ones(int(m.sum())))
    assert float(lv.bary[0].permute(1, 2, 0)[~m].abs().sum()) == 0.0
    corners = mesh.vertices[mesh.faces[lv.face_id[0, 0][m]]]
    torch.testing.assert_close((corners * bary.unsqueeze(-1)).sum(1), lv.position[0].permute(1, 2, 0)[m])


def test_first_frame_is_the_plain_light_view():
    mesh = sphere(10.0, 3)
    samples, pos, flux, stats = coherent_light_samples(mesh, LIGHT, 48, 1.3, None)
    want_pos, want_flux = _lit(light_view(mesh, LIGHT, 48, 1.3))
    assert torch.equal(pos[0], want_pos) and torch.equal(flux[0], want_flux)
    assert stats == {"new": want_pos.shape[0], "reused": 0, "dropped": 0, "merged": 0}
    assert samples.face_id.shape == samples.area.shape == samples.face_area.shape == (want_pos.shape[0],)


def test_attached_area_is_the_true_surface_area_at_any_tilt():
    # a 10 x 10 mm plane tilted by 70 degrees against a directional light: unclamped footprint / cos = 100 mm^2
    mesh = plane(10.0, 10.0, 2)
    for tilt in (0.0, 70.0):
        d = (math.sin(math.radians(tilt)), 0.0, -math.cos(math.radians(tilt)))
        s = attach_light_view(mesh, light_view(mesh, DirectionalLight(d, 1.0), 128, fresnel="none"))
        assert float(s.area.sum()) == pytest.approx(100.0, rel=0.03)
        torch.testing.assert_close(s.face_area, mesh.face_areas[s.face_id])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_unmoved_mesh_and_light_reuse_everything(dtype):
    mesh = torus(12.0, 5.0, 32, 16, dtype=dtype)
    s1, pos1, flux1, _ = coherent_light_samples(mesh, LIGHT, 40, 1.3, None)
    s2, pos2, flux2, st = coherent_light_samples(mesh, LIGHT, 40, 1.3, s1)
    assert st["new"] == 0 and st["dropped"] == 0 and st["reused"] == pos1.shape[1]
    # float64: the re-projection reproduces the samples and their flux to rounding (measured 3e-14). float32: the
    # re-projected samples' rounding gives their neighbours partition weights of ~1e-4, which moved 3 of 2841 flux
    # values by up to 1.1e-3 relative on one machine (and < 1e-3 on another)
    tol = {"pos": 1e-10, "rtol": 1e-9, "carry": 1e-9} if dtype == torch.float64 else \
        {"pos": 1e-5, "rtol": 3e-3, "carry": 1e-4}
    torch.testing.assert_close(pos2, pos1, rtol=0, atol=tol["pos"])
    torch.testing.assert_close(flux2, flux1, rtol=tol["rtol"], atol=1e-7)
    assert torch.equal(s2.face_id, s1.face_id)
    _, _, flux3, st = coherent_light_samples(mesh, LIGHT, 40, 1.3, s1, mode="carry")
    assert st["new"] == 0 and st["dropped"] == 0
    torch.testing.assert_close(flux3, flux1, rtol=tol["carry"], atol=1e-7)


def test_rigid_translation_with_the_light_changes_nothing():
    mesh = sphere(8.0, 3, dtype=torch.float64)
    s1, pos1, flux1, _ = coherent_light_samples(mesh, LIGHT, 32, 1.3, None)
    shift = torch.tensor([7.0, -3.0, 5.0], dtype=torch.float64)
    light2 = PointLight(tuple(p + float(d) for p, d in zip(LIGHT.position, shift)), LIGHT.intensity)
    _, pos2, flux2, st = coherent_light_samples(_moved(mesh, mesh.vertices + shift), light2, 32, 1.3, s1)
    assert st["new"] == 0 and st["dropped"] == 0
    torch.testing.assert_close(pos2, pos1 + shift, rtol=0, atol=1e-9)
    torch.testing.assert_close(flux2, flux1, rtol=1e-9, atol=0)


@pytest.mark.parametrize("scale", [1.2, 2.0])
def test_stretched_faces_scale_the_reused_area(scale):
    mesh = plane(10.0, 10.0, 4, dtype=torch.float64)
    light = DirectionalLight((0.0, 0.0, -1.0), 2.0)
    s1, _, flux1, _ = coherent_light_samples(mesh, light, 24, 1.3, None)
    stretched = _moved(mesh, mesh.vertices * torch.tensor([scale, 1.0, 1.0], dtype=torch.float64))
    # constant cos and irradiance: the flux of a reused sample is its old flux times the face's area ratio
    _, _, flux2, st = coherent_light_samples(stretched, light, 24, 1.3, s1, mode="carry", max_stretch=3.0)
    assert st["reused"] == flux1.shape[1]
    torch.testing.assert_close(flux2[:, : st["reused"]], flux1 * scale, rtol=1e-9, atol=0)
    fresh = float(light_view(stretched, light, 24, 1.3).flux.sum())
    assert float(flux2.sum()) == pytest.approx(fresh, rel=0.05)  # new samples only fill the plane's edges
    # with a max_stretch below the area a sample now covers in current light-view pixels, all are resampled:
    # that area is scale * (pixel size before / after)^2, the orthographic pixel size proportional to the
    # bounding-sphere radius that the light camera frames
    covered = scale * (bounding_sphere(mesh)[1] / bounding_sphere(stretched)[1]) ** 2
    _, _, _, st = coherent_light_samples(stretched, light, 24, 1.3, s1, mode="carry", max_stretch=0.99 * covered)
    assert st["reused"] == 0
    _, _, _, st = coherent_light_samples(stretched, light, 24, 1.3, s1, mode="carry", max_stretch=1.01 * covered)
    assert st["reused"] == flux1.shape[1]


def test_samples_rotated_to_the_dark_side_are_dropped():
    mesh = sphere(10.0, 3, dtype=torch.float64)
    light = DirectionalLight((0.0, 0.0, -1.0), 1.0)  # lights the +z hemisphere
    s1, _, _, _ = coherent_light_samples(mesh, light, 32, 1.3, None)
    rot = _rot_y(70.0, torch.float64)
    s2, _, _, st = coherent_light_samples(_moved(mesh, mesh.vertices @ rot.T), light, 32, 1.3, s1)
    # independent prediction: a sample stays lit when its rotated face normal still faces +z
    normal = (mesh.face_normals[s1.face_id] @ rot.T)[:, 2]
    dark = normal <= 0
    assert int(dark.sum()) > 50
    assert st["dropped"] >= int(dark.sum())
    kept = s2.face_id[: st["reused"]]
    assert bool(((mesh.face_normals[kept] @ rot.T)[:, 2] > 0).all())


def test_samples_hidden_behind_another_part_are_dropped():
    a, b = sphere(8.0, 3, dtype=torch.float64), sphere(8.0, 3, dtype=torch.float64)
    off = torch.tensor([20.0, 0.0, 0.0], dtype=torch.float64)
    faces = torch.cat([a.faces, b.faces + a.num_vertices])
    mesh = Mesh(torch.cat([a.vertices + off, b.vertices - off]), faces)
    light = DirectionalLight((0.0, 0.0, -1.0), 1.0)
    s1, _, _, _ = coherent_light_samples(mesh, light, 48, 1.3, None)
    on_a = s1.face_id < a.num_faces
    assert 0 < int(on_a.sum()) < s1.face_id.shape[0]
    # move sphere A right under sphere B (seen from the light): A's lit side still faces the light but is hidden
    moved = _moved(mesh, torch.cat([a.vertices - off - torch.tensor([0.0, 0.0, 30.0], dtype=torch.float64),
                                    b.vertices - off]))
    # (max_stretch high: the light camera reframes the smaller bounding sphere, which would resample everything)
    s2, _, _, st = coherent_light_samples(moved, light, 48, 1.3, s1, max_stretch=10.0)
    assert st["dropped"] == int(on_a.sum())
    assert st["reused"] == int((~on_a).sum())
    assert bool((s2.face_id >= a.num_faces).all())  # A is entirely hidden: no new sample on it either


def test_small_rotation_conserves_the_flux():
    mesh = torus(12.0, 5.0, 32, 16).with_dtype(torch.float64)
    light = PointLight((-40.0, 50.0, 60.0), 1e4)
    prev = None
    for step in range(4):
        m = _moved(mesh, mesh.vertices @ _rot_y(1.5 * step, torch.float64).T)
        prev, _, flux, st = coherent_light_samples(m, light, 48, 1.3, prev)
        fresh = float(light_view(m, light, 48, 1.3).flux.sum())
        assert float(flux.sum()) == pytest.approx(fresh, rel=0.03)
    assert st["reused"] > 0.8 * flux.shape[1]


def test_merge_mm_controls_which_new_samples_are_added():
    mesh = plane(10.0, 10.0, 4, dtype=torch.float64)
    light = DirectionalLight((0.0, 0.0, -1.0), 1.0)
    s1, pos1, _, _ = coherent_light_samples(mesh, light, 16, 1.3, None)
    # (a translation would not do: the light camera follows the mesh, pixels hit the same points again)
    shifted = _moved(mesh, mesh.vertices * torch.tensor([1.05, 1.0, 1.0], dtype=torch.float64))
    _, _, _, huge = coherent_light_samples(shifted, light, 16, 1.3, s1, mode="carry", merge_mm=100.0)
    _, _, _, tiny = coherent_light_samples(shifted, light, 16, 1.3, s1, mode="carry", merge_mm=1e-6)
    assert huge["new"] == 0 and huge["merged"] == tiny["new"] and huge["reused"] == tiny["reused"]
    assert huge["reused"] >= 0.8 * pos1.shape[1]  # (samples that slid off the plane's edge pixels are dropped)
    n_lit = _lit(light_view(shifted, light, 16, 1.3))[0].shape[0]
    assert tiny["merged"] == 0 and tiny["new"] == n_lit


def test_near_any_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    q, p = torch.rand(300, 2, generator=g) * 20, torch.rand(200, 2, generator=g) * 20
    qz, pz = torch.rand(300, generator=g), torch.rand(200, generator=g)
    radius, ztol = 0.3 + torch.rand(300, generator=g), torch.full((300,), 0.5)
    got = _near_any(q, p, radius, qz, pz, ztol)
    d = torch.cdist(q.double(), p.double())
    want = ((d < radius.double()[:, None]) & ((qz[:, None] - pz[None]).abs() <= 0.5)).any(1)
    assert torch.equal(got, want) and 0 < int(got.sum()) < 300
    assert not bool(_near_any(q, p[:0], radius, qz, pz[:0], ztol).any())


def test_bad_inputs_raise():
    mesh = sphere(10.0, 2)
    s, _, _, _ = coherent_light_samples(mesh, LIGHT, 16, 1.3, None)
    with pytest.raises(TypeError, match="previous"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, (s.face_id, s.bary))
    with pytest.raises(ValueError, match=r"previous\.face_id"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s._replace(face_id=s.face_id + mesh.num_faces))
    with pytest.raises(ValueError, match=r"previous\.bary"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s._replace(bary=s.bary[:, :2]))
    with pytest.raises(ValueError, match="merge_mm"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s, merge_mm=0.0)
    with pytest.raises(ValueError, match="max_stretch"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s, max_stretch=-1.0)
    with pytest.raises(ValueError, match="mode"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s, mode="copy")
    with pytest.raises(ValueError, match="weights"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s, weights="gauss")
    with pytest.raises(ValueError, match="radius_px"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s, radius_px=0.0)
    with pytest.raises(TypeError, match="radius_px"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s, radius_px="1")
    with pytest.raises(ValueError, match="fresnel"):
        coherent_light_samples(mesh, LIGHT, 16, 1.3, s, fresnel="fast")
    with pytest.raises(ValueError, match="resolution"):
        coherent_light_samples(mesh, LIGHT, 0, 1.3, s)
    with pytest.raises(TypeError, match="light"):
        coherent_light_samples(mesh, "sun", 16, 1.3, s)
    with pytest.raises(TypeError, match="mesh"):
        coherent_light_samples(mesh.vertices, LIGHT, 16, 1.3, s)
    with pytest.raises(TypeError, match="lv"):
        attach_light_view(mesh, mesh)
    assert isinstance(s, AttachedSamples)


@pytest.mark.parametrize("weights", ["tent", "nearest"])
def test_partition_flux_equals_the_light_view_exactly(weights):
    # a rotating, non-uniformly stretching torus under a point light: the total is the fresh light view's every frame
    mesh = torus(12.0, 5.0, 32, 16).with_dtype(torch.float64)
    light = PointLight((-40.0, 50.0, 60.0), (1e4, 2e4, 3e4))
    prev, reused = None, 0
    for step in range(5):
        scale = torch.tensor([1.0 + 0.04 * step, 1.0, 1.0], dtype=torch.float64)
        m = _moved(mesh, (mesh.vertices * scale) @ _rot_y(2.0 * step, torch.float64).T)
        prev, pos, flux, st = coherent_light_samples(m, light, 40, 1.3, prev, weights=weights)
        fresh = light_view(m, light, 40, 1.3).flux.sum((0, 2, 3))
        torch.testing.assert_close(flux[0].sum(0), fresh, rtol=1e-10, atol=0)
        assert bool((flux[0].amax(-1) > 0).all())  # kept samples that receive nothing are dropped
        assert st["reused"] + st["new"] == flux.shape[1] and st["merged"] + st["new"] == int(_lit_count(m, light))
        # the kept samples sit where their attachment puts them on the current mesh
        k = st["reused"]
        corners = m.vertices[m.faces[prev.face_id[:k]]]
        torch.testing.assert_close(pos[0, :k], (corners * prev.bary[:k].unsqueeze(-1)).sum(1), rtol=0, atol=1e-12)
        reused = max(reused, k)
    assert reused > 0.8 * flux.shape[1]


def _lit_count(mesh, light):
    return _lit(light_view(mesh, light, 40, 1.3))[0].shape[0]


def test_partition_of_an_unmoved_mesh_is_the_light_view_in_float64():
    mesh = sphere(10.0, 3, dtype=torch.float64)
    s1, _, flux1, _ = coherent_light_samples(mesh, LIGHT, 32, 1.3, None)
    for weights in ("tent", "nearest"):
        s2, _, flux2, st = coherent_light_samples(mesh, LIGHT, 32, 1.3, s1, weights=weights)
        assert st == {"new": 0, "reused": flux1.shape[1], "dropped": 0, "merged": flux1.shape[1]}
        torch.testing.assert_close(flux2, flux1, rtol=1e-9, atol=0)
        torch.testing.assert_close(s2.area, s1.area, rtol=1e-9, atol=0)


def test_partition_refills_gaps_with_new_samples():
    # a plane stretched to twice its width: the kept samples are two light-view pixels apart along x (the light
    # camera reframes the larger bounding sphere, ~1.5 px), the pixels between them reach none within 0.5 px
    mesh = plane(10.0, 10.0, 4, dtype=torch.float64)
    light = DirectionalLight((0.0, 0.0, -1.0), 2.0)
    s1, _, _, _ = coherent_light_samples(mesh, light, 24, 1.3, None)
    wide = _moved(mesh, mesh.vertices * torch.tensor([2.0, 1.0, 1.0], dtype=torch.float64))
    fresh = float(light_view(wide, light, 24, 1.3).flux.sum())
    _, _, f_small, small = coherent_light_samples(wide, light, 24, 1.3, s1, radius_px=0.5)
    _, _, f_big, big = coherent_light_samples(wide, light, 24, 1.3, s1, radius_px=2.0)
    assert small["new"] > 0.2 * (small["new"] + small["merged"])
    assert big["new"] < small["new"] and big["reused"] >= small["reused"]
    for f in (f_small, f_big):
        assert float(f.sum()) == pytest.approx(fresh, rel=1e-10)
