"""Visual odometry: feature tracking, keyframes, metric scale, the Kalman filter and the
:class:`~mavvo.odometry.pipeline.Odometry` pipeline. Pure: no threads, sockets or clocks. Imports
``mavvo.estimation``, ``mavvo.geometry`` and the top-level vocabulary only."""
