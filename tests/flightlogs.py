"""Small flight-controller logs and videos made from a simulated flight, for the replay tests.

The flight controller booted ``BOOT_S`` before the simulation started; the video starts ``video_start_s``
into the flight, so the offset ``mavvo replay`` must find is ``BOOT_S + video_start_s``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from log_writers import write_dataflash, write_ulog

from mavvo.evaluation.metrics import PoseSeries
from mavvo.evaluation.report import write_tum
from mavvo.geometry.frames import R_from_euler321, quat_wxyz_from_R
from mavvo.service.mavlink import mavutil
from mavvo.service.settings import ServiceConfig, config_yaml
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.service_run import config_for
from mavvo.sim.world.camera import SimCamera
from mavvo.sim.world.clock import LockstepClock
from mavvo.sim.world.scene import World
from mavvo.sim.world.trajectories import make_trajectory

BOOT_S = 100.0
UNIX_AT_BOOT_US = 1_790_000_000_000_000


@dataclass(frozen=True)
class LogFlight:
    log: Path
    video: Path
    config: Path
    true_offset_s: float
    duration_s: float
    truth: Path  # TUM on the flight controller's clock


def _samples(trajectory, duration_s: float, rate_hz: float, rng: np.random.Generator, noise_deg: float):
    for t in np.arange(0.0, duration_s, 1.0 / rate_hz):
        s = trajectory.state(float(t))
        n = np.radians(noise_deg) * rng.standard_normal(3)
        yield float(t), s.roll_rad + n[0], s.pitch_rad + n[1], s.yaw_rad + n[2], float(-s.p_ned_m[2])


def make_log_flight(
    tmp: Path,
    *,
    kind: str = "tlog",
    video: str = "folder",
    scenario: str = "figure_eight",
    duration_s: float = 16.0,
    video_start_s: float = 1.5,
    video_end_s: float | None = None,
    with_attitude: bool = True,
    with_local_position: bool = False,
    attitude_rate_hz: float = 50.0,
) -> LogFlight:
    """Write a log (``tlog``, ``bin`` or ``ulg``), a video (``folder`` with timestamps.txt or ``avi``)
    and the camera's config into ``tmp``."""
    sc = load_scenario(scenario)
    traj = make_trajectory(sc.trajectory)
    rng = np.random.default_rng(7)
    cfg = config_for(sc, ServiceConfig(), "udpout:127.0.0.1:14550")
    config = tmp / "camera.yaml"
    config.write_text(config_yaml(cfg), encoding="utf-8")

    att = list(_samples(traj, duration_s, attitude_rate_hz, rng, 0.02)) if with_attitude else []
    heights = [(t, h) for t, *_, h in _samples(traj, duration_s, 10.0, rng, 0.0)]
    poses = [(float(t), *traj.pose(float(t))) for t in np.arange(0.0, duration_s, 0.05)]
    ranges = [(t, -p[2] / R[2, 2]) for t, p, R in poses]  # the downward laser to flat ground
    if kind == "tlog":
        log = tmp / "flight.tlog"
        mav = mavutil().mavlink
        enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        events = [(t, mav.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)) for t in np.arange(0.0, duration_s, 1.0)]
        events += [
            (t, mav.MAVLink_attitude_message(int(round((t + BOOT_S) * 1e3)), r, p, y, 0, 0, 0)) for t, r, p, y, _ in att
        ]
        events += [
            (
                t,
                mav.MAVLink_global_position_int_message(
                    int(round((t + BOOT_S) * 1e3)), 0, 0, 0, int(h * 1e3), 0, 0, 0, 0
                ),
            )
            for t, h in heights
        ]
        events += [
            (
                t,
                mav.MAVLink_distance_sensor_message(
                    int(round((t + BOOT_S) * 1e3)), 20, 4000, int(round(r * 100)), 0, 0, 25, 255
                ),
            )
            for t, r in ranges
        ]
        if with_local_position:
            events += [
                (
                    t,
                    mav.MAVLink_local_position_ned_message(
                        int(round((t + BOOT_S) * 1e3)), *traj.state(t).p_ned_m, 0, 0, 0
                    ),
                )
                for t, _ in heights
            ]
        events.sort(key=lambda e: e[0])
        with log.open("wb") as f:
            for t, msg in events:
                f.write(struct.pack(">Q", UNIX_AT_BOOT_US + int((t + BOOT_S) * 1e6)) + msg.pack(enc))
    elif kind == "ulg":
        log = tmp / "flight.ulg"
        us = lambda ts: (np.asarray(ts, dtype=float) + BOOT_S) * 1e6  # noqa: E731
        quats = [quat_wxyz_from_R(R_from_euler321(r, p, y)) for _, r, p, y, _ in att]
        topics = {
            "vehicle_attitude": (
                [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[4]", "q")],
                {
                    "timestamp": us([a[0] for a in att]) + 800,
                    "timestamp_sample": us([a[0] for a in att]),
                    "q": np.array(quats).reshape(-1, 4),
                },
            ),
            "distance_sensor": (
                [
                    ("uint64_t", "timestamp"),
                    ("float", "min_distance"),
                    ("float", "max_distance"),
                    ("float", "current_distance"),
                    ("int8_t", "signal_quality"),
                    ("uint8_t", "orientation"),
                ],
                {
                    "timestamp": us([t for t, _ in ranges]),
                    "min_distance": np.full(len(ranges), 0.2),
                    "max_distance": np.full(len(ranges), 40.0),
                    "current_distance": np.array([r for _, r in ranges]),
                    "signal_quality": np.full(len(ranges), -1),
                    "orientation": np.full(len(ranges), 25),
                },
            ),
            "vehicle_air_data": (
                [("uint64_t", "timestamp"), ("float", "baro_alt_meter")],
                {"timestamp": us([t for t, _ in heights]), "baro_alt_meter": 488.0 + np.array([h for _, h in heights])},
            ),
        }
        write_ulog(log, topics)
    else:
        log = tmp / "flight.bin"
        formats = {
            "ATT": (60, "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
            "BARO": (61, "QBf", "TimeUS,I,Alt"),
            "RFND": (62, "QBfBB", "TimeUS,Instance,Dist,Stat,Orient"),
        }
        recs = [
            ("ATT", (int((t + BOOT_S) * 1e6), 0.0, np.degrees(r), 0.0, np.degrees(p), 0.0, np.degrees(y) % 360))
            for t, r, p, y, _ in att
        ]
        recs += [("BARO", (int((t + BOOT_S) * 1e6), 0, h)) for t, h in heights]
        recs += [("RFND", (int((t + BOOT_S) * 1e6), 0, r, 4, 25)) for t, r in ranges]
        recs.sort(key=lambda r: r[1][0])
        write_dataflash(log, formats, recs)

    cam = SimCamera(sc.camera, World.build(sc.world), traj, LockstepClock(), seed=sc.seed)
    end = duration_s - 0.3 if video_end_s is None else video_end_s
    times = np.arange(video_start_s, end, 1.0 / sc.camera.rate_hz)
    if video == "folder":
        out = tmp / "frames"
        out.mkdir()
        lines = []
        for k, t in enumerate(times):
            cv2.imwrite(str(out / f"{k:05d}.png"), cam.render_at(float(t)))
            lines.append(f"{float(t) - video_start_s + 5.0!r} {k:05d}.png")  # the video's own clock starts at 5 s
        (out / "timestamps.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    else:
        out = tmp / "flight.avi"
        w = cv2.VideoWriter(
            str(out),
            cv2.VideoWriter_fourcc(*"MJPG"),
            float(sc.camera.rate_hz),
            (sc.camera.width_px, sc.camera.height_px),
            False,
        )
        for t in times:
            w.write(cam.render_at(float(t)))
        w.release()
    truth = tmp / "truth.tum"
    times = np.arange(0.0, duration_s, 0.01)
    ts = traj.truth_series(times, sc.camera.lever_arm_m)
    write_tum(truth, PoseSeries(times + BOOT_S, ts.positions_xyz_m, ts.orientations_quat_wxyz))
    # The log's time at the video's time zero: a video file's first frame, or the folder's listed 0.
    offset_s = BOOT_S + video_start_s - (5.0 if video == "folder" else 0.0)
    return LogFlight(log, out, config, offset_s, duration_s, truth)


EUROC_T0_NS = 1_403_636_579_763_555_584
EUROC_GYRO_BIAS = np.array([-0.002, 0.021, 0.077])  # rad/s: of the order a EuRoC sequence's gyro shows


def make_euroc(tmp: Path, *, scenario: str = "figure_eight", duration_s: float = 12.0) -> Path:
    """A small EuRoC/ASL folder (mav0/cam0, imu0, state_groundtruth_estimate0) of a simulated flight,
    in the air from its first sample. The IMU frame is the body's turned to x forward, y left, z up (as
    a z-up IMU often is); its gyro has EUROC_GYRO_BIAS, and its samples carry the vibration of flight
    (white, 0.03 rad/s and 0.3 m/s^2)."""
    from mavvo.geometry.frames import rot_x

    sc = load_scenario(scenario)
    traj = make_trajectory(sc.trajectory)
    R_body_imu = rot_x(np.pi)
    D = np.diag([1.0, -1.0, -1.0])
    mav0 = tmp / "dataset" / "mav0"
    for d in ("cam0/data", "imu0", "state_groundtruth_estimate0"):
        (mav0 / d).mkdir(parents=True)
    ns = lambda t: EUROC_T0_NS + int(round(t * 1e9))  # noqa: E731
    rows = []
    rng = np.random.default_rng(7)
    for t in np.arange(0.0, duration_s, 1 / 200.0):
        st = traj.state(float(t))
        f_body = st.R_ned_body.T @ (st.a_ned_m_s2 - np.array([0.0, 0.0, 9.81]))
        w_imu = R_body_imu.T @ st.omega_body_rad_s + EUROC_GYRO_BIAS + 0.03 * rng.standard_normal(3)
        f_imu = R_body_imu.T @ f_body + 0.3 * rng.standard_normal(3)
        rows.append(f"{ns(t)},{','.join(repr(float(x)) for x in w_imu)},{','.join(repr(float(x)) for x in f_imu)}")
    (mav0 / "imu0" / "data.csv").write_text(
        "#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z\n" + "\n".join(rows) + "\n", encoding="utf-8"
    )
    gt = []
    for t in np.arange(0.0, duration_s, 1 / 200.0):
        st = traj.state(float(t))
        q = quat_wxyz_from_R(D @ st.R_ned_body @ R_body_imu)
        gt.append(
            f"{ns(t)},{','.join(repr(float(x)) for x in D @ st.p_ned_m)},{','.join(repr(float(x)) for x in q)},0,0,0,0,0,0,0,0,0"
        )
    (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text(
        "#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,v,v,v,bw,bw,bw,ba,ba,ba\n" + "\n".join(gt) + "\n", encoding="utf-8"
    )
    c = sc.camera
    R_imu_cam = R_body_imu.T @ c.R_body_cam()
    T = np.eye(4)
    T[:3, :3] = R_imu_cam
    T[:3, 3] = R_body_imu.T @ np.asarray(c.lever_arm_m)
    (mav0 / "cam0" / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: ["
        + ", ".join(repr(float(x)) for x in T.ravel())
        + "]\n"
        f"rate_hz: {c.rate_hz}\nresolution: [{c.width_px}, {c.height_px}]\ncamera_model: pinhole\n"
        f"intrinsics: [{c.fx_px}, {c.fy_px}, {c.cx_px}, {c.cy_px}]\ndistortion_model: radial-tangential\n"
        f"distortion_coefficients: [{', '.join(str(float(x)) for x in (tuple(c.distortion) + (0.0,) * 4)[:4])}]\n",
        encoding="utf-8",
    )
    cam = SimCamera(sc.camera, World.build(sc.world), traj, LockstepClock(), seed=sc.seed)
    lines = []
    for t in np.arange(0.5, duration_s - 0.3, 1.0 / c.rate_hz):
        name = f"{ns(t)}.png"
        cv2.imwrite(str(mav0 / "cam0" / "data" / name), cam.render_at(float(t)))
        lines.append(f"{ns(t)},{name}")
    (mav0 / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n" + "\n".join(lines) + "\n", encoding="utf-8")
    return tmp / "dataset"
