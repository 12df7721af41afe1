"""Exact visibility by ray casting (trimesh, with Embree when installed): the reference's shadows.

Not differentiable and not exportable: the reference renderer and the tests use it as ground truth for the
shadow maps and the rasterizer. Rays start at the surface point pushed off along its geometric normal by
``offset_mm`` (towards the light), so a surface never shadows itself.

CPU only by nature (trimesh, embree): the mesh is copied to the CPU once (cached on the mesh); for points on
another device they go to the CPU and the visibility comes back on every call, the one per-frame round trip of the
reference renderer on a GPU.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchsss._checks import check_shape, check_tensor
from torchsss.geometry.lights import DirectionalLight, Light, PointLight, SpotLight
from torchsss.geometry.mesh import Mesh

__all__ = ["point_inside", "ray_visibility"]


def _ray_mesh(mesh: Mesh):
    """The mesh as a CPU ``trimesh.Trimesh`` for ray casting, cached on the mesh.

    The ray casts (trimesh, embree) exist only on the CPU: a mesh on another device is copied to the CPU once per
    mesh rather than once per call, and the intersector's acceleration structure is built once.
    """
    return mesh._cached("trimesh", mesh.to_trimesh)


def ray_visibility(
    mesh: Mesh, light: Light, points: Tensor, normals: Tensor, *, offset_mm: float | None = None
) -> Tensor:
    """Visibility of a light from surface points by exact ray casting: 1 lit, 0 occluded.

    Args:
        mesh: the occluders (mm).
        light: the light.
        points: :math:`(N, 3)` surface positions in mm.
        normals: :math:`(N, 3)` unit normals (geometric or shading) used to push the ray origin off the surface.
        offset_mm: origin offset; default 1e-4 times the mesh's bounding-box diagonal.

    Returns:
        :math:`(N,)` visibility in the points' dtype.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> pts = torch.tensor([[0.0, 0.0, 10.0], [0.0, 0.0, -10.0]])
        >>> ray_visibility(sphere(10.0, 3), PointLight((0, 0, 100), 1.0), pts, pts / 10).tolist()
        [1.0, 0.0]
    """
    check_tensor(points, "points")
    dims = check_shape(points, "points", "N,3")
    check_shape(normals, "normals", "N,3", **dims)
    if dims["N"] == 0:
        return points.new_zeros(0)
    tm = _ray_mesh(mesh)
    off = 1e-4 * mesh.size_mm if offset_mm is None else float(offset_mm)
    p = points.detach().double().cpu().numpy()
    n = normals.detach().double().cpu().numpy()
    if isinstance(light, DirectionalLight):
        d = -np.broadcast_to(np.asarray(light.direction, dtype=np.float64), p.shape)
        dist = np.full(p.shape[0], math.inf)
    elif isinstance(light, (PointLight, SpotLight)):
        delta = np.asarray(light.position, dtype=np.float64) - p
        dist = np.linalg.norm(delta, axis=1)
        d = delta / np.maximum(dist, 1e-300)[:, None]
    else:
        raise TypeError(f"light: expected PointLight, DirectionalLight or SpotLight, got {type(light).__name__}")
    side = np.sign(np.einsum("ij,ij->i", n, d))
    side[side == 0] = 1.0
    origins = p + off * side[:, None] * n
    locations, ray_idx, _ = tm.ray.intersects_location(origins, np.ascontiguousarray(d), multiple_hits=False)
    blocked = np.zeros(p.shape[0], dtype=bool)
    if len(ray_idx):
        hit_dist = np.linalg.norm(locations - origins[ray_idx], axis=1)
        blocked[ray_idx] = hit_dist < dist[ray_idx] - off
    return torch.as_tensor(~blocked, device=points.device).to(points.dtype)


def point_inside(mesh: Mesh, point: tuple[float, float, float]) -> bool | None:
    """Whether ``point`` (mm) lies inside the mesh: True/False for a watertight mesh, None when undecidable.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> point_inside(sphere(10.0, 2), (0, 0, 0)), point_inside(sphere(10.0, 2), (0, 0, 50))
        (True, False)
    """
    if not mesh.is_watertight:
        return None
    return bool(_ray_mesh(mesh).contains(np.asarray([point], dtype=np.float64))[0])
