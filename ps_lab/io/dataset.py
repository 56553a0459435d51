"""Dataset loading: the input contract of ``ps-lab calibrate`` and ``ps-lab reconstruct``.

Two kinds of folder are datasets:

- an **image folder** (DiLiGenT layout): one image per light, ordered by ``filenames.txt`` when
  present, else by file name (numbers compared numerically); ``light_directions.txt``; optional
  ``light_intensities.txt``, ``mask.png``, ``normal_gt.npy`` or ``Normal_gt.mat``, ``dark.<ext>``;
- a **capture run** written by ``ps-lab capture`` (a folder with ``manifest.json``): frames come
  from the manifest, repeats are averaged, the dark frame is subtracted, exposures are equalised,
  and the lights come from ``light_directions.txt`` / ``light_intensities.txt`` written by
  ``ps-lab calibrate``.

:func:`load_frames` returns the linear frames (what calibration reads); :func:`load_dataset` adds
the lights, mask and ground truth and reduces colour to one observation per light and pixel (what
the solvers read). Every problem raises :class:`~ps_lab.errors.DatasetError` with one line naming
the file.

For captures too large for memory, :func:`open_dataset` checks a folder without reading pixels,
:mod:`ps_lab.io.bands` cuts it into row bands and stages its observations band by band; light
tables are read and written by :mod:`ps_lab.io.light_files`; the run format is :mod:`ps_lab.io.run`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.camera import CameraModel, undistort_frame
from ps_lab.io.coding import combine
from ps_lab.io.frames import (
    FramePlan,
    check_dataset_folder,
    find_mask,
    is_capture_run,
    plan_frames,
)
from ps_lab.io.images import (
    RAW_SUFFIXES,
    Image,
    check_is_file,
    decode_image,
    read_image,
    read_image_size,
    read_png_bytes,
)
from ps_lab.io.light_files import (
    find_lp,
    lp_directions_for,
    read_camera,
    read_light_anisotropy,
    read_light_directions,
    read_light_intensities,
    read_light_positions,
    read_object_outline,
)
from ps_lab.io.run import SIMULATION_DIR
from ps_lab.io.truth import _find_normal_gt

log = logging.getLogger("ps_lab.io.dataset")

CHANNELS = ("r", "g", "b", "mean")
FILENAMES = "filenames.txt"
LIGHT_DIRECTIONS = "light_directions.txt"
LIGHT_INTENSITIES = "light_intensities.txt"
LIGHT_POSITIONS = "light_positions.txt"
LIGHT_ANISOTROPY = "light_anisotropy.txt"
OBJECT_OUTLINE = "object_outline.txt"
CAMERA = "camera.txt"
MASK = "mask.png"

@dataclass(frozen=True)
class Frames:
    """Linear frames, one per light: dark-subtracted, exposure-normalised, repeats averaged.

    Attributes
    ----------
    images : ndarray of shape (n, H, W, C), float32
        C = 1 (grey) or 3 (RGB).
    saturated : ndarray of shape (n, H, W), bool
        True where any repeat of the frame clipped in any channel.
    names : list of str
        File name per frame (the first repeat's), in light order.
    root : Path
        The dataset folder.
    manifest : dict or None
        The parsed ``manifest.json`` of a capture run, else None.
    camera : CameraModel or None
        The dataset's ``camera.json``: the frames were undistorted with it.

    """

    images: np.ndarray
    saturated: np.ndarray
    names: list[str]
    root: Path
    manifest: dict | None
    camera: CameraModel | None = None


@dataclass(frozen=True)
class Dataset:
    """Observations and lights ready for the solvers.

    Attributes
    ----------
    images : ndarray of shape (n, H, W), float32
        Each channel divided by the light's intensity for that channel, then channels combined.
    valid : ndarray of shape (n, H, W), bool
        False where saturated, or at or below the shadow threshold when one was given.
    light_directions : ndarray of shape (n, 3), float64
        Unit vectors from the surface toward each light (x right, y up, z toward the camera).
    light_intensities : ndarray of shape (n, 3), float64
        Per-channel intensity of each light (ones when the folder has no intensities file).
    mask : ndarray of shape (H, W), bool
        Object pixels (all pixels when the folder has no mask).
    normal_gt : ndarray of shape (H, W, 3), float64, or None
        Ground-truth normals when the folder has them.
    names : list of str
        Frame file name per light.
    root : Path
        The dataset folder.

    """

    images: np.ndarray
    valid: np.ndarray
    light_directions: np.ndarray
    light_intensities: np.ndarray
    mask: np.ndarray
    normal_gt: np.ndarray | None
    names: list[str]
    root: Path


def load_frames(path: Path, encoding: str = "auto") -> Frames:
    """Load the linear frames of an image folder or capture run.

    Repeats of a light are averaged, a dark frame (manifest ``kind: dark``, or ``dark.<ext>`` in an
    image folder) is subtracted after scaling it by the exposure ratio, and every frame is scaled to
    the exposure of the first light frame when the exposures are known. When the folder has a
    ``camera.json`` (:mod:`ps_lab.io.camera`) the frames are undistorted; masks, circles and
    ground truth are then in undistorted pixels.

    Parameters
    ----------
    path : Path
        Dataset folder.
    encoding : {"auto", "linear", "srgb"}
        How integer pixel values map to light (:mod:`ps_lab.io.encoding`).

    Returns
    -------
    Frames
        ``images`` of shape (n, H, W, C) float32, ``saturated`` of shape (n, H, W).

    """
    plan = plan_frames(path, encoding)
    images: np.ndarray | None = None
    saturated: np.ndarray | None = None
    n = len(plan.light_files)
    for i, (frame, clipped) in enumerate(iter_frames(plan)):
        if images is None:
            images = np.empty((n, *frame.shape), dtype=np.float32)
            saturated = np.empty((n, *frame.shape[:2]), dtype=bool)
        images[i] = frame
        saturated[i] = clipped
    assert images is not None and saturated is not None
    return Frames(
        images=images, saturated=saturated, names=plan.names, root=plan.root,
        manifest=plan.manifest, camera=plan.camera,
    )


def iter_frames(
    plan: FramePlan,
    lights: Sequence[int] | None = None,
    *,
    common_exposure: float | None | str = "first light",
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield each light's frame in light order, one at a time (bounded memory).

    Parameters
    ----------
    plan : FramePlan
        The dataset's frame files.
    lights : sequence of int or None
        Indices of the lights to read (default: all, in order).
    common_exposure : float or None or "first light"
        The exposure frames are scaled to; by default :func:`reference_exposure` (the first
        light's). A process reading some of the lights passes the value found once for all.

    Yields
    ------
    image : ndarray of shape (H, W, C), float32
        Repeats averaged, dark frame subtracted, scaled to the first light frame's exposure.
    saturated : ndarray of shape (H, W), bool
        Saturated in any repeat.

    """
    reference: Image | None = None
    reference_path: Path | None = None
    darks = set(plan.dark_files)

    def read_checked(file: Path) -> Image:
        nonlocal reference, reference_path
        image = read_image(file, plan.encoding)
        if reference is None:
            reference, reference_path = image, file
        elif reference_path in darks and file not in darks:
            # The dark frame is read first; when the first light frame disagrees with it, the
            # dark frame is the odd one. Light frames are compared with this one from here on.
            _check_same_geometry(reference, reference_path, image, file)
            reference, reference_path = image, file
        else:
            _check_same_geometry(image, file, reference, reference_path)
        return image

    dark, dark_exposure = None, None
    if plan.dark_files:
        dark, dark_exposure = _average_dark(plan, read_checked)
    if common_exposure == "first light":
        common_exposure = reference_exposure(plan, read_checked)
    for i in range(len(plan.light_files)) if lights is None else lights:
        yield read_light_frame(plan, i, common_exposure, dark, dark_exposure, read_checked)


def reference_exposure(plan: FramePlan, read: Callable[[Path], Image] = read_image) -> float | None:
    """The exposure every frame is scaled to: the first known exposure among light 1's repeats.

    A frame's exposure is the manifest's, else the file's own (RAW metadata, so only RAW files are
    read here); None when no exposure is known (frames are then not scaled).
    """
    for file, exposure in zip(plan.light_files[0], plan.light_exposures[0], strict=True):
        if exposure is None and file.suffix.lower() in RAW_SUFFIXES:
            exposure = read(file).exposure_s
        if exposure is not None:
            return exposure
    return None


def read_light_frame(
    plan: FramePlan,
    light: int,
    common_exposure: float | None,
    dark: np.ndarray | None,
    dark_exposure: float | None,
    read: Callable[[Path], Image] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One light's frame: repeats averaged, dark frame subtracted, scaled to ``common_exposure``.

    What :func:`iter_frames` yields for that light, bit for bit, so that the frames of a capture
    can be read in any order and by several processes (``ps-lab reconstruct --scheduler``).

    Parameters
    ----------
    plan : FramePlan
        The dataset's frame files.
    light : int
        Index of the light (0-based, light order).
    common_exposure : float or None
        From :func:`reference_exposure`.
    dark : ndarray of shape (H, W, C), float32, or None
        The averaged dark frame (:func:`_average_dark`).
    dark_exposure : float or None
        Its exposure.
    read : callable
        ``read(path) -> Image`` (:func:`ps_lab.io.images.read_image`, or one that also checks the
        geometry).

    Returns
    -------
    image : ndarray of shape (H, W, C), float32
    saturated : ndarray of shape (H, W), bool
        Saturated in any repeat.

    """
    if read is None:
        read = lambda file: read_image(file, plan.encoding)  # noqa: E731
    total: np.ndarray | None = None
    clipped: np.ndarray | None = None
    files = plan.light_files[light]
    for file, exposure in zip(files, plan.light_exposures[light], strict=True):
        image = read(file)
        exposure = exposure if exposure is not None else image.exposure_s
        data = image.data
        if dark is not None:
            data = data - dark * np.float32(_ratio(exposure, dark_exposure))
        gain = _ratio(common_exposure, exposure)
        if gain != 1.0:
            data = data * np.float32(gain)
        total = data if total is None else total + data
        clipped = image.saturated if clipped is None else clipped | image.saturated
    assert total is not None and clipped is not None
    if len(files) > 1:
        total = total / np.float32(len(files))
    if plan.camera is not None:  # after the dark frame: both were recorded through the lens
        undistorted, spread = undistort_frame(plan.camera, total, clipped)
        assert spread is not None
        total, clipped = undistorted, spread
    return total, clipped


def load_dataset(
    path: Path,
    *,
    channel: str = "mean",
    shadow_threshold: float | None = None,
    encoding: str = "auto",
) -> Dataset:
    """Load a dataset folder into observations, lights, mask and ground truth.

    Colour rule: each channel is divided by the light's intensity for that channel, then the
    channels are combined: ``channel="mean"`` averages them, ``"r"``/``"g"``/``"b"`` keeps one. A
    grey image is divided by the selected channel's intensity (the mean of the three for
    ``"mean"``).

    Parameters
    ----------
    path : Path
        Image folder or capture run.
    channel : {"mean", "r", "g", "b"}
        How colour is reduced to one observation per light and pixel.
    shadow_threshold : float or None
        Observations at or below this value (after the intensity division) are marked invalid.
    encoding : {"auto", "linear", "srgb"}
        How the frames are decoded (:mod:`ps_lab.io.encoding`).

    Returns
    -------
    Dataset
        ``images`` of shape (n, H, W) float32, ``valid`` of shape (n, H, W), lights (n, 3).

    Raises
    ------
    DatasetError
        Any problem with the folder, with one line naming the file and the problem.

    """
    header = open_dataset(path, channel=channel, read_size=False, encoding=encoding)
    mask = None if header.mask_file is None else read_mask(header.mask_file)
    n = len(header.names)
    images: np.ndarray | None = None
    valid: np.ndarray | None = None
    for i, (frame, clipped) in enumerate(iter_frames(header.plan)):
        if images is None:
            images = np.empty((n, *frame.shape[:2]), dtype=np.float32)
            valid = np.empty((n, *frame.shape[:2]), dtype=bool)
        images[i], valid[i] = observe(
            frame, clipped, header.light_intensities[i], channel, shadow_threshold
        )
    assert images is not None and valid is not None
    height, width = images.shape[1:]
    if mask is None:
        mask = np.ones((height, width), dtype=bool)
    elif mask.shape != (height, width):
        raise DatasetError(
            f"{header.mask_file}: mask size {mask.shape[1]}x{mask.shape[0]} differs from the "
            f"image size {width}x{height}"
        )
    normal_gt = _find_normal_gt(header.root, (height, width))
    return Dataset(
        images=images,
        valid=valid,
        light_directions=header.light_directions,
        light_intensities=header.light_intensities,
        mask=mask,
        normal_gt=normal_gt,
        names=header.names,
        root=header.root,
    )


def observe(
    frame: np.ndarray,
    saturated: np.ndarray,
    intensity: np.ndarray,
    channel: str = "mean",
    shadow_threshold: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Turn one linear frame into the solvers' observations and their validity.

    The single place where the colour rule and the validity rule are applied, shared by
    :func:`load_dataset` and the streamed loader (:func:`ps_lab.io.bands.stage_observations`).

    Parameters
    ----------
    frame : ndarray of shape (H, W, C), float32
        A frame from :func:`iter_frames`.
    saturated : ndarray of shape (H, W), bool
    intensity : ndarray of shape (3,)
        The light's RGB intensity.
    channel : {"mean", "r", "g", "b"}
    shadow_threshold : float or None

    Returns
    -------
    observations : ndarray of shape (H, W), float32
    valid : ndarray of shape (H, W), bool
        Not saturated, and above the shadow threshold when one is given.

    """
    observations = combine(frame, intensity, channel)
    valid = np.logical_not(saturated)
    if shadow_threshold is not None:
        valid &= observations > np.float32(shadow_threshold)
    return observations, valid


@dataclass(frozen=True)
class DatasetHeader:
    """Everything about a dataset except its pixels (cheap to obtain, checked up front).

    Attributes
    ----------
    root : Path
    plan : FramePlan
    light_directions : ndarray of shape (n, 3), float64
    light_intensities : ndarray of shape (n, 3), float64
    mask_file : Path or None
    names : list of str
    shape : (H, W) or None
        Image size read from the first light frame's header (None when not asked for).
    light_positions : ndarray of shape (n, 3) or None
        LED positions from ``light_positions.txt`` (two-sphere calibration), else None.
    light_anisotropy : ndarray of shape (n,) or None
        The LEDs' ``cos^mu`` exponents from ``light_anisotropy.txt``, else None.
    object_outline : float or None
        Height of the object's outline above the spheres' plane (pixels) from
        ``object_outline.txt`` (near lights), else None.
    camera : (f, cx, cy) or None
        The perspective camera of a near-light calibration from ``camera.txt`` (pixels), else
        None (orthographic).

    """

    root: Path
    plan: FramePlan
    light_directions: np.ndarray
    light_intensities: np.ndarray
    mask_file: Path | None
    names: list[str]
    shape: tuple[int, int] | None
    light_positions: np.ndarray | None = None
    light_anisotropy: np.ndarray | None = None
    object_outline: float | None = None
    camera: tuple[float, float, float] | None = None

    def read_mask(self) -> np.ndarray:
        """The object mask of shape (H, W), bool (all pixels when there is no mask file)."""
        assert self.shape is not None
        if self.mask_file is None:
            return np.ones(self.shape, dtype=bool)
        return read_mask(self.mask_file, self.shape)


def open_dataset(
    path: Path, *, channel: str = "mean", read_size: bool = True, encoding: str = "auto"
) -> DatasetHeader:
    """Check a dataset folder and read everything but its pixels.

    Parameters
    ----------
    path : Path
        Image folder or capture run.
    channel : {"mean", "r", "g", "b"}
        Checked here so that a bad choice fails before any pixel is read.
    read_size : bool
        Read the image size from the first light frame (its header when the format allows).
    encoding : {"auto", "linear", "srgb"}
        How the frames are decoded (:mod:`ps_lab.io.encoding`).

    Returns
    -------
    DatasetHeader

    Raises
    ------
    DatasetError
        Any problem with the folder, the light files, the channel or the first frame's header.

    """
    if channel not in CHANNELS:
        raise DatasetError(f"unknown channel {channel!r} (choose one of {', '.join(CHANNELS)})")
    root = Path(path)
    check_dataset_folder(root)  # a result or a folder of datasets: said before "no lights"
    run = is_capture_run(root) if root.is_dir() else False
    # Lights are checked before pixels are read: a missing file should not cost a long load.
    directions_file = root / LIGHT_DIRECTIONS
    if directions_file.exists() or directions_file.is_symlink():
        check_is_file(directions_file, "light directions file")
    lp_file = find_lp(root) if root.is_dir() and not directions_file.is_file() else None
    if root.is_dir() and not directions_file.is_file() and lp_file is None:
        if run:
            raise DatasetError(f"run {root} is not calibrated: run `ps-lab calibrate {root}` first")
        raise DatasetError(
            f"{root}: no {LIGHT_DIRECTIONS} (one row 'x y z' per image) and no .lp light file"
        )
    plan = plan_frames(root, encoding)
    n = len(plan.light_files)
    if directions_file.is_file():
        light_directions = read_light_directions(directions_file, n)
    else:  # a RelightLab / RTIBuilder light file, matched to the images by file name
        light_directions = lp_directions_for(lp_file, [files[0] for files in plan.light_files])
    intensities_file = root / LIGHT_INTENSITIES
    if intensities_file.exists() or intensities_file.is_symlink():
        light_intensities = read_light_intensities(intensities_file, n)
    else:
        light_intensities = np.ones((n, 3))
    positions_file, anisotropy_file = root / LIGHT_POSITIONS, root / LIGHT_ANISOTROPY
    shape = _common_image_size(plan) if read_size else None
    mask_file = find_mask(root)
    if mask_file is not None:
        check_is_file(mask_file, "mask")
    return DatasetHeader(
        root=root,
        plan=plan,
        light_directions=light_directions,
        light_intensities=light_intensities,
        mask_file=mask_file if mask_file is not None else _find_file(root, MASK),
        names=plan.names,
        shape=shape,
        light_positions=read_light_positions(positions_file, n)
        if positions_file.is_file()
        else None,
        light_anisotropy=read_light_anisotropy(anisotropy_file, n)
        if anisotropy_file.is_file()
        else None,
        object_outline=read_object_outline(root / OBJECT_OUTLINE)
        if (root / OBJECT_OUTLINE).is_file()
        else None,
        camera=read_camera(root / CAMERA) if (root / CAMERA).is_file() else None,
    )


_HEADER_SUFFIXES = (".png", ".npy", ".tif", ".tiff")


def _common_image_size(plan: FramePlan) -> tuple[int, int]:
    """The image size ``(H, W)`` of the dataset, naming the frame that disagrees.

    Sizes come from the headers of every light and dark frame whose format has a cheap header
    (PNG, ``.npy``, TIFF); other formats are sized by their first frame. The size most light
    frames share is the dataset's, so a first image of the wrong size (or with a forged header)
    is the one named, not a correct mask, and a dark frame is named as the dark frame.
    """
    first = plan.light_files[0][0]
    lights = [
        f for files in plan.light_files for f in files if f.suffix.lower() in _HEADER_SUFFIXES
    ]
    if not lights:
        return read_image_size(first)
    sizes = {file: read_image_size(file) for file in lights}
    counts: dict[tuple[int, int], int] = {}
    for size in sizes.values():
        counts[size] = counts.get(size, 0) + 1
    common = max(counts, key=lambda size: (counts[size], size == sizes.get(first)))
    for file, size in sizes.items():
        if size != common:
            raise DatasetError(
                f"{file}: image size {size[1]}x{size[0]} differs from the other light frames "
                f"({common[1]}x{common[0]})"
            )
    for file in plan.dark_files:
        if file.suffix.lower() in _HEADER_SUFFIXES:
            size = read_image_size(file)
            if size != common:
                raise DatasetError(
                    f"{file}: dark frame size {size[1]}x{size[0]} differs from the light frames "
                    f"({common[1]}x{common[0]})"
                )
    return common


def _ratio(numerator: float | None, denominator: float | None) -> float:
    if numerator is None or denominator is None:
        return 1.0
    return numerator / denominator


def _average_dark(plan: FramePlan, read) -> tuple[np.ndarray, float | None]:
    total = None
    reference_exposure: float | None = None
    for file, exposure in zip(plan.dark_files, plan.dark_exposures, strict=True):
        image = read(file)
        exposure = exposure if exposure is not None else image.exposure_s
        if reference_exposure is None:
            reference_exposure = exposure
        data = image.data * np.float32(_ratio(reference_exposure, exposure))
        total = data if total is None else total + data
    return total / np.float32(len(plan.dark_files)), reference_exposure


def _check_same_geometry(image: Image, file: Path, reference: Image, reference_path: Path) -> None:
    if image.data.shape[:2] != reference.data.shape[:2]:
        h, w = image.data.shape[:2]
        rh, rw = reference.data.shape[:2]
        raise DatasetError(
            f"{file}: image size {w}x{h} differs from {reference_path.name} ({rw}x{rh})"
        )
    if image.data.shape[2] != reference.data.shape[2]:
        kinds = {1: "grey", 3: "colour"}
        raise DatasetError(
            f"{file}: {kinds[image.data.shape[2]]} image among "
            f"{kinds[reference.data.shape[2]]} images (first: {reference_path.name})"
        )
    if (
        image.bit_depth is not None
        and reference.bit_depth is not None
        and image.bit_depth != reference.bit_depth
    ):
        raise DatasetError(
            f"{file}: {image.bit_depth}-bit image among {reference.bit_depth}-bit images "
            f"(first: {reference_path.name}); a mix means a file from another capture"
        )


def read_mask(path: Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a mask image: any non-zero value marks an object pixel.

    Parameters
    ----------
    path : Path
        ``mask.png`` (grey or colour).
    shape : (H, W) or None
        Expected image size.

    Returns
    -------
    ndarray of shape (H, W), bool

    """
    check_is_file(path, "mask")
    if path.suffix.lower() == ".png":
        raw = read_png_bytes(path)
    else:
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None
    array, _ = decode_image(raw)
    if array is None:
        raise DatasetError(f"{path}: corrupt or unreadable mask image")
    mask = array != 0 if array.ndim == 2 else np.any(array[:, :, :3] != 0, axis=2)
    if shape is not None and mask.shape != tuple(shape):
        raise DatasetError(
            f"{path}: mask size {mask.shape[1]}x{mask.shape[0]} differs from the image size "
            f"{shape[1]}x{shape[0]}"
        )
    if not mask.any():
        raise DatasetError(f"{path}: mask is empty (no non-zero pixel)")
    return mask


def _find_file(root: Path, name: str) -> Path | None:
    """``root/name``, else ``root/simulation/name`` (simulator ground truth), else None."""
    for candidate in (root / name, root / SIMULATION_DIR / name):
        if candidate.is_file():
            return candidate
    return None
