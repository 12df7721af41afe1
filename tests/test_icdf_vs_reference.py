"""Chang et al.'s texture-space importance sampling (``icdf``) and hybrid split (``hybrid``) against the reference."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import eta_edit_case, rel_rmse

from torchsss.geometry import sphere
from torchsss.modules import DipoleMaterial
from torchsss.modules.chang import HybridTranslucency
from torchsss.pipelines import build
from torchsss.pipelines.chang import ChangScene, build_icdf, render_hybrid, render_icdf
from torchsss.pipelines.reference import render_reference
from torchsss.scene import default_scene_path, load_scene

#: relative RMSE bounds at atlas 128 and N = 8192 on the shared 16 mm sphere (measured: dipole 1.7%, tabulated
#: 1.7%, Burley 10%: its peaked profile, even with the averaged core, gives the pure estimator a heavy tail; the
#: hybrid's local filter takes that peak, see test_hybrid_vs_reference.py)
BOUNDS = {"dipole": 0.03, "tabulated": 0.03, "burley": 0.15}


@pytest.mark.parametrize("profile", sorted(BOUNDS))
def test_every_profile_against_the_reference_with_the_same_profile(vs_reference, profile):
    r = build("icdf", vs_reference.mesh, vs_reference.material.with_profile(profile), atlas_resolution=128,
              samples=8192)
    res = r.render(vs_reference.lights, vs_reference.camera)
    assert bool(torch.isfinite(res.radiance).all())
    err = vs_reference.error(res, profile)
    assert err < BOUNDS[profile], (profile, err)


def test_eta_edit_on_a_prebuilt_renderer_matches_a_fresh_build(vs_reference):
    before, edited, fresh = eta_edit_case("icdf", vs_reference, atlas_resolution=128, samples=2048)
    assert rel_rmse(before, fresh) > 0.03  # the edit matters
    assert rel_rmse(edited, fresh) < 1e-5


# -- (g) pipelines --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_scene():
    """The default scene's material, lights and camera direction (back-lit skin1) on a 20 mm sphere, 24 x 24.

    The sphere is convex, so the reference needs no shadow rays (self-shadowing is the cosine clamp).
    """
    sc = load_scene(default_scene_path())
    cam = dataclasses.replace(sc.camera, width=24, height=24)
    mesh = sphere(10.0, 3)
    ref = render_reference(mesh, sc.material, sc.lights, cam, shadows="none")
    built = build_icdf(mesh, sc.material, atlas_resolution=128)
    return sc, cam, mesh, ref, built


def _rel_rmse(res, ref):
    m = ref.mask.expand_as(ref.radiance)
    return float((res.radiance - ref.radiance)[m].pow(2).mean().sqrt() / ref.radiance[m].pow(2).mean().sqrt())


def test_render_icdf_close_to_reference(small_scene):
    sc, cam, mesh, ref, built = small_scene
    res = render_icdf(mesh, sc.material, sc.lights, cam, samples=16384, prebuilt=built,
                      shadow_resolution=512)
    assert res.radiance.shape == ref.radiance.shape and bool(torch.isfinite(res.radiance).all())
    assert bool((res.radiance[~ref.mask.expand_as(res.radiance)] == 0).all())
    assert _rel_rmse(res, ref) < 0.10
    for key in ("t_precompute_s", "t_frame_s", "t_module_s", "samples"):
        assert key in res.stats


def test_render_hybrid_beats_icdf_at_equal_samples(small_scene):
    sc, cam, mesh, ref, built = small_scene
    sa, ss, eta = sc.material.tensors(torch.float32)
    hy = ChangScene(mesh, built.atlas, HybridTranslucency.from_atlas(built.atlas, DipoleMaterial(sa, ss, eta)), {})
    res = render_hybrid(mesh, sc.material, sc.lights, cam, samples=1024, prebuilt=hy, shadow_resolution=512)
    pure = render_icdf(mesh, sc.material, sc.lights, cam, samples=1024, prebuilt=built, shadow_resolution=512)
    assert bool(torch.isfinite(res.radiance).all()) and bool((res.radiance >= 0).all())
    # back-lit dense skin: pure sampling spends its samples on the far lit side; the local filter covers the near
    # field (the tangent-plane filter is an approximation on the curved sphere, hence the loose bound)
    err_h, err_p = _rel_rmse(res, ref), _rel_rmse(pure, ref)
    assert err_h < 0.15 and err_h < 0.5 * err_p, (err_h, err_p)
