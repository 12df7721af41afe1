"""Closest points on a (coarser) mesh: carry points of a detailed surface onto a decimated copy and its atlas.

The atlas methods may build their atlas, kernels and throughput on a decimated mesh (the detail the material's
scattering length can show) while the camera sees the full mesh, as the reference does with its sample sources:
every visible point of the full mesh reads the radiosity at its closest point on the decimated surface.
:class:`SurfaceLocator` is the build-once object (a k-d tree over the coarse faces' centroids); per frame,
:meth:`SurfaceLocator.locate` finds each point's closest face and barycentrics exactly among the ``candidates``
faces with the nearest centroids, and :func:`transferred_uv` turns them into atlas coordinates for
:meth:`~torchsss.geometry.atlas.Atlas.sample`.
"""

from __future__ import annotations

import numbers
from typing import NamedTuple

import torch
from scipy.spatial import cKDTree
from torch import Tensor

from torchsss.geometry.mesh import Mesh, check_mesh
from torchsss.geometry.sampling import SurfaceSamples

__all__ = ["ClosestPoints", "SurfaceLocator", "closest_point_on_triangle", "closest_surface", "project_samples",
           "transferred_uv"]


class ClosestPoints(NamedTuple):
    """Closest points on a mesh (see :meth:`SurfaceLocator.locate`).

    Attributes:
        face: :math:`(P,)` int64 face of the closest point.
        bary: :math:`(P, 3)` its barycentrics in that face (non-negative, sum 1).
        distance: :math:`(P,)` mm from the query point.
    """

    face: Tensor
    bary: Tensor
    distance: Tensor


def closest_point_on_triangle(p: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Barycentrics :math:`(\\ldots, 3)` of the point of triangle ``abc`` closest to ``p`` (all :math:`(\\ldots, 3)`).

    Ericson's region test (Real-Time Collision Detection §5.1.5): vertex, edge or face region, so the result lies
    on the triangle (barycentrics in [0, 1]); a degenerate triangle falls back to its closest vertex or edge.

    Examples:
        >>> a, b, c = torch.tensor([0., 0, 0]), torch.tensor([1., 0, 0]), torch.tensor([0., 1, 0])
        >>> closest_point_on_triangle(torch.tensor([0.2, 0.2, 5.0]), a, b, c)
        tensor([0.6000, 0.2000, 0.2000])
        >>> closest_point_on_triangle(torch.tensor([2.0, -1.0, 0.0]), a, b, c)   # beyond vertex b
        tensor([0., 1., 0.])
    """
    ab, ac = b - a, c - a
    ap = p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    # b - p = (a - p) + ab and c - p = (a - p) + ac: the other dot products from d1, d2 and the edge products
    ab_ab, ab_ac, ac_ac = (ab * ab).sum(-1), (ab * ac).sum(-1), (ac * ac).sum(-1)
    d3, d4 = d1 - ab_ab, d2 - ab_ac
    d5, d6 = d1 - ab_ac, d2 - ac_ac
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    tiny = torch.finfo(p.dtype).tiny

    def ratio(num: Tensor, den: Tensor) -> Tensor:
        return (num / torch.where(den.abs() > tiny, den, torch.full_like(den, tiny))).clamp(0.0, 1.0)

    # (v, w) of the closest point = a + v ab + w ac, region by region; the lowest priority first, each region
    # overriding the ones after it in Ericson's order
    denom = va + vb + vc
    v, w = ratio(vb, denom), ratio(vc, denom)
    w_bc = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    r = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    v, w = torch.where(r, 1.0 - w_bc, v), torch.where(r, w_bc, w)
    r = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    v, w = torch.where(r, 0.0, v), torch.where(r, ratio(d2, d2 - d6), w)
    r = (d6 >= 0) & (d5 <= d6)
    v, w = torch.where(r, 0.0, v), torch.where(r, 1.0, w)
    r = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    v, w = torch.where(r, ratio(d1, d1 - d3), v), torch.where(r, 0.0, w)
    r = (d3 >= 0) & (d4 <= d3)
    v, w = torch.where(r, 1.0, v), torch.where(r, 0.0, w)
    r = (d1 <= 0) & (d2 <= 0)
    v, w = torch.where(r, 0.0, v), torch.where(r, 0.0, w)
    scale = (v + w).clamp_min(1.0)  # rounding in the face region: keep the point on the triangle
    v, w = v / scale, w / scale
    return torch.stack([1.0 - v - w, v, w], -1)


class SurfaceLocator:
    """Build once per (coarse) mesh: closest points on its surface for any query points.

    Args:
        mesh: The mesh to locate on (mm).
        candidates: Faces tested exactly per query: those with the nearest centroids (8; a point on a
            finely tessellated original of the mesh lies close to its surface, so its closest face is among them).

    Examples:
        >>> from torchsss.geometry import sphere
        >>> loc = SurfaceLocator(sphere(10.0, 2))
        >>> hit = loc.locate(torch.tensor([[0.0, 0.0, 12.0], [10.0, 0.0, 0.0]]))
        >>> [round(float(d), 1) for d in hit.distance]   # the icosphere's faces lie just inside the sphere
        [2.0, 0.0]
    """

    #: Query points located at a time (bounds the temporaries: about 1.3 kB a point at 8 candidates).
    block_points = 1 << 16

    def __init__(self, mesh: Mesh, candidates: int = 8) -> None:
        self.mesh = check_mesh(mesh)
        if isinstance(candidates, bool) or not isinstance(candidates, numbers.Integral) or candidates < 1:
            raise ValueError(f"candidates: expected an int >= 1, got {candidates!r}")
        self.candidates = min(int(candidates), mesh.num_faces)
        tri = mesh.vertices.detach()[mesh.faces]  # (F, 3, 3)
        self._tri = tri
        self._tree = cKDTree(tri.mean(1).double().cpu().numpy())

    def locate(self, points: Tensor) -> ClosestPoints:
        """Closest face, barycentrics and distance for :math:`(P, 3)` points (mm) -> :class:`ClosestPoints`.

        Raises:
            TypeError: ``points`` not a floating tensor.
            ValueError: ``points`` not of shape :math:`(P, 3)`.
        """
        if not isinstance(points, Tensor) or not points.is_floating_point():
            raise TypeError(f"points: expected a floating-point torch.Tensor, got {type(points).__name__}")
        if points.dim() != 2 or points.shape[-1] != 3:
            raise ValueError(f"points: expected shape (P, 3), got {tuple(points.shape)}")
        device = points.device
        if points.shape[0] == 0:
            empty = points.new_zeros(0)
            return ClosestPoints(torch.zeros(0, dtype=torch.int64, device=device), points.new_zeros(0, 3), empty)
        n = points.shape[0]
        face = torch.empty(n, dtype=torch.int64, device=device)
        bary_out = points.new_empty(n, 3)
        dist_out = points.new_empty(n)
        tris = self._tri.to(device=device, dtype=points.dtype)
        # in blocks of points: the candidates' triangles and the closest-point temporaries of every point at once
        # (about 1.3 kB a point) took 0.8 GB over the 626k texels of an atlas at 1024
        for lo in range(0, n, self.block_points):
            pts = points[lo:lo + self.block_points].detach()
            _, idx = self._tree.query(pts.double().cpu().numpy(), k=self.candidates, workers=-1)
            cand = torch.as_tensor(idx, dtype=torch.int64, device=device).reshape(pts.shape[0], -1)  # (p, K)
            tri = tris[cand]  # (p, K, 3, 3)
            p = pts[:, None, :]
            bary = closest_point_on_triangle(p, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])  # (p, K, 3)
            dist = ((bary[..., None] * tri).sum(-2) - p).norm(dim=-1)  # (p, K)
            best = dist.argmin(-1, keepdim=True)
            face[lo:lo + pts.shape[0]] = cand.gather(1, best).squeeze(1)
            bary_out[lo:lo + pts.shape[0]] = bary.gather(1, best[..., None].expand(-1, 1, 3)).squeeze(1)
            dist_out[lo:lo + pts.shape[0]] = dist.gather(1, best).squeeze(1)
        return ClosestPoints(face, bary_out, dist_out)


def transferred_uv(locator: SurfaceLocator, face_uvs: Tensor, position: Tensor, mask: Tensor) -> Tensor:
    """Atlas coordinates of the coarse mesh's closest points to camera pixels.

    Args:
        locator: :class:`SurfaceLocator` of the coarse mesh.
        face_uvs: :math:`(F, 3, 2)` per-corner uv of the coarse mesh's atlas (``Atlas.face_uvs``).
        position: :math:`(1, 3, H, W)` pixel positions (mm) on the detailed surface (a camera G-buffer).
        mask: :math:`(1, 1, H, W)` bool, covered pixels.

    Returns:
        :math:`(1, 2, H, W)` uv (0 where not covered), for :meth:`~torchsss.geometry.atlas.Atlas.sample`.
    """
    if face_uvs.dim() != 3 or face_uvs.shape[1:] != (3, 2) or face_uvs.shape[0] != locator.mesh.num_faces:
        raise ValueError(f"face_uvs: expected shape ({locator.mesh.num_faces}, 3, 2), got {tuple(face_uvs.shape)}")
    m = mask[0, 0]
    pts = position[0].permute(1, 2, 0)[m]  # (P, 3)
    hit = locator.locate(pts)
    uv = (hit.bary[..., None] * face_uvs.to(pts.dtype)[hit.face]).sum(1)  # (P, 2)
    out = position.new_zeros(position.shape[-2], position.shape[-1], 2)
    out[m] = uv
    return out.permute(2, 0, 1).unsqueeze(0)


def project_samples(locator: SurfaceLocator, samples: SurfaceSamples) -> SurfaceSamples:
    """Surface samples drawn on a decimated copy of a mesh, moved to their closest points on the mesh itself.

    Decimation is a way to fewer samples (a 268k-face scan holds one per face where the spacing asks for ~10k), not
    to another surface: each sample takes the closest point of ``locator``'s (detailed) mesh, its creased shading
    normal (:meth:`~torchsss.geometry.mesh.Mesh.corner_normals`), face and barycentrics there; its area (the
    decimated sub-triangle's) is kept. On a back-lit 25 mm apple igea scan decimated to 11,484 faces the sources'
    irradiance through the decimated normals (10-15% of them 6-10 degrees off) cost 1.53% against the full
    mesh's reference; projected, 0.58%.

    Args:
        locator: :class:`SurfaceLocator` of the detailed mesh (mm).
        samples: :math:`N` samples on a decimated copy of it (``face_id``, ``bary`` of the copy).

    Returns:
        :math:`N` samples on the detailed mesh (``face_id``, ``bary`` of it), areas unchanged.

    Examples:
        >>> from torchsss.geometry import decimate, sphere, surface_samples
        >>> fine = sphere(10.0, 4, dtype=torch.float64)
        >>> moved = project_samples(SurfaceLocator(fine), surface_samples(decimate(fine, 200), 2.0))
        >>> float((moved.position.norm(dim=-1) - 10.0).abs().max()) < 0.05  # on the fine sphere
        True
    """
    if not isinstance(samples, SurfaceSamples):
        raise TypeError(f"samples: expected SurfaceSamples, got {type(samples).__name__}")
    position, normal, hit = closest_surface(locator, samples.position)
    return SurfaceSamples(position, normal, samples.area, hit.face, hit.bary.to(samples.bary.dtype))


def closest_surface(locator: SurfaceLocator, points: Tensor) -> tuple[Tensor, Tensor, ClosestPoints]:
    """The closest points of ``locator``'s mesh to :math:`(P, 3)` points: where they lie and how they are shaded.

    Returns:
        ``(position, normal, hit)``: :math:`(P, 3)` positions on the mesh (mm) and unit creased shading normals
        there (:meth:`~torchsss.geometry.mesh.Mesh.corner_normals` interpolated), in ``points``' dtype, and the
        :class:`ClosestPoints` (face, barycentrics, distance).

    Examples:
        >>> from torchsss.geometry import sphere
        >>> pos, nrm, hit = closest_surface(SurfaceLocator(sphere(10.0, 3)), torch.tensor([[0.0, 0.0, 14.0]]))
        >>> round(float(pos[0, 2]), 1), round(float(nrm[0, 2]), 2), round(float(hit.distance[0]), 1)
        (10.0, 1.0, 4.0)
    """
    mesh = locator.mesh
    hit = locator.locate(points)
    dtype = points.dtype
    bary = hit.bary.to(dtype).unsqueeze(-1)
    position = (mesh.vertices.to(dtype)[mesh.faces[hit.face]] * bary).sum(1)
    normal = torch.nn.functional.normalize((mesh.corner_normals().to(dtype)[hit.face] * bary).sum(1), dim=-1,
                                           eps=1e-12)
    return position, normal, hit
