"""`ps-lab capture`: shoot a dark frame and one frame per light on a rig into a run folder."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import EXIT_INTERRUPTED, fail, lab_command, progress_bar
from ps_lab.capture._rig_lens import with_lens_camera
from ps_lab.capture.rig import apply_overrides, load_rig, parse_light_selection
from ps_lab.capture.session import CaptureSession


@lab_command
def capture(
    rig: Annotated[Path, typer.Option("--rig", help="Rig file (TOML), e.g. rigs/simulated.toml.")],
    out: Annotated[
        Path, typer.Option("--out", help="Run folder to create (or to continue with --resume).")
    ],
    lights: Annotated[
        str | None,
        typer.Option(
            "--lights",
            metavar="<list>",
            help="Lights to shoot, e.g. 1-24 or 1,3,5-9 (default: all).",
        ),
    ] = None,
    repeat: Annotated[
        int | None,
        typer.Option("--repeat", min=1, help="Frames per light, averaged when loaded (default 1)."),
    ] = None,
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue the run in --out from its manifest.")
    ] = False,
    dry_run: Annotated[
        bool,
        typer.Option(
            "--dry-run", help="Check the rig (handshake, camera ready) and print the plan."
        ),
    ] = False,
    port: Annotated[
        str | None,
        typer.Option(
            "--port",
            metavar="<port>",
            help="Serial port of the light controller (overrides the rig file).",
        ),
    ] = None,
    exposure: Annotated[
        float | None,
        typer.Option("--exposure", help="Exposure time in seconds (overrides the rig file)."),
    ] = None,
    camera: Annotated[
        Path | None,
        typer.Option(
            "--camera",
            help="camera.json of `ps-lab calibrate-camera`, copied into the run (overrides the "
            "rig file's [lens] camera); calibrate and reconstruct then undistort the frames.",
            show_default=False,
        ),
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Capture a photometric-stereo run: dark frame, then each light; resumable and crash-safe."""
    rig_config = apply_overrides(load_rig(rig), port=port, exposure_s=exposure)
    if camera is not None:
        rig_config = with_lens_camera(rig_config, camera)
    selection = parse_light_selection(lights, rig_config.n_lights) if lights is not None else None
    session = CaptureSession(
        rig_config,
        out,
        lights=selection,
        repeat=repeat,
        resume=resume,
        prompt=lambda message: typer.secho(f">>> {message}", fg=typer.colors.YELLOW, err=True),
    )
    if dry_run:
        for line in session.describe_plan():
            typer.echo(line)
        session.check()
        typer.echo("rig ready: controller answered, camera ready, lights off")
        return
    if session.complete:
        typer.echo(f"nothing to do: {session.status_line()}")
        return
    try:
        with progress_bar(len(session.remaining), "capture", enabled=not quiet) as advance:
            result = session.run(progress=advance)
    except KeyboardInterrupt:
        message = f"interrupted; {session.lights_note()}; {session.status_line()}"
        raise fail(message, EXIT_INTERRUPTED) from None
    retried = f", {result.retries} re-shot" if result.retries else ""
    typer.echo(
        f"captured {result.frames_captured} frames{retried} in {result.elapsed_s:.1f} s; "
        f"{session.status_line()}"
    )


def register(app: typer.Typer) -> None:
    """Add ``capture`` to ``app``."""
    app.command("capture")(capture)
