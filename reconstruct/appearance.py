"""Appearance models fitted per pixel beside the normals (``ps-lab reconstruct --appearance``).

:func:`fit_appearance` fits one model on whole arrays (tests, ``ps-lab bench relight``);
:func:`fit_appearance_bands` is the reconstruction's hook: it streams the observation store's row
bands (the bands the normals were solved on, in blocks of :data:`FIT_CHUNK` pixels so that the
fit stays within the band's memory), reads the result's normals and albedo row by row, writes the
coefficients into a temporary ``.npy`` in the staged result folder and then ``appearance.npz``
(:func:`ps_lab.io.appearance.write_appearance`). The models are defined in
:mod:`ps_lab.io.appearance`, the fits in :mod:`._appearance_fit`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.io.appearance import (
    APPEARANCE_MODELS,
    BASIS_TERMS,
    PS_TERMS,
    VISIBILITY_TERMS,
    Appearance,
    write_appearance,
)
from ps_lab.io.bands import ObservationStore
from ps_lab.io.files import allocate_npy, write_npy_rows
from ps_lab.reconstruct._appearance_fit import RBF_TERMS, fit_block, rbf_setup

__all__ = [
    "APPEARANCE_MODELS",
    "FIT_CHUNK",
    "fit_appearance",
    "fit_appearance_bands",
    "model_meta",
]

# Pixels per block of the streamed fit: bounds its float64 copies to ~17 bytes x lights x block.
FIT_CHUNK = 8192
_TEMP = ".appearance-coefficients.npy"
_TEMP_VIS = ".appearance-visibility.npy"


def _terms(model: str, channels: int, lights: int) -> list[str]:
    if model == "ps":
        return list(PS_TERMS)
    if model == "rbf":
        return [f"pc{k}" for k in range(min(RBF_TERMS, lights))]
    if model in BASIS_TERMS:
        return [f"{model}{k}" for k in range(BASIS_TERMS[model])]
    return []


def model_meta(model: str, channels: int, lights: int, sigma: float | None = None) -> dict:
    """The ``meta`` of an :class:`Appearance` of ``model`` (basis, K, term names, sigma)."""
    terms = _terms(model, channels, lights)
    meta: dict[str, Any] = {"basis": model, "K": len(terms), "terms": terms, "channels": channels}
    if model == "ps":
        meta["visibility"] = "clip-linear"
    if sigma is not None:
        meta["sigma"] = float(sigma)
    return meta


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
    model : {"ps", "ptm", "hsh2", "hsh3", "rbf", "none"}
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
    sigma, basis = None, None
    extra: dict[str, np.ndarray] = {}
    if model == "rbf":
        sigma, basis = rbf_setup(obs[:, _sample_index(p)], directions)
        extra = {"lights": directions.astype(np.float32), "basis": basis.astype(np.float32)}
    meta = model_meta(model, c, n, sigma)
    coeffs = np.zeros((*mask.shape, c, meta["K"]), np.float32)
    if model != "none":
        coeffs[mask], vis = fit_block(model, obs, directions, normals=normals, albedo=albedo,
                                      rbf_basis=basis)
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

    Returns
    -------
    dict
        The ``"appearance"`` entry of ``metrics.json``: model, coefficients per pixel, terms,
        ``timings`` (``fit_seconds``), and rbf's ``sigma``.

    """
    if model not in APPEARANCE_MODELS:
        raise ValueError(f"unknown appearance model {model!r}")
    if model == "none":
        return {"model": "none", "coefficients_per_pixel": 0}
    started = time.perf_counter()
    folder = Path(folder)
    directions = _unit_rows(directions)
    factor = np.ones(store.n_lights) if scale is None else np.asarray(scale, np.float64)
    normals = np.load(folder / "normals.npy", mmap_mode="r")
    albedo = np.load(folder / "albedo.npy", mmap_mode="r")
    colour = getattr(store, "colours", 0)  # colour frames: fit the three channels (issue 32)
    sample = (store.sample_colour if colour else _as_colour(store.sample_observations))
    sample = sample / factor[:, None, None]
    channels = sample.shape[2]
    sigma, basis = None, None
    extra: dict[str, np.ndarray] = {}
    if model == "rbf":
        sigma, basis = rbf_setup(sample, directions)
        extra = {"lights": directions.astype(np.float32), "basis": basis.astype(np.float32)}
    meta = model_meta(model, channels, store.n_lights, sigma)
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
                    observations = store.read_colour(band) if colour else store.read(band)[0]
                    obs = _as_colour(observations)
                    band_normals = np.asarray(normals[rows])[inside]
                    band_albedo = np.asarray(albedo[rows])[inside]
                    coeffs = np.empty((band.pixel_count, *shape[2:]), np.float32)
                    vis = np.empty((band.pixel_count, VISIBILITY_TERMS), np.float32)
                    for start in range(0, band.pixel_count, FIT_CHUNK):
                        part = slice(start, min(start + FIT_CHUNK, band.pixel_count))
                        coeffs[part], part_vis = fit_block(
                            model,
                            obs[:, part] / factor[:, None, None],
                            directions,
                            normals=band_normals[part],
                            albedo=band_albedo[part],
                            rbf_basis=basis,
                        )
                        if part_vis is not None:
                            vis[part] = part_vis
                        advance(part.stop - part.start)
                    block[inside] = coeffs
                    vis_block[inside] = vis
                write_npy_rows(temp, offset, band.row_start, block)
                if vis_offset is not None:
                    write_npy_rows(temp_vis, vis_offset, band.row_start, vis_block)
        coefficients = np.load(temp, mmap_mode="r")
        if vis_offset is not None:
            extra["visibility"] = np.load(temp_vis, mmap_mode="r")
        write_appearance(folder, Appearance(model, coefficients, meta, extra))
        del coefficients
        extra.pop("visibility", None)
    finally:
        temp.unlink(missing_ok=True)
        temp_vis.unlink(missing_ok=True)
    return {
        "model": model,
        "coefficients_per_pixel": channels * meta["K"] + (VISIBILITY_TERMS if model == "ps" else 0),
        "terms": meta["terms"],
        "timings": {"fit_seconds": time.perf_counter() - started},
        **({"sigma": sigma} if sigma is not None else {}),
    }


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
