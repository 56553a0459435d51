"""`ps-lab relight`: a result's object under any light direction, as EXR or PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import choices, lab_command
from ps_lab.appearance.relight import relight_result


RelightMode = choices("RelightMode", "fitted lambertian", "How the object is shaded.")


@lab_command
def relight(
    result: Annotated[
        Path, typer.Argument(help="A ps-lab reconstruct output folder.", show_default=False)
    ],
    light: Annotated[
        list[str],
        typer.Option(
            "--light",
            metavar="X,Y,Z",
            help="Light direction in the dataset's light frame (x right, y up, z toward the "
            "camera); for a near-light result an LED position (scene frame, pixels); repeat "
            "for several pictures.",
            show_default=False,
        ),
    ],
    out: Annotated[
        Path,
        typer.Option(
            help="Picture file: .exr (float linear RGB, the solver's units) or .png (sRGB, "
            "clipped at 1); several lights write OUT_light01.ext, OUT_light02.ext, ...",
            show_default=False,
        ),
    ],
    appearance: Annotated[
        RelightMode,
        typer.Option(
            case_sensitive=False,
            help="fitted: the result's appearance.npz (reconstruct --appearance); lambertian: "
            "albedo x max(n.l, 0).",
        ),
    ] = RelightMode.fitted,
) -> None:
    """Render the reconstructed object under new light directions (EXR or PNG)."""
    written = relight_result(result, light, out, appearance.value)
    for path, direction in written:
        typer.echo(f"{path}: light {direction[0]:.4f},{direction[1]:.4f},{direction[2]:.4f}")


def register(app: typer.Typer) -> None:
    """Add ``relight`` to the app."""
    app.command()(relight)
