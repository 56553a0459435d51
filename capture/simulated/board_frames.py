"""Board frames of a simulated rig's camera, for ``ps-lab calibrate-camera``.

A ChArUco board rendered at seeded poses through the rig's ``[lens]`` (``ps-lab rig
board-frames``); reached through :func:`ps_lab.capture.connect.write_rig_board_frames`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ps_lab.capture._rig_lens import simulated_lens
from ps_lab.errors import RigError
from ps_lab.io.camera import CameraModel
from ps_lab.render.board import CharucoTarget, write_board_frames


def write_rig_board_frames(rig: Any, out: Path, views: int = 12, seed: int = 0) -> list[Path]:
    """Board frames a simulated rig's camera records: a ChArUco board at seeded poses.

    The board (:func:`board_target`) is rendered through the rig's ``[lens]`` (its focal length,
    principal point and distortion; an ideal lens of focal length = scene width without one) at
    the loaded frames' size, what ``ps-lab calibrate-camera`` then calibrates.

    Raises
    ------
    RigError
        The rig's camera is not simulated (a real camera photographs a real board).
    """
    if rig.scene is None or not rig.simulated_camera:
        raise RigError(f"{rig.source or rig.name}: board frames are rendered for a simulated "
                       "camera only (photograph a printed board with a real one)")
    width, height = rig.scene.width, rig.scene.height
    camera = simulated_lens(rig.lens, width, height) or CameraModel(
        float(width), float(width), (width - 1) / 2.0, (height - 1) / 2.0,
        image_size=(width, height),
    )
    return write_board_frames(Path(out), board_target(width), camera, views, seed=seed)


def board_target(width: int) -> CharucoTarget:
    """The simulated rigs' board for frames ``width`` pixels wide.

    9 x 6 squares of 20 mm with 15 mm DICT_5X5_100 markers from 320 px up; on smaller frames
    6 x 4 squares with 16 mm DICT_4X4_50 markers, so that a marker's bit still spans ~3 pixels
    (the ArUco decoder's limit is about 2).
    """
    if width >= 320:
        return CharucoTarget(9, 6, 20.0, 15.0, "DICT_5X5_100")
    return CharucoTarget(6, 4, 20.0, 16.0, "DICT_4X4_50")
