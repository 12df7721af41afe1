"""Shared fixtures: devices (CUDA cases skip without a GPU), dtypes, paths to the shared data."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared"

_DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]


@pytest.fixture(params=_DEVICES)
def device(request) -> torch.device:
    """Every available device: CPU always, CUDA when present."""
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    """The two dtypes every op must support at full accuracy."""
    return request.param


@pytest.fixture(scope="module")
def one_thread():
    """Small tensors: one intra-op thread is fastest (and far faster on a loaded, shared machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def shared_dir() -> Path:
    """../shared next to the repository (tests may read its data)."""
    if not SHARED.is_dir():
        pytest.skip(f"shared data not found at {SHARED}")
    return SHARED


# -- the accuracy scene every method is compared on (tests/test_<method>_vs_reference.py) -----------------------------
class VsReference:
    """A 16 mm skin1 sphere lit from the side and a little behind, 24 x 24 pixels: small enough for every method.

    ``reference(profile)`` is the all-pairs reference image with that profile model (cached per session), at a
    sample spacing of 0.2 mm (below every profile's default).
    """

    def __init__(self) -> None:
        from torchsss.geometry import Camera, PointLight, sphere
        from torchsss.physics import Material

        self.mesh = sphere(8.0, 3)  # radius 8 mm, 642 vertices
        self.camera = Camera(eye=(0.0, 0.0, 45.0), target=(0.0, 0.0, 0.0), width=24, height=24, fov_deg=26.0)
        self.lights = [PointLight((40.0, 5.0, -20.0), (1500.0, 1500.0, 1500.0))]
        self.material = Material.from_json("skin1")
        self._refs: dict = {}

    def reference(self, profile: str):
        from torchsss.pipelines import build

        if profile not in self._refs:
            r = build("reference", self.mesh, self.material.with_profile(profile), spacing_mm=0.2)
            self._refs[profile] = r.render(self.lights, self.camera)
        return self._refs[profile]

    def error(self, result, profile: str) -> float:
        """Relative RMSE of ``result``'s radiance against the reference over the pixels both cover."""
        ref = self.reference(profile)
        m = (ref.mask & result.mask).expand_as(ref.radiance)
        d = (result.radiance - ref.radiance)[m]
        return float(d.square().mean().sqrt() / ref.radiance[m].square().mean().sqrt())


@pytest.fixture(scope="session")
def vs_reference() -> VsReference:
    """The shared accuracy scene (see :class:`VsReference`)."""
    return VsReference()


def eta_edit_case(method: str, scene: VsReference, **knobs):
    """Edit eta on a prebuilt renderer: (before, edited, fresh) radiance for eta 1.3 -> 1.6 (the one home of eta).

    ``fresh`` is a new build with eta 1.6; ``edited`` the prebuilt renderer after its material module's eta was set
    to 1.6 in place. Both Fresnel terms (irradiance and exit) and R_d must follow the edit.
    """
    import dataclasses

    from torchsss.modules import DipoleMaterial
    from torchsss.pipelines import build

    r = build(method, scene.mesh, scene.material, **knobs)
    before = r.render(scene.lights, scene.camera).radiance
    with torch.no_grad():
        r.material.raw_eta.copy_(DipoleMaterial(0.1, 1.0, 1.6).raw_eta.reshape(r.material.raw_eta.shape))
    edited = r.render(scene.lights, scene.camera).radiance
    fresh = build(method, scene.mesh, dataclasses.replace(scene.material, eta=1.6), **knobs)
    return before, edited, fresh.render(scene.lights, scene.camera).radiance


def rel_rmse(a: torch.Tensor, b: torch.Tensor) -> float:
    """Relative RMSE of ``a`` against ``b`` over the pixels where ``b`` is non-zero."""
    m = b != 0
    return float((a - b)[m].square().mean().sqrt() / b[m].square().mean().sqrt())


def assert_eta_gradient(f, shape, eta0: float = 1.3, h: float = 1e-6) -> torch.Tensor:
    """``f(eta)`` (a scalar) has a finite, non-zero gradient w.r.t. a float64 ``eta`` of ``shape`` that matches
    central finite differences (rtol 1e-6); returns the eta tensor (with its gradient)."""
    eta = torch.full(shape, eta0, dtype=torch.float64, requires_grad=True)
    f(eta).backward()
    grad = eta.grad.reshape(())
    fd = (f(torch.tensor(eta0 + h, dtype=torch.float64)) - f(torch.tensor(eta0 - h, dtype=torch.float64))) / (2 * h)
    assert torch.isfinite(grad) and grad != 0
    torch.testing.assert_close(grad, fd, rtol=1e-6, atol=0)
    return eta
