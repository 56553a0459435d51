"""``ps-lab view RESULT --export DIR --format relight``: a result in RelightLab's web layout.

The format itself (``info.json``, ``plane_N.jpg``, quantisation) is :mod:`ps_lab.io.relightlab`;
this module gathers what a result folder holds (its PTM / HSH fit from ``appearance.npz``, its
captured lights, its normal and albedo pictures) and writes the folder staged (complete or
absent). :func:`result_lights` is also what the viewer's light disc shows;
:func:`load_view_result` and :func:`result_appearance` let the viewer open such a folder.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from ps_lab.errors import DatasetError, OutputError, PsLabError
from ps_lab.io.appearance import Appearance, read_appearance
from ps_lab.io.encoding import srgb_to_linear
from ps_lab.io.files import staged_folder
from ps_lab.io.lights import find_lp, read_light_directions, read_lp
from ps_lab.io.relightlab import INFO, is_relightlab_folder, read_relightlab, write_relightlab
from ps_lab.view.result import CHANNELS, ViewResult, load_result

__all__ = [
    "export_relightlab",
    "load_view_result",
    "relightlab_lights",
    "result_appearance",
    "result_lights",
]


def result_lights(root: Path) -> np.ndarray | None:
    """The captured light directions of a result (n, 3), or None when none can be found.

    The result's own ``light_directions.txt`` (refined lights) first, else the dataset's that
    ``metrics.json`` names (its ``light_directions.txt`` or RelightLab ``.lp`` file).
    """
    root = Path(root)
    lights = relightlab_lights(root)
    if lights is not None:
        return lights
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


# --- the viewer's side: a result's fit, and a RelightLab folder as a result -----------------


def result_appearance(root: Path) -> Appearance | None:
    """The appearance fit the viewer relights: a RelightLab folder's, else ``appearance.npz``."""
    root = Path(root)
    if is_relightlab_folder(root) and not (root / "normals.npy").exists():
        return read_relightlab(root)[0]
    return read_appearance(root)


def load_view_result(root: Path, name: str | None = None) -> ViewResult:
    """:func:`ps_lab.view.result.load_result`, or a RelightLab folder read as a result.

    A RelightLab folder (``info.json``, ``plane_N.jpg``) gives its normals from ``normals.png``
    ((n + 1)/2, black outside the object; a flat normal (0, 0, 1) where it has none) and its
    albedo layer from ``albedo.png`` (sRGB decoded); ``albedo_scale`` is ``1 / exposure`` of
    ``info.json`` (the fit relit from above, 99th percentile), which the page divides the
    coefficients by.
    """
    root = Path(root)
    if not (is_relightlab_folder(root) and not (root / "normals.npy").exists()):
        return load_result(root, name)
    appearance, info = read_relightlab(root)
    h, w = appearance.coefficients.shape[:2]
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = 1.0
    picture = cv2.imread(str(root / "normals.png"), cv2.IMREAD_COLOR)
    if picture is not None and picture.shape[:2] == (h, w):
        rgb = picture[..., ::-1].astype(np.float32)
        decoded = rgb / 127.5 - 1.0
        length = np.linalg.norm(decoded, axis=2, keepdims=True)
        inside = rgb.any(axis=2)
        normals = np.where(inside[..., None], decoded / np.maximum(length, 1e-6), 0.0)
    mask = np.linalg.norm(normals, axis=2) > 0.5
    layers = np.zeros((h, w, len(CHANNELS)), np.float32)
    layers[..., 0:3] = normals
    layers[..., 5:8] = np.nan
    albedo = cv2.imread(str(root / "albedo.png"), cv2.IMREAD_COLOR)
    if albedo is not None and albedo.shape[:2] == (h, w):
        grey = srgb_to_linear(albedo[..., ::-1].astype(np.float32) / 255.0).mean(axis=2)
        layers[..., 3] = np.where(mask, grey, 0.0)
    else:
        layers[..., 3] = mask
    exposure = float((info.get("ps_lab") or {}).get("exposure", 1.0))
    has = {"outliers": False, "error": False, "depth": False, "mesh": False}
    metrics = {
        "method": f"RelightLab {info.get('type')}",
        "lights": len(info.get("lights", [])) // 3,
        "pixels": int(mask.sum()),
    }
    return ViewResult(root, name or root.name, layers, 1.0 / exposure, has, metrics, None)


def relightlab_lights(root: Path) -> np.ndarray | None:
    """A RelightLab folder's captured lights (``info.json``'s ``lights``), or None."""
    root = Path(root)
    if not is_relightlab_folder(root):
        return None
    try:
        info = json.loads((root / INFO).read_text(encoding="utf-8"))
        lights = np.asarray(info.get("lights", []), np.float64).reshape(-1, 3)
    except (OSError, ValueError, TypeError):
        return None
    return lights if lights.size else None
