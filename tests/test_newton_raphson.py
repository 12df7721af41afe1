"""newton_raphson_intersect / lookup_positions against exact ray-plane and ray-heightfield intersections.

The positions textures are made analytically: every light pixel's ray (``Camera.rays``) is cast onto the surface
(closed form for planes, march + bisection to machine precision for heightfields), and errors are measured against
the exact intersection of each test ray with the same surface, in texels of the light camera at the hit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchsss.geometry.camera import Camera
from torchsss.ops.newton_raphson import lookup_positions, newton_raphson_intersect
from torchsss.ops.refraction import refract

F64 = torch.float64
SIZE = 64


# -- scenes ---------------------------------------------------------------------------------------------------------
def _light(eye=(0.0, 0.0, 100.0), size=SIZE, ortho=False, half=40.0):
    kw = {"projection": "orthographic", "ortho_half_height": half} if ortho else {}
    return Camera(eye=eye, target=(0.0, 0.0, 0.0), fov_deg=40.0, width=size, height=size, near=1.0, far=500.0, **kw)


def _plane_texture(cam, z0=0.0):
    """(1, 3, H, W) world positions where the light's pixel rays meet the plane z = z0 (closed form)."""
    o, d = cam.rays(dtype=F64)
    t = (z0 - o[:, 2:3]) / d[:, 2:3]
    return o + t * d


def _texel_mm(cam, points):
    """Size of one light texel (mm) at world points (N, 3): 2 w tan(fov / 2) / H, or 2 h / H for orthographic."""
    if cam.projection == "orthographic":
        return torch.full(points.shape[:1], 2.0 * cam.ortho_half_height / cam.height, dtype=F64)
    vp = cam.view_proj(dtype=F64)
    w = points @ vp[3, :3] + vp[3, 3]
    return 2.0 * w * math.tan(math.radians(cam.fov_deg) / 2) / cam.height


def _rays_near_light(cam, n, max_angle_deg, seed, spread=22.0):
    """Origins between the light and the plane z = 0, directions within max_angle of the light's line of sight."""
    g = torch.Generator().manual_seed(seed)
    eye = torch.tensor(cam.eye, dtype=F64)
    target = torch.cat([(torch.rand(n, 2, generator=g, dtype=F64) - 0.5) * 2 * spread, torch.zeros(n, 1, dtype=F64)], 1)
    s = 0.4 + 0.5 * torch.rand(n, 1, generator=g, dtype=F64)
    o = eye + s * (target - eye)
    light = (target - eye) / torch.linalg.vector_norm(target - eye, dim=1, keepdim=True)
    axis = torch.randn(n, 3, generator=g, dtype=F64)
    axis = axis - (axis * light).sum(1, keepdim=True) * light
    axis = axis / torch.linalg.vector_norm(axis, dim=1, keepdim=True)
    theta = torch.rand(n, 1, generator=g, dtype=F64) * math.radians(max_angle_deg)
    r = torch.cos(theta) * light + torch.sin(theta) * axis
    keep = r[:, 2] < -0.2
    return o[keep], r[keep]


def _plane_hit(o, r, z0=0.0):
    """Exact distance along unit r to the plane z = z0."""
    return (z0 - o[:, 2]) / r[:, 2]


def _inside(cam, points, margin=1.0):
    """Points that project at least ``margin`` texels inside the light's image."""
    vp = cam.view_proj(dtype=F64)
    c = points @ vp[:, :3].T + vp[:, 3]
    ndc = c[:, :2] / c[:, 3:]
    lim = 1.0 - 2.0 * margin / cam.height
    return (c[:, 3] > 0) & (ndc.abs() <= lim).all(1)


def _run(o, r, tex, cam, iterations=5, method="shah", dtype=F64, **kw):
    vp = cam.view_proj(dtype=F64)[None]
    out = newton_raphson_intersect(
        o[None].to(dtype), r[None].to(dtype), tex.to(dtype), vp.to(dtype), iterations, method, **kw
    )
    return tuple(x[0] if isinstance(x, torch.Tensor) else {k: v[0] for k, v in x.items()} for x in out)


def _err_texels(cam, o, r, d, d_exact):
    hit = o + d_exact[:, None] * r
    return (d.double() - d_exact).abs() / _texel_mm(cam, hit)


# heightfields of the water-over-rugged-floor scene (Shah Figs. 5.5, 5.8), z up, mm
def _floor(x, y):
    return (
        -2.0
        + 1.5 * torch.sin(0.25 * x + 0.3) * torch.sin(0.2 * y)
        + 0.8 * torch.sin(0.13 * x - 0.21 * y + 1.0)
        + 0.3 * torch.sin(0.6 * x + 0.4 * y)
    )


def _water(x, y):
    return 40.0 + 1.0 * torch.sin(0.3 * x + 0.2 * y) + 0.5 * torch.sin(-0.25 * x + 0.45 * y + 0.5)


def _water_normal(x, y):
    dx = 0.3 * torch.cos(0.3 * x + 0.2 * y) - 0.125 * torch.cos(-0.25 * x + 0.45 * y + 0.5)
    dy = 0.2 * torch.cos(0.3 * x + 0.2 * y) + 0.225 * torch.cos(-0.25 * x + 0.45 * y + 0.5)
    return torch.stack([-dx, -dy, torch.ones_like(dx)], -1)


def _march(o, d, height, t0, t1, steps):
    """First t in [t0, t1] where o + t d goes below z = height(x, y): a sign change on a grid, then 60 bisections."""
    ts = torch.linspace(0.0, 1.0, steps + 1, dtype=F64)
    t = t0 + (t1 - t0) * ts
    x = o[:, None, :] + t[None, :, None] * d[:, None, :]
    below = (x[..., 2] - height(x[..., 0], x[..., 1])) <= 0
    first = below.to(torch.int8).argmax(1)
    ok = below.any(1) & (first > 0)
    i = first.clamp_min(1)
    a, b = t[i - 1], t[i]
    for _ in range(60):
        m = 0.5 * (a + b)
        xm = o + m[:, None] * d
        above = xm[:, 2] - height(xm[:, 0], xm[:, 1]) > 0
        a, b = torch.where(above, m, a), torch.where(above, b, m)
    return torch.where(ok, 0.5 * (a + b), torch.full_like(a, float("nan")))


@pytest.fixture(scope="module")
def water_scene():
    """Light 100 mm above a rugged floor; rays refracted (eta = 1/1.33) by a wavy water surface 40 mm up."""
    cam = _light()
    o_l, d_l = cam.rays(dtype=F64)
    ol, dl = o_l[0].reshape(3, -1).T, d_l[0].reshape(3, -1).T
    t = _march(ol, dl, _floor, 92.0, 122.0, 150)
    assert not bool(torch.isnan(t).any())
    tex = (ol + t[:, None] * dl).T.reshape(1, 3, SIZE, SIZE)
    g = torch.Generator().manual_seed(1)
    xy = (torch.rand(500, 2, generator=g, dtype=F64) - 0.5) * 36.0
    eye = torch.tensor(cam.eye, dtype=F64).expand(500, 3)
    sight = torch.cat([xy, torch.full((500, 1), -60.0, dtype=F64)], 1)
    sight = sight / torch.linalg.vector_norm(sight, dim=1, keepdim=True)
    o = eye + _march(eye, sight, _water, 40.0, 80.0, 100)[:, None] * sight
    r, tir = refract(sight, _water_normal(o[:, 0], o[:, 1]), 1.0 / 1.33)
    assert not tir.any()
    d_exact = _march(o, r, _floor, 0.0, 60.0, 300)
    assert not bool(torch.isnan(d_exact).any())
    return cam, tex, o, r, d_exact


# -- lookups --------------------------------------------------------------------------------------------------------
def test_lookup_is_exact_on_an_affine_texture():
    # An orthographic light over a plane stores positions that are affine in the pixel coordinates, so bilinear
    # lookups are exact between pixel centres: any half-texel offset or flipped row order would show up in mm.
    cam = _light(ortho=True, half=30.0, size=48)
    tex = _plane_texture(cam, z0=-3.0)
    g = torch.Generator().manual_seed(0)
    pts = torch.cat(
        [(torch.rand(1, 300, 2, generator=g, dtype=F64) - 0.5) * 58.0, torch.full((1, 300, 1), -3.0, dtype=F64)], 2
    )
    p, hit = lookup_positions(pts, tex, cam.view_proj(dtype=F64))
    assert hit.all()
    torch.testing.assert_close(p, pts, rtol=0, atol=1e-11)
    # points above the plane see the plane point straight below them (orthographic light looking down -z)
    above = pts + torch.tensor([0.0, 0.0, 17.0], dtype=F64)
    p2, hit2 = lookup_positions(above, tex, cam.view_proj(dtype=F64)[None])
    assert hit2.all()
    torch.testing.assert_close(p2, pts, rtol=0, atol=1e-11)
    # texel centres return the stored texels: row 0 (top) holds the largest y
    assert tex[0, 1, 0, 0] > tex[0, 1, -1, 0]


def test_lookup_frustum_behind_and_empty():
    cam = _light()
    tex = _plane_texture(cam)
    tex[:, :, :, :8] = float("nan")  # the left 8 columns (smallest x) hold no receiver
    vp = cam.view_proj(dtype=F64)
    pts = torch.tensor(
        [
            [
                [0.0, 0.0, 0.0],  # centre
                [0.0, 0.0, 150.0],  # behind the light
                [45.0, 0.0, 0.0],  # right of the frustum (half width 36.4 mm at z = 0)
                [0.0, -45.0, 0.0],  # below the frustum
                [-33.0, 0.0, 0.0],  # in the empty columns
                [float("nan"), 0.0, 0.0],
                [0.0, 0.0, 99.5],  # between the eye and the near plane: not clipped
            ]
        ],
        dtype=F64,
    )
    p, hit = lookup_positions(pts, tex, vp)
    assert hit.tolist() == [[True, False, False, False, False, False, True]]
    assert bool(torch.isfinite(p).all()) and torch.equal(p[0, ~hit[0]], torch.zeros(5, 3, dtype=F64))
    torch.testing.assert_close(p[0, [0, 6]], torch.zeros(2, 3, dtype=F64), rtol=0, atol=1e-6)
    # +-inf in any one channel also means "no receiver"; a texel next to an empty one still hits (coverage > 1/2)
    centres = tex[0, :, [45, 15, 30], [45, 45, 40]].T.clone()[None]  # texel centres: all the weight on one texel
    tex[:, 2, 40:50, 40:50] = float("inf")
    tex[:, 0, 10:20, 40:50] = -float("inf")
    tex[:, 1, 30, 41] = float("nan")
    texel = 2 * 100.0 * math.tan(math.radians(20.0)) / SIZE  # at z = 0; world +x is texture +column here
    shifted = centres[:, 2:] + torch.tensor([[[0.3 * texel, 0.0, 0.0], [0.7 * texel, 0.0, 0.0]]], dtype=F64)
    p, hit = lookup_positions(torch.cat([centres, shifted], 1), tex, vp)
    assert hit.tolist() == [[False, False, True, True, False]] and bool(torch.isfinite(p).all())
    # the hits average the receiver texels only: here just texel (30, 40), whatever the weight of its empty neighbour
    torch.testing.assert_close(p[0, 2:4], centres[0, 2:3].expand(2, 3), rtol=0, atol=1e-12)


# -- exact scenes ---------------------------------------------------------------------------------------------------
def test_orthographic_plane_shah_iterates_follow_the_closed_form():
    # Light looking straight down -z, plane z = 0: P(x) = (x_x, x_y, 0), so |P(o + d r) - o|^2 = d^2 (1 - r_z^2) + o_z^2
    # and Shah's estimates from d_0 = 0 are d_{k+1} = sqrt(d_k^2 (1 - r_z^2) + o_z^2), converging to o_z / |r_z|.
    cam = _light(ortho=True)
    tex = _plane_texture(cam)
    o, r = _rays_near_light(cam, 300, 50.0, seed=1, spread=15.0)
    keep = _inside(cam, o) & _inside(cam, o + _plane_hit(o, r)[:, None] * r)  # lookups exact between pixel centres
    o, r = o[keep], r[keep]
    assert o.shape[0] > 100
    d = torch.zeros(o.shape[0], dtype=F64)
    for k in range(1, 7):
        d = torch.sqrt(d * d * (1 - r[:, 2] ** 2) + o[:, 2] ** 2)
        got, valid = _run(o, r, tex, cam, k, "shah", fallback=False, tol=0.0)
        assert valid.all()
        torch.testing.assert_close(got, d, rtol=1e-12, atol=1e-9)
    # after enough iterations: the exact intersection
    got, valid = _run(o, r, tex, cam, 60, "shah", tol=0.0)
    torch.testing.assert_close(got, _plane_hit(o, r), rtol=0, atol=1e-8)


def test_orthographic_plane_newton_is_exact_after_one_iteration():
    # The light looks down -z, so f(d) = l.(P - x) = (0, 0, -1).(P - x) = o_z + d r_z is linear in d: one Newton step
    # with a forward difference lands on the root, and the converged rays stay there.
    cam = _light(ortho=True)
    tex = _plane_texture(cam)
    o, r = _rays_near_light(cam, 300, 70.0, seed=2, spread=15.0)
    keep = _inside(cam, o) & _inside(cam, o + _plane_hit(o, r)[:, None] * r)
    o, r = o[keep], r[keep]
    assert o.shape[0] > 100
    for k in (1, 2, 5):
        d, valid, info = _run(o, r, tex, cam, k, "newton", return_info=True)
        assert valid.all() and not info["oscillated"].any() and not info["fallback"].any()
        torch.testing.assert_close(d, _plane_hit(o, r), rtol=0, atol=1e-9)
        assert float(info["residual"].max()) < 1e-9


def test_perspective_plane_accuracy_per_method():
    cam = _light()
    tex = _plane_texture(cam)
    for max_angle, method, bound_median, bound_max in [
        (30.0, "shah", 0.01, 0.5),  # rays close to the light's lines of sight: Shah converges in a few steps
        (60.0, "shah", 0.05, None),  # far from them it converges slowly (fixed-point rate ~ sin^2 of the angle)
        (60.0, "newton", 0.01, 0.5),
    ]:
        o, r = _rays_near_light(cam, 400, max_angle, seed=3)
        d_exact = _plane_hit(o, r)
        hits_inside = _inside(cam, o + d_exact[:, None] * r, margin=2.0)
        d, valid = _run(o, r, tex, cam, 5, method)
        err = _err_texels(cam, o, r, d, d_exact)[valid]
        assert valid.sum() >= 0.7 * hits_inside.sum(), (method, max_angle)
        assert float(err.median()) < bound_median, (method, max_angle, err.median())
        if bound_max is not None:
            assert float(err.max()) < bound_max, (method, max_angle, err.max())
        assert not bool((valid & ~_inside(cam, o + d_exact[:, None] * r, margin=-1.0)).any())  # no hit off-texture


def test_tilted_light_plane():
    # an oblique light (not centred over the receiver, not axis-aligned) checks the row/column conventions
    cam = _light(eye=(30.0, -20.0, 90.0))
    tex = _plane_texture(cam)
    o, r = _rays_near_light(cam, 300, 20.0, seed=4, spread=15.0)
    d_exact = _plane_hit(o, r)
    for method in ("shah", "newton"):
        d, valid = _run(o, r, tex, cam, 5, method)
        assert valid.float().mean() > 0.9
        err = _err_texels(cam, o, r, d, d_exact)[valid]
        assert float(err.median()) < 0.05 and float(err.max()) < 0.5, method


def test_water_over_rugged_floor(water_scene):
    cam, tex, o, r, d_exact = water_scene
    # Each step moves only within the texture's bilinear approximation of the floor; both methods meet it well
    # within half a texel. Shah's fixed point can sit at a kink of the interpolant, hence its looser maximum.
    for method, bound_p90, bound_max in [("shah", 0.1, 1.0), ("newton", 0.1, 0.5)]:
        d, valid, info = _run(o, r, tex, cam, 5, method, return_info=True)
        assert valid.float().mean() > 0.97, method
        err = _err_texels(cam, o, r, d, d_exact)[valid]
        assert float(err.median()) < 0.5 / 10, (method, err.median())
        assert float(err.quantile(0.9)) < bound_p90, method
        assert float(err.max()) < bound_max, (method, err.max())
        assert float(info["residual"][valid].median()) < 0.1 * float(_texel_mm(cam, o[:1]).item())
    # a single Shah step (what Shah used for the caustics) is already within a few texels
    d1, valid1 = _run(o, r, tex, cam, 1, "shah")
    assert float(_err_texels(cam, o, r, d1, d_exact)[valid1].median()) < 2.0


def test_float32_matches_accuracy(water_scene):
    cam, tex, o, r, d_exact = water_scene
    for method in ("shah", "newton"):
        d, valid = _run(o, r, tex, cam, 5, method, dtype=torch.float32)
        assert d.dtype == torch.float32 and valid.float().mean() > 0.97
        err = _err_texels(cam, o, r, d, d_exact)[valid]
        assert float(err.median()) < 0.05 and float(err.quantile(0.9)) < 0.1, method


# -- oscillation and the bisection fallback ------------------------------------------------------------------------
def _atan_scene(size=128):
    """A receiver built so that f(d) = -(K / c) atan((d - d*) / L) along one ray (orthographic light looking down -z:
    f = x_z - height(x_x)): Newton from d = 0 overshoots with growing residuals (|d* / L| = 2.5 > 1.39), so it
    oscillates and diverges; the exact root is d*."""
    cam = _light(ortho=True, half=50.0, size=size)
    s, c = 0.8, 0.6
    o = torch.tensor([[-20.0, 0.0, 30.0]], dtype=F64)
    r = torch.tensor([[s, 0.0, -c]], dtype=F64)
    d_star, length, k = 20.0, 8.0, 3.0

    def height(x):
        d = (x - o[0, 0]) / s
        return o[0, 2] - c * d + (k / c) * torch.atan((d - d_star) / length)

    po, _ = cam.rays(dtype=F64)
    x, y = po[:, 0], po[:, 1]
    tex = torch.stack([x, y, height(x)], 1)
    return cam, tex, o, r, d_star


@pytest.mark.parametrize("method", ["shah", "newton"])
@pytest.mark.parametrize("fallback", [True, False])
def test_export_loop_matches_the_python_loop(method, fallback, monkeypatch):
    """Exported, the iterations run as one ``while_loop`` body (an ONNX Loop); run eagerly, that body gives exactly
    what the Python loop gives, diagnostics included (an oscillating scene exercises the bisection branch)."""
    import torchsss.ops.newton_raphson as nr

    for iterations in (4, 7):
        cam, tex, o, r, _ = _atan_scene()
        plain = _run(o, r, tex, cam, iterations, method, fallback=fallback, return_info=True)
        with monkeypatch.context() as m:
            m.setattr(nr, "is_exporting", lambda: True)
            looped = _run(o, r, tex, cam, iterations, method, fallback=fallback, return_info=True)
        assert torch.equal(plain[0], looped[0]) and torch.equal(plain[1], looped[1])
        for key in ("oscillated", "fallback", "residual"):
            assert torch.equal(plain[2][key], looped[2][key]), key


def test_light_centre_is_the_null_vector_of_the_lookup_rows():
    """The light's centre from the Levi-Civita contraction: a perspective light's eye solves rows 0, 1 and 3 of
    ``view_proj`` (against torch.linalg.solve); an orthographic light's direction is their null vector, oriented so
    that clip depth grows along it."""
    from torchsss.ops.newton_raphson import _sight_centre

    gen = torch.Generator().manual_seed(11)
    mats = torch.randn(6, 4, 4, generator=gen, dtype=F64)
    k = _sight_centre(mats)
    rows = mats[:, [0, 1, 3]]
    eye = torch.linalg.solve(rows[:, :, :3], -rows[:, :, 3:])[..., 0]
    torch.testing.assert_close(k[:, :3], eye, rtol=1e-10, atol=1e-10)
    assert torch.equal(k[:, 3], torch.ones(6, dtype=F64))
    cams = [_light(ortho=True, eye=e) for e in ((0.0, 0.0, 100.0), (30.0, -20.0, 60.0))]
    ortho = torch.stack([c.view_proj(dtype=F64) for c in cams])
    k = _sight_centre(ortho)
    assert torch.equal(k[:, 3], torch.zeros(2, dtype=F64))
    direction = -k[:, :3]  # the line of sight runs along K_w x - K_xyz = -K_xyz, away from the light
    for c, dvec in zip(cams, direction):
        towards = torch.tensor(c.target, dtype=F64) - torch.tensor(c.eye, dtype=F64)
        torch.testing.assert_close(dvec / dvec.norm(), towards / towards.norm(), rtol=0, atol=1e-12)
    assert (rows[:, :, :3] @ eye[..., None] + rows[:, :, 3:]).abs().max() < 1e-9


def test_oscillation_detected_and_rescued_by_bisection():
    cam, tex, o, r, d_star = _atan_scene()
    # without the fallback: the second step's residual grows across the root, then the estimate leaves the texture
    d, valid, info = _run(o, r, tex, cam, 8, "newton", fallback=False, return_info=True)
    assert bool(info["oscillated"].all()) and not bool(info["fallback"].any())
    assert not bool(valid.all()) or float((d - d_star).abs().max()) > 5.0
    # with it: the last two estimates bracket the root and are bisected, Newton finishes from inside
    d, valid, info = _run(o, r, tex, cam, 8, "newton", fallback=True, return_info=True)
    assert bool(valid.all()) and bool(info["oscillated"].all()) and bool(info["fallback"].all())
    texel = 100.0 / 128
    assert float((d - d_star).abs().max()) < 0.1 * texel, d
    assert float(info["residual"].max()) < 0.1 * texel


# -- extremes -------------------------------------------------------------------------------------------------------
def test_empty_texels_invalidate_without_nan():
    cam = _light()
    tex = _plane_texture(cam)
    tex[:, :, 20:40, 10:30] = float("nan")
    tex[:, 0, 45:50, 45:50] = float("inf")
    tex[:, 2, 50:55, 5:9] = -float("inf")
    o, r = _rays_near_light(cam, 400, 15.0, seed=5)
    d_exact = _plane_hit(o, r)
    hit = o + d_exact[:, None] * r
    vp = cam.view_proj(dtype=F64)
    c = hit @ vp[:, :3].T + vp[:, 3]
    col = (c[:, 0] / c[:, 3] + 1) * SIZE / 2
    row = (1 - c[:, 1] / c[:, 3]) * SIZE / 2
    deep = (row > 21) & (row < 39) & (col > 11) & (col < 29)  # more than a texel inside the NaN block
    far = ((row < 16) | (row > 44) | (col > 34)) & (row < 43) & (row > 2) & (col > 2) & (col < 42)
    assert deep.sum() > 10 and far.sum() > 50
    for method in ("shah", "newton"):
        for dtype in (F64, torch.float32):
            d, valid, info = _run(o, r, tex, cam, 5, method, dtype=dtype, return_info=True)
            assert bool(torch.isfinite(d).all()) and bool(torch.isfinite(info["residual"]).all())
            assert not bool(valid[deep].any())
            assert bool((d[~valid] == 0).all())
            far_ok = valid & far
            assert far_ok.sum() >= 0.9 * far.sum()
            assert float(_err_texels(cam, o, r, d, d_exact)[far_ok].max()) < 0.1
    # gradients through a texture with empty texels stay finite
    tex_g = tex.clone().requires_grad_()
    o_g = o.clone().requires_grad_()
    d, valid = newton_raphson_intersect(o_g[None], r[None], tex_g, vp[None], 3, "newton")
    d.sum().backward()
    assert bool(torch.isfinite(o_g.grad).all()) and bool(torch.isfinite(tex_g.grad).all())
    assert float(tex_g.grad.abs().sum()) > 0


def test_rays_pointing_away_behind_and_outside_are_invalid():
    cam = _light()
    tex = _plane_texture(cam)
    up = torch.tensor([[0.0, 0.0, 30.0], [5.0, -3.0, 50.0], [-10.0, 10.0, 20.0]], dtype=F64)
    rays = {
        "pointing away (up)": (up, torch.tensor([[0.1, 0.0, 1.0], [0.0, 0.2, 1.0], [-0.3, 0.1, 1.0]], dtype=F64)),
        "origin behind the light": (
            torch.tensor([[0.0, 0.0, 130.0]] * 3, dtype=F64),
            torch.tensor([[0.0, 0.0, -1.0], [0.1, 0.0, -1.0], [0.0, -0.1, -1.0]], dtype=F64),
        ),
        "origin outside the frustum": (
            torch.tensor([[40.0, 0.0, 30.0], [0.0, -60.0, 10.0], [-80.0, 0.0, 50.0]], dtype=F64),
            torch.tensor([[-0.3, 0.0, -1.0], [0.0, 0.5, -1.0], [0.6, 0.0, -1.0]], dtype=F64),
        ),
        # 45-50 degree rays whose hit lies 1.5-4 mm beyond the frustum's side (half width 36.4 mm at z = 0)
        "hit outside the frustum": (
            torch.tensor([[30.0, 0.0, 8.0], [0.0, -30.0, 8.0], [-30.0, 0.0, 10.0]], dtype=F64),
            torch.tensor([[1.0, 0.0, -1.0], [0.0, -1.0, -1.0], [-1.0, 0.0, -1.2]], dtype=F64),
        ),
    }
    for name, (o, r) in rays.items():
        for method in ("shah", "newton"):
            for fallback in (False, True):
                d, valid, info = _run(o, r, tex, cam, 5, method, fallback=fallback, return_info=True)
                assert not bool(valid.any()), (name, method, fallback)
                assert torch.equal(d, torch.zeros_like(d)) and bool(torch.isfinite(info["residual"]).all())


def test_degenerate_rays_are_invalid():
    cam = _light()
    tex = _plane_texture(cam)
    o = torch.tensor([[0.0, 0.0, 30.0], [float("nan"), 0.0, 30.0], [1.0, 1.0, 30.0], [2.0, 0.0, 20.0]], dtype=F64)
    r = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, float("inf"), -1.0], [0.1, 0.0, -1.0]], dtype=F64)
    # a TIR ray from refract is the zero vector
    r[0], tir = refract(torch.tensor([0.9, 0.0, -0.3], dtype=F64), torch.tensor([0.0, 0.0, 1.0], dtype=F64), 1.5)
    assert tir
    for method in ("shah", "newton"):
        d, valid = _run(o, r, tex, cam, 5, method)
        assert valid.tolist() == [False, False, False, True]
        assert bool(torch.isfinite(d).all())
        torch.testing.assert_close(d[3], _plane_hit(o[3:], r[3:] / r[3].norm())[0], rtol=0, atol=1e-3)


def test_grazing_rays():
    cam = _light()
    tex = _plane_texture(cam)
    # 80-86 degrees from the vertical, 2-4 mm above the plane, hitting it within the texture
    ang = torch.tensor([80.0, 83.0, 86.0], dtype=F64).deg2rad()
    o = torch.tensor([[-15.0, 0.0, 4.0], [0.0, -15.0, 3.0], [-10.0, 5.0, 2.0]], dtype=F64)
    horizontal = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.7071, 0.7071, 0.0]], dtype=F64)
    r = torch.sin(ang)[:, None] * horizontal - torch.cos(ang)[:, None] * torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    d_exact = _plane_hit(o, r)
    texel = _texel_mm(cam, o + d_exact[:, None] * r)
    # Newton on the line-of-sight residual: the depth below the light falls almost linearly along the ray
    d, valid, info = _run(o, r, tex, cam, 5, "newton", return_info=True)
    assert valid.all()
    assert float(((d - d_exact).abs() / texel).max()) < 0.01
    # Shah's fixed-point rate is close to 1 for rays this far from the light's lines of sight: it stalls short of
    # the hit, its residual says so, and max_residual drops such rays.
    d, valid, info = _run(o, r, tex, cam, 5, "shah", return_info=True)
    assert valid.all()
    assert bool(((d - d_exact).abs() / texel > 5.0).all()) and bool((info["residual"] > texel).all())
    _, valid_r = _run(o, r, tex, cam, 5, "shah", max_residual=float(texel.min()))
    assert not valid_r.any()
    # exactly parallel to the plane: no intersection; Newton leaves the texture, Shah's estimate is caught by the
    # residual bound
    o_p = torch.tensor([[-10.0, 0.0, 5.0], [0.0, 0.0, 5.0], [10.0, 3.0, 5.0]], dtype=F64)
    r_p = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=F64)
    d, valid = _run(o_p, r_p, tex, cam, 5, "newton")
    assert not valid.any() and torch.equal(d, torch.zeros(3, dtype=F64))
    for method in ("shah", "newton"):
        d, valid, info = _run(o_p, r_p, tex, cam, 5, method, max_residual=1.0, return_info=True)
        assert not valid.any() and bool(torch.isfinite(info["residual"]).all()), method


def test_initial_distance_and_zero_iterations():
    cam = _light()
    tex = _plane_texture(cam)
    o, r = _rays_near_light(cam, 50, 20.0, seed=6)
    d_exact = _plane_hit(o, r)
    # zero iterations return the initial estimate once the final lookup confirms it
    d, valid = _run(o, r, tex, cam, 0, "newton", initial_distance=d_exact[None])
    assert valid.float().mean() > 0.9
    torch.testing.assert_close(d[valid], d_exact[valid], rtol=0, atol=0)
    d, valid = _run(o, r, tex, cam, 0, "shah")  # d_0 = 0: the origin itself, not a hit
    assert not valid.any()
    # a scalar start; a non-finite start invalidates its ray only
    d, valid = _run(o, r, tex, cam, 5, "newton", initial_distance=30.0)
    assert float(_err_texels(cam, o, r, d, d_exact)[valid].max()) < 0.05
    start = torch.full((1, o.shape[0]), 30.0, dtype=F64)
    start[0, 0] = float("nan")
    d, valid = _run(o, r, tex, cam, 5, "newton", initial_distance=start)
    assert not valid[0] and d[0] == 0 and valid[1:].float().mean() > 0.9


def test_batch_equals_single_calls():
    cams = [_light(), _light(eye=(20.0, 10.0, 80.0))]
    tex = torch.cat([_plane_texture(cams[0]), _plane_texture(cams[1], z0=-5.0)])
    vp = torch.stack([c.view_proj(dtype=F64) for c in cams])
    o0, r0 = _rays_near_light(cams[0], 40, 20.0, seed=7)
    o1, r1 = _rays_near_light(cams[1], 60, 20.0, seed=8)
    n = min(o0.shape[0], o1.shape[0])
    o, r = torch.stack([o0[:n], o1[:n]]), torch.stack([r0[:n], r1[:n]])
    for method in ("shah", "newton"):
        d, valid = newton_raphson_intersect(o, r, tex, vp, 4, method)
        for b in range(2):
            db, vb = newton_raphson_intersect(o[b : b + 1], r[b : b + 1], tex[b : b + 1], vp[b], 4, method)
            torch.testing.assert_close(d[b : b + 1], db, rtol=0, atol=1e-12)
            assert torch.equal(valid[b : b + 1], vb)


def test_device_dtype(device, dtype):
    cam = _light()
    tex = _plane_texture(cam)
    o, r = _rays_near_light(cam, 100, 20.0, seed=9)
    vp = cam.view_proj(dtype=F64)[None]
    d, valid = newton_raphson_intersect(
        o[None].to(device, dtype), r[None].to(device, dtype), tex.to(device, dtype), vp.to(device, dtype), 5, "newton"
    )
    assert d.dtype == dtype and d.device.type == device.type and valid.device.type == device.type
    err = _err_texels(cam, o, r, d[0].cpu(), _plane_hit(o, r))[valid[0].cpu()]
    assert valid.float().mean() > 0.9 and float(err.max()) < 0.05
    # mixed dtypes promote; float16 is computed in float32 and returned as float16
    d2, _ = newton_raphson_intersect(o[None].float(), r[None].float(), tex, vp.float(), 2)
    assert d2.dtype == F64
    d3, v3 = newton_raphson_intersect(o[None].half(), r[None].half(), tex.half(), vp.half(), 5, "newton")
    assert d3.dtype == torch.float16 and v3.float().mean() > 0.9


# -- gradients ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["shah", "newton"])
def test_gradcheck(method, water_scene):
    cam, tex, o, r, _ = water_scene
    vp = cam.view_proj(dtype=F64)[None]
    o_g, r_g = o[None, :4].clone().requires_grad_(), r[None, :4].clone().requires_grad_()
    fn = lambda a, b: newton_raphson_intersect(a, b, tex, vp, 3, method)[0]  # noqa: E731
    assert bool(newton_raphson_intersect(o_g, r_g, tex, vp, 3, method)[1].all())
    assert torch.autograd.gradcheck(fn, (o_g, r_g), eps=1e-7, atol=1e-6)
    # and with respect to the texture (a small crop of it, to keep the Jacobian small)
    tex_g = tex.clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: newton_raphson_intersect(o_g.detach()[:, :2], r_g.detach()[:, :2], t, vp, 2, method)[0],
        (tex_g,),
        eps=1e-7,
        atol=1e-6,
        fast_mode=True,
    )


def test_gradient_matches_the_exact_intersection():
    # plane z = 0: d = -o_z |r| / r_z; the converged Newton distance carries the same derivatives
    cam = _light(ortho=True)
    tex = _plane_texture(cam)
    o, r = _rays_near_light(cam, 8, 40.0, seed=10, spread=10.0)
    r = r * 1.7
    o_g, r_g = o.clone().requires_grad_(), r.clone().requires_grad_()
    d, valid = newton_raphson_intersect(o_g[None], r_g[None], tex, cam.view_proj(dtype=F64), 3, "newton")
    assert valid.all()
    g_o, g_r = torch.autograd.grad(d.sum(), (o_g, r_g))
    o_e, r_e = o.clone().requires_grad_(), r.clone().requires_grad_()
    exact = -o_e[:, 2] * torch.linalg.vector_norm(r_e, dim=1) / r_e[:, 2]
    e_o, e_r = torch.autograd.grad(exact.sum(), (o_e, r_e))
    torch.testing.assert_close(g_o, e_o, rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(g_r, e_r, rtol=1e-6, atol=1e-8)


# -- errors ---------------------------------------------------------------------------------------------------------
def test_bad_inputs():
    o, r = torch.rand(2, 5, 3), torch.rand(2, 5, 3)
    tex, vp = torch.rand(2, 3, 8, 6), torch.eye(4).expand(2, 4, 4)
    nri = newton_raphson_intersect
    with pytest.raises(TypeError, match=r"origins: expected a torch.Tensor, got ndarray"):
        nri(np.zeros((2, 5, 3)), r, tex, vp)
    with pytest.raises(TypeError, match=r"directions: expected a floating-point tensor, got dtype torch.int64"):
        nri(o, torch.ones(2, 5, 3, dtype=torch.long), tex, vp)
    with pytest.raises(ValueError, match=r"origins: expected shape \(B, N, 3\), got \(2, 5, 4\)"):
        nri(torch.rand(2, 5, 4), r, tex, vp)
    with pytest.raises(ValueError, match=r"directions: expected shape \(B, N, 3\) with N=5, got \(2, 6, 3\)"):
        nri(o, torch.rand(2, 6, 3), tex, vp)
    with pytest.raises(ValueError, match=r"positions_texture: expected shape \(B, 3, H, W\), got \(2, 4, 8, 6\)"):
        nri(o, r, torch.rand(2, 4, 8, 6), vp)
    with pytest.raises(ValueError, match=r"positions_texture: expected shape \(B, 3, H, W\) with B=2, got \(1, 3"):
        nri(o, r, tex[:1], vp)
    with pytest.raises(ValueError, match=r"positions_texture: expected shape \(B, 3, H, W\) \(4 dims\), got \(3, 8"):
        nri(o, r, tex[0], vp)
    with pytest.raises(ValueError, match=r"view_proj: expected shape \(B, 4, 4\) with B=2, got \(3, 4, 4\)"):
        nri(o, r, tex, torch.eye(4).expand(3, 4, 4))
    with pytest.raises(ValueError, match=r"view_proj: expected shape \(4, 4\), got \(3, 4\)"):
        nri(o, r, tex, torch.rand(3, 4))
    with pytest.raises(TypeError, match=r"view_proj: expected a torch.Tensor, got list"):
        nri(o, r, tex, [[1.0]])
    with pytest.raises(ValueError, match=r"view_proj: expected finite values, got a non-finite entry"):
        nri(o, r, tex, torch.full((4, 4), float("nan")))
    with pytest.raises(ValueError, match=r"method: expected one of \('shah', 'newton'\), got 'secant'"):
        nri(o, r, tex, vp, 5, "secant")
    with pytest.raises(ValueError, match=r"iterations: expected an int >= 0, got -1"):
        nri(o, r, tex, vp, -1)
    for bad in (2.5, True, "5"):
        with pytest.raises(TypeError, match=r"iterations: expected an int >= 0, got"):
            nri(o, r, tex, vp, bad)
    with pytest.raises(TypeError, match=r"fallback: expected a bool, got int"):
        nri(o, r, tex, vp, fallback=1)
    with pytest.raises(TypeError, match=r"return_info: expected a bool, got str"):
        nri(o, r, tex, vp, return_info="yes")
    with pytest.raises(ValueError, match=r"fd_step: expected a finite number > 0, got 0"):
        nri(o, r, tex, vp, method="newton", fd_step=0)
    with pytest.raises(ValueError, match=r"tol: expected a finite number >= 0, got -1.0"):
        nri(o, r, tex, vp, tol=-1.0)
    with pytest.raises(ValueError, match=r"max_residual: expected a finite number >= 0, got nan"):
        nri(o, r, tex, vp, max_residual=float("nan"))
    with pytest.raises(TypeError, match=r"tol: expected a real number >= 0, got str"):
        nri(o, r, tex, vp, tol="1e-5")
    with pytest.raises(ValueError, match=r"initial_distance: expected shape \(B, N\) with N=5, got \(2, 4\)"):
        nri(o, r, tex, vp, initial_distance=torch.rand(2, 4))
    with pytest.raises(ValueError, match=r"initial_distance: expected a finite number, got inf"):
        nri(o, r, tex, vp, initial_distance=float("inf"))
    with pytest.raises(TypeError, match=r"initial_distance: expected None, a number or a \(B, N\) tensor, got list"):
        nri(o, r, tex, vp, initial_distance=[1.0])
    with pytest.raises(TypeError, match=r"points: expected a floating-point tensor"):
        lookup_positions(torch.ones(2, 5, 3, dtype=torch.int32), tex, vp)
    with pytest.raises(ValueError, match=r"points: expected shape \(B, N, 3\) \(3 dims\), got \(5, 3\)"):
        lookup_positions(o[0], tex, vp)
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"origins: expected a tensor on positions_texture's device"):
            nri(o.cuda(), r, tex, vp)


# -- ONNX -----------------------------------------------------------------------------------------------------------
class _Intersect(torch.nn.Module):
    """Test-only wrapper: ops/ stays free of nn.Modules."""

    def forward(self, origins, directions, positions, view_proj):
        # Newton with the fallback: its graph holds every branch (Newton step, Shah's update, bisection); two
        # iterations are unrolled (four or more are one ONNX Loop body: tests/test_search_module.py).
        d, valid, info = newton_raphson_intersect(
            origins, directions, positions, view_proj, 2, "newton", return_info=True
        )
        return d, valid, info["residual"], info["oscillated"]


def _onnx_case(b, n, h, w, seed):
    cams = [
        Camera(
            eye=(5.0 * i, -3.0 * i, 100.0 - 7 * i),
            target=(0.0, 0.0, 0.0),
            fov_deg=40.0,
            width=w,
            height=h,
            near=1.0,
            far=500.0,
        )
        for i in range(b)
    ]
    tex = torch.cat([_plane_texture(c, z0=-2.0 * i) for i, c in enumerate(cams)])
    tex[:, :, h // 3 : h // 2, w // 4 : w // 2] = float("nan")  # empty texels
    vp = torch.stack([c.view_proj(dtype=F64) for c in cams])
    os, rs = [], []
    for i, c in enumerate(cams):
        o, r = _rays_near_light(c, 3 * n, 25.0, seed=seed + i)
        os.append(o[:n])
        rs.append(r[:n])
    o, r = torch.stack(os), torch.stack(rs)
    o[:, 0] = torch.tensor([0.0, 0.0, 150.0], dtype=F64)  # behind the light: invalid
    r[:, 1] = -r[:, 1]  # pointing away: invalid
    return tuple(x.float() for x in (o, r, tex, vp))


# the same graph (NewtonRaphsonSearch(2, "newton", return_info=True) wraps this call with these arguments, the same
# dynamic dims and test size) is exported in the default run by tests/test_search_module.py's
# test_onnx_export_dynamic_sizes, which also compares with float64; this twin runs with -m slow
@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning")
@pytest.mark.filterwarnings("ignore:# The axis name:UserWarning")
def test_onnx_export_dynamic_size(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    from torch.export import Dim

    from torchsss.export import compare_with_eager, export_onnx, run_onnxruntime

    bd, nd, hd, wd = Dim("B", min=1, max=64), Dim("N"), Dim("H"), Dim("W")
    dyn = ({0: bd, 1: nd}, {0: bd, 1: nd}, {0: bd, 2: hd, 3: wd}, {0: bd})
    module = _Intersect()
    path = export_onnx(module, _onnx_case(2, 40, 24, 20, seed=20), tmp_path / "nr.onnx", dynamic_shapes=dyn)
    test = _onnx_case(3, 57, 37, 29, seed=30)  # a different batch, ray count and texture size
    res = compare_with_eager(module, path, test)
    assert res["shapes"] == [(3, 57), (3, 57), (3, 57), (3, 57)]
    assert res["nonfinite_match"] and res["zero_pattern_match"], res
    d, valid, residual, osc = run_onnxruntime(path, test)
    with torch.no_grad():
        d_e, valid_e, res_e, osc_e = module(*test)
        d_64 = module(*(x.double() for x in test))[0].numpy()
    assert np.array_equal(valid, valid_e.numpy()) and np.array_equal(osc, osc_e.numpy())
    assert not valid[:, :2].any() and valid.mean() > 0.5
    assert np.isfinite(d).all() and np.isfinite(residual).all()
    # float32 in both runtimes: the finite-difference slope and the bilinear weights round differently, so compare
    # both with the float64 result (a few 1e-5 relative at ~50 mm)
    assert np.abs(d - d_e.numpy()).max() <= 2e-3, res
    assert np.abs(d - d_64).max() <= 2e-3 and np.abs(d_e.numpy() - d_64).max() <= 2e-3
    np.testing.assert_allclose(residual, res_e.numpy(), rtol=0, atol=2e-3)
