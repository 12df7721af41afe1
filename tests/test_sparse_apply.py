"""sparse_apply_t (Lensch global response y = F^T x): csr and scatter vs a dense matmul, gradients, ONNX export."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchsss.ops import SparsePattern, sparse_apply_t, sparse_pattern

METHODS = ["csr", "scatter", "auto"]

# torch's exporter internals warn about a deprecated pytree API and unused axis names; not ours to fix.
pytestmark = [
    pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning"),
    pytest.mark.filterwarnings("ignore:# The axis name:UserWarning"),
]


def _random_case(n_rows, n_cols, nnz, *, seed=0, dup=True):
    g = torch.Generator().manual_seed(seed)
    rows = torch.randint(0, n_rows, (nnz,), generator=g)
    cols = torch.randint(0, n_cols, (nnz,), generator=g)
    if dup and nnz >= 4:  # make sure some (i, j) positions repeat
        rows[1], cols[1] = rows[0], cols[0]
        rows[3], cols[3] = rows[0], cols[0]
    return rows, cols


def dense_apply(x, rows, cols, values, n_rows, n_cols):
    """y = F^T x with F built densely (duplicates accumulate)."""
    x3 = x if x.dim() == 3 else x.unsqueeze(0)
    c = x3.shape[-1]
    v = values if values.dim() == 2 else values.unsqueeze(-1).expand(-1, c)
    dense = torch.zeros(n_rows, n_cols, c, dtype=v.dtype).index_put_((rows, cols), v, accumulate=True)
    y = torch.einsum("ijc,bic->bjc", dense, x3)
    return y if x.dim() == 3 else y[0]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("per_channel", [False, True], ids=["shared", "per_channel"])
@pytest.mark.parametrize("xshape", [(3,), (2, 3), (1, 1)], ids=["2d", "batch2", "b1c1"])
@pytest.mark.parametrize(("n_rows", "n_cols", "nnz"), [(9, 7, 40), (5, 12, 6), (20, 3, 100), (6, 6, 0)])
def test_matches_dense(method, per_channel, xshape, n_rows, n_cols, nnz):
    rows, cols = _random_case(n_rows, n_cols, nnz)
    pat = sparse_pattern(rows, cols, n_rows, n_cols)
    c = xshape[-1]
    x = torch.rand(*((xshape[0],) if len(xshape) == 2 else ()), n_rows, c, dtype=torch.float64) - 0.5
    values = torch.rand(*((nnz, c) if per_channel else (nnz,)), dtype=torch.float64)
    y = sparse_apply_t(x, pat, values, method=method)
    want = dense_apply(x, rows, cols, values, n_rows, n_cols)
    assert y.shape == want.shape == ((*x.shape[:-2], n_cols, c))
    torch.testing.assert_close(y, want, rtol=0, atol=1e-12)
    if nnz == 0:
        assert torch.equal(y, torch.zeros_like(y))


def test_duplicates_add_and_empty_rows_cols():
    # entries: (0,1) twice, (2,1), (2,2); row 1 and column 0 are empty
    rows, cols = torch.tensor([0, 2, 0, 2]), torch.tensor([1, 1, 1, 2])
    pat = sparse_pattern(rows, cols, 3, 3)
    assert pat.t_crow.tolist() == [0, 0, 3, 4]
    assert pat.t_perm.tolist() == [0, 1, 2, 3] and pat.t_col.tolist() == [0, 2, 0, 2]
    x = torch.tensor([[1.0], [100.0], [10.0]], dtype=torch.float64)
    v = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64)
    for method in METHODS:
        y = sparse_apply_t(x, pat, v, method=method)
        assert y.flatten().tolist() == [0.0, 1 + 20 + 3, 40.0]


def test_pattern_fields():
    rows, cols = _random_case(30, 20, 200, seed=3)
    pat = sparse_pattern(rows.int(), cols.int(), 30, 20)
    assert isinstance(pat, SparsePattern) and pat.n_rows == 30 and pat.n_cols == 20
    for t in (pat.rows, pat.cols, pat.t_crow, pat.t_col, pat.t_perm):
        assert t.dtype == torch.int64
    assert pat.t_crow.shape == (21,) and pat.t_crow[-1] == 200
    assert torch.equal(pat.t_col, rows[pat.t_perm].long())
    sorted_cols = cols[pat.t_perm]
    assert bool((sorted_cols[1:] >= sorted_cols[:-1]).all())
    # stable: within one column the original order is kept
    for j in range(20):
        seg = pat.t_perm[pat.t_crow[j]:pat.t_crow[j + 1]]
        assert bool((seg[1:] > seg[:-1]).all())
        assert bool((cols[seg] == j).all())


def test_device_dtype(device, dtype):
    rows, cols = _random_case(15, 11, 60, seed=4)
    pat = sparse_pattern(rows.to(device), cols.to(device), 15, 11)
    x = torch.rand(2, 15, 3, dtype=dtype, device=device)
    v = torch.rand(60, dtype=dtype, device=device)
    want = dense_apply(x.double().cpu(), rows, cols, v.double().cpu(), 15, 11)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for method in METHODS:
        y = sparse_apply_t(x, pat, v, method=method)
        assert y.dtype == dtype and y.device.type == device.type
        torch.testing.assert_close(y.double().cpu(), want, rtol=0, atol=tol)


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
def test_reduced_precision(low):
    rows, cols = _random_case(10, 8, 30, seed=5)
    pat = sparse_pattern(rows, cols, 10, 8)
    x, v = torch.rand(10, 2).to(low), torch.rand(30).to(low)
    for method in METHODS:
        y = sparse_apply_t(x, pat, v, method=method)
        assert y.dtype == low
        torch.testing.assert_close(y, sparse_apply_t(x.float(), pat, v.float(), method="scatter").to(low))


@pytest.mark.parametrize("per_channel", [False, True], ids=["shared", "per_channel"])
def test_gradcheck_scatter(per_channel):
    rows, cols = _random_case(7, 5, 25, seed=6)
    pat = sparse_pattern(rows, cols, 7, 5)
    x = torch.rand(2, 7, 3, dtype=torch.float64, requires_grad=True)
    v = torch.rand(*((25, 3) if per_channel else (25,)), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, v: sparse_apply_t(x, pat, v, method="scatter"), (x, v))
    # "auto" picks a method with a working gradient for values (the pattern has duplicates)
    assert torch.autograd.gradcheck(lambda x, v: sparse_apply_t(x, pat, v), (x, v))
    # csr: gradient w.r.t. x (values constant)
    assert torch.autograd.gradcheck(lambda x: sparse_apply_t(x, pat, v.detach(), method="csr"), (x,))


def test_csr_values_gradient_without_duplicates():
    # documented: torch's CSR backward gives the values gradient when the pattern has no duplicate entries
    n = 6
    rows, cols = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    keep = (rows - cols).abs() <= 1
    pat = sparse_pattern(rows[keep], cols[keep], n, n)
    x = torch.rand(2, n, 2, dtype=torch.float64, requires_grad=True)
    v = torch.rand(int(keep.sum()), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, v: sparse_apply_t(x, pat, v, method="csr"), (x, v))


def test_bad_inputs():
    rows, cols = torch.tensor([0, 1, 2]), torch.tensor([1, 0, 1])
    pat = sparse_pattern(rows, cols, 3, 2)
    x, v = torch.rand(3, 2), torch.rand(3)
    with pytest.raises(ValueError, match=r"rows: expected indices in \[0, n_rows\) = \[0, 2\), got 2"):
        sparse_pattern(rows, cols, 2, 2)
    with pytest.raises(ValueError, match=r"cols: expected indices in \[0, n_cols\) = \[0, 2\), got -1"):
        sparse_pattern(rows, torch.tensor([1, -1, 0]), 3, 2)
    with pytest.raises(ValueError, match=r"cols: expected shape \(3,\) \(the shape of rows\), got \(2,\)"):
        sparse_pattern(rows, cols[:2], 3, 2)
    with pytest.raises(ValueError, match=r"rows: expected shape \(nnz,\) \(1 dim\), got \(3, 1\)"):
        sparse_pattern(rows[:, None], cols, 3, 2)
    with pytest.raises(TypeError, match=r"rows: expected an integer tensor, got dtype torch.float32"):
        sparse_pattern(rows.float(), cols, 3, 2)
    with pytest.raises(TypeError, match=r"cols: expected a torch.Tensor of int64 indices, got list"):
        sparse_pattern(rows, [1, 0, 1], 3, 2)
    with pytest.raises(TypeError, match=r"n_cols: expected an int >= 0, got float"):
        sparse_pattern(rows, cols, 3, 2.0)
    with pytest.raises(ValueError, match=r"n_rows: expected an int >= 0, got -1"):
        sparse_pattern(rows, cols, -1, 2)
    with pytest.raises(ValueError, match=r"x: expected shape \(\.\.\., N, C\) with N = n_rows = 3, got \(4, 2\)"):
        sparse_apply_t(torch.rand(4, 2), pat, v)
    with pytest.raises(ValueError, match=r"x: expected shape \(N, C\) or \(B, N, C\)"):
        sparse_apply_t(torch.rand(3), pat, v)
    with pytest.raises(ValueError, match=r"values: expected shape \(nnz,\) = \(3,\) or \(nnz, C\) = \(3, 2\), got \(4"):
        sparse_apply_t(x, pat, torch.rand(4))
    with pytest.raises(ValueError, match=r"values: expected shape .* got \(3, 3\)"):
        sparse_apply_t(x, pat, torch.rand(3, 3))
    with pytest.raises(TypeError, match=r"x: expected a floating-point tensor, got dtype torch.int64"):
        sparse_apply_t(torch.ones(3, 2, dtype=torch.long), pat, v)
    with pytest.raises(TypeError, match=r"values: expected a torch.Tensor, got ndarray"):
        sparse_apply_t(x, pat, np.ones(3))
    with pytest.raises(TypeError, match=r"pattern: expected a SparsePattern \(from sparse_pattern\), got tuple"):
        sparse_apply_t(x, (rows, cols), v)
    with pytest.raises(ValueError, match=r"method: expected one of auto, csr, scatter, got 'dense'"):
        sparse_apply_t(x, pat, v, method="dense")


# -- ONNX ----------------------------------------------------------------------------------------------------------
class _SparseApply(torch.nn.Module):
    """Test-only wrapper: the pattern lives in buffers, x and values are graph inputs."""

    def __init__(self, pattern: SparsePattern) -> None:
        super().__init__()
        for name in ("rows", "cols", "t_crow", "t_col", "t_perm"):
            self.register_buffer(name, getattr(pattern, name))
        self.n_rows, self.n_cols = pattern.n_rows, pattern.n_cols

    def forward(self, x, values):
        # method "auto": csr in eager mode, scatter while exporting (the CSR arrays drop out of the graph)
        pat = SparsePattern(self.rows, self.cols, self.n_rows, self.n_cols, self.t_crow, self.t_col, self.t_perm)
        return sparse_apply_t(x, pat, values)


class _SparseApplyInputs(torch.nn.Module):
    """Test-only wrapper with the pattern as graph inputs, so that N and nnz can vary at run time."""

    def __init__(self, n_cols: int) -> None:
        super().__init__()
        self.n_cols = n_cols

    def forward(self, x, values, rows, cols):
        empty = rows[:0]  # CSR arrays unused by the scatter method
        pat = SparsePattern(rows, cols, x.shape[-2], self.n_cols, empty, empty, empty)
        return sparse_apply_t(x, pat, values, method="scatter")


def _onnx_deps():
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")


@pytest.mark.parametrize("per_channel", [False, True], ids=["shared", "per_channel"])
def test_onnx_export_pattern_buffers(tmp_path, per_channel):
    _onnx_deps()
    from torch.export import Dim

    from torchsss.export import compare_with_eager, export_onnx, run_onnxruntime

    rows, cols = _random_case(50, 40, 300, seed=7)
    pat = sparse_pattern(rows, cols, 50, 40)
    module = _SparseApply(pat)
    vshape = (300, 3) if per_channel else (300,)
    args = (torch.rand(2, 50, 3), torch.rand(*vshape))
    dyn = ({0: Dim("B", min=1, max=1024)}, None)
    path = export_onnx(module, args, tmp_path / "sparse.onnx", dynamic_shapes=dyn)
    test = (torch.rand(5, 50, 3) - 0.5, torch.rand(*vshape))  # a different batch, different values
    res = compare_with_eager(module, path, test)
    assert res["shapes"] == [(5, 40, 3)]
    assert res["max_abs_diff"] <= 1e-6, res
    (out,) = run_onnxruntime(path, test)
    want = dense_apply(test[0].double(), rows, cols, test[1].double(), 50, 40)
    np.testing.assert_allclose(out, want.numpy(), rtol=0, atol=1e-5)


def test_onnx_export_dynamic_n_and_nnz(tmp_path):
    _onnx_deps()
    from torch.export import Dim

    from torchsss.export import compare_with_eager, export_onnx

    rows, cols = _random_case(50, 40, 300, seed=8)
    module = _SparseApplyInputs(40)
    nnz, n = Dim("nnz", min=2), Dim("N", min=2)
    args = (torch.rand(2, 50, 3), torch.rand(300), rows, cols)
    dyn = ({0: Dim("B", min=1, max=1024), 1: n}, {0: nnz}, {0: nnz}, {0: nnz})
    path = export_onnx(module, args, tmp_path / "sparse_dyn.onnx", dynamic_shapes=dyn)
    rows2, cols2 = _random_case(77, 40, 1234, seed=9)
    test = (torch.rand(3, 77, 3), torch.rand(1234), rows2, cols2)
    res = compare_with_eager(module, path, test)
    assert res["shapes"] == [(3, 40, 3)]
    assert res["max_abs_diff"] <= 1e-6, res
