"""sv_conv2d (Lensch local response): fast path vs reference vs a Python loop, gradients, ONNX export."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchsss.ops import sv_conv2d, sv_conv2d_reference


def loop_conv(image, kernels):
    """Pure-Python definition: out[b, c, y, x] = sum_ij K[(b,) y, x, i, j] * image[b, c, y+i-p, x+j-p]."""
    b, _, h, w = image.shape
    k = kernels.shape[-1]
    p = k // 2
    out = torch.zeros_like(image)
    for bb in range(b):
        kern = kernels[bb] if kernels.dim() == 5 else kernels
        for y in range(h):
            for x in range(w):
                for i in range(k):
                    for j in range(k):
                        yy, xx = y + i - p, x + j - p
                        if 0 <= yy < h and 0 <= xx < w:
                            out[bb, :, y, x] += kern[y, x, i, j] * image[bb, :, yy, xx]
    return out


def _rand(*shape, dtype=torch.float64, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=torch.float64).to(dtype=dtype, device=device) - 0.3


@pytest.mark.parametrize("batched", [False, True], ids=["shared", "batched"])
@pytest.mark.parametrize(("h", "w", "k"), [(5, 4, 3), (6, 7, 5), (3, 3, 1), (4, 6, 7)])
def test_matches_reference_and_loop(h, w, k, batched):
    img = _rand(2, 3, h, w)
    kern = _rand(*((2,) if batched else ()), h, w, k, k, seed=1)
    want = loop_conv(img, kern)
    torch.testing.assert_close(sv_conv2d(img, kern), want, rtol=0, atol=1e-12)
    torch.testing.assert_close(sv_conv2d_reference(img, kern), want, rtol=0, atol=1e-12)
    # the autograd/export path (out-of-place) gives the same numbers
    torch.testing.assert_close(sv_conv2d(img.requires_grad_(), kern).detach(), want, rtol=0, atol=1e-12)


def test_device_dtype(device, dtype):
    img = _rand(2, 2, 9, 8, dtype=dtype, device=device)
    kern = _rand(9, 8, 5, 5, dtype=dtype, device=device, seed=2)
    out = sv_conv2d(img, kern)
    assert out.dtype == dtype and out.device.type == device.type and out.shape == img.shape
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(out, sv_conv2d_reference(img, kern), rtol=0, atol=tol)


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
def test_reduced_precision_computed_in_float32(low):
    img, kern = _rand(1, 3, 6, 5), _rand(6, 5, 3, 3, seed=3)
    out = sv_conv2d(img.to(low), kern.to(low))
    assert out.dtype == low
    want = sv_conv2d(img.to(low).float(), kern.to(low).float()).to(low)
    torch.testing.assert_close(out, want, rtol=0, atol=0)
    # mixed: promotion to the wider input
    assert sv_conv2d(img.to(low), kern.float()).dtype == torch.float32


def test_band_path_spans_several_bands(monkeypatch):
    # force tiny bands so that the band loop, including a short last band, is exercised
    import torchsss.ops.sv_conv as mod

    monkeypatch.setattr(mod, "_BAND_BYTES", 1)
    img = _rand(2, 3, 21, 6)
    for kern in (_rand(21, 6, 3, 3, seed=4), _rand(2, 21, 6, 5, 5, seed=5)):
        torch.testing.assert_close(sv_conv2d(img, kern), sv_conv2d_reference(img, kern), rtol=0, atol=1e-12)


def test_identity_and_ones():
    img = _rand(2, 3, 5, 6)
    torch.testing.assert_close(sv_conv2d(img, torch.ones(5, 6, 1, 1, dtype=torch.float64)), img, rtol=0, atol=0)
    delta = torch.zeros(5, 6, 3, 3, dtype=torch.float64)
    delta[..., 1, 1] = 1.0
    torch.testing.assert_close(sv_conv2d(img, delta), img, rtol=0, atol=0)
    # box kernel of ones = sum over the 3x3 neighbourhood with zero padding
    box = sv_conv2d(torch.ones(1, 1, 4, 4, dtype=torch.float64), torch.ones(4, 4, 3, 3, dtype=torch.float64))
    want = torch.tensor([[4, 6, 6, 4], [6, 9, 9, 6], [6, 9, 9, 6], [4, 6, 6, 4]], dtype=torch.float64)
    torch.testing.assert_close(box[0, 0], want, rtol=0, atol=0)


@pytest.mark.parametrize(("di", "dj"), [(-2, 0), (1, 2), (2, -1), (0, 0)])
def test_delta_kernel_shifts_with_zero_border(di, dj):
    h, w, k = 6, 7, 5
    img = _rand(1, 2, h, w)
    kern = torch.zeros(h, w, k, k, dtype=torch.float64)
    kern[..., k // 2 + di, k // 2 + dj] = 1.0
    out = sv_conv2d(img, kern)
    want = torch.zeros_like(img)
    ys, xs = slice(max(0, -di), h - max(0, di)), slice(max(0, -dj), w - max(0, dj))
    want[..., ys, xs] = img[..., max(0, di):h + min(0, di), max(0, dj):w + min(0, dj)]
    torch.testing.assert_close(out, want, rtol=0, atol=0)


def test_spatially_varying_delta():
    # each texel reads a different neighbour
    img = _rand(1, 1, 4, 4)
    kern = torch.zeros(4, 4, 3, 3, dtype=torch.float64)
    kern[:2, ..., 0, 1] = 1.0  # top half reads the texel above
    kern[2:, ..., 1, 0] = 1.0  # bottom half reads the texel to the left
    out = sv_conv2d(img, kern)[0, 0]
    assert torch.equal(out[0], torch.zeros(4, dtype=torch.float64))
    assert torch.equal(out[1], img[0, 0, 0])
    assert torch.equal(out[2:, 0], torch.zeros(2, dtype=torch.float64))
    assert torch.equal(out[2:, 1:], img[0, 0, 2:, :3])


def test_batched_kernels_equal_per_element_calls():
    img = _rand(3, 2, 6, 5)
    kern = _rand(3, 6, 5, 5, 5, seed=6)
    out = sv_conv2d(img, kern)
    for b in range(3):
        torch.testing.assert_close(out[b:b + 1], sv_conv2d(img[b:b + 1], kern[b]), rtol=0, atol=1e-12)
    # shared kernels == batched kernels repeated
    torch.testing.assert_close(sv_conv2d(img, kern[0]), sv_conv2d(img, kern[0].expand(3, -1, -1, -1, -1)),
                               rtol=0, atol=1e-12)


def test_extremes():
    # k larger than the image: only the in-image taps contribute
    img, kern = _rand(1, 2, 3, 2), _rand(3, 2, 9, 9, seed=7)
    torch.testing.assert_close(sv_conv2d(img, kern), loop_conv(img, kern), rtol=0, atol=1e-12)
    # 1x1 image: only the centre tap
    img1, kern1 = _rand(2, 3, 1, 1), _rand(1, 1, 5, 5, seed=8)
    torch.testing.assert_close(sv_conv2d(img1, kern1), img1 * kern1[0, 0, 2, 2], rtol=0, atol=0)
    # all-zero kernels
    assert torch.equal(sv_conv2d(_rand(2, 3, 4, 5), torch.zeros(4, 5, 3, 3, dtype=torch.float64)),
                       torch.zeros(2, 3, 4, 5, dtype=torch.float64))


@pytest.mark.parametrize("batched", [False, True], ids=["shared", "batched"])
def test_gradcheck(batched):
    img = _rand(2, 2, 4, 3).requires_grad_()
    kern = _rand(*((2,) if batched else ()), 4, 3, 3, 3, seed=9).requires_grad_()
    assert torch.autograd.gradcheck(sv_conv2d, (img, kern))
    # gradients agree with the reference's
    g1 = torch.autograd.grad(sv_conv2d(img, kern).square().sum(), (img, kern))
    g2 = torch.autograd.grad(sv_conv2d_reference(img, kern).square().sum(), (img, kern))
    for a, b in zip(g1, g2):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_bad_inputs():
    img, kern = torch.rand(1, 3, 4, 5), torch.rand(4, 5, 3, 3)
    with pytest.raises(TypeError, match=r"image: expected a torch.Tensor, got ndarray"):
        sv_conv2d(np.zeros((1, 3, 4, 5)), kern)
    with pytest.raises(TypeError, match=r"image: expected a floating-point tensor, got dtype torch.int64"):
        sv_conv2d(torch.ones(1, 3, 4, 5, dtype=torch.long), kern)
    with pytest.raises(TypeError, match=r"kernels: expected a floating-point tensor"):
        sv_conv2d(img, torch.ones(4, 5, 3, 3, dtype=torch.int32))
    with pytest.raises(ValueError, match=r"image: expected shape \(B, C, H, W\) \(4 dims\), got \(3, 4, 5\)"):
        sv_conv2d(img[0], kern)
    with pytest.raises(ValueError, match=r"kernels: expected shape \(H, W, k, k\) or \(B, H, W, k, k\)"):
        sv_conv2d(img, kern[0])
    with pytest.raises(ValueError, match=r"kernels: expected square kernels of odd size k.*got \(4, 5, 2, 2\)"):
        sv_conv2d(img, torch.rand(4, 5, 2, 2))
    with pytest.raises(ValueError, match=r"kernels: expected square kernels of odd size k.*got \(4, 5, 3, 5\)"):
        sv_conv2d(img, torch.rand(4, 5, 3, 5))
    with pytest.raises(ValueError, match=r"kernels: expected shape \(\.\.\., H, W, k, k\) with H=4, W=5"):
        sv_conv2d(img, torch.rand(5, 4, 3, 3))
    with pytest.raises(ValueError, match=r"kernels: expected shape \(B, H, W, k, k\) with B=1"):
        sv_conv2d(img, torch.rand(2, 4, 5, 3, 3))
    with pytest.raises(ValueError, match=r"kernels: expected square kernels"):
        sv_conv2d_reference(img, torch.rand(4, 5, 4, 4))


# -- ONNX ----------------------------------------------------------------------------------------------------------
class _SVConv(torch.nn.Module):
    """Test-only wrapper: ops/ stays free of nn.Modules."""

    def forward(self, image, kernels):
        return sv_conv2d(image, kernels)


@pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning")
@pytest.mark.filterwarnings("ignore:# The axis name:UserWarning")
@pytest.mark.parametrize("batched", [False, True], ids=["shared", "batched"])
def test_onnx_export_dynamic_size(tmp_path, batched):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    from torch.export import Dim

    from torchsss.export import compare_with_eager, export_onnx, run_onnxruntime

    k = 5
    bdim, cdim, hdim, wdim = Dim("B", min=1, max=64), Dim("C", min=1, max=64), Dim("H"), Dim("W")
    kshape = (2, 12, 10, k, k) if batched else (12, 10, k, k)
    args = (torch.rand(2, 3, 12, 10), torch.rand(*kshape))
    if batched:
        dyn = ({0: bdim, 1: cdim, 2: hdim, 3: wdim}, {0: bdim, 1: hdim, 2: wdim})
    else:
        dyn = ({0: bdim, 1: cdim, 2: hdim, 3: wdim}, {0: hdim, 1: wdim})
    path = export_onnx(_SVConv(), args, tmp_path / "svconv.onnx", dynamic_shapes=dyn)
    # run at a different batch, channel count and image size than exported
    test_k = (3, 17, 9, k, k) if batched else (17, 9, k, k)
    test = (torch.rand(3, 2, 17, 9) - 0.5, torch.rand(*test_k))
    res = compare_with_eager(_SVConv(), path, test)
    assert res["shapes"] == [(3, 2, 17, 9)]
    assert res["max_abs_diff"] <= 1e-6, res
    (out,) = run_onnxruntime(path, test)
    np.testing.assert_allclose(out, sv_conv2d_reference(*test).numpy(), rtol=0, atol=1e-5)


def _to_planes(kern):
    k = kern.shape[-1]
    lead = kern.shape[:-2]
    return kern.reshape(*lead, k * k).movedim(-1, -3)


@pytest.mark.parametrize("mode", ["off", "on"])
@pytest.mark.parametrize("batched", [False, True], ids=["shared", "batched"])
@pytest.mark.parametrize(("h", "w", "k"), [(5, 4, 3), (6, 7, 5), (3, 3, 1)])
def test_planes_layout_matches_the_loop(h, w, k, batched, mode, monkeypatch):
    """sv_conv2d_planes (kernels given tap-major, no permuting copy) against the loop: eager, compiled, autograd."""
    monkeypatch.setenv("TORCHSSS_COMPILE", mode)
    from torchsss.ops import sv_conv2d_planes

    img = _rand(2, 3, h, w, dtype=torch.float32)
    kern = _rand(*((2,) if batched else ()), h, w, k, k, seed=1, dtype=torch.float32)
    planes = _to_planes(kern)
    assert planes.shape == (*((2,) if batched else ()), k * k, h, w)
    want = loop_conv(img.double(), kern.double()).float()
    with torch.no_grad():
        torch.testing.assert_close(sv_conv2d_planes(img, planes), want, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(sv_conv2d_planes(img, planes.contiguous()), want, rtol=1e-5, atol=1e-6)
    got = sv_conv2d_planes(img.requires_grad_(), planes)
    torch.testing.assert_close(got.detach(), want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("batched", [False, True], ids=["shared", "batched"])
def test_planes_gradcheck(batched):
    from torchsss.ops import sv_conv2d_planes

    img = _rand(1, 2, 4, 5).requires_grad_()
    planes = _rand(*((1,) if batched else ()), 9, 4, 5, seed=2).requires_grad_()
    assert torch.autograd.gradcheck(sv_conv2d_planes, (img, planes))


def test_planes_bad_inputs():
    from torchsss.ops import sv_conv2d_planes

    img = _rand(1, 2, 4, 5)
    with pytest.raises(ValueError, match="planes: expected k\\*k taps with k odd"):
        sv_conv2d_planes(img, _rand(8, 4, 5))
    with pytest.raises(ValueError, match="planes: expected k\\*k taps with k odd"):
        sv_conv2d_planes(img, _rand(4, 4, 5))  # k = 2 is even
    with pytest.raises(ValueError, match="H=4, W=5"):
        sv_conv2d_planes(img, _rand(9, 5, 4))
    with pytest.raises(ValueError, match="B=1"):
        sv_conv2d_planes(img, _rand(2, 9, 4, 5))
    with pytest.raises(ValueError, match="planes: expected shape"):
        sv_conv2d_planes(img, _rand(9, 4))
    with pytest.raises(ValueError, match="image: expected shape"):
        sv_conv2d_planes(img[0], _rand(9, 4, 5))
    with pytest.raises(TypeError, match="planes"):
        sv_conv2d_planes(img, torch.ones(9, 4, 5, dtype=torch.int64))
