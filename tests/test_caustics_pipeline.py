"""The caustics pipeline: light-view G-buffers of meshes against closed-form hits, the rendered image, the energy,
and a --quick smoke run of benchmarks/bench_caustics.py."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchsss.geometry.camera import Camera, transform_points
from torchsss.geometry.lights import DirectionalLight, PointLight, SpotLight
from torchsss.geometry.mesh import mesh_from_arrays
from torchsss.geometry.procedural import plane, sphere
from torchsss.pipelines.caustics import caustic_gbuffers, render_caustics

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks" / "bench_caustics.py"
R, ZC = 10.0, 16.0
F64 = torch.float64
DOWN = DirectionalLight((0.0, 0.0, -1.0), 1.0)


@pytest.fixture(scope="module")
def scene():
    s = sphere(R, 5, dtype=F64)
    s = mesh_from_arrays(s.vertices + torch.tensor([0.0, 0.0, ZC], dtype=F64), s.faces, dtype=F64, name="sphere")
    return s, plane(120.0, 120.0, 4, dtype=F64)


def texel_rays(gb):
    """Origins (far behind) and unit directions of the light-view rays through every texel centre, (H*W, 3)."""
    h, w = gb.front_position.shape[-2:]
    xs = -1 + (np.arange(w) + 0.5) * 2 / w
    ys = 1 - (np.arange(h) + 0.5) * 2 / h
    nx, ny = np.meshgrid(xs, ys)
    inv = torch.linalg.inv(gb.view_proj[0]).numpy()

    def unproject(z):
        c = np.stack([nx.ravel(), ny.ravel(), np.full(nx.size, z), np.ones(nx.size)], -1) @ inv.T
        return c[:, :3] / c[:, 3:]

    a, b = unproject(-1.0), unproject(1.0)
    d = b - a
    return a, d / np.linalg.norm(d, axis=-1, keepdims=True)


def ray_sphere(o, d):
    oc = o - np.array([0.0, 0.0, ZC])
    bq = (oc * d).sum(-1)
    disc = bq * bq - ((oc * oc).sum(-1) - R * R)
    sq = np.sqrt(np.clip(disc, 0, None))
    return disc > 0, o + (-bq - sq)[:, None] * d, o + (-bq + sq)[:, None] * d, np.sqrt(np.clip(disc, 0, None))


@pytest.mark.parametrize("light", [DOWN, PointLight((8.0, -5.0, 90.0), 1.0)], ids=["directional", "point"])
def test_gbuffers_match_closed_form_hits(scene, light):
    refractor, receiver = scene
    g = 64
    gb = caustic_gbuffers(refractor, receiver, light, g, map_resolution=48)
    assert gb.camera.projection == ("orthographic" if isinstance(light, DirectionalLight) else "perspective")
    o, d = texel_rays(gb)
    hit, front, back, half_chord = ray_sphere(o, d)
    fm = gb.front_mask[0, 0].numpy().ravel()
    bm = gb.back_mask[0, 0].numpy().ravel()
    fp = gb.front_position[0].numpy().reshape(3, -1).T
    bp = gb.back_position[0].numpy().reshape(3, -1).T
    # coverage agrees except on the silhouette ring of the faceted sphere
    assert (fm == bm).all()
    assert fm.sum() > 0.25 * g * g / 1.5**2 * math.pi / 4
    assert not (fm & ~hit).any()
    inner = hit & (half_chord > 0.2 * R)  # away from the silhouette, where the facets' error is small
    assert (fm[inner]).all()
    # a texel's footprint (mm) at the sphere: the tolerance for where along the ray the hit is
    tex = 2 * 1.5 * R / g * (1.0 if isinstance(light, DirectionalLight) else 1.2)
    err_f = np.linalg.norm(fp[inner] - front[inner], axis=-1)
    err_b = np.linalg.norm(bp[inner] - back[inner], axis=-1)
    assert err_f.max() < 0.25 * tex and err_b.max() < 0.25 * tex, (err_f.max(), err_b.max())
    # normals: outward, close to the sphere's
    nf = gb.front_normal[0].numpy().reshape(3, -1).T[inner]
    assert (nf * (front[inner] - [0, 0, ZC]) / R).sum(-1).min() > 0.99
    # empty texels are non-finite
    assert np.isnan(fp[~fm]).all() and np.isnan(bp[~bm]).all()
    # receiver: the floor z = 0 along every ray, everywhere (the plane covers the whole light view)
    rec = gb.receiver_position[0].numpy().reshape(3, -1).T
    assert gb.receiver_mask.all()
    gr = caustic_gbuffers(refractor, receiver, light, 48)  # rays of the map's resolution
    o2, d2 = texel_rays(gr)
    expected = o2 - (o2[:, 2] / d2[:, 2])[:, None] * d2
    np.testing.assert_allclose(rec, expected, atol=1e-6)
    # a receiver smaller than the view leaves NaN texels
    small = caustic_gbuffers(refractor, plane(10.0, 10.0, 1, dtype=F64), light, 32)
    empty = ~small.receiver_mask[0, 0]
    assert empty.any() and torch.isnan(small.receiver_position[0][:, empty]).all()


def photon_flux_in_view(half: float, m: int = 700) -> float:
    """Flux (irradiance 1) through the exact sphere that lands on z = 0 inside |x|, |y| < half (closed-form rays)."""
    rng = np.random.default_rng(1)
    cell = 2 * R / m
    x = (-R + (np.arange(m)[None, :] + rng.random((m, m))) * cell).ravel()
    y = (-R + (np.arange(m)[:, None] + rng.random((m, m))) * cell).ravel()
    keep = x * x + y * y < R * R
    o = np.stack([x[keep], y[keep], np.full(keep.sum(), 100.0)], -1)
    d = np.broadcast_to([0.0, 0.0, -1.0], o.shape)
    _, p, _, _ = ray_sphere(o, d)

    def snell(i, n, eta):
        c = -(i * n).sum(-1, keepdims=True)
        k = 1 - eta**2 * (1 - c**2)
        t = eta * i + (eta * c - np.sqrt(np.clip(k, 0, None))) * n
        return t / np.linalg.norm(t, axis=-1, keepdims=True), k[:, 0] > 0

    c0 = np.array([0.0, 0.0, ZC])
    t1, _ = snell(d, (p - c0) / R, 1 / 1.5)
    q = p - 2 * ((p - c0) * t1).sum(-1)[:, None] * t1
    t2, ok = snell(t1, -(q - c0) / R, 1.5)
    ok &= t2[:, 2] < 0
    hit = q - (q[:, 2] / np.where(ok, t2[:, 2], -1.0))[:, None] * t2
    inside = ok & (np.abs(hit[:, 0]) < half) & (np.abs(hit[:, 1]) < half)
    return float(inside.sum() * cell * cell)


def pixel_of(camera: Camera, point) -> tuple[int, int]:
    clip = transform_points(torch.tensor([point], dtype=F64), camera.view_proj(dtype=F64))[0, 0]
    ndc = clip[:2] / clip[3]
    return int((1 - ndc[1]) / 2 * camera.height), int((ndc[0] + 1) / 2 * camera.width)


def test_render_caustics_brightens_under_the_sphere_and_conserves_energy(scene):
    refractor, receiver = scene
    camera = Camera(eye=(0.0, -80.0, 25.0), target=(0.0, 0.0, 4.0), fov_deg=30.0, width=96, height=96)
    res = render_caustics(refractor, receiver, DOWN, camera, ior=1.5, resolution=128, albedo=0.5,
                          environment=0.2, shadow_resolution=512)
    img = res.radiance
    assert img.shape == (1, 3, 96, 96) and torch.isfinite(img).all() and (img >= 0).all()
    assert res.receiver_mask.any() and res.refractor_mask.any()
    lit = 0.5 / math.pi * 1.0  # the unshadowed floor: albedo / pi * E
    far = pixel_of(camera, (25.0, 20.0, 0.0))
    torch.testing.assert_close(img[0, :, far[0], far[1]], torch.full((3,), lit, dtype=F64))
    # the focused caustic under the sphere: far brighter than direct light; there is no direct light (shadow)
    centre = pixel_of(camera, (0.0, 0.0, 0.0))
    assert res.direct[0, 0, centre[0], centre[1]] == 0
    assert img[0, 0, centre[0], centre[1]] > 5 * lit
    # the shadow ring between the focused spot and the sphere's silhouette is darker than the lit floor
    ring = pixel_of(camera, (-8.0, 0.0, 0.0))
    assert res.direct[0, 0, ring[0], ring[1]] == 0 and img[0, 0, ring[0], ring[1]] < 0.5 * lit
    # the refractor shows the Fresnel reflection of the environment and the floor through two refractions: > 0,
    # and no brighter than the brightest thing it can see (the floor with its caustic, or the sky)
    shade = img[0, 0][res.refractor_mask[0, 0]]
    assert (shade > 0).all() and shade.max() <= img[0, 0][res.receiver_mask[0, 0]].max()
    # energy: the caustic map's flux equals the flux the exact sphere transmits into the light view
    half = res.gbuffers[0].camera.ortho_half_height
    expected = photon_flux_in_view(half)
    assert expected > 0.85 * math.pi * R * R  # most of the light that enters reaches the floor inside the view
    total = res.caustic_maps[0][0].sum((-2, -1))
    torch.testing.assert_close(total, torch.full((3,), expected, dtype=F64), rtol=0.02, atol=0)
    # and the irradiance map integrates back to the flux over the floor (flat floor: area per texel = A_perp)
    texel_area = (2 * half / 128) ** 2
    torch.testing.assert_close(res.irradiance_maps[0][0].sum((-2, -1)) * texel_area, total, rtol=1e-9, atol=0)


def test_errors(scene):
    refractor, receiver = scene
    cam = Camera(eye=(0.0, -80.0, 25.0), target=(0.0, 0.0, 4.0), width=8, height=8)
    with pytest.raises(TypeError, match="refractor: expected a torchsss Mesh"):
        caustic_gbuffers("sphere", receiver, DOWN)
    with pytest.raises(TypeError, match="light: expected a DirectionalLight or PointLight"):
        caustic_gbuffers(refractor, receiver, SpotLight((0, 0, 90), (0, 0, -1), 1.0))
    with pytest.raises(ValueError, match="resolution: expected an int >= 1, got 0"):
        caustic_gbuffers(refractor, receiver, DOWN, 0)
    with pytest.raises(TypeError, match="map_resolution: expected an int"):
        caustic_gbuffers(refractor, receiver, DOWN, 8, map_resolution=8.0)
    with pytest.raises(ValueError, match="margin: expected a finite number > 0"):
        caustic_gbuffers(refractor, receiver, DOWN, 8, margin=0.0)
    with pytest.raises(ValueError, match="light: expected a point light outside"):
        caustic_gbuffers(refractor, receiver, PointLight((0.0, 0.0, ZC), 1.0), 8)
    with pytest.raises(TypeError, match="camera: expected a Camera"):
        render_caustics(refractor, receiver, DOWN, None)
    with pytest.raises(TypeError, match="lights: expected a light or a non-empty sequence"):
        render_caustics(refractor, receiver, [], cam)
    with pytest.raises(ValueError, match="albedo: expected one or three finite values"):
        render_caustics(refractor, receiver, DOWN, cam, albedo=[0.5, 0.5])
    with pytest.raises(ValueError, match="mode: expected one of"):
        render_caustics(refractor, receiver, DOWN, cam, mode="refract")


def test_bench_caustics_quick_smoke(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.run([sys.executable, str(BENCH), "--quick", "--out-dir", str(out)], capture_output=True,
                          text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    data = json.loads((out / "caustics_quick.json").read_text(encoding="utf-8"))
    assert (out / "caustics_quick.md").is_file()
    recs = data["records"]
    assert {(r["source"], r["splat"], r["grid"]) for r in recs} == {
        (s, k, g) for s in ("analytic", "mesh") for k in ("beam", "gaussian") for g in (64, 128)}
    for r in recs:
        for key in ("rel_rmse", "rel_l1", "focus_rel_l1", "energy_ratio", "t_module_ms", "t_frame_ms"):
            assert isinstance(r[key], float) and math.isfinite(r[key]) and r[key] >= 0, (key, r)
        assert abs(r["energy_ratio"] - 1.0) < 0.03 and r["focus_rel_l1"] < 0.05


def test_refractor_normals_choice_and_errors():
    from torchsss.geometry.procedural import sphere
    from torchsss.pipelines.caustics import refractor_normals

    m = sphere(5.0, 2)
    assert refractor_normals(m, "max") is m.vertex_normals_max
    assert refractor_normals(m, "area") is m.vertex_normals
    with pytest.raises(ValueError, match="normals: expected one of"):
        refractor_normals(m, "smooth")
