"""Writing the results of a reconstruction: normal and albedo maps, pictures and metrics.

Everything is written into a hidden temporary sibling of the output folder, which replaces the
output folder only once every file is complete (:func:`staged_folder`): a failed or interrupted run
leaves no partial output, and an earlier result stays untouched until the new one is ready.

Files (see ``docs/datasets.md``): ``normals.npy``, ``normal.png``, ``albedo.npy``, ``albedo.png``,
``corruption.png``, ``metrics.json``, and the refined ``light_directions.txt`` /
``light_intensities.txt`` when lights were refined.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ps_lab.dataset import Dataset, write_light_table
from ps_lab.errors import PsLabError

log = logging.getLogger("ps_lab.outputs")

RESULT_FORMAT = "ps-lab-reconstruction"
METRICS = "metrics.json"


class OutputError(PsLabError):
    """The output folder cannot be written or would overwrite something that is not a result."""


@dataclass(frozen=True)
class ResultMaps:
    """Per-pixel results laid out as images.

    Attributes
    ----------
    normals : ndarray of shape (H, W, 3), float32
        Unit normals inside the mask, zeros outside and where unsolvable.
    albedo : ndarray of shape (H, W), float32
        Zeros outside the mask.
    corruption : ndarray of shape (H, W), float32
        Share (0..1) of a pixel's usable observations that the method treated as outliers.
    solved : ndarray of shape (H, W), bool
        Mask pixels that received a normal.

    """

    normals: np.ndarray
    albedo: np.ndarray
    corruption: np.ndarray
    solved: np.ndarray


def solution_maps(solution: Any, mask: np.ndarray, valid: np.ndarray | None = None) -> ResultMaps:
    """Scatter a solver's per-pixel results (mask pixels in row-major order) back into images.

    Parameters
    ----------
    solution : ps_lab.reconstruct.Solution
        ``normals`` (P, 3), ``albedo`` (P,), ``outliers`` (n, P).
    mask : ndarray of shape (H, W), bool
        P = ``mask.sum()`` pixels.
    valid : ndarray of shape (n, P), bool, or None
        Usable observations; the corruption share is taken over these (all n when None).

    Returns
    -------
    ResultMaps

    """
    height, width = mask.shape
    normals = np.zeros((height, width, 3), dtype=np.float32)
    albedo = np.zeros((height, width), dtype=np.float32)
    corruption = np.zeros((height, width), dtype=np.float32)
    pixel_normals = np.asarray(solution.normals, dtype=np.float64)
    lengths = np.linalg.norm(pixel_normals, axis=1)
    solved_pixels = np.isfinite(lengths) & (lengths > 0.5)
    unit = np.zeros_like(pixel_normals)
    unit[solved_pixels] = pixel_normals[solved_pixels] / lengths[solved_pixels, None]
    normals[mask] = unit
    pixel_albedo = np.nan_to_num(np.asarray(solution.albedo, dtype=np.float64))
    albedo[mask] = np.where(solved_pixels, pixel_albedo, 0.0)
    outliers = np.asarray(solution.outliers, dtype=bool)
    used = outliers.shape[0] if valid is None else np.asarray(valid, dtype=bool).sum(axis=0)
    share = outliers.sum(axis=0) / np.maximum(used, 1)
    corruption[mask] = share
    solved = np.zeros((height, width), dtype=bool)
    solved[mask] = solved_pixels
    return ResultMaps(normals=normals, albedo=albedo, corruption=corruption, solved=solved)


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


def _statistics(values: np.ndarray) -> dict[str, float]:
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return {"mean": 0.0, "median": 0.0, "max": 0.0}
    return {
        "mean": float(values.mean()),
        "median": float(np.median(values)),
        "max": float(values.max()),
    }


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


def normal_errors(maps: ResultMaps, dataset: Dataset) -> np.ndarray | None:
    """Angular errors in degrees at solved mask pixels that have ground truth, or None.

    Returns
    -------
    ndarray of shape (k,) or None

    """
    if dataset.normal_gt is None:
        return None
    from ps_lab.reconstruct.metrics import angular_errors_deg

    has_truth = np.linalg.norm(dataset.normal_gt, axis=2) > 0.5
    pixels = maps.solved & has_truth & dataset.mask
    return angular_errors_deg(maps.normals[pixels].astype(np.float64), dataset.normal_gt[pixels])


def build_metrics(
    dataset: Dataset,
    solution: Any,
    maps: ResultMaps,
    *,
    solve_seconds: float,
    extra: dict | None = None,
) -> dict:
    """Collect the numbers of ``metrics.json``.

    Returns
    -------
    dict
        method, parameters, pixels, lights, ``solve_seconds``, iteration statistics, outlier share,
        and ``angular_error_deg`` (mean/median/p90/max) when the dataset has ground truth.

    """
    params = dict(getattr(solution, "params", {}) or {})
    valid = dataset.valid[:, dataset.mask]
    pixels = int(dataset.mask.sum())
    metrics: dict[str, Any] = {
        "format": RESULT_FORMAT,
        "method": params.get("method"),
        "parameters": params,
        "dataset": str(dataset.root),
        "image_size": [int(dataset.mask.shape[1]), int(dataset.mask.shape[0])],
        "pixels": pixels,
        "lights": int(dataset.images.shape[0]),
        "solve_seconds": float(solve_seconds),
        "iterations": _statistics(np.asarray(solution.iterations)),
        "valid_observation_share": float(valid.mean()) if valid.size else 0.0,
        "outlier_share": float(np.asarray(solution.outliers).sum() / max(int(valid.sum()), 1)),
        "unsolved_pixels": int(pixels - maps.solved[dataset.mask].sum()),
    }
    errors = normal_errors(maps, dataset)
    if errors is not None:
        from ps_lab.reconstruct.metrics import error_summary

        metrics["angular_error_deg"] = error_summary(errors) if errors.size else None
        metrics["error_pixels"] = int(errors.size)
    if extra:
        metrics.update(extra)
    return _json_safe(metrics)


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


def write_results(
    folder: Path,
    dataset: Dataset,
    solution: Any,
    *,
    solve_seconds: float,
    light_directions: np.ndarray | None = None,
    light_intensities: np.ndarray | None = None,
    extra: dict | None = None,
) -> dict:
    """Write every result file of one solve into ``folder`` (normally a :func:`staged_folder`).

    Parameters
    ----------
    folder : Path
        Existing folder to write into.
    dataset : Dataset
        The dataset that was solved (mask, ground truth, lights).
    solution : ps_lab.reconstruct.Solution
        Results for the P = ``dataset.mask.sum()`` mask pixels in row-major order.
    solve_seconds : float
        Wall-clock time of the solve.
    light_directions : ndarray of shape (n, 3) or None
        Refined light directions to write as ``light_directions.txt``.
    light_intensities : ndarray of shape (n, 3) or None
        Refined light intensities to write as ``light_intensities.txt``.
    extra : dict or None
        More entries for ``metrics.json``.

    Returns
    -------
    dict
        The metrics written to ``metrics.json``.

    """
    folder = Path(folder)
    mask = dataset.mask
    maps = solution_maps(solution, mask, dataset.valid[:, mask])
    try:
        np.save(folder / "normals.npy", maps.normals)
        np.save(folder / "albedo.npy", maps.albedo)
        write_png(folder / "normal.png", normal_picture(maps.normals, maps.solved))
        write_png(folder / "albedo.png", albedo_picture(maps.albedo, mask))
        write_png(folder / "corruption.png", corruption_picture(maps.corruption))
        if light_directions is not None:
            write_light_table(folder / "light_directions.txt", light_directions)
        if light_intensities is not None:
            write_light_table(folder / "light_intensities.txt", light_intensities)
        metrics = build_metrics(dataset, solution, maps, solve_seconds=solve_seconds, extra=extra)
        (folder / METRICS).write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"{folder}: cannot write results ({exc.strerror or exc})") from None
    return metrics


def reconstruct_to_folder(
    dataset: Dataset,
    out: Path,
    *,
    method: str = "sbl",
    threads: int | None = None,
    refine_lights: int = 0,
    fixed_intensities: bool = False,
    progress: Callable[[int], None] | None = None,
    extra: dict | None = None,
) -> dict:
    """Solve a loaded dataset and write every result file into ``out`` (staged, all or nothing).

    Parameters
    ----------
    dataset : Dataset
        Observations of the P = ``dataset.mask.sum()`` mask pixels are solved.
    out : Path
        Output folder: absent, empty or an earlier result (it is replaced only on success).
    method : {"ls", "l1", "sbl", "rpca"}
        Solver (:func:`ps_lab.reconstruct.solve`).
    threads : int or None
        Worker threads of the solver (default all cores).
    refine_lights : int
        Iterations of light refinement (:func:`ps_lab.reconstruct.refine_lights`); 0 = none. The
        refined lights are written as ``light_directions.txt`` / ``light_intensities.txt``.
    fixed_intensities : bool
        Refine directions only.
    progress : callable or None
        ``progress(k)`` with pixels just solved (P in all, P per solve when refining).
    extra : dict or None
        More entries for ``metrics.json``.

    Returns
    -------
    dict
        The metrics written to ``metrics.json`` (``out`` added under ``"out"``).

    """
    from ps_lab import reconstruct

    check_output_folder(out)
    observations = dataset.images[:, dataset.mask]
    valid = dataset.valid[:, dataset.mask]
    refined_directions = refined_intensities = None
    extra = dict(extra or {})
    with staged_folder(out) as stage:
        started = time.perf_counter()
        if refine_lights > 0:
            truth = None
            if dataset.normal_gt is not None:
                truth = dataset.normal_gt[dataset.mask]
                if not np.all(np.linalg.norm(truth, axis=1) > 0.5):
                    truth = None  # pixels without ground truth would read as 90-degree errors
            result = reconstruct.refine_lights(
                observations,
                dataset.light_directions,
                method=method,
                iterations=refine_lights,
                fixed_intensities=fixed_intensities,
                valid=valid,
                normal_gt=truth,
                threads=threads,
                progress=progress,
            )
            solution = result.solution
            refined_directions = np.asarray(result.light_directions, dtype=np.float64)
            # The observations were already divided by the file's intensities, so the refined
            # relative intensity multiplies them.
            scale = np.asarray(result.light_intensities, dtype=np.float64).reshape(-1, 1)
            refined_intensities = dataset.light_intensities * scale
            for step in result.history[1:]:
                log.info(
                    "light refinement iteration %d: mean direction change %.3f deg (max %.3f)",
                    step["iteration"],
                    step.get("mean_direction_change_deg", float("nan")),
                    step.get("max_direction_change_deg", float("nan")),
                )
            extra["refinement"] = {"iterations": refine_lights, "history": list(result.history)}
        else:
            solution = reconstruct.solve(
                observations,
                dataset.light_directions,
                method=method,
                valid=valid,
                threads=threads,
                progress=progress,
            )
        seconds = time.perf_counter() - started
        metrics = write_results(
            stage,
            dataset,
            solution,
            solve_seconds=seconds,
            light_directions=refined_directions,
            light_intensities=refined_intensities,
            extra=extra,
        )
    metrics["out"] = str(out)
    return metrics
