"""IcdfSampler: the module twin of icdf_sample with the pyramid depth fixed at build time."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchsss.modules import IcdfSampler
from torchsss.ops.icdf import MAX_LEVELS, icdf_sample, pyramid_levels

F64 = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _pdf(b, h, w, seed, dtype=F64):
    pdf = torch.rand(b, 1, h, w, generator=_gen(seed), dtype=F64) ** 3
    pdf[:, :, h // 3, :] = 0  # an empty row
    return pdf.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("h, w", [(1, 1), (7, 13), (16, 16), (33, 20)])
def test_matches_the_functional_op(h, w, dtype):
    pdf = _pdf(2, h, w, seed=1, dtype=dtype)
    u = torch.rand(2, 500, 2, generator=_gen(2), dtype=dtype)
    sampler = IcdfSampler(size=(h, w))
    assert sampler.levels == pyramid_levels(h, w)
    xy, p = sampler(pdf, u)
    want_xy, want_p = icdf_sample(pdf, u)  # the op's default depth is the same for a map of this size
    assert torch.equal(xy, want_xy) and torch.equal(p, want_p) and xy.dtype == dtype
    # a deeper fixed pyramid (one graph for every map up to 2**levels square) is the op with that depth
    deep = IcdfSampler(levels=pyramid_levels(h, w) + 2, size=(h, w))
    got, want = deep(pdf, u), icdf_sample(pdf, u, pyramid_levels(h, w) + 2)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    # and so is a sampler built for larger maps, on a smaller one
    assert all(torch.equal(a, b) for a, b in zip(IcdfSampler(6)(pdf, u), icdf_sample(pdf, u, 6)))


def test_levels_from_size_or_given():
    assert IcdfSampler(size=(1, 1)).levels == 0
    assert IcdfSampler(size=(512, 513)).levels == 10
    assert IcdfSampler(levels=4).levels == 4
    assert IcdfSampler(levels=4, size=[16, 9]).levels == 4
    assert IcdfSampler(None, (5, 3)).levels == 3
    m = IcdfSampler(levels=3)
    assert repr(m) == "IcdfSampler(levels=3)"
    assert list(m.parameters()) == [] and list(m.buffers()) == [] and m.state_dict() == {}


def test_gradcheck():
    pdf = (torch.rand(2, 1, 3, 5, generator=_gen(3), dtype=F64) + 0.1).requires_grad_()
    u = torch.rand(2, 6, 2, generator=_gen(4), dtype=F64).requires_grad_()
    sampler = IcdfSampler(size=(3, 5))
    assert torch.autograd.gradcheck(sampler, (pdf, u))
    # the same gradients as the op's
    xy, p = sampler(pdf, u)
    xy_o, p_o = icdf_sample(pdf, u)
    g = torch.autograd.grad((xy.sum() + p.sum()), (pdf, u))
    g_o = torch.autograd.grad((xy_o.sum() + p_o.sum()), (pdf, u))
    assert all(torch.equal(a, b) for a, b in zip(g, g_o))


def test_bad_arguments_raise_typed_errors():
    with pytest.raises(ValueError, match=r"levels, size: expected levels \(an int\) or the map size"):
        IcdfSampler()
    with pytest.raises(TypeError, match=r"levels: expected an int or None, got float"):
        IcdfSampler(4.0)
    with pytest.raises(TypeError, match=r"levels: expected an int or None, got bool"):
        IcdfSampler(True)
    with pytest.raises(ValueError, match=rf"levels: expected an int in \[0, {MAX_LEVELS}\], got 16"):
        IcdfSampler(16)
    with pytest.raises(ValueError, match=rf"levels: expected an int in \[0, {MAX_LEVELS}\], got -1"):
        IcdfSampler(-1)
    with pytest.raises(ValueError, match=r"levels: expected 2\*\*levels >= max\(H, W\) = 13 \(size\), got levels=3"):
        IcdfSampler(3, size=(7, 13))
    with pytest.raises(TypeError, match=r"size: expected a \(H, W\) pair of ints >= 1 or None, got int"):
        IcdfSampler(size=16)
    with pytest.raises(TypeError, match=r"size: expected a \(H, W\) pair of ints >= 1 or None, got \(16.0, 16\)"):
        IcdfSampler(size=(16.0, 16))
    with pytest.raises(TypeError, match=r"size: expected a \(H, W\) pair of ints >= 1 or None, got \(1, 2, 3\)"):
        IcdfSampler(size=(1, 2, 3))
    with pytest.raises(ValueError, match=r"size: expected a \(H, W\) pair of ints >= 1, got \(0, 4\)"):
        IcdfSampler(size=(0, 4))
    with pytest.raises(ValueError, match=rf"size: expected max\(H, W\) <= 2\*\*{MAX_LEVELS}"):
        IcdfSampler(size=(1, 2**MAX_LEVELS + 1))
    # a map larger than the fixed pyramid, and bad inputs, are reported by the op
    sampler = IcdfSampler(size=(8, 8))
    with pytest.raises(ValueError, match=r"levels: expected 2\*\*levels >= max\(H, W\) = 9, got levels=3"):
        sampler(torch.ones(1, 1, 9, 8), torch.rand(1, 4, 2))
    with pytest.raises(ValueError, match=r"u: expected values in \[0, 1\)"):
        sampler(torch.ones(1, 1, 8, 8), torch.full((1, 4, 2), 1.0))
    with pytest.raises(TypeError, match=r"pdf: expected a torch.Tensor, got ndarray"):
        sampler(np.ones((1, 1, 8, 8)), torch.rand(1, 4, 2))


# with -m slow: IcdfSampler.forward is icdf_sample(pdf, u, levels); the same graph (levels 6, the same dynamic dims)
# is exported in the default run by tests/test_icdf_sample.py::test_onnx_export_dynamic_sizes (other batch, sample
# count and map size; empty maps, a delta, holes, extreme u; bit for bit)
@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning")
@pytest.mark.filterwarnings("ignore:# The axis name:UserWarning")
def test_onnx_export_dynamic_sample_count(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    from torch.export import Dim

    from torchsss.export import compare_with_eager, export_onnx

    sampler = IcdfSampler(size=(40, 50))  # levels = 6: maps up to 64 x 64
    b, n, h, w = Dim("B", max=64), Dim("N"), Dim("H", max=64), Dim("W", max=64)
    args = (_pdf(2, 40, 50, seed=5, dtype=torch.float32), torch.rand(2, 100, 2, generator=_gen(6)))
    path = export_onnx(sampler, args, tmp_path / "sampler.onnx", dynamic_shapes=({0: b, 2: h, 3: w}, {0: b, 1: n}))
    # another sample count (and batch, and map size within 2**levels), an all-zero map
    pdf = _pdf(3, 40, 50, seed=7, dtype=torch.float32)
    pdf[1] = 0
    for test in ((pdf, torch.rand(3, 2049, 2, generator=_gen(8))),
                 (_pdf(1, 17, 63, seed=9, dtype=torch.float32), torch.rand(1, 7, 2, generator=_gen(10)))):
        res = compare_with_eager(sampler, path, test)
        n_test = test[1].shape[1]
        assert res["shapes"] == [(test[0].shape[0], n_test, 2), (test[0].shape[0], n_test)]
        assert res["max_abs_diff"] == 0.0, res  # bit for bit: the same sums in the same order
