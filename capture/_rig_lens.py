"""The rig file's ``[lens]`` table: the camera's calibration, and the simulated camera's lens.

::

    [lens]
    camera = "camera.json"          # `ps-lab calibrate-camera` output, relative to the rig file:
                                    # checked here, copied next to every run's manifest
    distortion = [-0.2, 0.05, 0.0, 0.0, 0.0]   # simulated camera only: k1 k2 p1 p2 k3 applied
    focal_length = 400.0            # to the rendered frames, with this focal length (pixels,
    principal_point = [161.0, 118.5]  # default the scene width) and principal point (default
                                    # the image centre), in loaded-image pixels

A real camera's lens is what it is; ``distortion`` describes the simulated one (the truth a
calibration of its board frames should find). Kept apart from :mod:`.rig` (the schema) so that
the camera's calibration has one small owner.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ps_lab.capture._rig_table import _Table
from ps_lab.errors import PsLabError, RigError
from ps_lab.io.camera import CameraModel, check_frame_size, read_camera_file


@dataclass(frozen=True)
class LensConfig:
    """``[lens]``: the calibrated camera file, and a simulated camera's lens."""

    camera: str | None = None
    distortion: tuple[float, ...] | None = None
    focal_length: float | None = None
    principal_point: tuple[float, float] | None = None


def parse_lens(t: _Table | None, source: Path | None, simulated: bool) -> LensConfig | None:
    """Validate ``[lens]`` (None when the rig file has none); ``simulated``: the camera is."""
    if t is None:
        return None
    camera = t.str("camera")
    distortion = t.data.get("distortion")
    if distortion is not None:
        if not isinstance(distortion, list) or not 1 <= len(distortion) <= 5:
            raise t.error("distortion", "expected 1 to 5 numbers [k1, k2, p1, p2, k3]")
        distortion = t.vector("distortion", len(distortion))
    focal_length = t.float("focal_length", lo=1e-6)
    principal_point = t.vector("principal_point", 2)
    t.done()
    lens = LensConfig(camera, distortion, focal_length, principal_point)
    if camera is not None:
        lens_camera(lens, source, t.origin)  # checked now, not at the first frame
    if distortion is not None and not simulated:
        raise t.error("distortion", "describes the simulated camera's lens (a real lens is "
                      "calibrated: give camera = \"camera.json\")")
    if distortion is None and (focal_length is not None or principal_point is not None):
        raise t.error("focal_length", "describes the simulated lens: give distortion too")
    return lens


def lens_camera_file(lens: LensConfig | None, source: Path | None) -> Path | None:
    """The ``camera.json`` the rig names, resolved against the rig file's folder."""
    if lens is None or lens.camera is None:
        return None
    path = Path(lens.camera).expanduser()
    if not path.is_absolute() and source is not None:
        path = Path(source).parent / path
    return path


def lens_camera(
    lens: LensConfig | None, source: Path | None, origin: str, scene: Any = None
) -> CameraModel | None:
    """The rig's calibrated camera, read and validated (a :class:`RigError` naming [lens]).

    With the rig's ``scene`` (a simulated camera: its frames are ``scene.width x
    scene.height``), a camera calibrated for another frame size is refused by the rule
    ``calibrate`` and ``reconstruct`` apply (:func:`ps_lab.io.camera.check_frame_size`); a real
    camera's frames are checked when a run is loaded.
    """
    path = lens_camera_file(lens, source)
    if path is None:
        return None
    if not path.is_file():
        raise RigError(f"{origin}: [lens] camera: {path} does not exist (write it with "
                       "`ps-lab calibrate-camera`)")
    try:
        camera = read_camera_file(path)
        if scene is not None:
            check_frame_size(camera, (scene.height, scene.width), "a frame of this rig")
    except PsLabError as exc:
        raise RigError(f"{origin}: [lens] camera: {exc}") from None
    return camera


def simulated_lens(lens: LensConfig | None, width: int, height: int) -> CameraModel | None:
    """The simulated camera's lens on frames of ``width x height`` loaded pixels, or None."""
    if lens is None or lens.distortion is None:
        return None
    f = float(lens.focal_length if lens.focal_length is not None else width)
    cx, cy = lens.principal_point or ((width - 1) / 2.0, (height - 1) / 2.0)
    coefficients = tuple(lens.distortion) + (0.0,) * (5 - len(lens.distortion))
    size = (width, height)
    return CameraModel(f, f, float(cx), float(cy), coefficients, size)  # type: ignore[arg-type]


def with_lens_camera(rig: Any, camera_file: Path) -> Any:
    """``rig`` with ``[lens] camera`` set to ``camera_file`` (``ps-lab capture --camera``)."""
    lens = dataclasses.replace(rig.lens or LensConfig(), camera=str(Path(camera_file).resolve()))
    try:
        lens_camera(lens, None, "--camera", rig.scene)
    except RigError as exc:
        raise RigError(str(exc).replace("--camera: [lens] camera: ", "--camera ")) from None
    return dataclasses.replace(rig, lens=lens)
