"""Rotations and the frame conventions of mavvo.

Frames (see design.md): ``cam`` is OpenCV (x right, y down, z forward); ``body`` is FRD; ``ned`` is
local North-East-Down; ``lvl`` is the level frame of one view: z along gravity (down), heading that of
the body, so two level frames differ by a rotation about z only.

``R_a_b`` maps vectors of frame b into frame a: ``x_a = R_a_b @ x_b``. Angles are radians. All
rotation matrices here are active (``rot_z(yaw) @ v`` turns v by +yaw about z).
"""

from __future__ import annotations

import math

import numpy as np

from mavvo.jit import kernel

# Camera mountings (R_body_cam). Nadir: looking down, image top towards the nose.
R_BODY_CAM_NADIR = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
# Forward: looking along the nose, image right towards the right wing.
R_BODY_CAM_FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def rot_x(angle_rad: float) -> np.ndarray:
    """(3,3) rotation by ``angle_rad`` about x."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> np.ndarray:
    """(3,3) rotation by ``angle_rad`` about y."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> np.ndarray:
    """(3,3) rotation by ``angle_rad`` about z."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def R_from_euler321(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """``R_ned_body`` from Euler 3-2-1 angles, the ATTITUDE convention of ArduPilot and PX4:
    yaw about z, then pitch about the new y, then roll about the new x."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def euler321_from_R(R_ned_body: np.ndarray) -> tuple[float, float, float]:
    """(roll_rad, pitch_rad, yaw_rad) of a rotation; pitch in [-pi/2, pi/2], yaw in (-pi, pi].

    At pitch = +-90 deg (gimbal lock) roll is set to 0 and the rotation about z goes to yaw.
    """
    R = as_rotation("R_ned_body", R_ned_body).tolist()  # scalar math from here: numpy's costs microseconds a call
    pitch = math.asin(min(max(-R[2][0], -1.0), 1.0))
    if abs(R[2][0]) < 1.0 - 1e-12:
        roll = math.atan2(R[2][1], R[2][2])
        yaw = math.atan2(R[1][0], R[0][0])
    else:
        roll = 0.0
        yaw = math.atan2(-R[0][1], R[1][1])
    return roll, pitch, yaw


def R_lvl_body(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """Rotation taking body vectors into the level frame: ``rot_y(pitch) @ rot_x(roll)``."""
    return rot_y(pitch_rad) @ rot_x(roll_rad)


def R_lvl_cam(roll_rad: float, pitch_rad: float, R_body_cam: np.ndarray) -> np.ndarray:
    """Rotation taking camera vectors into the level frame (z down, heading of the body)."""
    return R_lvl_body(roll_rad, pitch_rad) @ as_rotation("R_body_cam", R_body_cam)


def derotate(f_cam: np.ndarray, R_lvl_cam_: np.ndarray) -> np.ndarray:
    """Bearings (N,3) in the camera frame to the level frame: rows ``R_lvl_cam @ f``."""
    f = np.asarray(f_cam, dtype=float)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"f_cam: expected an (N,3) array of bearings, got shape {f.shape}")
    return f @ as_rotation("R_lvl_cam", R_lvl_cam_).T


def skew(t: np.ndarray) -> np.ndarray:
    """(3,3) cross-product matrix: ``skew(t) @ v == cross(t, v)``."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis of broadcastable (..., 3) arrays.

    The same as ``np.cross`` for 3-vectors, written out because np.cross costs about ten times more
    on the small arrays of the solvers' inner loops.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def rotation_angle_rad(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the rotation taking R_b to R_a (geodesic distance), radians.

    Uses ``|R_a - R_b|_F = 2 sqrt(2) sin(angle / 2)``, which keeps full precision for small angles
    where the trace formula's arccos bottoms out near 1e-8.
    """
    d = np.linalg.norm(np.asarray(R_a, dtype=float) - np.asarray(R_b, dtype=float))
    return float(2.0 * np.arcsin(np.clip(d / (2.0 * np.sqrt(2.0)), 0.0, 1.0)))


def angle_between_rad(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two (3,) vectors, radians, accurate for small angles (atan2, not arccos)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b))


def as_rotation(name: str, R: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """R as a float (3,3) array; ValueError naming ``name`` unless it is a finite rotation matrix."""
    arr = np.asarray(R, dtype=float)
    if arr.shape != (3, 3):
        raise ValueError(f"{name}: expected a finite (3,3) rotation matrix, got shape {arr.shape}")
    defect = _rotation_defect(np.ascontiguousarray(arr))
    if not defect < np.inf:
        raise ValueError(f"{name}: expected a finite (3,3) rotation matrix, got NaN or inf")
    if defect > tol:
        raise ValueError(f"{name}: expected a rotation matrix (orthonormal, det +1)")
    return arr


@kernel
def _rotation_defect(R: np.ndarray) -> float:
    """max |R R^T - I| of a (3, 3) matrix, at least 2 if its determinant is negative, inf if not finite.
    Compiled: every relative pose checks two rotations."""
    worst = 0.0
    for i in range(3):
        for j in range(3):
            if not abs(R[i, j]) < np.inf:
                return np.inf
            dot = R[i, 0] * R[j, 0] + R[i, 1] * R[j, 1] + R[i, 2] * R[j, 2]
            worst = max(worst, abs(dot - (1.0 if i == j else 0.0)))
    det = (
        R[0, 0] * (R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1])
        - R[0, 1] * (R[1, 0] * R[2, 2] - R[1, 2] * R[2, 0])
        + R[0, 2] * (R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0])
    )
    return max(worst, 2.0) if det < 0.0 else worst


def quat_wxyz_from_R(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a (3,3) rotation or (N,4) of an (N,3,3) stack
    (Hamilton convention, as MAVLink's ODOMETRY ``q`` and TUM files use, there ordered x y z w)."""
    R = np.asarray(R, dtype=float)
    single = R.ndim == 2
    Rs = R[None] if single else R
    if Rs.ndim != 3 or Rs.shape[1:] != (3, 3):
        raise ValueError(f"R: expected (3,3) or (N,3,3), got shape {R.shape}")
    m = Rs
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    # the four candidate magnitudes; take the largest per rotation for stability
    cand = np.stack(
        [
            1 + tr,
            1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
            1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
            1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2],
        ],
        axis=1,
    )
    k = np.argmax(cand, axis=1)
    q = np.empty((len(m), 4))
    s = 2.0 * np.sqrt(np.maximum(cand[np.arange(len(m)), k], 1e-300))
    a, b = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0]
    c = m[:, 1, 0] - m[:, 0, 1]
    d, e, f = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
    rows = {
        0: np.stack([s / 4, a / s, b / s, c / s], axis=1),
        1: np.stack([a / s, s / 4, d / s, e / s], axis=1),
        2: np.stack([b / s, d / s, s / 4, f / s], axis=1),
        3: np.stack([c / s, e / s, f / s, s / 4], axis=1),
    }
    for i, val in rows.items():
        q[k == i] = val[k == i]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q[0] if single else q


def R_from_quat_wxyz(q: np.ndarray) -> np.ndarray:
    """(3,3) rotation of a quaternion (w, x, y, z), or (N,3,3) of (N,4); the quaternion is normalised."""
    q = np.asarray(q, dtype=float)
    single = q.ndim == 1
    qs = q[None] if single else q
    if qs.ndim != 2 or qs.shape[1] != 4:
        raise ValueError(f"q: expected (4,) or (N,4), got shape {q.shape}")
    qs = qs / np.linalg.norm(qs, axis=1, keepdims=True)
    w, x, y, z = qs.T
    R = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )
    return R[0] if single else R


def interpolate_euler321(
    rpy0_rad: tuple[float, float, float], rpy1_rad: tuple[float, float, float], w: float
) -> tuple[float, float, float]:
    """Euler 3-2-1 angles (roll, pitch, yaw; radians) of the rotation a fraction ``w`` (0..1) of the way
    from ``rpy0_rad`` to ``rpy1_rad`` along the shortest arc (slerp): the attitude between two samples
    turning at a constant rate, which interpolating each angle on its own is not once the vehicle tilts
    and turns at once."""
    q0 = quat_wxyz_from_R(R_from_euler321(*rpy0_rad))
    q1 = quat_wxyz_from_R(R_from_euler321(*rpy1_rad))
    dot = float(q0 @ q1)
    if dot < 0.0:  # q and -q are one rotation: take the short way
        q1, dot = -q1, -dot
    theta = float(np.arccos(min(dot, 1.0)))
    if theta < 1e-9:
        q = q0
    else:
        q = (np.sin((1.0 - w) * theta) * q0 + np.sin(w * theta) * q1) / np.sin(theta)  # q(w) = slerp(q0, q1; w)
    return euler321_from_R(R_from_quat_wxyz(q))
