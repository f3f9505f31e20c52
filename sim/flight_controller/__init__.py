"""The simulated flight controller: an ArduPilot-like autopilot speaking MAVLink 2 on a socket, and
the sensors it reports (attitude, rangefinder, barometer) drawn from the truth."""
