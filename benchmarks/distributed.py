"""Distributed benchmark: throughput on local Dask workers against the threaded in-process solve.

Renders one synthetic capture (the sphere of ``benchmarks/scale.py``), then reconstructs it

- in this process with ``--threads`` solver threads (the default path of ``ps-lab reconstruct``);
- with ``--scheduler`` on a ``LocalCluster`` of 1 and of 2 worker processes (one thread each);

and a batch of ``--batch`` copies of it (``ps-lab batch``: one task per dataset) on the same
clusters. Every run is repeated ``--repeat`` times after one warm-up (numba compiles its kernels
once per worker process; ``cache=True`` makes that a load from ``__pycache__``) and the median is
reported. Also measured: the round trip of an empty task, and the overhead per band task (the
pass's wall time times the workers, less the time the tasks spent solving, per task). Usage::

    python benchmarks/distributed.py [--megapixels 1] [--lights 40] [--method sbl]
                                     [--repeat 3] [--batch 4] [--folder DIR] [--markdown FILE]
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

# This file is benchmarks/distributed.py: its folder must not hide the `distributed` package.
_HERE = Path(__file__).resolve().parent
sys.path[:] = [entry for entry in sys.path if Path(entry or ".").resolve() != _HERE]

import distributed  # noqa: E402
import numpy as np  # noqa: E402

from ps_lab.reconstruct import distributed as ps_distributed  # noqa: E402
from ps_lab.reconstruct.batch import reconstruct_batch  # noqa: E402
from ps_lab.reconstruct.pipeline import ReconstructOptions, reconstruct_to_folder  # noqa: E402

sys.path.append(str(_HERE))
from scale import generate  # noqa: E402 - the scale benchmark's capture

TASK_SECONDS: list[float] = []


class RecordingBands(ps_distributed.DaskBands):
    """The Dask executor, noting how long each band task spent solving."""

    def solve(self, *args, **kwargs):
        for result in super().solve(*args, **kwargs):
            TASK_SECONDS.append(result.seconds)
            yield result


def _noop(i):
    return i


def empty_task_ms(client, count: int = 300) -> float:
    client.submit(_noop, -1, pure=False).result()
    started = time.perf_counter()
    futures = [client.submit(_noop, i, pure=False) for i in range(count)]
    for future in distributed.as_completed(futures, loop=client.loop):
        future.result()
    return (time.perf_counter() - started) / count * 1e3


def run(capture: Path, out: Path, options: ReconstructOptions, workers: int) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    TASK_SECONDS.clear()
    started = time.perf_counter()
    metrics = reconstruct_to_folder(capture, out, options).metrics
    wall = time.perf_counter() - started
    timings = metrics["timings"]
    entry = {
        "wall": wall,
        "read": timings["read_seconds"],
        "solve": timings["solve_seconds"],
        "bands": metrics["streaming"]["bands"],
        "pixels": metrics["pixels"],
        "error": (metrics.get("angular_error_deg") or {}).get("mean"),
        "normals": np.load(out / "normals.npy"),
    }
    if TASK_SECONDS:
        busy = sum(TASK_SECONDS)
        entry["overhead_ms"] = (timings["solve_seconds"] * workers - busy) / len(TASK_SECONDS) * 1e3
    return entry


def median_of(entries: list[dict]) -> dict:
    keys = [k for k in entries[0] if isinstance(entries[0][k], (int, float))]
    result = {k: statistics.median(e[k] for e in entries) for k in keys}
    result["normals"] = entries[0]["normals"]
    return result


def batch_seconds(client, capture: Path, root: Path, copies: int, options) -> float:
    datasets = []
    for i in range(copies):
        link = root / "datasets" / f"capture{i}"
        link.parent.mkdir(parents=True, exist_ok=True)
        if not link.exists():
            link.symlink_to(capture, target_is_directory=True)
        datasets.append(link)
    shutil.rmtree(root / "results", ignore_errors=True)
    started = time.perf_counter()
    rows = reconstruct_batch(datasets, root / "results", options, client)
    assert all(row.status == "done" for row in rows), rows
    return time.perf_counter() - started


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--megapixels", type=float, default=1.0)
    parser.add_argument("--lights", type=int, default=40)
    parser.add_argument("--method", default="sbl", choices=("ls", "l1", "sbl", "rpca"))
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--batch", type=int, default=4, help="datasets in the batch runs")
    parser.add_argument("--folder", type=Path, default=None, help="capture folder (reused)")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the table here")
    args = parser.parse_args(argv)
    ps_distributed.DaskBands = RecordingBands
    work = Path(tempfile.mkdtemp(prefix="ps-lab-distributed-"))
    capture = args.folder or work / "capture"
    if not (capture / "light_directions.txt").exists():
        print(f"rendering {args.megapixels} MP x {args.lights} lights ...", file=sys.stderr)
        generate(capture, args.megapixels, args.lights)
    options = ReconstructOptions(method=args.method, threads=args.threads)
    load = os.getloadavg()[0]
    rows = []
    runs = [run(capture, work / "here", options, 1) for _ in range(args.repeat + 1)][1:]
    here = median_of(runs)
    print(f"  in process: {here['wall']:.1f} s per run", file=sys.stderr)
    rows.append((f"in process, {args.threads} threads", "-", "-", here, None))
    for workers in (1, 2):
        started = time.perf_counter()
        with distributed.LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            silence_logs=logging.CRITICAL,
        ) as cluster, distributed.Client(cluster, set_as_default=False) as client:
            start = time.perf_counter() - started
            empty = empty_task_ms(client)
            on = options.replace(scheduler=cluster.scheduler_address)
            runs = [run(capture, work / "there", on, workers) for _ in range(args.repeat + 1)][1:]
            there = median_of(runs)
            diff = float(np.abs(there["normals"] - here["normals"]).max())
            assert diff <= 1e-6, diff
            batch = batch_seconds(client, capture, work, args.batch, options)
        rows.append((f"Dask, {workers} worker process(es)", start, empty, there, batch))
        print(f"  {workers} worker(s) done: {there['wall']:.1f} s per run", file=sys.stderr)
    table = render_table(rows, here, args, load)
    print(table)
    if args.markdown:
        args.markdown.write_text(table + "\n", encoding="utf-8")
    shutil.rmtree(work, ignore_errors=True)
    return 0


def render_table(rows, here, args, load) -> str:
    pixels = here["pixels"]
    lines = [
        f"Capture: {args.megapixels} MP, {args.lights} lights, {pixels:.0f} mask pixels; "
        f"method {args.method}; median of {args.repeat} runs after a warm-up.",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, dask {distributed.__version__}; "
        f"load average {load:.1f} at the start.",
        "",
        "| run | cluster start s | empty task ms | bands | read s | solve s | solve pixels/s "
        "| total pixels/s | overhead per band task ms | batch of "
        f"{args.batch}: s per dataset |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, start, empty, entry, batch in rows:
        lines.append(
            f"| {name} | {fmt(start, 1)} | {fmt(empty, 1)} | {entry['bands']:.0f} "
            f"| {entry['read']:.2f} | {entry['solve']:.2f} | {pixels / entry['solve']:.0f} "
            f"| {pixels / entry['wall']:.0f} | {fmt(entry.get('overhead_ms'), 0)} "
            f"| {fmt(None if batch is None else batch / args.batch, 2)} |"
        )
    return "\n".join(lines)


def fmt(value, digits: int) -> str:
    return "-" if value is None or value == "-" else f"{value:.{digits}f}"


if __name__ == "__main__":
    raise SystemExit(main())
