"""`ps-lab rig`: a simulated controller or the emulated firmware on a pty; check a controller."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import (
    EXIT_INTERRUPTED,
    command_group,
    fail,
    interrupted_line,
    lab_command,
    progress_bar,
)
from ps_lab.capture.connect import (
    render_board_frames,
    serve_camera,
    serve_firmware,
    serve_simulator,
)
from ps_lab.capture.faults import parse_camera_faults, parse_faults
from ps_lab.capture.light_controllers import SerialLightController, walk_lights
from ps_lab.capture.rig import load_rig, parse_light_selection
from ps_lab.errors import PsLabError, RigError

rig_app = command_group(
    "Light-controller tools: a simulated controller or the compiled sketch in simavr on a "
    "pseudo-terminal, and a rig check."
)


@rig_app.command("serve-sim")
@lab_command
def serve_sim(
    lights: Annotated[int, typer.Option(min=1, max=255, help="Number of simulated lights.")] = 24,
    state_file: Annotated[
        Path | None,
        typer.Option(
            help="Publish the lit lights here as JSON on every change (for a simulated camera)."
        ),
    ] = None,
    fault: Annotated[
        list[str] | None,
        typer.Option(
            metavar="<kind@n>",
            help="Inject a fault: KIND@N at the N-th command, or KIND@pP with probability P "
            "per command; "
            "KIND is drop, garble, delay, reboot or silence. Repeatable."
        ),
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, help="Seed of probabilistic faults and garbling.")
    ] = 0,
    delay: Annotated[
        float,
        typer.Option(min=0.0, max=3600.0, help="Seconds a 'delay' fault holds a reply back."),
    ] = 1.0,
) -> None:
    """Print the device path of a simulated controller (protocol v1) and serve until Ctrl-C."""
    faults = parse_faults(",".join(fault or []))

    def announce(server) -> None:
        _ready(
            server.path,
            f"simulated light controller: {lights} lights on {server.path}"
            + (f", faults {', '.join(map(str, faults))}" if faults else "")
            + (f", state in {state_file}" if state_file else ""),
        )

    serve_simulator(
        lights=lights,
        faults=faults,
        seed=seed,
        delay_s=delay,
        state_file=state_file,
        on_ready=announce,
    )


@rig_app.command("serve-firmware")
@lab_command
def serve_firmware_command(
    elf: Annotated[
        Path | None,
        typer.Option(help="The sketch's ELF (default: build rigs/firmware/ps_lab_lights)."),
    ] = None,
    state_file: Annotated[
        Path | None,
        typer.Option(help="Publish the lights whose pins are driven here as JSON on every change."),
    ] = None,
    pins: Annotated[
        str | None,
        typer.Option(
            metavar="<list>",
            help="Wiring: Arduino pin of light 1,2,... (default: the sketch's table).",
        ),
    ] = None,
) -> None:
    """Print the device path of the compiled sketch running in simavr and serve until Ctrl-C."""

    def announce(board) -> None:
        _ready(
            board.path,
            f"emulated firmware {board.elf}: {board.lights} lights on {board.path}"
            + (f", state in {state_file}" if state_file else ""),
        )

    serve_firmware(elf=elf, state_file=state_file, pins=pins, on_ready=announce)


@rig_app.command("serve-camera")
@lab_command
def serve_camera_command(
    rig: Annotated[
        Path,
        typer.Option(help="Rig file with the [scene] and [camera] sensor to simulate."),
    ] = Path("rigs/simulated-ptpip.toml"),
    port: Annotated[
        int, typer.Option(min=0, max=65535, help="TCP port (0: any free one; PTP/IP's is 15740).")
    ] = 15740,
    state_file: Annotated[
        Path | None,
        typer.Option(help="Render the lights this file says are lit (ps-lab rig serve-sim's)."),
    ] = None,
    lit: Annotated[
        str,
        typer.Option(
            metavar="<list>", help="Without --state-file: the lights lit, e.g. 1,3-5 (none: dark)."
        ),
    ] = "",
    level: Annotated[int, typer.Option(min=0, max=255, help="PWM level of --lit lights.")] = 255,
    fault: Annotated[
        list[str] | None,
        typer.Option(
            help="Inject a fault at the N-th capture: KIND@N, KIND is busy, timeout, disconnect "
            "or slow. Repeatable."
        ),
    ] = None,
    slow: Annotated[
        float, typer.Option(min=0.0, max=600.0, help="Seconds a 'slow' download takes.")
    ] = 2.0,
    keep: Annotated[
        Path | None, typer.Option(help="Also write every frame shot to this folder.")
    ] = None,
) -> None:
    """Print the gphoto2 port of a simulated PTP/IP camera and serve until Ctrl-C."""
    loaded = load_rig(rig)
    faults = parse_camera_faults(",".join(fault or [])) if fault else None
    try:
        lights = parse_light_selection(lit, loaded.n_lights) if lit.strip() else ()
    except RigError as exc:
        raise RigError(str(exc).replace("--lights", "--lit", 1)) from None

    def announce(server) -> None:
        _ready(
            server.address,
            f"simulated PTP/IP camera ({loaded.name}) on 127.0.0.1:{server.port}"
            + (f", lights from {state_file}" if state_file else f", lights lit: {lit or 'none'}")
            + (f", faults {', '.join(map(str, faults))}" if faults else ""),
        )

    serve_camera(
        loaded,
        port=port,
        state_file=state_file,
        lit=lights,
        level=level,
        faults=faults,
        keep_dir=keep,
        slow_s=slow,
        on_ready=announce,
    )


@rig_app.command("check")
@lab_command
def check(
    port: Annotated[
        str,
        typer.Option(
            metavar="<port>",
            help="Serial port or URL: /dev/ttyACM0, /dev/pts/N, socket://host:port, pslabsim://..."
        ),
    ],
    lights: Annotated[int, typer.Option(min=1, help="Number of lights the rig has.")],
    dwell: Annotated[
        float,
        typer.Option(min=0.0, max=3600.0, help="Seconds each light stays on, to watch the rig."),
    ] = 0.0,
    timeout: Annotated[
        float, typer.Option(min=0.01, max=60.0, help="Seconds to wait for each reply.")
    ] = 0.5,
) -> None:
    """Handshake with a light controller, light each light alone, check what it reports."""
    controller = SerialLightController(port, lights, reply_timeout=timeout)
    try:
        with controller, progress_bar(lights, "lights") as advance:
            walk_lights(controller, dwell_s=dwell, progress=advance)
    except PsLabError as exc:
        message = str(exc) if port in str(exc) else f"{port}: {exc}"
        raise RigError(f"{message}; {controller.lit_note()}") from None
    except KeyboardInterrupt as exc:
        raise fail(f"{interrupted_line(exc)}; {controller.lit_note()}", EXIT_INTERRUPTED) from None
    typer.echo(
        f"{port}: protocol v1 controller, {lights} lights switched one by one and "
        "reported correctly"
    )


@rig_app.command("board-frames")
@lab_command
def board_frames(
    rig: Annotated[Path, typer.Option("--rig", help="A rig file with a simulated camera.")],
    out: Annotated[Path, typer.Option("--out", help="Folder for board_001.png, ...")],
    views: Annotated[int, typer.Option(min=3, max=100, help="Board poses to render.")] = 12,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the poses and the noise.")] = 0,
) -> None:
    """Render a ChArUco board at seeded poses through a simulated rig's lens ([lens]).

    The frames a real rig's camera would take of a printed board, for `ps-lab calibrate-camera`.
    """
    config = load_rig(rig)
    written, target = render_board_frames(config, out, views, seed)
    typer.echo(f"wrote {len(written)} board frames to {out}")
    typer.echo(
        f"next: ps-lab calibrate-camera {out}/board_*.png --board charuco:{target.cols}x"
        f"{target.rows}:{target.square:g}:{target.marker:g}:{target.dictionary} --out {out}"
    )


def _ready(address: str, serving: str) -> None:
    """A server is ready: its address alone on stdout (for scripts), what it serves on stderr."""
    typer.echo(address)
    typer.echo(f"{serving}; Ctrl-C stops", err=True)


def register(app: typer.Typer) -> None:
    """Add ``ps-lab rig`` to app."""
    app.add_typer(rig_app, name="rig")
