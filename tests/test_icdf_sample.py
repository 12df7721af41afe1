"""Texture-space importance sampling (Chang): sum-pyramid descent and the searchsorted reference.

Both samplers are checked against the distribution they must draw from (chi-square goodness of fit on the texels
and on the position inside a texel), against the contract p = pdf[texel] / sum(pdf), at the extremes (delta,
all-zero and 1x1 maps, u = 0 and the largest float below 1), and the descent against onnxruntime.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from torchsss.ops.icdf import MAX_LEVELS, icdf_sample, icdf_sample_reference, pyramid_levels, sum_pyramid

F64 = torch.float64
ALPHA = 1e-3  # significance of the goodness-of-fit tests (the seeds are fixed: a pass is reproducible)


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _rand_u(b, n, seed, dtype=F64):
    return torch.rand(b, n, 2, generator=_gen(seed), dtype=F64).to(dtype)


def _one_minus(dtype):
    return torch.nextafter(torch.tensor(1.0, dtype=dtype), torch.tensor(0.0, dtype=dtype)).item()


def _pdfs():
    """Named (B, 1, H, W) float64 maps; the batch elements differ."""
    g = _gen(0)
    rand = torch.rand(2, 1, 16, 16, generator=g, dtype=F64)
    yy, xx = torch.meshgrid(torch.arange(32.0, dtype=F64), torch.arange(32.0, dtype=F64), indexing="ij")
    peak = torch.stack(
        [
            torch.exp(-((xx - 9.3) ** 2 + (yy - 20.6) ** 2) / (2 * 1.5**2)),
            torch.exp(-((xx - 30.0) ** 2 + (yy - 1.0) ** 2) / (2 * 3.0**2)) + 1e-4,
        ]
    )[:, None]
    npot = torch.rand(2, 1, 7, 13, generator=g, dtype=F64) ** 3
    npot[0, 0, 2, :] = 0  # a zero row
    npot[1, 0, :, 5] = 0  # a zero column
    holes = torch.rand(2, 1, 9, 6, generator=g, dtype=F64)
    holes[holes < 0.5] = 0  # half the texels empty
    return {
        "random16": rand,
        "peaked32": peak,
        "npot7x13": npot,
        "holes9x6": holes,
        "row1x37": torch.rand(2, 1, 1, 37, generator=g, dtype=F64) + 0.1,
        "col29x1": torch.rand(2, 1, 29, 1, generator=g, dtype=F64) + 0.1,
    }


PDFS = _pdfs()


def _descent_deeper(pdf, u):
    """The descent with 2 more levels than needed (the fixed-depth export path): same distribution."""
    return icdf_sample(pdf, u, levels=pyramid_levels(*pdf.shape[-2:]) + 2)


SAMPLERS = {"descent": icdf_sample, "descent+2": _descent_deeper, "reference": icdf_sample_reference}


def _texels(xy, w):
    t = xy.floor().long()
    return t[..., 1] * w + t[..., 0]


def _gof_pvalue(counts, probs, n):
    """Chi-square p-value of ``counts`` (K,) against ``n * probs``; bins expecting < 5 are pooled into one."""
    counts = counts.double()
    expected = n * probs
    assert float(counts[probs == 0].sum()) == 0.0, "samples in zero-probability bins"
    small = (expected < 5) & (probs > 0)
    big = expected >= 5
    obs = torch.cat([counts[big], counts[small].sum().reshape(1)])
    exp = torch.cat([expected[big], expected[small].sum().reshape(1)])
    if float(exp[-1]) < 5:  # too little to stand alone: fold into the largest bin
        k = int(exp[:-1].argmax())
        obs[k] += obs[-1]
        exp[k] += exp[-1]
        obs, exp = obs[:-1], exp[:-1]
    stat = float(((obs - exp) ** 2 / exp).sum())
    return float(chi2.sf(stat, obs.numel() - 1))


def _texel_pvalues(pdf, xy):
    b, _, h, w = pdf.shape
    n = xy.shape[1]
    idx = _texels(xy, w)
    out = []
    for i in range(b):
        flat = pdf[i, 0].flatten()
        probs = flat / flat.sum() if float(flat.sum()) > 0 else torch.full_like(flat, 1.0 / flat.numel())
        out.append(_gof_pvalue(torch.bincount(idx[i], minlength=h * w), probs, n))
    return out


# -- distribution ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
@pytest.mark.parametrize("case", PDFS.keys())
def test_chi_square_over_texels(case, sampler):
    pdf = PDFS[case]
    n = 1 << 15
    xy, _ = sampler(pdf, _rand_u(pdf.shape[0], n, seed=1))
    for pv in _texel_pvalues(pdf, xy):
        assert pv > ALPHA, (case, pv)


@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
def test_chi_square_with_scrambled_sobol(sampler):
    pdf = torch.cat([PDFS["peaked32"][:1], PDFS["random16"][:1].repeat(1, 1, 2, 2)])
    u = torch.quasirandom.SobolEngine(2, scramble=True, seed=7).draw(1 << 14, dtype=F64).expand(2, -1, -1)
    xy, _ = sampler(pdf, u.contiguous())
    for pv in _texel_pvalues(pdf, xy):
        assert pv > ALPHA, pv


def test_goodness_of_fit_has_power():
    # the check above would catch a sampler that ignores the pdf (uniform draws) or mixes up x and y
    pdf = PDFS["peaked32"][:1]
    xy, _ = icdf_sample(torch.ones_like(pdf), _rand_u(1, 1 << 15, seed=2))
    with pytest.raises(AssertionError, match="zero-probability"):
        _gof_pvalue(torch.tensor([3, 0]), torch.tensor([0.0, 1.0], dtype=F64), 3)
    assert _texel_pvalues(pdf, xy)[0] < 1e-12
    skew = torch.rand(1, 1, 8, 8, generator=_gen(3), dtype=F64) ** 4
    xy, _ = icdf_sample(skew.transpose(-1, -2), _rand_u(1, 1 << 15, seed=4))
    assert _texel_pvalues(skew, xy)[0] < 1e-12


def test_uniform_pdf_keeps_sobol_stratification():
    # power-of-two uniform map: every share is 1/2, the walk maps each dyadic interval of u[..., 0] (u[..., 1]) to
    # one column (row), so the 2^14 points of a (0, m, 2)-net fill each of the 16 x 16 texels with exactly 64
    u = torch.quasirandom.SobolEngine(2, scramble=False).draw(1 << 14, dtype=F64)[None]
    xy, p = icdf_sample(torch.ones(1, 1, 16, 16, dtype=F64), u)
    counts = torch.bincount(_texels(xy, 16)[0], minlength=256)
    assert torch.equal(counts, torch.full((256,), 64))
    assert torch.equal(p, torch.full_like(p, 1 / 256))


@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
@pytest.mark.parametrize("case", ["npot7x13", "peaked32"])
def test_position_inside_texel_is_uniform(case, sampler):
    pdf = PDFS[case][:1]
    n = 1 << 15
    xy, _ = sampler(pdf, _rand_u(1, n, seed=5))
    frac = xy[0] - xy[0].floor()
    assert float(frac.min()) >= 0 and float(frac.max()) < 1
    cells = (frac * 4).floor().long()  # 4 x 4 joint bins: uniform and independent offsets
    counts = torch.bincount(cells[:, 1] * 4 + cells[:, 0], minlength=16)
    assert _gof_pvalue(counts, torch.full((16,), 1 / 16, dtype=F64), n) > ALPHA
    # also inside the most likely texel alone
    top = _texels(xy, pdf.shape[-1])[0] == int(pdf[0, 0].flatten().argmax())
    halves = cells[top] // 2  # 2 x 2 bins inside that texel
    counts = torch.bincount(halves[:, 1] * 2 + halves[:, 0], minlength=4)
    assert int(top.sum()) > 200
    assert _gof_pvalue(counts, torch.full((4,), 1 / 4, dtype=F64), int(top.sum())) > ALPHA


@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
def test_importance_sampling_estimate(sampler):
    # mean(f(xy) / p) estimates the integral of f over [0, W) x [0, H): f = x * y on 7 x 13 -> (13^2/2) (7^2/2)
    pdf = torch.rand(1, 1, 7, 13, generator=_gen(6), dtype=F64) + 0.05
    n = 1 << 16
    xy, p = sampler(pdf, _rand_u(1, n, seed=8))
    g = xy[0, :, 0] * xy[0, :, 1] / p[0]
    want = 13**2 / 2 * 7**2 / 2
    assert abs(float(g.mean()) - want) < 5 * float(g.std()) / math.sqrt(n)


# -- contract ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
@pytest.mark.parametrize("case", PDFS.keys())
def test_p_is_pdf_over_sum_at_the_texel(case, sampler, dtype):
    pdf = PDFS[case].to(dtype)
    b, _, h, w = pdf.shape
    xy, p = sampler(pdf, _rand_u(b, 2000, seed=9, dtype=dtype))
    assert xy.dtype == dtype and p.dtype == dtype and xy.shape == (b, 2000, 2) and p.shape == (b, 2000)
    assert bool((xy[..., 0] >= 0).all() and (xy[..., 0] < w).all() and (xy[..., 1] >= 0).all())
    assert bool((xy[..., 1] < h).all())
    flat = pdf.to(F64).flatten(1)
    want = torch.gather(flat, 1, _texels(xy, w)) / flat.sum(1, keepdim=True)
    assert bool((want > 0).all())  # never a zero texel
    rtol = 1e-12 if dtype == F64 else 1e-5
    torch.testing.assert_close(p.to(F64), want, rtol=rtol, atol=0)


@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
def test_deterministic_and_batch_independent(sampler):
    pdf = torch.cat([PDFS["npot7x13"], torch.zeros(1, 1, 7, 13, dtype=F64)])
    u = _rand_u(3, 500, seed=10)
    xy, p = sampler(pdf, u)
    xy2, p2 = sampler(pdf, u)
    assert torch.equal(xy, xy2) and torch.equal(p, p2)
    for i in range(3):
        xyi, pi = sampler(pdf[i : i + 1], u[i : i + 1])
        assert torch.equal(xyi, xy[i : i + 1]) and torch.equal(pi, p[i : i + 1])
    # scaling the map changes nothing that matters: same texels, same p
    xys, ps = sampler(pdf * 1e20, u)
    assert torch.equal(xys.floor(), xy.floor())
    torch.testing.assert_close(ps, p, rtol=1e-12, atol=0)


@pytest.mark.parametrize("dtype", [torch.float32, F64], ids=["f32", "f64"])
def test_inplace_and_autograd_paths_agree_exactly(dtype, monkeypatch):
    # inference runs the descent in place, autograd/export out of place: same ops, same bits
    import torchsss.ops.icdf as mod

    pdf = torch.cat([PDFS["npot7x13"], torch.zeros(1, 1, 7, 13, dtype=F64)]).to(dtype)
    u = _extreme_u(3, 700, dtype)
    u_before, pdf_before = u.clone(), pdf.clone()
    for levels in (None, 6):
        xy, p = icdf_sample(pdf, u, levels)
        assert torch.equal(u, u_before) and torch.equal(pdf, pdf_before)  # the in-place path works on copies
        xy_g, p_g = icdf_sample(pdf, u.clone().requires_grad_(), levels)
        assert torch.equal(xy, xy_g.detach()) and torch.equal(p, p_g.detach())
    # texel indices tracked in float64 (the path of pyramids deeper than 12 levels in float32): same results
    xy, p = icdf_sample(pdf, u)
    monkeypatch.setattr(mod, "_CHUNK", 7)  # 3 batch elements -> chunks of 2 samples, a short last chunk
    xy_c, p_c = icdf_sample(pdf, u)
    assert torch.equal(xy, xy_c) and torch.equal(p, p_c)
    monkeypatch.setattr(mod, "_CHUNK", 1 << 16)
    monkeypatch.setitem(mod._FLOAT_INDEX_LEVELS, dtype, 1)
    xy64, p64 = icdf_sample(pdf, u)
    assert torch.equal(xy, xy64) and torch.equal(p, p64)
    assert torch.equal(xy64, icdf_sample(pdf, u.clone().requires_grad_())[0].detach())


def test_float32_and_float64_agree_on_texels():
    pdf = PDFS["random16"]
    u = _rand_u(2, 4000, seed=11, dtype=torch.float32)
    xy32, p32 = icdf_sample(pdf.float(), u)
    xy64, p64 = icdf_sample(pdf, u.to(F64))
    same = (xy32.floor().to(F64) == xy64.floor()).all(-1)
    assert float(same.double().mean()) > 0.999  # only u within float32 rounding of a boundary may differ
    torch.testing.assert_close(xy32[same].to(F64), xy64[same], rtol=0, atol=1e-4)
    torch.testing.assert_close(p32.to(F64)[same], p64[same], rtol=1e-5, atol=0)


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
def test_reduced_precision_inputs(low):
    pdf = PDFS["npot7x13"].to(low)
    u = _rand_u(2, 300, seed=12).to(low).clamp(max=_one_minus(low))  # rounding to low precision can reach 1
    for sampler in (icdf_sample, icdf_sample_reference):
        xy, p = sampler(pdf, u)
        assert xy.dtype == low and p.dtype == low
        assert bool((xy[..., 0] < 13).all() and (xy[..., 1] < 7).all() and (xy >= 0).all())
        flat = pdf.to(F64).flatten(1)
        want = torch.gather(flat, 1, _texels(xy.to(F64), 13)) / flat.sum(1, keepdim=True)
        torch.testing.assert_close(p.to(F64), want, rtol=1e-2, atol=0)
    assert icdf_sample(pdf, u.float())[0].dtype == torch.float32  # promotion to the wider input


def test_device_dtype(device, dtype):
    pdf = PDFS["holes9x6"].to(device=device, dtype=dtype)
    u = _rand_u(2, 1000, seed=13, dtype=dtype).to(device)
    xy, p = icdf_sample(pdf, u)
    assert xy.device.type == device.type and p.device.type == device.type and xy.dtype == dtype
    xy_cpu, p_cpu = icdf_sample(pdf.cpu(), u.cpu())
    torch.testing.assert_close(xy.cpu(), xy_cpu, rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)
    torch.testing.assert_close(p.cpu(), p_cpu)


# -- extremes ---------------------------------------------------------------------------------------------------
def _extreme_u(b, n, dtype, seed=14):
    """Uniforms with 0, the largest float below 1, and both mixed, followed by random values."""
    top = _one_minus(dtype)
    corners = torch.tensor([[0.0, 0.0], [top, top], [0.0, top], [top, 0.0], [0.5, 0.5]], dtype=dtype)
    return torch.cat([corners.expand(b, -1, -1), _rand_u(b, n, seed=seed, dtype=dtype)], dim=1)


@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
@pytest.mark.parametrize(
    ("h", "w", "i", "j"),
    [(1, 1, 0, 0), (7, 13, 0, 0), (7, 13, 6, 12), (7, 13, 3, 0), (16, 16, 15, 0), (5, 1, 4, 0), (1, 9, 0, 8)],
)
@pytest.mark.parametrize("value", [1.0, 1e-30, 3e37], ids=["one", "tiny", "huge"])
def test_single_lit_texel(h, w, i, j, value, sampler, dtype):
    pdf = torch.zeros(2, 1, h, w, dtype=dtype)
    pdf[:, 0, i, j] = value
    xy, p = sampler(pdf, _extreme_u(2, 200, dtype))
    t = xy.floor()
    assert bool((t[..., 0] == j).all() and (t[..., 1] == i).all()), (t[..., 0].unique(), t[..., 1].unique())
    assert torch.equal(p, torch.ones_like(p))


def test_float32_sums_do_not_overflow():
    # every texel near the float32 maximum: the raw sum overflows, the sampler divides by the max first
    pdf = torch.full((1, 1, 6, 5), 3e38)
    pdf[0, 0, 2, 3] = 1.5e38
    assert torch.isinf(pdf.sum())
    xy, p = icdf_sample(pdf, _rand_u(1, 1 << 13, seed=24, dtype=torch.float32))
    want = pdf.double().flatten(1) / pdf.double().sum()
    assert bool(torch.isfinite(xy).all())
    torch.testing.assert_close(p.double(), torch.gather(want, 1, _texels(xy, 5)), rtol=1e-6, atol=0)
    assert _texel_pvalues(pdf.double(), xy.double())[0] > ALPHA


def test_subnormal_float32_texel_never_loses_to_zeros():
    pdf = torch.zeros(1, 1, 8, 8)
    pdf[0, 0, 5, 2] = 1e-40  # subnormal in float32; also the max, so normalisation lifts it to 1
    pdf2 = pdf.clone()
    pdf2[0, 0, 1, 1] = 1.0  # now it is a subnormal share next to a normal one
    u = _extreme_u(1, 4000, torch.float32)
    xy, p = icdf_sample(pdf, u)
    assert bool((xy.floor() == torch.tensor([2.0, 5.0])).all()) and torch.equal(p, torch.ones_like(p))
    xy2, _ = icdf_sample(pdf2, u)
    assert set(_texels(xy2, 8).unique().tolist()) <= {5 * 8 + 2, 1 * 8 + 1}


@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
def test_extreme_u_never_reaches_an_empty_texel(sampler, dtype):
    g = _gen(15)
    pdf = torch.rand(3, 1, 11, 10, generator=g, dtype=F64)
    pdf[pdf < 0.7] = 0
    pdf[1, 0, ::2] = 0  # whole rows empty
    pdf[2, 0, :, 1::2] = 0  # whole columns empty
    pdf = pdf.to(dtype)
    top = _one_minus(dtype)
    # a grid of u that includes both ends and every CDF boundary of the reference (u = cdf / total)
    grid = torch.cat([torch.linspace(0, 1, 301, dtype=F64)[:-1], torch.tensor([top], dtype=F64)]).to(dtype)
    u = torch.cartesian_prod(grid, grid[::10]).expand(3, -1, -1).contiguous()
    flat = pdf.to(F64).flatten(1)
    bounds = (flat.cumsum(1) / flat.sum(1, keepdim=True)).clamp(max=top).to(dtype)
    u = torch.cat([u, torch.stack([bounds, bounds], -1)], 1)
    xy, p = sampler(pdf, u)
    assert bool((torch.gather(flat, 1, _texels(xy, 10)) > 0).all())
    assert bool((p > 0).all())


@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
def test_all_zero_pdf(sampler):
    pdf = torch.cat([torch.zeros(1, 1, 7, 13, dtype=F64), PDFS["npot7x13"][:1]])
    n = 1 << 14
    u = _rand_u(2, n, seed=16)
    xy, p = sampler(pdf, u)
    assert torch.equal(p[0], torch.zeros(n, dtype=F64)) and bool(torch.isfinite(xy).all())
    assert bool((xy[0] >= 0).all() and (xy[0, :, 0] < 13).all() and (xy[0, :, 1] < 7).all())
    assert _texel_pvalues(pdf[:1], xy[:1])[0] > ALPHA  # uniform over the 7 x 13 texels, not the padding
    xy1, p1 = sampler(pdf[1:], u[1:])
    assert torch.equal(xy1, xy[1:]) and torch.equal(p1, p[1:])  # the empty neighbour changes nothing
    xy0, p0 = sampler(torch.zeros(1, 1, 1, 1), torch.full((1, 3, 2), 0.25))
    assert torch.equal(p0, torch.zeros(1, 3)) and bool((xy0.floor() == 0).all())


def test_one_by_one_map():
    u = _extreme_u(1, 100, F64)
    xy, p = icdf_sample(torch.full((1, 1, 1, 1), 2.5, dtype=F64), u)
    assert torch.equal(xy, u) and torch.equal(p, torch.ones_like(p))  # no level to descend: xy = u
    xy, p = icdf_sample(torch.full((1, 1, 1, 1), 2.5, dtype=F64), u, levels=3)
    assert bool((xy >= 0).all() and (xy < 1).all()) and torch.equal(p, torch.ones_like(p))
    xy, p = icdf_sample_reference(torch.full((1, 1, 1, 1), 2.5, dtype=F64), u)
    torch.testing.assert_close(xy, u, rtol=0, atol=1e-15)
    assert torch.equal(p, torch.ones_like(p))


@pytest.mark.parametrize("shape", [(1, 2048), (2048, 1)], ids=["row", "column"])
def test_float32_position_stays_inside_the_last_texel(shape):
    # 2047 + 0.99999 rounds to 2048 in float32: the point must still be inside texel 2047
    pdf = torch.zeros(1, 1, *shape)
    pdf.view(-1)[-1] = 1.0
    pdf.view(-1)[-2] = 1e-3
    u = _extreme_u(1, 50, torch.float32)
    for sampler in (icdf_sample, icdf_sample_reference):
        xy, _ = sampler(pdf, u)
        assert bool((xy[..., 0] < shape[1]).all() and (xy[..., 1] < shape[0]).all())
        last = (_texels(xy, shape[1]) == 2047)[0]
        assert bool(last[1]) and int(last.sum()) > 40  # u = (top, top) -> the last texel


@pytest.mark.parametrize("sampler", SAMPLERS.values(), ids=SAMPLERS.keys())
def test_empty_sample_or_batch(sampler):
    xy, p = sampler(PDFS["npot7x13"], torch.zeros(2, 0, 2, dtype=F64))
    assert xy.shape == (2, 0, 2) and p.shape == (2, 0)
    xy, p = sampler(torch.zeros(0, 1, 7, 13, dtype=F64), torch.zeros(0, 5, 2, dtype=F64))
    assert xy.shape == (0, 5, 2) and p.shape == (0, 5)


def test_many_samples_small_map():
    # 2^17 samples (2 chunks on the CPU) from a 3 x 2 map: frequencies within chi-square noise of pdf / sum
    pdf = torch.tensor([[[[1.0, 2.0], [0.0, 3.0], [0.5, 0.25]]]], dtype=F64)
    n = 1 << 17
    xy, p = icdf_sample(pdf, _rand_u(1, n, seed=25))
    assert _texel_pvalues(pdf, xy)[0] > ALPHA
    want = torch.tensor([0.25, 0.5, 1.0, 2.0, 3.0], dtype=F64) / 6.75
    torch.testing.assert_close(p[0].unique(), want, rtol=1e-15, atol=0)


# -- sum pyramid ------------------------------------------------------------------------------------------------
def _loop_pyramid(pdf, levels):
    """Level l, texel (i, j) = sum of pdf over rows [2^l i, 2^l (i+1)) x cols [2^l j, 2^l (j+1)), by loops."""
    b, _, h, w = pdf.shape
    out = []
    for level in range(levels + 1):
        s, k = 2 ** (levels - level), 2**level
        lvl = torch.zeros(b, 1, s, s, dtype=F64)
        for i in range(s):
            for j in range(s):
                lvl[:, 0, i, j] = pdf[:, 0, k * i : min(h, k * (i + 1)), k * j : min(w, k * (j + 1))].sum((-1, -2))
        out.append(lvl)
    return out


@pytest.mark.parametrize(("h", "w", "levels"), [(1, 1, None), (1, 1, 2), (7, 13, None), (16, 16, None), (5, 1, 4)])
def test_sum_pyramid_matches_loops(h, w, levels):
    pdf = torch.rand(2, 1, h, w, generator=_gen(17), dtype=F64)
    pyr = sum_pyramid(pdf, levels)
    want = _loop_pyramid(pdf, pyramid_levels(h, w) if levels is None else levels)
    assert len(pyr) == len(want)
    for got, ref in zip(pyr, want):
        torch.testing.assert_close(got, ref, rtol=1e-14, atol=0)
    assert torch.equal(pyr[0][..., :h, :w], pdf)


def test_sum_pyramid_float32_accuracy():
    # pairwise sums: the float32 total of a 1000^2 map of widely spread values is within a few ulps
    big = torch.rand(1, 1, 1000, 1000, generator=_gen(18), dtype=F64) ** 8
    assert abs(float(sum_pyramid(big.float())[-1]) / float(big.sum()) - 1) < 2e-6


def test_sum_pyramid_dtypes_and_gradcheck():
    assert sum_pyramid(torch.rand(1, 1, 3, 3, dtype=torch.float16))[-1].dtype == torch.float16
    sizes = [(1, 1), (2, 1), (3, 3), (4, 4), (5, 4), (1024, 1000)]
    assert [pyramid_levels(h, w) for h, w in sizes] == [0, 1, 2, 2, 3, 10]
    pdf = torch.rand(2, 1, 3, 5, generator=_gen(19), dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: tuple(sum_pyramid(x)), (pdf,))


# -- gradients --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sampler", [icdf_sample, icdf_sample_reference], ids=["descent", "reference"])
def test_gradcheck(sampler):
    pdf = (torch.rand(2, 1, 3, 5, generator=_gen(20), dtype=F64) + 0.1).requires_grad_()
    u = _rand_u(2, 6, seed=21).requires_grad_()
    assert torch.autograd.gradcheck(sampler, (pdf, u))
    # d p / d pdf in closed form: p = pdf_t / S -> dp/dpdf_k = (delta_tk - p) / S
    xy, p = sampler(pdf, u)
    (grad,) = torch.autograd.grad(p[0, 0], pdf)
    s = float(pdf[0].detach().sum())
    want = torch.full((3, 5), -float(p[0, 0].detach()) / s, dtype=F64)
    t = xy[0, 0].detach().floor().long()
    want[t[1], t[0]] += 1 / s
    torch.testing.assert_close(grad[0, 0], want, rtol=1e-10, atol=1e-12)
    assert torch.equal(grad[1], torch.zeros_like(grad[1]))


# -- errors -----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "fn", [icdf_sample, icdf_sample_reference, sum_pyramid], ids=["descent", "reference", "pyramid"]
)
def test_bad_pdf(fn):
    u = torch.rand(1, 4, 2)
    call = (lambda pdf: fn(pdf)) if fn is sum_pyramid else (lambda pdf: fn(pdf, u[: pdf.shape[0]]))
    with pytest.raises(TypeError, match=r"pdf: expected a torch.Tensor, got ndarray"):
        call(np.ones((1, 1, 2, 2)))
    with pytest.raises(TypeError, match=r"pdf: expected a floating-point tensor, got dtype torch.int64"):
        call(torch.ones(1, 1, 2, 2, dtype=torch.long))
    with pytest.raises(ValueError, match=r"pdf: expected shape \(B, 1, H, W\), got \(1, 2, 2\)"):
        call(torch.ones(1, 2, 2))
    with pytest.raises(ValueError, match=r"pdf: expected shape \(B, 1, H, W\), got \(1, 3, 2, 2\)"):
        call(torch.ones(1, 3, 2, 2))
    with pytest.raises(ValueError, match=r"pdf: expected H >= 1 and W >= 1, got shape \(1, 1, 0, 3\)"):
        call(torch.ones(1, 1, 0, 3))
    for bad, shown in [(-1.0, "-1.0"), (float("nan"), "nan"), (float("inf"), "inf")]:
        pdf = torch.ones(1, 1, 2, 3)
        pdf[0, 0, 1, 2] = bad
        with pytest.raises(ValueError, match=rf"pdf: expected finite values >= 0, got {shown} \(1 of 6"):
            call(pdf)


@pytest.mark.parametrize("fn", [icdf_sample, icdf_sample_reference], ids=["descent", "reference"])
def test_bad_u(fn):
    pdf = torch.ones(2, 1, 3, 3)
    with pytest.raises(TypeError, match=r"u: expected a torch.Tensor, got list"):
        fn(pdf, [[0.5, 0.5]])
    with pytest.raises(TypeError, match=r"u: expected a floating-point tensor, got dtype torch.int64"):
        fn(pdf, torch.zeros(2, 4, 2, dtype=torch.long))
    with pytest.raises(ValueError, match=r"u: expected shape \(B, N, 2\), got \(2, 4, 3\)"):
        fn(pdf, torch.rand(2, 4, 3))
    with pytest.raises(ValueError, match=r"u: expected shape \(B, N, 2\), got \(4, 2\)"):
        fn(pdf, torch.rand(4, 2))
    with pytest.raises(ValueError, match=r"u: expected shape \(B, N, 2\) with B=2 \(pdf's batch\), got \(1, 4, 2\)"):
        fn(pdf, torch.rand(1, 4, 2))
    for bad, shown in [(1.0, "1.0"), (-1e-9, "-1e-09"), (float("nan"), "nan"), (2.0, "2.0")]:
        u = torch.rand(2, 4, 2, dtype=F64) * 0.5
        u[1, 2, 0] = bad
        with pytest.raises(ValueError, match=rf"u: expected values in \[0, 1\), got {shown} \(1 of 16"):
            fn(pdf, u)


@pytest.mark.parametrize("fn", [icdf_sample, sum_pyramid], ids=["descent", "pyramid"])
def test_bad_levels(fn):
    pdf = torch.ones(1, 1, 7, 13)
    call = (lambda lv: fn(pdf, lv)) if fn is sum_pyramid else (lambda lv: fn(pdf, torch.rand(1, 3, 2), lv))
    with pytest.raises(ValueError, match=r"levels: expected 2\*\*levels >= max\(H, W\) = 13, got levels=3 \(8 x 8\)"):
        call(3)
    with pytest.raises(ValueError, match=rf"levels: expected an int in \[0, {MAX_LEVELS}\], got 16"):
        call(16)
    with pytest.raises(ValueError, match=rf"levels: expected an int in \[0, {MAX_LEVELS}\], got -1"):
        call(-1)
    with pytest.raises(TypeError, match=r"levels: expected an int or None, got float"):
        call(4.0)
    with pytest.raises(TypeError, match=r"levels: expected an int or None, got bool"):
        call(True)
    assert len(sum_pyramid(pdf, 4)) == 5 and call(4) is not None


# -- ONNX -------------------------------------------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning")
@pytest.mark.filterwarnings("ignore:# The axis name:UserWarning")
def test_onnx_export_dynamic_sizes(registry_export):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    from torchsss.export import compare_with_eager, run_onnxruntime

    # the registry's sampler (6 levels, exported at B 2, N 100, 40 x 50; tests/test_export_onnx.py checks it at
    # its own test shapes), here at extreme inputs
    case, path, _ = registry_export("icdf_sampler")
    module = case.module
    assert module.levels == 6 and [a.shape for a in case.example_args] == [(2, 1, 40, 50), (2, 100, 2)]

    # other batch, sample count and map size than exported; an empty map, a delta, a map with holes, extreme u
    g = _gen(22)
    pdf = torch.rand(4, 1, 17, 63, generator=g) ** 4
    pdf[1] = 0
    pdf[2] = 0
    pdf[2, 0, 16, 62] = 5.0
    pdf[3, 0, 3:, 10:40] = 0
    u = _extreme_u(4, 3000, torch.float32, seed=23)
    res = compare_with_eager(module, path, (pdf, u))
    assert res["shapes"] == [(4, 3005, 2), (4, 3005)]
    assert res["max_abs_diff"] == 0.0, res  # bit for bit: same sums in the same order
    xy, p = run_onnxruntime(path, (pdf, u))
    flat = pdf.double().flatten(1)
    texel = torch.from_numpy(np.floor(xy).astype(np.int64))
    want = torch.gather(flat, 1, texel[..., 1] * 63 + texel[..., 0]) / flat.sum(1, keepdim=True).clamp(min=1e-300)
    np.testing.assert_allclose(p, want.numpy(), rtol=1e-5, atol=0)
    assert (np.floor(xy[2]) == [62, 16]).all()
    assert (p[1] == 0).all() and np.isfinite(xy).all()
    assert (xy >= 0).all() and (xy[..., 0] < 63).all() and (xy[..., 1] < 17).all()
