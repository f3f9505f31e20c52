"""The general relative pose (5 degrees of freedom, no gravity) by OpenCV, on level-frame bearings.

- :func:`estimate_general_relpose`: the 5-point RANSAC, for when roll/pitch are worse than the relative
  pose was told. The bearings of each view are turned so that their mean points along +z and projected
  onto that virtual image plane (focal length 1), so the estimate works whichever way the camera
  looks; the pose is turned back into the level frames. Seeded through OpenCV's generator.
- :func:`estimate_ground_plane_relpose`: the pose a homography of points on the ground gives, with no
  use of roll/pitch beyond choosing which of its solutions has the ground's normal: a start for the
  refinement under the attitude prior that the attitude's error cannot have misled.
"""

from __future__ import annotations

import cv2
import numpy as np

from mavvo.geometry.frames import cross

__all__ = ["estimate_general_relpose", "estimate_ground_plane_relpose", "sampson_sq_general"]

_MIN_Z = 0.1  # bearings this close to a virtual image's horizon are left out of the estimate
_GROUND_MIN_Z = 0.3  # ground points: at least 17 deg below the horizon in both views (level z is down)
_GROUND_MIN_SHARE = 0.8  # ... and this share of all the points, or the scene is not ground


def _towards_z(f: np.ndarray) -> np.ndarray:
    """A rotation V (3, 3) with V @ mean(f) along +z."""
    m = f.mean(axis=0)
    m /= np.linalg.norm(m)
    axis = cross(m, np.array([0.0, 0.0, 1.0]))
    s, c = float(np.linalg.norm(axis)), float(m[2])
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return cv2.Rodrigues(axis / s * np.arctan2(s, c))[0]


def sampson_sq_general(E: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Squared Sampson errors (N,) on the bearings of any essential matrix E (3, 3) (as
    :func:`mavvo.geometry.residuals.sampson_sq_upright`: ``r^2 / (|E f1|^2 + |E^T f2|^2 - 2 r^2)``)."""
    Ef1 = f1 @ E.T
    Etf2 = f2 @ E
    r = np.einsum("ij,ij->i", f2, Ef1)
    den = np.einsum("ij,ij->i", Ef1, Ef1) + np.einsum("ij,ij->i", Etf2, Etf2) - 2.0 * r * r
    return np.where(den > 1e-300, r * r / np.maximum(den, 1e-300), np.inf)


def estimate_general_relpose(
    f1: np.ndarray, f2: np.ndarray, max_err_rad: float, *, seed: int = 0, confidence: float = 0.99,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(R_2_1, unit t_2_1, E)`` between the level frames of two views from bearings (N, 3), or None
    when OpenCV finds nothing (fewer than 5 usable points)."""
    V1, V2 = _towards_z(f1), _towards_z(f2)
    g1, g2 = f1 @ V1.T, f2 @ V2.T
    ok = (g1[:, 2] > _MIN_Z) & (g2[:, 2] > _MIN_Z)
    if np.count_nonzero(ok) < 5:
        return None
    p1 = np.ascontiguousarray(g1[ok, :2] / g1[ok, 2:])
    p2 = np.ascontiguousarray(g2[ok, :2] / g2[ok, 2:])
    cv2.setRNGSeed(seed)
    E_v, mask = cv2.findEssentialMat(p1, p2, focal=1.0, pp=(0.0, 0.0), method=cv2.RANSAC, prob=confidence, threshold=max_err_rad)
    if E_v is None or E_v.shape != (3, 3):
        return None
    _, R_v, t_v, _ = cv2.recoverPose(E_v, p1, p2, focal=1.0, pp=(0.0, 0.0), mask=mask)
    R = V2.T @ R_v @ V1
    t = V2.T @ t_v[:, 0]
    return R, t / np.linalg.norm(t), V2.T @ E_v @ V1


def estimate_ground_plane_relpose(f1: np.ndarray, f2: np.ndarray, max_err_rad: float, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """``(R_2_1, unit t_2_1)`` between the level frames of two views whose bearings (N, 3) see mostly
    the ground, from a general homography (8 degrees of freedom: OpenCV's RANSAC at ``2 * max_err_rad``
    on the level frames' image planes), decomposed; of its solutions the one whose plane normal in view
    1 is nearest the vertical. Roll/pitch errors go into ``R_2_1`` and the normal, not into the
    translation. None when under 80% of the points are well below the horizon in both views, or the
    homography is degenerate."""
    below = (f1[:, 2] > _GROUND_MIN_Z) & (f2[:, 2] > _GROUND_MIN_Z)
    if np.count_nonzero(below) < max(8, _GROUND_MIN_SHARE * len(f1)):
        return None
    p1 = np.ascontiguousarray(f1[below, :2] / f1[below, 2:])
    p2 = np.ascontiguousarray(f2[below, :2] / f2[below, 2:])
    cv2.setRNGSeed(seed)
    H, _ = cv2.findHomography(p1, p2, cv2.RANSAC, 2.0 * max_err_rad)
    if H is None:
        return None
    _, Rs, ts, normals = cv2.decomposeHomographyMat(H, np.eye(3))
    # H = R + t n^T / d: its solutions come in pairs of signs and in the plane's two poses; the
    # ground's normal is +-z in a level frame whatever the translation.
    best = max(range(len(Rs)), key=lambda i: abs(float(normals[i][2, 0])))
    t = ts[best][:, 0]
    nt = float(np.linalg.norm(t))
    return (Rs[best], t / nt) if nt > 1e-12 else None
