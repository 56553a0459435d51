"""Whether a camera calibration's board views determine the focal length and principal point.

Zhang's method finds the intrinsics from how the board's plane is seen at *different
orientations*: each view's homography gives two constraints on the image of the absolute conic,
and views of parallel planes give the same two. Views that repeat one another (the same photo
twice, the board not moved) add no constraint at all, and a set of views whose board normals are
all parallel (every view fronto-parallel, or every view tilted the same way) leaves the focal
length undetermined: OpenCV still returns a camera, with a low RMS and a wrong focal length
(issue 43: six copies of one view gave f 13 % off and the centre 42 px off at RMS 0.08 px).

This module judges a calibration by three numbers, each a pure function of the views:

- the number of *distinct* views (:func:`repeated_views`: a view repeats an earlier one when their
  common corners lie within :data:`REPEAT_SHARE` of the frame's diagonal, RMS);
- the *tilt spread* (:func:`tilt_spread_deg`): the largest angle between two views' board normals;
- OpenCV's standard deviations of the intrinsics (``calibrateCameraExtended``: from the Jacobian
  at the solution and the residual variance), relative to the focal length and the frame.

:func:`judge_views` refuses a set with fewer than 3 distinct views, a tilt spread below
:data:`MIN_TILT_SPREAD_DEG` (there the standard deviations are not to be trusted: the problem is
singular, and they come out small while f is tens of percent off), a focal length's standard
deviation above :data:`MAX_F_SIGMA` or a principal point's above :data:`MAX_C_SIGMA`, and warns
(one line, with the numbers) below :data:`WEAK_TILT_SPREAD_DEG` or above :data:`WEAK_F_SIGMA` / :data:`WEAK_C_SIGMA`. The bounds come
from seeded synthetic sets (0.1 px corner noise, 8 views of a 9x6 board, tilts up to T): T = 2 deg
(spread 3-4 deg) gave f errors up to 16 % with sigma_f/f 22-54 %; T = 4 deg (spread 6-9 deg) f
errors up to 4.8 % with sigma_f/f 6-12 %; T = 10 deg (spread 14-21 deg) errors below 1 % with
sigma_f/f 1.2-2.2 %; T = 20 deg and more, errors below 0.5 % with sigma_f/f below 0.7 %. Where the
problem is not singular the error stayed within about 2 sigma. Near the singular set the poses, and
with them the tilt spread, follow the wrong focal length: rendered fronto-parallel views came out
at f 6 x the truth with a "tilt spread" of 5.6 deg and sigma_f/f 0.8 %, but a principal point
sigma of 13 % of the frame: above :data:`MAX_C_SIGMA` a set is refused as well (varied views give
0.3 %).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

#: Two views repeat one another when their common corners are this share of the frame's diagonal
#: apart (RMS) or closer (2 px on 320x240, 36 px on 6000x4000: the board was not moved).
REPEAT_SHARE = 0.005
#: A view repeats another only when they share at least this share of the fewer corners.
REPEAT_OVERLAP = 0.5
#: Fewest distinct views (Zhang: 3 views fix the 5 intrinsics).
MIN_DISTINCT_VIEWS = 3
#: Below this tilt spread (deg) the views do not determine the focal length: refused.
MIN_TILT_SPREAD_DEG = 5.0
#: Below this tilt spread (deg) the focal length is weakly determined: a warning.
WEAK_TILT_SPREAD_DEG = 15.0
#: Refused above this standard deviation of the focal length, relative to it.
MAX_F_SIGMA = 0.05
#: A warning above this standard deviation of the focal length, relative to it.
WEAK_F_SIGMA = 0.01
#: Refused above this standard deviation of the principal point, relative to the frame's side.
MAX_C_SIGMA = 0.05
#: A warning above this standard deviation of the principal point, relative to the frame's side.
WEAK_C_SIGMA = 0.02


@dataclass(frozen=True)
class ViewVerdict:
    """What :func:`judge_views` found.

    Attributes
    ----------
    refused : str or None
        Why the calibration cannot be used, else None.
    warning : str or None
        Why it is weak (one line, with the numbers), else None.
    distinct_views : int
    repeats : dict of int -> int
        View index -> the earlier view it repeats.
    tilt_spread_deg : float
    """

    refused: str | None
    warning: str | None
    distinct_views: int
    repeats: dict[int, int]
    tilt_spread_deg: float


def _corner_keys(object_points: np.ndarray) -> np.ndarray:
    """Integer keys for board corners (their board coordinates, to 1e-6 of the board's span)."""
    pts = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)
    span = float(np.ptp(pts[:, :2])) if len(pts) else 1.0
    scale = 1e6 / (span if span > 0 else 1.0)
    q = np.round(pts[:, :2] * scale).astype(np.int64)
    return q[:, 0] * 4_000_003 + q[:, 1]


def repeated_views(
    object_points: Sequence[np.ndarray],
    image_points: Sequence[np.ndarray],
    image_size: tuple[int, int],
) -> dict[int, int]:
    """Which views repeat an earlier one (the board not moved between them).

    Parameters
    ----------
    object_points : sequence of ndarray of shape (m_k, 3)
        Each view's corners on the board.
    image_points : sequence of ndarray of shape (m_k, 2)
        Their image positions (pixels).
    image_size : (W, H)

    Returns
    -------
    dict of int -> int
        View index -> the index of the first earlier view (itself not a repeat) it repeats:
        at least :data:`REPEAT_OVERLAP` of the fewer corners in common, and those within
        :data:`REPEAT_SHARE` of the diagonal (RMS).
    """
    limit = REPEAT_SHARE * float(np.hypot(*image_size))
    keys = [_corner_keys(o) for o in object_points]
    pixels = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in image_points]
    repeats: dict[int, int] = {}
    for j in range(len(keys)):
        for i in range(j):
            if i in repeats:
                continue
            common, ii, jj = np.intersect1d(keys[i], keys[j], return_indices=True)
            if len(common) == 0 or len(common) < REPEAT_OVERLAP * min(len(keys[i]), len(keys[j])):
                continue
            d = pixels[i][ii] - pixels[j][jj]
            if float(np.sqrt(np.mean(np.sum(d * d, axis=1)))) <= limit:
                repeats[j] = i
                break
    return repeats


def tilt_spread_deg(rvecs: Sequence[np.ndarray]) -> float:
    """The largest angle between two views' board normals (deg; 0 for fewer than two views).

    Parameters
    ----------
    rvecs : sequence of ndarray of shape (3,) or (3, 1)
        Each view's board-to-camera rotation (Rodrigues vector, OpenCV's).
    """
    if len(rvecs) < 2:
        return 0.0
    normals = np.array([cv2.Rodrigues(np.asarray(r, np.float64).reshape(3, 1))[0][:, 2]
                        for r in rvecs])
    cosines = np.clip(np.abs(normals @ normals.T), 0.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


def judge_views(
    names: Sequence[str],
    repeats: dict[int, int],
    spread_deg: float,
    focal: tuple[float, float],
    sigma: Sequence[float],
    image_size: tuple[int, int],
) -> ViewVerdict:
    """Refuse or warn about a calibration by its views (module docstring).

    Parameters
    ----------
    names : sequence of str
        The kept views' frame names (for the lines).
    repeats : dict of int -> int
        From :func:`repeated_views`, indices into ``names``.
    spread_deg : float
        From :func:`tilt_spread_deg`.
    focal : (fx, fy)
    sigma : sequence of 4 float
        OpenCV's standard deviations of fx, fy, cx, cy (pixels).
    image_size : (W, H)

    Returns
    -------
    ViewVerdict
    """
    n = len(names)
    distinct = n - len(repeats)
    listed = [f"{names[j]} repeats {names[i]}" for j, i in sorted(repeats.items())]
    pairs = ", ".join(listed[:3]) + (f" and {len(listed) - 3} more" if len(listed) > 3 else "")
    advice = "move and tilt the board 20-40 deg in different directions between shots"

    def verdict(refused: str | None, warning: str | None) -> ViewVerdict:
        return ViewVerdict(refused, warning, distinct, dict(repeats), spread_deg)

    if distinct < MIN_DISTINCT_VIEWS:
        return verdict(
            f"the {n} usable board frames show {distinct} distinct view(s) ({pairs}); at least "
            f"{MIN_DISTINCT_VIEWS} are needed: {advice}", None,
        )
    if spread_deg < MIN_TILT_SPREAD_DEG:
        return verdict(
            f"the board is parallel in every view (tilt spread {spread_deg:.1f} deg, at least "
            f"{MIN_TILT_SPREAD_DEG:g} needed): such views do not determine the focal length; "
            f"{advice}", None,
        )
    f = float(np.sqrt(focal[0] * focal[1]))
    sf = max(float(sigma[0]), float(sigma[1])) / f
    sc = max(float(sigma[2]) / image_size[0], float(sigma[3]) / image_size[1])
    numbers = (f"sigma f {100 * sf:.2g} %, sigma c ({float(sigma[2]):.2g}, {float(sigma[3]):.2g}) "
               f"px, tilt spread {spread_deg:.1f} deg, {distinct} distinct views")
    if not np.isfinite(sf) or sf > MAX_F_SIGMA:
        return verdict(
            f"the views do not determine the focal length ({numbers}; at most "
            f"{100 * MAX_F_SIGMA:g} % sigma f): {advice}", None,
        )
    if not np.isfinite(sc) or sc > MAX_C_SIGMA:
        return verdict(
            f"the views do not determine the principal point ({numbers}; at most "
            f"{100 * MAX_C_SIGMA:g} % of the frame): {advice}", None,
        )
    reasons = []
    if spread_deg < WEAK_TILT_SPREAD_DEG:
        reasons.append(f"tilt spread below {WEAK_TILT_SPREAD_DEG:g} deg")
    if sf > WEAK_F_SIGMA:
        reasons.append(f"sigma f above {100 * WEAK_F_SIGMA:g} %")
    if sc > WEAK_C_SIGMA:
        reasons.append(f"sigma c above {100 * WEAK_C_SIGMA:g} % of the frame")
    if repeats:
        reasons.append(pairs)
    warning = None
    if reasons:
        warning = (f"weak calibration views ({'; '.join(reasons)}): {numbers}; for a firmer "
                   f"calibration {advice}")
    return verdict(None, warning)
