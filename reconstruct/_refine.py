"""Iterative light refinement (Ikehata et al. 2012, section 3.3b)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ._linalg import apply6, inverse6, outer6
from ._solution import RefinementResult, SolverInputError
from ._solve import solve
from .metrics import angular_errors_deg


def _fit_lights(obs, usable, x):
    """Least-squares light vector per light on the usable observations: (n, 3) and a fit mask."""
    w = usable.astype(np.float64)
    y = np.where(usable, obs, 0.0)
    m6 = w @ outer6(x)
    inv, ok = inverse6(m6, 1e-9)
    return apply6(inv, y @ x), ok


def refine_lights(
    observations: np.ndarray,
    light_directions: np.ndarray,
    *,
    method: str = "sbl",
    iterations: int = 1,
    fixed_intensities: bool = False,
    valid: np.ndarray | None = None,
    light_intensities: np.ndarray | None = None,
    normal_gt: np.ndarray | None = None,
    light_directions_gt: np.ndarray | None = None,
    threads: int | None = None,
    tile_size: int | None = None,
    progress: Callable[[int], None] | None = None,
    keep_gauge: bool = True,
    **method_params,
) -> RefinementResult:
    """Alternate normal estimation and per-light least-squares re-fits of the lights.

    Each iteration solves the normals with the current lights, then, normals and albedos fixed
    (``x_j = albedo_j n_j``), re-fits every light vector ``v_i = argmin sum_j (y_ij - x_j . v)^2``
    over the observations that are usable and that the solver did not flag as outliers. The
    direction becomes ``v_i / |v_i|``; the intensity is multiplied by ``|v_i|`` (normalised so the
    mean relative change is 1, since a common factor only rescales the albedo) unless
    ``fixed_intensities``. A final solve uses the refined lights.

    Gauge: a common rotation of all lights (with the normals rotated alike) explains the images
    equally well -- with free intensities even any common invertible linear map ``G``
    (lights ``L G``, normals ``G^-1 x``) -- so refinement can only remove light errors relative
    to each other; a global rotation of the whole light set is never recovered. With
    ``keep_gauge`` (default) each re-fitted light set is mapped by the least-squares ``G`` back
    onto the input lights, so the common part stays that of the input calibration instead of
    drifting; measured on rendered scenes this halves the remaining light error (see
    docs/solvers.md).

    Parameters
    ----------
    observations : ndarray of shape (n, P)
        Observations already divided by ``light_intensities`` (as :func:`solve` takes them).
    light_directions : ndarray of shape (n, 3)
        Initial unit light directions.
    method : str
        Solver used for the normals (any of ``METHODS``).
    iterations : int
        Number of refinement iterations K (0 = just solve).
    fixed_intensities : bool
        Keep the intensities; refine directions only.
    valid : ndarray of shape (n, P), bool, optional
        Usable observations (as for :func:`solve`).
    light_intensities : ndarray of shape (n,), optional
        The intensities the observations were divided by (default ones); the refined ones are
        these times the fitted relative factor.
    normal_gt : ndarray of shape (P, 3), optional
        Ground truth for the history's ``normal_error_deg``.
    light_directions_gt : ndarray of shape (n, 3), optional
        Ground truth for the history's ``light_error_deg``.
    threads, tile_size, progress, **method_params
        Passed to :func:`solve` (``progress`` counts the pixels of every solve).
    keep_gauge : bool
        Map each re-fitted light set back onto the input lights by the best common linear map
        (see Gauge above).

    Returns
    -------
    RefinementResult
        ``history[0]`` describes the initial lights; ``history[k]`` the lights after update k:
        ``mean_direction_change_deg`` / ``max_direction_change_deg`` (against the previous
        lights), ``mean_intensity_change`` (mean ``|factor - 1|``), ``used_fraction`` (share of
        usable observations that entered the fits) and, with ground truth given,
        ``normal_error_deg`` (mean) and ``light_error_deg`` (mean).
    """
    obs = np.asarray(observations, dtype=np.float64)
    lights = np.asarray(light_directions, dtype=np.float64)
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise SolverInputError(f"light_directions must be (n, 3), got {lights.shape}")
    if iterations < 0:
        raise SolverInputError(f"iterations must be >= 0, got {iterations}")
    norms = np.linalg.norm(lights, axis=1)
    if np.any(~np.isfinite(norms)) or np.any(norms == 0):
        raise SolverInputError("light_directions contain NaN or zero rows")
    directions = lights / norms[:, None]
    n = directions.shape[0]
    if light_intensities is None:
        base = np.ones(n)
    else:
        base = np.asarray(light_intensities, np.float64).reshape(n)
    factor = np.ones(n)
    usable = np.isfinite(obs) if valid is None else (np.asarray(valid, bool) & np.isfinite(obs))

    def run(dirs, fac):
        return solve(obs, dirs * fac[:, None], method=method, valid=valid, threads=threads,
                     tile_size=tile_size, progress=progress, **method_params)

    def errors(sol, dirs):
        entry = {}
        if normal_gt is not None:
            entry["normal_error_deg"] = float(np.mean(angular_errors_deg(sol.normals, normal_gt)))
        if light_directions_gt is not None:
            entry["light_error_deg"] = float(np.mean(angular_errors_deg(dirs, light_directions_gt)))
        return entry

    anchor_vectors = directions.copy()
    sol = run(directions, factor)
    history = [{"iteration": 0, **errors(sol, directions)}]
    for k in range(1, iterations + 1):
        x = sol.normals * sol.albedo[:, None]
        solved = sol.albedo > 0
        inliers = usable & ~sol.outliers & solved[None, :]
        v, ok = _fit_lights(obs, inliers, x)
        if keep_gauge and ok.sum() >= 3:
            # Gauge: any invertible G maps (lights, x) to (lights G, G^-1 x) with the same images,
            # so the data cannot tell the light set's common linear part; keep the input's.
            g, *_ = np.linalg.lstsq(v[ok], anchor_vectors[ok], rcond=None)
            v = v @ g
        length = np.linalg.norm(v, axis=1)
        ok &= length > 0
        new_dirs = np.where(ok[:, None], v / np.where(ok, length, 1.0)[:, None], directions)
        change = angular_errors_deg(new_dirs, directions)
        new_factor = factor
        if not fixed_intensities:
            # the fit is in the units of the current light vectors (direction * factor)
            raw = np.where(ok, length, factor)
            new_factor = raw / raw.mean() * factor.mean()
        entry = {
            "iteration": k,
            "mean_direction_change_deg": float(change.mean()),
            "max_direction_change_deg": float(change.max()),
            "mean_intensity_change": float(np.mean(np.abs(new_factor / factor - 1.0))),
            "used_fraction": float(inliers.sum() / max(usable.sum(), 1)),
        }
        directions, factor = new_dirs, new_factor
        sol = run(directions, factor)
        entry.update(errors(sol, directions))
        history.append(entry)
    sol.params["refine_iterations"] = iterations
    return RefinementResult(sol, directions, base * factor, history)
