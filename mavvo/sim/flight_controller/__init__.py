"""The simulated flight controller: an ArduPilot-like autopilot speaking MAVLink 2 on a socket, the
sensors it reports (attitude, rangefinder, barometer) drawn from the truth, and the position estimator
(its EKF) that fuses the vision it receives."""
