"""Writing the results of a reconstruction: normal and albedo maps, pictures and metrics.

Everything is written into a hidden temporary sibling of the output folder, which replaces the
output folder only once every file is complete (:func:`staged_folder`): a failed or interrupted run
leaves no partial output, and an earlier result stays untouched until the new one is ready.

Files (see ``docs/datasets.md``): ``normals.npy``, ``normal.png``, ``albedo.npy``, ``albedo.png``,
``corruption.png``, ``metrics.json``, and the refined ``light_directions.txt`` /
``light_intensities.txt`` when lights were refined.

:func:`reconstruct_to_folder` is the one production path of ``ps-lab reconstruct``: it streams a
capture of any size through row bands in bounded memory (``docs/scale.md``); a small dataset is
simply one band.
"""

from __future__ import annotations

import inspect
import json
import logging
import os
import re
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ps_lab.errors import PsLabError
from ps_lab.io.dataset import (
    ObservationStore,
    open_dataset,
    open_normal_gt,
    plan_bands,
    stage_observations,
    write_light_table,
)
from ps_lab.reconstruct._refine import fit_lights, light_fit_sums
from ps_lab.reconstruct._solution import Solution
from ps_lab.reconstruct._solve import estimate_noise, solve
from ps_lab.reconstruct.metrics import angular_errors_deg

log = logging.getLogger("ps_lab.reconstruct.pipeline")

RESULT_FORMAT = "ps-lab-reconstruction"
METRICS = "metrics.json"


class OutputError(PsLabError):
    """The output folder cannot be written or would overwrite something that is not a result."""


def normal_picture(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Colour-code normals as 8-bit RGB = (n + 1) / 2 · 255, black outside the mask.

    Returns
    -------
    ndarray of shape (H, W, 3), uint8, RGB

    """
    rgb = np.clip(np.rint((normals.astype(np.float64) + 1.0) * 127.5), 0, 255).astype(np.uint8)
    rgb[~mask] = 0
    return rgb


def albedo_picture(albedo: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Scale albedo to 8 bits by its 99th percentile inside the mask.

    Returns
    -------
    ndarray of shape (H, W), uint8

    """
    inside = albedo[mask]
    top = float(np.percentile(inside, 99)) if inside.size else 0.0
    if not np.isfinite(top) or top <= 0:
        return np.zeros(albedo.shape, dtype=np.uint8)
    picture = np.clip(np.rint(albedo / top * 255.0), 0, 255).astype(np.uint8)
    picture[~mask] = 0
    return picture


def corruption_picture(corruption: np.ndarray) -> np.ndarray:
    """Map the outlier share 0..1 to 0..255 (uint8, shape (H, W))."""
    return np.clip(np.rint(corruption * 255.0), 0, 255).astype(np.uint8)


def write_png(path: Path, picture: np.ndarray) -> None:
    """Write an 8-bit grey (H, W) or RGB (H, W, 3) picture as PNG."""
    if picture.ndim == 3:
        picture = np.ascontiguousarray(picture[:, :, ::-1])  # OpenCV stores BGR
    ok, encoded = cv2.imencode(".png", picture)
    if not ok:
        raise OutputError(f"{path}: cannot encode PNG")
    Path(path).write_bytes(encoded.tobytes())


def _json_safe(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist())
    if isinstance(value, np.generic):
        return _json_safe(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, Path):
        return str(value)
    return repr(value)


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
def staged_folder(out: Path) -> Iterator[Path]:
    """Yield an empty temporary folder that replaces ``out`` when the block succeeds.

    ``out`` must be absent, empty, or an earlier result (see :func:`check_output_folder`). On any
    exception (Ctrl-C included) the temporary folder, and any parent folder created for it, are
    removed and ``out`` is left as it was.
    """
    out = Path(out)
    check_output_folder(out)
    created: list[Path] = []
    parent = out.parent
    while not parent.exists():
        created.append(parent)
        parent = parent.parent
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        stage = out.parent / f".{out.name}.partial-{os.getpid()}"
        if stage.exists():
            shutil.rmtree(stage)
        stage.mkdir()
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the output folder ({exc.strerror})") from None
    try:
        yield stage
        retired = out.parent / f".{out.name}.old-{os.getpid()}"
        if out.exists():
            out.rename(retired)
        stage.rename(out)
        if retired.exists():
            shutil.rmtree(retired, ignore_errors=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        for folder in created:  # innermost first
            try:
                folder.rmdir()
            except OSError:
                break
        raise




# --- streamed reconstruction: one code path for captures of any size ----------------------------

DEFAULT_MEMORY_BUDGET = 1 << 30
# Bytes held per observation of a band while it is solved: the float32 observations, their
# validity, the solver's usable and outlier masks, and headroom for the refinement sums.
BYTES_PER_OBSERVATION = 12
# Bytes per pixel of a band: the solver's per-pixel results and the band's output images.
BYTES_PER_PIXEL = 200
# A store at most this share of the budget stays in memory; larger ones go to a temporary file.
IN_MEMORY_SHARE = 0.25
# Angular errors are summarised from a histogram of this bin width (degrees): median and p90 are
# within half a bin of the exact values, mean and max are exact.
ERROR_BIN_DEG = 0.001
_SIZE_UNITS = {"": 1 << 20, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


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


ProgressBars = Callable[[int, str], Any]


@contextmanager
def _no_bar(total: int, description: str) -> Iterator[Callable[..., None]]:
    yield lambda n=1, description=None: None


class _Histogram:
    """Streamed summary of non-negative values: exact count/mean/max, binned quantiles."""

    def __init__(self, bin_width: float, top: float) -> None:
        self.width = bin_width
        self.counts = np.zeros(int(np.ceil(top / bin_width)) + 1, np.int64)
        self.total = 0.0
        self.count = 0
        self.max = -np.inf

    def add(self, values: np.ndarray) -> None:
        values = np.asarray(values, np.float64).ravel()
        values = values[np.isfinite(values)]
        if not values.size:
            return
        bins = np.minimum((values / self.width).astype(np.int64), self.counts.size - 1)
        self.counts += np.bincount(bins, minlength=self.counts.size)
        self.total += float(values.sum())
        self.count += values.size
        self.max = max(self.max, float(values.max()))

    def quantile(self, q: float) -> float:
        """Linear-interpolated quantile (numpy's default rule) with values at bin centres."""
        rank = q * (self.count - 1)
        cumulative = np.cumsum(self.counts)
        lo, hi = int(np.floor(rank)), int(np.ceil(rank))
        value_lo, value_hi = (
            (int(np.searchsorted(cumulative, k, side="right")) + 0.5) * self.width for k in (lo, hi)
        )
        return min(value_lo + (rank - lo) * (value_hi - value_lo), self.max)

    def summary(self) -> dict[str, float] | None:
        if not self.count:
            return None
        return {
            "mean": self.total / self.count,
            "median": self.quantile(0.5),
            "p90": self.quantile(0.9),
            "max": self.max,
        }


def _iteration_statistics(counts: np.ndarray) -> dict[str, float]:
    """Mean, exact median and max of non-negative integers given as a bincount."""
    total = int(counts.sum())
    if total == 0:
        return {"mean": 0.0, "median": 0.0, "max": 0.0}
    values = np.arange(counts.size)
    cumulative = np.cumsum(counts)
    middle = ((total - 1) // 2, total // 2)
    lo, hi = (int(np.searchsorted(cumulative, k, side="right")) for k in middle)
    return {
        "mean": float((counts * values).sum() / total),
        "median": float(0.5 * (lo + hi)),
        "max": float(values[counts > 0].max()),
    }


@dataclass
class _PassResult:
    params: dict
    error_sum: float = 0.0
    all_have_truth: bool = True
    normal_matrices: np.ndarray | None = None  # (n, 6) sums of x x^T over each light's inliers
    normal_targets: np.ndarray | None = None  # (n, 3) sums of y x
    inliers: int = 0
    usable: int = 0


class _OutputWriter:
    """Result files written band by band: memory-mapped ``.npy`` rows and 8-bit pictures."""

    def __init__(self, folder: Path, mask: np.ndarray, truth, n_lights: int) -> None:
        self.folder = folder
        self.mask = mask
        self.truth = truth
        height, width = mask.shape
        self.offsets = {}
        for name, shape in (("normals", (height, width, 3)), ("albedo", (height, width))):
            array = np.lib.format.open_memmap(
                folder / f"{name}.npy", mode="w+", dtype=np.float32, shape=shape
            )
            self.offsets[name] = (array.offset, shape[1:])
            del array
        self.normal_png = np.zeros((height, width, 3), np.uint8)
        self.corruption_png = np.zeros((height, width), np.uint8)
        self.albedo_values = np.zeros(int(mask.sum()), np.float32)
        self.errors = _Histogram(ERROR_BIN_DEG, 180.0)
        self.iterations = np.zeros(1, np.int64)
        self.valid_count = 0
        self.outlier_count = 0
        self.solved_count = 0
        self.observation_count = 0

    def _write_rows(self, name: str, start: int, block: np.ndarray) -> None:
        offset, row_shape = self.offsets[name]
        row_bytes = int(np.prod(row_shape)) * 4
        rows = np.memmap(
            self.folder / f"{name}.npy",
            dtype=np.float32,
            mode="r+",
            offset=offset + start * row_bytes,
            shape=block.shape,
        )
        rows[...] = block
        rows.flush()
        del rows  # unmapped at once: written pages do not stay in the resident set

    def add(self, band, solution, valid: np.ndarray) -> None:
        rows = slice(band.row_start, band.row_stop)
        inside = self.mask[rows]
        height, width = inside.shape
        pixel_normals = np.asarray(solution.normals, dtype=np.float64)
        lengths = np.linalg.norm(pixel_normals, axis=1)
        solved = np.isfinite(lengths) & (lengths > 0.5)
        unit = np.zeros_like(pixel_normals)
        unit[solved] = pixel_normals[solved] / lengths[solved, None]
        normals = np.zeros((height, width, 3), np.float32)
        normals[inside] = unit
        albedo = np.zeros((height, width), np.float32)
        pixel_albedo = np.nan_to_num(np.asarray(solution.albedo, np.float64))
        albedo[inside] = np.where(solved, pixel_albedo, 0.0)
        outliers = np.asarray(solution.outliers, dtype=bool)
        used = valid.sum(axis=0)
        corruption = np.zeros((height, width), np.float32)
        corruption[inside] = outliers.sum(axis=0) / np.maximum(used, 1)
        solved_map = np.zeros((height, width), bool)
        solved_map[inside] = solved
        self._write_rows("normals", band.row_start, normals)
        self._write_rows("albedo", band.row_start, albedo)
        self.normal_png[rows] = normal_picture(normals, solved_map)
        self.corruption_png[rows] = corruption_picture(corruption)
        self.albedo_values[band.pixel_start : band.pixel_start + band.pixel_count] = albedo[inside]
        counts = np.bincount(np.asarray(solution.iterations, np.int64))
        if counts.size > self.iterations.size:
            counts[: self.iterations.size] += self.iterations
            self.iterations = counts
        else:
            self.iterations[: counts.size] += counts
        self.valid_count += int(used.sum())
        self.observation_count += valid.size
        self.outlier_count += int(outliers.sum())
        self.solved_count += int(solved.sum())
        if self.truth is not None:
            gt = self.truth.rows(band.row_start, band.row_stop)
            pixels = solved_map & inside & (np.linalg.norm(gt, axis=2) > 0.5)
            self.errors.add(angular_errors_deg(normals[pixels].astype(np.float64), gt[pixels]))

    def finish(self, header, params: dict, *, lights, intensities, seconds, extra) -> dict:
        folder = self.folder
        mask = self.mask
        write_png(folder / "normal.png", self.normal_png)
        self.normal_png = None
        write_png(folder / "corruption.png", self.corruption_png)
        self.corruption_png = None
        albedo_png = np.zeros(mask.shape, np.uint8)
        values = self.albedo_values
        top = float(np.percentile(values, 99)) if values.size else 0.0
        if np.isfinite(top) and top > 0:
            albedo_png[mask] = np.clip(np.rint(values / top * 255.0), 0, 255).astype(np.uint8)
        write_png(folder / "albedo.png", albedo_png)
        del albedo_png
        if lights is not None:
            write_light_table(folder / "light_directions.txt", lights)
        if intensities is not None:
            write_light_table(folder / "light_intensities.txt", intensities)
        pixels = int(mask.sum())
        metrics: dict[str, Any] = {
            "format": RESULT_FORMAT,
            "method": params.get("method"),
            "parameters": params,
            "dataset": str(header.root),
            "image_size": [int(mask.shape[1]), int(mask.shape[0])],
            "pixels": pixels,
            "lights": len(header.names),
            "solve_seconds": float(seconds),
            "iterations": _iteration_statistics(self.iterations),
            "valid_observation_share": self.valid_count / max(self.observation_count, 1),
            "outlier_share": self.outlier_count / max(self.valid_count, 1),
            "unsolved_pixels": pixels - self.solved_count,
        }
        if self.truth is not None:
            metrics["angular_error_deg"] = self.errors.summary()
            metrics["angular_error_method"] = (
                f"mean and max exact; median and p90 from a histogram of {ERROR_BIN_DEG} deg bins"
            )
            metrics["error_pixels"] = self.errors.count
        if extra:
            metrics.update(extra)
        metrics = _json_safe(metrics)
        (folder / METRICS).write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
        return metrics


def _whole_image_parameters(store: ObservationStore, vectors: np.ndarray, method: str) -> dict:
    """The noise level a single whole-image solve would estimate, fixed for every band.

    ``solve`` estimates it from an evenly spaced sample of all pixels (at most ``max_pixels`` of
    :func:`ps_lab.estimate_noise`); the store kept that very sample, so the estimate
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
    *,
    method: str,
    threads: int | None,
    truth,
    fit: bool,
    writer: _OutputWriter | None,
    advance: Callable[..., None],
    label: str,
) -> _PassResult:
    """Solve every band once with the light vectors ``vectors`` (n, 3)."""
    fixed = _whole_image_parameters(store, vectors, method)
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
            method=method,
            valid=valid,
            threads=threads,
            progress=advance,
            **fixed,
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


def reconstruct_to_folder(
    dataset: Path,
    out: Path,
    *,
    channel: str = "mean",
    shadow_threshold: float | None = None,
    method: str = "sbl",
    threads: int | None = None,
    refine_lights: int = 0,
    fixed_intensities: bool = False,
    memory_budget: int | str = DEFAULT_MEMORY_BUDGET,
    staging: str = "auto",
    progress_bars: ProgressBars | None = None,
    extra: dict | None = None,
) -> dict:
    """Reconstruct a dataset folder into ``out``, streamed by row bands in bounded memory.

    Pass 1 decodes each frame once and stores its mask pixels band by band
    (:func:`ps_lab.io.dataset.stage_observations`); each solve pass then reads one band's
    ``(n, P_band)`` block, solves it (:func:`ps_lab.reconstruct.solve`) and, on the last pass,
    writes the band's rows of every output. Light refinement runs K + 1 passes, accumulating each
    light's least-squares sums band by band. Everything is written into a staged folder that
    replaces ``out`` only on success (:func:`staged_folder`); the staging store is deleted in every
    case. Small datasets take the same path in one band.

    Parameters
    ----------
    dataset : Path
        Image folder or capture run.
    out : Path
        Output folder: absent, empty or an earlier result.
    channel, shadow_threshold
        As for :func:`ps_lab.io.dataset.load_dataset`.
    method : {"ls", "l1", "sbl", "rpca"}
        Solver. Noise level and outlier threshold are estimated once for the whole image; R-PCA's
        low-rank model is fitted per band.
    threads : int or None
        Solver threads (default all cores).
    refine_lights : int
        Iterations of light refinement (0 = none); the refined lights are written as
        ``light_directions.txt`` / ``light_intensities.txt``.
    fixed_intensities : bool
        Refine directions only.
    memory_budget : int or str
        Bytes (int), or a size such as ``"1GB"`` (see :func:`parse_memory_size`), that one band's
        solve may use; sets the band height.
    staging : {"auto", "memory", "file"}
        Backing of the observation store: in memory when small (``auto``), or forced.
    progress_bars : callable or None
        ``progress_bars(total, description)`` returning a context manager that yields
        ``advance(n=1, description=None)`` (e.g. :func:`ps_lab._cli_util.progress_bar`): one bar
        for reading the frames, one for the solve passes (pixels, band shown in the description).
    extra : dict or None
        More entries for ``metrics.json``.

    Returns
    -------
    dict
        The metrics written to ``metrics.json`` (``out`` added under ``"out"``).

    """
    if staging not in ("auto", "memory", "file"):
        raise OutputError(f"staging must be auto, memory or file, got {staging!r}")
    budget = memory_budget if isinstance(memory_budget, int) else parse_memory_size(memory_budget)
    if budget <= 0:
        raise OutputError(f"memory budget must be positive, got {memory_budget}")
    bars = progress_bars or _no_bar
    out = Path(out)
    check_output_folder(out)
    started = time.perf_counter()
    header = open_dataset(dataset, channel=channel)
    assert header.shape is not None
    mask = header.read_mask()
    truth = open_normal_gt(header.root, header.shape)
    n = len(header.names)
    bands = plan_bands(mask, band_pixels(budget, n))
    pixels = int(mask.sum())
    store_bytes = n * (4 * pixels + (pixels + 7 * len(bands)) // 8)
    small = store_bytes <= IN_MEMORY_SHARE * budget
    in_memory = staging == "memory" or (staging == "auto" and small)
    sample_pixels = _default(estimate_noise, "max_pixels", 20000)
    timings: dict[str, float] = {}
    with staged_folder(out) as stage:
        with bars(n, "reading images") as advance:
            store = stage_observations(
                header,
                mask,
                bands,
                channel=channel,
                shadow_threshold=shadow_threshold,
                folder=stage,
                in_memory=in_memory,
                sample_pixels=sample_pixels,
                progress=advance,
            )
        timings["read_seconds"] = time.perf_counter() - started
        log.info(
            "read %d images (%dx%d, %d mask pixels) in %.1f s: %d bands of at most %d pixels, "
            "%.2f GB staged in %s",
            n,
            mask.shape[1],
            mask.shape[0],
            pixels,
            timings["read_seconds"],
            len(bands),
            max(band.pixel_count for band in bands),
            store.nbytes / 1e9,
            "memory" if in_memory else "a file",
        )
        with store:
            metrics = _solve_and_write(
                store,
                header,
                truth,
                stage,
                method=method,
                threads=threads,
                refine_lights=refine_lights,
                fixed_intensities=fixed_intensities,
                bars=bars,
                timings=timings,
                extra={
                    **(extra or {}),
                    "streaming": {
                        "bands": len(bands),
                        "max_band_pixels": max(band.pixel_count for band in bands),
                        "memory_budget_bytes": budget,
                        "staging": "memory" if in_memory else "file",
                        "staging_bytes": store.nbytes,
                    },
                },
            )
    metrics["out"] = str(out)
    return metrics


def _default(function: Callable, name: str, fallback: Any) -> Any:
    parameter = inspect.signature(function).parameters.get(name)
    if parameter is None or parameter.default is inspect.Parameter.empty:
        return fallback
    return parameter.default


def _solve_and_write(
    store: ObservationStore,
    header,
    truth,
    stage: Path,
    *,
    method: str,
    threads: int | None,
    refine_lights: int,
    fixed_intensities: bool,
    bars: ProgressBars,
    timings: dict,
    extra: dict,
) -> dict:
    started = time.perf_counter()
    lights = np.asarray(header.light_directions, dtype=np.float64)
    directions = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    n = store.n_lights
    factor = np.ones(n)
    anchor = directions.copy()
    history: list[dict] = []
    pending: dict = {}
    passes = refine_lights + 1
    writer = _OutputWriter(stage, store.mask, truth, n)
    with bars(store.pixels * passes, f"{method}: pixels") as advance:
        for k in range(passes):
            final = k == refine_lights
            label = method if passes == 1 else f"{method} pass {k + 1}/{passes}"
            result = _solve_pass(
                store,
                directions * factor[:, None],
                method=method,
                threads=threads,
                truth=truth if refine_lights else None,
                fit=not final,
                writer=writer if final else None,
                advance=advance,
                label=label,
            )
            if refine_lights:
                errors = {}
                if truth is not None and result.all_have_truth:
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
                fixed_intensities,
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
    seconds = time.perf_counter() - started
    params = dict(result.params)
    extra = dict(extra)
    refined_directions = refined_intensities = None
    if refine_lights:
        params["refine_iterations"] = refine_lights
        refined_directions = directions
        # The observations were already divided by the file's intensities, so the refined
        # relative intensity multiplies them.
        refined_intensities = header.light_intensities * factor.reshape(-1, 1)
        extra["refinement"] = {"iterations": refine_lights, "history": history}
    written = time.perf_counter()
    timings["solve_seconds"] = seconds
    try:
        metrics_extra = {**extra, "timings": timings}
        metrics = writer.finish(
            header,
            params,
            lights=refined_directions,
            intensities=refined_intensities,
            seconds=seconds,
            extra=metrics_extra,
        )
    except OSError as exc:
        raise OutputError(f"{stage}: cannot write results ({exc.strerror or exc})") from None
    timings["write_seconds"] = time.perf_counter() - written
    metrics["timings"] = dict(timings)
    (stage / METRICS).write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    return metrics
