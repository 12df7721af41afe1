"""The export registry: every per-frame module of torchsss, with inputs at two sizes and a tolerance.

:data:`EXPORTABLE` maps a name to a function that builds an :class:`ExportCase`: the module (or an adapter of
:mod:`torchsss.export.adapters` / :mod:`torchsss.export.materials`), example inputs at the export size, test
inputs at other sizes (batch, sample count, receiver count, image or atlas size, as the module allows), the
dynamic dimensions and the tolerance of onnxruntime against eager PyTorch. ``export/onnx_export.py`` and
``tests/test_export_onnx.py`` iterate over this one list.

Examples:
    >>> len(EXPORTABLE) >= 12
    True
    >>> case = export_case("profile")
    >>> tuple(case.example_args[0].shape), tuple(case.test_args[0].shape)
    ((4, 48, 1), (3, 101, 1))
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.export import Dim

from torchsss.export.adapters import SplatExport
from torchsss.export.materials import with_material_inputs
from torchsss.geometry import (
    build_atlas,
    build_dense_throughput,
    build_throughput,
    hat_quadrature,
    local_kernel_geometry,
    sphere,
    vertex_weights,
)
from torchsss.geometry.camera import Camera
from torchsss.geometry.gbuffer import camera_gbuffer
from torchsss.geometry.neighbours import ball_pairs
from torchsss.geometry.procedural import plane
from torchsss.geometry.sampling import surface_samples
from torchsss.modules import (
    CausticMap,
    DipoleMaterial,
    DipoleProfile,
    GlobalResponse,
    HybridTranslucency,
    IcdfSampler,
    ImportanceSampledTranslucency,
    IrradianceAtlas,
    LenschTranslucency,
    LocalResponse,
    NewtonRaphsonSearch,
    SplatTranslucency,
    SurfaceLocal,
)
from torchsss.modules.chang import ChangLocalProfile
from torchsss.physics.materials import preset

__all__ = ["EXPORTABLE", "MATERIAL_PRESETS", "ExportCase", "export_case", "material_inputs"]

#: The presets of the material-input parity checks (one exported file, one onnxruntime session).
MATERIAL_PRESETS = ("skin1", "marble", "ketchup")


@dataclass(frozen=True)
class ExportCase:
    """A module with inputs at two sizes, ready for :func:`~torchsss.export.export_onnx` and comparison.

    Attributes:
        module: the module to export.
        example_args: inputs at the export size.
        test_args: inputs at a different size (other dynamic dims), to check that no size was frozen.
        dynamic_shapes: the ``dynamic_shapes`` spec (uses :class:`torch.export.Dim`); every dimension named here is
            checked to be symbolic in the written file.
        description: one line saying what the graph computes, with shapes and units.
        rtol: the largest elementwise relative difference onnxruntime vs eager that the entry accepts.
        scale: for outputs that sum terms of both signs, ``scale(*test_args)`` gives the magnitude of the summands
            per entry; the relative difference is taken against it where the sum cancels.
        atol: when set, the entry passes on ``max_abs_diff <= atol`` instead of the relative test (outputs whose
            float32 rounding is absolute, e.g. distances found by an iteration).
        input_names: optional graph input names (default: ``forward``'s parameter names).
        slow: the export is too long for the default test run (the tests put the entry behind ``-m slow``); no
            entry sets it today (the longest, ``caustic_map``, exports in ~27 s on a quiet 2-core machine).
        material_inputs: the last inputs are ``sigma_a, sigma_s_prime, eta`` (and for the splat ``r_max``).
    """

    module: nn.Module
    example_args: tuple[Tensor, ...]
    test_args: tuple[Tensor, ...]
    dynamic_shapes: dict[str, Any] | tuple[Any, ...] | None
    description: str
    rtol: float = 1e-5
    #: optional: test inputs -> per-entry magnitude of the summands of each output (see :func:`compare_with_eager`)
    scale: Callable[..., Tensor] | None = None
    atol: float | None = None
    input_names: tuple[str, ...] | None = None
    slow: bool = False
    material_inputs: bool = False


def _distances(shape: tuple[int, ...], r_max_mm: float) -> Tensor:
    """Evenly spaced distances 0..r_max_mm (mm, float32, both ends included) reshaped to ``shape``."""
    return torch.linspace(0.0, r_max_mm, math.prod(shape), dtype=torch.float32).reshape(shape)


def material_inputs(name: str, with_r_max: bool = False, eps: float = 0.01) -> tuple[Tensor, ...]:
    """``(sigma_a (3,), sigma_s_prime (3,), eta (1,))`` float32 of a preset, plus ``r_max (1,)`` mm if asked."""
    sa, ss, eta = preset(name).tensors(torch.float32)
    out = (sa, ss, eta.reshape(1))
    if with_r_max:
        out += (DipoleMaterial(sa, ss, eta).r_max(eps).amax().reshape(1),)
    return out


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# -- profile and material ---------------------------------------------------------------------------------------
def _profile_case() -> ExportCase:
    material = material_inputs("marble")
    n, m = Dim("N"), Dim("M")
    return ExportCase(
        module=DipoleProfile(),
        example_args=(_distances((4, 48, 1), 30.0), *material),
        test_args=(_distances((3, 101, 1), 30.0), *material_inputs("skin1")),
        dynamic_shapes=({0: n, 1: m}, None, None, None),
        description="DipoleProfile: r (N, M, 1) mm, sigma_a/sigma_s_prime (3,) mm^-1, eta (1,) -> R_d (N, M, 3) "
                    "mm^-2; example material: marble, test: skin1",
        material_inputs=True,
    )


def _material_case() -> ExportCase:
    return ExportCase(
        module=DipoleMaterial.from_preset("skin1"),
        example_args=(_distances((64, 1), 30.0),),
        test_args=(_distances((257, 1), 30.0),),
        dynamic_shapes=({0: Dim("N")},),
        description="DipoleMaterial('skin1'), parameters folded into the graph: r (N, 1) mm -> R_d (N, 3) mm^-2",
    )


# -- Lensch -------------------------------------------------------------------------------------------------------
def _lensch_parts(res: int = 64):
    mesh = sphere(6.0, 2)
    atlas = build_atlas(mesh, res, kernel_size=5)
    mat = DipoleMaterial.from_preset("skin1")
    local = LocalResponse(local_kernel_geometry(atlas, 5), mat)
    # as build_lensch unblended: the throughput integrated over the hats (the detail split in LenschTranslucency);
    # "scatter": the exported graph's summation order, so eager and ORT compare tightly
    tp = build_throughput(mesh, mat)
    hat = hat_quadrature(mesh, tp, scale_mm=float(mat.spacing(0.01).min()))
    glob = GlobalResponse(vertex_weights(mesh, atlas), tp, mat, atlas.valid_mask, method="scatter", hat=hat)
    return mesh, atlas, mat, local, glob


def _atlas_irradiance(atlas, b: int, seed: int) -> Tensor:
    return torch.rand(b, 3, *atlas.shape, generator=_gen(seed)) * atlas.valid_mask


# float32 sums of 25 kernel taps and ~160 vertex terms, in a different order than eager's in-place accumulation:
# measured 1.3e-5 elementwise (2.4e-7 absolute at values up to ~0.1). The dual-basis vertex irradiance of random
# texels is signed, so local + global can cancel to ~1e-6 at values of ~0.04: the difference is taken relative to
# |local| + |global| (one float32 rounding of a summand is 0.4% of such a sum).
_LENSCH_RTOL = 5e-5


def _lensch_case() -> ExportCase:
    _, atlas, _, local, glob = _lensch_parts()
    module = LenschTranslucency(local, glob, detail=True)
    return ExportCase(
        module=module,
        example_args=(_atlas_irradiance(atlas, 1, 0),),
        test_args=(_atlas_irradiance(atlas, 3, 1),),
        dynamic_shapes=({0: Dim("B")},),
        description="LenschTranslucency per frame (skin1, 10k-texel sphere atlas, 5x5 kernels, 162 vertices, hat "
                    "quadrature and detail split): "
                    "irradiance atlas (B, 3, 64, 64) -> radiosity atlas (B, 3, 64, 64)",
        rtol=_LENSCH_RTOL,
        scale=lambda e: module.local(e).abs() + module.global_response(e).abs(),
    )


def _lensch_materials_case() -> ExportCase:
    _, atlas, _, local, glob = _lensch_parts()
    module = with_material_inputs(LenschTranslucency(local, glob, detail=True))
    inner = module.module

    def scale(e, *mat):
        module.material.bind(*mat)
        return inner.local(e).abs() + inner.global_response(e).abs()

    return ExportCase(
        module=module,
        example_args=(_atlas_irradiance(atlas, 1, 0), *material_inputs("skin1")),
        test_args=(_atlas_irradiance(atlas, 2, 1), *material_inputs("marble")),
        dynamic_shapes=({0: Dim("B")}, None, None, None),
        description="LenschTranslucency with the material as inputs (throughput pattern of skin1): irradiance atlas "
                    "(B, 3, 64, 64), sigma_a/sigma_s_prime (3,) mm^-1, eta (1,) -> radiosity atlas (B, 3, 64, 64)",
        rtol=_LENSCH_RTOL,
        scale=scale,
        input_names=("irradiance", "sigma_a", "sigma_s_prime", "eta"),
        material_inputs=True,
    )


def _irradiance_atlas_case() -> ExportCase:
    _, atlas, mat, _, _ = _lensch_parts()
    module = IrradianceAtlas.from_atlas(atlas, mat)

    def args(b, seed):
        g = _gen(seed)
        light = torch.cat([torch.randn(b, 3, generator=g) * 30.0, torch.ones(b, 1)], 1)
        light[-1] = torch.tensor([0.6, 0.0, 0.8, 0.0])  # a directional light
        return light, torch.rand(b, 3, generator=g) * 1e3, torch.rand(b, 1, *atlas.shape, generator=g)

    return ExportCase(
        module=module,
        example_args=args(2, 0),
        test_args=args(3, 1),
        dynamic_shapes=({0: Dim("B")}, {0: Dim("B")}, {0: Dim("B")}),
        description="IrradianceAtlas (skin1 Fresnel, 64x64 sphere atlas): light (B, 4) mm, intensity (B, 3), "
                    "visibility (B, 1, 64, 64) -> irradiance atlas (B, 3, 64, 64)",
        # grazing texels: the Fresnel transmittance 1 - F_r cancels (values ~1e-5 of the median); on a machine
        # whose onnxruntime takes other vector paths, 3 of 36,864 texels differed by 1.7e-5 relative (the rest
        # <= 1.3e-6; 1e-5 elsewhere)
        rtol=5e-5,
    )


def _local_response_case() -> ExportCase:
    _, atlas, _, local, _ = _lensch_parts()
    return ExportCase(
        module=local,
        example_args=(_atlas_irradiance(atlas, 1, 0),),
        test_args=(_atlas_irradiance(atlas, 3, 1),),
        dynamic_shapes=({0: Dim("B")},),
        description="LocalResponse (sv_conv2d, 5x5 per-texel kernels, skin1): irradiance atlas (B, 3, 64, 64) -> "
                    "local radiosity (B, 3, 64, 64)",
    )


def _global_case(glob: GlobalResponse, atlas, kind: str) -> ExportCase:
    """A :class:`GlobalResponse` entry: batch 1 at export, 3 at test."""
    e1, e2 = _atlas_irradiance(atlas, 1, 0), _atlas_irradiance(atlas, 3, 1)
    # the dual-basis vertex irradiance is signed and the reconstruction cancels: relative to each map's largest
    return ExportCase(
        module=glob,
        example_args=(e1,),
        test_args=(e2,),
        dynamic_shapes=({0: Dim("B")},),
        description=f"GlobalResponse ({kind}, 162 vertices, skin1): irradiance atlas (B, 3, 64, 64) -> global "
                    "radiosity (B, 3, 64, 64)",
        rtol=_LENSCH_RTOL,
        scale=lambda e: glob(e).abs().amax((-2, -1), keepdim=True).expand_as(e),
    )


def _global_response_case() -> ExportCase:
    _, atlas, _, _, glob = _lensch_parts()
    return _global_case(glob, atlas, "sparse vertex throughput as gather + scatter_add")


def _global_response_dense_case() -> ExportCase:
    mesh, atlas, mat, _, _ = _lensch_parts()
    # as build_lensch blends: a zero diagonal, the layout its "auto" picks for a small mesh (every pair kept)
    tp = build_dense_throughput(mesh, mat, zero_diagonal=True)
    glob = GlobalResponse(vertex_weights(mesh, atlas, discrete=False), tp, mat, atlas.valid_mask)
    return _global_case(glob, atlas, "dense throughput, a batched matrix product per channel")


# -- splat --------------------------------------------------------------------------------------------------------
#: Window of the registered splat graphs: holds every skin1 footprint (r_max 13.7 mm) up to about 24 x 24 pixels
#: in the registry's camera (60 mm away, 30 degrees); larger images report truncated splats.
SPLAT_WINDOW = 25


def _splat_inputs(s: int, h: int, w: int, seed: int) -> tuple[Tensor, ...]:
    g = _gen(seed)
    cam = Camera(eye=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0), fov_deg=30.0, width=w, height=h)
    gb = camera_gbuffer(plane(40.0, 40.0, 4), cam)
    src = torch.cat([torch.rand(1, s, 2, generator=g) * 20 - 10, torch.zeros(1, s, 1)], -1)
    return src, torch.rand(1, s, 3, generator=g), gb.position, gb.mask, cam.view_proj(dtype=torch.float32)


def _splat_dyn(material: bool) -> tuple:
    s, h, w = Dim("S"), Dim("H"), Dim("W")
    per_src, per_pix = {1: s}, {2: h, 3: w}
    return (per_src, per_src, per_pix, per_pix, None) + ((None,) * 4 if material else ())


def _splat_case() -> ExportCase:
    module = SplatExport(SplatTranslucency(DipoleMaterial.from_preset("skin1"), window=SPLAT_WINDOW))
    return ExportCase(
        module=module,
        example_args=_splat_inputs(30, 16, 18, 0),
        test_args=_splat_inputs(45, 21, 23, 1),
        dynamic_shapes=_splat_dyn(False),
        description=f"SplatTranslucency (skin1, window {SPLAT_WINDOW}): src_pos (1, S, 3) mm, src_flux (1, S, 3), "
                    "dst_pos (1, 3, H, W) mm, dst_mask (1, 1, H, W), view_proj (4, 4) -> radiosity (1, 3, H, W), "
                    "truncated splats (1,)",
        input_names=("src_pos", "src_flux", "dst_pos", "dst_mask", "view_proj"),
    )


def _splat_materials_case() -> ExportCase:
    module = SplatExport(SplatTranslucency(DipoleMaterial.from_preset("skin1"), window=SPLAT_WINDOW), True)
    return ExportCase(
        module=module,
        example_args=(*_splat_inputs(30, 16, 18, 0), *material_inputs("skin1", True)),
        test_args=(*_splat_inputs(45, 21, 23, 1), *material_inputs("ketchup", True)),
        dynamic_shapes=_splat_dyn(True),
        description="SplatTranslucency with the material as inputs: as 'splat' plus sigma_a/sigma_s_prime (3,) "
                    "mm^-1, eta (1,), r_max (1,) mm -> radiosity (1, 3, H, W), truncated splats (1,)",
        input_names=("src_pos", "src_flux", "dst_pos", "dst_mask", "view_proj", "sigma_a", "sigma_s_prime", "eta",
                     "r_max"),
        material_inputs=True,
    )


# -- Chang ----------------------------------------------------------------------------------------------------------
def _chang_atlas():
    return build_atlas(sphere(6.0, 1), 32, kernel_size=3)


def _chang_args(atlas, b: int, n: int, m: int, seed: int, uv: bool) -> tuple[Tensor, ...]:
    g = _gen(seed)
    pts = atlas.position.flatten(2).transpose(1, 2)[:, atlas.chart_mask.flatten()]
    pick = torch.randint(0, pts.shape[1], (m,), generator=g)
    rec = pts[:, pick].expand(b, -1, -1) + 0.01 * torch.randn(b, m, 3, generator=g)
    out = (torch.rand(b, 3, 32, 32, generator=g) * atlas.valid_mask, torch.rand(b, n, 2, generator=g), rec)
    return out + ((torch.rand(b, m, 2, generator=g),) if uv else ())


def _chang_dyn(uv: bool, material: bool = False) -> tuple:
    b, n, m = Dim("B", max=64), Dim("N"), Dim("M")
    return ({0: b}, {0: b, 1: n}, {0: b, 1: m}) + (({0: b, 1: m},) if uv else ()) + ((None,) * 3 if material else ())


def _icdf_case() -> ExportCase:
    atlas = _chang_atlas()
    return ExportCase(
        module=ImportanceSampledTranslucency.from_atlas(atlas, DipoleMaterial.from_preset("skin1")),
        example_args=_chang_args(atlas, 2, 64, 40, 0, False),
        test_args=_chang_args(atlas, 3, 300, 57, 1, False),
        dynamic_shapes=_chang_dyn(False),
        description="ImportanceSampledTranslucency (skin1, 32x32 sphere atlas): irradiance (B, 3, 32, 32), "
                    "u (B, N, 2), receivers (B, M, 3) mm -> radiosity (B, M, 3)",
    )


def _icdf_materials_case() -> ExportCase:
    atlas = _chang_atlas()
    module = with_material_inputs(ImportanceSampledTranslucency.from_atlas(atlas, DipoleMaterial.from_preset("skin1")))
    return ExportCase(
        module=module,
        example_args=(*_chang_args(atlas, 2, 64, 40, 0, False), *material_inputs("skin1")),
        test_args=(*_chang_args(atlas, 3, 300, 57, 1, False), *material_inputs("marble")),
        dynamic_shapes=_chang_dyn(False, True),
        description="ImportanceSampledTranslucency with the material as inputs: as 'icdf' plus sigma_a/"
                    "sigma_s_prime (3,) mm^-1, eta (1,)",
        input_names=("irradiance", "u", "receivers", "sigma_a", "sigma_s_prime", "eta"),
        material_inputs=True,
    )


def _hybrid_case() -> ExportCase:
    atlas = _chang_atlas()
    return ExportCase(
        module=HybridTranslucency.from_atlas(atlas, DipoleMaterial.from_preset("skin1"), grid=64),
        example_args=_chang_args(atlas, 2, 64, 40, 0, True),
        test_args=_chang_args(atlas, 3, 300, 57, 1, True),
        dynamic_shapes=_chang_dyn(True),
        description="HybridTranslucency (skin1, 32x32 sphere atlas, 8x16 local pattern): irradiance (B, 3, 32, 32), "
                    "u (B, N, 2), receivers (B, M, 3) mm, receivers_uv (B, M, 2) -> radiosity (B, M, 3)",
    )


def _surface_local_case() -> ExportCase:
    atlas = _chang_atlas()
    mat = DipoleMaterial.from_preset("skin1")
    smp = surface_samples(sphere(6.0, 1), 1.0)  # the atlas's mesh
    uv = (smp.bary.unsqueeze(-1) * atlas.face_uvs[smp.face_id]).sum(1)
    module = SurfaceLocal(uv, smp.area, atlas.valid_mask, mat, ChangLocalProfile(1.2, 1.5, 3.0))

    def args(b, m, seed):
        g = _gen(seed)
        rec = smp.position[torch.randperm(smp.position.shape[0], generator=g)[:m]] * 1.01
        rows, cols, dist = ball_pairs(rec, smp.position, 3.0)
        return torch.rand(b, 3, *atlas.shape, generator=g) * atlas.valid_mask, rows, cols, dist, rec

    p, m = Dim("P"), Dim("M")
    return ExportCase(
        module=module,
        example_args=args(2, 40, 0),
        test_args=args(3, 57, 1),
        dynamic_shapes=({0: Dim("B")}, {0: p}, {0: p}, {0: p}, {0: m}),
        description="SurfaceLocal (the hybrid's local term gathered over surface samples, skin1, 32x32 sphere atlas): "
                    "irradiance (B, 3, 32, 32), pairs rows/cols/distance (P,), receivers (M, 3) mm -> local radiosity "
                    "(B, M, 3)",
    )


def _icdf_sampler_case() -> ExportCase:
    def args(b, n, h, w, seed):
        g = _gen(seed)
        pdf = torch.rand(b, 1, h, w, generator=g) * (torch.rand(b, 1, h, w, generator=g) > 0.3)
        return pdf, torch.rand(b, n, 2, generator=g)

    b, n, h, w = Dim("B", max=64), Dim("N"), Dim("H", max=64), Dim("W", max=64)
    return ExportCase(
        module=IcdfSampler(size=(40, 50)),
        example_args=args(2, 100, 40, 50, 0),
        test_args=args(3, 2049, 17, 63, 1),
        dynamic_shapes=({0: b, 2: h, 3: w}, {0: b, 1: n}),
        description="IcdfSampler (mip-pyramid descent, 6 levels: maps up to 64x64): pdf (B, 1, H, W), u (B, N, 2) "
                    "-> xy (B, N, 2) pixels, p (B, N)",
        rtol=0.0,
    )


# -- caustics -------------------------------------------------------------------------------------------------------
_HALF = 20.0


def _light_view_proj(b: int, half: float) -> Tensor:
    m = torch.zeros(4, 4)
    m[0, 0] = m[1, 1] = 1.0 / half
    m[2, 2] = -0.01
    m[3, 3] = 1.0
    return m.expand(b, 4, 4).clone()


def _tilted_planes(b: int, h: int, w: int, half: float = _HALF) -> Tensor:
    xs = -half + (torch.arange(w, dtype=torch.float64) + 0.5) * 2 * half / w
    ys = half - (torch.arange(h, dtype=torch.float64) + 0.5) * 2 * half / h
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    tex = torch.stack([torch.stack([x, y, 0.2 * x - 0.1 * y - k]) for k in range(b)])
    tex[:, :, h // 4: h // 3, w // 5: w // 3] = float("nan")  # a hole: no receiver there
    return tex.float()


def _newton_case() -> ExportCase:
    def args(b, n, h, w, seed):
        g = _gen(seed)
        o = (torch.rand(b, n, 3, generator=g) - 0.5) * 20.0
        o[..., 2] = 10.0 + 5.0 * torch.rand(b, n, generator=g)
        d = (torch.rand(b, n, 3, generator=g) - 0.5) * 0.7
        d[..., 2] = -1.0
        return o, d, _tilted_planes(b, h, w), _light_view_proj(b, _HALF)

    bd, nd, hd, wd = Dim("B", min=1, max=64), Dim("N"), Dim("H"), Dim("W")
    return ExportCase(
        module=NewtonRaphsonSearch(),
        example_args=args(2, 40, 24, 20, 0),
        test_args=args(3, 57, 37, 29, 1),
        dynamic_shapes=({0: bd, 1: nd}, {0: bd, 1: nd}, {0: bd, 2: hd, 3: wd}, {0: bd}),
        description="NewtonRaphsonSearch (Shah's estimator, 5 iterations): origins/directions (B, N, 3) mm, "
                    "receiver positions texture (B, 3, H, W) mm, view_proj (B, 4, 4) -> distance (B, N) mm, "
                    "valid (B, N)",
        # float32 in both runtimes: bilinear weights round differently (measured 2e-6 mm)
        atol=1e-4,
    )


def _sphere_gbuffers(g: int, radius: float = 10.0, half: float = 15.0) -> list[Tensor]:
    zc = 1.6 * radius
    xs = -half + (torch.arange(g, dtype=torch.float64) + 0.5) * 2 * half / g
    y, x = torch.meshgrid(-xs, xs, indexing="ij")
    r2 = x * x + y * y
    mask = r2 < radius * radius
    h = torch.sqrt((radius * radius - r2).clamp_min(0.0))
    nan = torch.where(mask, 1.0, float("nan"))
    front = torch.stack([x, y, zc + h]) * nan
    back = torch.stack([x, y, zc - h]) * nan
    n_front = torch.stack([x, y, h]) / radius
    n_back = torch.stack([x, y, -h]) / radius
    m = mask[None, None]
    return [front[None].float(), n_front[None].float(), m, back[None].float(), n_back[None].float(), m.clone()]


def _caustic_case() -> ExportCase:
    module = CausticMap([1.45, 1.55], 0.02, back_iterations=3, iterations=1)
    half = 15.0

    def args(g, hr):
        xs = -half + (torch.arange(hr, dtype=torch.float64) + 0.5) * 2 * half / hr
        y, x = torch.meshgrid(-xs, xs, indexing="ij")
        floor = torch.stack([x, y, torch.zeros_like(x)])[None].float()
        return (*_sphere_gbuffers(g, half=half), floor, torch.tensor([[0.0, 0.0, 1.0, 0.0]]), torch.ones(1, 2),
                _light_view_proj(1, half))

    gd, hr = Dim("G", min=4), Dim("Hr", min=4)
    img = {2: gd, 3: gd}
    return ExportCase(
        module=module,
        example_args=args(16, 20),
        test_args=args(24, 28),
        dynamic_shapes=(img, img, img, img, img, img, {2: hr, 3: hr}, None, None, None),
        description="CausticMap (2 wavelengths, double refraction, 3 back + 1 receiver Newton iterations): light-view "
                    "G-buffers (1, 3|1, G, G), receiver texture (1, 3, Hr, Hr) -> caustic map (1, 2, Hr, Hr)",
        rtol=1e-3,
        scale=lambda *a: module(*a).amax().expand(1, 2, a[6].shape[-2], a[6].shape[-1]),
    )


#: Exportable modules by name; each value builds a fresh :class:`ExportCase`.
EXPORTABLE: dict[str, Callable[[], ExportCase]] = {
    "profile": _profile_case,
    "material": _material_case,
    "irradiance_atlas": _irradiance_atlas_case,
    "local_response": _local_response_case,
    "global_response": _global_response_case,
    "global_response_dense": _global_response_dense_case,
    "lensch": _lensch_case,
    "lensch_materials": _lensch_materials_case,
    "splat": _splat_case,
    "splat_materials": _splat_materials_case,
    "icdf_sampler": _icdf_sampler_case,
    "icdf": _icdf_case,
    "icdf_materials": _icdf_materials_case,
    "hybrid": _hybrid_case,
    "hybrid_surface_local": _surface_local_case,
    "newton": _newton_case,
    "caustic_map": _caustic_case,
}


def export_case(name: str) -> ExportCase:
    """Build the :class:`ExportCase` registered under ``name`` in :data:`EXPORTABLE`.

    Raises:
        TypeError: ``name`` is not a str.
        ValueError: unknown name; the message lists the valid ones.
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a str, got {type(name).__name__}")
    if name not in EXPORTABLE:
        raise ValueError(f"name: expected one of {', '.join(sorted(EXPORTABLE))}, got {name!r}")
    return EXPORTABLE[name]()
