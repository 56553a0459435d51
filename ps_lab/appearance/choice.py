"""The appearance model chosen by cross-validation over the lights (``--appearance auto``).

Every candidate (``ptm``, ``hsh2``, ``hsh3``, ``rbf``, ``bln``, ``gp`` with their parameters, each
fitted in linear light or on sRGB-encoded values) is a *linear smoother* over the training lights:
its prediction of a pixel under light ``l`` is ``w(l)ᵀ y``, the weights depending on the lights
only. Its leave-one-light-out predictions are therefore one ``(n, n)`` matrix ``W`` applied to
every pixel (:func:`loo_weights`), in closed form where the model is a least-squares fit:

- ``ptm``/``hsh``: with the hat matrix ``H = X (XᵀX)⁻¹ Xᵀ``, the held-out residual is
  ``e_i / (1 − H_ii)``, so ``W = I − diag(1 − H_ii)⁻¹ (I − H)``;
- ``gp`` (penalised least squares, fixed ``σ`` and ``λ``): with ``A`` the top-left ``n × n`` block
  of the inverse system matrix (:func:`ps_lab.appearance.smoothers.gp_solve`), the fit is
  ``ŷ = y − λAy`` and the held-out residual ``(Ay)_i / A_ii``, so ``W = I − diag(A_ii)⁻¹ A``;
- ``rbf``: the normalised Gaussian weights with the light's own weight removed;
- ``bln``: its weights recomputed without each light in turn (``n`` small matrices).

``ps`` (when the normals and albedo are given) is not a smoother: it is scored by refitting it
``PS_FOLDS`` times on the sample, each time without every ``PS_FOLDS``-th light, predicting those
(the normals stay those solved on all the given lights).

The score of a candidate is the judged metric itself on a pixel sample: each training light's
leave-one-out prediction (decoded to linear light when fitted on sRGB values, clipped to [0, 1])
reduced to grey (the channel mean), sRGB-encoded, PSNR against the observation (peak 255), mean
over the lights (each light's PSNR capped at :data:`SCORE_CAP`). The choice
(:func:`choose_model`) is the first candidate of highest score; it only
ever sees the lights it is given (the training lights of a fold when benchmarking).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ps_lab.appearance.models import BASIS_TERMS, appearance_basis
from ps_lab.appearance.smoothers import (
    bln_weights,
    gaussian_weights,
    gp_solve,
    gp_weights,
    grid_nodes,
)
from ps_lab.errors import DatasetError
from ps_lab.io.encoding import linear_to_srgb, srgb_to_linear

__all__ = [
    "AUTO_MODELS",
    "CHOSEN_MODELS",
    "Choice",
    "SMOOTH_TERMS",
    "candidates",
    "choose_model",
    "encode",
    "grey_srgb",
    "psnr_per_light",
    "complete_pixels",
    "loo_weights",
    "predict_weights",
    "resolve_model",
    "smoother_setup",
]

#: Models the automatic choice considers.
AUTO_MODELS = ("ptm", "hsh3", "rbf", "bln", "gp")
#: Basis vectors per channel stored for an interpolating model chosen here (uncentred PCA).
SMOOTH_TERMS = 24
#: Pixels of the sample that score the candidates (evenly spread over it).
CHOICE_PIXELS = 2048
#: A light whose leverage is within this of 1 is fitted by its own term: the model's
#: leave-one-out prediction of it is undefined (and its closed form divides by ~0).
LEVERAGE_MARGIN = 1e-6
#: Per-light scores are capped here (dB): beyond it two exact candidates differ by rounding only
#: (e.g. ``ptm`` and a strongly ridged ``gp`` with its PTM mean on noise-free PTM data), and the
#: tie keeps the earlier, simpler candidate.
SCORE_CAP = 100.0
_GRIDS: dict[str, list[dict[str, Any]]] = {
    "ptm": [{}],
    "hsh2": [{}],
    "hsh3": [{}],
    "rbf": [{"sigma": float(s)} for s in np.geomspace(0.06, 0.6, 6)],
    "bln": [{"sigma": float(s), "resolution": r} for s in np.geomspace(0.08, 0.4, 4)
            for r in (8, 16)],
    # issue 38: the wider gp grid (σ 0.1-2, λ up to 3) gained +0.06 / +0.46 / +0.29 dB held out
    # on item1 / item3 / item9 over σ × 5 (0.15-1.2) × λ × 3 (docs/results.md)
    "gp": [{"sigma": float(s), "ridge": lam} for s in np.geomspace(0.1, 2.0, 9)
           for lam in (1e-3, 1e-2, 3e-2, 1e-1, 0.3, 1.0, 3.0)],
}


@dataclass
class Choice:
    """The chosen candidate and every candidate's score (dB)."""

    model: str
    space: str
    params: dict[str, Any]
    score: float
    table: list[dict[str, Any]] = field(default_factory=list)


def candidates(model: str) -> list[dict[str, Any]]:
    """The parameter grid of ``model`` (a list of parameter dicts)."""
    return [dict(p) for p in _GRIDS[model]]


def encode(observations: np.ndarray, space: str) -> np.ndarray:
    """Observations in the fit space: as given or sRGB-encoded (clipped); a missing (NaN)
    observation stays missing."""
    obs = np.asarray(observations, np.float64)
    return linear_to_srgb(obs) if space == "srgb" else obs


def complete_pixels(sample: np.ndarray, least: int = 64) -> np.ndarray:
    """Indices of the sample's pixels with every observation (saturated ones are NaN: dropped by
    every model), or all pixels when fewer than ``least`` (or a quarter) are complete.

    Parameters
    ----------
    sample : ndarray of shape (n, m, C)

    """
    complete = np.isfinite(sample).all(axis=(0, 2))
    m = sample.shape[1]
    if complete.sum() >= min(m, max(least, m // 4)):
        return np.flatnonzero(complete)
    return np.arange(m)


def _decode(values: np.ndarray, space: str) -> np.ndarray:
    v = np.clip(values, 0.0, 1.0)
    return srgb_to_linear(v).astype(np.float64) if space == "srgb" else v


def predict_weights(model: str, params: dict, lights: np.ndarray,
                    directions: np.ndarray) -> np.ndarray:
    """Weights (m, n) of ``model`` fitted on ``lights`` (n, 3) at ``directions`` (m, 3)."""
    if model in BASIS_TERMS:
        return appearance_basis(model, directions) @ np.linalg.pinv(
            appearance_basis(model, lights))
    if model == "rbf":
        return gaussian_weights(directions, lights, params["sigma"])
    if model == "bln":
        return bln_weights(directions, lights, params["sigma"], params["resolution"])
    if model == "gp":
        return gp_weights(directions, lights, params["sigma"],
                          gp_solve(lights, params["sigma"], params["ridge"]))
    raise ValueError(f"no interpolating weights for {model!r}")


def loo_weights(model: str, params: dict, lights: np.ndarray) -> np.ndarray:
    """Leave-one-light-out prediction matrix (n, n): row ``i`` predicts light ``i`` from the
    others (zero diagonal up to rounding); None where the model fitted without a light cannot
    predict it (a linear basis with as many terms as lights: leverage 1)."""
    lights = np.asarray(lights, np.float64)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    n = len(lights)
    eye = np.eye(n)
    if model in BASIS_TERMS:
        x = appearance_basis(model, lights)
        hat = x @ np.linalg.pinv(x)
        if np.any(np.diag(hat) > 1.0 - LEVERAGE_MARGIN):
            return None  # a light only its own term fits: no prediction of it from the others
        return eye - (eye - hat) / (1.0 - np.diag(hat))[:, None]
    if model == "gp":
        sigma, ridge = params["sigma"], params["ridge"]
        kernel = np.exp(-np.sum((lights[:, None] - lights[None]) ** 2, -1) / sigma**2)
        mean = appearance_basis("ptm", lights)
        m = mean.shape[1]
        system = np.block([[kernel + ridge * eye, mean], [mean.T, np.zeros((m, m))]])
        a = np.linalg.pinv(system)[:n, :n]
        if n <= m or np.any(np.abs(np.diag(a)) <= LEVERAGE_MARGIN * np.abs(a).max()):
            return None  # the PTM trend interpolates the lights (n <= its 6 terms)
        return eye - a / np.diag(a)[:, None]
    if model == "rbf":
        d2 = np.sum((lights[:, None] - lights[None]) ** 2, -1) / params["sigma"] ** 2
        np.fill_diagonal(d2, np.inf)
        w = np.exp(-(d2 - d2.min(axis=1, keepdims=True)))
        return w / w.sum(axis=1, keepdims=True)
    if model == "bln":
        return _bln_loo(lights, params["sigma"], params["resolution"])
    raise ValueError(f"no leave-one-out weights for {model!r}")


def _bln_loo(lights: np.ndarray, sigma: float, resolution: int) -> np.ndarray:
    """``bln``'s leave-one-out weights: a node's normalised Gaussian weights without light
    ``i`` are its weights with ``i``'s set to 0, divided by ``1 − w_i``."""
    n, r = len(lights), int(resolution)
    nodes = gaussian_weights(grid_nodes(r), lights, sigma)  # (r·r, n)
    g = np.clip((lights[:, :2] + 1.0) / 2.0 * (r - 1), 0.0, r - 1 - 1e-9)
    i0 = np.floor(g).astype(np.int64)
    t = g - i0
    out = np.zeros((n, n))
    rows = np.arange(n)
    for dy in (0, 1):
        for dx in (0, 1):
            wt = (t[:, 0] if dx else 1.0 - t[:, 0]) * (t[:, 1] if dy else 1.0 - t[:, 1])
            w = nodes[(i0[:, 1] + dy) * r + i0[:, 0] + dx].copy()  # (n, n): row i's node
            own = w[rows, rows]
            w[rows, rows] = 0.0
            out += (wt / np.maximum(1.0 - own, 1e-300))[:, None] * w
    return out


def grey_srgb(linear: np.ndarray) -> np.ndarray:
    """(..., C) linear -> (...) grey (channel mean), sRGB-encoded, at peak 255."""
    return linear_to_srgb(linear.mean(axis=-1)) * 255.0


def psnr_per_light(prediction: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """PSNR (dB, peak 255) of each row of (n, m) arrays."""
    mse = np.mean((prediction - truth) ** 2, axis=1)
    return 10.0 * np.log10(255.0**2 / np.maximum(mse, 1e-12))


def choose_model(
    sample: np.ndarray, lights: np.ndarray, models: tuple[str, ...] = AUTO_MODELS,
    spaces: tuple[str, ...] = ("linear", "srgb"),
) -> Choice:
    """The candidate of best leave-one-light-out score on ``sample``.

    Parameters
    ----------
    sample : ndarray of shape (n, m, C)
        Training observations (linear, the solver's units) of ``m`` pixels.
    lights : ndarray of shape (n, 3)
        Their light directions.
    models : tuple of str
        Among ``ptm``, ``hsh2``, ``hsh3``, ``rbf``, ``bln``, ``gp`` (each with its grid).
    spaces : tuple of str

    Returns
    -------
    Choice

    """
    obs = np.nan_to_num(np.asarray(sample, np.float64))
    if obs.ndim == 2:
        obs = obs[..., None]
    n, m, c = obs.shape
    truth = grey_srgb(np.clip(obs, 0.0, 1.0))  # (n, m)
    table: list[dict[str, Any]] = []
    best: Choice | None = None
    # each candidate's leave-one-out matrix depends on the lights only: once for both spaces
    weights = {(model, index): loo_weights(model, params, lights)
               for model in models for index, params in enumerate(candidates(model))}
    for space in spaces:
        y = encode(obs, space).reshape(n, m * c)
        for model in models:
            for index, params in enumerate(candidates(model)):
                w = weights[model, index]
                if w is None:  # not a candidate on these lights
                    continue
                predicted = _decode((w @ y).reshape(n, m, c), space)
                score = float(np.mean(np.minimum(
                    psnr_per_light(grey_srgb(predicted), truth), SCORE_CAP)))
                table.append({"model": model, "space": space, **params, "loo_psnr": score})
                if best is None or score > best.score:
                    best = Choice(model, space, dict(params), score)
    if best is None:
        raise DatasetError(
            f"--appearance {'/'.join(models)}: the {n} training lights cannot cross-validate it "
            "(each light is fitted by its own term); use --appearance rbf or bln, or more lights")
    best.table = table
    return best


#: ``--appearance`` values resolved here: the automatic choice, and the models whose parameters
#: (and fit space) are chosen by the same cross-validation.
CHOSEN_MODELS = ("auto", "bln", "gp")


def resolve_model(
    model: str, sample: np.ndarray, lights: np.ndarray,
    normals: np.ndarray | None = None, albedo: np.ndarray | None = None,
    ps_scorer: Callable[..., float] | None = None,
) -> tuple[Choice, dict[str, Any], dict[str, np.ndarray]]:
    """Choose (``auto``: among :data:`AUTO_MODELS`; ``bln``/``gp``: its parameters and space)
    and set up the model: the :class:`Choice`, the ``meta`` entries (space, parameters, K, terms,
    the cross-validation summary) and the ``extra`` arrays (:func:`smoother_setup`).

    Parameters
    ----------
    model : {"auto", "bln", "gp"}
    sample : ndarray of shape (n, m, C)
        Linear observations of a pixel sample (the solver's units).
    lights : ndarray of shape (n, 3)
    normals, albedo : ndarray of shape (m, 3) and (m,) or (m, C), or None
        The sample pixels' solved normals and albedo: ``auto`` then also scores ``ps`` with
        ``ps_scorer(sample, lights, normals, albedo)`` (:func:`._ps_cv.ps_cv_score`; chosen: no
        ``extra``, the caller fits ``ps`` as usual).
    ps_scorer : callable or None

    """
    obs = np.asarray(sample, np.float64)
    obs = obs[..., None] if obs.ndim == 2 else obs
    keep = complete_pixels(obs)  # cross-validation on measured values only
    obs = obs[:, keep]
    if normals is not None and albedo is not None:
        normals, albedo = np.asarray(normals)[keep], np.asarray(albedo)[keep]
    m = obs.shape[1]
    scored = np.unique(np.linspace(0, m - 1, min(m, CHOICE_PIXELS)).round().astype(np.int64))
    choice = choose_model(obs[:, scored], lights, AUTO_MODELS if model == "auto" else (model,))
    if model == "auto" and normals is not None and albedo is not None and ps_scorer:
        ps_score = ps_scorer(obs[:, scored], lights, np.asarray(normals)[scored],
                               np.asarray(albedo)[scored])
        choice.table.append({"model": "ps", "space": "linear", "loo_psnr": ps_score})
        if ps_score > choice.score:
            choice = Choice("ps", "linear", {}, ps_score, choice.table)
            return choice, {"choice": _summary(model, choice)}, {}
    meta, extra = smoother_setup(choice, obs, lights)
    k = extra["basis"].shape[2] if "basis" in extra else BASIS_TERMS[choice.model]
    prefix = "pc" if "basis" in extra else choice.model
    meta.update({"K": k, "terms": [f"{prefix}{i}" for i in range(k)]})
    meta["choice"] = _summary(model, choice)
    return choice, meta, extra


def _summary(requested: str, choice: Choice) -> dict[str, Any]:
    best: dict[str, float] = {}
    for row in choice.table:
        key = f"{row['model']}/{row['space']}"
        best[key] = max(best.get(key, -np.inf), round(float(row["loo_psnr"]), 3))
    return {"rule": "leave-one-light-out grey sRGB PSNR (ps: 8-fold)", "requested": requested,
            "model": choice.model, "space": choice.space,
            "loo_psnr": round(float(choice.score), 3), "best_per_model": best}


def leading_right_vectors(values: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` leading right-singular vectors of the (m, n) matrix ``values.T`` as columns.

    The eigenvectors of the (n, n) Gram matrix ``values values^T`` (descending eigenvalues):
    the same subspace as the SVD of the sample at ``m n^2`` instead of an SVD of ``m`` rows.

    Parameters
    ----------
    values : ndarray of shape (n, m)
        One channel's observations of ``m`` pixels under ``n`` lights.
    k : int

    Returns
    -------
    ndarray of shape (n, k), orthonormal columns

    """
    gram = values @ values.T
    _, vectors = np.linalg.eigh(gram)
    return np.ascontiguousarray(vectors[:, ::-1][:, :k])


def smoother_setup(
    choice: Choice, sample: np.ndarray, lights: np.ndarray, terms: int = SMOOTH_TERMS
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The ``meta`` entries and ``extra`` arrays of the chosen model.

    For ``rbf``, ``bln`` and ``gp``: the training lights, the per-channel basis (C, n, K) (the
    leading right-singular vectors of the sample in the fit space, ``K = min(terms, n)``) and the
    parameters (``gp``: also ``solve``). For the linear bases: the fit space only.

    Parameters
    ----------
    choice : Choice
    sample : ndarray of shape (n, m, C)
        Linear observations of a pixel sample.
    lights : ndarray of shape (n, 3)

    """
    meta: dict[str, Any] = {"space": choice.space, **choice.params}
    if choice.model in BASIS_TERMS:
        return meta, {}
    obs = np.asarray(sample, np.float64)
    obs = obs[..., None] if obs.ndim == 2 else obs
    obs = np.nan_to_num(encode(obs[:, complete_pixels(obs)], choice.space))
    n = obs.shape[0]
    k = min(terms, n)
    basis = np.stack([leading_right_vectors(obs[:, :, ch], k) for ch in range(obs.shape[2])])
    lights = np.asarray(lights, np.float64)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    extra = {"lights": lights.astype(np.float32), "basis": basis.astype(np.float32)}
    if choice.model == "gp":
        extra["solve"] = gp_solve(lights.astype(np.float32), choice.params["sigma"],
                                  choice.params["ridge"])
    return meta, extra
