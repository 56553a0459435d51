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
import re
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.errors import OutputError
from ps_lab.io.bands import ObservationStore, plan_bands, stage_observations
from ps_lab.io.dataset import DatasetHeader, open_dataset
from ps_lab.io.files import json_safe, staged_folder
from ps_lab.io.truth import open_normal_gt
from ps_lab.reconstruct._outputs import (
    ERROR_BIN_DEG,
    _Histogram,
    _OutputWriter,
    albedo_picture,
    corruption_picture,
    normal_picture,
    write_png,
)
from ps_lab.reconstruct._refine import fit_lights, light_fit_sums
from ps_lab.reconstruct._solution import Solution
from ps_lab.reconstruct._solve import estimate_noise, solve
from ps_lab.reconstruct.depth import DepthOptions, write_depth, write_normal_maps
from ps_lab.reconstruct.metrics import angular_errors_deg

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
        raise OutputError(f"memory budget {text!r}: expected a size such as 800MB or 2GB")
    size = int(float(match.group(1)) * _SIZE_UNITS[match.group(2).lower()])
    if size <= 0:
        raise OutputError(f"memory budget {text!r} must be positive")
    return size


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
    depth: str | None = None

    def __post_init__(self) -> None:
        if self.depth is not None:
            DepthOptions(method=self.depth)  # validates the method
        if self.staging not in STAGING:
            raise OutputError(f"staging must be auto, memory or file, got {self.staging!r}")
        budget = self.memory_budget
        if not isinstance(budget, int):
            object.__setattr__(self, "memory_budget", parse_memory_size(budget))
        elif budget <= 0:
            raise OutputError(f"memory budget must be positive, got {budget}")

    def solver_parameters(self) -> dict[str, Any]:
        """Keyword arguments for :func:`ps_lab.reconstruct.solve` that these options fix.

        None yet: solver parameters added as fields (``lam``, ``sigma_x2``, ``max_iter``, ``tol``)
        are returned here, and every band's solve receives them.
        """
        return {}

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


@dataclass
class _Solved:
    """Stage 3's product: parameters, lights after refinement, history and solve time."""

    params: dict
    directions: np.ndarray | None
    intensities: np.ndarray | None
    history: list[dict]
    seconds: float


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
    source = _read(dataset, options)
    with staged_folder(out, check=check_output_folder, error=OutputError) as stage:
        store = _stage(source, options, stage, bars)
        timings["read_seconds"] = time.perf_counter() - started
        with store:
            writer = _OutputWriter(stage, store.mask, source.truth, store.n_lights)
            solved = _solve_bands(store, source, options, writer, bars)
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
    return _Input(header, header.read_mask(), open_normal_gt(header.root, header.shape))


def _stage(source: _Input, options: ReconstructOptions, stage: Path, bars) -> ObservationStore:
    """Stage 2: decode every frame once into a row-band store (in memory or a file in ``stage``)."""
    started = time.perf_counter()
    header, mask = source.header, source.mask
    n = len(header.names)
    budget = options.memory_budget
    bands = plan_bands(mask, band_pixels(budget, n))
    pixels = int(mask.sum())
    store_bytes = n * (4 * pixels + (pixels + 7 * len(bands)) // 8)
    small = store_bytes <= IN_MEMORY_SHARE * budget
    in_memory = options.staging == "memory" or (options.staging == "auto" and small)
    with bars(n, "reading images") as advance:
        store = stage_observations(
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
        "memory" if in_memory else "a file",
    )
    return store


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
) -> _Solved:
    """Stage 3: K + 1 solve passes over the bands (K = ``options.refine_lights``).

    Between passes each light is re-fitted from the sums the pass accumulated; the last pass
    hands every band to ``writer``.
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
                directions * factor[:, None],
                options,
                truth=source.truth if refine else None,
                fit=not final,
                writer=writer if final else None,
                advance=advance,
                label=method if passes == 1 else f"{method} pass {k + 1}/{passes}",
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
    if not refine:
        return _Solved(params, None, None, history, time.perf_counter() - started)
    params["refine_iterations"] = refine
    # The observations were already divided by the file's intensities, so the refined relative
    # intensity multiplies them.
    intensities = source.header.light_intensities * factor.reshape(-1, 1)
    return _Solved(params, directions, intensities, history, time.perf_counter() - started)


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
    metrics["shadow_threshold"] = options.shadow_threshold
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


def _whole_image_parameters(store: ObservationStore, vectors: np.ndarray, method: str) -> dict:
    """The noise level a single whole-image solve would estimate, fixed for every band.

    ``solve`` estimates it from an evenly spaced sample of all pixels (at most ``max_pixels`` of
    :func:`ps_lab.reconstruct.estimate_noise`); the store kept that very sample, so the estimate
    on it is the whole-image one. Each band is solved with ``noise_sigma=`` it, from which
    ``solve`` derives the outlier threshold (and SBL's ``lam``), so results do not depend on the
    banding. Least squares takes no noise level.
    """
    if method == "ls" or store.sample_index.size == 0:
        return {}
    sigma = estimate_noise(
        store.sample_observations,
        vectors,
        store.sample_valid,
        max_pixels=store.sample_index.size,
    )
    return {"noise_sigma": sigma}


def _solve_pass(
    store: ObservationStore,
    vectors: np.ndarray,
    options: ReconstructOptions,
    *,
    truth,
    fit: bool,
    writer: _OutputWriter | None,
    advance: Callable[..., None],
    label: str,
) -> _PassResult:
    """Solve every band once with the light vectors ``vectors`` (n, 3)."""
    fixed = _whole_image_parameters(store, vectors, options.method)
    n = store.n_lights
    result = _PassResult(params={})
    if fit:
        result.normal_matrices = np.zeros((n, 6))
        result.normal_targets = np.zeros((n, 3))
    count = len(store.bands)
    started = time.perf_counter()
    for band in store.bands:
        if band.pixel_count == 0:
            continue
        advance(0, description=f"{label}: band {band.index + 1}/{count}")
        observations, valid = store.read(band)
        solution = solve(
            observations,
            vectors,
            method=options.method,
            valid=valid,
            threads=options.threads,
            progress=advance,
            **fixed,
            **options.solver_parameters(),
        )
        if not result.params:
            result.params = dict(solution.params)
        if writer is not None:
            writer.add(band, solution, valid)
        if truth is not None:
            rows = slice(band.row_start, band.row_stop)
            gt = truth.rows(band.row_start, band.row_stop)[store.mask[rows]]
            result.all_have_truth &= bool(np.all(np.linalg.norm(gt, axis=1) > 0.5))
            result.error_sum += float(angular_errors_deg(solution.normals, gt).sum())
        if fit:
            _accumulate_fit(result, observations, valid, solution)
        del observations, valid, solution
        log.info(
            "%s: band %d/%d done (%d pixels, %.1f s since the pass began)",
            label,
            band.index + 1,
            count,
            band.pixel_count,
            time.perf_counter() - started,
        )
    return result


def _accumulate_fit(result: _PassResult, observations, valid, solution, chunk: int = 65536) -> None:
    """Add one band's per-light least-squares sums (:func:`ps_lab.reconstruct.light_fit_sums`).

    The sums add over pixels; taking the band in chunks of pixels bounds the float64 copies.
    """
    for a in range(0, observations.shape[1], chunk):
        b = min(a + chunk, observations.shape[1])
        part = Solution(
            solution.normals[a:b],
            solution.albedo[a:b],
            solution.outliers[:, a:b],
            solution.iterations[a:b],
        )
        normal_matrices, normal_targets, used = light_fit_sums(
            observations[:, a:b], valid[:, a:b], part
        )
        result.normal_matrices += normal_matrices
        result.normal_targets += normal_targets
        result.inliers += used
        result.usable += int((valid[:, a:b] & np.isfinite(observations[:, a:b])).sum())
