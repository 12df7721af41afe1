"""The unblended Lensch sum without the near field counted twice (torchsss.geometry.lensch.window_overlap)."""

from __future__ import annotations

import pytest
import torch
from conftest import VsReference
from torch.func import functional_call

from torchsss.geometry import build_atlas, sphere
from torchsss.geometry.lensch import (
    WindowOverlap,
    build_throughput,
    kernel_reach,
    local_kernel_geometry,
    vertex_weights,
    window_overlap,
)
from torchsss.modules import DipoleMaterial
from torchsss.modules.lensch import GlobalResponse, LocalResponse
from torchsss.physics import total_diffuse_reflectance
from torchsss.pipelines import build
from torchsss.pipelines.lensch import build_lensch
from torchsss.scene import Material


def _material(name="skin1"):
    return DipoleMaterial(*Material.from_json(name).tensors(torch.float64))


def test_gamma_is_the_global_terms_own_weight_of_the_receiver():
    # at s = o the first-order form is exact: gamma(o) A(o) is what the throughput sends from texel o back to o
    mesh = sphere(6.0, 3, dtype=torch.float64)
    atlas = build_atlas(mesh, 64, kernel_size=5)
    mat = _material("marble")
    w = vertex_weights(mesh, atlas)
    glob = GlobalResponse(w, build_throughput(mesh, mat, threshold=0.0), mat, atlas.valid_mask, method="scatter")
    local = LocalResponse(local_kernel_geometry(atlas, 5), mat, overlap=window_overlap(mesh, atlas, w))
    gamma = local.overlap()  # (H, W, C)
    chart = atlas.chart_mask[0, 0].nonzero()
    picks = chart[torch.randperm(chart.shape[0], generator=torch.Generator().manual_seed(0))[:16]]
    e = torch.zeros(picks.shape[0], 3, 64, 64, dtype=torch.float64)
    e[torch.arange(picks.shape[0]), :, picks[:, 0], picks[:, 1]] = 1.0
    with torch.no_grad():
        out = glob(e)[torch.arange(picks.shape[0]), :, picks[:, 0], picks[:, 1]]  # (P, C)
    want = gamma[picks[:, 0], picks[:, 1]] * local.self_area[picks[:, 0], picks[:, 1]].unsqueeze(-1)
    torch.testing.assert_close(want, out, rtol=1e-10, atol=1e-14)
    # the local kernels carry A(s) (R_d - gamma(o)) on every tap
    plain = LocalResponse(local_kernel_geometry(atlas, 5), mat)
    with torch.no_grad():
        diff = plain.kernels() - local.kernels()
    torch.testing.assert_close(diff, (local.area.unsqueeze(-1) * gamma[:, :, None, None]).permute(4, 0, 1, 2, 3))


@pytest.fixture(scope="module")
def marble_sphere():
    scene = VsReference()
    material = Material.from_json("marble")
    ref = build("reference", scene.mesh, material, spacing_mm=0.2).render(scene.lights, scene.camera)
    return scene, material, ref


def _error_and_mean(out, ref):
    m = (ref.mask & out.mask).expand_as(ref.radiance)
    d = (out.radiance - ref.radiance)[m]
    err = float(d.square().mean().sqrt() / ref.radiance[m].square().mean().sqrt())
    return err, float(out.radiance[m].sum() / ref.radiance[m].sum())


def test_unblended_sum_no_longer_counts_the_window_twice(marble_sphere):
    # 16 mm marble sphere, side/back-lit, atlas 512 unblended (k = 7 reaches 0.17 median edges): the plain sum was
    # 5% too bright (9.9% relative RMSE), the corrected one is within 0.4% in the mean (3.4%)
    scene, material, ref = marble_sphere
    assert kernel_reach(scene.mesh, 512, 7) < 0.5
    plain = build("lensch", scene.mesh, material, atlas_resolution=512, blend=False, overlap=False)
    fixed = build("lensch", scene.mesh, material, atlas_resolution=512, blend=False)
    assert fixed.built.stats["overlap"] and not plain.built.stats["overlap"]
    err_plain, mean_plain = _error_and_mean(plain.render(scene.lights, scene.camera), ref)
    err_fixed, mean_fixed = _error_and_mean(fixed.render(scene.lights, scene.camera), ref)
    assert mean_plain > 1.03 and abs(mean_fixed - 1.0) < 0.015, (mean_plain, mean_fixed)
    assert err_fixed < 0.5 * err_plain and err_fixed < 0.05, (err_plain, err_fixed)


def test_overlap_is_left_out_where_the_window_spans_faces(marble_sphere):
    # atlas 128: a 7 x 7 window reaches 0.57 median edges; the first-order form does not hold there
    scene, material, _ = marble_sphere
    assert kernel_reach(scene.mesh, 128, 7) >= 0.5
    built = build_lensch(scene.mesh, material, resolution=128, blend=False)
    assert not built.stats["overlap"] and built.module.local.overlap() is None
    blended = build_lensch(scene.mesh, material, resolution=128, blend=True)
    assert not blended.stats["overlap"]  # blending joins the two terms itself


def test_overlap_gradients_wrt_the_material():
    mesh = sphere(4.0, 1, dtype=torch.float64)
    atlas = build_atlas(mesh, 24, kernel_size=3)
    mat = _material("marble")
    local = LocalResponse(local_kernel_geometry(atlas, 3), mat,
                          overlap=window_overlap(mesh, atlas, vertex_weights(mesh, atlas)))
    e = torch.rand(1, 3, 24, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * atlas.valid_mask
    raw = (mat.raw_sigma_a.detach().clone().requires_grad_(), mat.raw_sigma_s_prime.detach().clone().requires_grad_())

    probe = torch.rand(1, 3, 24, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(2))

    def f(raw_sa, raw_ss):  # three weighted sums of the output (the Jacobian of all 1728 outputs took 80 s)
        out = functional_call(local, {"material.raw_sigma_a": raw_sa, "material.raw_sigma_s_prime": raw_ss}, (e,))
        return (out * probe).sum((0, 2, 3))

    assert torch.autograd.gradcheck(f, raw, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_overlap_rejects_bad_input():
    mesh = sphere(4.0, 1, dtype=torch.float64)
    atlas = build_atlas(mesh, 24, kernel_size=3)
    geom = local_kernel_geometry(atlas, 3)
    w = vertex_weights(mesh, atlas)
    ov = window_overlap(mesh, atlas, w)
    with pytest.raises(TypeError, match="overlap"):
        LocalResponse(geom, _material(), overlap=(ov.weight, ov.distance, ov.vertex_area))
    with pytest.raises(ValueError, match=r"overlap\.weight"):
        LocalResponse(geom, _material(), overlap=WindowOverlap(ov.weight[..., :-1, :], ov.distance, ov.vertex_area))
    with pytest.raises(TypeError, match="weights"):
        window_overlap(mesh, atlas, (w.vertex_ids, w.dual, w.bary))
    with pytest.raises(TypeError, match="overlap"):
        build_lensch(mesh, "skin1", resolution=24, overlap="yes")


def test_overlap_at_the_extremes_of_r_max():
    # r_max far below a texel and far beyond the object: gamma stays finite and the radiosity positive. Under a
    # uniform irradiance with r_max << texel the truth is R_total: the plain sum counts it about twice (the centre
    # tap's disk integral and the vertices' own disks: measured +100%), the corrected one less so (+66%: the
    # throughput spreads each vertex's self-response over its hat, beyond the window; blending is the remedy)
    mesh = sphere(5.0, 2, dtype=torch.float64)
    atlas = build_atlas(mesh, 256, kernel_size=7)
    assert kernel_reach(mesh, 256, 7) < 0.5
    chart = atlas.chart_mask.expand(1, 3, 256, 256)
    w = vertex_weights(mesh, atlas)
    e = torch.ones(1, 3, 256, 256, dtype=torch.float64) * atlas.valid_mask
    for sa_v, ss_v in ((50.0, 500.0), (1e-4, 0.05)):
        sa, ss = torch.full((3,), sa_v, dtype=torch.float64), torch.full((3,), ss_v, dtype=torch.float64)
        mat = DipoleMaterial(sa, ss, torch.tensor(1.3, dtype=torch.float64))
        local = LocalResponse(local_kernel_geometry(atlas, 7), mat, overlap=window_overlap(mesh, atlas, w))
        plain = LocalResponse(local_kernel_geometry(atlas, 7), mat)
        glob = GlobalResponse(w, build_throughput(mesh, mat), mat, atlas.valid_mask)
        with torch.no_grad():
            gamma, bg = local.overlap(), glob(e)
            fixed, summed = local(e) + bg, plain(e) + bg
        assert bool(torch.isfinite(gamma).all()) and bool(torch.isfinite(fixed).all())
        assert float(fixed[chart].min()) > 0, (sa_v, float(fixed[chart].min()))
        assert float(fixed[chart].mean()) < float(summed[chart].mean())  # the correction only removes
        if sa_v > 1:
            r_total = float(total_diffuse_reflectance(sa, ss, 1.3)[0])
            err_fixed = abs(float(fixed[chart].mean()) / r_total - 1.0)
            err_summed = abs(float(summed[chart].mean()) / r_total - 1.0)
            assert err_fixed < err_summed, (err_fixed, err_summed)
