"""The result format: what makes a folder a ``ps-lab reconstruct`` result.

A result folder holds ``metrics.json`` whose ``"format"`` is :data:`RESULT_FORMAT`, beside
``normals.npy``, the pictures and, with depth, ``depth.*`` and ``mesh.ply`` (``docs/datasets.md``).
Written by :mod:`ps_lab.reconstruct.pipeline`; recognised here, at the bottom layer, so that the
dataset readers (:mod:`ps_lab.io.frames`) can refuse a result given where a dataset belongs, and
``ps-lab batch`` can read what an earlier run stored, without importing the reconstruction.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

__all__ = [
    "METRICS", "RESULT_FILES", "RESULT_FORMAT", "foreign_entries", "is_result_folder",
    "read_result_metrics",
]

RESULT_FORMAT = "ps-lab-reconstruction"
METRICS = "metrics.json"


def read_result_metrics(folder: Path) -> dict[str, Any] | None:
    """The ``metrics.json`` of a complete result in ``folder``; None if absent or not a result."""
    try:
        metrics = json.loads((Path(folder) / METRICS).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # nested beyond the parser's stack: not ours
        return None
    if not isinstance(metrics, dict) or metrics.get("format") != RESULT_FORMAT:
        return None
    return metrics


def is_result_folder(folder: Path) -> bool:
    """Tell whether ``folder`` holds a ``ps-lab reconstruct`` result (its ``metrics.json``)."""
    return read_result_metrics(folder) is not None


#: Every file a ps-lab result may hold: ``reconstruct``'s outputs, ``integrate``'s depth files
#: added later; a result's own ``metrics.json`` also lists what it wrote (``timings.files``).
RESULT_FILES = frozenset({
    METRICS, "normals.npy", "normal.png", "normal16.png", "normals.exr", "albedo.npy",
    "albedo.png", "albedo.exr", "corruption.png", "appearance.npz", "depth.npy", "depth.tiff",
    "depth.png", "mesh.ply", "light_directions.txt", "light_intensities.txt",
})


def foreign_entries(folder: Path, metrics: dict[str, Any] | None = None) -> list[str]:
    """Names in an earlier result ``folder`` that no ps-lab run wrote, sorted.

    A ps-lab result is replaced whole by the next run into its folder; anything else there (a
    user's notes, a sub-folder) would be deleted with it, so the caller refuses when this is not
    empty. The known names: :data:`RESULT_FILES` and the files ``metrics.json`` lists as written
    (``timings.files``). ``metrics``: the folder's, when already read.
    """
    folder = Path(folder)
    metrics = read_result_metrics(folder) if metrics is None else metrics
    listed = (metrics or {}).get("timings", {})
    listed = listed.get("files", {}) if isinstance(listed, dict) else {}
    known = RESULT_FILES | {name for name in listed if isinstance(name, str)}
    foreign = []
    for entry in sorted(os.scandir(folder), key=lambda e: e.name):
        if entry.name not in known or not entry.is_file(follow_symlinks=False):
            foreign.append(entry.name)
    return foreign

