"""Scenarios: a whole simulated flight in one YAML file (``mavvo/sim/scenarios/NAME.yaml``).

Top-level keys: ``name``, ``description``, ``duration_s`` (default: the trajectory's own length),
``seed`` (every random draw of the run), ``world``, ``trajectory`` (with ``type``: one of
:data:`mavvo.sim.world.trajectories.TRAJECTORY_SPECS`), ``camera``, ``flight_controller`` and ``faults`` (a list).
Every key is checked: an unknown key, a wrong type or an out-of-range value is a ConfigError that names
the file and the key path.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path

from mavvo.errors import ConfigError
from mavvo.options import bounded
from mavvo.service.yaml_loader import build, load_yaml
from mavvo.sim.flight_controller.spec import FlightControllerSpec
from mavvo.sim.world.camera import CameraSpec
from mavvo.sim.world.faults import FaultSpec
from mavvo.sim.world.scene import BoxSpec, PatchSpec, WorldSpec
from mavvo.sim.world.trajectories import TRAJECTORY_SPECS, HoverSpec, TrajectorySpec

SCENARIO_DIR = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Scenario:
    """One simulated flight."""

    name: str = bounded("unnamed", "short name")
    description: str = bounded("", "one line on what the scenario exercises")
    duration_s: float | None = bounded(None, "length of the run; default the trajectory's", gt=0)
    seed: int = bounded(0, "seed of every random draw (noise, textures are seeded by world.texture_seed)", ge=0)
    world: WorldSpec = field(default_factory=WorldSpec)
    trajectory: TrajectorySpec = field(default_factory=HoverSpec)
    camera: CameraSpec = field(default_factory=CameraSpec)
    flight_controller: FlightControllerSpec = field(default_factory=FlightControllerSpec)
    faults: tuple[FaultSpec, ...] = ()


def scenario_names() -> list[str]:
    """Names of the scenarios shipped in ``mavvo/sim/scenarios``."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def scenario_path(name_or_path: str | Path) -> Path:
    """A shipped scenario's file by name, or the given path; ConfigError if neither exists."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml"):
        if not p.is_file():
            raise ConfigError(f"{p}: scenario file not found")
        return p
    shipped = SCENARIO_DIR / f"{name_or_path}.yaml"
    if not shipped.is_file():
        raise ConfigError(
            f"scenario {str(name_or_path)!r}: not found; expected one of {', '.join(scenario_names())} or a .yaml path"
        )
    return shipped


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a scenario by shipped name or path."""
    path = scenario_path(name_or_path)
    return build(Scenario, load_yaml(path), str(path))


def scenario_keys_markdown() -> str:
    """Every scenario key with its default and help, as markdown tables (docs/simulator.md holds a copy
    that a test keeps current)."""
    sections = [(Scenario, "top level"), (WorldSpec, "world"), (BoxSpec, "world.boxes[]")]
    sections += [(PatchSpec, "world.plain_patches[]")]
    sections += [(cls, f"trajectory, type: {name}") for name, cls in TRAJECTORY_SPECS.items()]
    sections += [(CameraSpec, "camera"), (FlightControllerSpec, "flight_controller"), (FaultSpec, "faults[]")]
    out = []
    for cls, title in sections:
        out += [f"#### {title}", "", "| key | default | meaning |", "|---|---|---|"]
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if dataclasses.is_dataclass(hints[f.name]) or f.name in ("boxes", "plain_patches", "faults", "trajectory"):
                continue  # sections of their own
            d = f.default
            shown = "the trajectory's" if d is None else (list(d) if isinstance(d, tuple) else d)
            out.append(f"| `{f.name}` | `{shown}` | {f.metadata.get('help', '')} |")
        out.append("")
    return "\n".join(out)
