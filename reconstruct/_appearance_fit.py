"""Per-pixel least-squares fits of the appearance models (pure functions on arrays).

The models and their bases are defined in :mod:`ps_lab.io.appearance`. Every fit takes the
training observations of a block of pixels in colour, ``(n, P, C)`` in the solver's units (each
channel divided by its light's intensity), and returns coefficients ``(P, C, K)``:

- ``ptm``, ``hsh2``, ``hsh3``: as the RTI tools fit them, linear least squares of every finite
  observation on the light-only basis (one pseudo-inverse shared by all pixels);
- ``rbf``: the observations projected on a per-channel basis of the training lights
  (:func:`rbf_setup`: an uncentred PCA of a pixel sample and the Gaussian width chosen by
  leave-one-light-out prediction on that sample);
- ``ps``: the residual of the solver's Lambertian term, ``y − ρ·max(n·l, 0)``, fitted on the
  model's terms per pixel by ridge-regularised least squares (the ridge shrinks toward the
  Lambertian model, which is what extrapolation falls back on).
"""

from __future__ import annotations

import numpy as np

from ps_lab.io.appearance import (
    BASIS_TERMS,
    PS_TERMS,
    appearance_basis,
    ps_basis,
    rbf_weights,
)

# Terms per channel of the rbf model's light basis (as many as HSH order 3).
RBF_TERMS = 9
# Ridge of the ps fit, relative to the mean diagonal of each pixel's normal matrix.
PS_RIDGE = 1e-4
# Pixels per chunk of the ps fit (bounds its (n, chunk, K) float64 basis).
PS_CHUNK = 8192
_SIGMAS = np.geomspace(0.03, 1.0, 16)


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


def fit_ps(
    observations: np.ndarray,
    directions: np.ndarray,
    normals: np.ndarray,
    albedo: np.ndarray,
    terms: tuple[str, ...] = PS_TERMS,
    ridge: float = PS_RIDGE,
    chunk: int = PS_CHUNK,
) -> np.ndarray:
    """The ps model's coefficients: ridge least squares of the Lambertian residual.

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
    eye = np.eye(k)
    for start in range(0, p, chunk):
        part = slice(start, min(start + chunk, p))
        nrm = normals[part]
        dd = d if d.ndim == 2 else d[:, part]
        basis = ps_basis(dd, nrm, terms)  # (n, q, K)
        shade = np.maximum(np.einsum("nqk,qk->nq", dd if dd.ndim == 3 else
                                     np.broadcast_to(dd[:, None], (n, nrm.shape[0], 3)), nrm), 0)
        residual = obs[:, part] - rho[part][None] * shade[..., None]
        bt = basis.transpose(1, 2, 0)  # (q, K, n)
        w = good[:, part]
        if w.all():
            gram = np.matmul(bt, basis.transpose(1, 0, 2))[:, None]  # (q, 1, K, K)
        else:
            wt = w.astype(np.float64).transpose(1, 2, 0)[..., None, :]  # (q, C, 1, n)
            gram = np.matmul(bt[:, None] * wt, basis.transpose(1, 0, 2)[:, None])
            residual = residual * w
        rhs = np.matmul(bt, residual.transpose(1, 0, 2)).transpose(0, 2, 1)  # (q, C, K)
        scale = np.trace(gram, axis1=2, axis2=3)[..., None, None] / k
        gram = gram + (ridge * scale + 1e-12) * eye
        x = np.linalg.solve(np.broadcast_to(gram, (gram.shape[0], c, k, k)), rhs[..., None])[..., 0]
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
) -> np.ndarray:
    """Fit ``model`` on one block of pixels; returns coefficients (P, C, K) float32."""
    if model in BASIS_TERMS:
        return fit_linear(model, observations, directions)
    if model == "rbf":
        assert rbf_basis is not None
        return fit_rbf(observations, rbf_basis)
    if model == "ps":
        assert normals is not None and albedo is not None
        return fit_ps(observations, directions, normals, albedo, terms)
    raise ValueError(f"no fit for appearance model {model!r}")
