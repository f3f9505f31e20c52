"""The general relative pose (5 degrees of freedom, no gravity) by OpenCV, on level-frame bearings.

- :func:`estimate_general_relpose`: the 5-point RANSAC, for when roll/pitch are worse than the relative
  pose was told. The bearings of each view are turned so that their mean points along +z and projected
  onto that virtual image plane (focal length 1), so the estimate works whichever way the camera
  looks; the pose is turned back into the level frames. Seeded through OpenCV's generator.
- :func:`estimate_general_start`: the 5-point's pose without the triangulation that decides its
  translation's sign: a start for the refinement under the attitude prior.
- :func:`estimate_ground_plane_relpose`: the pose a homography of points on the ground gives
  (:func:`decompose_homography`), with no use of roll/pitch beyond choosing which of its solutions has
  the ground's normal: a start for the refinement under the attitude prior that the attitude's error
  cannot have misled.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from mavvo.geometry.frames import cross
from mavvo.jit import kernel

__all__ = [
    "decompose_homography",
    "estimate_general_relpose",
    "estimate_general_start",
    "estimate_ground_plane_relpose",
    "sampson_sq_general",
    "sees_ground",
]

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


def _virtual_images(f1: np.ndarray, f2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """``(V1, V2, p1, p2)``: each view's bearings (N, 3) turned by V (3, 3) so that their mean is along
    +z, and those well in front (M, 2) projected onto the plane z = 1; None with fewer than 5 such."""
    V1, V2 = _towards_z(f1), _towards_z(f2)
    g1, g2 = f1 @ V1.T, f2 @ V2.T
    ok = (g1[:, 2] > _MIN_Z) & (g2[:, 2] > _MIN_Z)
    if np.count_nonzero(ok) < 5:
        return None
    p1 = np.ascontiguousarray(g1[ok, :2] / g1[ok, 2:])
    p2 = np.ascontiguousarray(g2[ok, :2] / g2[ok, 2:])
    return V1, V2, p1, p2


def estimate_general_start(
    f1: np.ndarray, f2: np.ndarray, max_err_rad: float, R_near: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """``(R_2_1, unit t_2_1)`` between the level frames from the general 5-point (no use of
    roll/pitch), as a start for a refinement: of the essential matrix's two rotations the one nearer
    ``R_near`` (3, 3), and the translation's sign left to the caller's cheirality test. Cheaper than
    :func:`estimate_general_relpose` (no triangulation). None when OpenCV finds nothing."""
    virtual = _virtual_images(f1, f2)
    if virtual is None:
        return None
    V1, V2, p1, p2 = virtual
    # USAC_FAST: the same starts as RANSAC on the benchmark's pairs at a fraction of the time; its
    # generator is seeded by its own state, the same on every call.
    E_v, _ = cv2.findEssentialMat(
        p1, p2, focal=1.0, pp=(0.0, 0.0), method=cv2.USAC_FAST, prob=0.99, threshold=max_err_rad
    )
    if E_v is None or E_v.shape != (3, 3):
        return None
    Ra, Rb, t_v = cv2.decomposeEssentialMat(E_v)
    Rs = [V2.T @ R_v @ V1 for R_v in (Ra, Rb)]
    R = max(Rs, key=lambda R: float(np.trace(R_near.T @ R)))  # the larger trace, the smaller the angle between them
    t = V2.T @ t_v[:, 0]
    return R, t / np.linalg.norm(t)


def estimate_general_relpose(
    f1: np.ndarray,
    f2: np.ndarray,
    max_err_rad: float,
    *,
    seed: int = 0,
    confidence: float = 0.99,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(R_2_1, unit t_2_1, E)`` between the level frames of two views from bearings (N, 3), or None
    when OpenCV finds nothing (fewer than 5 usable points)."""
    virtual = _virtual_images(f1, f2)
    if virtual is None:
        return None
    V1, V2, p1, p2 = virtual
    cv2.setRNGSeed(seed)
    E_v, mask = cv2.findEssentialMat(
        p1, p2, focal=1.0, pp=(0.0, 0.0), method=cv2.RANSAC, prob=confidence, threshold=max_err_rad
    )
    if E_v is None or E_v.shape != (3, 3):
        return None
    _, R_v, t_v, _ = cv2.recoverPose(E_v, p1, p2, focal=1.0, pp=(0.0, 0.0), mask=mask)
    R = V2.T @ R_v @ V1
    t = V2.T @ t_v[:, 0]
    return R, t / np.linalg.norm(t), V2.T @ E_v @ V1


def _below_horizon(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """(N,) bool: the correspondences well below the horizon in both level frames."""
    return (f1[:, 2] > _GROUND_MIN_Z) & (f2[:, 2] > _GROUND_MIN_Z)


def _mostly(below: np.ndarray) -> bool:
    return bool(np.count_nonzero(below) >= max(8, _GROUND_MIN_SHARE * len(below)))


def sees_ground(f1: np.ndarray, f2: np.ndarray) -> bool:
    """True when most correspondences (bearings (N, 3) in the level frames) are well below the horizon
    in both views: the scene may be the ground plane, whose two poses the 5-point cannot tell apart."""
    return _mostly(_below_horizon(f1, f2))


def estimate_ground_plane_relpose(
    f1: np.ndarray, f2: np.ndarray, max_err_rad: float, *, seed: int = 0
) -> tuple[np.ndarray, np.ndarray] | None:
    """``(R_2_1, t_2_1 / d)`` between the level frames of two views whose bearings (N, 3) see mostly
    the ground, d the ground's distance from view 1 (so that ``|t_2_1 / d|`` is about the parallax the
    translation makes, in radians, looking down), from a general homography (8 degrees of freedom:
    OpenCV's RANSAC at ``2 * max_err_rad`` on the level frames' image planes) decomposed by
    :func:`decompose_homography`; of its solutions the one whose plane normal in view 1 is nearest the
    vertical. Roll/pitch errors go into ``R_2_1`` and the normal, not into the translation. None when
    under 80% of the points are well below the horizon in both views, or the homography is degenerate."""
    below = _below_horizon(f1, f2)
    if not _mostly(below):
        return None
    p1 = np.ascontiguousarray(f1[below, :2] / f1[below, 2:])
    p2 = np.ascontiguousarray(f2[below, :2] / f2[below, 2:])
    cv2.setRNGSeed(seed)
    H, _ = cv2.findHomography(p1, p2, cv2.RANSAC, 2.0 * max_err_rad)
    if H is None:
        return None
    solutions = decompose_homography(H, p1, p2)
    if not solutions:
        return None
    # H = R + t n^T / d: its solutions come in pairs of signs and in the plane's two poses; the
    # ground's normal is +-z in a level frame whatever the translation.
    R, t_per_d, _ = max(solutions, key=lambda sol: abs(float(sol[2][2])))
    return R, t_per_d


def decompose_homography(
    H: np.ndarray, p1: np.ndarray, p2: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The poses ``(R, t / d, n)`` of a calibrated homography H (3, 3) with ``x2 ~ (R + t n^T / d) x1``
    (Ma, Soatto, Kosecka and Sastry, An Invitation to 3-D Vision, 2004, section 5.3.3): four, two
    pairs that differ in sign; none where H is degenerate. H is scaled so its middle singular value is
    1 and signed so the image points p1, p2 (M, 2) lie in front (``x2^T H x1 > 0``). Unlike OpenCV's
    ``decomposeHomographyMat``, which calls a homography within 1e-3 of a rotation one (no plane, no
    translation), this keeps the translation of a pixel's parallax."""
    Rs, ts, ns = _decompose_homography_kernel(
        np.ascontiguousarray(H, dtype=np.float64),
        np.ascontiguousarray(p1, dtype=np.float64),
        np.ascontiguousarray(p2, dtype=np.float64),
    )
    return [(Rs[k], ts[k], ns[k]) for k in range(len(Rs))]


@kernel
def _decompose_homography_kernel(
    H: np.ndarray, p1: np.ndarray, p2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`decompose_homography`, compiled: (k, 3, 3) rotations, (k, 3) translations, (k, 3) normals, k = 4 or 0."""
    _, sv, Vt = np.linalg.svd(H)
    if not sv[1] > 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    Hn = H / sv[1]
    ahead = 0  # points with x2^T H x1 > 0, x1 = (px, py, 1)
    for i in range(p1.shape[0]):
        px, py = p1[i, 0], p1[i, 1]
        h0 = Hn[0, 0] * px + Hn[0, 1] * py + Hn[0, 2]
        h1 = Hn[1, 0] * px + Hn[1, 1] * py + Hn[1, 2]
        h2 = Hn[2, 0] * px + Hn[2, 1] * py + Hn[2, 2]
        ahead += p2[i, 0] * h0 + p2[i, 1] * h1 + h2 > 0.0
    if 2 * ahead < p1.shape[0]:
        Hn = -Hn
    # H^T H = V diag(s1^2, 1, s3^2) V^T, from H's own singular vectors
    s1, s3 = (sv[0] / sv[1]) ** 2, (sv[2] / sv[1]) ** 2
    span = s1 - s3
    if not span > 1e-12:  # to rounding: a real homography's noise alone is far above it
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3))  # a rotation: no plane, no translation
    v1, v2, v3 = Vt[0].copy(), Vt[1].copy(), Vt[2].copy()
    a, b = math.sqrt(max(1.0 - s3, 0.0)), math.sqrt(max(s1 - 1.0, 0.0))
    Rs, ts, ns = np.zeros((4, 3, 3)), np.zeros((4, 3)), np.zeros((4, 3))
    for k in range(2):
        u = (a * v1 + (b if k == 0 else -b) * v3) / math.sqrt(span)  # the plane's two poses
        n = np.cross(v2, u)
        Hv2, Hu = Hn @ v2, Hn @ u
        U = np.empty((3, 3))
        W = np.empty((3, 3))
        U[:, 0], U[:, 1], U[:, 2] = v2, u, n
        W[:, 0], W[:, 1], W[:, 2] = Hv2, Hu, np.cross(Hv2, Hu)
        R = W @ U.T
        t = (Hn - R) @ n
        Rs[2 * k], ts[2 * k], ns[2 * k] = R, t, n
        Rs[2 * k + 1], ts[2 * k + 1], ns[2 * k + 1] = R, -t, -n
    return Rs, ts, ns
