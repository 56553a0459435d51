"""Near lights: per-pixel light vectors, and the alternation of normals and depth.

With LEDs at a finite distance each pixel p sees its own light vectors
``L_j(X_p)`` (:func:`ps_lab.geometry.near_light_vectors`: direction toward the LED, ``1/d²``
fall-off, ``cos^mu`` emission), which depend on the surface point ``X_p``, hence on the depth. The
alternation (:func:`near_light_rounds`) starts from the plane of the object's outline (the spheres'
plane by default) and repeats: light vectors at the current points -> normals
(:func:`solve_near`: SBL, L1, LS with per-pixel lights) -> depth by integration -> the depth's
constant (:func:`fit_depth_offset`) -> until the largest depth change is below a tolerance (usually
2-4 rounds).

Integration gives depth up to a constant, and the constant matters (2.5 px at a 600 px dome moves
the result by 0.1 degrees): the outline anchors it first, then the near-light model itself, since
a wrong offset turns each pixel's lights by a different amount. Measurements: ``docs/solvers.md``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ps_lab.geometry import Camera, near_light_vectors, scene_points
from ps_lab.io.led_model import FlatField

from . import _near_kernels
from ._near_refine import fit_near_intensities
from ._solution import ALBEDO_DEFINITION, Solution, SolverInputError, _albedo_rows
from ._linalg import SOLVABLE_REL_DET, apply6, inverse6, pixel_scale, sym6
from ._noise import NOISE_SAMPLE_PIXELS, residual_noise
from ._solve import _method_params, noise_defaults
from ._tiles import DEFAULT_TILE_SIZE, LAMBDA_FLOOR
from .methods import METHODS, solver
from .integrate import integrate
from .integrate import integrate as integrate_depth

__all__ = [
    "DEPTH_TOLERANCE_PX",
    "MAX_ROUNDS",
    "NearLights",
    "NearRounds",
    "estimate_noise_near",
    "fit_depth_offset",
    "fit_near_intensities",
    "near_light_reconstruct",
    "near_light_rounds",
    "solve_near",
]

# Stop when no pixel's depth moved more than this (pixels) in a round.
DEPTH_TOLERANCE_PX = 0.5
MAX_ROUNDS = 6
# At most this many parabola steps of a depth search; the outline search stops at this step
# (pixels): below it the criterion's change is within its noise (docs/solvers.md).
_OFFSET_STEPS = 8
_OUTLINE_RESOLUTION_PX = 3.0
# At most this many searches: a polish that leaves the basin found starts another from there.
_OUTLINE_SEARCHES = 3


@dataclass(frozen=True)
class NearLights:
    """Lights at a finite distance, in the scene frame of :mod:`ps_lab.geometry`.

    Attributes
    ----------
    positions : ndarray of shape (n, 3)
        LED positions (pixel units); NaN rows for lights too far to place (directional).
    directions : ndarray of shape (n, 3)
        Unit directions from the scene origin (used for the NaN rows).
    anisotropy : ndarray of shape (n,)
        Each LED's ``cos^mu`` exponent (0: isotropic).
    intensities : ndarray of shape (n,)
        Factors on the intensities the observations were divided by (empty: ones); set by the
        intensity refinement (:func:`fit_near_intensities`).
    camera : Camera or None
        The perspective camera that sees them (:class:`ps_lab.geometry.Camera`); None:
        orthographic. Each pixel's point then lies on its own ray (:meth:`points`), and depth is
        integrated under perspective.
    axes : ndarray of shape (n, 3) or None
        Each LED's optical axis for the ``cos^mu`` beam (None: toward the origin).
    flat_field : FlatField or None
        Per-LED gains measured on a flat board (:class:`ps_lab.io.led_model.FlatField`),
        multiplied onto the light vectors (the LED model ``flat-field``).
    """

    positions: np.ndarray
    directions: np.ndarray
    anisotropy: np.ndarray = field(default_factory=lambda: np.zeros(0))
    intensities: np.ndarray = field(default_factory=lambda: np.zeros(0))
    camera: Camera | None = None
    axes: np.ndarray | None = None
    flat_field: FlatField | None = None

    def points(self, shape, rows, cols, heights) -> np.ndarray:
        """Scene-frame points (m, 3) of pixels at heights above the spheres' plane."""
        return scene_points(shape, rows, cols, heights, self.camera)

    def vectors(self, points: np.ndarray) -> np.ndarray:
        """Light vectors (m, n, 3) at scene-frame points (m, 3), the intensity factors applied."""
        mu = self.anisotropy if np.size(self.anisotropy) else None
        e = self.intensities if np.size(self.intensities) else None
        vectors = near_light_vectors(points, self.positions, self.directions, e, anisotropy=mu,
                                     axes=self.axes)
        if self.flat_field is not None:
            vectors *= self.flat_field.at(points)[:, :, None]
        return vectors


# --- per-pixel-light solves -------------------------------------------------------------------


def _check(observations, light_vectors, valid):
    obs = np.asarray(observations)
    if obs.ndim != 2:
        raise SolverInputError(f"observations must be (n_lights, n_pixels), got shape {obs.shape}")
    n, p = obs.shape
    vectors = np.asarray(light_vectors, dtype=np.float64)
    if vectors.shape != (p, n, 3):
        raise SolverInputError(f"light_vectors must be ({p}, {n}, 3), got {vectors.shape}")
    if not np.all(np.isfinite(vectors)):
        raise SolverInputError("light_vectors contain NaN or infinite values")
    usable = np.isfinite(obs)
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != obs.shape:
            raise SolverInputError(f"valid must have the observations' shape {obs.shape}")
        usable &= valid
    return obs, vectors, usable


def _prepare_tile(obs, usable, vectors, a, b):
    """Pixel-major scaled observations of pixels a:b, their lights and the solvable mask."""
    y = np.array(obs[:, a:b].T, dtype=np.float64, order="C")
    w = np.ascontiguousarray(usable[:, a:b].T)
    lights = np.ascontiguousarray(vectors[a:b])
    scale = pixel_scale(y, w)
    x, yv, z = lights[..., 0], lights[..., 1], lights[..., 2]
    outer = np.stack([x * x, yv * yv, z * z, x * yv, x * z, yv * z], axis=-1)
    _, ok = inverse6(np.einsum("mn,mnk->mk", w.astype(np.float64), outer), SOLVABLE_REL_DET)
    ok &= (scale > 0) & (w.sum(axis=1) >= 3)
    w &= ok[:, None]
    y /= np.where(ok, scale, 1.0)[:, None]
    y[~w] = 0.0
    return y, w.astype(np.float64), lights, scale, ok


def estimate_noise_near(observations, light_vectors, valid=None, *,
                        max_pixels: int = NOISE_SAMPLE_PIXELS) -> float:
    """:func:`ps_lab.reconstruct.estimate_noise` with per-pixel light vectors (P, n, 3)."""
    obs, vectors, usable = _check(observations, light_vectors, valid)
    p = obs.shape[1]
    if p == 0:
        return 0.0
    take = np.unique(np.linspace(0, p - 1, min(p, max_pixels)).round().astype(np.int64))
    y, w, lights, _, ok = _prepare_tile(obs[:, take], usable[:, take], vectors[take], 0, take.size)
    y, w, lights = y[ok], w[ok], lights[ok]
    if y.shape[0] == 0:
        return 0.0
    res = _near_kernels.l1_tile_pp(y, w, lights, max_iter=30, tol=1e-6, delta=1e-6,
                                   outlier_threshold=np.inf)
    return residual_noise(y, w, np.einsum("mk,mnk->mn", res.x, lights))


def solve_near(
    observations: np.ndarray,
    light_vectors: np.ndarray,
    *,
    method: str = "sbl",
    valid: np.ndarray | None = None,
    threads: int | None = None,
    tile_size: int | None = None,
    progress: Callable[[int], None] | None = None,
    **method_params,
) -> Solution:
    """Per-pixel normals and albedo with per-pixel light vectors (lights at a finite distance).

    As :func:`ps_lab.reconstruct.solve` (same parameters, defaults, scaling and noise estimate),
    with ``light_vectors`` of shape (P, n, 3): pixel p's vector toward light j, scaled by the
    light's relative irradiance there. R-PCA needs one light matrix for all pixels and is not
    available here.

    Parameters
    ----------
    observations : ndarray of shape (n, P)
        Observations (divided by the light intensities).
    light_vectors : ndarray of shape (P, n, 3)
        Each pixel's light vectors.
    method : str
        Solver (a method of the solver table, :mod:`ps_lab.reconstruct.methods`, with a
        ``near_tile``).
    valid, threads, tile_size, progress, **method_params
        As for :func:`ps_lab.reconstruct.solve`.

    Returns
    -------
    Solution
    """
    if method in METHODS and solver(method).near_tile is None:
        raise SolverInputError(
            f"{method} needs one light matrix for all pixels: use --lights directional with "
            f"{method}"
        )
    obs, vectors, usable = _check(observations, light_vectors, valid)
    params = _method_params(method, method_params)
    n, p = obs.shape
    used: dict = {"method": method, "light_model": "near"}
    fallback = solver(method).near_fallback
    if fallback is not None:
        # The per-pixel choice between SBL and PL-SBL is a test against each pixel's own noise
        # (the per-observation model: a noise floor relative to the pixel's scale, per light),
        # which near lights do not estimate (one relative lam below); with one lam the test is
        # miscalibrated and picks PL where it is worse (docs/solvers.md), so near lights' default
        # solves with SBL, its parameters as given.
        params = _method_params(fallback, {k: v for k, v in method_params.items()
                                           if k in solver(fallback).defaults})
        method = used["solved_with"] = fallback
    row = solver(method)
    if row.estimates_noise:
        noise = params.pop("noise_sigma")
        if noise is None:
            noise = estimate_noise_near(obs, vectors, usable)
        if row.sbl_noise:
            # One relative lam here: the directional solver's per-light noise floor is not
            # carried over to near lights (issue 12 left it out).
            params.pop("noise_floor")
            params.pop("light_noise")
            params.pop("noise_sigma_pl", None)  # PL models: the same one lam here
            if params["lam"] is None:
                params["lam"] = max(noise * noise, LAMBDA_FLOOR)
            used["lambda"] = float(params["lam"])
        noise_defaults(row, params, noise)
        used["noise_sigma"] = float(noise)
    params = {**params, **row.fixed}
    used.update({k: v for k, v in params.items() if k != "lam"})
    tile = int(tile_size) if tile_size else DEFAULT_TILE_SIZE
    workers = int(threads) if threads else (os.cpu_count() or 1)
    if tile < 1 or workers < 1:
        raise SolverInputError("tile_size and threads must be positive")
    used.update({"tile_size": tile, "threads": workers})
    normals = np.zeros((p, 3))
    albedo = np.zeros(p)
    outliers = np.zeros((n, p), bool)
    iterations = np.zeros(p, np.int64)
    kernel = row.near_tile

    def run_tile(a: int) -> int:
        b = min(a + tile, p)
        y, w, lights, scale, ok = _prepare_tile(obs, usable, vectors, a, b)
        res = kernel(y, w, lights, **params)
        x = res.x * scale[:, None]
        length = np.linalg.norm(x, axis=1)
        good = ok & (length > 0) & np.isfinite(length)
        unit = np.where(good[:, None], x / np.where(good, length, 1.0)[:, None], 0.0)
        normals[a:b] = unit
        # one albedo for every method: the Lambertian-equivalent reflectance on the inliers
        rho = _albedo_rows(np.einsum("pk,pnk->pn", unit, lights), (w > 0) & ~res.outliers,
                           y) * scale
        albedo[a:b] = np.where(good, np.where(np.isnan(rho), length, rho), 0.0)
        outliers[:, a:b] = (res.outliers & good[:, None]).T
        iterations[a:b] = np.where(ok, res.iterations, 0)
        return b - a

    starts = range(0, p, tile)
    if workers == 1 or len(starts) <= 1:
        done = map(run_tile, starts)
    else:
        pool = ThreadPoolExecutor(max_workers=workers)
        done = pool.map(run_tile, starts)
    for count in done:
        if progress is not None:
            progress(count)
    if workers > 1 and len(starts) > 1:
        pool.shutdown()
    used["albedo"] = ALBEDO_DEFINITION
    return Solution(normals, albedo, outliers, iterations, used)


# --- depth -----------------------------------------------------------------------------------


def _height_poisson(normals, mask, method="poisson", focal_length=None):
    """Height toward the camera (H, W) from normals inside ``mask``, pixel units, 0 outside.

    :func:`ps_lab.reconstruct.integrate.integrate` (least squares, orthographic) returns depth
    away from the camera; the near-light rounds work with heights above the spheres' plane.
    """
    depth = integrate(normals, mask, method=method, focal_length=focal_length).depth
    return np.where(mask, -np.nan_to_num(depth.astype(float)), 0.0)


def _anchored_heights(normals, mask, outline, height, lights: NearLights, integrate):
    """Heights above the spheres' plane from normals, the outline's mean height at ``height``.

    Orthographic: ``integrate``'s heights shifted. Perspective: :func:`integrate` gives depth
    ``D`` along the viewing axis up to a scale ``s``; a point at height ``z`` lies at depth
    ``f - z`` (the camera is ``f`` above the plane), so ``z = f - s D`` with ``s`` setting the
    outline's mean height.
    """
    if lights.camera is None:
        raw = np.asarray(integrate(normals, mask, method="poisson", focal_length=None), float)
        return np.where(mask, raw - raw[outline].mean() + height, height)
    f = float(lights.camera.focal_length)
    depth = integrate_depth(normals, mask, method="poisson", focal_length=f,
                            principal_point=tuple(lights.camera.principal_point)).depth
    depth = np.nan_to_num(np.asarray(depth, float), nan=0.0)
    scale = (f - height) / depth[outline].mean()
    return np.where(mask, f - scale * depth, height)


def _inlier_residual(observations, use, vectors):
    """Sum of squared residuals of per-pixel least squares on the ``use`` observations."""
    weighted = vectors * use.T[:, :, None]
    m = np.einsum("pni,pnj->pij", weighted, vectors)
    b = np.einsum("pni,np->pi", weighted, observations)
    inverse, ok = inverse6(sym6(m))
    x = apply6(inverse, b)
    r = (observations.T - np.einsum("pni,pi->pn", vectors, x)) * use.T
    return float(np.sum(r[ok] ** 2))


def fit_depth_offset(observations, use, points, lights: NearLights, *, step=None) -> float:
    """The constant depth shift that best explains the inlier observations.

    A wrong offset turns every pixel's light vectors by a pixel-dependent amount, so the inlier
    least-squares residual, as a function of the offset, has a clear minimum: found by three-point
    parabolas (step ``step``, default 0.5 % of the median LED distance; each move at most two
    steps; the step shrinks 4x once the minimum is bracketed, down to ``step / 16``).

    Parameters
    ----------
    observations : ndarray of shape (n, m)
        Observations of m (sample) pixels, already divided by the light intensities.
    use : ndarray of shape (n, m), bool
        Inliers (usable and not flagged by the solver).
    points : ndarray of shape (m, 3)
        The pixels' current scene-frame points.
    lights : NearLights
        The LEDs.
    step : float, optional
        First step of the search (pixels).

    Returns
    -------
    float
        The shift to add to every depth (pixels).
    """
    obs = np.where(use, observations, 0.0).astype(np.float64)
    finite = np.all(np.isfinite(lights.positions), axis=1)
    if step is None:
        if not finite.any():
            return 0.0
        step = 0.005 * float(np.median(np.linalg.norm(lights.positions[finite], axis=1)))

    def residual(shift: float) -> float:
        return _inlier_residual(obs, use, lights.vectors(points + np.array([0.0, 0.0, shift])))

    centre, h = 0.0, step
    for _ in range(_OFFSET_STEPS):
        f0, fm, fp = residual(centre), residual(centre - h), residual(centre + h)
        curvature = fp + fm - 2.0 * f0
        move = 0.5 * h * (fm - fp) / curvature if curvature > 0 else (h if fp < fm else -h)
        move = float(np.clip(move, -2.0 * h, 2.0 * h))
        centre += move
        if abs(move) < h:  # the minimum is bracketed: refine around it
            h /= 4.0
            if h < step / 16.0:
                break
    return centre


def _search_outline(score, tried, centre, step, mask):
    """Three-point parabolas over the outline height from ``centre``.

    First step ``step``, moves of at most three steps, down to ``_OUTLINE_RESOLUTION_PX``.
    Returns the height found and the settled depth of the nearest height tried, shifted to it.
    """
    h = step
    for _ in range(_OFFSET_STEPS if step > 0 else 0):
        f0, fm, fp = score(centre), score(centre - h), score(centre + h)
        curvature = fp + fm - 2.0 * f0
        move = 0.5 * h * (fm - fp) / curvature if curvature > 0 else (h if fp < fm else -h)
        move = float(np.clip(move, -3.0 * h, 3.0 * h))
        centre = round(centre + move, 6)
        if abs(move) < h:  # bracketed: refine around it
            h = max(abs(move), h / 4.0)
            if h < _OUTLINE_RESOLUTION_PX:
                break
    if not tried:
        return centre, np.full(mask.shape, centre)
    nearest = min(tried, key=lambda c: abs(c - centre))
    return centre, tried[nearest][1] + (centre - nearest)


@dataclass
class NearRounds:
    """What :func:`near_light_rounds` did.

    Attributes
    ----------
    depth : ndarray of shape (H, W)
        Final heights above the spheres' plane (pixel units; the outline's height off the mask).
    changes : list of float
        Largest depth change of each round (pixels), every evaluation of the search included.
    offsets : list of float
        The outline heights tried by the search (pixels, in the order tried); one entry, the
        stated height, when it was given.
    seconds : list of float
    outline : float
        The outline height the result has (pixels above the spheres' plane).
    outline_source : str
        ``"stated"`` or ``"fitted"``.
    residuals : list of float
        The sample's inlier residual at each height tried (the search's criterion).
    """

    depth: np.ndarray
    changes: list[float] = field(default_factory=list)
    offsets: list[float] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    outline: float = 0.0
    outline_source: str = "fitted"
    residuals: list[float] = field(default_factory=list)

    def record(self) -> dict:
        """JSON-ready summary (``metrics.json``)."""
        return {
            "rounds": len(self.changes),
            "depth_change_px": [round(c, 4) for c in self.changes],
            "outline_height_px": round(self.outline, 4),
            "outline_height_source": self.outline_source,
            "outline_heights_tried_px": [round(o, 4) for o in self.offsets],
            "outline_residuals": [float(f"{r:.6g}") for r in self.residuals],
            "seconds_per_round": [round(s, 3) for s in self.seconds],
        }


def near_light_rounds(
    solve_normals: Callable[[np.ndarray], np.ndarray],
    mask: np.ndarray,
    lights: NearLights,
    sample: tuple[np.ndarray, np.ndarray, np.ndarray],
    sample_solve: Callable[[np.ndarray, np.ndarray, np.ndarray], Solution],
    *,
    outline_depth: float | None = None,
    tolerance: float = DEPTH_TOLERANCE_PX,
    max_rounds: int = MAX_ROUNDS,
    integrate: Callable | None = None,
    set_noise: Callable[[float], None] | None = None,
) -> NearRounds:
    """Alternate normals and depth until the depth settles; find the outline's height if unknown.

    For one outline height ``c`` the rounds repeat: normals at the current points -> depth by
    integration, shifted so the outline's mean height is ``c`` -> until no depth moves more than
    ``tolerance``. Integration cannot tell ``c``; without ``outline_depth`` it is searched (a
    profile fit): each height tried is settled by its own rounds (warm-started from the nearest
    one tried), and scored by the least-squares residual of the sample's inliers at its settled
    points (:func:`_inlier_residual`). The score has a clear minimum at the true height, which
    three-point parabolas find (:func:`_search_outline`: first step 2 % of the median LED
    distance, moves of at most three steps, down to 3 px); then rounds from there, each shifted
    by :func:`fit_depth_offset` (the shift of the settled shape that minimises the same residual,
    finer than the search). That shift alone, from a height far off, is biased: normals solved
    at a wrong height integrate to a distorted shape that a shift partly explains. Far from the
    truth the score can be flat or bumpy; when the shifted rounds move more than two search
    steps, the search starts again from where they went (at most 3 searches). Measured in
    ``docs/solvers.md``.

    Parameters
    ----------
    solve_normals : callable
        ``solve_normals(depth (H, W)) -> normals (H, W, 3)``: every mask pixel solved with its
        light vectors at ``depth`` (the caller decides how: whole, or band by band).
    mask : ndarray of shape (H, W), bool
        The object.
    lights : NearLights
        The LEDs.
    sample : (observations (n, m), valid (n, m), pixel index (m,))
        Evenly spaced mask pixels (index into the mask's row-major pixels) for the search.
    sample_solve : callable
        ``sample_solve(observations, valid, light_vectors) -> Solution`` (for the inlier flags).
    outline_depth : float, optional
        Height of the object's outline above the spheres' plane when known (pixels; e.g. the
        table under spheres of radius r: ``-r``); None: searched, starting from 0.
    tolerance : float
        Stop a height's rounds once no depth moved more than this (pixels).
    max_rounds : int
        At most this many rounds per height.
    integrate : callable, optional
        ``integrate(normals, mask, method="poisson", focal_length=None) -> height (H, W)``
        toward the camera; default :func:`ps_lab.reconstruct.integrate.integrate` (Poisson).
    set_noise : callable, optional
        ``set_noise(sigma)``: the noise level ``solve_normals`` and ``sample_solve`` use from now
        on. Given, it is estimated on the sample (:func:`estimate_noise_near`) at the starting
        points of every height tried: at a wrong height the model error inflates it (a larger
        SBL lambda, fewer outliers flagged), which would blunt the search's criterion.

    Returns
    -------
    NearRounds
    """
    integrate = integrate or _height_poisson
    rows, cols = np.nonzero(mask)
    outline = mask & ~ndimage.binary_erosion(mask)
    observations, valid, index = sample
    result = NearRounds(depth=np.zeros(mask.shape))

    def settle(height: float, start: np.ndarray, rounds: int) -> np.ndarray:
        depth = np.where(mask, start, height)
        if set_noise is not None and index.size:
            points = lights.points(mask.shape, rows[index], cols[index], depth[rows, cols][index])
            set_noise(estimate_noise_near(observations, lights.vectors(points), valid))
        for _ in range(rounds):
            started = time.perf_counter()
            normals = solve_normals(depth)
            new = _anchored_heights(normals, mask, outline, height, lights, integrate)
            change = float(np.max(np.abs(new - depth)[mask])) if mask.any() else 0.0
            depth = new
            result.changes.append(change)
            result.seconds.append(time.perf_counter() - started)
            if change < tolerance:
                break
        return depth

    if outline_depth is not None or not index.size or not mask.any():
        height = 0.0 if outline_depth is None else float(outline_depth)
        result.depth = settle(height, np.full(mask.shape, height), max_rounds)
        result.outline, result.offsets = height, [height]
        result.outline_source = "fitted" if outline_depth is None else "stated"
        return result

    tried: dict[float, tuple[float, np.ndarray]] = {}

    def score(height: float) -> float:
        if height in tried:
            return tried[height][0]
        if tried:  # warm start: the nearest height tried, shifted
            near = min(tried, key=lambda h: abs(h - height))
            start = tried[near][1] + (height - near)
            depth = settle(height, start, max(2, max_rounds // 2))
        else:
            depth = settle(height, np.full(mask.shape, height), max_rounds)
        points = lights.points(mask.shape, rows[index], cols[index], depth[rows, cols][index])
        vectors = lights.vectors(points)
        use = valid & np.isfinite(observations) & ~sample_solve(observations, valid,
                                                                 vectors).outliers
        value = _inlier_residual(np.where(use, observations, 0.0), use, vectors)
        tried[height] = (value, depth)
        result.offsets.append(height)
        result.residuals.append(value)
        return value

    def polish(centre: float, depth: np.ndarray) -> tuple[np.ndarray, float]:
        """Rounds from the height found, each shifted to explain its shape best.

        The shift (:func:`fit_depth_offset`) is unbiased near the truth and finer than the
        search; returns the depth and the last shift.
        """
        # the noise level on the plane of the outline found, as the rounds had on their
        # starting plane before the search (issue 15): at the settled shape it is ~3x lower on
        # the demo's rig, and SBL's lambda = sigma^2 then too small for the model error there
        # (0.283 vs 0.265 deg; docs/solvers.md)
        if set_noise is not None:
            plane = np.full(index.size, centre)
            points = lights.points(mask.shape, rows[index], cols[index], plane)
            set_noise(estimate_noise_near(observations, lights.vectors(points), valid))
        shift = 0.0
        for _ in range(max_rounds):
            started = time.perf_counter()
            normals = solve_normals(depth)
            new = _anchored_heights(normals, mask, outline, centre, lights, integrate)
            points = lights.points(mask.shape, rows[index], cols[index], new[rows, cols][index])
            use = valid & np.isfinite(observations) & ~sample_solve(
                observations, valid, lights.vectors(points)).outliers
            shift = fit_depth_offset(observations, use, points, lights)
            new = _anchored_heights(normals, mask, outline, centre + shift, lights, integrate)
            change = float(np.max(np.abs(new - depth)[mask]))
            depth = new
            result.changes.append(change)
            result.offsets.append(centre + shift)
            result.seconds.append(time.perf_counter() - started)
            if change < tolerance:
                break
        return depth, shift

    finite = np.all(np.isfinite(lights.positions), axis=1)
    distance = float(np.median(np.linalg.norm(lights.positions[finite], axis=1))) if \
        finite.any() else 0.0
    step = 0.02 * distance
    centre = 0.0
    for _ in range(_OUTLINE_SEARCHES):
        centre, depth = _search_outline(score, tried, centre, step, mask)
        depth, shift = polish(centre, depth)
        centre = round(centre + shift, 6)
        if abs(shift) <= 2.0 * step:
            break
        # the polish left the basin the search settled in (the score can be flat or bumpy far
        # from the truth): search again from where it went
    result.depth = depth
    result.outline = centre
    return result


def near_light_reconstruct(
    observations: np.ndarray,
    mask: np.ndarray,
    lights: NearLights,
    *,
    method: str = "sbl",
    valid: np.ndarray | None = None,
    threads: int | None = None,
    outline_depth: float | None = None,
    tolerance: float = DEPTH_TOLERANCE_PX,
    max_rounds: int = MAX_ROUNDS,
    integrate: Callable | None = None,
    **method_params,
) -> tuple[Solution, NearRounds]:
    """Normals of lights at a finite distance, all pixels in memory (library and benchmarks).

    Parameters
    ----------
    observations : ndarray of shape (n, P)
        The mask's pixels in row-major order, divided by the light intensities (at the origin).
    mask : ndarray of shape (H, W), bool
        The object.
    lights : NearLights
        The LEDs.
    method, valid, threads, **method_params
        As for :func:`solve_near`.
    outline_depth, tolerance, max_rounds, integrate
        As for :func:`near_light_rounds`.

    Returns
    -------
    solution : Solution
        Solved at the final depth.
    rounds : NearRounds
    """
    obs = np.asarray(observations)
    usable = np.isfinite(obs) if valid is None else (np.isfinite(obs) & valid)
    rows, cols = np.nonzero(mask)
    if obs.shape[1] != rows.size:
        raise SolverInputError(f"{obs.shape[1]} observed pixels but the mask has {rows.size}")
    set_noise: Callable[[float], None] | None = None
    if solver(method).estimates_noise and method_params.get("noise_sigma") is None:
        # estimated by the rounds at each height they try
        set_noise = lambda sigma: method_params.__setitem__("noise_sigma", sigma)  # noqa: E731

    def solve_at(depth: np.ndarray) -> Solution:
        points = lights.points(mask.shape, rows, cols, depth[rows, cols])
        return solve_near(obs, lights.vectors(points), method=method, valid=usable,
                          threads=threads, **method_params)

    def normals_at(depth: np.ndarray) -> np.ndarray:
        normals = np.zeros((*mask.shape, 3))
        normals[rows, cols] = solve_at(depth).normals
        return normals

    take = np.unique(np.linspace(0, rows.size - 1, min(rows.size, NOISE_SAMPLE_PIXELS)).round())
    take = take.astype(np.int64) if rows.size else np.zeros(0, np.int64)

    def sample_solve(o, v, vectors):
        return solve_near(o, vectors, method=method, valid=v, threads=threads, **method_params)

    rounds = near_light_rounds(
        normals_at, mask, lights, (obs[:, take], usable[:, take], take), sample_solve,
        outline_depth=outline_depth, tolerance=tolerance, max_rounds=max_rounds,
        integrate=integrate, set_noise=set_noise,
    )
    solution = solve_at(rounds.depth)
    solution.params["near"] = rounds.record()
    return solution, rounds

