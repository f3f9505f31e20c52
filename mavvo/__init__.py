"""mavvo: visual odometry for drones with known gravity, over MAVLink.

The package is layered; each folder may import only the ones listed below it (``docs/design.md``):

- ``commands/`` and ``cli.py``: the ``mavvo`` command (argument parsing, one module per command);
- ``offline/``: logged flights (recordings, flight-controller logs, data sets) replayed through the daemon;
- ``sim/``: the simulator (world and renderer, the simulated flight controller, scenarios);
- ``evaluation/``: trajectory metrics and the files an evaluation leaves;
- ``calibration/``: camera calibration;
- ``service/``: the daemon and its edges (MAVLink link, camera sources, timing, recorder, settings);
- ``odometry/``: paired frames in, filtered metric poses out (pure: no threads, sockets or clocks);
- ``estimation/``: robust relative pose (RANSAC, refinement, model selection);
- ``geometry/``: frames, camera models and the paper's solvers;
- ``errors``, ``options``, ``types`` and ``jit`` at the top level: the shared vocabulary every layer may use.
"""

__version__ = "0.1.0"
