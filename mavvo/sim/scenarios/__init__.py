"""Scenarios: whole simulated flights in YAML files (this folder), their loader, a flight assembled
from one (clock, flight controller, camera), paired frames without MAVLink, and the daemon flown
against a scenario."""

from mavvo.sim.scenarios.flight import Simulation
from mavvo.sim.scenarios.loader import Scenario, load_scenario, scenario_names
from mavvo.sim.scenarios.service_run import SimRun, run_daemon_in_sim

__all__ = ["Scenario", "SimRun", "Simulation", "load_scenario", "run_daemon_in_sim", "scenario_names"]
