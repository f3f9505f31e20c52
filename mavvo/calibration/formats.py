"""Other tools' calibration files, read into mavvo's intrinsics, and the ``camera:`` section written.

Read: OpenCV's ``FileStorage`` YAML (``camera_matrix``, ``distortion_coefficients``, ``image_width``,
``image_height``; what OpenCV's calibration sample writes), ROS ``camera_info`` YAML
(``camera_matrix.data``, ``distortion_model`` plumb_bob / equidistant, ``distortion_coefficients.data``)
and a Kalibr camchain (``cam0``: ``intrinsics`` fu fv pu pv, ``distortion_model`` radtan / equidistant,
``distortion_coeffs``, ``resolution``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from mavvo.errors import ConfigError
from mavvo.geometry.camera_model import CameraIntrinsics

__all__ = ["read_intrinsics", "camera_section_yaml"]

_MODELS = {
    "plumb_bob": "pinhole",
    "radtan": "pinhole",
    "rational_polynomial": None,
    "equidistant": "fisheye",
    "fisheye": "fisheye",
    "pinhole": "pinhole",
}


def _intrinsics(path: Path, size: Any, K: Any, model: str, dist: Any) -> CameraIntrinsics:
    try:
        w, h = (int(v) for v in size)
        K = np.asarray(K, dtype=float).reshape(3, 3)
        d = [float(x) for x in np.asarray(dist, dtype=float).ravel()]
        mavvo_model = _MODELS.get(model)
        if mavvo_model is None:
            raise ValueError(f"distortion model {model!r} is not one mavvo has (radtan/plumb_bob or equidistant)")
        if mavvo_model == "pinhole":
            d = d[:5] if any(d[4:5]) else d[:4]
        if not any(d):
            d = []
        return CameraIntrinsics(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], mavvo_model, tuple(d))  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{path}: {e}") from e


def read_intrinsics(path: str | Path) -> CameraIntrinsics:
    """The intrinsics in an OpenCV, ROS camera_info or Kalibr camchain file (told apart by their keys);
    ConfigError naming the file otherwise."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{p}: cannot read: {e}") from e
    if text.lstrip().startswith("%YAML"):  # OpenCV FileStorage
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        try:
            K, D = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
            w, h = fs.getNode("image_width").real(), fs.getNode("image_height").real()
        finally:
            fs.release()
        if K is None or D is None or not w or not h:
            raise ConfigError(
                f"{p}: expected camera_matrix, distortion_coefficients, image_width and image_height (OpenCV calibration file)"
            )
        return _intrinsics(p, (w, h), K, "radtan", D)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not valid YAML: {' '.join(str(e).split())}") from e
    if isinstance(data, dict) and "camera_matrix" in data:  # ROS camera_info
        return _intrinsics(
            p,
            (data.get("image_width"), data.get("image_height")),
            data["camera_matrix"].get("data"),
            data.get("distortion_model", "plumb_bob"),
            (data.get("distortion_coefficients") or {}).get("data", []),
        )
    if isinstance(data, dict) and isinstance(data.get("cam0"), dict):  # Kalibr camchain
        c = data["cam0"]
        fu, fv, pu, pv = c.get("intrinsics", (None,) * 4)
        return _intrinsics(
            p,
            c.get("resolution"),
            [[fu, 0, pu], [0, fv, pv], [0, 0, 1]],
            c.get("distortion_model", "radtan"),
            c.get("distortion_coeffs", []),
        )
    raise ConfigError(f"{p}: expected an OpenCV calibration file, a ROS camera_info YAML or a Kalibr camchain")


def camera_section_yaml(intrinsics: CameraIntrinsics, comment: str = "") -> str:
    """The ``camera:`` section of a mavvo configuration file holding ``intrinsics`` (floats exact)."""
    lines = [f"# {line}" for line in comment.splitlines()] + [
        "camera:",
        f"  width_px: {intrinsics.width_px}",
        f"  height_px: {intrinsics.height_px}",
        f"  fx_px: {intrinsics.fx_px!r}",
        f"  fy_px: {intrinsics.fy_px!r}",
        f"  cx_px: {intrinsics.cx_px!r}",
        f"  cy_px: {intrinsics.cy_px!r}",
        f"  model: {intrinsics.model}",
        f"  distortion: [{', '.join(repr(x) for x in intrinsics.distortion)}]",
    ]
    return "\n".join(lines) + "\n"
