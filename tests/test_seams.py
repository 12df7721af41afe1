"""No seams along atlas chart boundaries (issue 16): the atlas methods' error beside a chart edge matches the error
away from it.

A seam is a systematic brightness step where the surface crosses from one atlas chart to another (the near-field
filter or the kernels reading the gutter or the wrong chart). On the default scene (back-lit skin1 spot, 38 charts)
at 64x64 the camera pixels whose atlas texel lies within ~1 mm (10 texels at 512) of a chart edge form the seam band
(~300 of 938 pixels); the test compares the signed mean error against the reference there with the one elsewhere.
Measured (N = 16384 for icdf/hybrid): hybrid +0.49% in the band vs +0.23% elsewhere, icdf +0.53% vs +0.09%, Lensch
(atlas 256, blended) +3.25% vs +3.64% (at its planned default, atlas 1024 unblended, -0.32% vs +0.15%, measured
once; the test keeps 256 for time: 6 s against 17 s). The chart-less hybrid split that issue 16 reported as "bright
seams" (its filter read across charts and gutters) measures -13.6% vs -1.9% here: the negative control that shows
the test can fail.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F

from torchsss.geometry.gbuffer import camera_gbuffer
from torchsss.pipelines import build
from torchsss.scene import default_scene_path, load_scene

#: the largest step (signed mean relative error in the band minus elsewhere) that does not show as a seam
MAX_STEP = 0.015
#: texels either side of a chart edge (512 atlas: about 1 mm on the default scene)
BAND_TEXELS = 10


@pytest.fixture(scope="module")
def default_64():
    s = load_scene(default_scene_path())
    camera = dataclasses.replace(s.camera, width=64, height=64)
    mesh = s.load_mesh()
    ref = build("reference", mesh, s.material).render(list(s.lights), camera)
    return s, mesh, camera, ref


def seam_band(renderer, camera) -> torch.Tensor:
    """:math:`(H, W)` bool: covered pixels whose atlas texel lies within ``BAND_TEXELS`` (scaled to a 512 atlas) of
    another chart or of an invalid (gutter) texel."""
    gb = camera_gbuffer(renderer.mesh, camera)
    uv = renderer.view.uv(camera, gb.position, gb.mask, gb.face_id)[0]  # (2, H, W), v up
    atlas = renderer.atlas
    k = 2 * max(1, round(BAND_TEXELS * atlas.resolution / 512)) + 1
    chart = torch.where(atlas.valid_mask.bool(), atlas.chart_id, torch.full_like(atlas.chart_id, -1)).double()
    hi = F.max_pool2d(chart, k, 1, k // 2)
    lo = -F.max_pool2d(-chart, k, 1, k // 2)
    band = (hi != lo).double()
    grid = torch.stack([uv[0] * 2 - 1, (1 - uv[1]) * 2 - 1], -1).unsqueeze(0).double()
    hit = F.grid_sample(band, grid, mode="nearest", align_corners=False)[0, 0] > 0.5
    return hit & gb.mask[0, 0]


def _step(out, ref, band: torch.Tensor) -> tuple[float, float, int]:
    both = out.mask[0, 0] & ref.mask[0, 0]
    rel = (out.radiance - ref.radiance).sum(1)[0] / ref.radiance.sum(1)[0].clamp_min(1e-12)
    inside, outside = band & both, both & ~band
    return float(rel[inside].mean()), float(rel[outside].mean()), int(inside.sum())


@pytest.mark.parametrize("method, knobs", [("hybrid", {"samples": 16384}), ("icdf", {"samples": 16384}),
                                           ("lensch", {"atlas_resolution": 256})])
def test_no_step_along_chart_edges(default_64, method, knobs):
    s, mesh, camera, ref = default_64
    r = build(method, mesh, s.material, **knobs)
    band = seam_band(r, camera)
    seam, rest, n = _step(r.render(list(s.lights), camera), ref, band)
    assert n >= 100, n  # the band holds enough pixels to see a step
    assert abs(seam - rest) < MAX_STEP, (method, seam, rest)


def test_the_chart_less_split_shows_its_seam(default_64):
    """The negative control: the hybrid split without chart ids (the filter reads across charts and gutters)."""
    s, mesh, camera, ref = default_64
    r = build("hybrid", mesh, s.material, samples=16384, local="atlas")
    r.module.chart_id = None
    seam, rest, n = _step(r.render(list(s.lights), camera), ref, seam_band(r, camera))
    assert n >= 100 and seam - rest < -5 * MAX_STEP, (seam, rest)


def test_hybrid_noise_does_not_gather_along_chart_edges(default_64):
    """The speckle the README's gallery showed along chart edges: Chang's atlas filter hands the near field across a
    seam to the sampled global term, so the relative RMS error within the seam band is several times that elsewhere
    (measured at N = 4096: 13.8% against 3.3%); gathered over the surface (the default) it is not (2.2% against
    1.8%), and smaller everywhere."""
    s, mesh, camera, ref = default_64
    rms = {}
    for local in ("surface", "atlas"):
        r = build("hybrid", mesh, s.material, samples=4096, local=local)
        out = r.render(list(s.lights), camera)
        band = seam_band(r, camera)
        both = out.mask[0, 0] & ref.mask[0, 0]
        rel = (out.radiance - ref.radiance).sum(1)[0] / ref.radiance.sum(1)[0].clamp_min(1e-12)
        rms[local] = (float(rel[band & both].pow(2).mean().sqrt()), float(rel[~band & both].pow(2).mean().sqrt()))
        assert out.stats["local_term"] == local
    print(rms)
    assert rms["surface"][0] < 1.5 * rms["surface"][1], rms
    assert rms["atlas"][0] > 2.5 * rms["atlas"][1], rms  # the control: the check can fail
    assert rms["surface"][0] < 0.5 * rms["atlas"][0], rms
