"""Whole frames as ONNX graphs, and the G-buffer files that a torch-free runner renders from.

:func:`save_gbuffers` builds a renderer for a scene (``splat`` or ``lensch``), computes one frame's inputs with the
library (the light-view splat sources or the irradiance atlas, the camera G-buffer), exports the frame's graph
(:class:`SplatFrame` or :class:`LenschFrame`: the per-frame module, the atlas lookup and the exit radiance, with the
material as inputs) and writes everything into one ``.npz``: the ONNX model's bytes (``model``), the graph input
names (``input_names``) and one array per input, plus the library's own radiance of that frame (``radiance``) for
checks. ``export/ort_render.py`` renders it with numpy and onnxruntime only.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from torchsss.export.core import export_onnx
from torchsss.export.materials import InputDipoleMaterial, find_dipole_material, swap_material
from torchsss.modules.material import DipoleMaterial
from torchsss.modules.splat import SplatTranslucency
from torchsss.ops.splat import splat_radiosity, splat_window_size
from torchsss.physics.fresnel import exit_radiance

__all__ = ["FRAME_METHODS", "LenschFrame", "SplatFrame", "check_gbuffer_request", "frame_inputs", "save_gbuffers",
           "save_scene_gbuffers"]

#: Methods whose frames :func:`save_gbuffers` can write.
FRAME_METHODS = ("splat", "lensch")

_MATERIAL = ("sigma_a", "sigma_s_prime", "eta")


def _bind_copy(module: nn.Module) -> tuple[nn.Module, InputDipoleMaterial]:
    import copy

    module = copy.deepcopy(module)
    old = find_dipole_material(module)
    new = InputDipoleMaterial(old)
    swap_material(module, old, new)
    return module, new


class SplatFrame(nn.Module):
    """One splat frame: ``(radiance (1, 3, H, W), truncated (1,))`` from the light-view sources and the G-buffer.

    ``forward(src_pos (1, S, 3) mm, src_flux (1, S, 3), dst_pos (1, 3, H, W) mm, dst_mask (1, 1, H, W) bool,
    view_proj (4, 4), cos_o (1, 1, H, W), sigma_a (3,), sigma_s_prime (3,), eta (1,), r_max (1,) mm)``: the splat
    radiosity (window path, fixed ``window``), then :func:`~torchsss.physics.fresnel.exit_radiance` with the input
    eta, times the mask. ``truncated`` counts the splats whose footprint may exceed the window
    (:meth:`~torchsss.modules.SplatTranslucency.count_truncated`); :func:`save_gbuffers` picks a window that holds
    every footprint of the saved frame, so it is 0 there.

    Args:
        module: a one-material :class:`~torchsss.modules.SplatTranslucency` (its dipole material becomes inputs).
        window: odd window side in pixels.
    """

    input_names = ("src_pos", "src_flux", "dst_pos", "dst_mask", "view_proj", "cos_o", *_MATERIAL, "r_max")

    def __init__(self, module: SplatTranslucency, window: int) -> None:
        super().__init__()
        module, self._material = _bind_copy(module)
        self.splat = module
        self.window = int(window)

    def forward(self, src_pos: Tensor, src_flux: Tensor, dst_pos: Tensor, dst_mask: Tensor, view_proj: Tensor,
                cos_o: Tensor, sigma_a: Tensor, sigma_s_prime: Tensor, eta: Tensor,
                r_max: Tensor) -> tuple[Tensor, Tensor]:
        """Radiance :math:`(1, 3, H, W)` and truncated-splat counts :math:`(1,)`."""
        self._material.bind(sigma_a, sigma_s_prime, eta)
        b = splat_radiosity(src_pos, src_flux, dst_pos, dst_mask, view_proj, list(self.splat.materials), r_max,
                            method="window", window=self.window)
        radiance = exit_radiance(b, cos_o, eta) * dst_mask
        return radiance, self.splat.count_truncated(src_pos, dst_pos, view_proj, self.window, r_max=r_max)


class LenschFrame(nn.Module):
    """One Lensch frame: radiance :math:`(1, 3, H, W)` from the irradiance atlas and the camera's atlas lookups.

    ``forward(irradiance (1, 3, R, R), uv (1, 2, H, W), mask (1, 1, H, W), cos_o (1, 1, H, W), sigma_a (3,),
    sigma_s_prime (3,), eta (1,))``: :class:`~torchsss.modules.LenschTranslucency` (material as inputs; its throughput
    pattern, blending weights and atlas are those of the build), the bilinear atlas lookup of
    :meth:`~torchsss.geometry.atlas.Atlas.sample`, the exit radiance and the mask, as
    :class:`~torchsss.pipelines.LenschRenderer` renders a frame.

    Args:
        module: the renderer's :class:`~torchsss.modules.LenschTranslucency`.
        atlas: the renderer's :class:`~torchsss.geometry.atlas.Atlas`.
    """

    input_names = ("irradiance", "uv", "mask", "cos_o", *_MATERIAL)

    def __init__(self, module: nn.Module, atlas) -> None:
        super().__init__()
        module, self._material = _bind_copy(module)
        self.lensch = module
        self.atlas = atlas

    def forward(self, irradiance: Tensor, uv: Tensor, mask: Tensor, cos_o: Tensor, sigma_a: Tensor,
                sigma_s_prime: Tensor, eta: Tensor) -> Tensor:
        """Radiance :math:`(1, 3, H, W)`."""
        self._material.bind(sigma_a, sigma_s_prime, eta)
        b = self.atlas.sample(self.lensch(irradiance), uv) * mask
        return exit_radiance(b, cos_o, eta) * mask


def _material_values(material: nn.Module) -> dict[str, Tensor]:
    if not isinstance(material, DipoleMaterial):
        raise ValueError(f"material: expected the dipole profile (DipoleMaterial) for an exported frame, got "
                         f"{type(material).__name__}")
    return {"sigma_a": material.sigma_a.detach().float(), "sigma_s_prime": material.sigma_s_prime.detach().float(),
            "eta": material.eta.detach().float().reshape(-1)[:1]}


def frame_inputs(renderer, lights, camera) -> tuple[nn.Module, dict[str, Tensor], dict]:
    """The frame graph of a built renderer and its inputs for one frame: ``(module, inputs by name, meta)``.

    Raises:
        ValueError: a method other than ``splat``/``lensch``, a profile other than the dipole, per-vertex modifiers
            or ``specular`` (not in the frame graph), a float64 renderer.
    """
    from torchsss.geometry.gbuffer import camera_gbuffer, view_cosine

    method = getattr(renderer, "method", None)
    if method not in FRAME_METHODS:
        raise ValueError(f"method: expected one of {FRAME_METHODS} for --save-gbuffers, got {method!r}")
    if renderer.knobs.get("specular"):
        raise ValueError("specular: expected off for --save-gbuffers (the frame graph has no specular term), got on")
    if renderer.dtype != torch.float32:
        raise ValueError(f"dtype: expected float32 for --save-gbuffers, got {renderer.dtype}")
    mesh, eta = renderer.mesh, renderer.eta
    mat = _material_values(renderer.material)
    gbuf = camera_gbuffer(mesh, camera)
    cos_o = view_cosine(gbuf)
    meta = {"method": method, "width": camera.width, "height": camera.height}
    with torch.no_grad():
        if method == "splat":
            from torchsss.pipelines.splat import light_sources

            if any(m is not None for m in (renderer.md, renderer.mi)):
                raise ValueError("distance_scale/irradiance_scale: expected none for --save-gbuffers, got modifiers")
            srcs = [light_sources(mesh, light, renderer.knobs["grid"], eta, renderer.knobs["peel_layers"],
                                   renderer.knobs["max_stretch"], renderer.knobs["coverage"]) for light in lights]
            pos = torch.cat([s[0] for s in srcs]).unsqueeze(0)
            flux = torch.cat([s[1] for s in srcs]).unsqueeze(0)
            view_proj = camera.view_proj(dtype=torch.float32, device=mesh.vertices.device)
            r_max = renderer.module.r_max.reshape(1).float()
            window = splat_window_size(pos, view_proj, float(r_max), camera.height, camera.width)
            module = SplatFrame(renderer.module, window)
            inputs = {"src_pos": pos, "src_flux": flux, "dst_pos": gbuf.position, "dst_mask": gbuf.mask,
                      "view_proj": view_proj, "cos_o": cos_o, **mat, "r_max": r_max}
            meta.update(window=window, splats=int(pos.shape[1]))
        else:
            from torchsss.geometry.atlas_frame import camera_uv, irradiance_atlas

            e = irradiance_atlas(mesh, renderer.atlas, lights, eta,
                                 shadow_resolution=renderer.knobs["shadow_resolution"])
            uv, mask = camera_uv(mesh, renderer.atlas, camera)
            module = LenschFrame(renderer.module, renderer.atlas)
            inputs = {"irradiance": e, "uv": uv, "mask": mask.to(torch.float32), "cos_o": cos_o, **mat}
            meta.update(atlas_resolution=renderer.atlas.resolution)
    return module, inputs, meta


def save_gbuffers(path: str | os.PathLike, renderer, lights, camera, radiance: Tensor | None = None) -> Path:
    """Write one frame's G-buffers, the exported frame graph and (optionally) the library's radiance to ``path``.

    Args:
        path: the ``.npz`` to write.
        renderer: a built ``splat`` or ``lensch`` renderer (:func:`torchsss.build`).
        lights: the frame's lights.
        camera: the frame's camera.
        radiance: the library's :math:`(1, 3, H, W)` radiance of this frame, stored as ``radiance`` for checks.

    Returns:
        The path written.

    Raises:
        ValueError: see :func:`frame_inputs`.
        ImportError: the ``torchsss[export]`` extra is missing.
    """
    module, inputs, meta = frame_inputs(renderer, lights, camera)
    names = list(module.input_names)
    args = tuple(inputs[n] for n in names)
    with tempfile.TemporaryDirectory() as tmp:
        onnx_path = export_onnx(module, args, Path(tmp) / "frame.onnx", input_names=names)
        model = np.frombuffer(onnx_path.read_bytes(), dtype=np.uint8)
    arrays = {n: inputs[n].detach().cpu().numpy() for n in names}
    if radiance is not None:
        arrays["radiance"] = radiance.detach().float().cpu().numpy()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, model=model, input_names=np.array(names), meta=np.array(json.dumps(meta)), **arrays)
    return path


def save_scene_gbuffers(path: str | os.PathLike, scene, method: str, *, dtype: torch.dtype = torch.float32,
                        frames: int = 1, spp: int = 1, options: dict | None = None,
                        radiance: Tensor | None = None) -> Path:
    """:func:`save_gbuffers` for the first frame of ``render_scene(scene, method, ...)`` (``render --save-gbuffers``).

    Builds the scene's renderer again with the same knobs (``options``) and takes frame 0's lights as
    :func:`torchsss.registry.render_scene` does, so the saved frame is the one the library rendered.

    Raises:
        ValueError: ``spp`` != 1, a multi-object scene, or see :func:`frame_inputs`.
    """
    from torchsss.registry import build_scene, orbit_lights

    check_gbuffer_request(method, spp, scene)
    renderer = build_scene(scene, method, dtype=dtype, **(options or {}))
    v = renderer.mesh.vertices
    centre = tuple(float(c) for c in (v.amax(0) + v.amin(0)) / 2)
    lights = orbit_lights(scene.lights, 0, frames, centre=centre, axis=scene.camera.up)
    return save_gbuffers(path, renderer, lights, scene.camera, radiance)


def check_gbuffer_request(method: str, spp: int = 1, scene=None) -> None:
    """Refuse early what :func:`save_scene_gbuffers` cannot write (``method`` ``"auto"`` passes until planned).

    Raises:
        ValueError: a method other than splat/lensch, ``spp`` != 1, a multi-object scene.
    """
    if method not in (*FRAME_METHODS, "auto"):
        raise ValueError(f"save_gbuffers: expected --method splat or lensch, got {method!r}")
    if spp != 1:
        raise ValueError(f"save_gbuffers: expected --spp 1 (the frame graph renders one sample per pixel), got {spp}")
    if scene is not None and len(scene.objects) > 1:
        raise ValueError(f"save_gbuffers: expected a single-object scene, got {len(scene.objects)} objects")
