"""Robust estimation: relative pose with known gravity (RANSAC, local optimisation, refinement, model
selection). Imports ``mavvo.geometry`` and the top-level vocabulary only.

The entry points users call: :func:`estimate_relpose_known_gravity` (matched pixels and each view's
gravity) and :func:`estimate_upright_relpose` (level-frame bearings), with :class:`RelposeOptions`.
"""

from mavvo.estimation.relpose import estimate_relpose_known_gravity, estimate_upright_relpose
from mavvo.estimation.relpose_types import (
    CameraRelpose,
    RelposeFailure,
    RelposeModel,
    RelposeOptions,
    RelposeStats,
    UprightRelpose,
)

__all__ = [
    "CameraRelpose",
    "RelposeFailure",
    "RelposeModel",
    "RelposeOptions",
    "RelposeStats",
    "UprightRelpose",
    "estimate_relpose_known_gravity",
    "estimate_upright_relpose",
]
