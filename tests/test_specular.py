"""Opt-in GGX specular highlights: closed form at the mirror configuration, visibility, and the render flag."""

from __future__ import annotations

import math

import pytest
import torch

from torchsss.cli import main
from torchsss.geometry import DirectionalLight, PointLight
from torchsss.geometry.gbuffer import GBuffer
from torchsss.io import read_exr
from torchsss.physics import fresnel_reflectance
from torchsss.pipelines.specular import specular_radiance


def _gbuffer(view_dirs: list[list[float]]) -> GBuffer:
    n = len(view_dirs)
    pos = torch.zeros(1, 3, 1, n, dtype=torch.float64)
    nrm = torch.zeros(1, 3, 1, n, dtype=torch.float64)
    nrm[:, 2] = 1.0
    vd = torch.nn.functional.normalize(torch.tensor(view_dirs, dtype=torch.float64), dim=-1).T.reshape(1, 3, 1, n)
    return GBuffer(pos, nrm, vd, torch.zeros(1, 1, 1, n, dtype=torch.long), torch.ones(1, 1, 1, n, dtype=torch.bool))


@pytest.mark.parametrize("theta_deg", [0.0, 30.0, 60.0])
@pytest.mark.parametrize("alpha", [0.1, 0.3, 0.7])
def test_mirror_configuration_closed_form(theta_deg, alpha):
    t = math.radians(theta_deg)
    light = DirectionalLight((-math.sin(t), 0.0, -math.cos(t)), 2.0)  # travels down, arrives from +x side
    g = _gbuffer([[-math.sin(t), 0.0, math.cos(t)]])  # the mirror direction
    got = specular_radiance(g, [light], 1.4, roughness=alpha)[0, :, 0, 0]
    c = math.cos(t)
    k = alpha / 2
    g1 = c / (c * (1 - k) + k)
    d = 1.0 / (math.pi * alpha * alpha)
    f = float(fresnel_reflectance(torch.tensor(c, dtype=torch.float64), 1.4)) * d * g1 * g1 / (4 * c * c)
    torch.testing.assert_close(got, torch.full((3,), 2.0 * f * c, dtype=torch.float64), rtol=1e-10, atol=0)


def test_peak_at_mirror_and_zero_when_unlit_or_shadowed():
    light = PointLight((-30.0, 0.0, 30.0), 1e3)
    angles = torch.linspace(-80, 80, 33)
    dirs = [[math.sin(math.radians(a)), 0.0, math.cos(math.radians(a))] for a in angles.tolist()]
    # a smooth boundary peaks at the mirror direction (rough ones peak off-specular towards grazing, as GGX does)
    sharp = specular_radiance(_gbuffer(dirs), [light], 1.3, roughness=0.1)[0, 0, 0]
    assert abs(float(angles[int(sharp.argmax())]) - 45.0) <= 5.0
    s = specular_radiance(_gbuffer(dirs), [light], 1.3)[0, 0, 0]
    below = DirectionalLight((0.0, 0.0, 1.0), 1.0)  # arrives from under the surface
    assert float(specular_radiance(_gbuffer(dirs), [below], 1.3).abs().max()) == 0.0
    shadowed = specular_radiance(_gbuffer(dirs), [light], 1.3, visibility=[torch.zeros(1, 33, dtype=torch.float64)])
    assert float(shadowed.abs().max()) == 0.0
    brighter = specular_radiance(_gbuffer(dirs), [light], 1.8)[0, 0, 0]
    assert bool((brighter >= s).all()) and float((brighter - s).max()) > 0


def test_bad_roughness():
    with pytest.raises(ValueError, match="roughness"):
        specular_radiance(_gbuffer([[0.0, 0.0, 1.0]]), [DirectionalLight((0, 0, -1), 1.0)], 1.3, roughness=0.0)
    with pytest.raises(ValueError, match="visibility"):
        specular_radiance(_gbuffer([[0.0, 0.0, 1.0]]), [DirectionalLight((0, 0, -1), 1.0)], 1.3, visibility=[])


def test_render_flag_adds_highlights(tmp_path):
    # one sample per pixel for both: --specular renders 1 spp by default (upsampling forms B's radiance alone)
    base = ["render", "default", "--resolution", "20x20", "--spacing", "3.0", "--no-progress", "--spp", "1"]
    assert main([*base, "--out", str(tmp_path / "a.exr")]) == 0
    assert main([*base, "--out", str(tmp_path / "b.exr"), "--specular"]) == 0
    a, b = read_exr(tmp_path / "a.exr"), read_exr(tmp_path / "b.exr")
    assert bool((b >= a - 1e-7).all()) and float((b - a).max()) > 0
