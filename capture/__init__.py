"""ps_lab.capture: drive a photometric-stereo rig and read what it shoots.

- light controllers: :class:`LightController`, :class:`SerialLightController` (protocol v1 over
  pyserial; importing this package registers the ``pslabsim://`` URL of the simulated controller);
- cameras: :class:`CameraDevice`, :class:`FolderCamera`,
  :class:`~ps_lab.capture.gphoto2_camera.Gphoto2Camera` (optional extra ``ps-lab[gphoto2]``);
- linear RAW (re-exported from :mod:`ps_lab.io`): :func:`load_raw`, :func:`write_dng`;
- rig files and capture sessions: :func:`load_rig`, :class:`CaptureSession`.

The simulators (:mod:`ps_lab.capture.simulated`: controller firmware, its ``pslabsim://`` URL
handler, the simulated camera) are imported only by :mod:`ps_lab.capture.connect`, when a rig
file selects them.
"""

from ps_lab.capture.camera_devices import CameraDevice, CapturedFrame, FolderCamera
from ps_lab.capture.light_controllers import LightController, LightState, SerialLightController
from ps_lab.capture.rig import Rig, load_rig
from ps_lab.capture.session import CaptureSession
from ps_lab.io.dng import write_dng
from ps_lab.io.raw import RAW_SUFFIXES, RawImage, load_raw

__all__ = [
    "RAW_SUFFIXES",
    "CameraDevice",
    "CaptureSession",
    "CapturedFrame",
    "FolderCamera",
    "LightController",
    "LightState",
    "RawImage",
    "Rig",
    "SerialLightController",
    "load_raw",
    "load_rig",
    "write_dng",
]
