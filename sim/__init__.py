"""The world outside the companion computer, for tests, ``mavvo sim`` and ``mavvo replay``.

Folders, lowest first (each may import the ones before it, and any of ``mavvo`` but its commands):
``evaluation/`` (trajectory metrics and report files), ``world/`` (scene, renderer, trajectories,
clock, faults, the simulated camera), ``flight_controller/`` (the simulated autopilot and its
sensors), ``scenarios/`` (the YAML scenarios and a whole simulated flight), ``replay/`` (recordings,
flight-controller logs and data sets fed to the daemon), ``faults/`` (the fault suite and the
settings-file fuzzer; above even ``mavvo``'s command line, which it drives). ``mavvo`` imports ``sim`` only from its
command modules, and only when the command runs."""
