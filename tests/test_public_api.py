"""What users import: the entry points from their package's ``__init__``, one name per module (the old
flat names are gone), and a keyword an earlier release had, still taken with a warning."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from mavvo.sim.world.twoview import make_scene


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


def test_the_old_confidence_keyword_is_taken_with_a_warning_naming_its_replacement() -> None:
    from mavvo.estimation import RelposeOptions, estimate_upright_relpose

    scene = make_scene(np.random.default_rng(5), 60, motion="sideways")
    f1, f2 = scene.f1_lvl, scene.f2_lvl
    with pytest.warns(DeprecationWarning, match=r"options=RelposeOptions\(confidence=\.\.\.\)"):
        old = estimate_upright_relpose(f1, f2, max_err_rad=1e-3, confidence=0.999)
    new = estimate_upright_relpose(f1, f2, max_err_rad=1e-3, options=RelposeOptions(confidence=0.999))
    assert old.success and new.success
    np.testing.assert_array_equal(old.R_2_1, new.R_2_1)
    with pytest.raises(ValueError, match="confidence"), pytest.warns(DeprecationWarning):
        estimate_upright_relpose(f1, f2, max_err_rad=1e-3, confidence=1.5)
