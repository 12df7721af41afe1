"""Coarse evaluation of the radiosity with edge-aware interpolation (torchsss.pipelines.coarse)."""

from __future__ import annotations

import pytest
import torch

from torchsss.geometry import Camera, DirectionalLight, sphere
from torchsss.pipelines.build import build
from torchsss.pipelines.coarse import coarse_receivers
from torchsss.trade import image_error


def _plane(h: int, w: int, z=None):
    yy, xx = torch.meshgrid(torch.arange(float(h)), torch.arange(float(w)), indexing="ij")
    pos = torch.stack([xx, yy, torch.zeros_like(xx) if z is None else z], -1)
    nrm = torch.zeros(h, w, 3)
    nrm[..., 2] = 1.0
    return pos, nrm


@pytest.mark.parametrize("stride", [2, 3, 4])
def test_linear_field_is_interpolated_exactly(stride):
    """Bilinear interpolation reproduces a linear field; every covered pixel is either evaluated or filled."""
    h, w = 13, 17
    pos, nrm = _plane(h, w)
    mask = torch.ones(h, w, dtype=torch.bool)
    plan = coarse_receivers(pos.double(), nrm.double(), mask, stride)
    pos = pos.double()
    field = (2.0 + 0.3 * pos[..., 0] - 0.1 * pos[..., 1]).reshape(-1, 1)
    img = plan.scatter(field[plan.evaluate], h, w)
    torch.testing.assert_close(img.reshape(-1, 1), field, rtol=1e-12, atol=1e-12)
    assert plan.evaluate.numel() + plan.fill.numel() == h * w
    grid = (len(range(0, h, stride)) + ((h - 1) % stride > 0)) * (
        len(range(0, w, stride)) + ((w - 1) % stride > 0))
    assert plan.evaluate.numel() == grid  # a flat plane: only the grid (with the last row and column)
    assert plan.evaluate.numel() < h * w / 2


def test_depth_step_and_silhouette_are_evaluated_exactly():
    """Pixels whose grid corners lie on another surface (a depth step) or outside the mask are not interpolated."""
    h, w = 16, 16
    z = torch.zeros(h, w)
    z[:, 8:] = 50.0  # a 50 mm step between columns 7 and 8
    pos, nrm = _plane(h, w, z)
    mask = torch.ones(h, w, dtype=torch.bool)
    mask[12:, :] = False
    plan = coarse_receivers(pos, nrm, mask, 4)
    filled = torch.zeros(h * w, dtype=torch.bool)
    filled[plan.fill] = True
    filled = filled.reshape(h, w)
    assert not filled[:, 5:8].any()  # the cells bracketing the step (grid columns 4 and 8): exact
    assert filled[:8, 9:12].all()  # beyond it the grid columns 8 and 12 share the far surface
    assert not filled[9:12].any()  # the grid's next row is outside the mask: exact
    assert filled[:8, :4].any()  # the smooth interior is interpolated
    assert not filled[~mask].any() and int(plan.evaluate.numel() + plan.fill.numel()) == int(mask.sum())


def test_refine_flags_sharp_values():
    h, w = 9, 9
    pos, nrm = _plane(h, w)
    plan = coarse_receivers(pos, nrm, torch.ones(h, w, dtype=torch.bool), 4)
    values = torch.ones(plan.evaluate.numel(), 3)
    values[plan.evaluate % w >= 8] = 3.0  # a step at the last grid column: corners 1 and 3
    flagged = plan.fill[plan.refine(values, 0.2)] % w
    assert flagged.numel() and bool((flagged >= 4).all())  # only the cells between columns 4 and 8
    assert plan.refine(values, 0.9).numel() == 0


def test_bad_arguments():
    pos, nrm = _plane(4, 4)
    mask = torch.ones(4, 4, dtype=torch.bool)
    with pytest.raises(ValueError, match="stride: expected an int >= 1, got 0"):
        coarse_receivers(pos, nrm, mask, 0)
    with pytest.raises(ValueError, match="position: expected shape"):
        coarse_receivers(pos[..., :2], nrm, mask, 2)
    with pytest.raises(ValueError, match="normal, mask"):
        coarse_receivers(pos, nrm, mask[:3], 2)


def test_reference_renderer_stride():
    """stride 2 on a lit sphere: half the receivers, within 1% of the full render; stride 1 is the full render.

    At the default spacing (aliasing of the source lattice below 1%); with sources much coarser than the pixels,
    the full render itself carries the lattice's pattern, which interpolation does not reproduce.
    """
    r = build("reference", sphere(5.0, 4), "marble")
    cam = Camera(eye=(0, 0, 22), target=(0, 0, 0), width=64, height=64)
    light = DirectionalLight((0.3, -0.2, -1), 1.0)
    full = r.render(light, cam)
    r.knobs["stride"] = 2
    coarse = r.render(light, cam)
    assert coarse.stats["receivers"] < 0.6 * full.stats["receivers"]
    assert coarse.stats["receivers"] + coarse.stats["interpolated"] == full.stats["receivers"]
    assert image_error(coarse, full)["rel_rmse"] < 0.01, image_error(coarse, full)
    r.knobs["stride"] = 1
    assert torch.equal(r.render(light, cam).radiance, full.radiance)


def test_supersampled_reference_converges_to_the_pixel_integral_at_little_cost():
    """The reference's default with ``spp=16``: B on the fine grid at stride 4 (the supersampling factor).

    A back-lit thin torus (the light behind it, a 5% fill beside the camera) at 24x24: one sample per pixel is
    several % off the pixel integral (silhouettes and the thin tube's terminators); 16 spp with the automatic
    stride is within 1% of the fully evaluated 16-spp frame, with a fraction of its receivers (measured: 0.4% and
    11.8% at the default spacing, 2,477 receivers against 6,074).
    """
    from torchsss.geometry import PointLight, torus

    mesh = torus(5.0, 1.8, 40, 20)
    cam = Camera(eye=(0, 3.0, 24.0), target=(0, 0, 0), width=24, height=24, fov_deg=30.0)
    lights = [PointLight((-4.0, 5.0, -30.0), 900.0), PointLight((12.0, 6.0, 16.0), 20.0)]
    r = build("reference", mesh, "apple", spacing_mm=1.0)  # coarser sources than the default: a faster test
    auto = r.render(lights, cam, spp=16)
    one = r.render(lights, cam)
    r.knobs["stride"] = 1
    full = r.render(lights, cam, spp=16)
    err_auto, err_one = image_error(auto, full)["rel_rmse"], image_error(one, full)["rel_rmse"]
    assert err_auto < 0.01, err_auto
    assert err_one > 0.03, err_one  # pixel integration matters on this scene
    assert auto.stats["receivers"] < 0.5 * full.stats["receivers"], (auto.stats["receivers"], full.stats["receivers"])
