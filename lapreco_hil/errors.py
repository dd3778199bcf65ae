"""The project's exceptions: a small hierarchy, each message says what is wrong and what to do.

The CLI prints ``lapreco: error: <message>`` for any :class:`LaprecoError` and exits non-zero, so every
message must stand alone on one line (which file/device/field, and the remedy).
"""


class LaprecoError(Exception):
    """Base class of every error the app raises on purpose."""


class ConfigError(LaprecoError):
    """A configuration file or value is malformed (names the file and the key)."""


class CalibrationError(LaprecoError):
    """A calibration file is missing, malformed or inconsistent."""


class SceneError(LaprecoError):
    """An unknown or unusable simulated scene."""


class DeviceError(LaprecoError):
    """A device could not be opened, read or understood."""


class DeviceNotFoundError(DeviceError):
    """The device named by a URL does not exist (the message lists what does)."""


class DeviceTimeoutError(DeviceError):
    """A device did not answer in time."""


class DeviceDisconnectedError(DeviceError):
    """A device that was open went away (cable pulled, port closed); drivers try to reconnect."""


class ProtocolError(DeviceError):
    """A device answered with bytes that break its protocol (CRC, framing, error byte)."""


class OutputError(LaprecoError):
    """An output folder or file cannot be written."""


class ReconstructionError(LaprecoError):
    """The pipeline could not produce a reconstruction from its input (too few tracks, no parallax)."""


class SessionError(LaprecoError):
    """A recorded session is missing, malformed or cut short in a way that cannot be read."""
