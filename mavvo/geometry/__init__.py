"""Geometry: frames and rotations, camera models, polynomial roots, the paper's solvers (one per
module), residuals and least-squares refinement, medians. numpy, OpenCV and compiled kernels
(``mavvo.jit``); imports nothing else of mavvo but ``mavvo.errors``, ``mavvo.options`` and ``mavvo.types``."""

from mavvo.geometry.camera_model import CameraIntrinsics, CameraModel
from mavvo.geometry.essential import (
    alpha_beta_gamma,
    as_bearing_pair,
    epipolar_rows,
    essential_from_vector,
    essential_to_vector,
    upright_constraint_residual,
)
from mavvo.geometry.ground_2pt import (
    ground_homography_from_similarity,
    ground_pose_from_homography,
    solve_ground_2pt_batch,
)
from mavvo.geometry.upright_3pt import solve_upright_3pt, solve_upright_3pt_batch
from mavvo.geometry.upright_4pt import solve_upright_4pt
from mavvo.geometry.upright_linear5pt import solve_upright_linear5pt
from mavvo.geometry.upright_pose import upright_pose_from_essential

__all__ = [
    "CameraIntrinsics",
    "CameraModel",
    "alpha_beta_gamma",
    "as_bearing_pair",
    "epipolar_rows",
    "essential_from_vector",
    "essential_to_vector",
    "upright_constraint_residual",
    "ground_homography_from_similarity",
    "ground_pose_from_homography",
    "solve_ground_2pt_batch",
    "solve_upright_3pt",
    "solve_upright_3pt_batch",
    "solve_upright_4pt",
    "solve_upright_linear5pt",
    "upright_pose_from_essential",
]
