"""Regression tests of the reliability defects found in the ops by an independent test battery.

1. ``pairwise_distance`` turned NaN distances into 0 (``reference_radiosity`` put a NaN source on every receiver);
   ``reference_radiosity`` now rejects non-finite inputs, naming the input and the first bad index.
2. ``refract`` / ``reflect`` normalised with ``sum(v * v)``, which underflows (1e-30) or overflows (1e30).
3. ``newton_raphson_intersect`` likewise for the ray directions.
4. ``CausticMap`` returned an all-zero map for a NaN ``intensity``.
5. Meta tensors reached ``.item()``, mixed devices and complex dtypes failed inside torch; ``check_devices`` now
   runs first in the ops and names the offending argument and both devices.
"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import caustic_plane_inputs

import torchsss._checks as checks
from torchsss._checks import check_devices, check_finite, check_nonnegative, check_positive, check_tensor
from torchsss.modules.caustics import CausticMap
from torchsss.ops.icdf import icdf_sample, icdf_sample_reference, sum_pyramid
from torchsss.ops.newton_raphson import newton_raphson_intersect
from torchsss.ops.reference import pairwise_distance, reference_radiosity
from torchsss.ops.refraction import reflect, refract
from torchsss.ops.sparse import sparse_apply_t, sparse_pattern
from torchsss.ops.splat import splat_radiosity
from torchsss.ops.sv_conv import sv_conv2d, sv_conv2d_reference

NAN = float("nan")
INF = float("inf")
META = torch.device("meta")
# a second device to mix with the CPU: meta always, CUDA where there is one
OTHER = [pytest.param("meta", id="meta"),
         pytest.param("cuda", id="cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]


def _exp_profile(r: torch.Tensor) -> torch.Tensor:
    """A device-agnostic profile (closes over no tensor): exp(-r) mm^-2, one channel."""
    return torch.exp(-r)


@pytest.fixture
def tracing(monkeypatch):
    """Pretend a graph is being traced: value checks must be skipped."""
    monkeypatch.setattr(checks, "is_tracing", lambda: True)


# -- 1. pairwise_distance / reference_radiosity --------------------------------------------------------------------
def test_pairwise_distance_nan_in_nan_out():
    a = torch.tensor([[[0.0, 0.0, 0.0], [NAN, 0.0, 0.0], [1.0, 2.0, 2.0]]])
    b = torch.tensor([[[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, NAN, 1.0]]])
    d = pairwise_distance(a, b)[0, :, :, 0]
    assert d.shape == (3, 3)
    assert torch.isnan(d[1]).all()  # NaN row
    assert torch.isnan(d[:, 2]).all()  # NaN column
    assert d[0, 0].item() == 5.0 and d[0, 1].item() == 0.0 and d[2, 1].item() == 3.0
    # infinite on both sides: inf - inf is NaN, never 0
    inf_d = pairwise_distance(torch.tensor([[[INF, 0.0, 0.0]]]), torch.tensor([[[INF, 0.0, 0.0]]]))
    assert torch.isnan(inf_d).all()
    assert pairwise_distance(torch.tensor([[[INF, 0.0, 0.0]]]), torch.zeros(1, 1, 3)).item() == INF


def test_pairwise_distance_keeps_zero_gradient_at_coincident_points():
    a = torch.tensor([[[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]]], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([[[1.0, 2.0, 3.0]]], dtype=torch.float64)
    d = pairwise_distance(a, b)
    d.sum().backward()
    assert d[0, 0, 0, 0].item() == 0.0
    assert torch.isfinite(a.grad).all() and (a.grad[0, 0] == 0).all()
    assert torch.allclose(a.grad[0, 1], -b[0, 0] / b[0, 0].norm())


def _reference_inputs(n: int = 5, m: int = 4):
    g = torch.Generator().manual_seed(0)
    return (torch.rand(1, n, 3, generator=g), torch.rand(1, n, 2, generator=g), torch.full((1, n), 0.01),
            torch.rand(1, m, 3, generator=g))


@pytest.mark.parametrize(
    ("index", "where", "bad", "message"),
    [
        (0, (0, 2, 0), NAN, r"src_pos: expected finite values, got nan \(1 of 15 entries bad, the first at index "
                            r"\(0, 2, 0\)\)"),
        (1, (0, 3, 1), INF, r"src_irradiance: expected finite values, got inf \(1 of 10 entries bad, the first at "
                            r"index \(0, 3, 1\)\)"),
        (2, (0, 4), NAN, r"src_area: expected finite values >= 0, got nan \(1 of 5 entries bad, the first at index "
                         r"\(0, 4\)\)"),
        (3, (0, 1, 2), NAN, r"dst_pos: expected finite values, got nan \(1 of 12 entries bad, the first at index "
                            r"\(0, 1, 2\)\)"),
        (3, (0, 3, 0), -INF, r"dst_pos: expected finite values, got -inf .* index \(0, 3, 0\)"),
    ],
)
def test_reference_radiosity_rejects_non_finite_inputs(index, where, bad, message):
    args = list(_reference_inputs())
    args[index] = args[index].clone()
    args[index][where] = bad
    with pytest.raises(ValueError, match=message):
        reference_radiosity(*args, _exp_profile)


def test_reference_radiosity_rejects_non_finite_modifiers():
    src, e, a, dst = _reference_inputs()
    md = torch.ones(1, 5, 1)
    md[0, 1, 0] = NAN
    with pytest.raises(ValueError, match=r"src_distance_scale: expected finite values, got nan .*\(0, 1, 0\)"):
        reference_radiosity(src, e, a, dst, _exp_profile, src_distance_scale=md)
    mi = torch.ones(1, 5, 2)
    mi[0, 4, 1] = INF
    with pytest.raises(ValueError, match=r"src_irradiance_scale: expected finite values, got inf .*\(0, 4, 1\)"):
        reference_radiosity(src, e, a, dst, _exp_profile, src_irradiance_scale=mi)


def test_reference_radiosity_nan_never_becomes_plausible_when_checks_are_skipped(tracing):
    """With the value checks skipped (tracing), a NaN source or receiver propagates as NaN, never as 0 distance."""
    src, e, a, dst = _reference_inputs()
    good = reference_radiosity(src, e, a, dst, _exp_profile)
    assert torch.isfinite(good).all()
    bad_dst = dst.clone()
    bad_dst[0, 2, 1] = NAN
    out = reference_radiosity(src, e, a, bad_dst, _exp_profile)
    assert torch.isnan(out[0, 2]).all()
    assert torch.equal(out[0, [0, 1, 3]], good[0, [0, 1, 3]])
    bad_src = src.clone()
    bad_src[0, 0, 0] = NAN
    assert torch.isnan(reference_radiosity(bad_src, e, a, dst, _exp_profile)).all()


def test_reference_radiosity_devices_and_meta():
    src, e, a, dst = _reference_inputs()
    with pytest.raises(ValueError, match=r"src_irradiance: expected a tensor on src_pos's device cpu, got one on meta"):
        reference_radiosity(src, e.to(META), a, dst, _exp_profile)
    with pytest.raises(ValueError, match=r"src_ids: expected a tensor on src_pos's device cpu, got one on meta"):
        reference_radiosity(src, e, a, dst, _exp_profile, src_ids=torch.zeros(1, 5, dtype=torch.long, device=META),
                            dst_ids=torch.zeros(1, 4, dtype=torch.long))
    with pytest.raises(TypeError, match=r"src_area: expected a real floating-point tensor, got complex dtype"):
        reference_radiosity(src, e, a.to(torch.complex64), dst, _exp_profile)
    # meta: the value checks are skipped and the shape comes out
    out = reference_radiosity(src.to(META), e.to(META), a.to(META), dst.to(META), _exp_profile)
    assert out.device.type == "meta" and out.shape == (1, 4, 2)


# -- 2. refract / reflect: scale-safe normalisation ----------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_refract_and_reflect_any_nonzero_length(dtype):
    s = 0.5
    i = torch.tensor([s, 0.0, -math.sqrt(1 - s * s)], dtype=dtype)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    t_ref, tir_ref = refract(i, n, 1.0 / 1.5)
    r_ref = reflect(i, n)
    assert not tir_ref and abs(t_ref[0].item() - 1 / 3) < 1e-6
    tiny = torch.finfo(dtype).tiny
    scales = [1e-30, 1e30, tiny, tiny / 16, 1e-20, 1e20] + ([1e-300, 1e300] if dtype == torch.float64 else [1e38])
    for scale in scales:
        for ii, nn in ((i * scale, n), (i, n * scale), (i * scale, n * scale)):
            assert (ii != 0).any() and torch.isfinite(ii).all()
            t, tir = refract(ii, nn, 1.0 / 1.5)
            assert not tir, scale
            torch.testing.assert_close(t, t_ref, msg=f"refract, scale {scale}")
            torch.testing.assert_close(reflect(ii, nn), r_ref, msg=f"reflect, scale {scale}")
    # total internal reflection is found at any scale too
    for scale in (1e-30, 1e30):
        t, tir = refract(i * scale, n, 2.5)
        assert tir and (t == 0).all()


def test_refract_zero_vectors_give_documented_result():
    n = torch.tensor([0.0, 0.0, 1.0])
    i = torch.tensor([0.3, 0.0, -1.0])
    for ii, nn in ((torch.zeros(3), n), (i, torch.zeros(3))):
        t, tir = refract(ii, nn, 1.0 / 1.5)
        assert (t == 0).all() and not tir  # no direction: zero vector, not TIR (a real result has length 1)
        assert (reflect(ii, nn) == 0).all()
    # gradients stay finite at zero vectors and at tiny scales
    for v in (torch.zeros(3), i * 1e-20):
        v = v.clone().requires_grad_(True)
        t, _ = refract(v, n, 1.0 / 1.5)
        t.sum().backward()
        assert torch.isfinite(v.grad).all()


# -- 3. newton_raphson_intersect: scale-safe directions ------------------------------------------------------------
def _plane_scene():
    ys, xs = torch.meshgrid(7.5 - 5.0 * torch.arange(4.0), -7.5 + 5.0 * torch.arange(4.0), indexing="ij")
    tex = torch.stack([xs, ys, torch.zeros(4, 4)])[None]
    vp = torch.tensor([[0.1, 0, 0, 0], [0, 0.1, 0, 0], [0, 0, -0.1, 0], [0, 0, 0, 1.0]])
    o = torch.tensor([[[0.0, 0.0, 4.0], [1.0, -1.0, 4.0]]])
    r = torch.tensor([[[0.6, 0.0, -0.8], [0.0, 0.0, -1.0]]])
    return o, r, tex, vp


@pytest.mark.parametrize("method", ["shah", "newton"])
def test_newton_raphson_any_nonzero_direction_length(method):
    o, r, tex, vp = _plane_scene()
    d_ref, ok_ref = newton_raphson_intersect(o, r, tex, vp, 4, method)
    assert ok_ref.all()
    for scale in (1e-30, 1e30, 1e-40, 1e38, 1e-20, 1e20):
        d, ok = newton_raphson_intersect(o, r * scale, tex, vp, 4, method)
        assert ok.all(), scale
        # 1e-40 is subnormal in float32: the scaled input itself keeps only ~17 bits
        tol = {"rtol": 1e-3, "atol": 1e-3} if scale < torch.finfo(r.dtype).tiny else {}
        torch.testing.assert_close(d, d_ref, msg=f"scale {scale}", **tol)
    # zero and non-finite directions stay invalid
    bad = r.clone()
    bad[0, 0] = 0.0
    bad[0, 1, 2] = NAN
    d, ok = newton_raphson_intersect(o, bad, tex, vp, 4, method)
    assert not ok.any() and (d == 0).all()


# -- 4. CausticMap: non-finite intensity ----------------------------------------------------------------------------
def _caustic_inputs() -> list:
    return list(caustic_plane_inputs().values())  # positional, in forward()'s order


def test_caustic_map_rejects_non_finite_intensity():
    module = CausticMap(1.33, mode="single", iterations=2)
    args = _caustic_inputs()
    out = module(*args)
    assert out.shape == (1, 1, 8, 8) and out.sum() > 0
    for bad in (NAN, INF):
        args[8] = torch.tensor([[bad]], dtype=torch.float64)
        with pytest.raises(ValueError, match=rf"intensity: expected finite values, got {bad!r}"):
            module(*args)


def test_caustic_map_device_mismatch_named():
    module = CausticMap(1.33, mode="single", iterations=2)
    args = _caustic_inputs()
    args[2] = args[2].to(META)
    with pytest.raises(ValueError, match=r"front_mask: expected a tensor on front_position's device cpu, got one "
                                         r"on meta"):
        module(*args)


# -- 5. devices, meta tensors, complex dtypes ------------------------------------------------------------------------
def test_check_devices_helper():
    cpu = torch.zeros(2)
    assert check_devices({"a": cpu, "b": None, "c": 1.0, "d": torch.ones(3, dtype=torch.long)}) == torch.device("cpu")
    assert check_devices({}) is None
    with pytest.raises(ValueError, match=r"^b: expected a tensor on a's device cpu, got one on meta$"):
        check_devices({"a": cpu, "b": cpu.to(META), "c": cpu.to(META)})
    with pytest.raises(ValueError, match=r"a: expected a tensor with data .* got one on the meta device"):
        check_devices({"a": cpu.to(META)}, allow_meta=False)
    assert check_devices({"a": cpu.to(META)}) == META
    with pytest.raises(TypeError, match=r"b: expected a real floating-point tensor, got complex dtype torch.complex64"):
        check_devices({"a": cpu, "b": cpu.to(torch.complex64)}, floating=True)
    with pytest.raises(TypeError, match=r"b: expected a floating-point tensor, got dtype torch.int64"):
        check_devices({"a": cpu, "b": cpu.long()}, floating=("b",))
    with pytest.raises(TypeError, match=r"b: expected a torch.Tensor, got list"):
        check_devices({"a": cpu, "b": [1.0]}, floating=("a", "b"))
    check_devices({"a": cpu, "b": cpu.long()}, floating=("a",))  # not required to be floating


def test_check_tensor_rejects_complex_and_value_checks_skip_meta():
    for dtype in (torch.complex64, torch.complex128):
        with pytest.raises(TypeError, match=rf"eta: expected a real floating-point tensor, got complex dtype {dtype}"):
            check_tensor(torch.ones(2, dtype=dtype), "eta")
    meta = torch.ones(3, device=META)
    check_nonnegative(meta, "x")
    check_positive(meta, "x")
    check_finite(meta, "x")
    with pytest.raises(ValueError, match=r"x: expected finite values > 0, got 0.0 \(1 of 3 entries bad, the first at "
                                         r"index \(1,\)\)"):
        check_positive(torch.tensor([1.0, 0.0, 2.0]), "x")
    with pytest.raises(ValueError, match=r"x: expected finite values >= 0, got -1.0 \(1 of 1 entries bad\)$"):
        check_nonnegative(torch.tensor(-1.0), "x")


def test_dipole_rd_on_meta():
    from torchsss import dipole_rd

    out = dipole_rd(torch.ones(2, 1, device=META), torch.ones(3, device=META), torch.ones(3, device=META))
    assert out.device.type == "meta" and out.shape == (2, 3)


def _splat_inputs():
    ys, xs = torch.meshgrid(torch.linspace(-3.5, 3.5, 8), torch.linspace(-3.5, 3.5, 8), indexing="ij")
    dst = torch.stack([xs, -ys, torch.zeros_like(xs)])[None]
    vp = torch.diag(torch.tensor([0.25, 0.25, 1.0, 1.0]))
    return (torch.zeros(1, 1, 3), torch.ones(1, 1, 1), dst, torch.ones(1, 1, 8, 8, dtype=torch.bool), vp)


@pytest.mark.parametrize("other", OTHER)
def test_splat_radiosity_devices(other):
    args = list(_splat_inputs())
    ok = splat_radiosity(*args, _exp_profile, r_max=2.0, method="window")
    assert ok.shape == (1, 1, 8, 8) and ok.sum() > 0
    names = ["src_pos", "src_flux", "dst_pos", "dst_mask", "view_proj"]
    for k in range(1, 5):
        bad = list(args)
        bad[k] = bad[k].to(other)
        with pytest.raises(ValueError, match=rf"{names[k]}: expected a tensor on src_pos's device cpu, got one on "
                                             rf"{other}"):
            splat_radiosity(*bad, _exp_profile, r_max=2.0)
    with pytest.raises(ValueError, match=rf"r_max: expected a tensor on src_pos's device cpu, got one on {other}"):
        splat_radiosity(*args, _exp_profile, r_max=torch.tensor(2.0, device=other))
    with pytest.raises(ValueError, match=rf"src_material: expected a tensor on src_pos's device cpu, got one on "
                                         rf"{other}"):
        splat_radiosity(*args, _exp_profile, r_max=2.0, src_material=torch.zeros(1, 1, dtype=torch.long,
                                                                                   device=other))


def test_splat_radiosity_meta_and_complex():
    args = [t.to(META) for t in _splat_inputs()]
    with pytest.raises(ValueError, match=r"src_pos: expected a tensor with data .* meta device"):
        splat_radiosity(*args, _exp_profile, r_max=2.0)
    args = list(_splat_inputs())
    args[1] = args[1].to(torch.complex64)
    with pytest.raises(TypeError, match=r"src_flux: expected a real floating-point tensor, got complex dtype"):
        splat_radiosity(*args, _exp_profile, r_max=2.0)


@pytest.mark.parametrize("other", OTHER)
def test_icdf_devices(other):
    pdf, u = torch.rand(2, 1, 5, 7), torch.rand(2, 9, 2)
    for fn in (icdf_sample, icdf_sample_reference):
        with pytest.raises(ValueError, match=rf"u: expected a tensor on pdf's device cpu, got one on {other}"):
            fn(pdf, u.to(other))
        # the reference sampler refuses meta tensors outright (its search needs data)
        first = "pdf: expected a tensor with data" if (other, fn) == ("meta", icdf_sample_reference) else (
            rf"u: expected a tensor on pdf's device {other}(:0)?, got one on cpu")
        with pytest.raises(ValueError, match=first):
            fn(pdf.to(other), u)


def test_icdf_meta_and_complex():
    xy, p = icdf_sample(torch.rand(2, 1, 5, 7, device=META), torch.rand(2, 9, 2, device=META))
    assert xy.device.type == "meta" and xy.shape == (2, 9, 2) and p.shape == (2, 9)
    pyr = sum_pyramid(torch.rand(1, 1, 4, 4, device=META))
    assert pyr[-1].device.type == "meta"
    with pytest.raises(ValueError, match=r"pdf: expected a tensor with data .* meta device"):
        icdf_sample_reference(torch.rand(2, 1, 5, 7, device=META), torch.rand(2, 9, 2, device=META))
    with pytest.raises(TypeError, match=r"u: expected a real floating-point tensor, got complex dtype"):
        icdf_sample(torch.rand(2, 1, 5, 7), torch.rand(2, 9, 2).to(torch.complex64))
    with pytest.raises(TypeError, match=r"pdf: expected a real floating-point tensor, got complex dtype"):
        icdf_sample(torch.rand(2, 1, 5, 7).to(torch.complex128), torch.rand(2, 9, 2))


@pytest.mark.parametrize("other", OTHER)
def test_sv_conv_devices(other):
    img, kern = torch.rand(1, 2, 4, 5), torch.rand(4, 5, 3, 3)
    for fn in (sv_conv2d, sv_conv2d_reference):
        with pytest.raises(ValueError, match=rf"kernels: expected a tensor on image's device cpu, got one on {other}"):
            fn(img, kern.to(other))
        with pytest.raises(ValueError,
                           match=rf"kernels: expected a tensor on image's device {other}(:0)?, got one on cpu"):
            fn(img.to(other), kern)


def test_sv_conv_meta_and_complex():
    out = sv_conv2d(torch.rand(1, 2, 4, 5, device=META), torch.rand(4, 5, 3, 3, device=META))
    assert out.device.type == "meta" and out.shape == (1, 2, 4, 5)
    with pytest.raises(TypeError, match=r"kernels: expected a real floating-point tensor, got complex dtype"):
        sv_conv2d(torch.rand(1, 2, 4, 5), torch.rand(4, 5, 3, 3).to(torch.complex64))


@pytest.mark.parametrize("other", OTHER)
def test_sparse_apply_devices(other):
    pat = sparse_pattern(torch.tensor([0, 1, 1]), torch.tensor([1, 0, 0]), 2, 2)
    x, v = torch.tensor([[1.0], [10.0]]), torch.tensor([2.0, 3.0, 4.0])
    for method in ("auto", "csr", "scatter"):
        with pytest.raises(ValueError, match=rf"values: expected a tensor on x's device cpu, got one on {other}"):
            sparse_apply_t(x, pat, v.to(other), method=method)
        with pytest.raises(ValueError, match=rf"values: expected a tensor on x's device {other}(:0)?, got one on cpu"):
            sparse_apply_t(x.to(other), pat, v, method=method)
        with pytest.raises(ValueError, match=rf"pattern.rows: expected a tensor on x's device {other}(:0)?, got one on "
                                             r"cpu"):
            sparse_apply_t(x.to(other), pat, v.to(other), method=method)
    with pytest.raises(ValueError, match=rf"cols: expected a tensor on rows's device cpu, got one on {other}"):
        sparse_pattern(torch.tensor([0, 1]), torch.tensor([1, 0], device=other), 2, 2)


def test_sparse_meta_and_complex():
    pat = sparse_pattern(torch.tensor([0, 1, 1]), torch.tensor([1, 0, 0]), 2, 2)
    meta_pat = pat._replace(**{k: getattr(pat, k).to(META) for k in ("rows", "cols", "t_crow", "t_col", "t_perm")})
    x, v = torch.rand(3, 2, 4, device=META), torch.rand(3, device=META)
    y = sparse_apply_t(x, meta_pat, v)  # auto: the scatter path, which has meta kernels
    assert y.device.type == "meta" and y.shape == (3, 2, 4)
    with pytest.raises(ValueError, match=r"method: expected 'auto' or 'scatter' on the meta device"):
        sparse_apply_t(x, meta_pat, v, method="csr")
    with pytest.raises(ValueError, match=r"rows: expected a tensor with data .* meta device"):
        sparse_pattern(torch.tensor([0, 1], device=META), torch.tensor([1, 0], device=META), 2, 2)
    with pytest.raises(TypeError, match=r"values: expected a real floating-point tensor, got complex dtype"):
        sparse_apply_t(torch.rand(2, 1), pat, torch.rand(3).to(torch.complex64))


def test_caustic_map_any_normal_length():
    """The refractor's normals may have any non-zero length (the Fresnel cosine and the refraction alike)."""
    module = CausticMap(1.33, mode="single", iterations=2, fresnel=True)
    args = _caustic_inputs()
    ref = module(*args)
    for scale in (1e-30, 1e30, 1e-170, 1e170):  # float64: the squared norm underflows / overflows past 1e+-154
        scaled = list(args)
        scaled[1] = args[1] * scale
        torch.testing.assert_close(module(*scaled), ref)
