"""One band's solve, reduced to what the output writer and light refinement need.

:func:`solve_band` is the unit of work of every solve pass of :mod:`.pipeline`: in this process
(:class:`LocalBands`, threads inside each solve) or as a task on a Dask worker
(:mod:`.distributed`). It returns a :class:`BandResult` whose arrays are over the band's mask
pixels only, so the same small object crosses the network, and the writer and the refinement sums
see exactly the same numbers wherever the band was solved.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.io.bands import Band, ObservationStore, stage_observations
from ps_lab.io.coding import Coding
from ps_lab.io.dataset import DatasetHeader
from ps_lab.reconstruct._colour import colour_albedo
from ps_lab.reconstruct._refine import light_fit_sums
from ps_lab.reconstruct._solution import Solution
from ps_lab.reconstruct._solve import solve
from ps_lab.reconstruct.metrics import angular_errors_deg

# Pixels per chunk of the light-refinement sums (bounds their float64 copies).
FIT_CHUNK = 65536


@dataclass
class BandResult:
    """A solved band, reduced: pixel vectors over its mask pixels (row-major) and sums.

    Attributes
    ----------
    index : int
        The band's index.
    params : dict
        The solver's parameters as used (``Solution.params``).
    normals : ndarray of shape (P, 3), float32, or None
        Unit normals, zeros where unsolved (last pass only; None on refinement passes).
    albedo : ndarray of shape (P,), float32, or None
        Zero where unsolved.
    colour_albedo : ndarray of shape (P, C), float32, or None
        Per-channel albedo (:func:`ps_lab.reconstruct._colour.colour_albedo`) when the band's
        colour observations were given (last pass only); zero where unsolved.
    corruption : ndarray of shape (P,), float32, or None
        Share of each pixel's usable observations flagged as outliers.
    solved : ndarray of shape (P,), bool, or None
    iteration_counts : ndarray of shape (k,), int64, or None
        ``bincount`` of the per-pixel iterations.
    valid_count, observation_count, outlier_count : int
        Usable observations, all observations, outliers.
    fit_sums : list of tuple
        Refinement passes: per chunk of :data:`FIT_CHUNK` pixels, ``(normal_matrices (n, 6),
        normal_targets (n, 3), inliers, usable)`` of :func:`ps_lab.reconstruct.light_fit_sums`;
        the caller adds them in band and chunk order (the in-process order).
    error_sum : float
        Sum of the angular errors (degrees, float64 normals) against ground truth, when given.
    all_have_truth : bool
        Every pixel of the band has a ground-truth normal.
    seconds : float
        Time spent solving (for the overhead measurements of ``benchmarks/distributed.py``).

    """

    index: int
    params: dict
    normals: np.ndarray | None = None
    albedo: np.ndarray | None = None
    colour_albedo: np.ndarray | None = None
    corruption: np.ndarray | None = None
    solved: np.ndarray | None = None
    iteration_counts: np.ndarray | None = None
    valid_count: int = 0
    observation_count: int = 0
    outlier_count: int = 0
    fit_sums: list = field(default_factory=list)
    error_sum: float = 0.0
    all_have_truth: bool = True
    seconds: float = 0.0


def solve_band(
    observations: np.ndarray,
    valid: np.ndarray,
    index: int,
    vectors: np.ndarray,
    *,
    method: str,
    parameters: dict[str, Any],
    threads: int | None,
    final: bool,
    truth_rows: np.ndarray | None = None,
    progress: Callable[[int], None] | None = None,
    black: np.ndarray | None = None,
    colour: np.ndarray | None = None,
) -> BandResult:
    """Solve one band and reduce the solution.

    Parameters
    ----------
    observations : ndarray of shape (n, P), float32
        The band's observations (:meth:`ps_lab.io.bands.ObservationStore.read`).
    valid : ndarray of shape (n, P), bool
        Their validity.
    index : int
        The band's index (carried into the result).
    vectors : ndarray of shape (n, 3)
        Light vectors (directions times relative intensities).
    method : str
        Solver (``ps_lab.reconstruct.METHODS``).
    parameters : dict
        Keyword arguments of :func:`ps_lab.reconstruct.solve` (the whole-image ``noise_sigma``
        and the options' solver parameters).
    threads : int or None
        Threads over tiles (None: all cores).
    final : bool
        The last pass: keep the pixel vectors for the writer; else the refinement sums.
    truth_rows : ndarray of shape (P, 3) or None
        Ground truth of the band's mask pixels (refinement history).
    progress : callable or None
        ``progress(k)`` after each tile of k pixels.
    black : ndarray of shape (n,) or None
        Each light's level of black: observations at or below it are shadows, dropped
        (:func:`ps_lab.reconstruct._shadows.black_threshold`).
    colour : ndarray of shape (n, P, C) or None
        The band's colour observations (:meth:`ps_lab.io.bands.ObservationStore.read_colour`):
        with ``final``, the result carries their per-channel albedo over the solver's inliers.

    Returns
    -------
    BandResult

    """
    started = time.perf_counter()
    if black is not None:
        valid = valid & (observations > black[:, None])
    solution = solve(
        observations,
        vectors,
        method=method,
        valid=valid,
        threads=threads,
        progress=progress,
        **parameters,
    )
    result = BandResult(index, dict(solution.params))
    if final:
        _reduce_for_writer(result, solution, valid)
        if colour is not None:
            result.colour_albedo = band_colour_albedo(result, solution, valid, colour, vectors)
    else:
        result.fit_sums = _fit_sums(observations, valid, solution)
    if truth_rows is not None:
        result.all_have_truth = bool(np.all(np.linalg.norm(truth_rows, axis=1) > 0.5))
        result.error_sum = float(angular_errors_deg(solution.normals, truth_rows).sum())
    result.seconds = time.perf_counter() - started
    return result


def reduce_solution(index: int, solution: Solution, valid: np.ndarray) -> BandResult:
    """A band's :class:`BandResult` for the writer from its solution and validity (n, P)."""
    result = BandResult(index, dict(solution.params))
    _reduce_for_writer(result, solution, valid)
    return result


def band_colour_albedo(
    result: BandResult, solution: Solution, valid: np.ndarray, colour: np.ndarray, vectors
) -> np.ndarray:
    """The per-channel albedo (P, C) of a reduced band: inliers = valid and not outliers.

    ``vectors`` (n, 3) or (n, P, 3): the light vectors the band was solved with (the colour
    observations are divided by the file's intensities, as the solve channel's are).
    """
    inliers = valid & ~np.asarray(solution.outliers, dtype=bool)
    albedo = colour_albedo(result.normals, inliers, colour, vectors)
    albedo[~result.solved] = 0.0
    return albedo


def _reduce_for_writer(result: BandResult, solution: Solution, valid: np.ndarray) -> None:
    pixel_normals = np.asarray(solution.normals, dtype=np.float64)
    lengths = np.linalg.norm(pixel_normals, axis=1)
    solved = np.isfinite(lengths) & (lengths > 0.5)
    unit = np.zeros_like(pixel_normals)
    unit[solved] = pixel_normals[solved] / lengths[solved, None]
    pixel_albedo = np.nan_to_num(np.asarray(solution.albedo, np.float64))
    outliers = np.asarray(solution.outliers, dtype=bool)
    used = valid.sum(axis=0)
    result.normals = unit.astype(np.float32)
    result.albedo = np.where(solved, pixel_albedo, 0.0).astype(np.float32)
    result.corruption = (outliers.sum(axis=0) / np.maximum(used, 1)).astype(np.float32)
    result.solved = solved
    result.iteration_counts = np.bincount(np.asarray(solution.iterations, np.int64))
    result.valid_count = int(used.sum())
    result.observation_count = int(valid.size)
    result.outlier_count = int(outliers.sum())


def _fit_sums(observations, valid, solution, chunk: int = FIT_CHUNK) -> list:
    """Per-chunk :func:`ps_lab.reconstruct.light_fit_sums` of one band (they add over pixels)."""
    sums = []
    for a in range(0, observations.shape[1], chunk):
        b = min(a + chunk, observations.shape[1])
        part = Solution(
            solution.normals[a:b],
            solution.albedo[a:b],
            solution.outliers[:, a:b],
            solution.iterations[a:b],
        )
        matrices, targets, used = light_fit_sums(observations[:, a:b], valid[:, a:b], part)
        usable = int((valid[:, a:b] & np.isfinite(observations[:, a:b])).sum())
        sums.append((matrices, targets, used, usable))
    return sums


def band_truth(truth, mask: np.ndarray, band: Band) -> np.ndarray:
    """Ground truth (P, 3) of a band's mask pixels from a :class:`ps_lab.io.truth.NormalTruth`."""
    rows = slice(band.row_start, band.row_stop)
    return truth.rows(band.row_start, band.row_stop)[mask[rows]]


class LocalBands:
    """The in-process band executor: stage in this process, solve bands one after the other.

    Each band's solve uses ``threads`` threads over tiles. The Dask executor
    (:class:`ps_lab.reconstruct.distributed.DaskBands`) has the same two methods.
    """

    name = "local"

    def __init__(self, threads: int | None = None) -> None:
        self.threads = threads

    def band_pixels(self, budget_pixels: int, pixels: int, keep_plan: bool) -> int:
        """Most mask pixels per band: what the memory budget allows."""
        return budget_pixels

    def stage(
        self,
        header: DatasetHeader,
        mask: np.ndarray,
        bands: list[Band],
        *,
        channel: str,
        shadow_threshold: float | None,
        folder: Path,
        in_memory: bool,
        sample_pixels: int,
        progress: Callable[[int], None],
        colours: int = 0,
        coding: Coding | None = None,
        decoders: int | None = None,
    ) -> ObservationStore:
        """Pass 1: :func:`ps_lab.io.bands.stage_observations` (``decoders`` frames at once)."""
        return stage_observations(
            header,
            mask,
            bands,
            channel=channel,
            shadow_threshold=shadow_threshold,
            folder=folder,
            in_memory=in_memory,
            sample_pixels=sample_pixels,
            progress=progress,
            colours=colours,
            coding=coding,
            threads=decoders or self.threads,
        )

    def solve(
        self,
        store: ObservationStore,
        header: DatasetHeader,
        vectors: np.ndarray,
        *,
        method: str,
        parameters: dict[str, Any],
        final: bool,
        truth,
        advance: Callable[..., None],
        label: str,
        black: np.ndarray | None = None,
    ) -> Iterator[BandResult]:
        """One solve pass: yield each non-empty band's result, in band order."""
        count = len(store.bands)
        for band in store.bands:
            if band.pixel_count == 0:
                continue
            advance(0, description=f"{label}: band {band.index + 1}/{count}")
            # the store's buffers: this band's arrays are done with before the next is read
            observations, valid, colour = store.observe(band, colour=final, reuse=True)
            yield solve_band(
                observations,
                valid,
                band.index,
                vectors,
                method=method,
                parameters=parameters,
                threads=self.threads,
                final=final,
                truth_rows=None if truth is None else band_truth(truth, store.mask, band),
                progress=advance,
                black=black,
                colour=colour,
            )
