"""Which files are the frames of a dataset, before any pixel is read.

An image folder lists one image per light (``filenames.txt``, else the images its ``.lp`` file
names when it has no ``light_directions.txt``, else file names in natural order; never its
outputs, mask or ground truth; ``dark.<ext>`` is a dark frame); a capture run lists its
frames in ``manifest.json`` (:mod:`ps_lab.io.run`). :func:`plan_frames` returns a
:class:`FramePlan` for either; :mod:`ps_lab.io.dataset` reads the pixels.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.files import sha256
from ps_lab.io.images import SUPPORTED_SUFFIXES, check_is_file, is_supported
from ps_lab.io.lights import find_lp, lp_image_files, read_lp
from ps_lab.io.run import MANIFEST_NAME, is_run, read_manifest

log = logging.getLogger("ps_lab.io.dataset")

FILENAMES = "filenames.txt"
_LIGHT_DIRECTIONS = "light_directions.txt"

# Files in an image folder that are never light frames (outputs, calibration pictures, truth).
_NOT_FRAMES = {
    "mask.png",
    "normal.png",
    "normals.npy",
    "normals.exr",
    "normal16.png",
    "albedo.png",
    "albedo.npy",
    "corruption.png",
    "calibration.png",
}
_GT_NAME = re.compile(r".*[_-]gt(\.[^.]+)?$", re.IGNORECASE)
_DARK_STEM = "dark"


@dataclass(frozen=True)
class FramePlan:
    """Which files make up each frame of a dataset, before any pixel is read.

    Attributes
    ----------
    light_files : list of list of Path
        Per light (in light order), the files of its repeats.
    light_exposures : list of list of float or None
        Exposure time of each of those files when known (manifest), else None.
    dark_files : list of Path
        Dark frames (all lights off); may be empty.
    dark_exposures : list of float or None
    root : Path
    manifest : dict or None

    """

    light_files: list[list[Path]]
    light_exposures: list[list[float | None]]
    dark_files: list[Path]
    dark_exposures: list[float | None]
    root: Path
    manifest: dict | None

    @property
    def names(self) -> list[str]:
        """File name per light (the first repeat's)."""
        return [files[0].name for files in self.light_files]


def is_capture_run(path: Path) -> bool:
    """Tell whether ``path`` is a capture-run folder (it holds ``manifest.json``)."""
    return is_run(path)


def plan_frames(path: Path) -> FramePlan:
    """List the files of every frame of an image folder or capture run.

    Parameters
    ----------
    path : Path
        Dataset folder.

    Returns
    -------
    FramePlan

    Raises
    ------
    DatasetError
        Missing folder, no images, unreadable ``filenames.txt`` or ``manifest.json``, missing files.

    """
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"{root}: no such dataset folder")
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder (a dataset is a folder of images)")
    if is_capture_run(root):
        return _plan_run(root)
    return _plan_image_folder(root)


def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _is_light_frame(path: Path) -> bool:
    name = path.name
    return (
        path.is_file()
        and is_supported(path)
        and not name.startswith(".")
        and name.lower() not in _NOT_FRAMES
        and not _GT_NAME.match(name)
        and path.stem.lower() != _DARK_STEM
    )


def _plan_image_folder(root: Path) -> FramePlan:
    listing = root / FILENAMES
    if listing.exists() or listing.is_symlink():
        check_is_file(listing, "image list")
        try:
            names = [line.strip() for line in listing.read_text(encoding="utf-8-sig").splitlines()]
        except (OSError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{listing}: cannot read file ({exc})") from None
        names = [name for name in names if name and not name.startswith("#")]
        if not names:
            raise DatasetError(f"{listing}: lists no images")
        files = []
        seen: dict[str, int] = {}
        for number, name in enumerate(names, start=1):
            file = root / name
            if name in seen:
                raise DatasetError(
                    f"{listing}: lists {name} twice (entries {seen[name]} and {number})"
                )
            seen[name] = number
            if not (file.exists() or file.is_symlink()):
                raise DatasetError(f"{listing}: lists {name}, which does not exist")
            check_is_file(file, "image file")
            if not is_supported(file):
                raise DatasetError(f"{file}: unsupported image type {file.suffix!r}")
            if not _is_light_frame(file):
                raise DatasetError(
                    f"{listing}: lists {name}, which is not a light image (mask, result, "
                    "ground truth or dark frame)"
                )
            files.append(file)
    elif not (root / _LIGHT_DIRECTIONS).exists() and (lp := find_lp(root)) is not None:
        # The images of an .lp file, in its order, wherever it says they are (RelightLab).
        files = lp_image_files(lp, read_lp(lp)[0], is_supported)
        for file in files:
            check_is_file(file, "image file")
            if not is_supported(file):
                raise DatasetError(f"{file}: unsupported image type {file.suffix!r}")
    else:
        files = sorted(
            (p for p in root.iterdir() if _is_light_frame(p)), key=lambda p: _natural_key(p.name)
        )
        if not files:
            raise DatasetError(
                f"{root}: no images found (supported: {' '.join(SUPPORTED_SUFFIXES)})"
            )
    darks = [p for p in sorted(root.iterdir()) if p.stem.lower() == _DARK_STEM and is_supported(p)]
    if len(darks) > 1:
        raise DatasetError(f"{root}: more than one dark frame ({', '.join(p.name for p in darks)})")
    return FramePlan(
        light_files=[[f] for f in files],
        light_exposures=[[None] for _ in files],
        dark_files=darks,
        dark_exposures=[None] * len(darks),
        root=root,
        manifest=None,
    )


def _plan_run(root: Path) -> FramePlan:
    manifest_file = root / MANIFEST_NAME
    manifest = read_manifest(root, complete=False)
    records = manifest.get("frames")
    if not isinstance(records, list):
        raise DatasetError(f"{manifest_file}: 'frames' is missing or not a list")

    per_light: dict[int, list[dict]] = {}
    darks: list[dict] = []
    for position, record in enumerate(records):
        if not isinstance(record, dict) or "file" not in record or "kind" not in record:
            raise DatasetError(f"{manifest_file}: frame record {position} lacks 'kind' or 'file'")
        if record["kind"] == "dark":
            darks.append(record)
        elif record["kind"] == "light":
            lights = record.get("lights")
            if not isinstance(lights, list) or len(lights) != 1:
                log.debug("skipping frame %s: not a single-light frame", record["file"])
                continue
            per_light.setdefault(int(lights[0]), []).append(record)
        else:
            log.debug("skipping frame %s of kind %r", record["file"], record["kind"])

    plan = manifest.get("plan") or {}
    order = plan.get("lights") if isinstance(plan, dict) else None
    if not order:
        order = sorted(per_light)
    if not order:
        raise DatasetError(f"{manifest_file}: the run has no light frames")
    missing = [light for light in order if light not in per_light]
    if missing:
        raise DatasetError(
            f"{manifest_file}: run is incomplete: no frame for light(s) "
            f"{', '.join(str(m) for m in missing[:10])} (resume the capture with --resume)"
        )

    def file_of(record: dict) -> Path:
        file = root / record["file"]
        if not file.is_file():
            raise DatasetError(f"{file}: frame file listed in {MANIFEST_NAME} is missing")
        digest = record.get("sha256")
        if digest and sha256(file) != str(digest).lower():
            raise DatasetError(f"{file}: frame file changed since capture (sha256 mismatch)")
        return file

    def exposure_of(record: dict) -> float | None:
        value = record.get("exposure_s")
        if value is None:
            return None
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise DatasetError(
                f"{manifest_file}: bad exposure_s {value!r} for {record['file']}"
            ) from None
        if not np.isfinite(value) or value <= 0:
            raise DatasetError(f"{manifest_file}: exposure_s must be positive for {record['file']}")
        return value

    light_records = [sorted(per_light[light], key=lambda r: r.get("repeat", 0)) for light in order]
    return FramePlan(
        light_files=[[file_of(r) for r in records_] for records_ in light_records],
        light_exposures=[[exposure_of(r) for r in records_] for records_ in light_records],
        dark_files=[file_of(r) for r in darks],
        dark_exposures=[exposure_of(r) for r in darks],
        root=root,
        manifest=manifest,
    )
