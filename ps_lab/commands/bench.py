"""`ps-lab bench`: benchmarks that regenerate published results (rendered scenes, real data)."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated, Any

import typer

from ps_lab._cli_util import command_group, lab_command, progress_bar
from ps_lab.bench import paper as bench_paper
from ps_lab.bench import real as bench_real
from ps_lab.bench import relight as bench_relight
from ps_lab.bench import report
from ps_lab.errors import DatasetError, OutputError
from ps_lab.io.dataset import open_dataset
from ps_lab.io.files import write_json_atomic

MarkdownFlag = Annotated[
    bool, typer.Option("--markdown", help="Print Markdown (for docs/results.md) instead of text.")
]
JsonFile = Annotated[
    Path | None, typer.Option("--json", help="Also write all numbers to this JSON file.")
]



def check_json_path(path: Path | None) -> None:
    """Refuse, before any work, a ``--json`` file that could not be written at the end.

    A folder, a link to one, a file in a missing or read-only folder: :class:`OutputError`
    naming ``--json`` and the path.
    """
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"--json {path}: is a folder; give a file name")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"--json {path}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"--json {path}: the folder {parent} is not writable")
    if path.exists() and not path.is_file():
        raise OutputError(f"--json {path}: exists and is not a file")


def finite_json(value: Any) -> Any:
    """``value`` with every NaN or infinite float as None (JSON has no NaN: ``null``)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    return value


def write_json(path: Path | None, results: Any) -> None:
    """Write ``--json`` (atomically; NaN as null) when asked for."""
    if path is not None:
        write_json_atomic(path, finite_json(results))


def check_bench_folder(folder: Path | None, found: list[Path], default: Path, what: str) -> bool:
    """Whether to run on ``found`` (the benchmark's inputs under ``folder``).

    The default shared-data folder absent: False (the caller prints "skipped"). A folder the
    user named that is missing, a file, or holds none of ``what``: :class:`DatasetError`.
    """
    if folder is None and not default.is_dir():
        return False
    folder = default if folder is None else Path(folder)
    if not folder.exists():
        raise DatasetError(f"{folder}: no such folder")
    if not folder.is_dir():
        raise DatasetError(f"{folder}: is a file, not a folder of {what}")
    if not found:
        raise DatasetError(f"{folder}: holds no {what}")
    return True


def check_light_counts(paths: list[Path], minimum: int, reason: str) -> None:
    """Every capture in ``paths`` opened (files checked, no pixel read) and holding at least
    ``minimum`` lights, else :class:`DatasetError` naming it."""
    for path in paths:
        n = len(open_dataset(path, read_size=False).names)
        if n < minimum:
            raise DatasetError(f"{path}: {n} lights; {reason} needs at least {minimum}")


bench_app = command_group("Benchmarks on rendered scenes (the paper's tables).", name="bench")


@bench_app.command("paper")
@lab_command
def paper(
    quick: Annotated[
        bool,
        typer.Option("--quick", help="Reduced run for CI: 48x48 images, two light sets, no R-PCA."),
    ] = False,
    size: Annotated[
        int | None,
        typer.Option(
            min=8, max=2048, help="Image width and height in pixels (default 128; --quick 48)."
        ),
    ] = None,
    light_sets: Annotated[
        int | None,
        typer.Option(min=1, help="Random light sets to average (default 5; 2 with --quick)."),
    ] = None,
    seed: Annotated[
        int | None, typer.Option(min=0, help="Seed of the light sets (default 0).")
    ] = None,
    tables: Annotated[
        str | None,
        typer.Option(
            metavar="<list>", help="Tables to run, comma-separated from 1,3,4,5 (default all)."
        ),
    ] = None,
    markdown: MarkdownFlag = False,
    json_out: JsonFile = None,
    progress: Annotated[bool, typer.Option(help="Show a progress bar on stderr.")] = True,
) -> None:
    """Regenerate Tables 1, 3, 4 and 5 of Ikehata et al. (CVPR 2012) for LS, L1, R-PCA and SBL."""
    try:
        config = bench_paper.make_config(
            quick=quick,
            size=size,
            light_sets=light_sets,
            seed=seed,
            tables=bench_paper.parse_tables(tables) if tables else None,
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    check_json_path(json_out)
    with progress_bar(bench_paper.total_steps(config), "paper tables", enabled=progress) as advance:
        results = bench_paper.run_paper(config, progress=advance)
    typer.echo(
        report.format_markdown(results) if markdown else report.format_text(results)
    )
    write_json(json_out, report.results_as_dict(results))


@bench_app.command("real")
@lab_command
def real(
    folder: Annotated[
        Path | None,
        typer.Argument(
            help="Folder of object folders (DiLiGenT layout with normal_gt) "
            "(default: ../shared/data/diligent-8bit from the repository root).",
            show_default=False,
        ),
    ] = None,
    every: Annotated[
        int, typer.Option(min=1, help="Keep every N-th mask pixel (quick runs).")
    ] = 1,
    markdown: MarkdownFlag = False,
    json_out: JsonFile = None,
    threads: Annotated[
        int | None,
        typer.Option(min=1, help="Solver threads (default: all cores).", show_default=False),
    ] = None,
) -> None:
    """The default, LS, L1, SBL, PL-LS, PL-SBL, R-PCA and SBL at fixed lambda on real objects."""
    check_json_path(json_out)
    objects = bench_real.find_objects(folder if folder is not None else bench_real.DEFAULT_FOLDER)
    what = "object folders with light_directions.txt and ground truth"
    if not check_bench_folder(folder, objects, bench_real.DEFAULT_FOLDER, what):
        typer.echo(f"skipped: no {what} under {bench_real.DEFAULT_FOLDER}")
        return
    folder = folder if folder is not None else bench_real.DEFAULT_FOLDER
    check_light_counts(objects, bench_real.RELIGHT_EVERY,
                       f"holding out every {bench_real.RELIGHT_EVERY}th light")
    total = len(objects) * len(bench_real.columns())
    with progress_bar(total, "real objects", enabled=True) as advance:
        rows = bench_real.run_real(folder, every=every, threads=threads,
                                   progress=lambda label: advance(1, description=label))
    typer.echo(bench_real.format_table(rows, markdown=markdown))
    write_json(json_out, bench_real.results_as_dict(rows))


@bench_app.command("relight")
@lab_command
def relight(
    folder: Annotated[
        Path | None,
        typer.Argument(
            help="A capture folder, or a folder of them (default: the shared DiLiGenT objects, "
            "../shared/data/diligent-8bit from the repository root).",
            show_default=False,
        ),
    ] = None,
    extrapolate: Annotated[
        bool,
        typer.Option(
            "--extrapolate",
            help="Hold out the lowest eighth of the lights (outside the training range) instead "
            "of every 8th.",
        ),
    ] = False,
    markdown: MarkdownFlag = False,
    json_out: JsonFile = None,
) -> None:
    """Held-out relighting PSNR and SSIM of every appearance model (eight folds: every light
    held out once)."""
    check_json_path(json_out)
    folder_given = folder
    folder = folder if folder is not None else bench_relight.DEFAULT_FOLDER
    captures = bench_relight.find_captures(folder)
    what = "capture folders (light_directions.txt or an .lp file)"
    if not check_bench_folder(folder_given, captures, bench_relight.DEFAULT_FOLDER, what):
        typer.echo(f"skipped: no {what} under {folder}")
        return
    every = bench_relight.HOLD_OUT_EVERY  # each of the eight folds holds out one light at least
    check_light_counts(captures, every, f"holding out every {every}th light")
    total = len(captures) * len(bench_relight.MODELS) * bench_relight.folds_of(
        folder, extrapolate=extrapolate)
    with progress_bar(total, "relighting", enabled=True) as advance:
        rows = [
            bench_relight.evaluate_capture(
                path, progress=lambda label: advance(1, description=label),
                extrapolate=extrapolate,
            )
            for path in captures
        ]
    typer.echo(bench_relight.format_table(rows, markdown=markdown))
    write_json(json_out, bench_relight.results_as_dict(rows))


def register(app: typer.Typer) -> None:
    """Add the ``bench`` command group to ``app``."""
    app.add_typer(bench_app, name="bench")
