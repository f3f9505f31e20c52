"""The two-view models :func:`mavvo.estimation.ransac.lo_ransac` estimates, on level-frame bearings.

Each is an :class:`mavvo.estimation.ransac.Estimator`: a sample size, a batched generator from a
minimal solver, MSAC costs and squared residuals from :mod:`mavvo.geometry.residuals` (so their errors
compare under one noise sigma for model selection), and a refinement on inliers.

- :class:`UprightEssential`: ``E = [t]x Rz(yaw)``, 3 points (the paper's solver, batched), or 4 or 5
  (its 4-point and linear 5-point); refined by Gauss-Newton on the upright manifold, plus the 4-point
  or linear 5-point least squares on the inliers when asked. Models: e vectors (M, 6).
- :class:`GroundHomography`: the known-gravity ground-plane homography, 2 points (Saurer et al.);
  refined in closed form. Models: (M, 3, 3).
- :class:`PureRotation`: no baseline; 1 point gives the yaw, the refinement all three axes in closed
  form. Models: (M, 3, 3).
"""

from __future__ import annotations

import cmath
import math
from typing import Literal

import numpy as np

from mavvo.estimation.ransac import CostsFromResiduals
from mavvo.geometry import essential_to_vector, solve_upright_4pt, solve_upright_linear5pt
from mavvo.geometry.frames import rot_z
from mavvo.geometry.ground_2pt import homography_from_similarity, solve_ground_2pt_samples
from mavvo.geometry.refine import fit_rotation, gauss_newton_upright, ground_similarity, upright_vector
from mavvo.geometry.residuals import ground_msac, ground_sq, rotation_sq, sampson_msac_upright, sampson_sq_upright
from mavvo.geometry.upright_3pt import solve_samples as solve_upright_3pt_samples
from mavvo.geometry.upright_pose import upright_pose_kernel
from mavvo.jit import kernel

__all__ = ["UprightEssential", "GroundHomography", "PureRotation", "upright_e", "decompose_upright", "yaw_of"]

MinimalSolver = Literal["3pt", "4pt", "linear5pt"]
NonminimalSolver = Literal["none", "4pt", "linear5pt"]
SAMPLE_SIZE = {"3pt": 3, "4pt": 4, "linear5pt": 5}


def yaw_of(R: np.ndarray) -> float:
    """Yaw (Euler 3-2-1) of a rotation (3, 3)."""
    return float(np.arctan2(R[1, 0], R[0, 0]))


def upright_e(yaw: float, t: np.ndarray) -> np.ndarray:
    """e vector (6,) of ``[t]x Rz(yaw)``."""
    return upright_vector(float(yaw), np.asarray(t, dtype=np.float64))


def decompose_upright(e: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(yaw, unit t) of an upright e (6,), cheirality decided on the given unit bearings; None without any."""
    n = float(np.linalg.norm(e))
    if len(f1) == 0 or not n > 0:
        return None
    yaw, t = upright_pose_kernel(
        np.ascontiguousarray(e, dtype=np.float64) / n, np.ascontiguousarray(f1), np.ascontiguousarray(f2)
    )
    return float(yaw), t


@kernel
def _near_yaw(e: np.ndarray, prior: float, tol: float) -> np.ndarray:
    """(M,) bool: the yaw of each upright hypothesis e (M, 6) is within ``tol`` of ``prior``.

    For ``E = [t]x Rz(yaw)`` with |t| = 1: ``-conj(gamma) * beta = exp(i yaw) |t_xy|^2`` fixes the yaw
    whenever t has a horizontal part; for t along z only ``alpha^2 = -t_z^2 exp(2i yaw)`` is left,
    which fixes it up to pi.
    """
    out = np.empty(e.shape[0], dtype=np.bool_)
    ref = complex(math.cos(prior), math.sin(prior))
    for m in range(e.shape[0]):
        alpha, beta, gamma = complex(e[m, 2], e[m, 1]), complex(e[m, 0], e[m, 3]), complex(e[m, 4], e[m, 5])
        a2, b2 = abs(alpha) ** 2, abs(beta) ** 2
        # A solver's E has the upright form exactly, so even a small horizontal part fixes the yaw.
        if b2 > 1e-9 * (a2 + b2):
            d = abs(cmath.phase(-gamma.conjugate() * beta * ref.conjugate()))
        else:
            d = 0.5 * abs(cmath.phase(-(alpha * alpha) * (ref * ref).conjugate()))
        out[m] = d <= tol
    return out


@kernel
def _decompose_and_refine(e: np.ndarray, f1: np.ndarray, f2: np.ndarray, steps: int) -> np.ndarray:
    """The upright e (6,) refitted on the inliers f1, f2 (N, 3): decomposed with cheirality
    (:func:`decompose_upright`), then ``steps`` Gauss-Newton steps on yaw and translation (none with
    fewer than 3 points); empty (0,) without inliers or for e = 0. One compiled call per local
    optimisation."""
    n = math.sqrt(np.sum(e * e))
    if f1.shape[0] == 0 or not n > 0.0:
        return np.zeros(0)
    yaw, t = upright_pose_kernel(e / n, f1, f2)
    x = np.zeros(8)
    x[0], x[1:4] = yaw, t
    if f1.shape[0] >= 3:
        gauss_newton_upright(x, f1, f2, steps, False, np.zeros(4), 1.0, 0.0)
    return upright_vector(math.atan2(math.sin(x[0]), math.cos(x[0])), x[1:4])


class UprightEssential:
    """The upright essential matrix between two level frames (see the module docstring).

    ``yaw_prior_rad``: hypotheses further than ``yaw_tolerance_rad`` from it are dropped (a nadir camera
    over flat ground sees a twin at yaw + 180 deg). ``lo_steps``: Gauss-Newton steps per refinement.
    """

    def __init__(
        self,
        f1: np.ndarray,
        f2: np.ndarray,
        *,
        solver: MinimalSolver = "3pt",
        nonminimal: NonminimalSolver = "none",
        lo_steps: int = 3,
        yaw_prior_rad: float | None = None,
        yaw_tolerance_rad: float = math.pi,
    ) -> None:
        self.f1, self.f2 = f1, f2
        self.num_data = len(f1)
        self.sample_size = SAMPLE_SIZE[solver]
        self.solver, self.nonminimal, self.lo_steps = solver, nonminimal, lo_steps
        self.yaw_prior_rad, self.yaw_tolerance_rad = yaw_prior_rad, yaw_tolerance_rad
        self._xyz = (np.ascontiguousarray(f1.T), np.ascontiguousarray(f2.T))  # (3, N) each: the scoring kernel's layout
        self._sub: tuple[np.ndarray, np.ndarray, np.ndarray] | None = (
            None  # (rows, f1, f2 of them as (3, n)): the loop's fixed subset
        )

    def generate(self, samples: np.ndarray) -> np.ndarray:
        f1, f2 = self.f1, self.f2
        if self.solver == "3pt":
            e, valid = solve_upright_3pt_samples(f1.take(samples, axis=0), f2.take(samples, axis=0))
            e = e[valid]
        else:
            solve = solve_upright_4pt if self.solver == "4pt" else solve_upright_linear5pt
            out = [essential_to_vector(solve(f1[row], f2[row])) for row in samples]
            e = np.concatenate(out) if out else np.zeros((0, 6))
        if self.yaw_prior_rad is not None and len(e):
            e = e[_near_yaw(e, float(self.yaw_prior_rad), float(self.yaw_tolerance_rad))]
        return e

    def costs(self, models: np.ndarray, thr_sq: float, rows: np.ndarray | None = None) -> np.ndarray:
        if rows is None:
            return sampson_msac_upright(models, *self._xyz, thr_sq)
        if self._sub is None or self._sub[0] is not rows:
            self._sub = (rows, np.ascontiguousarray(self._xyz[0][:, rows]), np.ascontiguousarray(self._xyz[1][:, rows]))
        return sampson_msac_upright(models, self._sub[1], self._sub[2], thr_sq)

    def residuals_sq(self, models: np.ndarray) -> np.ndarray:
        return sampson_sq_upright(models, self.f1, self.f2)

    def refine(self, model: np.ndarray, inliers: np.ndarray) -> np.ndarray:
        f1, f2 = self.f1.compress(inliers, axis=0), self.f2.compress(inliers, axis=0)
        out = []
        if self.nonminimal != "none" and len(f1) >= SAMPLE_SIZE[self.nonminimal]:
            solve = solve_upright_4pt if self.nonminimal == "4pt" else solve_upright_linear5pt
            e = essential_to_vector(solve(f1, f2))
            out += list(e / np.linalg.norm(e, axis=1, keepdims=True))
        if self.lo_steps > 0:
            e = _decompose_and_refine(np.ascontiguousarray(model[0], dtype=np.float64), f1, f2, self.lo_steps)
            if e.size:
                out.append(e)
        return np.array(out).reshape(-1, 6)


@kernel
def _ground_refit(f1: np.ndarray, f2: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """The ground homography (3, 3) fitted on the inliers ((N,) bool) in closed form
    (:func:`~mavvo.geometry.refine.ground_similarity`); NaN where that has no answer."""
    H = np.full((3, 3), np.nan)
    ok, m, tau = ground_similarity(f1[inliers], f2[inliers])
    if ok:
        homography_from_similarity(m, tau, H)
    return H


class GroundHomography:
    """The ground-plane homography ``x_2 ~ H x_1`` of known gravity (see the module docstring); data
    are the correspondences given, which the caller picks below the horizon in both views."""

    sample_size = 2

    def __init__(self, f1: np.ndarray, f2: np.ndarray) -> None:
        self.f1, self.f2 = np.ascontiguousarray(f1), np.ascontiguousarray(f2)
        self.num_data = len(f1)
        self._sub: tuple[np.ndarray, np.ndarray, np.ndarray] | None = (
            None  # (rows, f1, f2 of them): the loop's fixed subset
        )

    def generate(self, samples: np.ndarray) -> np.ndarray:
        H, valid = solve_ground_2pt_samples(self.f1.take(samples, axis=0), self.f2.take(samples, axis=0))
        return H[valid]

    def costs(self, models: np.ndarray, thr_sq: float, rows: np.ndarray | None = None) -> np.ndarray:
        if rows is None:
            return ground_msac(models, self.f1, self.f2, thr_sq)
        if self._sub is None or self._sub[0] is not rows:
            self._sub = (rows, self.f1[rows], self.f2[rows])
        return ground_msac(models, self._sub[1], self._sub[2], thr_sq)

    def residuals_sq(self, models: np.ndarray) -> np.ndarray:
        return ground_sq(models, self.f1, self.f2)

    def refine(self, model: np.ndarray, inliers: np.ndarray) -> np.ndarray:
        H = _ground_refit(self.f1, self.f2, inliers)
        return np.zeros((0, 3, 3)) if np.isnan(H[0, 0]) else H[None]


class PureRotation(CostsFromResiduals):
    """A rotation without baseline, ``f2 = R f1`` (see the module docstring). Points along the vertical
    in either view say nothing about yaw and are not sampled."""

    sample_size = 1

    def __init__(self, f1: np.ndarray, f2: np.ndarray) -> None:
        self.f1, self.f2 = f1, f2
        self._h1 = f1[:, 0] + 1j * f1[:, 1]
        self._h2 = f2[:, 0] + 1j * f2[:, 1]
        self.usable = np.nonzero((np.abs(self._h1) > 1e-6) & (np.abs(self._h2) > 1e-6))[0]
        self.num_data = len(f1)

    def generate(self, samples: np.ndarray) -> np.ndarray:
        pick = samples[:, 0]
        pick = pick[np.isin(pick, self.usable)]
        return np.array([rot_z(y) for y in np.angle(self._h2[pick] * np.conj(self._h1[pick]))]).reshape(-1, 3, 3)

    def residuals_sq(self, models: np.ndarray) -> np.ndarray:
        return rotation_sq(models, self.f1, self.f2)

    def residuals_on(self, models: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return rotation_sq(models, self.f1[rows], self.f2[rows])

    def refine(self, model: np.ndarray, inliers: np.ndarray) -> np.ndarray:
        R = fit_rotation(self.f1[inliers], self.f2[inliers])
        return np.zeros((0, 3, 3)) if R is None else R[None]
