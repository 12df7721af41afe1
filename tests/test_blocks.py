"""``torchsss.modules.blocks.in_blocks``: blocks written into one output equal one call."""

import itertools

import pytest
import torch

from torchsss.modules.blocks import in_blocks


@pytest.mark.parametrize("n", [0, 1, 7, 64])
@pytest.mark.parametrize("block", [1, 3, 64, 1000])
@pytest.mark.parametrize("dim", [0, 1])
def test_in_blocks_equals_one_call(n, block, dim):
    g = torch.Generator().manual_seed(n + block)
    table = torch.randn(3, n, 2, generator=g, dtype=torch.float64)
    calls = []

    def fn(lo, hi):
        calls.append((lo, hi))
        x = table[:, lo:hi].sin() * 2.0  # (3, hi - lo, 2)
        return x.movedim(1, 0) if dim == 0 else x

    want = (table.sin() * 2.0)
    want = want.movedim(1, 0) if dim == 0 else want
    got = in_blocks(fn, n, block, dim=dim)
    assert got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    # every row exactly once, in order, at most `block` per call (n = 0: one empty call)
    if n == 0:
        assert calls == [(0, 0)]
    else:
        assert calls[0][0] == 0 and calls[-1][1] == n
        assert all(hi - lo <= block for lo, hi in calls)
        assert all(a[1] == b[0] for a, b in itertools.pairwise(calls))


def test_in_blocks_single_block_is_returned_as_is():
    x = torch.arange(5.0)
    out = in_blocks(lambda lo, hi: x[lo:hi], 5, 8)
    assert out.data_ptr() == x.data_ptr()


def test_in_blocks_bad_input():
    with pytest.raises(ValueError, match="n: expected an int >= 0, got -1"):
        in_blocks(lambda lo, hi: torch.zeros(hi - lo), -1, 4)
    with pytest.raises(ValueError, match="block: expected an int >= 1, got 0"):
        in_blocks(lambda lo, hi: torch.zeros(hi - lo), 4, 0)
    with pytest.raises(TypeError, match="block: expected an int >= 1, got float"):
        in_blocks(lambda lo, hi: torch.zeros(hi - lo), 4, 2.0)
    with pytest.raises(ValueError, match="fn: expected 2 rows along dim 0 for the block 0:2, got 3"):
        in_blocks(lambda lo, hi: torch.zeros(3), 4, 2)
