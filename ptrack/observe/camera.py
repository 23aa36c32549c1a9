"""A pinhole camera: world points -> pixels, pixels -> world rays.

Conventions (stated once for ptrack): the world frame is metres, Y up (CMU). Camera axes follow
OpenCV: x right, y down, z forward, and ``x_cam = R @ x_world + t``. Pixel coordinates are
continuous: pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``, so the image is ``[0, W) x [0, H)``
and its centre is ``(W / 2, H / 2)``. No lens distortion.

A camera holds one ``K, R, t`` (no batch of cameras); every method takes points with arbitrary
leading batch dims (unbatched (3,) / (2,) included), and its outputs follow the points' dtype
and device. The maths is a few lines of torch rather than kornia's `project_points` because ptrack
honours K's skew entry (kornia ignores it) and clamps depth for points behind the camera;
tests/test_camera.py checks agreement with kornia for zero-skew K and points in front.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from ptrack.checks import as_float_tensor
from ptrack.errors import InputError

#: largest allowed |R R^T - I| entry and |det R - 1| for a rotation matrix.
ROTATION_TOL = 1e-4

_DICT_KEYS = ("K", "R", "t", "width", "height")


class Projection(NamedTuple):
    """Result of `Camera.project` for points ``X: (..., 3)``."""

    pixels: Tensor  # (..., 2) pixel coordinates (u, v)
    depth: Tensor  # (...,) z in the camera frame, metres (negative behind the camera)
    in_front: Tensor  # (...,) bool, depth > min_depth


def _check_size(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value <= 0:
        raise InputError(f"Camera.{name} must be a positive integer, got {value!r}")
    return int(value)


def _require_float_points(name: str, x: Tensor, last: int) -> None:
    if not isinstance(x, Tensor) or not x.is_floating_point():
        kind = x.dtype if isinstance(x, Tensor) else type(x).__name__
        raise InputError(f"{name} must be a floating point tensor, got {kind}")
    if x.ndim == 0 or x.shape[-1] != last:
        raise InputError(f"{name} must have shape (..., {last}), got {tuple(x.shape)}")


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera with intrinsics ``K`` and world-to-camera extrinsics ``R, t``.

    K: (3, 3) upper triangular, ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with fx, fy > 0.
    R: (3, 3) rotation, world to camera.  t: (3,) translation, ``x_cam = R @ x_world + t``.
    width, height: image size in pixels.

    Array-likes are converted to tensors; K, R, t are promoted to one floating dtype and must share
    a device. Invalid values raise `InputError` naming the field.
    """

    K: Tensor
    R: Tensor
    t: Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        K = as_float_tensor(self.K, "Camera.K")
        R = as_float_tensor(self.R, "Camera.R")
        t = as_float_tensor(self.t, "Camera.t")
        for name, x, shape in (("K", K, (3, 3)), ("R", R, (3, 3)), ("t", t, (3,))):
            if tuple(x.shape) != shape:
                raise InputError(f"Camera.{name} must have shape {shape}, got {tuple(x.shape)}")
        if not (K.device == R.device == t.device):
            raise InputError(f"Camera.K, R, t must share a device, got {K.device}, {R.device}, {t.device}")
        dtype = torch.promote_types(torch.promote_types(K.dtype, R.dtype), t.dtype)
        K, R, t = K.to(dtype), R.to(dtype), t.to(dtype)
        with torch.no_grad():
            for name, x in (("K", K), ("R", R), ("t", t)):
                if not bool(torch.isfinite(x).all()):
                    raise InputError(f"Camera.{name} has non-finite values: {x.tolist()}")
            Kd = K.double()
            if Kd[2].tolist() != [0.0, 0.0, 1.0] or float(Kd[1, 0]) != 0.0:
                raise InputError(f"Camera.K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
            if not (float(Kd[0, 0]) > 0.0 and float(Kd[1, 1]) > 0.0):
                raise InputError(f"Camera.K focal lengths must be > 0, got {K.tolist()}")
            Rd = R.double()
            eye = torch.eye(3, dtype=Rd.dtype, device=Rd.device)
            ortho_err = float((Rd @ Rd.T - eye).abs().max())
            det = float(torch.linalg.det(Rd))
            if ortho_err > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
                raise InputError(
                    f"Camera.R (shape (3, 3)) is not a rotation: |R R^T - I| = {ortho_err:.3g}, det = {det:.6g}"
                )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "width", _check_size("width", self.width))
        object.__setattr__(self, "height", _check_size("height", self.height))

    # -- basic properties ----------------------------------------------------------------------

    @property
    def center(self) -> Tensor:
        """Camera centre in the world frame, ``-R^T t``: (3,)."""
        return -(self.R.T @ self.t)

    @property
    def dtype(self) -> torch.dtype:
        return self.K.dtype

    @property
    def device(self) -> torch.device:
        return self.K.device

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Camera:
        """A copy with K, R, t moved to ``device`` and/or cast to floating ``dtype``."""
        if dtype is not None and not dtype.is_floating_point:
            raise InputError(f"Camera.to: dtype must be floating point, got {dtype}")
        return Camera(
            K=self.K.to(device=device, dtype=dtype),
            R=self.R.to(device=device, dtype=dtype),
            t=self.t.to(device=device, dtype=dtype),
            width=self.width,
            height=self.height,
        )

    def _params_like(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        kw: dict[str, Any] = {"dtype": x.dtype, "device": x.device}
        return self.K.to(**kw), self.R.to(**kw), self.t.to(**kw)

    # -- geometry ------------------------------------------------------------------------------

    def world_to_camera(self, X: Tensor) -> Tensor:
        """World points to camera-frame points, ``R @ X + t``: X (..., 3) -> (..., 3)."""
        _require_float_points("X", X, 3)
        _, R, t = self._params_like(X)
        return X @ R.T + t

    def project(self, X: Tensor, min_depth: float = 1e-3) -> Projection:
        """Project world points to pixels: X (..., 3) -> Projection(pixels (..., 2), depth (...,),
        in_front (...,)).

        The perspective divide uses ``max(depth, min_depth)``, so a point behind the camera is not
        mirrored onto the image: it lands far outside it, on the side of its camera-frame x/y
        (at the principal point if it sits on the optical axis), and ``in_front`` is False.
        Gradients are finite everywhere, including depth 0 (zero w.r.t. depth below ``min_depth``).
        """
        if not min_depth > 0.0:
            raise InputError(f"project: min_depth must be > 0, got {min_depth!r}")
        x_cam = self.world_to_camera(X)
        K, _, _ = self._params_like(X)
        depth = x_cam[..., 2]
        xy = x_cam[..., :2] / depth.clamp_min(min_depth).unsqueeze(-1)
        pixels = xy @ K[:2, :2].T + K[:2, 2]
        return Projection(pixels=pixels, depth=depth, in_front=depth > min_depth)

    def project_jacobian(self, X: Tensor, min_depth: float = 1e-3) -> tuple[Projection, Tensor]:
        """`project` and its derivative w.r.t. the world points: X (..., 3) -> (Projection,
        d pixels / d X (..., 2, 3)); d depth / d X is R[2] for every point. Zero w.r.t. depth
        below ``min_depth``, like `project`'s gradient."""
        proj = self.project(X, min_depth)
        K, R, _ = self._params_like(X)
        z = proj.depth.clamp_min(min_depth)
        xy = (proj.pixels - K[:2, 2]) @ torch.linalg.inv(K[:2, :2]).T  # camera-frame x/z, y/z
        front = (proj.depth > min_depth).to(X.dtype)
        # d (x/z, y/z) / d x_cam = [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]
        d_xy = torch.zeros(*X.shape[:-1], 2, 3, dtype=X.dtype, device=X.device)
        d_xy[..., 0, 0] = 1.0 / z
        d_xy[..., 1, 1] = 1.0 / z
        d_xy[..., :, 2] = -xy * (front / z)[..., None]
        return proj, K[:2, :2] @ d_xy @ R

    def in_image(self, pixels: Tensor) -> Tensor:
        """Whether pixels lie inside ``[0, W) x [0, H)``: pixels (..., 2) -> (...,) bool.

        Says nothing about depth: combine with `Projection.in_front` for visibility.
        """
        _require_float_points("pixels", pixels, 2)
        u, v = pixels[..., 0], pixels[..., 1]
        return (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)

    def rays(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        """Back-project pixels to world rays: pixels (..., 2) -> origins, directions (..., 3).

        Origins are the camera centre (broadcast); directions are unit vectors in the world frame
        pointing forward (positive depth). Point ``origin + s * direction`` projects to the pixel.
        """
        _require_float_points("pixels", pixels, 2)
        K, R, t = self._params_like(pixels)
        d_cam = F.pad(pixels, (0, 1), value=1.0) @ torch.linalg.inv(K).T  # (..., 3), z = 1
        directions = F.normalize(d_cam @ R, dim=-1)  # R^T d per point
        origins = (-(R.T @ t)).expand(directions.shape)
        return origins, directions

    # -- serialisation -------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict: ``{"K": 3x3 lists, "R": 3x3 lists, "t": 3 list, "width", "height"}``."""
        return {
            "K": self.K.detach().cpu().double().tolist(),
            "R": self.R.detach().cpu().double().tolist(),
            "t": self.t.detach().cpu().double().tolist(),
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], dtype: torch.dtype | None = None) -> Camera:
        """Inverse of `to_dict`; tensors get ``dtype`` (default: torch's default dtype).

        Missing or unknown keys and malformed values raise `InputError` naming the key.
        """
        if not isinstance(d, Mapping):
            raise InputError(f"camera dict must be a mapping, got {type(d).__name__}")
        missing = [k for k in _DICT_KEYS if k not in d]
        unknown = sorted(str(k) for k in d if k not in _DICT_KEYS)
        if missing or unknown:
            raise InputError(f"camera dict: missing keys {missing}, unknown keys {unknown}")
        dtype = dtype or torch.get_default_dtype()
        arrays = {}
        for key in ("K", "R", "t"):
            value = d[key]
            if isinstance(value, (str, bytes)) or not isinstance(value, (Sequence, Tensor)):
                raise InputError(f"camera dict key {key!r} must be a number list, got {value!r}")
            try:
                arrays[key] = torch.tensor(value, dtype=dtype)
            except (TypeError, ValueError, RuntimeError) as e:
                raise InputError(f"camera dict key {key!r} is not a numeric array: {e}") from e
        return cls(width=d["width"], height=d["height"], **arrays)


# -- constructors ------------------------------------------------------------------------------


def _unit(v: Tensor) -> Tensor:
    return v / torch.linalg.vector_norm(v)


def look_at(
    target: Tensor | Sequence[float],
    distance_m: float,
    azimuth_deg: float,
    elevation_deg: float,
    focal_px: float,
    width: int,
    height: int,
    up: Sequence[float] = (0.0, 1.0, 0.0),
) -> Camera:
    """A camera at ``distance_m`` from ``target`` (3,), looking at it; target maps to (W/2, H/2).

    With ``up = +Y`` the camera centre is
    ``target + d * (cos(el) sin(az), sin(el), cos(el) cos(az))``: azimuth 0 is on the +Z side
    looking towards -Z, azimuth 90 on the +X side; positive elevation is above target, looking
    down. Image right is ``cos(az) X - sin(az) Z`` (independent of elevation, so +-90 degrees is
    well defined) and image down is world-downward, so a standing person projects upright.
    For another ``up`` the same formula holds in the frame (e_x, up, e_z) where e_z is +Z made
    orthogonal to up (+X is used instead when up is along Z).

    The camera has target's dtype and device when target is a floating tensor, else the default
    dtype. Square pixels, no skew.
    """
    if not distance_m > 0.0 or not math.isfinite(distance_m):
        raise InputError(f"look_at: distance_m must be finite and > 0, got {distance_m!r}")
    if not focal_px > 0.0 or not math.isfinite(focal_px):
        raise InputError(f"look_at: focal_px must be finite and > 0, got {focal_px!r}")
    for name, a in (("azimuth_deg", azimuth_deg), ("elevation_deg", elevation_deg)):
        if not math.isfinite(a):
            raise InputError(f"look_at: {name} must be finite, got {a!r}")
    width, height = _check_size("width", width), _check_size("height", height)
    tgt = target if isinstance(target, Tensor) else torch.as_tensor(target, dtype=torch.float64)
    if tuple(tgt.shape) != (3,) or not bool(torch.isfinite(tgt).all()):
        raise InputError(f"look_at: target must be 3 finite numbers, got shape {tuple(tgt.shape)}")
    floating_tensor = isinstance(target, Tensor) and target.is_floating_point()
    out_dtype = tgt.dtype if floating_tensor else torch.get_default_dtype()
    f64: dict[str, Any] = {"dtype": torch.float64, "device": tgt.device}
    tgt = tgt.detach().to(**f64)

    e_y = torch.as_tensor(up, **f64)
    if tuple(e_y.shape) != (3,) or not bool(torch.isfinite(e_y).all()) or float(e_y.norm()) < 1e-9:
        raise InputError(f"look_at: up must be a finite non-zero 3-vector, got {up!r}")
    e_y = _unit(e_y)
    z_axis, x_axis = torch.tensor([0.0, 0.0, 1.0], **f64), torch.tensor([1.0, 0.0, 0.0], **f64)
    if abs(float(e_y @ z_axis)) < 0.999:
        e_z = _unit(z_axis - (z_axis @ e_y) * e_y)
        e_x = torch.linalg.cross(e_y, e_z)
    else:
        e_x = _unit(x_axis - (x_axis @ e_y) * e_y)
        e_z = torch.linalg.cross(e_x, e_y)

    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    ce, se, ca, sa = math.cos(el), math.sin(el), math.cos(az), math.sin(az)
    outward = ce * sa * e_x + se * e_y + ce * ca * e_z
    center = tgt + distance_m * outward
    forward = -outward
    right = ca * e_x - sa * e_z
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])
    t = -(R @ center)
    K = torch.tensor([[focal_px, 0.0, width / 2.0], [0.0, focal_px, height / 2.0], [0.0, 0.0, 1.0]], **f64)
    return Camera(K=K, R=R, t=t, width=width, height=height).to(dtype=out_dtype)


def camera_for_motion(
    joints: Tensor,
    distance_m: float,
    azimuth_deg: float,
    elevation_deg: float,
    focal_px: float,
    width: int,
    height: int,
) -> Camera:
    """`look_at` the centre of the axis-aligned bounding box of all joints over all frames.

    joints: (T, J, 3) world positions, metres.
    """
    if not isinstance(joints, Tensor) or joints.ndim != 3 or joints.shape[-1] != 3:
        shape = tuple(joints.shape) if isinstance(joints, Tensor) else type(joints).__name__
        raise InputError(f"camera_for_motion: joints must have shape (T, J, 3), got {shape}")
    if joints.shape[0] == 0 or joints.shape[1] == 0:
        raise InputError(f"camera_for_motion: joints is empty, shape {tuple(joints.shape)}")
    if not bool(torch.isfinite(joints).all()):
        raise InputError("camera_for_motion: joints has non-finite values")
    flat = joints.detach().reshape(-1, 3)
    target = (flat.amin(dim=0) + flat.amax(dim=0)) / 2
    return look_at(target, distance_m, azimuth_deg, elevation_deg, focal_px, width, height)
