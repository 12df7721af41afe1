"""Lensch et al. 2002 (atlas, local kernels, throughput, blending) against the reference, with every profile."""

from __future__ import annotations

import pytest
import torch
from conftest import eta_edit_case, rel_rmse

from torchsss.geometry import Camera, PointLight, sphere
from torchsss.pipelines import build
from torchsss.pipelines.lensch import render_lensch
from torchsss.pipelines.reference import render_reference
from torchsss.scene import Material

#: relative RMSE bounds at atlas 128 (kernel and blending planned) on the shared 16 mm sphere (measured: dipole 5.0%,
#: tabulated 5.0%, Burley 4.5%)
BOUNDS = {"dipole": 0.07, "tabulated": 0.07, "burley": 0.07}


@pytest.mark.parametrize("profile", sorted(BOUNDS))
def test_every_profile_against_the_reference_with_the_same_profile(vs_reference, profile):
    r = build("lensch", vs_reference.mesh, vs_reference.material.with_profile(profile), atlas_resolution=128)
    res = r.render(vs_reference.lights, vs_reference.camera)
    assert bool(torch.isfinite(res.radiance).all())
    err = vs_reference.error(res, profile)
    assert err < BOUNDS[profile], (profile, err)
    assert res.stats["nnz"] > 0 and res.stats["knobs"]["kernel_size"] % 2 == 1


def test_eta_edit_on_a_prebuilt_renderer_matches_a_fresh_build(vs_reference):
    # a dense throughput and no blending: nothing that the build fits to the build's material
    before, edited, fresh = eta_edit_case("lensch", vs_reference, atlas_resolution=128, threshold=0.0, blend=False)
    assert rel_rmse(before, fresh) > 0.03  # the edit matters
    assert rel_rmse(edited, fresh) < 1e-5


# 20 s (a dense 2562-vertex throughput at atlas 256): with -m slow. In the default run lensch against the reference
# is test_every_profile_against_the_reference_with_the_same_profile[dipole] (same skin1, a tighter 7% bound) and
# render_lensch itself runs in tests/test_bench_lensch.py::test_bench_lensch_quick_smoke
@pytest.mark.slow
def test_render_lensch_close_to_reference():
    mesh = sphere(10.0, 4)
    material = Material.from_json("skin1")
    lights = [PointLight((40.0, 30.0, 30.0), 5e3)]
    cam = Camera(eye=(0.0, 10.0, 60.0), target=(0.0, 0.0, 0.0), fov_deg=30.0, width=48, height=48)
    ref = render_reference(mesh, material, lights, cam, shadows="shadowmap")
    res = render_lensch(mesh, material, lights, cam, resolution=256)
    m = ref.mask & res.mask
    diff = (res.radiance - ref.radiance)[m.expand_as(ref.radiance)]
    rel_rmse = float(diff.pow(2).mean().sqrt() / ref.radiance[m.expand_as(ref.radiance)].pow(2).mean().sqrt())
    print(f"lensch vs reference, sphere r=10 mm skin1, atlas 256: relative RMSE {rel_rmse:.3%}")
    assert rel_rmse < 0.10
    assert res.stats["t_frame_s"] > 0 and res.stats["nnz"] > 0


