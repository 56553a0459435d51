"""Per-pixel least-squares fits of the appearance models (pure functions on arrays).

The models and their bases are defined in :mod:`ps_lab.appearance.models`. Every fit takes the
training observations of a block of pixels in colour, ``(n, P, C)`` in the solver's units (each
channel divided by its light's intensity; the fits also take the observations as stored and the
per-light divisor ``scale``, so that no divided copy is made), and returns coefficients
``(P, C, K)``:

- ``ptm``, ``hsh2``, ``hsh3``: as the RTI tools fit them, linear least squares of every finite
  observation on the light-only basis (one pseudo-inverse shared by all pixels whose
  observations are all finite: one matrix product; per-pixel normal equations for the others),
  on the terms the lights determine (:mod:`.design`; the others 0);
- ``rbf``: the observations projected on a per-channel basis of the training lights
  (:func:`rbf_setup`: an uncentred PCA of a pixel sample, one vector per distinct light at
  most, and the Gaussian width chosen by leave-one-light-out prediction on that sample);
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

from functools import lru_cache

import numpy as np
from numba import njit

from ps_lab.appearance.models import (
    BASIS_TERMS,
    PS_TERMS,
    appearance_basis,
)

from .design import determined_terms, distinct_lights
from .choice import encode
from ._ps_kernel import (
    PS_RIDGE,
    _as_block,
    _fit_ps_block,
    _scale,
)

# Terms per channel of the rbf model's light basis (as many as HSH order 3).
RBF_TERMS = 9
# Pixels per chunk of the ps fit (no longer bounds any memory: the kernel's work arrays are
# (K + 16, n) per call; kept for the signature of fit_ps).
PS_CHUNK = 8192
_SIGMAS = np.geomspace(0.03, 1.0, 16)
#: The ridge of a pixel's least squares on its finite observations, relative to the basis' trace
#: (a pixel with too few of them gets its least-norm solution).
MASKED_RIDGE = 1e-9


# ---------------------------------------------------------------------------------------------
# Observations


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

    Only the terms the lights determine are fitted (:func:`.design.determined_terms`);
    the others are 0.

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
    full = appearance_basis(model, directions)  # (n, K)
    keep = _determined(model, np.ascontiguousarray(directions, np.float64).tobytes())
    if len(keep) < full.shape[1]:  # the terms the lights do not determine are 0
        out = np.zeros((p, c, full.shape[1]), np.float32)
        out[..., keep] = _fit_columns(full[:, keep], obs, scale)
        return out
    return _fit_columns(full, obs, scale)


@lru_cache(maxsize=16)
def _determined(model: str, directions: bytes) -> np.ndarray:
    """:func:`determined_terms`' columns of a linear model, once per set of lights (the fit
    runs block by block on the same lights)."""
    d = np.frombuffer(directions, np.float64).reshape(-1, 3)
    return determined_terms(model, d, tuple(range(BASIS_TERMS[model])))[0]


def _fit_columns(basis: np.ndarray, obs: np.ndarray, scale: np.ndarray | None) -> np.ndarray:
    """Least squares of (n, P, C) observations on a basis (n, K) of full column rank."""
    n, p, c = obs.shape
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
    out[bad] = _masked_solve(basis, obs[:, bad] / factor[:, None, None])
    return out


def _masked_solve(basis: np.ndarray, sub: np.ndarray) -> np.ndarray:
    """Per pixel and channel, least squares on the finite observations (ridge
    :data:`MASKED_RIDGE` of the basis' trace: a pixel with too few finite ones gets its
    least-norm solution).

    Parameters
    ----------
    basis : ndarray of shape (n, K)
    sub : ndarray of shape (n, q, C), NaN where missing

    Returns
    -------
    ndarray of shape (q, C, K), float64

    """
    n, k = basis.shape
    q, c = sub.shape[1:]
    good = np.isfinite(sub)
    # each pixel's Gram matrix sum_i g_i b_i b_i^T as one product with the outer products
    outer = (basis[:, :, None] * basis[:, None, :]).reshape(n, k * k)
    gram = (good.reshape(n, q * c).T.astype(np.float64) @ outer).reshape(q, c, k, k)
    gram += MASKED_RIDGE * np.trace(basis.T @ basis) * np.eye(k)
    rhs = (np.where(good, sub, 0.0).reshape(n, q * c).T @ basis).reshape(q, c, k)
    return np.linalg.solve(gram, rhs[..., None])[..., 0]


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
    complete = np.isfinite(obs).all(axis=(0, 2))
    n = obs.shape[0]
    k = min(terms, len(distinct_lights(directions)))
    # the basis from the sample's pixels with every observation (saturated ones are NaN)
    obs = obs[:, complete] if complete.sum() >= k else np.where(np.isfinite(obs), obs, 0.0)
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
    """Coefficients of the observations on the rbf basis (its orthonormal columns: a projection;
    a pixel with missing (NaN) observations: least squares on its finite ones).

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
    raw = _as_block(observations)
    n, p, c = raw.shape
    finite = _pixel_finite(raw)
    obs = raw if finite is None else np.where(np.isfinite(raw), raw, 0.0)
    factor = _scale(scale, n)
    weights = np.asarray(basis, np.float64) / factor[:, None]  # (C, n, K)
    out = np.empty((p, c, weights.shape[2]), np.float32)
    for ch in range(c):
        out[:, ch] = obs[:, :, ch].T @ weights[ch]
    if finite is not None:  # missing (saturated) observations: least squares on the others
        bad = np.flatnonzero(~finite)
        sub = raw[:, bad] / factor[:, None, None]
        for ch in range(c):
            out[bad, ch] = masked_projection(sub[..., ch], basis[ch])
    return out



def masked_projection(sub: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Per pixel, least squares on its finite observations (:func:`_masked_solve`'s systems,
    ridge :data:`MASKED_RIDGE` of the basis' trace), for a basis shared by every pixel.

    The pixel's Gram matrix is ``A - M^T M``: ``A = B^T B + r I`` less the basis rows ``M`` of
    its ``m`` missing observations. By Woodbury its solution is ``g + (A^-1 B^T)[:, miss] z``
    with ``g = A^-1 B^T y0`` (``y0``: missing as 0; one product for all pixels) and
    ``(I - H[miss, miss]) z = (B g)[miss]``, ``H = B A^-1 B^T`` (n x n, formed once): an
    ``m x m`` solve per pixel instead of ``K x K`` (:func:`_masked_kernel`).

    Parameters
    ----------
    sub : ndarray of shape (n, q), NaN where missing
    basis : ndarray of shape (n, K)

    Returns
    -------
    ndarray of shape (q, K), float64

    """
    b = np.ascontiguousarray(basis, np.float64)
    gram = b.T @ b
    inverse = np.linalg.inv(gram + MASKED_RIDGE * np.trace(gram) * np.eye(len(gram)))
    spread = np.ascontiguousarray(inverse @ b.T)  # (K, n): A^-1 B^T
    hat = np.ascontiguousarray(b @ spread)  # (n, n)
    y = np.ascontiguousarray(sub, np.float64)
    out = np.ascontiguousarray(np.where(np.isfinite(y), y, 0.0).T @ spread.T)  # g (q, K)
    _masked_kernel(y, b, hat, spread, out)
    return out


@njit(cache=True, nogil=True)
def _masked_kernel(sub, basis, hat, spread, out):  # pragma: no cover - numba
    """:func:`masked_projection`'s correction of ``out`` (``g`` on entry) per pixel.

    sub (n, q) NaN where missing; basis (n, K); hat (n, n) ``B A^-1 B^T``; spread (K, n)
    ``A^-1 B^T``; out (q, K) float64, ``g`` in, the solution out.
    """
    n, q = sub.shape
    k = basis.shape[1]
    miss = np.empty(n, np.int64)
    for p in range(q):
        m = 0
        for i in range(n):
            v = sub[i, p]
            if v != v:
                miss[m] = i
                m += 1
        if m == 0:
            continue
        s = np.empty((m, m))
        t = np.empty(m)
        for u in range(m):
            iu = miss[u]
            acc = 0.0
            for j in range(k):
                acc += basis[iu, j] * out[p, j]
            t[u] = acc
            for v2 in range(m):
                s[u, v2] = (1.0 if u == v2 else 0.0) - hat[iu, miss[v2]]
        z = np.linalg.solve(s, t)
        for u in range(m):
            iu = miss[u]
            zu = z[u]
            for j in range(k):
                out[p, j] += spread[j, iu] * zu


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
    space: str = "linear",
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
    space : {"linear", "srgb"}
        The fit space: the observations are encoded (:func:`.choice.encode`; a
        missing one stays missing) and fitted as in linear; ``bln`` and ``gp`` project on their
        basis as ``rbf`` does.

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
    if space != "linear" or model in ("bln", "gp"):
        obs = encode(obs[:, part] / _scale(scale, obs.shape[0])[:, None, None], space)
        part, scale = slice(0, obs.shape[1]), None
        if model in ("bln", "gp"):
            assert rbf_basis is not None
            return fit_rbf(obs, rbf_basis), None
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
