"""Logged flights, offline: mavvo recordings, flight-controller logs with a video and EuRoC/ASL data sets
read, aligned in time and fed to the daemon through the simulated flight controller and an injected
camera (the replay driver), the report a replay leaves, and ``inspect``."""
