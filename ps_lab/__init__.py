"""ps-lab: capture, calibrate and reconstruct for photometric stereo.

Sub-packages: :mod:`ps_lab.capture` (rig drivers, cameras, simulators, renderer),
:mod:`ps_lab.calibration` (chrome-sphere light calibration) and
:mod:`ps_lab.reconstruct` (LS / L1 / SBL / R-PCA normal solvers, light refinement).
"""

from ps_lab.errors import CalibrationError, CameraError, DatasetError, PsLabError, RigError

__version__ = "0.1.0"

__all__ = [
    "CalibrationError",
    "CameraError",
    "DatasetError",
    "PsLabError",
    "RigError",
    "__version__",
]
