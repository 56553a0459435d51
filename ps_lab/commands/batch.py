"""`ps-lab batch`: many datasets on a Dask cluster, one result folder each, and a summary."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import fail, lab_command
from ps_lab.commands.reconstruct import (
    Channel,
    ChannelOption,
    DepthOption,
    FixedIntensitiesOption,
    LambdaOption,
    Lights,
    LightsOption,
    MaxIterOption,
    MemoryBudgetOption,
    Method,
    MethodOption,
    RefineLightsOption,
    ShadowThresholdOption,
    SigmaX2Option,
    TolOption,
    _terminal_bars,
    options_from,
)
from ps_lab.reconstruct.batch import failure_line, run_batch, summary_table
from ps_lab.reconstruct.methods import DEFAULT_METHOD


@lab_command
def batch(
    datasets: Annotated[
        list[Path],
        typer.Argument(help="Image folders or capture runs (distinct folder names).",
                       show_default=False),
    ],
    out_root: Annotated[
        Path,
        typer.Option(help="Results go to OUT_ROOT/<dataset folder name>.", show_default=False),
    ],
    scheduler: Annotated[
        str | None,
        typer.Option(
            envvar="PS_LAB_SCHEDULER",
            metavar="<address>",
            help="Dask scheduler address (tcp://host:8786); without it, a local cluster.",
            show_default=False,
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            min=1,
            help="Local worker processes without --scheduler (default: one per core).",
            show_default=False,
        ),
    ] = None,
    method: MethodOption = Method(DEFAULT_METHOD),
    shadow_threshold: ShadowThresholdOption = None,
    channel: ChannelOption = Channel.mean,
    refine_lights: RefineLightsOption = 0,
    fixed_intensities: FixedIntensitiesOption = False,
    memory_budget: MemoryBudgetOption = "auto",
    lights: LightsOption = Lights.auto,
    lam: LambdaOption = None,
    sigma_x2: SigmaX2Option = None,
    max_iter: MaxIterOption = None,
    tol: TolOption = None,
    depth: DepthOption = None,
    overwrite: Annotated[
        bool,
        typer.Option(
            "--overwrite",
            help="Replace results in OUT_ROOT made with other options (default: keep them, "
            "with a warning naming the options).",
        ),
    ] = False,
) -> None:
    """Reconstruct many datasets on a Dask cluster; skip those already done; print a summary.

    A result already in OUT_ROOT made with the same options is skipped; one made with other
    options is kept, and a warning names the dataset and the options (--overwrite replaces it).
    """
    options = options_from(locals(), leave=("scheduler",))  # the cluster's, not each dataset's
    rows = run_batch(
        datasets,
        out_root,
        options,
        scheduler=scheduler,
        workers=workers,
        progress_bars=_terminal_bars,
        overwrite=overwrite,
    )
    typer.echo(summary_table(rows))
    failed = failure_line(rows)
    if failed:
        raise fail(failed)


def register(app: typer.Typer) -> None:
    """Add ``batch`` to the app."""
    app.command("batch")(batch)
