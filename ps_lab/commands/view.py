"""`ps-lab view`: relight and inspect results in the browser, or export them as a static folder."""

from __future__ import annotations

import os
import sys
import threading
import webbrowser
from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import EXIT_INTERRUPTED, choices, fail, interrupted_line, lab_command
from ps_lab.appearance.export import export_relightlab
from ps_lab.view import ViewSite, export_site, serve
from ps_lab.view.relightlab import load_view_result


ExportFormat = choices(
    "ExportFormat", "site relight", "What --export writes (--format): the viewer or RelightLab's."
)


@lab_command
def view(
    results: Annotated[
        list[Path],
        typer.Argument(
            help="One or more ps-lab reconstruct result folders, or RelightLab web folders "
            "(info.json, plane_N.jpg) (two or more: side by side).",
            show_default=False,
        ),
    ],
    port: Annotated[
        int,
        typer.Option(
            min=0, max=65535, help="Port on 127.0.0.1 (default: a free one).", show_default=False
        ),
    ] = 0,
    no_browser: Annotated[
        bool, typer.Option("--no-browser", help="Print the address only; open no browser.")
    ] = False,
    export: Annotated[
        Path | None,
        typer.Option(
            help="Write the viewer and its data into this folder (for any static web server) "
            "instead of serving.",
            show_default=False,
        ),
    ] = None,
    export_format: Annotated[
        ExportFormat,
        typer.Option(
            "--format",
            case_sensitive=False,
            help="With --export: site (the viewer as a static folder) or relight "
            "(RelightLab's web layout of one result for OpenLIME's RTI layer: info.json, "
            "plane_N.jpg, normals.png, albedo.png; a PTM / HSH fit as it is, any other model "
            "converted to RBF, its PSNR against the model printed).",
        ),
    ] = ExportFormat.site,
) -> None:
    """Relight results under a virtual light, see their layers and mesh, compare them.

    The server listens on 127.0.0.1 and answers only requests addressed to its own names
    (127.0.0.1, localhost, [::1]); it only reads, and drops a client that stalls for 10 s.
    """
    if export_format is ExportFormat.relight:
        if export is None or len(results) != 1:
            raise fail("--format relight needs --export DIR and exactly one result")
        _, line = export_relightlab(results[0], export)
        typer.echo(line)
        return
    site = ViewSite([load_view_result(result) for result in results])
    if export is not None:
        size = export_site(site, export)
        typer.echo(f"viewer written to {export} ({size / 2**20:.1f} MiB); serve the folder, e.g.")
        typer.echo(f"  python3 -m http.server -d {export} 8000   then open http://127.0.0.1:8000/")
        return

    def ready(address: str) -> None:
        typer.echo(f"ps-lab view: {address}  (Ctrl-C stops)")
        if no_browser:
            return
        if sys.platform.startswith("linux") and not (
            os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
        ):
            # webbrowser would start a console browser (lynx, w3m) in this terminal.
            port_used = address.rstrip("/").rsplit(":", 1)[1]
            typer.echo(
                "no display here: open the address in a browser (an SSH tunnel works, to the "
                f"same port: ssh -L {port_used}:127.0.0.1:{port_used} THIS-HOST)"
            )
            return
        # In a thread: some browsers' launchers wait until the browser exits.
        threading.Thread(target=webbrowser.open, args=(address,), daemon=True).start()

    try:
        serve(site, port, on_ready=ready)
    except KeyboardInterrupt as exc:
        raise fail(f"{interrupted_line(exc)}; viewer stopped", EXIT_INTERRUPTED) from None


def register(app: typer.Typer) -> None:
    """Add ``view`` to the app."""
    app.command()(view)
