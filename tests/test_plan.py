"""The planner (torchsss.plan): each "model only what a scene requires" rule on a scene built to trigger it, the
frames trade-off, measured trades, and the rules' physics (shadows, source decimation) against full renders."""

import dataclasses
import json
import math
import re
from pathlib import Path

import pytest
import torch

from torchsss.cli import main
from torchsss.geometry import Camera, PointLight, sphere
from torchsss.ops import fused
from torchsss.pipelines import build
from torchsss.pipelines.splat import MIN_GRID, splat_grid
from torchsss.plan import (
    MARGIN,
    MARGINS,
    MODEL,
    RULES,
    Plan,
    SceneFacts,
    candidates,
    detail_faces,
    hybrid_error,
    hybrid_local_bound,
    hybrid_local_plan,
    hybrid_split_plan,
    icdf_error,
    plan,
    plan_method,
    predict,
    sampling_spread,
    sampling_terms,
    source_count,
)
from torchsss.scene import Scene, default_scene_path, load_scene


@pytest.fixture(autouse=True)
def _fresh_process(monkeypatch):
    """Plan as a fresh ``python -m torchsss render`` does: compilation in its default mode, nothing compiled yet."""
    monkeypatch.setenv("TORCHSSS_COMPILE", "auto")
    monkeypatch.setattr(fused, "_WARM", set())


def _scene(mesh="sphere", size=20.0, material="skin1", res=16, light=(0.0, 0.0, 1.0), decimate=None):
    d = 2.5 * size
    s = {"mesh": mesh, "size_mm": size, "material": material,
         "lights": [{"type": "point", "position": [v * d for v in light], "intensity": 4 * d * d}],
         "camera": {"eye": [0, 0, d], "target": [0, 0, 0], "fov_deg": 30.0, "width": res, "height": res}}
    if decimate:
        s["decimate"] = decimate
    return Scene.from_dict(s)


def test_facts_closed_form_sphere():
    s = _scene(res=32)
    f = SceneFacts.from_scene(s)
    r = f.radius_mm
    assert f.convex
    assert f.area_mm2 == pytest.approx(4 * math.pi * r * r, rel=0.02)
    assert f.thickness_mm == pytest.approx(4 * r / 3, rel=0.03)  # mean chord of a ball: 4V/S = 4r/3
    # the Cauchy estimate of the covered pixels against the rasterised count
    ref = build("reference", s.load_mesh(), "skin1", spacing_mm=4.0).render(s.lights, s.camera)
    assert f.covered_px == pytest.approx(float(ref.mask.sum()), rel=0.25)
    assert f.sources[0] >= f.faces and list(f.sources) == sorted(f.sources, reverse=True)
    assert not SceneFacts.from_scene(_scene(mesh="torus")).convex


@pytest.mark.parametrize("mesh, light", [("sphere", (0.0, 0.0, 1.0)), ("slab", (0.0, 0.0, 1.0)),
                                         ("slab", (1.0, 0.0, 0.2)), ("torus", (0.0, 0.5, 1.0)),
                                         ("torus", (1.0, 0.0, 0.0))])
def test_light_fill_predicts_splats_light_view_samples(mesh, light):
    """SceneFacts.light_fill x grid^2 (the planner's splat count) against the splats the renderer makes at its own
    grid: within 12%, on a sphere (pi / 4 of the texels in closed form, a few more where grazing light at the rim
    cuts them), a slab lit face-on and edge-on (its fill differs 3x) and a torus lit from above and from the side."""
    s = _scene(mesh=mesh, size=20.0, material="marble", res=16, light=light)
    f = SceneFacts.from_scene(s, throughput=False, spread=False)
    if mesh == "sphere":
        assert math.pi / 4 <= f.light_fill <= 1.1 * math.pi / 4
    out = build("splat", s.load_mesh(), "marble", eps=0.01, oversample=2.0).render(s.lights, s.camera)
    grid, splats = out.stats["grid"], out.stats["splats"]
    assert grid > 40 and f.light_fill * grid * grid == pytest.approx(splats, rel=0.12), (f.light_fill, grid, splats)


def test_source_count_matches_sampler():
    from torchsss.geometry.sampling import surface_samples
    m = sphere(10.0, 3)
    for h in (0.5, 2.0, 8.0):
        assert source_count(m, h) == surface_samples(m, h).area.shape[0]


def test_rule_shadows_convex_only():
    conv = plan(_scene(), 0.05, methods=["reference"])
    assert conv.knobs.get("shadows") == "none" and "shadows" in conv.reasons and "shadow rays" in conv.skipped
    nonconv = plan(_scene(mesh="torus"), 0.05, methods=["reference"])
    assert "shadows" not in nonconv.knobs and "shadows" in nonconv.modelled


def test_rule_shadows_is_exact_on_convex_object():
    """The rule's premise: on a convex object shadows 'none' renders the image of ray-traced shadows (up to the
    few terminator samples whose smooth normal faces the light while a neighbouring facet blocks the ray)."""
    m = sphere(10.0, 3)
    lights = [PointLight((30.0, 10.0, 20.0), 5e3), PointLight((-20.0, 0.0, -30.0), 5e3)]
    cam = Camera(eye=(0, 0, 50), target=(0, 0, 0), width=20, height=20)
    a = build("reference", m, "marble", spacing_mm=1.5, shadows="none").render(lights, cam).radiance
    b = build("reference", m, "marble", spacing_mm=1.5, shadows="raytrace").render(lights, cam).radiance
    assert float((a - b).square().mean().sqrt() / b.square().mean().sqrt()) < 1e-3
    assert float((a - b).abs().max()) < 1e-3 * float(b.max())


def test_rule_sources_decimated():
    s = _scene(res=16)
    mesh = sphere(10.0, 6)  # 81920 faces, ~0.1 mm edges; skin1's spacing at eps 0.1 is ~1 mm
    p = plan(s, 0.05, methods=["reference"], mesh=mesh)
    assert p.knobs.get("source_faces") and p.knobs["source_faces"] < mesh.num_faces / 4
    assert "sources" in p.reasons


def test_reference_candidates_keep_the_full_sources_beside_the_decimated_ones():
    """Decimated sources are offered beside the full mesh's, never instead of them.

    An 8 mm potato torus at 256x256: every spacing asks for fewer samples than its 2,304 faces hold, and the mesh
    decimated to the spacing strays 1.4-2.8% (predicted) from the surface; with only those offered, the plan for 1%
    was the icdf estimator at N 65536 (10.7 s) where the full sources met it in 0.74 s (the second verification
    set, benchmarks/results/planner_fresh.md).
    """
    s = _scene(mesh="torus", size=8.0, material="potato", res=256, light=(1.0, 0.3, 0.1))
    facts = SceneFacts.from_scene(s)
    rows = [c for c in candidates(s, facts, 0.01, ["reference"])]
    full = [c for c in rows if "source_faces" not in c["knobs"]]
    fewer = [c for c in rows if "source_faces" in c["knobs"]]
    assert sorted(c["knobs"]["eps"] for c in full) == [0.01, 0.02, 0.05, 0.1, 0.2, 0.3]
    assert fewer and all(c["_sources"] < facts.faces for c in fewer)
    p = plan(s, 0.01, methods=["reference"])
    assert "source_faces" not in p.knobs and p.predicted_error * MARGINS["reference"] <= 0.01
    best_fewer = min(predict("reference", c["knobs"], facts, s.material, sources=c["_sources"])["error"]
                     for c in fewer)
    assert best_fewer * MARGINS["reference"] > 0.01  # only the full sources meet 1% here


def test_atlas_methods_charge_their_decimated_meshs_deviation():
    """icdf, hybrid and Lensch on the mesh decimated to the detail faces carry its surface deviation, as the
    reference's decimated sources do; undecimated, nothing is added.

    (The front-lit 40 mm skin2 igea of the second verification set: icdf N 4096 on 11,960 faces measured 2.06% where
    0.52% was predicted; the term now adds 1.2%.)
    """
    s = _scene(res=64)
    mesh = sphere(10.0, 6)  # 81920 faces: decimated for the atlas methods
    v = mesh.vertices
    u = v / v.norm(dim=1, keepdim=True)
    bumps = 1.0 + 0.02 * torch.sin(25 * u[:, 0]) * torch.sin(25 * u[:, 1]) * torch.sin(25 * u[:, 2] + 1.0)
    mesh = dataclasses.replace(mesh, vertices=v * bumps.unsqueeze(-1))
    f = SceneFacts.from_scene(s, mesh, throughput=False)
    target = detail_faces(f)
    assert target is not None and f.atlas_deviation_mm > 0
    from torchsss.geometry.mesh import decimate, surface_deviation

    assert f.atlas_deviation_mm == pytest.approx(surface_deviation(mesh, decimate(mesh, target)), rel=1e-3)
    term = f.atlas_deviation_mm / min(f.ell_mm)
    flat = dataclasses.replace(f, atlas_deviation_mm=0.0)
    for method, knobs in (("icdf", {"samples": 4096}), ("hybrid", {"samples": 4096}),
                          ("lensch", {"atlas_resolution": 512})):
        with_dev = predict(method, knobs, f, s.material, decimate=target)["error"]
        assert with_dev - predict(method, knobs, flat, s.material, decimate=target)["error"] == pytest.approx(term)
        coarser = predict(method, knobs, f, s.material, decimate=target // 2)["error"]
        assert coarser - predict(method, knobs, flat, s.material, decimate=target // 2)["error"] == \
            pytest.approx(2 * term, rel=1e-3)  # half the faces: about twice the squared edge
        assert predict(method, knobs, f, s.material)["error"] == predict(method, knobs, flat, s.material)["error"]


def test_rule_sources_charges_the_decimated_surfaces_deviation():
    # a bumpy sphere (a scan's detail): its sources on the mesh decimated to the spacing sit off the true surface,
    # and the predicted error carries that offset over the shortest 1/sigma_tr; a smooth sphere's barely moves
    import torch

    from torchsss.geometry.mesh import decimate, surface_deviation

    smooth = sphere(10.0, 6)
    v = smooth.vertices
    u = v / v.norm(dim=1, keepdim=True)
    bumps = 1.0 + 0.02 * torch.sin(25 * u[:, 0]) * torch.sin(25 * u[:, 1]) * torch.sin(25 * u[:, 2] + 1.0)
    bumpy = dataclasses.replace(smooth, vertices=v * bumps.unsqueeze(-1))
    s = _scene(res=16)
    preds = {}
    for name, mesh in (("smooth", smooth), ("bumpy", bumpy)):
        f = SceneFacts.from_scene(s, mesh)
        i = max(range(len(f.source_faces)), key=lambda k: f.source_deviation_mm[k])
        knobs = {"eps": [0.01, 0.02, 0.05, 0.1, 0.2, 0.3][i], "source_faces": f.source_faces[i]}
        dev = surface_deviation(mesh, decimate(mesh, f.source_faces[i]))
        assert f.source_deviation_mm[i] == pytest.approx(dev, rel=1e-3)  # the facts decimate in float64
        with_dev = predict("reference", knobs, f, s.material)["error"]
        without = predict("reference", knobs, dataclasses.replace(f, source_deviation_mm=()), s.material)["error"]
        assert with_dev - without == pytest.approx(f.source_deviation_mm[i] / min(f.ell_mm))
        preds[name] = dev
    assert preds["bumpy"] > 2.5 * preds["smooth"] > 0  # measured 0.0186 against 0.0058 mm
    # the coarse sphere strays by about its sagitta: e^2 / (8 R) for edges e on a radius R
    coarse = decimate(smooth, 1280)
    e2 = 4.0 * float(coarse.area) / coarse.num_faces / math.sqrt(3.0)  # equilateral faces of the same area
    r = float(smooth.vertices.norm(dim=1).mean())
    assert 0.2 * e2 / (8 * r) < surface_deviation(smooth, coarse) < 2.0 * e2 / (8 * r)
    assert surface_deviation(smooth, smooth) == 0.0
    with pytest.raises(ValueError, match="quantile"):
        surface_deviation(smooth, coarse, quantile=0.0)
    with pytest.raises(TypeError, match="coarse"):
        surface_deviation(smooth, None)


def test_margins_come_from_cross_validation():
    # every method's margin is at least the in-sample one, and matches the held-out rule of fit_planner --cv
    cv = json.loads((Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "planner_cv.json").read_text())
    for method, margin in MARGINS.items():
        assert margin >= MARGIN
        held = cv[method]["margin"]
        assert held is not None, method
        # the Monte Carlo estimators, and splat (the planner picks its cheapest false accepts: plan.MARGINS): above
        # the 5% rule, at most the no-miss margin
        if method in ("icdf", "hybrid", "splat"):
            assert max(MARGIN, held) <= margin <= cv[method]["margin_no_false_accept"], (method, margin, cv[method])
        else:
            assert margin == max(MARGIN, held), (method, margin, held)
    assert MARGINS["icdf"] == cv["icdf"]["margin_no_false_accept"]
    s = _scene(res=16, light=(-0.3, 0.2, -1.0))
    for method in ("icdf", "hybrid", "splat"):
        p = plan(s, 0.1, methods=[method])
        assert p.predicted_error * MARGINS[method] <= 0.1 < p.predicted_error * MARGINS[method] * 4


def test_source_faces_knob_against_full_sources():
    """Sources from a mesh decimated to the spacing (the planner's rule) render the full mesh's image to < 1%."""
    m = sphere(10.0, 6)  # 81920 faces, 0.1 mm edges: one sample per face, far finer than skin1's 0.6 mm spacing
    lights = [PointLight((40.0, 20.0, 30.0), 1e4)]
    cam = Camera(eye=(0, 0, 50), target=(0, 0, 0), width=12, height=12)
    full = build("reference", m, "skin1").render(lights, cam)
    facts = SceneFacts.from_scene(_scene(size=20 * math.sqrt(3)), m)  # the same sphere (r = 10 mm)
    wanted, predicted = facts.source_faces[0], facts.sources_decimated[0]
    dec = build("reference", m, "skin1", source_faces=wanted)
    n = dec.samples.area.shape[0]
    assert dec.source_mesh.num_faces <= 1.1 * wanted and n < full.stats["samples"] / 2
    assert 0.7 < predicted / n < 1.4  # the planner's estimate of the decimated source count
    img = dec.render(lights, cam)
    mk = full.mask.expand_as(full.radiance)
    err = float((img.radiance - full.radiance)[mk].square().mean().sqrt() / full.radiance[mk].square().mean().sqrt())
    assert err < 0.01
    with pytest.raises(ValueError, match="source_faces"):
        build("reference", m, "skin1", source_faces=2.5)


def test_rule_decimate_atlas_methods():
    s = _scene(res=16)
    mesh = sphere(10.0, 6)
    f = SceneFacts.from_scene(s, mesh)
    target = detail_faces(f)
    assert target is not None and 2000 <= target <= f.faces // 2
    p = plan(s, 0.2, methods=["icdf"], mesh=mesh)
    # the atlas is built on the decimated mesh; the camera sees the full one
    assert p.method == "icdf" and p.knobs["source_faces"] == target and p.decimate is None
    assert "decimate" in p.reasons and "camera sees the full mesh" in p.reasons["decimate"]
    assert any("detail beyond" in x for x in p.skipped)
    # a coarse mesh is kept
    assert detail_faces(SceneFacts.from_scene(s, sphere(10.0, 2))) is None


def test_lensch_decimation_fits_the_throughput_cap_on_the_bunny(shared_dir):
    # the 50 mm example bunny: at 0.6 of the cap the planned source mesh was estimated at 1.01e7 entries and the
    # builder refused it (benchmarks/bench_frames.py); the plan must pass the builder's own check
    from torchsss.geometry.lensch import MAX_THROUGHPUT_ENTRIES, THROUGHPUT_THRESHOLD, check_entries
    from torchsss.modules.material import material_module
    from torchsss.pipelines.atlas_view import source_mesh

    s = load_scene(Path(__file__).resolve().parents[1] / "examples" / "scenes" / "bunny.json")
    s = dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=256, height=256))
    knobs, _, _ = plan_method(s, "lensch", 0.03)
    mesh = source_mesh(s.load_mesh(), knobs["source_faces"])
    est = check_entries(mesh, material_module(s.material, dtype=mesh.vertices.dtype),
                        threshold=THROUGHPUT_THRESHOLD, relative=True, max_entries=MAX_THROUGHPUT_ENTRIES)
    assert 0.2 * MAX_THROUGHPUT_ENTRIES <= est <= MAX_THROUGHPUT_ENTRIES


def test_lensch_decimation_grows_into_the_cap(shared_dir):
    """The side-lit 30 mm marble bunny of the spread: 0.6 of the cap from the full mesh's estimate left the
    decimated mesh at 0.70 of it (5,360 faces; Lensch 3.0% there, 2.5% at 6,400); the planner now grows the
    decimation towards 0.85 of the cap, checked on the grown mesh, and stays within the builder's own check."""
    from torchsss.geometry.lensch import MAX_THROUGHPUT_ENTRIES, THROUGHPUT_THRESHOLD, check_entries
    from torchsss.modules.material import material_module
    from torchsss.pipelines.atlas_view import source_mesh

    d = 30.0
    s = Scene.from_dict({"mesh": str(shared_dir / "data" / "meshes" / "stanford-bunny.obj"), "size_mm": d,
                         "material": "marble",
                         "lights": [{"type": "point", "position": [2.5 * d, 0.5 * d, 0.0],
                                     "intensity": (2.5 * d) ** 2}],
                         "camera": {"eye": [0.0, 0.25 * d, 1.6 * d], "target": [0, 0, 0], "fov_deg": 30.0,
                                    "width": 256, "height": 256}})  # (a smaller image decimates further)
    knobs, _, _ = plan_method(s, "lensch", 0.03)
    mesh = source_mesh(s.load_mesh(), knobs["source_faces"])
    est = check_entries(mesh, material_module(s.material, dtype=mesh.vertices.dtype),
                        threshold=THROUGHPUT_THRESHOLD, relative=True, max_entries=MAX_THROUGHPUT_ENTRIES)
    assert knobs["source_faces"] > 5360 and 0.75 * MAX_THROUGHPUT_ENTRIES <= est <= 0.9 * MAX_THROUGHPUT_ENTRIES, \
        (knobs, est)


def test_rule_samples_from_tolerance():
    s = _scene(res=48, light=(-0.3, 0.2, -1.0))  # back-lit: the estimator's noise matters
    # not decimated for the atlas (at 16x16 it is, and the decimated mesh's deviation takes its share of the
    # tolerance: tested in test_atlas_methods_charge_their_decimated_meshs_deviation)
    assert detail_faces(SceneFacts.from_scene(s, throughput=False)) is None
    n = {t: plan(s, t, methods=["icdf"]).knobs["samples"] for t in (0.02, 0.01, 0.005)}
    assert n[0.02] < n[0.01] < n[0.005]
    # error ~ N^-0.78: halving the tolerance asks about 2.4x the samples (powers of two), more near the floor
    assert 2 <= n[0.01] / n[0.02] <= 4
    p = plan(s, 0.01, methods=["icdf"])
    assert p.predicted_error <= 0.01 and "samples" in p.reasons


def test_samples_below_the_floor_plan_the_most_accurate_hybrid():
    # the hybrid's local-filter floor exceeds 0.5%: no N meets it, yet `render --method hybrid` must not fall back to
    # the 4096-sample defaults but get the candidate whose sampling error sits under the floor
    s = _scene(res=16, light=(-0.3, 0.2, -1.0))
    facts = SceneFacts.from_scene(s)
    cand = [c for c in candidates(s, facts, 0.005, ["hybrid"]) if c["method"] == "hybrid"]
    assert len(cand) == 1 and "floor" in cand[0]["rules"]["samples"]
    n = cand[0]["knobs"]["samples"]
    assert 4096 < n <= 1 << 16
    pred = predict("hybrid", {"samples": n}, facts, s.material)["error"]
    floor = predict("hybrid", {"samples": 1 << 24}, facts, s.material)["error"]
    # misses the tolerance, sits within ~12% of the floor
    assert pred * MARGINS["hybrid"] > 0.005 and pred <= 1.15 * floor
    knobs, _, note = plan_method(s, "hybrid", 0.005)
    assert knobs["samples"] == n and "most accurate" in note


def test_hybrid_local_pairs_predicted_like_the_renderer_counts_them():
    # the default scene at 48 x 48: the renderer's surface local term at stride 1 lists every covered pixel's samples
    # within the local bound; the plan's count from the facts (samples x pi r_b^2 / area)
    s = load_scene(default_scene_path())
    s = dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=48, height=48))
    facts = SceneFacts.from_scene(s, throughput=False)
    stride, pairs, per = hybrid_local_plan(facts)
    assert stride == 1 and pairs == pytest.approx(per * facts.covered_px)
    res = build("hybrid", s.load_mesh(), s.material, samples=1024).render(s.lights, s.camera)
    st = res.stats
    assert st["local_term"] == "surface" and st["local_stride"] == 1
    assert facts.local_bound_mm == pytest.approx(st["local_bound_mm"], rel=1e-6)
    measured = st["local_pairs"] / float(res.mask.sum())
    assert per == pytest.approx(measured, rel=0.3)


def test_hybrid_split_narrowing_is_predicted_and_planned_with_the_sampled_near_field():
    s = _scene(mesh="torus", size=30.0, material="marble", res=64, light=(1.0, 0.3, 0.2))
    facts = SceneFacts.from_scene(s, throughput=False)
    assert facts.local_bound_mm > 0
    mat = s.material
    for_n = {"samples": 4096}
    stride, _, per = hybrid_local_plan(facts)
    assert stride >= 1 and per > 0
    assert hybrid_split_plan(facts)[:2] == (1, stride)
    plain = predict("hybrid", for_n, facts, mat)
    hf, ha, _ = sampling_terms(facts, "hybrid")
    assert plain["error"] == pytest.approx(math.hypot(hf, ha))  # the default split: the hybrid's own model
    assert facts.narrowed_bounds_mm == ()  # not needed: the default split fits
    # the renderer narrows c in steps of 2 while the pairs do not fit: seen by 16x the pixels (256 x 256) stride 8
    # cannot hold the pairs at c = 0.1, and the facts hold each step's local bound, which shrinks (0 where R_p
    # vanishes: the split narrowed away)
    s_big = dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=256, height=256))
    big = SceneFacts.from_scene(s_big, throughput=False)
    assert big.covered_px == pytest.approx(16 * facts.covered_px, rel=1e-6)
    bounds = big.narrowed_bounds_mm
    assert len(bounds) == 4 and all(b <= a for a, b in zip((big.local_bound_mm, *bounds), bounds))
    assert all(b == pytest.approx(hybrid_local_bound(_mat64(s), big.radius_mm, c=0.1 * 2 ** (i + 1)))
               for i, b in enumerate(bounds))
    # the first narrowed split whose pairs fit is taken, with its own stride and pairs, and the spread of the near
    # field it samples (its global part's), which exceeds the default split's and stays below the whole profile's
    assert hybrid_local_plan(big)[0] == -1
    scale, st, pairs, per_n = hybrid_split_plan(big)
    assert scale in (2, 4, 8, 16) and st >= 1 and per_n < per and pairs > 0
    assert bounds[(2, 4, 8, 16).index(scale)] > 0
    assert 0.0 < big.narrowed_spread < big.sampling_spread
    # its error: the larger of the hybrid's own model and the icdf estimator's with the narrowed split's spread
    for spread in (0.2, 50.0):
        nar = dataclasses.replace(big, narrowed_spread=spread)
        want = max(math.hypot(hf, ha), icdf_error(nar, 4096, spread=spread))
        assert predict("hybrid", for_n, nar, mat)["error"] == pytest.approx(want)
        assert hybrid_error(nar, 4096) == pytest.approx(want)
    assert icdf_error(dataclasses.replace(big, narrowed_spread=50.0), 4096, spread=50.0) > math.hypot(hf, ha)
    # nothing fits even at c x 16: the icdf estimator; every narrowed bound 0: narrowed away, the icdf estimator
    huge = dataclasses.replace(big, covered_px=facts.covered_px * 1e6, narrowed_bounds_mm=(4.0, 3.0, 2.0, 1.0))
    assert hybrid_split_plan(huge)[:2] == (16, -1)
    assert predict("hybrid", for_n, huge, mat)["error"] == pytest.approx(predict("icdf", for_n, huge, mat)["error"])
    away = dataclasses.replace(big, narrowed_bounds_mm=(0.0, 0.0, 0.0, 0.0))
    assert hybrid_split_plan(away) == (0, 0, 0.0, 0.0)
    assert predict("hybrid", for_n, away, mat)["error"] == pytest.approx(predict("icdf", for_n, away, mat)["error"])
    # the planned N follows the same model: the narrowed hybrid at a large spread plans at least the icdf's N at
    # the hybrid's margin on that spread
    tol = 0.05
    nar = dataclasses.replace(big, narrowed_spread=20.0)
    (hyb,) = [c for c in candidates(s, nar, tol, ["hybrid"]) if c["method"] == "hybrid"]
    assert "narrows to c = " in hyb["rules"]["local_term"] and "local_term" in RULES
    n = hyb["knobs"]["samples"]
    assert hybrid_error(nar, n) * MARGINS["hybrid"] <= tol < hybrid_error(nar, n // 2) * MARGINS["hybrid"]
    # strides grow with the pixels while they fit; the local term's pairs cost frame and setup time
    strides = [hybrid_local_plan(dataclasses.replace(facts, covered_px=facts.covered_px * f))[0]
               for f in (1, 2, 4, 8, 16, 64, 400)]
    order = [99 if st == -1 else st for st in strides]  # narrowed after every stride
    assert order == sorted(order) and strides[0] >= 1 and len(set(strides)) >= 3
    none = dataclasses.replace(facts, local_bound_mm=0.0)
    assert hybrid_local_plan(none) == (0, 0.0, 0.0) and hybrid_split_plan(none) == (0, 0, 0.0, 0.0)
    assert predict("hybrid", for_n, none, mat)["frame_s"] < plain["frame_s"]
    # no split: the hybrid is the icdf estimator (the teapot in ketchup at 3% was planned N = 1024 on the hybrid's
    # own model, 1.88% predicted, and measured 3.63%)
    assert predict("hybrid", for_n, none, mat)["error"] == pytest.approx(predict("icdf", for_n, none, mat)["error"])
    (off,) = [c for c in candidates(s, none, 0.05, ["hybrid"]) if c["method"] == "hybrid"]
    assert "split is off" in off["rules"]["local_term"]
    # the split is off where the bound exceeds 0.8 x the object's radius (build_hybrid's max_reach)
    m = _mat64(s)
    assert hybrid_local_bound(m, 1.0) == 0.0 and hybrid_local_bound(m, 100.0) > 0
    assert hybrid_local_bound(m, 100.0, c=0.4) < hybrid_local_bound(m, 100.0)
    # the bounds are the renderer's own: its default split and the narrowed ones it builds (their weight's tail at
    # most 2 R_p past R_p)
    renderer = build("hybrid", sphere(15.0, 2), "marble", samples=64)
    assert renderer.module.bound == pytest.approx(hybrid_local_bound(m, 100.0), rel=1e-6)
    for c in (0.2, 0.4, 0.8):
        module = renderer._split(c)[0]
        assert module.bound == pytest.approx(hybrid_local_bound(m, 100.0, c=c), rel=1e-6, abs=1e-9)


def _mat64(s):
    from torchsss.modules.material import material_module

    return material_module(s.material, dtype=torch.float64)


def test_hybrid_local_samples_follow_the_builders_decimation():
    # a finely tessellated 4 mm sphere (20,480 faces) in marble, whose spacing needs far fewer: the hybrid samples the
    # mesh decimated to the spacing (build_hybrid), not one sample per face as the full mesh's reference does
    from torchsss.geometry.sampling import faces_for_spacing, surface_samples
    from torchsss.pipelines.atlas_view import source_mesh
    from torchsss.pipelines.reference import default_spacing

    s = Scene.from_dict({"mesh": "sphere", "size_mm": 4.0, "material": "marble",
                         "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
                         "camera": {"eye": [0, 0, 100], "target": [0, 0, 0], "width": 16, "height": 16}})
    mesh = sphere(2.0, 5)
    assert mesh.num_faces == 20480
    facts = SceneFacts.from_scene(s, mesh, throughput=False)
    mat = _mat64(s)
    h = default_spacing(mat, mesh)
    built = surface_samples(source_mesh(mesh, faces_for_spacing(mesh.area, h)), h).area.shape[0]
    assert facts.local_samples == pytest.approx(built, rel=0.3)
    assert facts.local_samples < 0.5 * facts.sources[0]  # the reference's full-mesh count, which it used before


def test_sampling_spread_of_a_sampled_part():
    # sampling the part g = R_d / 2 (the rest computed exactly): the one-sample deviation of Phi g is half that of
    # Phi R_d, relative to the same radiosity; sampling nothing leaves no noise
    s = _scene(mesh="torus", size=20.0, material="skin1", light=(1.0, 0.3, 0.2))
    mesh = s.load_mesh()
    m = _mat64(s)
    whole = sampling_spread(mesh, m, s.lights, s.camera.eye)
    assert sampling_spread(mesh, m, s.lights, s.camera.eye, sampled=m) == pytest.approx(whole, rel=1e-4)
    half = sampling_spread(mesh, m, s.lights, s.camera.eye, sampled=lambda r: 0.5 * m(r))
    assert half == pytest.approx(0.5 * whole, rel=1e-3)
    assert sampling_spread(mesh, m, s.lights, s.camera.eye, sampled=lambda r: 0.0 * m(r)) == 0.0
    with pytest.raises(TypeError, match="sampled: expected a callable"):
        sampling_spread(mesh, m, s.lights, s.camera.eye, sampled=3.0)
    # a split of the profile itself (SplitProfile, the hybrid's global part) is weighed on the profile's table:
    # the same as the split evaluated through the formula (any callable)
    from torchsss.modules.chang import ChangLocalProfile, SplitProfile

    split = SplitProfile(m, ChangLocalProfile(1.0, 1.5, 3.0), "global")
    formula = sampling_spread(mesh, m, s.lights, s.camera.eye, sampled=lambda r: split(r))
    tabled = sampling_spread(mesh, m, s.lights, s.camera.eye, sampled=split)
    assert 0.0 < tabled < whole and tabled == pytest.approx(formula, rel=1e-3)
    local = SplitProfile(m, ChangLocalProfile(1.0, 1.5, 3.0), "local")
    assert sampling_spread(mesh, m, s.lights, s.camera.eye, sampled=local) == pytest.approx(
        sampling_spread(mesh, m, s.lights, s.camera.eye, sampled=lambda r: local(r)), rel=1e-3)


def test_source_mesh_ladder_decimates_from_the_coarsest_finer_mesh_made():
    from torchsss.plan import _source_mesh

    mesh = sphere(10.0, 5)  # 20480 faces
    direct = _source_mesh(mesh, 4000)
    assert _source_mesh(mesh, 4000) is direct and 3800 <= direct.num_faces <= 4200  # remembered
    stand_in = _source_mesh(mesh, 1000, ladder=True)
    assert 950 <= stand_in.num_faces <= 1050
    assert _source_mesh(direct, 1000).vertices.shape == stand_in.vertices.shape  # made from the 4,000 faces
    assert torch.equal(_source_mesh(direct, 1000).vertices, stand_in.vertices)
    assert _source_mesh(mesh, 1000) is not stand_in  # the renderers' count is decimated from the full mesh
    assert _source_mesh(mesh, 10 ** 6) is mesh


def test_splat_truncation_and_sample_floor_hold_whatever_the_light():
    # the predicted error holds the truncation the scene's facts computed (truncation_error at r_max(eps), SPLAT_EPS)
    # and, for an eps they do not hold, the planar tail between r_max and the object's diameter (closed form: at
    # most eps itself); nothing is dropped where r_max spans the object (a 5 mm chicken1 bunny, front-lit, measured
    # 2.72% at eps 0.03 and 0.1 alike, every oversample: its error is not the truncation's); the floor holds too
    from torchsss.physics.budget import profile_tail_fraction
    from torchsss.plan import SPLAT_EPS, _Profile

    for size in (5.0, 80.0):
        s = _scene(res=16, light=(0.0, 0.0, 1.0), material="chicken1", size=size)
        facts = SceneFacts.from_scene(s)
        prof = _Profile.of(s.material)
        assert len(facts.splat_truncation) == len(SPLAT_EPS)
        for eps in (0.003, 0.01, 0.03, 0.1):
            r, diameter = prof.r_max(eps), 2.0 * facts.radius_mm
            cut = prof.tail_between(r, diameter)
            mt = [t.double() for t in prof.mt]
            t_r = profile_tail_fraction(torch.tensor(r, dtype=torch.float64), *mt)
            t_d = profile_tail_fraction(torch.tensor(diameter, dtype=torch.float64), *mt)
            assert cut == pytest.approx(float((t_r - t_d).clamp_min(0).max()), rel=1e-9)
            assert cut <= eps * (1 + 1e-6) and (cut == 0.0) == (r >= diameter)
            err = predict("splat", {"eps": eps, "oversample": 4.0}, facts, s.material)["error"]
            floor = MODEL["splat_floor"] * max(facts.unlit, 0.1) ** MODEL["splat_u_floor"]
            trunc = facts.splat_truncation[SPLAT_EPS.index(eps)] if eps in SPLAT_EPS else cut
            assert err >= max(trunc, floor * 0.999)
            if r >= diameter and eps in SPLAT_EPS:
                assert trunc == 0.0
        assert prof.tail_between(prof.r_max(0.03), 1e6) == pytest.approx(0.03, rel=1e-6)  # an unbounded object
    # a loose tolerance plans no fewer samples than the calibration measured (the N^-p law is not extrapolated)
    for method in ("icdf", "hybrid"):
        assert plan(s, 0.5, methods=[method]).knobs["samples"] >= 1024


def _loop_truncation(mesh, profile, light_dir, eye, radii):
    """truncation_error as loops over receivers and sources in float64 (faces at their centroids, the own face a
    disk, the annulus inside two face spacings in the receiver's plane)."""
    from torchsss.plan import _disk_moments

    v, f = mesh.vertices.double(), mesh.faces
    tri = v[f]
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    area = 0.5 * cross.norm(dim=-1)
    normal = cross / (2 * area[:, None])
    c = tri.mean(1)
    to_light = -torch.tensor(light_dir, dtype=torch.float64)
    to_light = to_light / to_light.norm()
    e = (normal @ to_light).clamp_min(0.0)
    eye_t = torch.tensor(eye, dtype=torch.float64)
    near = 2.0 * math.sqrt(float(area.mean()))

    def prof(x):
        return profile(x.reshape(-1, 1)).double().reshape(-1)

    def disk(radius):
        return _disk_moments(lambda x: profile(x).double(), torch.tensor([radius], dtype=torch.float64))[0][0]

    num = [0.0] * len(radii)
    den = 0.0
    for i in range(f.shape[0]):
        view = eye_t - c[i]
        cos = float(normal[i] @ view / view.norm())
        if cos <= 0:
            continue
        w = float(area[i]) * cos / float(view.norm()) ** 2
        lum = e[i] * disk(math.sqrt(float(area[i]) / math.pi))
        far = [torch.zeros(3, dtype=torch.float64) for _ in radii]
        for j in range(f.shape[0]):
            if j == i or e[j] <= 0:
                continue
            d = float((c[i] - c[j]).norm())
            contrib = prof(torch.tensor([d], dtype=torch.float64)) * e[j] * area[j]
            lum = lum + contrib
            for k, radius in enumerate(radii):
                if d > max(radius, near):
                    far[k] = far[k] + contrib
        for k, radius in enumerate(radii):
            if radius < near:
                far[k] = far[k] + e[i] * (disk(near) - disk(radius))
            num[k] += w * float(far[k].square().sum())
        den += w * float(lum.square().sum())
    return [math.sqrt(n / den) for n in num]


def test_truncation_error_against_a_loop_reference_and_closed_forms():
    # the pairs in float32 through the profile's table, against float64 loops; a radius past the object drops
    # nothing, a larger radius never more; a wide face-on slab (80 mm, skin1) drops what the plane's tail says
    # (the channels' tails weighted by their radiosity), at two face resolutions alike
    from torchsss.geometry import DirectionalLight
    from torchsss.geometry.procedural import slab
    from torchsss.modules import DipoleMaterial
    from torchsss.physics import total_diffuse_reflectance
    from torchsss.physics.budget import profile_tail_fraction
    from torchsss.plan import truncation_error

    mat = DipoleMaterial.from_preset("marble")
    mesh = sphere(6.0, 1)  # 80 faces: no decimation, every receiver kept
    radii = (0.3, 2.0, 5.0, 9.0, 20.0)
    light = DirectionalLight((0.3, -0.2, -1.0), 1.0)
    got = truncation_error(mesh, mat, [light], (0.0, 0.0, 40.0), radii)
    with torch.no_grad():
        want = _loop_truncation(mesh, mat, (0.3, -0.2, -1.0), (0.0, 0.0, 40.0), radii)
    assert got == pytest.approx(want, rel=2e-3, abs=1e-7)
    assert got[-1] == 0.0 and list(got) == sorted(got, reverse=True) and got[0] > 0.5
    skin = DipoleMaterial.from_preset("skin1")
    sa, ss = skin.sigma_a.detach().double(), skin.sigma_s_prime.detach().double()
    lum = total_diffuse_reflectance(sa, ss).reshape(-1)
    for radius in (2.0, 4.0):
        tail = profile_tail_fraction(torch.tensor(radius, dtype=torch.float64), sa, ss).reshape(-1)
        plane = float(((tail * lum).square().sum() / lum.square().sum()).sqrt())
        for segments in (16, 48):
            wide = slab(80.0, 80.0, 4.0, segments=segments)
            (t,) = truncation_error(wide, skin, [DirectionalLight((0, 0, -1), 1.0)], (0.0, 0.0, 300.0), (radius,))
            assert t == pytest.approx(plane, rel=0.2), (radius, segments, t, plane)
    with pytest.raises(ValueError, match="radii"):
        truncation_error(mesh, mat, [light], (0.0, 0.0, 40.0), (-1.0,))
    with pytest.raises(ValueError, match="eye"):
        truncation_error(mesh, mat, [light], (0.0, 0.0), (1.0,))
    with pytest.raises(TypeError, match="profile"):
        truncation_error(mesh, "marble", [light], (0.0, 0.0, 40.0), (1.0,))


def test_rule_splat_budget_tighter_for_lower_tolerance():
    # a back-lit 40 mm skin1 spot: the profile's tail beyond r_max lies on the object, the budget matters
    s = _scene(mesh="spot", size=40.0, res=32, light=(-0.5, 0.4, -1.0))
    loose, tight = plan(s, 0.3, methods=["splat"]), plan(s, 0.07, methods=["splat"])
    assert loose.method == tight.method == "splat"
    mesh = s.load_mesh()
    grid = {id(p): splat_grid(mesh, s.material, p.knobs["eps"], oversample=p.knobs["oversample"])
            for p in (loose, tight)}
    assert grid[id(tight)] >= grid[id(loose)] >= MIN_GRID and loose.predicted_frame_s <= tight.predicted_frame_s
    assert tight.predicted_error * MARGINS["splat"] <= 0.07 < loose.predicted_error * MARGINS["splat"]
    assert "splat_budget" in tight.reasons


def test_rule_blend_reported():
    s = _scene(res=16)
    coarse = [c for c in candidates(s, SceneFacts.from_scene(s, sphere(10.0, 1)), 0.05, ["lensch"])]
    fine = [c for c in candidates(s, SceneFacts.from_scene(s, sphere(10.0, 4)), 0.05, ["lensch"])]
    assert all("skipped" in c["rules"]["blend"] for c in coarse)
    assert any("on" in c["rules"]["blend"] for c in fine)


def test_lensch_offers_the_unblended_1024_atlas_and_picks_it_as_the_most_accurate():
    # re-measured at 96 x 96 on four calibration scenes: atlas 1024 unblended 0.20-2.04%, 512 blended 2.0-6.6%
    s = load_scene(default_scene_path())
    facts = SceneFacts.from_scene(s)
    lensch = {c["knobs"]["atlas_resolution"]: c for c in candidates(s, facts, 0.03, ["lensch"])}
    assert set(lensch) == {256, 512, 1024}
    assert "skipped" in lensch[1024]["rules"]["blend"]
    knobs, _, note = plan_method(s, "lensch", 0.03)  # met within its margin
    assert knobs["atlas_resolution"] == 1024 and "planned for 3%" in note
    knobs, _, note = plan_method(s, "lensch", 0.01)  # below its floor: the most accurate configuration
    assert knobs["atlas_resolution"] == 1024 and "most accurate" in note
    # the note gives the prediction with the margin that kept it out (1.79% predicted was read as within 2%)
    err = float(re.search(r"\(([0-9.]+)% predicted, ([0-9.]+)% with the planner's safety margin 1.25\)", note)[1])
    assert err * 1.25 > 1.0
    # no blending fit in the 1024 build: its predicted setup is below the blended 512 one's
    pred = {r: predict("lensch", {"atlas_resolution": r}, facts, s.material) for r in (512, 1024)}
    assert "on" in lensch[512]["rules"]["blend"] and pred[1024]["setup_s"] < pred[512]["setup_s"]
    assert pred[1024]["error"] < pred[512]["error"]


def test_lensch_setup_carries_its_first_frames_profile_evaluations():
    """The first frame after a build evaluates the profile at every throughput entry and kernel tap (3-4 s at atlas
    1024 on the shared meshes): charged with the setup, separately given as ``first_s``, growing with the entries
    (the full mesh's estimate scaled by faces^2, capped) and the atlas; none of it without an entry estimate but
    the taps; the blended build's full planes at k^2 taps."""
    s = load_scene(default_scene_path())
    facts = SceneFacts.from_scene(s)
    assert facts.throughput_entries > 1_000_000
    zero = {"lensch_t_entry": 0.0, "lensch_t_tap": 0.0, "lensch_t_tap_full": 0.0}
    for res in (512, 1024):
        p = predict("lensch", {"atlas_resolution": res}, facts, s.material)
        bare = predict("lensch", {"atlas_resolution": res}, facts, s.material, model=zero)
        assert p["first_s"] > 0.0 and bare["first_s"] == 0.0
        assert p["setup_s"] == pytest.approx(bare["setup_s"] + p["first_s"])
        assert p["frame_s"] == bare["frame_s"] and p["error"] == bare["error"]
    full = predict("lensch", {"atlas_resolution": 1024}, facts, s.material)
    fewer = predict("lensch", {"atlas_resolution": 1024, "source_faces": facts.faces // 2}, facts, s.material)
    unknown = predict("lensch", {"atlas_resolution": 1024}, dataclasses.replace(facts, throughput_entries=-1),
                      s.material)
    assert unknown["first_s"] < fewer["first_s"] < full["first_s"]
    assert full["first_s"] - unknown["first_s"] == pytest.approx(MODEL["lensch_t_entry"] * facts.throughput_entries)
    taps = predict("lensch", {"atlas_resolution": 1024}, facts, s.material, model={"lensch_t_entry": 0.0})
    assert taps["first_s"] == pytest.approx(MODEL["lensch_t_tap"] * 1024 ** 2 * 49)  # unblended: k = 7
    blended = predict("lensch", {"atlas_resolution": 512}, facts, s.material, model={"lensch_t_entry": 0.0})
    assert blended["first_s"] > MODEL["lensch_t_tap_full"] * 512 ** 2 * 49  # blended: k > 7, full planes


def test_rule_reference_when_cheapest():
    p = plan(_scene(res=8), 0.02)
    assert p.method == "reference" and "reference" in p.reasons


def test_frames_amortise_setup():
    s = load_scene(default_scene_path())
    one, many = plan(s, 0.05, frames=1), plan(s, 0.05, frames=10_000)
    assert many.predicted_frame_s <= one.predicted_frame_s
    assert many.predicted_total_s <= one.predicted_setup_s + 10_000 * one.predicted_frame_s
    for p in (one, many):  # the chosen candidate is the cheapest qualifying one
        ok = [c for c in p.candidates if c["error"] * MARGINS[c["method"]] <= 0.05]
        assert min(c["total_s"] for c in ok) == pytest.approx(p.predicted_total_s)


def test_compiled_kernels_are_charged_once_per_process(monkeypatch):
    # 256 x 256 of the default scene: the reference's all-pairs frame is over COLD_WORK pairs (a cold compile)
    s = load_scene(default_scene_path())
    f = SceneFacts.from_scene(s)
    assert f.covered_px * f.sources[0] >= fused.COLD_WORK
    cold = predict("reference", {}, f, s.material)
    warm = predict("reference", {}, f, s.material, warm=frozenset({"plain"}))
    assert cold["compile_s"] > 0 and warm["compile_s"] == 0
    assert cold["setup_s"] - warm["setup_s"] == pytest.approx(cold["compile_s"])
    assert warm["frame_s"] == pytest.approx(cold["frame_s"])
    # the hybrid needs the split variant: a warm plain kernel does not spare its compile, but inductor is up (a
    # further variant's compile is charged, not the first's)
    hyb = predict("hybrid", {"samples": 65536}, f, s.material, warm=frozenset({"plain"}))["compile_s"]
    assert hyb == MODEL["fused_variant_s"] < MODEL["fused_compile_s"]
    assert predict("hybrid", {"samples": 65536}, f, s.material)["compile_s"] == MODEL["fused_compile_s"]
    # compilation switched off: the eager rate, no compile
    monkeypatch.setenv("TORCHSSS_COMPILE", "0")
    off = predict("reference", {}, f, s.material)
    assert off["compile_s"] == 0 and off["frame_s"] > 3 * cold["frame_s"]
    # plan() reads the process's state: the same plan, cheaper, once the plain kernel is compiled
    monkeypatch.setenv("TORCHSSS_COMPILE", "auto")
    p0 = plan(s, 0.001, methods=["reference"])
    assert "compile" in p0.reasons and "charged" in p0.reasons["compile"]
    fused._WARM.add(("dipole_pair_sum", "cpu", torch.float32, 1, 3, None, False, False))
    assert fused.is_warm("dipole_pair_sum") and not fused.is_warm("dipole_pair_sum", split=True)
    p1 = plan(s, 0.001, methods=["reference"])
    assert "already compiled" in p1.reasons["compile"]
    assert p0.predicted_setup_s - p1.predicted_setup_s == pytest.approx(MODEL["fused_compile_s"])


def test_compiled_pairs_are_costed_in_whole_blocks(monkeypatch):
    """The compiled pair sum pads receivers and sources to whole blocks (fused.block_shape): a warm reference frame
    of 363 sources costs as many pairs as one of 2,048, and one of 2,049 twice that; splat's compiled gather the
    same over its light view's sources (the light view's fill x grid^2)."""
    monkeypatch.setenv("TORCHSSS_COMPILE", "on")
    s = _scene(res=64)
    f = SceneFacts.from_scene(s, throughput=False, spread=False)
    rb, sb = fused.block_shape("cpu")
    warm = frozenset({"plain", "truncated"})

    def pair_s(n):
        p = predict("reference", {}, f, s.material, sources=n, warm=warm)
        return p["frame_s"] - MODEL["ref_t_src"] * n - MODEL["ref_t_px"] * f.pixels

    blocks = math.ceil(f.covered_px / rb)
    assert pair_s(363) == pytest.approx(MODEL["fused_t_pair"] * blocks * rb * sb)
    assert pair_s(2048) == pytest.approx(pair_s(363)) and pair_s(2049) == pytest.approx(2 * pair_s(2048))
    small = dataclasses.replace(f, light_fill=100 / 32 ** 2)  # 100 splats at grid 32 (oversample 1, eps 0.03)
    sp = predict("splat", {"eps": 0.03, "oversample": 1.0}, small, s.material, warm=warm)
    texels = MODEL["splat_t_texel"] * 32 * 32 + MODEL["splat_f0"]
    assert sp["frame_s"] - texels == pytest.approx(MODEL["splat_t_gather"] * blocks * rb * sb)


def test_lensch_is_not_costed_below_its_floor():
    # below Lensch's error floor (x its margin) no Lensch candidate can qualify: the plan skips them, and their
    # throughput estimate (most of the facts' time); asked for by name, Lensch is planned as before
    s = _scene(res=16)
    p = plan(s, 0.02)
    assert "lensch" in p.reasons and not any(c["method"] == "lensch" for c in p.candidates)
    assert p.facts["throughput_entries"] == -1
    q = plan(s, 0.02, methods=["lensch"])
    assert q.method in ("lensch", "reference") and q.facts["throughput_entries"] > 0
    assert any(c["method"] == "lensch" for c in q.candidates)
    # above its floor it is costed unless its setup and frames alone exceed the best other plan (then its
    # throughput estimate is skipped too, and the reason says so)
    loose = plan(_scene(res=16, size=21.0), 0.5)
    assert loose.predicted_total_s < 3.0 and loose.facts["throughput_entries"] == -1
    assert "exceed the best other plan" in loose.reasons["lensch"]
    assert not any(c["method"] == "lensch" for c in loose.candidates)
    free = plan(s, 0.5, model={"lensch_s0": 0.0, "lensch_f0": 0.0})  # no lower bound: always costed
    assert any(c["method"] == "lensch" for c in free.candidates) and "lensch" not in free.reasons
    assert free.facts["throughput_entries"] > 0


def test_measured_trade_overrides_predictions():
    s = load_scene(default_scene_path())
    p = plan(s, 0.05)
    assert any(c["method"] == p.method and c["knobs"] == p.knobs for c in p.candidates)  # a candidate, not the truth
    knobs = dict(p.knobs)
    if p.decimate:
        knobs["decimate"] = p.decimate
    trade = {"rows": [{"method": p.method, "knobs": knobs, "rel_rmse": 0.5, "setup_s": 0.1, "frame_s": 0.1}]}
    q = plan(s, 0.05, trade=trade)
    assert (q.method, q.knobs) != (p.method, p.knobs)
    measured = [c for c in q.candidates if c["source"] == "measured"]
    assert len(measured) == 1 and measured[0]["error"] == 0.5


def test_predict_monotone_in_knobs():
    s = _scene(res=32)
    f = SceneFacts.from_scene(s)
    e = [predict("icdf", {"samples": n}, f, s.material)["error"] for n in (1024, 4096, 16384)]
    assert e[0] > e[1] > e[2]
    t = [predict("icdf", {"samples": n}, f, s.material)["frame_s"] for n in (1024, 4096, 16384)]
    assert t[0] < t[1] < t[2]
    with pytest.raises(ValueError, match="method"):
        predict("magic", {}, f, s.material)


def test_plan_bad_input():
    s = _scene()
    for bad in (0.0, 1.0, -0.1, True, "0.1"):
        with pytest.raises(ValueError, match="tolerance"):
            plan(s, bad)
    with pytest.raises(ValueError, match="frames"):
        plan(s, 0.02, frames=0)
    glass = Scene.from_dict({"mesh": "sphere", "size_mm": 20, "material": "skin1",
                             "lights": [{"type": "point", "position": [0, 0, 100], "intensity": 1e4}],
                             "camera": {"eye": [0, 0, 80], "target": [0, 0, 0], "width": 8, "height": 8},
                             "caustics": {"ior": 1.5}})
    with pytest.raises(ValueError, match="caustics"):
        plan(glass, 0.02)


def test_plan_json_and_str():
    p = plan(_scene(), 0.05)
    d = json.loads(json.dumps(p.to_json()))
    assert d["method"] == p.method and d["predicted_total_s"] == pytest.approx(p.predicted_total_s)
    assert isinstance(p, Plan) and p.method in str(p) and "predicted error" in str(p)
    assert set(RULES) >= {"decimate", "sources", "shadows", "samples", "splat_budget", "blend", "reference"}


def test_cli_plan_and_auto_render(tmp_path, capsys):
    path = tmp_path / "s.json"
    path.write_text(json.dumps({"mesh": "sphere", "size_mm": 20.0, "material": "skin1",
                                "lights": [{"type": "point", "position": [0, 0, 50], "intensity": 1e4}],
                                "camera": {"eye": [0, 0, 50], "target": [0, 0, 0], "width": 12, "height": 12}}))
    assert main(["plan", str(path), "--tolerance", "0.05", "--json", str(tmp_path / "p.json")]) == 0
    assert "plan:" in capsys.readouterr().out and json.loads((tmp_path / "p.json").read_text())["candidates"]
    out = tmp_path / "r.png"
    assert main(["render", str(path), "--tolerance", "0.05", "--out", str(out), "--no-progress"]) == 0
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["plan"]["tolerance"] == 0.05 and summary["method"] == summary["plan"]["method"]
    # an explicit knob restricts the planner to the methods that take it
    assert main(["render", str(path), "--spacing", "3", "--out", str(tmp_path / "q.exr"), "--no-progress"]) == 0
    q = json.loads((tmp_path / "q.json").read_text())
    assert q["method"] == "reference" and q["knobs"]["spacing_mm"] == 3.0
    with pytest.raises(SystemExit):
        main(["render", str(path), "--method", "reference", "--samples", "64", "--out", str(tmp_path / "z.exr")])
    with pytest.raises(SystemExit):
        main(["render", str(path), "--method", "reference", "--tolerance", "0.05", "--out", str(tmp_path / "z.exr")])
    # a method named: its knobs are the planner's for it alone; given flags override them
    assert main(["render", str(path), "--method", "splat", "--tolerance", "0.05", "--out", str(tmp_path / "sp.exr"),
                 "--no-progress"]) == 0
    sp = json.loads((tmp_path / "sp.json").read_text())
    want, _, _ = plan_method(load_scene(path), "splat", 0.05)
    assert sp["method_plan"]["knobs"] == want and sp["knobs"]["eps"] == want["eps"]
    assert main(["render", str(path), "--method", "splat", "--eps", "0.2", "--out", str(tmp_path / "t.exr"),
                 "--no-progress"]) == 0
    assert json.loads((tmp_path / "t.json").read_text())["knobs"]["eps"] == 0.2
    assert "warning" not in capsys.readouterr().err
    # a method that cannot be planned within the tolerance renders its most accurate knobs and says so
    assert main(["render", str(path), "--method", "splat", "--tolerance", "0.001", "--out", str(tmp_path / "w.exr"),
                 "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "warning: splat: no configuration predicted within 0.1%" in err and "--method auto" in err
    assert json.loads((tmp_path / "w.json").read_text())["method_plan"]["note"].startswith("no configuration")


def test_scene_facts_are_cached_per_scene_and_mesh():
    """Planning a scene again reuses its facts; another scene, mesh or a throughput request recomputes them."""
    s = _scene(res=16, size=23.0)
    a = SceneFacts.from_scene(s, throughput=False)
    assert SceneFacts.from_scene(s, throughput=False) is a and a.throughput_entries == -1
    full = SceneFacts.from_scene(s)  # the throughput was not estimated: recomputed with it
    assert full is not a and full.throughput_entries > 0 and len(full.throughput_cut) == 3
    assert dataclasses.replace(full, throughput_entries=-1, throughput_cut=()) == a
    assert SceneFacts.from_scene(s, throughput=False) is full  # a superset serves
    other = SceneFacts.from_scene(dataclasses.replace(s, size_mm=24.0), throughput=False)
    assert other.size_mm > a.size_mm
    assert SceneFacts.from_scene(s, sphere(11.5, 2), throughput=False).faces != a.faces


def _loop_irradiance_detail(mesh, light_dir):
    """Loop reference of ``irradiance_detail`` for one directional light of unit irradiance per channel."""
    v, f = mesh.vertices.double(), mesh.faces.tolist()
    to_light = -torch.tensor(light_dir, dtype=torch.float64)
    to_light = to_light / to_light.norm()
    area, normal, e = [], [], []
    for a, b, c in f:
        cr = torch.linalg.cross(v[b] - v[a], v[c] - v[a], dim=-1)
        area.append(0.5 * float(cr.norm()))
        normal.append(cr / cr.norm())
        e.append(3.0 * max(0.0, float(normal[-1] @ to_light)))
    ev = {}
    for k, face in enumerate(f):
        for vert in face:
            s, w = ev.get(vert, (0.0, 0.0))
            ev[vert] = (s + area[k] * e[k], w + area[k])
    crease_faces = set()
    for i in range(len(f)):
        for j in range(i + 1, len(f)):
            if len(set(f[i]) & set(f[j])) == 2 and float(normal[i] @ normal[j]) < 0.5:
                crease_faces |= {i, j}
    num = sum(area[k] * (e[k] - sum(ev[x][0] / ev[x][1] for x in f[k]) / 3) ** 2 for k in crease_faces)
    return math.sqrt(num / sum(area[k] * e[k] ** 2 for k in range(len(f))))


def test_irradiance_detail_matches_a_loop_reference_and_lensch_is_charged_it():
    """The irradiance's detail where a crease's faces meet (what Lensch's vertex hats cannot carry and its kernels
    cannot reach across the seam): zero on a smooth sphere, large on a slab lit at 5.5 degrees to its face (its rim
    takes ten times the face's irradiance; Lensch measured 31% there for 1.75% predicted before it was charged)."""
    from torchsss.geometry import DirectionalLight
    from torchsss.geometry.procedural import slab
    from torchsss.plan import irradiance_detail

    box = slab(10.0, 8.0, 3.0, segments=2, dtype=torch.float64)
    for direction in ((-1.0, -0.3, -0.1), (0.0, 0.0, -1.0), (0.5, -0.2, 0.8)):
        got = irradiance_detail(box, [DirectionalLight(direction, 1.0)])
        assert got == pytest.approx(_loop_irradiance_detail(box, direction), rel=1e-9, abs=1e-12)
    assert irradiance_detail(sphere(10.0, 3), [DirectionalLight((0.3, 0.2, -1.0), 1.0)]) == 0.0
    assert irradiance_detail(box, []) == 0.0
    n = math.sqrt(1.0 + 0.09 + 0.01)
    side = _scene("slab", 25.0, "cream", 32, light=(1.0 / n, 0.3 / n, 0.1 / n))
    facts = SceneFacts.from_scene(side)
    front = SceneFacts.from_scene(_scene("slab", 25.0, "cream", 32))
    assert facts.irradiance_detail > 0.4 > front.irradiance_detail
    assert predict("lensch", {"atlas_resolution": 512}, facts, side.material)["error"] >= facts.irradiance_detail
    assert plan(side, 0.05).method != "lensch"
    assert all("creases" in c["rules"] for c in candidates(side, facts, 0.05, ["lensch"]))
    assert SceneFacts.from_scene(_scene()).irradiance_detail == 0.0


def test_plan_method_gives_icdf_its_most_accurate_n_where_the_tolerance_is_out_of_reach():
    """Where the tolerance needs more than 2^18 samples the icdf/hybrid candidate used to be dropped, and
    ``render --method icdf`` fell back to the default N 4096 (7.7% on the shared igea at 3%, where N 65,536 measured
    1.5%); now the most accurate N worth having is offered, predicted outside the tolerance and said so."""
    from torchsss.plan import SceneFacts, candidates

    s = _scene(res=32, light=(-0.3, 0.2, -1.0))
    facts = SceneFacts.from_scene(s, throughput=False)
    for method in ("icdf", "hybrid"):
        tight = 1e-4  # far below the estimator's reach
        cands = [c for c in candidates(s, facts, tight, [method])]
        assert cands and all(4096 < c["knobs"]["samples"] <= 1 << 16 for c in cands), cands
        assert "out of the estimator's reach" in cands[0]["rules"]["samples"]
        knobs, _, note = plan_method(s, method, tight)
        assert knobs["samples"] == cands[0]["knobs"]["samples"] and "no configuration predicted within" in note
        # a reachable tolerance still plans the N that meets it
        loose = plan_method(s, method, 0.05)
        assert loose[0]["samples"] <= 1 << 18 and "planned for 5%" in loose[2]


@pytest.mark.parametrize("spec", [dict(tol=0.05), dict(tol=0.01), dict(mesh="torus", material="marble", tol=0.02),
                                  dict(light=(-0.3, 0.2, -1.0), tol=0.02, res=48)])
def test_estimators_costed_only_where_they_could_win(spec):
    # the icdf estimator's one-sample spread (most of a small scene's planning time) is computed only where icdf or
    # the hybrid at their fewest samples could beat the best other plan; skipping them never changes the plan
    spec = dict(spec)
    tol = spec.pop("tol")
    s = _scene(**spec)
    from torchsss.plan import _FACTS
    from torchsss.trade import applicable_methods

    _FACTS.clear()
    lazy = plan(s, tol)
    _FACTS.clear()
    full = plan(s, tol, methods=list(applicable_methods(s)))
    assert (lazy.method, lazy.knobs) == (full.method, full.knobs)
    assert full.facts["sampling_spread"] > 0
    skipped = [m for m in ("icdf", "hybrid") if "not costed" in lazy.reasons.get(m, "")]
    costed = {c["method"] for c in lazy.candidates}
    assert not set(skipped) & costed
    if len(skipped) == 2:  # neither could win: the spread was never computed
        assert lazy.facts["sampling_spread"] == -1.0
        assert all(re.search(r"at 1024 samples alone \(>= [0-9.]+ s\) exceed", lazy.reasons[m]) for m in skipped)
    else:
        assert lazy.facts["sampling_spread"] == pytest.approx(full.facts["sampling_spread"])


def test_estimators_spread_gated_when_lensch_is_out(monkeypatch):
    # at 1% Lensch's floor rules Lensch out; the Monte Carlo estimators' one-sample spread is still computed only
    # where they could beat the best other plan (a warm process: the reference's frames are cheap and the
    # estimators' setup and frames at their fewest samples cannot win; until 2026-11-29 the gate was off there)
    import torchsss.plan as planner

    monkeypatch.setattr(planner, "warm_kernels", lambda *a, **k: frozenset({"plain", "split", "truncated"}))
    s = _scene(res=16, size=21.0)
    p = plan(s, 0.01)
    assert "lensch" in p.reasons and "exceed the best other plan" in p.reasons["icdf"]
    assert p.facts["sampling_spread"] == -1.0
    assert not any(c["method"] in ("icdf", "hybrid", "lensch") for c in p.candidates)
    # the gate skips work, not plans: with the estimators costed by name the method chosen is the same
    q = plan(s, 0.01, methods=["reference", "splat", "icdf", "hybrid"])
    assert (q.method, q.knobs) == (p.method, p.knobs)


def test_splat_object_scale_term_falls_with_the_grid():
    # a side-lit 8 mm potato torus: its profile asks for fewer than MIN_GRID texels, so the grid is MIN_GRID x
    # oversample and the predicted error falls with the oversampling (measured 1.92 / 0.93 / 0.53%,
    # benchmarks/results/splat_calibration.md); a convex object is charged no object-scale term
    torus = _scene(mesh="torus", size=8.0, material="potato", res=32, light=(1.0, 0.3, 0.1))
    f = SceneFacts.from_scene(torus)
    assert not f.convex
    errs = [predict("splat", {"eps": 0.01, "oversample": o}, f, torus.material)["error"] for o in (1.0, 2.0, 4.0)]
    assert errs[0] > errs[1] > errs[2]
    obj = MODEL["splat_obj"] * (MIN_GRID / (MIN_GRID * 2.0)) ** MODEL["splat_obj_p"]
    assert errs[1] >= obj  # the term is part of the hypot
    ball = _scene(mesh="sphere", size=8.0, material="potato", res=32, light=(1.0, 0.3, 0.1))
    fb = SceneFacts.from_scene(ball)
    assert fb.convex
    free = predict("splat", {"eps": 0.01, "oversample": 1.0}, fb, ball.material, model={"splat_obj_convex": 0.0})
    same = predict("splat", {"eps": 0.01, "oversample": 1.0}, fb, ball.material)
    assert same["error"] == pytest.approx(free["error"], rel=1e-3)
    charged = predict("splat", {"eps": 0.01, "oversample": 1.0}, fb, ball.material, model={"splat_obj_convex": 1.0})
    assert charged["error"] > same["error"]


def test_splat_is_planned_at_oversample_one_and_a_half_between_one_and_two():
    # every splat eps is offered at the oversamplings of SPLAT_OVERSAMPLE; 1.5 lies between 1 and 2 in both the
    # predicted error and the predicted frame (2.25x oversample 1's texels, 4x at oversample 2)
    from torchsss.plan import SPLAT_OVERSAMPLE, candidates

    assert SPLAT_OVERSAMPLE == (1.0, 1.5, 2.0, 4.0)
    s = _scene(mesh="torus", size=20.0, material="skin1", res=64, light=(1.0, 0.3, 0.2))
    f = SceneFacts.from_scene(s, throughput=False, spread=False)
    offered = {(c["knobs"]["eps"], c["knobs"]["oversample"]) for c in candidates(s, f, 0.02, ["splat"])}
    assert offered == {(e, o) for e in (0.003, 0.01, 0.03) for o in SPLAT_OVERSAMPLE}
    p = {o: predict("splat", {"eps": 0.01, "oversample": o}, f, s.material) for o in (1.0, 1.5, 2.0)}
    assert p[1.0]["error"] > p[1.5]["error"] > p[2.0]["error"]
    assert p[1.0]["frame_s"] < p[1.5]["frame_s"] < p[2.0]["frame_s"]


def test_deviations_measure_three_counts_and_interpolate_the_others_within_twenty_percent(monkeypatch):
    # a bumpy sphere (a scan's detail) at six source counts: the smallest, middle and largest decimated and measured
    # exactly, the other three within 20% of their own decimation's deviation (a power of the face count between
    # the measured neighbours; measured -3.5%, +16.5%, -2.2%), three decimations instead of six
    import torch

    import torchsss.plan as plan_mod
    from torchsss.geometry.mesh import decimate, surface_deviation

    smooth = sphere(10.0, 5)
    v = smooth.vertices
    u = v / v.norm(dim=1, keepdim=True)
    bumps = 1.0 + 0.02 * torch.sin(25 * u[:, 0]) * torch.sin(25 * u[:, 1]) * torch.sin(25 * u[:, 2] + 1.0)
    bumpy = dataclasses.replace(smooth, vertices=v * bumps.unsqueeze(-1))
    counts = [1500, 2000, 2800, 3900, 5400, 7500]
    calls = []
    real = plan_mod.surface_deviation
    monkeypatch.setattr(plan_mod, "surface_deviation", lambda *a, **k: calls.append(1) or real(*a, **k))
    dev = plan_mod._deviations(bumpy, bumpy, [*counts, 2000])
    assert sorted(dev) == counts and len(calls) == 3
    for w in counts:
        want = surface_deviation(bumpy, decimate(bumpy, w))
        if w in (1500, 3900, 7500):
            assert dev[w] == pytest.approx(want, rel=1e-12)
        else:
            assert dev[w] == pytest.approx(want, rel=0.2)
    calls.clear()
    assert plan_mod._deviations(bumpy, bumpy, [1500, 3900, 7500]).keys() == {1500, 3900, 7500} and len(calls) == 3


def test_splat_truncation_not_computed_under_an_environment():
    # an environment's light is not in truncation_error's closed form: the facts hold none, and predict charges the
    # planar tail between r_max and the object's diameter instead
    from torchsss.geometry import EnvironmentLight
    from torchsss.plan import _Profile

    s = _scene(size=40.0, res=16)
    lit = SceneFacts.from_scene(s)
    assert len(lit.splat_truncation) == 3
    sky = dataclasses.replace(s, lights=(*s.lights, EnvironmentLight.uniform(0.2)))
    facts = SceneFacts.from_scene(sky)
    assert facts.splat_truncation == ()
    prof = _Profile.of(s.material)
    cut = prof.tail_between(prof.r_max(0.03), 2.0 * facts.radius_mm)
    assert cut > 0 and predict("splat", {"eps": 0.03, "oversample": 4.0}, facts, s.material)["error"] >= cut
