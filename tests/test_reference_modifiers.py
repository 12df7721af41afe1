"""Per-vertex heterogeneous modifiers (Shah eq. 7.4) in the reference renderer: closed forms, a loop reference,
the default spacing, and typed errors (the gradient against central differences is in test_pipeline_gradients)."""

from __future__ import annotations

import pytest
import torch

from torchsss.geometry import Camera, PointLight, sphere
from torchsss.ops import reference_radiosity
from torchsss.physics.materials import Material
from torchsss.pipelines import build, default_spacing

F64 = torch.float64
CAM = Camera(eye=(0.0, 0.0, 40.0), target=(0.0, 0.0, 0.0), width=12, height=12)
LIGHTS = [PointLight((30.0, 10.0, 30.0), 2e3)]


def _render(material, spacing=1.0, **mods):
    return build("reference", sphere(6.0, 2, dtype=F64), material, dtype=F64, spacing_mm=spacing,
                 **mods).render(LIGHTS, CAM).radiance


def test_unit_modifiers_change_nothing():
    v = sphere(6.0, 2).vertices.shape[0]
    plain = _render("skin1")
    ones = _render("skin1", distance_scale=torch.ones(v, dtype=F64), irradiance_scale=torch.ones(v, 3, dtype=F64))
    assert float(plain.amax()) > 0
    torch.testing.assert_close(ones, plain, rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("s", [0.5, 2.0])
def test_uniform_distance_scale_is_a_scaled_material(s):
    """Closed form: the dipole of coefficients s sigma is :math:`s^2 R_d(s r)`, so a uniform :math:`M_d = s` renders
    the material with every coefficient times s, divided by :math:`s^2` (same samples, same eta)."""
    base = Material.from_json("skin1")
    scaled = Material.from_json({"sigma_a": [s * x for x in base.sigma_a],
                                 "sigma_s_prime": [s * x for x in base.sigma_s_prime], "eta": base.eta})
    v = sphere(6.0, 2).vertices.shape[0]
    got = _render(base, distance_scale=torch.full((v,), s, dtype=F64))
    want = _render(scaled) / s**2
    assert float(want.amax()) > 0
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)
    # and it is not the unmodified image: the check can fail
    assert float((got - _render(base)).abs().amax()) > 0.05 * float(want.amax())


def test_uniform_irradiance_scale_scales_the_image():
    v = sphere(6.0, 2).vertices.shape[0]
    torch.testing.assert_close(_render("marble", irradiance_scale=torch.full((v, 1), 0.3, dtype=F64)),
                               0.3 * _render("marble"), rtol=1e-12, atol=0.0)


def test_varying_maps_match_a_loop_over_samples():
    """A per-vertex, per-channel map against the integral written out sample by sample (interpolated modifiers,
    one reference_radiosity call per receiver pixel with per-source scales built in a Python loop)."""
    mesh = sphere(6.0, 2, dtype=F64)
    gen = torch.Generator().manual_seed(3)
    v = mesh.vertices.shape[0]
    md = 0.6 + 0.8 * torch.rand(v, 3, dtype=F64, generator=gen)
    mi = 0.5 + torch.rand(v, dtype=F64, generator=gen)
    r = build("reference", mesh, "skin1", dtype=F64, spacing_mm=1.5, stride=1, distance_scale=md,
              irradiance_scale=mi)
    res = r.render(LIGHTS, CAM)
    from torchsss.pipelines.reference import sample_irradiance

    smp = r.samples
    e = sample_irradiance(mesh, smp, LIGHTS, r.eta)
    md_s = torch.stack([sum(float(smp.bary[i, j]) * md[int(mesh.faces[smp.face_id[i], j])] for j in range(3))
                        for i in range(smp.area.shape[0])])
    mi_s = torch.stack([sum(float(smp.bary[i, j]) * mi[int(mesh.faces[smp.face_id[i], j])] for j in range(3))
                        for i in range(smp.area.shape[0])])
    mask = res.mask[0, 0]
    from torchsss.geometry.gbuffer import camera_gbuffer

    dst = camera_gbuffer(mesh, CAM).position[0].permute(1, 2, 0)[mask]
    with torch.no_grad():
        want = reference_radiosity(smp.position[None], e[None], smp.area[None], dst[None], r.material,
                                   src_distance_scale=md_s[None], src_irradiance_scale=mi_s[None, :, None])[0]
    got = res.radiosity[0].permute(1, 2, 0)[mask]
    assert float(want.amax()) > 0
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)


def test_default_spacing_follows_the_largest_distance_scale():
    mesh = sphere(6.0, 2)
    v = mesh.vertices.shape[0]
    md = torch.ones(v)
    md[0] = 2.5
    plain = default_spacing(Material.from_json("skin1"), mesh)
    r = build("reference", mesh, "skin1", distance_scale=md)
    assert r.knobs["spacing_mm"] == pytest.approx(plain / 2.5)
    # M_d < 1 widens the profile: the spacing is not coarsened
    r = build("reference", mesh, "skin1", distance_scale=torch.full((v,), 0.5))
    assert r.knobs["spacing_mm"] == pytest.approx(plain)


def test_modifier_errors():
    mesh = sphere(6.0, 2)
    v = mesh.vertices.shape[0]
    with pytest.raises(ValueError, match=r"distance_scale: expected shape \(162,\)"):
        build("reference", mesh, "skin1", distance_scale=torch.ones(v + 1))
    with pytest.raises(TypeError, match="irradiance_scale: expected a floating tensor"):
        build("reference", mesh, "skin1", irradiance_scale=[1.0] * v)
    with pytest.raises(ValueError, match="distance_scale: expected values > 0"):
        build("reference", mesh, "skin1", distance_scale=torch.zeros(v))
    with pytest.raises(ValueError, match="irradiance_scale: expected values >= 0"):
        build("reference", mesh, "skin1", irradiance_scale=-torch.ones(v))
    with pytest.raises(ValueError, match="distance_scale"):
        build("reference", mesh, "skin1", distance_scale=torch.full((v,), float("nan")))
    with pytest.raises(ValueError, match="source_faces: expected None with per-vertex"):
        build("reference", mesh, "skin1", distance_scale=torch.ones(v), source_faces=100)
    # the methods without per-vertex maps refuse them by name
    with pytest.raises((TypeError, ValueError), match="distance_scale"):
        build("icdf", mesh, "skin1", distance_scale=torch.ones(v))
