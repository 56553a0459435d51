"""The ps appearance model's fit as numba kernels (``reconstruct --appearance ps``).

:func:`_fit_ps_block` fits the visibility half-space and the ridge least squares of the visible
Lambertian residual (the maths of :mod:`.blocks`, whose ``fit_visibility``, ``fit_ps``
and ``fit_block`` call it) for groups of :data:`LANES` pixels side by side: float32
observations read once, float64 sums, the small systems solved in registers. Also the
observation helpers both modules share.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ps_lab.appearance.models import PS_TERMS
from ps_lab.jit import INLINE, VECTOR

from ._ps_terms import (
    _HSH,
    _DX,
    _DY,
    _DZ,
    _XX,
    _YY,
    _ZZ,
    _XY,
    _XZ,
    _YZ,
    TABLE_ROWS,
    _CNT,
    _MEAN,
    _S,
    _F,
    _L,
    _SH,
    WORK_ROWS,
    LANES,
    TILE,
    PART,
    _fill_table,
    _load_tile,
    _pixel_rows,
    _term_codes,
    _terms_pixel,
)

# Ridge of the ps fit, relative to the mean diagonal of each pixel's normal matrix.
PS_RIDGE = 1e-4
# Visibility: a training light shadows the pixel when the pixel is below this fraction of its
# Lambertian prediction; only lights with n·l above VIS_MARGIN carry evidence (near the
# terminator the ratio is noise); ridge toward V = 1 (relative to the lights' count).
VIS_LABEL = 0.5
VIS_MARGIN = 0.1
VIS_RIDGE = 1e-3
VIS_ROUNDS = 4
# Ridge of the visibility's constant term (relative to the lights' count).
VIS_RIDGE_CONSTANT = 1e-6
# Added to every ps normal matrix's diagonal (besides the relative ridge).
PS_FLOOR = 1e-12


# ---------------------------------------------------------------------------------------------
# Observations


def _as_block(observations: np.ndarray) -> np.ndarray:
    """``(n, P, C)`` view of ``(n, P, C)`` or ``(n, P)`` observations (no copy)."""
    obs = np.asarray(observations)
    return obs[..., None] if obs.ndim == 2 else obs


def _scale(scale: np.ndarray | None, lights: int) -> np.ndarray:
    """Per-light divisors (n,) float64 (ones when None)."""
    if scale is None:
        return np.ones(lights)
    # a writable copy: numba compiles another version for a read-only array
    return np.array(np.broadcast_to(np.asarray(scale, np.float64), (lights,)))


# ---------------------------------------------------------------------------------------------
# The ps model: one numba kernel per block


@njit(**INLINE)
def _solve4(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, b0, b1, b2, b3):
    """Solve a symmetric positive-definite 4x4 system (upper triangle given) by Cholesky."""
    l00 = math.sqrt(a00)
    l10, l20, l30 = a01 / l00, a02 / l00, a03 / l00
    l11 = math.sqrt(a11 - l10 * l10)
    l21 = (a12 - l20 * l10) / l11
    l31 = (a13 - l30 * l10) / l11
    l22 = math.sqrt(a22 - l20 * l20 - l21 * l21)
    l32 = (a23 - l30 * l20 - l31 * l21) / l22
    l33 = math.sqrt(a33 - l30 * l30 - l31 * l31 - l32 * l32)
    z0 = b0 / l00
    z1 = (b1 - l10 * z0) / l11
    z2 = (b2 - l20 * z0 - l21 * z1) / l22
    z3 = (b3 - l30 * z0 - l31 * z1 - l32 * z2) / l33
    x3 = z3 / l33
    x2 = (z2 - l32 * x3) / l22
    x1 = (z1 - l21 * x2 - l31 * x3) / l11
    x0 = (z0 - l10 * x1 - l20 * x2 - l30 * x3) / l00
    return x0, x1, x2, x3


@njit(**INLINE)
def _visibility_start(work, weight, t, n, rho_half):
    """Lane t's facing and label rows (``_F``, ``_L``) from its ``_CNT``, ``_MEAN`` and ``_S``,
    and its weights ``weight[t]`` (the facing lights); returns the count of facing lights
    labelled shadowed (none: the fit is exactly ``w = (0, 0, 0, 1)``, the right-hand side of
    every round being the last column of its matrix)."""
    shadowed = 0
    for i in range(n):
        s = work[t, _S, i]
        facing = 1.0 if s > VIS_MARGIN else 0.0
        work[t, _F, i] = facing if work[t, _CNT, i] > 0.0 else 0.0
    for i in range(n):
        s = work[t, _S, i]
        shade = s if s > 0.0 else 0.0
        work[t, _L, i] = 1.0 if work[t, _MEAN, i] >= rho_half * shade else 0.0
    for i in range(n):
        facing = work[t, _F, i]
        weight[t, i] = facing
        shadowed += 1 if facing > work[t, _L, i] else 0
    return shadowed


@njit(**INLINE)
def _visibility_sums(tab, work, weight, t, n, sums):
    """Lane t's weighted normal equations of the visibility: ``sums[:, t]`` (14)."""
    xx = yy = zz = xy = xz = yz = sx = sy = sz = s1 = 0.0
    tx = ty = tz = t1 = 0.0
    for i in range(n):
        wi = weight[t, i]
        xx += wi * tab[_XX, i]
        yy += wi * tab[_YY, i]
        zz += wi * tab[_ZZ, i]
        xy += wi * tab[_XY, i]
        xz += wi * tab[_XZ, i]
        yz += wi * tab[_YZ, i]
        sx += wi * tab[_DX, i]
        sy += wi * tab[_DY, i]
        sz += wi * tab[_DZ, i]
        s1 += wi
        wl = wi * work[t, _L, i]
        tx += wl * tab[_DX, i]
        ty += wl * tab[_DY, i]
        tz += wl * tab[_DZ, i]
        t1 += wl
    sums[0, t], sums[1, t], sums[2, t], sums[3, t], sums[4, t] = xx, yy, zz, xy, xz
    sums[5, t], sums[6, t], sums[7, t], sums[8, t], sums[9, t] = yz, sx, sy, sz, s1
    sums[10, t], sums[11, t], sums[12, t], sums[13, t] = tx, ty, tz, t1


@njit(**INLINE)
def _visibility_settle(tab, work, weight, t, n, w0, w1, w2, w3):
    """Drop from lane t's weights the lights the clamp to [0, 1] already fits; the count of
    weights that changed."""
    changed = 0
    for i in range(n):
        value = w0 * tab[_DX, i] + w1 * tab[_DY, i] + w2 * tab[_DZ, i] + w3
        label = work[t, _L, i]
        high = 1.0 if value >= 1.0 else 0.0
        low = 1.0 if value <= 0.0 else 0.0
        keep = 1.0 - (high * label + low * (1.0 - label))
        new = work[t, _F, i] * keep
        changed += 1 if new != weight[t, i] else 0
        weight[t, i] = new
    return changed


@njit(**PART)
def _visibility_group(tabs, per_pixel, work, weight, lanes, n, fit, sums, vis_w, moved):
    """The visibility of the pixels of a group (lanes with ``fit[t]``): ``VIS_ROUNDS`` rounds of
    least squares, the lanes' 4 x 4 solves side by side; ``vis_w`` (4, LANES) written.

    A lane whose weights did not change in a round keeps its sums, and so its solution: the
    rounds left give it the same numbers, and they end when no lane moved.
    """
    ridge = VIS_RIDGE * n
    ridge1 = VIS_RIDGE_CONSTANT * n
    for t in range(LANES):
        moved[t] = 1 if t < lanes and fit[t] else 0
    for r in range(VIS_ROUNDS):
        for t in range(lanes):
            if moved[t] > 0:
                _visibility_sums(tabs[t if per_pixel else 0], work, weight, t, n, sums)
        for t in range(LANES):
            w0, w1, w2, w3 = _solve4(
                sums[0, t] + ridge, sums[3, t], sums[4, t], sums[6, t], sums[1, t] + ridge,
                sums[5, t], sums[7, t], sums[2, t] + ridge, sums[8, t], sums[9, t] + ridge1,
                sums[10, t], sums[11, t], sums[12, t], sums[13, t] + ridge1)
            vis_w[0, t], vis_w[1, t], vis_w[2, t], vis_w[3, t] = w0, w1, w2, w3
        if r == VIS_ROUNDS - 1:
            break
        total = 0
        for t in range(lanes):
            if moved[t] > 0:
                moved[t] = _visibility_settle(tabs[t if per_pixel else 0], work, weight, t, n,
                                              vis_w[0, t], vis_w[1, t], vis_w[2, t], vis_w[3, t])
                total += moved[t]
        if total == 0:
            break


@njit(**INLINE)
def _normal_equations(b, res, weight, use_weight, n, k, c0, c1, ridge, g, r, t):
    """``g[:, :, t]`` (lower triangle) ``= Σ_i ω_i b_i b_iᵀ + (ridge·tr/K + PS_FLOOR) I`` and
    ``r[:, c0:c1, t] = Σ_i b_i res[c, i]`` (``ω = weight`` where ``use_weight``, else 1)."""
    trace = 0.0
    for a in range(k):
        for a2 in range(a + 1):
            s = 0.0
            if use_weight:
                for i in range(n):
                    s += weight[i] * b[a, i] * b[a2, i]
            else:
                for i in range(n):
                    s += b[a, i] * b[a2, i]
            g[a, a2, t] = s
        trace += g[a, a, t]
        for c in range(c0, c1):
            s = 0.0
            for i in range(n):
                s += b[a, i] * res[c, i]
            r[a, c, t] = s
    shift = ridge * (trace / k) + PS_FLOOR
    for a in range(k):
        g[a, a, t] += shift


@njit(**INLINE)
def _normal_equations6(b, res, n, channels, ridge, g, r, t):
    """:func:`_normal_equations` for K = 6 (the default terms), all weights 1: the 21 products
    in one pass over the lights (11 % less time for the whole fit than 21 dot products)."""
    g00 = g10 = g11 = g20 = g21 = g22 = g30 = g31 = g32 = g33 = 0.0
    g40 = g41 = g42 = g43 = g44 = g50 = g51 = g52 = g53 = g54 = g55 = 0.0
    for i in range(n):
        b0, b1, b2, b3, b4, b5 = b[0, i], b[1, i], b[2, i], b[3, i], b[4, i], b[5, i]
        g00 += b0 * b0
        g10 += b1 * b0
        g11 += b1 * b1
        g20 += b2 * b0
        g21 += b2 * b1
        g22 += b2 * b2
        g30 += b3 * b0
        g31 += b3 * b1
        g32 += b3 * b2
        g33 += b3 * b3
        g40 += b4 * b0
        g41 += b4 * b1
        g42 += b4 * b2
        g43 += b4 * b3
        g44 += b4 * b4
        g50 += b5 * b0
        g51 += b5 * b1
        g52 += b5 * b2
        g53 += b5 * b3
        g54 += b5 * b4
        g55 += b5 * b5
    g[0, 0, t] = g00
    g[1, 0, t], g[1, 1, t] = g10, g11
    g[2, 0, t], g[2, 1, t], g[2, 2, t] = g20, g21, g22
    g[3, 0, t], g[3, 1, t], g[3, 2, t], g[3, 3, t] = g30, g31, g32, g33
    g[4, 0, t], g[4, 1, t], g[4, 2, t], g[4, 3, t], g[4, 4, t] = g40, g41, g42, g43, g44
    g[5, 0, t], g[5, 1, t], g[5, 2, t], g[5, 3, t], g[5, 4, t] = g50, g51, g52, g53, g54
    g[5, 5, t] = g55
    for c in range(channels):
        r0 = r1 = r2 = r3 = r4 = r5 = 0.0
        for i in range(n):
            x = res[c, i]
            r0 += b[0, i] * x
            r1 += b[1, i] * x
            r2 += b[2, i] * x
            r3 += b[3, i] * x
            r4 += b[4, i] * x
            r5 += b[5, i] * x
        r[0, c, t], r[1, c, t], r[2, c, t] = r0, r1, r2
        r[3, c, t], r[4, c, t], r[5, c, t] = r3, r4, r5
    shift = ridge * ((g00 + g11 + g22 + g33 + g44 + g55) / 6) + PS_FLOOR
    for a in range(6):
        g[a, a, t] += shift


@njit(**PART)
def _cholesky_lanes(g, r, k, channels, valid, d, scratch):
    """Solve ``g[:, :, t] x = r[:, :, t]`` for every lane t (SIMD across the lanes) in place.

    ``g`` (K, K, LANES) symmetric positive definite, its lower triangle given (overwritten by
    the Cholesky factor), ``r`` (K, C, LANES); ``valid[t]`` becomes 0 where a pivot is not
    positive (``r`` is then meaningless there). ``d`` (K, LANES) and ``scratch`` (LANES,) work.
    """
    for t in range(LANES):
        valid[t] = 1.0
    for j in range(k):
        for i in range(j, k):  # column j: the pivot (i == j) first, then the rows below it
            for t in range(LANES):
                scratch[t] = g[i, j, t]
            for m in range(j):
                for t in range(LANES):
                    scratch[t] -= g[i, m, t] * g[j, m, t]
            if i == j:
                for t in range(LANES):
                    pivot = scratch[t]
                    valid[t] = valid[t] if pivot > 0.0 else 0.0
                    root = math.sqrt(pivot) if pivot > 0.0 else 1.0
                    g[j, j, t] = root
                    d[j, t] = 1.0 / root
            else:
                for t in range(LANES):
                    g[i, j, t] = scratch[t] * d[j, t]
    for c in range(channels):
        for i in range(k):
            for m in range(i):
                for t in range(LANES):
                    r[i, c, t] -= g[i, m, t] * r[m, c, t]
            for t in range(LANES):
                r[i, c, t] *= d[i, t]
        for i in range(k - 1, -1, -1):
            for m in range(i + 1, k):
                for t in range(LANES):
                    r[i, c, t] -= g[m, i, t] * r[m, c, t]
            for t in range(LANES):
                r[i, c, t] *= d[i, t]


@njit(**INLINE)
def _clear_lane(g, r, k, channels, t):
    """An identity system with zero right-hand side in lane t (its solution: 0)."""
    for a in range(k):
        for a2 in range(k):
            g[a, a2, t] = 1.0 if a == a2 else 0.0
        for c in range(channels):
            r[a, c, t] = 0.0


@njit(nogil=True, cache=True, **VECTOR)
def _ps_kernel(obs, start, dirs, per_pixel, scale, normals, rho, rho_vis, kinds, params, direct,
               ridge, fit_vis, do_ps, use_vis, skip_unsolved, vis, coef):
    """The ps fit of pixels ``start .. start + q`` of ``obs`` (see :func:`_fit_ps_block`), in
    groups of ``LANES`` pixels."""
    n, total, channels = obs.shape
    flat = obs.reshape(n, total * channels)
    q = normals.shape[0]
    k = kinds.shape[0]
    kk = max(k, 1)
    need_hsh = False
    for a in range(k):
        need_hsh = need_hsh or kinds[a] == _HSH
    inv = np.empty(n)
    for i in range(n):
        inv[i] = 1.0 / scale[i]
    tabs = np.zeros((LANES if per_pixel else 1, TABLE_ROWS, n))
    work = np.zeros((LANES, WORK_ROWS, n))
    y = np.zeros((TILE, channels, n))
    ok = np.ones((LANES, channels, n))
    bad = np.zeros(LANES, np.int64)
    fit = np.zeros(LANES, np.bool_)
    solved = np.zeros(LANES, np.bool_)
    moved = np.zeros(LANES, np.int64)
    weight = np.zeros((LANES, n))
    sums = np.ones((14, LANES))
    vis_w = np.zeros((4, LANES))
    res = np.zeros((channels, n))
    b = np.zeros((kk, n))
    g = np.zeros((kk, kk, LANES))
    r = np.zeros((kk, channels, LANES))
    g1 = np.zeros((kk, kk, LANES))
    r1 = np.zeros((kk, channels, LANES))
    d = np.zeros((kk, LANES))
    valid = np.zeros(LANES)
    scratch = np.zeros(LANES)
    if not per_pixel:
        _fill_table(dirs, 0, tabs[0], need_hsh)
    for first in range(0, q, LANES):
        lanes = min(LANES, q - first)
        yo = first % TILE
        if yo == 0:
            _load_tile(flat, start + first, min(TILE, q - first), channels, inv, y, n)
        for t in range(lanes):
            j = first + t
            nx, ny, nz = normals[j, 0], normals[j, 1], normals[j, 2]
            solved[t] = math.sqrt(nx * nx + ny * ny + nz * nz) > 0.5
            fit[t] = fit_vis and (solved[t] or not skip_unsolved)
            bad[t] = 0
            if fit[t] or (do_ps and solved[t]):
                tab = tabs[t if per_pixel else 0]
                if per_pixel:
                    _fill_table(dirs, start + j, tab, need_hsh)
                bad[t] = _pixel_rows(y, yo, ok, t, tab, work, n, channels, nx, ny, nz)
        if fit_vis:
            for t in range(lanes):
                if fit[t]:
                    fit[t] = _visibility_start(work, weight, t, n,
                                               VIS_LABEL * rho_vis[first + t]) > 0
            _visibility_group(tabs, per_pixel, work, weight, lanes, n, fit, sums, vis_w, moved)
            for t in range(lanes):
                j = first + t
                if fit[t]:
                    vis[j, 0], vis[j, 1], vis[j, 2], vis[j, 3] = (
                        vis_w[0, t], vis_w[1, t], vis_w[2, t], vis_w[3, t])
                else:  # no facing light shadowed (or unsolved and skipped)
                    vis[j, 0], vis[j, 1], vis[j, 2], vis[j, 3] = 0.0, 0.0, 0.0, 1.0
        if not do_ps:
            continue
        for t in range(LANES):
            _clear_lane(g, r, kk, channels, t)
        for t in range(lanes):
            if not solved[t]:
                continue
            j = first + t
            _terms_pixel(tabs[t if per_pixel else 0], work, t, n, normals[j, 0], normals[j, 1],
                         normals[j, 2], vis[j, 0], vis[j, 1], vis[j, 2], vis[j, 3], use_vis,
                         kinds, params, direct, b)
            for c in range(channels):
                rc = rho[j, c]
                for i in range(n):
                    res[c, i] = y[yo + t, c, i] - rc * work[t, _SH, i]
            if bad[t] == 0:
                if k == 6:
                    _normal_equations6(b, res, n, channels, ridge, g, r, t)
                else:
                    _normal_equations(b, res, res[0], False, n, k, 0, channels, ridge, g, r, t)
                continue
            # missing observations: one normal matrix per channel (lane 0 of g1)
            for c in range(channels):
                for i in range(n):
                    res[c, i] *= ok[t, c, i]
            for c in range(channels):
                for t1 in range(LANES):
                    _clear_lane(g1, r1, kk, channels, t1)
                _normal_equations(b, res, ok[t, c], True, n, k, c, c + 1, ridge, g1, r1, 0)
                _cholesky_lanes(g1, r1, k, channels, valid, d, scratch)
                for a in range(k):
                    coef[j, c, a] = r1[a, c, 0] if valid[0] > 0.0 else 0.0
        _cholesky_lanes(g, r, k, channels, valid, d, scratch)
        for t in range(lanes):
            if solved[t] and bad[t] == 0:
                j = first + t
                for c in range(channels):
                    for a in range(k):
                        coef[j, c, a] = r[a, c, t] if valid[t] > 0.0 else 0.0


def _fit_ps_block(
    observations: np.ndarray,
    directions: np.ndarray,
    normals: np.ndarray,
    albedo: np.ndarray,
    *,
    start: int = 0,
    scale: np.ndarray | None = None,
    terms: tuple[str, ...] = PS_TERMS,
    ridge: float = PS_RIDGE,
    visibility: np.ndarray | None = None,
    fit_vis: bool,
    do_ps: bool,
    skip_unsolved: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Run :func:`_ps_kernel` on the ``q`` pixels ``start .. start + q`` of the observations.

    Parameters
    ----------
    observations : ndarray of shape (n, P, C) (or (n, P))
        float32 is read as is, other dtypes as float64 (copied only when not C-contiguous,
        writable and one of the two).
    directions : ndarray of shape (n, 3) or (n, P, 3)
        Light vectors (per pixel: on the observations' pixel axis).
    normals : ndarray of shape (q, 3)
    albedo : ndarray of shape (q,) or (q, C)
    start : int
        The block's first pixel in ``observations``.
    scale : ndarray of shape (n,) or None
        Each light's divisor of the observations.
    terms, ridge : as :func:`fit_ps`
    visibility : ndarray of shape (q, 4) or None
        Given visibility weights for the ps terms (unless ``fit_vis``).
    fit_vis : bool
        Fit the visibility (:func:`fit_visibility`) and use it in the ps fit.
    do_ps : bool
        Fit the ps coefficients.
    skip_unsolved : bool
        Pixels with ``|n| <= 0.5`` get the visibility ``(0, 0, 0, 1)`` without a fit.

    Returns
    -------
    coefficients : ndarray of shape (q, C, K), float32 (0 where ``|n| <= 0.5``)
    visibility : ndarray of shape (q, 4), float64

    """
    obs = _as_block(observations)
    dtype = np.float32 if obs.dtype == np.float32 else np.float64
    obs = np.require(obs, dtype, "CW")  # numba: one compiled version per dtype
    n, _, channels = obs.shape
    nrm = np.require(np.asarray(normals, np.float64).reshape(-1, 3), None, "CW")
    q = len(nrm)
    rho_in = np.asarray(albedo, np.float64)
    # writable copies (numba compiles another version for a read-only array)
    rho = np.array(np.broadcast_to(rho_in[:, None] if rho_in.ndim == 1 else rho_in,
                                   (q, channels)))
    rho_vis = np.array(rho_in.mean(axis=1) if rho_in.ndim == 2 else rho_in)
    d = np.asarray(directions, np.float64)
    per_pixel = d.ndim == 3
    dirs = np.require(d if per_pixel else d[:, None, :], None, "CW")
    # the kernel does not check its indices
    if not 0 <= start <= start + q <= obs.shape[1] or len(rho_in) != q:
        raise ValueError(f"{q} normals and {len(rho_in)} albedos for pixels {start}.. of "
                         f"{obs.shape[1]} observations")
    if dirs.shape[0] != n or dirs.shape[2] != 3 or (per_pixel and dirs.shape[1] != obs.shape[1]):
        raise ValueError(f"light directions {d.shape} for observations {obs.shape}")
    kinds, params, direct = _term_codes(tuple(terms))
    if visibility is not None and not fit_vis:
        vis = np.require(np.asarray(visibility, np.float64).reshape(q, 4), None, "CWO")
    else:
        vis = np.zeros((q, 4))
        vis[:, 3] = 1.0
    coef = np.zeros((q, channels, len(kinds)), np.float32)
    _ps_kernel(obs, int(start), dirs, bool(per_pixel), _scale(scale, n), nrm, rho, rho_vis,
               kinds, params, direct, float(ridge), bool(fit_vis), bool(do_ps),
               bool(fit_vis or visibility is not None), bool(skip_unsolved), vis, coef)
    return coef, vis
