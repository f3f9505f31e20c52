"""Camera models against OpenCV's own projection functions."""

import cv2
import numpy as np
import pytest

from mavvo.geometry.camera_model import CameraModel

PINHOLE = CameraModel(640, 480, 420.0, 418.0, 322.5, 241.0, "pinhole", (-0.28, 0.09, 0.0012, -0.0007, -0.012))
FISHEYE = CameraModel(800, 600, 285.0, 286.0, 401.0, 299.0, "fisheye", (-0.012, 0.051, -0.049, 0.012))


def _points(rng: np.random.Generator, n: int, half_angle: float) -> np.ndarray:
    ang = half_angle * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(ang) * np.cos(phi), np.sin(ang) * np.sin(phi), np.cos(ang)], axis=1) * rng.uniform(
        1, 20, (n, 1)
    )


def test_pinhole_projection_matches_opencv() -> None:
    X = _points(np.random.default_rng(1), 500, np.radians(35))
    ours = PINHOLE.bearings_to_pixels(X)
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), PINHOLE.K, np.array(PINHOLE.distortion))
    np.testing.assert_allclose(ours, ref[:, 0], atol=1e-9)


def test_fisheye_projection_matches_opencv() -> None:
    X = _points(np.random.default_rng(2), 500, np.radians(80))
    ours = FISHEYE.bearings_to_pixels(X)
    ref, _ = cv2.fisheye.projectPoints(X[:, None], np.zeros(3), np.zeros(3), FISHEYE.K, np.array(FISHEYE.distortion))
    np.testing.assert_allclose(ours, ref[:, 0], atol=1e-8)


@pytest.mark.parametrize("camera, half_angle", [(PINHOLE, np.radians(35)), (FISHEYE, np.radians(80))])
def test_pixels_to_bearings_inverts_projection(camera: CameraModel, half_angle: float) -> None:
    X = _points(np.random.default_rng(3), 500, half_angle)
    f = camera.pixels_to_bearings(camera.bearings_to_pixels(X))
    np.testing.assert_allclose(f, X / np.linalg.norm(X, axis=1, keepdims=True), atol=1e-10)
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-14)


def test_undistortion_agrees_with_opencv_inside_the_image() -> None:
    rng = np.random.default_rng(4)
    uv = np.stack([rng.uniform(20, 620, 300), rng.uniform(20, 460, 300)], axis=1)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    ref = cv2.undistortPoints(uv[:, None], PINHOLE.K, np.array(PINHOLE.distortion), criteria=criteria)[:, 0]
    f = PINHOLE.pixels_to_bearings(uv)
    np.testing.assert_allclose(f[:, :2] / f[:, 2:], ref, atol=1e-8)


def test_no_distortion_is_the_plain_pinhole() -> None:
    cam = CameraModel(100, 80, 50.0, 50.0, 49.5, 39.5)
    np.testing.assert_allclose(cam.pixels_to_bearings(np.array([[49.5, 39.5]])), [[0, 0, 1]])
    np.testing.assert_allclose(cam.bearings_to_pixels(np.array([[1.0, 0.0, 1.0]])), [[99.5, 39.5]])
    assert np.all(np.isnan(cam.bearings_to_pixels(np.array([[0.0, 0.0, -1.0]]))))


def test_from_matrix() -> None:
    cam = CameraModel.from_matrix(PINHOLE.K, 640, 480, PINHOLE.distortion)
    assert cam == PINHOLE


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"width_px": 0}, "width_px: expected a positive integer"),
        ({"fx_px": -1.0}, "fx_px, fy_px: expected positive focal lengths"),
        ({"cx_px": float("nan")}, "cx_px: expected a finite number"),
        ({"model": "orthographic"}, "model: expected 'pinhole' or 'fisheye'"),
        ({"distortion": (0.1, 0.2, 0.3)}, "distortion: expected 4 or 5 coefficients for pinhole, got 3"),
        ({"model": "fisheye", "distortion": (0.1,) * 5}, "distortion: expected 4 coefficients for fisheye, got 5"),
    ],
)
def test_bad_parameters_are_named(kwargs: dict, match: str) -> None:
    base = {"width_px": 640, "height_px": 480, "fx_px": 400.0, "fy_px": 400.0, "cx_px": 320.0, "cy_px": 240.0}
    with pytest.raises(ValueError, match=match):
        CameraModel(**{**base, **kwargs})


def test_bad_arrays_are_named() -> None:
    with pytest.raises(ValueError, match=r"uv_px: expected an \(N,2\)"):
        PINHOLE.pixels_to_bearings(np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"f_cam: expected an \(N,3\)"):
        PINHOLE.bearings_to_pixels(np.zeros(3))
