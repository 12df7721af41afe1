"""What the camera of an atlas method reads: the full mesh in view, the atlas built on a (decimated) source mesh.

The atlas methods (Lensch, icdf, hybrid) may build on the mesh decimated to the detail that the material's
scattering length shows (knob ``source_faces``, set by the planner), as the reference takes its sample sources
from a decimated mesh: the camera still sees the full mesh (its silhouette, normals and Fresnel terms), and every
visible pixel reads the atlas at its closest point on the decimated surface
(:class:`~torchsss.geometry.transfer.SurfaceLocator`). Without decimation the pixel's own atlas coordinates are
used (:func:`~torchsss.geometry.atlas_frame.camera_uv`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsss.geometry.atlas import Atlas
from torchsss.geometry.atlas_frame import camera_uv
from torchsss.geometry.camera import Camera
from torchsss.geometry.mesh import Mesh, decimate
from torchsss.geometry.transfer import SurfaceLocator, closest_point_on_triangle, closest_surface, transferred_uv

__all__ = ["AtlasView", "source_mesh"]


def source_mesh(mesh: Mesh, source_faces: object) -> Mesh:
    """``mesh`` decimated to about ``source_faces`` faces (None, or at least the mesh's count: ``mesh`` itself).

    Raises:
        ValueError: ``source_faces`` not None and not an int >= 4.
    """
    if source_faces is None:
        return mesh
    if isinstance(source_faces, bool) or not isinstance(source_faces, int) or source_faces < 4:
        raise ValueError(f"source_faces: expected an int >= 4 or None, got {source_faces!r}")
    return decimate(mesh, source_faces) if source_faces < mesh.num_faces else mesh


class AtlasView:
    """Atlas coordinates of every camera pixel, built once per (mesh, source mesh, atlas); cached per camera.

    Args:
        mesh: The mesh the camera sees (mm).
        source: The mesh the atlas was built on (``mesh`` itself, or a decimated copy of it, or a refinement of it).
        atlas: The atlas of ``source``.
        parent: :math:`(F_s,)` int64, for a ``source`` that refines ``mesh`` (each of its faces lies in one face of
            ``mesh``, :func:`~torchsss.geometry.refine.refine_creases`): that face. Texels are then lit on their own
            face's parent and pixels read their own face's children, never the face across a crease (a closest
            point at a crease may land on either side: the rim's light on the face beside it).
    """

    def __init__(self, mesh: Mesh, source: Mesh, atlas: Atlas, parent: Tensor | None = None) -> None:
        self.mesh, self.source, self.atlas = mesh, source, atlas
        self.parent = parent
        self.locator = None if (source is mesh or parent is not None) else SurfaceLocator(source)
        self._camera: Camera | None = None
        self._uv: Tensor | None = None
        self._lit: tuple[Tensor, Tensor, Tensor] | None = None
        self._points: tuple | None = None  # source_points' last camera, image size and (face, bary)
        self._csr: tuple[Tensor, Tensor, Tensor] | None = None  # the children of every face of mesh (parent given)

    def lit_texels(self) -> tuple[Tensor, Tensor, Tensor]:
        """Where the lights meet the atlas's valid texels: ``(index, position, normal)``, built once.

        Without decimation :attr:`~torchsss.geometry.atlas.Atlas.valid_texels`. On a decimated source mesh every valid
        texel (gutters too: they stand in for the surface across their chart's edge) is lit at its closest point on
        the mesh the camera sees, with that mesh's creased shading normal, and shadowed against that mesh (pass
        ``mesh`` to :func:`~torchsss.geometry.atlas_frame.irradiance_atlas`), as the reference's decimated sources
        are (:func:`~torchsss.geometry.transfer.project_samples`): the decimation sets how many texels and where the
        kernels and throughput reach, not the surface that is lit. The shared igea (268,686 faces, 30 mm skin1, 256 x
        256): Lensch on 5,874 faces 2.36% -> 1.13% against the reference, icdf on 17,139 faces 1.54% -> 0.50%.
        """
        if self.parent is not None:
            if self._lit is None:
                index, points, _ = self.atlas.valid_texels
                face = self.parent[self.atlas.face_id.reshape(-1)[index]]
                tri = self.mesh.vertices.to(points.dtype)[self.mesh.faces[face]]
                bary = closest_point_on_triangle(points, tri[:, 0], tri[:, 1], tri[:, 2]).to(points.dtype)
                position = (tri * bary[..., None]).sum(1)
                normal = torch.nn.functional.normalize(
                    (self.mesh.corner_normals().to(points.dtype)[face] * bary[..., None]).sum(1), dim=-1, eps=1e-12)
                self._lit = (index, position.contiguous(), normal.contiguous())
            return self._lit
        if self.locator is None:
            return self.atlas.valid_texels
        if self._lit is None:
            index, points, _ = self.atlas.valid_texels
            position, normal, _ = closest_surface(SurfaceLocator(self.mesh.with_dtype(points.dtype)), points)
            self._lit = (index, position.contiguous(), normal.contiguous())
        return self._lit

    @property
    def transferred(self) -> bool:
        """Whether pixels read the atlas through closest points on a decimated source mesh."""
        return self.locator is not None

    def uv(self, camera: Camera, position: Tensor, mask: Tensor, face_id: Tensor | None = None) -> Tensor:
        """:math:`(1, 2, H, W)` uv for :meth:`Atlas.sample` from the camera G-buffer of ``mesh``.

        Args:
            camera: The camera (a repeated camera reuses the last frame's uv: lights may move, the view did not).
            position: :math:`(1, 3, H, W)` G-buffer positions of ``mesh`` (mm).
            mask: :math:`(1, 1, H, W)` its coverage.
            face_id: :math:`(1, 1, H, W)` G-buffer face ids of ``mesh`` (required with ``parent``).
        """
        if self._camera is not None and camera == self._camera and self._uv is not None \
                and self._uv.shape[-2:] == position.shape[-2:]:
            return self._uv
        if self.parent is not None:
            face, bary = self.source_points(camera, face_id, position, mask)  # one search for both (cached)
            uv = position.new_zeros(1, 2, *position.shape[-2:])
            pix = (self.atlas.face_uvs.to(position.dtype)[face] * bary[..., None]).sum(1)  # (P, 2)
            uv[0, :, mask[0, 0]] = pix.T
        elif self.locator is None:
            uv, _ = camera_uv(self.mesh, self.atlas, camera)
        else:
            uv = transferred_uv(self.locator, self.atlas.face_uvs, position, mask)
        uv = self._onto_valid(uv, mask)
        self._camera, self._uv = camera, uv
        return uv

    def source_points(self, camera: Camera, face_id: Tensor, position: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """Every covered pixel's point on the source mesh: ``(face, bary)``, :math:`(P,)` int64 and :math:`(P, 3)`.

        Pixels in ``mask`` order (row-major). Without decimation or refinement the pixel's own face and its
        barycentrics there; otherwise the closest point of the source mesh (:class:`SurfaceLocator`). Cached per
        camera, as :meth:`uv`.

        Args:
            camera: The camera.
            face_id: :math:`(1, 1, H, W)` G-buffer face ids of ``mesh``.
            position: :math:`(1, 3, H, W)` G-buffer positions of ``mesh`` (mm).
            mask: :math:`(1, 1, H, W)` its coverage.
        """
        hit = self._points
        if hit is not None and hit[0] == camera and hit[1] == tuple(position.shape[-2:]):
            return hit[2], hit[3]
        pts = position[0].permute(1, 2, 0)[mask[0, 0]].detach()
        if self.parent is not None:
            face, bary = self._children(face_id, position, mask)
        elif self.locator is None:
            face = face_id[0, 0][mask[0, 0]]
            tri = self.source.vertices.detach().to(pts.dtype)[self.source.faces[face]]
            bary = closest_point_on_triangle(pts, tri[:, 0], tri[:, 1], tri[:, 2])
        else:
            located = self.locator.locate(pts)
            face, bary = located.face, located.bary.to(pts.dtype)
        self._points = (camera, tuple(position.shape[-2:]), face, bary)
        return face, bary

    def _children(self, face_id: Tensor | None, position: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """Every covered pixel's closest point among its own face's children in ``source``: ``(face, bary)``."""
        if face_id is None:
            raise ValueError("face_id: expected the camera G-buffer's face ids with a refined source, got None")
        if self._csr is None:
            order = torch.argsort(self.parent, stable=True)
            counts = torch.bincount(self.parent, minlength=self.mesh.num_faces)
            self._csr = (order, torch.cumsum(counts, 0) - counts, counts)
        order, start, counts = self._csr
        pts = position[0].permute(1, 2, 0)[mask[0, 0]].detach()
        own = face_id[0, 0][mask[0, 0]]
        k = int(counts[own].max()) if own.numel() else 1
        slot = (start[own][:, None] + torch.arange(k, device=own.device)[None, :]).clamp_max(order.numel() - 1)
        cand = order[slot]  # (P, k), padded with other faces
        real = torch.arange(k, device=own.device)[None, :] < counts[own][:, None]
        tri = self.source.vertices.detach().to(pts.dtype)[self.source.faces[cand]]  # (P, k, 3, 3)
        p = pts[:, None, :].expand(-1, k, -1)
        bary = closest_point_on_triangle(p, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]).to(pts.dtype)
        dist = (p - (tri * bary[..., None]).sum(-2)).norm(dim=-1).masked_fill(~real, float("inf"))
        best = dist.argmin(1)
        rows = torch.arange(pts.shape[0], device=pts.device)
        return cand[rows, best], bary[rows, best]

    def _onto_valid(self, uv: Tensor, mask: Tensor) -> Tensor:
        """Move the covered pixels whose bilinear footprint holds no valid texel to the nearest valid texel centre.

        A sliver face's uv triangle can cover no texel centre over most of its length, farther than the gutter
        reaches from its chart's texels: a pixel there read 0 (a black pixel on the 5 mm chicken bunny, its
        source mesh decimated to 5,780 faces). Gutters keep charts apart, so the nearest valid texel in uv is
        one of the pixel's own chart.
        """
        valid = self.atlas.valid_mask.to(uv.dtype)
        weight = self.atlas.sample(valid, uv)[0, 0]
        bad = mask[0, 0] & (weight <= 1e-6)
        if not bool(bad.any()):
            return uv
        from scipy.spatial import cKDTree

        h, w = self.atlas.shape
        rows, cols = self.atlas.valid_mask[0, 0].nonzero(as_tuple=True)
        centres = torch.stack([(cols.to(torch.float64) + 0.5) / w, 1.0 - (rows.to(torch.float64) + 0.5) / h], -1)
        query = uv[0].permute(1, 2, 0)[bad].detach().to(torch.float64).cpu().numpy()
        _, idx = cKDTree(centres.cpu().numpy()).query(query)
        out = uv.clone()
        fixed = centres[torch.as_tensor(idx, device=centres.device)].to(uv.dtype).to(uv.device)
        out[0, :, bad] = fixed.T
        return out
