"""How closely two numerical paths must agree: each bound derived once here, cited by the tests.

The solver kernels are compiled by numba with fastmath reassociation, so a sum over the lights is
split into as many partial sums as the CPU's SIMD width and unrolling suggest, and BLAS picks its
kernels by CPU and array shape: two paths that are equal in exact arithmetic (the per-pixel-light
kernels and the directional ones, a solver and its numpy oracle, bands and the whole image) agree
only as far as the arithmetic guarantees. The functions below return those bounds; each docstring
gives the derivation, and each test names the function in a one-line comment. Where two paths run
the same compiled code on the same numbers, the tests ask for bit equality instead.

Units: the solvers divide each pixel's observations by its robust scale ``s`` (the median usable
observation) and solve for ``x = albedo * normal / s``, so ``|x| >= 1`` wherever at most half of
a pixel's observations are raised by corruptions (a Lambertian observation is at most the albedo).
A unit normal ``x / |x|`` then moves by at most ``2 |dx| / |x|`` when ``x`` moves by ``dx``.
"""

from __future__ import annotations

import numpy as np

from ps_lab.reconstruct._linalg import SOLVABLE_REL_DET, pixel_scale
from ps_lab.reconstruct._tiles import LAMBDA_FLOOR

EPS = float(np.finfo(np.float64).eps)
EPS32 = float(np.finfo(np.float32).eps)
# Light tables are written with 9 decimals (ps_lab.io.light_files.write_light_table).
LIGHT_TABLE_ROUNDING = 5e-10
# A solvable pixel has det(A^T A) >= SOLVABLE_REL_DET (tr/3)^3, so the smallest eigenvalue of
# A^T A is >= det / tr^2 >= SOLVABLE_REL_DET tr / 27 and cond(A)^2 <= 27 / SOLVABLE_REL_DET.
SOLVABLE_COND = float(np.sqrt(27.0 / SOLVABLE_REL_DET))


def light_conditioning(lights: np.ndarray, valid: np.ndarray | None = None):
    """Smallest singular value and condition number of each pixel's usable light matrix.

    Parameters
    ----------
    lights : ndarray of shape (n, 3), or (P, n, 3) per pixel
    valid : ndarray of shape (n, P), bool, optional

    Returns
    -------
    sigma_min, cond : ndarray of shape (P,)
        0 and inf for pixels with fewer than three usable lights.
    """
    lights = np.asarray(lights, np.float64)
    if valid is None:
        per_pixel = lights if lights.ndim == 3 else lights[None]
        s = np.linalg.svd(per_pixel, compute_uv=False)
    else:
        valid = np.asarray(valid, bool)
        per_pixel = lights if lights.ndim == 3 else np.broadcast_to(lights, (valid.shape[1],
                                                                              *lights.shape))
        s = np.linalg.svd(per_pixel * valid.T[:, :, None], compute_uv=False)
    with np.errstate(divide="ignore"):
        return s[:, -1], np.where(s[:, -1] > 0, s[:, 0] / s[:, -1], np.inf)


def scaled_pixels(observations: np.ndarray, valid: np.ndarray | None, albedo: np.ndarray):
    """``|x|`` and the largest possible residual ``r_max`` of each pixel, in the solver's units.

    ``|x| = albedo / s``; a residual ``|y_i / s - a_i . x|`` is at most ``max_i |y_i| / s + |x|``
    for light vectors of length <= 1.
    """
    obs = np.asarray(observations, np.float64)
    usable = np.isfinite(obs) if valid is None else np.asarray(valid, bool) & np.isfinite(obs)
    scale = pixel_scale(np.ascontiguousarray(obs.T), np.ascontiguousarray(usable.T))
    safe = np.where(scale > 0, scale, 1.0)
    length = np.asarray(albedo, np.float64) / safe
    largest = np.where(usable, np.abs(np.nan_to_num(obs)), 0.0).max(axis=0) / safe
    return length, largest + length


def scaled_norm(observations: np.ndarray, valid: np.ndarray | None) -> float:
    """Frobenius norm of the usable observations divided by their pixels' scales (R-PCA's D)."""
    obs = np.asarray(observations, np.float64)
    usable = np.isfinite(obs) if valid is None else np.asarray(valid, bool) & np.isfinite(obs)
    scale = pixel_scale(np.ascontiguousarray(obs.T), np.ascontiguousarray(usable.T))
    safe = np.where(scale > 0, scale, 1.0)
    return float(np.linalg.norm(np.where(usable & (scale > 0), np.nan_to_num(obs) / safe, 0.0)))


def least_squares(n: int, cond=SOLVABLE_COND):
    """Normals of one least-squares fit when its sums of ``n`` terms are added in another order.

    Each sum is exact to ``(n - 1) eps/2`` times the sum of its terms' magnitudes (Higham,
    *Accuracy and Stability of Numerical Algorithms*, sect. 4.2), which is at most 3x the norm of
    ``A^T A`` (three columns) or ``A^T y`` (y >= 0): the normal equations move by ``3 n eps/2``
    relative, their solution by ``cond(A)^2`` times that for the matrix and again for the
    right-hand side, ``3 n eps cond^2``; the two paths differ by twice that and the unit normals
    by twice again: ``12 n eps cond^2``. Without ``cond``: the worst a solvable pixel may have
    (``SOLVABLE_COND``).
    """
    return 12.0 * n * EPS * np.asarray(cond, np.float64) ** 2


def reweighted(n: int, cond, weight_range):
    """Normals of two runs of an iteratively re-weighted fit (L1, SBL) with the same iterations.

    Each iteration is a least-squares fit whose weights span ``weight_range`` (largest over
    smallest), so its matrix has ``cond(A)^2 * weight_range``: one iteration's rounding is
    :func:`least_squares` with that; an iteration that contracts (steps that at least halve,
    as the stopping rule presumes) carries at most twice one iteration's error.
    """
    return 2.0 * least_squares(n, np.asarray(cond) * np.sqrt(weight_range))


def l1_weight_range(r_max, delta: float):
    """IRLS weights ``1 / max(|r|, delta)`` lie in ``[1 / max(r_max, delta), 1 / delta]``."""
    return np.maximum(r_max, delta) / delta


def sbl_weight_range(r_max, lam_min: float):
    """SBL's weights ``1 / (gamma + lam)`` near the limit (where the errors are made that a
    contracting iteration keeps) run from ``1 / (floor + lam)`` to ``1 / (z^2 + lam)``,
    ``|z| <= r_max``."""
    return (np.asarray(r_max) ** 2 + lam_min) / lam_min


def l1_stop(tol: float) -> float:
    """Normals of two L1-IRLS runs that may stop at different iterations.

    Both iterate the same map and stop at the first step with ``max_k |dx_k| < tol``; with steps
    that at least halve near the end each stops within ``tol`` of the common limit, so the two
    ``x`` differ by ``2 tol`` per component, ``2 sqrt(3) tol`` in length, the normals by
    ``4 sqrt(3) tol``.
    """
    return 4.0 * np.sqrt(3.0) * tol


def sbl_stop(tol: float, n: int, sigma_min, lam_ratio=1.0):
    """Normals of two SBL runs that may stop at different iterations.

    SBL stops at the first ``max_i |dz_i| < tol`` of its corruption estimate ``z = Gamma S y``.
    At any gamma the posterior mean solves ``(A^T L^-1 A + I / sigma_x2) x = A^T L^-1 (y - z)``
    over the usable observations (``L = diag(lam)``; from ``A^T D (y - A x) = x / sigma_x2`` and
    ``y - A x - z = L D (y - A x)``): a weighted least-squares fit of ``y - z`` whose gain is at
    most ``sqrt(lam_ratio) / sigma_min(A)``. Each run stops within ``tol`` of the common limit
    (steps that at least halve), so ``|dz|_2 <= 2 sqrt(n) tol`` and the normals differ by
    ``4 sqrt(n lam_ratio) tol / sigma_min(A)``.
    """
    return 4.0 * np.sqrt(n * lam_ratio) * tol / np.asarray(sigma_min, np.float64)


def rpca_columns(tol: float, rho: float, data_norm: float) -> float:
    """How far one column of R-PCA's low-rank or sparse part may differ between two runs.

    The ALM stops when ``||D - L - E||_F <= tol ||D||_F``; ``mu`` grows by ``rho`` per iteration
    and the steps shrink with ``1 / mu``, so each run stops within ``tol ||D||_F / (rho - 1)``
    (the geometric tail) of the common limit, and any column of ``L`` or ``E`` of the two runs
    differs by at most twice that.
    """
    return 2.0 * tol * data_norm / (rho - 1.0)


def rpca_stop(tol: float, rho: float, data_norm: float, sigma_min) -> float:
    """Normals of two R-PCA runs: each column of ``L`` (:func:`rpca_columns`) is fitted by least
    squares with all lights (gain ``1 / sigma_min(A)``), and the unit normals move by 2x that."""
    return 2.0 * rpca_columns(tol, rho, data_norm) / np.asarray(sigma_min, np.float64)


def light_refit(normal_matrices, light_vectors, pixels: int, x_change=0.0):
    """Relative change of :func:`ps_lab.reconstruct.fit_lights`' light vectors between two paths.

    Parameters
    ----------
    normal_matrices : ndarray of shape (n, 6)
        The fit's sums ``M_i = sum_j x_j x_j^T`` (:func:`ps_lab.reconstruct.light_fit_sums`).
    light_vectors : ndarray of shape (n, 3)
        The fitted vectors ``V`` (directions times intensities).
    pixels : int
        How many pixels the sums run over.
    x_change : float
        ``sum_j |dx_j|`` over the pixels, if the two paths' ``x_j = albedo_j n_j`` differ.

    Two sources: the sums added in another order (:func:`least_squares` with ``cond(M_i) =
    cond(X_i)^2``), and moved ``x_j``: ``v_i = M_i^-1 t_i`` moves by ``|M_i^-1| sum_j (|y_ij| +
    2 |x_j| |v_i|) |dx_j| <= 3 |M_i^-1| sum_j |dx_j|`` (observations, ``|x_j|`` and ``|v_i|``
    at most about 1). The gauge fit ``G = V^+ anchor`` multiplies both by at most
    ``1 + 2 cond(V)^2`` (first order, its residual at most ``|V G|``), and unit directions move by
    twice the relative change.
    """
    m = np.asarray(normal_matrices, np.float64)[:, [0, 3, 4, 3, 1, 5, 4, 5, 2]].reshape(-1, 3, 3)
    eigen = np.linalg.eigvalsh(m)
    length = np.linalg.norm(light_vectors, axis=1)
    moved = 3.0 * x_change / (eigen[:, 0] * length)
    gauge = 1.0 + 2.0 * np.linalg.cond(light_vectors) ** 2
    return (least_squares(pixels, np.sqrt(eigen[:, -1] / eigen[:, 0])) + 2.0 * moved).max() * gauge


def moved_lights(light_change, cond):
    """Normals of a converged solve when its light vectors move by ``light_change`` (relative).

    A converged robust fit moves like least squares on its inliers: ``x = A^+ y`` moves by
    ``cond(A) + cond(A)^2 |r| / (|A| |x|) <= 2 cond(A)^2`` times the change, the unit normals by
    twice that.
    """
    return 4.0 * np.asarray(cond, np.float64) ** 2 * light_change


def stored_float32(bound):
    """Values in [-1, 1] written as float32 are each rounded by at most ``eps32 / 2``."""
    return bound + EPS32


def angles_deg(normal_bound):
    """Angles (degrees) to a reference move by at most the angle between the two normals:
    ``2 asin(|dn| / 2) <= (pi / 2) |dn|``, ``|dn| <= sqrt(3)`` times the per-component bound."""
    return 90.0 * np.sqrt(3.0) * normal_bound


#: Piecewise-linear models (plls, plsbl, auto) against their oracle: their (K + 2)^2 normal
#: equations weigh the data by K^2 / LAMBDA_FLOOR (9e6 for K = 3) against the slopes' unit prior,
#: so with ``|B|^2`` up to ~n their condition reaches ~1e9 (n = 100); eps x 1e9 = 2e-7 on the
#: slopes, and the oracle's inverse and the kernel's Cholesky differ by that much: normals 1e-6,
#: albedo (|n| over the secant slope, the slopes' error undamped) 1e-5 relative.
PL_NORMALS = 1e-6
PL_ALBEDO = 1e-5


def solver_bounds(method: str, params: dict, observations, lights, valid, albedo,
                  same_iterations):
    """Per-pixel bounds of two runs of one solver on the same pixels (kernels, oracle, near).

    Parameters
    ----------
    method : {"ls", "l1", "sbl", "rpca", "plls", "plsbl", "auto"}
        (the piecewise-linear models: ``PL_NORMALS``, ``PL_ALBEDO``)
    params : dict
        The parameters as used (``Solution.params``).
    observations, valid : ndarray of shape (n, P)
    lights : ndarray of shape (n, 3), or (P, n, 3)
    albedo : ndarray of shape (P,)
        One run's albedo (for ``|x|`` and the residuals' range).
    same_iterations : ndarray of shape (P,), bool
        Pixels whose two runs took as many iterations: they differ by rounding
        (:func:`least_squares`, :func:`reweighted`); the others may also have stopped apart
        (:func:`l1_stop`, :func:`sbl_stop`).

    Returns
    -------
    normals : ndarray of shape (P,)
        Per-component bound on the two unit normals.
    flag_margin : ndarray of shape (P,)
        How far the two runs' flag statistics may differ (:func:`assert_flags_agree`): ``|dr_i|
        <= |dx|`` (L1; ``|dx| = |x|`` times half the normal bound), ``|dz_i| <= 2 tol`` plus that
        (SBL: each run within tol of the limit), a column of E (R-PCA).
    """
    n = np.shape(lights)[-2]
    sigma_min, cond = light_conditioning(lights, valid)
    length, r_max = scaled_pixels(observations, valid, albedo)
    same = np.asarray(same_iterations, bool)
    if method == "ls":
        bound = least_squares(n, cond)
        return bound, np.zeros_like(bound)
    if method == "rpca":
        data_norm = scaled_norm(observations, valid)
        all_lights = light_conditioning(lights)[0]  # each column is fitted with every light
        bound = np.broadcast_to(rpca_stop(params["tol"], params["rho"], data_norm, all_lights),
                                length.shape).copy()
        return bound, np.full(length.shape, rpca_columns(params["tol"], params["rho"], data_norm))
    if method == "l1":
        rounding = reweighted(n, cond, l1_weight_range(r_max, params["delta"]))
        bound = np.where(same, rounding, rounding + l1_stop(params["tol"]))
        return bound, 0.5 * bound * length
    if method in ("plls", "plsbl", "auto"):
        bound = np.full(length.shape, PL_NORMALS)
        return bound, 2.0 * (params.get("tol") or 0.0) + PL_ALBEDO * length
    lam = params.get("lambda") or LAMBDA_FLOOR
    factors = params.get("light_noise")
    lam_ratio = 1.0 if factors is None else (max(factors) / min(factors)) ** 2
    rounding = reweighted(n, cond, sbl_weight_range(r_max, lam))
    bound = np.where(same, rounding,
                     rounding + sbl_stop(params["tol"], n, sigma_min, lam_ratio))
    return bound, 2.0 * params["tol"] + 0.5 * bound * length


def error_summary(pixels: int, normal_bound: float, bin_width: float) -> dict:
    """``pytest.approx`` arguments for two runs' angular-error summaries (mean, median, p90, max).

    The mean adds the ``pixels`` angles in another order (``pixels * eps`` relative); with normals
    that differ by ``normal_bound`` every angle moves by :func:`angles_deg` of it, and a quantile
    read from a histogram of ``bin_width`` bins by one bin more.
    """
    shift = angles_deg(normal_bound) + bin_width if normal_bound > 0 else 0.0
    return {"rel": pixels * EPS, "abs": shift}


def assert_within(values, reference, bound, what: str = "normals") -> None:
    """``|values - reference| <= bound`` elementwise (``bound`` broadcast along the rows' values),
    naming the worst entry in the message."""
    diff = np.abs(np.asarray(values, np.float64) - np.asarray(reference, np.float64))
    bound = np.asarray(bound, np.float64)
    bound = bound.reshape(bound.shape + (1,) * (diff.ndim - bound.ndim))
    excess = diff - bound
    if excess.size and excess.max() > 0:
        worst = np.unravel_index(int(np.argmax(excess)), excess.shape)
        limit = np.broadcast_to(bound, diff.shape)[worst]
        raise AssertionError(f"{what}: entry {tuple(int(i) for i in worst)} differs by "
                             f"{diff[worst]:.3g} > {limit:.3g}")


def assert_flags_agree(flags, reference, statistic, threshold, margin) -> None:
    """Outlier flags (n, P) of two paths agree, except where the flag could legitimately flip.

    A flag is ``statistic > threshold``; it can differ only where the statistic (of either path:
    here the reference's, shape (n, P)) lies within ``margin`` (scalar or per pixel) of the
    threshold, ``margin`` being how far the two paths' statistics may differ.
    """
    lights, pixels = np.nonzero(np.asarray(flags) != np.asarray(reference))
    margin = np.broadcast_to(np.asarray(margin, np.float64), (np.shape(flags)[1],))
    gap = np.abs(np.asarray(statistic)[lights, pixels] - threshold)
    bad = gap > margin[pixels]
    assert not bad.any(), (
        f"{bad.sum()} of {lights.size} differing flags lie farther than the margin from the "
        f"threshold (first: light {lights[bad][0]}, pixel {pixels[bad][0]})"
    )
