"""The LEDs' beams and a flat-field, from frames of a flat matte board under every light.

A real LED is not an isotropic point: its radiance falls off away from its optical axis (about
``cos^mu``; ``mu = 1`` a Lambertian emitter) and LEDs of one type differ in output by several
per cent. A flat matte board of known height (on the table the chrome spheres rest on, by
default) photographed under every light shows both: with the LED at ``P`` (triangulated from the
chrome spheres), the board point ``X`` (normal ``z``) is lit by

    B(X) = k * c(X)^mu * (P - X)_z / |P - X|^3,    c(X) = (X - P) . a / |X - P|,

with ``a`` the LED's axis and ``k`` its output times the board's albedo and the exposure.
:func:`fit_led_beams` fits ``k, a, mu`` per LED (the *beam* model). :func:`fit_flat_field`
keeps, instead of a model, the measured ratio of ``B`` to the isotropic model's prediction (the
*flat-field*): a gain per LED and board point, looked up at reconstruct where the ray from the
LED through the surface point meets the board (an LED's emission depends only on the direction,
so that board point carries the same factor as the surface point). Both are in the scene frame
of :mod:`ps_lab.geometry` (pixel units).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from ps_lab.errors import CalibrationError
from ps_lab.geometry import Camera, scene_points
from ps_lab.io.led_model import FlatField

__all__ = ["LedBeams", "LedModel", "beam_intensities_at_origin", "calibrate_leds",
           "fit_flat_field", "fit_led_beams", "with_led_model"]

# Board pixels dimmer than this share of the frame's 99th percentile are left out (noise, the
# frame's dark border).
MIN_SHARE = 0.05


@dataclass(frozen=True)
class LedBeams:
    """Per-LED beam fitted on the board (:func:`fit_led_beams`).

    Attributes
    ----------
    axes : ndarray of shape (n, 3)
        Unit optical axes (scene frame).
    mu : ndarray of shape (n,)
        ``cos^mu`` exponents (0: isotropic).
    outputs : ndarray of shape (n,)
        Radiant intensity on the axis, relative (mean 1).
    rms_pct : ndarray of shape (n,)
        RMS relative residual of each LED's fit on the board (per cent).
    """

    axes: np.ndarray
    mu: np.ndarray
    outputs: np.ndarray
    rms_pct: np.ndarray


def _board_points(shape, height, camera, step):
    """Scene points (m, 3) and their (rows, cols) on a grid of every ``step``-th pixel."""
    h, w = shape
    rows, cols = np.mgrid[step // 2:h:step, step // 2:w:step]
    rows, cols = rows.ravel(), cols.ravel()
    pts = scene_points(shape, rows, cols, np.full(rows.size, float(height)), camera)
    return pts, rows, cols


def _isotropic(points, p):
    """``(P - X)_z / |P - X|^3`` (m,): the isotropic irradiance on the board, up to the output."""
    d = p[None, :] - points
    dist = np.linalg.norm(d, axis=1)
    return np.clip(d[:, 2], 0.0, None) / dist ** 3


def _usable(board, saturated):
    """(n, H, W) bool: pixels of each board frame used in the fits."""
    level = np.percentile(board.reshape(len(board), -1), 99, axis=1)[:, None, None]
    ok = np.isfinite(board) & (board > MIN_SHARE * level)
    if saturated is not None:
        ok &= ~saturated
    return ok


def fit_led_beams(board: np.ndarray, positions: np.ndarray, height: float,
                  camera: Camera | None = None, *, saturated: np.ndarray | None = None,
                  step: int | None = None) -> LedBeams:
    """Fit each LED's output, axis and ``cos^mu`` exponent to its board frame.

    Least squares on the log brightness (the noise is about proportional to it): unknowns
    ``log k``, ``mu >= 0`` and two tilts of the axis from the LED-to-origin direction. Every
    ``step``-th pixel in each direction is used (default: about 3000 pixels, for four unknowns).

    Parameters
    ----------
    board : ndarray of shape (n, H, W)
        Linear frames of the flat matte board, one per light, dark-subtracted.
    positions : ndarray of shape (n, 3)
        LED positions (scene frame).
    height : float
        The board's height above the spheres' plane (pixels).
    camera : Camera, optional
        Perspective camera (None: orthographic).
    saturated : ndarray of shape (n, H, W), bool, optional
    step : int, optional

    Returns
    -------
    LedBeams

    Raises
    ------
    CalibrationError
        An LED without a position, or a board frame with too few lit pixels.
    """
    board = np.asarray(board, np.float64)
    n = len(board)
    pos = np.asarray(positions, np.float64).reshape(n, 3)
    if not np.all(np.isfinite(pos)):
        raise CalibrationError("--flat-field: every LED needs a position (two chrome spheres)")
    if step is None:
        step = max(1, int(round(np.sqrt(board.shape[1] * board.shape[2] / 3000.0))))
    pts, rows, cols = _board_points(board.shape[1:], height, camera, step)
    usable = _usable(board, saturated)
    axes, mu, outputs, rms = np.zeros((n, 3)), np.zeros(n), np.zeros(n), np.zeros(n)
    for j in range(n):
        keep = usable[j, rows, cols]
        if keep.sum() < 20:
            raise CalibrationError(f"--flat-field: board frame {j + 1} has too few lit pixels")
        x = pts[keep]
        value = np.log(board[j, rows[keep], cols[keep]])
        base = np.log(np.clip(_isotropic(x, pos[j]), 1e-300, None))
        a0 = -pos[j] / np.linalg.norm(pos[j])
        e1 = np.cross(a0, [0.0, 0.0, 1.0] if abs(a0[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a0, e1)
        ray = x - pos[j][None, :]
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)

        def axis(q):
            a = a0 + q[0] * e1 + q[1] * e2
            return a / np.linalg.norm(a)

        def residual(q):
            cos = np.clip(ray @ axis(q[2:]), 1e-6, None)
            return q[0] + q[1] * np.log(cos) + base - value

        def jacobian(q):
            v = a0 + q[2] * e1 + q[3] * e2
            norm = np.linalg.norm(v)
            a = v / norm
            cos = np.clip(ray @ a, 1e-6, None)
            jac = np.empty((len(ray), 4))
            jac[:, 0] = 1.0
            jac[:, 1] = np.log(cos)
            for k, e in ((2, e1), (3, e2)):
                jac[:, k] = q[1] * (ray @ ((e - a * (a @ e)) / norm)) / cos
            return jac

        start = np.array([float(np.median(value - base)), 1.0, 0.0, 0.0])
        fit = least_squares(residual, start, jac=jacobian, bounds=([-np.inf, 0.0, -1.0, -1.0],
                                                     [np.inf, 50.0, 1.0, 1.0]))
        axes[j], mu[j], outputs[j] = axis(fit.x[2:]), fit.x[1], np.exp(fit.x[0])
        rms[j] = 100.0 * float(np.sqrt(np.mean(fit.fun ** 2)))
    return LedBeams(axes, mu, outputs / outputs.mean(), rms)


def beam_intensities_at_origin(beams: LedBeams, positions: np.ndarray) -> np.ndarray:
    """Each LED's irradiance at the scene origin, ``k c(O)^mu / |P|^2`` (n,), mean 1."""
    pos = np.asarray(positions, np.float64)
    dist = np.linalg.norm(pos, axis=1)
    cos = np.clip(-np.einsum("nk,nk->n", beams.axes, pos) / dist, 1e-6, None)
    e = beams.outputs * cos ** beams.mu / dist ** 2
    return e / e.mean()


def fit_flat_field(board: np.ndarray, positions: np.ndarray, intensities: np.ndarray,
                   height: float, camera: Camera | None = None, *,
                   saturated: np.ndarray | None = None, cell: int = 8) -> FlatField:
    """The flat-field: measured over predicted board irradiance per LED, on a grid of cells.

    The prediction is the isotropic near-light model the solver uses
    (:func:`ps_lab.geometry.near_light_vectors` with the board's normal) times the light's
    intensity at the origin ``intensities`` (what the observations are divided by). Each
    ``cell`` x ``cell`` block's mean ratio is a grid node (cells without lit pixels take
    their nearest neighbour's); one common scale (the median over all LEDs and cells) leaves
    the albedo and the exposure out.

    Parameters
    ----------
    board : ndarray of shape (n, H, W)
    positions : ndarray of shape (n, 3)
    intensities : ndarray of shape (n,)
    height : float
    camera : Camera, optional
    saturated : ndarray of shape (n, H, W), bool, optional
    cell : int

    Returns
    -------
    FlatField
    """
    board = np.asarray(board, np.float64)
    n, h, w = board.shape
    pos = np.asarray(positions, np.float64).reshape(n, 3)
    e = np.asarray(intensities, np.float64).reshape(n)
    gh, gw = -(-h // cell), -(-w // cell)
    rows, cols = np.mgrid[0:h, 0:w]
    pts = scene_points((h, w), rows.ravel(), cols.ravel(), np.full(h * w, float(height)), camera)
    usable = _usable(board, saturated)
    label = ((rows // cell) * gw + cols // cell).ravel()
    gains = np.full((n, gh, gw), np.nan)
    for j in range(n):
        if not np.all(np.isfinite(pos[j])):
            gains[j] = 1.0
            continue
        ref2 = float(pos[j] @ pos[j])
        ratio = board[j].ravel() / (e[j] * ref2 * _isotropic(pts, pos[j]))
        ok = usable[j].ravel() & np.isfinite(ratio)
        count = np.bincount(label[ok], minlength=gh * gw)
        total = np.bincount(label[ok], ratio[ok], minlength=gh * gw)
        grid = np.where(count > 0, total / np.maximum(count, 1), np.nan).reshape(gh, gw)
        missing = ~np.isfinite(grid)
        if missing.all():
            raise CalibrationError(f"--flat-field: board frame {j + 1} has no lit pixels")
        if missing.any():
            near = ndimage.distance_transform_edt(missing, return_distances=False,
                                                  return_indices=True)
            grid = grid[tuple(near)]
        gains[j] = grid
    gains /= np.median(gains)
    centre_rows = (np.arange(gh) * cell + np.minimum(np.arange(1, gh + 1) * cell, h) - 1) / 2.0
    centre_cols = (np.arange(gw) * cell + np.minimum(np.arange(1, gw + 1) * cell, w) - 1) / 2.0
    xs = scene_points((h, w), np.zeros(gw), centre_cols, np.full(gw, float(height)), camera)[:, 0]
    ys = scene_points((h, w), centre_rows, np.zeros(gh), np.full(gh, float(height)), camera)[:, 1]
    return FlatField(gains.astype(np.float32), xs, ys, float(height), pos)


@dataclass(frozen=True)
class LedModel:
    """Both LED models of one board calibration (:func:`calibrate_leds`).

    Attributes
    ----------
    beams : LedBeams
    flat : FlatField
    intensities : ndarray of shape (n,)
        Each LED's irradiance at the origin from the beams (mean 1); the flat-field's gains are
        relative to these.
    """

    beams: LedBeams
    flat: FlatField
    intensities: np.ndarray

    def record(self) -> dict:
        """Summary for calibration.json."""
        b = self.beams
        return {
            "board_height_px": self.flat.height,
            "mu": [round(float(v), 4) for v in b.mu],
            "axes": [[round(float(v), 6) for v in a] for a in b.axes],
            "outputs": [round(float(v), 5) for v in b.outputs],
            "fit_rms_pct": [round(float(v), 3) for v in b.rms_pct],
            "flat_field_grid": list(self.flat.gains.shape[1:]),
            "flat_field_range": [round(float(self.flat.gains.min()), 4),
                                 round(float(self.flat.gains.max()), 4)],
        }


def calibrate_leds(board: np.ndarray, positions: np.ndarray, height: float,
                   camera: Camera | None = None, *, saturated: np.ndarray | None = None
                   ) -> LedModel:
    """Beams (:func:`fit_led_beams`), the intensities they give at the origin, and the
    flat-field relative to those (:func:`fit_flat_field`), from the board frames (n, H, W)."""
    beams = fit_led_beams(board, positions, height, camera, saturated=saturated)
    e = beam_intensities_at_origin(beams, positions)
    flat = fit_flat_field(board, positions, e, height, camera, saturated=saturated)
    return LedModel(beams, flat, e)


#: A flat matte board's frames fit the beam model within a few percent (docs/results.md); beyond
#: this the frames are not of a board under these LEDs (wrong folder, order, or height).
MAX_BEAM_RMS_PCT = 20.0


def check_board_below_leds(height: float, positions: np.ndarray, option: str) -> None:
    """The board's plane below every placed LED and within reach of them, else an error naming
    ``option`` (the ``--board`` that gave ``height``) and the reason.

    Parameters
    ----------
    height : float
        The board plane's z (pixels, scene frame).
    positions : ndarray of shape (n, 3)
        The LED positions (NaN rows: lights not placed).
    option : str
        The option as the user gave it, for the message.
    """
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    placed = np.isfinite(pos).all(axis=1)
    if not placed.any():
        raise CalibrationError(f"{option}: no LED could be placed (their positions are NaN)")
    z = pos[placed, 2]
    if not np.isfinite(height) or height >= z.min():
        where = "every LED" if height >= z.max() else f"{int(np.sum(z <= height))} of the LEDs"
        low = int(np.flatnonzero(placed)[np.argmin(z)])
        raise CalibrationError(
            f"{option}: the board plane at z={height:g} px is not below {where} (LED {low + 1} "
            f"at z={z.min():.1f} px); the board must lie under every light"
        )
    reach = float(np.max(np.linalg.norm(pos[placed], axis=1)))
    if z.min() - height > 10.0 * reach:
        raise CalibrationError(
            f"{option}: the board plane at z={height:g} px is more than 10 times the LEDs' "
            f"distance ({reach:.0f} px) below them"
        )


def with_led_model(calibration, board: np.ndarray, height: float | str = "table", *,
                   saturated: np.ndarray | None = None):
    """The calibration with its LEDs' beams and flat-field fitted on board frames.

    Parameters
    ----------
    calibration : Calibration
        A near-light calibration (two or more chrome spheres).
    board : ndarray of shape (n, H, W) or (n, H, W, C)
        The flat matte board under every light, the same lights in the same order, linear.
    height : float or "table"
        The board's height above the spheres' plane; ``"table"``: on the table the spheres
        rest on (minus their mean radius).
    saturated : ndarray of shape (n, H, W), bool, optional

    Returns
    -------
    Calibration
        ``light_intensities`` from the beams (:func:`beam_intensities_at_origin`), ``led_model``
        set, ``metadata["led_model"]`` its summary.

    Raises
    ------
    CalibrationError
        No LED positions, a board of another light count or image size, a board plane not
        below every LED (:func:`check_board_below_leds`).
    """
    tri = calibration.triangulation
    if tri is None:
        raise CalibrationError("--flat-field needs LED positions: give two chrome spheres")
    board = np.asarray(board, np.float64)
    if board.ndim == 4:
        board = board.mean(axis=3)
    n = len(calibration.light_directions)
    if board.shape[0] != n:
        raise CalibrationError(f"--flat-field: {board.shape[0]} board frames for {n} lights")
    if calibration.image_shape is not None and board.shape[1:] != tuple(calibration.image_shape):
        raise CalibrationError(f"--flat-field: board frames are {board.shape[2]}x"
                               f"{board.shape[1]}, the capture's {calibration.image_shape[1]}x"
                               f"{calibration.image_shape[0]}")
    option = "--board table" if height == "table" else f"--board {float(height):g}"
    if height == "table":
        height = -float(np.mean([c.radius for c in calibration.circles]))
    check_board_below_leds(float(height), tri.positions, option)
    model = calibrate_leds(board, tri.positions, float(height), calibration.camera,
                           saturated=saturated)
    misfit = np.flatnonzero(np.nan_to_num(model.beams.rms_pct, nan=np.inf) > MAX_BEAM_RMS_PCT)
    if misfit.size:
        j = int(misfit[0])
        raise CalibrationError(
            f"--flat-field: board frame {j + 1} is not a flat board lit by LED {j + 1} (the beam "
            f"model misses it by {model.beams.rms_pct[j]:.0f} % RMS, a board fits within a few "
            f"%; {misfit.size} frame(s) so): check the frames and --board"
        )
    columns = calibration.light_intensities.shape[1]
    metadata = {**calibration.metadata, "led_model": model.record()}
    return replace(calibration, led_model=model, metadata=metadata,
                   light_intensities=np.repeat(model.intensities[:, None], columns, axis=1),
                   intensity_source="LED beams fitted on a flat board (--flat-field)")
