"""The light view's exact face coverage (torchsss.geometry.coverage) and splat's flux correction with it."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torchsss.geometry.camera import Camera
from torchsss.geometry.coverage import MIN_COVERAGE_PX, coverage_scale, projected_face_area
from torchsss.geometry.gbuffer import layer_gbuffer, light_view
from torchsss.geometry.lights import DirectionalLight
from torchsss.geometry.objects import merge_meshes
from torchsss.geometry.procedural import plane, slab, sphere
from torchsss.pipelines.splat import light_sources

F64 = torch.float64


def test_projected_area_against_a_loop_under_perspective():
    mesh = sphere(10.0, 2, dtype=F64)
    cam = Camera(eye=(12.0, 20.0, 45.0), target=(0.0, 0.0, 0.0), fov_deg=35.0, width=80, height=60)
    vp = cam.view_proj(dtype=F64)
    got = projected_face_area(mesh, vp, (60, 80))
    for f in range(0, mesh.num_faces, 7):
        pts = []
        for i in mesh.faces[f].tolist():
            c = vp @ torch.cat([mesh.vertices[i], torch.ones(1, dtype=F64)])
            pts.append((float(c[0] / c[3]) * 40.0, float(c[1] / c[3]) * 30.0))
        (ax, ay), (bx, by), (cx, cy) = pts
        want = 0.5 * abs((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))
        assert abs(float(got[f]) - want) <= 1e-9 * max(1.0, want)
    # the front faces of a convex object tile its silhouette: their areas sum to its covered pixels, within the
    # silhouette's boundary
    fid = layer_gbuffer(mesh, vp, (60, 80)).face_id
    seen = torch.unique(fid[fid >= 0])
    covered = int((fid >= 0).sum())
    total = float(got[seen].sum())
    assert abs(total - covered) < 0.1 * covered


def _per_face(scale, fid, faces):
    return torch.zeros(faces, dtype=F64).index_add_(0, fid[fid >= 0], scale[fid >= 0])


def test_coverage_scale_makes_large_silhouette_faces_exact_and_leaves_the_rest():
    cam = Camera(eye=(0, 0, 50), target=(0, 0, 0), projection="orthographic", ortho_half_height=10.0,
                 width=64, height=64)
    vp = cam.view_proj(dtype=F64)
    big = plane(10.3, 10.3, 1, dtype=F64)  # 2 faces of 555 pixels
    fid = layer_gbuffer(big, vp, 64).face_id
    n = torch.bincount(fid[fid >= 0], minlength=2).to(F64)
    exact = projected_face_area(big, vp, (64, 64))
    scale = coverage_scale(big, fid, vp)
    # the two faces share an edge: one run, whose pixels sum to its exact area
    assert abs(float(n.sum() - exact.sum())) > 10 and abs(float(_per_face(scale, fid, 2).sum() - exact.sum())) < 1e-9
    # only the silhouette's pixels change; nothing seen stays 1
    inner = torch.zeros_like(fid[0, 0], dtype=torch.bool)
    inner[1:-1, 1:-1] = (fid[0, 0, :-2, 1:-1] >= 0) & (fid[0, 0, 2:, 1:-1] >= 0) & (fid[0, 0, 1:-1, :-2] >= 0) \
        & (fid[0, 0, 1:-1, 2:] >= 0)
    assert bool((scale[0, 0][inner] == 1).all()) and bool((scale[0, 0][fid[0, 0] < 0] == 1).all())
    # faces of about 2 pixels: the runs along the border bring the total nearer the exact area, the inside keeps 1;
    # runs smaller than min_pixels keep their pixels
    fine = plane(10.3, 10.3, 16, dtype=F64)  # 512 faces
    fid_f = layer_gbuffer(fine, vp, 64).face_id
    assert bool((projected_face_area(fine, vp, (64, 64)) < MIN_COVERAGE_PX).all())
    sf = coverage_scale(fine, fid_f, vp)
    before = abs(float((fid_f >= 0).sum()) - float(exact.sum()))
    after = abs(float((sf * (fid_f >= 0)).sum()) - float(exact.sum()))
    assert after < 0.8 * before and bool((sf[0, 0][inner] == 1).all())
    assert bool((coverage_scale(fine, fid_f, vp, min_pixels=1e9) == 1).all())
    # an occluder in front of a fifth of one face (inside it for either diagonal): that face keeps its pixels (a
    # shortfall beyond its boundary's), the other is still made exact
    square = plane(4.0, 2.6, 1, dtype=F64)
    cover = dataclasses.replace(square, vertices=square.vertices + torch.tensor([0.0, -3.5, 5.0], dtype=F64))
    both, _ = merge_meshes([big, cover])
    fid_b = layer_gbuffer(both, vp, 64).face_id
    sb = coverage_scale(both, fid_b, vp)
    nb = torch.bincount(fid_b[fid_b >= 0], minlength=both.num_faces).to(F64)
    hidden = int(torch.argmin(nb[:2] / exact))
    assert nb[hidden] < 0.9 * exact[hidden] and bool((sb[fid_b == hidden] == 1).all())
    assert abs(float(_per_face(sb, fid_b, both.num_faces)[1 - hidden]) - float(exact[1 - hidden])) < 1e-9
    # faces the caller leaves out keep their pixels
    keep = coverage_scale(big, fid, vp, faces=torch.tensor([False, False]))
    assert bool((keep == 1).all())
    with pytest.raises(ValueError, match="faces: expected a bool tensor of shape"):
        coverage_scale(big, fid, vp, faces=torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"view_proj: expected a \(4, 4\) tensor"):
        projected_face_area(big, vp[:3], (64, 64))
    with pytest.raises(ValueError, match="size: expected"):
        projected_face_area(big, vp, (64, 0))
    with pytest.raises(TypeError, match="mesh: expected a Mesh"):
        projected_face_area("plane", vp, (64, 64))
    with pytest.raises(ValueError, match="face_id: expected shape"):
        coverage_scale(big, fid[0], vp)
    with pytest.raises(ValueError, match="min_pixels"):
        coverage_scale(big, fid, vp, min_pixels=-1.0)


@pytest.mark.parametrize(("grid", "misaligned"), [(128, True), (160, True), (200, False)])
def test_splat_sources_carry_a_thin_rims_exact_flux(grid, misaligned):
    """A 1.25 mm rim lit face-on (no Fresnel loss at eta 1): its sources' flux is E times its area exactly.

    Without the correction the light view counts the rim's 3.4-5.6 pixel rows to whole pixels (the fault behind
    the rim-lit cream slab's 3.6% at the default budget).
    """
    mesh = slab(25.0, 25.0, 1.25, 16, dtype=F64)
    light = DirectionalLight((-1.0, 0.0, 0.0), (2.0, 2.0, 2.0))
    exact = 2.0 * 25.0 * 1.25
    totals = {}
    for coverage in (False, True):
        _, flux, _, _ = light_sources(mesh, light, grid, 1.0, 8, 4.0, coverage)
        totals[coverage] = float(flux[:, 0].sum())
    assert abs(totals[True] - exact) <= 1e-9 * exact
    lv = light_view(mesh, light, grid, 1.0)
    rows = 1.25 / (2.0 * lv.camera.ortho_half_height / grid)
    assert (abs(rows - round(rows)) > 0.2) == misaligned  # 4.43, 5.54 and 6.93 rows
    if misaligned:  # the uncorrected count is a whole number of rows
        assert abs(totals[False] - exact) > 0.03 * exact


def test_splat_coverage_knob():
    """``coverage`` is a bool knob of the splat renderer (typed error otherwise); False keeps each pixel's flux."""
    from torchsss.pipelines.build import build

    mesh = slab(25.0, 25.0, 1.25, 16)
    with pytest.raises(TypeError, match="coverage: expected a bool"):
        build("splat", mesh, "cream", coverage=1)
    light = DirectionalLight((-1.0, 0.0, 0.0), (2.0, 2.0, 2.0))
    lv = light_view(mesh, light, 128, 1.3)
    _, flux, _, _ = light_sources(mesh, light, 128, 1.3, 8, None, False)
    assert torch.allclose(flux.sum(0), lv.flux[0].sum((1, 2)), rtol=1e-6)
    cam = Camera(eye=(30.0, 10.0, 40.0), target=(0.0, 0.0, 0.0), width=24, height=24)
    on = build("splat", mesh, "cream", grid=128).render([light], cam)
    off = build("splat", mesh, "cream", grid=128, coverage=False).render([light], cam)
    assert on.stats["knobs"]["coverage"] is True and not torch.equal(on.radiance, off.radiance)
