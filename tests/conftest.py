"""Shared fixtures: devices (CUDA cases skip without a GPU), dtypes, paths to the shared data."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared"

# Compiled kernels (torchsss.ops.fused) stay off unless a test switches them on (tests/test_fused*.py): the "auto"
# rule compiles once a process has spent enough eager work, which in a test session would depend on test order.
os.environ.setdefault("TORCHSSS_COMPILE", "0")

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


@pytest.fixture(scope="session")
def registry_export(tmp_path_factory):
    """Export an entry of :data:`torchsss.export.registry.EXPORTABLE` once per session: name -> (case, path, seconds).

    The registry is the one list of exported modules: the export tests and the op tests that check an exported
    file at extreme inputs share its files.
    """
    import time

    cache = {}

    def get(name):
        if name not in cache:
            from torchsss.export import export_onnx
            from torchsss.export.registry import export_case

            case = export_case(name)
            path = tmp_path_factory.mktemp("onnx") / f"{name}.onnx"
            t0 = time.perf_counter()
            export_onnx(case.module, case.example_args, path, dynamic_shapes=case.dynamic_shapes,
                        input_names=case.input_names)
            cache[name] = (case, path, time.perf_counter() - t0)
        return cache[name]

    return get


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


def caustic_plane_inputs(g: int = 8, half: float = 10.0) -> dict[str, torch.Tensor]:
    """CausticMap inputs by name: a flat refracting layer at z = 5 mm over a floor at z = 0, lit from above.

    A ``g x g`` light view over ``2 half`` mm (float64, directional light straight down, orthographic camera).
    """
    c = -half + (torch.arange(g, dtype=torch.float64) + 0.5) * 2 * half / g
    y, x = torch.meshgrid(-c, c, indexing="ij")  # row 0 at the top (largest y)
    surface = torch.stack([x, y, torch.full_like(x, 5.0)])[None]
    normal = torch.zeros_like(surface)
    normal[:, 2] = 1.0
    mask = torch.ones(1, 1, g, g, dtype=torch.bool)
    floor = torch.stack([x, y, torch.zeros_like(x)])[None]
    light = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    vp = torch.zeros(1, 4, 4, dtype=torch.float64)
    vp[0, 0, 0] = vp[0, 1, 1] = 1.0 / half
    vp[0, 2, 2] = -0.01
    vp[0, 3, 3] = 1.0
    return {"front_position": surface, "front_normal": normal, "front_mask": mask, "back_position": surface.clone(),
            "back_normal": normal.clone(), "back_mask": mask.clone(), "receiver_position": floor, "light": light,
            "intensity": torch.ones(1, 1, dtype=torch.float64), "view_proj": vp}


def loop_edge_faces(faces: list[list[int]]) -> dict[tuple[int, int], list[int]]:
    """Loop reference: every undirected edge ``(min, max)`` and the faces that hold it, in face order."""
    out: dict[tuple[int, int], list[int]] = {}
    for i, tri in enumerate(faces):
        for k in range(3):
            a, b = tri[k], tri[(k + 1) % 3]
            out.setdefault((min(a, b), max(a, b)), []).append(i)
    return out
