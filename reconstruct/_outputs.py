"""Result files of a reconstruction, written band by band: normal and albedo maps, pictures.

Files (see ``docs/datasets.md``): ``normals.npy``, ``normal.png``, ``albedo.npy``, ``albedo.png``,
(colour frames: ``albedo.npy`` (H, W, 3) linear RGB, ``albedo.png`` sRGB and ``albedo.exr``;
:mod:`._colour`), ``corruption.png`` and, when lights were refined, ``light_directions.txt`` /
``light_intensities.txt``. :mod:`ps_lab.reconstruct.pipeline` owns the flow and writes
``metrics.json`` from the summary :meth:`_OutputWriter.finish` returns.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ps_lab.errors import DatasetError, OutputError
from ps_lab.io.files import allocate_npy, write_npy_rows
from ps_lab.io.light_files import write_light_table
from ps_lab.reconstruct._bands import reduce_solution
from ps_lab.reconstruct._colour import colour_albedo_picture, write_albedo_exr
from ps_lab.reconstruct.metrics import angular_errors_deg

# Angular errors are summarised from a histogram of this bin width (degrees): median and p90 are
# within half a bin of the exact values, mean and max are exact.
ERROR_BIN_DEG = 0.001
# A result with at least this share of its mask pixels unsolved is reported in one warning line.
UNSOLVED_WARNING_SHARE = 0.10

log = logging.getLogger(__name__)


def check_solved_share(root: Path, solved: int, pixels: int) -> None:
    """Refuse a result where no pixel was solved; warn in one line when many were not.

    A pixel is unsolved when it has too few usable observations for a normal: the images are
    dark, saturated or NaN there, or every value is at or below ``--shadow-threshold``.

    Raises
    ------
    DatasetError
        No mask pixel could be solved (the caller writes nothing).

    """
    why = "too few usable observations: dark, saturated, NaN, or at or below --shadow-threshold"
    if pixels and solved == 0:
        raise DatasetError(f"{root}: no pixel can be solved ({why}); nothing written")
    unsolved = pixels - solved
    if pixels and unsolved >= UNSOLVED_WARNING_SHARE * pixels:
        log.warning(
            "%s: %.0f%% of the %d mask pixels could not be solved (%s); their normals are 0",
            root,
            100.0 * unsolved / pixels,
            pixels,
            why,
        )


def scatter_rows(inside: np.ndarray, values: np.ndarray, dtype) -> np.ndarray:
    """Rows of an image from their mask pixels' values, zeros elsewhere.

    ``image[inside] = values`` on a zero image: pixels with several channels are moved as one
    item each (a ``void`` view of their bytes), which numpy's boolean assignment does several
    times faster than channel by channel.

    Parameters
    ----------
    inside : ndarray of shape (h, w), bool
    values : ndarray of shape (P,) or (P, C)
        One row per True pixel of ``inside``, in row-major order.
    dtype : numpy dtype
        Of the image (``values`` are converted to it as numpy's assignment converts them).

    Returns
    -------
    ndarray of shape (h, w) or (h, w, C)

    """
    values = np.asarray(values)
    image = np.zeros((*inside.shape, *values.shape[1:]), dtype)
    if values.ndim == 1:
        image[inside] = values
        return image
    channels = int(np.prod(values.shape[1:]))
    pixels = np.ascontiguousarray(values, dtype).reshape(len(values), channels)
    item = np.dtype((np.void, channels * image.itemsize))
    image.reshape(*inside.shape, -1).view(item)[..., 0][inside] = pixels.view(item)[:, 0]
    return image


def brightest_channel(values: np.ndarray) -> np.ndarray:
    """``values.max(axis=-1)`` of (P, C) values, the same values (NaN included).

    Channel-wise maxima in the reduction's order, ``maximum(maximum(v0, v1), v2)``: numpy's
    reduction over a short last axis is slow.
    """
    values = np.asarray(values)
    top = values[:, 0]
    for channel in range(1, values.shape[1]):
        top = np.maximum(top, values[:, channel])
    return top


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
    """Write an 8-bit grey (H, W) or RGB (H, W, 3) picture as PNG.

    OpenCV's PNG encoder with its default settings, its fastest (zlib level 1, run-length
    strategy, ``sub`` filter in OpenCV 5): an explicit level 1-3 took 1.5-2x as long on the
    pictures of a 4 MP result, level 0 no less time for 2.5x the bytes.
    """
    if picture.ndim == 3:
        picture = np.ascontiguousarray(picture[:, :, ::-1])  # OpenCV stores BGR
    ok, encoded = cv2.imencode(".png", picture)
    if not ok:
        raise OutputError(f"{path}: cannot encode PNG")
    Path(path).write_bytes(encoded.tobytes())


def run_jobs(jobs: list[Callable[[], None]], threads: int | None = None) -> None:
    """Run file writers side by side on up to ``threads`` threads (None: all cores).

    The encoders (OpenCV's PNG, OpenEXR) and numpy release the GIL, so the result's pictures
    are encoded in parallel. Every job runs to its end; then the first failure, in the order of
    ``jobs``, is raised.
    """
    workers = min(len(jobs), int(threads) if threads else (os.cpu_count() or 1))
    failures: list[BaseException] = []
    if workers <= 1:
        for job in jobs:
            try:
                job()
            except Exception as exc:  # noqa: BLE001 - raised below, after the other jobs
                failures.append(exc)
    else:
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="ps-lab-write") as pool:
            futures = [pool.submit(job) for job in jobs]
        failures = [f.exception() for f in futures if f.exception() is not None]
    if failures:
        raise failures[0]


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


class _OutputWriter:
    """Result files written band by band: memory-mapped ``.npy`` rows and 8-bit pictures."""

    def __init__(
        self, folder: Path, mask: np.ndarray, truth, n_lights: int, colours: int = 0,
        threads: int | None = None,
    ) -> None:
        self.folder = folder
        self.threads = threads
        self.mask = mask
        self.truth = truth
        self.colours = int(colours)
        height, width = mask.shape
        self.offsets = {}
        albedo_shape = (height, width, self.colours) if self.colours else (height, width)
        for name, shape in (("normals", (height, width, 3)), ("albedo", albedo_shape)):
            # Reserved on disk first: a full disk is an error line here, not SIGBUS later.
            offset = allocate_npy(folder / f"{name}.npy", shape, np.float32)
            self.offsets[name] = (offset, shape[1:])
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
        offset, _ = self.offsets[name]
        write_npy_rows(self.folder / f"{name}.npy", offset, start,
                       block.astype(np.float32, copy=False))

    def add(self, band, result, valid: np.ndarray | None = None) -> None:
        """Write a band's rows from its :class:`ps_lab.reconstruct._bands.BandResult`.

        A :class:`ps_lab.reconstruct.Solution` with its ``valid`` (n, P) is reduced here first
        (:func:`ps_lab.reconstruct._bands.reduce_solution`), for callers that solve bands
        themselves.
        """
        if valid is not None:
            result = reduce_solution(band.index, result, valid)
        rows = slice(band.row_start, band.row_stop)
        inside = self.mask[rows]
        normals = scatter_rows(inside, result.normals, np.float32)
        if self.colours and result.colour_albedo is not None:
            pixel_albedo = np.asarray(result.colour_albedo, np.float32)
        else:
            pixel_albedo = np.asarray(result.albedo, np.float32)
        albedo = scatter_rows(inside, pixel_albedo, np.float32)
        corruption = scatter_rows(inside, result.corruption, np.float32)
        solved_map = scatter_rows(inside, result.solved, bool)
        self._write_rows("normals", band.row_start, normals)
        self._write_rows("albedo", band.row_start, albedo)
        self.normal_png[rows] = normal_picture(normals, solved_map)
        self.corruption_png[rows] = corruption_picture(corruption)
        # grey: the values; colour: the brightest channel (the picture's one scale), in the
        # order of ``max(axis=-1)``: maximum(maximum(c0, c1), c2)
        values = pixel_albedo if pixel_albedo.ndim == 1 else brightest_channel(pixel_albedo)
        self.albedo_values[band.pixel_start : band.pixel_start + band.pixel_count] = values
        counts = result.iteration_counts
        if counts.size > self.iterations.size:
            counts = counts.copy()
            counts[: self.iterations.size] += self.iterations
            self.iterations = counts
        else:
            self.iterations[: counts.size] += counts
        self.valid_count += result.valid_count
        self.observation_count += result.observation_count
        self.outlier_count += result.outlier_count
        self.solved_count += int(result.solved.sum())
        if self.truth is not None:
            gt = self.truth.rows(band.row_start, band.row_stop)
            pixels = solved_map & inside & (np.linalg.norm(gt, axis=2) > 0.5)
            self.errors.add(angular_errors_deg(normals[pixels].astype(np.float64), gt[pixels]))

    def finish(self, header, params: dict, *, lights, intensities, seconds, result_format) -> dict:
        """Write the pictures (and refined light tables); return the metrics of the result.

        ``metrics.json`` itself is written by the pipeline, which adds its own entries.
        """
        folder = self.folder
        mask = self.mask
        run_jobs(self._picture_jobs(), self.threads)
        if lights is not None:
            write_light_table(folder / "light_directions.txt", lights)
        if intensities is not None:
            write_light_table(folder / "light_intensities.txt", intensities)
        pixels = int(mask.sum())
        metrics: dict[str, Any] = {
            "format": result_format,
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
            "albedo": {
                "channels": "rgb" if self.colours else "grey",
                "definition": "Lambertian-equivalent reflectance per channel, linear, each "
                "channel divided by its light intensity" if self.colours else "solver",
            },
        }
        if self.truth is not None:
            metrics["angular_error_deg"] = self.errors.summary()
            metrics["angular_error_method"] = (
                f"mean and max exact; median and p90 from a histogram of {ERROR_BIN_DEG} deg bins"
            )
            metrics["error_pixels"] = self.errors.count
        return metrics

    def _picture_jobs(self) -> list[Callable[[], None]]:
        """Writers of the pictures and ``albedo.exr``, for :func:`run_jobs`.

        The writer's own references to its 8-bit pictures are dropped (the jobs hold them).
        """
        folder, mask, values = self.folder, self.mask, self.albedo_values
        normal_png, corruption_png = self.normal_png, self.corruption_png
        self.normal_png = self.corruption_png = None

        def albedo_top() -> float:
            return float(np.percentile(values, 99)) if values.size else 0.0

        def albedo() -> np.ndarray:  # the rows written band by band, memory-mapped
            return np.load(folder / "albedo.npy", mmap_mode="r")

        def grey_png() -> None:
            top = albedo_top()
            albedo_png = np.zeros(mask.shape, np.uint8)
            if np.isfinite(top) and top > 0:
                albedo_png[mask] = np.clip(np.rint(values / top * 255.0), 0, 255).astype(np.uint8)
            write_png(folder / "albedo.png", albedo_png)

        jobs = [
            lambda: write_png(folder / "normal.png", normal_png),
            lambda: write_png(folder / "corruption.png", corruption_png),
        ]
        if not self.colours:
            return [*jobs, grey_png]
        return [
            *jobs,
            lambda: write_png(folder / "albedo.png",
                              colour_albedo_picture(albedo(), mask, albedo_top())),
            lambda: write_albedo_exr(folder / "albedo.exr", albedo()),
        ]
