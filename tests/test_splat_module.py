"""SplatTranslucency as a layer: the material table, object ids, heterogeneous modifiers, extremes and ONNX."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import camera_gbuffer, light_view
from torchsss.geometry.lights import DirectionalLight, SpotLight
from torchsss.geometry.procedural import plane, sphere
from torchsss.modules import DipoleMaterial, SplatTranslucency
from torchsss.ops.splat import splat_window_size
from torchsss.physics.dipole import dipole_rd
from torchsss.pipelines.splat import render_splat
from torchsss.scene import Material

CAM = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0), fov_deg=30.0, width=24, height=24)


def _plane_view(dtype=torch.float64, cam=CAM, size=40.0):
    g = camera_gbuffer(plane(size, size, 4, dtype=dtype), cam)
    return g.position, g.mask, cam.view_proj(dtype=dtype)


def _grid_sources(spacing, half, dtype=torch.float64, x_range=None, y_range=None):
    """Sources on a square lattice of the plane z = 0, each carrying the flux of a unit irradiance on its cell."""
    xr = (-half, half) if x_range is None else x_range
    yr = (-half, half) if y_range is None else y_range
    # cells end exactly at the upper bound (the edge of a lit half-plane)
    xs_ = xr[1] - spacing / 2 - spacing * torch.arange(math.ceil((xr[1] - xr[0]) / spacing), dtype=dtype)
    ys_ = yr[1] - spacing / 2 - spacing * torch.arange(math.ceil((yr[1] - yr[0]) / spacing), dtype=dtype)
    ys, xs = torch.meshgrid(ys_, xs_, indexing="ij")
    pts = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.zeros(xs.numel(), dtype=dtype)], -1)
    flux = torch.full((pts.shape[0], 3), spacing * spacing, dtype=dtype)
    return pts.unsqueeze(0), flux.unsqueeze(0)


def _mat(name, dtype=torch.float64):
    return DipoleMaterial.from_preset(name, dtype=dtype)


def test_material_table_equals_one_module_per_material():
    dst, mask, vp = _plane_view()
    g = torch.Generator().manual_seed(0)
    src = torch.cat([torch.rand(1, 40, 2, generator=g, dtype=torch.float64) * 16 - 8,
                     torch.zeros(1, 40, 1, dtype=torch.float64)], -1)
    flux = torch.rand(1, 40, 3, generator=g, dtype=torch.float64)
    ids = torch.randint(0, 3, (1, 40), generator=g)
    names = ["skin1", "marble", "ketchup"]
    table = SplatTranslucency([_mat(n) for n in names])
    got = table(src, flux, dst, mask, vp, src_material=ids)
    want = sum(SplatTranslucency(_mat(n))(src, flux * (ids == k).unsqueeze(-1), dst, mask, vp)
               for k, n in enumerate(names))
    assert float(want.detach().amax()) > 0
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)
    assert table.r_max.shape == (3,) and float(table.r_max[1]) > float(table.r_max[0])  # marble reaches farther
    # gradients reach every row of the table
    got.sum().backward()
    assert all(float(m.raw_sigma_s_prime.grad.abs().sum()) > 0 for m in table.materials)


def test_object_ids_stop_light_at_the_object_boundary():
    dst, mask, vp = _plane_view()
    dst_obj = (dst[:, :1] > 0).to(torch.int64)  # object 1: x > 0, object 0: x <= 0
    src, flux = _grid_sources(0.5, 8.0)
    src_obj = (src[..., 0] > 0).to(torch.int64)
    m = SplatTranslucency(_mat("marble")).requires_grad_(False)
    clipped = m(src, flux, dst, mask, vp, src_object=src_obj, dst_object=dst_obj)
    left_only = m(src, flux * (src_obj == 0).unsqueeze(-1), dst, mask, vp)
    right_only = m(src, flux * (src_obj == 1).unsqueeze(-1), dst, mask, vp)
    want = torch.where(dst_obj.bool(), right_only, left_only) * mask
    torch.testing.assert_close(clipped, want, rtol=1e-10, atol=1e-14)
    free = m(src, flux, dst, mask, vp)
    assert float((free - clipped).abs().amax()) > 1e-3 * float(free.amax())  # marble scatters across x = 0


def _half_plane_quadrature(x, sa, ss, eta, r_max, md):
    """B(x) of a unit irradiance on the half-plane y < 0 (1D: x is the distance past the edge), by quadrature."""
    # B(x) = int_{u > x} int_t R_d(sqrt(u^2 + t^2) * md) dt du, truncated at r = r_max / md
    reach = r_max / md
    u = torch.linspace(0.0, reach, 801, dtype=torch.float64)
    t = torch.linspace(-reach, reach, 1601, dtype=torch.float64)
    uu, tt = torch.meshgrid(u, t, indexing="ij")
    r = torch.sqrt(uu**2 + tt**2)
    prof = dipole_rd(r.unsqueeze(-1) * md, sa, ss, eta) * (r <= reach).unsqueeze(-1)
    inner = torch.trapezoid(prof, t, dim=1)  # (U, C): line integral across
    out = []
    for xv in x.tolist():
        sel = u >= abs(xv)
        part = torch.trapezoid(inner[sel], u[sel], dim=0) if int(sel.sum()) > 1 else torch.zeros(3, dtype=u.dtype)
        total = torch.trapezoid(inner, u, dim=0) * 2
        out.append(part if xv >= 0 else total - part)
    return torch.stack(out)


@pytest.mark.parametrize("md", [1.0, 0.6])
def test_painted_distance_multiplier_renders_blurrier_as_the_model_says(md):
    """Sources lit on x < 0 only; a distance multiplier M_d < 1 widens the response past the edge by 1 / M_d."""
    mat = _mat("skin1")
    sa, ss, eta = mat.sigma_a.detach(), mat.sigma_s_prime.detach(), mat.eta.detach()
    cam = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0), fov_deg=0.4, width=40, height=1)
    dst, mask, vp = _plane_view(cam=cam, size=100.0)  # one row, x in [-8.4, 8.4] mm
    m = SplatTranslucency(mat)
    reach = float(m.r_max) / md
    src, flux = _grid_sources(0.25, 0.0, x_range=(-4.5 - reach, 0.0), y_range=(-0.1 - reach, 0.1 + reach))
    scale = torch.full((1, src.shape[1], 1), md, dtype=torch.float64)
    out = m(src, flux, dst, mask, vp, src_distance_scale=scale)
    row = out[0, :, 0, :].T  # (W, C) along x
    x = dst[0, 0, 0, :]
    sel = x.abs() < 4.0
    assert bool(mask.all()) and int(sel.sum()) >= 18
    want = _half_plane_quadrature(x[sel], sa, ss, eta, float(m.r_max), md)
    rel = ((row[sel] - want).abs() / want.abs().amax(0)).amax()
    assert float(rel) < 0.02, float(rel)
    # the behaviour the painter expects: blurrier (a larger fraction of the lit level past the edge)
    i_in, i_out = int(torch.argmin((x + 2.0).abs())), int(torch.argmin((x - 1.0).abs()))
    spread = row[i_out] / row[i_in]
    if md < 1.0:
        base = m(src, flux, dst, mask, vp)[0, :, 0, :].T
        assert bool((spread > base[i_out] / base[i_in]).all())


def test_painted_irradiance_modulation_renders_brighter_as_the_model_says():
    dst, mask, vp = _plane_view()
    src, flux = _grid_sources(0.25, 12.0)
    painted = (src[..., 0] > 0).unsqueeze(-1)
    mi = torch.where(painted, 2.0, 1.0).to(torch.float64)
    dense = DipoleMaterial((0.5, 0.4, 0.3), (5.0, 6.0, 7.0), 1.3, dtype=torch.float64)  # r_max ~ 2 mm
    m = SplatTranslucency(dense, method="window")  # many small splats on few pixels: the scatter form
    plain, bright = m(src, flux, dst, mask, vp), m(src, flux, dst, mask, vp, src_irradiance_scale=mi)
    x = dst[:, :1].expand_as(plain)
    reach = float(m.r_max)
    inside, outside = mask & (x > reach) & (x < 12 - reach), mask & (x < -reach) & (x > -12 + reach)
    assert int(inside.sum()) > 20 and int(outside.sum()) > 20
    torch.testing.assert_close(bright[inside.expand_as(plain)], 2 * plain[inside.expand_as(plain)], rtol=1e-10,
                               atol=0.0)
    torch.testing.assert_close(bright[outside.expand_as(plain)], plain[outside.expand_as(plain)], rtol=1e-12,
                               atol=0.0)


def test_gradcheck_wrt_modifiers():
    g = torch.Generator().manual_seed(3)
    cam = Camera(eye=(0.0, 0.0, 30.0), target=(0.0, 0.0, 0.0), width=5, height=5, fov_deg=15.0)
    dst, mask, vp = _plane_view(cam=cam, size=20.0)
    src = torch.cat([torch.rand(1, 5, 2, generator=g, dtype=torch.float64) * 4 - 2,
                     torch.zeros(1, 5, 1, dtype=torch.float64)], -1)
    flux = torch.rand(1, 5, 3, generator=g, dtype=torch.float64)
    m = SplatTranslucency([_mat("skin1"), _mat("marble")])
    ids = torch.tensor([[0, 1, 0, 1, 1]])
    md = (0.6 + 0.6 * torch.rand(1, 5, 1, generator=g, dtype=torch.float64)).requires_grad_()
    mi = torch.rand(1, 5, 3, generator=g, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda a, b: m(src, flux, dst, mask, vp, src_material=ids, src_distance_scale=a, src_irradiance_scale=b),
        (md, mi))


def test_grazing_light_view_area_is_bounded_and_flux_exact():
    """A plane lit at 86 degrees: dA = footprint / cos is clamped by min_cos, E dA stays exact and small."""
    theta = math.radians(86.0)
    light = DirectionalLight((math.sin(theta), 0.0, -math.cos(theta)), 1.0)
    lv = light_view(plane(10.0, 10.0, 4, dtype=torch.float64), light, 256, 1.3, fresnel="none", min_cos=0.2)
    area, flux = lv.area[lv.mask.expand_as(lv.area)], lv.flux[0, 0][lv.mask[0, 0]]
    assert bool(torch.isfinite(area).all()) and bool(torch.isfinite(flux).all())
    assert area.numel() > 100
    footprint = (2 * lv.camera.ortho_half_height / 256) ** 2  # the orthographic light view's pixel
    torch.testing.assert_close(area, torch.full_like(area, footprint / 0.2), rtol=1e-3, atol=0.0)  # clamped
    # total flux through the plane = E_perp cos(theta) * 100 mm^2, whatever the clamping of dA
    assert float(flux.sum()) == pytest.approx(math.cos(theta) * 100.0, rel=0.05)


def test_unlit_object_renders_zeros_not_nan():
    mesh = sphere(10.0, 3)
    cam = Camera(eye=(0.0, -40.0, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), width=16, height=16)
    away = SpotLight(position=(0.0, 0.0, 60.0), direction=(0.0, 0.0, 1.0), intensity=100.0, cone_deg=10.0)
    res = render_splat(mesh, Material.from_json("skin1"), [away], cam)
    assert bool(res.mask.any()) and bool(torch.isfinite(res.radiance).all())
    assert bool((res.radiance == 0).all())


class _Export(torch.nn.Module):
    """The module with every optional input wired, for export."""

    def __init__(self, module):
        super().__init__()
        self.m = module

    def forward(self, src, flux, dst, mask, vp, mat, obj, dst_obj, md, mi):
        return self.m(src, flux, dst, mask, vp, src_material=mat, src_object=obj, dst_object=dst_obj,
                      src_distance_scale=md, src_irradiance_scale=mi)


def _export_inputs(s, h, w, seed):
    g = torch.Generator().manual_seed(seed)
    cam = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0), fov_deg=30.0, width=w, height=h)
    dst, mask, vp = _plane_view(torch.float32, cam=cam)
    src = torch.cat([torch.rand(1, s, 2, generator=g) * 20 - 10, torch.zeros(1, s, 1)], -1)
    obj = (src[..., 0] > 0).to(torch.int64)
    return (src, torch.rand(1, s, 3, generator=g), dst, mask, vp, obj, obj, (dst[:, :1] > 0).to(torch.int64),
            0.8 + 0.4 * torch.rand(1, s, 1, generator=g), torch.rand(1, s, 3, generator=g) * 2)


@pytest.mark.filterwarnings("ignore:`isinstance\\(treespec, LeafSpec\\)` is deprecated:FutureWarning")
@pytest.mark.filterwarnings("ignore:# The axis name:UserWarning")
def test_module_exports_to_onnx_with_parity(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from torch.export import Dim

    from torchsss.export import compare_with_eager, export_onnx

    module = SplatTranslucency([DipoleMaterial.from_preset("skin1"), DipoleMaterial.from_preset("marble")],
                               window=23).eval()
    sd, hd, wd = Dim("S"), Dim("H"), Dim("W")
    per_src, per_pix = {1: sd}, {2: hd, 3: wd}
    dyn = (per_src, per_src, per_pix, per_pix, None, per_src, per_src, per_pix, per_src, per_src)
    path = export_onnx(_Export(module), _export_inputs(30, 16, 18, 0), tmp_path / "splat_module.onnx",
                       dynamic_shapes=dyn)
    test = _export_inputs(45, 13, 21, 1)  # another splat count and image size than exported
    reach = float(module.r_max.amax()) / 0.8
    assert splat_window_size(test[0], test[4], reach, 13, 21) <= 23  # the window holds every footprint
    res = compare_with_eager(_Export(module), path, test)
    assert res["shapes"] == [(1, 3, 13, 21)] and res["zero_pattern_match"], res
    assert res["max_rel_diff"] <= 1e-5, res
    # and the eager window path agrees with the exact tile path on these inputs
    exact = SplatTranslucency(list(module.materials), method="tile")
    with torch.no_grad():
        np.testing.assert_allclose(_Export(module)(*test).numpy(), _Export(exact)(*test).numpy(), rtol=1e-4,
                                   atol=1e-7)


def test_bad_inputs():
    with pytest.raises(TypeError, match="material"):
        SplatTranslucency([])
    with pytest.raises(TypeError, match=r"material\[1\]"):
        SplatTranslucency([_mat("skin1"), "marble"])
    with pytest.raises(ValueError, match="channels"):
        SplatTranslucency([_mat("skin1"), DipoleMaterial(0.1, 1.0, 1.3, dtype=torch.float64)])
    m = SplatTranslucency([_mat("skin1"), _mat("marble")])
    dst, mask, vp = _plane_view()
    src, flux = torch.zeros(1, 2, 3, dtype=torch.float64), torch.ones(1, 2, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="src_material"):
        m(src, flux, dst, mask, vp)
    with pytest.raises(ValueError, match="src_material"):
        m(src, flux, dst, mask, vp, src_material=torch.tensor([[0, 2]]))
