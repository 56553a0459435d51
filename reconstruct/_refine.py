"""Iterative light refinement (Ikehata et al. 2012, section 3.3b)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ._linalg import apply6, inverse6, outer6
from ._solution import RefinementResult, SolverInputError
from ._solve import solve
from .metrics import angular_errors_deg


def light_fit_sums(observations: np.ndarray, valid: np.ndarray | None, solution) -> tuple:
    """Normal-equation sums of the per-light least-squares re-fit, over one set of pixels.

    Sums are additive over pixels, so a capture solved in bands accumulates them band by band
    and calls :func:`fit_lights` once.

    Parameters
    ----------
    observations : ndarray of shape (n, P)
    valid : ndarray of shape (n, P), bool, or None
    solution : Solution
        The solver's result for these pixels (normals, albedo, outliers).

    Returns
    -------
    normal_matrices : ndarray of shape (n, 6)
        ``sum_j x_j x_j^T`` per light over the observations that are usable, of solved pixels and
        not flagged as outliers (``x_j`` = albedo * normal), as ``(xx, yy, zz, xy, xz, yz)``.
    normal_targets : ndarray of shape (n, 3)
        ``sum_j y_ij x_j`` over the same observations.
    used : int
        Number of observations that entered.
    """
    obs = np.asarray(observations, dtype=np.float64)
    usable = np.isfinite(obs) if valid is None else (np.asarray(valid, bool) & np.isfinite(obs))
    x = solution.normals * solution.albedo[:, None]
    inliers = usable & ~solution.outliers & (solution.albedo > 0)[None, :]
    y = np.where(inliers, obs, 0.0)
    return inliers.astype(np.float64) @ outer6(x), y @ x, int(inliers.sum())


def fit_lights(
    normal_matrices: np.ndarray,
    normal_targets: np.ndarray,
    directions: np.ndarray,
    factor: np.ndarray,
    anchor: np.ndarray | None,
    fixed_intensities: bool = False,
) -> tuple:
    """One refinement update of the lights from :func:`light_fit_sums`.

    Parameters
    ----------
    normal_matrices, normal_targets : ndarray of shape (n, 6), (n, 3)
        Sums over all pixels.
    directions : ndarray of shape (n, 3)
        Current unit directions (kept for a light whose fit is singular).
    factor : ndarray of shape (n,)
        Current relative intensity factors (the light vectors solved with are
        ``directions * factor``).
    anchor : ndarray of shape (n, 3) or None
        Input light vectors whose gauge is kept (see :func:`refine_lights`); None lets it drift.
    fixed_intensities : bool
        Keep ``factor``.

    Returns
    -------
    directions : ndarray of shape (n, 3)
    factor : ndarray of shape (n,)
    entry : dict
        ``mean_direction_change_deg``, ``max_direction_change_deg``, ``mean_intensity_change``.
    """
    inv, ok = inverse6(np.asarray(normal_matrices, np.float64), 1e-9)
    v = apply6(inv, np.asarray(normal_targets, np.float64))
    if anchor is not None and ok.sum() >= 3:
        # Gauge: any invertible G maps (lights, x) to (lights G, G^-1 x) with the same images,
        # so the data cannot tell the light set's common linear part; keep the input's.
        g, *_ = np.linalg.lstsq(v[ok], np.asarray(anchor, np.float64)[ok], rcond=None)
        v = v @ g
    length = np.linalg.norm(v, axis=1)
    ok &= length > 0
    new_dirs = np.where(ok[:, None], v / np.where(ok, length, 1.0)[:, None], directions)
    change = angular_errors_deg(new_dirs, directions)
    new_factor = factor
    if not fixed_intensities:
        raw = np.where(ok, length, factor)
        new_factor = raw / raw.mean() * factor.mean()
    entry = {
        "mean_direction_change_deg": float(change.mean()),
        "max_direction_change_deg": float(change.max()),
        "mean_intensity_change": float(np.mean(np.abs(new_factor / factor - 1.0))),
    }
    return new_dirs, new_factor, entry


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
        sums_m, sums_t, used = light_fit_sums(obs, valid, sol)
        new_dirs, new_factor, update = fit_lights(sums_m, sums_t, directions, factor,
                                                  anchor_vectors if keep_gauge else None,
                                                  fixed_intensities)
        entry = {"iteration": k, **update,
                 "used_fraction": float(used / max(usable.sum(), 1))}
        directions, factor = new_dirs, new_factor
        sol = run(directions, factor)
        entry.update(errors(sol, directions))
        history.append(entry)
    sol.params["refine_iterations"] = iterations
    return RefinementResult(sol, directions, base * factor, history)
