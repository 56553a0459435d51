"""``ps-lab view RESULT --export DIR --format relight``: a result in RelightLab's web layout.

The format itself (``info.json``, ``plane_N.jpg``, quantisation) is :mod:`ps_lab.io.relightlab`;
this module gathers what a result folder holds (its PTM / HSH fit from ``appearance.npz``, its
captured lights, its normal and albedo pictures) and writes the folder staged (complete or
absent). :func:`result_lights` is also what the viewer's light disc shows.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from ps_lab.errors import DatasetError, OutputError, PsLabError
from ps_lab.io.appearance import read_appearance
from ps_lab.io.files import staged_folder
from ps_lab.io.lights import find_lp, read_light_directions, read_lp
from ps_lab.io.relightlab import INFO, write_relightlab

__all__ = ["export_relightlab", "result_lights"]


def result_lights(root: Path) -> np.ndarray | None:
    """The captured light directions of a result (n, 3), or None when none can be found.

    The result's own ``light_directions.txt`` (refined lights) first, else the dataset's that
    ``metrics.json`` names (its ``light_directions.txt`` or RelightLab ``.lp`` file).
    """
    root = Path(root)
    own = root / "light_directions.txt"
    candidates = [own]
    try:
        metrics = json.loads((root / "metrics.json").read_text(encoding="utf-8"))
        dataset = Path(metrics["dataset"]) if isinstance(metrics, dict) else None
    except (OSError, ValueError, KeyError, TypeError):
        dataset = None
    if dataset is not None:
        candidates.append(dataset / "light_directions.txt")
    for file in candidates:
        if file.is_file():
            try:
                return read_light_directions(file)
            except PsLabError:
                continue
    if dataset is not None and dataset.is_dir():
        lp = find_lp(dataset)
        if lp is not None:
            try:
                return np.asarray(read_lp(lp)[1], np.float64)
            except PsLabError:
                return None
    return None


def export_relightlab(result: Path, out: Path) -> dict:
    """Write the result's PTM or HSH fit into ``out`` in RelightLab's web layout.

    ``out`` must be absent, empty or an earlier such export; it is replaced only when the new
    folder is complete.

    Returns
    -------
    dict
        The ``info.json`` written.

    Raises
    ------
    DatasetError
        The result has no appearance fit, or a file of it cannot be read.
    OutputError
        A model the layout cannot hold, or ``out`` cannot be written.

    """
    result, out = Path(result), Path(out)
    if not (result / "normals.npy").is_file():
        raise DatasetError(f"{result}: not a ps-lab result (no normals.npy)")
    appearance = read_appearance(result)
    if appearance is None:
        raise DatasetError(
            f"{result}: no appearance.npz; reconstruct with --appearance ptm, hsh2 or hsh3"
        )
    lights = result_lights(result)
    if lights is None:
        lights = np.zeros((0, 3))
    pictures = {}
    for name in ("normal.png", "albedo.png"):
        picture = cv2.imread(str(result / name), cv2.IMREAD_COLOR)
        pictures[name] = None if picture is None else picture[..., ::-1]

    def check(folder: Path) -> None:
        if folder.exists() and (not folder.is_dir() or (
            any(folder.iterdir()) and not (folder / INFO).is_file()
        )):
            raise OutputError(
                f"{folder}: not a RelightLab export and not empty (choose a new or empty folder)"
            )

    with staged_folder(out, check=check, error=OutputError) as stage:
        info = write_relightlab(
            stage, appearance, lights,
            normal_picture=pictures["normal.png"], albedo_picture=pictures["albedo.png"],
        )
    return info
