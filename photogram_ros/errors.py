"""Every exception photogram_ros raises on bad input.

Each message says what was wrong and what the user can do about it. Expected numerical failures
(no convergence, too few points) are not exceptions: they come back as results with a status.
"""


class PhotogramError(Exception):
    """Base class: catch this to handle any photogram_ros input error."""


class ConfigError(PhotogramError):
    """A parameter or configuration file is missing, mistyped or out of range."""


class CalibrationError(PhotogramError):
    """The camera calibration is missing or inconsistent with the images."""


class BagError(PhotogramError):
    """A bag cannot be read or written: not a bag, truncated, or an unknown message type."""


class MavlinkError(PhotogramError):
    """A MAVLink link cannot be opened or a log cannot be read."""


class GeodesyError(PhotogramError):
    """Coordinates out of range, or a coordinate reference system that cannot be used."""


class DataError(PhotogramError):
    """Input data (images, fixes, GCP files, point clouds) is malformed or out of range."""


class StorageError(PhotogramError, OSError):
    """A file cannot be written (a full disk, a read-only or missing folder). It is an OSError too,
    so code that handles failed writes handles it; `errno` is the system's."""

    def __init__(self, message: str, errno: int | None = None):
        super().__init__(message)
        self.errno = errno
