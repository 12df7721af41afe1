"""The hybrid's local term gathered over the surface in 3-D (issue 16: no seams): ball_pairs, SurfaceLocal, and the
hybrid renderer's ``local="surface"``."""

from __future__ import annotations

import math

import pytest
import torch

from torchsss.geometry import plane, sphere
from torchsss.geometry.neighbours import ball_pairs
from torchsss.geometry.sampling import surface_samples
from torchsss.modules import DipoleMaterial, SurfaceLocal
from torchsss.modules.chang import ChangLocalProfile
from torchsss.physics import chang_rp
from torchsss.scene import Material

F64 = torch.float64


def test_ball_pairs_against_a_loop():
    gen = torch.Generator().manual_seed(0)
    rec = torch.rand(40, 3, generator=gen, dtype=F64) * 10.0
    src = torch.rand(70, 3, generator=gen, dtype=F64) * 10.0
    rows, cols, dist = ball_pairs(rec, src, 2.5)
    want = {(i, j): float((rec[i] - src[j]).norm()) for i in range(40) for j in range(70)
            if float((rec[i] - src[j]).norm()) <= 2.5}
    got = {(int(i), int(j)): float(d) for i, j, d in zip(rows, cols, dist)}
    assert got.keys() == want.keys() and len(got) > 50
    assert max(abs(got[k] - want[k]) for k in got) < 1e-12
    assert bool((rows[1:] >= rows[:-1]).all())  # sorted by receiver
    r0, _, d0 = ball_pairs(rec, src, 0.0)
    assert r0.numel() == 0 and d0.dtype == F64


@pytest.mark.parametrize("method", ["kdtree", "grid"])
def test_ball_pairs_paths_against_a_loop(method, device):
    """Both paths (and "auto" on every device) list the loop's pairs, sorted by receiver, with its distances."""
    gen = torch.Generator().manual_seed(1)
    rec = (torch.rand(60, 3, generator=gen, dtype=F64) * torch.tensor([10.0, 3.0, 0.5], dtype=F64)).to(device)
    src = (torch.rand(90, 3, generator=gen, dtype=F64) * torch.tensor([10.0, 3.0, 0.5], dtype=F64)).to(device)
    src[5] = rec[3]  # a coincident pair (distance 0) and a pair exactly at the radius
    rec[4] = torch.tensor([2.0, 1.0, 0.25], dtype=F64, device=device)  # exact in float32: distance 1.25 exactly
    src[6] = torch.tensor([3.25, 1.0, 0.25], dtype=F64, device=device)
    for meth in (method, "auto"):
        rows, cols, dist = ball_pairs(rec.float(), src.float(), 1.25, method=meth)
        assert rows.device.type == device.type and dist.dtype == torch.float32
        got = {(int(i), int(j)): float(d) for i, j, d in zip(rows.cpu(), cols.cpu(), dist.cpu())}
        want32 = {(i, j) for i in range(60) for j in range(90)
                  if float((rec[i].float().double() - src[j].float().double()).norm()) <= 1.25}
        assert got.keys() == want32 and (3, 5) in got and (4, 6) in got and len(got) > 100
        assert max(abs(got[k] - float((rec[k[0]] - src[k[1]]).norm())) for k in got) < 1e-5
        assert bool((rows[1:] >= rows[:-1]).all())
    # extremes: no receivers, no sources, radius 0, every point in one place, a radius far below the extent
    e = torch.zeros(0, 3, dtype=F64, device=device)
    assert ball_pairs(e, src, 1.0, method=method)[0].numel() == 0
    assert ball_pairs(rec, e, 1.0, method=method)[0].numel() == 0
    r0, c0, _ = ball_pairs(rec, src, 0.0, method=method)
    assert (r0.tolist(), c0.tolist()) == ([3], [5])
    same = torch.ones(4, 3, dtype=F64, device=device)
    assert ball_pairs(same, same, 0.0, method=method)[0].numel() == 16
    far = torch.tensor([[0.0, 0, 0], [1e6, 0, 0]], dtype=F64, device=device)
    rows, cols, _ = ball_pairs(far, far, 1e-3, method=method)
    assert (rows.tolist(), cols.tolist()) == ([0, 1], [0, 1])


def test_ball_pairs_grid_blocks_and_refusal(monkeypatch):
    """The grid path lists the same pairs in blocks of any size, and refuses too many pairs with a typed error."""
    import torchsss.geometry.neighbours as nb

    gen = torch.Generator().manual_seed(2)
    rec = torch.rand(300, 3, generator=gen, dtype=F64) * 6.0
    src = torch.rand(400, 3, generator=gen, dtype=F64) * 6.0
    whole = ball_pairs(rec, src, 1.5, method="grid")
    monkeypatch.setattr(nb, "GRID_BLOCK", 50)  # fewer candidates than one receiver has: a block of one receiver
    blocks = ball_pairs(rec, src, 1.5, method="grid")
    for a, b in zip(whole, blocks):
        assert torch.equal(a, b)
    tree = ball_pairs(rec, src, 1.5, method="kdtree")
    assert whole[0].numel() == tree[0].numel() > 1000
    with pytest.raises(ValueError, match="max_pairs: expected at most 100 pairs"):
        ball_pairs(rec, src, 1.5, max_pairs=100, method="grid")
    with pytest.raises(ValueError, match="method: expected one of"):
        ball_pairs(rec, src, 1.5, method="octree")
    with pytest.raises(ValueError, match="max_pairs: expected at most 100 pairs"):
        ball_pairs(rec, src, 1.5, max_pairs=100, method="kdtree")


def test_ball_pairs_kdtree_blocks(monkeypatch):
    """The tree path lists blocks of consecutive receivers, each ordered by (receiver, source): any block size
    (here down to blocks of one receiver, and receivers without a pair) gives the same pairs in the same order."""
    import torchsss.geometry.neighbours as nb

    gen = torch.Generator().manual_seed(3)
    rec = torch.cat([torch.rand(250, 3, generator=gen, dtype=F64) * 6.0, torch.full((5, 3), 100.0, dtype=F64)])
    src = torch.rand(400, 3, generator=gen, dtype=F64) * 6.0
    whole = ball_pairs(rec, src, 1.5, method="kdtree")
    key = whole[0] * src.shape[0] + whole[1]
    assert bool((key[1:] > key[:-1]).all())  # (receiver, source) order, no pair twice
    torch.testing.assert_close(whole[2], (rec[whole[0]] - src[whole[1]]).norm(dim=1), rtol=1e-12, atol=0)
    for block in (1, 37, 5000):
        monkeypatch.setattr(nb, "KDTREE_BLOCK", block)
        for a, b in zip(whole, ball_pairs(rec, src, 1.5, method="kdtree")):
            assert torch.equal(a, b)


def test_ball_pairs_errors():
    x = torch.zeros(3, 3)
    with pytest.raises(TypeError, match="receivers: expected a floating tensor"):
        ball_pairs(torch.zeros(3, 3, dtype=torch.int64), x, 1.0)
    with pytest.raises(ValueError, match=r"sources: expected shape \(n, 3\)"):
        ball_pairs(x, torch.zeros(3, 2), 1.0)
    with pytest.raises(ValueError, match="radius_mm: expected a finite number >= 0"):
        ball_pairs(x, x, -1.0)
    with pytest.raises(ValueError, match="max_pairs: expected at most 5 pairs"):
        ball_pairs(x, x, 1.0, max_pairs=5)


def _flat_local(material, spacing=0.05, half=12.0):
    """SurfaceLocal over a flat square (uv = the square mapped to [0, 1]^2) with every sample's irradiance 1."""
    mesh = plane(2 * half, 2 * half, 24, dtype=F64)
    smp = surface_samples(mesh, spacing)
    uv = (smp.position[:, :2] + half) / (2 * half)
    with torch.no_grad():
        r_p = float(chang_rp(material.sigma_a, material.sigma_s_prime, material.eta, c=0.1).amax())
    w = ChangLocalProfile(r_p, 1.5, r_p + math.log(0.5 / 1e-2) / 1.5)
    valid = torch.ones(1, 1, 8, 8, dtype=torch.bool)
    return SurfaceLocal(uv, smp.area, valid, material, w), smp, w


def test_surface_local_on_a_plane_is_the_closed_form_local_mass():
    """Uniform irradiance on a large plane: the local radiosity at its centre is the integral of R_d W_l^b over the
    plane, int_0^b 2 pi r R_d W_l dr (a fine 1-D quadrature here), for every channel (0.05 mm samples: 0.3%)."""
    mat = DipoleMaterial(*Material.from_json("skin1").tensors(F64)).requires_grad_(False)
    local, smp, w = _flat_local(mat)
    centre = torch.zeros(1, 3, dtype=F64)
    rows, cols, dist = ball_pairs(centre, smp.position, w.bound)
    e = torch.ones(1, 3, 8, 8, dtype=F64)
    got = local(e, rows, cols, dist, 1)[0, 0]
    r = torch.linspace(0.0, w.bound, 200001, dtype=F64)[1:, None]
    f = 2 * math.pi * r * mat(r) * w(r)
    want = torch.trapezoid(f, r[:, 0], dim=0)
    torch.testing.assert_close(got, want, rtol=3e-3, atol=0.0)
    assert float(want.min()) > 0.1 * float(want.max()) > 0


def test_surface_local_matches_a_loop_with_varying_irradiance():
    """A varying irradiance atlas: the module equals the sum written out pair by pair (bilinear lookups over the
    valid texels at the samples' uv, A R_d W_l E)."""
    mat = DipoleMaterial(*Material.from_json("marble").tensors(F64)).requires_grad_(False)
    mesh = sphere(4.0, 2, dtype=F64)
    smp = surface_samples(mesh, 0.8)
    gen = torch.Generator().manual_seed(1)
    uv = torch.rand(smp.area.shape[0], 2, generator=gen, dtype=F64)
    valid = torch.rand(1, 1, 16, 16, generator=gen) > 0.2
    w = ChangLocalProfile(1.0, 1.5, 3.0)
    local = SurfaceLocal(uv, smp.area, valid, mat, w)
    rec = smp.position[:9] * 1.05
    rows, cols, dist = ball_pairs(rec, smp.position, w.bound)
    e = torch.rand(2, 3, 16, 16, generator=gen, dtype=F64)
    got = local(e, rows, cols, dist, rec.shape[0])
    # the loop: bilinear lookup by hand (texel centres at (c + 0.5) / 16, v up), renormalised over valid texels
    ev = e * valid

    def lookup(img, u, v):
        x, y = u * 16 - 0.5, (1 - v) * 16 - 0.5
        x0, y0 = math.floor(x), math.floor(y)
        acc = torch.zeros(img.shape[0], dtype=F64)
        for dy in (0, 1):
            for dx in (0, 1):
                xi, yi = x0 + dx, y0 + dy
                wt = (1 - abs(x - xi)) * (1 - abs(y - yi))
                if 0 <= xi < 16 and 0 <= yi < 16:
                    acc += wt * img[:, yi, xi]
        return acc

    want = torch.zeros(2, rec.shape[0], 3, dtype=F64)
    for i, j, d in zip(rows.tolist(), cols.tolist(), dist.tolist()):
        u, v = float(uv[j, 0]), float(uv[j, 1])
        den = float(lookup(valid[0].to(F64), u, v)[0])
        for b in range(2):
            es = lookup(ev[b], u, v) / max(den, 1e-6)
            dd = torch.tensor([[d]], dtype=F64)
            want[b, i] += smp.area[j] * mat(dd)[0] * w(dd)[0] * es
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)
    assert float(want.abs().max()) > 0


def test_surface_local_keeps_its_cached_pairs_past_an_uncached_call(monkeypatch):
    """A frame's refined pixels (cache=False) neither evict the view's cached pair weights nor get cached."""
    mat = DipoleMaterial(*Material.from_json("marble").tensors(F64)).requires_grad_(False)
    local, smp, w = _flat_local(mat, spacing=0.5, half=6.0)
    e = torch.ones(1, 3, 8, 8, dtype=F64)
    a = ball_pairs(torch.zeros(4, 3, dtype=F64), smp.position, w.bound)
    b = ball_pairs(torch.full((3, 3), 0.7, dtype=F64) * torch.tensor([1.0, 1.0, 0.0], dtype=F64), smp.position,
                   w.bound)
    calls = []
    original = SurfaceLocal.pair_weights

    def counted(self, cols, distance):
        calls.append(int(cols.numel()))
        return original(self, cols, distance)

    monkeypatch.setattr(SurfaceLocal, "pair_weights", counted)
    with torch.no_grad():
        first = local(e, *a, 4)
        other = local(e, *b, 3, cache=False)
        again = local(e, *a, 4)
        other_again = local(e, *b, 3, cache=False)
    # the cached pairs were weighted once; the uncached ones on every call
    assert calls == [a[0].numel(), b[0].numel(), b[0].numel()]
    torch.testing.assert_close(again, first, rtol=0, atol=0)
    torch.testing.assert_close(other_again, other, rtol=0, atol=0)
    with pytest.raises(TypeError, match="cache"):
        local(e, *a, 4, cache=1)


def test_surface_local_gradcheck_and_errors():
    mat = DipoleMaterial(*Material.from_json("skin1").tensors(F64))
    mesh = sphere(3.0, 1, dtype=F64)
    smp = surface_samples(mesh, 1.0)
    uv = torch.rand(smp.area.shape[0], 2, generator=torch.Generator().manual_seed(2), dtype=F64)
    w = ChangLocalProfile(0.8, 1.5, 2.5)
    local = SurfaceLocal(uv, smp.area, torch.ones(1, 1, 6, 6, dtype=torch.bool), mat, w)
    rows, cols, dist = ball_pairs(smp.position[:4], smp.position, w.bound)
    e = torch.rand(1, 3, 6, 6, dtype=F64, generator=torch.Generator().manual_seed(3)).requires_grad_()
    raw = (mat.raw_sigma_a.detach().clone().requires_grad_(), mat.raw_sigma_s_prime.detach().clone().requires_grad_())
    from torch.func import functional_call

    def f(e, sa, ss):
        return functional_call(local, {"material.raw_sigma_a": sa, "material.raw_sigma_s_prime": ss},
                               (e, rows, cols, dist, 4)).sum((0, 1))

    assert torch.autograd.gradcheck(f, (e, *raw), eps=1e-6, atol=1e-8, rtol=1e-5)
    with pytest.raises(ValueError, match=r"sample_area: expected shape"):
        SurfaceLocal(uv, smp.area[:-1], torch.ones(1, 1, 6, 6, dtype=torch.bool), mat, w)
    with pytest.raises(TypeError, match="weight: expected a ChangLocalProfile"):
        SurfaceLocal(uv, smp.area, torch.ones(1, 1, 6, 6, dtype=torch.bool), mat, 1.0)
    with pytest.raises(ValueError, match="irradiance"):
        local(torch.ones(1, 3, 5, 6, dtype=F64), rows, cols, dist, 4)
    with pytest.raises(ValueError, match="rows"):
        local(torch.ones(1, 3, 6, 6, dtype=F64), rows[:-1], cols, dist, 4)
    with pytest.raises(ValueError, match="irradiance"):
        local(torch.full((1, 3, 6, 6), float("nan"), dtype=F64), rows, cols, dist, 4)


def test_hybrid_renderer_plans_the_local_grid_and_falls_back():
    """``local="surface"``: the local term at every pixel when its pairs fit ``max_local_pairs``; on a coarser pixel
    grid (interpolated where smooth, exact at edges) when they do not, within 1% of the full evaluation; a narrower
    split (said in the stats) when even stride 8 would not fit; ``local="atlas"``: Chang's filter."""
    from torchsss.geometry import Camera, PointLight
    from torchsss.pipelines import build

    mesh = sphere(8.0, 3)
    lights = [PointLight((40.0, 5.0, 30.0), 3e3)]
    camera = Camera(eye=(0.0, 0.0, 45.0), target=(0.0, 0.0, 0.0), width=48, height=48, fov_deg=26.0)
    full = build("hybrid", mesh, "skin1", atlas_resolution=256, samples=1024).render(lights, camera)
    assert full.stats["local_term"] == "surface" and full.stats["local_stride"] == 1
    pairs = full.stats["local_pairs"]
    coarse = build("hybrid", mesh, "skin1", atlas_resolution=256, samples=1024,
                   max_local_pairs=pairs // 3).render(lights, camera)
    assert coarse.stats["local_term"] == "surface" and coarse.stats["local_stride"] > 1
    assert coarse.stats["local_pairs"] < pairs
    m = full.mask.expand_as(full.radiance)
    rel = float((coarse.radiance - full.radiance)[m].norm() / full.radiance[m].norm())
    assert rel < 0.01, rel
    # nothing fits: the split narrows (c doubles) until it does; for skin1 at c = 0.2 it narrows away (R_p = 0) and
    # every source is sampled: noisier, still without seams
    narrow = build("hybrid", mesh, "skin1", atlas_resolution=256, samples=1024, max_local_pairs=10)
    out = narrow.render(lights, camera)
    assert out.stats["local_term"].startswith("none (split narrowed away at c = 0.2") and out.stats["local_c"] == 0.2
    rel = float((out.radiance - full.radiance)[m].norm() / full.radiance[m].norm())
    assert bool(torch.isfinite(out.radiance).all()) and rel < 0.1, rel
    atlas = build("hybrid", mesh, "skin1", atlas_resolution=256, samples=1024, local="atlas").render(lights, camera)
    assert atlas.stats["local_term"] == "atlas" and "local_stride" not in atlas.stats
    with pytest.raises(ValueError, match="local: expected 'surface' or 'atlas'"):
        build("hybrid", mesh, "skin1", atlas_resolution=64, local="texture")


def test_surface_local_pair_weights_in_blocks():
    """Outside autograd the pairs' weights are evaluated in blocks (bounded temporaries): any block size gives what
    one block gives, and both agree with the material's own formula under autograd (the table's tolerance)."""
    mat = DipoleMaterial(*Material.from_json("marble").tensors(F64)).requires_grad_(False)
    local, smp, w = _flat_local(mat, spacing=0.2)
    rec = smp.position[::2000]
    _, cols, dist = ball_pairs(rec, smp.position, w.bound)
    assert dist.numel() > 5000
    with torch.no_grad():
        whole = local.pair_weights(cols, dist)
        local.weight_block = 999
        blocks = local.pair_weights(cols, dist)
    assert torch.equal(whole, blocks)
    with torch.enable_grad():
        exact = local.pair_weights(cols, dist)
    torch.testing.assert_close(blocks, exact.detach(), rtol=1e-6, atol=1e-12 * float(exact.abs().max()))
