"""Property-based checks of the profile over random materials (hypothesis)."""

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchsss.physics import dipole_cumulative, dipole_rd, profile_tail_fraction, total_diffuse_reflectance

coeff = st.floats(min_value=1e-4, max_value=1e2, allow_nan=False, allow_infinity=False)
absorb = st.one_of(st.just(0.0), st.floats(min_value=1e-6, max_value=1e2))
eta = st.floats(min_value=0.7, max_value=2.5)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(sa=absorb, ss=coeff, e=eta, radii=st.lists(st.floats(0.0, 1e3), min_size=2, max_size=20))
def test_profile_properties(sa, ss, e, radii):
    r = torch.tensor(sorted(radii), dtype=torch.float64)
    sa, ss, e = (torch.tensor(v, dtype=torch.float64) for v in (sa, ss, e))  # numbers alone would be float32
    v = dipole_rd(r, sa, ss, e)
    assert torch.isfinite(v).all() and (v >= 0).all()
    assert (v[1:] <= v[:-1]).all()
    total = total_diffuse_reflectance(sa, ss, e).item()
    assert 0.0 <= total <= 1.0 + 1e-12
    cum = dipole_cumulative(r, sa, ss, e)
    assert (cum[1:] >= cum[:-1] - 1e-15).all() and (cum <= total * (1 + 1e-10)).all()
    tail = profile_tail_fraction(r, sa, ss, e)
    # 1 - cum / total cancels: the closed forms agree to ~1e-12 absolute
    assert torch.allclose(tail, 1 - cum / total, rtol=1e-9, atol=1e-10)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(sa=absorb, ss=coeff, e=eta, scale=st.floats(0.1, 10.0), r=st.floats(0.0, 100.0))
def test_distance_scale_is_a_change_of_variable(sa, ss, e, scale, r):
    a = dipole_rd(torch.tensor([r], dtype=torch.float64), sa, ss, e, distance_scale=scale).item()
    b = dipole_rd(torch.tensor([r * scale], dtype=torch.float64), sa, ss, e).item()
    assert math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-300)
