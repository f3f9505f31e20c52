"""Exception hierarchy: one root, one subclass per boundary the service crosses."""


class MavvoError(Exception):
    """Root of every error mavvo raises on purpose."""


class ConfigError(MavvoError):
    """A configuration file or value is invalid; the message names the key path."""


class LinkError(MavvoError):
    """The MAVLink connection failed or was misconfigured."""


class CameraError(MavvoError):
    """A frame source failed or was misconfigured."""


class CameraEnded(CameraError):
    """A finite frame source (file, folder, simulation) has no more frames: a normal end."""
