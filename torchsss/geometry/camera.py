"""Pinhole and orthographic cameras: view and projection matrices, point transforms and primary rays.

Conventions (OpenGL style, the same as the rasterizer in :mod:`torchsss.geometry.raster`):

* World space is right-handed, in millimetres. The camera sits at ``eye`` and looks down its own :math:`-z`
  axis; its :math:`+y` axis is the projection of ``up`` and :math:`+x = -z \\times y` points to the right.
* Clip space is homogeneous; after the perspective divide NDC :math:`x, y, z \\in [-1, 1]`, NDC :math:`y` points
  *up* and NDC :math:`z = -1` on the near plane, :math:`+1` on the far plane.
* Images are :math:`(B, C, H, W)` with row 0 at the *top* (NDC :math:`y = +1`); pixel (row :math:`r`, column
  :math:`c`) has its centre at :math:`(c + 0.5, r + 0.5)`, i.e. NDC
  :math:`x = 2 (c + 0.5) / W - 1`, :math:`y = 1 - 2 (r + 0.5) / H`.
* ``fov_deg`` is the *vertical* field of view; the horizontal extent follows from the aspect ratio
  :math:`W / H` (square pixels).

Matrices act on column vectors (``clip = P @ V @ [x, y, z, 1]``); :func:`transform_points` applies them to row
point sets.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from torchsss._checks import as_float_tensor, check_broadcastable, check_tensor, is_tracing

__all__ = ["Camera", "look_at", "orthographic", "perspective", "pixel_centers_ndc", "transform_points"]

_PROJECTIONS = ("perspective", "orthographic")


# -- matrices -------------------------------------------------------------------------------------------------------
def _check_vec3(x: Tensor, name: str) -> None:
    if x.dim() == 0 or x.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (..., 3), got {tuple(x.shape)}")


def look_at(eye: Tensor | Sequence[float], target: Tensor | Sequence[float],
            up: Tensor | Sequence[float]) -> Tensor:
    """World-to-view matrix of a camera at ``eye`` looking at ``target`` (OpenGL ``gluLookAt``).

    The view frame has its origin at ``eye``; ``target`` lies on its :math:`-z` axis and ``up`` projects onto
    its :math:`+y` axis. The rows of the rotation are :math:`s = \\hat f \\times \\hat u` (right), :math:`u' = s
    \\times \\hat f` (up) and :math:`-\\hat f` (back), with :math:`\\hat f` the unit view direction.

    Args:
        eye: camera position, :math:`(..., 3)` (tensor or sequence of numbers).
        target: point looked at, :math:`(..., 3)`, broadcastable with ``eye``.
        up: approximate up direction, :math:`(..., 3)`, broadcastable; must not be parallel to the view direction.

    Returns:
        :math:`(..., 4, 4)` rigid transform, dtype promoted from the inputs (float32 for Python numbers).

    Raises:
        TypeError: a non-numeric input.
        ValueError: a last dimension other than 3, ``eye == target``, or ``up`` parallel to ``target - eye``.

    Examples:
        >>> v = look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        >>> v[:3, 3].tolist()  # the world origin is 5 mm in front of the camera, on its -z axis
        [0.0, 0.0, -5.0]
    """
    eye_t = as_float_tensor(eye, "eye")
    target_t = as_float_tensor(target, "target", like=eye_t)
    up_t = as_float_tensor(up, "up", like=eye_t)
    for t, n in ((eye_t, "eye"), (target_t, "target"), (up_t, "up")):
        _check_vec3(t, n)
    shape = check_broadcastable(eye=eye_t, target=target_t, up=up_t)
    dtype = torch.promote_types(torch.promote_types(eye_t.dtype, target_t.dtype), up_t.dtype)
    eye_t, target_t, up_t = (t.to(dtype).expand(shape) for t in (eye_t, target_t, up_t))

    fwd = target_t - eye_t
    fwd_len = torch.linalg.vector_norm(fwd, dim=-1, keepdim=True)
    up_len = torch.linalg.vector_norm(up_t, dim=-1, keepdim=True)
    if not is_tracing():
        if bool((fwd_len == 0).any()) or not bool(torch.isfinite(fwd_len).all()):
            raise ValueError(f"eye, target: expected distinct finite points, got eye {eye_t.tolist()} "
                             f"and target {target_t.tolist()}")
        if bool((up_len == 0).any()) or not bool(torch.isfinite(up_len).all()):
            raise ValueError(f"up: expected a finite non-zero vector, got {up_t.tolist()}")
    f = fwd / fwd_len
    s = torch.linalg.cross(f, up_t / up_len)
    s_len = torch.linalg.vector_norm(s, dim=-1, keepdim=True)
    if not is_tracing() and bool((s_len <= 1e3 * torch.finfo(dtype).eps).any()):
        raise ValueError(f"up: expected a vector not parallel to the view direction target - eye, got up "
                         f"{up_t.tolist()} and direction {fwd.tolist()}")
    s = s / s_len
    u = torch.linalg.cross(s, f)
    rot = torch.stack([s, u, -f], dim=-2)  # (..., 3, 3)
    trans = -(rot @ eye_t.unsqueeze(-1))  # (..., 3, 1)
    top = torch.cat([rot, trans], dim=-1)
    bottom = torch.zeros((*shape[:-1], 1, 4), dtype=dtype, device=eye_t.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def _check_real(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name}: expected a real number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    return v


def _check_near_far(near: object, far: object, positive_near: bool) -> tuple[float, float]:
    n = _check_real(near, "near")
    f = _check_real(far, "far")
    if positive_near and n <= 0:
        raise ValueError(f"near: expected a distance > 0 for a perspective projection, got {near!r}")
    if not f > n:
        raise ValueError(f"far: expected far > near = {n!r}, got {far!r}")
    return n, f


def perspective(fov_y_deg: float, aspect: float, near: float, far: float, *,
                dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Tensor:
    """OpenGL perspective projection (``gluPerspective``): view space to clip space.

    A view-space point at distance :math:`d = -z_{view}` in front of the camera gets :math:`w = d`; after the
    divide the near plane (:math:`d =` ``near``) maps to NDC :math:`z = -1` and the far plane to :math:`+1`.

    Args:
        fov_y_deg: vertical field of view in degrees, in (0, 180).
        aspect: width / height (> 0).
        near: distance of the near plane (> 0), in mm.
        far: distance of the far plane (> ``near``), in mm.
        dtype: floating dtype of the result (default: torch's default dtype).
        device: device of the result.

    Returns:
        :math:`(4, 4)` projection matrix.

    Raises:
        TypeError: a non-numeric argument.
        ValueError: a value out of range.

    Examples:
        >>> p = perspective(90.0, 1.0, 1.0, 100.0, dtype=torch.float64)
        >>> clip = p @ torch.tensor([0.0, 0.0, -1.0, 1.0], dtype=torch.float64)  # on the near plane
        >>> round((clip[2] / clip[3]).item(), 12)
        -1.0
    """
    fov = _check_real(fov_y_deg, "fov_y_deg")
    if not 0.0 < fov < 180.0:
        raise ValueError(f"fov_y_deg: expected a field of view in (0, 180) degrees, got {fov_y_deg!r}")
    a = _check_real(aspect, "aspect")
    if a <= 0:
        raise ValueError(f"aspect: expected a ratio > 0, got {aspect!r}")
    n, f = _check_near_far(near, far, positive_near=True)
    focal = 1.0 / math.tan(math.radians(fov) / 2.0)
    m = torch.zeros(4, 4, dtype=torch.float64)
    m[0, 0] = focal / a
    m[1, 1] = focal
    m[2, 2] = (f + n) / (n - f)
    m[2, 3] = 2.0 * f * n / (n - f)
    m[3, 2] = -1.0
    return m.to(dtype=dtype or torch.get_default_dtype(), device=device)


def orthographic(half_height: float, aspect: float, near: float, far: float, *,
                 dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Tensor:
    """OpenGL orthographic projection (``glOrtho``) of a centred view volume.

    The view volume is :math:`x \\in [-h a, h a]`, :math:`y \\in [-h, h]` and distances :math:`-z_{view} \\in`
    [``near``, ``far``], mapped to NDC :math:`[-1, 1]^3` (near to :math:`z = -1`); :math:`w = 1`.

    Args:
        half_height: :math:`h`, half the height of the view volume in mm (> 0).
        aspect: :math:`a`, width / height (> 0).
        near: distance of the near plane in mm (may be <= 0: an orthographic camera sees behind its eye).
        far: distance of the far plane in mm (> ``near``).
        dtype: floating dtype of the result (default: torch's default dtype).
        device: device of the result.

    Returns:
        :math:`(4, 4)` projection matrix.

    Raises:
        TypeError: a non-numeric argument.
        ValueError: a value out of range.

    Examples:
        >>> p = orthographic(2.0, 1.5, 0.0, 10.0, dtype=torch.float64)
        >>> (p @ torch.tensor([3.0, -2.0, -10.0, 1.0], dtype=torch.float64)).tolist()
        [1.0, -1.0, 1.0, 1.0]
    """
    h = _check_real(half_height, "half_height")
    if h <= 0:
        raise ValueError(f"half_height: expected a length > 0, got {half_height!r}")
    a = _check_real(aspect, "aspect")
    if a <= 0:
        raise ValueError(f"aspect: expected a ratio > 0, got {aspect!r}")
    n, f = _check_near_far(near, far, positive_near=False)
    m = torch.zeros(4, 4, dtype=torch.float64)
    m[0, 0] = 1.0 / (h * a)
    m[1, 1] = 1.0 / h
    m[2, 2] = -2.0 / (f - n)
    m[2, 3] = -(f + n) / (f - n)
    m[3, 3] = 1.0
    return m.to(dtype=dtype or torch.get_default_dtype(), device=device)


def transform_points(points: Tensor, matrix: Tensor) -> Tensor:
    """Apply a :math:`4 \\times 4` matrix to 3-D points, returning homogeneous coordinates (no divide).

    Args:
        points: :math:`(N, 3)` or :math:`(B, N, 3)` floating tensor.
        matrix: :math:`(4, 4)` or :math:`(B, 4, 4)`, acting on column vectors :math:`[x, y, z, 1]^T`.
            Batch sizes must match or one of them be absent (or 1).

    Returns:
        :math:`(B, N, 4)` homogeneous coordinates (:math:`B = 1` if neither input is batched), dtype promoted.

    Raises:
        TypeError: a non-tensor or non-floating input.
        ValueError: wrong shapes or batch sizes that do not broadcast.

    Examples:
        >>> m = torch.eye(4)
        >>> m[:3, 3] = torch.tensor([1.0, 2.0, 3.0])  # a translation
        >>> transform_points(torch.zeros(2, 3), m).tolist()
        [[[1.0, 2.0, 3.0, 1.0], [1.0, 2.0, 3.0, 1.0]]]
    """
    check_tensor(points, "points")
    check_tensor(matrix, "matrix")
    if points.dim() not in (2, 3) or points.shape[-1] != 3:
        raise ValueError(f"points: expected shape (N, 3) or (B, N, 3), got {tuple(points.shape)}")
    if matrix.dim() not in (2, 3) or matrix.shape[-2:] != (4, 4):
        raise ValueError(f"matrix: expected shape (4, 4) or (B, 4, 4), got {tuple(matrix.shape)}")
    pts = points if points.dim() == 3 else points.unsqueeze(0)
    mat = matrix if matrix.dim() == 3 else matrix.unsqueeze(0)
    if pts.shape[0] != mat.shape[0] and 1 not in (pts.shape[0], mat.shape[0]):
        raise ValueError(f"points, matrix: expected equal batch sizes, got points {tuple(points.shape)} and "
                         f"matrix {tuple(matrix.shape)}")
    dtype = torch.promote_types(pts.dtype, mat.dtype)
    pts, mat = pts.to(dtype), mat.to(dtype)
    # p' = R p + t, written as one batched matmul against the transposed 3x4 block, plus the last row for w.
    out = torch.matmul(pts, mat[:, :, :3].transpose(1, 2)) + mat[:, None, :, 3]
    return out


def pixel_centers_ndc(height: int, width: int, *, dtype: torch.dtype | None = None,
                      device: torch.device | str | None = None) -> Tensor:
    """NDC coordinates of the pixel centres of an :math:`H \\times W` image.

    Pixel (row :math:`r`, column :math:`c`) has its centre at :math:`x = 2 (c + 0.5) / W - 1`,
    :math:`y = 1 - 2 (r + 0.5) / H`: row 0 is at the top (NDC :math:`y` close to +1).

    Args:
        height: :math:`H` (positive int).
        width: :math:`W` (positive int).
        dtype: floating dtype (default: torch's default dtype).
        device: device of the result.

    Returns:
        :math:`(2, H, W)`: channel 0 is NDC :math:`x`, channel 1 NDC :math:`y`.

    Raises:
        TypeError: a non-integer size.
        ValueError: a size < 1.

    Examples:
        >>> pixel_centers_ndc(2, 2)[:, 0, 0].tolist()  # top-left pixel
        [-0.5, 0.5]
    """
    h = _check_size(height, "height")
    w = _check_size(width, "width")
    dtype = dtype or torch.get_default_dtype()
    xs = (torch.arange(w, dtype=torch.float64, device=device) + 0.5) * (2.0 / w) - 1.0
    ys = 1.0 - (torch.arange(h, dtype=torch.float64, device=device) + 0.5) * (2.0 / h)
    grid = torch.stack([xs.expand(h, w), ys[:, None].expand(h, w)])
    return grid.to(dtype)


def _check_size(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name}: expected a positive int, got {type(value).__name__}")
    if value < 1:
        raise ValueError(f"{name}: expected a positive int, got {value!r}")
    return int(value)


# -- camera ---------------------------------------------------------------------------------------------------------
def _check_point(value: object, name: str) -> tuple[float, float, float]:
    if isinstance(value, Tensor):
        value = value.detach().cpu().tolist()
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise TypeError(f"{name}: expected a sequence of 3 numbers, got {type(value).__name__}")
    if len(value) != 3:
        raise ValueError(f"{name}: expected a sequence of 3 numbers, got {len(value)} entries: {value!r}")
    return tuple(_check_real(v, name) for v in value)  # type: ignore[return-value]


@dataclass(frozen=True)
class Camera:
    """A pinhole (or orthographic) camera in millimetres, as in the scene-JSON ``"camera"`` block.

    The camera looks from ``eye`` at ``target`` with ``up`` roughly up; see the module docstring for the
    conventions (right-handed world, camera looking down its :math:`-z`, OpenGL clip space, row 0 at the top,
    pixel centres at :math:`i + 0.5`, vertical field of view). All fields are validated on construction.

    Attributes:
        eye: camera position (mm).
        target: point looked at (mm).
        up: approximate up direction (not parallel to ``target - eye``).
        fov_deg: vertical field of view in degrees, in (0, 180) (perspective only).
        width: image width :math:`W` in pixels.
        height: image height :math:`H` in pixels.
        near: near-plane distance in mm (> 0 for a perspective camera).
        far: far-plane distance in mm (> ``near``).
        projection: ``"perspective"`` or ``"orthographic"``.
        ortho_half_height: half the height of the orthographic view volume in mm.

    Examples:
        >>> cam = Camera(eye=(0.0, 0.0, 100.0), target=(0.0, 0.0, 0.0), width=4, height=3)
        >>> cam.resolution, tuple(cam.view_proj().shape)
        ((3, 4), (4, 4))
    """

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 40.0
    width: int = 256
    height: int = 256
    near: float = 1.0
    far: float = 1000.0
    projection: str = "perspective"
    ortho_half_height: float = 50.0

    def __post_init__(self) -> None:
        for name in ("eye", "target", "up"):
            object.__setattr__(self, name, _check_point(getattr(self, name), name))
        fov = _check_real(self.fov_deg, "fov_deg")
        if not 0.0 < fov < 180.0:
            raise ValueError(f"fov_deg: expected a field of view in (0, 180) degrees, got {self.fov_deg!r}")
        object.__setattr__(self, "fov_deg", fov)
        object.__setattr__(self, "width", _check_size(self.width, "width"))
        object.__setattr__(self, "height", _check_size(self.height, "height"))
        if not isinstance(self.projection, str) or self.projection not in _PROJECTIONS:
            raise ValueError(f"projection: expected one of {_PROJECTIONS}, got {self.projection!r}")
        near, far = _check_near_far(self.near, self.far, positive_near=self.projection == "perspective")
        object.__setattr__(self, "near", near)
        object.__setattr__(self, "far", far)
        half = _check_real(self.ortho_half_height, "ortho_half_height")
        if half <= 0:
            raise ValueError(f"ortho_half_height: expected a length > 0, got {self.ortho_half_height!r}")
        object.__setattr__(self, "ortho_half_height", half)
        look_at(torch.tensor(self.eye, dtype=torch.float64), torch.tensor(self.target, dtype=torch.float64),
                torch.tensor(self.up, dtype=torch.float64))  # raises for eye == target or a parallel up

    @classmethod
    def from_dict(cls, d: Mapping) -> Camera:
        """Build a camera from the scene-JSON ``"camera"`` block (DESIGN.md §5).

        Args:
            d: mapping with ``"eye"``, ``"target"`` (required) and optionally ``"up"``, ``"fov_deg"``,
                ``"width"``, ``"height"``, ``"near"``, ``"far"``, ``"projection"``, ``"ortho_half_height"``.

        Returns:
            The validated camera.

        Raises:
            TypeError: ``d`` is not a mapping, or a value of the wrong type (the key is named).
            ValueError: an unknown or missing key (the allowed keys are listed), or a value out of range.

        Examples:
            >>> Camera.from_dict({"eye": [0, 0, 50], "target": [0, 0, 0], "width": 64, "height": 48}).resolution
            (48, 64)
        """
        if not isinstance(d, Mapping):
            raise TypeError(f"camera: expected a mapping (the scene 'camera' block), got {type(d).__name__}")
        allowed = [f.name for f in fields(cls)]
        unknown = sorted(str(k) for k in d if k not in allowed)
        if unknown:
            raise ValueError(f"camera: expected keys among {allowed}, got unknown key(s) {unknown}")
        missing = [k for k in ("eye", "target") if k not in d]
        if missing:
            raise ValueError(f"camera: expected the required key(s) {missing}, got keys {sorted(map(str, d))}")
        return cls(**dict(d))

    def to_dict(self) -> dict:
        """The camera as a JSON-ready dict that :meth:`from_dict` reads back (every field, lists for vectors)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out

    @property
    def resolution(self) -> tuple[int, int]:
        """Image size :math:`(H, W)`."""
        return (self.height, self.width)

    @property
    def aspect(self) -> float:
        """Width / height."""
        return self.width / self.height

    def view_matrix(self, *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """World-to-view matrix :math:`V`, :math:`(4, 4)` (computed in float64, then cast)."""
        v = look_at(torch.tensor(self.eye, dtype=torch.float64), torch.tensor(self.target, dtype=torch.float64),
                    torch.tensor(self.up, dtype=torch.float64))
        return v.to(dtype=dtype, device=device)

    def projection_matrix(self, *, dtype: torch.dtype = torch.float32,
                          device: torch.device | str | None = None) -> Tensor:
        """View-to-clip matrix :math:`P`, :math:`(4, 4)`: :func:`perspective` or :func:`orthographic`."""
        if self.projection == "perspective":
            return perspective(self.fov_deg, self.aspect, self.near, self.far, dtype=dtype, device=device)
        return orthographic(self.ortho_half_height, self.aspect, self.near, self.far, dtype=dtype, device=device)

    def view_proj(self, *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """World-to-clip matrix :math:`P V`, :math:`(4, 4)` (product taken in float64, then cast)."""
        m = self.projection_matrix(dtype=torch.float64) @ self.view_matrix(dtype=torch.float64)
        return m.to(dtype=dtype, device=device)

    def rays(self, *, dtype: torch.dtype = torch.float32,
             device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
        """Primary rays through the pixel centres, in world space.

        Perspective: every ray starts at ``eye`` and passes through its pixel centre on the image plane.
        Orthographic: the rays are parallel to the view direction and start on the *near plane*
        (``near`` mm in front of ``eye``, behind it if ``near < 0``), at the pixel centre's position in the
        view volume. Either way, ``origins + t * directions`` projects onto the pixel centre for every ``t``.

        Args:
            dtype: floating dtype of the result (computed in float64, then cast).
            device: device of the result.

        Returns:
            ``(origins, directions)``, both :math:`(1, 3, H, W)`; directions have unit length.

        Examples:
            >>> cam = Camera(eye=(0.0, 0.0, 10.0), target=(0.0, 0.0, 0.0), width=3, height=3)
            >>> o, d = cam.rays(dtype=torch.float64)
            >>> d[0, :, 1, 1].tolist(), o[0, :, 1, 1].tolist()  # the centre pixel looks along -z from the eye
            ([0.0, 0.0, -1.0], [0.0, 0.0, 10.0])
        """
        view = self.view_matrix(dtype=torch.float64)
        rot_t = view[:3, :3].T  # view-to-world rotation: columns are right, up, back
        eye = torch.tensor(self.eye, dtype=torch.float64)
        ndc = pixel_centers_ndc(self.height, self.width, dtype=torch.float64)
        h, w = self.height, self.width
        if self.projection == "perspective":
            t = math.tan(math.radians(self.fov_deg) / 2.0)
            d_view = torch.stack([ndc[0] * (t * self.aspect), ndc[1] * t, torch.full((h, w), -1.0,
                                                                                       dtype=torch.float64)])
            d = torch.einsum("ij,jhw->ihw", rot_t, d_view)
            d = d / torch.linalg.vector_norm(d, dim=0, keepdim=True)
            o = eye[:, None, None].expand(3, h, w)
        else:
            hh = self.ortho_half_height
            p_view = torch.stack([ndc[0] * (hh * self.aspect), ndc[1] * hh, torch.full((h, w), -self.near,
                                                                                        dtype=torch.float64)])
            o = torch.einsum("ij,jhw->ihw", rot_t, p_view) + eye[:, None, None]
            d = (-rot_t[:, 2])[:, None, None].expand(3, h, w)
        return (o.unsqueeze(0).to(dtype=dtype, device=device).contiguous(),
                d.unsqueeze(0).to(dtype=dtype, device=device).contiguous())
