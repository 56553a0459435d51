"""Per-pixel least-squares fits of the appearance models (pure functions on arrays).

The models and their bases are defined in :mod:`ps_lab.io.appearance`. Every fit takes the
training observations of a block of pixels in colour, ``(n, P, C)`` in the solver's units (each
channel divided by its light's intensity), and returns coefficients ``(P, C, K)``:

- ``ptm``, ``hsh2``, ``hsh3``: as the RTI tools fit them, linear least squares of every finite
  observation on the light-only basis (one pseudo-inverse shared by all pixels);
- ``rbf``: the observations projected on a per-channel basis of the training lights
  (:func:`rbf_setup`: an uncentred PCA of a pixel sample and the Gaussian width chosen by
  leave-one-light-out prediction on that sample);
- ``ps``: first the visibility ``V(l) = clamp(w·[l, 1], 0, 1)`` (:func:`fit_visibility`:
  least squares of a 0/1 label, "the pixel is lit", on the training lights that face it), then
  the residual of the visible Lambertian term, ``y − V·ρ·max(n·l, 0)``, fitted on the model's
  terms (the direct ones times ``V``) per pixel by ridge-regularised least squares (the ridge
  shrinks toward the Lambertian model, which is what extrapolation falls back on).

Every fit is vectorised over the pixels of a block: normal equations ``(P, K, K)`` by batched
products, one solve per pixel for all channels.
"""

from __future__ import annotations

import numpy as np

from ps_lab.io.appearance import (
    BASIS_TERMS,
    PS_TERMS,
    appearance_basis,
    is_direct,
    ps_basis,
    ps_visibility,
    rbf_weights,
)

# Terms per channel of the rbf model's light basis (as many as HSH order 3).
RBF_TERMS = 9
# Ridge of the ps fit, relative to the mean diagonal of each pixel's normal matrix.
PS_RIDGE = 1e-4
# Pixels per chunk of the ps fit (bounds its (n, chunk, K) float64 basis).
PS_CHUNK = 8192
_SIGMAS = np.geomspace(0.03, 1.0, 16)
# Visibility: a training light shadows the pixel when the pixel is below this fraction of its
# Lambertian prediction; only lights with n·l above VIS_MARGIN carry evidence (near the
# terminator the ratio is noise); ridge toward V = 1 (relative to the lights' count).
VIS_LABEL = 0.5
VIS_MARGIN = 0.1
VIS_RIDGE = 1e-3
VIS_ROUNDS = 4


def _finite(observations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    obs = np.asarray(observations, np.float64)
    if obs.ndim == 2:
        obs = obs[..., None]
    good = np.isfinite(obs)
    return np.where(good, obs, 0.0), good


def fit_linear(model: str, observations: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """PTM / HSH coefficients by least squares on every finite observation.

    Parameters
    ----------
    model : {"ptm", "hsh2", "hsh3"}
    observations : ndarray of shape (n, P, C) (or (n, P))
    directions : ndarray of shape (n, 3)
        Unit training light directions.

    Returns
    -------
    ndarray of shape (P, C, K), float32

    """
    obs, good = _finite(observations)
    basis = appearance_basis(model, directions)  # (n, K)
    if good.all():
        return np.einsum("kn,npc->pck", np.linalg.pinv(basis), obs).astype(np.float32)
    # Missing observations: per-pixel normal equations on the finite ones.
    w = good.astype(np.float64)
    gram = np.einsum("nk,nj,npc->pckj", basis, basis, w)
    gram += 1e-9 * np.trace(basis.T @ basis) * np.eye(basis.shape[1])
    rhs = np.einsum("nk,npc->pck", basis, obs * w)
    return np.linalg.solve(gram, rhs[..., None])[..., 0].astype(np.float32)


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
    obs, _ = _finite(sample)
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


def fit_rbf(observations: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Coefficients of the observations on the rbf basis ``(C, n, K)``; returns (P, C, K)."""
    obs, _ = _finite(observations)
    return np.einsum("cnk,npc->pck", basis, obs).astype(np.float32)


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
    without the lights the clamp to [0, 1] already fits. Vectorised over pixels.

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
    obs = np.asarray(observations, np.float64)
    obs = obs[..., None] if obs.ndim == 2 else obs
    n, p, _ = obs.shape
    good = np.isfinite(obs)
    # Pixel-major (P, n) layout: the per-pixel sums over lights below are matrix products (and
    # so is the channel sum: a reduction over a short last axis is slow).
    ones = np.ones(obs.shape[2])
    if good.all():
        count = np.full((n, p), float(obs.shape[2]))
        total = obs @ ones
    else:
        count = good.astype(np.float64) @ ones
        total = np.where(good, obs, 0.0) @ ones
    mean = (total / np.maximum(count, 1.0)).T
    seen = (count > 0).T
    d = np.asarray(directions, np.float64)
    rho = np.asarray(albedo, np.float64)
    rho = rho.mean(axis=1) if rho.ndim == 2 else rho
    if d.ndim == 2:
        shade = np.asarray(normals, np.float64) @ d.T  # (P, n)
        features = np.concatenate([d, np.ones((n, 1))], axis=1)  # (n, 4)
        outer = (features[:, :, None] * features[:, None, :]).reshape(n, 16)
    else:
        shade = np.einsum("npk,pk->pn", d, np.asarray(normals, np.float64))
        features = np.concatenate([d, np.ones((n, p, 1))], axis=2)  # (n, P, 4)
    facing = (shade > VIS_MARGIN) & seen
    label = (mean >= VIS_LABEL * rho[:, None] * np.maximum(shade, 0.0)).astype(np.float64)
    ridge = np.diag([VIS_RIDGE] * 3 + [1e-6]) * n
    prior = ridge @ np.array([0.0, 0.0, 0.0, 1.0])
    weight = facing.astype(np.float64)
    w = np.tile([0.0, 0.0, 0.0, 1.0], (p, 1))
    for _ in range(VIS_ROUNDS):
        if d.ndim == 2:
            gram = (weight @ outer).reshape(p, 4, 4)
            rhs = (weight * label) @ features
        else:
            gram = np.einsum("pn,npi,npj->pij", weight, features, features)
            rhs = np.einsum("pn,npi->pi", weight * label, features)
        w = np.linalg.solve(gram + ridge, (rhs + prior)[..., None])[..., 0]
        value = w @ features.T if d.ndim == 2 else np.einsum("npi,pi->pn", features, w)
        settled = ((value >= 1) & (label == 1)) | ((value <= 0) & (label == 0))
        weight = (facing & ~settled).astype(np.float64)
    return w


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
        Pixels per block.
    visibility : ndarray of shape (P, 4) or None
        :func:`fit_visibility`'s weights (None: V = 1).

    Returns
    -------
    ndarray of shape (P, C, K), float32

    """
    obs, good = _finite(observations)
    n, p, c = obs.shape
    normals = np.asarray(normals, np.float64)
    rho = np.asarray(albedo, np.float64)
    rho = np.broadcast_to(rho[:, None] if rho.ndim == 1 else rho, (p, c))
    d = np.asarray(directions, np.float64)
    k = len(terms)
    out = np.zeros((p, c, k), np.float32)
    solved = np.linalg.norm(normals, axis=1) > 0.5
    direct = np.array([is_direct(t) for t in terms])
    eye = np.eye(k)
    for start in range(0, p, chunk):
        part = slice(start, min(start + chunk, p))
        nrm = normals[part]
        dd = d if d.ndim == 2 else d[:, part]
        planes = np.moveaxis(ps_basis(dd, nrm, terms), -1, 0)  # (K, n, q), contiguous
        shade = dd @ nrm.T if dd.ndim == 2 else np.einsum("nqk,qk->nq", dd, nrm)
        shade = np.maximum(shade, 0.0)
        if visibility is not None:
            v = ps_visibility(dd, visibility[part])  # (n, q)
            shade *= v
            planes[direct] *= v
        residual = obs[:, part] - rho[part][None] * shade[..., None]  # (n, q, C)
        w = good[:, part]
        if w.all():
            bt = np.ascontiguousarray(planes.transpose(2, 0, 1))  # (q, K, n)
            gram = np.matmul(bt, bt.transpose(0, 2, 1))  # (q, K, K)
            rhs = np.matmul(bt, residual.transpose(1, 0, 2))  # (q, K, C)
            scale = np.trace(gram, axis1=1, axis2=2)[:, None, None] / k
            x = np.linalg.solve(gram + (ridge * scale + 1e-12) * eye, rhs).transpose(0, 2, 1)
        else:
            bt = planes.transpose(2, 0, 1)  # (q, K, n)
            wt = w.astype(np.float64).transpose(1, 2, 0)[..., None, :]  # (q, C, 1, n)
            gram = np.matmul(bt[:, None] * wt, bt.transpose(0, 2, 1)[:, None])  # (q, C, K, K)
            rhs = np.matmul(bt, (residual * w).transpose(1, 0, 2)).transpose(0, 2, 1)
            scale = np.trace(gram, axis1=2, axis2=3)[..., None, None] / k
            x = np.linalg.solve(gram + (ridge * scale + 1e-12) * eye, rhs[..., None])[..., 0]
        x[~solved[part]] = 0.0
        out[part] = x
    return out


def fit_block(
    model: str,
    observations: np.ndarray,
    directions: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    rbf_basis: np.ndarray | None = None,
    terms: tuple[str, ...] = PS_TERMS,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Fit ``model`` on one block of pixels.

    Returns
    -------
    coefficients : ndarray of shape (P, C, K), float32
    visibility : ndarray of shape (P, 4), float32, or None
        The ps model's visibility weights (None for the other models).

    """
    if model in BASIS_TERMS:
        return fit_linear(model, observations, directions), None
    if model == "rbf":
        assert rbf_basis is not None
        return fit_rbf(observations, rbf_basis), None
    if model == "ps":
        assert normals is not None and albedo is not None
        normals = np.asarray(normals, np.float64)
        solved = np.linalg.norm(normals, axis=1) > 0.5
        d = np.asarray(directions)
        obs = np.asarray(observations)
        rho = np.asarray(albedo)
        vis = np.concatenate([  # in blocks: the (P, n) work arrays stay in cache
            fit_visibility(obs[:, part], d if d.ndim == 2 else d[:, part], normals[part],
                           rho[part])
            for part in (slice(s, s + PS_CHUNK) for s in range(0, len(normals), PS_CHUNK))
        ]) if len(normals) else np.zeros((0, 4))
        vis[~solved] = (0.0, 0.0, 0.0, 1.0)
        coeffs = fit_ps(observations, directions, normals, albedo, terms, visibility=vis)
        return coeffs, vis.astype(np.float32)
    raise ValueError(f"no fit for appearance model {model!r}")
