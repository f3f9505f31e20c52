"""Compile every kernel of mavvo once, so the cache holds them before the service starts.

    python -m mavvo.estimation.warmup

``make setup`` runs it for the checkout and ``make install`` for the installed service's cache
(``NUMBA_CACHE_DIR``, which the systemd unit sets): a cold start compiles for several seconds, a warm one
loads the kernels in a fraction of a second (docs/benchmarks.md, "Start-up").
"""

from __future__ import annotations

import sys
import time

import numpy as np

from mavvo.estimation.general5pt import decompose_homography
from mavvo.estimation.relpose import estimate_relpose_known_gravity, estimate_upright_relpose
from mavvo.estimation.relpose_types import RelposeOptions
from mavvo.geometry import solve_upright_3pt
from mavvo.geometry.affine_consensus import off_affine_consensus
from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.medians import median, weighted_median
from mavvo.geometry.triangulation import triangulate_midpoints
from mavvo.jit import refresh_cache

__all__ = ["warm_kernels"]


def _scene(rng: np.random.Generator, n: int, ground: bool) -> tuple[np.ndarray, np.ndarray]:
    """Level-frame bearings (N, 3) of points seen from two views 1 m apart, 0.1 rad of yaw."""
    xy = rng.uniform(-6.0, 6.0, (n, 2))
    z = np.full(n, 10.0) if ground else rng.uniform(6.0, 14.0, n)
    p1 = np.column_stack([xy, z])
    c, s = np.cos(0.1), np.sin(0.1)
    p2 = p1 @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + np.array([1.0, 0.2, 0.1])
    return p1 / np.linalg.norm(p1, axis=1)[:, None], p2 / np.linalg.norm(p2, axis=1)[:, None]


def warm_kernels() -> float:
    """Run the relative pose on small synthetic scenes through every path (exact and uncertain
    attitude, a 3-D scene, flat ground, a pure rotation, the yaw prior, pixels in), and the medians:
    each kernel is compiled, or
    loaded from the cache (first emptied of kernels compiled from other sources: :func:`refresh_cache`).
    Returns the CPU seconds it took."""
    t0 = time.process_time()
    refresh_cache()
    rng = np.random.default_rng(0)
    for ground in (False, True):
        f1, f2 = _scene(rng, 60, ground)
        for sigma in (None, (0.003, 0.003)):
            estimate_upright_relpose(f1, f2, max_err_rad=0.002, attitude_sigma_rad=sigma, yaw_prior_rad=0.1)
        estimate_upright_relpose(f1, f1, max_err_rad=0.002, options=RelposeOptions())  # no baseline
    solve_upright_3pt(f1[:3], f2[:3])
    # The ground start's decomposition, which the scenes above (parallax to spare) never need.
    decompose_homography(
        np.eye(3) + np.outer([0.01, 0.0, 0.0], [0.0, 0.0, 1.0]), f1[:, :2] / f1[:, 2:], f2[:, :2] / f2[:, 2:]
    )
    # The pixel entry (bearings of an undistorted pinhole, the rotation checks), as the frontend and
    # the odometry use them, the medians and the triangulation of the odometry and the scale.
    camera = CameraModel(640, 480, 500.0, 500.0, 320.0, 240.0)
    uv = 500.0 * f1[:, :2] / f1[:, 2:] + np.array([320.0, 240.0])
    estimate_relpose_known_gravity(uv, uv + 3.0, camera, np.eye(3), np.eye(3))
    median(f1[:, 0])
    weighted_median(f1[:, 0], f1[:, 2])
    triangulate_midpoints(f1, f2, np.eye(3), np.array([1.0, 0.0, 0.0]), 0.001)
    off_affine_consensus(uv, uv + 3.0, np.ones(len(uv), dtype=bool), 8.0)  # the frontend's check per pair
    return time.process_time() - t0


def main() -> int:
    # Said first: on a cold cache (the first run after an install or a change of the kernels' sources)
    # the compilation takes about a minute with nothing else on screen.
    print(
        "mavvo kernels: loading, or compiling where the cache has none (the first time: about a minute) ...",
        file=sys.stderr,
        flush=True,
    )
    seconds = warm_kernels()
    print(f"mavvo kernels ready ({seconds:.1f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
