"""The result format: what makes a folder a ``ps-lab reconstruct`` result.

A result folder holds ``metrics.json`` whose ``"format"`` is :data:`RESULT_FORMAT`, beside
``normals.npy``, the pictures and, with depth, ``depth.*`` and ``mesh.ply`` (``docs/datasets.md``).
Written by :mod:`ps_lab.reconstruct.pipeline`; recognised here, at the bottom layer, so that the
dataset readers (:mod:`ps_lab.io.frames`) can refuse a result given where a dataset belongs, and
``ps-lab batch`` can read what an earlier run stored, without importing the reconstruction.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["METRICS", "RESULT_FORMAT", "is_result_folder", "read_result_metrics"]

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
