"""Stage 3 of the reconstruction: solve passes over the row bands of an observation store.

:func:`solve_bands` runs K + 1 passes with directional lights (K = light refinement iterations,
each light re-fitted from the sums a pass accumulated); :func:`solve_near_bands` alternates band
solves with per-pixel light vectors and depth until the depth settles. Both hand the last pass's
bands to the output writer and return a :class:`Solved`; :func:`black_level` sets the default
shadow threshold first. The flow that calls them is
:func:`ps_lab.reconstruct.pipeline.reconstruct_to_folder`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.io.bands import ObservationStore
from ps_lab.io.dataset import DatasetHeader
from ps_lab.reconstruct._bands import BandResult, band_colour_albedo, reduce_solution
from ps_lab.reconstruct._outputs import _OutputWriter
from ps_lab.reconstruct._refine import fit_lights
from ps_lab.reconstruct._shadows import black_threshold
from ps_lab.reconstruct._solution import SolverInputError
from ps_lab.reconstruct._noise import estimate_noise_model, light_noise_factors, pl_noise_level
from ps_lab.reconstruct.methods import solver
from ps_lab.reconstruct.near import (
    NearLights,
    NearRounds,
    fit_near_intensities,
    near_light_rounds,
    solve_near,
)
from ps_lab.reconstruct.options import ReconstructOptions

log = logging.getLogger(__name__)

ProgressBars = Callable[[int, str], Any]


@dataclass(frozen=True)
class SolveInput:
    """Stage 1's product: the dataset's header, mask and ground truth (or None)."""

    header: DatasetHeader
    mask: np.ndarray
    truth: Any
    near: NearLights | None = None  # lights at a finite distance, when the options choose them
    outline: float | None = None  # the object's outline height the dataset states (near lights)


@dataclass
class Solved:
    """Stage 3's product: parameters, lights after refinement, history and solve time."""

    params: dict
    directions: np.ndarray | None
    intensities: np.ndarray | None
    history: list[dict]
    seconds: float
    near: NearRounds | None = None
    black: list[float] | None = None


def black_level(
    store: ObservationStore, header: DatasetHeader, options: ReconstructOptions
) -> np.ndarray | None:
    """Without ``--shadow-threshold``: each light's level of black, from the store's sample.

    :func:`ps_lab.reconstruct._shadows.black_threshold` measures the noise at black on the
    negative observations of the sample; observations at or below it are shadows. The sample's
    validity is updated here, so the noise level estimated next sees what the bands will see.
    Returns None (every observation kept) with an explicit threshold or no measurable noise.
    """
    if options.shadow_threshold is not None or store.sample_index.size == 0:
        return None
    factors = light_noise_factors(header.light_intensities, options.channel)
    black = black_threshold(store.sample_observations, store.sample_valid, factors,
                            light_directions=header.light_directions)
    if black is not None:
        store.sample_valid &= store.sample_observations > black[:, None]
        log.info("shadows: observations within %.3g (mean) of black are dropped", black.mean())
    return black


def solve_bands(
    store: ObservationStore,
    source: SolveInput,
    options: ReconstructOptions,
    writer: _OutputWriter,
    bars: ProgressBars,
    executor,
    black: np.ndarray | None = None,
) -> Solved:
    """Stage 3: K + 1 solve passes over the bands (K = ``options.refine_lights``).

    Between passes each light is re-fitted from the sums the pass accumulated; the last pass
    hands every band to ``writer``. ``black`` (n,): observations at or below it are shadows.
    """
    started = time.perf_counter()
    method, refine = options.method, options.refine_lights
    lights = np.asarray(source.header.light_directions, dtype=np.float64)
    directions = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    factor = np.ones(store.n_lights)
    anchor = directions.copy()
    history: list[dict] = []
    pending: dict = {}
    passes = refine + 1
    with bars(store.pixels * passes, f"{method}: pixels") as advance:
        for k in range(passes):
            final = k == refine
            result = _solve_pass(
                store,
                source.header,
                executor,
                directions * factor[:, None],
                options,
                truth=source.truth if refine else None,
                fit=not final,
                writer=writer if final else None,
                advance=advance,
                label=method if passes == 1 else f"{method} pass {k + 1}/{passes}",
                intensities=source.header.light_intensities,
                black=black,
            )
            if refine:
                errors = {}
                if source.truth is not None and result.all_have_truth:
                    errors["normal_error_deg"] = result.error_sum / max(store.pixels, 1)
                history.append({"iteration": 0, **errors} if k == 0 else {**pending, **errors})
            if final:
                break
            directions, factor, update = fit_lights(
                result.normal_matrices,
                result.normal_targets,
                directions,
                factor,
                anchor,
                options.fixed_intensities,
            )
            pending = {
                "iteration": k + 1,
                **update,
                "used_fraction": float(result.inliers / max(result.usable, 1)),
            }
            log.info(
                "light refinement iteration %d: mean direction change %.3f deg (max %.3f)",
                k + 1,
                pending["mean_direction_change_deg"],
                pending["max_direction_change_deg"],
            )
    params = dict(result.params)
    listed = None if black is None else black.tolist()
    if not refine:
        return Solved(params, None, None, history, time.perf_counter() - started, black=listed)
    params["refine_iterations"] = refine
    # The observations were already divided by the file's intensities, so the refined relative
    # intensity multiplies them.
    intensities = source.header.light_intensities * factor.reshape(-1, 1)
    return Solved(
        params, directions, intensities, history, time.perf_counter() - started, black=listed
    )


def solve_near_bands(
    store: ObservationStore,
    source: SolveInput,
    options: ReconstructOptions,
    writer: _OutputWriter,
    bars: ProgressBars,
    stage: Path,
    black: np.ndarray | None = None,
) -> Solved:
    """Stage 3 with lights at a finite distance: rounds of band solves and depth, then the last.

    Each round solves every band with per-pixel light vectors at the current depth
    (:func:`ps_lab.reconstruct.near.solve_near`) into a whole-image normal map, which
    :func:`ps_lab.reconstruct.near.near_light_rounds` integrates to depth (the outline's height
    as stated by the options or the dataset's ``object_outline.txt``, else searched); the noise
    level is estimated on the store's sample, so bands agree. The final pass at the settled depth
    hands every band to ``writer``; ``depth.npy`` (heights above the spheres' plane, pixel
    units, NaN off the mask) is written beside the normals.

    With ``options.refine_lights`` = K, K times: the rounds settle, then every light's relative
    intensity is re-fitted on the store's sample at the settled points
    (:func:`ps_lab.reconstruct.near.fit_near_intensities`) and the rounds run again; the refined
    intensities are returned (``light_intensities.txt`` of the result).
    """
    started = time.perf_counter()
    lights, mask = source.near, store.mask
    assert lights is not None
    rows, cols = np.nonzero(mask)
    method = options.method
    fixed: dict = {}
    sample = (store.sample_observations, store.sample_valid, store.sample_index)
    set_noise = None
    if solver(method).estimates_noise and store.sample_index.size:
        # the same level for every band, re-estimated on the sample at each height tried
        set_noise = lambda sigma: fixed.__setitem__("noise_sigma", sigma)  # noqa: E731
    params: dict = {}

    def solve_pass(depth: np.ndarray, advance, final: bool) -> np.ndarray:
        normals = np.zeros((*mask.shape, 3))
        for band in store.bands:
            if band.pixel_count == 0:
                continue
            observations, valid = store.read(band)
            if black is not None:
                valid &= observations > black[:, None]
            pixels = slice(band.pixel_start, band.pixel_start + band.pixel_count)
            r, c = rows[pixels], cols[pixels]
            vectors = lights.vectors(lights.points(mask.shape, r, c, depth[r, c]))
            solution = solve_near(
                observations, vectors, method=method, valid=valid, threads=options.threads,
                progress=advance, **fixed, **options.solver_parameters(),
            )
            params.update(solution.params)
            normals[r, c] = solution.normals
            if final:
                reduced = reduce_solution(band.index, solution, valid)
                colour = store.read_colour(band)
                if colour is not None:
                    reduced.colour_albedo = band_colour_albedo(
                        reduced, solution, valid, colour, vectors.transpose(1, 0, 2)
                    )
                writer.add(band, reduced)
        return normals

    def sample_solve(observations, valid, vectors):
        return solve_near(observations, vectors, method=method, valid=valid,
                          threads=options.threads, **fixed, **options.solver_parameters())

    outline = options.object_outline if options.object_outline is not None else source.outline
    factors = np.ones(store.n_lights)
    history: list[dict] = [{"iteration": 0}] if options.refine_lights else []
    with bars(store.pixels, f"{method} (near lights): round 1") as advance:
        round_count = [0]

        def round_normals(depth: np.ndarray) -> np.ndarray:
            round_count[0] += 1
            advance(0, description=f"{method} (near lights): round {round_count[0]}")
            return solve_pass(depth, advance, final=False)

        for k in range(options.refine_lights + 1):
            rounds = near_light_rounds(round_normals, mask, lights, sample, sample_solve,
                                       outline_depth=outline, set_noise=set_noise)
            if k == options.refine_lights:
                break
            lights, step = _refine_near_intensities(lights, rounds, store, sample_solve)
            factors = lights.intensities
            history.append({"iteration": k + 1, **step})
            log.info("near intensity refinement %d: rms change %.3f %%, conditioning %.3g",
                     k + 1, step["intensity_change_rms_pct"], step["conditioning"])
        advance(0, description=f"{method} (near lights): final pass")
        solve_pass(rounds.depth, advance, final=True)
    np.save(stage / "depth.npy", np.where(mask, rounds.depth, np.nan).astype(np.float32))
    log.info("near lights: %d rounds, depth changes %s px", len(rounds.changes), rounds.changes)
    listed = None if black is None else black.tolist()
    intensities = None
    if options.refine_lights:
        params["refine_iterations"] = options.refine_lights
        intensities = source.header.light_intensities * factors.reshape(-1, 1)
        if outline is None:
            log.warning("near-light intensities refined with the outline's height unknown: the "
                        "two trade off (docs/solvers.md); state it with calibrate --object")
    return Solved(params, None, intensities, history, time.perf_counter() - started, rounds,
                  listed)


def _refine_near_intensities(lights: NearLights, rounds: NearRounds, store: ObservationStore,
                             sample_solve) -> tuple[NearLights, dict]:
    """One intensity refinement step on the store's sample at the rounds' settled points."""
    rows, cols = np.nonzero(store.mask)
    index = store.sample_index
    points = lights.points(store.mask.shape, rows[index], cols[index],
                          rounds.depth[rows[index], cols[index]])
    vectors = lights.vectors(points)
    observations, valid = store.sample_observations, store.sample_valid
    use = valid & np.isfinite(observations) & ~sample_solve(observations, valid, vectors).outliers
    current = lights.intensities if np.size(lights.intensities) else np.ones(store.n_lights)
    try:
        factors, conditioning = fit_near_intensities(observations, use, vectors)
    except SolverInputError as exc:
        log.warning("near-light intensities kept: %s", exc)
        factors, conditioning = np.ones(current.size), float("nan")
    updated = current * factors
    updated = updated / updated.mean()
    change = 100.0 * (factors - 1.0)
    step = {
        "intensity_change_rms_pct": float(np.sqrt(np.mean(change ** 2))),
        "intensity_change_max_pct": float(np.abs(change).max()),
        "conditioning": conditioning,
        "outline_height_px": rounds.outline,
    }
    return dataclasses.replace(lights, intensities=updated), step


# --- one solve pass over the bands ----------------------------------------------------------


@dataclass
class _PassResult:
    params: dict
    error_sum: float = 0.0
    all_have_truth: bool = True
    normal_matrices: np.ndarray | None = None  # (n, 6) sums of x x^T over each light's inliers
    normal_targets: np.ndarray | None = None  # (n, 3) sums of y x
    inliers: int = 0
    usable: int = 0


def _whole_image_parameters(
    store: ObservationStore, vectors: np.ndarray, options: ReconstructOptions, intensities
) -> dict:
    """The noise level a single whole-image solve would estimate, fixed for every band.

    ``solve`` estimates it from an evenly spaced sample of all pixels (at most ``max_pixels`` of
    :func:`ps_lab.reconstruct.estimate_noise`); the store kept that very sample, so the estimate
    on it is the whole-image one. Each band is solved with ``noise_sigma=`` it, from which
    ``solve`` derives the outlier threshold (and SBL's ``lam``), so results do not depend on the
    banding. Least squares takes no noise level; SBL also gets the noise floor (``noise_floor=``,
    :func:`ps_lab.reconstruct.estimate_noise_model`) of its default ``lam`` and each light's share
    of it (``light_noise=``: the images were divided by the file's light intensities).
    """
    if not solver(options.method).estimates_noise or store.sample_index.size == 0:
        return {}
    workers = int(options.threads) if options.threads else (os.cpu_count() or 1)
    with ThreadPoolExecutor(max(workers, 1)) as pool:
        return _noise_parameters(store, vectors, options, intensities, pool.map, workers)


def _noise_parameters(store, vectors, options, intensities, mapper, workers) -> dict:
    row = solver(options.method)
    sbl_like = row.sbl_noise
    light_noise = light_noise_factors(intensities, options.channel) if sbl_like else None
    sigma, floor = estimate_noise_model(
        store.sample_observations,
        vectors,
        store.sample_valid,
        max_pixels=store.sample_index.size,
        light_noise=light_noise,
        mapper=mapper,
        workers=workers,
    )
    if not sbl_like:
        return {"noise_sigma": sigma}
    whole = {"noise_sigma": sigma, "noise_floor": floor, "light_noise": light_noise}
    if row.pl_noise:  # the PL model's own noise level, on the same sample
        whole["noise_sigma_pl"] = pl_noise_level(
            store.sample_observations, vectors, store.sample_valid,
            segments=options.segments or row.defaults["segments"], noise_sigma=sigma,
            max_pixels=store.sample_index.size, mapper=mapper, workers=workers)
    return whole


def _solve_pass(
    store: ObservationStore,
    header: DatasetHeader,
    executor,
    vectors: np.ndarray,
    options: ReconstructOptions,
    *,
    truth,
    fit: bool,
    writer: _OutputWriter | None,
    advance: Callable[..., None],
    label: str,
    intensities: np.ndarray,
    black: np.ndarray | None = None,
) -> _PassResult:
    """Solve every band once with the light vectors ``vectors`` (n, 3), on ``executor``.

    ``intensities`` (n, 3) are the light intensities the observations were divided by;
    observations at or below ``black`` (n,) are shadows.

    Band results may arrive in any order (Dask); the writer takes them as they come, and the
    parameters, error sums and refinement sums are combined in band order, as one process would.
    """
    fixed = _whole_image_parameters(store, vectors, options, intensities)
    count = len(store.bands)
    started = time.perf_counter()
    done: dict[int, BandResult] = {}
    for band_result in executor.solve(
        store,
        header,
        vectors,
        method=options.method,
        parameters={**fixed, **options.solver_parameters()},
        final=writer is not None,
        truth=truth,
        advance=advance,
        label=label,
        black=black,
    ):
        band = store.bands[band_result.index]
        if writer is not None:
            writer.add(band, band_result)
            band_result.normals = band_result.albedo = band_result.corruption = None
            band_result.colour_albedo = None
        done[band.index] = band_result
        log.info(
            "%s: band %d/%d done (%d pixels, %.1f s since the pass began)",
            label,
            band.index + 1,
            count,
            band.pixel_count,
            time.perf_counter() - started,
        )
    return _combine(done, store.n_lights, fit)


def _combine(done: dict[int, BandResult], n: int, fit: bool) -> _PassResult:
    """Add up a pass's band results in band order (the order of a single-process run)."""
    ordered = [done[index] for index in sorted(done)]
    result = _PassResult(params=dict(ordered[0].params) if ordered else {})
    if fit:
        result.normal_matrices = np.zeros((n, 6))
        result.normal_targets = np.zeros((n, 3))
    for band_result in ordered:
        result.all_have_truth &= band_result.all_have_truth
        result.error_sum += band_result.error_sum
        for matrices, targets, inliers, usable in band_result.fit_sums if fit else ():
            result.normal_matrices += matrices
            result.normal_targets += targets
            result.inliers += inliers
            result.usable += usable
    return result
