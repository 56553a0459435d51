"""`ps-lab simulate`: render a scene under random lights and write it as a dataset folder."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import choices, from_params, lab_command, progress_bar
from ps_lab.errors import DatasetError
from ps_lab.render import SimulationSettings, check_new_dataset_folder, write_simulated_dataset
from ps_lab.render.simulate import board_spec, simulated_board


SceneKind = choices("SceneKind", "sphere relief", "Rendered objects.")
ImageFormat = choices(
    "ImageFormat", "png16 tiff32 npy", "Image file formats of the written dataset."
)


@lab_command
def simulate(
    out: Annotated[
        Path,
        typer.Argument(help="New dataset folder (must not exist or be empty).", show_default=False),
    ],
    scene: Annotated[
        SceneKind,
        typer.Option(
            case_sensitive=False,
            help="sphere, or relief (a height field whose bumps cast shadows).",
        ),
    ] = SceneKind.sphere,
    lights: Annotated[int, typer.Option(min=3, help="Number of random lights.")] = 40,
    size: Annotated[
        int, typer.Option(min=8, max=8192, help="Image width and height in pixels.")
    ] = 128,
    seed: Annotated[
        int, typer.Option(min=0, help="Seed of the lights, the relief layout and the noise.")
    ] = 0,
    specular: Annotated[
        float, typer.Option(min=0.0, help="Cook-Torrance strength (0 = Lambertian).")
    ] = 0.0,
    roughness: Annotated[float, typer.Option(min=1e-3, help="Beckmann roughness m.")] = 0.3,
    noise_fraction: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="Share of observations that get Gaussian noise.")
    ] = 0.0,
    noise_sigma: Annotated[
        float, typer.Option(min=0.0, help="Standard deviation of that noise.")
    ] = 0.0,
    cast_shadows: Annotated[bool, typer.Option(help="Ray-march cast shadows.")] = True,
    max_zenith: Annotated[
        float, typer.Option(help="Largest light angle from the camera axis, degrees.")
    ] = 60.0,
    image_format: Annotated[
        ImageFormat,
        typer.Option(
            "--format",
            case_sensitive=False,
            help="png16 (scaled: peak = 0.9 x 65535), tiff32 or npy (linear)."
        ),
    ] = ImageFormat.png16,
    lens: Annotated[
        str | None,
        typer.Option(
            metavar="<k1,k2,p1,p2,k3>",
            help="Lens distortion K1[,K2,P1,P2,K3] (OpenCV's radial-tangential model) applied "
            "to the frames; ground truth stays undistorted (camera_truth.json).",
            show_default=False,
        ),
    ] = None,
    focal_length: Annotated[
        float | None,
        typer.Option(help="That lens's focal length in pixels (default: the image size).",
                     show_default=False),
    ] = None,
    board_frames: Annotated[
        int,
        typer.Option(min=0, help="With --lens: also render this many ChArUco board views into "
                     "OUT/board/ for `ps-lab calibrate-camera`."),
    ] = 0,
) -> None:
    """Render a sphere or relief under random lights and write it as a dataset with ground truth.

    Writes the images, filenames.txt, light_directions.txt, light_intensities.txt, mask.png,
    normal_gt.npy and depth_gt.npy.
    """
    settings = from_params(
        SimulationSettings,
        locals(),
        max_zenith_deg=max_zenith,
        lens=None if lens is None else _lens(lens),
    )
    settings.validate()
    check_new_dataset_folder(out)
    with progress_bar(2 * lights, f"rendering {scene.value}") as advance:
        result = write_simulated_dataset(out, settings, progress=advance)
    if board_frames and lens is not None:
        typer.echo(
            f"board views: ps-lab calibrate-camera {out}/board/*.png --board "
            f"{board_spec(simulated_board(size))} --out {out}"
        )
    typer.echo(
        f"wrote {result['images']} images of {size}x{size} "
        f"({result['pixels']} object pixels) to {out}"
    )


def _lens(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise DatasetError(f"--lens {text}: give K1[,K2,P1,P2,K3] as numbers") from None


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to the app."""
    app.command()(simulate)
