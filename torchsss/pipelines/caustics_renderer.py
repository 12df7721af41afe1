"""Caustics (Shah ch. 5) in the build-once / render-frames shape of every method: :class:`CausticsRenderer`."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from torchsss.geometry.camera import Camera
from torchsss.geometry.lights import Light
from torchsss.geometry.procedural import plane
from torchsss.modules.caustics import CausticMap
from torchsss.pipelines.caustics import render_caustics
from torchsss.pipelines.renderer import Renderer, RenderResult

__all__ = ["CausticsRenderer"]


class CausticsRenderer(Renderer):
    """A glass object over a diffuse receiver plane (Shah ch. 5): the receiver and the caustic module once.

    The mesh is the refractor; the translucent ``material`` is not used (pass None): the glass is described by
    the knobs. Per frame: light-view G-buffers, refraction, the Newton-Raphson receiver search, the caustic map
    and the shading of :func:`~torchsss.pipelines.caustics.render_caustics`.

    Knobs:
        ior: refractor index (a number, or 3 values for dispersion).
        absorption: :math:`K_a` in mm^-1 (a number or 3 values).
        mode: ``"double"`` (front and back refraction), ``"single"`` or ``"reflect"``.
        receiver_size_mm: side of the square receiver plane (mm), facing +z.
        receiver_center: its centre (mm).
        albedo: receiver diffuse albedo (number or RGB).
        grid: light-view (refractive grid) resolution.
        map_resolution: caustic-map size (None: ``grid``).
        environment: environment radiance at the horizon (number or RGB): seen in the refractor's reflection and
            refraction and on the background.
        environment_zenith: radiance at the zenith (+z) of the sky gradient (None: a uniform environment).
        appearance: draw the refractor with its reflection and refraction of the scene (Shah §5.2), or (False)
            with the Fresnel reflection of the environment only.
        lookup_scale: field of the receiver's camera-view lookup texture over the camera's.
        shadow_resolution: shadow-map size for the refractor's shadow.
        margin: light-camera half-extent over the refractor's bounding radius.
        normals: the refractor's vertex normals, ``"max"`` (Max's weights, default) or ``"area"``
            (:func:`~torchsss.pipelines.caustics.refractor_normals`).
    """

    method = "caustics"
    needs_material = False
    defaults: ClassVar[dict] = dict(ior=1.5, absorption=0.0, mode="double", receiver_size_mm=120.0,
                                    receiver_center=(0.0, 0.0, 0.0), albedo=0.8, grid=256, map_resolution=None,
                                    environment=(0.09, 0.1, 0.12), environment_zenith=(0.16, 0.2, 0.3),
                                    appearance=True, lookup_scale=2.0, shadow_resolution=1024, margin=1.5,
                                    normals="max")

    def _build(self) -> None:
        k = self.knobs
        size = float(k["receiver_size_mm"])
        receiver = plane(size, size, 1, dtype=self.dtype)
        receiver = dataclasses.replace(receiver, vertices=receiver.vertices + receiver.vertices.new_tensor(
            tuple(k["receiver_center"])))
        self.receiver = receiver.with_device(self.device)
        self.module = CausticMap(k["ior"], k["absorption"], mode=k["mode"]).to(self.device)

    def _render(self, lights: list[Light], camera: Camera) -> RenderResult:
        k = self.knobs
        res = render_caustics(self.mesh, self.receiver, lights, camera, resolution=k["grid"],
                              map_resolution=k["map_resolution"], albedo=k["albedo"], environment=k["environment"],
                              environment_zenith=k["environment_zenith"], appearance=k["appearance"],
                              lookup_scale=k["lookup_scale"], shadow_resolution=k["shadow_resolution"],
                              margin=k["margin"], normals=k["normals"], module=self.module)
        mask = res.receiver_mask | res.refractor_mask
        return RenderResult(res.radiance, res.direct + res.caustic, mask, dict(res.stats))
