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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w, h = result.intrinsics.width_px, result.intrinsics.height_px
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    a.scatter(result.corners_px[:, 0], result.corners_px[:, 1], s=3, c="tab:blue")
    for x in np.linspace(0, w, GRID[0] + 1):
        a.axvline(x, color="0.85", lw=0.5)
    for y in np.linspace(0, h, GRID[1] + 1):
        a.axhline(y, color="0.85", lw=0.5)
    a.set(
        xlim=(0, w),
        ylim=(h, 0),
        aspect="equal",
        title=f"corners of the {len(result.views_used)} views used: {100 * result.coverage:.0f}% of the cells",
    )
    scale = 0.25 * w / max(float(np.max(np.abs(result.residuals_px))), 1e-6)
    b.quiver(
        result.corners_px[:, 0],
        result.corners_px[:, 1],
        result.residuals_px[:, 0] * scale,
        -result.residuals_px[:, 1] * scale,
        angles="xy",
        scale_units="xy",
        scale=1,
        width=0.002,
    )
    b.set(
        xlim=(0, w),
        ylim=(h, 0),
        aspect="equal",
        title=f"reprojection residuals (RMS {result.rms_px:.2f} px, arrows x{scale:.0f})",
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _write(text: str, out: Path | None, force: bool) -> None:
    if out is None:
        sys.stdout.write(text)
        return
    if out.exists() and not force:
        raise ConfigError(
            f"--out {out}: exists; expected a new file (or --force to overwrite; merge the camera: section into your settings by hand)"
        )
    out.write_text(text, encoding="utf-8")
    print(f"camera: section written to {out}", file=sys.stderr)


def main(args: argparse.Namespace) -> int:
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
    i = result.intrinsics
    print(
        f"calibrate: {len(result.views_used)} of {len(detections)} views used; reprojection RMS {result.rms_px:.3f} px; coverage "
        f"{100 * result.coverage:.0f}% of the image\n  fx {i.fx_px:.2f}  fy {i.fy_px:.2f}  cx {i.cx_px:.2f}  cy {i.cy_px:.2f}  {i.model} "
        f"distortion {', '.join(f'{x:.5f}' for x in i.distortion)}",
        file=sys.stderr,
    )
    if result.rms_px > _GOOD_RMS_PX:
        print(
            f"calibrate: warning: RMS {result.rms_px:.2f} px is high (expected under {_GOOD_RMS_PX} px): blurred or bent board?",
            file=sys.stderr,
        )
    if result.coverage < _GOOD_COVERAGE:
        print(
            f"calibrate: warning: the corners cover {100 * result.coverage:.0f}% of the image: distortion near the edges is a guess; "
            "show the board in the corners too",
            file=sys.stderr,
        )
    if args.plot is not None:
        _plot(result, args.plot)
    _write(
        camera_section_yaml(
            i, f"mavvo calibrate {args.source}: RMS {result.rms_px:.3f} px, coverage {100 * result.coverage:.0f}%"
        ),
        args.out,
        args.force,
    )
    return 0
