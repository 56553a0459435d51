"""A capture read as its codes: whether it can be, and its frames one light at a time.

:func:`frame_coding` says how a dataset's frames are staged (:mod:`ps_lab.io.bands`): as the
codes of their 8- or 16-bit files when nothing but the transfer curve lies between a file and its
light, else as linear float32 (:func:`ps_lab.io.dataset.iter_frames`). :func:`read_coded_light`
reads one light's codes and :func:`check_coded_geometry` checks them against the first light's
as :func:`ps_lab.io.dataset.iter_frames` checks decoded frames; a frame unlike the first raises
:class:`NotCodedError`, after which the caller stages in float (where that frame meets the
float path's own checks).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.coding import Coded, Coding, float_coding
from ps_lab.io.frames import FramePlan
from ps_lab.io.images import read_frame

__all__ = ["CodedLight", "NotCodedError", "check_coded_geometry", "frame_coding",
           "read_coded_light"]


def frame_coding(plan: FramePlan) -> Coding:
    """How a dataset's frames are staged (:mod:`ps_lab.io.bands`); reads light 1's file.

    Their codes (:class:`ps_lab.io.coding.Coded`) when every light is one 8- or 16-bit file read
    as it is: no dark frame to subtract, no exposure to scale to, no repeats to average and no
    lens distortion to undo (what :func:`ps_lab.io.dataset.read_light_frame` would compute is
    then the code table's value, bit for bit); else linear float32 of the frames' channels.
    """
    first = read_frame(plan.light_files[0][0], plan.encoding)
    if isinstance(first, Coded):
        if _read_as_coded(plan):
            return first.coding
        return float_coding(first.channels)
    return float_coding(first.data.shape[2])


def _read_as_coded(plan: FramePlan) -> bool:
    if plan.dark_files or plan.camera is not None:
        return False
    if any(len(files) != 1 for files in plan.light_files):
        return False
    known = {e for (e,) in plan.light_exposures if e is not None}
    return len(known) <= 1


class NotCodedError(DatasetError):
    """A frame of a capture staged as codes is not like light 1's (the caller stages in float)."""


@dataclass(frozen=True)
class CodedLight:
    """One light's frame of a coded capture (:func:`read_coded_light`)."""

    light: int
    file: Path
    frame: Coded


def read_coded_light(plan: FramePlan, light: int) -> CodedLight:
    """Light ``light``'s file as codes (a capture :func:`frame_coding` stages as codes).

    Raises
    ------
    DatasetError
        The file is unreadable, or not an 8- or 16-bit file like light 1's.
    """
    file = plan.light_files[light][0]
    frame = read_frame(file, plan.encoding)
    if not isinstance(frame, Coded):
        first = plan.light_files[0][0]
        raise NotCodedError(
            f"{file}: not an 8- or 16-bit image like the others (first: {first.name}); "
            "a mix means a file from another capture"
        )
    return CodedLight(light, file, frame)


def check_coded_geometry(frame: CodedLight, reference: CodedLight) -> None:
    """The checks of :func:`iter_frames` (size, channels, bit depth) between two coded frames."""
    codes, first = frame.frame.codes, reference.frame.codes
    if codes.shape[:2] != first.shape[:2]:
        h, w = codes.shape[:2]
        rh, rw = first.shape[:2]
        raise DatasetError(
            f"{frame.file}: image size {w}x{h} differs from {reference.file.name} ({rw}x{rh})"
        )
    if codes.shape[2] != first.shape[2]:
        kinds = {1: "grey", 3: "colour"}
        raise DatasetError(
            f"{frame.file}: {kinds[codes.shape[2]]} image among "
            f"{kinds[first.shape[2]]} images (first: {reference.file.name})"
        )
    if frame.frame.bit_depth != reference.frame.bit_depth or (
            frame.frame.coding.clip != reference.frame.coding.clip):
        raise NotCodedError(
            f"{frame.file}: {frame.frame.bit_depth}-bit image among "
            f"{reference.frame.bit_depth}-bit images (first: {reference.file.name}); "
            "a mix means a file from another capture"
        )
    table, expected = frame.frame.coding.table, reference.frame.coding.table
    if table is not expected and not np.array_equal(table, expected):
        raise NotCodedError(
            f"{frame.file}: its encoding ({frame.frame.encoding}) differs from "
            f"{reference.file.name}'s ({reference.frame.encoding}); a mix means a file from "
            "another capture (or give --encoding)"
        )
