"""Light-view samples split under grazing light (``geometry.grazing.split_grazing``) and the splat renderer's use."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh
from conftest import rel_rmse

from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import light_view
from torchsss.geometry.grazing import split_grazing
from torchsss.geometry.lights import DirectionalLight
from torchsss.geometry.procedural import sphere
from torchsss.pipelines import build
from torchsss.pipelines.splat import light_sources
from torchsss.scene import Scene

D = torch.float64


def _tilted_plane(slope: float, size: int = 8, step: bool = False):
    """An orthographic light along -z over the plane z = slope * x (pixel centres at x, y = -3.5 .. 3.5 mm, 1 mm
    pixels); ``step`` lifts the half x > 0 by 20 mm (a depth jump between two parallel planes)."""
    cam = Camera(eye=(0, 0, 100), target=(0, 0, 0), width=size, height=size, projection="orthographic",
                 ortho_half_height=size / 2)
    c = torch.arange(size, dtype=D) - (size - 1) / 2
    x, y = torch.meshgrid(c, -c, indexing="xy")
    z = slope * x + (20.0 * (x > 0) if step else 0.0)
    pos = torch.stack([x, y, z]).unsqueeze(0)
    big = torch.tensor([[-50.0, -50, -50 * slope], [50, -50, 50 * slope], [0, 50, 0]], dtype=D)
    corners = big.reshape(1, 9, 1, 1).expand(1, 9, size, size).clone()
    if step:
        corners[:, 2::3] += 20.0 * (x > 0)
    light = torch.tensor([0.0, 0.0, 1.0], dtype=D).view(1, 3, 1, 1).expand(1, 3, size, size)
    mask = torch.ones(1, 1, size, size, dtype=torch.bool)
    flux = torch.rand(1, 3, size, size, dtype=D, generator=torch.Generator().manual_seed(1)) + 0.5
    return pos, mask, flux, corners, light, torch.ones(1, 1, size, size, dtype=D), cam.view_proj(dtype=D)


@pytest.mark.parametrize("slope,max_stretch", [(10.0, 2.0), (10.0, 4.0), (3.0, 1.0), (40.0, 2.0)])
def test_split_matches_the_strips_on_a_tilted_plane(slope, max_stretch):
    """Closed form: pixel c's ray tube cuts the plane in x in [x_c - 1/2, x_c + 1/2]; its m pieces sit at the centres
    of m equal parts (z = slope x on the plane), each with 1/m of the flux; edge pixels too (within the face)."""
    pos, mask, flux, corners, light, texel, vp = _tilted_plane(slope)
    p, f, index = split_grazing(pos, mask, flux, corners, light, texel, vp, max_stretch=max_stretch)
    stretch = math.sqrt(1.0 + slope * slope)  # 1 / cos
    m = min(16, math.ceil(stretch / max_stretch - 1e-9))
    assert p.shape[0] == 64 * m and torch.equal(index, torch.arange(64).repeat_interleave(m))
    src = pos[0].permute(1, 2, 0).reshape(-1, 3)[index]
    t = ((torch.arange(m, dtype=D) + 0.5) / m - 0.5).repeat(64)
    expected = torch.stack([src[:, 0] + t, src[:, 1], slope * (src[:, 0] + t)], dim=-1)
    order = torch.argsort(p[:, 0].view(64, m), dim=1)  # each pixel's pieces by x (the strip runs either way)
    got = torch.gather(p.view(64, m, 3), 1, order.unsqueeze(-1).expand(-1, -1, 3)).reshape(-1, 3)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-9)
    torch.testing.assert_close(f.sum(0), flux.sum((0, 2, 3)), rtol=1e-12, atol=0)
    torch.testing.assert_close(f, (flux[0].permute(1, 2, 0).reshape(-1, 3) / m)[index], rtol=1e-12, atol=0)


def test_head_on_light_is_untouched_and_max_split_caps():
    pos, mask, flux, corners, light, texel, vp = _tilted_plane(0.5)  # cos 0.89: stretch 1.12 < 2
    p, f, index = split_grazing(pos, mask, flux, corners, light, texel, vp)
    torch.testing.assert_close(p, pos[0].permute(1, 2, 0).reshape(-1, 3), rtol=0, atol=0)
    assert torch.equal(index, torch.arange(64))
    pos, mask, flux, corners, light, texel, vp = _tilted_plane(1e4)  # edge-on: capped
    p, _, _ = split_grazing(pos, mask, flux, corners, light, texel, vp, max_split=5)
    assert p.shape[0] == 64 * 5
    # exactly edge-on (cos = 0): capped, every piece finite and on its face, the flux kept
    flat = torch.zeros_like(pos)
    flat[:, :2] = pos[:, :2]
    tri = torch.tensor([[-50.0, -50, 0], [50, -50, 0], [0, 50, 0]], dtype=D).reshape(1, 9, 1, 1).expand_as(corners)
    sideways = torch.tensor([1.0, 0.0, 0.0], dtype=D).view(1, 3, 1, 1).expand_as(light)
    p, f, _ = split_grazing(flat, mask, flux, tri, sideways, texel, vp, max_split=8)
    assert p.shape[0] == 64 * 8 and bool(torch.isfinite(p).all()) and float(p[:, 2].abs().max()) == 0.0
    torch.testing.assert_close(f.sum(0), flux.sum((0, 2, 3)), rtol=1e-12, atol=0)
    empty = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
    p, f, index = split_grazing(pos, empty, flux, corners, light, texel, vp)
    assert p.shape == (0, 3) and f.shape == (0, 3) and index.shape == (0,)


def test_a_depth_jump_keeps_pieces_on_their_surface():
    """Two parallel planes 20 mm apart: no piece is interpolated across the jump (each lies on its pixel's plane)."""
    pos, mask, flux, corners, light, texel, vp = _tilted_plane(10.0, step=True)
    p, _, index = split_grazing(pos, mask, flux, corners, light, texel, vp)
    lifted = (pos[0, 0].reshape(-1) > 0)[index]
    torch.testing.assert_close(p[:, 2], 10.0 * p[:, 0] + 20.0 * lifted, rtol=0, atol=1e-9)


def test_pieces_follow_a_curved_surface():
    """A sphere lit from the side: the flux of the light view is conserved and the pieces lie on the mesh, up to the
    sag of the chord between two neighbouring pixels' points near the terminator (measured 0.09 mm = 0.21 texels;
    the others within 1e-9 mm), where the face's tangent plane would run off the sphere."""
    m = sphere(10.0, 4, dtype=D)
    light = DirectionalLight((-1.0, 0.0, 0.0), 1.0)
    lv = light_view(m, light, 48, 1.3)
    p, f, _, _ = light_sources(m, light, 48, 1.3, 8, 4.0, flux="facet")  # the light view's own flux, split
    assert p.shape[0] > int(lv.mask.sum())
    torch.testing.assert_close(f.sum(0), lv.flux.sum((0, 2, 3)), rtol=1e-10, atol=0)
    tm = trimesh.Trimesh(m.vertices.numpy(), m.faces.numpy(), process=False)
    _, dist, _ = trimesh.proximity.closest_point(tm, p.numpy())
    texel = 2.0 * 10.0 * 1.05 / 48  # the light view spans the bounding sphere (with its margin)
    assert float(dist.max()) < 0.25 * texel, float(dist.max())
    centre_distance = p.norm(dim=-1).numpy()
    assert float(centre_distance.max()) < 10.0 + 1e-9  # chords of a convex surface: never floating off the sphere


def test_split_gradcheck_and_bad_input():
    pos, mask, flux, corners, light, texel, vp = _tilted_plane(10.0, size=4)
    pos = pos.clone().requires_grad_(True)
    flux = flux.clone().requires_grad_(True)
    weights = torch.randn(200, 6, dtype=D, generator=torch.Generator().manual_seed(0))

    def f(p_, f_):
        a, b, _ = split_grazing(p_, mask, f_, corners, light, texel, vp)
        return (torch.cat([a, b], -1) * weights[: a.shape[0]]).sum()

    assert torch.autograd.gradcheck(f, (pos, flux))
    args = _tilted_plane(10.0)
    with pytest.raises(TypeError, match="max_stretch"):
        split_grazing(*args, max_stretch="2")
    with pytest.raises(ValueError, match="max_stretch"):
        split_grazing(*args, max_stretch=0.5)
    with pytest.raises(TypeError, match="max_split"):
        split_grazing(*args, max_split=2.0)
    with pytest.raises(ValueError, match="max_split"):
        split_grazing(*args, max_split=0)
    with pytest.raises(ValueError, match="mask"):
        split_grazing(args[0], args[1][..., :4], *args[2:])


def _grazing_slab_scene() -> Scene:
    """A 25 mm cream slab (1.25 mm thick) facing the camera, lit from the side: the front face at 5.5° to the light."""
    d = 62.5
    v = (1.0, 0.3, 0.1)
    n = math.sqrt(sum(x * x for x in v))
    return Scene.from_dict({
        "name": "grazing slab", "mesh": "slab", "size_mm": 25.0, "material": "cream",
        "lights": [{"type": "point", "position": [x / n * d for x in v], "intensity": [4.0 * d * d] * 3}],
        "camera": {"eye": [0.0, 0.0, 55.0], "target": [0.0, 0.0, 0.0], "fov_deg": 30.0, "width": 64, "height": 64}})


def test_splat_under_grazing_light_follows_the_reference():
    """Shah's one splat per light-view pixel leaves the grazing-lit face in stripes ten texels apart; the split
    splats follow the reference (measured at 64 x 64: 12.9% -> 1.95%, 7,661 -> 17,666 splats)."""
    scene = _grazing_slab_scene()
    mesh, mat, lights, cam = scene.load_mesh(), scene.material, scene.lights, scene.camera
    ref = build("reference", mesh, mat, eps=0.3).render(lights, cam)
    split = build("splat", mesh, mat).render(lights, cam)
    whole = build("splat", mesh, mat, max_stretch=None).render(lights, cam)
    err_split, err_whole = rel_rmse(split.radiance, ref.radiance), rel_rmse(whole.radiance, ref.radiance)
    assert err_split < 0.04 and err_whole > 3.0 * err_split, (err_split, err_whole)
    assert split.stats["splats"] > whole.stats["splats"]
    assert split.stats["knobs"]["max_stretch"] == 4.0
    for bad in (0.5, "2", math.inf):
        with pytest.raises(ValueError, match="max_stretch"):
            build("splat", mesh, mat, max_stretch=bad)
