"""The ``ps-lab`` command line: thin wiring of the library, one module per command.

Commands are registered here, in :data:`COMMANDS`. Their modules are loaded lazily, in this one
place: ``ps-lab reconstruct`` imports only ``ps_lab.commands.reconstruct`` (so reading a dataset
loads no pyserial, no capture package and no renderer), while ``ps-lab --help``, an unknown
command and ``ps_lab.cli.app`` (the tests' CliRunner) load them all.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Iterable, Sequence
from typing import Annotated, Any

import typer

from ps_lab import __version__
from ps_lab._cli_util import HELP_SETTINGS, LabGroup, configure_logging

#: Command name -> module with ``register(app)``, in the order of ``ps-lab --help``.
COMMANDS = {
    "simulate": "ps_lab.commands.simulate",
    "reconstruct": "ps_lab.commands.reconstruct",
    "batch": "ps_lab.commands.batch",
    "integrate": "ps_lab.commands.integrate",
    "relight": "ps_lab.commands.relight",
    "view": "ps_lab.commands.view",
    "capture": "ps_lab.commands.capture",
    "calibrate": "ps_lab.commands.calibrate",
    "calibrate-camera": "ps_lab.commands.calibrate_camera",
    "rig": "ps_lab.commands.rig",
    "bench": "ps_lab.commands.bench",
}


def make_app(commands: Iterable[str] = tuple(COMMANDS)) -> typer.Typer:
    """Build the ``ps-lab`` app with the named commands (all by default)."""
    app = typer.Typer(
        name="ps-lab",
        help=(
            "Photometric stereo in the lab: capture one frame per light on a rig, calibrate the "
            "light directions from a chrome sphere, and reconstruct surface normals robustly "
            "(SBL)."
        ),
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
        cls=LabGroup,  # one `error:` line and exit 2 for every failure, 130 for a signal
        **HELP_SETTINGS,
    )
    app.callback()(_root)
    for name in commands:
        importlib.import_module(COMMANDS[name]).register(app)
    return app


def _version(value: bool) -> None:
    if value:
        typer.echo(f"ps-lab {__version__}")
        raise typer.Exit()


def _root(
    verbose: Annotated[
        int,
        typer.Option(
            "--verbose",
            "-v",
            count=True,
            show_default=False,
            help="-v: info, -vv: debug (serial traffic); before the command.",
        ),
    ] = 0,
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.")
    ] = False,
) -> None:
    """Configure logging for every command."""
    configure_logging(verbose)


def __getattr__(name: str) -> Any:
    # ``ps_lab.cli.app``: the app with every command, built on first use (PEP 562).
    if name == "app":
        app = make_app()
        globals()["app"] = app
        return app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main(argv: Sequence[str] | None = None) -> None:
    """Console-script entry point: load only the command that is run."""
    args = list(sys.argv[1:] if argv is None else argv)
    command = next((arg for arg in args if not arg.startswith("-")), None)
    make_app([command] if command in COMMANDS else COMMANDS)(args=args, prog_name="ps-lab")
