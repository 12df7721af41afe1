"""Lensch's throughput threshold, planned from the scene: geometry.lensch.throughput_cut (the share of the seen
radiosity the threshold cuts) and the planner's finer-threshold candidates (issue 14, "model only what a scene
requires": the far entries are kept only where the seen side is lit along them)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

import torchsss.plan as plan_mod
from torchsss.geometry import DirectionalLight, PointLight, sphere
from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.lensch import _absolute_threshold, _profile64, throughput_cut
from torchsss.modules import DipoleMaterial
from torchsss.plan import CUT_MATTERS, LENSCH_THRESHOLDS, SceneFacts, candidates, plan, predict

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_planner import make_scene

F64 = torch.float64


def _loop_cut(mesh, material, lights, eye, threshold):
    """The cut written out vertex pair by vertex pair over every facing vertex (no subsets), largest channel."""
    prof, c = _profile64(material, torch.device("cpu"))
    v, n, a = (t.detach().double() for t in (mesh.vertices, mesh.vertex_normals, mesh.vertex_areas))
    thr = _absolute_threshold(a, prof, threshold, True)
    eye = torch.tensor(eye, dtype=F64)
    e = torch.zeros(v.shape[0], c, dtype=F64)
    for light in lights:
        for i in range(v.shape[0]):
            if isinstance(light, PointLight):
                d = torch.tensor(light.position, dtype=F64) - v[i]
                cos = max(0.0, float(n[i] @ (d / d.norm())))
                e[i] += cos * torch.tensor(light.intensity, dtype=F64)[:c] / float(d @ d)
            else:
                cos = max(0.0, float(n[i] @ -torch.tensor(light.direction, dtype=F64)))
                e[i] += cos * torch.tensor(light.irradiance, dtype=F64)[:c]
    num = torch.zeros(c, dtype=F64)
    den = torch.zeros(c, dtype=F64)
    for j in range(v.shape[0]):
        view = eye - v[j]
        cos_v = float(n[j] @ view) / float(view.norm())
        if cos_v <= 0:
            continue
        w = float(a[j]) * cos_v / float(view @ view)
        total = torch.zeros(c, dtype=F64)
        kept = torch.zeros(c, dtype=F64)
        for i in range(v.shape[0]):
            rd = prof((v[i] - v[j]).norm().reshape(1, 1))[0]
            b = a[i] * e[i] * rd
            total += b
            if float(a[i] * rd.max()) >= thr:
                kept += b
        num += w * (total - kept) ** 2
        den += w * total ** 2
    return float((num / den).sqrt().max())


@pytest.mark.parametrize("light", [PointLight((-20.0, 10.0, -60.0), 4e3), DirectionalLight((0.3, 0.0, 1.0), 2.0)])
def test_throughput_cut_against_a_loop(light):
    """Every facing vertex as a receiver and every lit one as a source: equal to the pair-by-pair loop (1e-10)."""
    mesh = sphere(20.0, 1, dtype=F64)  # 42 vertices, 20 mm radius
    mat = DipoleMaterial.from_preset("wholemilk").double()
    eye = (0.0, 0.0, 80.0)
    for t in (1e-4, 1e-3):  # a coarse mesh: large vertex areas, so larger thresholds cut
        got = throughput_cut(mesh, mat, [light], eye, (t,), receivers=10_000)[0]
        want = _loop_cut(mesh, mat, [light], eye, t)
        assert want > 1e-4  # the test can tell a cut from none
        assert got == pytest.approx(want, rel=1e-10, abs=1e-14)


def test_throughput_cut_at_the_extremes():
    mesh = sphere(30.0, 3)
    mat = DipoleMaterial.from_preset("wholemilk")
    back = [PointLight((0.0, 0.0, -150.0), 1e4)]
    cuts = throughput_cut(mesh, mat, back, (0.0, 0.0, 130.0), LENSCH_THRESHOLDS)
    assert cuts[0] > 0.3 and cuts[0] >= cuts[1] >= cuts[2] >= 0.0  # finer thresholds cut less
    assert throughput_cut(mesh, mat, back, (0.0, 0.0, 130.0), (0.0,)) == (0.0,)  # nothing cut at 0
    front = throughput_cut(mesh, mat, [PointLight((0.0, 0.0, 150.0), 1e4)], (0.0, 0.0, 130.0), (1e-5,))
    assert front[0] < 1e-3  # the seen side lit directly: its near field is kept
    ketchup = throughput_cut(mesh, DipoleMaterial.from_preset("ketchup"), back, (0.0, 0.0, 130.0), (1e-5,))
    assert ketchup[0] > 0.05  # what little crosses 60 mm of ketchup does so along cut entries too
    dark = [PointLight((0.0, 0.0, -150.0), 0.0)]
    assert throughput_cut(mesh, mat, dark, (0.0, 0.0, 130.0), (1e-5,)) == (0.0,)  # nothing lit
    env = [EnvironmentLight.uniform(1.0)]
    assert throughput_cut(mesh, mat, env, (0.0, 0.0, 130.0), (1e-5,)) == (0.0,)  # environments are skipped
    assert throughput_cut(mesh, mat, back, (0.0, 0.0, 0.0), (1e-5,)) == (0.0,)  # the eye inside: nothing faces it
    sub = throughput_cut(sphere(30.0, 4), mat, back, (0.0, 0.0, 130.0), (1e-5,), max_sources=500)
    assert sub[0] > 0.3  # a random subset of the sources estimates the same share


def test_throughput_cut_rejects_a_bad_profile():
    with pytest.raises(TypeError, match="profile"):
        throughput_cut(sphere(10.0, 1), "wholemilk", [], (0.0, 0.0, 50.0))


@pytest.fixture(scope="module")
def backlit_sphere():
    """The planner verification's miss: a 60 mm whole-milk sphere lit from behind (7.4% at the default threshold)."""
    return make_scene("sphere 60 mm wholemilk back", "sphere", 60, "wholemilk", "back", 48)


def test_planner_keeps_the_far_entries_only_where_the_image_needs_them(backlit_sphere):
    facts = SceneFacts.from_scene(backlit_sphere)
    assert facts.throughput_cut[0] > 0.02 and facts.throughput_cut[1] < CUT_MATTERS
    assert len(facts.throughput_entries_finer) == 2 and facts.throughput_entries_finer[0] > facts.throughput_entries
    cands = [c for c in candidates(backlit_sphere, facts, 0.05, ["lensch"]) if c["method"] == "lensch"]
    finer = [c for c in cands if c["knobs"].get("threshold") == LENSCH_THRESHOLDS[1]]
    assert finer and all("cuts" in c["rules"]["threshold"] for c in cands)
    assert not any(c["knobs"].get("threshold") == LENSCH_THRESHOLDS[2] for c in cands)  # 1e-6 already keeps it
    coarse = predict("lensch", {"atlas_resolution": 1024}, facts, backlit_sphere.material)
    fine = predict("lensch", {"atlas_resolution": 1024, "threshold": 1e-6}, facts, backlit_sphere.material)
    assert coarse["error"] >= facts.throughput_cut[0] > fine["error"]
    assert fine["first_s"] > coarse["first_s"]  # more entries to evaluate
    p = plan(backlit_sphere, 0.05, frames=100, methods=["lensch"])
    assert p.knobs.get("threshold") == LENSCH_THRESHOLDS[1] and "threshold" in p.reasons
    # front-lit: nothing cut, no finer candidate, the default said
    front = make_scene("sphere 60 mm wholemilk front", "sphere", 60, "wholemilk", "front", 48)
    f2 = SceneFacts.from_scene(front)
    assert f2.throughput_cut[0] < CUT_MATTERS and f2.throughput_entries_finer == ()
    cands = [c for c in candidates(front, f2, 0.05, ["lensch"]) if c["method"] == "lensch"]
    assert cands and all("threshold" not in c["knobs"] and "(default)" in c["rules"]["threshold"] for c in cands)


def test_finer_threshold_over_the_cap_is_not_offered(backlit_sphere, monkeypatch):
    monkeypatch.setattr(plan_mod, "MAX_THROUGHPUT_ENTRIES", 5_000_000)  # under the 1e-6 throughput's ~6.6M
    facts = SceneFacts.from_scene(backlit_sphere)
    cands = [c for c in candidates(backlit_sphere, facts, 0.05, ["lensch"]) if c["method"] == "lensch"]
    assert cands and not any("threshold" in c["knobs"] for c in cands)
    assert all("over the cap: not offered" in c["rules"]["threshold"] for c in cands)


def test_finer_threshold_renders_the_backlit_sphere_within_tolerance(backlit_sphere):
    """At 48 x 48 and atlas 256: the default threshold 8.9% against the reference, 1e-6 2.3% (measured)."""
    from torchsss.trade import image_error, run_config

    truth, _ = run_config(backlit_sphere, "reference", {}, 1, torch.float32)
    coarse, _ = run_config(backlit_sphere, "lensch", {"atlas_resolution": 256}, 1, torch.float32)
    fine, _ = run_config(backlit_sphere, "lensch", {"atlas_resolution": 256, "threshold": 1e-6}, 1, torch.float32)
    e_coarse, e_fine = image_error(coarse, truth)["rel_rmse"], image_error(fine, truth)["rel_rmse"]
    assert e_coarse > 0.06 and e_fine < 0.035, (e_coarse, e_fine)
