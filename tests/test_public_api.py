"""What users import: the entry points from their package's ``__init__``, one name per module (the old
flat names are gone), and a keyword an earlier release had, still taken with a warning."""

from __future__ import annotations

import importlib

import numpy as np
import pytest


def test_entry_points_import_from_their_packages() -> None:
    from mavvo.estimation import RelposeOptions, estimate_relpose_known_gravity, estimate_upright_relpose
    from mavvo.geometry import CameraModel, solve_upright_3pt
    from mavvo.sim.scenarios import load_scenario, scenario_names

    assert estimate_upright_relpose.__module__ == "mavvo.estimation.relpose"
    assert estimate_relpose_known_gravity.__module__ == "mavvo.estimation.relpose"
    assert RelposeOptions().confidence == pytest.approx(0.99)
    assert CameraModel.__module__ == "mavvo.geometry.camera_model"
    assert solve_upright_3pt.__module__ == "mavvo.geometry.upright_3pt"
    assert "hover" in scenario_names() and load_scenario("hover").name == "hover"


@pytest.mark.parametrize("old", ["mavvo.frames", "mavvo.relpose", "mavvo.settings", "sim", "sim.world"])
def test_old_names_are_gone(old: str) -> None:
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(old)


def _bearings(seed: int, n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Points 2-6 m below a camera that moved 0.3 m sideways and turned 10 deg about the vertical."""
    rng = np.random.default_rng(seed)
    X1 = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), rng.uniform(2, 6, n)])
    yaw = np.radians(10.0)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    X2 = X1 @ R.T + np.array([0.3, 0.0, 0.0])
    return X1 / np.linalg.norm(X1, axis=1)[:, None], X2 / np.linalg.norm(X2, axis=1)[:, None]


def test_the_old_confidence_keyword_is_taken_with_a_warning_naming_its_replacement() -> None:
    from mavvo.estimation import RelposeOptions, estimate_upright_relpose

    f1, f2 = _bearings(5)
    with pytest.warns(DeprecationWarning, match=r"options=RelposeOptions\(confidence=\.\.\.\)"):
        old = estimate_upright_relpose(f1, f2, max_err_rad=1e-3, confidence=0.999)
    new = estimate_upright_relpose(f1, f2, max_err_rad=1e-3, options=RelposeOptions(confidence=0.999))
    assert old.success and new.success
    np.testing.assert_array_equal(old.R_2_1, new.R_2_1)
    with pytest.raises(ValueError, match="confidence"), pytest.warns(DeprecationWarning):
        estimate_upright_relpose(f1, f2, max_err_rad=1e-3, confidence=1.5)
