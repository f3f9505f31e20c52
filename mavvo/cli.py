"""The ``mavvo`` command line: the only place that parses argv, maps errors to exit codes and exits.

Exit codes: 0 a clean stop (also after SIGINT/SIGTERM), 2 bad arguments or configuration, 1 anything
else, always with one readable line on stderr (the traceback only with ``--log-level debug``).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import Sequence

from mavvo import __version__
from mavvo.commands import batch, calibrate, camera, check_config, inspect, monitor, preflight, replay, run, sim
from mavvo.errors import ConfigError, MavvoError

log = logging.getLogger("mavvo")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="mavvo",
        description="Visual odometry for drones over MAVLink: roll/pitch from the flight controller, pose back to it.",
    )
    p.add_argument("--version", action="version", version=f"mavvo {__version__}")
    p.add_argument(
        "--log-level",
        default="info",
        choices=("debug", "info", "warning", "error"),
        help="log detail on stderr (default info)",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="same as --log-level debug")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    for command in (run, check_config, preflight, camera, sim, replay, batch, inspect, calibrate, monitor):
        command.add_parser(sub)
    return p


def _one_line(e: BaseException) -> str:
    """An error's text on one line (a key or value quoted from a file may hold line breaks)."""
    return str(e).replace("\r", "\\r").replace("\n", "\\n")


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else getattr(logging, args.log_level.upper())
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.handler(args)
    except ConfigError as e:
        print(f"mavvo: {_one_line(e)}", file=sys.stderr)
        return 2
    except MavvoError as e:
        print(f"mavvo: {_one_line(e)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C before the service installed its handler
        return 0
    except BrokenPipeError:  # the reader went away (`mavvo sim --list | head -1`): nothing to tell it
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so that the interpreter's own flush at exit is silent too
        return 0
    except Exception as e:  # a bug: one line for the operator, the traceback for the developer
        log.debug("unexpected error", exc_info=True)
        print(f"mavvo: unexpected {type(e).__name__}: {e} (--log-level debug shows where)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
