"""`ps-lab calibrate`: light directions (and intensities) from a chrome sphere in every frame."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from ps_lab._cli_util import lab_command, naming_folder, parse_numbers, positive, progress_bar
from ps_lab.calibration import calibrate as run_calibration
from ps_lab.calibration import (
    combine_probes,
    rig_anisotropy,
    rig_chrome_spheres,
    rig_circles,
    rig_led_intensities,
    rig_object_outline,
    with_led_model,
    write_calibration,
)
from ps_lab.commands._shared_options import Encoding, EncodingOption
from ps_lab.errors import CalibrationError
from ps_lab.io.camera import camera_record, undistort_frame
from ps_lab.io.dataset import Frames, load_frames
from ps_lab.io.encoding import frames_encoding
from ps_lab.io.images import read_image
from ps_lab.io.light_files import read_led_intensities


def circle_in_image(circle: tuple[float, ...], width: int, height: int) -> bool:
    """Whether the circle's centre lies in the image and the circle overlaps it."""
    cx, cy, r = circle
    return 0 <= cx < width and 0 <= cy < height and r < max(width, height)


@lab_command
def calibrate(
    data: Annotated[
        list[Path],
        typer.Argument(
            help="Capture run or image folder (one frame per light); several folders: one "
            "chrome probe each, photographed under the same lights (one light set).",
            show_default=False,
        ),
    ],
    sphere: Annotated[
        list[str] | None,
        typer.Option(
            metavar="<cx,cy,r>",
            help="Chrome sphere circle CX,CY,R in pixels (x = column, y = row), used as given; "
            "give it twice (two spheres) for LED positions."
        ),
    ] = None,
    roi: Annotated[
        str | None,
        typer.Option(metavar="<x,y,w,h>", help="Search the sphere only in X,Y,W,H (pixels)."),
    ] = None,
    matte: Annotated[
        str | None,
        typer.Option(
            metavar="<cx,cy,r>",
            help="Matte (Lambertian) sphere CX,CY,R for light intensities (default: rig file)."
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(help="Output folder (default: DATA, so reconstruct picks the lights up)."),
    ] = None,
    focal_length: Annotated[
        float | None,
        typer.Option(
            help="Lens focal length in mm, for the perspective correction (default: with two "
            "or more chrome spheres, the intrinsics of a camera.json in DATA; its frames are "
            "read undistorted in any case)."
        ),
    ] = None,
    pixel_pitch: Annotated[
        float | None,
        typer.Option(
            help="Pixel pitch of the loaded image in micrometres "
            "(2x the sensor's for half-size RAW)."
        ),
    ] = None,
    safe_radius: Annotated[
        float,
        typer.Option(
            min=0.1, max=0.99, help="Reject highlights beyond this share of the sphere radius."
        ),
    ] = 0.9,
    pixel_size: Annotated[
        float | None,
        typer.Option(min=0.0, help="Millimetres per pixel: LED positions also reported in mm."),
    ] = None,
    object_outline: Annotated[
        str | None,
        typer.Option(
            "--object",
            metavar="<table|z>",
            help="Near lights: where the object's outline lies, 'table' (on the table the "
            "spheres rest on) or its height in pixels above the spheres' centres (default: rig "
            "file, else reconstruct finds it).",
        ),
    ] = None,
    led_intensities: Annotated[
        str | None,
        typer.Option(
            metavar="<equal|origin|file>",
            help="Near lights without a matte sphere: 'equal' (identical LEDs, the default), "
            "'origin' (equal irradiance at the scene origin) or a file of each LED's relative "
            "radiant intensity (one row per light).",
        ),
    ] = None,
    flat_field: Annotated[
        Path | None,
        typer.Option(
            "--flat-field",
            metavar="<folder>",
            help="Frames of a flat matte board under every light (same lights, same order, "
            "same camera): fits each LED's axis, cos^mu beam and output (light_axes.txt, "
            "light_anisotropy.txt, light_intensities.txt) and a per-light gain map "
            "(flat_field.npz); reconstruct --led-model chooses. Needs two chrome spheres.",
        ),
    ] = None,
    board: Annotated[
        str,
        typer.Option(
            metavar="<table|Z>",
            help="With --flat-field: the board's height, 'table' (on the table the chrome "
            "spheres rest on) or pixels above the spheres' centres' plane.",
        ),
    ] = "table",
    encoding: EncodingOption = Encoding.auto,
    outline_frame: Annotated[
        list[Path] | None,
        typer.Option(
            help="A frame with room light in which the sphere outline is visible (e.g. "
            "PSBox's ref.JPG): the outline is fitted on it. One per DATA folder, in order."
        ),
    ] = None,
    ambient_frame: Annotated[
        list[Path] | None,
        typer.Option(
            help="A frame with the rig's lights off (ambient light only), subtracted from "
            "every frame. One per DATA folder, in order (ambient.<ext> in a folder is used "
            "without this option)."
        ),
    ] = None,
) -> None:
    """Find the chrome sphere and its highlight in every frame; calibrate the lights.

    Writes light_directions.txt, light_intensities.txt, calibration.json and calibration.png;
    with two or more chrome spheres also light_positions.txt (scene frame, pixels).
    """
    spheres = [parse_numbers(t, "--sphere", "CX,CY,R", positive=("R",)) for t in sphere or []]
    sphere_c = spheres[0] if spheres else None
    matte_c = parse_numbers(matte, "--matte", "CX,CY,R", positive=("R",))
    roi_v = parse_numbers(roi, "--roi", "X,Y,W,H", positive=("W", "H"))
    positive(focal_length, "--focal-length")
    positive(pixel_pitch, "--pixel-pitch")
    if (focal_length is None) != (pixel_pitch is None):
        raise CalibrationError(
            "--focal-length and --pixel-pitch go together (perspective correction)"
        )
    focal_px = None if focal_length is None else focal_length / (pixel_pitch * 1e-3)  # type: ignore[operator]

    for option, files in (("--outline-frame", outline_frame), ("--ambient-frame", ambient_frame)):
        if files and len(files) != len(data):
            raise CalibrationError(
                f"{option} given {len(files)} time(s) for {len(data)} DATA folder(s): give one "
                "per folder, in order"
            )
    results, roots = [], []
    for k, folder in enumerate(data):
        frames = load_frames(folder, encoding.value)
        if ambient_frame:
            frames = _subtract_ambient(frames, ambient_frame[k], encoding.value)
        outline = None
        if outline_frame:
            outline = _side_frame(outline_frame[k], frames, encoding.value, "outline frame")
        result = _calibrate_folder(
            frames, spheres, sphere_c, matte_c, roi_v, safe_radius, focal_px, pixel_size, outline,
            *_near_models(frames, object_outline, led_intensities),
            outline_name=str(outline_frame[k]) if outline_frame else "outline frame",
        )
        result.metadata["encoding"] = frames_encoding(frames.root / frames.names[0], encoding.value)
        if frames.camera is not None:
            result.metadata["camera"] = camera_record(frames.camera, Path(frames.camera.source))
        results.append(result)
        roots.append(frames.root)
    result = combine_probes(results, [str(r) for r in roots])
    if flat_field is not None:
        result = _with_board(result, flat_field, board, encoding.value)
    frames_root = roots[0]
    n = len(result.light_directions)
    paths = write_calibration(result, out if out is not None else frames_root)
    c = result.circle
    residual = "n/a" if result.residual != result.residual else f"{result.residual:.3f} px"
    typer.echo(
        f"chrome sphere ({c.x:.2f}, {c.y:.2f}) r={c.radius:.2f} px [{result.circle_source}], "
        f"outline residual {residual}"
    )
    intensities = result.intensity_source
    typer.echo(f"{n} lights calibrated; intensities: {intensities}")
    if result.triangulation is not None:
        tri = result.triangulation
        typer.echo(
            f"LED positions from {len(result.circles)} chrome spheres: "
            f"{int((~tri.too_far).sum())} placed, mean ray miss {np.nanmean(tri.miss):.2f} px"
            if (~tri.too_far).any()
            else "LED positions: every light too far to place (directional)"
        )
    probes = result.metadata.get("probes")
    if probes is not None:
        worst = np.max(probes["disagreement_deg"], axis=0)
        typer.echo(
            f"one light set from {len(probes['labels'])} probes: probe vs probe "
            f"{probes['pairwise_deg']['mean']:.2f} deg mean, {probes['pairwise_deg']['max']:.2f} "
            f"max; per light, largest disagreement with the set (deg): "
            + " ".join(f"{v:.2f}" for v in worst)
        )
    for warning in result.warnings:
        typer.secho(f"warning: {warning}", fg=typer.colors.YELLOW, err=True)
    for path in paths.values():
        typer.echo(f"wrote {path}")


def _with_board(result, folder: Path, board: str, encoding: str):
    """The calibration with the LED model fitted on ``--flat-field``'s board frames."""
    height: str | float = board
    if board != "table":
        try:
            height = float(board)
        except ValueError:
            raise CalibrationError(f"--board {board}: give 'table' or a height in pixels") from None
        if not np.isfinite(height):
            raise CalibrationError(f"--board {board}: must be a finite number")
    frames = load_frames(folder, encoding)
    with naming_folder(frames.root):
        return with_led_model(result, frames.images, height, saturated=frames.saturated)


def _near_models(
    frames: Frames, object_outline: str | None, led_intensities: str | None
) -> tuple[str | float | None, str | np.ndarray]:
    """Where the object's outline lies and the LEDs' intensity model (options, else rig file)."""
    outline = object_outline if object_outline is not None else rig_object_outline(
        frames.manifest
    )
    if isinstance(outline, str) and outline != "table":
        try:
            outline = float(outline)
        except ValueError:
            raise CalibrationError(
                f"--object {outline}: give 'table' or a height in pixels"
            ) from None
        if not np.isfinite(outline):
            raise CalibrationError(f"--object {object_outline}: must be a finite number")
    model: str | np.ndarray = led_intensities or rig_led_intensities(frames.manifest)
    if isinstance(model, str) and model not in ("equal", "origin"):
        model = read_led_intensities(Path(model), frames.images.shape[0])
    return outline, model


def _calibrate_folder(
    frames: Frames, spheres, sphere_c, matte_c, roi_v, safe_radius, focal_px, pixel_size, outline,
    object_outline, led_intensities, outline_name,
):
    """One folder's calibration (the rig snapshot's spheres unless circles are given)."""
    _, rig_matte = rig_circles(frames.manifest)
    rig_chrome = rig_chrome_spheres(frames.manifest)
    hints = [] if sphere_c is not None or roi_v is not None else rig_chrome
    n, height, width = frames.images.shape[:3]
    principal_point = None
    if focal_px is None and frames.camera is not None and max(len(spheres), len(hints)) > 1:
        # camera.json with two or more chrome spheres (near lights): the LEDs are triangulated
        # through the calibrated perspective camera. One sphere (directional lights) keeps the
        # directional model's distant camera unless --focal-length asks for the correction.
        focal_px = frames.camera.focal_length
        principal_point = (frames.camera.cx, frames.camera.cy)
    circles = [("--sphere", c) for c in spheres] + [("--matte", matte_c)]
    for option, circle in circles:
        if circle is not None and not circle_in_image(circle, width, height):
            raise CalibrationError(
                f"{option} {circle[0]:g},{circle[1]:g},{circle[2]:g} is not inside the "
                f"{width}x{height} image of {frames.root}"
            )
    with (
        progress_bar(n * max(len(spheres), len(hints), 1), "highlights") as advance,
        naming_folder(frames.root, unless=outline_name if outline is not None else None),
    ):
        return run_calibration(
            frames.images,
            sphere=sphere_c,
            sphere_hint=hints[0] if hints else None,
            extra_spheres=spheres[1:],
            extra_sphere_hints=hints[1:],
            anisotropy=rig_anisotropy(frames.manifest),
            pixel_size=pixel_size,
            roi=None if roi_v is None else tuple(int(round(v)) for v in roi_v),
            matte_sphere=matte_c,
            matte_hint=None if matte_c is not None else rig_matte,
            saturated=frames.saturated,
            safe_radius=safe_radius,
            focal_length_px=focal_px,
            principal_point=principal_point,
            names=frames.names,
            progress=advance,
            outline=outline,
            led_intensities=led_intensities,
            object_outline=object_outline,
            outline_name=outline_name,
        )


def _side_frame(path: Path, frames: Frames, encoding: str, what: str) -> np.ndarray:
    """An extra frame (outline, ambient) of the same size as the light frames, linear."""
    image = read_image(path, encoding)
    if image.shape != frames.images.shape[1:3]:
        h, w = frames.images.shape[1:3]
        raise CalibrationError(
            f"{path}: {what} is {image.shape[1]}x{image.shape[0]}, the frames of {frames.root} "
            f"are {w}x{h}"
        )
    if frames.camera is not None:  # the light frames were undistorted: this one too
        return undistort_frame(frames.camera, image.data)[0]
    return image.data


def _subtract_ambient(frames: Frames, path: Path, encoding: str) -> Frames:
    ambient = _side_frame(path, frames, encoding, "ambient frame")
    if ambient.shape[-1] != frames.images.shape[-1]:
        ambient = ambient.mean(axis=-1, keepdims=True)
    images = frames.images - ambient[None]
    return Frames(images, frames.saturated, frames.names, frames.root, frames.manifest,
                  frames.camera)


def register(app: typer.Typer) -> None:
    """Add ``calibrate`` to the app."""
    app.command()(calibrate)
