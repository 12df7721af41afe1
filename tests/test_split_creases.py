"""Vertex hats parted at creases (``torchsss.geometry.mesh.split_creases``) and their use by Lensch's build."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import loop_edge_faces

from torchsss.geometry import build_atlas, sphere
from torchsss.geometry.lensch import build_throughput, hat_quadrature, vertex_weights
from torchsss.geometry.mesh import CREASE_DEG, Mesh, split_creases
from torchsss.geometry.procedural import slab, torus
from torchsss.geometry.sampling import subdivision_barycentrics
from torchsss.modules import DipoleMaterial
from torchsss.modules.lensch import GlobalResponse
from torchsss.scene import Material

F64 = torch.float64


def _loop_fans(mesh: Mesh, crease_deg: float) -> set[frozenset[tuple[int, int]]]:
    """Per vertex: its corners (face, k) grouped by flood fill over the edges through it that are not creases."""
    f = mesh.faces.tolist()
    n = mesh.face_normals.double()
    cos = math.cos(math.radians(crease_deg))
    edge_faces = loop_edge_faces(f)
    fans = set()
    for vert in range(mesh.num_vertices):
        corners = {i: face.index(vert) for i, face in enumerate(f) if vert in face}
        left = set(corners)
        while left:
            todo, group = [left.pop()], set()
            while todo:
                i = todo.pop()
                group.add(i)
                for other in f[i]:
                    if other == vert:
                        continue
                    shared = edge_faces[(min(vert, other), max(vert, other))]
                    if len(shared) != 2:
                        continue
                    j = shared[0] if shared[1] == i else shared[1]
                    if j in left and float(n[i] @ n[j]) >= cos:
                        left.discard(j)
                        todo.append(j)
            fans.add(frozenset((i, corners[i]) for i in group))
    return fans


def _fans_of_split(split: Mesh) -> set[frozenset[tuple[int, int]]]:
    out: dict[int, set] = {}
    for i, face in enumerate(split.faces.tolist()):
        for k, v in enumerate(face):
            out.setdefault(v, set()).add((i, k))
    return {frozenset(c) for c in out.values()}


def _creased_torus() -> Mesh:
    """A coarse torus (dihedral angles 72° and 90°) with one vertex pulled out into a spike."""
    m = torus(10.0, 4.0, major_segments=5, minor_segments=4, dtype=F64)
    v = m.vertices.clone()
    v[0] = v[0] * 1.6
    return Mesh(v, m.faces)


@pytest.mark.parametrize("crease", [30.0, 60.0, 80.0, 100.0, 180.0])
def test_split_creases_matches_a_flood_fill_loop(crease):
    """Every copy holds exactly the corners of one fan that a loop's flood fill finds; copies sit at their origin."""
    m = _creased_torus()
    split, origin = split_creases(m, crease)
    assert _fans_of_split(split) == _loop_fans(m, crease)
    assert torch.equal(split.vertices, m.vertices[origin])
    assert torch.equal(origin[split.faces], m.faces)  # every corner points at a copy of its own vertex


def test_split_creases_closed_counts_and_invariants():
    """A slab of s x s quads: 8 corners x 3 copies, the other 8 (s - 1) rim points x 2, the inner points once; the
    copies' vertex areas sum to their origin's; a sphere has no crease and comes back as itself."""
    s = 5
    m = slab(10.0, 8.0, 1.5, segments=s, dtype=F64)
    split, origin = split_creases(m)
    assert split.num_vertices == 8 * 3 + 8 * (s - 1) * 2 + 2 * (s - 1) ** 2
    assert split.num_faces == m.num_faces and split.area == pytest.approx(m.area, rel=1e-12)
    summed = torch.zeros(m.num_vertices, dtype=F64).index_add_(0, origin, split.vertex_areas)
    torch.testing.assert_close(summed, m.vertex_areas, rtol=1e-12, atol=0.0)
    # every copy's faces are coplanar: the slab's faces are flat, so a fan never turns
    fn = split.face_normals
    for v in range(split.num_vertices):
        around = (split.faces == v).any(1)
        assert float((fn[around] - fn[around][0]).abs().max()) < 1e-12
    sp = sphere(5.0, 2)
    same, ident = split_creases(sp)
    assert same is sp and torch.equal(ident, torch.arange(sp.num_vertices))


def test_split_creases_keeps_the_vertices_gradient():
    m = slab(10.0, 8.0, 1.5, segments=2, dtype=F64)
    v = m.vertices.clone().requires_grad_(True)
    split, origin = split_creases(Mesh(v, m.faces))
    split.vertices.sum().backward()
    counts = torch.bincount(origin, minlength=m.num_vertices).to(F64)
    torch.testing.assert_close(v.grad, counts[:, None].expand(-1, 3))


@pytest.mark.parametrize("bad, err", [(0.0, ValueError), (181.0, ValueError), ("60", TypeError)])
def test_split_creases_rejects_bad_input(bad, err):
    with pytest.raises(err, match="crease_deg"):
        split_creases(slab(10.0, 8.0, 1.5, segments=2), bad)
    with pytest.raises(TypeError, match="mesh"):
        split_creases("slab", CREASE_DEG)


def test_hat_quadrature_resolves_the_peak_at_a_copy_across_a_crease():
    """The entries between two copies of one rim vertex (distance 0, different hats) take the Duffy rule with its
    apex at the shared point: within 1% of a 96^2-point rule per face, where the regular rule of a face that does
    not hold the receiver by index is far off (so the test can fail)."""
    m = slab(6.0, 6.0, 1.0, segments=3, dtype=F64)
    split, _ = split_creases(m)
    mat = DipoleMaterial(*Material.from_json("marble").tensors(F64)).requires_grad_(False)
    tp = build_throughput(split, mat, threshold=0.0)
    hq = hat_quadrature(split, tp, scale_mm=float(mat.spacing(0.01).min()))
    near_rows, near_cols = tp.rows[hq.entries], tp.cols[hq.entries]
    copy = ((split.vertices[near_rows] - split.vertices[near_cols]).norm(dim=-1) == 0) & (near_rows != near_cols)
    idx = copy.nonzero()[:, 0][:12]
    assert idx.numel() == 12
    got = torch.zeros(hq.entries.numel(), 3, dtype=F64).index_add_(
        0, hq.term_entry, hq.weight[:, None] * mat(hq.distance[:, None]))[idx]

    def rule(n, i, j):
        b = subdivision_barycentrics(n, dtype=F64)
        v, faces, area = split.vertices, split.faces, split.face_areas
        total = torch.zeros(3, dtype=F64)
        for f in (faces == i).any(1).nonzero()[:, 0].tolist():
            k = int((faces[f] == i).nonzero()[0, 0])
            pts = b @ v[faces[f]]
            total = total + (area[f] / (n * n) * b[:, k, None] * mat((pts - v[j]).norm(dim=-1)[:, None])).sum(0)
        return total

    pairs = list(zip(near_rows[idx].tolist(), near_cols[idx].tolist()))
    want = torch.stack([rule(96, i, j) for i, j in pairs])
    torch.testing.assert_close(got, want, rtol=1e-2, atol=0.0)
    coarse = torch.stack([rule(4, i, j) for i, j in pairs])
    assert float(((coarse - want) / want).abs().max()) > 0.05


def test_a_rim_only_irradiance_stays_on_the_rim_hats():
    """Irradiance on the rim alone (1 there, 0 on the large faces), projected onto the hats and reconstructed (what
    Lensch's throughput carries): split at the creases it is reproduced exactly, 0 on the large faces; the unsplit
    hats of the rim's vertices reach a hat's width into the large faces and carry it there."""
    m = slab(6.0, 6.0, 0.8, segments=4, dtype=F64)
    atlas = build_atlas(m, 256, kernel_size=3)
    rim = m.face_normals[atlas.face_id[0, 0], 2].abs() < 0.5  # texels whose face is a side of the slab
    e = (rim & atlas.valid_mask[0, 0]).to(F64).expand(1, 3, -1, -1)
    chart = atlas.chart_mask[0, 0]
    mat = DipoleMaterial(*Material.from_json("cream").tensors(F64)).requires_grad_(False)
    out = {}
    for name, mesh in (("split", split_creases(m)[0]), ("whole", m)):
        glob = GlobalResponse(vertex_weights(mesh, atlas), build_throughput(mesh, mat), mat, atlas.valid_mask)
        with torch.no_grad():
            out[name] = glob.reconstruct(glob.vertex_irradiance(e))[0, 0]
    top = chart & ~rim
    assert float(out["split"][top].abs().max()) < 1e-9
    torch.testing.assert_close(out["split"][chart & rim], e[0, 0][chart & rim], rtol=0, atol=1e-6)
    assert float(out["whole"][top].abs().max()) > 0.2  # the test can fail: unsplit hats leak


def test_lensch_build_reports_its_crease_angle_to_a_renderer_around_it():
    # a renderer around a built scene takes the crease angle it was built with, not its default
    from torchsss.pipelines.lensch import LenschRenderer, build_lensch

    m = slab(6.0, 6.0, 0.8, segments=2)
    for crease in (None, CREASE_DEG):
        built = build_lensch(m, "cream", resolution=64, crease_deg=crease)
        assert built.stats["crease_deg"] == crease
        assert built.stats["split_vertices"] == (0 if crease is None else split_creases(m)[0].num_vertices
                                                 - m.num_vertices)
        assert LenschRenderer.from_built(built).knobs["crease_deg"] == crease
