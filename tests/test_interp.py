"""torchsss.ops.barycentric_interpolate: linear and geometric interpolation of per-vertex values at points."""

from __future__ import annotations

import math

import pytest
import torch

from torchsss.ops import barycentric_interpolate, barycentric_interpolate_reference

F64 = torch.float64


def _random(b=2, v=7, c=3, p=11, seed=0, positive=True):
    g = torch.Generator().manual_seed(seed)
    values = torch.rand(b, v, c, generator=g, dtype=F64) + (0.05 if positive else -0.3)
    corners = torch.randint(0, v, (p, 3), generator=g)
    bary = torch.rand(p, 3, generator=g, dtype=F64)
    return values, corners, bary / bary.sum(1, keepdim=True)


@pytest.mark.parametrize("mode", ["linear", "geometric", "adaptive"])
@pytest.mark.parametrize("positive", [True, False])
def test_against_the_loop(mode, positive):
    values, corners, bary = _random(positive=positive)
    torch.testing.assert_close(barycentric_interpolate(values, corners, bary, mode),
                               barycentric_interpolate_reference(values, corners, bary, mode), rtol=1e-12, atol=0)


def test_geometric_reproduces_an_exponential_and_linear_a_plane():
    """Values e^{-s x} at the corners of triangles on a line: the geometric mean is e^{-s x} at every point (closed
    form); the linear rule overestimates it (convex) by a known amount, and reproduces a linear field exactly."""
    s = 3.0
    x = torch.tensor([0.0, 0.4, 1.0], dtype=F64)  # vertex positions along x
    values = torch.exp(-s * x)[None, :, None]
    corners = torch.tensor([[0, 1, 2]] * 5)
    g = torch.Generator().manual_seed(1)
    bary = torch.rand(5, 3, generator=g, dtype=F64)
    bary = bary / bary.sum(1, keepdim=True)
    px = bary @ x
    geo = barycentric_interpolate(values, corners, bary, "geometric")[0, :, 0]
    torch.testing.assert_close(geo, torch.exp(-s * px), rtol=1e-13, atol=0)
    lin = barycentric_interpolate(values, corners, bary, "linear")[0, :, 0]
    assert bool((lin > torch.exp(-s * px)).all())  # Jensen: the chord lies above a convex function
    plane = (2.0 - 0.5 * x)[None, :, None]
    torch.testing.assert_close(barycentric_interpolate(plane, corners, bary)[0, :, 0], 2.0 - 0.5 * px, rtol=1e-14,
                               atol=0)
    # adaptive: geometric where the corners differ by 2x or more (e^{-3} here), linear within a few %
    torch.testing.assert_close(barycentric_interpolate(values, corners, bary, "adaptive")[0, :, 0], geo, rtol=1e-14,
                               atol=0)
    near = torch.tensor([[[1.0], [1.01], [1.02]]], dtype=F64)
    want = barycentric_interpolate(near, corners, bary)
    got = barycentric_interpolate(near, corners, bary, "adaptive")
    geo_near = barycentric_interpolate(near, corners, bary, "geometric")
    torch.testing.assert_close(got, want + 0.02 * (geo_near - want), rtol=1e-13, atol=0)  # w = 1.02 / 1 - 1


def test_extremes():
    """Equal corners give that value in both modes; a zero corner falls back to linear (no NaN, no -inf); values
    spanning 1e-300..1e300 stay finite; a vertex corner (bary one-hot) returns the vertex value."""
    corners = torch.tensor([[0, 1, 2]])
    bary = torch.tensor([[0.2, 0.3, 0.5]], dtype=F64)
    same = torch.full((1, 3, 1), 0.7, dtype=F64)
    for mode in ("linear", "geometric", "adaptive"):
        torch.testing.assert_close(barycentric_interpolate(same, corners, bary, mode), same[:, :1], rtol=1e-14, atol=0)
    zero = torch.tensor([[[0.0], [1.0], [2.0]]], dtype=F64)
    out = barycentric_interpolate(zero, corners, bary, "geometric")
    torch.testing.assert_close(out, barycentric_interpolate(zero, corners, bary, "linear"))
    wide = torch.tensor([[[1e-300], [1.0], [1e300]]], dtype=F64)
    out = barycentric_interpolate(wide, corners, bary, "geometric")
    assert math.isfinite(float(out)) and abs(math.log10(float(out)) - (0.5 * 300 - 0.2 * 300)) < 1e-9
    onehot = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    values, _, _ = _random()
    got = barycentric_interpolate(values, torch.tensor([[3, 5, 6]]), onehot, "geometric")
    torch.testing.assert_close(got, values[:, 5:6], rtol=1e-14, atol=0)
    empty = barycentric_interpolate(values, torch.zeros(0, 3, dtype=torch.int64), torch.zeros(0, 3, dtype=F64))
    assert empty.shape == (2, 0, 3)


@pytest.mark.parametrize("mode", ["linear", "geometric", "adaptive"])
def test_gradcheck(mode):
    values, corners, bary = _random(b=1, v=5, c=2, p=4)
    values.requires_grad_(True)
    bary.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v, b: barycentric_interpolate(v, corners, b, mode), (values, bary))
    # a zero corner: the linear branch's gradient, finite
    z = values.detach().clone()
    z[0, corners[0, 0]] = 0.0
    z.requires_grad_(True)
    barycentric_interpolate(z, corners, bary.detach(), mode).sum().backward()
    assert bool(torch.isfinite(z.grad).all())


def test_dtype_promotion():
    values, corners, bary = _random()
    out = barycentric_interpolate(values.float(), corners, bary, "geometric")
    assert out.dtype == F64


def test_typed_errors():
    values, corners, bary = _random()
    with pytest.raises(TypeError, match="values"):
        barycentric_interpolate(values.long(), corners, bary)
    with pytest.raises(TypeError, match="corners"):
        barycentric_interpolate(values, corners.double(), bary)
    with pytest.raises(TypeError, match="bary"):
        barycentric_interpolate(values, corners, [0.3, 0.3, 0.4])
    with pytest.raises(ValueError, match="values: expected shape"):
        barycentric_interpolate(values[0], corners, bary)
    with pytest.raises(ValueError, match="bary: expected shape"):
        barycentric_interpolate(values, corners, bary[:-1])
    with pytest.raises(ValueError, match="corners: expected vertex indices"):
        barycentric_interpolate(values, corners + 100, bary)
    with pytest.raises(ValueError, match="mode"):
        barycentric_interpolate(values, corners, bary, "cubic")
