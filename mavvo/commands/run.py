"""``mavvo run``: the service, as systemd starts it."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from mavvo.errors import ServiceFailed
from mavvo.service.daemon import Daemon
from mavvo.service.settings import ServiceConfig, load_config


def add_parser(sub: Any) -> None:
    r = sub.add_parser(
        "run",
        help="run the service (what systemd starts)",
        description="Run the visual-odometry service: read ATTITUDE from the flight controller, frames from the camera, "
        "send VISION_POSITION_ESTIMATE back. Stops cleanly on SIGTERM or Ctrl-C (a second one skips the drain); SIGHUP "
        "reopens the recording's files. Exits 1 when it cannot go on (a thread died, the camera is lost), for systemd to restart it.",
    )
    r.add_argument(
        "--config",
        required=True,
        type=Path,
        metavar="FILE",
        help="the YAML settings (see config/default.yaml for every key)",
    )
    r.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="DIR",
        help="record the flight for mavvo replay into a new folder under DIR (sets record.dir)",
    )

    r.set_defaults(handler=main)


def sim_camera(argument: str, options: Any, clock: Any, fc: Any = None) -> Any:
    """``camera.source: sim:SCENARIO``: the simulator's rendered camera, in real time, flying the
    scenario on the simulated flight controller's clock (``mavvo sim --fc-only``) once it is heard."""
    from mavvo.sim.scenarios.flight import scenario_camera  # sim is loaded only when asked for

    return scenario_camera(argument, clock, fc)


def with_record(config: ServiceConfig, record: Path | None) -> ServiceConfig:
    """``config`` recording into ``record`` when given."""
    return (
        config
        if record is None
        else dataclasses.replace(config, record=dataclasses.replace(config.record, dir=str(record)))
    )


def main(args: argparse.Namespace) -> int:
    config = with_record(load_config(args.config), args.record)
    daemon = Daemon(config, schemes={"sim": sim_camera})
    summary = daemon.run()
    if summary.failure:  # exit non-zero: systemd restarts the service
        raise ServiceFailed(summary.failure)
    return 0
