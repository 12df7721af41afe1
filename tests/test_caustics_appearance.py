"""The refractor's own appearance (Shah §5.2-5.3): camera-view reflection and double refraction found by the
Newton-Raphson search in positions textures, against an exact ray tracer of a glass sphere over a plane.

The exact tracer is independent of the code under test: closed-form ray-sphere and ray-plane intersections and
Snell's law in numpy, per pixel centre of the camera.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchsss.geometry.camera import Camera
from torchsss.geometry.lights import DirectionalLight
from torchsss.geometry.mesh import mesh_from_arrays
from torchsss.geometry.procedural import plane, sphere
from torchsss.modules.caustics import CausticMap
from torchsss.pipelines.caustics import lookup_camera, refractor_paths, render_caustics, sky_radiance

R, ZC = 10.0, 16.0
F64 = torch.float64
CAM = Camera(eye=(0.0, -60.0, 40.0), target=(0.0, 0.0, 10.0), fov_deg=30.0, width=64, height=64, near=5.0,
             far=300.0)

pytestmark = pytest.mark.usefixtures("one_thread")


def pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Eye and unit directions (H, W, 3) through the pixel centres (row 0 at the top)."""
    h, w = camera.resolution
    inv = torch.linalg.inv(camera.view_proj(dtype=F64)).numpy()
    nx = -1 + (np.arange(w) + 0.5) * 2 / w
    ny = 1 - (np.arange(h) + 0.5) * 2 / h
    x, y = np.meshgrid(nx, ny)

    def unproject(z):
        c = np.stack([x, y, np.full_like(x, z), np.ones_like(x)], -1) @ inv.T
        return c[..., :3] / c[..., 3:]

    a, b = unproject(-1.0), unproject(1.0)
    d = b - a
    return np.asarray(camera.eye, dtype=float), d / np.linalg.norm(d, axis=-1, keepdims=True)


def hit_sphere(o, d, far: bool):
    oc = o - np.array([0.0, 0.0, ZC])
    bq = (oc * d).sum(-1)
    disc = bq * bq - ((oc * oc).sum(-1) - R * R)
    t = -bq + (1 if far else -1) * np.sqrt(np.clip(disc, 0, None))
    return disc > 0, o + t[..., None] * d


def snell(i, n, eta):
    c = -(i * n).sum(-1, keepdims=True)
    k = 1.0 - eta**2 * (1.0 - c**2)
    t = eta * i + (eta * c - np.sqrt(np.clip(k, 0.0, None))) * n
    return t / np.linalg.norm(t, axis=-1, keepdims=True), k[..., 0] > 0


def fresnel_r(cos_i, n1, n2):
    sin_t = n1 / n2 * np.sqrt(np.clip(1 - cos_i**2, 0, None))
    cos_t = np.sqrt(np.clip(1 - sin_t**2, 0, None))
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)
    return np.where(sin_t < 1, 0.5 * (rs**2 + rp**2), 1.0)


def exact_paths(eye, d, ior):
    """Exact front point, exit point, exit direction, floor point (z = 0) and Fresnel transmittance per ray."""
    ok, p = hit_sphere(eye, d, far=False)
    n1 = (p - np.array([0, 0, ZC])) / R
    t1, _ = snell(d, n1, 1 / ior)
    _, q = hit_sphere(p + 1e-9 * t1, t1, far=True)
    n2 = (q - np.array([0, 0, ZC])) / R
    t2, ok2 = snell(t1, -n2, ior)
    t = -q[..., 2] / np.where(t2[..., 2] < 0, t2[..., 2], -1.0)
    floor = q + t[..., None] * t2
    weight = (1 - fresnel_r(-(d * n1).sum(-1), 1.0, ior)) * (1 - fresnel_r((t1 * n2).sum(-1), ior, 1.0))
    return ok, p, n1, q, t2, floor, ok2 & (t2[..., 2] < 0), weight


def analytic_textures(camera: Camera, ior: float):
    """Camera-view G-buffers of the exact sphere (front and back layers) and the lookup camera's floor texture."""
    eye, d = pixel_rays(camera)
    ok, p, n1, *_ = exact_paths(eye, d, ior)
    _, q = hit_sphere(eye, d, far=True)
    nan = np.where(ok[..., None], 1.0, np.nan)

    def img(a):
        return torch.tensor(np.moveaxis(a, -1, 0))[None]

    back = img(q * nan)
    back_n = img((q - np.array([0, 0, ZC])) / R * nan)
    mask = torch.tensor(ok)[None, None]
    look = lookup_camera(camera, 2.0)
    le, ld = pixel_rays(look)
    t = -le[2] / np.where(ld[..., 2] < 0, ld[..., 2], np.nan)
    floor = le + t[..., None] * ld  # the infinite plane z = 0 (NaN where the ray does not go down)
    return ok, p, n1, back, back_n, mask, img(floor), look


def test_double_refraction_finds_the_exact_floor_point():
    """Analytic camera-view textures: the looked-up floor point through two refractions is within 0.02 mm
    (median) of the exact ray tracer's, and the Fresnel weight matches the exact two-interface transmittance."""
    ior = 1.5
    ok, p, n1, back, back_n, mask, floor, look = analytic_textures(CAM, ior)
    module = CausticMap(ior)
    sel = ok.reshape(-1)
    pos = torch.tensor(p.reshape(-1, 3)[sel])
    nrm = torch.tensor(n1.reshape(-1, 3)[sel])
    eye = torch.tensor(CAM.eye, dtype=F64)
    paths = refractor_paths(module, pos, nrm, eye, back, back_n, mask, CAM.view_proj(dtype=F64), floor,
                            look.view_proj(dtype=F64))
    e, d = pixel_rays(CAM)
    _, _, _, _, _, exact_floor, exact_ok, weight = exact_paths(e, d, ior)
    exact_floor, exact_ok, weight = exact_floor.reshape(-1, 3)[sel], exact_ok.reshape(-1)[sel], weight.reshape(-1)[sel]
    got, hit = paths.transmit_point[:, 0].numpy(), paths.transmit_hit[:, 0].numpy()
    both = hit & exact_ok
    err = np.linalg.norm(got - exact_floor, axis=-1)[both]
    print(f"{sel.sum()} refractor pixels, {both.sum()} reach the floor; looked-up floor point error median "
          f"{np.median(err):.4f} mm, 95th percentile {np.percentile(err, 95):.4f} mm, max {err.max():.3f} mm")
    # the floor points the exact tracer finds inside the lookup camera's view: all of them are found
    clip = np.concatenate([exact_floor, np.ones((len(exact_floor), 1))], -1) @ look.view_proj(dtype=F64).numpy().T
    in_view = exact_ok & (clip[:, 3] > 0) & (np.abs(clip[:, :2] / clip[:, 3:]) < 0.98).all(-1)
    print(f"floor hits: exact {exact_ok.sum()} ({in_view.sum()} inside the lookup view), found {hit.sum()}, "
          f"found and inside {(hit & in_view).sum()}, found outside the exact ones {(hit & ~exact_ok).sum()}")
    # (the misses are grazing exit rays at the rim, |t_z| ~ 0.2, landing 50-75 mm away: they take the sky)
    assert (hit & in_view).sum() > 0.9 * in_view.sum() and (hit & ~exact_ok).sum() == 0
    assert np.median(err) < 0.05 and np.percentile(err, 95) < 0.3
    np.testing.assert_allclose(paths.transmit_weight[:, 0].numpy()[both], weight[both], rtol=0.03, atol=1e-6)
    # the mirror rays: exact reflection of the view ray, Fresnel reflectance as the weight
    cos_v = -(d.reshape(-1, 3)[sel] * n1.reshape(-1, 3)[sel]).sum(-1)
    np.testing.assert_allclose(paths.reflect_weight[:, 0].numpy(), fresnel_r(cos_v, 1.0, ior), rtol=1e-9)


@pytest.fixture(scope="module")
def rendered():
    s = sphere(R, 4, dtype=F64)
    ball = mesh_from_arrays(s.vertices + torch.tensor([0.0, 0.0, ZC], dtype=F64), s.faces, dtype=F64, name="ball")
    floor = plane(120.0, 120.0, 4, dtype=F64)
    horizon, zenith = (0.1, 0.1, 0.1), (0.2, 0.3, 0.5)
    res = render_caustics(ball, floor, DirectionalLight((0.0, 0.0, -1.0), 1.0), CAM, ior=1.5, resolution=128,
                          environment=horizon, environment_zenith=zenith, shadow_resolution=512)
    return res, horizon, zenith


def test_mesh_sphere_sees_the_floor_through_itself(rendered):
    """The whole pipeline on a tessellated sphere: the refracted floor points are close to the exact ones, the
    glass is not black, and its pixels are the Fresnel-weighted sum of what the two rays see."""
    res, horizon, zenith = rendered
    paths = res.paths
    ref = res.refractor_mask[0, 0].reshape(-1).numpy()
    e, d = pixel_rays(CAM)
    ok, *_, exact_floor, exact_ok, _ = exact_paths(e, d, 1.5)
    sel = ref & ok.reshape(-1)
    idx = np.flatnonzero(ref)
    keep = sel[idx]
    got = paths.transmit_point[:, 0].numpy()[keep]
    both = paths.transmit_hit[:, 0].numpy()[keep] & exact_ok.reshape(-1)[sel]
    err = np.linalg.norm(got - exact_floor.reshape(-1, 3)[sel], axis=-1)[both]
    print(f"mesh sphere: floor point error median {np.median(err):.3f} mm, 90th percentile "
          f"{np.percentile(err, 90):.3f} mm over {both.sum()} pixels")
    assert both.sum() > 0.5 * keep.sum()
    assert np.median(err) < 0.3
    glass = res.radiance[0][:, res.refractor_mask[0, 0]]
    assert bool((glass > 0).all()) and float(glass.mean()) > 0.05  # the floor (0.8 / pi lit) shows through
    # the background is the sky gradient
    bg = ~(res.receiver_mask | res.refractor_mask)[0, 0]
    sky = res.radiance[0][:, bg]
    assert float(sky.min()) >= min(horizon) - 1e-12 and float(sky.max()) <= max(zenith) + 1e-12


def test_sky_radiance_gradient():
    h, z = torch.tensor([0.1, 0.2, 0.3], dtype=F64), torch.tensor([0.5, 0.6, 0.7], dtype=F64)
    d = torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 1.0]], dtype=F64)
    out = sky_radiance(d, h, z)
    torch.testing.assert_close(out[0], z)
    torch.testing.assert_close(out[1], h)
    torch.testing.assert_close(out[2], h)
    torch.testing.assert_close(out[3], h + (z - h) * math.sqrt(0.5))
