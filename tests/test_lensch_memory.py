"""Lensch's memory-saving forms give what the plain forms give (float64, small meshes).

- :class:`LocalResponse` from an atlas relights with half the kernel planes (the symmetric factor of the kernels);
- :class:`GlobalResponse` keeps its pattern in int32 and only F^T's CSR matrices between frames;
- :class:`GlobalResponse` with a hat quadrature keeps the hats' moments per vertex and derives each entry's rule;
- :func:`hat_quadrature` writes its terms straight into their sorted place.
"""

from __future__ import annotations

import pytest
import torch

from torchsss.geometry import build_atlas, sphere
from torchsss.geometry.lensch import build_throughput, hat_quadrature, vertex_weights
from torchsss.modules import DipoleMaterial
from torchsss.modules.lensch import GlobalResponse, LocalResponse
from torchsss.ops.sparse import sparse_apply_t, sparse_pattern
from torchsss.ops.sv_conv import sv_conv2d_planes
from torchsss.scene import Material


def _material(name="skin1", dtype=torch.float64):
    sa, ss, eta = Material.from_json(name).tensors(dtype)
    return DipoleMaterial(sa, ss, eta)


@pytest.fixture(scope="module")
def small():
    mesh = sphere(6.0, 2, dtype=torch.float64)
    return mesh, build_atlas(mesh, 48, kernel_size=5)


@pytest.mark.parametrize("k", [3, 5])
@pytest.mark.parametrize("self_term", ["disk", "point"])
def test_half_planes_equal_the_full_planes(small, k, self_term):
    _, atlas = small
    local = LocalResponse.from_atlas(atlas, k, _material(), self_term=self_term)
    assert local._symmetric()
    e = torch.rand(2, 3, *atlas.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        half = local(e)  # the cached half planes
        full = sv_conv2d_planes(e.transpose(0, 1), local.planes()).transpose(0, 1)
        half_p, centre = local.half_planes()
    torch.testing.assert_close(half, full, rtol=1e-12, atol=1e-14)
    assert half_p.shape[1] == (k * k - 1) // 2 and centre.shape == (3, *atlas.shape)
    # the stored planes are the kernels without the source area: tap t of receiver o, and its mirror at o + delta_t
    kern = local.kernels()  # (C, H, W, k, k)
    r = k // 2
    area = local.src_area.view(atlas.shape[0] + 2 * r, -1)
    y, x = (atlas.valid_mask[0, 0]).nonzero()[len(local.index) // 2].tolist()
    for t in range(half_p.shape[1]):
        i, j = divmod(t, k)
        src_area = area[y + i, x + j]
        torch.testing.assert_close(kern[:, y, x, i, j], src_area * half_p[:, t, y, x], rtol=1e-15, atol=0)
    torch.testing.assert_close(kern[:, :, :, r, r], centre, rtol=0, atol=0)


def test_half_planes_follow_material_edits_and_gradients(small):
    _, atlas = small
    mat = _material()
    local = LocalResponse.from_atlas(atlas, 3, mat)
    e = torch.rand(1, 3, *atlas.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        before = local(e)
        mat.raw_sigma_a.add_(0.2)
        after = local(e)
        full = sv_conv2d_planes(e.transpose(0, 1), local.planes()).transpose(0, 1)
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, full, rtol=1e-12, atol=1e-14)
    out = local(e)  # with autograd: the planes path, gradients reach the material
    out.sum().backward()
    assert mat.raw_sigma_a.grad is not None and bool(mat.raw_sigma_a.grad.abs().sum() > 0)
    torch.testing.assert_close(out.detach(), full, rtol=1e-12, atol=1e-14)


def test_masked_or_corrected_local_keeps_the_planes(small):
    _, atlas = small
    mask = (torch.rand(1, 1, *atlas.shape, generator=torch.Generator().manual_seed(2)) > 0.3).double()
    local = LocalResponse.from_atlas(atlas, 3, _material(), mask=mask)
    assert not local._symmetric()


@pytest.mark.parametrize("hat", [False, True])
def test_global_csr_cache_equals_the_scatter_product(small, hat):
    mesh, atlas = small
    mat = _material()
    tp = build_throughput(mesh, mat)
    hq = hat_quadrature(mesh, tp) if hat else None
    glob = GlobalResponse(vertex_weights(mesh, atlas), tp, mat, atlas.valid_mask, hat=hq)
    assert glob._p_rows.dtype == torch.int32 and glob._p_t_perm.dtype == torch.int32
    want = sparse_pattern(tp.rows, tp.cols, mesh.num_vertices, mesh.num_vertices)
    got = glob._pattern()
    for a, b in zip(got, want):
        assert torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b
    e = torch.rand(2, 3, *atlas.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        eg = glob.vertex_irradiance(e)
        cached = glob.vertex_radiosity(e, eg)
        again = glob.vertex_radiosity(e, eg)
        ref = sparse_apply_t(eg, want, glob.throughput_values(), method="scatter")
    torch.testing.assert_close(cached, ref, rtol=1e-12, atol=1e-16)
    assert torch.equal(cached, again)


def test_hat_terms_are_sorted_by_entry(small):
    mesh, _ = small
    mat = _material()
    tp = build_throughput(mesh, mat)
    hq = hat_quadrature(mesh, tp)
    te = hq.term_entry.long()
    assert bool((te[1:] >= te[:-1]).all())
    # every term written once in its place: the per-entry sums are the hat's area
    per_entry = torch.zeros(hq.entries.numel(), dtype=torch.float64).index_add_(0, te, hq.weight.double())
    torch.testing.assert_close(per_entry, mesh.vertex_areas[tp.rows[hq.entries]].double(), rtol=1e-10, atol=0)


def test_hat_moment_rule_is_derived_from_per_vertex_moments(small):
    """The module keeps the hats' centroids and covariances, not four numbers per entry, and derives the same rule.

    Against the rule written out from :func:`hat_quadrature`'s per-entry columns (float64), with and without a
    distance multiplier; the self entries (r = 0 from a hat's own vertex only when the hat is symmetric) and the
    extremes of :func:`entry_moments` (a coincident vertex and centroid: no direction, all variance transverse).
    """
    from torchsss.geometry.lensch import HatMoments, entry_moments

    mesh, atlas = small
    mat = _material()
    tp = build_throughput(mesh, mat)
    hq = hat_quadrature(mesh, tp)
    n = mesh.num_vertices
    for md in (None, torch.full((1, 1, *atlas.shape), 1.3, dtype=torch.float64)):
        glob = GlobalResponse(vertex_weights(mesh, atlas), tp, mat, atlas.valid_mask, hat=hq, distance_scale=md)
        assert glob.distance is None and glob.source_area is None and glob._h_centroid.shape == (n, 3)
        assert glob.nnz == tp.rows.numel()
        # a uniform M_d projects to itself on every vertex with texels (1 on the 6 of 162 without, whose irradiance
        # is 0 anyway)
        s = 1.0 if md is None else glob._h_scale[tp.rows]
        if md is not None:
            assert int(((glob._h_scale - 1.3).abs() < 1e-9).sum()) >= 0.9 * n
        r, sr = hq.centroid_distance * s, hq.radial_var.sqrt() * s
        rt = (hq.centroid_distance**2 + hq.transverse_var).sqrt() * s
        f = [mat(x[:, None]) for x in (r, r + sr, (r - sr).abs(), rt)]
        want = tp.source_area[:, None] * (0.5 * (f[1] + f[2]) + f[3] - f[0])
        with torch.enable_grad():  # the profile's formula, not its table
            got = glob._moment_rule(0, glob.nnz)
        torch.testing.assert_close(got.detach(), want, rtol=1e-10, atol=1e-14)
    moments = HatMoments(torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64),
                         torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64),
                         torch.diag(torch.tensor([0.5, 0.25, 0.0], dtype=torch.float64))[None])
    r, radial, transverse = entry_moments(moments, torch.tensor([0]), torch.tensor([0]))
    assert float(r) == 0.0 and float(radial) == 0.0 and float(transverse) == 0.75
    far = HatMoments(moments.vertices * 1e6, moments.centroid * 0, moments.covariance)
    r, radial, transverse = entry_moments(far, torch.tensor([0]), torch.tensor([0]))
    assert torch.isfinite(torch.stack([r, radial, transverse])).all() and float(radial + transverse) == 0.75


def test_entry_moments_typed_errors():
    from torchsss.geometry.lensch import HatMoments, entry_moments

    m = HatMoments(torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(4, 3, 3))
    idx = torch.tensor([0, 1])
    with pytest.raises(TypeError, match="moments: expected a HatMoments"):
        entry_moments((m.vertices, m.centroid, m.covariance), idx, idx)
    with pytest.raises(ValueError, match=r"moments.covariance: expected shape \(4, 3, 3\)"):
        entry_moments(HatMoments(m.vertices, m.centroid, torch.zeros(4, 9)), idx, idx)
    with pytest.raises(TypeError, match="cols: expected an integer tensor"):
        entry_moments(m, idx, idx.float())
    with pytest.raises(ValueError, match="rows, cols: expected two equal"):
        entry_moments(m, idx, torch.tensor([0, 1, 2]))
