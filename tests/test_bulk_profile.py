"""Profile tables for the no-grad precomputes: fitted_profile_table (physics) and bulk_profile (modules), and the
Lensch modules' first-frame evaluations through them against the material's own formula."""

from __future__ import annotations

import pytest
import torch

from torchsss.geometry import build_atlas, sphere, torus
from torchsss.geometry.lensch import build_throughput, hat_quadrature, local_kernel_geometry, vertex_weights
from torchsss.modules import DipoleMaterial
from torchsss.modules.lensch import GlobalResponse, LocalResponse
from torchsss.modules.material import BULK_TOLERANCE, bulk_profile
from torchsss.physics import dipole_rd, fitted_profile_table, lookup_profile_table
from torchsss.scene import Material

F32, F64 = torch.float32, torch.float64
MATERIALS = ("ketchup", "skin1", "marble", "cream", "skimmilk", "wholemilk", "apple")


def _floor_error(approx: torch.Tensor, exact: torch.Tensor, floor: float = 1e-6) -> torch.Tensor:
    """Per channel max |a - e| / max(|e|, floor * max |e|) (the tables' error measure), in float64."""
    approx, exact = approx.double(), exact.double()
    level = torch.maximum(exact.abs(), floor * exact.abs().amax(0))
    return ((approx - exact).abs() / level).amax(0)


@pytest.mark.parametrize("name", MATERIALS)
@pytest.mark.parametrize("r_max", [0.2, 30.0, 160.0])
def test_fitted_table_meets_its_tolerance_at_random_distances(name, r_max):
    """Checked at node midpoints when fitted; here at 200k random distances (not the check's points) against the
    dipole evaluated in float64, for materials from ketchup to skim milk and ranges from 0.2 to 160 mm."""
    sa, ss, eta = Material.from_json(name).tensors(F64)
    exact = lambda r: dipole_rd(r, sa, ss, eta)  # noqa: E731
    table = fitted_profile_table(lambda r: dipole_rd(r, sa.float(), ss.float(), eta.float()), r_max)
    assert table is not None and table.shared_range and table.size in (4096, 16384, 65536)
    g = torch.Generator().manual_seed(3)
    r = torch.rand(200_000, 1, generator=g, dtype=F64) ** 2 * r_max
    err = _floor_error(lookup_profile_table(r.float(), table), exact(r))
    assert bool((err <= 2.5 * 2e-5).all()), err  # float32 distances and lerp add ~1e-6 to the float64 check


def test_fitted_table_refuses_a_profile_it_cannot_hold():
    """A profile with a jump (no table of any size interpolates it within 2e-5) gives None, as does a range
    that is too wide for the largest size (a 0.01 mm profile over 10 m)."""
    def step(r):
        return torch.where(r < 1.2345, torch.ones_like(r), torch.full_like(r, 0.5))

    assert fitted_profile_table(step, 10.0) is None
    sa, ss, eta = Material.from_json("ketchup").tensors(F32)
    assert fitted_profile_table(lambda r: dipole_rd(r, sa * 50, ss * 50, eta), 10_000.0) is None
    assert fitted_profile_table(lambda r: dipole_rd(r, sa * 50, ss * 50, eta), 10_000.0, tolerance=1.0) is not None


@pytest.mark.parametrize("bad", [0.0, -1.0, float("inf"), float("nan"), True, "3"])
def test_fitted_table_rejects_a_bad_range(bad):
    with pytest.raises(ValueError, match="r_max"):
        fitted_profile_table(lambda r: torch.exp(-r), bad)


def test_fitted_table_rejects_a_bad_tolerance():
    with pytest.raises(ValueError, match="tolerance"):
        fitted_profile_table(lambda r: torch.exp(-r), 1.0, tolerance=0.0)


def test_bulk_profile_is_the_material_where_a_table_must_not_serve():
    mat = DipoleMaterial.from_preset("skin1")
    with torch.no_grad():
        fast = bulk_profile(mat, 20.0)
        assert fast is not mat
        assert bulk_profile(mat, 20.0, F64) is mat  # exact evaluation asked for
        assert bulk_profile(mat, float("inf")) is mat and bulk_profile(mat, 0.0) is mat
        mat64 = DipoleMaterial(*Material.from_json("skin1").tensors(F64))
        assert bulk_profile(mat64, 20.0) is mat64
    with torch.enable_grad():
        assert bulk_profile(mat, 20.0) is mat  # a table would carry no gradient
    r = torch.linspace(0.0, 20.0, 10_001).unsqueeze(-1)
    with torch.no_grad():
        err = _floor_error(fast(r), mat(r.double()))
    assert bool((err <= 2.5 * BULK_TOLERANCE).all()), err


@pytest.fixture(scope="module")
def torus_modules():
    """A side-lit-sized 12 mm torus at atlas 96: the Lensch modules at float32, with the hat quadrature."""
    mesh = torus(6.0, 2.5, 24, 12)
    atlas = build_atlas(mesh, 96, kernel_size=5)
    mat = DipoleMaterial.from_preset("marble").requires_grad_(False)
    tp = build_throughput(mesh, mat)
    glob = GlobalResponse(vertex_weights(mesh, atlas), tp, mat, atlas.valid_mask, hat=hat_quadrature(mesh, tp))
    stored = LocalResponse(local_kernel_geometry(atlas, 5, compact=True), mat)
    derived = LocalResponse.from_atlas(atlas, 5, mat)
    return mat, glob, stored, derived


def test_lensch_first_frame_through_tables_matches_the_formula(torus_modules):
    """The throughput values (moment rule and hat quadrature) and the local kernels (full and symmetric planes)
    evaluated outside autograd (through bulk_profile's tables) against the same evaluations under autograd (the
    material's formula, one expression): within 1e-4 of each entry (against a millionth of the largest)."""
    _, glob, stored, derived = torus_modules
    with torch.no_grad():
        fast_values = glob.throughput_values()
        fast_planes = stored.planes()
        half, centre = derived.half_planes()
    with torch.enable_grad():
        exact_values = glob.throughput_values().detach()
        exact_planes = stored.planes().detach()
    assert fast_values.shape == exact_values.shape and fast_values.dtype == F32
    assert bool((_floor_error(fast_values, exact_values) < 1e-4).all())
    assert bool((_floor_error(fast_planes.reshape(3, -1).T, exact_planes.reshape(3, -1).T) < 1e-4).all())
    # the symmetric planes hold the same off-centre kernels: tap t of receiver o is P_t(o) A(o + delta_t)
    k2 = fast_planes.shape[1]
    assert bool((_floor_error(centre.reshape(3, -1).T, exact_planes[:, k2 // 2].reshape(3, -1).T) < 1e-4).all())
    assert half.shape[1] == (k2 - 1) // 2


def test_lensch_module_output_through_tables_matches_the_formula(torus_modules):
    """A whole local and global response of a random irradiance: the cached no-grad evaluation against a fresh one
    under autograd, within 1e-4 relative RMS."""
    _, glob, _, derived = torus_modules
    e = torch.rand(1, 3, 96, 96, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        fast = glob(e) + derived(e)
    with torch.enable_grad():
        exact = (glob(e) + derived(e)).detach()
    rel = float((fast - exact).square().mean().sqrt() / exact.square().mean().sqrt())
    assert rel < 1e-4, rel


def test_float64_modules_stay_exact():
    """A float64 material never takes a table: the no-grad values equal the autograd ones to rounding."""
    mesh = sphere(4.0, 1, dtype=F64)
    atlas = build_atlas(mesh, 24, kernel_size=3)
    mat = DipoleMaterial(*Material.from_json("marble").tensors(F64)).requires_grad_(False)
    tp = build_throughput(mesh, mat)
    glob = GlobalResponse(vertex_weights(mesh, atlas), tp, mat, atlas.valid_mask, hat=hat_quadrature(mesh, tp))
    with torch.no_grad():
        a = glob.throughput_values()
    with torch.enable_grad():
        b = glob.throughput_values().detach()
    torch.testing.assert_close(a, b, rtol=1e-12, atol=0)


def test_hybrid_surface_local_weights_through_tables_match_the_formula(monkeypatch):
    """The hybrid's local pair weights A_s R_d W_l (float32, outside autograd through a table) against the formula
    under autograd: within 1e-4 of each weight (against a millionth of the largest); float64 stays exact."""
    import torchsss.modules.material as material_mod
    from torchsss.geometry.neighbours import ball_pairs
    from torchsss.geometry.sampling import surface_samples
    from torchsss.modules import SurfaceLocal
    from torchsss.modules.chang import ChangLocalProfile

    monkeypatch.setattr(material_mod, "BULK_MIN_VALUES", 10_000)  # a table for this test's ~50k pairs
    mesh = sphere(6.0, 3)
    smp = surface_samples(mesh, 0.3)
    uv = torch.rand(smp.area.shape[0], 2, generator=torch.Generator().manual_seed(2))
    w = ChangLocalProfile(1.0, 1.5, 4.0)
    for dtype in (F32, F64):
        mat = DipoleMaterial(*Material.from_json("skin1").tensors(dtype)).requires_grad_(False)
        local = SurfaceLocal(uv.to(dtype), smp.area.to(dtype), torch.ones(1, 1, 8, 8, dtype=torch.bool), mat, w)
        _, cols, dist = ball_pairs(smp.position[:200].to(dtype), smp.position.to(dtype), w.bound)
        with torch.no_grad():
            fast = local.pair_weights(cols, dist)
        with torch.enable_grad():
            exact = local.pair_weights(cols, dist).detach()
        assert dist.numel() > 10_000
        if dtype == F32:
            assert bool((_floor_error(fast, exact) < 1e-4).all()) and not torch.equal(fast, exact)  # a table served
        else:
            torch.testing.assert_close(fast, exact, rtol=1e-14, atol=0)


@pytest.mark.parametrize("method", ["window", "tile"])
def test_splat_eager_paths_through_tables_match_the_formula(monkeypatch, method):
    """Splatting's eager per-pair paths (window, tile) evaluate the profile through a table outside autograd
    (float32, enough pairs): the image within 1e-4 of the formula's (evaluated under autograd, where no table
    serves), and a table did serve; float64 stays exact. A plane of 24 x 24 receivers, 150 sources, ketchup."""
    import torchsss.ops.splat as splat_mod
    from torchsss.ops import splat_radiosity

    served = []

    def spy(*args, **kwargs):
        out = bulk_profile(*args, **kwargs)
        served.append(out is not args[0])
        return out

    monkeypatch.setattr(splat_mod, "bulk_profile", spy)
    monkeypatch.setattr(splat_mod, "BULK_MIN_VALUES", 10_000)  # a table for this test's 86k pairs
    g = torch.Generator().manual_seed(4)
    ys, xs = torch.meshgrid(torch.linspace(-12, 12, 24, dtype=F64), torch.linspace(-12, 12, 24, dtype=F64),
                            indexing="ij")
    dst = torch.stack([xs, -ys, torch.zeros_like(xs)])[None]
    mask = torch.ones(1, 1, 24, 24, dtype=torch.bool)
    src = torch.cat([torch.rand(1, 150, 2, generator=g, dtype=F64) * 24 - 12, torch.zeros(1, 150, 1, dtype=F64)], -1)
    flux = torch.rand(1, 150, 3, generator=g, dtype=F64)
    vp = torch.diag(torch.tensor([1 / 12.5, 1 / 12.5, 1.0, 1.0], dtype=F64))
    for dtype in (F32, F64):
        mat = DipoleMaterial(*Material.from_json("ketchup").tensors(dtype)).requires_grad_(False)
        args = (src.to(dtype), flux.to(dtype), dst.to(dtype), mask, vp.to(dtype), mat, 20.0)
        served.clear()
        with torch.no_grad():
            fast = splat_radiosity(*args, method=method)
        assert served == [dtype == F32]  # float64: bulk_profile keeps the formula
        with torch.enable_grad():
            exact = splat_radiosity(*args, method=method).detach()
        assert float(exact.amin()) > 0  # every receiver within reach of some source
        err = ((fast.double() - exact.double()).abs() / exact.double().abs()).amax()
        if dtype == F32:
            assert float(err) < 1e-4 and not torch.equal(fast, exact), float(err)
        else:
            torch.testing.assert_close(fast, exact, rtol=1e-14, atol=0)
