"""Lensch modules: irradiance atlas, local and global response, the composed method, gradients, export."""

from __future__ import annotations

import functools
import math

import pytest
import torch
from torch.func import functional_call

from torchsss.geometry import DirectionalLight, PointLight, build_atlas, sphere, surface_irradiance
from torchsss.geometry.lensch import blending_weights, build_throughput, local_kernel_geometry, vertex_weights
from torchsss.modules import DipoleMaterial, TabulatedMaterial
from torchsss.modules.lensch import GlobalResponse, IrradianceAtlas, LenschTranslucency, LocalResponse
from torchsss.ops.sv_conv import sv_conv2d_reference
from torchsss.physics import dipole_cumulative, dipole_rd, total_diffuse_reflectance
from torchsss.scene import Material


def _dip(sa, ss, eta=1.3):
    """A dipole profile callable from coefficients (the throughput build's profile)."""
    return functools.partial(dipole_rd, sigma_a=sa, sigma_s_prime=ss, eta=eta)


@pytest.fixture(scope="module")
def small():
    mesh = sphere(6.0, 3, dtype=torch.float64)
    atlas = build_atlas(mesh, 64, kernel_size=5)
    return mesh, atlas


def _material(name="skin1", dtype=torch.float64):
    sa, ss, eta = Material.from_json(name).tensors(dtype)
    return DipoleMaterial(sa, ss, eta)


def test_irradiance_atlas_matches_surface_irradiance(small):
    _, atlas = small
    mod = IrradianceAtlas.from_atlas(atlas, eta=1.3)
    pts = atlas.position.flatten(2).transpose(1, 2)
    nrm = atlas.normal.flatten(2).transpose(1, 2)
    for light, hom, inten in (
        (PointLight((20.0, 10.0, 30.0), (1e3, 2e3, 3e3)), [20.0, 10.0, 30.0, 1.0], [1e3, 2e3, 3e3]),
        (DirectionalLight((0.0, -0.6, -0.8), (1.0, 2.0, 3.0)), [0.0, 0.6, 0.8, 0.0], [1.0, 2.0, 3.0]),
    ):
        e = mod(torch.tensor([hom], dtype=torch.float64), torch.tensor([inten], dtype=torch.float64))
        want = surface_irradiance(pts, nrm, light, 1.3).transpose(1, 2).reshape(1, 3, 64, 64) * atlas.valid_mask
        torch.testing.assert_close(e, want, rtol=1e-10, atol=1e-12)


def test_irradiance_atlas_lights_only_valid_texels_as_the_full_image_does():
    """The frame's irradiance atlas (valid texels only) against the whole-image formulation, shadowed and not."""
    from torchsss.geometry import build_shadow_map, shadow_visibility, torus
    from torchsss.geometry.atlas_frame import irradiance_atlas

    mesh = torus(8.0, 3.0, 24, 12, dtype=torch.float64)  # the ring shadows itself under an oblique light
    atlas = build_atlas(mesh, 64, kernel_size=5)
    index, pos, nrm = atlas.valid_texels
    assert index.shape == (int(atlas.valid_mask.sum()),) and pos.is_contiguous() and nrm.is_contiguous()
    torch.testing.assert_close(pos, atlas.position.reshape(3, -1)[:, index].T)
    torch.testing.assert_close(nrm, atlas.normal.reshape(3, -1)[:, index].T)
    pts_all = atlas.position.flatten(2).transpose(1, 2)
    nrm_all = atlas.normal.flatten(2).transpose(1, 2)
    lights = [PointLight((30.0, 5.0, 12.0), (4e3, 3e3, 2e3)), DirectionalLight((-0.3, 0.2, -0.93), (1.0, 2.0, 3.0))]
    for subset in (lights[:1], lights):
        got = irradiance_atlas(mesh, atlas, subset, 1.4, shadow_resolution=256)
        vis = [shadow_visibility(build_shadow_map(mesh, light, 256), pts_all, nrm_all, light) for light in subset]
        assert any(bool((v[atlas.valid_mask.reshape(1, -1)] == 0).any()) for v in vis)  # shadows do occur
        want = surface_irradiance(pts_all, nrm_all, subset, 1.4, visibility=vis)
        want = want.transpose(1, 2).reshape(1, 3, 64, 64) * atlas.valid_mask
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)
    # gradients reach a tensor eta through the scatter into the image
    eta = torch.tensor(1.4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: irradiance_atlas(mesh, atlas, lights, x, shadow_resolution=64)
                                    .sum(), (eta,))


def test_local_response_is_the_kernel_convolution(small):
    _, atlas = small
    geom = local_kernel_geometry(atlas, 5)
    mat = _material()
    local = LocalResponse(geom, mat, self_term="point")
    k = local.kernels()
    want = geom.area.unsqueeze(-1) * mat(geom.distance.unsqueeze(-1))
    torch.testing.assert_close(k, want.permute(4, 0, 1, 2, 3))
    # the default self term: the closed-form disk integral of R_d over the texel's area at the centre tap
    kd = LocalResponse(geom, mat).kernels()
    disk = dipole_cumulative(torch.sqrt(geom.area[:, :, 2, 2] / math.pi).unsqueeze(-1), mat.sigma_a,
                             mat.sigma_s_prime, mat.eta)
    torch.testing.assert_close(kd[:, :, :, 2, 2], disk.permute(2, 0, 1))
    off = torch.ones(5, 5, dtype=torch.bool)
    off[2, 2] = False
    torch.testing.assert_close(kd[..., off], k[..., off])
    e = torch.rand(2, 3, 64, 64, dtype=torch.float64) * atlas.valid_mask
    out = local(e)
    for c in range(3):
        ref = sv_conv2d_reference(e[:, c:c + 1], k[c])
        torch.testing.assert_close(out[:, c:c + 1], ref, rtol=1e-10, atol=1e-14)


def test_local_response_copy_flag_shares_or_copies_the_build_tensors(small):
    _, atlas = small
    geom = local_kernel_geometry(atlas, 5, compact=True)
    mat = _material()
    correction = torch.rand(3, geom.index.numel(), 5, 5, dtype=torch.float64)
    shared = LocalResponse(geom, mat, correction=correction, copy=False)
    copied = LocalResponse(geom, mat, correction=correction)
    assert shared.distance.data_ptr() == geom.distance.data_ptr()
    assert shared.correction.data_ptr() == correction.data_ptr()
    assert copied.distance.data_ptr() != geom.distance.data_ptr()
    assert copied.correction.data_ptr() != correction.data_ptr()
    torch.testing.assert_close(shared.kernels(), copied.kernels(), rtol=0, atol=0)
    with pytest.raises(TypeError, match="copy: expected a bool"):
        LocalResponse(geom, mat, copy="no")


def test_compact_local_response_equals_the_full_one(small):
    """Kernels held for the valid receivers only: the same kernels, planes and response as the full geometry's,
    with a blending correction, M_d, a mask and M_i; receivers outside the compact set get exactly 0."""
    _, atlas = small
    full = local_kernel_geometry(atlas, 5)
    comp = local_kernel_geometry(atlas, 5, compact=True)
    valid = atlas.valid_mask[0, 0].reshape(-1)
    assert torch.equal(comp.index, valid.nonzero(as_tuple=True)[0]) and comp.shape == (64, 64)
    assert 0 < comp.index.numel() < 64 * 64
    torch.testing.assert_close(comp.distance, full.distance.reshape(-1, 5, 5)[comp.index], rtol=0, atol=0)
    torch.testing.assert_close(comp.area, full.area.reshape(-1, 5, 5)[comp.index], rtol=0, atol=0)
    outside = torch.ones(64 * 64, dtype=torch.bool)
    outside[comp.index] = False
    assert float(full.area.reshape(-1, 5, 5)[outside].abs().max()) == 0.0
    mat = _material()
    g = torch.Generator().manual_seed(3)
    corr_full = torch.rand(3, 64, 64, 5, 5, dtype=torch.float64, generator=g) * valid.reshape(1, 64, 64, 1, 1)
    corr_comp = corr_full.reshape(3, -1, 5, 5)[:, comp.index]
    md = 0.5 + torch.rand(1, 1, 64, 64, dtype=torch.float64, generator=g)
    mask = (torch.rand(1, 1, 64, 64, generator=g) > 0.3).to(torch.float64)
    mi = 0.5 + torch.rand(1, 3, 64, 64, dtype=torch.float64, generator=g)
    kw = dict(distance_scale=md, mask=mask, irradiance_scale=mi)
    a = LocalResponse(full, mat, correction=corr_full, **kw)
    b = LocalResponse(comp, mat, correction=corr_comp, **kw)
    torch.testing.assert_close(a.kernels(), b.kernels(), rtol=1e-14, atol=0)
    e = torch.rand(2, 3, 64, 64, dtype=torch.float64, generator=g) * atlas.valid_mask
    torch.testing.assert_close(a(e), b(e), rtol=1e-13, atol=0)
    # the loop-based reference: every tap of every valid receiver written out (M_d on the distance, the mask on
    # both ends, the disk self term at the centre, the correction added)
    kern = b.kernels().detach()
    m = mask.reshape(64, 64)
    mdp = torch.nn.functional.pad(md[0, 0], (2, 2, 2, 2))
    mp = torch.nn.functional.pad(m, (2, 2, 2, 2))
    for flat in comp.index[:: max(1, comp.index.numel() // 40)].tolist():
        y, x = divmod(flat, 64)
        d = full.distance[y, x] * mdp[y:y + 5, x:x + 5]
        ar = full.area[y, x] * mp[y:y + 5, x:x + 5] * m[y, x]
        want = ar.unsqueeze(-1) * mat(d.unsqueeze(-1))
        disk = dipole_cumulative(torch.sqrt(ar[2, 2] / math.pi).reshape(1, 1) * md[0, 0, y, x], mat.sigma_a,
                                 mat.sigma_s_prime, mat.eta)[0] / md[0, 0, y, x] ** 2
        want[2, 2] = disk
        want = want.permute(2, 0, 1) + corr_full[:, y, x]
        torch.testing.assert_close(kern[:, y, x], want, rtol=1e-12, atol=1e-15)
    assert float(kern.reshape(3, -1, 5, 5)[:, outside].abs().max()) == 0.0
    with pytest.raises(ValueError, match="correction: expected shape"):
        LocalResponse(comp, mat, correction=corr_full)
    with pytest.raises(ValueError, match="needs its shape"):
        LocalResponse(comp._replace(shape=None), mat)


def test_compact_blending_correction_is_the_full_one_at_its_receivers(small):
    mesh, atlas = small
    mat = _material("marble")
    comp = local_kernel_geometry(atlas, 5, compact=True)
    full = blending_weights(mesh, atlas, mat, kernel_size=5)
    part = blending_weights(mesh, atlas, mat, kernel_size=5, index=comp.index)
    torch.testing.assert_close(part.weights, full.weights, rtol=0, atol=0)
    torch.testing.assert_close(part.kernel_correction, full.kernel_correction.reshape(3, -1, 5, 5)[:, comp.index],
                               rtol=0, atol=0)
    assert float(full.kernel_correction.abs().amax()) > 0
    with pytest.raises(ValueError, match="every valid texel"):
        blending_weights(mesh, atlas, mat, kernel_size=5, index=comp.index[1:])
    with pytest.raises(TypeError, match="index: expected a \\(N,\\) int64 tensor"):
        blending_weights(mesh, atlas, mat, kernel_size=5, index=comp.index.to(torch.int32))
    with pytest.raises(ValueError, match="index: expected flat texels"):
        blending_weights(mesh, atlas, mat, kernel_size=5, index=comp.index + 64 * 64)


def test_global_response_compact_texels_equal_the_whole_image_form(small, monkeypatch):
    """Outside tracing the per-frame gather and scatter run on the texels that carry anything; the traced (exported)
    whole-image form gives the same values and gradients, whatever lies in the invalid texels."""
    import torchsss.modules.lensch as lensch_module

    mesh, atlas = small
    mat = _material()
    w = vertex_weights(mesh, atlas)
    tp = build_throughput(mesh, _dip(*Material.from_json("skin1").tensors(torch.float64)), threshold=1e-4)
    glob = GlobalResponse(w, tp, mat, atlas.valid_mask)
    assert glob._gather_texels.numel() == int(atlas.valid_mask.sum()) < 64 * 64
    e = torch.rand(2, 3, 64, 64, dtype=torch.float64)  # nonzero in invalid texels too
    vv = torch.rand(2, mesh.num_vertices, 3, dtype=torch.float64, requires_grad=True)
    compact = (glob.vertex_irradiance(e), glob.reconstruct(vv), glob(e))
    g_compact = torch.autograd.grad(glob.reconstruct(vv).square().sum(), vv)[0]
    monkeypatch.setattr(lensch_module, "is_tracing", lambda: True)
    whole = (glob.vertex_irradiance(e), glob.reconstruct(vv), glob(e))
    g_whole = torch.autograd.grad(glob.reconstruct(vv).square().sum(), vv)[0]
    for a, b in zip(compact, whole):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(g_compact, g_whole, rtol=1e-12, atol=1e-14)
    monkeypatch.undo()
    assert torch.autograd.gradcheck(lambda x: glob.reconstruct(x), (vv[:1, :, :1].detach().clone().requires_grad_(),))


def test_global_response_against_dense_sums(small):
    mesh, atlas = small
    mat = _material()
    w = vertex_weights(mesh, atlas)
    tp = build_throughput(mesh, _dip(*Material.from_json("skin1").tensors(torch.float64)), threshold=0.0)
    glob = GlobalResponse(w, tp, mat, atlas.valid_mask, method="scatter")
    e = torch.rand(1, 3, 64, 64, dtype=torch.float64) * atlas.valid_mask
    eg = glob.vertex_irradiance(e)
    ids = w.vertex_ids.reshape(3, -1)
    dual = w.dual.reshape(3, -1)
    want = torch.zeros(mesh.num_vertices, 3, dtype=torch.float64)
    for k in range(3):
        want.index_add_(0, ids[k], (dual[k].unsqueeze(-1) * e[0].reshape(3, -1).T))
    torch.testing.assert_close(eg[0], want)
    # full (threshold 0) throughput = dense F^T E^g
    v = mesh.vertices
    d = (v[:, None, :] - v[None, :, :]).norm(dim=-1, keepdim=True)
    f = mesh.vertex_areas[:, None, None] * mat(d)  # (N, N, C): F_ij
    n = mesh.num_vertices
    f[torch.arange(n), torch.arange(n)] = dipole_cumulative(  # the diagonal: R_d integrated over the vertex's disk
        torch.sqrt(mesh.vertex_areas / math.pi).unsqueeze(-1), mat.sigma_a, mat.sigma_s_prime, mat.eta)
    dense = torch.einsum("ic,ijc->jc", eg[0], f)
    torch.testing.assert_close(glob.vertex_radiosity(e)[0], dense, rtol=1e-9, atol=1e-12)
    csr = GlobalResponse(w, tp, mat, atlas.valid_mask, method="csr")
    with torch.no_grad():
        torch.testing.assert_close(csr(e), glob(e), rtol=1e-9, atol=1e-12)


def test_material_gradients_flow(small):
    mesh, atlas = small
    mat = _material()
    sa, ss, eta = Material.from_json("skin1").tensors(torch.float64)
    module = LenschTranslucency(LocalResponse(local_kernel_geometry(atlas, 5), mat),
                                GlobalResponse(vertex_weights(mesh, atlas),
                                    build_throughput(mesh, _dip(sa, ss, eta)), mat,
                                               atlas.valid_mask, method="scatter"))
    e = torch.rand(1, 3, 64, 64, dtype=torch.float64) * atlas.valid_mask
    module(e).sum().backward()
    grads = [p.grad for p in mat.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0 for g in grads)


@pytest.fixture
def _one_thread_for_this_test():
    """conftest's one_thread for a single test: 24 x 24 tensors, ~2000 evaluations (one intra-op thread is as fast
    on an idle machine and several times faster on a loaded one)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.usefixtures("_one_thread_for_this_test")
def test_gradcheck_wrt_irradiance():
    mesh = sphere(4.0, 1, dtype=torch.float64)
    atlas = build_atlas(mesh, 24, kernel_size=3)
    sa, ss, eta = Material.from_json("marble").tensors(torch.float64)
    mat = DipoleMaterial(sa, ss, eta)
    module = LenschTranslucency(LocalResponse(local_kernel_geometry(atlas, 3), mat),
                                GlobalResponse(vertex_weights(mesh, atlas),
                                    build_throughput(mesh, _dip(sa, ss, eta)), mat,
                                               atlas.valid_mask, method="scatter"))
    valid = atlas.valid_mask.expand(1, 3, 24, 24)
    e = torch.rand(1, 3, 24, 24, dtype=torch.float64) * atlas.valid_mask

    def on_valid(ev):  # the module as a function of the valid texels only (235 of 576: 2.5x fewer evaluations)
        return module(torch.zeros_like(e).masked_scatter(valid, ev))

    # fast mode: the Jacobian along random directions (705 inputs; the full Jacobian took 16 s)
    assert torch.autograd.gradcheck(on_valid, (e[valid].requires_grad_(),), eps=1e-6, atol=1e-8, fast_mode=True)
    # the texels outside the valid mask: neither the output nor its gradient depends on them
    with torch.no_grad():
        torch.testing.assert_close(module(e + torch.rand_like(e) * ~valid), module(e), rtol=0, atol=0)
    e = e.requires_grad_()
    out = module(e)
    (grad,) = torch.autograd.grad(out, e, torch.randn_like(out))
    assert bool((grad[~valid] == 0).all()) and bool((grad[valid] != 0).any())


def test_heterogeneous_painted_region(small):
    """M_d < 1 in a region spreads its light farther (blurrier); M_i = 2 doubles what it sends (brighter)."""
    _, atlas = small
    geom = local_kernel_geometry(atlas, 5)
    painted = (atlas.position[:, 0:1] > 2.0).to(torch.float64)  # the +x cap
    md = 1.0 - 0.5 * painted
    mi = 1.0 + painted
    base = LocalResponse(geom, _material())
    blur = LocalResponse(geom, _material(), distance_scale=md)
    bright = LocalResponse(geom, _material(), irradiance_scale=mi.expand(1, 3, 64, 64))
    # one lit texel inside the painted region, one outside
    cand = torch.nonzero((painted[0, 0] > 0) & atlas.chart_mask[0, 0])
    idx = cand[len(cand) // 2]
    e = torch.zeros(1, 3, 64, 64, dtype=torch.float64)
    e[0, :, idx[0], idx[1]] = 1.0
    with torch.no_grad():
        b0, b1, b2 = base(e), blur(e), bright(e)
    r = (atlas.position - atlas.position[:, :, idx[0], idx[1]].view(1, 3, 1, 1)).norm(dim=1, keepdim=True)
    spread = lambda b: float((b[:, 0:1] * r**2).sum() / b[:, 0:1].sum())  # noqa: E731
    assert spread(b1) > spread(b0) * 1.2, "M_d < 1 must spread the light farther"
    assert float(b1.sum()) > float(b0.sum())
    torch.testing.assert_close(b2, 2.0 * b0)


# with -m slow: the same LenschTranslucency graph (GlobalResponse "auto" is "scatter" while exporting) is exported in
# the default run by tests/test_export_onnx.py::test_registry_entry_matches_eager_at_test_size[lensch] (with a
# dynamic batch), and "auto" resolving to "scatter" under export by tests/test_sparse_apply.py's
# test_onnx_export_pattern_buffers
@pytest.mark.slow
def test_per_frame_module_exports_to_onnx(small, tmp_path):
    pytest.importorskip("onnxruntime")
    from torchsss.export import export_onnx, run_onnxruntime

    mesh, _ = small
    sa, ss, eta = Material.from_json("skin1").tensors(torch.float32)
    mesh32 = mesh.with_dtype(torch.float32)
    atlas32 = build_atlas(mesh32, 64, kernel_size=5)
    mat = DipoleMaterial(sa, ss, eta)
    module = LenschTranslucency(LocalResponse(local_kernel_geometry(atlas32, 5), mat),
                                GlobalResponse(vertex_weights(mesh32, atlas32),
                                    build_throughput(mesh32, _dip(sa, ss, eta)),
                                               mat, atlas32.valid_mask)).eval()
    e = torch.rand(1, 3, 64, 64) * atlas32.valid_mask
    path = export_onnx(module, (e,), tmp_path / "lensch.onnx")
    e2 = torch.rand(1, 3, 64, 64) * atlas32.valid_mask
    (got,) = run_onnxruntime(path, (e2,))
    with torch.no_grad():
        want = module(e2)
    rel = float((torch.from_numpy(got) - want).abs().max() / want.abs().max())
    assert rel < 1e-5, rel
    assert math.isfinite(rel)


def test_extremes_tiny_and_huge_r_max():
    """r_max far below a texel (local kernel ~ identity) and far beyond the object (global term dominates)."""
    mesh = sphere(5.0, 2, dtype=torch.float64)
    atlas = build_atlas(mesh, 128, kernel_size=5)
    chart = atlas.chart_mask.expand(1, 3, 128, 128)
    for sa_v, ss_v in ((50.0, 500.0), (1e-4, 0.05)):
        sa = torch.full((3,), sa_v, dtype=torch.float64)
        ss = torch.full((3,), ss_v, dtype=torch.float64)
        mat = DipoleMaterial(sa, ss, torch.tensor(1.3, dtype=torch.float64))
        local = LocalResponse(local_kernel_geometry(atlas, 5), mat)
        glob = GlobalResponse(vertex_weights(mesh, atlas), build_throughput(mesh, _dip(sa, ss, 1.3)), mat,
                              atlas.valid_mask)
        e = torch.ones(1, 3, 128, 128, dtype=torch.float64) * atlas.valid_mask
        with torch.no_grad():
            bl, bg = local(e), glob(e)
        b = bl + bg
        assert bool(torch.isfinite(b).all()) and float(b[chart].min()) > 0
        r_total = float(total_diffuse_reflectance(sa, ss, 1.3)[0])
        if sa_v > 1:  # r_max << texel: the local kernel is the identity times the disk integral ~ R_total
            assert float(bl[chart].mean()) == pytest.approx(r_total, rel=0.05)
        else:  # the global term carries (almost) everything
            assert float(bg[chart].mean()) > 20 * float(bl[chart].mean())


def test_row_block_kernels_match_the_one_expression(small, monkeypatch):
    """The eager blocks of receivers (only the valid ones are held) against the autograd path's one expression."""
    _, atlas = small
    local = LocalResponse(local_kernel_geometry(atlas, 5), _material("marble"))
    assert 0 < local.index.numel() < 64 * 64  # some receivers are not held: the test covers the compaction
    monkeypatch.setattr(LocalResponse, "block_bytes", 5 * 25 * 4 * 8 * 97)  # 97 receivers a block: 23 blocks
    with torch.no_grad():
        blocks = local.planes()
    with torch.enable_grad():
        whole = local.planes().detach()
    torch.testing.assert_close(blocks, whole, rtol=1e-12, atol=0)
    assert float(whole.abs().amax()) > 0


def test_cached_kernels_follow_material_edits(small):
    """Relighting reuses the evaluated kernels/throughput, but an edited material is never served stale."""
    mesh, atlas = small
    sa, ss, eta = Material.from_json("skin1").tensors(torch.float64)
    mat = DipoleMaterial(sa, ss, eta)
    module = LenschTranslucency(LocalResponse(local_kernel_geometry(atlas, 5), mat),
                                GlobalResponse(vertex_weights(mesh, atlas),
                                    build_throughput(mesh, _dip(sa, ss, eta)), mat,
                                               atlas.valid_mask))
    e = torch.rand(1, 3, 64, 64, dtype=torch.float64) * atlas.valid_mask
    with torch.no_grad():
        first, again = module(e), module(e)
        torch.testing.assert_close(first, again)
        next(iter(mat.parameters())).add_(0.5)  # edit the material in place
        edited = module(e)
    fresh = module(e).detach()  # with autograd: recomputed from scratch
    torch.testing.assert_close(edited, fresh)
    assert float((edited - first).abs().max()) > 1e-6


def test_modules_reject_bad_input(small):
    mesh, atlas = small
    geom = local_kernel_geometry(atlas, 5)
    with pytest.raises(ValueError, match="fresnel"):
        IrradianceAtlas.from_atlas(atlas, fresnel="fast")
    with pytest.raises(ValueError, match="position"):
        IrradianceAtlas(atlas.position[0], atlas.normal, atlas.valid_mask)
    mod = IrradianceAtlas.from_atlas(atlas)
    with pytest.raises(ValueError, match="light"):
        mod(torch.zeros(1, 3, dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="intensity"):
        mod(torch.zeros(2, 4, dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="self_term"):
        LocalResponse(geom, _material(), self_term="exact")
    with pytest.raises(ValueError, match="distance_scale"):
        LocalResponse(geom, _material(), distance_scale=torch.ones(1, 1, 32, 32, dtype=torch.float64))
    with pytest.raises(ValueError, match="valid"):
        GlobalResponse(vertex_weights(mesh, atlas),
            build_throughput(mesh, _dip(*Material.from_json("skin1").tensors())),
                       _material(), torch.ones(1, 1, 8, 8, dtype=torch.bool))
    with pytest.raises(ValueError, match="albedo"):
        LenschTranslucency(LocalResponse(geom, _material()),
                           GlobalResponse(vertex_weights(mesh, atlas),
                                          build_throughput(mesh, _dip(*Material.from_json("skin1").tensors())),
                                          _material(), atlas.valid_mask),
                           albedo=torch.ones(1, 3, 64, 64, dtype=torch.float64))


def test_tabulated_material_matches_the_analytic_profile(small):
    """LUT speed path: the whole Lensch module through TabulatedMaterial vs the analytic dipole; gradients flow."""
    mesh, atlas = small
    geom = local_kernel_geometry(atlas, 5)
    weights = vertex_weights(mesh, atlas)
    mat = _material("marble")
    tp = build_throughput(mesh, mat)
    e = torch.rand(1, 3, 64, 64, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * atlas.valid_mask

    def module(m):
        return LenschTranslucency(LocalResponse(geom, m), GlobalResponse(weights, tp, m, atlas.valid_mask))

    want = module(mat)(e)
    errors = []
    for size in (64, 4096):
        tab = TabulatedMaterial(mat, size=size, eps=1e-6)
        got = module(tab)(e)
        errors.append(float((got - want).detach().norm() / want.detach().norm()))
    assert errors[1] < 1e-4, errors
    assert errors[0] > 10 * errors[1], errors  # the error shrinks with the table size
    # the disk self term stays closed-form through the wrapper's coefficients
    torch.testing.assert_close(LocalResponse(geom, TabulatedMaterial(mat)).kernels()[:, :, :, 2, 2],
                               LocalResponse(geom, mat).kernels()[:, :, :, 2, 2])
    tab = TabulatedMaterial(mat, size=256)
    module(tab)(e).sum().backward()
    assert mat.raw_sigma_a.grad is not None and bool(torch.isfinite(mat.raw_sigma_a.grad).all())
    assert float(mat.raw_sigma_s_prime.grad.abs().sum()) > 0
    with pytest.raises(TypeError, match="material"):
        TabulatedMaterial(lambda r: r)
    with pytest.raises(ValueError, match="size"):
        TabulatedMaterial(mat, size=1)


def test_tabulated_material_gradients_converge_to_the_dipole_gradients():
    """The table's range r_max(eps) is a discrete budget (bisection, no gradient), so the table is only
    piecewise smooth in the material and a finite-difference gradcheck sees its node shifts. The autograd
    gradient holds the nodes fixed: it is the gradient of the interpolated profile and must converge to the exact
    dipole gradient as the table grows (the table's own values are gradchecked in test_lut_burley.py)."""
    mat = _material("skin1")
    r = torch.tensor([[0.0], [0.3], [1.7], [4.0]], dtype=torch.float64)
    md = torch.tensor([[1.0], [0.7], [1.3], [1.0]], dtype=torch.float64)
    raw = (mat.raw_sigma_a.detach().clone(), mat.raw_sigma_s_prime.detach().clone())

    def jac(module, prefix):
        def f(raw_sa, raw_ss):
            params = {f"{prefix}raw_sigma_a": raw_sa, f"{prefix}raw_sigma_s_prime": raw_ss}
            return functional_call(module, params, (r,), {"distance_scale": md})
        return torch.cat([j.flatten() for j in torch.autograd.functional.jacobian(f, raw)])

    exact = jac(mat, "")
    errors = [float((jac(TabulatedMaterial(mat, size=n), "material.") - exact).norm() / exact.norm())
              for n in (64, 1024, 8192)]
    assert errors[0] < 0.05 and errors[1] < 1e-4 and errors[2] < 1e-5, errors
    assert errors[2] < errors[1] < errors[0], errors


def test_local_response_from_atlas_derives_the_stored_taps_bit_for_bit(small):
    """Taps gathered from the atlas's maps at evaluation time equal the stored compact geometry's, with M_d, a mask,
    M_i and a correction, in the eager blocks and on the autograd path; gradients reach the material alike."""
    _, atlas = small
    comp = local_kernel_geometry(atlas, 5, compact=True)
    g = torch.Generator().manual_seed(5)
    corr = torch.rand(3, comp.index.numel(), 5, 5, dtype=torch.float64, generator=g)
    md = 0.5 + torch.rand(1, 1, 64, 64, dtype=torch.float64, generator=g)
    mask = (torch.rand(1, 1, 64, 64, generator=g) > 0.3).to(torch.float64)
    mi = 0.5 + torch.rand(1, 3, 64, 64, dtype=torch.float64, generator=g)
    e = torch.rand(1, 3, 64, 64, dtype=torch.float64, generator=g) * atlas.valid_mask
    for kw in ({}, {"correction": corr, "distance_scale": md, "mask": mask, "irradiance_scale": mi}):
        mat_a, mat_b = _material(), _material()
        stored = LocalResponse(comp, mat_a, **kw)
        derived = LocalResponse.from_atlas(atlas, 5, mat_b, **kw)
        assert derived.distance is None and derived.area is None
        with torch.no_grad():
            torch.testing.assert_close(derived.planes(), stored.planes(), rtol=0, atol=0)
        out_a, out_b = stored(e), derived(e)
        torch.testing.assert_close(out_b, out_a, rtol=0, atol=0)
        out_a.sum().backward()
        out_b.sum().backward()
        for pa, pb in zip(mat_a.parameters(), mat_b.parameters()):
            torch.testing.assert_close(pb.grad, pa.grad, rtol=1e-12, atol=0)
    with pytest.raises(TypeError, match="atlas"):
        LocalResponse.from_atlas(None, 5, _material())
    with pytest.raises(ValueError, match="kernel_size"):
        LocalResponse.from_atlas(atlas, 4, _material())
    with pytest.raises(ValueError, match="correction: expected shape"):
        LocalResponse.from_atlas(atlas, 5, _material(), correction=corr[:, 1:])
