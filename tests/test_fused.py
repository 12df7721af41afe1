"""The fused (compiled) kernels of torchsss.ops.fused against their eager references, and when they are used."""

from __future__ import annotations

import pytest
import torch
from torch._dynamo.utils import counters

from torchsss import DipoleMaterial
from torchsss.ops import fused
from torchsss.ops.fused import COLD_WORK, WARM_WORK, dipole_pair_sum, dipole_pair_sum_eager, use_compiled
from torchsss.ops.reference import reference_radiosity
from torchsss.physics import dipole_rd


def _scene(b: int, m: int, n: int, dtype: torch.dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    src = torch.rand(b, n, 3, generator=g, dtype=dtype) * 20.0
    # receivers partly on the sources (r = 0 pairs) and partly elsewhere
    k = min(n, m // 2)
    dst = torch.cat([src[:, :k], torch.rand(b, m - k, 3, generator=g, dtype=dtype) * 20.0], 1)
    e = torch.rand(b, n, 3, generator=g, dtype=dtype)
    area = torch.rand(b, n, generator=g, dtype=dtype) * 0.1
    return src, e, area, dst


MATERIALS = {
    "marble": DipoleMaterial.from_preset("marble"),
    "ketchup": DipoleMaterial.from_preset("ketchup"),
    # sigma_a = 0 in one channel (beta = 0), eta < 1 (the other F_dr fit), a per-channel eta
    "edge": DipoleMaterial([0.0, 0.5, 3.0], [0.2, 1.0, 40.0], [0.8, 1.0, 1.6]),
}


def _eager(monkeypatch, *args, **kwargs):
    monkeypatch.setenv("TORCHSSS_COMPILE", "0")
    with torch.no_grad():
        return reference_radiosity(*args, **kwargs)


def _compiled(monkeypatch, *args, **kwargs):
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    with torch.no_grad():
        return reference_radiosity(*args, **kwargs)


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_compiled_matches_eager_reference_float32(monkeypatch, name):
    """The fused kernel against the eager integrator through ``dipole_rd`` (an independent formulation)."""
    mat = MATERIALS[name]
    src, e, area, dst = _scene(2, 700, 2600, torch.float32)
    ref = _eager(monkeypatch, src, e, area, dst, mat)
    out = _compiled(monkeypatch, src, e, area, dst, mat)
    assert fused._WARM, "the compiled kernel did not run"
    assert out.shape == ref.shape == (2, 700, 3) and out.dtype == torch.float32
    assert torch.allclose(out, ref, rtol=2e-5, atol=1e-7 * float(ref.abs().max()))


@pytest.mark.parametrize("channels", [1, 3])
def test_compiled_distance_scale_float64(monkeypatch, channels):
    """M_d per source (one or three channels) and the irradiance modulation, in float64 to 1e-12."""
    mat = DipoleMaterial.from_preset("skin1", dtype=torch.float64)
    src, e, area, dst = _scene(1, 300, 900, torch.float64, seed=1)
    g = torch.Generator().manual_seed(2)
    md = 0.5 + torch.rand(1, 900, channels, generator=g, dtype=torch.float64)
    mi = torch.rand(1, 900, 1, generator=g, dtype=torch.float64)
    kw = dict(src_distance_scale=md, src_irradiance_scale=mi)
    ref = _eager(monkeypatch, src, e, area, dst, mat, **kw)
    out = _compiled(monkeypatch, src, e, area, dst, mat, **kw)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=0.0)


def test_no_recompile_for_new_sizes_materials_or_lights(monkeypatch):
    """Once compiled, new sample and receiver counts, new materials and new irradiance reuse the graph."""
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    src, e, area, dst = _scene(1, 333, 1500, torch.float32, seed=3)
    with torch.no_grad():
        reference_radiosity(src, e, area, dst, MATERIALS["marble"])
        before = counters["stats"]["unique_graphs"]
        for m, n, mat in ((100, 3000, "ketchup"), (2000, 700, "edge"), (37, 5000, "marble")):
            s2, e2, a2, d2 = _scene(1, m, n, torch.float32, seed=m)
            out = reference_radiosity(s2, e2 * 3.0, a2, d2, MATERIALS[mat])
            assert out.shape == (1, m, 3) and bool(torch.isfinite(out).all())
    assert counters["stats"]["unique_graphs"] == before


def test_blocks_bound_the_work_of_one_call(monkeypatch):
    """No call sees more than the device's pair budget (inductor stores one (B, C, m, n) block per call)."""
    seen = []
    monkeypatch.setenv("TORCHSSS_COMPILE", "0")
    monkeypatch.setattr(fused, "_EAGER_PAIRS", 1 << 12)
    real = fused._call

    def spy(kernel, variant, dst, src, *rest):
        seen.append(dst.shape[1] * src.shape[1])
        return real(kernel, variant, dst, src, *rest)

    monkeypatch.setattr(fused, "_call", spy)
    src, e, area, dst = _scene(1, 300, 1000, torch.float64)
    mat = DipoleMaterial.from_preset("marble", dtype=torch.float64)
    w = e * area[..., None]
    out = dipole_pair_sum(dst, src, w, mat.sigma_a.detach(), mat.sigma_s_prime.detach(), mat.eta.detach())
    assert max(seen) <= 1 << 12 and sum(seen) == 300 * 1000
    whole = dipole_pair_sum_eager(dst, src, w, mat.sigma_a.detach(), mat.sigma_s_prime.detach(), mat.eta.detach())
    torch.testing.assert_close(out, whole, rtol=1e-12, atol=0.0)


def test_policy(monkeypatch):
    """auto: eager until the eager work spent reaches COLD_WORK (ski rental), then compiled above WARM_WORK."""
    x = torch.zeros(3)
    monkeypatch.setattr(fused, "_WARM", set())
    monkeypatch.setattr(fused, "_EAGER_WORK", {})
    monkeypatch.setenv("TORCHSSS_COMPILE", "auto")
    assert not use_compiled("k", ("cpu",), COLD_WORK // 2, (x,))  # a compile would cost more than this call
    assert not use_compiled("k", ("gpu",), COLD_WORK // 2, (x,))  # another variant keeps its own account
    assert use_compiled("k", ("cpu",), COLD_WORK // 2, (x,))  # the eager work so far has paid for a compile
    fused._WARM.add(("k", "cpu"))
    assert use_compiled("k", ("cpu",), WARM_WORK, (x,)) and not use_compiled("k", ("cpu",), WARM_WORK - 1, (x,))
    monkeypatch.setenv("TORCHSSS_COMPILE", "0")
    assert not use_compiled("k", ("cpu",), 1e12, (x,))
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    assert use_compiled("k", ("cpu",), 1, (x,))
    p = torch.zeros(3, requires_grad=True)
    assert not use_compiled("k", ("cpu",), 1e12, (x, p))  # autograd records: eager
    with torch.no_grad():
        assert use_compiled("k", ("cpu",), 1e12, (x, p))
    assert not use_compiled("k", ("meta",), 1e12, (x.to("meta"),))


def test_expected_work_compiles_a_blocked_frame_at_once(monkeypatch):
    """An announced frame of >= COLD_WORK compiles at its first block; nested blocks restore; typed errors."""
    x = torch.zeros(3)
    monkeypatch.setattr(fused, "_WARM", set())
    monkeypatch.setattr(fused, "_EAGER_WORK", {})
    monkeypatch.setenv("TORCHSSS_COMPILE", "auto")
    with fused.expected_work("k", COLD_WORK - 1):
        assert not use_compiled("k", ("cpu",), 10, (x,))  # the whole frame is cheaper eager than a compile
    with fused.expected_work("k", 2 * COLD_WORK):
        with fused.expected_work("other", 0):  # another kernel's announcement does not count for "k"
            assert use_compiled("k", ("a",), 10, (x,))
        with fused.expected_work("k", 0):
            assert not use_compiled("k", ("b",), 10, (x,))  # the innermost announcement counts
        assert use_compiled("k", ("b",), 10, (x,))  # ... and the outer one is back
    assert fused._EXPECTED == {}
    assert not use_compiled("k", ("c",), 10, (x,))  # nothing announced: the ski-rental account
    with pytest.raises(ValueError, match="work"):
        with fused.expected_work("k", -1.0):
            pass
    with pytest.raises(TypeError, match="name"):
        with fused.expected_work(3, 1.0):
            pass


def test_reference_frame_compiles_at_its_first_block(monkeypatch):
    """reference_radiosity_at announces its frame: with a small COLD_WORK, every block of the frame is compiled."""
    import torchsss.ops.reference as ref_ops
    from torchsss.geometry import sphere
    from torchsss.geometry.sampling import surface_samples
    from torchsss.pipelines.reference import reference_radiosity_at

    calls = []

    def spy(*args, compiled=None, **kwargs):
        calls.append(compiled)
        return fused.dipole_pair_sum(*args, compiled=False, **kwargs)

    monkeypatch.setattr(fused, "_WARM", set())
    monkeypatch.setattr(fused, "_EAGER_WORK", {})
    monkeypatch.setenv("TORCHSSS_COMPILE", "auto")
    monkeypatch.setattr(ref_ops, "dipole_pair_sum", spy)
    samples = surface_samples(sphere(10.0, 2), 2.0)
    n = samples.area.shape[0]
    points = samples.position[:300]
    e = torch.ones(n, 3)
    with torch.no_grad():
        monkeypatch.setattr(fused, "COLD_WORK", 300 * n)  # the frame pays for exactly one compile
        out = reference_radiosity_at(points, samples, e, "marble", max_pairs=8 * n)  # blocks of 64 receivers
        assert len(calls) == 5 and all(calls), calls
        monkeypatch.setattr(fused, "_WARM", set())
        monkeypatch.setattr(fused, "_EAGER_WORK", {})
        monkeypatch.setattr(fused, "COLD_WORK", 300 * n + 1)  # it does not: eager throughout
        calls.clear()
        again = reference_radiosity_at(points, samples, e, "marble", max_pairs=8 * n)
        assert calls == []
    torch.testing.assert_close(out, again, rtol=1e-5, atol=0.0)


def test_compile_config_trusts_the_isa_flags_and_retries(monkeypatch):
    """Our compiles skip inductor's per-ISA probe builds unless the user set vec_isa_ok; a failure retries once."""
    from torch._inductor import config

    with config.patch({"cpp.vec_isa_ok": None}):
        with fused._compile_config():
            assert config.cpp.vec_isa_ok is True
        assert config.cpp.vec_isa_ok is None
        with config.patch({"cpp.vec_isa_ok": False}), fused._compile_config():
            assert config.cpp.vec_isa_ok is False  # the user's choice stands
        seen = []

        def kernel(t):
            seen.append(config.cpp.vec_isa_ok)
            if len(seen) == 1:
                raise RuntimeError("cannot build for a reported ISA")
            return t + 1

        kernel.torchsss_name, kernel.torchsss_eager = "flaky", lambda t: t - 1
        monkeypatch.setattr(fused, "_BROKEN", {})
        monkeypatch.setattr(fused, "_WARM", set())
        monkeypatch.setattr(fused, "_RAN", set())
        out = fused._call(kernel, ("cpu",), torch.zeros(2))
        assert seen == [True, None] and "flaky" not in fused._BROKEN  # retried with inductor's own probes
        torch.testing.assert_close(out, torch.ones(2))
        fused._call(kernel, ("cpu",), torch.zeros(2))  # it has run compiled: the setting is not patched again
        fused._call(kernel, ("gpu",), torch.zeros(2))  # a new variant compiles: patched
    assert seen == [True, None, None, True]


def test_gradients_take_the_eager_path(monkeypatch):
    """With parameters that record, the integrator stays differentiable (the compiled path is inference only)."""
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    mat = DipoleMaterial.from_preset("marble", dtype=torch.float64)
    src, e, area, dst = _scene(1, 20, 40, torch.float64)
    out = reference_radiosity(src, e, area, dst, mat)
    out.sum().backward()
    assert mat.raw_sigma_a.grad is not None and bool((mat.raw_sigma_a.grad != 0).all())


def test_failed_compile_falls_back_with_one_warning(monkeypatch):
    """Without a working compiler the result is the eager one, with one RuntimeWarning for the process."""
    def broken(fn, **kwargs):
        def run(*args):
            raise RuntimeError("no C++ compiler")
        return run

    monkeypatch.setattr(fused, "_COMPILED", {})
    monkeypatch.setattr(fused, "_BROKEN", {})
    monkeypatch.setattr(fused, "_WARM", set())
    monkeypatch.setattr(torch, "compile", broken)
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    src, e, area, dst = _scene(1, 50, 80, torch.float64)
    mat = DipoleMaterial.from_preset("marble", dtype=torch.float64)
    w = e * area[..., None]
    coeffs = (mat.sigma_a.detach(), mat.sigma_s_prime.detach(), mat.eta.detach())
    with pytest.warns(RuntimeWarning, match="compiling dipole_pair_sum failed"):
        out = dipole_pair_sum(dst, src, w, *coeffs)
    torch.testing.assert_close(out, dipole_pair_sum_eager(dst, src, w, *coeffs), rtol=1e-12, atol=0.0)
    assert "dipole_pair_sum" in fused._BROKEN and not fused._WARM


def test_reference_renderer_compiles_once(monkeypatch):
    """A moving light and a new camera (another resolution) render without a recompile; the image is the eager one."""
    from torchsss.geometry import Camera, DirectionalLight, PointLight, sphere
    from torchsss.pipelines.build import build

    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    r = build("reference", sphere(10.0, 3), "skin1", spacing_mm=1.0)
    cam = Camera(eye=(0, 0, 60), target=(0, 0, 0), width=24, height=24)
    first = r.render(DirectionalLight((0, 0, -1), 1.0), cam)
    before = counters["stats"]["unique_graphs"]
    moved = r.render(PointLight((30.0, 20.0, 40.0), 3e3), Camera(eye=(20, 0, 50), target=(0, 0, 0), width=31,
                                                                 height=17))
    assert counters["stats"]["unique_graphs"] == before
    monkeypatch.setenv("TORCHSSS_COMPILE", "0")
    eager = r.render(DirectionalLight((0, 0, -1), 1.0), cam)
    assert moved.radiance.shape == (1, 3, 17, 31) and float(moved.radiance.max()) > 0
    torch.testing.assert_close(first.radiance, eager.radiance, rtol=1e-4, atol=1e-6 * float(eager.radiance.max()))


@pytest.mark.parametrize("split", [False, True], ids=["ids", "chang_split"])
def test_compiled_ids_and_chang_split(monkeypatch, split):
    """Object/chart ids and the hybrid's global factor 1 - W_l^b(r M_d) [same], against the eager callable."""
    from torchsss.modules.chang import ChangLocalProfile

    mat = DipoleMaterial.from_preset("skin1")
    src, e, area, dst = _scene(1, 400, 1200, torch.float32, seed=5)
    g = torch.Generator().manual_seed(6)
    sid, did = torch.randint(0, 3, (1, 1200), generator=g), torch.randint(0, 3, (1, 400), generator=g)
    md = 0.5 + torch.rand(1, 1200, 1, generator=g)
    kw = dict(src_distance_scale=md, src_ids=sid, dst_ids=did)
    if split:
        lw = ChangLocalProfile(2.0, 1.5, 5.0)

        def plain(r, same):
            return 1.0 - lw(r) * same.to(r.dtype)

        def tagged(r, same):
            return plain(r, same)

        tagged.chang_split = (lw.r_p, lw.k, lw.bound)
        ref = _eager(monkeypatch, src, e, area, dst, mat, id_weight=plain, **kw)
        out = _compiled(monkeypatch, src, e, area, dst, mat, id_weight=tagged, **kw)
        # the factor matters: without it the sum differs
        whole = _eager(monkeypatch, src, e, area, dst, mat, src_distance_scale=md)
        assert not torch.allclose(ref, whole, rtol=1e-2)
    else:
        ref = _eager(monkeypatch, src, e, area, dst, mat, **kw)
        out = _compiled(monkeypatch, src, e, area, dst, mat, **kw)
    assert any(k[-1] == split and k[-2] for k in fused._WARM), "the compiled kernel did not run"
    assert torch.allclose(out, ref, rtol=2e-5, atol=1e-7 * float(ref.abs().max()))


def test_auto_stays_compiled_after_the_switch(monkeypatch):
    """Once the eager work has paid for a compile, every later call of the variant is compiled (even small ones)."""
    x = torch.zeros(3)
    monkeypatch.setattr(fused, "_WARM", set())
    monkeypatch.setattr(fused, "_EAGER_WORK", {})
    monkeypatch.setenv("TORCHSSS_COMPILE", "auto")
    calls = [use_compiled("v", ("cpu",), COLD_WORK * 0.4, (x,)) for _ in range(5)]
    assert calls == [False, False, True, True, True]


@pytest.mark.parametrize("md_channels", [0, 1, 3])
def test_dipole_taps_compiled_matches_the_profile(monkeypatch, md_channels):
    """Splat weights R_d(r M_d) [r M_d <= r_max] E dA: compiled (with a padded last block) against dipole_rd."""
    from torchsss.ops.fused import dipole_taps

    monkeypatch.setattr(fused, "_TAPS", 1000)
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    mat = DipoleMaterial.from_preset("ketchup")
    g = torch.Generator().manual_seed(7)
    p = 2500
    r = torch.rand(p, generator=g) * 6.0
    r[:10] = 0.0
    flux = torch.rand(3, p, generator=g)
    md = None if md_channels == 0 else 0.5 + torch.rand(md_channels, p, generator=g)
    rmax = torch.tensor([[4.0]])
    coeffs = [t.detach() for t in mat.dipole_coefficients()]
    with torch.no_grad():
        out = dipole_taps(r, flux, rmax, *coeffs, md, compiled=True)
        r_eff = r[None] if md is None else r[None] * md
        want = mat(r_eff.T).T * flux  # the profile channels-last: (P, 1 or C) -> (P, C)
        want = torch.where(r_eff <= rmax, want, torch.zeros_like(want))
    assert any(k[0] == "dipole_taps" for k in fused._WARM)
    torch.testing.assert_close(out, want, rtol=2e-5, atol=1e-7 * float(want.abs().max()))


def test_splat_renderer_compiled_matches_eager(monkeypatch):
    from torchsss.geometry import Camera, DirectionalLight, sphere
    from torchsss.pipelines.build import build

    r = build("splat", sphere(8.0, 3), "skin1", eps=0.01)
    cam = Camera(eye=(0, 0, 40), target=(0, 0, 0), width=32, height=32)
    light = DirectionalLight((0.2, 0.1, -1), 1.0)
    monkeypatch.setenv("TORCHSSS_COMPILE", "0")
    eager = r.render(light, cam).radiance
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    out = r.render(light, cam).radiance
    assert any(k[0] == "dipole_taps" for k in fused._WARM)
    torch.testing.assert_close(out, eager, rtol=1e-4, atol=1e-6 * float(eager.max()))


@pytest.mark.parametrize("compiled", [False, True])
def test_truncated_pair_sum_matches_a_loop(monkeypatch, compiled):
    """r_max (the splat's disk on the scaled distance): only pairs with r M_d <= r_max count; eager and compiled."""
    monkeypatch.setenv("TORCHSSS_COMPILE", "1" if compiled else "0")
    src, e, area, dst = _scene(1, 40, 70, torch.float32 if compiled else torch.float64)
    mat = DipoleMaterial.from_preset("marble", dtype=src.dtype)
    coeffs = tuple(t.detach() for t in (mat.sigma_a, mat.sigma_s_prime, mat.eta))
    g = torch.Generator().manual_seed(3)
    md = (0.5 + torch.rand(1, 70, 3, generator=g)).to(src.dtype)
    w = e * area[..., None]
    with torch.no_grad():
        out = dipole_pair_sum(dst, src, w, *coeffs, md, r_max=6.0)
        want = torch.zeros(1, 40, 3, dtype=torch.float64)
        for i in range(40):
            for j in range(70):
                r = (dst[0, i] - src[0, j]).norm().double() * md[0, j].double()  # (3,) per channel
                rd = torch.stack([dipole_rd(r[c].reshape(1, 1), *(t.double().reshape(-1).expand(3)[c]
                                                                  for t in coeffs)).reshape(-1)[0] for c in range(3)])
                want[0, i] += torch.where(r <= 6.0, rd * w[0, j].double(), torch.zeros(3, dtype=torch.float64))
    kept = int(((dst[0, :, None] - src[0, None]).norm(dim=-1)[..., None] * md[0, None] <= 6.0).sum())
    assert 0 < kept < 40 * 70 * 3  # the disk cuts some pairs and keeps others
    torch.testing.assert_close(out.double(), want, rtol=1e-5 if compiled else 1e-10, atol=1e-12)
    if compiled:
        assert fused.is_warm("dipole_pair_sum", truncated=True) and any("truncated" in k for k in fused._WARM)


def test_would_compile_answers_without_side_effects(monkeypatch):
    """would_compile mirrors use_compiled's policy and leaves its accounts alone."""
    monkeypatch.setattr(fused, "_WARM", set())
    monkeypatch.setattr(fused, "_EAGER_WORK", {})
    monkeypatch.setattr(fused, "_BROKEN", {})
    monkeypatch.setenv("TORCHSSS_COMPILE", "auto")
    assert not fused.would_compile("dipole_pair_sum", COLD_WORK - 1)
    assert fused.would_compile("dipole_pair_sum", COLD_WORK)
    with fused.expected_work("dipole_pair_sum", COLD_WORK):
        assert fused.would_compile("dipole_pair_sum", 1)
    fused._WARM.add(("dipole_pair_sum", "cpu", torch.float32, 1, 3, None, False, "truncated", False))
    assert fused.would_compile("dipole_pair_sum", WARM_WORK, truncated=True)
    assert not fused.would_compile("dipole_pair_sum", WARM_WORK - 1, truncated=True)
    assert not fused.would_compile("dipole_pair_sum", WARM_WORK, truncated=False)  # only the truncated one is warm
    assert fused._EAGER_WORK == {}
    monkeypatch.setenv("TORCHSSS_COMPILE", "0")
    assert not fused.would_compile("dipole_pair_sum", 1e12)
    monkeypatch.setenv("TORCHSSS_COMPILE", "1")
    assert fused.would_compile("dipole_pair_sum", 1)
    fused._BROKEN["dipole_pair_sum"] = "no compiler"
    assert not fused.would_compile("dipole_pair_sum", 1e12)
    del fused._BROKEN["dipole_pair_sum"]
    x = torch.zeros(3, requires_grad=True)
    assert not fused.would_compile("dipole_pair_sum", 1e12, (x,))  # autograd records through x: eager
    with torch.no_grad():
        assert fused.would_compile("dipole_pair_sum", 1e12, (x,))
    assert not fused.would_compile("dipole_pair_sum", 1e12, (x.detach().to("meta"),))


@pytest.mark.parametrize("mode", ["off", "on", "auto"])
def test_compile_policy_is_the_rule_use_compiled_applies(monkeypatch, mode):
    """The pure rule against a loop over works and warm states, and use_compiled's decisions against the rule."""
    monkeypatch.setattr(fused, "_WARM", set())
    monkeypatch.setattr(fused, "_EAGER_WORK", {})
    monkeypatch.setattr(fused, "_BROKEN", {})
    monkeypatch.setenv("TORCHSSS_COMPILE", mode)
    x = torch.zeros(2)
    for work in (0, 1, WARM_WORK - 1, WARM_WORK, COLD_WORK - 1, COLD_WORK, 1e15):
        for warm in (False, True):
            expected = {"off": False, "on": True}.get(mode, work >= (WARM_WORK if warm else COLD_WORK))
            assert fused.compile_policy(work, warm=warm) is expected
            assert fused.compile_policy(work, warm=warm, mode="off") is False
        key = ("v", str(work))  # a fresh variant: cold, its eager account empty
        assert fused.use_compiled("k", key, work, (x,)) is fused.compile_policy(work, warm=False)
        if mode == "auto" and work >= COLD_WORK:  # now warm: the warm rule
            assert fused.use_compiled("k", key, WARM_WORK - 1, (x,)) is False
            assert fused.use_compiled("k", key, WARM_WORK, (x,)) is True
    with pytest.raises(ValueError, match="mode"):
        fused.compile_policy(1.0, warm=False, mode="always")
