"""Old flat module names keep working (code written against earlier versions, the README's example)."""

from __future__ import annotations

import importlib

import pytest


@pytest.mark.parametrize(
    "old, new",
    [
        ("mavvo.frames", "mavvo.geometry.frames"),
        ("mavvo.camera_model", "mavvo.geometry.camera_model"),
        ("mavvo.relpose", "mavvo.estimation.relpose"),
        ("mavvo.settings", "mavvo.service.settings"),
        ("mavvo.solvers", "mavvo.geometry"),
    ],
)
def test_an_old_module_name_is_the_new_module(old: str, new: str) -> None:
    assert importlib.import_module(old) is importlib.import_module(new)


def test_the_readme_example_imports() -> None:
    from mavvo.camera_model import CameraModel
    from mavvo.frames import R_BODY_CAM_NADIR, R_lvl_cam
    from mavvo.relpose import RelposeOptions, estimate_relpose_known_gravity
    from mavvo.solvers import solve_upright_3pt

    assert CameraModel.__module__ == "mavvo.geometry.camera_model"
    assert R_lvl_cam(0.0, 0.0, R_BODY_CAM_NADIR).shape == (3, 3)
    assert RelposeOptions().tilt_sigma_rad is None and callable(estimate_relpose_known_gravity)
    assert solve_upright_3pt.__module__ == "mavvo.geometry.upright_3pt"


def test_an_unknown_name_is_still_an_import_error() -> None:
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("mavvo.no_such_module")
