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

from ps_lab.geometry import near_light_vectors, scene_points

from . import _near_kernels
from ._linalg import inverse6
from ._solution import Solution, SolverInputError
from ._solve import (
    DEFAULT_TILE_SIZE,
    LAMBDA_FLOOR,
    MIN_OUTLIER_THRESHOLD,
    NOISE_SAMPLE_PIXELS,
    SBL_TOL_MIN,
    SBL_TOL_NOISE_SHARE,
    SOLVABLE_REL_DET,
    _method_params,
    pixel_scale,
    residual_noise,
    tile_kernel,
)
from .integrate import integrate

__all__ = [
    "DEPTH_TOLERANCE_PX",
    "MAX_ROUNDS",
    "NearLights",
    "NearRounds",
    "estimate_noise_near",
    "fit_depth_offset",
    "near_light_reconstruct",
    "near_light_rounds",
    "solve_near",
]

# Stop when no pixel's depth moved more than this (pixels) in a round.
DEPTH_TOLERANCE_PX = 0.5
MAX_ROUNDS = 6
_KERNELS = {
    "ls": _near_kernels.ls_tile_pp,
    "l1": _near_kernels.l1_tile_pp,
    "sbl": _near_kernels.sbl_tile_pp,
    # the piecewise-linear kernels take per-pixel lights (m, n, 3) as they are
    "plls": tile_kernel("plls"),
    "plsbl": tile_kernel("plsbl"),
    "auto": tile_kernel("auto"),
}
# At most this many parabola steps of the depth-offset search.
_OFFSET_STEPS = 8


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
    """

    positions: np.ndarray
    directions: np.ndarray
    anisotropy: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def vectors(self, points: np.ndarray) -> np.ndarray:
        """Light vectors (m, n, 3) at scene-frame points (m, 3), unit intensity at the origin."""
        mu = self.anisotropy if np.size(self.anisotropy) else None
        return near_light_vectors(points, self.positions, self.directions, anisotropy=mu)


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
    method : {"ls", "l1", "sbl"}
        Solver.
    valid, threads, tile_size, progress, **method_params
        As for :func:`ps_lab.reconstruct.solve`.

    Returns
    -------
    Solution
    """
    if method == "rpca":
        raise SolverInputError(
            "rpca needs one light matrix for all pixels: use --lights directional with rpca"
        )
    obs, vectors, usable = _check(observations, light_vectors, valid)
    params = _method_params(method, method_params)
    n, p = obs.shape
    used: dict = {"method": method, "light_model": "near"}
    if method not in ("ls", "plls"):
        noise = params.pop("noise_sigma")
        if noise is None:
            noise = estimate_noise_near(obs, vectors, usable)
        if method in ("sbl", "plsbl", "auto"):
            # One relative lam here: the directional solver's per-light noise floor is not
            # carried over to near lights (issue 12 left it out).
            params.pop("noise_floor")
            params.pop("light_noise")
            params.pop("noise_sigma_pl", None)  # PL models: the same one lam here
            if params["lam"] is None:
                params["lam"] = max(noise * noise, LAMBDA_FLOOR)
            used["lambda"] = float(params["lam"])
        if params["outlier_threshold"] is None:
            params["outlier_threshold"] = max(3.0 * noise, MIN_OUTLIER_THRESHOLD)
        used["noise_sigma"] = float(noise)
        if method in ("sbl", "plsbl", "auto") and params["tol"] is None:
            params["tol"] = max(SBL_TOL_MIN, SBL_TOL_NOISE_SHARE * noise)
    elif method == "ls":
        params = {"outlier_threshold": np.inf}
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
    kernel = _KERNELS[method]

    def run_tile(a: int) -> int:
        b = min(a + tile, p)
        y, w, lights, scale, ok = _prepare_tile(obs, usable, vectors, a, b)
        res = kernel(y, w, lights, **params)
        x = res.x * scale[:, None]
        length = np.linalg.norm(x, axis=1)
        good = ok & (length > 0) & np.isfinite(length)
        normals[a:b] = np.where(good[:, None], x / np.where(good, length, 1.0)[:, None], 0.0)
        albedo[a:b] = np.where(good, length, 0.0)
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
    return Solution(normals, albedo, outliers, iterations, used)


# --- depth -----------------------------------------------------------------------------------


def _height_poisson(normals, mask, method="poisson", focal_length=None):
    """Height toward the camera (H, W) from normals inside ``mask``, pixel units, 0 outside.

    :func:`ps_lab.reconstruct.integrate.integrate` (least squares, orthographic) returns depth
    away from the camera; the near-light rounds work with heights above the spheres' plane.
    """
    depth = integrate(normals, mask, method=method, focal_length=focal_length).depth
    return np.where(mask, -np.nan_to_num(depth.astype(float)), 0.0)


def _inlier_residual(observations, use, vectors):
    """Sum of squared residuals of per-pixel least squares on the ``use`` observations."""
    weighted = vectors * use.T[:, :, None]
    m = np.einsum("pni,pnj->pij", weighted, vectors)
    b = np.einsum("pni,np->pi", weighted, observations)
    det = np.linalg.det(m)
    ok = det > 1e-12 * np.einsum("pii->p", m) ** 3
    x = np.zeros((m.shape[0], 3))
    x[ok] = np.linalg.solve(m[ok], b[ok][..., None])[..., 0]
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


@dataclass
class NearRounds:
    """What :func:`near_light_rounds` did.

    Attributes
    ----------
    depth : ndarray of shape (H, W)
        Final heights above the spheres' plane (pixel units; ``outline_depth`` off the mask).
    changes : list of float
        Largest depth change of each round (pixels).
    offsets : list of float
        Depth shift the near-light fit added in each round.
    seconds : list of float
    """

    depth: np.ndarray
    changes: list[float] = field(default_factory=list)
    offsets: list[float] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)

    def record(self) -> dict:
        """JSON-ready summary (``metrics.json``)."""
        return {
            "rounds": len(self.changes),
            "depth_change_px": [round(c, 4) for c in self.changes],
            "depth_offset_px": [round(o, 4) for o in self.offsets],
            "seconds_per_round": [round(s, 3) for s in self.seconds],
        }


def near_light_rounds(
    solve_normals: Callable[[np.ndarray], np.ndarray],
    mask: np.ndarray,
    lights: NearLights,
    sample: tuple[np.ndarray, np.ndarray, np.ndarray],
    sample_solve: Callable[[np.ndarray, np.ndarray, np.ndarray], Solution],
    *,
    outline_depth: float = 0.0,
    tolerance: float = DEPTH_TOLERANCE_PX,
    max_rounds: int = MAX_ROUNDS,
    integrate: Callable | None = None,
) -> NearRounds:
    """Alternate normals and depth until the depth settles.

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
        Evenly spaced mask pixels (index into the mask's row-major pixels) for the depth offset.
    sample_solve : callable
        ``sample_solve(observations, valid, light_vectors) -> Solution`` (for the inlier flags).
    outline_depth : float
        Height of the object's outline above the spheres' plane (the start and first anchor).
    tolerance : float
        Stop once no depth moved more than this (pixels).
    max_rounds : int
        At most this many rounds.
    integrate : callable, optional
        ``integrate(normals, mask, method="poisson", focal_length=None) -> height (H, W)``
        toward the camera; default :func:`ps_lab.reconstruct.integrate.integrate` (Poisson).

    Returns
    -------
    NearRounds
    """
    integrate = integrate or _height_poisson
    rows, cols = np.nonzero(mask)
    outline = mask & ~ndimage.binary_erosion(mask)
    observations, valid, index = sample
    result = NearRounds(depth=np.full(mask.shape, float(outline_depth)))
    for _ in range(max_rounds):
        started = time.perf_counter()
        normals = solve_normals(result.depth)
        depth = np.asarray(integrate(normals, mask, method="poisson", focal_length=None), float)
        depth = depth - depth[outline].mean() + outline_depth
        offset = 0.0
        if index.size:
            points = scene_points(mask.shape, rows[index], cols[index], depth[rows, cols][index])
            solution = sample_solve(observations, valid, lights.vectors(points))
            use = valid & np.isfinite(observations) & ~solution.outliers
            offset = fit_depth_offset(observations, use, points, lights)
        depth = np.where(mask, depth + offset, outline_depth)
        change = float(np.max(np.abs(depth - result.depth)[mask])) if mask.any() else 0.0
        result.depth = depth
        result.changes.append(change)
        result.offsets.append(offset)
        result.seconds.append(time.perf_counter() - started)
        if change < tolerance:
            break
    return result


def near_light_reconstruct(
    observations: np.ndarray,
    mask: np.ndarray,
    lights: NearLights,
    *,
    method: str = "sbl",
    valid: np.ndarray | None = None,
    threads: int | None = None,
    outline_depth: float = 0.0,
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
    if method != "ls" and method_params.get("noise_sigma") is None:
        plane = scene_points(mask.shape, rows, cols, np.full(rows.size, float(outline_depth)))
        method_params["noise_sigma"] = estimate_noise_near(obs, lights.vectors(plane), usable)

    def solve_at(depth: np.ndarray) -> Solution:
        points = scene_points(mask.shape, rows, cols, depth[rows, cols])
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
        integrate=integrate,
    )
    solution = solve_at(rounds.depth)
    solution.params["near"] = rounds.record()
    return solution, rounds

