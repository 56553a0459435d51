"""The camera file (``camera.json``): intrinsics, lens distortion, frames undistorted by them.

``ps-lab calibrate-camera`` writes it; a rig file names it (``[lens] camera``) and ``ps-lab
capture`` copies it next to every run's manifest; ``ps-lab calibrate``, ``reconstruct`` and
``integrate`` read it from a dataset folder. It lives here, below the stages, so that they read it
without importing :mod:`ps_lab.calibration`.

Model (OpenCV's radial-tangential, "Brown-Conrady" with 5 coefficients): a point ``(X, Y, Z)`` in
the camera frame (x right, y down, z along the optical axis) has normalised coordinates
``x = X/Z, y = Y/Z``; with ``r² = x² + y²``

    x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y

and the pixel (column, row) is ``(fx x_d + cx, fy y_d + cy)``, origin at the centre of the top-left
pixel. An undistorted frame is the image the same camera matrix would form without distortion:
same size, same ``fx, fy, cx, cy`` (so the intrinsics hold for it as they are).

File layout (``"format": "ps-lab camera 1"``)::

    {"format": ..., "image_size": [W, H], "camera_matrix": [[fx,0,cx],[0,fy,cy],[0,0,1]],
     "distortion": {"k1":..,"k2":..,"p1":..,"p2":..,"k3":..}, "rms_px": .., ...}

Other keys (per-frame RMS, refused frames, the board) are kept as written and not checked.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.files import json_safe, sha256, write_json_atomic

CAMERA_FILE = "camera.json"
CAMERA_FORMAT = "ps-lab camera 1"
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class CameraModel:
    """A calibrated camera: pinhole intrinsics and 5 radial-tangential distortion coefficients.

    Attributes
    ----------
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point (column, row) in pixels, origin at the centre of the top-left pixel.
    distortion : tuple of 5 float
        ``(k1, k2, p1, p2, k3)``, OpenCV's order.
    image_size : (W, H)
        The size of the frames it was calibrated on (frames of another size are refused).
    rms_px : float or None
        Overall reprojection RMS of the calibration (pixels), when known.
    source : str
        Where it was read from (for messages and records).
    extra : dict
        The file's other keys, as written (not compared).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    image_size: tuple[int, int] = (0, 0)
    rms_px: float | None = None
    source: str = field(default="", compare=False)
    extra: dict = field(default_factory=dict, compare=False, hash=False)

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def coefficients(self) -> np.ndarray:
        """(5,) distortion coefficients ``k1, k2, p1, p2, k3``."""
        return np.array(self.distortion, dtype=np.float64)

    @property
    def focal_length(self) -> float:
        """One focal length for square-pixel models (the geometric mean of fx and fy)."""
        return float(np.sqrt(self.fx * self.fy))

    @property
    def has_distortion(self) -> bool:
        """Whether undistorting frames changes them."""
        return any(c != 0.0 for c in self.distortion)

    def record(self) -> dict[str, Any]:
        """What a run records about the camera it used (metrics.json, calibration.json)."""
        return {
            "file": self.source,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "distortion": dict(zip(DISTORTION_NAMES, self.distortion, strict=True)),
            "image_size": list(self.image_size),
            "rms_px": self.rms_px,
        }


def camera_from_arrays(
    matrix: np.ndarray,
    distortion: np.ndarray,
    image_size: tuple[int, int],
    rms_px: float | None = None,
    source: str = "",
) -> CameraModel:
    """A :class:`CameraModel` from OpenCV's arrays (3x3 matrix, 4-14 coefficients)."""
    k = np.asarray(matrix, dtype=np.float64).reshape(3, 3)
    d = np.zeros(5)
    flat = np.asarray(distortion, dtype=np.float64).ravel()[:5]
    d[: flat.size] = flat
    return CameraModel(
        fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]),
        distortion=tuple(float(v) for v in d),  # type: ignore[arg-type]
        image_size=(int(image_size[0]), int(image_size[1])),
        rms_px=None if rms_px is None else float(rms_px),
        source=source,
    )


def camera_json(camera: CameraModel, **extra: Any) -> dict[str, Any]:
    """The JSON object of ``camera.json`` (``extra``: per-frame RMS, refused frames, board...)."""
    obj: dict[str, Any] = {
        "format": CAMERA_FORMAT,
        "model": "pinhole + radial-tangential (OpenCV, 5 coefficients)",
        "image_size": list(camera.image_size),
        "camera_matrix": camera.matrix.tolist(),
        "distortion": dict(zip(DISTORTION_NAMES, camera.distortion, strict=True)),
        "distortion_coefficients": list(camera.distortion),
        "rms_px": camera.rms_px,
    }
    obj.update(camera.extra)
    obj.update(extra)
    return json_safe(obj)


def write_camera(path: Path, camera: CameraModel, **extra: Any) -> Path:
    """Write ``camera.json`` atomically; return its path."""
    write_json_atomic(Path(path), camera_json(camera, **extra))
    return Path(path)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DatasetError(f"{where}: expected a finite number, got {value!r}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond float range
        raise DatasetError(f"{where}: expected a finite number, got an integer of "
                           f"{len(str(abs(value)))} digits") from None
    if not np.isfinite(number):
        raise DatasetError(f"{where}: expected a finite number, got {value!r}")
    return number


#: Largest frame side a camera file may name (pixels).
MAX_IMAGE_SIDE = 100_000
#: Focal lengths in this range times the frame's larger side: a horizontal field of view from
#: ~0.06 deg (long telephoto, microscope) to ~157 deg (beyond that the pinhole model with 5
#: coefficients does not describe the lens).
FOCAL_RANGE = (0.1, 1000.0)
#: Largest fx / fy (or fy / fx): square pixels are 1, anamorphic lenses up to 2.
MAX_ASPECT = 2.0
#: The undistorted frame must read at least this share of its pixels inside the recorded one.
MIN_UNDISTORTED_COVERAGE = 0.5


def camera_problem(camera: CameraModel) -> str | None:
    """Why ``camera`` cannot describe a lens for its frame size, else None.

    One rule for every command that reads or writes a ``camera.json``: finite values; focal
    lengths positive and within :data:`FOCAL_RANGE` of the frame's larger side, aspect within
    :data:`MAX_ASPECT`; the principal point inside the frame; a distortion model that is
    one-to-one over the undistorted frame (its Jacobian stays positive along every ray from the
    principal point out to the frame's border, so the undistortion map
    (:func:`undistortion_maps`) is monotonic and never shows a recorded pixel twice) and whose
    undistorted frame reads at least :data:`MIN_UNDISTORTED_COVERAGE` of its pixels from inside
    the recorded frame (else nearly every undistorted pixel is black). Recorded pixels beyond
    the model's reach (a wide lens's corners under barrel distortion) are simply cropped.

    Parameters
    ----------
    camera : CameraModel

    Returns
    -------
    str or None
        The reason, worded for an error line after the file's name.
    """
    w, h = camera.image_size
    values = np.array([camera.fx, camera.fy, camera.cx, camera.cy, *camera.distortion])
    if not np.all(np.isfinite(values)):
        return "camera values must be finite numbers"
    if not (0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE):
        return f"image_size {w}x{h} is not a frame size (1 to {MAX_IMAGE_SIDE} px a side)"
    side = max(w, h)
    lo, hi = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    for name, f in (("fx", camera.fx), ("fy", camera.fy)):
        if not lo <= f <= hi:
            return (f"focal length {name} {f:g} px is implausible for {w}x{h} frames (expected "
                    f"{lo:g} to {hi:g} px, {FOCAL_RANGE[0]:g} to {FOCAL_RANGE[1]:g} x the larger "
                    "side)")
    if max(camera.fx / camera.fy, camera.fy / camera.fx) > MAX_ASPECT:
        return (f"fx {camera.fx:g} and fy {camera.fy:g} px differ by more than a factor "
                f"{MAX_ASPECT:g} (pixel aspect ratio)")
    if not (-0.5 <= camera.cx <= w - 0.5 and -0.5 <= camera.cy <= h - 0.5):
        return f"principal point ({camera.cx:g}, {camera.cy:g}) is outside the {w}x{h} image"
    if camera.has_distortion:
        return _distortion_problem(camera)
    return None


def _distortion_problem(camera: CameraModel) -> str | None:
    w, h = camera.image_size
    coefficients = camera.coefficients
    # the undistorted frame's pixels (the border densely, the inside on a grid), normalised:
    # undistortion reads each at distort(p) in the recorded frame (undistortion_maps)
    edge_u, edge_v = np.linspace(-0.5, w - 0.5, 129), np.linspace(-0.5, h - 0.5, 97)
    grid_u, grid_v = np.meshgrid(np.linspace(-0.5, w - 0.5, 33), np.linspace(-0.5, h - 0.5, 33))
    u = np.concatenate([edge_u, edge_u, np.full(97, -0.5), np.full(97, w - 0.5), grid_u.ravel()])
    v = np.concatenate([np.full(129, -0.5), np.full(129, h - 0.5), edge_v, edge_v, grid_v.ravel()])
    x, y = (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy
    with np.errstate(all="ignore"):
        t = np.linspace(0.0, 1.0, 33)[:, None]
        det = _distortion_jacobian_det(t * x, t * y, coefficients)
        xd, yd = distort_normalised(x, y, coefficients)
        pu, pv = xd * camera.fx + camera.cx, yd * camera.fy + camera.cy
        folds = not bool(np.all(np.isfinite(det) & (det > 0)))
        inside = np.isfinite(pu) & np.isfinite(pv) & (pu >= -0.5) & (pu <= w - 0.5) \
            & (pv >= -0.5) & (pv <= h - 0.5)
    if folds:
        return ("the distortion coefficients fold the lens model inside the frame (undistortion "
                "would not be one-to-one over it): not a calibration of this lens")
    share = float(np.mean(inside[-grid_u.size:]))
    if share < MIN_UNDISTORTED_COVERAGE:
        return (f"the distortion coefficients leave {100 * (1 - share):.0f} % of the undistorted "
                f"frame outside the recorded one (at most {100 * (1 - MIN_UNDISTORTED_COVERAGE):g}"
                " % for a real lens)")
    return None


def _distortion_jacobian_det(x: np.ndarray, y: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """Determinant of d(x_d, y_d) / d(x, y) of :func:`distort_normalised` (same shapes)."""
    k1, k2, p1, p2, k3 = (float(c) for c in coefficients)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    a = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
    return a * d - b * b


def read_camera_file(path: Path) -> CameraModel:
    """Read and validate a ``camera.json``.

    Raises
    ------
    DatasetError
        Unreadable file, not JSON, wrong format, a matrix that is not a camera matrix, or values
        no lens has (:func:`camera_problem`); the line names the file.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text("utf-8"))
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read camera file ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise DatasetError(f"{path}: not a JSON camera file ({exc})") from None
    except RecursionError:
        raise DatasetError(f"{path}: not a JSON camera file (nested too deeply)") from None
    if not isinstance(data, dict) or data.get("format") != CAMERA_FORMAT:
        raise DatasetError(
            f"{path}: not a ps-lab camera file (expected \"format\": \"{CAMERA_FORMAT}\"; "
            "write one with `ps-lab calibrate-camera`)"
        )
    size = data.get("image_size")
    if (
        not isinstance(size, list) or len(size) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= MAX_IMAGE_SIDE
                   for v in size)
    ):
        raise DatasetError(f"{path}: image_size must be [width, height] in pixels (1 to "
                           f"{MAX_IMAGE_SIDE}), got {_short(size)}")
    matrix = data.get("camera_matrix")
    if not (isinstance(matrix, list) and len(matrix) == 3
            and all(isinstance(r, list) and len(r) == 3 for r in matrix)):
        raise DatasetError(f"{path}: camera_matrix must be 3 rows of 3 numbers")
    k = np.array([[_number(v, f"{path}: camera_matrix") for v in row] for row in matrix])
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise DatasetError(f"{path}: camera_matrix focal lengths must be positive")
    if abs(k[0, 1]) > 1e-9 * k[0, 0] or np.any(k[1:, 0] != 0) or k[2, 1] != 0 or k[2, 2] != 1:
        raise DatasetError(f"{path}: camera_matrix must be [[fx,0,cx],[0,fy,cy],[0,0,1]]")
    dist = data.get("distortion")
    if isinstance(dist, dict):
        missing = [n for n in DISTORTION_NAMES if n not in dist]
        if missing:
            raise DatasetError(f"{path}: distortion lacks {', '.join(missing)}")
        coefficients = [_number(dist[n], f"{path}: distortion {n}") for n in DISTORTION_NAMES]
    else:
        raise DatasetError(f"{path}: distortion must be {{\"k1\", \"k2\", \"p1\", \"p2\", \"k3\"}}")
    rms = data.get("rms_px")
    if rms is not None and _number(rms, f"{path}: rms_px") < 0:
        raise DatasetError(f"{path}: rms_px must not be negative, got {rms!r}")
    known = {"format", "model", "image_size", "camera_matrix", "distortion",
             "distortion_coefficients", "rms_px"}
    camera = camera_from_arrays(
        k, np.array(coefficients), (size[0], size[1]),
        None if rms is None else _number(rms, f"{path}: rms_px"), str(path),
    )
    problem = camera_problem(camera)
    if problem is not None:
        raise DatasetError(f"{path}: {problem}")
    return CameraModel(**{**camera.__dict__, "extra": {k_: v for k_, v in data.items()
                                                        if k_ not in known}})


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def camera_record(camera: CameraModel, path: Path | None = None) -> dict[str, Any]:
    """:meth:`CameraModel.record` plus the file's sha256 and that frames were undistorted."""
    record = camera.record()
    record["undistorted"] = camera.has_distortion
    if path is not None and Path(path).is_file():
        record["sha256"] = sha256(Path(path))
    return record


def check_frame_size(camera: CameraModel, shape: tuple[int, int], what: str) -> None:
    """Refuse frames of another size than the camera was calibrated on."""
    w, h = camera.image_size
    if (shape[1], shape[0]) != (w, h):
        raise DatasetError(
            f"{camera.source or CAMERA_FILE}: calibrated for {w}x{h} frames, {what} is "
            f"{shape[1]}x{shape[0]} (calibrate the camera on frames as this dataset stores them)"
        )


def read_result_camera(path: Path, result: Path) -> CameraModel:
    """``ps-lab integrate --camera``: :func:`read_camera_file`, refused for a result of another
    frame size (:func:`check_frame_size`, the rule ``calibrate`` and ``reconstruct`` apply to
    the frames).

    The result's frame size is its ``normals.npy``'s (memory-mapped: the header only); a result
    without a readable one is left to the command's own checks.
    """
    camera = read_camera_file(path)
    normals = Path(result) / "normals.npy"
    try:
        shape = np.load(normals, mmap_mode="r", allow_pickle=False).shape
    except (OSError, ValueError, TypeError, EOFError, AttributeError):
        return camera
    if isinstance(shape, tuple) and len(shape) == 3:
        check_frame_size(camera, shape[:2], f"{normals}")
    return camera


@lru_cache(maxsize=4)
def _maps(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    w, h = camera.image_size
    map_x, map_y = cv2.initUndistortRectifyMap(
        camera.matrix, camera.coefficients, None, camera.matrix, (w, h), cv2.CV_32FC1
    )
    return map_x, map_y


def undistortion_maps(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the undistorted frame lies in the recorded one.

    Returns
    -------
    map_x, map_y : ndarray of shape (H, W), float32
        Column and row in the distorted (recorded) frame of every undistorted pixel, for
        ``cv2.remap``; the same camera matrix before and after (OpenCV's
        ``initUndistortRectifyMap`` with ``newCameraMatrix = K``).
    """
    return _maps(camera)


def undistort_frame(
    camera: CameraModel, image: np.ndarray, saturated: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Resample one frame onto the undistorted pixel grid (bilinear).

    Bilinear, not bicubic: it never rings, so a chrome sphere's one-pixel highlight and the
    saturation mask keep their place (bicubic moved the simulated rig's worst highlight by
    2.3 deg of light direction; docs/results.md, Calibration).

    Parameters
    ----------
    camera : CameraModel
    image : ndarray of shape (H, W) or (H, W, C), float32
        A linear frame, C <= 4.
    saturated : ndarray of shape (H, W), bool, optional
        Its clipping mask: an undistorted pixel is saturated when any recorded pixel it reads is.

    Returns
    -------
    image : ndarray, same shape and dtype
        Pixels that map outside the recorded frame are 0.
    saturated : ndarray of shape (H, W), bool, or None
    """
    check_frame_size(camera, image.shape[:2], "the frame")
    if not camera.has_distortion:
        return image, saturated
    map_x, map_y = undistortion_maps(camera)
    data = np.ascontiguousarray(image, dtype=np.float32)
    squeeze = data.ndim == 3 and data.shape[2] == 1
    out = cv2.remap(data[..., 0] if squeeze else data, map_x, map_y, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if squeeze:
        out = out[..., None]
    clipped = None
    if saturated is not None:
        spread = cv2.remap(saturated.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        clipped = spread > 0
    return out.astype(image.dtype, copy=False), clipped


def distort_points(camera: CameraModel, points: np.ndarray) -> np.ndarray:
    """Undistorted pixel positions -> where the lens puts them in the recorded frame.

    Parameters
    ----------
    points : ndarray of shape (m, 2)
        (column, row) in the undistorted frame.

    Returns
    -------
    ndarray of shape (m, 2)
    """
    return _in_normalised(camera, points, distort_normalised)


def distort_normalised(
    x: np.ndarray, y: np.ndarray, coefficients: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The radial-tangential model on normalised coordinates (module docstring)."""
    k1, k2, p1, p2, k3 = (float(c) for c in coefficients)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def undistort_normalised(
    xd: np.ndarray, yd: np.ndarray, coefficients: np.ndarray, iterations: int = 30
) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort_normalised` by Newton's method (to ~1e-12 where it is invertible).

    Starts from the distorted position; each step solves the 2x2 Jacobian system. Points where
    the model folds over (beyond the lens's field) keep their last iterate.
    """
    k1, k2, p1, p2, k3 = (float(c) for c in coefficients)
    x, y = xd.astype(np.float64).copy(), yd.astype(np.float64).copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        fx_ = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        a = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        c = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * c
        ok = np.abs(det) > 1e-12
        safe = np.where(ok, det, 1.0)
        step_x = np.where(ok, (d * fx_ - b * fy_) / safe, 0.0)
        step_y = np.where(ok, (a * fy_ - c * fx_) / safe, 0.0)
        x -= step_x
        y -= step_y
        if max(np.abs(step_x).max(initial=0.0), np.abs(step_y).max(initial=0.0)) < 1e-13:
            break
    return x, y


def undistort_points(camera: CameraModel, points: np.ndarray) -> np.ndarray:
    """Recorded (distorted) pixel positions -> their positions in the undistorted frame.

    Parameters
    ----------
    points : ndarray of shape (m, 2)
        (column, row) in the recorded frame.

    Returns
    -------
    ndarray of shape (m, 2)
    """
    return _in_normalised(camera, points, undistort_normalised)


def _in_normalised(
    camera: CameraModel,
    points: np.ndarray,
    mapping: Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
) -> np.ndarray:
    """Apply ``mapping`` (x, y, coefficients) -> (x', y') of normalised coordinates to pixels.

    Parameters
    ----------
    points : ndarray of shape (m, 2) or anything that reshapes to it
        (column, row) pixel positions.

    Returns
    -------
    ndarray of shape (m, 2)
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    x, y = mapping(
        (p[:, 0] - camera.cx) / camera.fx, (p[:, 1] - camera.cy) / camera.fy, camera.coefficients
    )
    return np.column_stack([x * camera.fx + camera.cx, y * camera.fy + camera.cy])
