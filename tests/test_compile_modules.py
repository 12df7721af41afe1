"""torch.compile of every per-frame module with its build-time defaults: same outputs as eager, no recompilation.

Each module is built at a small size with its defaults, compiled, and called twice with inputs of the same shapes
but different values (light positions, irradiance, uniforms, distances, material values). Both calls must match
eager mode, and the second must reuse the first call's graph: per-frame data never becomes a guard.

Backends: compiling with inductor costs seconds per graph on a shared 2-core machine (gcc builds a C++ kernel per
fused group; about 15 s for the first graph of a process with a cold cache), so inductor runs the two smallest
graphs (IrradianceAtlas, BurleyMaterial), ``aot_eager`` (dynamo + AOT autograd's functionalised, decomposed
graph, run eagerly) the others, and plain ``eager`` (dynamo's graph) the 2,700-op CausticMap. Every backend is
wrapped in ``CompileCounterWithBackend`` to count the compiled frames.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch._dynamo
from torch._dynamo.testing import CompileCounterWithBackend

from torchsss.geometry import build_atlas, sphere
from torchsss.geometry.lensch import build_throughput, local_kernel_geometry, vertex_weights
from torchsss.modules import (
    BurleyMaterial,
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
)
from torchsss.physics.materials import preset

F32, F64 = torch.float32, torch.float64
RES = 32  # atlas resolution

# inductor's own imports warn about a deprecated torch.jit API; not ours to fix.
pytestmark = [pytest.mark.filterwarnings("ignore:`torch.jit.script_method` is deprecated:DeprecationWarning"),
              pytest.mark.usefixtures("one_thread")]




@pytest.fixture(autouse=True)
def _fresh_dynamo():
    """Every test starts and ends with an empty dynamo cache (no graph is reused across tests)."""
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


@pytest.fixture(scope="module")
def tiny():
    """A 42-vertex sphere (radius 6 mm), its 32 x 32 atlas and a skin1 material (float32)."""
    mesh = sphere(6.0, 1)
    atlas = build_atlas(mesh, RES, kernel_size=3)
    return mesh, atlas, DipoleMaterial.from_preset("skin1")


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _flat(out: object) -> list[torch.Tensor]:
    """Tensors of a module output (tensor, tuple or dict), in a fixed order."""
    if isinstance(out, torch.Tensor):
        return [out]
    if isinstance(out, dict):
        return [t for k in sorted(out) for t in _flat(out[k])]
    return [t for o in out for t in _flat(o)]


def check_compiled(module, first, second, *, backend="aot_eager", rtol=1e-5, atol=1e-6, between=None):
    """``torch.compile(module)`` matches ``module`` on two input tuples of the same shapes, compiling once.

    ``atol`` is relative to the largest magnitude of each eager output. ``between`` (optional) runs between the
    two calls, e.g. to change a material's parameters in place.
    """
    module.eval()
    counter = CompileCounterWithBackend(backend)
    compiled = torch.compile(module, backend=counter)
    frames = None
    for args in (first, second):
        if frames is not None and between is not None:
            between()
        with torch.no_grad():
            want = _flat(module(*args))
            with torch._dynamo.config.patch(error_on_recompile=frames is not None):
                got = _flat(compiled(*args))
        assert len(got) == len(want)
        for g, w in zip(got, want):
            assert g.shape == w.shape and g.dtype == w.dtype
            if w.is_floating_point():
                scale = float(w.abs().max()) if w.numel() else 0.0
                torch.testing.assert_close(g, w, rtol=rtol, atol=atol * scale)
            else:
                assert torch.equal(g, w)
        if frames is None:
            frames = counter.frame_count
            assert frames >= 1
    assert counter.frame_count == frames, "the second call recompiled"
    return want


def _irradiance(atlas, seed: int, b: int = 1) -> torch.Tensor:
    return torch.rand(b, 3, RES, RES, generator=_gen(seed)) * atlas.valid_mask


def _receivers(atlas) -> torch.Tensor:
    pts = atlas.position.flatten(2).transpose(1, 2)[:, atlas.chart_mask.flatten()]
    return pts[:, ::20] + 0.05  # (1, 7, 3), off the texel centres


# -- Lensch -----------------------------------------------------------------------------------------------------------
def test_irradiance_atlas(tiny):
    _, atlas, _ = tiny
    first = (torch.tensor([[20.0, 10.0, 30.0, 1.0]]), torch.tensor([[1e3, 2e3, 3e3]]))
    second = (torch.tensor([[-15.0, 25.0, 5.0, 1.0]]), torch.tensor([[3e3, 1e3, 2e3]]))
    out = check_compiled(IrradianceAtlas.from_atlas(atlas), first, second, backend="inductor")
    assert out[0].amax() > 0


def test_local_response(tiny):
    _, atlas, mat = tiny
    check_compiled(LocalResponse(local_kernel_geometry(atlas, 3), mat), (_irradiance(atlas, 1),),
                   (_irradiance(atlas, 2),))


def test_global_response(tiny):
    mesh, atlas, mat = tiny
    module = GlobalResponse(vertex_weights(mesh, atlas), build_throughput(mesh, mat), mat, atlas.valid_mask)
    check_compiled(module, (_irradiance(atlas, 3),), (_irradiance(atlas, 4),))


def test_lensch_translucency(tiny):
    mesh, atlas, mat = tiny
    module = LenschTranslucency(
        LocalResponse(local_kernel_geometry(atlas, 3), mat),
        GlobalResponse(vertex_weights(mesh, atlas), build_throughput(mesh, mat), mat, atlas.valid_mask),
    )
    out = check_compiled(module, (_irradiance(atlas, 5),), (_irradiance(atlas, 6),))
    assert out[0].amax() > 0


# -- Chang ------------------------------------------------------------------------------------------------------------
def test_importance_sampled_translucency(tiny):
    _, atlas, mat = tiny
    module = ImportanceSampledTranslucency.from_atlas(atlas, mat)  # levels from the atlas size
    rec = _receivers(atlas)
    first = (_irradiance(atlas, 7), torch.rand(1, 64, 2, generator=_gen(8)), rec)
    second = (_irradiance(atlas, 9), torch.rand(1, 64, 2, generator=_gen(10)), rec + 0.1)
    out = check_compiled(module, first, second)
    assert out[0].amax() > 0


def test_hybrid_translucency(tiny):
    _, atlas, mat = tiny
    module = HybridTranslucency.from_atlas(atlas, mat)
    rec = _receivers(atlas)
    uv = torch.rand(1, rec.shape[1], 2, generator=_gen(11))
    first = (_irradiance(atlas, 12), torch.rand(1, 64, 2, generator=_gen(13)), rec, uv)
    second = (_irradiance(atlas, 14), torch.rand(1, 64, 2, generator=_gen(15)), rec + 0.1, uv.flip(-1))
    check_compiled(module, first, second)


def test_icdf_sampler():
    first = (torch.rand(2, 1, 20, 32, generator=_gen(16)) ** 3, torch.rand(2, 256, 2, generator=_gen(17)))
    second = (torch.rand(2, 1, 20, 32, generator=_gen(18)), torch.rand(2, 256, 2, generator=_gen(19)))
    _, p = check_compiled(IcdfSampler(size=(20, 32)), first, second, rtol=0, atol=0)  # the same ops: exact
    assert (p > 0).all()


# -- caustics ---------------------------------------------------------------------------------------------------------
HALF = 15.0  # half width of the orthographic light frustum (mm)


def _ortho(dtype=F64) -> torch.Tensor:
    """(1, 4, 4) light looking down -z: NDC x = x / HALF, y = y / HALF."""
    m = torch.zeros(1, 4, 4, dtype=dtype)
    m[0, 0, 0] = m[0, 1, 1] = 1.0 / HALF
    m[0, 2, 2] = -0.01
    m[0, 3, 3] = 1.0
    return m


def _centres(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World x, y (n, n) of the light's texel centres, row 0 at the top."""
    t = -HALF + (torch.arange(n, dtype=F64) + 0.5) * 2 * HALF / n
    y, x = torch.meshgrid(-t, t, indexing="ij")
    return x, y


def _floor(n: int) -> torch.Tensor:
    x, y = _centres(n)
    return torch.stack([x, y, torch.zeros_like(x)])[None]


def _glass_sphere(g: int, radius: float = 10.0, z: float = 16.0):
    """Front / back positions, normals and masks (1, c, g, g) of a sphere seen from above."""
    x, y = _centres(g)
    r2 = x * x + y * y
    mask = r2 < radius * radius
    h = torch.sqrt((radius * radius - r2).clamp_min(0.0))
    hole = torch.where(mask, 1.0, float("nan")).to(F64)
    front, back = torch.stack([x, y, z + h]) * hole, torch.stack([x, y, z - h]) * hole
    n_front, n_back = torch.stack([x, y, h]) / radius, torch.stack([x, y, -h]) / radius
    m = mask[None, None]
    return front[None], n_front[None], m, back[None], n_back[None], m.clone()


def test_caustic_map():
    tilt = math.radians(3.0)
    first = (*_glass_sphere(8), _floor(12), torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=F64),
             torch.tensor([[1.0, 2.0]], dtype=F64), _ortho())
    second = (*_glass_sphere(8), _floor(12), torch.tensor([[math.sin(tilt), 0.0, math.cos(tilt), 0.0]], dtype=F64),
              torch.tensor([[3.0, 0.5]], dtype=F64), _ortho())
    out = check_compiled(CausticMap([1.45, 1.55], 0.02), first, second, backend="eager", rtol=1e-10, atol=1e-12)
    assert out[0].sum() > 0


def test_newton_raphson_search():
    def rays(seed):
        g = _gen(seed)
        o = (torch.rand(1, 48, 3, generator=g, dtype=F64) - 0.5) * 10.0
        o[..., 2] = 8.0
        r = (torch.rand(1, 48, 3, generator=g, dtype=F64) - 0.5) * 0.4
        r[..., 2] = -1.0
        return o, r, _floor(12), _ortho()

    d, valid = check_compiled(NewtonRaphsonSearch(), rays(20), rays(21), rtol=1e-10, atol=1e-12)
    assert valid.all() and (d > 0).all()


# -- materials and profiles -------------------------------------------------------------------------------------------
def _distances(seed: int) -> tuple[torch.Tensor]:
    return (torch.rand(64, 1, generator=_gen(seed)) * 10.0,)


def test_dipole_material():
    mat = DipoleMaterial.from_preset("skin1")

    def edit():  # a training step / per-frame material edit: parameters change in place, no recompilation
        with torch.no_grad():
            mat.raw_sigma_a.mul_(1.5)

    check_compiled(mat, _distances(22), _distances(23), between=edit)


def test_burley_material():
    check_compiled(BurleyMaterial.from_preset("marble"), _distances(24), _distances(25), backend="inductor")


def test_dipole_profile():
    a, b = preset("skin1").tensors(F32), preset("marble").tensors(F32)
    check_compiled(DipoleProfile(), (*_distances(26), *a), (*_distances(27), *b))


# -- splatting --------------------------------------------------------------------------------------------------------
def _splat_inputs(seed: int):
    g = _gen(seed)
    src = (torch.rand(1, 20, 3, generator=g) - 0.5) * 4.0
    src[..., 2] = 0.0
    flux = torch.rand(1, 20, 3, generator=g)
    x, y = _centres(8)
    dst = (torch.stack([x, y, torch.zeros_like(x)]).float() * 0.2)[None]  # a plane, 0.75 mm pixels
    mask = torch.ones(1, 1, 8, 8, dtype=torch.bool)
    view_proj = torch.diag(torch.tensor([1.0 / 3.0, 1.0 / 3.0, -0.01, 1.0]))[None]
    return src, flux, dst, mask, view_proj


def test_splat_translucency():
    module = SplatTranslucency(DipoleMaterial.from_preset("skin1"))  # no window=: the build-time default
    out = check_compiled(module, _splat_inputs(28), _splat_inputs(29))
    assert out[0].amax() > 0
