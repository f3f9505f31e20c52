"""Exception hierarchy: one root, one subclass per boundary the service crosses."""


class MavvoError(Exception):
    """Root of every error mavvo raises on purpose."""


class ConfigError(MavvoError):
    """A configuration file or value is invalid; the message names the key path."""


class LinkError(MavvoError):
    """The MAVLink connection failed or was misconfigured."""


class RecordingError(MavvoError):
    """A recording could not be started (the folder cannot be made); the service runs without it."""


class CameraError(MavvoError):
    """A frame source failed or was misconfigured."""


class CameraEnded(CameraError):
    """A finite frame source (file, folder, simulation) has no more frames: a normal end."""


class FrameRefused(CameraError):
    """One frame was refused (larger than ``camera.width_px`` x ``camera.height_px``); the source goes on."""


class CameraLost(CameraError):
    """A frame source failed and retrying for ``camera.lost_after_s`` did not bring it back: the service
    ends non-zero so that its supervisor (systemd) restarts it."""


class ServiceFailed(MavvoError):
    """The service cannot go on (a thread died, the camera is lost); the process exits non-zero."""
