"""NewtonRaphsonSearch: the module twin of newton_raphson_intersect (same outputs, gradients, errors, ONNX)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchsss.modules import CausticMap, NewtonRaphsonSearch
from torchsss.ops.newton_raphson import newton_raphson_intersect

F64 = torch.float64
HALF = 20.0  # half width of the orthographic light frustum (mm)


pytestmark = pytest.mark.usefixtures("one_thread")


def _view_proj(b: int = 1, dtype=F64) -> torch.Tensor:
    """(B, 4, 4) light looking down -z: NDC x = x / HALF, y = y / HALF, depth growing downwards."""
    m = torch.zeros(4, 4, dtype=dtype)
    m[0, 0] = m[1, 1] = 1.0 / HALF
    m[2, 2] = -0.01
    m[3, 3] = 1.0
    return m.expand(b, 4, 4).clone()


def _texture(b: int, h: int, w: int, dtype=F64, holes: bool = True) -> torch.Tensor:
    """(B, 3, H, W) positions of tilted planes z = 0.2 x - 0.1 y - k (one per batch element); optional holes."""
    xs = -HALF + (torch.arange(w, dtype=F64) + 0.5) * 2 * HALF / w
    ys = HALF - (torch.arange(h, dtype=F64) + 0.5) * 2 * HALF / h  # row 0 at the top
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    tex = torch.stack([torch.stack([x, y, 0.2 * x - 0.1 * y - k]) for k in range(b)])
    if holes:
        tex[:, :, h // 4: h // 3, w // 5: w // 3] = float("nan")  # no receiver there
    return tex.to(dtype)


def _rays(b: int, n: int, seed: int, dtype=F64) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, N, 3) origins 10-15 mm above the planes and directions within ~20 degrees of straight down."""
    g = torch.Generator().manual_seed(seed)
    o = (torch.rand(b, n, 3, generator=g, dtype=F64) - 0.5) * 20.0
    o[..., 2] = 10.0 + 5.0 * torch.rand(b, n, generator=g, dtype=F64)
    r = (torch.rand(b, n, 3, generator=g, dtype=F64) - 0.5) * 0.7
    r[..., 2] = -1.0
    r = r * (0.5 + torch.rand(b, n, 1, generator=g, dtype=F64))  # any non-zero length
    r[:, 0] = 0.0  # a zero direction: invalid ray
    r[:, 1, 2] = 1.0  # pointing away from the receivers: invalid
    return o.to(dtype), r.to(dtype)


OPTIONS = [
    {},
    {"iterations": 3, "method": "newton"},
    {"iterations": 4, "method": "newton", "fallback": False, "fd_step": 1e-2, "tol": 0.0},
    {"iterations": 0},
    {"iterations": 2, "max_residual": 0.05, "return_info": True},
]


@pytest.mark.parametrize("dtype", [torch.float32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("options", OPTIONS, ids=lambda o: ",".join(f"{k}={v}" for k, v in o.items()) or "defaults")
def test_matches_the_functional_op(options, dtype):
    o, r = _rays(2, 64, seed=1, dtype=dtype)
    tex, vp = _texture(2, 24, 20, dtype), _view_proj(2, dtype)
    module = NewtonRaphsonSearch(**options)
    got = module(o, r, tex, vp)
    want = newton_raphson_intersect(o, r, tex, vp, **options)
    assert len(got) == len(want) == (3 if options.get("return_info") else 2)
    torch.testing.assert_close(got[0], want[0], rtol=0, atol=0)
    assert torch.equal(got[1], want[1]) and got[0].dtype == dtype
    if options.get("return_info"):
        assert got[2].keys() == want[2].keys()
        for key in want[2]:
            torch.testing.assert_close(got[2][key], want[2][key], rtol=0, atol=0)
    if options.get("iterations", 5) > 0:
        assert got[1].float().mean() > 0.5 and not got[1][:, :2].any()  # the checks are not vacuous
    # initial_distance and a (4, 4) matrix pass through as well
    d0 = torch.full(o.shape[:2], 3.0, dtype=dtype)
    got = module(o, r, tex, vp[0], d0)
    want = newton_raphson_intersect(o, r, tex, vp[0], initial_distance=d0, **options)
    torch.testing.assert_close(got[0], want[0], rtol=0, atol=0)
    assert torch.equal(got[1], want[1])


def test_options_are_stored_and_shown():
    m = NewtonRaphsonSearch(3, "newton", fallback=False, fd_step=1e-2, tol=1e-6, max_residual=0.5)
    assert (m.iterations, m.method, m.fallback, m.fd_step, m.tol, m.max_residual, m.return_info) == (
        3, "newton", False, 1e-2, 1e-6, 0.5, False)
    assert "method='newton'" in repr(m) and "max_residual=0.5" in repr(m)
    assert list(m.parameters()) == [] and list(m.buffers()) == [] and m.state_dict() == {}


@pytest.mark.parametrize("method", ["shah", "newton"])
def test_gradcheck(method):
    # planar receivers, no holes: the bilinear lookups of a plane are smooth, so are the distances
    o, r = _rays(1, 8, seed=2)
    o, r = o[:, 2:], r[:, 2:]  # valid rays only
    tex, vp = _texture(1, 16, 16, holes=False), _view_proj()
    module = NewtonRaphsonSearch(3, method)
    assert bool(module(o, r, tex, vp)[1].all())
    o_g, r_g = o.clone().requires_grad_(), r.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: module(a, b, tex, vp)[0], (o_g, r_g), eps=1e-7, atol=1e-6)
    tex_g = tex.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda t: module(o[:, :2], r[:, :2], t, vp)[0], (tex_g,), eps=1e-7,
                                    atol=1e-6, fast_mode=True)


def test_bad_options_raise_typed_errors():
    with pytest.raises(TypeError, match=r"iterations: expected an int >= 0, got float"):
        NewtonRaphsonSearch(2.0)
    with pytest.raises(TypeError, match=r"iterations: expected an int >= 0, got bool"):
        NewtonRaphsonSearch(True)
    with pytest.raises(ValueError, match=r"iterations: expected an int >= 0, got -1"):
        NewtonRaphsonSearch(-1)
    with pytest.raises(ValueError, match=r"method: expected one of \('shah', 'newton'\), got 'bisect'"):
        NewtonRaphsonSearch(method="bisect")
    with pytest.raises(TypeError, match=r"fallback: expected a bool, got int"):
        NewtonRaphsonSearch(fallback=1)
    with pytest.raises(TypeError, match=r"return_info: expected a bool, got str"):
        NewtonRaphsonSearch(return_info="yes")
    with pytest.raises(ValueError, match=r"fd_step: expected a finite number > 0, got 0"):
        NewtonRaphsonSearch(fd_step=0)
    with pytest.raises(ValueError, match=r"tol: expected a finite number >= 0, got -1.0"):
        NewtonRaphsonSearch(tol=-1.0)
    with pytest.raises(TypeError, match=r"tol: expected a real number >= 0, got str"):
        NewtonRaphsonSearch(tol="1e-5")
    with pytest.raises(ValueError, match=r"max_residual: expected a finite number >= 0, got inf"):
        NewtonRaphsonSearch(max_residual=float("inf"))
    # bad inputs are reported by the op, naming the argument
    m = NewtonRaphsonSearch()
    o, r = _rays(1, 4, seed=3)
    with pytest.raises(ValueError, match=r"directions: expected shape \(B, N, 3\)"):
        m(o, r[..., :2], _texture(1, 8, 8), _view_proj())
    with pytest.raises(TypeError, match=r"positions_texture: expected a torch.Tensor, got ndarray"):
        m(o, r, _texture(1, 8, 8).numpy(), _view_proj())


def test_caustic_map_holds_the_searches():
    m = CausticMap(iterations=3, method="shah", back_iterations=7, back_method="newton")
    assert isinstance(m.search, NewtonRaphsonSearch) and isinstance(m.back_search, NewtonRaphsonSearch)
    assert (m.iterations, m.method, m.back_iterations, m.back_method) == (3, "shah", 7, "newton")
    assert (m.search.iterations, m.search.method) == (3, "shah")
    assert (m.back_search.iterations, m.back_search.method) == (7, "newton")
    assert set(m.state_dict()) == {"ior", "absorption"}  # the searches hold no state


# -- ONNX -----------------------------------------------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning")
@pytest.mark.filterwarnings("ignore:# The axis name:UserWarning")
def test_onnx_export_dynamic_sizes(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    from torch.export import Dim

    from torchsss.export import export_onnx, run_onnxruntime

    # Newton with the fallback holds every branch; four iterations are one ONNX Loop
    module = NewtonRaphsonSearch(4, "newton", return_info=True)
    bd, nd, hd, wd = Dim("B", min=1, max=64), Dim("N"), Dim("H"), Dim("W")
    dyn = ({0: bd, 1: nd}, {0: bd, 1: nd}, {0: bd, 2: hd, 3: wd}, {0: bd})

    def args(b, n, h, w, seed):
        o, r = _rays(b, n, seed, torch.float32)
        return o, r, _texture(b, h, w, torch.float32), _view_proj(b, torch.float32)

    path = export_onnx(module, args(2, 40, 24, 20, seed=4), tmp_path / "search.onnx", dynamic_shapes=dyn)
    test = args(3, 57, 37, 29, seed=5)  # another batch, ray count and texture size
    d, valid, oscillated, fallback, residual = run_onnxruntime(path, test)  # the info dict flattened in key order
    with torch.no_grad():
        d_e, valid_e, info_e = module(*test)
        d_64 = module(*(x.double() for x in test))[0].numpy()
    assert d.shape == valid.shape == residual.shape == (3, 57)
    assert np.array_equal(valid, valid_e.numpy()) and valid.mean() > 0.5 and not valid[:, :2].any()
    assert np.array_equal(oscillated, info_e["oscillated"].numpy())
    assert np.array_equal(fallback, info_e["fallback"].numpy())
    # float32 in both runtimes: the bilinear weights and the finite-difference slope (step 1e-3 relative) round
    # differently, a few 1e-5 relative at ~15 mm (as tests/test_newton_raphson.py's export test)
    np.testing.assert_allclose(d, d_e.numpy(), rtol=0, atol=2e-3)
    assert np.abs(d - d_64).max() <= 2e-3 and np.abs(d_e.numpy() - d_64).max() <= 2e-3  # both against float64
    np.testing.assert_allclose(residual, info_e["residual"].numpy(), rtol=0, atol=2e-3)

    # the iterations are one ONNX Loop: eight of them give the same graph as four, and the same answers as eager
    import onnx

    module8 = NewtonRaphsonSearch(8, "newton", return_info=True)
    path8 = export_onnx(module8, args(2, 40, 24, 20, seed=4), tmp_path / "search8.onnx", dynamic_shapes=dyn)
    graphs = [onnx.load(str(p)).graph for p in (path, path8)]
    assert [sum(n.op_type == "Loop" for n in g.node) for g in graphs] == [1, 1]
    assert len(graphs[0].node) == len(graphs[1].node)
    d8, valid8, osc8, _fb8, _res8 = run_onnxruntime(path8, test)
    with torch.no_grad():
        d8_e, valid8_e, info8_e = module8(*test)
    assert np.array_equal(valid8, valid8_e.numpy()) and np.array_equal(osc8, info8_e["oscillated"].numpy())
    np.testing.assert_allclose(d8, d8_e.numpy(), rtol=0, atol=2e-3)

    # the default options (Shah's estimator, 5 iterations): the registry's 'newton' entry (tests/test_export_onnx.py)
