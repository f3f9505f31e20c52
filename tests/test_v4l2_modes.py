"""V4L2 mode listing against an object that answers the enumeration ioctls as a driver does
(``linux/videodev2.h``'s structs, EINVAL past the last entry): no camera is attached here."""

from __future__ import annotations

import errno
import os
import struct

from mavvo.service.v4l2_modes import (
    VIDIOC_ENUM_FMT,
    VIDIOC_ENUM_FRAMEINTERVALS,
    VIDIOC_ENUM_FRAMESIZES,
    V4L2Mode,
    enumerate_modes,
    v4l2_modes,
)


def fourcc(text: str) -> int:
    return sum(ord(c) << (8 * k) for k, c in enumerate(text))


class FakeV4L2DriverFollowingKernelABI:
    """YUYV at 640x480 (30, 15 fps) and 320x240 (60 fps); MJPG stepwise 160x120-1280x720 at 5-30 fps."""

    def __init__(self) -> None:
        self.requests: list[int] = []

    def __call__(self, fd: int, request: int, buf: bytearray) -> int:
        self.requests.append(request)
        index = struct.unpack_from("=I", buf, 0)[0]
        if request == VIDIOC_ENUM_FMT:
            assert len(buf) == 64 and struct.unpack_from("=I", buf, 4)[0] == 1  # VIDEO_CAPTURE
            fmts = [(b"YUYV 4:2:2", fourcc("YUYV")), (b"Motion-JPEG", fourcc("MJPG"))]
            self._need(index < len(fmts))
            struct.pack_into("=32sI", buf, 12, fmts[index][0], fmts[index][1])
        elif request == VIDIOC_ENUM_FRAMESIZES:
            assert len(buf) == 44
            pix = struct.unpack_from("=I", buf, 4)[0]
            if pix == fourcc("YUYV"):
                sizes = [(640, 480), (320, 240)]
                self._need(index < len(sizes))
                struct.pack_into("=III", buf, 8, 1, *sizes[index])  # DISCRETE
            else:
                self._need(index == 0)
                struct.pack_into("=7I", buf, 8, 3, 160, 1280, 8, 120, 720, 8)  # STEPWISE
        elif request == VIDIOC_ENUM_FRAMEINTERVALS:
            assert len(buf) == 52
            pix, w, h = struct.unpack_from("=III", buf, 4)
            if pix == fourcc("YUYV"):
                rates = {(640, 480): [30, 15], (320, 240): [60]}[(w, h)]
                self._need(index < len(rates))
                struct.pack_into("=III", buf, 16, 1, 1, rates[index])  # DISCRETE 1/fps s
            else:
                assert (w, h) == (1280, 720)
                self._need(index == 0)
                struct.pack_into("=7I", buf, 16, 3, 1, 30, 1, 5, 1, 1)  # STEPWISE 1/30 .. 1/5 s
        else:
            raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")
        return 0

    @staticmethod
    def _need(ok: bool) -> None:
        if not ok:
            raise OSError(errno.EINVAL, "Invalid argument")


def test_the_modes_a_driver_enumerates() -> None:
    modes = enumerate_modes(3, FakeV4L2DriverFollowingKernelABI())
    assert modes == [
        V4L2Mode("YUYV", 640, 480, "30, 15 fps"),
        V4L2Mode("YUYV", 320, 240, "60 fps"),
        V4L2Mode("MJPG", 1280, 720, "5-30 fps (any size from 160x120)"),
    ]
    assert str(modes[0]) == "YUYV 640x480 30, 15 fps"


def test_a_device_that_cannot_be_read_says_why_in_one_line(tmp_path) -> None:
    # The system's own words for the errno (glibc and musl word ENOTTY differently).
    assert v4l2_modes(str(tmp_path / "video7")) == [f"cannot open: {os.strerror(errno.ENOENT)}"]
    assert v4l2_modes("/dev/null") == [f"cannot list modes: {os.strerror(errno.ENOTTY)}"]
