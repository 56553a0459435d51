"""Many datasets on a Dask cluster: one task per dataset, one result folder each (``ps-lab batch``).

Each dataset is reconstructed whole by one worker, with the in-process pipeline
(:func:`ps_lab.reconstruct.pipeline.reconstruct_to_folder`, one thread) writing its own staged
output folder ``OUT_ROOT/<dataset name>`` (a shared filesystem is assumed, as for
``--scheduler``). A dataset whose folder already holds a complete result made with the same
options is skipped, so a batch can be run again after an interruption; a result made with other
options (another ``--method``, say) is kept and named in a warning (:func:`option_differences`),
or replaced with ``overwrite``; a dataset that fails is reported and does not stop the others; a
worker that dies has its dataset run again elsewhere by Dask.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Callable, Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ps_lab.errors import DatasetError, PsLabError
from ps_lab.io.frames import FolderOfDatasetsError
from ps_lab.io.result import read_result_metrics
from ps_lab.reconstruct import distributed
from ps_lab.reconstruct.pipeline import SOLVER_OPTIONS, ReconstructOptions, reconstruct_to_folder
from ps_lab.reconstruct.options import MIN_AUTO_BUDGET, auto_memory_budget

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BatchRow:
    """One dataset of a batch.

    Attributes
    ----------
    dataset : Path
    out : Path
        Its result folder.
    status : {"done", "skipped", "kept", "failed"}
        ``skipped``: a complete result made with the same options was already there; ``kept``:
        one made with other options was there and was left as it is (``message`` names them).
    pixels : int or None
    seconds : float or None
        Wall time of its reconstruction on the worker (None when skipped or failed).
    error_deg : float or None
        Mean angular error against ground truth, when the dataset has it.
    message : str or None
        Why it failed, or which options of a kept result differ.
    warnings : tuple of str
        The warnings its reconstruction logged on the worker (said again by the batch, each
        naming the dataset: a worker process has no terminal of its own).
    pid : int or None
        The process that reconstructed it.

    """

    dataset: Path
    out: Path
    status: str
    pixels: int | None = None
    seconds: float | None = None
    error_deg: float | None = None
    message: str | None = None
    warnings: tuple[str, ...] = ()
    pid: int | None = None


def result_folders(datasets: Sequence[Path], out_root: Path) -> list[Path]:
    """``out_root / <name>`` for each dataset; raises DatasetError if two names collide."""
    # The name as given (a link keeps its own name), made absolute so that "." has one.
    outs = [Path(out_root) / Path(os.path.abspath(dataset)).name for dataset in datasets]
    seen: dict[Path, Path] = {}
    for dataset, out in zip(datasets, outs, strict=True):
        if out in seen:
            raise DatasetError(
                f"{dataset} and {seen[out]} would both write {out} (datasets need distinct names)"
            )
        seen[out] = Path(dataset)
    return outs


def finished_metrics(out: Path) -> dict | None:
    """The metrics of a complete result in ``out``, or None."""
    return read_result_metrics(out)


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    return "default" if value is None else str(value)


def option_differences(metrics: dict, options: ReconstructOptions) -> list[str]:
    """The options a stored result was made with that differ from ``options``.

    Parameters
    ----------
    metrics : dict
        The result's ``metrics.json``.
    options : ReconstructOptions
        The options asked for.

    Returns
    -------
    list of str
        One ``"--method sbl (asked ls)"`` per differing option, in command-line order; empty when
        the result is what ``options`` would make. Compared: what ``metrics.json`` records
        (method, channel, shadow threshold, fixed intensities, solver options, light model when
        asked for explicitly, light-refinement iterations, and depth when asked for); not
        ``threads`` or ``memory_budget`` (they do not change the result). An entry an older
        result does not record is not compared.
    """
    pairs: list[tuple[str, Any, Any]] = []
    for flag, key, asked in (
        ("--method", "method", options.method),
        ("--channel", "channel", options.channel),
        ("--shadow-threshold", "shadow_threshold", options.shadow_threshold),
        ("--fixed-intensities", "fixed_intensities", options.fixed_intensities),
    ):
        if key in metrics:
            pairs.append((flag, metrics[key], asked))
    solver = metrics.get("solver_options")
    if isinstance(solver, dict):
        for name, (flag, _) in SOLVER_OPTIONS.items():
            if flag[2:] in solver:
                pairs.append((flag, solver[flag[2:]], getattr(options, name)))
    if options.lights != "auto" and "light_model" in metrics:
        pairs.append(("--lights", metrics["light_model"], options.lights))
    refinement = metrics.get("refinement")
    refined = refinement.get("iterations", 0) if isinstance(refinement, dict) else 0
    pairs.append(("--refine-lights", refined, options.refine_lights))
    if options.depth is not None:
        depth = metrics.get("depth")
        method = depth.get("method") if isinstance(depth, dict) else "none"
        pairs.append(("--depth", method, options.depth))
    return [f"{flag} {_shown(was)} (asked {_shown(asked)})" for flag, was, asked in pairs
            if was != asked]


def _row(dataset: Path, out: Path, status: str, metrics: dict, seconds=None) -> BatchRow:
    errors = metrics.get("angular_error_deg") or {}
    return BatchRow(
        Path(dataset), Path(out), status, metrics.get("pixels"), seconds, errors.get("mean")
    )


class _Collected(logging.Handler):
    """The WARNING+ messages logged while one dataset is reconstructed."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def reconstruct_one(dataset: Path, out: Path, options: ReconstructOptions) -> BatchRow:
    """Reconstruct one dataset in this process (the task of a batch); errors become a row.

    Its warnings travel in the row (:func:`reconstruct_batch` says them in the batch's own
    process); in a worker process they would otherwise reach stderr bare, without ``warning:``.
    """
    started = time.perf_counter()
    collected = _Collected()
    root = logging.getLogger()
    root.addHandler(collected)
    try:
        metrics = reconstruct_to_folder(dataset, out, options).metrics
    except FolderOfDatasetsError as exc:
        message = f"{exc}, or give them all: {exc.folder}/*"
        return BatchRow(Path(dataset), Path(out), "failed", message=message)
    except PsLabError as exc:
        return BatchRow(Path(dataset), Path(out), "failed", message=str(exc))
    finally:
        root.removeHandler(collected)
    row = _row(dataset, out, "done", metrics, time.perf_counter() - started)
    return dataclasses.replace(row, warnings=tuple(collected.messages), pid=os.getpid())


def reconstruct_batch(
    datasets: Sequence[Path],
    out_root: Path,
    options: ReconstructOptions,
    client: Any,
    *,
    progress: Callable[..., None] | None = None,
    overwrite: bool = False,
) -> list[BatchRow]:
    """Reconstruct every dataset as one task on ``client``'s cluster; rows in input order.

    Parameters
    ----------
    datasets : sequence of Path
        Image folders or capture runs, with distinct folder names.
    out_root : Path
        Result folders are ``out_root / <dataset folder name>``.
    options : ReconstructOptions
        Used for every dataset (its ``scheduler`` and ``threads`` are replaced: each task solves
        in its worker with one thread; ``memory_budget`` None: the automatic budget shared by the
        cluster's workers).
    client : distributed.Client
        From :func:`ps_lab.reconstruct.distributed.connect` or ``local_cluster``.
    progress : callable or None
        ``progress(1, description=name)`` after each dataset (done, skipped, kept or failed).
    overwrite : bool
        Replace a result made with other options (else it is kept, with a warning in the log
        naming the dataset and the differing options). A result made with these options is
        skipped either way.

    Returns
    -------
    list of BatchRow

    """
    outs = result_folders(datasets, out_root)
    task_options = options.replace(scheduler=None, threads=1)
    if options.memory_budget is None:
        # --memory-budget auto: the workers share the memory (each task would take half of it)
        workers = max(len(client.scheduler_info().get("workers", {})), 1)
        task_options = task_options.replace(
            memory_budget=max(auto_memory_budget() // workers, MIN_AUTO_BUDGET))
    rows: dict[int, BatchRow] = {}
    futures = {}
    for index, (dataset, out) in enumerate(zip(datasets, outs, strict=True)):
        metrics = finished_metrics(out)
        differences = [] if metrics is None else option_differences(metrics, options)
        if metrics is not None and not (differences and overwrite):
            row = _row(dataset, out, "skipped", metrics)
            rows[index] = _kept(row, differences) if differences else row
            if progress is not None:
                done = "kept (other options)" if differences else "already done"
                progress(1, description=f"{Path(dataset).name}: {done}")
            continue
        # Dask's messages are UTF-8: a name that is not is escaped in the key (a label only).
        label = out.name.encode("utf-8", "backslashreplace").decode("ascii", "backslashreplace")
        key = f"ps-lab-dataset-{index}-{label}"
        future = client.submit(reconstruct_one, Path(dataset), out, task_options, key=key)
        futures[future.key] = (index, future)
    keys = {future.key: index for index, future in futures.values()}
    pending = [future for _, future in futures.values()]
    lost = "finished datasets are kept: run the batch again to do the rest"
    for future, row, exc in distributed.completed(client, pending, lost=lost):
        index = keys[future.key]
        if exc is not None:  # the task itself raised: a bug, or a worker that died too often
            message = f"{type(exc).__name__}: {exc}"
            row = BatchRow(Path(datasets[index]), outs[index], "failed", message=message)
        if row.pid is not None and row.pid != os.getpid():  # in-process: already logged here
            for message in row.warnings:  # each naming its dataset
                named = str(row.dataset) in message
                log.warning("%s%s", "" if named else f"{row.dataset}: ", message)
        rows[index] = row
        if progress is not None:
            progress(1, description=f"{row.dataset.name}: {row.status}")
    return [rows[index] for index in range(len(datasets))]


def _kept(row: BatchRow, differences: list[str]) -> BatchRow:
    """The row of a result made with other options, and the warning that names them."""
    made = ", ".join(differences)
    log.warning(
        "%s: kept the result in %s, made with other options: %s; --overwrite replaces it "
        "(or choose another --out-root)",
        row.dataset,
        row.out,
        made,
    )
    return BatchRow(row.dataset, row.out, "kept", row.pixels, None, row.error_deg,
                    f"made with {made}")


def run_batch(
    datasets: Sequence[Path],
    out_root: Path,
    options: ReconstructOptions,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress_bars: Callable[[int, str], Any] | None = None,
    overwrite: bool = False,
) -> list[BatchRow]:
    """Reconstruct many datasets on the Dask scheduler ``scheduler``, else on a local cluster.

    Parameters
    ----------
    datasets, out_root, options
        As for :func:`reconstruct_batch`.
    scheduler : str or None
        Address of a running Dask scheduler; None starts a cluster of ``workers`` processes on
        this machine for the batch (the embedded default).
    workers : int or None
        Local worker processes (default: one per core); ignored with ``scheduler``.
    progress_bars : callable or None
        ``progress_bars(total, description)`` (see :func:`ps_lab.reconstruct.pipeline.
        reconstruct_to_folder`): one bar over the datasets.
    overwrite : bool
        As for :func:`reconstruct_batch`.

    Returns
    -------
    list of BatchRow

    Raises
    ------
    ClusterError
        Dask not installed, the scheduler unreachable or lost.
    DatasetError
        Two datasets with the same folder name.

    """
    outs = result_folders(datasets, out_root)  # name clashes fail before any cluster starts
    check_out_root(out_root)
    distributed.require_dask()
    if scheduler is not None:
        cluster = distributed.connect(scheduler)
    else:
        cluster = distributed.local_cluster(workers or os.cpu_count() or 1)
    bar = (
        progress_bars(len(datasets), "datasets")
        if progress_bars is not None
        else nullcontext(lambda n=1, description=None: None)
    )
    before = [finished_metrics(out) is not None for out in outs]
    try:
        with cluster as client, bar as advance:
            return reconstruct_batch(
                datasets, out_root, options, client, progress=advance, overwrite=overwrite
            )
    except KeyboardInterrupt as exc:
        # Counted once the cluster is closed: a dataset a worker finished meanwhile counts.
        done = sum(
            not was and finished_metrics(out) is not None
            for was, out in zip(before, outs, strict=True)
        )
        kept = sum(before)
        exc.outcome = (  # type: ignore[attr-defined] - read by ps_lab._cli_util.lab_command
            f"{done} of {len(outs)} datasets finished in this run"
            + (f" ({kept} were already done)" if kept else "")
            + "; their results are complete, the others were not written: run the batch again "
            "to do the rest"
        )
        raise


def check_out_root(out_root: Path) -> None:
    """Refuse an ``--out-root`` that exists and is not a folder (before any cluster starts)."""
    out_root = Path(out_root)
    if (out_root.exists() or out_root.is_symlink()) and not out_root.is_dir():
        raise DatasetError(
            f"--out-root {out_root}: exists and is not a folder (results go to "
            "OUT_ROOT/<dataset folder name>)"
        )


def failure_line(rows: Sequence[BatchRow]) -> str | None:
    """The one error line of a batch with failed datasets (naming the first), or None."""
    failed = [row for row in rows if row.status == "failed"]
    if not failed:
        return None
    first = failed[0]
    more = f" (and {len(failed) - 1} more, see the summary)" if len(failed) > 1 else ""
    message = first.message or "failed"
    if str(first.dataset) not in message:
        message = f"{first.dataset}: {message}"
    return f"{len(failed)} of {len(rows)} datasets failed: {message}{more}"


def summary_table(rows: Sequence[BatchRow]) -> str:
    """The batch summary: dataset, pixels, seconds, mean error (when ground truth), status."""
    header = ("dataset", "pixels", "seconds", "error (deg)", "status")
    lines = [header]
    for row in rows:
        status = row.status if row.message is None else f"{row.status}: {row.message}"
        lines.append(
            (
                str(row.dataset),
                "-" if row.pixels is None else str(row.pixels),
                "-" if row.seconds is None else f"{row.seconds:.1f}",
                "-" if row.error_deg is None else f"{row.error_deg:.2f}",
                status,
            )
        )
    widths = [max(len(line[k]) for line in lines) for k in range(len(header) - 1)]
    return "\n".join(
        "  ".join(
            [cell.ljust(width) if k == 0 else cell.rjust(width) for k, (cell, width) in
             enumerate(zip(line[:-1], widths, strict=True))] + [line[-1]]
        )
        for line in lines
    )
