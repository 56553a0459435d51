"""The exception hierarchy. The CLI turns any :class:`PsLabError` into one red line and exit 2."""


class PsLabError(Exception):
    """Base of every error ps-lab reports to the user as a one-line message."""


class RigError(PsLabError):
    """The light controller or rig file is unusable: no reply, wrong protocol, bad settings."""


class CameraError(PsLabError):
    """A camera failed to capture, timed out, or produced an unreadable frame."""


class CalibrationError(PsLabError):
    """Light calibration failed: no sphere, no highlight, degenerate geometry."""


class DatasetError(PsLabError):
    """A dataset folder is missing files, inconsistent, or holds unreadable images."""


class OutputError(PsLabError):
    """An output folder cannot be written or would overwrite something that is not a result."""


class ClusterError(PsLabError):
    """A Dask cluster is unusable: Dask not installed, no scheduler at the address, or lost."""
