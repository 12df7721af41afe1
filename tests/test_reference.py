import math
from functools import partial

import pytest
import torch

from torchsss import DipoleMaterial, reference_radiosity
from torchsss.ops import pairwise_distance
from torchsss.physics import dipole_rd, total_diffuse_reflectance
from torchsss.testing import assert_close


def _naive(src, e, area, dst, sa, ss, eta, md=None, mi=None, src_ids=None, dst_ids=None):
    """Double loop in Python floats: B[b, o, c] = sum_i E[b, i, c] A[b, i] M_i R_d(|x_i - x_o| M_d)."""
    b_, n, _ = src.shape
    m, c_ = dst.shape[1], e.shape[2]
    out = torch.zeros(b_, m, c_, dtype=torch.float64)
    for b in range(b_):
        for o in range(m):
            for i in range(n):
                if src_ids is not None and int(src_ids[b, i]) != int(dst_ids[b, o]):
                    continue
                r = math.dist(src[b, i].tolist(), dst[b, o].tolist())
                for c in range(c_):
                    scale_d = 1.0 if md is None else md[b, i, c if md.shape[-1] > 1 else 0].item()
                    scale_i = 1.0 if mi is None else mi[b, i, c if mi.shape[-1] > 1 else 0].item()
                    rd = dipole_rd(torch.tensor(r * scale_d, dtype=torch.float64), sa[c].item(), ss[c].item(),
                                   eta).item()
                    out[b, o, c] += e[b, i, c].item() * area[b, i].item() * scale_i * rd
    return out


@pytest.fixture
def scene():
    g = torch.Generator().manual_seed(0)
    src = torch.rand(2, 9, 3, generator=g, dtype=torch.float64) * 4
    dst = torch.cat([src[:, :3], torch.rand(2, 4, 3, generator=g, dtype=torch.float64) * 4], dim=1)
    e = torch.rand(2, 9, 3, generator=g, dtype=torch.float64)
    area = torch.rand(2, 9, generator=g, dtype=torch.float64) * 0.1
    sa = torch.tensor([0.01, 0.1, 0.5], dtype=torch.float64)
    ss = torch.tensor([1.0, 2.0, 0.7], dtype=torch.float64)
    return src, e, area, dst, sa, ss, 1.3


@pytest.mark.parametrize("max_pairs", [1, 5, 7, 10_000])
def test_exact_against_double_loop(scene, max_pairs):
    src, e, area, dst, sa, ss, eta = scene
    prof = partial(dipole_rd, sigma_a=sa, sigma_s_prime=ss, eta=eta)
    got = reference_radiosity(src, e, area, dst, prof, max_pairs=max_pairs)
    assert_close(got, _naive(src, e, area, dst, sa, ss, eta), rtol=1e-13, atol=1e-300)


def test_modifiers_and_object_ids(scene):
    src, e, area, dst, sa, ss, eta = scene
    g = torch.Generator().manual_seed(1)
    md = 0.5 + torch.rand(2, 9, 3, generator=g, dtype=torch.float64)
    mi = torch.rand(2, 9, 1, generator=g, dtype=torch.float64)
    src_ids = torch.randint(0, 2, (2, 9), generator=g)
    dst_ids = torch.randint(0, 2, (2, 7), generator=g)
    prof = partial(dipole_rd, sigma_a=sa, sigma_s_prime=ss, eta=eta)
    got = reference_radiosity(src, e, area, dst, prof, src_distance_scale=md, src_irradiance_scale=mi,
                              src_ids=src_ids, dst_ids=dst_ids, max_pairs=6)
    expected = _naive(src, e, area, dst, sa, ss, eta, md=md, mi=mi, src_ids=src_ids, dst_ids=dst_ids)
    assert_close(got, expected, rtol=1e-13, atol=1e-300)


def test_uniform_plane_converges_to_total_reflectance():
    """Uniform unit irradiance on a fine plane grid: B at the centre -> R_total (closed form)."""
    m = DipoleMaterial.from_preset("skin1", dtype=torch.float64)
    h = 0.05
    n = int(30 / h)
    g = (torch.arange(-n, n + 1, dtype=torch.float64)) * h
    gx, gy = torch.meshgrid(g, g, indexing="ij")
    src = torch.stack([gx, gy, torch.zeros_like(gx)], -1).reshape(1, -1, 3)
    e = torch.ones(1, src.shape[1], 3, dtype=torch.float64)
    area = torch.full((1, src.shape[1]), h * h, dtype=torch.float64)
    dst = torch.tensor([[[0.0, 0.0, 0.0], [0.02, 0.01, 0.0]]], dtype=torch.float64)
    with torch.no_grad():
        b = reference_radiosity(src, e, area, dst, m, max_pairs=1 << 18)
    total = total_diffuse_reflectance(m.sigma_a, m.sigma_s_prime, m.eta).detach()
    # truncation at 30 mm loses < 1e-4 for skin1; the lattice sum at h = 0.05 mm is accurate to ~1e-6
    assert_close(b[0], total.expand(2, 3), rtol=2e-4, atol=0)


def test_gradcheck_reference(scene):
    src, e, area, dst, sa, ss, eta = scene
    src, e, area, dst = src[:1, :4], e[:1, :4], area[:1, :4], dst[:1, 3:6]
    sa_p = sa.clone().requires_grad_(True)

    def f(e_, area_, src_, dst_, sa_):
        return reference_radiosity(src_, e_, area_, dst_, partial(dipole_rd, sigma_a=sa_, sigma_s_prime=ss, eta=eta),
                                   max_pairs=5)

    inputs = (e.clone().requires_grad_(True), area.clone().requires_grad_(True), src.clone().requires_grad_(True),
              dst.clone().requires_grad_(True), sa_p)
    assert torch.autograd.gradcheck(f, inputs)


def test_coincident_points_have_finite_gradients():
    x = torch.zeros(1, 2, 3, dtype=torch.float64, requires_grad=True)
    d = pairwise_distance(x, x)
    d.sum().backward()
    assert torch.isfinite(x.grad).all() and d.max().item() == 0.0


def test_material_module_as_profile_gets_gradients(scene):
    src, e, area, dst, *_ = scene
    m = DipoleMaterial.from_preset("marble", dtype=torch.float64)
    reference_radiosity(src, e, area, dst, m).sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
               for p in m.parameters())


def test_float32_matches_float64(scene):
    src, e, area, dst, sa, ss, eta = scene
    prof = partial(dipole_rd, sigma_a=sa, sigma_s_prime=ss, eta=eta)
    b64 = reference_radiosity(src, e, area, dst, prof)
    prof32 = partial(dipole_rd, sigma_a=sa.float(), sigma_s_prime=ss.float(), eta=eta)
    b32 = reference_radiosity(src.float(), e.float(), area.float(), dst.float(), prof32)
    assert b32.dtype == torch.float32
    assert_close(b32, b64.float(), rtol=2e-5, atol=0)


def test_memory_bounded_chunks_large_input():
    # 20k x 20k pairs would be 400M x 3 floats at once; with the default budget this runs in bounded memory
    g = torch.Generator().manual_seed(3)
    src = torch.rand(1, 20000, 3, generator=g) * 30
    prof = partial(dipole_rd, sigma_a=torch.tensor([0.01]), sigma_s_prime=torch.tensor([1.0]), eta=1.3)
    b = reference_radiosity(src, torch.ones(1, 20000, 1), torch.full((1, 20000), 0.01), src[:, :20], prof,
                            max_pairs=1 << 15)
    assert b.shape == (1, 20, 1) and torch.isfinite(b).all() and (b > 0).all()


@pytest.mark.parametrize(
    "change,exc,match",
    [
        (dict(src_pos=torch.rand(1, 4, 2)), ValueError, "src_pos"),
        (dict(src_irradiance=torch.rand(1, 5, 3)), ValueError, "src_irradiance"),
        (dict(src_area=torch.rand(1, 4, 2)), ValueError, "src_area"),
        (dict(src_area=-torch.rand(1, 4)), ValueError, "src_area"),
        (dict(dst_pos=torch.rand(2, 3, 3)), ValueError, "dst_pos"),
        (dict(dst_pos=[[0.0, 0.0, 0.0]]), TypeError, "dst_pos"),
        (dict(src_pos=torch.zeros(1, 4, 3, dtype=torch.int64)), TypeError, "src_pos"),
        (dict(max_pairs=0), ValueError, "max_pairs"),
        (dict(src_ids=torch.zeros(1, 4, dtype=torch.int64)), ValueError, "src_ids, dst_ids"),
        (dict(src_ids=torch.zeros(1, 4), dst_ids=torch.zeros(1, 3)), TypeError, "src_ids"),
        (dict(src_distance_scale=torch.ones(1, 4, 2)), ValueError, "src_distance_scale"),
    ],
)
def test_bad_input(change, exc, match):
    args = dict(src_pos=torch.rand(1, 4, 3), src_irradiance=torch.rand(1, 4, 3), src_area=torch.rand(1, 4),
                dst_pos=torch.rand(1, 3, 3), profile=partial(dipole_rd, sigma_a=0.1, sigma_s_prime=1.0))
    args.update(change)
    with pytest.raises(exc, match=match):
        reference_radiosity(**args)


def test_reference_radiosity_id_weight_generalises_the_ids_rule():
    """``id_weight(r, same)`` multiplies each pair's kernel: the default rule is ``same``; a loop computes any."""
    from torchsss.ops import reference_radiosity
    from torchsss.ops.reference import pairwise_distance

    g = torch.Generator().manual_seed(3)
    src, dst = torch.rand(2, 7, 3, generator=g, dtype=torch.float64) * 4, torch.rand(2, 5, 3, generator=g,
                                                                                      dtype=torch.float64) * 4
    e, area = torch.rand(2, 7, 3, generator=g, dtype=torch.float64), torch.rand(2, 7, generator=g, dtype=torch.float64)
    sid, did = torch.randint(2, (2, 7), generator=g), torch.randint(2, (2, 5), generator=g)

    def profile(r):
        return torch.exp(-r).expand(*r.shape[:-1], 3)

    def weight(r, same):
        return 1.0 - 0.5 * torch.exp(-r) * same.to(r.dtype)

    got = reference_radiosity(src, e, area, dst, profile, src_ids=sid, dst_ids=did, id_weight=weight, max_pairs=6)
    r = pairwise_distance(dst, src)
    same = (did[:, :, None] == sid[:, None, :]).unsqueeze(-1)
    loop = (profile(r) * weight(r, same) * (e * area.unsqueeze(-1))[:, None]).sum(2)
    torch.testing.assert_close(got, loop)
    plain = reference_radiosity(src, e, area, dst, profile, src_ids=sid, dst_ids=did)
    torch.testing.assert_close(plain, (profile(r) * same * (e * area.unsqueeze(-1))[:, None]).sum(2))
    with pytest.raises(ValueError, match="id_weight: expected a callable"):
        reference_radiosity(src, e, area, dst, profile, id_weight=weight)
