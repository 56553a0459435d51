"""Which files are the frames of a dataset, before any pixel is read.

An image folder lists one image per light (``filenames.txt``, else the images its ``.lp`` file
names when it has no ``light_directions.txt``, else file names in natural order; never its
outputs, mask or ground truth; ``dark.<ext>`` and ``ambient.<ext>`` are the frame with the rig's
lights off, subtracted from every frame; ``ref.<ext>``, ``reference.<ext>`` and ``outline.<ext>``
are room-light frames for the sphere outline, never lights; ``<name>.mask.png`` is a mask, as
``mask.png`` is); a capture run lists its frames in ``manifest.json`` (:mod:`ps_lab.io.run`).
docs/datasets.md lists what counts as a frame. :func:`plan_frames` returns a
:class:`FramePlan` for either; :mod:`ps_lab.io.dataset` reads the pixels.

Two folders that are not datasets are told apart before any file is taken for a frame
(:func:`check_dataset_folder`): a ``ps-lab reconstruct`` result (:mod:`ps_lab.io.result`), and a
folder that holds datasets in subfolders (the input of ``ps-lab batch``).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.camera import CAMERA_FILE, CameraModel, read_camera_file
from ps_lab.io.files import sha256
from ps_lab.io.images import ENCODINGS, SUPPORTED_SUFFIXES, check_is_file, is_supported
from ps_lab.io.light_files import find_lp, lp_image_files, read_lp_rows
from ps_lab.io.result import is_result_folder, read_result_metrics
from ps_lab.io.run import MANIFEST_NAME, is_run, read_manifest

log = logging.getLogger("ps_lab.io.dataset")

FILENAMES = "filenames.txt"
_LIGHT_DIRECTIONS = "light_directions.txt"

# Files in an image folder that are never light frames (outputs, calibration pictures, truth).
_NOT_FRAMES = {
    "mask.png",
    "normal.png",
    "normal16.png",
    "normals.npy",
    "normals.exr",
    "normal16.png",
    "albedo.png",
    "albedo.npy",
    "albedo.exr",
    "corruption.png",
    "calibration.png",
    "camera.png",
    "depth.npy",
    "depth.tiff",
    "depth.png",
}
# Subfolders named in an error about a folder of datasets.
_NAMED_SUBFOLDERS = 3
_GT_NAME = re.compile(r".*[_-]gt(\.[^.]+)?$", re.IGNORECASE)
_DARK_STEM = "dark"
# Frames with the rig's lights off (subtracted like the dark frame) and room-light frames of
# the sphere outline (PSBox's ref.JPG): never lights.
_AMBIENT_STEMS = ("dark", "ambient")
REFERENCE_STEMS = ("ref", "reference", "outline")
MASK_NAME = "mask.png"
_MASK_SUFFIX = ".mask.png"  # <name>.mask.png beside <name>.<k>.png (a common layout)


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
    encoding : str
        How the frames' integer values map to light (``ps_lab.io.encoding``).
    camera : CameraModel or None
        The dataset's ``camera.json`` (:mod:`ps_lab.io.camera`): its frames are read undistorted.

    """

    light_files: list[list[Path]]
    light_exposures: list[list[float | None]]
    dark_files: list[Path]
    dark_exposures: list[float | None]
    root: Path
    manifest: dict | None
    encoding: str = "auto"
    camera: CameraModel | None = None

    @property
    def names(self) -> list[str]:
        """File name per light (the first repeat's)."""
        return [files[0].name for files in self.light_files]


class FolderOfDatasetsError(DatasetError):
    """A folder with no frames of its own whose subfolders are datasets.

    Attributes
    ----------
    folder : Path
    datasets : list of Path
        The subfolders that are image folders or capture runs, in natural order.
    """

    def __init__(self, folder: Path, datasets: list[Path]) -> None:
        self.folder = Path(folder)
        self.datasets = list(datasets)
        names = [p.name for p in datasets[:_NAMED_SUBFOLDERS]]
        more = ", ..." if len(datasets) > _NAMED_SUBFOLDERS else ""
        kind = "subfolder holds a dataset" if len(datasets) == 1 else "subfolders hold datasets"
        super().__init__(
            f"{folder}: a folder of datasets, not a dataset (no frames of its own; "
            f"{len(datasets)} {kind}: {', '.join(names)}{more}): give one of them, "
            f"e.g. {datasets[0]}"
        )


def is_capture_run(path: Path) -> bool:
    """Tell whether ``path`` is a capture-run folder (it holds ``manifest.json``)."""
    return is_run(path)


def check_dataset_folder(path: Path) -> None:
    """Refuse a folder that is not a dataset but looks like one to a file listing.

    Raises
    ------
    DatasetError
        ``path`` is a ``ps-lab reconstruct`` result (its ``metrics.json``; the line names the
        dataset it came from), or it holds no frames of its own and only results in its
        subfolders.
    FolderOfDatasetsError
        It holds no frames of its own, and datasets in its subfolders.

    """
    root = Path(path)
    if not root.is_dir():
        return
    metrics = read_result_metrics(root)
    if metrics is not None:
        source = metrics.get("dataset")
        made_from = f"; give the dataset it was made from: {source}" if source else ""
        raise DatasetError(
            f"{root}: a ps-lab reconstruct result (its metrics.json), not a dataset{made_from}"
        )
    if (
        is_capture_run(root)
        or (root / FILENAMES).exists()
        or _has_frames(root)
        or find_lp(root) is not None  # its images may lie in a subfolder (jpg/Name_0001.jpg)
    ):
        return
    subfolders = sorted(
        (p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")),
        key=lambda p: _natural_key(p.name),
    )
    datasets = [p for p in subfolders if not is_result_folder(p) and _looks_like_dataset(p)]
    if datasets:
        raise FolderOfDatasetsError(root, datasets)
    results = [p.name for p in subfolders if is_result_folder(p)]
    if results:
        more = ", ..." if len(results) > _NAMED_SUBFOLDERS else ""
        raise DatasetError(
            f"{root}: not a dataset: no frames of its own, and its subfolders are ps-lab "
            f"reconstruct results ({', '.join(results[:_NAMED_SUBFOLDERS])}{more})"
        )


def _has_frames(folder: Path) -> bool:
    return any(_is_light_frame(p) for p in folder.iterdir())


def _looks_like_dataset(folder: Path) -> bool:
    try:
        return is_capture_run(folder) or (folder / FILENAMES).is_file() or _has_frames(folder)
    except OSError:  # an unreadable subfolder is no dataset of ours
        return False


def plan_frames(path: Path, encoding: str = "auto") -> FramePlan:
    """List the files of every frame of an image folder or capture run.

    Parameters
    ----------
    path : Path
        Dataset folder.
    encoding : {"auto", "linear", "srgb"}
        Recorded in the plan: how the frames are decoded (:func:`ps_lab.io.images.read_image`).

    Returns
    -------
    FramePlan

    Raises
    ------
    DatasetError
        Missing folder, no images, unreadable ``filenames.txt`` or ``manifest.json``, missing files;
        a reconstruct result or a folder of datasets (:func:`check_dataset_folder`).

    """
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"{root}: no such dataset folder")
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder (a dataset is a folder of images)")
    if encoding not in ENCODINGS:
        raise DatasetError(
            f"unknown encoding {encoding!r} (choose one of {', '.join(ENCODINGS)})"
        )
    check_dataset_folder(root)
    plan = _plan_run(root) if is_capture_run(root) else _plan_image_folder(root)
    camera_file = root / CAMERA_FILE
    camera = read_camera_file(camera_file) if camera_file.is_file() else None
    return replace(plan, encoding=encoding, camera=camera)


def is_mask_name(name: str) -> bool:
    """``mask.png`` or ``<name>.mask.png`` (case-insensitive)."""
    low = name.lower()
    return low == MASK_NAME or low.endswith(_MASK_SUFFIX)


def find_mask(root: Path) -> Path | None:
    """The mask of an image folder: ``mask.png``, else the one ``<name>.mask.png``, else None.

    Raises
    ------
    DatasetError
        Several ``*.mask.png`` and no ``mask.png``.
    """
    plain = root / MASK_NAME
    if plain.exists() or plain.is_symlink():
        return plain
    if not root.is_dir():
        return None
    named = sorted(p for p in root.iterdir() if p.name.lower().endswith(_MASK_SUFFIX))
    if len(named) > 1:
        raise DatasetError(
            f"{root}: more than one mask ({', '.join(p.name for p in named)}); keep one"
        )
    return named[0] if named else None


def reference_frame(root: Path) -> Path | None:
    """An image folder's room-light frame of the sphere outline (``ref.<ext>``, ...), or None."""
    if not root.is_dir():
        return None
    found = sorted(
        p for p in root.iterdir() if p.stem.lower() in REFERENCE_STEMS and is_supported(p)
    )
    return found[0] if found else None


def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _is_light_frame(path: Path) -> bool:
    name = path.name
    return (
        path.is_file()
        and is_supported(path)
        and not name.startswith(".")
        and name.lower() not in _NOT_FRAMES
        and not is_mask_name(name)
        and not _GT_NAME.match(name)
        and path.stem.lower() not in _AMBIENT_STEMS
        and path.stem.lower() not in REFERENCE_STEMS
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
                    "ground truth, dark, ambient or reference frame)"
                )
            files.append(file)
    elif not (root / _LIGHT_DIRECTIONS).exists() and (lp := find_lp(root)) is not None:
        # The images of an .lp file, in its order, wherever it says they are (RelightLab).
        names, _, lines = read_lp_rows(lp)
        files = lp_image_files(lp, names, is_supported, lines)
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
    darks = [
        p for p in sorted(root.iterdir()) if p.stem.lower() in _AMBIENT_STEMS and is_supported(p)
    ]
    if len(darks) > 1:
        raise DatasetError(
            f"{root}: more than one dark/ambient frame ({', '.join(p.name for p in darks)})"
        )
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
