"""`ps-lab integrate`: depth maps and a mesh from a reconstruct result's normals."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import lab_command
from ps_lab.commands.reconstruct import DepthMethod, _depth_line, _terminal_bars
from ps_lab.io.camera import read_result_camera
from ps_lab.reconstruct.depth import DepthOptions, integrate_result, with_camera


@lab_command
def integrate(
    result: Annotated[
        Path, typer.Argument(help="A ps-lab reconstruct output folder.", show_default=False)
    ],
    method: Annotated[
        DepthMethod,
        typer.Option(
            case_sensitive=False, help="poisson (least squares) or bilateral (keeps depth steps)."
        ),
    ] = DepthMethod.poisson,
    pixel_size: Annotated[
        float | None,
        typer.Option(help="Pixel width on the object in mm: depth and mesh in mm.", min=0.0),
    ] = None,
    focal_length: Annotated[
        float | None,
        typer.Option(help="Perspective camera: focal length in pixels (default: orthographic)."),
    ] = None,
    camera: Annotated[
        Path | None,
        typer.Option(
            help="A camera.json (ps-lab calibrate-camera): perspective integration with its "
            "focal length and principal point (default: the one the reconstruction's dataset "
            "had, recorded in metrics.json). With --pixel-size, depth in mm.",
            show_default=False,
        ),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Output folder (default: RESULT).", show_default=False)
    ] = None,
) -> None:
    """Integrate normals.npy into depth.npy, depth.tiff, depth.png and mesh.ply."""
    options = DepthOptions(method=method.value, pixel_size=pixel_size, focal_length=focal_length)
    if camera is not None:
        options = with_camera(options, read_result_camera(camera, result))
    depth = integrate_result(result, out, options, progress_bars=_terminal_bars)
    typer.echo(_depth_line(depth))
    typer.echo(f"results: {out if out is not None else result}")


def register(app: typer.Typer) -> None:
    """Add ``integrate`` to the app."""
    app.command()(integrate)
