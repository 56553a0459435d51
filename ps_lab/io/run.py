"""The run format: one folder per capture, described by its ``manifest.json``.

A run folder holds ``manifest.json`` (format ``"ps-lab-run"``, version :data:`RUN_VERSION`) and
``frames/``; a simulated run also ``simulation/`` (the true scene) and
``light_directions_nominal.txt``. ``ps-lab calibrate`` adds ``light_directions.txt`` and
``light_intensities.txt``. The manifest lists exactly the complete frames (``"frames"``: records
with ``kind``, ``file``, ``lights``, ``exposure_s``, ``sha256``, ...), the plan, the camera
settings and a snapshot of the rig file (``"rig"``). See ``docs/capture.md``.

Written by :mod:`ps_lab.capture.session` (:func:`write_manifest`), read by
:mod:`ps_lab.io.dataset` and ``ps-lab calibrate`` (:func:`read_manifest`,
:func:`calibration_target`). Nothing else knows these names.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ps_lab.errors import DatasetError
from ps_lab.io.files import PARTIAL_PREFIX, write_json_atomic

__all__ = [
    "FRAMES_DIR",
    "MANIFEST_NAME",
    "NOMINAL_DIRECTIONS",
    "PARTIAL_PREFIX",
    "RUN_FORMAT",
    "RUN_VERSION",
    "SIMULATION_DIR",
    "calibration_target",
    "is_run",
    "read_manifest",
    "write_manifest",
]

MANIFEST_NAME = "manifest.json"
RUN_FORMAT = "ps-lab-run"
RUN_VERSION = 1
FRAMES_DIR = "frames"
SIMULATION_DIR = "simulation"
NOMINAL_DIRECTIONS = "light_directions_nominal.txt"
#: Keys a manifest written by ``ps-lab capture`` always has.
MANIFEST_KEYS = ("rig", "camera_settings", "plan", "frames")


def is_run(path: Path) -> bool:
    """Tell whether ``path`` is a capture-run folder (it holds ``manifest.json``)."""
    return (Path(path) / MANIFEST_NAME).is_file()


def read_manifest(run_dir: Path, *, complete: bool = True) -> dict[str, Any]:
    """Read and check the manifest of a capture run.

    Parameters
    ----------
    run_dir : Path
        The run folder.
    complete : bool
        Also require this version and every key ``ps-lab capture`` writes (resuming a capture);
        readers of the frames (``complete=False``) need the format only.

    Raises
    ------
    DatasetError
        No manifest, not JSON, or not a ps-lab run manifest.

    """
    path = Path(run_dir) / MANIFEST_NAME
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DatasetError(f"{run_dir} is not a capture run (no {MANIFEST_NAME})") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path} is unreadable: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != RUN_FORMAT:
        raise DatasetError(f"{path} is not a ps-lab run manifest (format != {RUN_FORMAT!r})")
    if not complete:
        return manifest
    if manifest.get("version") != RUN_VERSION:
        raise DatasetError(
            f"{path}: run format version {manifest.get('version')} "
            f"(this ps-lab reads {RUN_VERSION})"
        )
    for key in MANIFEST_KEYS:
        if key not in manifest:
            raise DatasetError(f"{path}: missing {key!r}")
    return manifest


def write_manifest(run_dir: Path, manifest: dict[str, Any]) -> None:
    """Write ``manifest.json`` atomically (the old or the new manifest, never a part)."""
    write_json_atomic(Path(run_dir) / MANIFEST_NAME, manifest)


def calibration_target(manifest: dict[str, Any] | None) -> dict[str, Any]:
    """The rig's ``[calibration]`` table as the run recorded it (empty when absent)."""
    if not manifest:
        return {}
    return (manifest.get("rig") or {}).get("calibration") or {}
