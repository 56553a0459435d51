"""A RelightLab folder opened by the viewer as a result, and the fit the viewer relights.

The format is :mod:`ps_lab.appearance.relightlab`, the export that writes such a folder
:mod:`ps_lab.appearance.export`: :func:`load_view_result` and :func:`result_appearance` let the
viewer open either a result folder or a RelightLab folder.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ps_lab.appearance.models import Appearance
from ps_lab.appearance.relightlab import is_relightlab_folder, read_relightlab
from ps_lab.appearance.store import read_appearance
from ps_lab.io.encoding import srgb_to_linear
from ps_lab.view.result import CHANNELS, ViewResult, load_result

__all__ = ["load_view_result", "result_appearance"]


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
    exposure = float(info.get("ps_lab", {}).get("exposure", 1.0))
    has = {"outliers": False, "error": False, "depth": False, "mesh": False}
    metrics = {
        "method": f"RelightLab {info.get('type')}",
        "lights": len(info.get("lights", [])) // 3,
        "pixels": int(mask.sum()),
    }
    return ViewResult(root, name or root.name, layers, 1.0 / exposure, has, metrics, None)
