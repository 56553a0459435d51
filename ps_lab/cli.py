"""The ``ps-lab`` command line: thin wiring of the library, one module per command."""

from __future__ import annotations

import logging
from typing import Annotated

import typer

from ps_lab import __version__
from ps_lab.commands import bench, calibrate, capture, reconstruct, rig, simulate

app = typer.Typer(
    name="ps-lab",
    help=(
        "Photometric stereo in the lab: capture one frame per light on a rig, calibrate the "
        "light directions from a chrome sphere, and reconstruct surface normals robustly (SBL)."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"ps-lab {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: Annotated[
        int, typer.Option("--verbose", "-v", count=True, help="-v: info, -vv: debug (serial traffic).")
    ] = 0,
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.")
    ] = False,
) -> None:
    """Configure logging for every command."""
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


for _module in (simulate, reconstruct, capture, calibrate, rig, bench):
    _module.register(app)


def main() -> None:
    """Console-script entry point."""
    app(prog_name="ps-lab")
