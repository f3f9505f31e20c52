"""Replay: logged flights (mavvo recordings, flight-controller logs with a video, EuRoC/ASL data
sets) fed to the daemon through the simulated flight controller and an injected camera, and the
report a replay leaves."""
