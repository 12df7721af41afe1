"""Property-based suite (hypothesis) over the public ops and modules: extremes, dtypes and NaN at the boundaries.

Three classes of behaviour are asserted, each on random shapes, dtypes and values:

- **finite valid input -> finite output and gradients.** Values include 0, subnormals, 1e-30, 1e30 (intensities,
  irradiance, flux, coefficients, distances; positions stay at object scale, since a 1e30 mm object cannot be in
  any camera's view) and r = inf for the profiles. In float16/bfloat16 the output must never be NaN and must be
  finite wherever the float64 value fits the dtype; every output is compared with the float64 computation.
- **NaN or inf input to a validated module -> a typed error** (ValueError naming the input and the index of the
  first bad entry), never a silent finite result.
- **low-level ops propagate NaN by design** (as torch does): NaN in, NaN out, never a plausible finite value.

The example counts are bounded (``max_examples``) and derandomized, so the suite is deterministic and stays
within a few tens of seconds of the default test run.
"""

from __future__ import annotations

import math
import re

import pytest
import torch
from conftest import caustic_plane_inputs
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from torchsss import BurleyMaterial, DipoleMaterial, TabulatedMaterial, burley_rd, dipole_rd, validation
from torchsss.geometry import build_atlas, sphere
from torchsss.modules import SplatTranslucency
from torchsss.modules.caustics import CausticMap
from torchsss.modules.chang import HybridTranslucency, ImportanceSampledTranslucency
from torchsss.modules.lensch import IrradianceAtlas
from torchsss.modules.sampling import IcdfSampler
from torchsss.ops import reference_radiosity, sparse_apply_t, sparse_pattern, sv_conv2d
from torchsss.ops.reference import pairwise_distance
from torchsss.ops.refraction import reflect, refract
from torchsss.pipelines import build

FLOATS = (torch.float32, torch.float64)
ALL_FLOATS = (torch.float32, torch.float64, torch.float16, torch.bfloat16)
SETTINGS = settings(max_examples=25, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FEW = settings(max_examples=12, deadline=None, derandomize=True,
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

#: Magnitudes a value may take: 0, a subnormal (scaled to the dtype), tiny, ordinary and huge.
SPECIAL = ("zero", "subnormal", "1e-30", "1e-6", "one", "1e3", "1e30")


def _special(kind: str, dtype: torch.dtype) -> float:
    if kind == "subnormal":
        return torch.finfo(dtype).tiny / 4.0
    return {"zero": 0.0, "1e-30": 1e-30, "1e-6": 1e-6, "one": 1.0, "1e3": 1e3, "1e30": 1e30}[kind]


@st.composite
def extreme_values(draw, shape, dtype, *, kinds=SPECIAL, low=0.0):
    """A tensor of ``shape``: uniform in [low, scale) with some entries set to special magnitudes."""
    seed = draw(st.integers(0, 2**31 - 1))
    scale = _special(draw(st.sampled_from([k for k in kinds if k != "zero"] or ["one"])), torch.float64)
    g = torch.Generator().manual_seed(seed)
    x = low + torch.rand(shape, generator=g, dtype=torch.float64) * scale
    n = x.numel()
    for kind in draw(st.lists(st.sampled_from(kinds), max_size=3 if n else 0)):
        x.view(-1)[int(torch.randint(n, (1,), generator=g))] = _special(kind, dtype)
    out = x.to(dtype)
    assume(bool(torch.isfinite(out).all()))  # 1e30 does not fit float16: not a finite input there
    return out


def _assert_like_float64(out: torch.Tensor, ref: torch.Tensor, what: str) -> None:
    """No NaN; finite and close to the float64 value wherever that fits the dtype (inf only where it does not)."""
    assert not bool(torch.isnan(out).any()), f"{what}: NaN for valid input"
    big = torch.finfo(out.dtype).max / 4
    fits = ref.abs() < big
    assert bool(torch.isfinite(out[fits]).all()), f"{what}: non-finite where the float64 value fits {out.dtype}"
    rtol = {torch.float64: 1e-9, torch.float32: 2e-3}.get(out.dtype, 3e-2)
    atol = 1e3 * torch.finfo(out.dtype).tiny if out.dtype in FLOATS else 4 * torch.finfo(out.dtype).tiny
    o, r = out.double()[fits], ref[fits]
    assert torch.allclose(o, r, rtol=rtol, atol=atol), (
        f"{what}: max relative deviation from float64 {float(((o - r).abs() / (r.abs() + atol)).max().detach()):.3g}")


def _assert_error_names(err: pytest.ExceptionInfo, name: str, index: tuple[int, ...]) -> None:
    msg = str(err.value)
    assert msg.startswith(f"{name}: expected finite"), msg
    got = re.search(r"the first at index \(([\d, ]+)\)", msg)
    assert got is not None, msg
    assert tuple(int(i) for i in got.group(1).split(",") if i.strip()) == index, msg


def _poison(x: torch.Tensor, data, bad: float) -> tuple[torch.Tensor, tuple[int, ...]]:
    """A copy of ``x`` with one entry (drawn) set to ``bad``; returns it and the entry's index."""
    flat = data.draw(st.integers(0, x.numel() - 1), label="bad entry")
    index = tuple(int(i) for i in torch.unravel_index(torch.tensor(flat), tuple(x.shape)))
    y = x.detach().clone()
    y[index] = bad
    return y, index


# -- profiles: finite in, finite out (values and gradients), any dtype ----------------------------------------------
@SETTINGS
@given(data=st.data(), dtype=st.sampled_from(ALL_FLOATS), n=st.integers(1, 6))
def test_dipole_rd_finite_for_valid_extremes(data, dtype, n):
    r = data.draw(extreme_values((n, 1), dtype), label="r")
    if data.draw(st.booleans(), label="an infinite r"):
        r[0, 0] = math.inf
    sa = data.draw(extreme_values((3,), dtype), label="sigma_a")
    ss = data.draw(extreme_values((3,), dtype, kinds=("1e-6", "one", "1e3", "1e30")), label="sigma_s_prime")
    assume(bool((sa.double() + ss.double() > 0).all()))
    eta = torch.tensor(data.draw(st.floats(0.7, 2.5), label="eta"), dtype=dtype)
    leaves = [t.clone().requires_grad_(True) for t in (r, sa, ss, eta)]
    out = dipole_rd(*leaves)
    assert out.dtype == dtype and out.shape == (n, 3)
    _assert_like_float64(out.detach(), dipole_rd(*(t.double() for t in (r, sa, ss, eta))), "dipole_rd")
    value = out.detach()
    out.sum().backward()
    # where the true value overflows the dtype (e.g. R_d(0) ~ sigma_t'^2 for sigma_s' = 1e30 in float32) the output
    # is inf and no gradient is defined; everywhere else the gradients are NaN-free, and finite in float32/64
    if bool(torch.isfinite(value).all()):
        for name, leaf in zip(("r", "sigma_a", "sigma_s_prime", "eta"), leaves):
            assert not bool(torch.isnan(leaf.grad).any()), f"d/d{name}: NaN"
            if dtype in FLOATS and float(value.abs().max()) < 1e30:
                assert bool(torch.isfinite(leaf.grad).all()), f"d/d{name}: not finite"


@SETTINGS
@given(data=st.data(), dtype=st.sampled_from(ALL_FLOATS), n=st.integers(1, 6))
def test_burley_rd_finite_for_valid_extremes(data, dtype, n):
    r = data.draw(extreme_values((n, 1), dtype), label="r")
    if data.draw(st.booleans(), label="an infinite r"):
        r[-1, 0] = math.inf
    albedo = data.draw(extreme_values((3,), dtype, kinds=("zero", "subnormal", "1e-6", "one")), label="albedo")
    albedo = albedo.clamp(max=1.0)
    s = data.draw(extreme_values((3,), dtype, kinds=("1e-6", "one", "1e3")), label="s")
    assume(bool((s > 0).all()))
    leaves = [t.clone().requires_grad_(True) for t in (r, albedo, s)]
    out = burley_rd(*leaves)
    _assert_like_float64(out.detach(), burley_rd(*(t.double() for t in (r, albedo, s))), "burley_rd")
    value = out.detach()
    out.sum().backward()
    if bool(torch.isfinite(value).all()):
        for name, leaf in zip(("r", "albedo", "s"), leaves):
            assert not bool(torch.isnan(leaf.grad).any()), f"d/d{name}: NaN"


_MATERIALS = {}


def _material(kind: str, dtype: torch.dtype):
    key = (kind, dtype)
    if key not in _MATERIALS:
        if kind == "dipole":
            m = DipoleMaterial.from_preset("skin1", dtype=dtype)
        elif kind == "burley":
            m = BurleyMaterial.from_preset("skin1", dtype=dtype)
        else:
            m = TabulatedMaterial(DipoleMaterial.from_preset("skin1", dtype=dtype), size=256)
        _MATERIALS[key] = m
    return _MATERIALS[key]


@SETTINGS
@given(data=st.data(), kind=st.sampled_from(["dipole", "burley", "tabulated"]), dtype=st.sampled_from(FLOATS),
       n=st.integers(1, 8))
def test_material_modules_finite_values_and_gradients(data, kind, dtype, n):
    material = _material(kind, dtype)
    r = data.draw(extreme_values((n, 1), dtype), label="r")
    if data.draw(st.booleans(), label="an infinite r"):
        r[0, 0] = math.inf
    r.requires_grad_(True)
    material.zero_grad()
    out = material(r)
    assert out.shape == (n, 3) and bool(torch.isfinite(out).all()) and bool((out >= 0).all())
    out.sum().backward()
    assert bool(torch.isfinite(r.grad).all())
    for name, p in material.named_parameters():
        assert p.grad is None or bool(torch.isfinite(p.grad).all()), f"{kind}.{name}: non-finite gradient"


@FEW
@given(data=st.data(), kind=st.sampled_from(["dipole", "burley"]))
def test_material_modules_name_a_nan_distance(data, kind):
    """A NaN distance is named (typed error); with validation off it stays NaN in its own row, never plausible."""
    material = _material(kind, torch.float32)
    r = data.draw(extreme_values((5, 1), torch.float32, kinds=("zero", "one", "1e3")), label="r")
    bad, index = _poison(r, data, math.nan)
    with pytest.raises(ValueError) as err:
        material(bad)
    assert str(err.value).startswith("r: expected") and f"index {index}" in str(err.value)
    with validation(False):
        out = material(bad)
    assert bool(torch.isnan(out[index[0]]).all())
    keep = torch.ones(5, dtype=torch.bool)
    keep[index[0]] = False
    assert bool(torch.isfinite(out[keep]).all())


# -- low-level ops: NaN propagates by design ------------------------------------------------------------------------
@FEW
@given(data=st.data(), m=st.integers(1, 5), n=st.integers(1, 5))
def test_pairwise_distance_propagates_nan(data, m, n):
    a = data.draw(extreme_values((1, m, 3), torch.float64, kinds=("zero", "one", "1e3")), label="a")
    b = data.draw(extreme_values((1, n, 3), torch.float64, kinds=("zero", "one", "1e3")), label="b")
    bad, index = _poison(a, data, math.nan)
    d = pairwise_distance(bad, b)
    assert bool(torch.isnan(d[0, index[1]]).all())
    assert bool(torch.isfinite(pairwise_distance(a, b)).all())


@SETTINGS
@given(data=st.data(), dtype=st.sampled_from(ALL_FLOATS), h=st.integers(1, 9), w=st.integers(1, 9),
       k=st.sampled_from([1, 3, 5]))
def test_sv_conv2d_finite_and_nan_propagating(data, dtype, h, w, k):
    image = data.draw(extreme_values((1, 2, h, w), dtype), label="image")
    kern = data.draw(extreme_values((h, w, k, k), dtype, kinds=("zero", "subnormal", "1e-6", "one")), label="kernels")
    out = sv_conv2d(image, kern)
    ref = sv_conv2d(image.double(), kern.double())
    _assert_like_float64(out, ref, "sv_conv2d")
    if dtype in FLOATS:
        x = image.clone().requires_grad_(True)
        kk = kern.clone().requires_grad_(True)
        sv_conv2d(x, kk).sum().backward()
        assert bool(torch.isfinite(x.grad).all()) and bool(torch.isfinite(kk.grad).all())
    bad, index = _poison(image, data, math.nan)
    assert bool(torch.isnan(sv_conv2d(bad, torch.ones_like(kern))[0, index[1], index[2], index[3]]))


@SETTINGS
@given(data=st.data(), dtype=st.sampled_from(ALL_FLOATS), n_rows=st.integers(1, 8), n_cols=st.integers(1, 8),
       nnz=st.integers(0, 20))
def test_sparse_apply_t_finite_and_nan_propagating(data, dtype, n_rows, n_cols, nnz):
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1), label="pattern seed"))
    rows = torch.randint(n_rows, (nnz,), generator=g)
    cols = torch.randint(n_cols, (nnz,), generator=g)
    pattern = sparse_pattern(rows, cols, n_rows, n_cols)
    x = data.draw(extreme_values((n_rows, 3), dtype), label="x")
    values = data.draw(extreme_values((nnz,), dtype, kinds=("zero", "subnormal", "1e-6", "one")), label="values")
    out = sparse_apply_t(x, pattern, values)
    _assert_like_float64(out, sparse_apply_t(x.double(), pattern, values.double()), "sparse_apply_t")
    bad, index = _poison(x, data, math.nan)
    hit = cols[rows == index[0]]
    out = sparse_apply_t(bad, pattern, torch.ones_like(values))
    assert bool(torch.isnan(out[hit, index[1]]).all())


@SETTINGS
@given(data=st.data(), dtype=st.sampled_from(FLOATS),
       scale_i=st.sampled_from([1e-30, 1e-6, 1.0, 1e30]), scale_n=st.sampled_from([1e-30, 1.0, 1e30]),
       eta=st.floats(0.5, 2.0))
def test_refract_and_reflect_any_length(data, dtype, scale_i, scale_n, eta):
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1)))
    i = torch.nn.functional.normalize(torch.randn(16, 3, generator=g, dtype=torch.float64), dim=-1)
    n = torch.nn.functional.normalize(torch.randn(16, 3, generator=g, dtype=torch.float64), dim=-1)
    t_unit, tir_unit = refract(i, n, eta)
    t, tir = refract((i * scale_i).to(dtype), (n * scale_n).to(dtype), eta)
    assert torch.equal(tir, tir_unit) or int((tir != tir_unit).sum()) <= 1  # one ray may sit at the critical angle
    same = tir == tir_unit
    assert torch.allclose(t[same].double(), t_unit[same], atol=1e-5)
    r = reflect((i * scale_i).to(dtype), (n * scale_n).to(dtype))
    assert torch.allclose(r.double(), reflect(i, n), atol=1e-5)


@FEW
@given(data=st.data(), dtype=st.sampled_from(ALL_FLOATS), h=st.integers(1, 12), w=st.integers(1, 12),
       n=st.integers(1, 40))
def test_icdf_sampler_valid_extremes_and_nan(data, dtype, h, w, n):
    sampler = IcdfSampler(size=(h, w))
    pdf = data.draw(extreme_values((1, 1, h, w), dtype), label="pdf")
    u = data.draw(extreme_values((1, n, 2), torch.float64, kinds=("zero", "subnormal", "one")), label="u")
    u = u.to(dtype if dtype in FLOATS else torch.float32)
    u = u.clamp(max=float(torch.nextafter(torch.tensor(1.0, dtype=u.dtype), torch.tensor(0.0, dtype=u.dtype))))
    xy, p = sampler(pdf, u)
    assert bool(torch.isfinite(xy).all()) and bool(torch.isfinite(p).all()) and bool((p >= 0).all())
    assert bool((xy[..., 0] >= 0).all() and (xy[..., 0] <= w).all() and (xy[..., 1] >= 0).all()
                and (xy[..., 1] <= h).all())
    for name, bad_value in (("pdf", math.nan), ("pdf", math.inf), ("u", math.nan)):
        x = pdf if name == "pdf" else u
        bad, _ = _poison(x, data, bad_value)
        with pytest.raises(ValueError, match=rf"^{name}: expected"):
            sampler(bad, u) if name == "pdf" else sampler(pdf, bad)


# -- validated modules: finite in -> finite out and gradients; NaN/inf in -> ValueError naming input and index -----
@pytest.fixture(scope="module")
def atlas():
    return build_atlas(sphere(10.0, 2), 32, kernel_size=3)


@pytest.fixture(scope="module")
def chang_modules(atlas):
    mat = DipoleMaterial.from_preset("skin1")
    return {"icdf": ImportanceSampledTranslucency.from_atlas(atlas, mat),
            "hybrid": HybridTranslucency.from_atlas(atlas, mat),
            "irradiance_atlas": IrradianceAtlas.from_atlas(atlas, mat)}


@pytest.fixture(scope="module")
def lensch_module():
    return build("lensch", sphere(8.0, 2), "skin1", atlas_resolution=64, blend=False).module


def _receivers(atlas, m: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    valid = atlas.valid_mask[0, 0].nonzero()
    g = torch.Generator().manual_seed(seed)
    pick = valid[torch.randint(valid.shape[0], (m,), generator=g)]
    pos = atlas.position[0, :, pick[:, 0], pick[:, 1]].T[None].contiguous()
    uv = torch.stack([(pick[:, 1] + 0.5) / 32, (pick[:, 0] + 0.5) / 32], -1)[None].float()
    return pos, uv


@SETTINGS
@given(data=st.data(), method=st.sampled_from(["icdf", "hybrid"]), m=st.integers(1, 4), n=st.integers(1, 64))
def test_chang_modules_finite_valid_extremes_and_named_nan(chang_modules, atlas, data, method, m, n):
    module = chang_modules[method]
    e = data.draw(extreme_values((1, 3, 32, 32), torch.float32), label="irradiance") * atlas.valid_mask
    u = data.draw(extreme_values((1, n, 2), torch.float32, kinds=("zero", "one")), label="u").clamp(max=0.999)
    rec, uv = _receivers(atlas, m, data.draw(st.integers(0, 1000), label="receiver seed"))
    x = e.clone().requires_grad_(True)
    args = (x, u, rec) if method == "icdf" else (x, u, rec, uv)
    out = module(*args)
    assert out.shape == (1, m, 3) and bool(torch.isfinite(out).all()) and bool((out >= 0).all())
    out.sum().backward()
    assert bool(torch.isfinite(x.grad).all())
    names = ["irradiance", "receivers"] + (["receivers_uv"] if method == "hybrid" else [])
    name = data.draw(st.sampled_from(names), label="poisoned input")
    bad_value = data.draw(st.sampled_from([math.nan, math.inf, -math.inf]), label="bad value")
    clean = {"irradiance": e, "receivers": rec, "receivers_uv": uv}
    bad, index = _poison(clean[name], data, bad_value)
    clean[name] = bad
    call = (clean["irradiance"], u, clean["receivers"]) + (() if method == "icdf" else (clean["receivers_uv"],))
    with pytest.raises(ValueError) as err:
        module(*call)
    if name == "irradiance":  # irradiance is also checked for sign: the message says "finite values >= 0"
        assert str(err.value).startswith("irradiance: expected finite values") and "first at index" in str(err.value)
    else:
        _assert_error_names(err, name, index)


@SETTINGS
@given(data=st.data(), b=st.integers(1, 2))
def test_lensch_and_irradiance_atlas_finite_extremes_and_named_nan(lensch_module, chang_modules, data, b):
    irr_module = chang_modules["irradiance_atlas"]
    light = torch.tensor([[0.0, 0.0, 100.0, 1.0], [0.0, 1.0, 0.0, 0.0]])[:b]
    intensity = data.draw(extreme_values((b, 3), torch.float32), label="intensity")
    atlas_e = irr_module(light, intensity)
    assert bool(torch.isfinite(atlas_e).all()) and bool((atlas_e >= 0).all())
    e = data.draw(extreme_values((b, 3, 64, 64), torch.float32), label="irradiance").requires_grad_(True)
    out = lensch_module(e)
    assert bool(torch.isfinite(out).all())
    out.sum().backward()
    assert bool(torch.isfinite(e.grad).all())
    bad_value = data.draw(st.sampled_from([math.nan, math.inf]), label="bad value")
    bad, index = _poison(e, data, bad_value)
    with pytest.raises(ValueError) as err:
        lensch_module(bad)
    _assert_error_names(err, "irradiance", index)
    which = data.draw(st.sampled_from(["light", "intensity"]), label="poisoned input")
    bad, index = _poison(light if which == "light" else intensity, data, bad_value)
    with pytest.raises(ValueError) as err:
        irr_module(bad, intensity) if which == "light" else irr_module(light, bad)
    _assert_error_names(err, which, index)


def _plane(h: int, w: int, dtype: torch.dtype):
    ys, xs = torch.meshgrid(torch.linspace(-3.5, 3.5, h, dtype=dtype), torch.linspace(-3.5, 3.5, w, dtype=dtype),
                            indexing="ij")
    dst = torch.stack([xs, -ys, torch.zeros_like(xs)])[None]
    vp = torch.diag(torch.tensor([0.25, 0.25, 1.0, 1.0], dtype=dtype))
    return dst, torch.ones(1, 1, h, w, dtype=torch.bool), vp


@SETTINGS
@given(data=st.data(), dtype=st.sampled_from(ALL_FLOATS), s=st.integers(1, 12), h=st.integers(1, 8))
def test_splat_finite_extremes_and_named_nan(data, dtype, s, h):
    work = dtype if dtype in FLOATS else torch.float32  # a float32 module computes reduced-precision inputs
    module = SplatTranslucency(_material("dipole", work), eps=0.01)
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1), label="positions"))
    src = torch.cat([torch.rand(1, s, 2, generator=g) * 8 - 4, torch.zeros(1, s, 1)], -1).to(dtype)
    flux = data.draw(extreme_values((1, s, 3), dtype), label="src_flux")
    dst, mask, vp = _plane(h, h, dtype)
    out = module(src, flux, dst, mask, vp)
    assert out.dtype == work  # the promotion of the inputs and the module's float32 buffers
    ref = SplatTranslucency(_material("dipole", torch.float64), eps=0.01)(src.double(), flux.double(),
                                                                            dst.double(), mask, vp.double())
    _assert_like_float64(out, ref, "SplatTranslucency")
    if dtype in FLOATS:
        f = flux.clone().requires_grad_(True)
        module(src, f, dst, mask, vp).sum().backward()
        assert bool(torch.isfinite(f.grad).all())
    name = data.draw(st.sampled_from(["src_pos", "src_flux", "dst_pos"]), label="poisoned input")
    clean = {"src_pos": src, "src_flux": flux, "dst_pos": dst}
    bad, index = _poison(clean[name], data, data.draw(st.sampled_from([math.nan, math.inf])))
    clean[name] = bad
    with pytest.raises(ValueError) as err:
        module(clean["src_pos"], clean["src_flux"], clean["dst_pos"], mask, vp)
    _assert_error_names(err, name, index)
    off = mask.clone()
    if name == "dst_pos":  # off the mask, a position may hold anything: not checked, not used
        off[0, 0, index[2], index[3]] = False
        out = module(src, flux, bad, off, vp)
        assert bool(torch.isfinite(out).all()) and float(out[0, :, index[2], index[3]].abs().max()) == 0.0


@SETTINGS
@given(data=st.data(), dtype=st.sampled_from(ALL_FLOATS), n=st.integers(1, 8), m=st.integers(1, 6))
def test_reference_radiosity_finite_extremes_and_named_nan(data, dtype, n, m):
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1), label="positions"))
    src = (torch.rand(1, n, 3, generator=g) * 10).to(dtype)
    dst = (torch.rand(1, m, 3, generator=g) * 10).to(dtype)
    e = data.draw(extreme_values((1, n, 3), dtype), label="src_irradiance")
    area = data.draw(extreme_values((1, n, 1), dtype, kinds=("zero", "subnormal", "1e-6", "one")), label="area")
    material = _material("dipole", dtype if dtype in FLOATS else torch.float32)
    out = reference_radiosity(src, e, area, dst, material)
    ref = reference_radiosity(src.double(), e.double(), area.double(), dst.double(), _material("dipole", torch.float64))
    _assert_like_float64(out, ref, "reference_radiosity")
    name = data.draw(st.sampled_from(["src_pos", "src_irradiance", "dst_pos"]), label="poisoned input")
    clean = {"src_pos": src, "src_irradiance": e, "dst_pos": dst}
    bad, index = _poison(clean[name], data, data.draw(st.sampled_from([math.nan, math.inf])))
    clean[name] = bad
    with pytest.raises(ValueError) as err:
        reference_radiosity(clean["src_pos"], clean["src_irradiance"], area, clean["dst_pos"], material)
    _assert_error_names(err, name, index)


@FEW
@given(data=st.data())
def test_caustic_map_finite_extremes_and_named_nan(data):
    module = CausticMap(1.33, mode="single", iterations=2)
    inputs = caustic_plane_inputs()
    inputs["intensity"] = data.draw(extreme_values((1, 1), torch.float64), label="intensity")
    out = module(**inputs)
    assert bool(torch.isfinite(out).all()) and bool((out >= 0).all())
    name = data.draw(st.sampled_from(["intensity", "front_position", "front_normal"]), label="poisoned input")
    bad, index = _poison(inputs[name], data, data.draw(st.sampled_from([math.nan, math.inf])))
    with pytest.raises(ValueError) as err:
        module(**{**inputs, name: bad})
    _assert_error_names(err, name, index)


def test_validation_off_skips_the_checks_and_restores_them(chang_modules, atlas):
    """With validation off the module runs on (NaN in, NaN out: the caller chose speed); the setting is restored."""
    module = chang_modules["irradiance_atlas"]
    light = torch.tensor([[0.0, 0.0, 100.0, 1.0]])
    bad = torch.tensor([[math.nan, 1.0, 1.0]])
    with validation(False):
        out = module(light, bad)
    assert bool(torch.isnan(out[:, 0][atlas.valid_mask[:, 0] > 0]).any())
    with pytest.raises(ValueError, match=r"^intensity: expected finite values"):
        module(light, bad)
