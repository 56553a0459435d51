"""Appearance models fitted per pixel beside the normals (``ps-lab reconstruct --appearance``).

:func:`fit_appearance` fits one model on whole arrays (tests, ``ps-lab bench relight``);
:func:`fit_appearance_bands` is the reconstruction's hook: it streams the observation store's row
bands (the bands the normals were solved on, in blocks of :data:`FIT_CHUNK` pixels so that the
fit stays within the band's memory), reads the result's normals and albedo row by row, writes the
coefficients into a temporary ``.npy`` in the staged result folder and then ``appearance.npz``
(:func:`ps_lab.appearance.store.write_appearance`). The models are defined in
:mod:`ps_lab.appearance.models`, the fits in :mod:`.blocks`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.appearance._ps_cv import ps_cv_score
from ps_lab.appearance.blocks import RBF_TERMS, fit_block, rbf_setup
from ps_lab.appearance.choice import CHOSEN_MODELS, resolve_model
from ps_lab.appearance.design import (
    TERM_NAMES,
    determined_terms,
    distinct_lights,
    saturated_observations,
)
from ps_lab.appearance.models import (
    APPEARANCE_MODELS,
    BASIS_TERMS,
    PS_TERMS,
    VISIBILITY_TERMS,
    Appearance,
)
from ps_lab.appearance.store import write_appearance
from ps_lab.io.bands import ObservationStore
from ps_lab.io.files import allocate_npy, write_npy_rows

__all__ = [
    "APPEARANCE_MODELS",
    "FIT_CHUNK",
    "FIT_WORKERS",
    "check_lights",
    "fit_appearance",
    "fit_appearance_bands",
    "model_meta",
]

# Pixels per block of the streamed fit (the unit of the progress bar and of the threads; the ps
# kernel needs only a small tile, the linear models a float64 copy of a block's observations).
FIT_CHUNK = 8192
# Threads fitting the blocks of a band with the ps model (its numba kernel releases the GIL; the
# linear models' products are BLAS's, threaded by BLAS itself).
FIT_WORKERS = 2
log = logging.getLogger(__name__)
_TEMP = ".appearance-coefficients.npy"
_TEMP_VIS = ".appearance-visibility.npy"


def _terms(model: str, channels: int, lights: int) -> list[str]:
    """The term names of ``model`` (``rbf``: as many as ``lights``, the distinct ones, up to
    :data:`RBF_TERMS`)."""
    if model == "ps":
        return list(PS_TERMS)
    if model == "rbf":
        return [f"pc{k}" for k in range(min(RBF_TERMS, lights))]
    if model in BASIS_TERMS:
        return [f"{model}{k}" for k in range(BASIS_TERMS[model])]
    return []


def model_meta(model: str, channels: int, lights: int, sigma: float | None = None,
               terms: list[str] | None = None) -> dict:
    """The ``meta`` of an :class:`Appearance` of ``model`` (basis, K, term names, sigma);
    ``terms``: the names fitted (``ps``: those the lights determine) instead of the model's."""
    terms = _terms(model, channels, lights) if terms is None else list(terms)
    meta: dict[str, Any] = {"basis": model, "K": len(terms), "terms": terms, "channels": channels}
    if model == "ps":
        meta["visibility"] = "clip-linear"
    if sigma is not None:
        meta["sigma"] = float(sigma)
    return meta


def check_lights(model: str, directions: np.ndarray) -> tuple[int, list[str] | None]:
    """What the training lights determine of ``model``, said once as a ``warning:`` line.

    Returns the count of distinct lights and, for ``ps``, the terms it fits (None: the
    model's own). The rule (:func:`ps_lab.appearance.design.determined_terms`):
    terms the design at the distinct lights does not determine are not fitted (``ptm``/``hsh*``:
    stored as 0; ``ps``: left out of its terms; ``rbf``: one basis vector per distinct light).
    """
    distinct = len(distinct_lights(directions))
    if model == "none" or model in CHOSEN_MODELS or model in ("bln", "gp"):
        # chosen models are checked once resolved; bln and gp interpolate the lights they have
        return distinct, None
    names = _terms(model, 1, len(directions))
    keep, warning = determined_terms(model, directions, TERM_NAMES.get(model, tuple(names)))
    if warning is not None:
        log.warning(warning)
    if model == "ps":
        return distinct, [names[k] for k in keep]
    return distinct, None


def _as_colour(observations: np.ndarray) -> np.ndarray:
    return observations[..., None] if observations.ndim == 2 else observations


def fit_appearance(
    model: str,
    observations: np.ndarray,
    directions: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
) -> Appearance:
    """Fit ``model`` on every mask pixel at once.

    Parameters
    ----------
    model : {"auto", "ps", "ptm", "hsh2", "hsh3", "rbf", "bln", "gp", "none"}
        ``auto``: chosen by cross-validation (:mod:`.choice`); ``bln``, ``gp``: their
        parameters and fit space chosen so.
    observations : ndarray of shape (n, P, C) or (n, P)
        Training observations of the P mask pixels (row-major), solver units.
    directions : ndarray of shape (n, 3)
        Unit training light directions.
    mask : ndarray of shape (H, W), bool
        P true pixels.
    normals : ndarray of shape (P, 3) or None
        The solver's normals (``ps``).
    albedo : ndarray of shape (P,) or (P, C) or None
        The solver's albedo (``ps``).

    Returns
    -------
    Appearance
        Coefficients (H, W, C, K), zero outside the mask.

    """
    obs = _as_colour(np.asarray(observations))
    n, p, c = obs.shape
    directions = _unit_rows(directions)
    distinct, terms = check_lights(model, directions)
    sigma, basis = None, None
    extra: dict[str, np.ndarray] = {}
    chosen: dict[str, Any] = {}
    if model in CHOSEN_MODELS:
        pick = _sample_index(p)
        choice, chosen, extra = resolve_model(
            model, obs[:, pick], directions, *(() if normals is None or albedo is None else
                                              (np.asarray(normals)[pick], np.asarray(albedo)[pick])),
            ps_scorer=ps_cv_score)
        model, basis = choice.model, extra.get("basis")
    elif model == "rbf":
        sigma, basis = rbf_setup(obs[:, _sample_index(p)], directions)
        extra = {"lights": directions.astype(np.float32), "basis": basis.astype(np.float32)}
    if chosen:  # the model the choice resolved to: what the lights determine of it
        distinct, terms = check_lights(model, directions)
    meta = {**model_meta(model, c, distinct, sigma, terms), **chosen}
    coeffs = np.zeros((*mask.shape, c, meta["K"]), np.float32)
    if model != "none":
        coeffs[mask], vis = fit_block(model, obs, directions, normals=normals, albedo=albedo,
                                      rbf_basis=basis, terms=tuple(meta["terms"]),
                                      space=meta.get("space", "linear"))
        if vis is not None:
            extra["visibility"] = np.zeros((*mask.shape, VISIBILITY_TERMS), np.float32)
            extra["visibility"][..., 3] = 1.0
            extra["visibility"][mask] = vis
    return Appearance(model, coeffs, meta, extra)


def _unit_rows(directions: np.ndarray) -> np.ndarray:
    d = np.asarray(directions, np.float64)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _sample_index(pixels: int, size: int = 20000) -> np.ndarray:
    return np.unique(np.linspace(0, pixels - 1, min(pixels, size)).round().astype(np.int64))


def fit_appearance_bands(
    store: ObservationStore,
    folder: Path,
    model: str,
    directions: np.ndarray,
    scale: np.ndarray | None = None,
    *,
    progress_bars: Callable[[int, str], Any] | None = None,
    workers: int = FIT_WORKERS,
) -> dict[str, Any]:
    """Fit ``model`` band by band on a staged store and write ``folder/appearance.npz``.

    Parameters
    ----------
    store : ObservationStore
        The observations the normals were solved on; ``read(band)`` gives (n, P) (one channel)
        or (n, P, C) (colour).
    folder : Path
        The (staged) result folder holding ``normals.npy`` and ``albedo.npy``.
    model : str
        One of :data:`APPEARANCE_MODELS`; ``none`` writes no file.
    directions : ndarray of shape (n, 3)
        Light directions the normals were solved with (refined ones after refinement).
    scale : ndarray of shape (n,) or None
        Refined relative intensities (the observations are divided by them).
    progress_bars : callable or None
        As for :func:`ps_lab.reconstruct.pipeline.reconstruct_to_folder`.
    workers : int
        Threads fitting a band's blocks side by side with the ps model (its kernel releases the
        GIL; the coefficients do not depend on the count).

    Returns
    -------
    dict
        The ``"appearance"`` entry of ``metrics.json``: model, coefficients per pixel, terms,
        ``timings`` (``fit_seconds``), and rbf's ``sigma``.

    """
    if model not in APPEARANCE_MODELS and model not in CHOSEN_MODELS:
        raise ValueError(f"unknown appearance model {model!r}")
    if model == "none":
        return {"model": "none", "coefficients_per_pixel": 0}
    started = time.perf_counter()
    folder = Path(folder)
    directions = _unit_rows(directions)
    factor = np.ones(store.n_lights) if scale is None else np.asarray(scale, np.float64)
    normals = np.load(folder / "normals.npy", mmap_mode="r")
    albedo = np.load(folder / "albedo.npy", mmap_mode="r")
    distinct, terms = check_lights(model, directions)
    colour = getattr(store, "colours", 0)  # colour frames: fit the three channels (issue 32)
    rule = getattr(store, "rule", None)
    threshold = rule.threshold if rule is not None and rule.use_threshold else None
    sample = (store.sample_colour if colour else _as_colour(store.sample_observations))
    sample = sample / factor[:, None, None]
    fitted_terms = (len(terms) if terms is not None else
                    RBF_TERMS if model in CHOSEN_MODELS else len(_terms(model, 1, distinct)))
    sample[saturated_observations(store.sample_observations, store.sample_valid, threshold,
                                  fitted_terms)] = np.nan
    channels = sample.shape[2]
    sigma, basis = None, None
    extra: dict[str, np.ndarray] = {}
    chosen: dict[str, Any] = {}
    if model in CHOSEN_MODELS:
        choice, chosen, extra = resolve_model(
            model, sample, directions, *_sample_solution(store, normals, albedo),
            ps_scorer=ps_cv_score)
        model, basis = choice.model, extra.get("basis")
    elif model == "rbf":
        sigma, basis = rbf_setup(sample, directions)
        extra = {"lights": directions.astype(np.float32), "basis": basis.astype(np.float32)}
    if chosen:  # the model the choice resolved to: what the lights determine of it
        distinct, terms = check_lights(model, directions)
    meta = {**model_meta(model, channels, distinct, sigma, terms), **chosen}
    space = meta.get("space", "linear")
    height, width = store.shape
    shape = (height, width, channels, meta["K"])
    temp, temp_vis = folder / _TEMP, folder / _TEMP_VIS
    offset = allocate_npy(temp, shape, np.float32)
    vis_offset = (allocate_npy(temp_vis, (height, width, VISIBILITY_TERMS), np.float32)
                  if model == "ps" else None)
    bars = progress_bars or _no_bar
    try:
        with bars(store.pixels, f"appearance {model}: pixels") as advance:
            for band in store.bands:
                rows = slice(band.row_start, band.row_stop)
                inside = store.mask[rows]
                block = np.zeros((band.row_stop - band.row_start, width, *shape[2:]), np.float32)
                vis_block = np.zeros((*block.shape[:2], VISIBILITY_TERMS), np.float32)
                vis_block[..., 3] = 1.0
                if band.pixel_count:
                    # the store's buffers (this band's observations are used up before the next)
                    read = store.observe(band, colour=bool(colour), reuse=True)
                    observations = read[2] if colour else read[0]
                    # saturated observations are dropped (NaN: missing) by every model
                    observations[saturated_observations(read[0], read[1], threshold,
                                                        fitted_terms)] = np.nan
                    coeffs, vis = _fit_band(model, _as_colour(observations), directions, factor,
                                            np.asarray(normals[rows])[inside],
                                            np.asarray(albedo[rows])[inside], basis, workers,
                                            advance, tuple(meta["terms"]), space)
                    block[inside] = coeffs
                    if vis is not None:
                        vis_block[inside] = vis
                write_npy_rows(temp, offset, band.row_start, block)
                if vis_offset is not None:
                    write_npy_rows(temp_vis, vis_offset, band.row_start, vis_block)
        coefficients = np.load(temp, mmap_mode="r")
        if vis_offset is not None:
            extra["visibility"] = np.load(temp_vis, mmap_mode="r")
        write_appearance(folder, Appearance(model, coefficients, meta, extra))
        del coefficients
        extra.clear()
    finally:
        temp.unlink(missing_ok=True)
        temp_vis.unlink(missing_ok=True)
    return {
        "model": model,
        "coefficients_per_pixel": channels * meta["K"] + (VISIBILITY_TERMS if model == "ps" else 0),
        "terms": meta["terms"],
        "timings": {"fit_seconds": time.perf_counter() - started},
        **({"sigma": sigma} if sigma is not None else {}),
        **({"space": space, "choice": meta["choice"]} if "choice" in meta else {}),
    }


def _sample_solution(store: ObservationStore, normals: np.ndarray, albedo: np.ndarray):
    """The normals (m, 3) and albedo of the store's sample pixels (the mask's pixels
    ``store.sample_index`` in row-major order)."""
    rows, cols = np.nonzero(store.mask)
    r, c = rows[store.sample_index], cols[store.sample_index]
    return np.asarray(normals[r, c], np.float64), np.asarray(albedo[r, c], np.float64)


def _fit_band(
    model: str,
    observations: np.ndarray,
    directions: np.ndarray,
    factor: np.ndarray,
    normals: np.ndarray,
    albedo: np.ndarray,
    basis: np.ndarray | None,
    workers: int,
    advance: Callable[..., None],
    terms: tuple[str, ...] = PS_TERMS,
    space: str = "linear",
) -> tuple[np.ndarray, np.ndarray | None]:
    """One band's coefficients (P, C, K) float32 and the ps visibility (P, 4) float32 (or None).

    The band's blocks of :data:`FIT_CHUNK` pixels are fitted in place in the band's observations
    (n, P, C) (no per-block copy), by ``workers`` threads; ``advance`` is called as
    each block completes, in order.
    """
    pixels = observations.shape[1]
    parts = [slice(s, min(s + FIT_CHUNK, pixels)) for s in range(0, pixels, FIT_CHUNK)]

    def fit(part: slice) -> tuple[np.ndarray, np.ndarray | None]:
        return fit_block(model, observations, directions, pixels=part, scale=factor,
                         normals=normals[part], albedo=albedo[part], rbf_basis=basis,
                         terms=terms if model == "ps" else PS_TERMS, space=space)

    results: list[tuple[np.ndarray, np.ndarray | None]] = []
    if workers > 1 and len(parts) > 1:  # the kernels and numpy's products release the GIL
        with ThreadPoolExecutor(min(workers, len(parts))) as pool:
            for part, result in zip(parts, pool.map(fit, parts)):
                results.append(result)
                advance(part.stop - part.start)
    else:
        for part in parts:
            results.append(fit(part))
            advance(part.stop - part.start)
    coeffs = np.concatenate([c for c, _ in results])
    vis = None if results[0][1] is None else np.concatenate([v for _, v in results])
    return coeffs, vis


class _no_bar:
    def __init__(self, total: int, description: str) -> None:
        pass

    def __enter__(self) -> Callable[..., None]:
        return lambda n=1, description=None: None

    def __exit__(self, *exc_info: Any) -> None:
        return None


def solved_lights(source: Any, solved: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """The light directions the normals were solved with, and the refined relative intensities.

    ``source`` and ``solved`` are the pipeline's ``SolveInput`` and ``Solved``: without
    refinement the dataset's directions (scale None); with it the refined directions, and each
    light's refined intensity over the file's (the observations are divided by it).
    """
    if solved.directions is None:
        return np.asarray(source.header.light_directions, np.float64), None
    given = np.asarray(source.header.light_intensities, np.float64).reshape(len(solved.directions), -1)
    refined = np.asarray(solved.intensities, np.float64).reshape(given.shape)
    return np.asarray(solved.directions, np.float64), np.mean(refined / given, axis=1)
