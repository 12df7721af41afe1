"""Render an animation of a moving or deforming mesh with Shah's splatting, reusing the samples between frames.

Every frame is rendered as :func:`~torchsss.pipelines.splat.render_splat` renders it (camera G-buffer,
:class:`~torchsss.modules.splat.SplatTranslucency` per light, :math:`L = F_t/\\pi\\,B`); only the splat sources
differ. With ``coherent=False`` they are the covered pixels of a fresh light view each frame, so the frames are
``render_splat``'s exactly with ``flux="facet"`` (Shah's flux, each pixel's footprint, which the coherent samples
carry too; ``render_splat`` defaults to the shading normals' convention, ``torchsss.geometry.shading_flux``). With
``coherent=True`` (Shah 2007, sec. 6.5.2) each light keeps its samples attached to the surface
(:func:`~torchsss.geometry.coherence.coherent_light_samples`, ``mode="partition"``): the positions follow the mesh
from frame to frame, while the fluxes are the current light view's, split among the kept samples, so the total flux
of every frame is the fresh light view's. The meshes must share one topology (the samples are
stored as face id and barycentrics).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Sequence

import torch
from torch import Tensor

from torchsss.geometry.camera import Camera
from torchsss.geometry.coherence import AttachedSamples, coherent_light_samples
from torchsss.geometry.environment import EnvironmentLight
from torchsss.geometry.gbuffer import camera_gbuffer, view_cosine
from torchsss.geometry.lights import Light
from torchsss.geometry.mesh import Mesh, check_mesh
from torchsss.modules.material import material_module
from torchsss.modules.splat import SplatTranslucency
from torchsss.physics.fresnel import exit_radiance
from torchsss.physics.materials import Material
from torchsss.pipelines.renderer import RenderResult
from torchsss.pipelines.splat import MAX_STRETCH, light_sources, splat_grid

__all__ = ["render_splat_sequence"]


def render_splat_sequence(
    meshes: Iterable[Mesh],
    material: Material,
    lights: Sequence[Light],
    camera: Camera,
    *,
    coherent: bool = True,
    eps: float = 0.01,
    grid: int | None = None,
    max_grid: int = 512,
    oversample: float = 2.0,
    method: str = "auto",
    dtype: torch.dtype = torch.float32,
    radius_px: float = 1.0,
    weights: str = "tent",
    max_stretch: float | None = MAX_STRETCH,
) -> Iterator[RenderResult]:
    """Render the frames of a mesh sequence with Shah's splatting, one :class:`RenderResult` per mesh (lazily).

    Args:
        meshes: the object in every frame (mm), all with the same faces.
        material: its material.
        lights: point, spot or directional lights (fixed for the sequence).
        camera: the viewing camera.
        coherent: reuse the light-view samples between frames (module docstring); False renders every frame
            exactly as :func:`~torchsss.pipelines.splat.render_splat`.
        eps: splat budget tolerance (r_max and the splat spacing).
        grid: light-view resolution (default: :func:`~torchsss.pipelines.splat.splat_grid` of each frame's mesh).
        max_grid: cap of the automatic grid.
        oversample: factor on the budget's grid.
        method: splat method of :func:`~torchsss.ops.splat.splat_radiosity`.
        dtype: float dtype of the computation.
        radius_px: ``coherent``: a light-view pixel shares its flux among the kept samples within this many
            pixels.
        weights: ``coherent``: ``"tent"`` or ``"nearest"``
            (:func:`~torchsss.geometry.coherence.coherent_light_samples`).
        max_stretch: without ``coherent``: the longest light-view footprint one splat stands for, as in
            :func:`~torchsss.pipelines.splat.render_splat` (None: one splat per pixel). Coherent frames keep one
            sample per light-view pixel (the samples they carry between frames are not cut under grazing light).

    Yields:
        A :class:`~torchsss.pipelines.reference.RenderResult` per frame: radiance :math:`(1, 3, H, W)`; ``stats``
        holds the grid, the splat count, the source flux (total over lights, per channel), and with ``coherent``
        the counts ``reused`` and ``new`` (summed over lights), and the time.

    Raises:
        TypeError: a frame that is not a Mesh, a bad ``material`` or an empty ``lights``.
        ValueError: an environment light (its sources are not light-view samples).
        ValueError: a frame whose faces differ from the first frame's (changing topology), a bad ``grid``.

    Examples:
        >>> from torchsss.geometry.lights import DirectionalLight
        >>> from torchsss.geometry.procedural import sphere
        >>> m = sphere(5.0, 2)
        >>> frames = [Mesh(m.vertices + torch.tensor([0.1 * t, 0.0, 0.0]), m.faces) for t in range(3)]
        >>> cam = Camera(eye=(0, 0, 60), target=(0, 0, 0), width=16, height=16)
        >>> out = list(render_splat_sequence(frames, Material.from_json("skin1"), [DirectionalLight((0, 0, -1), 1.0)],
        ...                                  cam, grid=24))
        >>> len(out), tuple(out[0].radiance.shape), out[2].stats["reused"] > 0
        (3, (1, 3, 16, 16), True)
    """
    if not isinstance(material, Material):
        raise TypeError(f"material: expected a Material, got {type(material).__name__}")
    lights = list(lights)
    if not lights:
        raise TypeError("lights: expected at least one light, got none")
    if any(isinstance(light, EnvironmentLight) for light in lights):
        raise ValueError("lights: expected point, spot or directional lights (light-view samples are reused), got "
                         "an environment light; render its frames with render_splat (depth-peeled every frame)")
    if grid is not None and (isinstance(grid, bool) or not isinstance(grid, int) or grid < 2):
        raise ValueError(f"grid: expected an int >= 2 or None, got {grid!r}")
    return _frames(meshes, material, lights, camera, coherent=bool(coherent), eps=eps, grid=grid,
                   max_grid=max_grid, oversample=oversample, method=method, dtype=dtype, radius_px=radius_px,
                   weights=weights, max_stretch=max_stretch)


def _frames(meshes: Iterable[Mesh], material: Material, lights: list[Light], camera: Camera, *, coherent: bool,
            eps: float, grid: int | None, max_grid: int, oversample: float, method: str, dtype: torch.dtype,
            radius_px: float, weights: str, max_stretch: float | None) -> Iterator[RenderResult]:
    profile = material_module(material, dtype=None if isinstance(material, torch.nn.Module) else dtype)
    module = SplatTranslucency(profile, eps=eps, method=method)
    faces: Tensor | None = None
    previous: list[AttachedSamples | None] = [None] * len(lights)
    for t, mesh in enumerate(meshes):
        if not isinstance(mesh, Mesh):
            raise TypeError(f"meshes: expected a Mesh in every frame, got {type(mesh).__name__} at frame {t}")
        mesh = check_mesh(mesh).with_dtype(dtype)
        if faces is None:
            faces = mesh.faces
        elif mesh.faces.shape != faces.shape or not torch.equal(mesh.faces.to(faces.device), faces):
            raise ValueError(
                f"meshes: expected the same faces (topology) in every frame, got {tuple(mesh.faces.shape)} faces "
                f"differing from the first frame's {tuple(faces.shape)} at frame {t}"
            )
        t0 = time.perf_counter()
        n = splat_grid(mesh, material, eps, max_grid, oversample) if grid is None else grid
        gbuf = camera_gbuffer(mesh, camera)
        view_proj = camera.view_proj(dtype=dtype, device=mesh.vertices.device)
        b = torch.zeros(1, 3, camera.height, camera.width, dtype=dtype, device=mesh.vertices.device)
        splats, reused, new = 0, 0, 0
        total = torch.zeros(3, dtype=dtype, device=mesh.vertices.device)
        for k, light in enumerate(lights):
            if coherent:
                previous[k], src_pos, src_flux, st = coherent_light_samples(
                    mesh, light, n, profile.eta, previous[k], radius_px=radius_px, weights=weights)
                reused, new = reused + st["reused"], new + st["new"]
            else:
                # Shah's flux, as the coherent samples carry it (their light-view pixel's footprint)
                pos, flux, _, _ = light_sources(mesh, light, n, profile.eta, 0, max_stretch, flux="facet")
                src_pos, src_flux = pos.unsqueeze(0), flux.unsqueeze(0)
            splats += int(src_pos.shape[1])
            total = total + src_flux[0].sum(0)
            with torch.no_grad():
                b = b + module(src_pos, src_flux, gbuf.position, gbuf.mask, view_proj)
        cos_o = view_cosine(gbuf)
        radiance = exit_radiance(b, cos_o, profile.eta) * gbuf.mask
        stats = {"frame": t, "grid": n, "splats": splats, "flux": [float(v) for v in total],
                 "r_max_mm": float(module.r_max), "eps": eps, "coherent": coherent,
                 "t_frame_s": time.perf_counter() - t0}
        if coherent:
            stats.update(reused=reused, new=new)
        yield RenderResult(radiance, b, gbuf.mask, stats)
