"""splat_radiosity (Shah 6.4 image-space splatting): window, tile and gather paths vs the all-pairs reference,
gradients, extremes, typed errors, ONNX export of the window path."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

import torchsss.ops.splat as splat_mod
from torchsss import DipoleMaterial
from torchsss.geometry.camera import Camera, transform_points
from torchsss.ops.reference import reference_radiosity
from torchsss.ops.splat import splat_radiosity, splat_window_size
from torchsss.physics import dipole_rd, preset

METHODS = ["window", "tile", "gather"]
F64 = torch.float64


# -- scenes: analytic G-buffers (ray casting through the pixel centres of a torchsss Camera) --------------------------
def _camera(h, w, eye=(0.0, 0.0, 40.0), target=(0.0, 0.0, 0.0), fov=30.0, **kw):
    return Camera(eye=eye, target=target, width=w, height=h, fov_deg=fov, near=1.0, far=500.0, **kw)


def _plane_gbuffer(cam, normal, half_size, dtype=F64):
    """Square of side 2*half_size through the origin with unit ``normal``; (1, 3, H, W) positions, (1, 1, H, W) mask."""
    o, d = cam.rays(dtype=dtype)
    n = torch.tensor(normal, dtype=dtype).view(1, 3, 1, 1)
    n = n / n.norm()
    t = -(o * n).sum(1, keepdim=True) / (d * n).sum(1, keepdim=True)
    pos = o + t * d
    u = torch.linalg.cross(n.flatten(), torch.tensor([0.0, 1.0, 0.1], dtype=dtype))
    u = (u / u.norm()).view(1, 3, 1, 1)
    v = torch.linalg.cross(n, u, dim=1)
    mask = (
        (t > 0)
        & ((pos * u).sum(1, keepdim=True).abs() <= half_size)
        & ((pos * v).sum(1, keepdim=True).abs() <= half_size)
    )
    return torch.where(mask, pos, torch.zeros_like(pos)), mask, (n.flatten(), u.flatten(), v.flatten())


def _sphere_gbuffer(cam, centre, radius, dtype=F64):
    o, d = cam.rays(dtype=dtype)
    c = torch.tensor(centre, dtype=dtype).view(1, 3, 1, 1)
    oc = o - c
    b = (oc * d).sum(1, keepdim=True)
    disc = b * b - ((oc * oc).sum(1, keepdim=True) - radius * radius)
    mask = disc >= 0
    t = -b - torch.sqrt(disc.clamp_min(0.0))
    pos = o + t * d
    return torch.where(mask, pos, torch.zeros_like(pos)), mask


def _sphere_points(n, centre, radius, gen, dtype=F64):
    v = torch.randn(n, 3, generator=gen, dtype=F64)
    v = v / v.norm(dim=-1, keepdim=True)
    return (v * radius + torch.tensor(centre, dtype=F64)).to(dtype)


def _table_profiles(sa, ss, eta):
    """The material table (M, C) / (C,) coefficients as the op's list of profile callables (one per row)."""
    sa2, ss2 = sa.reshape(-1, sa.shape[-1]), ss.reshape(-1, ss.shape[-1])
    m = sa2.shape[0]
    et = torch.as_tensor(eta, dtype=sa2.dtype).reshape(-1).expand(m)
    return [functools.partial(dipole_rd, sigma_a=sa2[k], sigma_s_prime=ss2[k], eta=et[k]) for k in range(m)]


def _dipole_profiles(sa, ss, eta):
    """The material table as plain-dipole modules (the gather form's fused pair sum needs them), frozen."""
    sa2, ss2 = sa.reshape(-1, sa.shape[-1]), ss.reshape(-1, ss.shape[-1])
    m = sa2.shape[0]
    et = torch.as_tensor(eta, dtype=sa2.dtype).reshape(-1).expand(m)
    return [DipoleMaterial(sa2[k], ss2[k], et[k], dtype=sa2.dtype).requires_grad_(False) for k in range(m)]


def _op(src_pos, flux, dst, mask, vp, sa, ss, eta, rmax, **kw):
    """splat_radiosity with the material given as coefficient tables (dipole profiles; modules for the gather)."""
    make = _dipole_profiles if kw.get("method") == "gather" else _table_profiles
    return splat_radiosity(src_pos, flux, dst, mask, vp, make(sa, ss, eta), rmax, **kw)


def _materials(names, dtype=F64):
    rows = [preset(nm).tensors(dtype) for nm in names]
    return (torch.stack([r[0] for r in rows]), torch.stack([r[1] for r in rows]), torch.stack([r[2] for r in rows]))


# -- the brute-force reference: reference_radiosity (all pairs) with a truncating profile, one material at a time ----
def _reference(
    src_pos,
    flux,
    dst_pos,
    mask,
    sa,
    ss,
    eta,
    rmax,
    *,
    material=None,
    src_object=None,
    dst_object=None,
    md=None,
    mi=None,
):
    b, _, h, w = dst_pos.shape
    sa, ss = sa.reshape(-1, sa.shape[-1]), ss.reshape(-1, ss.shape[-1])
    m = sa.shape[0]
    eta = torch.as_tensor(eta, dtype=sa.dtype).reshape(-1).expand(m)
    rmax = torch.as_tensor(rmax, dtype=sa.dtype).reshape(-1).expand(m)
    dst = torch.where(mask, dst_pos, torch.zeros_like(dst_pos)).flatten(2).transpose(1, 2)
    ids = {}
    if src_object is not None:
        ids = {"src_ids": src_object, "dst_ids": dst_object.flatten(1)}
    total = 0.0
    for k in range(m):
        sel = torch.ones_like(flux[..., :1]) if material is None else (material == k).unsqueeze(-1).to(flux.dtype)

        def prof(r, k=k):
            return dipole_rd(r, sa[k], ss[k], eta[k]) * (r <= rmax[k]).to(r.dtype)

        total = total + reference_radiosity(
            src_pos,
            flux * sel,
            torch.ones_like(flux[..., 0]),
            dst,
            prof,
            src_distance_scale=md,
            src_irradiance_scale=mi,
            **ids,
        )
    total = total * mask.flatten(2).transpose(1, 2).to(total.dtype)
    return total.transpose(1, 2).reshape(b, -1, h, w)


def _plane_scene(dtype=F64, s=60, seed=0, h=20, w=24):
    """B = 2: a plane facing the camera, and a plane tilted by 70 degrees seen by another (perspective) camera."""
    gen = torch.Generator().manual_seed(seed)
    cams = [_camera(h, w), _camera(h, w, eye=(6.0, -4.0, 25.0), fov=40.0)]
    bufs = [
        _plane_gbuffer(cams[0], (0.0, 0.0, 1.0), 8.0, dtype),
        _plane_gbuffer(cams[1], (math.sin(1.22), 0.0, math.cos(1.22)), 8.0, dtype),
    ]
    src = []
    for _, _, (_, u, v) in bufs:
        a = torch.rand(s, 2, generator=gen, dtype=F64) * 18.0 - 9.0  # some sources beyond the square's edge
        src.append((a[:, :1] * u + a[:, 1:] * v).to(dtype))
    src_pos = torch.stack(src)
    flux = torch.rand(2, s, 3, generator=gen, dtype=F64).to(dtype)
    dst = torch.cat([bb[0] for bb in bufs])
    mask = torch.cat([bb[1] for bb in bufs])
    vp = torch.stack([c.view_proj(dtype=dtype) for c in cams])
    return src_pos, flux, dst, mask, vp


# -- correctness against the reference -------------------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
def test_planes_match_reference(method):
    src_pos, flux, dst, mask, vp = _plane_scene()
    sa, ss, eta = preset("skin1").tensors(F64)
    for rmax in (1.5, 4.0):
        out = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, rmax, method=method)
        want = _reference(src_pos, flux, dst, mask, sa, ss, eta, rmax)
        assert out.shape == (2, 3, 20, 24) and out.dtype == F64
        assert float(want.amax()) > 0 and int((want > 0).sum()) > 100  # the scene is not trivially empty
        torch.testing.assert_close(out, want, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("method", METHODS)
def test_sphere_two_materials_and_modifiers_match_reference(method):
    gen = torch.Generator().manual_seed(1)
    cam = _camera(22, 22, eye=(10.0, 8.0, 30.0), fov=35.0)
    dst, mask = _sphere_gbuffer(cam, (0.0, 0.0, 0.0), 6.0)
    s = 150
    src_pos = _sphere_points(s, (0.0, 0.0, 0.0), 6.0, gen).unsqueeze(0)  # the whole sphere, back side included
    flux = torch.rand(1, s, 3, generator=gen, dtype=F64)
    material = torch.randint(0, 2, (1, s), generator=gen)
    sa, ss, eta = _materials(["skin1", "marble"])
    eta = torch.tensor([1.3, 1.45], dtype=F64)
    rmax = torch.tensor([2.5, 4.0], dtype=F64)
    md = 0.6 + torch.rand(1, s, 3, generator=gen, dtype=F64)  # per channel: truncation differs per channel
    mi = torch.rand(1, s, 1, generator=gen, dtype=F64)
    out = _op(
        src_pos,
        flux,
        dst,
        mask,
        cam.view_proj(dtype=F64),
        sa,
        ss,
        eta,
        rmax,
        src_material=material,
        src_distance_scale=md,
        src_irradiance_scale=mi,
        method=method,
    )
    want = _reference(src_pos, flux, dst, mask, sa, ss, eta, rmax, material=material, md=md, mi=mi)
    assert int((want > 0).sum()) > 300
    torch.testing.assert_close(out, want, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("method", METHODS)
def test_two_touching_objects_no_crosstalk(method):
    gen = torch.Generator().manual_seed(2)
    cam = _camera(16, 28, eye=(0.0, 0.0, 45.0), fov=30.0)
    d0, m0 = _sphere_gbuffer(cam, (-5.0, 0.0, 0.0), 5.0)
    d1, m1 = _sphere_gbuffer(cam, (5.0, 0.0, 0.0), 5.0)
    z0 = torch.where(m0, d0[:, 2:], torch.full_like(d0[:, 2:], -1e9))
    z1 = torch.where(m1, d1[:, 2:], torch.full_like(d1[:, 2:], -1e9))
    first = z0 >= z1  # the nearer surface wins (z towards the camera)
    dst = torch.where(first, d0, d1)
    mask = m0 | m1
    dst_obj = torch.where(first, 0, 1).to(torch.int64) * mask
    s = 80
    src_pos = torch.cat(
        [_sphere_points(s, (-5.0, 0.0, 0.0), 5.0, gen), _sphere_points(s, (5.0, 0.0, 0.0), 5.0, gen)]
    ).unsqueeze(0)
    obj = torch.cat([torch.zeros(s, dtype=torch.int64), torch.ones(s, dtype=torch.int64)]).unsqueeze(0)
    flux = torch.rand(1, 2 * s, 3, generator=gen, dtype=F64)
    sa, ss, _ = _materials(["ketchup", "marble"])
    rmax = torch.tensor([6.0, 6.0], dtype=F64)
    vp = cam.view_proj(dtype=F64)
    kw = dict(src_material=obj, method=method)
    out = _op(src_pos, flux, dst, mask, vp, sa, ss, 1.3, rmax, src_object=obj, dst_object=dst_obj, **kw)
    want = _reference(src_pos, flux, dst, mask, sa, ss, 1.3, rmax, material=obj, src_object=obj, dst_object=dst_obj)
    torch.testing.assert_close(out, want, rtol=1e-10, atol=1e-14)
    # each object's pixels see exactly its own sources: splatting one object alone gives the same pixels
    for k in (0, 1):
        sel = obj[0] == k
        alone = _op(
            src_pos[:, sel], flux[:, sel], dst, mask, vp, sa, ss, 1.3, rmax, src_material=obj[:, sel], method=method
        )
        px = (dst_obj == k) & mask
        torch.testing.assert_close(out * px, alone * px, rtol=1e-12, atol=1e-15)
    # without the ids the neighbour's light leaks in (so the check above is not vacuous)
    leak = _op(src_pos, flux, dst, mask, vp, sa, ss, 1.3, rmax, **kw)
    assert float((leak - out).amax()) > 1e-3 * float(out.amax())


def test_window_covers_the_near_side_of_the_ball():
    # a plane at grazing incidence close to the camera: the footprint's near side projects much larger than
    # r_max * focal / depth; the automatic window must still catch every pixel within r_max
    cam = _camera(24, 24, eye=(0.0, -14.0, 6.0), target=(0.0, 0.0, 0.0), fov=60.0)
    dst, mask, (_, u, v) = _plane_gbuffer(cam, (0.0, 0.0, 1.0), 30.0)
    gen = torch.Generator().manual_seed(3)
    a = torch.rand(40, 2, generator=gen, dtype=F64) * 20.0 - 10.0
    src_pos = (a[:, :1] * u + a[:, 1:] * v).unsqueeze(0)
    flux = torch.rand(1, 40, 3, generator=gen, dtype=F64)
    sa, ss, eta = preset("skin1").tensors(F64)
    vp = cam.view_proj(dtype=F64)
    want = _reference(src_pos, flux, dst, mask, sa, ss, eta, 3.0)
    out = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method="window")
    torch.testing.assert_close(out, want, rtol=1e-10, atol=1e-14)
    # the naive window (projected radius at the centre's depth) is too small here: it misses light
    clip = transform_points(src_pos, vp)
    naive = 3.0 * vp[1, 1] / clip[..., 3] * 12.0  # r_max * focal / depth, in pixels
    k_naive = 2 * math.ceil(float(naive.max())) + 1
    k_auto = splat_window_size(src_pos, vp, 3.0, 24, 24)
    assert k_naive < k_auto
    short = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method="window", window=k_naive)
    assert bool((short <= want + 1e-15).all()) and float((want - short).amax()) > 1e-3 * float(want.amax())
    big = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method="window", window=k_auto)
    torch.testing.assert_close(big, want, rtol=1e-10, atol=1e-14)


def test_window_of_one_pixel_closed_form():
    # window=1: each splat lights only the pixel its centre projects into, with R_d(|x_o - x_i|) E dA
    src_pos, flux, dst, mask, vp = _plane_scene(s=25)
    sa, ss, eta = preset("marble").tensors(F64)
    out = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 50.0, method="window", window=1)
    want = torch.zeros_like(out)
    clip = transform_points(src_pos, vp)
    for bb in range(2):
        for i in range(25):
            x, y, _, ww = clip[bb, i].tolist()
            col, row = round((x / ww + 1) * 12 - 0.5), round((1 - y / ww) * 10 - 0.5)
            col, row = min(max(col, 0), 23), min(max(row, 0), 19)
            if mask[bb, 0, row, col]:
                r = (dst[bb, :, row, col] - src_pos[bb, i]).norm()
                want[bb, :, row, col] += dipole_rd(r.view(1), sa, ss, eta) * flux[bb, i]
    assert int((want > 0).sum()) > 10
    torch.testing.assert_close(out, want, rtol=1e-12, atol=0.0)


def test_splat_window_size_bounds_projected_balls():
    # brute force: project points all over each ball's surface; every projection lies within K // 2 pixels
    gen = torch.Generator().manual_seed(4)
    cam = _camera(30, 40, eye=(3.0, 2.0, 20.0), fov=50.0)
    vp = cam.view_proj(dtype=F64)
    centres = (torch.rand(1, 12, 3, generator=gen, dtype=F64) - 0.5) * torch.tensor([16.0, 12.0, 10.0], dtype=F64)
    radius = 0.5 + 3.0 * torch.rand(1, 12, generator=gen, dtype=F64)
    k = splat_window_size(centres, vp, radius, 30, 40)
    assert k % 2 == 1 and 1 < k < 40
    dirs = torch.randn(4000, 3, generator=gen, dtype=F64)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    pts = centres[0, :, None] + radius[0, :, None, None] * dirs  # (12, 4000, 3)

    def pix(p):
        c = transform_points(p.reshape(1, -1, 3), vp)[0]
        return torch.stack([(c[:, 0] / c[:, 3] + 1) * 20 - 0.5, (1 - c[:, 1] / c[:, 3]) * 15 - 0.5], -1)

    centre_px = torch.round(pix(centres[0])).reshape(12, 1, 2)
    spread = (pix(pts).reshape(12, 4000, 2) - centre_px).abs().amax()
    assert float(spread) <= k // 2
    # orthographic closed form: radius 0.25 NDC = 2 px of a 16 px image, +1 px slack, K = 2 * 3 + 1
    assert splat_window_size(torch.zeros(1, 1, 3), torch.eye(4), 0.25, 16, 16) == 7
    # a ball entirely behind the camera is ignored; one that reaches the camera plane needs the whole image
    behind = torch.tensor([[[0.0, 0.0, 60.0]]], dtype=F64)
    assert splat_window_size(behind, vp, 1.0, 30, 40) == 1
    assert splat_window_size(torch.tensor([[[0.0, 0.0, 19.0]]], dtype=F64), vp, 2.0, 30, 40) == 41


# -- extremes ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
def test_empty_sources_and_zero_flux_give_zeros(method):
    src_pos, flux, dst, mask, vp = _plane_scene(s=10)
    sa, ss, eta = preset("skin1").tensors(F64)
    out = _op(src_pos[:, :0], flux[:, :0], dst, mask, vp, sa, ss, eta, 3.0, method=method)
    assert out.shape == (2, 3, 20, 24) and torch.equal(out, torch.zeros_like(out))
    out = _op(src_pos, torch.zeros_like(flux), dst, mask, vp, sa, ss, eta, 3.0, method=method)
    assert torch.equal(out, torch.zeros_like(out))
    out = _op(src_pos, flux, dst, torch.zeros_like(mask), vp, sa, ss, eta, 3.0, method=method)
    assert torch.equal(out, torch.zeros_like(out))
    # zero flux that requires a gradient is kept (its gradient is not zero)
    f0 = torch.zeros_like(flux).requires_grad_()
    _op(src_pos, f0, dst, mask, vp, sa, ss, eta, 3.0, method=method).sum().backward()
    assert float(f0.grad.abs().sum()) > 0


@pytest.mark.parametrize("method", METHODS)
def test_offscreen_and_behind_camera_splats_contribute_nothing(method):
    src_pos, flux, dst, mask, vp = _plane_scene(s=30)
    sa, ss, eta = preset("skin1").tensors(F64)
    far = torch.tensor([[[500.0, 0.0, 0.0], [0.0, -300.0, 0.0], [0.0, 0.0, 60.0], [0.0, 0.0, 40.0]]], dtype=F64)
    far = far.expand(2, -1, -1)  # off to the side, below, behind the camera, at the eye itself
    more_pos = torch.cat([src_pos, far], 1)
    more_flux = torch.cat([flux, torch.ones(2, 4, 3, dtype=F64)], 1)
    base = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method=method)
    out = _op(more_pos, more_flux, dst, mask, vp, sa, ss, eta, 3.0, method=method)
    # the gather sums every pair (zeros beyond reach): another summation order, not another value
    torch.testing.assert_close(out, base, rtol=1e-14 if method == "gather" else 0, atol=0)
    only_far = _op(far, torch.ones(2, 4, 3, dtype=F64), dst, mask, vp, sa, ss, eta, 3.0, method=method)
    assert torch.equal(only_far, torch.zeros_like(only_far))


@pytest.mark.parametrize("method", METHODS)
def test_footprint_covering_the_whole_image(method):
    # r_max far larger than the scene: every splat reaches every pixel (the window is the whole image)
    src_pos, flux, dst, mask, vp = _plane_scene(s=15)
    sa, ss, eta = preset("marble").tensors(F64)
    out = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 1000.0, method=method)
    want = _reference(src_pos, flux, dst, mask, sa, ss, eta, 1000.0)
    assert bool((want[mask.expand_as(want)] > 0).all())
    torch.testing.assert_close(out, want, rtol=1e-10, atol=1e-14)
    # the source close to the camera makes the window the whole image
    near = torch.cat([src_pos, torch.tensor([0.0, 0.0, 39.0], dtype=F64).expand(2, 1, 3)], 1)
    fl = torch.cat([flux, torch.ones(2, 1, 3, dtype=F64)], 1)
    assert splat_window_size(near, vp, 2.0, 20, 24) == 25
    torch.testing.assert_close(
        _op(near, fl, dst, mask, vp, sa, ss, eta, 2.0, method=method),
        _reference(near, fl, dst, mask, sa, ss, eta, 2.0),
        rtol=1e-10,
        atol=1e-14,
    )


@pytest.mark.parametrize("method", METHODS)
def test_nonfinite_positions_outside_the_mask_do_not_leak(method):
    src_pos, flux, dst, mask, vp = _plane_scene(s=20)
    sa, ss, eta = preset("skin1").tensors(F64)
    bad = dst.clone()
    bad[:, 0][~mask[:, 0]] = float("nan")
    bad[:, 2][~mask[:, 0]] = float("inf")
    assert not bool(torch.isfinite(bad).all())
    f = flux.clone().requires_grad_()
    sa_g = sa.clone().requires_grad_()
    out = _op(src_pos, f, bad, mask, vp, sa_g, ss, eta, 4.0, method=method)
    torch.testing.assert_close(
        out, _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 4.0, method=method), rtol=0, atol=0
    )
    out.sum().backward()
    assert bool(torch.isfinite(f.grad).all())
    if method != "gather":  # (the gather's profiles are modules built from sa's values: no gradient reaches sa_g)
        assert bool(torch.isfinite(sa_g.grad).all())


@pytest.mark.parametrize("method", METHODS)
def test_tiny_images_and_chunking(method, monkeypatch):
    sa, ss, eta = preset("skin1").tensors(F64)
    # 1 x 1 image, a source exactly at the pixel's point (r = 0)
    cam = _camera(1, 1)
    dst, mask, _ = _plane_gbuffer(cam, (0.0, 0.0, 1.0), 5.0)
    src = dst[:, :, 0, 0].reshape(1, 1, 3)
    out = _op(
        src, torch.ones(1, 1, 3, dtype=F64), dst, mask, cam.view_proj(dtype=F64), sa, ss, eta, 1.0, method=method
    )
    torch.testing.assert_close(out.reshape(3), dipole_rd(torch.zeros(1, dtype=F64), sa, ss, eta), rtol=1e-14, atol=0)
    # tiny chunks (one splat / tile / pair at a time) and odd tile sizes give the same image
    src_pos, flux, dst, mask, vp = _plane_scene(s=12, h=10, w=12)
    want = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method=method)
    assert int((want > 0).sum()) > 20
    monkeypatch.setattr(splat_mod, "_EVAL_PAIRS", 7)
    monkeypatch.setattr(splat_mod, "_MAX_CHUNK_TAPS", 5)
    for tile_size in (1, 5, 32):
        got = _op(
            src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method=method, tile_size=tile_size, max_memory_mb=1e-3
        )
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-16)


def test_auto_picks_the_scatter_form_when_splats_outnumber_pixels():
    src_pos, flux, dst, mask, vp = _plane_scene(s=400, h=6, w=7)
    sa, ss, eta = preset("skin2").tensors(F64)
    assert int(mask.sum()) < 400
    auto = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0)
    window = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method="window")
    torch.testing.assert_close(auto, window, rtol=0, atol=0)
    assert float(window.amax()) > 0


def test_batch_elements_are_independent_and_methods_agree():
    src_pos, flux, dst, mask, vp = _plane_scene(s=40)
    sa, ss, eta = preset("skin2").tensors(F64)
    full = {m: _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method=m) for m in [*METHODS, "auto"]}
    for bb in range(2):
        one = _op(
            src_pos[bb : bb + 1],
            flux[bb : bb + 1],
            dst[bb : bb + 1],
            mask[bb : bb + 1],
            vp[bb],
            sa,
            ss,
            eta,
            3.0,
            method="window",
        )
        torch.testing.assert_close(full["window"][bb : bb + 1], one, rtol=1e-12, atol=1e-16)
    torch.testing.assert_close(full["tile"], full["window"], rtol=1e-12, atol=1e-16)
    # auto: 40 splats per element, fewer than the covered pixels -> the gather form, bit for bit
    assert int(mask[0].sum()) > 40
    torch.testing.assert_close(full["auto"], full["tile"], rtol=0, atol=0)


def test_device_dtype(device, dtype):
    src_pos, flux, dst, mask, vp = _plane_scene(s=30)
    sa, ss, eta = preset("skin1").tensors(F64)
    want = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0)
    args = [t.to(device=device, dtype=dtype) for t in (src_pos, flux, dst)]
    for method in METHODS:
        out = _op(
            *args,
            mask.to(device),
            vp.to(device=device, dtype=dtype),
            sa.to(device, dtype),
            ss.to(device, dtype),
            eta.to(device, dtype),
            3.0,
            method=method,
        )
        assert out.dtype == dtype and out.device.type == device.type and out.shape == want.shape
        tol = 1e-10 if dtype == F64 else 2e-5
        torch.testing.assert_close(out.cpu().double(), want, rtol=tol, atol=tol * float(want.amax()))


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
def test_reduced_precision_computed_in_float32(low):
    src_pos, flux, dst, mask, vp = _plane_scene(s=20, dtype=torch.float32)
    sa, ss, _ = preset("skin1").tensors(torch.float32)
    out = _op(src_pos.to(low), flux.to(low), dst.to(low), mask, vp, sa.to(low), ss.to(low), 1.3, 3.0)
    # (Python numbers such as eta = 1.3 take the material's dtype, as in dipole_rd)
    assert out.dtype == low
    eta_low = torch.tensor(1.3, dtype=low).float()
    want = _op(
        src_pos.to(low).float(),
        flux.to(low).float(),
        dst.to(low).float(),
        mask,
        vp,
        sa.to(low).float(),
        ss.to(low).float(),
        eta_low,
        3.0,
    )
    assert float(want.amax()) > 0
    torch.testing.assert_close(out, want.to(low), rtol=0, atol=0)
    # mixed: promotion to the wider input
    assert _op(src_pos.to(low), flux, dst.to(low), mask, vp, sa, ss, 1.3, 3.0).dtype == torch.float32


# -- gradients ---------------------------------------------------------------------------------------------------------
def _small_scene():
    gen = torch.Generator().manual_seed(5)
    cam = _camera(7, 6, eye=(0.0, 0.0, 20.0), fov=30.0)
    dst, mask, _ = _plane_gbuffer(cam, (0.0, 0.0, 1.0), 4.0)
    src_pos = torch.cat([torch.rand(1, 6, 2, generator=gen, dtype=F64) * 8 - 4, torch.zeros(1, 6, 1, dtype=F64)], -1)
    return gen, cam.view_proj(dtype=F64), dst, mask, src_pos


@pytest.mark.parametrize("method", METHODS)
def test_gradcheck(method):
    gen, vp, dst, mask, src_pos = _small_scene()
    flux = torch.rand(1, 6, 3, generator=gen, dtype=F64).requires_grad_()
    sa, ss, _ = _materials(["skin1", "ketchup"])
    sa, ss = sa.requires_grad_(), ss.requires_grad_()
    eta = torch.tensor([1.3, 1.4], dtype=F64, requires_grad=True)
    mi = torch.rand(1, 6, 3, generator=gen, dtype=F64).requires_grad_()
    mat = torch.tensor([[0, 1, 0, 1, 1, 0]])
    rmax = torch.tensor([2.0, 3.0], dtype=F64)

    def f(flux, sa, ss, eta, mi):
        return _op(
            src_pos, flux, dst, mask, vp, sa, ss, eta, rmax, src_material=mat, src_irradiance_scale=mi, method=method
        )

    # fast mode (random projections of the Jacobian) keeps this quick; the full gradients are compared with the
    # reference's below. The gather's profiles are modules built from the coefficients' values (their own
    # parameters: test_gather_gradients_reach_the_material_module), so there the coefficients are held fixed.
    wrt = (flux, sa, ss, eta, mi) if method != "gather" else (flux, mi)
    if method == "gather":
        def f_g(flux, mi):
            return f(flux, sa.detach(), ss.detach(), eta.detach(), mi)
        assert torch.autograd.gradcheck(f_g, wrt, fast_mode=True)
    else:
        assert torch.autograd.gradcheck(f, wrt, fast_mode=True)
    # the distance scale moves the truncation edge: check it with every pair inside r_max
    md = (0.5 + torch.rand(1, 6, 1, generator=gen, dtype=F64)).requires_grad_()

    def g(md):
        return _op(
            src_pos,
            flux.detach(),
            dst,
            mask,
            vp,
            sa.detach(),
            ss.detach(),
            1.3,
            100.0,
            src_material=mat,
            src_distance_scale=md,
            method=method,
        )

    assert torch.autograd.gradcheck(g, (md,), fast_mode=True)
    # and the gradients equal those of the all-pairs reference
    out = f(flux, sa, ss, eta, mi)
    ref = _reference(src_pos, flux, dst, mask, sa, ss, eta, rmax, material=mat, mi=mi)
    for a, b in zip(
        torch.autograd.grad(out.square().sum(), wrt),
        torch.autograd.grad(ref.square().sum(), wrt),
    ):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-14)


def test_gather_gradients_reach_the_material_module():
    """The gather form (eager while autograd records) differentiates the module's parameters as the tile form does."""
    gen, vp, dst, mask, src_pos = _small_scene()
    flux = torch.rand(1, 6, 3, generator=gen, dtype=F64)
    grads = {}
    for method in ("tile", "gather"):
        mat = DipoleMaterial.from_preset("skin1", dtype=F64)
        out = splat_radiosity(src_pos, flux, dst, mask, vp, mat, 2.5, method=method)
        out.square().sum().backward()
        grads[method] = [p.grad for p in mat.parameters()]
        assert all(g is not None and bool((g != 0).any()) for g in grads[method])
    for a, b in zip(grads["tile"], grads["gather"]):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("compiled", ["0", "1"])
def test_auto_picks_the_fused_gather_where_r_max_spans_the_pixels(monkeypatch, compiled):
    """auto: the gather where most pairs are in reach (inference, compilation allowed), else tile / window; the
    compiled gather equals the eager forms in float32."""
    monkeypatch.setenv("TORCHSSS_COMPILE", compiled)
    calls = []
    real = splat_mod._splat_gather
    monkeypatch.setattr(splat_mod, "_splat_gather", lambda *a: calls.append(1) or real(*a))
    src_pos, flux, dst, mask, vp = _plane_scene(s=40, dtype=torch.float32)
    mat = DipoleMaterial.from_preset("skin1").requires_grad_(False)
    with torch.no_grad():
        wide = splat_radiosity(src_pos, flux, dst, mask, vp, mat, 30.0)  # r_max spans the planes
        assert len(calls) == (1 if compiled == "1" else 0)  # compilation off: the per-pair paths
        narrow = splat_radiosity(src_pos, flux, dst, mask, vp, mat, 0.5)  # a few pairs in reach
        assert len(calls) == (1 if compiled == "1" else 0)
        tile = splat_radiosity(src_pos, flux, dst, mask, vp, mat, 30.0, method="tile")
        torch.testing.assert_close(wide, tile, rtol=2e-5, atol=1e-9)
        assert float(narrow.amax()) > 0
    # autograd records through the flux: the per-pair paths
    f = flux.clone().requires_grad_()
    splat_radiosity(src_pos, f, dst, mask, vp, mat, 30.0)
    assert len(calls) == (1 if compiled == "1" else 0)
    share = splat_mod._reach_share({"pos": src_pos[0], "reach": torch.full((40,), 30.0)}, dst[0].permute(1, 2, 0)
                                   .reshape(-1, 3), mask[0].reshape(-1))
    assert share == 1.0


def test_gather_needs_a_plain_dipole():
    src_pos, flux, dst, mask, vp = _plane_scene(s=4)
    sa, ss, eta = preset("skin1").tensors(F64)
    with pytest.raises(ValueError, match="plain dipole"):
        splat_radiosity(src_pos, flux, dst, mask, vp, _table_profiles(sa, ss, eta), 2.0, method="gather")


# -- typed errors ------------------------------------------------------------------------------------------------------
def test_bad_inputs():
    src_pos, flux, dst, mask, vp = _plane_scene(s=4, h=5, w=6, dtype=torch.float32)
    sa, ss, eta = preset("skin1").tensors(torch.float32)
    args = (src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0)

    def call(*a, **kw):
        a = list(a) + list(args[len(a) :])
        return _op(*a, **kw)

    with pytest.raises(TypeError, match=r"src_pos: expected a torch.Tensor, got ndarray"):
        call(np.zeros((2, 4, 3)))
    with pytest.raises(TypeError, match=r"src_flux: expected a floating-point tensor, got dtype torch.int64"):
        call(src_pos, torch.ones(2, 4, 3, dtype=torch.long))
    with pytest.raises(ValueError, match=r"src_pos: expected shape \(B, S, 3\) \(3 dims\), got \(4, 3\)"):
        call(src_pos[0])
    with pytest.raises(ValueError, match=r"src_flux: expected shape \(B, S, C\) with S=4, got \(2, 5, 3\)"):
        call(src_pos, torch.ones(2, 5, 3))
    with pytest.raises(ValueError, match=r"dst_pos: expected shape \(B, 3, H, W\), got \(2, 2, 5, 6\)"):
        call(src_pos, flux, dst[:, :2])
    with pytest.raises(TypeError, match=r"dst_mask: expected a bool tensor, got torch.float32"):
        call(src_pos, flux, dst, mask.float())
    with pytest.raises(ValueError, match=r"dst_mask: expected shape \(B, 1, H, W\) with W=6, got \(2, 1, 5, 7\)"):
        call(src_pos, flux, dst, torch.ones(2, 1, 5, 7, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"view_proj: expected shape \(4, 4\) or \(B, 4, 4\) with B=2"):
        call(src_pos, flux, dst, mask, torch.eye(3))
    with pytest.raises(ValueError, match=r"profile\[0\]: expected R_d of shape \(\.\.\., 3\) \(the channels"):
        call(src_pos, flux, dst, mask, vp, sa[:2], ss[:2])
    with pytest.raises(TypeError, match=r"profile: expected a callable from distances \(mm\) to R_d"):
        splat_radiosity(src_pos, flux, dst, mask, vp, sa, 3.0)
    with pytest.raises(TypeError, match=r"profile\[1\]: expected a callable"):
        splat_radiosity(src_pos, flux, dst, mask, vp, [_table_profiles(sa, ss, eta)[0], "marble"], 3.0)
    with pytest.raises(ValueError, match=r"r_max: expected a number or a tensor of shape \(\) or \(M,\) with M=1"):
        call(src_pos, flux, dst, mask, vp, sa, ss, eta, torch.ones(3))
    with pytest.raises(ValueError, match=r"r_max: expected finite values > 0, got -1.0"):
        call(src_pos, flux, dst, mask, vp, sa, ss, eta, -1.0)
    with pytest.raises(ValueError, match=r"sigma_a: expected finite values >= 0"):
        call(src_pos, flux, dst, mask, vp, -sa)
    two = torch.stack([sa, sa])
    with pytest.raises(
        ValueError,
        match=r"src_material: expected a \(B, S\) integer tensor with M=2 materials, "
        r"got None",
    ):
        call(src_pos, flux, dst, mask, vp, two, torch.stack([ss, ss]))
    with pytest.raises(ValueError, match=r"src_material: expected indices in \[0, 2\).*got 2"):
        call(src_pos, flux, dst, mask, vp, two, torch.stack([ss, ss]), src_material=torch.full((2, 4), 2))
    with pytest.raises(TypeError, match=r"src_material: expected an integer tensor, got torch.float32"):
        call(src_material=torch.zeros(2, 4))
    with pytest.raises(ValueError, match=r"src_object, dst_object: expected both or neither, got only src_object"):
        call(src_object=torch.zeros(2, 4, dtype=torch.long))
    with pytest.raises(TypeError, match=r"dst_object: expected an integer tensor, got torch.bool"):
        call(src_object=torch.zeros(2, 4, dtype=torch.long), dst_object=mask)
    with pytest.raises(
        ValueError,
        match=r"src_distance_scale: expected shape \(B, S, 1\) or \(B, S, 3\), "
        r"got \(2, 4, 2\)",
    ):
        call(src_distance_scale=torch.ones(2, 4, 2))
    with pytest.raises(ValueError, match=r"src_distance_scale: expected finite values > 0, got 0.0"):
        call(src_distance_scale=torch.zeros(2, 4, 1))
    with pytest.raises(ValueError, match=r"src_irradiance_scale: expected finite values >= 0"):
        call(src_irradiance_scale=-torch.ones(2, 4, 1))
    with pytest.raises(ValueError,
                       match=r"method: expected one of \('auto', 'window', 'tile', 'gather'\), got 'scatter'"):
        call(method="scatter")
    with pytest.raises(TypeError, match=r"method: expected a str, got int"):
        call(method=1)
    with pytest.raises(ValueError, match=r"window: expected an odd int >= 1, got 4"):
        call(window=4)
    with pytest.raises(TypeError, match=r"window: expected an odd int >= 1, got float"):
        call(window=3.0)
    with pytest.raises(ValueError, match=r"tile_size: expected an int >= 1, got 0"):
        call(tile_size=0)
    with pytest.raises(ValueError, match=r"max_memory_mb: expected a finite number > 0, got 0"):
        call(max_memory_mb=0)
    with pytest.raises(ValueError, match=r"src_pos: expected finite values, got nan .*the first at index"):
        call(torch.full_like(src_pos, float("nan")))
    nan_dst = dst.clone()
    nan_dst[mask.expand_as(dst)] = float("inf")
    with pytest.raises(ValueError, match=r"dst_pos: expected finite values, got"):
        call(src_pos, flux, nan_dst)
    with pytest.raises(ValueError, match=r"radius: expected finite values > 0"):
        splat_window_size(src_pos, vp, 0.0, 5, 6)
    with pytest.raises(TypeError, match=r"height: expected an int >= 1, got float"):
        splat_window_size(src_pos, vp, 1.0, 5.0, 6)


def test_tracing_needs_the_window_path_and_a_fixed_window(monkeypatch):
    src_pos, flux, dst, mask, vp = _plane_scene(s=4, h=5, w=6, dtype=torch.float32)
    sa, ss, eta = preset("skin1").tensors(torch.float32)
    monkeypatch.setattr(splat_mod, "is_exporting", lambda: True)
    with pytest.raises(ValueError, match=r"method: expected 'window' while tracing/exporting.*got 'tile'"):
        _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method="tile", window=5)
    with pytest.raises(ValueError, match=r"method: expected 'window' while tracing/exporting.*got 'gather'"):
        _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method="gather", window=5)
    with pytest.raises(ValueError, match=r"window: expected an odd int while tracing/exporting.*got None"):
        _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0)
    # the traced (dense, one chunk) formulation gives the eager numbers
    got = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, window=11)
    monkeypatch.undo()
    want = _op(src_pos, flux, dst, mask, vp, sa, ss, eta, 3.0, method="window", window=11)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-9)


# -- ONNX --------------------------------------------------------------------------------------------------------------
class _Splat(torch.nn.Module):
    """Test-only wrapper: ops/ stays free of nn.Modules. Two materials, object ids, a fixed 15 x 15 window."""

    def forward(
        self, src_pos, src_flux, src_material, src_object, dst_pos, dst_mask, dst_object, view_proj, sa, ss, eta, r_max
    ):
        return _op(
            src_pos,
            src_flux,
            dst_pos,
            dst_mask,
            view_proj,
            sa,
            ss,
            eta,
            r_max,
            src_material=src_material,
            src_object=src_object,
            dst_object=dst_object,
            method="window",
            window=15,
        )


def _onnx_inputs(s, h, w, seed):
    gen = torch.Generator().manual_seed(seed)
    cam = _camera(h, w, eye=(0.0, 0.0, 60.0), fov=30.0)
    dst, mask, _ = _plane_gbuffer(cam, (0.0, 0.0, 1.0), 10.0, torch.float32)
    dst_obj = (dst[:, :1] > 0).to(torch.int64)  # two objects: left and right half of the plane
    src = torch.cat([torch.rand(1, s, 2, generator=gen) * 22 - 11, torch.zeros(1, s, 1)], -1)
    obj = (src[..., 0] > 0).to(torch.int64)
    sa, ss, eta = _materials(["skin1", "marble"], torch.float32)
    return (
        src,
        torch.rand(1, s, 3, generator=gen),
        obj,
        obj,
        dst,
        mask,
        dst_obj,
        cam.view_proj(),
        sa,
        ss,
        eta,
        torch.tensor([3.0, 4.0]),
    )


@pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning")
@pytest.mark.filterwarnings("ignore:# The axis name:UserWarning")
def test_onnx_export_window_path_dynamic_sizes(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    from torch.export import Dim

    from torchsss.export import compare_with_eager, export_onnx, run_onnxruntime

    sd, hd, wd = Dim("S"), Dim("H"), Dim("W")
    dyn = (
        {1: sd},
        {1: sd},
        {1: sd},
        {1: sd},
        {2: hd, 3: wd},
        {2: hd, 3: wd},
        {2: hd, 3: wd},
        None,
        None,
        None,
        None,
        None,
    )
    path = export_onnx(_Splat(), _onnx_inputs(20, 16, 18, 0), tmp_path / "splat.onnx", dynamic_shapes=dyn)
    test = _onnx_inputs(37, 13, 21, 1)  # other splat count and image size than exported
    assert splat_window_size(test[0], test[7], 4.0, 13, 21) <= 15  # the window holds every footprint
    res = compare_with_eager(_Splat(), path, test)
    assert res["shapes"] == [(1, 3, 13, 21)]
    assert res["zero_pattern_match"] and res["nonfinite_match"], res
    assert res["max_rel_diff"] <= 1e-5, res
    (out,) = run_onnxruntime(path, test)
    src, flux, mat, obj, dst, mask, dst_obj, _, sa, ss, eta, rmax = (
        t.double() if t.is_floating_point() else t for t in test
    )
    want = _reference(src, flux, dst, mask, sa, ss, eta, rmax, material=mat, src_object=obj, dst_object=dst_obj)
    assert float(want.amax()) > 0
    np.testing.assert_allclose(out, want.numpy(), rtol=1e-4, atol=1e-6 * float(want.amax()))
