"""The dense throughput layout: same entries as the sparse build, same global response, gradients, layout rule."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import functional_call

from torchsss.geometry import build_atlas, sphere
from torchsss.geometry.lensch import (
    DenseThroughput,
    build_dense_throughput,
    build_throughput,
    hat_quadrature,
    throughput_layout,
    vertex_weights,
)
from torchsss.modules import DipoleMaterial
from torchsss.modules.lensch import GlobalResponse
from torchsss.physics import dipole_cumulative
from torchsss.pipelines.lensch import build_lensch
from torchsss.scene import Material


def _material(name="skin1", dtype=torch.float64):
    sa, ss, eta = Material.from_json(name).tensors(dtype)
    return DipoleMaterial(sa, ss, eta)


@pytest.fixture(scope="module")
def small():
    mesh = sphere(6.0, 3, dtype=torch.float64)  # 642 vertices
    return mesh, build_atlas(mesh, 64, kernel_size=5)


@pytest.mark.parametrize("zero_diagonal", [False, True])
@pytest.mark.parametrize("threshold", [1e-5, 1e-2])
def test_dense_throughput_keeps_the_sparse_entries(zero_diagonal, threshold):
    mesh = sphere(40.0, 3, dtype=torch.float64)  # skin1 reaches a part of it: pairs are dropped
    mat = _material("skin1")
    sp = build_throughput(mesh, mat, threshold=threshold, zero_diagonal=zero_diagonal)
    de = build_dense_throughput(mesh, mat, threshold=threshold, zero_diagonal=zero_diagonal)
    n = mesh.num_vertices
    assert de.distance.shape == (n, n) and de.keep.dtype == torch.bool
    want = torch.zeros(n, n, dtype=torch.bool)
    want[sp.rows, sp.cols] = True
    assert torch.equal(de.keep, want)
    assert int(de.keep.sum()) < n * n  # the threshold drops pairs: the mask is tested, not trivially all True
    torch.testing.assert_close(de.distance[sp.rows, sp.cols], sp.distance, rtol=0, atol=0)
    # every pair's distance, kept or not, the Euclidean one
    v = mesh.vertices
    torch.testing.assert_close(de.distance, (v[:, None] - v[None]).norm(dim=-1), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(de.source_area, mesh.vertex_areas)
    assert de.cutoff_mm == sp.cutoff_mm and de.num_vertices == n


def test_dense_blocks_do_not_change_the_build(small):
    mesh, _ = small
    mat = _material()
    one = build_dense_throughput(mesh, mat)
    blocks = build_dense_throughput(mesh, mat, max_memory_mb=0.05)  # a few rows a block
    assert torch.equal(one.keep, blocks.keep) and torch.equal(one.distance, blocks.distance)


@pytest.mark.parametrize("zero_diagonal", [False, True])
def test_dense_global_response_equals_the_sparse_one_and_the_loop(small, zero_diagonal):
    mesh, atlas = small
    mat = _material("skin1")
    w = vertex_weights(mesh, atlas)
    scale = 0.5 + torch.rand(1, 1, 64, 64, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    e = torch.rand(2, 3, 64, 64, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * atlas.valid_mask
    for ds in (None, scale):
        sp = GlobalResponse(w, build_throughput(mesh, mat, threshold=1e-3, zero_diagonal=zero_diagonal), mat,
                            atlas.valid_mask, distance_scale=ds, method="scatter")
        de = GlobalResponse(w, build_dense_throughput(mesh, mat, threshold=1e-3, zero_diagonal=zero_diagonal), mat,
                            atlas.valid_mask, distance_scale=ds)
        assert de.dense and not sp.dense
        with torch.no_grad():
            torch.testing.assert_close(de(e), sp(e), rtol=1e-10, atol=1e-13)
    # against a loop over the kept pairs (no M_d): B_j = sum_i E_i F_ij, the diagonal the disk integral
    tp = build_dense_throughput(mesh, mat, threshold=1e-3, zero_diagonal=zero_diagonal)
    de = GlobalResponse(w, tp, mat, atlas.valid_mask)
    with torch.no_grad():
        eg = de.vertex_irradiance(e[:1])[0]
        got = de.vertex_radiosity(e[:1])[0]
    n = mesh.num_vertices
    f = mesh.vertex_areas[:, None, None] * mat(tp.distance.unsqueeze(-1)).detach()
    disk = dipole_cumulative(torch.sqrt(mesh.vertex_areas / math.pi).unsqueeze(-1), mat.sigma_a, mat.sigma_s_prime,
                             mat.eta).detach()
    want = torch.zeros(n, 3, dtype=torch.float64)
    rows, cols = tp.keep.nonzero(as_tuple=True)
    for i, j in zip(rows.tolist(), cols.tolist()):
        want[j] += eg[i] * (disk[i] if i == j else f[i, j])
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)


def test_dense_global_response_gradcheck():
    mesh = sphere(4.0, 1, dtype=torch.float64)
    atlas = build_atlas(mesh, 24, kernel_size=3)
    mat = _material("marble")
    glob = GlobalResponse(vertex_weights(mesh, atlas), build_dense_throughput(mesh, mat, threshold=1e-2), mat,
                          atlas.valid_mask)
    valid = atlas.valid_mask.expand(1, 3, 24, 24)
    e = torch.rand(1, 3, 24, 24, dtype=torch.float64) * atlas.valid_mask

    def on_valid(ev):
        return glob(torch.zeros_like(e).masked_scatter(valid, ev))

    assert torch.autograd.gradcheck(on_valid, (e[valid].requires_grad_(),), eps=1e-6, atol=1e-8, fast_mode=True)
    # the material's (raw) parameters, through the profile and the diagonal's disk integral
    names = [n for n, _ in mat.named_parameters()]
    params = tuple(p.detach().clone().requires_grad_() for _, p in mat.named_parameters())

    def of_material(*p):
        return functional_call(glob, {f"material.{n}": x for n, x in zip(names, p)}, (e,))

    assert torch.autograd.gradcheck(of_material, params, eps=1e-7, atol=1e-7, fast_mode=True)
    grads = torch.autograd.grad(of_material(*params).sum(), params)
    assert all(float(g.abs().sum()) > 0 for g in grads)


def test_dense_values_in_blocks_equal_one_expression(small, monkeypatch):
    mesh, atlas = small
    mat = _material()
    glob = GlobalResponse(vertex_weights(mesh, atlas), build_dense_throughput(mesh, mat, zero_diagonal=False), mat,
                          atlas.valid_mask)
    with torch.enable_grad():  # autograd: one expression
        whole = glob.throughput_values().detach()
    monkeypatch.setattr(GlobalResponse, "value_block", 5000)  # 7 rows of 642 a block, the last one short
    with torch.no_grad():
        blocks = glob.throughput_values()
    torch.testing.assert_close(blocks, whole, rtol=0, atol=0)
    n = mesh.num_vertices
    assert blocks.shape == (3, n, n)
    # the diagonal is the disk integral, not A_i/3 R_d(0)
    disk = dipole_cumulative(torch.sqrt(mesh.vertex_areas / math.pi).unsqueeze(-1), mat.sigma_a, mat.sigma_s_prime,
                             mat.eta).detach()
    torch.testing.assert_close(blocks.diagonal(dim1=1, dim2=2).T, disk, rtol=1e-12, atol=0)


def test_throughput_layout_is_the_smaller_one():
    # dense: N^2 (5 + 4C) bytes; sparse: nnz (24 + 8C) (int32 pattern): at C = 3 they cross at nnz / N^2 = 17 / 48
    n = 1000
    assert throughput_layout(n, 354_167) == "dense"
    assert throughput_layout(n, 354_166) == "sparse"
    assert throughput_layout(n, n * n) == "dense" and throughput_layout(n, 0) == "sparse"
    # one channel: dense 9 bytes a pair, sparse 32 an entry
    assert throughput_layout(n, math.ceil(n * n * 9 / 32), channels=1) == "dense"
    assert throughput_layout(n, n * n * 9 // 32 - 1, channels=1) == "sparse"
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="num_vertices"):
            throughput_layout(bad, 10)
        with pytest.raises(ValueError, match="entries"):
            throughput_layout(10, bad)


def test_dense_rejects_bad_input(small):
    mesh, atlas = small
    mat = _material()
    with pytest.raises(ValueError, match="max_pairs"):
        build_dense_throughput(mesh, mat, max_pairs=100)
    with pytest.raises(ValueError, match="max_pairs"):
        build_dense_throughput(mesh, mat, max_pairs=0)
    with pytest.raises(TypeError, match="max_memory_mb"):
        build_dense_throughput(mesh, mat, max_memory_mb="1")
    with pytest.raises(ValueError, match="max_memory_mb"):
        build_dense_throughput(mesh, mat, max_memory_mb=-1.0)
    with pytest.raises(TypeError, match="zero_diagonal"):
        build_dense_throughput(mesh, mat, zero_diagonal=1)
    with pytest.raises(TypeError, match="profile"):
        build_dense_throughput(mesh, 3.0)
    w = vertex_weights(mesh, atlas)
    tp = build_throughput(mesh, mat)
    with pytest.raises(ValueError, match="hat"):
        GlobalResponse(w, build_dense_throughput(mesh, mat), mat, atlas.valid_mask, hat=hat_quadrature(mesh, tp))
    with pytest.raises(TypeError, match="throughput"):
        GlobalResponse(w, (tp.rows, tp.cols), mat, atlas.valid_mask)
    de = build_dense_throughput(mesh, mat)
    with pytest.raises(ValueError, match=r"throughput\.keep"):
        GlobalResponse(w, de._replace(keep=de.keep[:-1]), mat, atlas.valid_mask)
    with pytest.raises(ValueError, match="layout"):
        build_lensch(mesh, mat, resolution=32, layout="csr")
    with pytest.raises(ValueError, match="layout"):
        build_lensch(mesh, mat, resolution=64, blend=False, detail=True, layout="dense")


def test_build_lensch_picks_the_layout_and_both_render_alike():
    mesh = sphere(5.0, 2, dtype=torch.float64)  # 162 vertices: every pair kept for skin1
    mat = _material("skin1")
    e = None
    out = {}
    for layout in ("auto", "sparse", "dense"):
        built = build_lensch(mesh, mat, resolution=48, blend=True, kernel_size=5, layout=layout)
        assert built.stats["layout"] == ("dense" if layout == "auto" else layout)
        assert isinstance(built.module.global_response.dense, bool)
        if e is None:
            e = torch.rand(1, 3, *built.atlas.shape, dtype=torch.float64) * built.atlas.valid_mask
        with torch.no_grad():
            out[layout] = built.module(e)
    torch.testing.assert_close(out["dense"], out["sparse"], rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(out["auto"], out["dense"], rtol=0, atol=0)
    # the unblended default builds the hat quadrature: sparse whatever the density
    built = build_lensch(mesh, mat, resolution=48, blend=False)
    assert built.stats["layout"] == "sparse" and built.module.global_response.hat_entries is not None
    assert isinstance(build_dense_throughput(mesh, mat), DenseThroughput)
