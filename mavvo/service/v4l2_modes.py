"""The capture modes of a V4L2 device (pixel format, frame size, frame rates), read with the kernel's
enumeration ioctls, for ``mavvo camera``'s listing.

The three ioctls and their structs are the kernel's user-space ABI (``linux/videodev2.h``):

- ``VIDIOC_ENUM_FMT`` on ``struct v4l2_fmtdesc`` (64 bytes: index, type, flags, description[32],
  pixelformat, mbus_code, reserved[3]);
- ``VIDIOC_ENUM_FRAMESIZES`` on ``struct v4l2_frmsizeenum`` (44 bytes: index, pixel_format, type, then
  width, height for a discrete size or min/max/step of each for a stepwise one, reserved[2]);
- ``VIDIOC_ENUM_FRAMEINTERVALS`` on ``struct v4l2_frmivalenum`` (52 bytes: index, pixel_format, width,
  height, type, then a fraction of seconds, or min/max/step fractions, reserved[2]).

Each is called with index 0, 1, ... until the driver answers EINVAL. The ioctl call is a parameter so the
tests can answer as a driver does where no camera is attached.
"""

from __future__ import annotations

import errno
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["V4L2Mode", "v4l2_modes", "enumerate_modes"]

_IOC_READ_WRITE = 3


def _iowr(nr: int, size: int) -> int:
    return (_IOC_READ_WRITE << 30) | (size << 16) | (ord("V") << 8) | nr


_FMTDESC = struct.Struct("=III32sII3I")  # 64 bytes
_FRMSIZE = struct.Struct("=III6I2I")  # 44 bytes
_FRMIVAL = struct.Struct("=IIIII6I2I")  # 52 bytes
VIDIOC_ENUM_FMT = _iowr(2, _FMTDESC.size)
VIDIOC_ENUM_FRAMESIZES = _iowr(74, _FRMSIZE.size)
VIDIOC_ENUM_FRAMEINTERVALS = _iowr(75, _FRMIVAL.size)
_BUF_TYPE_VIDEO_CAPTURE = 1
_DISCRETE = 1  # V4L2_FRMSIZE_TYPE_DISCRETE and V4L2_FRMIVAL_TYPE_DISCRETE
_MAX_ENTRIES = 64  # a driver that never answers EINVAL does not hang the listing

Ioctl = Callable[[int, int, bytearray], object]


def _fourcc(code: int) -> str:
    return "".join(chr((code >> (8 * k)) & 0xFF) for k in range(4)).strip()


def _enumerate(fd: int, ioctl: Ioctl, request: int, layout: struct.Struct, head: tuple[int, ...]) -> list[tuple]:
    """The driver's answers to ``request`` for index 0, 1, ... (``head`` follows the index)."""
    out = []
    for index in range(_MAX_ENTRIES):
        buf = bytearray(layout.size)  # every field zero but the leading u32s: index, then head
        struct.pack_into(f"={1 + len(head)}I", buf, 0, index, *head)
        try:
            ioctl(fd, request, buf)
        except OSError as e:
            if e.errno == errno.EINVAL:  # past the last entry
                break
            raise
        out.append(layout.unpack(bytes(buf)))
    return out


def _rates(fd: int, ioctl: Ioctl, pixfmt: int, width: int, height: int) -> str:
    """The frame rates of one format and size, as text: '30, 15 fps' or '5-60 fps'."""
    answers = _enumerate(fd, ioctl, VIDIOC_ENUM_FRAMEINTERVALS, _FRMIVAL, (pixfmt, width, height))
    rates = []
    for a in answers:
        kind, num, den, max_num, max_den = a[4], a[5], a[6], a[7], a[8]
        if kind == _DISCRETE and num > 0:
            rates.append(f"{den / num:g}")
        elif num > 0 and max_den > 0:  # stepwise or continuous: the fastest is the shortest interval
            return f"{max_den / max_num:g}-{den / num:g} fps" if max_num > 0 else f"up to {den / num:g} fps"
    return f"{', '.join(rates)} fps" if rates else "rate not listed"


@dataclass(frozen=True)
class V4L2Mode:
    """One capture mode: the pixel format's fourcc (e.g. YUYV, MJPG, GREY), the size, its rates as text."""

    fourcc: str
    width_px: int
    height_px: int
    rates: str

    def __str__(self) -> str:
        return f"{self.fourcc} {self.width_px}x{self.height_px} {self.rates}"


def enumerate_modes(fd: int, ioctl: Ioctl) -> list[V4L2Mode]:
    """Every capture format, frame size and rate the device behind ``fd`` lists."""
    modes = []
    for fmt in _enumerate(fd, ioctl, VIDIOC_ENUM_FMT, _FMTDESC, (_BUF_TYPE_VIDEO_CAPTURE,)):
        pixfmt = fmt[4]
        for size in _enumerate(fd, ioctl, VIDIOC_ENUM_FRAMESIZES, _FRMSIZE, (pixfmt,)):
            kind = size[2]
            if kind == _DISCRETE:
                w, h = size[3], size[4]
                modes.append(V4L2Mode(_fourcc(pixfmt), w, h, _rates(fd, ioctl, pixfmt, w, h)))
            else:  # stepwise or continuous: the largest size stands for the range
                min_w, max_w, _, min_h, max_h, _ = size[3:9]
                rates = _rates(fd, ioctl, pixfmt, max_w, max_h)
                modes.append(V4L2Mode(_fourcc(pixfmt), max_w, max_h, f"{rates} (any size from {min_w}x{min_h})"))
    return modes


def v4l2_modes(device: str) -> list[str]:
    """The modes of ``device`` (e.g. /dev/video0), one line each; a one-line reason where it cannot be read
    (busy, no permission, not a capture device)."""
    import fcntl

    try:
        fd = os.open(device, os.O_RDWR | os.O_NONBLOCK)
    except OSError as e:
        return [f"cannot open: {e.strerror}"]
    try:
        return [str(m) for m in enumerate_modes(fd, fcntl.ioctl)] or ["no capture formats"]
    except OSError as e:
        return [f"cannot list modes: {e.strerror}"]
    finally:
        os.close(fd)
