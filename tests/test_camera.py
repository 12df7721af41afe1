"""Cameras: look_at, projections, pixel centres, primary rays and the scene-JSON camera block."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torchsss.geometry.camera import (
    Camera,
    look_at,
    orthographic,
    perspective,
    pixel_centers_ndc,
    transform_points,
)

F64 = torch.float64


def _project(cam: Camera, points: torch.Tensor) -> torch.Tensor:
    """World points (N, 3) -> continuous pixel coordinates (N, 2) as (column, row), pixel centres at i + 0.5."""
    clip = transform_points(points, cam.view_proj(dtype=F64))[0]
    ndc = clip[:, :3] / clip[:, 3:]
    col = (ndc[:, 0] + 1.0) * 0.5 * cam.width
    row = (1.0 - ndc[:, 1]) * 0.5 * cam.height
    return torch.stack([col, row], dim=1)


# -- look_at --------------------------------------------------------------------------------------------------------
def test_look_at_maps_eye_to_origin_and_target_onto_minus_z(dtype):
    eye = torch.tensor([30.0, -20.0, 50.0], dtype=dtype)
    target = torch.tensor([1.0, 2.0, -3.0], dtype=dtype)
    v = look_at(eye, target, torch.tensor([0.0, 1.0, 0.0], dtype=dtype))
    assert v.shape == (4, 4) and v.dtype == dtype
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    pts = transform_points(torch.stack([eye, target]), v)[0]
    torch.testing.assert_close(pts[0], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype), atol=tol, rtol=0)
    dist = torch.linalg.vector_norm(target - eye)
    torch.testing.assert_close(pts[1, :3], torch.stack([dist * 0, dist * 0, -dist]), atol=tol * 100, rtol=0)
    # a rigid transform: orthonormal rotation with det +1, last row (0, 0, 0, 1)
    rot = v[:3, :3].double()
    torch.testing.assert_close(rot @ rot.T, torch.eye(3, dtype=F64), atol=1e-6, rtol=0)
    assert math.isclose(torch.linalg.det(rot).item(), 1.0, abs_tol=1e-6)
    assert v[3].tolist() == [0.0, 0.0, 0.0, 1.0]


def test_look_at_up_vector_maps_to_plus_y():
    v = look_at([0.0, 0.0, 10.0], [0.0, 0.0, 0.0], [0.3, 2.0, 0.0])  # up need not be unit or orthogonal
    up_view = v[:3, :3].double() @ torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    assert up_view[1] > 0.9 and abs(up_view[2]) < 1e-6
    right = v[:3, :3].double() @ torch.tensor([1.0, 0.0, 0.0], dtype=F64)  # world +x is to the right
    assert right[0] > 0.9


def test_look_at_batched_matches_single():
    eyes = torch.tensor([[0.0, 0.0, 5.0], [3.0, 4.0, 5.0]], dtype=F64)
    target = torch.zeros(3, dtype=F64)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    vb = look_at(eyes, target, up)
    assert vb.shape == (2, 4, 4)
    for i in range(2):
        torch.testing.assert_close(vb[i], look_at(eyes[i], target, up), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("eye", "target", "up", "word"),
    [
        ([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [0.0, 1.0, 0.0], "eye"),
        ([0.0, 5.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], "up"),
        ([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 0.0, -2.0], "up"),
        ([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], "up"),
    ],
)
def test_look_at_degenerate_raises(eye, target, up, word):
    with pytest.raises(ValueError, match=word):
        look_at(eye, target, up)


def test_look_at_bad_shape_and_type():
    with pytest.raises(ValueError, match="eye"):
        look_at([0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    with pytest.raises(TypeError, match="target"):
        look_at([0.0, 0.0, 1.0], "origin", [0.0, 1.0, 0.0])


# -- projections ----------------------------------------------------------------------------------------------------
def test_perspective_maps_near_far_to_ndc_minus_one_plus_one(dtype):
    near, far = 2.5, 700.0
    p = perspective(35.0, 1.5, near, far, dtype=dtype)
    assert p.shape == (4, 4) and p.dtype == dtype
    pts = torch.tensor([[0.0, 0.0, -near, 1.0], [0.0, 0.0, -far, 1.0], [1.0, 1.0, -10.0, 1.0]], dtype=dtype)
    clip = pts @ p.T
    ndc_z = clip[:, 2] / clip[:, 3]
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert abs(ndc_z[0].item() + 1.0) < tol and abs(ndc_z[1].item() - 1.0) < tol
    assert torch.allclose(clip[:, 3], -pts[:, 2])  # w = distance in front of the camera


def test_perspective_vertical_fov_and_aspect():
    fov, aspect = 50.0, 2.0
    p = perspective(fov, aspect, 1.0, 100.0, dtype=F64)
    t = math.tan(math.radians(fov / 2))
    # a point on the top edge of the frustum at depth 10, and one on the right edge
    pts = torch.tensor([[0.0, 10.0 * t, -10.0, 1.0], [10.0 * t * aspect, 0.0, -10.0, 1.0]], dtype=F64)
    clip = pts @ p.T
    ndc = clip[:, :2] / clip[:, 3:]
    torch.testing.assert_close(ndc, torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=F64), rtol=0, atol=1e-12)


def test_orthographic_view_volume(dtype):
    h, a, n, f = 20.0, 1.25, -5.0, 80.0
    p = orthographic(h, a, n, f, dtype=dtype)
    corners = torch.tensor([[-h * a, -h, -n, 1.0], [h * a, h, -f, 1.0]], dtype=dtype)
    clip = corners @ p.T
    torch.testing.assert_close(clip, torch.tensor([[-1.0, -1.0, -1.0, 1.0], [1.0, 1.0, 1.0, 1.0]], dtype=dtype))


@pytest.mark.parametrize(
    ("args", "word", "exc"),
    [
        ((0.0, 1.0, 1.0, 10.0), "fov_y_deg", ValueError),
        ((180.0, 1.0, 1.0, 10.0), "fov_y_deg", ValueError),
        ((40.0, -1.0, 1.0, 10.0), "aspect", ValueError),
        ((40.0, 1.0, 0.0, 10.0), "near", ValueError),
        ((40.0, 1.0, 10.0, 10.0), "far", ValueError),
        ((40.0, 1.0, 1.0, float("nan")), "far", ValueError),
        (("40", 1.0, 1.0, 10.0), "fov_y_deg", TypeError),
    ],
)
def test_perspective_bad_arguments(args, word, exc):
    with pytest.raises(exc, match=word):
        perspective(*args)


def test_orthographic_bad_arguments():
    with pytest.raises(ValueError, match="half_height"):
        orthographic(0.0, 1.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="far"):
        orthographic(1.0, 1.0, 5.0, 1.0)


# -- transform_points / pixel centres -------------------------------------------------------------------------------
def test_transform_points_shapes_and_batching():
    pts = torch.randn(5, 3, dtype=F64)
    m = torch.randn(2, 4, 4, dtype=F64)
    out = transform_points(pts, m)
    assert out.shape == (2, 5, 4)
    for i in range(2):
        ref = torch.cat([pts, torch.ones(5, 1, dtype=F64)], 1) @ m[i].T
        torch.testing.assert_close(out[i], ref)
    assert transform_points(pts[None].expand(2, 5, 3), m[0]).shape == (2, 5, 4)
    with pytest.raises(ValueError, match="points"):
        transform_points(torch.zeros(5, 4), torch.eye(4))
    with pytest.raises(ValueError, match="matrix"):
        transform_points(torch.zeros(5, 3), torch.eye(3))
    with pytest.raises(ValueError, match="batch"):
        transform_points(torch.zeros(3, 5, 3), torch.zeros(2, 4, 4))
    with pytest.raises(TypeError, match="points"):
        transform_points(torch.zeros(5, 3, dtype=torch.int64), torch.eye(4))


def test_pixel_centers_ndc_convention(device):
    h, w = 3, 4
    g = pixel_centers_ndc(h, w, dtype=F64, device=device)
    assert g.shape == (2, h, w) and g.device.type == device.type
    # columns: x = 2 (c + 0.5) / W - 1; rows: y = 1 - 2 (r + 0.5) / H, row 0 at the top
    assert g[0, 0].tolist() == [-0.75, -0.25, 0.25, 0.75]
    torch.testing.assert_close(g[1, :, 0].cpu(), torch.tensor([2 / 3, 0.0, -2 / 3], dtype=F64))
    with pytest.raises(ValueError, match="height"):
        pixel_centers_ndc(0, 4)
    with pytest.raises(TypeError, match="width"):
        pixel_centers_ndc(4, 2.0)


# -- Camera ---------------------------------------------------------------------------------------------------------
def test_centre_pixel_of_odd_image_looks_along_view_direction():
    cam = Camera(eye=(10.0, 20.0, 30.0), target=(-5.0, 2.0, 1.0), fov_deg=33.0, width=31, height=17)
    o, d = cam.rays(dtype=F64)
    assert o.shape == (1, 3, 17, 31) and d.shape == (1, 3, 17, 31)
    view_dir = torch.tensor(cam.target, dtype=F64) - torch.tensor(cam.eye, dtype=F64)
    view_dir = view_dir / view_dir.norm()
    torch.testing.assert_close(d[0, :, 8, 15], view_dir, rtol=0, atol=1e-12)
    torch.testing.assert_close(d.norm(dim=1), torch.ones(1, 17, 31, dtype=F64), rtol=0, atol=1e-12)
    # the target projects onto the centre of the image
    torch.testing.assert_close(_project(cam, torch.tensor([cam.target], dtype=F64))[0],
                               torch.tensor([15.5, 8.5], dtype=F64), rtol=0, atol=1e-9)


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_rays_pass_through_projected_pixel_centres(projection):
    cam = Camera(eye=(40.0, 25.0, 120.0), target=(0.0, 5.0, 0.0), up=(0.1, 1.0, 0.0), fov_deg=47.0, width=13,
                 height=9, near=2.0, far=500.0, projection=projection, ortho_half_height=30.0)
    o, d = cam.rays(dtype=F64)
    cols, rows = torch.meshgrid(torch.arange(13, dtype=F64), torch.arange(9, dtype=F64), indexing="xy")
    expect = torch.stack([cols + 0.5, rows + 0.5], dim=-1).reshape(-1, 2)
    for t in (5.0, 80.0, 300.0):
        pts = (o + t * d)[0].permute(1, 2, 0).reshape(-1, 3)
        torch.testing.assert_close(_project(cam, pts), expect, rtol=0, atol=1e-9)
    if projection == "orthographic":  # parallel rays along the view direction, starting on the near plane
        fwd = torch.tensor(cam.target, dtype=F64) - torch.tensor(cam.eye, dtype=F64)
        fwd = fwd / fwd.norm()
        torch.testing.assert_close(d[0, :, 4, 6], fwd, rtol=0, atol=1e-12)
        depth = ((o[0].permute(1, 2, 0) - torch.tensor(cam.eye, dtype=F64)) @ fwd)
        torch.testing.assert_close(depth, torch.full((9, 13), cam.near, dtype=F64), rtol=0, atol=1e-9)
    else:
        torch.testing.assert_close(o[0, :, 3, 7], torch.tensor(cam.eye, dtype=F64), rtol=0, atol=0)


def test_row_zero_is_at_the_top():
    cam = Camera(eye=(0.0, 0.0, 100.0), target=(0.0, 0.0, 0.0), width=64, height=48)
    above = _project(cam, torch.tensor([[0.0, 20.0, 0.0], [0.0, -20.0, 0.0], [20.0, 0.0, 0.0]], dtype=F64))
    assert above[0, 1] < 24.0 - 5 and above[1, 1] > 24.0 + 5  # above the target: small row index
    assert above[2, 0] > 32.0 + 5  # world +x (camera right): large column index
    _, d = cam.rays(dtype=F64)
    assert d[0, 1, 0, 32] > 0 > d[0, 1, 47, 32]  # top row looks up, bottom row looks down
    assert d[0, 0, 24, 0] < 0 < d[0, 0, 24, 63]


def test_camera_matrices_consistent(dtype):
    cam = Camera(eye=(1.0, 2.0, 3.0), target=(0.0, 0.0, 0.0), width=20, height=10, fov_deg=60.0)
    vp = cam.view_proj(dtype=dtype)
    assert vp.dtype == dtype and vp.shape == (4, 4)
    ref = cam.projection_matrix(dtype=F64) @ cam.view_matrix(dtype=F64)
    torch.testing.assert_close(vp.double(), ref, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(cam.projection_matrix(dtype=F64), perspective(60.0, 2.0, 1.0, 1000.0, dtype=F64))
    assert cam.resolution == (10, 20)


def test_from_dict_round_trip_and_json():
    block = {"eye": [0, 50, 200], "target": [0, 10, 0], "up": [0, 1, 0], "fov_deg": 35, "width": 320,
             "height": 240, "near": 5, "far": 900, "projection": "orthographic", "ortho_half_height": 60}
    cam = Camera.from_dict(block)
    assert cam.eye == (0.0, 50.0, 200.0) and cam.width == 320 and cam.projection == "orthographic"
    assert isinstance(cam.fov_deg, float)
    again = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    assert again == cam
    minimal = Camera.from_dict({"eye": [0, 0, 1], "target": [0, 0, 0]})
    assert (minimal.up, minimal.fov_deg, minimal.width, minimal.height) == ((0.0, 1.0, 0.0), 40.0, 256, 256)
    assert (minimal.near, minimal.far, minimal.projection) == (1.0, 1000.0, "perspective")


@pytest.mark.parametrize(
    ("patch", "exc", "word"),
    [
        ({"fov": 40}, ValueError, "fov"),  # unknown key: the message lists the allowed keys
        ({"width": 0}, ValueError, "width"),
        ({"width": 64.0}, TypeError, "width"),
        ({"height": True}, TypeError, "height"),
        ({"fov_deg": 180}, ValueError, "fov_deg"),
        ({"fov_deg": "wide"}, TypeError, "fov_deg"),
        ({"near": 10, "far": 5}, ValueError, "far"),
        ({"near": 0}, ValueError, "near"),
        ({"eye": [0, 0]}, ValueError, "eye"),
        ({"eye": "0 0 1"}, TypeError, "eye"),
        ({"target": [0, 0, float("inf")]}, ValueError, "target"),
        ({"projection": "fisheye"}, ValueError, "projection"),
        ({"ortho_half_height": -1}, ValueError, "ortho_half_height"),
        ({"target": [0, 0, 100]}, ValueError, "eye"),  # eye == target
        ({"up": [0, 0, 5]}, ValueError, "up"),  # parallel to the view direction
    ],
)
def test_from_dict_bad_input(patch, exc, word):
    block = {"eye": [0, 0, 100], "target": [0, 0, 0], **patch}
    with pytest.raises(exc, match=word) as info:
        Camera.from_dict(block)
    if "fov" in patch:
        assert "fov_deg" in str(info.value) and "ortho_half_height" in str(info.value)


def test_from_dict_missing_and_not_a_mapping():
    with pytest.raises(ValueError, match="target"):
        Camera.from_dict({"eye": [0, 0, 1]})
    with pytest.raises(TypeError, match="camera"):
        Camera.from_dict([("eye", [0, 0, 1])])


def test_orthographic_camera_allows_near_behind_eye():
    cam = Camera(eye=(0.0, 0.0, 10.0), target=(0.0, 0.0, 0.0), projection="orthographic", near=-10.0, far=10.0)
    p = cam.projection_matrix(dtype=F64)
    clip = p @ torch.tensor([0.0, 0.0, 10.0, 1.0], dtype=F64)  # 10 mm behind the eye: on the near plane
    assert abs(clip[2].item() + 1.0) < 1e-12
