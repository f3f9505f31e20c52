"""mavvo against its best peer on the same trials: success counts and median errors with a paired
bootstrap interval, for the relative-pose benchmarks' "at least the best peer's" goals.

A difference of medians over 90 trials moved by a few hundredths of a degree from one seed to the
next (over a few hundred, still by some thousandths); the interval says whether a gap between two
medians is larger than that. Trials are paired (every method ran on the same tracks and the same
attitude errors), so the bootstrap resamples trial indices and takes both medians on the same
resample.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

SUCCESS_ROT_DEG, SUCCESS_TRANS_DEG = (
    2.0,
    10.0,
)  # a pose is found: rotation error and translation direction error under these
YAW_PRIOR_NOISE_DEG = 1.0  # mavvo is told the flight controller's yaw change, as the odometry tells it, this far off
BOOTSTRAP_DRAWS = 2000
INTERVAL = (5.0, 95.0)  # percentiles of the bootstrap difference: a 90% interval


@dataclass(frozen=True)
class TrialErrors:
    """One method's errors per trial (deg, shape (trials,)), ``inf`` where it gave no pose."""

    rot_deg: np.ndarray
    trans_deg: np.ndarray

    @property
    def found_trials(self) -> np.ndarray:
        """(trials,) bool: rotation under ``SUCCESS_ROT_DEG`` and translation under ``SUCCESS_TRANS_DEG``."""
        return (self.rot_deg < SUCCESS_ROT_DEG) & (self.trans_deg < SUCCESS_TRANS_DEG)

    @property
    def found(self) -> int:
        """How many trials :attr:`found_trials` holds."""
        return int(np.count_nonzero(self.found_trials))


@dataclass(frozen=True)
class PairedMedians:
    """Median errors of mavvo and a peer on the same trials, the 90% bootstrap interval of their
    difference (mavvo minus peer: negative is mavvo lower), and the share of the trials where both gave a
    pose on which mavvo's error is the lower. In the errors' unit: degrees for the relative pose's
    trials, metres for a flight's end error."""

    ours: float
    peer: float
    diff_low: float
    diff_high: float
    ours_lower_share: float


def paired_medians(ours: np.ndarray, peer: np.ndarray, seed: int = 0, draws: int = BOOTSTRAP_DRAWS) -> PairedMedians:
    """Medians of two paired error arrays (trials,) with a bootstrap interval of their difference."""
    a, b = np.asarray(ours, dtype=float), np.asarray(peer, dtype=float)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise ValueError(f"paired_medians: expected two equal 1-D arrays of errors, got shapes {a.shape} and {b.shape}")
    idx = np.random.default_rng(seed).integers(0, a.size, (draws, a.size))
    with np.errstate(invalid="ignore"):  # inf - inf where both medians are failures: no difference to tell
        diffs = np.median(a[idx], axis=1) - np.median(b[idx], axis=1)
        low, high = np.nanpercentile(diffs, INTERVAL) if np.any(np.isfinite(diffs)) else (np.nan, np.nan)
    both = np.isfinite(a) & np.isfinite(b)
    share = float(np.mean(a[both] < b[both])) if np.any(both) else float("nan")
    return PairedMedians(float(np.median(a)), float(np.median(b)), float(low), float(high), share)


def best_peer_cells(ours: TrialErrors, peers: Mapping[str, TrialErrors]) -> list[str]:
    """Markdown cells: success against the peer finding the most, then the rotation and the translation
    median against the peer with the lowest one, each with the paired interval, mavvo's share and the
    two medians over the trials both found.

    The medians over all trials count a failure as an infinite error, so a trial going from no pose to
    a wrong one moves them by a rank without any estimate being better; over the trials both found
    they compare estimates only."""
    if not peers:
        raise ValueError("best_peer_cells: no peer to compare with")
    best = max(peers, key=lambda m: peers[m].found)
    cells = [f"{ours.found} vs {peers[best].found} ({best})"]
    for field in ("rot_deg", "trans_deg"):
        lowest = min(peers, key=lambda m: float(np.median(getattr(peers[m], field))))
        p = paired_medians(getattr(ours, field), getattr(peers[lowest], field))
        both = ours.found_trials & peers[lowest].found_trials
        common = (
            (
                f"on the {np.count_nonzero(both)} both found {np.median(getattr(ours, field)[both]):.4f} vs "
                f"{np.median(getattr(peers[lowest], field)[both]):.4f}"
            )
            if np.any(both)
            else "none found by both"
        )
        # Four decimals: over flat ground the rotation medians are 0.005 deg, and the gaps 0.0001-0.001.
        cells.append(
            f"{p.ours:.4f} vs {p.peer:.4f} ({lowest}): {p.diff_low:+.4f} to {p.diff_high:+.4f}, "
            f"lower on {p.ours_lower_share:.0%}; {common}"
        )
    return cells


BEST_PEER_HEADER = (
    "success: mavvo vs best peer",
    "rotation median (deg): mavvo vs lowest peer, 90% interval of the difference, mavvo lower on; the two medians on the pairs both found",
    "translation median (deg): the same",
)
