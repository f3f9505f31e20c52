"""``mavvo calibrate``: the camera's intrinsics and distortion from views of a calibration board, or
from another tool's calibration file, written as the ``camera:`` section of mavvo's settings."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from mavvo.calibration.boards import BoardSpec, Detection, detect, parse_board
from mavvo.calibration.formats import camera_section_yaml, read_intrinsics
from mavvo.calibration.solve import GRID, CalibrationResult, calibrate
from mavvo.errors import CameraError, ConfigError

log = logging.getLogger(__name__)

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".tif", ".tiff")
_PROGRESS_EVERY = 25
_GOOD_RMS_PX = 1.0
_GOOD_COVERAGE = 0.5
_GOOD_FX_SIGMA = 0.01  # fx's standard deviation over fx above this: the views do not pin it down
_GOOD_TILT_DEG = 20.0  # (fisheye) boards all nearer face-on than this: focal length and distance trade off


def add_parser(sub: Any) -> None:
    c = sub.add_parser(
        "calibrate",
        help="calibrate the camera from views of a checkerboard or ChArUco board",
        description="Find a calibration board in a video, an image folder or a live V4L2 camera, solve for the intrinsics and "
        "distortion, and write the camera: section of mavvo's settings. Move the board over the whole image, near and far, "
        "tilted up to about 45 deg. With --import, convert an OpenCV, ROS camera_info or Kalibr camchain file instead.",
    )
    c.add_argument("source", nargs="?", help="a video file, a folder of images, or /dev/videoN")
    c.add_argument(
        "--board", metavar="COLSxROWS", help="checkerboard: its inner corners (9x6); --charuco: its squares (e.g. 8x6)"
    )
    c.add_argument("--square-m", type=float, metavar="S", help="side of one square in metres")
    c.add_argument(
        "--charuco", action="store_true", help="a ChArUco board (OpenCV's 5x5 dictionary) instead of a checkerboard"
    )
    c.add_argument(
        "--marker-m",
        type=float,
        default=None,
        metavar="M",
        help="--charuco: side of a marker in metres (default 0.75 of a square)",
    )
    c.add_argument(
        "--model",
        choices=("pinhole", "fisheye"),
        default="pinhole",
        help="pinhole (radtan k1 k2 p1 p2 k3, default) or fisheye (equidistant)",
    )
    c.add_argument(
        "--k3",
        action="store_true",
        help="pinhole: also solve for k3 (wide-angle lenses; on narrow ones it soaks up noise)",
    )
    c.add_argument(
        "--max-frames",
        type=int,
        default=600,
        metavar="N",
        help="read at most N frames (a live camera: N frames, default 600)",
    )
    c.add_argument("--every", type=int, default=1, metavar="K", help="use every K-th frame of a video (default 1)")
    c.add_argument(
        "--import",
        dest="import_file",
        type=Path,
        default=None,
        metavar="FILE",
        help="convert this OpenCV / ROS / Kalibr calibration instead",
    )
    c.add_argument(
        "--out", type=Path, default=None, metavar="FILE", help="write the camera: section here (default: print it)"
    )
    c.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    c.add_argument("--plot", type=Path, default=None, metavar="PNG", help="write the coverage and residual plot here")
    c.set_defaults(handler=main)


def _frames(source: str, max_frames: int, every: int) -> Iterator[np.ndarray]:
    """Grey frames of a folder (images in name order), a video file or a V4L2 device."""
    p = Path(source)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in _IMAGE_SUFFIXES)
        if not files:
            raise CameraError(f"{p}: expected images ({', '.join(_IMAGE_SUFFIXES)}), found none")
        for f in files[:max_frames]:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                log.warning("%s: cannot read; skipped", f)
                continue
            yield img
        return
    if not (p.is_file() or source.startswith("/dev/video")):
        raise CameraError(f"{source}: expected a video file, a folder of images or /dev/videoN; nothing there")
    cap = cv2.VideoCapture(source, cv2.CAP_V4L2) if source.startswith("/dev/video") else cv2.VideoCapture(source)
    if not cap.isOpened():
        raise CameraError(f"{source}: cannot open")
    try:
        n = 0
        while n < max_frames * every:
            ok, img = cap.read()
            if not ok:
                return
            if n % every == 0:
                yield cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
            n += 1
    finally:
        cap.release()


def _plot(result: CalibrationResult, path: Path) -> None:
    """Where the corners were (coverage), how far each missed its reprojection, and each view's RMS."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w, h = result.intrinsics.width_px, result.intrinsics.height_px
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(15, 4.5), gridspec_kw={"width_ratios": [4, 3, 3]})
    a.scatter(result.corners_px[:, 0], result.corners_px[:, 1], s=3, c="tab:blue")
    for x in np.linspace(0, w, GRID[0] + 1):
        a.axvline(x, color="0.85", lw=0.5)
    for y in np.linspace(0, h, GRID[1] + 1):
        a.axhline(y, color="0.85", lw=0.5)
    a.set(xlim=(0, w), ylim=(h, 0), aspect="equal", xlabel="x (px)", ylabel="y (px)")
    a.set_title(f"corners of the {len(result.views_used)} views used: {100 * result.coverage:.0f}% of the cells")
    r = result.residuals_px
    b.scatter(r[:, 0], r[:, 1], s=2, alpha=0.4, c="tab:blue")
    b.add_patch(plt.Circle((0, 0), result.rms_px, fill=False, color="tab:red", label=f"RMS {result.rms_px:.3f} px"))
    lim = 1.1 * max(float(np.max(np.abs(r))), result.rms_px)
    b.set(xlim=(-lim, lim), ylim=(lim, -lim), aspect="equal", xlabel="dx (px)", ylabel="dy (px)")
    b.set_title("each corner: observed minus reprojected")
    b.legend(loc="upper right")
    c.bar(range(len(result.view_rms_px)), result.view_rms_px, color="tab:blue")
    c.set(xlabel="view (in the order used)", ylabel="RMS (px)")
    dropped = f"; {len(result.views_dropped)} dropped as outliers" if result.views_dropped else ""
    c.set_title(f"reprojection RMS per view{dropped}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _check_out(out: Path | None, force: bool) -> None:
    if out is not None and out.exists() and not force:
        raise ConfigError(
            f"--out {out}: exists; expected a new file (or --force to overwrite; merge the camera: section into your settings by hand)"
        )


def _write(text: str, out: Path | None, force: bool) -> None:
    if out is None:
        sys.stdout.write(text)
        return
    _check_out(out, force)
    out.write_text(text, encoding="utf-8")
    print(f"camera: section written to {out}", file=sys.stderr)


def _report(result: CalibrationResult, n_found: int) -> None:
    """The result on stderr, with a warning for each way it may be less than it looks."""
    i = result.intrinsics
    sigma = f" +- {result.fx_sigma_px:.2f}" if np.isfinite(result.fx_sigma_px) else ""
    print(
        f"calibrate: {len(result.views_used)} of {n_found} views used; reprojection RMS {result.rms_px:.3f} px; coverage "
        f"{100 * result.coverage:.0f}% of the image; board tilted up to {result.max_tilt_deg:.0f} deg\n"
        f"  fx {i.fx_px:.2f}{sigma}  fy {i.fy_px:.2f}  cx {i.cx_px:.2f}  cy {i.cy_px:.2f}  {i.model} "
        f"distortion {', '.join(f'{x:.5f}' for x in i.distortion)}",
        file=sys.stderr,
    )
    warnings = []
    if result.views_dropped:
        warnings.append(
            f"{len(result.views_dropped)} view(s) dropped as outliers (their corners far off the rest's fit): "
            f"frames {', '.join(str(k + 1) for k in result.views_dropped)} of those with the board"
        )
    if result.rms_px > _GOOD_RMS_PX:
        warnings.append(
            f"RMS {result.rms_px:.2f} px is high (expected under {_GOOD_RMS_PX} px): blurred or bent board?"
        )
    if result.coverage < _GOOD_COVERAGE:
        warnings.append(
            f"the corners cover {100 * result.coverage:.0f}% of the image: distortion near the edges is a guess; "
            "show the board in the corners too"
        )
    # OpenCV's sigma where the model gives one (pinhole); the boards' tilt where it does not (fisheye).
    if (
        result.fx_sigma_px > _GOOD_FX_SIGMA * i.fx_px
        if np.isfinite(result.fx_sigma_px)
        else result.max_tilt_deg < _GOOD_TILT_DEG
    ):
        warnings.append(
            f"the focal length is poorly pinned down (fx{sigma} px, the board tilted at most {result.max_tilt_deg:.0f} deg): "
            f"tilt the board {_GOOD_TILT_DEG:.0f}-45 deg toward and away from the camera in some views"
        )
    for text in warnings:
        print(f"calibrate: warning: {text}", file=sys.stderr)


def main(args: argparse.Namespace) -> int:
    _check_out(args.out, args.force)  # before a capture is spent
    if args.import_file is not None:
        intr = read_intrinsics(args.import_file)
        _write(camera_section_yaml(intr, f"from {args.import_file}"), args.out, args.force)
        return 0
    if args.source is None or args.board is None or args.square_m is None:
        raise ConfigError("calibrate: expected SOURCE, --board COLSxROWS and --square-m S (or --import FILE)")
    if args.max_frames < 1 or args.every < 1:
        raise ConfigError(f"--max-frames, --every: expected positive numbers, got {args.max_frames}, {args.every}")
    cols, rows = parse_board(args.board)
    board = BoardSpec(cols, rows, args.square_m, args.charuco, args.marker_m)
    detections: list[Detection] = []
    size: tuple[int, int] | None = None
    n = 0
    for n, img in enumerate(_frames(args.source, args.max_frames, args.every), 1):
        shape = (img.shape[1], img.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            raise CameraError(
                f"{args.source}: frame {n} is {shape[0]}x{shape[1]}, the first was {size[0]}x{size[1]}; expected one size"
            )
        d = detect(img, board)
        if d is not None:
            detections.append(d)
        if n % _PROGRESS_EVERY == 0:
            print(
                f"\rcalibrate: {n} frames read, board found in {len(detections)}", end="", file=sys.stderr, flush=True
            )
    print(f"\rcalibrate: {n} frames read, board found in {len(detections)}", file=sys.stderr)
    if size is None:
        raise CameraError(f"{args.source}: no frames")
    result = calibrate(detections, size, args.model, k3=args.k3)
    _report(result, len(detections))
    if args.plot is not None:
        _plot(result, args.plot)
    _write(
        camera_section_yaml(
            result.intrinsics,
            f"mavvo calibrate {args.source}: RMS {result.rms_px:.3f} px, coverage {100 * result.coverage:.0f}%",
        ),
        args.out,
        args.force,
    )
    return 0
