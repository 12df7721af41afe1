"""Chang et al.'s hybrid local/global split against the all-pairs reference, with every profile.

(``test_icdf_vs_reference.py::test_render_hybrid_beats_icdf_at_equal_samples`` compares it with pure sampling.)
"""

from __future__ import annotations

import pytest
import torch

from torchsss.pipelines import build

#: relative RMSE bounds at atlas 128 and N = 8192 on the shared 16 mm sphere (measured: dipole 3.6%, tabulated
#: 3.6%, Burley 2.9%)
BOUNDS = {"dipole": 0.055, "tabulated": 0.055, "burley": 0.055}


@pytest.mark.parametrize("profile", sorted(BOUNDS))
def test_every_profile_against_the_reference_with_the_same_profile(vs_reference, profile):
    r = build("hybrid", vs_reference.mesh, vs_reference.material.with_profile(profile), atlas_resolution=128,
              samples=8192)
    res = r.render(vs_reference.lights, vs_reference.camera)
    assert bool(torch.isfinite(res.radiance).all())
    err = vs_reference.error(res, profile)
    assert err < BOUNDS[profile], (profile, err)
    assert res.stats["r_p_mm"] > 0


@pytest.mark.parametrize("where", ["front", "side", "back"])
def test_hybrid_keeps_the_energy_whichever_side_the_light_is_on(where):
    """The split must add up: the hybrid's image mean matches the reference in every channel within 1% (issue 16:
    it was 0.66-0.89x on scanned meshes). The chart-aware split (sources of another chart are entirely global; the
    local filter reads the receiver's chart only and weighs each point by its 3-D distance) is checked against the
    chart-less split it replaced, which lost 6-9% on this 20 mm marble sphere (front/side; measured 0.2% after).
    Back-lit, the visible side is farther than the split's reach from the lit side, so both agree there."""
    from torchsss.geometry import Camera, PointLight, sphere

    mesh = sphere(10.0, 3)
    light = {"front": (0.0, 0.0, 100.0), "side": (100.0, 0.0, 0.0), "back": (0.0, 15.0, -100.0)}[where]
    lights = [PointLight(light, 8e3)]
    camera = Camera(eye=(0.0, 0.0, 65.0), target=(0.0, 0.0, 0.0), width=32, height=32)
    ref = build("reference", mesh, "marble").render(lights, camera)
    hybrid = build("hybrid", mesh, "marble", atlas_resolution=256, samples=8192)
    assert hybrid.module.chart_id is not None and hybrid.built.local is not None

    def means(res):
        m = (res.mask & ref.mask).expand_as(ref.radiance)
        return res.radiance[m].view(3, -1).mean(1) / ref.radiance[m].view(3, -1).mean(1)

    ratio = means(hybrid.render(lights, camera))  # the default: the local term gathered over the surface
    assert float((ratio - 1).abs().max()) < 0.005, ratio.tolist()
    atlas = build("hybrid", mesh, "marble", atlas_resolution=256, samples=8192, local="atlas")
    ratio = means(atlas.render(lights, camera))  # Chang's atlas filter with the chart-aware split
    assert float((ratio - 1).abs().max()) < 0.01, ratio.tolist()
    if where != "back":
        atlas.module.chart_id = None
        old = means(atlas.render(lights, camera))
        assert float((old - 1).abs().max()) > 0.03, old.tolist()


def test_hybrid_turns_its_split_off_on_objects_smaller_than_its_reach():
    """On a 10 mm skin1 sphere the local bound (6 mm) exceeds 0.8 x the radius (5 mm): the tangent-plane filter
    would be wrong (measured: a 10 mm skin1 head scan 2-7% too bright with the split), so the split is off, the
    stats say why, and the image mean matches the reference; max_reach=None keeps the split."""
    from torchsss.geometry import Camera, PointLight, sphere

    mesh = sphere(5.0, 3)
    lights = [PointLight((40.0, 5.0, 10.0), 2e3)]
    camera = Camera(eye=(0.0, 0.0, 32.0), target=(0.0, 0.0, 0.0), width=24, height=24)
    ref = build("reference", mesh, "skin1").render(lights, camera)
    res = build("hybrid", mesh, "skin1", atlas_resolution=128, samples=4096).render(lights, camera)
    assert res.stats["split"].startswith("off: the local bound") and res.stats["local_bound_mm"] == 0.0
    m = (res.mask & ref.mask).expand_as(ref.radiance)
    ratio = res.radiance[m].view(3, -1).mean(1) / ref.radiance[m].view(3, -1).mean(1)
    assert float((ratio - 1).abs().max()) < 0.02, ratio.tolist()
    kept = build("hybrid", mesh, "skin1", atlas_resolution=128, samples=64, max_reach=None)
    assert kept.module.bound > 0.8 * 5.0 and kept.built.stats["split"].startswith("on:")
    with pytest.raises(ValueError, match="max_reach: expected a number > 0 or None"):
        build("hybrid", mesh, "skin1", atlas_resolution=128, max_reach=0)
