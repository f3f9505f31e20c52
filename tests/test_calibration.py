"""``mavvo calibrate``: boards the test renders with known intrinsics are found and the intrinsics
recovered within 1%; other tools' calibration files, written by their own libraries or in their own
layout, are read; the command writes a camera: section that check-config accepts."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from mavvo.calibration.boards import BoardSpec, Detection, detect, parse_board
from mavvo.calibration.formats import camera_section_yaml, read_intrinsics
from mavvo.calibration.solve import CalibrationError, calibrate, coverage, select_views
from mavvo.cli import main
from mavvo.errors import ConfigError
from mavvo.geometry.camera_model import CameraIntrinsics

W, H = 640, 480
K_TRUE = np.array([[612.0, 0.0, 331.0], [0.0, 608.0, 236.5], [0.0, 0.0, 1.0]])
BOARD = BoardSpec(9, 6, 0.03)
_PX_PER_SQUARE = 60


def _texture(board: BoardSpec) -> tuple[np.ndarray, float]:
    """The board's image (white margin of one square) and its metres per texture pixel."""
    if board.charuco:
        size = (
            (board.cols + 2) * _PX_PER_SQUARE,
            (board.rows + 2) * _PX_PER_SQUARE,
        )  # the board itself, then a square of margin
        img = board.charuco_board().generateImage(size, marginSize=_PX_PER_SQUARE)
        return img, board.square_m / _PX_PER_SQUARE
    sq = _PX_PER_SQUARE
    n_x, n_y = board.cols + 1, board.rows + 1  # squares: inner corners + 1
    img = np.full(((n_y + 2) * sq, (n_x + 2) * sq), 255, np.uint8)
    for j in range(n_y):
        for i in range(n_x):
            if (i + j) % 2 == 0:
                img[(j + 1) * sq : (j + 2) * sq, (i + 1) * sq : (i + 2) * sq] = 0
    return img, board.square_m / sq


def render_views(
    board: BoardSpec, n: int, seed: int, K: np.ndarray = K_TRUE, max_tilt_rad: float = 0.6
) -> list[np.ndarray]:
    """``n`` grey 640x480 views of ``board`` at seeded poses (0.35-0.8 m away, tilted up to
    ``max_tilt_rad`` about each image axis, spread over the image), through a distortion-free pinhole ``K``."""
    tex, m_per_px = _texture(board)
    # Texture pixel -> board frame (metres): the first inner corner, two squares in, at the origin.
    origin_m = 2 * _PX_PER_SQUARE * m_per_px
    S = np.array([[m_per_px, 0, -origin_m], [0, m_per_px, -origin_m], [0, 0, 1.0]])
    centre = np.array([(board.cols - 1) * board.square_m / 2, (board.rows - 1) * board.square_m / 2, 0.0])
    rng = np.random.default_rng(seed)
    views = []
    while len(views) < n:
        rvec = rng.uniform(-1.0, 1.0, 3) * np.array([max_tilt_rad, max_tilt_rad, 0.3])
        R, _ = cv2.Rodrigues(rvec)
        z = rng.uniform(0.35, 0.8)
        target = np.array([rng.uniform(60, W - 60), rng.uniform(60, H - 60)])
        ray = np.linalg.solve(K, np.array([*target, 1.0]))
        t = ray * z - R @ centre  # the board's centre on the ray to the target pixel
        Hm = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
        img = cv2.warpPerspective(
            tex, Hm, (W, H), flags=cv2.INTER_AREA, borderMode=cv2.BORDER_CONSTANT, borderValue=128
        )
        corners = (K @ (R @ board.corners_m().T + t[:, None])).T
        uv = corners[:, :2] / corners[:, 2:]
        if np.all((uv > 15) & (uv < [W - 15, H - 15])):
            views.append(img)
    return views


@pytest.fixture(scope="module")
def views():
    return render_views(BOARD, 24, seed=11)


def test_board_text_and_bounds():
    assert parse_board("9x6") == (9, 6) and parse_board(" 10 X 7 ") == (10, 7)
    with pytest.raises(ConfigError, match="--board: expected COLSxROWS"):
        parse_board("9,6")
    with pytest.raises(ConfigError, match="--square-m"):
        BoardSpec(9, 6, 0.0)


def test_rendered_checkerboards_give_the_intrinsics_within_1_percent(views):
    detections = [d for d in (detect(v, BOARD) for v in views) if d is not None]
    assert len(detections) >= 20
    r = calibrate(detections, (W, H))
    i = r.intrinsics
    for got, want in ((i.fx_px, 612.0), (i.fy_px, 608.0), (i.cx_px, 331.0), (i.cy_px, 236.5)):
        assert got == pytest.approx(want, rel=0.01)
    assert r.rms_px < 0.5 and 0.3 < r.coverage <= 1.0 and len(r.views_used) >= 4
    assert max(abs(x) for x in i.distortion) < 0.05  # the views had none


def test_view_selection_keeps_views_that_add_coverage(views):
    detections = [d for d in (detect(v, BOARD) for v in views) if d is not None]
    chosen = select_views(detections + detections, (W, H))  # every view twice: duplicates add nothing
    assert len(chosen) == len(set(chosen)) and all(c < 2 * len(detections) for c in chosen)
    assert len([c for c in chosen if c >= len(detections)]) <= 1
    assert coverage([detections[i] for i in chosen], (W, H)) == pytest.approx(coverage(detections, (W, H)))


def test_too_few_views_is_a_clear_error(views):
    d = detect(views[0], BOARD)
    assert d is not None
    with pytest.raises(CalibrationError, match="expected at least 4"):
        calibrate([d], (W, H))


def test_charuco_board_is_found_and_calibrated():
    board = BoardSpec(8, 6, 0.03, charuco=True)
    detections = [d for d in (detect(v, board) for v in render_views(board, 40, seed=5)) if d is not None]
    assert len(detections) >= 30
    i = calibrate(
        detections, (W, H)
    ).intrinsics  # ChArUco corners are noisier (0.23 px RMS here against 0.07): more views
    for got, want in ((i.fx_px, 612.0), (i.fy_px, 608.0), (i.cx_px, 331.0), (i.cy_px, 236.5)):
        assert got == pytest.approx(want, rel=0.01)


def test_the_command_writes_a_camera_section_that_check_config_accepts(tmp_path, views, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, v in enumerate(views):
        cv2.imwrite(str(folder / f"{k:03d}.png"), v)
    out, plot = tmp_path / "camera.yaml", tmp_path / "calibration.png"
    assert (
        main(["calibrate", str(folder), "--board", "9x6", "--square-m", "0.03", "--out", str(out), "--plot", str(plot)])
        == 0
    )
    err = capsys.readouterr().err
    assert "24 frames read, board found in 24" in err and "reprojection RMS" in err
    assert "warning" not in err  # tilted views over the image: nothing to warn of
    cam = yaml.safe_load(out.read_text())["camera"]
    assert cam["fx_px"] == pytest.approx(612.0, rel=0.01) and cam["width_px"] == 640
    assert main(["check-config", str(out)]) == 0
    assert plot.stat().st_size > 10_000
    assert (
        main(["calibrate", str(folder), "--board", "9x6", "--square-m", "0.03", "--out", str(out)]) == 2
    )  # never over a file
    assert "exists" in capsys.readouterr().err


def test_other_tools_files_are_read(tmp_path):
    want = CameraIntrinsics(
        752, 480, 458.654, 457.296, 367.215, 248.375, "pinhole", (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    )
    fs = cv2.FileStorage(
        str(tmp_path / "opencv.yaml"), cv2.FILE_STORAGE_WRITE
    )  # as OpenCV's calibration sample writes it
    fs.write("image_width", 752)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]]))
    fs.release()
    ros = {
        "image_width": 752,
        "image_height": 480,
        "camera_name": "cam0",
        "distortion_model": "plumb_bob",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [458.654, 0, 367.215, 0, 457.296, 248.375, 0, 0, 1]},
        "distortion_coefficients": {
            "rows": 1,
            "cols": 5,
            "data": [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0],
        },
    }
    (tmp_path / "ros.yaml").write_text(yaml.safe_dump(ros))
    kalibr = {
        "cam0": {
            "camera_model": "pinhole",
            "intrinsics": [458.654, 457.296, 367.215, 248.375],
            "distortion_model": "radtan",
            "distortion_coeffs": [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
            "resolution": [752, 480],
        }
    }
    (tmp_path / "kalibr.yaml").write_text(yaml.safe_dump(kalibr))
    for name in ("opencv.yaml", "ros.yaml", "kalibr.yaml"):
        got = read_intrinsics(tmp_path / name)
        assert got == want, name
    fisheye = {
        "cam0": {
            "intrinsics": [380.0, 381.0, 320.0, 240.0],
            "distortion_model": "equidistant",
            "distortion_coeffs": [0.01, -0.002, 0.0003, -0.00001],
            "resolution": [640, 480],
        }
    }
    (tmp_path / "fisheye.yaml").write_text(yaml.safe_dump(fisheye))
    assert read_intrinsics(tmp_path / "fisheye.yaml").model == "fisheye"
    (tmp_path / "other.yaml").write_text("a: 1\n")
    with pytest.raises(ConfigError, match="other.yaml: expected an OpenCV calibration file"):
        read_intrinsics(tmp_path / "other.yaml")
    section = camera_section_yaml(want)
    assert yaml.safe_load(section)["camera"]["distortion"] == list(want.distortion)


def test_a_view_far_off_the_rest_is_dropped_and_the_rest_solved_again(views):
    """One frame's corners 3 px off (a blurred frame, a grid misread): dropped, the intrinsics as before."""
    detections = [detect(v, BOARD) for v in views]
    rng = np.random.default_rng(1)
    bad = detections[5]
    detections[5] = Detection(bad.image_px + rng.normal(0.0, 3.0, bad.image_px.shape), bad.board_m)
    result = calibrate(detections, (W, H))
    assert result.views_dropped == (5,) and 5 not in result.views_used
    assert result.intrinsics.fx_px == pytest.approx(612.0, rel=0.01) and result.rms_px < 0.2


def test_corners_that_fit_no_camera_are_refused(views):
    """Three views in five with their corners matched to the wrong board corners (a grid read across two
    printed sheets): no camera fits; refused, naming --board, instead of intrinsics that are not."""
    rng = np.random.default_rng(3)
    detections = [detect(v, BOARD) for v in views]
    mixed = [
        Detection(d.image_px[rng.permutation(len(d.image_px))], d.board_m) if k % 5 < 3 else d
        for k, d in enumerate(detections)
    ]
    with pytest.raises(CalibrationError, match=r"reprojection RMS .* the corners do not fit one camera; is --board"):
        calibrate(mixed, (W, H))


def test_a_principal_point_outside_the_image_is_refused(views, monkeypatch):
    """A solve that puts the principal point outside the image (real floor views whose grids spanned two
    printed sheets did): a calibration error that says what to change, not the camera model's ValueError."""
    import mavvo.calibration.solve as solve

    real = solve._solve

    def off_centre(*args, **kwargs):
        s = real(*args, **kwargs)
        K = s.K.copy()
        K[0, 2] = 700.0
        return solve._Solve(K, s.D, s.rvecs, s.tvecs, s.fx_sigma_px)

    monkeypatch.setattr(solve, "_solve", off_centre)
    with pytest.raises(
        CalibrationError, match=r"no camera of this image has \(cx_px, cy_px: .* got \(700\.0, .*one printed board"
    ):
        calibrate([detect(v, BOARD) for v in views], (W, H))


def test_a_broken_grid_from_the_detector_is_no_detection(views, monkeypatch):
    """What OpenCV may return for a frame: found, but corners outside the image, not finite, or too few."""
    good = cv2.findChessboardCornersSB(views[0], (9, 6))[1]
    for broken in (good * 5.0, np.where(np.arange(len(good))[:, None, None] == 3, np.nan, good), good[:20]):
        monkeypatch.setattr(cv2, "findChessboardCornersSB", lambda *a, broken=broken, **k: (True, broken))
        assert detect(views[0], BOARD) is None
    monkeypatch.setattr(cv2, "findChessboardCornersSB", lambda *a, **k: (True, good))
    assert detect(views[0], BOARD) is not None


def test_an_existing_out_file_is_refused_before_any_frame_is_read(tmp_path, capsys):
    out = tmp_path / "camera.yaml"
    out.write_text("camera: {}\n")
    missing = tmp_path / "no-such-folder"
    assert main(["calibrate", str(missing), "--board", "9x6", "--square-m", "0.03", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: exists" in err and "no-such-folder" not in err


def test_views_seen_face_on_warn_that_the_focal_length_is_loose(tmp_path, capsys):
    """Boards tilted at most 3 deg: the focal length and the distance trade off (OpenCV's sigma of fx over
    1%); the command says so and how to fix it. The tilted views of the other tests do not warn."""
    folder = tmp_path / "flat"
    folder.mkdir()
    for k, v in enumerate(render_views(BOARD, 16, seed=11, max_tilt_rad=0.05)):
        cv2.imwrite(str(folder / f"{k:03d}.png"), v)
    assert (
        main(["calibrate", str(folder), "--board", "9x6", "--square-m", "0.03", "--out", str(tmp_path / "c.yaml")]) == 0
    )
    err = capsys.readouterr().err
    assert "warning: the focal length is poorly pinned down" in err and "tilt the board 20-45 deg" in err
