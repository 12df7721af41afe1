"""Dense, deterministic, area-weighted surface samples for the reference renderer.

Every face is split into :math:`n^2` congruent sub-triangles (n chosen per face so that the longest
sub-triangle edge is at most ``spacing_mm``); one sample sits at each sub-triangle's centroid and carries
its area :math:`A_f / n^2`. The samples form a near-regular lattice on every face, which keeps the quadrature
error of :math:`\\sum_i E_i A_i R_d(|x_i - x_o|)` small (no random noise, and aliasing controlled by the
spacing, see :func:`torchsss.physics.splat_alias_error`), and the areas sum to the mesh area exactly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchsss.geometry.mesh import Mesh

__all__ = ["SurfaceSamples", "faces_for_spacing", "refine_samples", "subdivision_barycentrics", "surface_samples"]


class SurfaceSamples(NamedTuple):
    """Surface samples as point sets.

    Attributes:
        position: :math:`(N, 3)` mm.
        normal: :math:`(N, 3)` unit shading normals (interpolated :meth:`~torchsss.geometry.mesh.Mesh.corner_normals`).
        area: :math:`(N,)` mm^2, summing to the mesh area.
        face_id: :math:`(N,)` int64.
        bary: :math:`(N, 3)` barycentrics within the face.
    """

    position: Tensor
    normal: Tensor
    area: Tensor
    face_id: Tensor
    bary: Tensor


def faces_for_spacing(area_mm2: float, spacing_mm: float) -> int:
    """Faces that carry samples at ``spacing_mm`` on a surface of ``area_mm2``: :math:`8A/h^2`, at least 500.

    :func:`surface_samples` puts :math:`\\lceil l / h \\rceil^2` samples on a face with longest edge :math:`l`, at
    least one, so a finely tessellated scan has far more samples than its spacing asks for; decimated to this many
    faces it has about as few as the spacing allows. A decimated mesh's faces are irregular, so fewer, larger faces
    do not mean fewer samples: on a decimated sphere the count is least (1.15 samples per face) at :math:`8A/h^2`
    faces (edges about :math:`0.54 h`) and 10% and 20% higher at 6 and 4 :math:`A/h^2`.

    Examples:
        >>> faces_for_spacing(1000.0, 1.0)
        8000
    """
    return max(500, int(8.0 * area_mm2 / (spacing_mm * spacing_mm)))


def subdivision_barycentrics(n: int, *, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """Barycentric centroids of the :math:`n^2` sub-triangles of a regular n-fold subdivision.

    Returns:
        :math:`(n^2, 3)` barycentric coordinates (each row sums to 1).

    Examples:
        >>> [round(v, 6) for v in subdivision_barycentrics(1)[0].tolist()]
        [0.333333, 0.333333, 0.333333]
        >>> tuple(subdivision_barycentrics(4).shape)
        (16, 3)
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n: expected a positive int, got {n!r}")
    i, j = torch.meshgrid(torch.arange(n, dtype=dtype, device=device), torch.arange(n, dtype=dtype, device=device),
                          indexing="ij")
    up = (i + j) <= n - 1
    down = (i + j) <= n - 2
    a = torch.cat([(i[up] + 1.0 / 3.0), (i[down] + 2.0 / 3.0)]) / n
    b = torch.cat([(j[up] + 1.0 / 3.0), (j[down] + 2.0 / 3.0)]) / n
    return torch.stack([1.0 - a - b, a, b], dim=-1)


def surface_samples(mesh: Mesh, spacing_mm: float, *, max_samples: int = 4_000_000) -> SurfaceSamples:
    """Area-weighted samples with at most ``spacing_mm`` between neighbours on every face.

    Args:
        mesh: the surface (mm).
        spacing_mm: the longest sub-triangle edge (> 0).
        max_samples: guard against a spacing that would need more samples than this (ValueError).

    Returns:
        :class:`SurfaceSamples` in the mesh's dtype and device.

    Examples:
        >>> from torchsss.geometry.procedural import plane
        >>> s = surface_samples(plane(10.0, 10.0, 10), 1.5)  # 200 faces with 1.41 mm edges: 1 sample each
        >>> s.position.shape[0], round(s.area.sum().item(), 6)
        (200, 100.0)
    """
    if not (isinstance(spacing_mm, (int, float)) and math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm: expected a finite number > 0, got {spacing_mm!r}")
    n_per_face = _folds(mesh, spacing_mm)
    total = int((n_per_face * n_per_face).sum())
    if total > max_samples:
        raise ValueError(
            f"spacing_mm: {spacing_mm} mm needs {total} samples on this mesh, more than max_samples={max_samples}; "
            "raise the spacing or max_samples"
        )
    return _subdivide(mesh, torch.arange(mesh.num_faces, device=mesh.faces.device), n_per_face)


def refine_samples(mesh: Mesh, samples: SurfaceSamples, faces: Tensor, spacing_mm: float,
                   factor: int) -> tuple[SurfaceSamples, Tensor]:
    """The samples of ``surface_samples(mesh, spacing_mm)`` with those of ``faces`` subdivided ``factor`` times finer.

    A face that held :math:`n^2` samples holds :math:`(n k)^2` (``factor`` :math:`k`): the same subdivision at
    :math:`k` times the resolution, so the areas still sum to the mesh area exactly. The refined faces' samples
    come last.

    Args:
        mesh: the surface ``samples`` were drawn on (mm).
        samples: :math:`N` samples of :func:`surface_samples` at ``spacing_mm``.
        faces: :math:`(F,)` bool, the faces to refine.
        spacing_mm: the spacing ``samples`` were drawn at (> 0).
        factor: the refinement :math:`k \\ge 1` (1: the samples as they are).

    Returns:
        ``(refined, kept)``: the new :class:`SurfaceSamples` and the :math:`(N,)` bool mask of the input samples
        it keeps (first, in their order).

    Examples:
        >>> from torchsss.geometry.procedural import plane
        >>> m = plane(10.0, 10.0, 10)
        >>> s = surface_samples(m, 1.5)
        >>> r, kept = refine_samples(m, s, torch.arange(200) < 2, 1.5, 3)
        >>> r.position.shape[0], int(kept.sum()), round(r.area.sum().item(), 6)
        (216, 198, 100.0)
    """
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise ValueError(f"factor: expected an int >= 1, got {factor!r}")
    if not (isinstance(faces, Tensor) and faces.dtype == torch.bool and faces.shape == (mesh.num_faces,)):
        got = f"{tuple(faces.shape)} {faces.dtype}" if isinstance(faces, Tensor) else type(faces).__name__
        raise ValueError(f"faces: expected a ({mesh.num_faces},) bool tensor, got {got}")
    if not (isinstance(spacing_mm, (int, float)) and math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm: expected a finite number > 0, got {spacing_mm!r}")
    kept = ~faces[samples.face_id]
    if factor == 1 or not bool(faces.any()):
        return samples, torch.ones_like(kept)
    ids = torch.nonzero(faces).squeeze(1)
    fine = _subdivide(mesh, ids, _folds(mesh, spacing_mm)[ids] * factor)
    return SurfaceSamples(*(torch.cat([a[kept], b]) for a, b in zip(samples, fine))), kept


def _folds(mesh: Mesh, spacing_mm: float) -> Tensor:
    """Per face, the subdivision :math:`n = \\lceil l / h \\rceil` (at least 1) of :func:`surface_samples`."""
    tri = mesh.triangles()
    edges = torch.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], dim=1)
    longest = edges.norm(dim=-1).amax(dim=1)
    return torch.ceil(longest / spacing_mm).clamp_min(1).long()


def _subdivide(mesh: Mesh, face_ids: Tensor, n_per_face: Tensor) -> SurfaceSamples:
    """Samples at the sub-triangle centroids of faces ``face_ids``, each split :math:`n^2` ways (``n_per_face``)."""
    tri = mesh.triangles()[face_ids]
    cn = mesh.corner_normals()
    pos, nrm, area, fid, bary = [], [], [], [], []
    for n in torch.unique(n_per_face).tolist():
        sel = torch.nonzero(n_per_face == n).squeeze(1)
        faces = face_ids[sel]
        b = subdivision_barycentrics(n, dtype=tri.dtype, device=tri.device)  # (S, 3)
        corners = tri[sel]  # (f, 3, 3)
        pos.append(torch.einsum("sk,fkc->fsc", b, corners).reshape(-1, 3))
        ncorners = cn[faces]
        nrm.append(F.normalize(torch.einsum("sk,fkc->fsc", b, ncorners), dim=-1, eps=1e-12).reshape(-1, 3))
        area.append((mesh.face_areas[faces] / (n * n)).repeat_interleave(b.shape[0]))
        fid.append(faces.repeat_interleave(b.shape[0]))
        bary.append(b.repeat(faces.shape[0], 1))
    if not pos:
        z = tri.new_zeros(0, 3)
        return SurfaceSamples(z, z.clone(), tri.new_zeros(0), face_ids.new_zeros(0), z.clone())
    return SurfaceSamples(torch.cat(pos), torch.cat(nrm), torch.cat(area), torch.cat(fid), torch.cat(bary))
