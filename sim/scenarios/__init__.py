"""Scenarios: whole simulated flights in YAML files (this folder), their loader, a flight assembled
from one (clock, flight controller, camera), paired frames without MAVLink, and the daemon flown
against a scenario."""
