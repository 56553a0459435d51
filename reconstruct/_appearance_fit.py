"""Per-pixel least-squares fits of the appearance models (pure functions on arrays).

The models and their bases are defined in :mod:`ps_lab.io.appearance`. Every fit takes the
training observations of a block of pixels in colour, ``(n, P, C)`` in the solver's units (each
channel divided by its light's intensity; the fits also take the observations as stored and the
per-light divisor ``scale``, so that no divided copy is made), and returns coefficients
``(P, C, K)``:

- ``ptm``, ``hsh2``, ``hsh3``: as the RTI tools fit them, linear least squares of every finite
  observation on the light-only basis (one pseudo-inverse shared by all pixels whose
  observations are all finite: one matrix product; per-pixel normal equations for the others);
- ``rbf``: the observations projected on a per-channel basis of the training lights
  (:func:`rbf_setup`: an uncentred PCA of a pixel sample and the Gaussian width chosen by
  leave-one-light-out prediction on that sample);
- ``ps``: first the visibility ``V(l) = clamp(w·[l, 1], 0, 1)`` (:func:`fit_visibility`:
  least squares of a 0/1 label, "the pixel is lit", on the training lights that face it), then
  the residual of the visible Lambertian term, ``y − V·ρ·max(n·l, 0)``, fitted on the model's
  terms (the direct ones times ``V``) per pixel by ridge-regularised least squares (the ridge
  shrinks toward the Lambertian model, which is what extrapolation falls back on).

The ``ps`` fit is one numba kernel (:func:`_ps_kernel`, ``nogil``: blocks may run on threads)
that takes the pixels through the whole fit in groups of :data:`LANES`: it copies a tile of the
float32 (or float64) observations pixel-major as float64 (each light's run read once), fits the
visibility (four rounds of ``4 × 4`` normal equations; exactly ``w = (0, 0, 0, 1)`` where no
facing light is labelled shadowed), builds each pixel's terms as rows of a ``(K, n)`` table
(loops over the lights that the compiler vectorises), forms the ``K × K`` normal equations as
dot products over the lights, and solves the group's systems by Cholesky side by side (a pixel
with missing observations: one system per channel). The results are those of the per-pixel
formulas up to float64 rounding. See docs/appearance.md (Large captures) for the measurements.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numba import njit

from ps_lab.io.appearance import (
    BASIS_TERMS,
    PS_TERMS,
    appearance_basis,
    is_direct,
)

from ._kernels import INLINE, VECTOR

# Terms per channel of the rbf model's light basis (as many as HSH order 3).
RBF_TERMS = 9
# Ridge of the ps fit, relative to the mean diagonal of each pixel's normal matrix.
PS_RIDGE = 1e-4
# Pixels per chunk of the ps fit (no longer bounds any memory: the kernel's work arrays are
# (K + 16, n) per call; kept for the signature of fit_ps).
PS_CHUNK = 8192
_SIGMAS = np.geomspace(0.03, 1.0, 16)
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


def _pixel_finite(obs: np.ndarray) -> np.ndarray | None:
    """None when every observation is finite, else (P,) bool: the pixels with all finite.

    Parameters
    ----------
    obs : ndarray of shape (n, P, C)

    """
    good = np.isfinite(obs)
    if good.all():
        return None
    return good.all(axis=(0, 2))


# ---------------------------------------------------------------------------------------------
# Linear RTI bases and rbf


def fit_linear(
    model: str,
    observations: np.ndarray,
    directions: np.ndarray,
    scale: np.ndarray | None = None,
) -> np.ndarray:
    """PTM / HSH coefficients by least squares on every finite observation.

    A pixel whose observations are all finite gets ``pinv(B) y`` (one matrix product for all
    such pixels and channels); a pixel with missing observations the solution of its normal
    equations on the finite ones (regularised by ``1e-9`` of the basis' trace).

    Parameters
    ----------
    model : {"ptm", "hsh2", "hsh3"}
    observations : ndarray of shape (n, P, C) (or (n, P))
        Any float dtype; float32 is read as is (the product accumulates in float64).
    directions : ndarray of shape (n, 3)
        Unit training light directions.
    scale : ndarray of shape (n,) or None
        Each light's divisor of the observations (None: 1).

    Returns
    -------
    ndarray of shape (P, C, K), float32

    """
    obs = _as_block(observations)
    n, p, c = obs.shape
    basis = appearance_basis(model, directions)  # (n, K)
    k = basis.shape[1]
    factor = _scale(scale, n)
    weights = np.linalg.pinv(basis) / factor  # (K, n): the divisor folded into the product
    finite = _pixel_finite(obs)
    out = np.empty((p, c, k), np.float32)
    if finite is None:
        _project(weights, obs, out)
        return out
    _project(weights, np.where(np.isfinite(obs), obs, 0.0), out)
    # Missing observations: per-pixel normal equations on the finite ones.
    bad = ~finite
    sub = obs[:, bad] / factor[:, None, None]
    good = np.isfinite(sub)
    w = good.astype(np.float64)
    gram = np.einsum("nk,nj,npc->pckj", basis, basis, w)
    gram += 1e-9 * np.trace(basis.T @ basis) * np.eye(k)
    rhs = np.einsum("nk,npc->pck", basis, np.where(good, sub, 0.0))
    out[bad] = np.linalg.solve(gram, rhs[..., None])[..., 0]
    return out


def _project(weights: np.ndarray, obs: np.ndarray, out: np.ndarray) -> None:
    """``out[p, c, k] = Σ_i weights[k, i] obs[i, p, c]`` as one matrix product.

    Parameters
    ----------
    weights : ndarray of shape (K, n), float64
    obs : ndarray of shape (n, P, C)
    out : ndarray of shape (P, C, K), float32 (written)

    """
    n, p, c = obs.shape
    flat = obs.reshape(n, p * c)  # a view for a slice of whole pixels
    out[...] = (weights @ flat).reshape(len(weights), p, c).transpose(1, 2, 0)


def rbf_setup(
    sample: np.ndarray, directions: np.ndarray, terms: int = RBF_TERMS
) -> tuple[float, np.ndarray]:
    """The rbf model's Gaussian width and per-channel light basis, from a pixel sample.

    Parameters
    ----------
    sample : ndarray of shape (n, m, C)
        Training observations of ``m`` pixels spread over the image.
    directions : ndarray of shape (n, 3)
    terms : int
        Basis vectors per channel (at most n).

    Returns
    -------
    sigma : float
        The width among a geometric series that best predicts each training light from the
        others (normalised Gaussian weights, RelightLab's interpolation).
    basis : ndarray of shape (C, n, K), float64
        Orthonormal columns: the leading right-singular vectors of each channel's sample.

    """
    obs = np.asarray(_as_block(sample), np.float64)
    obs = np.where(np.isfinite(obs), obs, 0.0)
    n = obs.shape[0]
    k = min(terms, n)
    basis = np.stack(
        [np.linalg.svd(obs[:, :, c].T, full_matrices=False)[2][:k].T for c in range(obs.shape[2])]
    )
    d = np.asarray(directions, np.float64)
    d2 = np.sum((d[:, None] - d[None]) ** 2, axis=-1)
    best, best_err = float(_SIGMAS[0]), np.inf
    flat = obs.reshape(n, -1)
    for sigma in _SIGMAS:
        w = np.exp(-d2 / sigma**2)
        np.fill_diagonal(w, 0.0)
        total = w.sum(axis=1, keepdims=True)
        if np.any(total <= 1e-300):
            continue
        err = float(np.mean(((w / total) @ flat - flat) ** 2))
        if err < best_err:
            best, best_err = float(sigma), err
    return best, basis


def fit_rbf(
    observations: np.ndarray, basis: np.ndarray, scale: np.ndarray | None = None
) -> np.ndarray:
    """Coefficients of the observations on the rbf basis (non-finite observations count 0).

    Parameters
    ----------
    observations : ndarray of shape (n, P, C) (or (n, P))
    basis : ndarray of shape (C, n, K)
    scale : ndarray of shape (n,) or None
        Each light's divisor of the observations (None: 1).

    Returns
    -------
    ndarray of shape (P, C, K), float32

    """
    obs = _as_block(observations)
    n, p, c = obs.shape
    if _pixel_finite(obs) is not None:
        obs = np.where(np.isfinite(obs), obs, 0.0)
    weights = np.asarray(basis, np.float64) / _scale(scale, n)[:, None]  # (C, n, K)
    out = np.empty((p, c, weights.shape[2]), np.float32)
    for ch in range(c):
        out[:, ch] = obs[:, :, ch].T @ weights[ch]
    return out


# ---------------------------------------------------------------------------------------------
# The ps model: one numba kernel per block

# Term kinds of the kernel (``_term_codes``).
_LAMBERT, _AMBIENT, _LX, _LY, _LZ, _LOBE, _LOBEX, _LOBEY, _HSH = range(9)
# Rows of the kernel's light table (one column per light): the light vector as given (the
# visibility's features and ``n·l`` of the Lambertian term), normalised (the terms' ``l``), the
# half vector, the given vector's products (the visibility's normal matrix), the HSH terms.
_DX, _DY, _DZ, _UX, _UY, _UZ, _HX, _HY, _HZ = range(9)
_XX, _YY, _ZZ, _XY, _XZ, _YZ = range(9, 15)
_H0 = 15
TABLE_ROWS = 24
# Rows of the kernel's per-pixel work array (one per lane): observed channels, channel mean,
# n·l (given vector), facing (1/0), label (1/0), V, V·max(n·l, 0), n·l (unit vector),
# max(n·h, 0), step(n·l), step(n·l)·V, and a row for powers.
_CNT, _MEAN, _S, _F, _L, _V, _SH, _U, _NH, _LIT, _LV, _P = range(12)
WORK_ROWS = 12
# Pixels handled together: their solves (the visibility's 4 x 4 rounds, the K x K systems) run
# side by side, one pixel per SIMD lane.
LANES = 8
# Pixels whose observations are copied (as float64, pixel-major) at a time: (TILE, C, n) stays in
# the L2 cache.
TILE = 8 * LANES
PART = {"nogil": True, "cache": True, **VECTOR}
# Integer lobe exponents up to this are powers by repeated squaring (exact up to rounding).
_MAX_INT_POWER = 1 << 12


@lru_cache(maxsize=64)
def _term_codes(terms: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's description of ps terms: kind (K,) int64, parameter (K,) float64 (the
    exponent of a lobe, the index of an HSH term), direct (K,) bool.

    Raises
    ------
    ValueError
        An unknown term (as :func:`ps_lab.io.appearance.ps_term`).

    """
    kinds, params = [], []
    for term in terms:
        kind, param = _term_code(term)
        kinds.append(kind)
        params.append(param)
    direct = np.array([is_direct(t) for t in terms], bool)
    return np.array(kinds, np.int64), np.array(params, np.float64), direct


def _term_code(term: str) -> tuple[int, float]:
    simple = {"lambert": _LAMBERT, "ambient": _AMBIENT, "lx": _LX, "ly": _LY, "lz": _LZ}
    if term in simple:
        return simple[term], 0.0
    if term.startswith("lobe"):
        kind, _, power_text = term.partition(":")
        lobes = {"lobe": _LOBE, "lobex": _LOBEX, "lobey": _LOBEY}
        if kind in lobes:
            return lobes[kind], float(power_text)
    if term.startswith("hsh:"):
        index = int(term[4:])
        if 0 <= index < 9:
            return _HSH, float(index)
    raise ValueError(f"unknown ps term {term!r}")


@njit(**PART)
def _fill_table(dirs, col, tab, need_hsh):
    """``tab`` (TABLE_ROWS, n) from the light vectors ``dirs[:, col]`` ((n, ·, 3)).

    As :func:`ps_lab.io.appearance.ps_basis` forms them: ``l̂ = l / |l|`` (``l`` where
    ``|l| = 0``), ``h = normalise(l̂ + (0, 0, 1))``, and HSH of ``l̂``.
    """
    for i in range(dirs.shape[0]):
        x, y, z = dirs[i, col, 0], dirs[i, col, 1], dirs[i, col, 2]
        tab[_DX, i], tab[_DY, i], tab[_DZ, i] = x, y, z
        tab[_XX, i], tab[_YY, i], tab[_ZZ, i] = x * x, y * y, z * z
        tab[_XY, i], tab[_XZ, i], tab[_YZ, i] = x * y, x * z, y * z
        norm = math.sqrt(x * x + y * y + z * z)
        norm = norm if norm > 0.0 else 1.0
        ux, uy, uz = x / norm, y / norm, z / norm
        tab[_UX, i], tab[_UY, i], tab[_UZ, i] = ux, uy, uz
        hz = uz + 1.0
        half = math.sqrt(ux * ux + uy * uy + hz * hz)
        half = half if half > 0.0 else 1.0
        tab[_HX, i], tab[_HY, i], tab[_HZ, i] = ux / half, uy / half, hz / half
        if need_hsh:
            c = min(max(uz, 0.0), 1.0)
            phi = math.atan2(uy, ux)
            s = math.sqrt(max(c - c * c, 0.0))
            cp, sp = math.cos(phi), math.sin(phi)
            k = math.sqrt(30.0 / math.pi)
            tab[_H0, i] = 1.0 / math.sqrt(2.0 * math.pi)
            tab[_H0 + 1, i] = math.sqrt(6.0 / math.pi) * cp * s
            tab[_H0 + 2, i] = math.sqrt(3.0 / (2.0 * math.pi)) * (2.0 * c - 1.0)
            tab[_H0 + 3, i] = math.sqrt(6.0 / math.pi) * sp * s
            tab[_H0 + 4, i] = k * math.cos(2.0 * phi) * (c * c - c)
            tab[_H0 + 5, i] = k * cp * (2.0 * c - 1.0) * s
            tab[_H0 + 6, i] = math.sqrt(5.0 / (2.0 * math.pi)) * (6.0 * c * c - 6.0 * c + 1.0)
            tab[_H0 + 7, i] = k * sp * (2.0 * c - 1.0) * s
            tab[_H0 + 8, i] = k * math.sin(2.0 * phi) * (c * c - c)


@njit(**PART)
def _load_tile(flat, first, count, channels, inv, y, n):
    """Observations of pixels ``first .. first + count`` (columns of ``flat`` (n, P·C)) times
    ``inv`` into ``y`` (TILE, C, n) as float64.

    A pixel's observations are ``n`` values far apart in ``flat``: the copy reads eight
    lights' runs of ``count · C`` values side by side (streams the prefetcher follows) and
    writes whole cache lines of ``y``. (Views, so that every index counts from 0: numba then
    drops its negative-index handling.)
    """
    width = count * channels
    src = flat[:, first * channels:first * channels + width]
    dst = y.reshape(y.shape[0] * channels, n)
    for i0 in range(0, n, 8):
        rows = src[i0:i0 + 8]
        cols = dst[:, i0:i0 + 8]
        scale = inv[i0:i0 + 8]
        for m in range(width):
            for di in range(rows.shape[0]):
                cols[m, di] = rows[di, m] * scale[di]


@njit(**INLINE)
def _pixel_rows(y, yo, ok, t, tab, work, n, channels, nx, ny, nz):
    """Lane t's rows ``_CNT``, ``_MEAN`` (count and mean of the finite channels of pixel
    ``yo + t`` of ``y``) and ``_S`` (``n·l`` of the given light vector).

    Non-finite observations of ``y`` become 0 and ``ok[t]`` (C, n) their flags. Returns the
    count of non-finite observations (``ok[t]`` is written only when there are some).
    """
    bad = 0
    for c in range(channels):
        for i in range(n):
            bad += 0 if np.isfinite(y[yo + t, c, i]) else 1
    if bad == 0:
        for i in range(n):
            work[t, _MEAN, i] = y[yo + t, 0, i]
        for c in range(1, channels):
            for i in range(n):
                work[t, _MEAN, i] += y[yo + t, c, i]
        for i in range(n):
            work[t, _MEAN, i] = work[t, _MEAN, i] / channels
        for i in range(n):
            work[t, _CNT, i] = channels
        for i in range(n):
            work[t, _S, i] = tab[_DX, i] * nx + tab[_DY, i] * ny + tab[_DZ, i] * nz
        return 0
    for i in range(n):
        work[t, _CNT, i] = 0.0
        work[t, _MEAN, i] = 0.0
    for c in range(channels):
        for i in range(n):
            value = y[yo + t, c, i]
            finite = np.isfinite(value)
            ok[t, c, i] = 1.0 if finite else 0.0
            y[yo + t, c, i] = value if finite else 0.0
            work[t, _CNT, i] += ok[t, c, i]
            work[t, _MEAN, i] += y[yo + t, c, i]
    for i in range(n):
        count = work[t, _CNT, i]
        work[t, _MEAN, i] = work[t, _MEAN, i] / (count if count > 1.0 else 1.0)
        work[t, _S, i] = tab[_DX, i] * nx + tab[_DY, i] * ny + tab[_DZ, i] * nz
    return bad


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
def _power_row(work, t, n, exponent, out, k):
    """``out[k, i] = work[t, _NH, i] ** exponent`` (integers by repeated squaring; row ``_P``
    is overwritten)."""
    e = int(exponent) if 0.0 <= exponent <= _MAX_INT_POWER else -1
    if e < 0 or e != exponent:
        for i in range(n):
            out[k, i] = work[t, _NH, i] ** exponent
        return
    if e == 0:
        for i in range(n):
            out[k, i] = 1.0
        return
    for i in range(n):
        work[t, _P, i] = work[t, _NH, i]
    first = True
    while True:
        if e & 1:
            if first:
                for i in range(n):
                    out[k, i] = work[t, _P, i]
                first = False
            else:
                for i in range(n):
                    out[k, i] *= work[t, _P, i]
        e >>= 1
        if e == 0:
            break
        for i in range(n):
            work[t, _P, i] *= work[t, _P, i]


@njit(**PART)
def _terms_pixel(tab, work, t, n, nx, ny, nz, v0, v1, v2, v3, use_vis, kinds, params, direct,
                 b):
    """Lane t's terms ``b`` (K, n) and its rows ``_U``, ``_NH``, ``_LIT``, ``_LV``, ``_V``,
    ``_SH`` (``_S``, the given vector's ``n·l``, already there)."""
    # one row per loop: the loops vectorise
    for i in range(n):
        work[t, _U, i] = tab[_UX, i] * nx + tab[_UY, i] * ny + tab[_UZ, i] * nz
    for i in range(n):
        nh = tab[_HX, i] * nx + tab[_HY, i] * ny + tab[_HZ, i] * nz
        work[t, _NH, i] = nh if nh > 0.0 else 0.0
    for i in range(n):
        work[t, _LIT, i] = 1.0 if work[t, _U, i] > 0.0 else 0.0
    if use_vis:
        for i in range(n):
            v = tab[_UX, i] * v0 + tab[_UY, i] * v1 + tab[_UZ, i] * v2 + v3
            work[t, _V, i] = min(max(v, 0.0), 1.0)
    else:
        for i in range(n):
            work[t, _V, i] = 1.0
    for i in range(n):
        work[t, _LV, i] = work[t, _LIT, i] * work[t, _V, i]
    for i in range(n):
        s = work[t, _S, i]
        work[t, _SH, i] = (s if s > 0.0 else 0.0) * work[t, _V, i]
    for k in range(kinds.shape[0]):
        kind = kinds[k]
        gated = use_vis and direct[k]
        gate = _LV if gated else _LIT
        if kind == _LAMBERT:
            for i in range(n):
                u = work[t, _U, i]
                b[k, i] = u if u > 0.0 else 0.0
        elif kind == _AMBIENT:
            for i in range(n):
                b[k, i] = 1.0
        elif kind == _LX or kind == _LY or kind == _LZ:
            row = _UX + (kind - _LX)
            for i in range(n):
                b[k, i] = tab[row, i] * work[t, gate, i]
            gated = False
        elif kind == _LOBE:
            _power_row(work, t, n, params[k], b, k)
            for i in range(n):
                b[k, i] *= work[t, gate, i]
            gated = False
        elif kind == _LOBEX or kind == _LOBEY:
            _power_row(work, t, n, params[k] - 1.0, b, k)
            row = _HX + (kind - _LOBEX)
            for i in range(n):
                b[k, i] = b[k, i] * tab[row, i] * work[t, gate, i]
            gated = False
        else:  # _HSH
            row = _H0 + int(params[k])
            for i in range(n):
                b[k, i] = tab[row, i]
        if gated:
            for i in range(n):
                b[k, i] *= work[t, _V, i]


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
        for t in range(LANES):
            scratch[t] = g[j, j, t]
        for m in range(j):
            for t in range(LANES):
                scratch[t] -= g[j, m, t] * g[j, m, t]
        for t in range(LANES):
            pivot = scratch[t]
            valid[t] = valid[t] if pivot > 0.0 else 0.0
            root = math.sqrt(pivot) if pivot > 0.0 else 1.0
            g[j, j, t] = root
            d[j, t] = 1.0 / root
        for i in range(j + 1, k):
            for t in range(LANES):
                scratch[t] = g[i, j, t]
            for m in range(j):
                for t in range(LANES):
                    scratch[t] -= g[i, m, t] * g[j, m, t]
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


def fit_visibility(
    observations: np.ndarray,
    directions: np.ndarray,
    normals: np.ndarray,
    albedo: np.ndarray,
) -> np.ndarray:
    """The ps model's visibility weights per pixel (cast shadows).

    Each training light that faces the pixel (``n·l > VIS_MARGIN``) is labelled lit (1) when
    the channel-mean observation is at least ``VIS_LABEL`` of the Lambertian prediction
    ``ρ·max(n·l, 0)``, else shadowed (0); ``w`` is the least-squares fit of the labels by
    ``w·[l, 1]``, ridge toward ``(0, 0, 0, 1)`` (no shadow), refitted ``VIS_ROUNDS`` times
    without the lights the clamp to [0, 1] already fits. One pass of :func:`_ps_kernel`.

    Parameters
    ----------
    observations : ndarray of shape (n, P, C) (or (n, P))
    directions : ndarray of shape (n, 3) or (n, P, 3)
    normals : ndarray of shape (P, 3)
    albedo : ndarray of shape (P,) or (P, C)

    Returns
    -------
    ndarray of shape (P, 4), float64: ``V(l) = clamp(w·[l, 1], 0, 1)``

    """
    _, vis = _fit_ps_block(observations, directions, normals, albedo, fit_vis=True, do_ps=False)
    return vis


def fit_ps(
    observations: np.ndarray,
    directions: np.ndarray,
    normals: np.ndarray,
    albedo: np.ndarray,
    terms: tuple[str, ...] = PS_TERMS,
    ridge: float = PS_RIDGE,
    chunk: int = PS_CHUNK,
    visibility: np.ndarray | None = None,
) -> np.ndarray:
    """The ps model's coefficients: ridge least squares of the visible Lambertian residual.

    Per pixel and channel, ``x`` solves ``(BᵀB + (ridge·tr(BᵀB)/K + 1e-12) I) x = Bᵀ r`` with
    ``B`` (n, K) the pixel's terms at the lights with a finite observation (the direct ones
    times ``V``) and ``r = y − V·ρ·max(n·l, 0)`` (Cholesky; 0 where the matrix is not
    numerically positive definite, possible only with ``ridge = 0``).

    Parameters
    ----------
    observations : ndarray of shape (n, P, C) (or (n, P))
    directions : ndarray of shape (n, 3) or (n, P, 3)
        Unit training light directions (per pixel for near lights).
    normals : ndarray of shape (P, 3)
        The solver's unit normals (zero where unsolved: coefficients 0 there).
    albedo : ndarray of shape (P,) or (P, C)
    terms : tuple of str
    ridge : float
        Relative to the mean diagonal of each pixel's normal matrix.
    chunk : int
        Unused (the kernel works pixel by pixel); kept for compatibility.
    visibility : ndarray of shape (P, 4) or None
        :func:`fit_visibility`'s weights (None: V = 1).

    Returns
    -------
    ndarray of shape (P, C, K), float32

    """
    coef, _ = _fit_ps_block(observations, directions, normals, albedo, terms=terms, ridge=ridge,
                            visibility=visibility, fit_vis=False, do_ps=True)
    return coef


def fit_block(
    model: str,
    observations: np.ndarray,
    directions: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    rbf_basis: np.ndarray | None = None,
    terms: tuple[str, ...] = PS_TERMS,
    pixels: slice | None = None,
    scale: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Fit ``model`` on one block of pixels.

    Parameters
    ----------
    model : str
    observations : ndarray of shape (n, P, C) (or (n, P))
        As stored (float32 is not copied).
    directions : ndarray of shape (n, 3) (or (n, P, 3) for ``ps``)
    normals : ndarray of shape (q, 3) or None
        The block's normals (``ps``).
    albedo : ndarray of shape (q,) or (q, C) or None
        The block's albedo (``ps``).
    rbf_basis : ndarray of shape (C, n, K) or None
    terms : tuple of str
        The ps terms.
    pixels : slice or None
        The block: the consecutive pixels ``pixels`` of the observations (None: all,
        ``q = P``).
    scale : ndarray of shape (n,) or None
        Each light's divisor of the observations (None: 1).

    Returns
    -------
    coefficients : ndarray of shape (q, C, K), float32
    visibility : ndarray of shape (q, 4), float32, or None
        The ps model's visibility weights (None for the other models).

    """
    obs = _as_block(observations)
    part = slice(0, obs.shape[1]) if pixels is None else slice(*pixels.indices(obs.shape[1]))
    if part.step not in (None, 1):
        raise ValueError(f"a block is a run of consecutive pixels, not {pixels}")
    if model in BASIS_TERMS:
        return fit_linear(model, obs[:, part], directions, scale), None
    if model == "rbf":
        assert rbf_basis is not None
        return fit_rbf(obs[:, part], rbf_basis, scale), None
    if model == "ps":
        assert normals is not None and albedo is not None
        if obs.dtype not in (np.float32, np.float64) or not obs.flags.c_contiguous:
            obs = np.ascontiguousarray(obs[:, part], np.float64)
            d = np.asarray(directions)
            directions = d[:, part] if d.ndim == 3 else d
            part = slice(0, obs.shape[1])
        coeffs, vis = _fit_ps_block(obs, directions, normals, albedo, start=part.start,
                                    scale=scale, terms=terms, fit_vis=True, do_ps=True,
                                    skip_unsolved=True)
        return coeffs, vis.astype(np.float32)
    raise ValueError(f"no fit for appearance model {model!r}")
