"""Beam splats (issue 16): splat_caustic_beams against closed-form binned irradiance, energy, extremes, gradients,
typed errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchsss.ops.caustic_splat import splat_caustic_beams

F64 = torch.float64
EYE = torch.eye(4, dtype=F64)[None]  # the map spans NDC [-1, 1]^2 of the world x, y


def grid_points(g: int, scale: float, offset=(0.0, 0.0), half: float = 1.0) -> torch.Tensor:
    """(1, g, g, 1, 3) points: the texel centres of a g x g grid over [-half, half]^2, scaled and shifted."""
    c = -half + (torch.arange(g, dtype=F64) + 0.5) * 2 * half / g
    y, x = torch.meshgrid(-c, c, indexing="ij")
    return torch.stack([x * scale + offset[0], y * scale + offset[1], torch.zeros_like(x)], -1)[None, :, :, None]


def binned_square(size: int, lo: np.ndarray, hi: np.ndarray, total: float) -> np.ndarray:
    """Flux per texel of a uniform square [lo, hi] (NDC) of total flux ``total`` on a size x size map (exact)."""
    edges = np.linspace(-1, 1, size + 1)
    ox = np.clip(np.minimum(edges[1:], hi[0]) - np.maximum(edges[:-1], lo[0]), 0, None)
    oy = np.clip(np.minimum(edges[1:], hi[1]) - np.maximum(edges[:-1], lo[1]), 0, None)[::-1]  # row 0 = top
    return total * np.outer(oy, ox) / ((hi[0] - lo[0]) * (hi[1] - lo[1]))


@pytest.mark.parametrize(("scale", "offset"), [(0.37, (0.11, -0.23)), (1.0, (0.013, 0.0)), (0.05, (0.3, 0.3))])
def test_uniform_beam_is_the_exact_binned_irradiance(scale, offset):
    """A uniformly lit grid mapped by a (concentrating / shifting) similarity: the map is the exact box-binned flux
    of the mapped square, whatever the texel alignment."""
    g, size = 16, 24
    pts = grid_points(g, scale, offset, half=0.9)
    flux = torch.full((1, g, g, 1), 0.5, dtype=F64)
    out = splat_caustic_beams(pts, flux, torch.ones(1, g, g, 1, dtype=torch.bool), EYE, (size, size))[0, 0]
    half = 0.9 * scale
    ref = binned_square(size, np.array(offset) - half, np.array(offset) + half, 0.5 * g * g)
    np.testing.assert_allclose(out.numpy(), ref, rtol=0, atol=1e-9 * ref.max())


@pytest.mark.parametrize("subdivisions", [1, 2, 3, 5])
def test_odd_and_even_subdivisions_keep_the_flux(subdivisions):
    """Every one of the s x s sub-points deposits: an odd s has a middle row and column of offset 0 (they were
    dropped once, so s = 1 splatted nothing and s = 3 lost 5/9 of the flux)."""
    g, size = 16, 24
    pts = grid_points(g, 0.37, (0.11, -0.23), half=0.9)
    flux = torch.full((1, g, g, 1), 0.5, dtype=F64)
    out = splat_caustic_beams(pts, flux, torch.ones(1, g, g, 1, dtype=torch.bool), EYE, (size, size),
                              subdivisions)[0, 0]
    assert out.sum().item() == pytest.approx(0.5 * g * g, rel=1e-12)
    ref = binned_square(size, np.array((0.11, -0.23)) - 0.9 * 0.37, np.array((0.11, -0.23)) + 0.9 * 0.37, 0.5 * g * g)
    np.testing.assert_allclose(out.numpy(), ref, rtol=0, atol=1e-9 * ref.max())


def test_traced_single_pass_matches_the_eager_quadrants(monkeypatch):
    """The traced formulation (every grid point, all sub-points in one pass) gives the eager result (grid points
    that carry flux only, one quadrant at a time), with discontinuities, invalid points and a coverage mask."""
    import torchsss.ops.caustic_splat as cs

    gen = torch.Generator().manual_seed(3)
    g = 14
    pts = grid_points(g, 0.8).expand(2, g, g, 2, 3).clone()
    pts = pts + 0.02 * torch.randn(pts.shape, generator=gen, dtype=F64)
    pts[:, 3:5, 4:7] += 0.9  # a fold: neighbours farther than max_stretch_px
    flux = torch.rand(2, g, g, 2, generator=gen, dtype=F64)
    valid = torch.rand(2, g, g, 2, generator=gen) > 0.15
    cover = torch.rand(2, 1, 19, 19, generator=gen) > 0.1
    vp = EYE.expand(2, 4, 4)
    for s in (2, 3, 4):
        eager = splat_caustic_beams(pts, flux, valid, vp, (19, 19), s, max_stretch_px=4.0, coverage=cover)
        with monkeypatch.context() as m:
            m.setattr(cs, "is_tracing", lambda: True)
            traced = splat_caustic_beams(pts, flux, valid, vp, (19, 19), s, max_stretch_px=4.0, coverage=cover)
        torch.testing.assert_close(traced, eager, rtol=0, atol=1e-13)


def test_disc_keeps_its_flux_and_single_points_land_in_their_texel():
    g = 20
    pts = grid_points(g, 0.6)
    r = pts[0, :, :, 0, :2].norm(dim=-1)
    valid = (r < 0.5)[None, ..., None]
    flux = torch.rand(1, g, g, 1, dtype=F64, generator=torch.Generator().manual_seed(0))
    out = splat_caustic_beams(pts, flux, valid, EYE, (13, 17))
    assert out.sum().item() == pytest.approx(float((flux * valid).sum()), rel=1e-12)  # rim texels keep their flux
    # an isolated point (no valid neighbour): all its flux in the texel that contains it
    one = torch.zeros(1, g, g, 1, dtype=torch.bool)
    one[0, 3, 4, 0] = True
    out = splat_caustic_beams(pts, flux, one, EYE, (8, 8))[0, 0]
    assert (out > 0).sum() == 1 and out.sum().item() == pytest.approx(float(flux[0, 3, 4, 0]))
    # nothing valid, or every point behind the light: an empty map
    assert (splat_caustic_beams(pts, flux, one & False, EYE, (8, 8)) == 0).all()
    back = EYE.clone()
    back[0, 3, 3] = -1.0
    assert (splat_caustic_beams(pts, flux, valid, back, (8, 8)) == 0).all()


def test_coverage_keeps_the_beam_on_the_receiver():
    g = 16
    pts = grid_points(g, 1.0)
    flux = torch.ones(1, g, g, 1, dtype=F64)
    cover = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
    cover[..., :, :8] = True
    valid = (pts[..., 0] < 0.0)  # the rays that land on the left half only
    out = splat_caustic_beams(pts, flux, valid, EYE, (16, 16), coverage=cover)[0, 0]
    assert (out[:, 8:] == 0).all() and out.sum().item() == pytest.approx(float(valid.sum()))


def test_beam_splat_gradcheck():
    g = 4
    pts = grid_points(g, 0.7, (0.03, -0.02))
    valid = torch.ones(1, g, g, 2, dtype=torch.bool)
    valid[0, 0, 0, 1] = False
    pts2 = torch.cat([pts, pts * 0.9], 3)
    flux = torch.rand(1, g, g, 2, dtype=F64, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f: splat_caustic_beams(pts2, f, valid, EYE, (6, 7), 2), (flux,))
    p = grid_points(3, 0.7, (0.03, -0.02)).requires_grad_(True)
    f = flux.detach()[:, :3, :3, :1]
    # the weights are piecewise linear in the points: tiny steps stay on one piece
    assert torch.autograd.gradcheck(lambda q: splat_caustic_beams(q, f, valid[:, :3, :3, :1], EYE, (4, 5), 2), (p,),
                                    eps=1e-8, atol=1e-5)


def test_beam_splat_errors():
    pts = grid_points(4, 1.0)
    flux = torch.ones(1, 4, 4, 1, dtype=F64)
    valid = torch.ones(1, 4, 4, 1, dtype=torch.bool)
    with pytest.raises(TypeError, match=r"points: expected a torch\.Tensor"):
        splat_caustic_beams(pts.numpy(), flux, valid, EYE, (4, 4))
    with pytest.raises(TypeError, match="valid: expected a bool tensor"):
        splat_caustic_beams(pts, flux, valid.double(), EYE, (4, 4))
    with pytest.raises(ValueError, match=r"points: expected shape \(B, Hg, Wg, C, 3\)"):
        splat_caustic_beams(pts[..., 0, :], flux, valid, EYE, (4, 4))
    with pytest.raises(ValueError, match=r"flux: expected shape \(B, Hg, Wg, C\)"):
        splat_caustic_beams(pts, flux[:, :3], valid, EYE, (4, 4))
    with pytest.raises(ValueError, match="subdivisions: expected an int >= 1, got 0"):
        splat_caustic_beams(pts, flux, valid, EYE, (4, 4), 0)
    with pytest.raises(TypeError, match="taps: expected an int"):
        splat_caustic_beams(pts, flux, valid, EYE, (4, 4), 2, 2.5)
    with pytest.raises(ValueError, match="max_stretch_px: expected a finite number > 0"):
        splat_caustic_beams(pts, flux, valid, EYE, (4, 4), max_stretch_px=0.0)
    with pytest.raises(ValueError, match="view_proj: expected finite"):
        splat_caustic_beams(pts, flux, valid, EYE * float("nan"), (4, 4))
    with pytest.raises(ValueError, match="coverage: expected shape"):
        splat_caustic_beams(pts, flux, valid, EYE, (4, 4), coverage=torch.ones(1, 1, 3, 4, dtype=torch.bool))
