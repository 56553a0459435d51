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

import inspect
import json
import logging
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.appearance.fit import fit_appearance_bands, solved_lights as _solved_lights
from ps_lab.errors import DatasetError, OutputError
from ps_lab.geometry import Camera
from ps_lab.io.bands import ObservationStore, plan_bands
from ps_lab.io.camera import camera_record
from ps_lab.io.coded_frames import frame_coding
from ps_lab.io.dataset import LIGHT_POSITIONS, OBJECT_OUTLINE, DatasetHeader, open_dataset
from ps_lab.io.encoding import frames_encoding
from ps_lab.io.files import json_safe, staged_folder
from ps_lab.io.led_model import FLAT_FIELD, LIGHT_AXES, read_flat_field, read_light_axes
from ps_lab.io.result import METRICS, RESULT_FORMAT, foreign_entries, read_result_metrics
from ps_lab.io.truth import open_normal_gt
from ps_lab.reconstruct._bands import LocalBands
from ps_lab.reconstruct._colour import grey_albedo
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
from ps_lab.reconstruct._passes import (
    ProgressBars,
    Solved,
    SolveInput,
    black_level,
    solve_bands,
    solve_near_bands,
)
from ps_lab.reconstruct._noise import estimate_noise
from ps_lab.reconstruct._warm_up import start_warm_up
from ps_lab.reconstruct.depth import (
    DepthOptions,
    with_result_camera,
    write_depth,
    write_normal_maps,
)
from ps_lab.reconstruct.integrate import IntegrationInputError
from ps_lab.reconstruct.methods import solver
from ps_lab.reconstruct.near import NearLights
from ps_lab.reconstruct.options import (
    BYTES_PER_OBSERVATION,
    BYTES_PER_PIXEL,
    COLOUR_BYTES_PER_OBSERVATION,
    MAX_BAND_PIXELS,
    NEAR_BYTES_PER_OBSERVATION,
    SOLVER_OPTIONS,
    ReconstructOptions,
    auto_memory_budget,
    band_pixels,
    parse_memory_budget,
    parse_memory_size,
)

__all__ = [
    "BYTES_PER_OBSERVATION",
    "BYTES_PER_PIXEL",
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
    "parse_memory_budget",
    "parse_memory_size",
    "reconstruct_to_folder",
    "write_png",
]

log = logging.getLogger(__name__)

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


def check_output_folder(out: Path) -> None:
    """Raise :class:`OutputError` unless ``out`` is absent, empty or an earlier ps-lab result
    holding only files ps-lab wrote (:func:`ps_lab.io.result.foreign_entries`)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder")
    if not out.is_dir() or not any(out.iterdir()):
        return
    metrics = read_result_metrics(out)
    if metrics is None:
        raise OutputError(
            f"{out}: exists and is not a ps-lab result folder (no {METRICS}); "
            "choose another --out or remove it"
        )
    foreign = foreign_entries(out, metrics)
    if foreign:
        more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
        raise OutputError(
            f"{out / foreign[0]}{more}: not written by ps-lab, in the earlier result that this "
            "run would replace; move it out of the folder or choose another --out"
        )


@contextmanager
def _no_bar(total: int, description: str) -> Iterator[Callable[..., None]]:
    yield lambda n=1, description=None: None


# --- the flow -------------------------------------------------------------------------------


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
    clock = _StageClock()
    # The solver kernels load while the images are read (see _warm_up.warm_up).
    warm_up = start_warm_up(options.method)
    with clock("open"):
        source = _read(dataset, options)
    with _band_executor(options) as executor, staged_folder(
        out, check=check_output_folder, error=OutputError
    ) as stage:
        budget = (options.memory_budget if options.memory_budget is not None
                  else auto_memory_budget())
        with clock("decode and stage"):
            store = _stage(source, options, budget, stage, bars, executor)
        timings["read_seconds"] = time.perf_counter() - started
        warm_up.join()
        with store:
            writer = _OutputWriter(
                stage, store.mask, source.truth, store.n_lights, colours=store.colours,
                threads=options.threads,
            )
            with clock("solve"):
                black = black_level(store, source.header, options)
                if source.near is None:
                    solved = solve_bands(store, source, options, writer, bars, executor, black)
                else:
                    solved = solve_near_bands(store, source, options, writer, bars, stage,
                                              black)
                check_solved_share(source.header.root, writer.solved_count, store.pixels)
            timings["solve_seconds"] = solved.seconds
            written = time.perf_counter()
            with clock("outputs"):
                metrics = _write_results(writer, stage, source, options, store, solved, timings,
                                         budget)
            with clock("appearance"):
                metrics["appearance"] = fit_appearance_bands(
                    store, stage, options.appearance, *_solved_lights(source, solved),
                    progress_bars=bars,
                )
            timings["write_seconds"] = time.perf_counter() - written
            metrics["timings"] = dict(timings)
            with clock("surface"):
                _write_surface(stage, options, metrics, bars)
            metrics["timings"]["stages"] = clock.summary(store)
            metrics["timings"]["files"] = _file_sizes(stage)
            metrics["timings"]["total_seconds"] = time.perf_counter() - started
            _write_metrics(stage, metrics)
    metrics["out"] = str(out)
    return ReconstructResult(out=out, metrics=metrics)


class _StageClock:
    """Wall and CPU seconds (all threads) of the flow's stages, for ``metrics.json``."""

    def __init__(self) -> None:
        self.stages: dict[str, dict[str, float]] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            entry = self.stages.setdefault(name, {"wall_seconds": 0.0, "cpu_seconds": 0.0})
            entry["wall_seconds"] += time.perf_counter() - wall
            entry["cpu_seconds"] += time.process_time() - cpu

    def summary(self, store: ObservationStore) -> dict[str, dict[str, float]]:
        """The stages in order, with what the store measured inside them.

        ``decode and stage``: the bytes of the frame files, ``decode_thread_seconds`` (the
        decoders' time summed over threads) and the bytes staged; ``observe`` (inside ``solve``
        and ``appearance``): turning staged values into observations when a band is read, with
        the bytes of values read.
        """
        stages = {name: dict(entry) for name, entry in self.stages.items()}
        staged = stages.get("decode and stage")
        if staged is not None:
            staged["bytes"] = store.stats["file_bytes"]
            staged["decode_thread_seconds"] = store.stats["decode_seconds"]
            staged["staged_bytes"] = store.nbytes
        stages["observe"] = {"wall_seconds": store.stats["observe_seconds"],
                             "bytes": store.stats["observed_bytes"]}
        return stages


def _file_sizes(folder: Path) -> dict[str, dict[str, int]]:
    """Bytes of each result file written (the staged folder, before it is published)."""
    return {entry.name: {"bytes": entry.stat().st_size} for entry in sorted(folder.iterdir())
            if entry.is_file() and not entry.name.startswith(".")}


def _read(dataset: Path, options: ReconstructOptions) -> SolveInput:
    """Stage 1: the dataset's header, mask and ground truth."""
    header = open_dataset(dataset, channel=options.channel, encoding=options.encoding)
    assert header.shape is not None
    near = _near_lights(header, options)
    truth = open_normal_gt(header.root, header.shape)
    return SolveInput(header, header.read_mask(), truth, near, header.object_outline)


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
    if options.refine_lights and options.fixed_intensities:
        raise DatasetError(
            "--fixed-intensities: near lights refine intensities only (positions stay); "
            "add --lights directional to refine directions"
        )
    if solver(options.method).near_tile is None:
        raise DatasetError(f"{options.method} needs one light matrix for all pixels: add "
                           "--lights directional")
    if options.scheduler is not None:
        raise DatasetError("--scheduler solves directional lights only: add --lights directional")
    n = len(header.names)
    anisotropy = header.light_anisotropy if header.light_anisotropy is not None else np.zeros(n)
    camera = None
    if header.camera is not None:
        f, cx, cy = header.camera
        camera = Camera(f, (cx, cy))
    elif header.plan.camera is not None:  # camera.json: the calibrated intrinsics
        camera = Camera.from_intrinsics(
            header.plan.camera.fx, header.plan.camera.fy, header.plan.camera.cx,
            header.plan.camera.cy,
        )
    _check_leds_above_outline(header)
    axes, flat = _led_model(header.root, options.led_model, n, positions)
    if flat is not None or options.led_model == "isotropic":
        anisotropy = np.zeros(n)  # the board's gains carry the beam; or no beam asked for
    return NearLights(positions, header.light_directions, anisotropy, camera=camera, axes=axes,
                      flat_field=flat)


def _check_leds_above_outline(header: DatasetHeader) -> None:
    """Every placed LED above the object's outline plane (``object_outline.txt``), else an error
    naming both files: an LED at or below the plane the object stands on lights none of it."""
    positions, outline = header.light_positions, header.object_outline
    if positions is None or outline is None:
        return
    placed = np.isfinite(positions).all(axis=1)
    low = np.flatnonzero(placed & (positions[:, 2] <= outline))
    if low.size:
        j = int(low[0])
        raise DatasetError(
            f"{header.root / LIGHT_POSITIONS}: LED {j + 1} (z={positions[j, 2]:g} px) is not "
            f"above the object's outline plane (z={outline:g} px, {OBJECT_OUTLINE})"
        )


def _led_model(root, model: str, n: int, positions: np.ndarray | None = None):
    """The LED axes and flat-field ``--led-model`` asks for (files of ``calibrate --flat-field``)."""
    axes_file, flat_file = root / LIGHT_AXES, root / FLAT_FIELD
    if model == "auto":
        model = ("flat-field" if flat_file.is_file() else "beam" if axes_file.is_file()
                 else "isotropic")
    if model == "flat-field":
        if not flat_file.is_file():
            raise DatasetError(f"{root}: --led-model flat-field needs {FLAT_FIELD} "
                               "(ps-lab calibrate --flat-field BOARD_FOLDER)")
        return None, read_flat_field(flat_file, n)
    if model == "beam":
        if not axes_file.is_file():
            raise DatasetError(f"{root}: --led-model beam needs {LIGHT_AXES} "
                               "(ps-lab calibrate --flat-field BOARD_FOLDER)")
        return read_light_axes(axes_file, n, positions), None
    return None, None


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
    source: SolveInput, options: ReconstructOptions, budget: int, stage: Path, bars, executor
) -> ObservationStore:
    """Stage 2: decode every frame once into a row-band store (in memory or a file in ``stage``).

    The budget (``options.memory_budget``, or :func:`auto_memory_budget` at the start) holds the
    store when it fits beside one band's work, else the store goes to a temporary file; bands
    hold at most :data:`MAX_BAND_PIXELS` mask pixels (fewer when the budget says so).
    """
    started = time.perf_counter()
    header, mask = source.header, source.mask
    n = len(header.names)
    coding = frame_coding(header.plan)
    extra = 0 if source.near is None else NEAR_BYTES_PER_OBSERVATION // BYTES_PER_OBSERVATION
    # colour frames: the three channels are read beside the solve channel (colour albedo)
    colours = 3 if coding.channels == 3 else 0
    extra += COLOUR_BYTES_PER_OBSERVATION // BYTES_PER_OBSERVATION if colours else 0
    per_light = n * (1 + extra)
    pixels = int(mask.sum())
    whole_bands = solver(options.method).one_light_matrix  # R-PCA: fitted per band, not capped
    keep_plan = whole_bands or options.refine_lights > 0
    limit = band_pixels(budget, per_light)
    if not whole_bands:
        limit = min(limit, MAX_BAND_PIXELS)
    limit = executor.band_pixels(limit, pixels, keep_plan)
    bands = plan_bands(mask, limit)
    bits = 0 if coding.coded else 1
    values = coding.channels * coding.itemsize * pixels
    store_bytes = n * (values + (bits * pixels + 7 * len(bands)) // 8)
    band_bytes = max(band.pixel_count for band in bands) * (
        per_light * BYTES_PER_OBSERVATION + BYTES_PER_PIXEL)
    small = store_bytes + band_bytes <= budget
    in_memory = options.staging == "memory" or (options.staging == "auto" and small)
    # frames decoded at once: each holds its codes (and a float copy when staged in float); as
    # many as the cores while a quarter of the budget holds them and the one being stored
    height, width = mask.shape
    frame_bytes = height * width * coding.channels * (coding.itemsize + (0 if coding.coded else 8))
    cores = int(options.threads) if options.threads else (os.cpu_count() or 1)
    decoders = int(max(1, min(cores, budget // 4 // max(frame_bytes, 1) - 1)))
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
            colours=colours,
            coding=coding,
            decoders=decoders,
        )
    log.info(
        "read %d images (%dx%d, %d mask pixels) in %.1f s: %d bands of at most %d pixels, "
        "%.2f GB staged in %s (%s), memory budget %.2f GB%s",
        n,
        mask.shape[1],
        mask.shape[0],
        pixels,
        time.perf_counter() - started,
        len(bands),
        max(band.pixel_count for band in bands),
        store.nbytes / 1e9,
        "memory" if store.path is None else "a file",
        np.dtype(store.coding.dtype).name,
        budget / 1e9,
        "" if options.memory_budget is not None else " (auto)",
    )
    return store


def _default(function: Callable, name: str, fallback: Any) -> Any:
    parameter = inspect.signature(function).parameters.get(name)
    if parameter is None or parameter.default is inspect.Parameter.empty:
        return fallback
    return parameter.default


def _write_results(
    writer: _OutputWriter,
    stage: Path,
    source: SolveInput,
    options: ReconstructOptions,
    store: ObservationStore,
    solved: Solved,
    timings: dict[str, float],
    budget: int,
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
    metrics["encoding"] = frames_encoding(source.header.plan.light_files[0][0], options.encoding)
    metrics["solver_options"] = {
        flag[2:]: getattr(options, name) for name, (flag, _) in SOLVER_OPTIONS.items()
    }
    metrics["fixed_intensities"] = options.fixed_intensities
    metrics["shadow_threshold"] = options.shadow_threshold
    metrics["black_threshold"] = solved.black
    metrics["light_model"] = "directional" if source.near is None else "near"
    camera = source.header.plan.camera
    if camera is not None:
        metrics["camera"] = camera_record(camera, Path(camera.source))
    if solved.near is not None:
        metrics["near"] = solved.near.record()
        lights = source.near
        metrics["near"]["led_model"] = ("flat-field" if lights.flat_field is not None else "beam"
                                        if lights.axes is not None and np.any(lights.anisotropy)
                                        else "isotropic")
    metrics["streaming"] = {
        "bands": len(store.bands),
        "max_band_pixels": max(band.pixel_count for band in store.bands),
        "memory_budget_bytes": budget,
        "memory_budget": ("auto: half the available memory" if options.memory_budget is None
                          else "given"),
        "staging": "file" if store.path is not None else "memory",
        "staging_bytes": store.nbytes,
        "staged_values": np.dtype(store.coding.dtype).name,
    }
    if options.refine_lights:
        metrics["refinement"] = {"iterations": options.refine_lights, "history": solved.history}
    metrics["timings"] = dict(timings)
    return json_safe(metrics)


def _write_surface(
    stage: Path, options: ReconstructOptions, metrics: dict, bars: ProgressBars
) -> None:
    """Stage 5: normal maps for other tools and, with ``options.depth``, depth and mesh."""
    started = time.perf_counter()
    normals = np.load(stage / "normals.npy", mmap_mode="r")  # the written file, paged in once
    try:
        mask = np.linalg.norm(normals, axis=-1) > 0.5
        write_normal_maps(stage, normals, mask, options.normal_map, options.threads)
        metrics["normal_maps"] = {"convention": options.normal_map}
        if options.depth is not None:
            albedo = grey_albedo(np.load(stage / "albedo.npy"), options.channel)
            try:
                depth = write_depth(
                    stage, normals, albedo,
                    with_result_camera(DepthOptions(method=options.depth), metrics),
                    progress_bars=bars,
                )
            except IntegrationInputError as exc:  # the normals just solved cannot be integrated
                raise DatasetError(f"--depth {options.depth}: {exc}") from None
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

