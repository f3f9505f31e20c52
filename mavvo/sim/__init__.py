"""The simulator: the world outside the companion computer, for tests, ``mavvo sim`` and ``mavvo run``'s
``sim:`` camera.

Folders, lowest first (each may import the ones before it, ``mavvo.evaluation`` and any layer of
``mavvo`` below it; never the commands): ``world/`` (scene, renderer, trajectories, clock, faults, the
simulated camera), ``flight_controller/`` (the simulated autopilot and its sensors), ``scenarios/`` (the
YAML scenarios and a whole simulated flight). The commands import it only when a command runs.
"""
