"""``mavvo check-config FILE``: load a settings file strictly and report the first problem."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mavvo.errors import ConfigError
from mavvo.service.link_options import read_signing_key
from mavvo.service.settings import load_config
from mavvo.service.yaml_loader import load_yaml


def add_parser(sub: Any) -> None:
    c = sub.add_parser(
        "check-config",
        help="check a settings file and exit",
        description="Load a settings file strictly and report the first problem, with its key path "
        "(also the signing key file, as mavvo run reads it). Exit 0: ok; 2: a problem.",
    )
    c.add_argument("file", type=Path, metavar="FILE")

    c.set_defaults(handler=main)


def main(args: argparse.Namespace) -> int:
    cfg = load_config(args.file)
    if cfg.link.signing_key_file:  # exactly the check mavvo run makes when it opens the link
        try:
            read_signing_key(cfg.link.signing_key_file)
        except ConfigError as e:
            raise ConfigError(f"{args.file}: {e}") from e
    # An empty file (or one of comments only) is valid, but most likely not what was meant.
    nothing = "; it sets nothing, so every setting is its default" if not load_yaml(args.file) else ""
    print(
        f"{args.file}: ok (link {cfg.link.url}, camera {cfg.camera.source} {cfg.camera.width_px}x{cfg.camera.height_px}, scale from {cfg.odometry.scale.source}){nothing}"
    )
    return 0
