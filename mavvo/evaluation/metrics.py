"""Trajectory error metrics, pure functions on pose series.

- Absolute trajectory error (ATE): RMSE of position differences after the best rigid (SE(3)) alignment
  of the estimate onto the truth (Umeyama 1991); the similarity (Sim(3)) alignment and its scale are
  reported too, since a scale error is what a monocular system gets wrong first.
- Relative pose error (RPE) per metre and per second: for each pose, the pose a given path length (or
  time) later; the error of the estimated relative motion against the true one, translation divided by
  the true path length between them (so 0.01 is 1% drift) or by the time, rotation in degrees likewise.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from mavvo.geometry.frames import R_from_quat_wxyz, quat_wxyz_from_R, rotation_angle_rad


@dataclass(frozen=True)
class PoseSeries:
    """Poses over time: ``timestamps_s`` (N,), ``positions_xyz_m`` (N,3), ``orientations_quat_wxyz``
    (N,4) giving R_world_body."""

    timestamps_s: np.ndarray
    positions_xyz_m: np.ndarray
    orientations_quat_wxyz: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps_s, dtype=float)
        p = np.asarray(self.positions_xyz_m, dtype=float)
        q = np.asarray(self.orientations_quat_wxyz, dtype=float)
        n = len(t)
        if t.ndim != 1 or p.shape != (n, 3) or q.shape != (n, 4):
            raise ValueError(f"PoseSeries: expected (N,), (N,3), (N,4); got {t.shape}, {p.shape}, {q.shape}")
        if n and (not np.all(np.isfinite(t)) or not np.all(np.isfinite(p)) or not np.all(np.isfinite(q))):
            raise ValueError("PoseSeries: non-finite timestamps, positions or orientations")
        if np.any(np.diff(t) < 0):
            raise ValueError("PoseSeries: timestamps must not decrease")
        object.__setattr__(self, "timestamps_s", t)
        object.__setattr__(self, "positions_xyz_m", p)
        object.__setattr__(self, "orientations_quat_wxyz", q)

    @classmethod
    def from_rotations(
        cls, timestamps_s: np.ndarray, positions_xyz_m: np.ndarray, R_world_body: np.ndarray
    ) -> "PoseSeries":
        return cls(
            np.asarray(timestamps_s, dtype=float),
            positions_xyz_m,
            quat_wxyz_from_R(np.asarray(R_world_body, dtype=float)),
        )

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @property
    def rotations(self) -> np.ndarray:
        """(N,3,3) R_world_body."""
        return R_from_quat_wxyz(self.orientations_quat_wxyz)

    def path_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions_xyz_m, axis=0), axis=1).sum()) if len(self) > 1 else 0.0

    def transformed(self, R: np.ndarray, t: np.ndarray, scale: float = 1.0) -> "PoseSeries":
        """The series moved by ``x -> scale R x + t`` (orientations rotated by R)."""
        return PoseSeries.from_rotations(self.timestamps_s, scale * self.positions_xyz_m @ R.T + t, R @ self.rotations)


def align_umeyama(src_xyz: np.ndarray, dst_xyz: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) minimising sum |dst - (s R src + t)|^2 over rotations R (and s > 0 if with_scale,
    else s = 1), for (N,3) point rows, N >= 3 (Umeyama, PAMI 1991)."""
    src = np.asarray(src_xyz, dtype=float)
    dst = np.asarray(dst_xyz, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"align_umeyama: expected two (N,3) arrays with N >= 3, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_s = (a * a).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s) if with_scale and var_s > 0 else 1.0
    return R, mu_d - s * R @ mu_s, s


def associate(est: PoseSeries, gt: PoseSeries, max_dt_s: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i_est, i_gt) matching each estimate to the nearest truth within ``max_dt_s``."""
    if len(gt) == 0 or len(est) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    j = np.clip(np.searchsorted(gt.timestamps_s, est.timestamps_s), 1, len(gt) - 1)
    left = gt.timestamps_s[j - 1]
    right = gt.timestamps_s[j]
    j = np.where(np.abs(est.timestamps_s - left) <= np.abs(right - est.timestamps_s), j - 1, j)
    ok = np.abs(gt.timestamps_s[j] - est.timestamps_s) <= max_dt_s
    return np.flatnonzero(ok), j[ok]


def _stats(x: np.ndarray) -> dict[str, float]:
    if len(x) == 0:
        return {"rmse": float("nan"), "mean": float("nan"), "median": float("nan"), "max": float("nan")}
    return {
        "rmse": float(np.sqrt(np.mean(x * x))),
        "mean": float(np.mean(x)),
        "median": float(np.median(x)),
        "max": float(np.max(x)),
    }


def position_errors_m(est: PoseSeries, gt: PoseSeries) -> np.ndarray:
    """(N,) distances between matched positions (same length series)."""
    return np.linalg.norm(est.positions_xyz_m - gt.positions_xyz_m, axis=1)


def relative_errors(est: PoseSeries, gt: PoseSeries, delta: float, unit: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair (translation error / span, rotation error deg / span) with spans of ``delta`` metres of
    true path (``unit="m"``) or seconds (``unit="s"``). Matched, equal-length series."""
    if unit == "m":
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt.positions_xyz_m, axis=0), axis=1))])
    elif unit == "s":
        along = gt.timestamps_s - gt.timestamps_s[0] if len(gt) else np.zeros(0)
    else:
        raise ValueError(f"unit: expected 'm' or 's', got {unit!r}")
    j = np.searchsorted(along, along + delta)
    i = np.flatnonzero(j < len(along))
    j = j[i]
    Rg, Re = gt.rotations, est.rotations
    pg, pe = gt.positions_xyz_m, est.positions_xyz_m
    trans, rot = [], []
    for a, b in zip(i, j):
        span = along[b] - along[a]
        if span <= 0:
            continue
        dR_g, dp_g = Rg[a].T @ Rg[b], Rg[a].T @ (pg[b] - pg[a])
        dR_e, dp_e = Re[a].T @ Re[b], Re[a].T @ (pe[b] - pe[a])
        trans.append(np.linalg.norm(dR_g.T @ (dp_e - dp_g)) / span)
        rot.append(np.degrees(rotation_angle_rad(dR_e, dR_g)) / span)
    return np.array(trans), np.array(rot)


@dataclass(frozen=True)
class Evaluation:
    """Errors of an estimated trajectory against the truth (see the module docstring).

    Lengths in metres, angles in degrees; ``rpe_*_per_m`` translation is a fraction of the path.
    """

    poses: int
    duration_s: float
    path_length_m: float
    ate_se3_m: dict
    ate_sim3_m: dict
    sim3_scale: float
    ate_se3_rmse_percent_of_path: float
    rpe_translation_per_m: dict
    rpe_rotation_deg_per_m: dict
    rpe_translation_m_per_s: dict
    rpe_rotation_deg_per_s: dict
    rpe_delta_m: float
    rpe_delta_s: float

    def to_dict(self) -> dict:
        return asdict(self)


def evaluate(
    est: PoseSeries, gt: PoseSeries, *, rpe_delta_m: float = 10.0, rpe_delta_s: float = 1.0
) -> tuple[Evaluation, PoseSeries]:
    """Errors of ``est`` against ``gt`` (matched, equal length, N >= 3), and ``est`` after SE(3)
    alignment onto ``gt`` (for plots)."""
    if len(est) != len(gt):
        raise ValueError(f"evaluate: expected matched series, got {len(est)} and {len(gt)} poses")
    if len(est) < 3:
        raise ValueError(f"evaluate: need at least 3 poses, got {len(est)}")
    R, t, _ = align_umeyama(est.positions_xyz_m, gt.positions_xyz_m, with_scale=False)
    aligned = est.transformed(R, t)
    Rs, ts, s = align_umeyama(est.positions_xyz_m, gt.positions_xyz_m, with_scale=True)
    e_se3 = position_errors_m(aligned, gt)
    e_sim3 = position_errors_m(est.transformed(Rs, ts, s), gt)
    length = gt.path_length_m()
    tm, rm = relative_errors(est, gt, rpe_delta_m, "m")
    tsec, rsec = relative_errors(est, gt, rpe_delta_s, "s")
    se3 = _stats(e_se3)
    ev = Evaluation(
        poses=len(est),
        duration_s=float(gt.timestamps_s[-1] - gt.timestamps_s[0]),
        path_length_m=length,
        ate_se3_m=se3,
        ate_sim3_m=_stats(e_sim3),
        sim3_scale=s,
        ate_se3_rmse_percent_of_path=100.0 * se3["rmse"] / length if length > 0 else float("nan"),
        rpe_translation_per_m=_stats(tm),
        rpe_rotation_deg_per_m=_stats(rm),
        rpe_translation_m_per_s=_stats(tsec),
        rpe_rotation_deg_per_s=_stats(rsec),
        rpe_delta_m=rpe_delta_m,
        rpe_delta_s=rpe_delta_s,
    )
    return ev, aligned
