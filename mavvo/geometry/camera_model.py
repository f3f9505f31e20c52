"""Camera models: pixels to unit bearings and back, vectorised.

Two models, with OpenCV's parameter conventions so calibrations carry over unchanged:

- ``pinhole``: radial-tangential ("radtan", ``cv2.projectPoints``) with coefficients
  (k1, k2, p1, p2[, k3]);
- ``fisheye``: equidistant (``cv2.fisheye``) with coefficients (k1, k2, k3, k4).

Bearings are unit rows in the camera frame (x right, y down, z forward); pixels are (u, v) rows with
the origin at the centre of the top-left pixel, as in OpenCV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Literal

import numpy as np

from mavvo.jit import kernel
from mavvo.options import bounded

ModelName = Literal["pinhole", "fisheye"]

_NEWTON_STEPS = 20
_NEWTON_TOL = 1e-13


@dataclass(frozen=True)
class CameraIntrinsics:
    """Image size, focal lengths, principal point and distortion: the ``camera:`` keys that the
    service's camera (:class:`mavvo.service.camera.CameraOptions`) and the simulator's share."""

    width_px: int = bounded(
        640, "image width (a device is asked for it; frames of another size are rejected)", gt=0, le=16384
    )
    height_px: int = bounded(480, "image height", gt=0, le=16384)
    fx_px: float = bounded(500.0, "focal length, x", gt=0, le=1e5)
    fy_px: float = bounded(500.0, "focal length, y", gt=0, le=1e5)
    cx_px: float = bounded(319.5, "principal point, x (inside the image)", ge=0, le=16384)
    cy_px: float = bounded(239.5, "principal point, y (inside the image)", ge=0, le=16384)
    model: ModelName = bounded("pinhole", "pinhole (OpenCV radtan distortion) or fisheye (equidistant)")
    distortion: tuple[float, ...] = bounded(
        (), "pinhole: k1 k2 p1 p2 [k3]; fisheye: k1 k2 k3 k4; empty for none", ge=-100, le=100
    )

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v <= 0:
                raise ValueError(f"{name}: expected a positive integer, got {v!r}")
        for name in ("fx_px", "fy_px", "cx_px", "cy_px"):
            v = getattr(self, name)
            if not np.isfinite(v):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
        if self.fx_px <= 0 or self.fy_px <= 0:
            raise ValueError(f"fx_px, fy_px: expected positive focal lengths, got {self.fx_px}, {self.fy_px}")
        if self.model not in ("pinhole", "fisheye"):
            raise ValueError(f"model: expected 'pinhole' or 'fisheye', got {self.model!r}")
        allowed = (4, 5) if self.model == "pinhole" else (4,)
        d = tuple(float(x) for x in self.distortion)
        if d and len(d) not in allowed:
            raise ValueError(
                f"distortion: expected {' or '.join(map(str, allowed))} coefficients for {self.model}, got {len(d)}"
            )
        if not all(np.isfinite(d)):
            raise ValueError(f"distortion: expected finite coefficients, got {d}")
        object.__setattr__(self, "distortion", d)
        if not (0.0 <= self.cx_px <= self.width_px and 0.0 <= self.cy_px <= self.height_px):
            raise ValueError(
                f"cx_px, cy_px: expected the principal point inside the {self.width_px}x{self.height_px} image, got ({self.cx_px}, {self.cy_px})"
            )

    def camera_model(self) -> CameraModel:
        """The camera model of these intrinsics."""
        return CameraModel(**{f.name: getattr(self, f.name) for f in fields(CameraIntrinsics)})


@dataclass(frozen=True)
class CameraModel(CameraIntrinsics):
    """A camera: :class:`CameraIntrinsics` with the maps between pixels and bearings.

    Attributes:
        width_px, height_px: image size.
        fx_px, fy_px: focal lengths; cx_px, cy_px: principal point.
        model: ``"pinhole"`` (radtan) or ``"fisheye"`` (equidistant).
        distortion: pinhole (k1, k2, p1, p2) or (k1, k2, p1, p2, k3); fisheye (k1, k2, k3, k4).
            Empty means no distortion.
    """

    @classmethod
    def from_matrix(
        cls,
        K: np.ndarray,
        width_px: int,
        height_px: int,
        distortion: tuple[float, ...] = (),
        model: ModelName = "pinhole",
    ) -> "CameraModel":
        """Build from a 3x3 intrinsic matrix as OpenCV calibrations give it."""
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise ValueError(f"K: expected a (3,3) intrinsic matrix, got shape {K.shape}")
        return cls(width_px, height_px, K[0, 0], K[1, 1], K[0, 2], K[1, 2], model, tuple(distortion))

    @property
    def K(self) -> np.ndarray:
        """(3,3) intrinsic matrix."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    def _coeffs(self) -> np.ndarray:
        n = 5 if self.model == "pinhole" else 4
        return np.array(self.distortion + (0.0,) * (n - len(self.distortion)))

    # ------------------------------------------------------------------ pixels -> bearings

    def pixels_to_bearings(self, uv_px: np.ndarray) -> np.ndarray:
        """(N,2) pixels to (N,3) unit bearings in the camera frame.

        Distortion is inverted by Newton's method per point; a pixel whose inversion does not
        converge (far outside the calibrated field of view) gives a NaN row.
        """
        uv = np.asarray(uv_px, dtype=float)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"uv_px: expected an (N,2) array of pixels, got shape {uv.shape}")
        if self.model == "pinhole" and not any(self.distortion):  # every frame's tracks: one compiled pass
            return _pinhole_bearings(np.ascontiguousarray(uv), self.fx_px, self.fy_px, self.cx_px, self.cy_px)
        xd = np.stack([(uv[:, 0] - self.cx_px) / self.fx_px, (uv[:, 1] - self.cy_px) / self.fy_px], axis=1)
        if self.model == "pinhole":
            xu = self._undistort_radtan(xd)
            f = np.concatenate([xu, np.ones((len(xu), 1))], axis=1)
        else:
            f = self._unproject_fisheye(xd)
        return f / np.linalg.norm(f, axis=1, keepdims=True)

    def _distort_radtan(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates and the (N,2,2) Jacobian d(distorted)/d(x)."""
        k1, k2, p1, p2, k3 = self._coeffs()
        a, b = x[:, 0], x[:, 1]
        r2 = a * a + b * b
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        xd = np.stack(
            [a * radial + 2 * p1 * a * b + p2 * (r2 + 2 * a * a), b * radial + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b],
            axis=1,
        )
        J = np.empty((len(x), 2, 2))
        J[:, 0, 0] = radial + a * drad * 2 * a + 2 * p1 * b + p2 * 6 * a
        J[:, 0, 1] = a * drad * 2 * b + 2 * p1 * a + p2 * 2 * b
        J[:, 1, 0] = b * drad * 2 * a + p1 * 2 * a + 2 * p2 * b
        J[:, 1, 1] = radial + b * drad * 2 * b + p1 * 6 * b + 2 * p2 * a
        return xd, J

    def _undistort_radtan(self, xd: np.ndarray) -> np.ndarray:
        if not any(self.distortion):
            return xd
        x = xd.copy()
        for _ in range(_NEWTON_STEPS):
            f, J = self._distort_radtan(x)
            step = np.linalg.solve(J, (f - xd)[..., None])[..., 0]
            x -= step
            if np.all(np.abs(step) < _NEWTON_TOL):
                break
        f, _ = self._distort_radtan(x)
        bad = np.linalg.norm(f - xd, axis=1) > 1e-9
        x[bad] = np.nan
        return x

    def _unproject_fisheye(self, xd: np.ndarray) -> np.ndarray:
        k1, k2, k3, k4 = self._coeffs()
        theta_d = np.linalg.norm(xd, axis=1)
        theta = theta_d.copy()
        for _ in range(_NEWTON_STEPS):
            t2 = theta * theta
            g = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
            dg = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            step = g / dg
            theta -= step
            if np.all(np.abs(step) < _NEWTON_TOL):
                break
        bad = ~(np.isfinite(theta)) | (theta < 0) | (theta > np.pi)
        scale = np.where(theta_d > 1e-15, np.sin(theta) / np.where(theta_d > 1e-15, theta_d, 1.0), 1.0)
        f = np.concatenate([xd * scale[:, None], np.cos(theta)[:, None]], axis=1)
        f[bad] = np.nan
        return f

    # ------------------------------------------------------------------ bearings -> pixels

    def bearings_to_pixels(self, f_cam: np.ndarray) -> np.ndarray:
        """(N,3) bearings in the camera frame (any length) to (N,2) pixels.

        Pinhole: points at or behind the image plane (z <= 0) give NaN rows. Fisheye: every
        direction but straight back has a pixel.
        """
        f = np.asarray(f_cam, dtype=float)
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"f_cam: expected an (N,3) array of bearings, got shape {f.shape}")
        if self.model == "pinhole":
            z = f[:, 2]
            front = z > 1e-12
            x = f[:, :2] / np.where(front, z, 1.0)[:, None]
            xd = self._distort_radtan(x)[0] if any(self.distortion) else x
            xd[~front] = np.nan
        else:
            k1, k2, k3, k4 = self._coeffs()
            rxy = np.linalg.norm(f[:, :2], axis=1)
            theta = np.arctan2(rxy, f[:, 2])
            t2 = theta * theta
            theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
            scale = np.where(rxy > 1e-15, theta_d / np.where(rxy > 1e-15, rxy, 1.0), 0.0)
            xd = f[:, :2] * scale[:, None]
        return np.stack([self.fx_px * xd[:, 0] + self.cx_px, self.fy_px * xd[:, 1] + self.cy_px], axis=1)


@kernel
def _pinhole_bearings(uv: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Unit bearings (N, 3) of pixels uv (N, 2) through an undistorted pinhole."""
    out = np.empty((uv.shape[0], 3))
    for i in range(uv.shape[0]):
        x, y = (uv[i, 0] - cx) / fx, (uv[i, 1] - cy) / fy
        norm = math.sqrt(x * x + y * y + 1.0)
        out[i, 0], out[i, 1], out[i, 2] = x / norm, y / norm, 1.0 / norm
    return out
