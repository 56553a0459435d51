"""Tiles of the per-pixel solvers: the tile size, and scaled observations in, unit normals and
albedo out.

:func:`solve_tiles` runs a method's tile kernel over a solve's tiles (on the solve's threads);
the default's two passes (:mod:`._auto`) use the same ends. Both ends are numba
kernels that release the GIL (:func:`_prepare_kernel`, :func:`_store_kernel`): the tile threads
run them in parallel, at the speed of one pass over the tile's observations, where the same
algebra as whole-tile numpy operations held the GIL for as long as the SBL kernel itself took
(docs/results.md, issue 37). ``_prepare_tile`` is :func:`._linalg.pixel_scale`,
:func:`._linalg.inverse6` and the scaling in one pass; ``_store_tile`` the normalisation and
:func:`._solution._albedo_rows` (rounding-level differences: sums in another order).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._linalg import SOLVABLE_REL_DET, inverse3, solve3
from ._solution import ALBEDO_DEFINITION, Solution

# Noise level floor (relative to the pixel scale): the paper's lambda for noise-free data.
LAMBDA_FLOOR = 1e-6
DEFAULT_TILE_SIZE = 4096
# Smaller tiles when there would be fewer than this many per thread (so that no thread idles
# while another finishes a large last tile), but never below MIN_TILE_SIZE pixels.
TILES_PER_THREAD = 4
MIN_TILE_SIZE = 512


def sbl_lambda(scale: np.ndarray, noise_sigma: float, noise_floor: float,
               light_noise: np.ndarray | None = None) -> np.ndarray:
    """SBL's default noise variance per observation, in units of the pixel's scale squared.

    Parameters
    ----------
    scale : ndarray of shape (m,)
        The pixels' robust scales (:func:`pixel_scale`), in the observations' units.
    noise_sigma : float
        Noise proportional to the signal, relative to the pixel scale (:func:`estimate_noise`).
    noise_floor : float
        Noise constant in the observations' units (:func:`estimate_noise_model`).
    light_noise : ndarray of shape (n,), optional
        Relative size of the noise floor under each light (mean square 1; default all 1): a floor
        constant in the *image* units becomes ``floor / intensity`` once each image is divided by
        its light's intensity (:func:`light_noise_factors`).

    Returns
    -------
    ndarray of shape (m, 1), or (m, n) with ``light_noise``
        ``max(noise_sigma^2 + (noise_floor * light_noise_i / scale)^2, LAMBDA_FLOOR)`` (the floor
        where ``scale`` is 0: unsolvable pixels).
    """
    s = np.asarray(scale, dtype=np.float64)[:, None]
    f2 = np.ones(1) if light_noise is None else np.asarray(light_noise, dtype=np.float64) ** 2
    with np.errstate(divide="ignore"):
        inv = np.where(s > 0, 1.0 / np.where(s > 0, s, 1.0) ** 2, 0.0)
    return np.maximum(noise_sigma * noise_sigma + noise_floor**2 * inv * f2[None, :],
                      LAMBDA_FLOOR)


def _prepare_tile(obs, usable, lights, a, b):
    """Pixel-major scaled observations of pixels a:b and the solvable-pixel mask.

    Returns ``y`` (m, n) float64 (each pixel divided by its robust scale, 0 where not usable),
    ``w`` (m, n) float64 1/0 (usable, and the pixel solvable), ``scale`` (m,) and ``ok`` (m,):
    the pixel has a positive scale, at least 3 usable observations and a well-conditioned
    normal matrix (``det >= SOLVABLE_REL_DET (trace / 3)^3``).
    """
    m = b - a
    n = obs.shape[0]
    y = np.empty((m, n))
    w = np.empty((m, n))
    scale = np.empty(m)
    ok = np.empty(m, np.bool_)
    lights = np.ascontiguousarray(lights, dtype=np.float64)
    obs, usable = np.ascontiguousarray(obs), np.ascontiguousarray(usable)  # no copy when C
    if m:
        _prepare_kernel(obs, usable, lights, a, SOLVABLE_REL_DET, y, w, scale, ok)
    return y, w, scale, ok


@njit(inline="always")
def _median(buf, k):
    """Median of ``buf[:k]`` (k > 0; reordered in place): Wirth's selection, O(k)."""
    lo = (k - 1) // 2
    left, right = 0, k - 1
    while left < right:
        pivot = buf[lo]
        i, j = left, right
        while i <= j:
            while buf[i] < pivot:
                i += 1
            while pivot < buf[j]:
                j -= 1
            if i <= j:
                buf[i], buf[j] = buf[j], buf[i]
                i += 1
                j -= 1
        if j < lo:
            left = i
        if lo < i:
            right = j
    low = buf[lo]
    if k % 2:
        return low
    high = buf[lo + 1]
    for j in range(lo + 2, k):
        if buf[j] < high:
            high = buf[j]
    return 0.5 * (low + high)


@njit(inline="always")
def _solvable(xx, yy, zz, xy, xz, yz, rel_eps):
    """The normal matrix is well conditioned: ``det > rel_eps (trace / 3)^3``, trace > 0."""
    return inverse3(xx, yy, zz, xy, xz, yz, rel_eps)[0]


@njit(nogil=True, cache=True, error_model="numpy")
def _prepare_kernel(obs, usable, lights, a, rel_eps, y, w, scale, ok):
    m, n = y.shape
    for i in range(n):  # the tile, transposed (light-major reads, one pass)
        for p in range(m):
            y[p, i] = obs[i, a + p]
            w[p, i] = 1.0 if usable[i, a + p] else 0.0
    buf = np.empty(n)
    for p in range(m):
        k = 0
        total = 0.0
        xx = yy = zz = xy = xz = yz = 0.0
        for i in range(n):
            wi = w[p, i]
            l0, l1, l2 = lights[i, 0], lights[i, 1], lights[i, 2]
            xx += wi * l0 * l0
            yy += wi * l1 * l1
            zz += wi * l2 * l2
            xy += wi * l0 * l1
            xz += wi * l0 * l2
            yz += wi * l1 * l2
            if wi > 0.0:
                v = abs(y[p, i])
                buf[k] = v
                total += v
                k += 1
        s = 0.0
        if k > 0:
            s = _median(buf, k)
            if not s > 0.0:  # dark under most lights: the mean magnitude
                s = total / k
        good = _solvable(xx, yy, zz, xy, xz, yz, rel_eps) and s > 0.0 and k >= 3
        scale[p] = s
        ok[p] = good
        inv = 1.0 / s if good else 0.0
        for i in range(n):
            keep = good and w[p, i] > 0.0
            y[p, i] = y[p, i] * inv if keep else 0.0
            w[p, i] = 1.0 if keep else 0.0


def _store_tile(a, b, y, w, scale, ok, res, lights, normals, albedo, outliers, iterations,
                segments, albedo_flags=None, albedo_x=None):
    """Unit normals, the Lambertian-equivalent albedo and flags of pixels a:b into the outputs.

    ``albedo_flags`` (m, n) and ``albedo_x`` (m, 3): the observations left out of the albedo and
    the fit whose normal shades it (default the result's outliers and ``x``; the default method:
    SBL's, whichever model gave the normal).
    """
    has_segments = segments is not None
    flags = np.ascontiguousarray(res.outliers)
    x = np.ascontiguousarray(res.x, dtype=np.float64)
    _store_kernel(a, y, w, scale, ok, x,
                  x if albedo_x is None else np.ascontiguousarray(albedo_x, dtype=np.float64),
                  flags, flags if albedo_flags is None else np.ascontiguousarray(albedo_flags),
                  np.ascontiguousarray(res.iterations),
                  np.ascontiguousarray(res.segments) if has_segments else res.iterations,
                  np.ascontiguousarray(lights, dtype=np.float64), normals, albedo, outliers,
                  iterations, segments if has_segments else iterations, has_segments)


@njit(nogil=True, cache=True, error_model="numpy")
def _store_kernel(a, y, w, scale, ok, x, albedo_x, flags, albedo_flags, iters, segs, lights,
                  normals, albedo, outliers, iterations, segments, has_segments):
    m, n = y.shape
    for p in range(m):
        q = a + p
        s = scale[p]
        x0, x1, x2 = x[p, 0] * s, x[p, 1] * s, x[p, 2] * s
        length = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        good = ok[p] and length > 0.0 and math.isfinite(length)
        if good:
            u0, u1, u2 = x0 / length, x1 / length, x2 / length
        else:
            u0 = u1 = u2 = 0.0
        normals[q, 0], normals[q, 1], normals[q, 2] = u0, u1, u2
        # one albedo for every method: the Lambertian-equivalent reflectance on the inliers
        v0, v1, v2 = albedo_x[p, 0], albedo_x[p, 1], albedo_x[p, 2]
        vl = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if vl > 0.0 and math.isfinite(vl):
            v0, v1, v2 = v0 / vl, v1 / vl, v2 / vl
        else:
            v0, v1, v2 = u0, u1, u2
        num = 0.0
        den = 0.0
        for i in range(n):
            sh = v0 * lights[i, 0] + v1 * lights[i, 1] + v2 * lights[i, 2]
            if w[p, i] > 0.0 and not albedo_flags[p, i] and sh > 0.0:
                num += sh * y[p, i]
                den += sh * sh
        if not good:
            albedo[q] = 0.0
        elif den > 0.0:
            rho = num / den
            albedo[q] = (rho if rho > 0.0 else 0.0) * s
        else:
            albedo[q] = length
        for i in range(n):
            outliers[i, q] = flags[p, i] and good
        iterations[q] = iters[p] if ok[p] else 0
        if has_segments:
            segments[q] = segs[p] if ok[p] else 0


def ls_tiles(obs, usable, lights, a, b, normals, albedo, iterations):
    """Least squares of pixels a:b straight from the observations into the outputs.

    What :func:`_prepare_tile`, :func:`._kernels.ls_tile` and :func:`_store_tile` would give (the
    normals do not depend on the pixel's scale, so none is taken; the mean magnitude decides
    solvability, as there), in one pass per pixel: least squares is a few sums, and the three
    passes over a float64 copy of the tile cost ten times its arithmetic. No outliers.
    """
    obs, usable = np.ascontiguousarray(obs), np.ascontiguousarray(usable)
    if b > a:
        _ls_direct(obs, usable, np.ascontiguousarray(lights, dtype=np.float64), a, b,
                   SOLVABLE_REL_DET, normals, albedo, iterations)


@njit(nogil=True, cache=True, error_model="numpy")
def _ls_direct(obs, usable, lights, a, b, rel_eps, normals, albedo, iterations):
    n = obs.shape[0]
    for q in range(a, b):
        k = 0
        total = 0.0
        xx = yy = zz = xy = xz = yz = 0.0
        t0 = t1 = t2 = 0.0
        for i in range(n):
            if usable[i, q]:
                v = np.float64(obs[i, q])
                l0, l1, l2 = lights[i, 0], lights[i, 1], lights[i, 2]
                xx += l0 * l0
                yy += l1 * l1
                zz += l2 * l2
                xy += l0 * l1
                xz += l0 * l2
                yz += l1 * l2
                t0 += v * l0
                t1 += v * l1
                t2 += v * l2
                total += abs(v)
                k += 1
        good = k >= 3 and total > 0.0 and _solvable(xx, yy, zz, xy, xz, yz, rel_eps)
        length = 0.0
        u0 = u1 = u2 = 0.0
        if good:
            r = solve3(xx, yy, zz, xy, xz, yz, t0, t1, t2)
            length = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
            good = length > 0.0 and math.isfinite(length)
            if good:
                u0, u1, u2 = r[0] / length, r[1] / length, r[2] / length
        normals[q, 0], normals[q, 1], normals[q, 2] = u0, u1, u2
        iterations[q] = 1 if good else 0
        # the Lambertian-equivalent reflectance on the usable observations (no outliers)
        num = 0.0
        den = 0.0
        if good:
            for i in range(n):
                sh = u0 * lights[i, 0] + u1 * lights[i, 1] + u2 * lights[i, 2]
                if usable[i, q] and sh > 0.0:
                    num += sh * np.float64(obs[i, q])
                    den += sh * sh
        rho = num / den if den > 0.0 else length
        albedo[q] = (rho if rho > 0.0 else 0.0) if good else 0.0


def _finish_solution(used, normals, albedo, outliers, iterations, segments):
    if segments is not None:
        solved = segments > 0
        used["pixels_per_segments"] = {int(k): int(c) for k, c in
                                       zip(*np.unique(segments[solved], return_counts=True),
                                           strict=True)}
    used["albedo"] = ALBEDO_DEFINITION
    return Solution(normals, albedo, outliers, iterations, used)


def tile_pixels(pixels: int, workers: int, bound: int) -> int:
    """Pixels per tile: ``bound``, or fewer for a small input on several threads.

    Each of the ``workers`` threads gets ``TILES_PER_THREAD`` tiles, but a tile is never smaller
    than ``MIN_TILE_SIZE`` pixels (nor larger than ``bound``).
    """
    if workers == 1:
        return bound
    share = -(-pixels // (workers * TILES_PER_THREAD))
    return int(min(bound, max(MIN_TILE_SIZE, share)))


def solve_tiles(obs, lights, usable, row, params, used, starts, tile, mapper, progress):
    """Run a method's tile kernel over the tiles starting at ``starts``; the Solution.

    ``row`` is the method's :class:`~ps_lab.reconstruct.methods.SolverMethod`, ``params`` its
    parameters with the data-driven defaults filled in (``_solve._solve_params``), ``used`` the
    parameters as reported; ``mapper`` runs the tiles (a thread pool's ``map``, or ``map``).
    """
    n, p = obs.shape
    normals = np.zeros((p, 3))
    albedo = np.zeros(p)
    outliers = np.zeros((n, p), bool)
    iterations = np.zeros(p, np.int64)
    segments = np.zeros(p, np.int64) if row.segments else None
    kernel = row.tile
    kernel_params = {**{k: v for k, v in params.items()
                        if k not in ("noise_floor", "light_noise", "noise_sigma_pl")},
                     **row.fixed}
    per_pixel_lam = row.sbl_noise and params["lam"] is None

    def run_tile(a: int) -> int:
        b = min(a + tile, p)
        if row.direct_tiles is not None:  # e.g. least squares: a few sums per pixel
            row.direct_tiles(obs, usable, lights, a, b, normals, albedo, iterations)
            return b - a
        y, w, scale, ok = _prepare_tile(obs, usable, lights, a, b)
        tile_params = kernel_params
        if per_pixel_lam:
            floor, factors = params["noise_floor"], params["light_noise"]
            tile_params = {**kernel_params,
                           "lam": sbl_lambda(scale, used["noise_sigma"], floor, factors)}
            if row.pl_noise:
                # the PL model's noise: the same floor, its own relative noise (pl_noise_level)
                lam_pl = sbl_lambda(scale, params["noise_sigma_pl"], floor, factors)
                tile_params["lam_pl" if row.chooses else "lam"] = lam_pl
        res = kernel(y, w, lights, **tile_params)
        _store_tile(a, b, y, w, scale, ok, res, lights, normals, albedo, outliers, iterations,
                    segments)
        return b - a

    for done in mapper(run_tile, starts):
        if progress is not None:
            progress(done)
    return _finish_solution(used, normals, albedo, outliers, iterations, segments)
