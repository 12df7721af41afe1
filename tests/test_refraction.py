"""refract / reflect: Snell's law angles, closed forms, total internal reflection, identities, gradients, ONNX."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchsss.ops.refraction import reflect, refract

F64 = torch.float64


def _unit(v):
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def _random_setup(n, seed=0, eta_range=(0.5, 2.0)):
    """Random normals (either orientation, any length), incident directions, per-ray eta."""
    g = torch.Generator().manual_seed(seed)
    normal = torch.randn(n, 3, generator=g, dtype=F64) * (0.5 + torch.rand(n, 1, generator=g, dtype=F64))
    incident = torch.randn(n, 3, generator=g, dtype=F64) * 3.0
    lo, hi = eta_range
    eta = lo + (hi - lo) * torch.rand(n, generator=g, dtype=F64)
    return incident, normal, eta


def _facing(incident, normal):
    """Unit normal flipped to face the incoming light, and cos(theta_i) >= 0 (independent of the code under test)."""
    i, n = _unit(incident), _unit(normal)
    c = -(i * n).sum(-1, keepdim=True)
    n = torch.where(c < 0, -n, n)
    return i, n, c.abs()[..., 0]


def _sin(a, b):
    return torch.linalg.vector_norm(torch.linalg.cross(a, b), dim=-1)


# -- refract --------------------------------------------------------------------------------------------------------
def test_snell_law_angles_plane_and_side():
    incident, normal, eta = _random_setup(4000)
    t, tir = refract(incident, normal, eta)
    i, n, cos_i = _facing(incident, normal)
    sin_i = _sin(i, n)
    expect_tir = eta * sin_i > 1.0
    margin = (eta * sin_i - 1.0).abs() > 1e-9  # away from the critical angle
    assert torch.equal(tir[margin], expect_tir[margin])
    ok = ~tir
    assert ok.sum() > 1000 and tir.sum() > 300
    # n1 sin(theta_1) = n2 sin(theta_2) with eta = n1 / n2, unit length, on the far side, in the plane of incidence
    torch.testing.assert_close(_sin(t[ok], -n[ok]), eta[ok] * sin_i[ok], rtol=0, atol=1e-12)
    torch.testing.assert_close(
        torch.linalg.vector_norm(t[ok], dim=-1), torch.ones(int(ok.sum()), dtype=F64), rtol=0, atol=1e-14
    )
    assert bool(((t[ok] * n[ok]).sum(-1) < 0).all())
    coplanar = torch.linalg.det(torch.stack([i[ok], n[ok], t[ok]], dim=-2))
    assert float(coplanar.abs().max()) < 1e-12
    # the transmitted ray turns in the same tangential direction as the incident one
    tan_i = i[ok] + cos_i[ok, None] * n[ok]
    tan_t = t[ok] - (t[ok] * n[ok]).sum(-1, keepdim=True) * n[ok]
    assert bool(((tan_i * tan_t).sum(-1) >= -1e-15).all())
    # TIR entries are exact zero vectors
    assert torch.equal(t[tir], torch.zeros_like(t[tir]))


def test_closed_forms():
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    # normal incidence: no bending, whatever eta; eta = 1: no bending at any angle
    for eta in (0.3, 1.0, 1.5, 3.0):
        t, tir = refract(torch.tensor([0.0, 0.0, -2.0], dtype=F64), z, eta)
        torch.testing.assert_close(t, -z, rtol=0, atol=0)
        assert not tir
    i = _unit(torch.tensor([[1.0, 2.0, -3.0], [0.5, -0.1, -0.01]], dtype=F64))
    t, tir = refract(i, z, 1.0)
    torch.testing.assert_close(t, i, rtol=0, atol=1e-15)
    assert not tir.any()
    # 45 degrees from air into water (n = 1.33): sin(theta_t) = sin(45) / 1.33
    s = math.sqrt(0.5)
    t, _ = refract(torch.tensor([s, 0.0, -s], dtype=F64), z, 1.0 / 1.33)
    st = s / 1.33
    torch.testing.assert_close(t, torch.tensor([st, 0.0, -math.sqrt(1 - st * st)], dtype=F64), rtol=0, atol=1e-15)
    # 60 degrees out of glass (1.5) into air is beyond the critical angle 41.8 degrees
    t, tir = refract(torch.tensor([math.sin(math.pi / 3), 0.0, -0.5], dtype=F64), z, 1.5)
    assert tir and torch.equal(t, torch.zeros(3, dtype=F64))
    # 30 degrees out of glass: sin(theta_t) = 1.5 * 0.5 = 0.75
    t, tir = refract(torch.tensor([0.5, 0.0, -math.sqrt(0.75)], dtype=F64), z, 1.5)
    torch.testing.assert_close(t, torch.tensor([0.75, 0.0, -math.sqrt(1 - 0.5625)], dtype=F64), rtol=0, atol=1e-15)
    assert not tir


def test_normal_orientation_and_length_do_not_matter():
    incident, normal, eta = _random_setup(500, seed=1)
    t1, tir1 = refract(incident, normal, eta)
    t2, tir2 = refract(incident * 7.0, -normal * 0.01, eta)
    torch.testing.assert_close(t1, t2, rtol=0, atol=1e-14)
    assert torch.equal(tir1, tir2)


def test_entering_and_leaving_are_inverse():
    # air -> glass, then the reversed ray glass -> air retraces the path (Helmholtz reciprocity of directions)
    incident, normal, _ = _random_setup(300, seed=2)
    t, tir = refract(incident, normal, 1.0 / 1.5)
    assert not tir.any()
    back, tir_back = refract(-t, normal, 1.5)
    assert not tir_back.any()
    torch.testing.assert_close(back, -_unit(incident), rtol=0, atol=1e-12)


@pytest.mark.parametrize("eta", [1.2, 1.5, 2.4])
def test_tir_around_the_critical_angle(eta):
    theta_c = math.asin(1.0 / eta)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)

    def incident(theta):
        return torch.tensor([math.sin(theta), 0.0, -math.cos(theta)], dtype=F64)

    t, tir = refract(incident(theta_c + 1e-7), z, eta)
    assert tir and torch.equal(t, torch.zeros(3, dtype=F64))
    t, tir = refract(incident(min(theta_c + 0.3, math.pi / 2)), z, eta)
    assert tir
    t, tir = refract(incident(theta_c - 1e-7), z, eta)
    assert not tir
    # just below the critical angle the transmitted ray runs along the surface: |cos theta_t| ~ sqrt(2 eta^2 s c d)
    assert abs(t[2].item()) < 1e-3 and t[0].item() > 0.999999
    # far below: ordinary refraction
    t, tir = refract(incident(theta_c - 0.2), z, eta)
    assert not tir and math.isclose(t[0].item(), eta * math.sin(theta_c - 0.2), abs_tol=1e-14)


def test_critical_angle_exactly_counts_as_tir():
    # eta = 1 at grazing incidence: k = 1 - eta^2 sin^2 = 0 exactly, the transmitted ray would run along the surface
    t, tir = refract(torch.tensor([1.0, 0.0, 0.0], dtype=F64), torch.tensor([0.0, 0.0, 1.0], dtype=F64), 1.0)
    assert tir and torch.equal(t, torch.zeros(3, dtype=F64))
    # eta < 1 never reflects totally, even at grazing incidence
    t, tir = refract(torch.tensor([1.0, 0.0, 0.0], dtype=F64), torch.tensor([0.0, 0.0, 1.0], dtype=F64), 0.75)
    assert not tir
    torch.testing.assert_close(t, torch.tensor([0.75, 0.0, -math.sqrt(1 - 0.5625)], dtype=F64), rtol=0, atol=1e-15)


def test_per_channel_eta_dispersion():
    incident, normal, _ = _random_setup(50, seed=3)
    eta = torch.tensor([1 / 1.31, 1 / 1.33, 1 / 1.35], dtype=F64)
    t, tir = refract(incident[:, None, :], normal[:, None, :], eta)
    assert t.shape == (50, 3, 3) and tir.shape == (50, 3)
    for c in range(3):
        tc, tirc = refract(incident, normal, eta[c].item())
        torch.testing.assert_close(t[:, c], tc, rtol=0, atol=0)
        assert torch.equal(tir[:, c], tirc)
    # a denser medium (smaller n1 / n2) bends the ray more toward the normal
    _, n, _ = _facing(incident, normal)
    cos_t = -(t * n[:, None, :]).sum(-1)
    assert bool((cos_t[:, 2] >= cos_t[:, 1]).all()) and bool((cos_t[:, 1] >= cos_t[:, 0]).all())


def test_broadcasting_shared_normal():
    incident, _, _ = _random_setup(20, seed=4)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    t, tir = refract(incident, z, 0.8)
    t2, tir2 = refract(incident, z.expand(20, 3), torch.full((20,), 0.8, dtype=F64))
    assert t.shape == (20, 3) and tir.shape == (20,)
    torch.testing.assert_close(t, t2, rtol=0, atol=0)
    assert torch.equal(tir, tir2)


def test_zero_vectors_give_zero_without_nan():
    z = torch.tensor([0.0, 0.0, 1.0])
    t, tir = refract(torch.zeros(2, 3), z, torch.tensor([0.7, 1.5]))
    assert torch.equal(t, torch.zeros(2, 3)) and not tir.any()
    t, tir = refract(torch.tensor([1.0, 0.0, -1.0]), torch.zeros(3), 1.5)
    assert torch.equal(t, torch.zeros(3)) and not tir
    assert torch.equal(reflect(torch.zeros(3), z), torch.zeros(3))
    assert torch.equal(reflect(z, torch.zeros(3)), torch.zeros(3))
    # gradients stay finite at zero vectors and at TIR
    i = torch.tensor([[0.0, 0.0, 0.0], [0.9, 0.0, -0.1], [0.1, 0.0, -1.0]], dtype=F64, requires_grad=True)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64, requires_grad=True)
    eta = torch.tensor(1.5, dtype=F64, requires_grad=True)
    t, tir = refract(i, n, eta)
    assert tir.tolist() == [False, True, False]
    (t.sum() + reflect(i, n).sum()).backward()
    assert all(bool(torch.isfinite(g).all()) for g in (i.grad, n.grad, eta.grad))


def test_device_dtype(device, dtype):
    incident, normal, eta = _random_setup(100, seed=5)
    t64, tir64 = refract(incident, normal, eta)
    t, tir = refract(incident.to(device, dtype), normal.to(device, dtype), eta.to(device, dtype))
    assert t.dtype == dtype and t.device.type == device.type and tir.dtype == torch.bool
    tol = 1e-12 if dtype == F64 else 2e-5
    far = tir64 == tir.cpu()
    assert far.float().mean() > 0.98  # float32 may flip rays within rounding of the critical angle
    torch.testing.assert_close(t.cpu().double()[far], t64[far], rtol=0, atol=tol)
    r = reflect(incident.to(device, dtype), normal.to(device, dtype))
    assert r.dtype == dtype and r.device.type == device.type


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
def test_reduced_precision_computed_in_float32(low):
    incident, normal, _ = _random_setup(30, seed=6)
    t, _ = refract(incident.to(low), normal.to(low), 0.75)
    assert t.dtype == low
    want, _ = refract(incident.to(low).float(), normal.to(low).float(), 0.75)
    torch.testing.assert_close(t, want.to(low), rtol=0, atol=0)
    assert reflect(incident.to(low), normal.float()).dtype == torch.float32


# -- reflect --------------------------------------------------------------------------------------------------------
def test_reflect_identities():
    incident, normal, _ = _random_setup(2000, seed=7)
    r = reflect(incident, normal)
    i, n = _unit(incident), _unit(normal)
    torch.testing.assert_close(torch.linalg.vector_norm(r, dim=-1), torch.ones(2000, dtype=F64), rtol=0, atol=1e-14)
    torch.testing.assert_close((r * n).sum(-1), -(i * n).sum(-1), rtol=0, atol=1e-14)  # normal part flips
    torch.testing.assert_close(
        r - (r * n).sum(-1, keepdim=True) * n, i - (i * n).sum(-1, keepdim=True) * n, rtol=0, atol=1e-14
    )  # tangential part kept
    torch.testing.assert_close(reflect(r, normal), i, rtol=0, atol=1e-14)  # an involution
    torch.testing.assert_close(reflect(incident, -3.0 * normal), r, rtol=0, atol=1e-14)  # orientation-free
    # angle of reflection = angle of incidence, and normal incidence comes straight back
    torch.testing.assert_close(_sin(r, n), _sin(i, n), rtol=0, atol=1e-13)
    torch.testing.assert_close(reflect(-normal, normal), _unit(normal), rtol=0, atol=1e-15)
    # a grazing ray is unchanged
    torch.testing.assert_close(
        reflect(torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, 1.0])),
        torch.tensor([1.0, 0.0, 0.0]),
        rtol=0,
        atol=0,
    )


def test_reflect_equals_refract_limit_and_fresnel_mirror():
    # refract at TIR and reflect are complementary: past the critical angle only the reflected ray exists
    i = _unit(torch.tensor([0.9, 0.2, -0.3], dtype=F64))
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    _, tir = refract(i, z, 1.5)
    r = reflect(i, z)
    assert tir and torch.allclose(r, i * torch.tensor([1.0, 1.0, -1.0], dtype=F64), rtol=0, atol=1e-15)


# -- gradients ------------------------------------------------------------------------------------------------------
def test_gradcheck_refract():
    incident, normal, eta = _random_setup(12, seed=8, eta_range=(0.6, 0.9))  # eta < 1: never near TIR
    args = (incident.requires_grad_(), normal.requires_grad_(), eta.requires_grad_())
    assert torch.autograd.gradcheck(lambda a, b, c: refract(a, b, c)[0], args)
    # per-channel eta, with some rays in TIR (zero gradients there)
    i2, n2, _ = _random_setup(6, seed=9)
    e2 = torch.tensor([0.8, 1.3, 1.7], dtype=F64, requires_grad=True)
    _, tir = refract(i2[:, None], n2[:, None], e2)
    _, nn_, _ = _facing(i2, n2)  # keep away from the critical angle, where the derivative is infinite
    s = _sin(_unit(i2), nn_)
    k_margin = bool(((e2.detach()[None] * s[:, None] - 1).abs() > 1e-3).all())
    assert k_margin and tir.any()
    assert torch.autograd.gradcheck(
        lambda a, b, c: refract(a[:, None], b[:, None], c)[0], (i2.requires_grad_(), n2.requires_grad_(), e2)
    )


def test_gradcheck_reflect():
    incident, normal, _ = _random_setup(10, seed=10)
    assert torch.autograd.gradcheck(reflect, (incident.requires_grad_(), normal.requires_grad_()))


# -- errors ---------------------------------------------------------------------------------------------------------
def test_bad_inputs():
    v, z = torch.rand(4, 3), torch.tensor([0.0, 0.0, 1.0])
    with pytest.raises(TypeError, match=r"incident: expected a torch.Tensor, got ndarray"):
        refract(np.zeros((4, 3)), z, 1.5)
    with pytest.raises(TypeError, match=r"normal: expected a floating-point tensor, got dtype torch.int64"):
        refract(v, torch.tensor([0, 0, 1]), 1.5)
    with pytest.raises(ValueError, match=r"incident: expected shape \(\.\.\., 3\), got \(4, 2\)"):
        refract(torch.rand(4, 2), z, 1.5)
    with pytest.raises(ValueError, match=r"normal: expected shape \(\.\.\., 3\), got \(\)"):
        refract(v, torch.tensor(1.0), 1.5)
    with pytest.raises(ValueError, match=r"eta: expected finite values > 0, got 0.0"):
        refract(v, z, 0.0)
    with pytest.raises(ValueError, match=r"eta: expected finite values > 0, got nan"):
        refract(v, z, torch.tensor([1.0, float("nan"), 1.0, 1.0]))
    with pytest.raises(TypeError, match=r"eta: expected numbers, got '1.5'"):
        refract(v, z, "1.5")
    with pytest.raises(TypeError, match=r"eta: expected a tensor, a number or a sequence of numbers, got NoneType"):
        refract(v, z, None)
    with pytest.raises(ValueError, match=r"expected leading shapes that broadcast, got incident \(4,\) \(\+3\)"):
        refract(v, torch.rand(5, 3), 1.5)
    with pytest.raises(ValueError, match=r"eta \(3,\)"):
        refract(v, z, torch.tensor([0.7, 0.8, 0.9]))  # a per-channel eta needs a channel axis on the vectors
    with pytest.raises(TypeError, match=r"incident: expected a torch.Tensor, got list"):
        reflect([1.0, 0.0, 0.0], z)
    with pytest.raises(ValueError, match=r"normal: expected shape \(\.\.\., 3\), got \(4,\)"):
        reflect(v, torch.rand(4))
    with pytest.raises(ValueError, match=r"incident, normal: expected shapes that broadcast"):
        reflect(v, torch.rand(5, 3))


# -- ONNX -----------------------------------------------------------------------------------------------------------
class _Refract(torch.nn.Module):
    """Test-only wrapper: ops/ stays free of nn.Modules."""

    def forward(self, incident, normal, eta):
        t, tir = refract(incident, normal, eta)
        return t, tir, reflect(incident, normal)


@pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning")
@pytest.mark.filterwarnings("ignore:# The axis name:UserWarning")
def test_onnx_export_dynamic_size(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    from torch.export import Dim

    from torchsss.export import compare_with_eager, export_onnx, run_onnxruntime

    def make(n, seed):
        i, nn_, _ = _random_setup(n, seed=seed)
        return (i[:, None].float(), nn_[:, None].float(), torch.tensor([0.7, 1.0, 1.6]))

    ndim = Dim("N")
    path = export_onnx(_Refract(), make(40, 11), tmp_path / "refract.onnx", dynamic_shapes=({0: ndim}, {0: ndim}, None))
    test = make(73, 12)
    res = compare_with_eager(_Refract(), path, test)
    assert res["shapes"] == [(73, 3, 3), (73, 3), (73, 1, 3)]
    assert res["max_abs_diff"] <= 1e-6 and res["nonfinite_match"], res
    t, tir, r = run_onnxruntime(path, test)
    want_t, want_tir = refract(*(x.double() for x in test))
    assert tir.any() and np.array_equal(tir, want_tir.numpy())
    # float32 rounding against the float64 result (near-tangent rays amplify it: |dt| ~ eps / sqrt(k))
    np.testing.assert_allclose(t, want_t.numpy(), rtol=0, atol=2e-5)
    np.testing.assert_allclose(r, reflect(test[0].double(), test[1].double()).numpy(), rtol=0, atol=1e-6)
