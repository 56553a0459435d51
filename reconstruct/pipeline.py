"""The reconstruction flow, one owner: read -> stage -> solve bands -> write.

:func:`reconstruct_to_folder` is the one production path of ``ps-lab reconstruct``. It takes one
:class:`ReconstructOptions` (a frozen dataclass) and returns one :class:`ReconstructResult`; the
stages below it receive that options object and return what they made, so a new option is one
field here and a new stage one function called from :func:`reconstruct_to_folder`.

1. **read**: open the dataset header, mask and (optional) ground truth (:mod:`ps_lab.io.dataset`);
2. **stage**: decode each frame once into a row-band observation store in bounded memory
   (:func:`ps_lab.io.bands.stage_observations`, ``docs/scale.md``); a small dataset is one band;
3. **solve bands**: each pass solves every band (:func:`ps_lab.reconstruct.solve`); light
   refinement runs K + 1 passes, accumulating each light's least-squares sums band by band;
4. **write**: the last pass writes each band's rows of every output (:mod:`._outputs`), then
   ``metrics.json`` is written once, here (:func:`_write_metrics`).

Everything is written into a staged folder that replaces the output folder only on success
(:func:`ps_lab.io.files.staged_folder`): a failed or interrupted run leaves no partial output, and
an earlier result stays untouched until the new one is ready.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import logging
import math
import re
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.errors import DatasetError, OutputError
from ps_lab.geometry import scene_points
from ps_lab.io.bands import ObservationStore, plan_bands
from ps_lab.io.dataset import DatasetHeader, open_dataset
from ps_lab.io.files import json_safe, staged_folder
from ps_lab.io.truth import open_normal_gt
from ps_lab.reconstruct._bands import BandResult, LocalBands
from ps_lab.reconstruct._kernels import start_warm_up
from ps_lab.reconstruct._outputs import (
    ERROR_BIN_DEG,
    _Histogram,
    _OutputWriter,
    albedo_picture,
    check_solved_share,
    corruption_picture,
    normal_picture,
    write_png,
)
from ps_lab.reconstruct._refine import fit_lights
from ps_lab.reconstruct._shadows import black_threshold
from ps_lab.reconstruct._solution import SolverInputError
from ps_lab.reconstruct._solve import (
    estimate_noise,
    estimate_noise_model,
    light_noise_factors,
)
from ps_lab.reconstruct.depth import DepthOptions, write_depth, write_normal_maps
from ps_lab.reconstruct.near import (
    NearLights,
    NearRounds,
    estimate_noise_near,
    near_light_rounds,
    solve_near,
)

__all__ = [
    "BYTES_PER_OBSERVATION",
    "BYTES_PER_PIXEL",
    "DEFAULT_MEMORY_BUDGET",
    "ERROR_BIN_DEG",
    "METRICS",
    "RESULT_FORMAT",
    "OutputError",
    "ReconstructOptions",
    "ReconstructResult",
    "_Histogram",
    "albedo_picture",
    "band_pixels",
    "check_output_folder",
    "corruption_picture",
    "normal_picture",
    "parse_memory_size",
    "reconstruct_to_folder",
    "write_png",
]

log = logging.getLogger(__name__)

RESULT_FORMAT = "ps-lab-reconstruction"
METRICS = "metrics.json"
DEFAULT_MEMORY_BUDGET = 1 << 30
# Bytes held per observation of a band while it is solved: the float32 observations, their
# validity, the solver's usable and outlier masks, and headroom for the refinement sums.
BYTES_PER_OBSERVATION = 12
# Bytes per pixel of a band: the solver's per-pixel results and the band's output images.
BYTES_PER_PIXEL = 200
# A store at most this share of the budget stays in memory; larger ones go to a temporary file.
IN_MEMORY_SHARE = 0.25
_SIZE_UNITS = {"": 1 << 20, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}
STAGING = ("auto", "memory", "file")
LIGHT_MODELS = ("auto", "near", "directional")
# Per-pixel light vectors (float64 x 3) held beside a band's observations in near-light mode.
NEAR_BYTES_PER_OBSERVATION = 24

ProgressBars = Callable[[int, str], Any]


def parse_memory_size(text: str) -> int:
    """Parse a memory size such as ``"512MB"``, ``"1.5G"``, ``"2 GiB"`` or ``"800"`` (MB), in bytes.

    Raises
    ------
    OutputError
        Not a positive size.

    """
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([kKmMgGtT]?)(?:i?[bB])?\s*", str(text))
    if match is None:
        raise OutputError(f"--memory-budget {text!r}: expected a size such as 800MB or 2GB")
    size = int(float(match.group(1)) * _SIZE_UNITS[match.group(2).lower()])
    if size <= 0:
        raise OutputError(f"--memory-budget {text!r} must be positive")
    return size


# Solver fields of ReconstructOptions -> (command-line flag, methods they apply to).
SOLVER_OPTIONS = {
    "lam": ("--lambda", ("sbl", "rpca")),
    "sigma_x2": ("--sigma-x2", ("sbl",)),
    "max_iter": ("--max-iter", ("l1", "sbl", "rpca")),
    "tol": ("--tol", ("l1", "sbl", "rpca")),
}


def _check_solver_options(options: ReconstructOptions) -> None:
    """Raise :class:`SolverInputError` for a bad solver field.

    A field must be finite and positive (``max_iter`` whole) and apply to ``options.method``.
    """
    for name, (flag, methods) in SOLVER_OPTIONS.items():
        value = getattr(options, name)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SolverInputError(f"{flag} must be a number, got {value!r}")
        if not math.isfinite(value) or value <= 0:
            raise SolverInputError(f"{flag} must be finite and positive, got {value!r}")
        if name == "max_iter" and int(value) != value:
            raise SolverInputError(f"{flag} must be a whole number, got {value!r}")
        if options.method not in methods:
            raise SolverInputError(
                f"{flag} does not apply to method {options.method} (only {', '.join(methods)})"
            )


def band_pixels(memory_budget: int, n_lights: int) -> int:
    """Most mask pixels per band that keep one band's solve within ``memory_budget`` bytes."""
    per_pixel = n_lights * BYTES_PER_OBSERVATION + BYTES_PER_PIXEL
    return max(int(memory_budget) // per_pixel, 1)


@dataclass(frozen=True)
class ReconstructOptions:
    """Every choice of one reconstruction; passed whole to each stage of the pipeline.

    Attributes
    ----------
    method : {"ls", "l1", "sbl", "rpca"}
        Solver. Noise level and outlier threshold are estimated once for the whole image; R-PCA's
        low-rank model is fitted per band.
    channel : {"r", "g", "b", "mean"}
        As for :func:`ps_lab.io.dataset.load_dataset`.
    shadow_threshold : float or None
        Observations at or below it are dropped (as for :func:`ps_lab.io.dataset.load_dataset`).
    threads : int or None
        Solver threads (default all cores).
    refine_lights : int
        Iterations of light refinement (0 = none); the refined lights are written as
        ``light_directions.txt`` / ``light_intensities.txt``.
    fixed_intensities : bool
        Refine directions only.
    memory_budget : int or str
        Bytes, or a size such as ``"1GB"`` (:func:`parse_memory_size`; stored as bytes), that one
        band's solve may use; sets the band height.
    staging : {"auto", "memory", "file"}
        Backing of the observation store: in memory when small (``auto``), or forced.
    lights : {"auto", "near", "directional"}
        Light model: ``near`` solves with per-pixel light vectors from ``light_positions.txt``
        (LEDs at a finite distance, alternating normals and depth; :mod:`ps_lab.reconstruct.near`),
        ``directional`` with ``light_directions.txt`` alone; ``auto`` is near when the dataset
        has ``light_positions.txt``.
    scheduler : str or None
        Address of a Dask scheduler (``tcp://host:8786``): the frames are staged and the bands
        solved as tasks on its workers (:mod:`ps_lab.reconstruct.distributed`; the dataset and
        the output folder must be on a filesystem the workers share). None: in this process.
    lam, sigma_x2, max_iter, tol : float, float, int, float, or None
        Solver parameters in the units of ``docs/solvers.md`` (relative to each pixel's robust
        scale); None keeps the method's default. ``lam``: SBL's noise variance, or R-PCA's
        sparse weight; ``sigma_x2``: SBL's prior variance of ``x``; ``max_iter`` and ``tol``:
        SBL, L1 and R-PCA. Each must be finite and positive, and apply to ``method``.
    depth : {"poisson", "bilateral"} or None
        Also integrate the normals into depth maps and a mesh (:mod:`ps_lab.reconstruct.depth`).
    """

    method: str = "sbl"
    channel: str = "mean"
    shadow_threshold: float | None = None
    threads: int | None = None
    refine_lights: int = 0
    fixed_intensities: bool = False
    memory_budget: int = DEFAULT_MEMORY_BUDGET
    staging: str = "auto"
    lights: str = "auto"
    scheduler: str | None = None
    lam: float | None = None
    sigma_x2: float | None = None
    max_iter: int | None = None
    tol: float | None = None

    depth: str | None = None

    def __post_init__(self) -> None:
        if self.depth is not None:
            DepthOptions(method=self.depth)  # validates the method
        _check_solver_options(self)
        if self.shadow_threshold is not None and not math.isfinite(self.shadow_threshold):
            raise OutputError(f"--shadow-threshold {self.shadow_threshold} is not a finite number")
        if self.staging not in STAGING:
            raise OutputError(f"staging must be auto, memory or file, got {self.staging!r}")
        if self.lights not in LIGHT_MODELS:
            raise OutputError(f"lights must be auto, near or directional, got {self.lights!r}")
        budget = self.memory_budget
        if not isinstance(budget, int):
            object.__setattr__(self, "memory_budget", parse_memory_size(budget))
        elif budget <= 0:
            raise OutputError(f"memory budget must be positive, got {budget}")

    def solver_parameters(self) -> dict[str, Any]:
        """Keyword arguments for :func:`ps_lab.reconstruct.solve` that these options fix.

        The solver fields that are set (``lam`` is R-PCA's ``lam_sparse``); every band's solve
        receives them.
        """
        given = {name: getattr(self, name) for name in SOLVER_OPTIONS}
        names = {"lam": "lam_sparse"} if self.method == "rpca" else {}
        return {names.get(k, k): v for k, v in given.items() if v is not None}

    def replace(self, **changes: Any) -> ReconstructOptions:
        """Return a copy with some fields changed (:func:`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class ReconstructResult:
    """What :func:`reconstruct_to_folder` made.

    Attributes
    ----------
    out : Path
        The result folder.
    metrics : dict
        Exactly what ``out / "metrics.json"`` holds (method, parameters, pixels, lights,
        ``solve_seconds``, iterations, angular errors when ground truth exists, streaming,
        refinement and timings).
    """

    out: Path
    metrics: dict[str, Any]

    @property
    def pixels(self) -> int:
        """Mask pixels reconstructed."""
        return int(self.metrics["pixels"])

    @property
    def lights(self) -> int:
        """Lights (images) used."""
        return int(self.metrics["lights"])

    @property
    def solve_seconds(self) -> float:
        """Seconds spent in the solve passes."""
        return float(self.metrics["solve_seconds"])

    @property
    def angular_error_deg(self) -> dict[str, float] | None:
        """Mean / median / p90 / max angular error against ground truth, or None."""
        return self.metrics.get("angular_error_deg")

    @property
    def refinement_history(self) -> list[dict[str, Any]]:
        """One entry per light-refinement iteration (empty without refinement)."""
        return list(self.metrics.get("refinement", {}).get("history", []))


def _is_result_folder(folder: Path) -> bool:
    if not any(folder.iterdir()):
        return True
    try:
        metrics = json.loads((folder / METRICS).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(metrics, dict) and metrics.get("format") == RESULT_FORMAT


def check_output_folder(out: Path) -> None:
    """Raise :class:`OutputError` unless ``out`` is absent, empty or an earlier ps-lab result."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder")
    if out.is_dir() and not _is_result_folder(out):
        raise OutputError(
            f"{out}: exists and is not a ps-lab result folder (no {METRICS}); "
            "choose another --out or remove it"
        )


@contextmanager
def _no_bar(total: int, description: str) -> Iterator[Callable[..., None]]:
    yield lambda n=1, description=None: None


# --- the flow -------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Input:
    """Stage 1's product: the dataset's header, mask and ground truth (or None)."""

    header: DatasetHeader
    mask: np.ndarray
    truth: Any
    near: NearLights | None = None  # lights at a finite distance, when the options choose them


@dataclass
class _Solved:
    """Stage 3's product: parameters, lights after refinement, history and solve time."""

    params: dict
    directions: np.ndarray | None
    intensities: np.ndarray | None
    history: list[dict]
    seconds: float
    near: NearRounds | None = None
    black: list[float] | None = None


def reconstruct_to_folder(
    dataset: Path,
    out: Path,
    options: ReconstructOptions | None = None,
    *,
    progress_bars: ProgressBars | None = None,
) -> ReconstructResult:
    """Reconstruct a dataset folder into ``out``, streamed by row bands in bounded memory.

    Parameters
    ----------
    dataset : Path
        Image folder or capture run.
    out : Path
        Output folder: absent, empty or an earlier result.
    options : ReconstructOptions or None
        Every choice of the reconstruction (defaults when None).
    progress_bars : callable or None
        ``progress_bars(total, description)`` returning a context manager that yields
        ``advance(n=1, description=None)`` (e.g. :func:`ps_lab._cli_util.progress_bar`): one bar
        for reading the frames, one for the solve passes (pixels, band shown in the description).

    Returns
    -------
    ReconstructResult

    """
    options = options if options is not None else ReconstructOptions()
    bars = progress_bars or _no_bar
    out = Path(out)
    check_output_folder(out)
    started = time.perf_counter()
    timings: dict[str, float] = {}
    # The solver kernels load while the images are read (see _kernels.warm_up).
    warm_up = start_warm_up(options.method)
    source = _read(dataset, options)
    with _band_executor(options) as executor, staged_folder(
        out, check=check_output_folder, error=OutputError
    ) as stage:
        store = _stage(source, options, stage, bars, executor)
        timings["read_seconds"] = time.perf_counter() - started
        warm_up.join()
        with store:
            writer = _OutputWriter(stage, store.mask, source.truth, store.n_lights)
            black = _black_threshold(store, source.header, options)
            if source.near is None:
                solved = _solve_bands(store, source, options, writer, bars, executor, black)
            else:
                solved = _solve_near_bands(store, source, options, writer, bars, stage, black)
            check_solved_share(source.header.root, writer.solved_count, store.pixels)
            timings["solve_seconds"] = solved.seconds
            written = time.perf_counter()
            metrics = _write_results(writer, stage, source, options, store, solved, timings)
            timings["write_seconds"] = time.perf_counter() - written
            metrics["timings"] = dict(timings)
            _write_surface(stage, options, metrics)
            _write_metrics(stage, metrics)
    metrics["out"] = str(out)
    return ReconstructResult(out=out, metrics=metrics)


def _read(dataset: Path, options: ReconstructOptions) -> _Input:
    """Stage 1: the dataset's header, mask and ground truth."""
    header = open_dataset(dataset, channel=options.channel)
    assert header.shape is not None
    near = _near_lights(header, options)
    return _Input(header, header.read_mask(), open_normal_gt(header.root, header.shape), near)


def _near_lights(header: DatasetHeader, options: ReconstructOptions) -> NearLights | None:
    """The near-light model the options ask for (None: directional)."""
    positions = header.light_positions
    if options.lights == "directional" or (options.lights == "auto" and positions is None):
        return None
    if positions is None:
        raise DatasetError(
            f"{header.root}: --lights near needs light_positions.txt "
            "(calibrate with two chrome spheres)"
        )
    if options.refine_lights:
        raise DatasetError(
            "--refine-lights refines directional lights: add --lights directional"
        )
    if options.method == "rpca":
        raise DatasetError("rpca needs one light matrix for all pixels: add --lights directional")
    if options.scheduler is not None:
        raise DatasetError("--scheduler solves directional lights only: add --lights directional")
    n = len(header.names)
    anisotropy = header.light_anisotropy if header.light_anisotropy is not None else np.zeros(n)
    return NearLights(positions, header.light_directions, anisotropy)


@contextmanager
def _band_executor(options: ReconstructOptions) -> Iterator[Any]:
    """The executor of the band work: this process, or the Dask cluster ``options.scheduler``.

    The one place that loads :mod:`ps_lab.reconstruct.distributed` (and so Dask): a run without
    a scheduler never imports it.
    """
    if options.scheduler is None:
        yield LocalBands(options.threads)
        return
    from ps_lab.reconstruct import distributed

    with distributed.connect(options.scheduler) as client:
        yield distributed.DaskBands(client)


def _stage(
    source: _Input, options: ReconstructOptions, stage: Path, bars, executor
) -> ObservationStore:
    """Stage 2: decode every frame once into a row-band store (in memory or a file in ``stage``)."""
    started = time.perf_counter()
    header, mask = source.header, source.mask
    n = len(header.names)
    budget = options.memory_budget
    extra = 0 if source.near is None else NEAR_BYTES_PER_OBSERVATION // BYTES_PER_OBSERVATION
    per_light = n * (1 + extra)
    pixels = int(mask.sum())
    keep_plan = options.method == "rpca" or options.refine_lights > 0
    limit = executor.band_pixels(band_pixels(budget, per_light), pixels, keep_plan)
    bands = plan_bands(mask, limit)
    store_bytes = n * (4 * pixels + (pixels + 7 * len(bands)) // 8)
    small = store_bytes <= IN_MEMORY_SHARE * budget
    in_memory = options.staging == "memory" or (options.staging == "auto" and small)
    with bars(n, "reading images") as advance:
        store = executor.stage(
            header,
            mask,
            bands,
            channel=options.channel,
            shadow_threshold=options.shadow_threshold,
            folder=stage,
            in_memory=in_memory,
            sample_pixels=_default(estimate_noise, "max_pixels", 20000),
            progress=advance,
        )
    log.info(
        "read %d images (%dx%d, %d mask pixels) in %.1f s: %d bands of at most %d pixels, "
        "%.2f GB staged in %s",
        n,
        mask.shape[1],
        mask.shape[0],
        pixels,
        time.perf_counter() - started,
        len(bands),
        max(band.pixel_count for band in bands),
        store.nbytes / 1e9,
        "memory" if store.path is None else "a file",
    )
    return store


def _black_threshold(
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
    black = black_threshold(store.sample_observations, store.sample_valid, factors)
    if black is not None:
        store.sample_valid &= store.sample_observations > black[:, None]
        log.info("shadows: observations within %.3g (mean) of black are dropped", black.mean())
    return black


def _default(function: Callable, name: str, fallback: Any) -> Any:
    parameter = inspect.signature(function).parameters.get(name)
    if parameter is None or parameter.default is inspect.Parameter.empty:
        return fallback
    return parameter.default


def _solve_bands(
    store: ObservationStore,
    source: _Input,
    options: ReconstructOptions,
    writer: _OutputWriter,
    bars: ProgressBars,
    executor,
    black: np.ndarray | None = None,
) -> _Solved:
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
        return _Solved(params, None, None, history, time.perf_counter() - started, black=listed)
    params["refine_iterations"] = refine
    # The observations were already divided by the file's intensities, so the refined relative
    # intensity multiplies them.
    intensities = source.header.light_intensities * factor.reshape(-1, 1)
    return _Solved(
        params, directions, intensities, history, time.perf_counter() - started, black=listed
    )


def _solve_near_bands(
    store: ObservationStore,
    source: _Input,
    options: ReconstructOptions,
    writer: _OutputWriter,
    bars: ProgressBars,
    stage: Path,
    black: np.ndarray | None = None,
) -> _Solved:
    """Stage 3 with lights at a finite distance: rounds of band solves and depth, then the last.

    Each round solves every band with per-pixel light vectors at the current depth
    (:func:`ps_lab.reconstruct.near.solve_near`) into a whole-image normal map, which
    :func:`ps_lab.reconstruct.near.near_light_rounds` integrates to depth; the noise level is
    estimated once, on the store's sample at the starting plane, so bands agree. The final pass
    at the settled depth hands every band to ``writer``; ``depth.npy`` (heights above the spheres'
    plane, pixel units, NaN off the mask) is written beside the normals.
    """
    started = time.perf_counter()
    lights, mask = source.near, store.mask
    assert lights is not None
    rows, cols = np.nonzero(mask)
    method = options.method
    fixed: dict = {}
    sample = (store.sample_observations, store.sample_valid, store.sample_index)
    if method != "ls" and store.sample_index.size:
        index = store.sample_index
        plane = scene_points(mask.shape, rows[index], cols[index], np.zeros(index.size))
        fixed["noise_sigma"] = estimate_noise_near(
            store.sample_observations, lights.vectors(plane), store.sample_valid
        )
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
            vectors = lights.vectors(scene_points(mask.shape, r, c, depth[r, c]))
            solution = solve_near(
                observations, vectors, method=method, valid=valid, threads=options.threads,
                progress=advance, **fixed, **options.solver_parameters(),
            )
            params.update(solution.params)
            normals[r, c] = solution.normals
            if final:
                writer.add(band, solution, valid)
        return normals

    def sample_solve(observations, valid, vectors):
        return solve_near(observations, vectors, method=method, valid=valid,
                          threads=options.threads, **fixed, **options.solver_parameters())

    with bars(store.pixels, f"{method} (near lights): round 1") as advance:
        round_count = [0]

        def round_normals(depth: np.ndarray) -> np.ndarray:
            round_count[0] += 1
            advance(0, description=f"{method} (near lights): round {round_count[0]}")
            return solve_pass(depth, advance, final=False)

        rounds = near_light_rounds(round_normals, mask, lights, sample, sample_solve)
        advance(0, description=f"{method} (near lights): final pass")
        solve_pass(rounds.depth, advance, final=True)
    np.save(stage / "depth.npy", np.where(mask, rounds.depth, np.nan).astype(np.float32))
    log.info("near lights: %d rounds, depth changes %s px", len(rounds.changes), rounds.changes)
    listed = None if black is None else black.tolist()
    return _Solved(params, None, None, [], time.perf_counter() - started, rounds, listed)


def _write_results(
    writer: _OutputWriter,
    stage: Path,
    source: _Input,
    options: ReconstructOptions,
    store: ObservationStore,
    solved: _Solved,
    timings: dict[str, float],
) -> dict:
    """Stage 4: pictures and light tables; return the metrics (``metrics.json`` comes after)."""
    try:
        metrics = writer.finish(
            source.header,
            solved.params,
            lights=solved.directions,
            intensities=solved.intensities,
            seconds=solved.seconds,
            result_format=RESULT_FORMAT,
        )
    except OSError as exc:
        raise OutputError(f"{stage}: cannot write results ({exc.strerror or exc})") from None
    metrics["channel"] = options.channel
    metrics["solver_options"] = {
        flag[2:]: getattr(options, name) for name, (flag, _) in SOLVER_OPTIONS.items()
    }
    metrics["shadow_threshold"] = options.shadow_threshold
    metrics["black_threshold"] = solved.black
    metrics["light_model"] = "directional" if source.near is None else "near"
    if solved.near is not None:
        metrics["near"] = solved.near.record()
    metrics["streaming"] = {
        "bands": len(store.bands),
        "max_band_pixels": max(band.pixel_count for band in store.bands),
        "memory_budget_bytes": options.memory_budget,
        "staging": "file" if store.path is not None else "memory",
        "staging_bytes": store.nbytes,
    }
    if options.refine_lights:
        metrics["refinement"] = {"iterations": options.refine_lights, "history": solved.history}
    metrics["timings"] = dict(timings)
    return json_safe(metrics)


def _write_surface(stage: Path, options: ReconstructOptions, metrics: dict) -> None:
    """Stage 5: normal maps for other tools and, with ``options.depth``, depth and mesh."""
    started = time.perf_counter()
    normals = np.load(stage / "normals.npy")
    try:
        write_normal_maps(stage, normals, np.linalg.norm(normals, axis=-1) > 0.5)
        if options.depth is not None:
            albedo = np.load(stage / "albedo.npy")
            depth = write_depth(stage, normals, albedo, DepthOptions(method=options.depth))
            metrics["depth"] = json_safe(depth)
    except OSError as exc:
        raise OutputError(f"{stage}: cannot write results ({exc.strerror or exc})") from None
    metrics["timings"]["surface_seconds"] = time.perf_counter() - started


def _write_metrics(folder: Path, metrics: dict) -> None:
    """Write ``metrics.json``: the one place it is written."""
    try:
        (folder / METRICS).write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"{folder}: cannot write results ({exc.strerror or exc})") from None


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
    method = options.method
    if method == "ls" or store.sample_index.size == 0:
        return {}
    light_noise = light_noise_factors(intensities, options.channel) if method == "sbl" else None
    sigma, floor = estimate_noise_model(
        store.sample_observations,
        vectors,
        store.sample_valid,
        max_pixels=store.sample_index.size,
        light_noise=light_noise,
    )
    if method != "sbl":
        return {"noise_sigma": sigma}
    return {"noise_sigma": sigma, "noise_floor": floor, "light_noise": light_noise}


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
