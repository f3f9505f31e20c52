"""mavvo: visual odometry for drones with known gravity, over MAVLink."""

__version__ = "0.1.0"
