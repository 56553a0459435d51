"""`ps-lab bench`: benchmarks that regenerate published results (rendered scenes, real data)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import HELP_SETTINGS, HelpGroup, lab_command, progress_bar
from ps_lab.bench import paper as bench_paper
from ps_lab.bench import real as bench_real
from ps_lab.bench import relight as bench_relight
from ps_lab.bench import report

MarkdownFlag = Annotated[
    bool, typer.Option("--markdown", help="Print Markdown (for docs/results.md) instead of text.")
]
JsonFile = Annotated[
    Path | None, typer.Option("--json", help="Also write all numbers to this JSON file.")
]

bench_app = typer.Typer(
    name="bench",
    help="Benchmarks on rendered scenes (the paper's tables).",
    no_args_is_help=True,
    cls=HelpGroup,
    **HELP_SETTINGS,
)


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
    with progress_bar(bench_paper.total_steps(config), "paper tables", enabled=progress) as advance:
        results = bench_paper.run_paper(config, progress=advance)
    typer.echo(
        report.format_markdown(results) if markdown else report.format_text(results)
    )
    if json_out is not None:
        json_out.write_text(json.dumps(report.results_as_dict(results), indent=1))


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
    folder = folder if folder is not None else bench_real.DEFAULT_FOLDER
    objects = bench_real.find_objects(folder)
    if not objects:
        typer.echo(f"skipped: no object folders with ground truth under {folder}")
        return
    total = len(objects) * len(bench_real.columns())
    with progress_bar(total, "real objects", enabled=True) as advance:
        rows = bench_real.run_real(folder, every=every, threads=threads,
                                   progress=lambda label: advance(1, description=label))
    typer.echo(bench_real.format_table(rows, markdown=markdown))
    if json_out is not None:
        json_out.write_text(json.dumps(bench_real.results_as_dict(rows), indent=1))


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
    folder = folder if folder is not None else bench_relight.DEFAULT_FOLDER
    captures = bench_relight.find_captures(folder)
    if not captures:
        typer.echo(f"skipped: no capture folders (light directions) under {folder}")
        return
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
    if json_out is not None:
        json_out.write_text(json.dumps(bench_relight.results_as_dict(rows), indent=1))


def register(app: typer.Typer) -> None:
    """Add the ``bench`` command group to ``app``."""
    app.add_typer(bench_app, name="bench")
