"""Camera calibration: intrinsics and lens distortion from photographs of a board.

Zhang's method as OpenCV implements it (``cv2.calibrateCamera``: the pinhole matrix and the
5-coefficient radial-tangential model of :mod:`ps_lab.io.camera`, Levenberg-Marquardt on the
reprojection error). Corners come from a ChArUco board (``cv2.aruco.CharucoDetector``: markers
identify each corner, so a partly visible or partly cut board still counts, and the corners are
refined to sub-pixel on the image) or, as the fallback, a plain chessboard
(``cv2.findChessboardCornersSB``, else ``findChessboardCorners`` + ``cornerSubPix``).

Frames are refused, each with its reason, when the board is not found, too few corners are seen,
or (after a first calibration) their reprojection RMS is an outlier: above both
:data:`OUTLIER_FACTOR` times the median frame's and :data:`OUTLIER_FLOOR_PX` (a blurred or moved
frame, a wrong detection). The worst such frame is dropped and the calibration repeated until
none is left. The overall RMS is then OpenCV's own on the kept corners; k3 is held at 0 unless
fitting it lowers that RMS by more than :data:`K3_GAIN` (:func:`_calibrate`).

:func:`calibrate_camera_files` is the one owner of the flow (read, detect, calibrate, write
``camera.json`` and ``camera.png``); the rest are pure functions on arrays.

References
----------
Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ps_lab.calibration._camera_views import (
    ViewVerdict,
    judge_views,
    repeated_views,
    tilt_spread_deg,
)
from ps_lab.errors import CalibrationError, PsLabError
from ps_lab.io.camera import (
    CAMERA_FILE,
    CameraModel,
    camera_from_arrays,
    camera_json,
    camera_problem,
)
from ps_lab.io.codecs import imwrite
from ps_lab.io.files import staged_files, write_json_atomic
from ps_lab.io.images import read_image

#: A frame whose RMS is above this many times the median frame's (and the floor) is refused.
OUTLIER_FACTOR = 3.0
#: ... and above this many pixels (a good frame of a sharp board is well below).
OUTLIER_FLOOR_PX = 0.5
#: Fewest usable frames for a calibration (Zhang: 3 views fix 5 intrinsics; distortion wants more).
MIN_FRAMES = 3
#: Fewest corners a frame must show.
MIN_CORNERS = 8
#: A calibration whose RMS is above this (pixels), or above MAX_RMS_SHARE of the frame's diagonal
#: where that is more, is refused: sub-pixel corners of a flat board sit well below 1 px, and
#: an RMS of several pixels is a wrong board spec, a bent board or misdetected corners.
MAX_RMS_PX = 2.0
MAX_RMS_SHARE = 5e-4
#: A board square (and marker) side in mm: a printed board's, from a micro target to a wall.
SQUARE_RANGE_MM = (0.01, 10_000.0)
#: Most squares along a board's side.
MAX_SQUARES = 200
#: Smallest marker side as a share of the square's.
MIN_MARKER_SHARE = 0.1
CAMERA_PICTURE = "camera.png"
DEFAULT_DICTIONARY = "DICT_5X5_100"
_DICTIONARIES = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board.

    Attributes
    ----------
    kind : {"charuco", "chessboard"}
    cols, rows : int
        Squares across and down (a chessboard's inner corners are ``(cols-1) x (rows-1)``).
    square : float
        Side of a square, in the rig's unit (mm).
    marker : float or None
        Side of a ChArUco marker (same unit).
    dictionary : str
        ArUco dictionary name (``DICT_5X5_100``...).
    """

    kind: str
    cols: int
    rows: int
    square: float
    marker: float | None = None
    dictionary: str = DEFAULT_DICTIONARY

    def charuco_board(self, legacy: bool = False) -> cv2.aruco.CharucoBoard:
        """OpenCV's board (``legacy``: the pattern of OpenCV < 4.6 for even row counts)."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, dictionary)
        board.setLegacyPattern(legacy)
        return board

    def describe(self) -> str:
        """The spec as given on the command line."""
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square:g}"
        return f"charuco:{self.cols}x{self.rows}:{self.square:g}:{self.marker:g}:{self.dictionary}"


def parse_board(text: str) -> BoardSpec:
    """Parse ``charuco:COLSxROWS:SQUARE:MARKER[:DICT]`` or ``chessboard:COLSxROWS:SQUARE``.

    Raises
    ------
    CalibrationError
        A line naming ``--board`` and what is wrong.
    """
    parts = str(text).strip().split(":")
    usage = "charuco:COLSxROWS:SQUARE:MARKER[:DICT] or chessboard:COLSxROWS:SQUARE"
    kind = parts[0].lower()
    if kind not in ("charuco", "chessboard"):
        raise CalibrationError(f"--board {text}: unknown board kind {parts[0]!r} (give {usage})")
    expected = (4, 5) if kind == "charuco" else (3,)
    if len(parts) not in expected:
        raise CalibrationError(f"--board {text}: expected {usage}")
    size = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", parts[1])
    if size is None:
        raise CalibrationError(f"--board {text}: size {parts[1]!r} is not COLSxROWS (e.g. 9x6)")
    cols, rows = int(size.group(1)), int(size.group(2))
    if cols < 3 or rows < 3:
        raise CalibrationError(f"--board {text}: a board needs at least 3x3 squares")
    if kind == "chessboard" and (cols < 4 or rows < 4):  # OpenCV's detector: 3x3 inner corners
        raise CalibrationError(f"--board {text}: a chessboard needs at least 4x4 squares "
                               "(3x3 inner corners)")
    if cols > MAX_SQUARES or rows > MAX_SQUARES:
        raise CalibrationError(
            f"--board {text}: at most {MAX_SQUARES} squares a side (got {cols}x{rows})"
        )

    def length(value: str, name: str) -> float:
        try:
            number = float(value)
        except ValueError:
            raise CalibrationError(f"--board {text}: {name} {value!r} is not a number") from None
        lo, hi = SQUARE_RANGE_MM
        if not (np.isfinite(number) and number > 0):
            raise CalibrationError(f"--board {text}: {name} must be positive (a length in mm)")
        if not lo <= number <= hi:
            raise CalibrationError(
                f"--board {text}: {name} {number:g} mm is not a printed board's size "
                f"({lo:g} to {hi:g} mm)"
            )
        return number

    square = length(parts[2], "SQUARE")
    if kind == "chessboard":
        return BoardSpec("chessboard", cols, rows, square)
    marker = length(parts[3], "MARKER")
    if marker >= square:
        raise CalibrationError(f"--board {text}: MARKER must be smaller than SQUARE")
    if marker < MIN_MARKER_SHARE * square:
        raise CalibrationError(
            f"--board {text}: MARKER must be at least {MIN_MARKER_SHARE:g} x SQUARE (markers "
            "that small are not decoded)"
        )
    dictionary = DEFAULT_DICTIONARY
    if len(parts) == 5:
        name = parts[4].strip().upper()
        name = name if name.startswith("DICT_") else f"DICT_{name}"
        if name not in _DICTIONARIES:
            raise CalibrationError(
                f"--board {text}: unknown ArUco dictionary {parts[4]!r} (e.g. DICT_4X4_50, "
                "DICT_5X5_100, DICT_6X6_250, DICT_APRILTAG_36H11)"
            )
        dictionary = name
    count = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    if count < cols * rows // 2:
        raise CalibrationError(
            f"--board {text}: {dictionary} has {count} markers, a {cols}x{rows} board needs "
            f"{cols * rows // 2}"
        )
    return BoardSpec("charuco", cols, rows, square, marker, dictionary)


@dataclass(frozen=True)
class Detection:
    """One frame's corners (or why there are none).

    Attributes
    ----------
    object_points : ndarray of shape (m, 3), float32
        Corners on the board (board frame, board units).
    image_points : ndarray of shape (m, 2), float32
        Their sub-pixel image positions (column, row).
    refused : str or None
        Why the frame cannot be used, else None.
    """

    object_points: np.ndarray
    image_points: np.ndarray
    refused: str | None = None


def grey_u8(image: np.ndarray, bit_depth: int | None = None) -> np.ndarray:
    """An 8-bit grey picture for the detectors: 8-bit files as they are, others tone-mapped.

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, C), float in [0, 1] (8-bit files) or linear
    bit_depth : int or None
        8 for an 8-bit file (values are ``code / 255``), else the data is stretched to its 99.5th
        percentile with a 1/2.2 gamma (linear RAW).
    """
    grey = image if image.ndim == 2 else image.mean(axis=2)
    if bit_depth == 8:
        return np.clip(grey * 255.0 + 0.5, 0, 255).astype(np.uint8)
    top = float(np.percentile(grey, 99.5))
    scaled = np.clip(grey / top, 0.0, 1.0) if top > 0 else np.zeros_like(grey)
    return np.clip(scaled ** (1 / 2.2) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _refused(reason: str) -> Detection:
    empty = np.zeros((0, 3), np.float32)
    return Detection(empty, np.zeros((0, 2), np.float32), reason)


def _collinear(objects: np.ndarray) -> bool:
    """Whether board corners (m, 3) lie on one line (no homography, no calibration)."""
    xy = objects[:, :2].astype(np.float64)
    centred = xy - xy.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    return len(xy) < 4 or singular[-1] <= 1e-6 * max(singular[0], 1e-300)


def detect_corners(grey: np.ndarray, board: BoardSpec, legacy: bool = False) -> Detection:
    """Find the board's corners in one 8-bit grey frame.

    Parameters
    ----------
    grey : ndarray of shape (H, W), uint8
    board : BoardSpec
    legacy : bool
        ChArUco boards printed by OpenCV < 4.6 with an even number of rows.

    Returns
    -------
    Detection
    """
    if board.kind == "charuco":
        detector = cv2.aruco.CharucoDetector(board.charuco_board(legacy))
        corners, ids, _, marker_ids = detector.detectBoard(grey)
        if ids is None or len(ids) == 0:
            markers = 0 if marker_ids is None else len(marker_ids)
            return _refused(f"board not found ({markers} markers of {board.dictionary} seen)")
        if len(ids) < MIN_CORNERS:
            return _refused(f"only {len(ids)} corners seen (at least {MIN_CORNERS})")
        objects, images = board.charuco_board(legacy).matchImagePoints(corners, ids)
        objects = objects.reshape(-1, 3).astype(np.float32)
        if _collinear(objects):
            return _refused(f"the {len(ids)} corners seen lie on one line of the board (a "
                            "plane needs corners off it)")
        return Detection(objects, images.reshape(-1, 2).astype(np.float32))
    pattern = (board.cols - 1, board.rows - 1)
    found, corners = cv2.findChessboardCornersSB(grey, pattern, flags=cv2.CALIB_CB_ACCURACY)
    if not found:
        found, corners = cv2.findChessboardCorners(
            grey, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        )
        if not found:
            return _refused(f"chessboard of {pattern[0]}x{pattern[1]} inner corners not found")
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
        corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), criteria)
    grid = np.mgrid[1 : board.cols, 1 : board.rows].T.reshape(-1, 2) * board.square
    objects = np.column_stack([grid, np.zeros(len(grid))]).astype(np.float32)
    return Detection(objects, corners.reshape(-1, 2).astype(np.float32))


@dataclass(frozen=True)
class CameraCalibration:
    """The result of :func:`calibrate_from_corners`.

    Attributes
    ----------
    camera : CameraModel
        Intrinsics, distortion, image size and the overall RMS (OpenCV's, kept frames).
    frame_rms : ndarray of shape (n,)
        Reprojection RMS per frame (pixels; NaN for frames refused before calibration); refused
        outliers keep the RMS the calibration that refused them gave them.
    refused : dict of int -> str
        Frame index -> why it was not used.
    residuals : list of ndarray of shape (m_k, 2)
        Detected minus reprojected corner, per frame (empty for refused-before frames).
    rms_all_frames : float or None
        OpenCV's RMS with every detected frame (before outliers were refused).
    rms_opencv : float or None
        OpenCV's own RMS (all 5 coefficients free) on the kept frames' corners.
    k3_fitted : bool
        Whether k3 was fitted (else held at 0: :func:`_calibrate`).
    sigma : dict of str -> float
        OpenCV's standard deviations (1 sigma, pixels) of ``fx``, ``fy``, ``cx``, ``cy``
        (``calibrateCameraExtended``: from the Jacobian at the solution and the residual
        variance; meaningful only for views that determine them, :mod:`._camera_views`).
    views : ViewVerdict or None
        Distinct views, tilt spread and the warning, if any (:func:`judge_views`).
    """

    camera: CameraModel
    frame_rms: np.ndarray
    refused: dict[int, str]
    residuals: list[np.ndarray] = field(default_factory=list)
    rms_all_frames: float | None = None
    rms_opencv: float | None = None
    k3_fitted: bool = True
    sigma: dict[str, float] = field(default_factory=dict)
    views: ViewVerdict | None = None

    @property
    def warning(self) -> str | None:
        """Why the views make a weak calibration (one line), else None."""
        return None if self.views is None else self.views.warning


#: Free k3 only where it lowers the reprojection RMS by more than this share (module docstring).
K3_GAIN = 0.02


def _calibrate(objects, images, size):
    """OpenCV's calibration with k3 held at 0 unless freeing it pays.

    The sixth-order term k3 is weakly determined by boards that do not reach the frame's
    corners and then extrapolates wildly there (ROS's camera_calibration holds it at 0 by
    default for the same reason). It is fitted both ways; the free fit is kept only when its
    RMS is more than :data:`K3_GAIN` below the held one, so the RMS stays within that share of
    OpenCV's own 5-coefficient fit on the same corners (returned as ``rms_free``).
    """
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    free = cv2.calibrateCameraExtended(objects, images, size, None, None, flags=0,
                                       criteria=criteria)
    held = cv2.calibrateCameraExtended(objects, images, size, None, None,
                                       flags=cv2.CALIB_FIX_K3, criteria=criteria)
    use_free = held[0] > (1.0 + K3_GAIN) * free[0]
    rms, k, d, rvecs, tvecs, sigma = (free if use_free else held)[:6]
    residuals = []
    for obj, img, r, t in zip(objects, images, rvecs, tvecs, strict=True):
        projected, _ = cv2.projectPoints(obj, r, t, k, d)
        residuals.append(img.reshape(-1, 2).astype(np.float64) - projected.reshape(-1, 2))
    fit = _Fit(k, d, [np.asarray(r).reshape(3) for r in rvecs],
               np.asarray(sigma, np.float64).ravel()[:4])
    return float(rms), fit, residuals, float(free[0]), use_free


@dataclass(frozen=True)
class _Fit:
    """One OpenCV calibration: matrix (3, 3), coefficients, rvecs (n x (3,)), sigma (4,)."""

    matrix: np.ndarray
    distortion: np.ndarray
    rvecs: list[np.ndarray]
    sigma: np.ndarray


def calibrate_from_corners(
    detections: Sequence[Detection], image_size: tuple[int, int], names: Sequence[str] | None = None
) -> CameraCalibration:
    """Calibrate from detected corners, refusing outlier frames by their reprojection RMS.

    Parameters
    ----------
    detections : sequence of Detection
        One per frame (refused ones are skipped, their reason kept).
    image_size : (W, H)
    names : sequence of str, optional
        Frame names for messages.

    Returns
    -------
    CameraCalibration

    Raises
    ------
    CalibrationError
        Fewer than :data:`MIN_FRAMES` usable frames (before or after refusing outliers).
    """
    n = len(detections)
    names = list(names) if names is not None else [f"frame {k + 1}" for k in range(n)]
    refused = {k: d.refused for k, d in enumerate(detections) if d.refused is not None}
    for k, d in enumerate(detections):
        if k not in refused and _collinear(d.object_points):
            refused[k] = "its corners lie on one line of the board (a plane needs corners off it)"
    frame_rms = np.full(n, np.nan)
    residuals: list[np.ndarray] = [np.zeros((0, 2)) for _ in range(n)]
    rms_all = None
    while True:
        kept = [k for k in range(n) if k not in refused]
        if len(kept) < MIN_FRAMES:
            why = "; ".join(f"{names[k]}: {refused[k]}" for k in sorted(refused))
            raise CalibrationError(
                f"{len(kept)} usable board frame(s) of {n}, at least {MIN_FRAMES} needed"
                + (f" ({why})" if why else "")
            )
        try:
            rms, fit, res, rms_free, k3_free = _calibrate(
                [detections[k].object_points for k in kept],
                [detections[k].image_points for k in kept], image_size,
            )
        except cv2.error as exc:  # a configuration its initialisation cannot start from
            reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else "no reason given"
            raise CalibrationError(
                f"board frames {names[kept[0]]} ... {names[kept[-1]]}: OpenCV cannot calibrate "
                f"from these corners ({reason[:160]}): {len(kept)} frames, "
                f"{sum(len(detections[k].image_points) for k in kept)} corners"
            ) from None
        if rms_all is None:
            rms_all = rms
        per_frame = np.array([np.sqrt(np.mean(np.sum(r * r, axis=1))) for r in res])
        for k, value, r in zip(kept, per_frame, res, strict=True):
            frame_rms[k], residuals[k] = value, r
        median = float(np.median(per_frame))
        limit = max(OUTLIER_FACTOR * median, OUTLIER_FLOOR_PX)
        worst = int(np.argmax(per_frame))
        if per_frame[worst] <= limit:
            break
        refused[kept[worst]] = (
            f"reprojection RMS {per_frame[worst]:.3f} px is an outlier (median frame "
            f"{median:.3f} px, limit {limit:.3f} px)"
        )
    camera = camera_from_arrays(fit.matrix, fit.distortion, image_size, rms)
    span = f"{names[kept[0]]} ... {names[kept[-1]]}"
    limit = max(MAX_RMS_PX, MAX_RMS_SHARE * float(np.hypot(*image_size)))
    if not np.isfinite(rms) or rms > limit:
        raise CalibrationError(
            f"board frames {span}: reprojection RMS {rms:.4g} px is implausible for a lens "
            f"(at most {limit:.3g} px): check --board (kind, squares, square and marker size) "
            "and that the board is flat and sharp in the frames"
        )
    verdict = judge_views(
        [names[k] for k in kept],
        repeated_views([detections[k].object_points for k in kept],
                       [detections[k].image_points for k in kept], image_size),
        tilt_spread_deg(fit.rvecs), (camera.fx, camera.fy), fit.sigma, image_size,
    )
    if verdict.refused is not None:
        raise CalibrationError(f"board frames {span}: {verdict.refused}")
    problem = camera_problem(camera)
    if problem is not None:
        raise CalibrationError(f"board frames {span}: the calibration found no usable lens "
                               f"model ({problem})")
    sigma = {name: float(v) for name, v in zip(("fx", "fy", "cx", "cy"), fit.sigma, strict=True)}
    return CameraCalibration(camera, frame_rms, refused, residuals, rms_all, rms_free, k3_free,
                             sigma, verdict)


def _read_frame(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(8-bit grey for detection, picture background) of one board photo."""
    try:
        image = read_image(path, "linear")
    except PsLabError as exc:
        message = str(exc)
        raise CalibrationError(message if str(path) in message else f"{path}: {message}") from None
    return grey_u8(image.data, image.bit_depth), image.data


def calibrate_camera_files(
    frames: Sequence[Path],
    board: BoardSpec,
    out: Path,
    *,
    progress: Callable[[int], None] | None = None,
) -> tuple[CameraCalibration, dict[str, Path]]:
    """``ps-lab calibrate-camera``: detect, calibrate, write ``camera.json`` and ``camera.png``.

    Parameters
    ----------
    frames : sequence of Path
        Photos of the board (any format :func:`ps_lab.io.images.read_image` reads), same size.
    board : BoardSpec
    out : Path
        Output folder (created; the two files appear together when complete).
    progress : callable, optional
        Called with 1 after each frame's detection.

    Returns
    -------
    (CameraCalibration, dict of file name -> path)

    Raises
    ------
    CalibrationError
        Unreadable frame, frames of different sizes, too few usable frames; the line names the
        file or the option.
    """
    if not frames:
        raise CalibrationError("no board frames given (FRAMES...)")
    out = Path(out)
    _check_out(out)  # before the work
    paths = [Path(f) for f in frames]
    for path in paths:
        if not path.is_file():
            raise CalibrationError(f"{path}: no such board frame")
    greys, detections, size = [], [], None
    legacy = decided = False
    for k, path in enumerate(paths):
        grey, _ = _read_frame(path)
        if size is None:
            size = (grey.shape[1], grey.shape[0])
        elif (grey.shape[1], grey.shape[0]) != size:
            raise CalibrationError(
                f"{path}: frame is {grey.shape[1]}x{grey.shape[0]}, {paths[0].name} is "
                f"{size[0]}x{size[1]} (one camera, one image size)"
            )
        detection = detect_corners(grey, board, legacy)
        if board.kind == "charuco" and board.rows % 2 == 0 and not decided:
            # OpenCV 4.6 changed the pattern of boards with an even number of rows: a board
            # printed before reads with the legacy pattern. The first frame that shows the
            # board decides for all.
            other = detect_corners(grey, board, True)
            if len(other.image_points) > len(detection.image_points):
                legacy, detection = True, other
            decided = len(detection.image_points) > 0
        greys.append(grey)
        detections.append(detection)
        if progress is not None:
            progress(1)
    assert size is not None
    result = calibrate_from_corners(detections, size, [p.name for p in paths])
    kept = [k for k in range(len(paths)) if k not in result.refused]
    extra = {
        "board": board.describe() + (" (legacy pattern)" if legacy else ""),
        "frames": [
            {
                "file": str(path),
                "corners": int(len(d.image_points)),
                "rms_px": None if not np.isfinite(result.frame_rms[k]) else result.frame_rms[k],
                "used": k not in result.refused,
                **({"refused": result.refused[k]} if k in result.refused else {}),
            }
            for k, (path, d) in enumerate(zip(paths, detections, strict=True))
        ],
        "rms_all_detected_frames_px": result.rms_all_frames,
        "rms_opencv_5_coefficients_px": result.rms_opencv,
        "k3": "fitted" if result.k3_fitted else "held at 0 (freeing it lowered the RMS by "
        f"less than {100 * K3_GAIN:g} %)",
        "rms_method": "cv2.calibrateCamera on the kept frames' sub-pixel corners",
        "uncertainty_px": {
            **result.sigma,
            "meaning": "1-sigma standard deviations of fx, fy, cx, cy from "
            "cv2.calibrateCameraExtended (Jacobian at the solution, residual variance)",
        },
        "views": {
            "distinct": result.views.distinct_views if result.views else None,
            "tilt_spread_deg": result.views.tilt_spread_deg if result.views else None,
            "repeats": {paths[kept[j]].name: paths[kept[i]].name
                        for j, i in (result.views.repeats.items() if result.views else ())},
            "warning": result.warning,
        },
    }
    picture = camera_picture(greys, detections, result)
    written: dict[str, Path] = {}
    try:
        with staged_files(out, prefix=".calibrate-camera-", error=CalibrationError) as stage:
            write_json_atomic(stage / CAMERA_FILE, camera_json(result.camera, **extra))
            if not imwrite(stage / CAMERA_PICTURE, picture):
                raise CalibrationError(f"{out / CAMERA_PICTURE}: OpenCV could not write the PNG")
    except OSError as exc:  # the staging folder's name is ours, not the user's: name ``out``
        raise CalibrationError(f"{out}: cannot write {CAMERA_FILE} and {CAMERA_PICTURE} "
                               f"({exc.strerror or type(exc).__name__}); nothing written") from None
    for name in (CAMERA_FILE, CAMERA_PICTURE):
        written[name] = out / name
    return result, written


def _check_out(out: Path) -> None:
    """Refuse an ``--out`` that cannot take ``camera.json`` (a file, a read-only folder)."""
    if out.exists() and not out.is_dir():
        raise CalibrationError(f"--out {out}: not a folder")
    folder = out
    while not folder.exists():
        if folder.is_symlink():
            raise CalibrationError(f"--out {out}: {folder} is a broken link")
        if folder.parent == folder:
            break
        folder = folder.parent
    if not folder.is_dir():
        raise CalibrationError(f"--out {out}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CalibrationError(f"--out {out}: {folder} is not writable (read-only or no "
                               "permission)")


def camera_picture(
    greys: Sequence[np.ndarray],
    detections: Sequence[Detection],
    result: CameraCalibration,
    *,
    tile_width: int = 480,
    magnify: float | None = None,
) -> np.ndarray:
    """A contact sheet: each frame with its corners (green), residuals (red, magnified), refusals.

    Residual vectors are drawn ``magnify`` times longer (default: so that the 95th percentile
    residual is 15 px on the tile); the factor is printed on every tile.

    Returns
    -------
    ndarray of shape (rows * th, cols * tile_width, 3), uint8 (BGR)
    """
    all_res = np.concatenate([r for r in result.residuals if len(r)] or [np.zeros((1, 2))])
    h, w = greys[0].shape
    scale = tile_width / w
    th = int(round(h * scale))
    if magnify is None:
        p95 = float(np.percentile(np.linalg.norm(all_res, axis=1), 95)) or 1.0
        magnify = max(1.0, 15.0 / (p95 * scale))
    n = len(greys)
    cols = min(4, n)
    rows = (n + cols - 1) // cols
    sheet = np.full((rows * th, cols * tile_width, 3), 40, np.uint8)
    for k, (grey, det) in enumerate(zip(greys, detections, strict=True)):
        tile = cv2.cvtColor(cv2.resize(grey, (tile_width, th), interpolation=cv2.INTER_AREA),
                            cv2.COLOR_GRAY2BGR)
        tile = (tile * 0.6).astype(np.uint8)
        res = result.residuals[k]
        for j, p in enumerate(det.image_points):
            q = (float(p[0] * scale), float(p[1] * scale))
            cv2.circle(tile, (int(round(q[0])), int(round(q[1]))), 2, (0, 220, 0), -1)
            if j < len(res):
                end = (q[0] - res[j, 0] * magnify * scale, q[1] - res[j, 1] * magnify * scale)
                cv2.line(tile, (int(round(q[0])), int(round(q[1]))),
                         (int(round(end[0])), int(round(end[1]))), (0, 0, 255), 1, cv2.LINE_AA)
        rms = result.frame_rms[k]
        label = f"{k + 1}: " + (f"{rms:.3f} px" if np.isfinite(rms) else "no corners")
        colour = (255, 255, 255)
        if k in result.refused:
            label += " REFUSED"
            colour = (0, 0, 255)
            cv2.rectangle(tile, (0, 0), (tile_width - 1, th - 1), (0, 0, 255), 3)
        cv2.putText(tile, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
        cv2.putText(tile, f"residuals x{magnify:.0f}", (6, th - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 255), 1, cv2.LINE_AA)
        r, c = divmod(k, cols)
        sheet[r * th:(r + 1) * th, c * tile_width:(c + 1) * tile_width] = tile
    return sheet
