"""Lensch et al. 2002 precomputation: local kernel geometry, dual-basis vertex weights, throughput, blending."""

from __future__ import annotations

import functools
import itertools
import math

import numpy as np
import pytest
import torch

from torchsss.geometry import build_atlas, plane, sphere
from torchsss.geometry.lensch import (
    BlendWeights,
    Throughput,
    blending_weights,
    build_throughput,
    local_kernel_geometry,
    plan_kernel_size,
    plan_lensch,
    throughput_values,
    vertex_weights,
)
from torchsss.physics.dipole import dipole_cumulative, dipole_rd


def _dip(sa, ss, eta=1.3):
    """A dipole profile callable (distances (..., 1) mm -> R_d (..., C)) from coefficients."""
    return functools.partial(dipole_rd, sigma_a=sa, sigma_s_prime=ss, eta=eta)


def _self_peak(mesh, material):
    """The relative threshold's reference: the largest vertex's self throughput, the disk integral of R_d."""
    radius = torch.sqrt(mesh.vertex_areas.to(torch.float64).max() / math.pi)
    return float(dipole_cumulative(radius, *material).max())

MARBLE = (torch.tensor([0.0021, 0.0041, 0.0071], dtype=torch.float64),
          torch.tensor([2.19, 2.62, 3.00], dtype=torch.float64), 1.3)
SKIN1 = (torch.tensor([0.032, 0.17, 0.48], dtype=torch.float64),
         torch.tensor([0.74, 0.88, 1.01], dtype=torch.float64), 1.3)


@pytest.fixture(scope="module")
def small_sphere():
    return sphere(10.0, 2, dtype=torch.float64)


@pytest.fixture(scope="module")
def small_atlas(small_sphere):
    return build_atlas(small_sphere, 48, kernel_size=5)


# ---- local kernel geometry -----------------------------------------------------------------------------------


@pytest.mark.parametrize("k", [3, 5])
def test_local_kernel_geometry_matches_brute_force(small_atlas, k):
    geo = local_kernel_geometry(small_atlas, k)
    h, w = small_atlas.shape
    assert geo.kernel_size == k
    assert geo.distance.shape == (h, w, k, k) and geo.area.shape == (h, w, k, k)
    assert geo.distance.dtype == torch.float64
    pos = small_atlas.position[0].permute(1, 2, 0).numpy()
    valid = small_atlas.valid_mask[0, 0].numpy()
    area = small_atlas.area[0, 0].numpy()
    dist_ref = np.zeros((h, w, k, k))
    area_ref = np.zeros((h, w, k, k))
    r = k // 2
    for y in range(h):
        for x in range(w):
            if not valid[y, x]:
                continue
            for i in range(k):
                for j in range(k):
                    sy, sx = y + i - r, x + j - r
                    if 0 <= sy < h and 0 <= sx < w and valid[sy, sx]:
                        dist_ref[y, x, i, j] = np.linalg.norm(pos[y, x] - pos[sy, sx])
                        area_ref[y, x, i, j] = area[sy, sx]
    np.testing.assert_allclose(geo.distance.numpy(), dist_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(geo.area.numpy(), area_ref)


def test_local_kernel_area_zero_outside_and_invalid(small_atlas):
    k = 5
    geo = local_kernel_geometry(small_atlas, k)
    valid = small_atlas.valid_mask[0, 0]
    assert bool((geo.area[~valid] == 0).all()) and bool((geo.distance[~valid] == 0).all())
    # taps reading outside the image are zero: top rows read rows -2, -1 with i = 0, 1
    assert bool((geo.area[0, :, :2] == 0).all()) and bool((geo.area[:, -1, :, -2:] == 0).all())
    assert bool((geo.area >= 0).all())
    # a positive area means both ends are valid; the centre tap is the texel itself at distance 0
    assert torch.equal(geo.area[..., 2, 2], small_atlas.area[0, 0] * valid)
    assert bool((geo.distance[..., 2, 2] == 0).all())
    # kernels read well past chart edges into the filled gutters: every chart receiver has all k*k sources
    chart = small_atlas.chart_mask[0, 0]
    full = (geo.area[chart] > 0).flatten(1).all(1).float().mean().item()
    assert full > 0.99, full


def test_local_kernel_float32(small_sphere):
    atlas = build_atlas(small_sphere.with_dtype(torch.float32), 32, kernel_size=3)
    geo = local_kernel_geometry(atlas)
    assert geo.distance.dtype == torch.float32 and geo.area.shape == (32, 32, 7, 7)


# ---- vertex weights ------------------------------------------------------------------------------------------


def _project(vw, values, num_vertices):
    """E^g_i = sum over texels of dual * E (values (1, 1, H, W))."""
    return torch.zeros(num_vertices, dtype=torch.float64).index_add_(
        0, vw.vertex_ids.flatten(), (vw.dual * values).flatten().to(torch.float64))


def test_vertex_weights_reproduce_linear_functions():
    """The discrete dual (default) reproduces a function linear on the faces exactly at every vertex, and its
    weighted sum is the exact surface integral; the continuum dual 4 beta - 1 only to first order in the texel size
    (midpoint quadrature of the dual functions: 5.0% at 512, 2.1% at 1024 on this sphere), conserving the texel sum
    instead."""
    mesh = sphere(10.0, 3, dtype=torch.float64)
    coef = torch.tensor([0.3, -0.7, 1.1], dtype=torch.float64)
    exact = mesh.vertices @ coef + 20.0  # E(v_i), E = a.x + c > 0
    tri = mesh.vertices[mesh.faces]
    surface = (mesh.face_areas * (tri.mean(1) @ coef + 20.0)).sum()  # exact for a function linear per face
    errors = {}
    for res in (512, 1024):
        atlas = build_atlas(mesh, res)
        values = (atlas.position * coef[:, None, None]).sum(1, keepdim=True) + 20.0
        e_g = _project(vertex_weights(mesh, atlas), values, mesh.num_vertices)
        torch.testing.assert_close(e_g, exact, rtol=1e-10, atol=0.0)
        torch.testing.assert_close((e_g * mesh.vertex_areas).sum(), surface, rtol=1e-10, atol=0.0)
        cont = _project(vertex_weights(mesh, atlas, discrete=False), values, mesh.num_vertices)
        errors[res] = ((cont - exact).abs().max() / exact.abs().max()).item()
        chart_sum = (values * atlas.area * atlas.chart_mask).sum()
        torch.testing.assert_close((cont * mesh.vertex_areas).sum(), chart_sum, rtol=1e-10, atol=0)
        assert abs(chart_sum / surface - 1) < 5e-4  # texel quadrature: 6e-5 measured at 512
    assert 0.005 < errors[1024] < 0.03 and errors[1024] < 0.6 * errors[512], errors
    with pytest.raises(TypeError, match="discrete: expected a bool"):
        vertex_weights(mesh, build_atlas(mesh, 64), discrete=1)


def test_vertex_weights_layout_and_bary_reconstruction(small_sphere, small_atlas):
    vw = vertex_weights(small_sphere, small_atlas)
    h, w = small_atlas.shape
    for t in vw:
        assert t.shape == (1, 3, h, w)
    assert vw.vertex_ids.dtype == torch.int64 and vw.dual.dtype == torch.float64
    valid = small_atlas.valid_mask[0, 0]
    chart = small_atlas.chart_mask[0, 0]
    assert bool((vw.vertex_ids[0][:, ~valid] == 0).all()) and bool((vw.bary[0][:, ~valid] == 0).all())
    assert bool((vw.dual[0][:, ~chart] == 0).all())  # gutters carry no dual weight
    torch.testing.assert_close(vw.bary[0].sum(0)[valid], torch.ones(int(valid.sum()), dtype=torch.float64))
    # reconstructing a linear vertex function with bary equals the linear function of the texel position
    coef = torch.tensor([1.5, 0.25, -2.0], dtype=torch.float64)
    vertex_values = small_sphere.vertices @ coef
    recon = (vw.bary[0] * vertex_values[vw.vertex_ids[0]]).sum(0)
    direct = (small_atlas.position[0] * coef[:, None, None]).sum(0)
    torch.testing.assert_close(recon[chart], direct[chart], rtol=0, atol=1e-9)
    torch.testing.assert_close(recon[valid], direct[valid], rtol=0, atol=1e-9)  # gutters continue the plane
    # the continuum dual at a texel: sum_nu dual_nu * A_nu / 3 = the texel's area; the discrete one: its corrected
    # weight, which sums over every face's texels to the face's area
    big_a = small_sphere.vertex_areas[vw.vertex_ids[0]]
    cont = vertex_weights(small_sphere, small_atlas, discrete=False)
    torch.testing.assert_close((cont.dual[0] * big_a).sum(0), small_atlas.area[0, 0] * chart)
    weight = (vw.dual[0] * big_a).sum(0)
    face = small_atlas.face_id[0, 0]
    per_face = torch.zeros(small_sphere.num_faces, dtype=torch.float64).index_add_(0, face[chart], weight[chart])
    seen = torch.bincount(face[chart], minlength=small_sphere.num_faces) >= 3
    torch.testing.assert_close(per_face[seen], small_sphere.face_areas[seen], rtol=1e-10, atol=0.0)
    assert float((weight[chart] - small_atlas.area[0, 0][chart]).abs().max()) > 0  # it is a correction


# ---- throughput ----------------------------------------------------------------------------------------------


def _dense(mesh, material):
    v = mesh.vertices.to(torch.float64)
    d = torch.cdist(v, v, compute_mode="donot_use_mm_for_euclid_dist")
    rd = dipole_rd(d[..., None], *material)
    return d, mesh.vertex_areas.to(torch.float64)[:, None, None] * rd  # (N, N), (N, N, C)


def _pairs(tp):
    return set(zip(tp.rows.tolist(), tp.cols.tolist()))


@pytest.mark.parametrize("material", [MARBLE, SKIN1], ids=["marble", "skin1"])
@pytest.mark.parametrize("subdivisions", [2, 3])
def test_throughput_matches_dense(material, subdivisions):
    mesh = sphere(10.0, subdivisions, dtype=torch.float64)
    d, f = _dense(mesh, material)
    fmax = f.amax(-1)
    n = mesh.num_vertices
    for threshold, relative in ((1e-2, True), (1e-4, True), (1e-4 * float(fmax.max()), False)):
        tp = build_throughput(mesh, _dip(*material), threshold=threshold, relative=relative)
        assert isinstance(tp, Throughput) and tp.num_vertices == n and tp.relative is relative
        absolute = threshold * _self_peak(mesh, material) if relative else threshold
        keep = fmax >= absolute
        assert 0 < int(keep.sum()) < n * n
        rows, cols = keep.nonzero(as_tuple=True)  # row-major, like the blockwise build
        assert torch.equal(tp.rows, rows) and torch.equal(tp.cols, cols)
        torch.testing.assert_close(tp.distance, d[rows, cols], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(tp.source_area, mesh.vertex_areas[rows])
        values = throughput_values(tp, lambda r: dipole_rd(r, *material))
        torch.testing.assert_close(values, f[rows, cols], rtol=1e-12, atol=0)
        assert tp.cutoff_mm == pytest.approx(float(d[keep].max()), rel=1e-12)
        # zero_diagonal drops exactly the diagonal
        tp0 = build_throughput(mesh, _dip(*material), threshold=threshold, relative=relative, zero_diagonal=True)
        assert _pairs(tp0) == _pairs(tp) - {(i, i) for i in range(n)}
        assert all(i != j for i, j in _pairs(tp0)) and len(_pairs(tp)) - len(_pairs(tp0)) == n
        # a tiny block size gives the identical result
        tpb = build_throughput(mesh, _dip(*material), threshold=threshold, relative=relative, block_rows=7)
        for a, b in zip(tp[:4], tpb[:4]):
            assert torch.equal(a, b)
        assert tpb.cutoff_mm == tp.cutoff_mm


def test_throughput_memory_blocks_and_progress(small_sphere):
    tp = build_throughput(small_sphere, _dip(*MARBLE), threshold=1e-3)
    tp_small = build_throughput(small_sphere, _dip(*MARBLE), threshold=1e-3, max_memory_mb=0.01, progress=True)
    assert all(torch.equal(a, b) for a, b in zip(tp[:4], tp_small[:4]))
    assert tp.build_seconds > 0 and tp.threshold == 1e-3


def test_throughput_threshold_sweep_monotone(small_sphere):
    counts, cutoffs = [], []
    for threshold in (0.0, 1e-6, 1e-4, 1e-3, 1e-2, 1e-1, 1.0):
        tp = build_throughput(small_sphere, _dip(*SKIN1), threshold=threshold)
        counts.append(tp.rows.numel())
        cutoffs.append(tp.cutoff_mm)
    assert counts[0] == small_sphere.num_vertices ** 2
    assert all(a >= b for a, b in itertools.pairwise(counts)) and counts[-1] >= 1
    assert all(a >= b for a, b in itertools.pairwise(cutoffs))
    assert counts[2] < counts[0]


def test_throughput_float32_mesh_and_scalar_material():
    mesh = sphere(10.0, 1)
    tp = build_throughput(mesh, _dip(0.01, 1.0), threshold=1e-3)
    assert tp.distance.dtype == torch.float32 and tp.rows.dtype == torch.int64
    values = throughput_values(tp, lambda r: dipole_rd(r, torch.tensor([0.01]), 1.0))
    assert values.shape == (tp.rows.numel(), 1) and values.dtype == torch.float32


# ---- blending ------------------------------------------------------------------------------------------------


def _impulse_response(mesh, atlas, material, bw, geo, vw, tp0, o):
    """Blended (local + B^g0 + B^d) and unblended global response to a unit impulse of E at texel o."""
    h, w = atlas.shape
    k = geo.kernel_size
    r = k // 2
    oy, ox = o
    kernels = geo.area[..., None] * dipole_rd(geo.distance[..., None], *material)  # (H, W, k, k, C)
    kernels = kernels + bw.kernel_correction.permute(1, 2, 3, 4, 0)
    local = torch.zeros(h, w, 3, dtype=torch.float64)
    for y in range(max(0, oy - r), min(h, oy + r + 1)):
        for x in range(max(0, ox - r), min(w, ox + r + 1)):
            local[y, x] = kernels[y, x, oy - y + r, ox - x + r]  # gather: receiver (y, x) reads o
    ids_o = vw.vertex_ids[0, :, oy, ox]
    e_g = torch.zeros(mesh.num_vertices, dtype=torch.float64).index_add_(0, ids_o, vw.dual[0, :, oy, ox])
    values0 = throughput_values(tp0, lambda q: dipole_rd(q, *material))
    b_g0 = torch.zeros(mesh.num_vertices, 3, dtype=torch.float64).index_add_(0, tp0.cols, e_g[tp0.rows, None] * values0)
    b_d = torch.zeros(mesh.num_vertices, 3, dtype=torch.float64).index_add_(0, ids_o, bw.weights[:, :, oy, ox].T)
    diag = torch.zeros(mesh.num_vertices, 3, dtype=torch.float64)
    diag[ids_o] = e_g[ids_o, None] * mesh.vertex_areas[ids_o, None] * dipole_rd(torch.zeros(1, 1), *material)

    def interp(vals):
        return (vw.bary[0, :, :, :, None] * vals[vw.vertex_ids[0]]).sum(0)  # (H, W, C)

    valid = atlas.valid_mask[0, 0, :, :, None]
    return (local + interp(b_g0 + b_d)) * valid, interp(b_g0 + diag) * valid, interp(b_g0) * valid


def test_blending_reproduces_kernel_inside_window_and_global_far_away():
    mesh = sphere(10.0, 2, dtype=torch.float64)
    atlas = build_atlas(mesh, 96, kernel_size=7)
    k, threshold = 7, 1e-5
    bw = blending_weights(mesh, atlas, _dip(*MARBLE), kernel_size=k, threshold=threshold)
    assert isinstance(bw, BlendWeights)
    assert bw.weights.shape == (3, 3, 96, 96) and bw.kernel_correction.shape == (3, 96, 96, k, k)
    chart = atlas.chart_mask[0, 0]
    assert bool((bw.weights[:, :, ~chart] == 0).all())
    geo = local_kernel_geometry(atlas, k)
    vw = vertex_weights(mesh, atlas, discrete=False)  # what the blending fit is made against
    tp0 = build_throughput(mesh, _dip(*MARBLE), threshold=threshold, zero_diagonal=True)
    pos = atlas.position[0].permute(1, 2, 0)
    ys, xs = chart.nonzero(as_tuple=True)
    gen = torch.Generator().manual_seed(0)
    picks = torch.randperm(ys.numel(), generator=gen)[:6]
    for p in picks.tolist():
        oy, ox = int(ys[p]), int(xs[p])
        total, global_full, _ = _impulse_response(mesh, atlas, MARBLE, bw, geo, vw, tp0, (oy, ox))
        target = atlas.area[0, 0, oy, ox] * dipole_rd((pos - pos[oy, ox]).norm(dim=-1)[..., None], *MARBLE)
        window = (slice(max(0, oy - 3), oy + 4), slice(max(0, ox - 3), ox + 4))
        valid_w = atlas.valid_mask[0, 0][window]
        torch.testing.assert_close(total[window][valid_w], target[window][valid_w], rtol=1e-9, atol=1e-12)
        # far away (outside the window, receiver face sharing no vertex with o's face): the global response
        ids_o = set(vw.vertex_ids[0, :, oy, ox].tolist())
        far = atlas.valid_mask[0, 0].clone()
        far[max(0, oy - 3):oy + 4, max(0, ox - 3):ox + 4] = False
        touches = torch.zeros_like(far)
        for vid in ids_o:
            touches |= (vw.vertex_ids[0] == vid).any(0)
        far &= ~touches
        torch.testing.assert_close(total[far], global_full[far], rtol=1e-9, atol=1e-15)


def test_blending_ring_fit_is_least_squares_optimal():
    mesh = sphere(10.0, 2, dtype=torch.float64)
    atlas = build_atlas(mesh, 96, kernel_size=7)
    bw = blending_weights(mesh, atlas, _dip(*SKIN1), kernel_size=7, chunk_texels=257)  # odd chunking
    bw_ref = blending_weights(mesh, atlas, _dip(*SKIN1), kernel_size=7)
    torch.testing.assert_close(bw.weights, bw_ref.weights, rtol=1e-9, atol=1e-15)
    geo = local_kernel_geometry(atlas, 7)
    vw = vertex_weights(mesh, atlas, discrete=False)  # what the blending fit is made against
    tp0 = build_throughput(mesh, _dip(*SKIN1), zero_diagonal=True)
    pos = atlas.position[0].permute(1, 2, 0)
    chart = atlas.chart_mask[0, 0]
    ys, xs = chart.nonzero(as_tuple=True)
    fitted, unfitted = [], []
    for p in torch.randperm(ys.numel(), generator=torch.Generator().manual_seed(1))[:6].tolist():
        oy, ox = int(ys[p]), int(xs[p])
        total, _, g0 = _impulse_response(mesh, atlas, SKIN1, bw, geo, vw, tp0, (oy, ox))
        target = atlas.area[0, 0, oy, ox] * dipole_rd((pos - pos[oy, ox]).norm(dim=-1)[..., None], *SKIN1)
        ring = torch.zeros_like(chart)
        ring[max(0, oy - 4):oy + 5, max(0, ox - 4):ox + 5] = True
        ring[max(0, oy - 3):oy + 4, max(0, ox - 3):ox + 4] = False
        ring &= atlas.valid_mask[0, 0]
        res = (target - total)[ring]  # on the ring the local kernel is 0: total = B^g0 + B^d
        res0 = (target - g0)[ring]
        fitted.append(res.norm().item() / target[ring].norm().item())
        unfitted.append(res0.norm().item() / target[ring].norm().item())
        assert res.norm() <= res0.norm() * (1 + 1e-9)
        # perturbing w in any direction cannot lower the ring residual (normal equations)
        b_d_dir = torch.zeros(3, dtype=torch.float64)
        ids_o = vw.vertex_ids[0, :, oy, ox]
        for nu in range(3):
            hat = (vw.bary[0] * (vw.vertex_ids[0] == ids_o[nu])).sum(0)[ring]
            b_d_dir[nu] = (hat[:, None] * res).sum(0).abs().max() / (hat.norm() * res.norm() + 1e-300)
        assert bool((b_d_dir < 1e-6).all()), b_d_dir
    assert np.mean(fitted) <= np.mean(unfitted)


def test_blending_plane_interior_lowers_ring_error():
    mesh = plane(20.0, 20.0, 4, dtype=torch.float64)
    atlas = build_atlas(mesh, 64, kernel_size=5)
    bw = blending_weights(mesh, atlas, _dip(*MARBLE), kernel_size=5, threshold=0.0)
    assert torch.isfinite(bw.weights).all() and torch.isfinite(bw.kernel_correction).all()
    assert bool((bw.kernel_correction[:, ~atlas.valid_mask[0, 0]] == 0).all())


# ---- bad input -----------------------------------------------------------------------------------------------


def test_bad_input(small_sphere, small_atlas):
    with pytest.raises(TypeError, match="atlas"):
        local_kernel_geometry("atlas")
    with pytest.raises(ValueError, match="kernel_size"):
        local_kernel_geometry(small_atlas, 4)
    with pytest.raises(TypeError, match="kernel_size"):
        local_kernel_geometry(small_atlas, 7.0)
    with pytest.raises(TypeError, match="mesh"):
        vertex_weights(small_atlas, small_atlas)
    with pytest.raises(ValueError, match="atlas"):
        vertex_weights(sphere(10.0, 1), small_atlas)
    with pytest.raises(ValueError, match="threshold"):
        build_throughput(small_sphere, _dip(*MARBLE), threshold=-1e-5)
    with pytest.raises(ValueError, match="threshold"):
        build_throughput(small_sphere, _dip(*MARBLE), threshold=2.0)
    with pytest.raises(TypeError, match="threshold"):
        build_throughput(small_sphere, _dip(*MARBLE), threshold="1e-5")
    with pytest.raises(TypeError, match="relative"):
        build_throughput(small_sphere, _dip(*MARBLE), relative=1)
    with pytest.raises(ValueError, match="block_rows"):
        build_throughput(small_sphere, _dip(*MARBLE), block_rows=0)
    with pytest.raises(ValueError, match="max_memory_mb"):
        build_throughput(small_sphere, _dip(*MARBLE), max_memory_mb=-1.0)
    with pytest.raises(ValueError, match="sigma_a"):
        build_throughput(small_sphere, _dip(-0.1, 1.0))
    with pytest.raises(TypeError, match=r"profile: expected a callable"):
        build_throughput(small_sphere, 0.1)
    with pytest.raises(ValueError, match=r"profile: expected R_d of shape \(N, C\)"):
        build_throughput(small_sphere, lambda r: r.sum())
    with pytest.raises(TypeError, match="profile"):
        throughput_values(build_throughput(sphere(10.0, 0), _dip(0.1, 1.0)), 3.0)
    with pytest.raises(TypeError, match="tp"):
        throughput_values((1, 2), lambda r: r)
    with pytest.raises(ValueError, match="kernel_size"):
        blending_weights(small_sphere, small_atlas, _dip(*MARBLE), kernel_size=6)
    with pytest.raises(ValueError, match="chunk_texels"):
        blending_weights(small_sphere, small_atlas, _dip(*MARBLE), chunk_texels=0)


def test_plan_kernel_size_follows_vertex_spacing_and_texel_size():
    coarse, fine = sphere(10.0, 2), sphere(10.0, 4)  # the same surface, edges 4x shorter on the fine one
    k_coarse, k_fine = plan_kernel_size(coarse, 256), plan_kernel_size(fine, 256)
    assert k_coarse % 2 == 1 and k_fine % 2 == 1
    assert k_coarse > k_fine
    # the kernel reaches ~0.7 median edges when not clamped: check the rule against a direct computation
    f = fine.faces
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edge = float((fine.vertices[e[:, 0]] - fine.vertices[e[:, 1]]).norm(dim=1).median())
    texel = math.sqrt(float(fine.area) / (0.45 * 256 * 256))
    assert k_fine == min(max(2 * round(0.7 * edge / texel) + 1, 5), 11)
    # finer texels need more taps for the same reach; the clamps hold
    assert plan_kernel_size(fine, 1024) >= plan_kernel_size(fine, 256)
    assert plan_kernel_size(coarse, 4096, k_max=15) == 15
    assert plan_kernel_size(fine, 16, k_min=3) == 3
    with pytest.raises(TypeError, match="mesh"):
        plan_kernel_size("sphere", 512)
    with pytest.raises(ValueError, match="resolution"):
        plan_kernel_size(fine, 0)
    with pytest.raises(ValueError, match="k_min, k_max"):
        plan_kernel_size(fine, 512, k_min=9, k_max=5)
    with pytest.raises(ValueError, match="kernel_size"):
        plan_kernel_size(fine, 512, k_max=8)
    with pytest.raises(ValueError, match="reach"):
        plan_kernel_size(fine, 512, reach=0.0)


@pytest.mark.parametrize("threshold", [1e-3, 1e-2, 0.3])
def test_throughput_kdtree_path_matches_brute_force(threshold):
    """Short cutoffs take the k-d tree path (O(nnz)); it must keep exactly the pairs of the all-pairs test."""
    mesh = sphere(30.0, 4, dtype=torch.float64)
    material = SKIN1
    d, f = _dense(mesh, material)
    fmax = f.amax(-1)
    absolute = threshold * _self_peak(mesh, material)
    radius = float(d[fmax >= absolute].max())
    diag = float((mesh.vertices.amax(0) - mesh.vertices.amin(0)).norm())
    assert radius < 0.5 * diag  # this case exercises the k-d tree candidates
    for zero_diagonal in (False, True):
        tp = build_throughput(mesh, _dip(*material), threshold=threshold, zero_diagonal=zero_diagonal)
        keep = fmax >= absolute
        if zero_diagonal:
            keep &= ~torch.eye(mesh.num_vertices, dtype=torch.bool)
        rows, cols = keep.nonzero(as_tuple=True)
        assert torch.equal(tp.rows, rows) and torch.equal(tp.cols, cols)
        torch.testing.assert_close(tp.distance, d[rows, cols], rtol=1e-12, atol=1e-12)


def test_blending_band_fit_reduces_the_energy_overshoot():
    """Lensch's ring fit spreads the ring's (high) level over the vertex hats: the impulse response carries too
    much energy. Fitting on a band out towards the neighbouring vertices (fit_radius) brings it closer to the
    exact discrete energy sum_x A_x A_o R_d(|x - x_o|)."""
    mesh = plane(12.0, 12.0, 12, dtype=torch.float64)  # 1 mm vertex spacing
    atlas = build_atlas(mesh, 128, kernel_size=5)  # ~0.1 mm texels
    k = 5
    geo = local_kernel_geometry(atlas, k)
    vw = vertex_weights(mesh, atlas, discrete=False)  # what the blending fit is made against
    tp0 = build_throughput(mesh, _dip(*SKIN1), zero_diagonal=True)
    ring = blending_weights(mesh, atlas, _dip(*SKIN1), kernel_size=k)
    same = blending_weights(mesh, atlas, _dip(*SKIN1), kernel_size=k, fit_radius=k // 2 + 1)
    assert torch.equal(ring.weights, same.weights) and torch.equal(ring.kernel_correction, same.kernel_correction)
    band = blending_weights(mesh, atlas, _dip(*SKIN1), kernel_size=k, fit_radius=8)
    area = (atlas.area * atlas.valid_mask)[0, 0, :, :, None]
    pos = atlas.position[0].permute(1, 2, 0)
    chart = atlas.chart_mask[0, 0].nonzero()
    o = tuple(chart[torch.argmin((pos[chart[:, 0], chart[:, 1]]).norm(dim=-1))].tolist())  # texel at the centre
    exact = (area * dipole_rd((pos - pos[o]).norm(dim=-1)[..., None], *SKIN1)).sum((0, 1)) * area[o]
    over = []
    for bw in (ring, band):
        blended, _, _ = _impulse_response(mesh, atlas, SKIN1, bw, geo, vw, tp0, o)
        over.append(((blended * area).sum((0, 1)) / exact - 1.0).abs())
    assert bool((over[1] < over[0]).all()), over
    with pytest.raises(ValueError, match="fit_radius"):
        blending_weights(mesh, atlas, _dip(*SKIN1), kernel_size=k, fit_radius=2)
    with pytest.raises(TypeError, match="fit_radius"):
        blending_weights(mesh, atlas, _dip(*SKIN1), kernel_size=k, fit_radius=4.0)


def test_plan_lensch_blends_only_when_the_kernel_reaches_the_vertices():
    # fine mesh against the texels: the planned kernel reaches > half an edge -> blend with the planned k
    fine = sphere(10.0, 4)
    k, blend = plan_lensch(fine, 512)
    assert blend and k == plan_kernel_size(fine, 512)
    # coarse mesh (edges ~10x the texels times 11): no kernel up to 11 reaches half an edge -> Lensch's k 7, no blend
    coarse = plane(30.0, 30.0, 6)
    assert plan_lensch(coarse, 1024) == (7, False)


def test_throughput_entry_cap_refuses_before_allocating():
    """A profile that reaches across the object keeps every vertex pair: over the cap the build refuses with a
    ValueError that says how far to decimate, instead of growing past the machine's memory."""
    import pytest

    from torchsss.geometry import sphere
    from torchsss.geometry.lensch import build_throughput, estimate_throughput_entries
    from torchsss.modules import DipoleMaterial
    from torchsss.pipelines.lensch import build_lensch

    m, mat = sphere(10.0, 3), DipoleMaterial.from_preset("marble")  # marble: r_max beyond the 20 mm sphere
    est = estimate_throughput_entries(m, mat)
    assert est > 0.8 * m.num_vertices ** 2  # nearly every pair
    with pytest.raises(ValueError, match="decimate the mesh to about"):
        build_throughput(m, mat, max_entries=est // 4)
    with pytest.raises(ValueError, match="max_entries"):
        build_lensch(m, mat, resolution=64, max_entries=est // 4)  # refused before the atlas is built
    assert build_throughput(m, mat, max_entries=None).rows.numel() == pytest.approx(est, rel=0.2)
