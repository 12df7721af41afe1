"""Learned heterogeneous translucency: Shah's modifiers :math:`M_d` and :math:`M_i` (eq. 7.4) as learnable maps.

Shah ch. 7 edits a homogeneous material into a heterogeneous one with two per-point modifiers of the profile,
:math:`R'(r) = M_i\\,R_d(r\\,M_d)`: :math:`M_d > 0` scales the distance (:math:`M_d > 1` is a denser material, whose
profile is narrower) and :math:`M_i \\ge 0` scales the irradiance entering at the source. Every method takes them
(``distance_scale=`` and ``irradiance_scale=`` of the profiles; per vertex in
:class:`~torchsss.pipelines.splat.SplatRenderer`, per source in :func:`~torchsss.ops.reference_radiosity`).
:class:`HeterogeneousMaps` turns the editing around: the maps are ``nn.Parameter`` s over the vertices of a mesh,
fitted from images, with :func:`edge_smoothness` as the regulariser.

**Parameterisation.** Both maps are stored as logarithms (``log_distance_scale``, ``log_irradiance_scale``,
:math:`(V, K)` with K = 1 or C channels), so :math:`M_d = e^{\\theta_d} > 0` and :math:`M_i = e^{\\theta_i} > 0`
whatever a gradient step does, and a step changes a modifier by a relative amount (a stripe twice as dense is as
far from 1 as one half as dense). A map fixed at 1 (``learn_irradiance=False``) is a buffer, not a parameter.

**Regulariser.** :func:`edge_smoothness` is the mean over the mesh's edges of the squared difference of the log
maps at the two ends, :math:`\\frac{1}{|E|}\\sum_{(i,j)\\in E} \\lVert\\theta_i - \\theta_j\\rVert^2` (a graph
Laplacian energy): it is 0 for a constant map, does not depend on the map's mean (which the data determine), and
penalises a step across one edge as much as the same step spread over several edges would cost in total only when
the step is sharp, so it favours smooth maps without shrinking a real contrast the images support.

The module holds only registered parameters and buffers (the edge list), no Python-side state that changes during
training, so it works under :class:`torch.nn.parallel.DistributedDataParallel`.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchsss._checks import check_finite
from torchsss.geometry.mesh import Mesh

__all__ = ["HeterogeneousMaps", "edge_smoothness", "mesh_edges"]


def mesh_edges(faces: Tensor) -> Tensor:
    """The unique undirected edges of a triangle mesh.

    Args:
        faces: :math:`(F, 3)` integer vertex indices.

    Returns:
        :math:`(E, 2)` int64 vertex pairs, each with the smaller index first, sorted.

    Examples:
        >>> mesh_edges(torch.tensor([[0, 1, 2], [2, 1, 3]])).tolist()
        [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    """
    if not isinstance(faces, Tensor) or faces.dtype.is_floating_point or faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected an integer tensor of shape (F, 3), got "
                         f"{tuple(faces.shape) if isinstance(faces, Tensor) else type(faces).__name__}")
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).long()
    e = torch.sort(e, dim=1).values
    return torch.unique(e, dim=0)


def edge_smoothness(values: Tensor, edges: Tensor) -> Tensor:
    """Mean squared difference of per-vertex values across the edges.

    :math:`\\frac{1}{|E|}\\sum_{(i,j)} \\lVert v_i - v_j\\rVert^2` over the edges :math:`(i, j)`.

    Args:
        values: :math:`(V,)` or :math:`(V, K)` per-vertex values (the log maps of :class:`HeterogeneousMaps`).
        edges: :math:`(E, 2)` integer vertex pairs (:func:`mesh_edges`).

    Returns:
        A :math:`()` tensor, differentiable with respect to ``values``; 0 for a constant map (or no edges).

    Raises:
        TypeError: non-tensor or non-floating ``values``, non-integer ``edges``.
        ValueError: bad shapes, an edge index out of range.

    Examples:
        >>> e = torch.tensor([[0, 1], [1, 2]])
        >>> float(edge_smoothness(torch.tensor([0.0, 1.0, 3.0]), e))
        2.5
    """
    if not isinstance(values, Tensor) or not values.is_floating_point():
        raise TypeError(f"values: expected a floating tensor, got "
                        f"{values.dtype if isinstance(values, Tensor) else type(values).__name__}")
    if not isinstance(edges, Tensor) or edges.dtype.is_floating_point or edges.dtype == torch.bool:
        raise TypeError(f"edges: expected an integer tensor, got "
                        f"{edges.dtype if isinstance(edges, Tensor) else type(edges).__name__}")
    if values.dim() not in (1, 2):
        raise ValueError(f"values: expected shape (V,) or (V, K), got {tuple(values.shape)}")
    if edges.dim() != 2 or edges.shape[1] != 2:
        raise ValueError(f"edges: expected shape (E, 2), got {tuple(edges.shape)}")
    if edges.numel() and (int(edges.min()) < 0 or int(edges.max()) >= values.shape[0]):
        raise ValueError(f"edges: expected vertex indices in [0, {values.shape[0]}), got "
                         f"[{int(edges.min())}, {int(edges.max())}]")
    if edges.shape[0] == 0:
        return values.sum() * 0
    v = values.reshape(values.shape[0], -1)
    d = v[edges[:, 0]] - v[edges[:, 1]]
    return (d * d).sum(-1).mean()


class HeterogeneousMaps(nn.Module):
    """Per-vertex learnable modifiers :math:`M_d` (distance) and :math:`M_i` (irradiance) of Shah eq. 7.4.

    Args:
        mesh: the object whose vertices carry the maps (its faces give the regulariser's edges).
        channels: K, 1 (one map for every colour channel) or the material's C.
        distance_scale: initial :math:`M_d` (> 0): a number or :math:`(V,)` / :math:`(V, K)`; default 1.
        irradiance_scale: initial :math:`M_i` (> 0), likewise; default 1.
        learn_distance: whether :math:`M_d` is a parameter (else a fixed buffer).
        learn_irradiance: whether :math:`M_i` is a parameter (else a fixed buffer).
        dtype, device: of the maps (default float32, the mesh's device).

    Shapes:
        ``forward()`` -> ``(distance_scale, irradiance_scale)``, each :math:`(V, K)`, ready for the renderers'
        per-vertex ``distance_scale=`` / ``irradiance_scale=``.

    Examples:
        >>> from torchsss.geometry import sphere
        >>> maps = HeterogeneousMaps(sphere(5.0, 1), distance_scale=2.0, learn_irradiance=False)
        >>> md, mi = maps()
        >>> tuple(md.shape), float(md[0, 0]), float(mi[0, 0]), [n for n, _ in maps.named_parameters()]
        ((42, 1), 2.0, 1.0, ['log_distance_scale'])
        >>> float(maps.smoothness())
        0.0
    """

    def __init__(self, mesh: Mesh, channels: int = 1, *, distance_scale: float | Tensor = 1.0,
                 irradiance_scale: float | Tensor = 1.0, learn_distance: bool = True, learn_irradiance: bool = True,
                 dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> None:
        super().__init__()
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh: expected a torchsss Mesh, got {type(mesh).__name__}")
        if isinstance(channels, bool) or not isinstance(channels, int) or channels < 1:
            raise ValueError(f"channels: expected an int >= 1, got {channels!r}")
        device = mesh.vertices.device if device is None else device
        self.num_vertices = int(mesh.vertices.shape[0])
        logs = []
        for name, value in (("distance_scale", distance_scale), ("irradiance_scale", irradiance_scale)):
            t = torch.as_tensor(value, dtype=dtype).to(device)
            if t.dim() == 1 and t.shape[0] == self.num_vertices:
                t = t.unsqueeze(-1)
            if t.dim() not in (0, 2) or (t.dim() == 2 and (t.shape[0] != self.num_vertices
                                                          or t.shape[1] not in (1, channels))):
                raise ValueError(f"{name}: expected a number or shape ({self.num_vertices},) or "
                                 f"({self.num_vertices}, {channels}), got {tuple(t.shape)}")
            check_finite(t, name)
            if bool((t <= 0).any()):
                raise ValueError(f"{name}: expected values > 0 (the map is stored as its logarithm), got min "
                                 f"{float(t.min())}")
            logs.append(torch.log(t).expand(self.num_vertices, channels).clone())
        for name, log, learn in (("log_distance_scale", logs[0], learn_distance),
                                 ("log_irradiance_scale", logs[1], learn_irradiance)):
            if learn:
                setattr(self, name, nn.Parameter(log))
            else:
                self.register_buffer(name, log)
        self.register_buffer("edges", mesh_edges(mesh.faces.to(device)), persistent=False)

    def forward(self) -> tuple[Tensor, Tensor]:
        """``(M_d, M_i)``, each :math:`(V, K)`: the exponentials of the log maps."""
        return torch.exp(self.log_distance_scale), torch.exp(self.log_irradiance_scale)

    def smoothness(self) -> Tensor:
        """:func:`edge_smoothness` of both log maps (their sum): the regulariser, a :math:`()` tensor."""
        return edge_smoothness(self.log_distance_scale, self.edges) + \
            edge_smoothness(self.log_irradiance_scale, self.edges)
