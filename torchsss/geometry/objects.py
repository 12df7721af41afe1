"""Several objects in one scene (Shah 2007, 6.4.3): one merged mesh for rasterizing and shadowing, object ids.

A scene of several translucent objects is rendered from one mesh that holds all their faces (so that the
camera's depth test and the lights' visibility see every object, and the objects shadow each other) together with
a per-face object id. Image-space methods turn the G-buffers' ``face_id`` into object ids to pick each pixel's
material and to keep light from scattering from one object into another.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchsss._checks import check_shape
from torchsss.geometry.mesh import Mesh

__all__ = ["merge_meshes", "object_ids", "object_masks"]


def merge_meshes(meshes: Sequence[Mesh]) -> tuple[Mesh, Tensor]:
    """One mesh holding the faces of all ``meshes`` (vertex indices offset) and the object id of every face.

    The vertices are concatenated in order and every mesh's face indices are shifted by the number of vertices
    before it, so face ``f`` of object ``k`` keeps its vertices and winding. Per-corner texture coordinates are
    kept only when every mesh has them.

    Args:
        meshes: :math:`K \\ge 1` meshes with the same vertex dtype and device.

    Returns:
        ``(merged, face_object)``: the merged mesh (named ``"a+b+..."``) and :math:`(F,)` int64 object ids in
        :math:`[0, K)`, on the vertices' device, faces in the order of ``meshes``.

    Raises:
        TypeError: ``meshes`` is not a sequence of meshes, or their dtypes differ.
        ValueError: no mesh, or meshes on different devices.

    Examples:
        >>> from torchsss.geometry.procedural import sphere
        >>> a, b = sphere(5.0, 1), sphere(3.0, 1)
        >>> m, ids = merge_meshes([a, b])
        >>> m.num_faces == a.num_faces + b.num_faces, ids[0].item(), ids[-1].item()
        (True, 0, 1)
        >>> int(m.faces[a.num_faces:].min()) == a.num_vertices
        True
    """
    if isinstance(meshes, Mesh) or not isinstance(meshes, Sequence):
        raise TypeError(f"meshes: expected a sequence of Mesh, got {type(meshes).__name__}")
    if len(meshes) == 0:
        raise ValueError("meshes: expected at least one mesh, got none")
    for i, m in enumerate(meshes):
        if not isinstance(m, Mesh):
            raise TypeError(f"meshes[{i}]: expected a Mesh, got {type(m).__name__}")
    first = meshes[0].vertices
    for i, m in enumerate(meshes):
        if m.vertices.dtype != first.dtype:
            raise TypeError(f"meshes[{i}]: expected vertices of dtype {first.dtype} (as meshes[0]), "
                            f"got {m.vertices.dtype}")
        if m.vertices.device != first.device:
            raise ValueError(f"meshes[{i}]: expected vertices on {first.device} (as meshes[0]), "
                             f"got {m.vertices.device}")
    if len(meshes) == 1:
        m = meshes[0]
        return m, torch.zeros(m.num_faces, dtype=torch.int64, device=first.device)
    offsets = [0]
    for m in meshes[:-1]:
        offsets.append(offsets[-1] + m.num_vertices)
    vertices = torch.cat([m.vertices for m in meshes])
    faces = torch.cat([m.faces + off for m, off in zip(meshes, offsets)])
    uvs = None
    if all(m.face_uvs is not None for m in meshes):
        uvs = torch.cat([m.face_uvs for m in meshes])  # type: ignore[misc]
    face_object = torch.cat([torch.full((m.num_faces,), k, dtype=torch.int64, device=first.device)
                             for k, m in enumerate(meshes)])
    merged = Mesh(vertices, faces, face_uvs=uvs, name="+".join(m.name or f"object{k}" for k, m in enumerate(meshes)))
    return merged, face_object


def object_ids(face_id: Tensor, face_object: Tensor) -> Tensor:
    """Object-id image from a face-id image: ``face_object[face_id]``, -1 where ``face_id`` is -1 (background).

    Args:
        face_id: :math:`(B, 1, H, W)` integer face indices of the merged mesh, -1 on the background (e.g.
            ``GBuffer.face_id`` or ``LightView.face_id``).
        face_object: :math:`(F,)` integer object id of every face (from :func:`merge_meshes`).

    Returns:
        :math:`(B, 1, H, W)` int64 object ids, -1 on the background.

    Raises:
        TypeError: non-integer tensors.
        ValueError: wrong shapes, or face indices outside :math:`[-1, F)`.

    Examples:
        >>> object_ids(torch.tensor([[[[-1, 0], [2, 1]]]]), torch.tensor([0, 0, 1])).tolist()
        [[[[-1, 0], [1, 0]]]]
    """
    for name, t in (("face_id", face_id), ("face_object", face_object)):
        if not isinstance(t, Tensor) or t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
            got = t.dtype if isinstance(t, Tensor) else type(t).__name__
            raise TypeError(f"{name}: expected an integer tensor, got {got}")
    check_shape(face_id, "face_id", "B,1,H,W")
    check_shape(face_object, "face_object", "F")
    f = face_object.shape[0]
    if face_id.numel() and (int(face_id.min()) < -1 or int(face_id.max()) >= f):
        raise ValueError(f"face_id: expected values in [-1, {f}) (F = len(face_object)), got values in "
                         f"[{int(face_id.min())}, {int(face_id.max())}]")
    fo = face_object.to(device=face_id.device, dtype=torch.int64)
    bg = face_id < 0
    out = fo[face_id.clamp_min(0).long()] if f else torch.zeros_like(face_id, dtype=torch.int64)
    return torch.where(bg, torch.full_like(out, -1), out)


def object_masks(object_id: Tensor, num_objects: int) -> Tensor:
    """One boolean mask per object from an object-id image.

    Args:
        object_id: :math:`(B, 1, H, W)` integer object ids, -1 on the background.
        num_objects: :math:`K \\ge 1`.

    Returns:
        :math:`(B, K, H, W)` bool, channel ``k`` True where the pixel shows object ``k``.

    Examples:
        >>> object_masks(torch.tensor([[[[-1, 0, 1]]]]), 2)[0, :, 0].tolist()
        [[False, True, False], [False, False, True]]
    """
    if not isinstance(object_id, Tensor) or object_id.is_floating_point() or object_id.dtype == torch.bool:
        got = object_id.dtype if isinstance(object_id, Tensor) else type(object_id).__name__
        raise TypeError(f"object_id: expected an integer tensor, got {got}")
    check_shape(object_id, "object_id", "B,1,H,W")
    if isinstance(num_objects, bool) or not isinstance(num_objects, int) or num_objects < 1:
        raise ValueError(f"num_objects: expected an int >= 1, got {num_objects!r}")
    k = torch.arange(num_objects, device=object_id.device).view(1, -1, 1, 1)
    return object_id == k
