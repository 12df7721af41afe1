"""The fast paths of Lensch's ops: the compiled sv_conv2d and the cached CSR matrix of sparse_apply_t."""

from __future__ import annotations

import pytest
import torch
from torch._dynamo.utils import counters

from torchsss.ops import fused, sparse_apply_t, sparse_pattern, sv_conv2d, sv_conv2d_reference
from torchsss.ops import sv_conv as sv_conv_mod

# small kernels (k = 3) and images: the compiles stay short


def _conv_case(dtype, batched=False, b=2, c=3, h=13, w=10, k=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(b, c, h, w, generator=g, dtype=dtype)
    shape = (b, h, w, k, k) if batched else (h, w, k, k)
    return image, torch.rand(*shape, generator=g, dtype=dtype)


@pytest.fixture
def compiled(monkeypatch):
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    monkeypatch.setattr(fused, "_BROKEN", {})


@pytest.mark.parametrize("batched", [False, True], ids=["shared", "batched"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_sv_conv2d_compiled_matches_reference(compiled, dtype, batched):
    image, kernels = _conv_case(dtype, batched)
    calls = []
    real = fused._call
    with torch.no_grad():
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(fused, "_call", lambda *a: calls.append(1) or real(*a))
            out = sv_conv2d(image, kernels)
        ref = sv_conv2d_reference(image, kernels)
    assert calls, "the compiled kernel did not run"
    assert out.dtype == dtype and out.shape == image.shape
    tol = 1e-6 if dtype == torch.float32 else 1e-13
    torch.testing.assert_close(out, ref, rtol=tol, atol=tol)


def test_sv_conv2d_groups_and_no_recompile_for_new_images(compiled):
    """Five images share one kernel set (groups of 4 + 1); new images (frames) reuse the graphs and planes."""
    image, kernels = _conv_case(torch.float32, b=5, c=1, h=9, w=11, seed=1)
    with torch.inference_mode():
        sv_conv2d(image, kernels)
        before = counters["stats"]["unique_graphs"]
        permutes = []
        real = sv_conv_mod._planes
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(sv_conv_mod, "_planes", lambda *a: permutes.append(1) or real(*a))
            for seed in range(3):
                frame = torch.rand(5, 1, 9, 11, generator=torch.Generator().manual_seed(seed))
                torch.testing.assert_close(sv_conv2d(frame, kernels), sv_conv2d_reference(frame, kernels))
            assert not permutes, "the kernel planes were rebuilt for a new image"
            changed = kernels * 2.0  # new kernels: new planes, same graph
            frame = torch.rand(5, 1, 9, 11)
            torch.testing.assert_close(sv_conv2d(frame, changed), sv_conv2d_reference(frame, changed))
            assert len(permutes) == 1
    assert counters["stats"]["unique_graphs"] == before


def test_sv_conv2d_kernels_changed_in_place(compiled):
    """Kernels edited in place (outside inference mode: the version counter) get new planes."""
    image, kernels = _conv_case(torch.float64, seed=2)
    with torch.no_grad():
        sv_conv2d(image, kernels)
        kernels.mul_(0.5)
        torch.testing.assert_close(sv_conv2d(image, kernels), sv_conv2d_reference(image, kernels))


def test_sv_conv2d_two_threads_equal_one(compiled):
    image, kernels = _conv_case(torch.float32, batched=True, seed=3)
    before = torch.get_num_threads()
    try:
        with torch.inference_mode():
            torch.set_num_threads(1)
            one = sv_conv2d(image, kernels)
            torch.set_num_threads(2)
            two = sv_conv2d(image, kernels)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one, two)


def test_sv_conv2d_fallback_when_compile_fails(monkeypatch):
    """A compile that fails warns once, then the eager paths serve every later call."""
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    monkeypatch.setattr(fused, "_BROKEN", {})
    monkeypatch.setattr(fused, "_COMPILED", {})

    def broken(fn, **kwargs):
        def fail(*args):
            raise RuntimeError("no C++ compiler")
        return fail

    monkeypatch.setattr(torch, "compile", broken)
    image, kernels = _conv_case(torch.float32, seed=4)
    with torch.no_grad():
        with pytest.warns(RuntimeWarning, match="compiling sv_conv2d failed"):
            out = sv_conv2d(image, kernels)
        torch.testing.assert_close(out, sv_conv2d_reference(image, kernels))
        assert "sv_conv2d" in fused._BROKEN
        torch.testing.assert_close(sv_conv2d(image, kernels), sv_conv2d_reference(image, kernels))


def test_sv_conv2d_graph_path_keeps_gradients(compiled):
    """Inputs that require grad take the differentiable eager path, not the compiled one."""
    image, kernels = _conv_case(torch.float64, seed=5)
    image.requires_grad_()
    out = sv_conv2d(image, kernels)
    out.sum().backward()
    assert image.grad is not None and image.grad.shape == image.shape


def test_sv_conv2d_auto_compiles_once_frames_pay(monkeypatch):
    """``auto``: frames of one variant add up; once their eager work pays for a compile the compiled path runs."""
    monkeypatch.setenv("TORCHSSS_COMPILE", "auto")
    monkeypatch.setattr(fused, "_EAGER_WORK", {})
    monkeypatch.setattr(fused, "_WARM", set())
    image, kernels = _conv_case(torch.float32, c=1, seed=6)  # two images: one group, one kernel call
    per_call = image.numel() * 9 / sv_conv_mod._MACS_PER_WORK
    monkeypatch.setattr(fused, "COLD_WORK", 2.5 * per_call)
    monkeypatch.setattr(fused, "WARM_WORK", per_call)
    ran = []
    monkeypatch.setattr(sv_conv_mod, "_sv_conv2d_tiled", lambda *a: ran.append("eager") or torch.zeros_like(image))
    monkeypatch.setattr(fused, "_call", lambda *a: ran.append("compiled") or torch.zeros(1, 2, 13, 10))
    with torch.no_grad():
        for _ in range(4):
            sv_conv2d(image, kernels)
    assert ran == ["eager", "eager", "compiled", "compiled"], ran


# -- sparse_apply_t -------------------------------------------------------------------------------------------------
def _sparse_case(dtype, per_channel=False, seed=0):
    g = torch.Generator().manual_seed(seed)
    n, nnz, c = 40, 300, 3
    rows = torch.randint(0, n, (nnz,), generator=g)
    cols = torch.randint(0, n, (nnz,), generator=g)
    rows[1], cols[1] = rows[0], cols[0]  # a duplicate entry
    values = torch.rand((nnz, c) if per_channel else (nnz,), generator=g, dtype=dtype)
    x = torch.rand(2, n, c, generator=g, dtype=dtype)
    return x, sparse_pattern(rows, cols, n, n), values


@pytest.mark.parametrize("per_channel", [False, True], ids=["shared", "per_channel"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_sparse_cached_csr_matches_scatter(dtype, per_channel):
    x, pat, values = _sparse_case(dtype, per_channel)
    with torch.inference_mode():
        ref = sparse_apply_t(x, pat, values, method="scatter")
        first = sparse_apply_t(x, pat, values, method="csr")
        x2 = torch.rand_like(x)  # relighting: new x, same values -> the cached matrix
        again = sparse_apply_t(x2, pat, values, method="csr")
        ref2 = sparse_apply_t(x2, pat, values, method="scatter")
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(first, ref, rtol=tol, atol=tol)
    torch.testing.assert_close(again, ref2, rtol=tol, atol=tol)


def test_sparse_cache_builds_once_and_follows_new_values(monkeypatch):
    x, pat, values = _sparse_case(torch.float64, seed=1)
    from torchsss.ops import sparse as sparse_mod
    built = []
    real = sparse_mod._csr
    monkeypatch.setattr(sparse_mod, "_csr", lambda *a: built.append(1) or real(*a))
    with torch.no_grad():
        for _ in range(3):
            sparse_apply_t(x, pat, values)
        assert len(built) == 1
        values.mul_(2.0)  # changed in place: rebuilt
        torch.testing.assert_close(sparse_apply_t(x, pat, values), sparse_apply_t(x, pat, values, method="scatter"))
        assert len(built) == 2


def test_sparse_two_threads_equal_one():
    x, pat, values = _sparse_case(torch.float32, seed=2)
    before = torch.get_num_threads()
    try:
        with torch.inference_mode():
            torch.set_num_threads(1)
            one = sparse_apply_t(x, pat, values)
            torch.set_num_threads(2)
            two = sparse_apply_t(x, pat, values)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one, two)


def test_sparse_values_gradient_skips_the_cache():
    x, pat, values = _sparse_case(torch.float64, seed=3)
    values.requires_grad_()
    y = sparse_apply_t(x, pat, values)  # "auto" picks scatter for a gradient to the values
    y.sum().backward()
    assert values.grad is not None
    v2 = values.detach().clone()
    x.requires_grad_()
    y = sparse_apply_t(x, pat, v2, method="csr")  # a gradient to x through the cached matrix
    y.sum().backward()
    torch.testing.assert_close(x.grad[0], torch.zeros(40, 3, dtype=torch.float64).index_add_(
        0, pat.rows, v2[:, None].expand(-1, 3).contiguous()))
