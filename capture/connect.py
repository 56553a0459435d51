"""Rig -> drivers: a light controller and a camera opened from a :class:`~ps_lab.capture.rig.Rig`.

:func:`open_rig` turns a rig into live hardware. For a simulated controller it starts the simulated
firmware on an in-process pseudo-terminal and opens the pty's device path through the OS serial
layer, exactly as a real ``/dev/ttyACM0`` would be opened, and hands the firmware's light state to
the simulated camera so that a driver bug that leaves the wrong light on shows up in the images.
For ``driver = "firmware"`` the controller is the compiled Arduino sketch running in simavr
(:mod:`~ps_lab.capture.simulated.avr_firmware`), and the camera sees the lights whose pins the
emulated MCU drives. A gphoto2 camera on ``ptpip:127.0.0.1`` with a ``[scene]`` is the PTP/IP
camera simulator (:mod:`~ps_lab.capture.simulated.ptpip_camera`), started in its own process and
told the lit lights through a state file; the driver reaches it through the real libgphoto2.
A simulated rig's true scene and lights (:mod:`~ps_lab.capture.simulated.simulation`) come with
the opened rig, as the hook :attr:`OpenRig.write_truth` that writes them into a run.

This is the one production module that imports :mod:`ps_lab.capture.simulated` (an import-linter
contract), each simulator inside the function that starts it: a real rig loads neither the
simulators nor the renderer (another contract keeps :mod:`ps_lab.render` out of the rest of
capture).
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import shutil
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.capture import camera_devices, gphoto2_camera, light_controllers
from ps_lab.capture._rig_lens import simulated_lens
from ps_lab.capture.faults import Fault
from ps_lab.capture.light_controllers import LightState
from ps_lab.capture.rig import Rig, local_ptpip_port
from ps_lab.errors import CameraError, PsLabError, RigError

log = logging.getLogger("ps_lab.capture.rig")

__all__ = [
    "OpenRig",
    "nominal_directions",
    "open_rig",
    # The simulators are reached through this module only, each imported when it is used (a real
    # rig loads neither them nor the renderer). A simulated controller served on its own pty
    # (``ps-lab rig serve-sim``; its faults: ``capture.faults.parse_faults``):
    "serve_simulator",
    # The compiled sketch in simavr on its own pty (``ps-lab rig serve-firmware``).
    "serve_firmware",
    # The PTP/IP camera simulator (``ps-lab rig serve-camera``).
    "serve_camera",
    # A simulated camera's board frames (``ps-lab rig board-frames``).
    "render_board_frames",
]

# --------------------------------------------------------------------------------------------
# Simulators, imported when a rig selects one
# --------------------------------------------------------------------------------------------


def serve_simulator(**options: Any) -> None:
    """Serve the simulated controller on a pty until Ctrl-C (``ps-lab rig serve-sim``).

    ``options``: those of :func:`ps_lab.capture.simulated.pty_server.serve_simulator`.
    """
    from ps_lab.capture.simulated.pty_server import serve_simulator as serve

    serve(**options)


def serve_firmware(**options: Any) -> None:
    """Serve the compiled sketch in simavr on a pty until Ctrl-C (``ps-lab rig serve-firmware``).

    ``options``: those of :func:`ps_lab.capture.simulated.avr_firmware.serve_firmware`.
    """
    from ps_lab.capture.simulated.avr_firmware import serve_firmware as serve

    serve(**options)


def render_board_frames(
    rig: Rig, out: Path, views: int = 12, seed: int = 0
) -> tuple[list[Path], Any]:
    """A simulated rig's board frames, and the board (``ps-lab rig board-frames``).

    Returns the written frames and the :class:`~ps_lab.render.board.CharucoTarget` they show
    (:func:`ps_lab.capture.simulated.board_frames.write_rig_board_frames`).
    """
    from ps_lab.capture.simulated.board_frames import board_target, write_rig_board_frames

    written = write_rig_board_frames(rig, out, views, seed)
    return written, board_target(rig.scene.width if rig.scene is not None else 0)


def _simulation(rig: Rig, opened: OpenRig) -> Any:
    """The rig's true scene and lights; the session then writes them into the run."""
    from ps_lab.capture.simulated.simulation import build_simulation, write_truth

    simulation = build_simulation(rig)
    opened.simulation = simulation

    def truth(run_dir: Path, plan_lights: Sequence[int]) -> None:
        write_truth(simulation, run_dir, plan_lights)

    opened.write_truth = truth
    return simulation


def nominal_directions(rig: Rig, simulation: Any = None) -> np.ndarray | None:
    """Return the rig's nominal light directions (N, 3), if it has any.

    For a simulated rig without ``[controller] directions``, the nominal directions are the true
    ones turned by ``[scene.lights] nominal_error_deg`` (when > 0) in a seeded random direction:
    what a lab would know from measuring its rig with a ruler.
    """
    if rig.controller.directions is not None:
        return np.asarray(rig.controller.directions, dtype=np.float64)
    if simulation is None or rig.scene is None:
        return None
    true = simulation.light_directions
    err = math.radians(rig.scene.lights.nominal_error_deg)
    if err == 0.0:
        return None
    rng = np.random.default_rng([rig.scene.lights.seed, 2])
    axis = np.cross(true, rng.normal(size=true.shape))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    # Rodrigues rotation about an axis perpendicular to each direction.
    rotated = true * math.cos(err) + np.cross(axis, true) * math.sin(err)
    return rotated / np.linalg.norm(rotated, axis=1, keepdims=True)


# --------------------------------------------------------------------------------------------
# Opening the hardware
# --------------------------------------------------------------------------------------------


class OpenRig:
    """A rig with its controller and camera open; a context manager that closes both.

    Closing switches the lights off (the controller's own close does that) and stops the
    simulated controller's pty server, whatever happened before.
    """

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.controller: Any = None
        self.camera: Any = None
        #: A simulated rig's true scene and lights (``capture.simulated.simulation.Simulation``)
        #: and the hook that writes them into a run (``write_truth(run_dir, plan_lights)``);
        #: None on a real rig.
        self.simulation: Any = None
        self.write_truth: Callable[[Path, Sequence[int]], None] | None = None
        self.firmware: Any = None  # the simulated controller's firmware, when simulated
        self.board: Any = None  # the emulated MCU (EmulatedFirmware), for driver = "firmware"
        #: The PTP/IP camera simulator's frames (``ServedFrame``: handle, name, sha256, size),
        #: known once the rig is closed, for a gphoto2 camera on a simulated scene.
        self.served_frames: list[Any] | None = None
        #: ... and the InitiateCapture requests it received.
        self.served_captures: int | None = None
        #: False when closing could not confirm that the lights are off (the controller's
        #: watchdog switches them off then).
        self.lights_off_confirmed = True
        self._closers: list[Callable[[], None]] = []

    def __enter__(self) -> OpenRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the camera, the controller (lights off) and any simulator, in that order."""
        first_error: BaseException | None = None
        while self._closers:
            closer = self._closers.pop()
            try:
                closer()
            except Exception as exc:  # keep closing the rest; report the first failure
                log.info("while closing the rig: %s", exc)
                if self.controller is not None and closer == self.controller.close:
                    self.lights_off_confirmed = False
                first_error = first_error or exc
        if first_error is not None and not isinstance(first_error, PsLabError):
            log.debug("close error", exc_info=first_error)


def open_rig(
    rig: Rig, *, open_camera: bool = True, prompt: Callable[[str], Any] | None = None
) -> OpenRig:
    """Open the controller (handshake) and the camera of ``rig``.

    ``prompt`` tells the operator to press the shutter (folder camera with ``prompt = true``).

    Returns
    -------
    OpenRig
        Use it as a context manager; it closes everything (lights off) on exit.

    Raises
    ------
    RigError, CameraError
        With a one-line reason (port missing, busy, permission denied, no handshake, ...).

    """
    opened = OpenRig(rig)
    try:
        light_state = _open_controller(rig, opened)
        if open_camera:
            _open_camera(rig, opened, light_state, prompt)
    except BaseException:
        opened.close()
        raise
    return opened


def _open_controller(rig: Rig, opened: OpenRig) -> Callable[[], Any] | None:
    cfg = rig.controller
    light_state: Callable[[], Any] | None = None
    state_file = _camera_state_file(rig, opened)
    if cfg.driver == "simulated":
        from ps_lab.capture.simulated import firmware as sim_lights
        from ps_lab.capture.simulated.pty_server import PtyServer, write_state_file

        firmware = _make_firmware(sim_lights, rig)
        if state_file is not None:  # for the PTP/IP camera simulator in its own process
            firmware.add_listener(lambda state: write_state_file(state_file, state))
        server = PtyServer(firmware).start()
        opened._closers.append(server.stop)
        assert server.path is not None
        port = server.path
        light_state = firmware.state
        opened.firmware = firmware
        log.info("simulated controller on %s", port)
    elif cfg.driver == "firmware":
        # The compiled sketch in simavr: the camera sees the lights whose pins are driven.
        from ps_lab.capture.simulated.avr_firmware import EmulatedFirmware

        board = EmulatedFirmware(cfg.elf, pins=cfg.pins, state_file=state_file).start()
        opened._closers.append(board.stop)
        assert board.path is not None
        port = board.path
        light_state = board.light_state
        opened.board = board
    else:
        port = cfg.port
        assert port is not None
        _check_port(port)
    controller = _make_controller(light_controllers, port, rig)
    opened.controller = controller
    opened._closers.append(controller.close)
    return light_state


def _make_firmware(sim_lights: Any, rig: Rig) -> Any:
    # A delayed reply arrives well after the driver has given up on it.
    return sim_lights.SimulatedFirmware(
        rig.n_lights,
        faults=rig.faults.controller,
        seed=rig.faults.seed,
        delay_s=max(0.2, 3.0 * rig.controller.timeout_s),
    )


def _check_port(port: str) -> None:
    """Turn the usual reasons a device port cannot be opened into one clear line."""
    if "://" in port:
        return
    path = Path(port)
    if not path.exists():
        raise RigError(f"serial port {port} does not exist (is the controller plugged in?)")


def _make_controller(lights: Any, port: str, rig: Rig) -> Any:
    cfg = rig.controller
    try:
        return lights.SerialLightController(
            port,
            cfg.lights,
            level=cfg.level,
            watchdog_ms=cfg.watchdog_ms,
            reply_timeout=cfg.timeout_s,
            baudrate=cfg.baudrate,
        )
    except PermissionError:
        raise RigError(_PERMISSION.format(port=port)) from None
    except OSError as exc:
        raise RigError(f"cannot open serial port {port}: {exc}") from None
    except RigError as exc:
        # Name the two everyday causes in the lab's words rather than in errno's.
        text = str(exc)
        if "exclusively lock" in text or "Errno 11" in text or "Device or resource busy" in text:
            raise RigError(
                f"serial port {port} is busy: another program has it open (close it and retry)"
            ) from None
        if "Errno 13" in text or "Permission denied" in text:
            raise RigError(_PERMISSION.format(port=port)) from None
        raise


_PERMISSION = (
    "permission denied opening serial port {port} (on Linux: add yourself to the 'dialout' group)"
)


def _open_camera(
    rig: Rig,
    opened: OpenRig,
    light_state: Callable[[], Any] | None,
    prompt: Callable[[str], Any] | None,
) -> None:
    cfg = rig.camera
    if cfg.driver == "simulated":
        if light_state is None:
            from ps_lab.capture.simulated.pty_server import state_file_reader

            assert cfg.light_state_file is not None
            light_state = state_file_reader(Path(cfg.light_state_file))
        camera: Any = _simulated_camera(
            rig,
            _simulation(rig, opened),
            light_state,
            timeout_s=cfg.timeout_s,
            faults=[{"kind": f.kind, "at": f.at} for f in rig.faults.camera],
        )
    elif cfg.driver == "folder":
        assert cfg.folder is not None
        camera = camera_devices.FolderCamera(
            Path(cfg.folder),
            timeout_s=cfg.timeout_s,
            pattern=cfg.pattern,
            prompt=prompt if cfg.prompt else None,
            exposure_s=cfg.exposure_s,
        )
    elif cfg.driver == "gphoto2":
        port = cfg.port
        if rig.scene is not None:  # the PTP/IP camera simulator, in its own process
            port = _start_camera_process(rig, opened)
            _simulation(rig, opened)  # the run's ground truth
        camera = gphoto2_camera.Gphoto2Camera(
            port,
            settings=dict(cfg.settings),
            timeout_s=cfg.timeout_s,
            exposure_s=cfg.exposure_s,
            iso=cfg.iso,
            aperture=cfg.aperture,
        )
    else:  # pragma: no cover - parse_rig rejects other drivers
        raise CameraError(f"unknown camera driver {cfg.driver!r}")
    opened.camera = camera
    opened._closers.append(camera.close)


# --------------------------------------------------------------------------------------------
# The PTP/IP camera simulator (a gphoto2 camera on a simulated scene)
# --------------------------------------------------------------------------------------------


def _camera_state_file(rig: Rig, opened: OpenRig) -> Path | None:
    """Where the controller publishes its lights for the PTP/IP camera simulator (or None)."""
    if rig.camera.driver != "gphoto2" or rig.scene is None:
        return None
    if rig.controller.driver == "serial":
        assert rig.camera.light_state_file is not None  # parse_rig requires it
        return Path(rig.camera.light_state_file)
    folder = Path(tempfile.mkdtemp(prefix="ps-lab-rig-"))
    opened._closers.append(lambda: shutil.rmtree(folder, ignore_errors=True))
    opened._state_file = folder / "lights.json"  # type: ignore[attr-defined]
    return opened._state_file  # type: ignore[attr-defined]


def _simulated_camera(rig: Rig, simulation: Any, light_state: Any, **extra: Any) -> Any:
    """The rig's scene seen by its [camera] sensor (black and white level, gain, noise, seed)."""
    from ps_lab.capture.simulated.simulated_camera import SimulatedCamera

    cfg = rig.camera
    return SimulatedCamera(
        simulation.scene,
        simulation.light_directions,
        simulation.light_intensities,
        light_state,
        exposure_s=cfg.exposure_s,
        **cfg.sensor(),
        point_lights=simulation.point_lights,
        lens=simulated_lens(rig.lens, rig.scene.width, rig.scene.height) if rig.scene else None,
        **extra,
    )


def serve_camera(
    rig: Rig,
    *,
    port: int | None = None,
    state_file: Path | str | None = None,
    lit: Iterable[int] = (),
    level: int = 255,
    faults: Iterable[Fault] | None = None,
    keep_dir: Path | str | None = None,
    slow_s: float = 2.0,
    on_ready: Callable[[Any], None] | None = None,
) -> None:
    """Serve the rig's scene as a PTP/IP camera until Ctrl-C or SIGTERM (``rig serve-camera``).

    Each capture renders the scene under the lights in ``state_file`` (written by the simulated
    controller, ``ps-lab rig serve-sim --state-file``) or, without one, under lights ``lit`` at
    ``level``, with the rig's [camera] sensor (black and white level, gain, noise, seed).
    ``faults`` default to the rig's ``[faults] camera``. ``on_ready(server)`` is called once
    the port listens; ``port`` defaults to PTP/IP's 15740.
    """
    from ps_lab.capture.simulated.ptpip_camera import DEFAULT_PORT, PtpIpCamera, dng_shooter
    from ps_lab.capture.simulated.pty_server import serve_until_interrupted, state_file_reader
    from ps_lab.capture.simulated.simulation import build_simulation

    if rig.scene is None:
        raise RigError(f"rig {rig.name!r} has no [scene] for the camera to see")
    if state_file is not None:
        light_state = state_file_reader(Path(state_file))
    else:
        fixed = LightState(frozenset(int(i) for i in lit), int(level))

        def light_state() -> LightState:
            return fixed

    cfg = rig.camera
    camera = _simulated_camera(rig, build_simulation(rig), light_state)
    server = PtpIpCamera(
        dng_shooter(camera),
        port=DEFAULT_PORT if port is None else port,
        faults=rig.faults.camera if faults is None else faults,
        exposure_s=cfg.exposure_s,
        iso=cfg.iso or 100,
        f_number=cfg.aperture or 8.0,
        slow_s=slow_s,
        keep_dir=keep_dir,
        events_on_default_port=True,
    )
    serve_until_interrupted(server, on_ready, "PTP/IP camera")


def _camera_child(rig: Rig, state_file: str, port: int, pipe: Any) -> None:
    """In a spawned process: serve the camera, send its port, and its frames when stopped."""
    served: list[Any] = []  # the PtpIpCamera

    def ready(server: Any) -> None:
        served.append(server)
        pipe.send(server.port)

    try:
        serve_camera(rig, port=port, state_file=state_file, on_ready=ready)
    except PsLabError as exc:
        pipe.send(str(exc))
        return
    pipe.send((list(served[0].frames), served[0].captures) if served else ([], 0))


def _start_camera_process(rig: Rig, opened: OpenRig) -> str:
    """Start the PTP/IP camera simulator in its own process; return its gphoto2 port.

    Its own process, as a real camera is its own device: python-gphoto2 holds the GIL during
    some libgphoto2 calls (``get_summary``), which would stall a simulator in the same process.
    """
    from ps_lab.capture.simulated.ptpip_camera import PtpIpCamera

    port = local_ptpip_port(rig.camera.port)
    assert port is not None  # parse_rig requires a local ptpip port with a [scene]
    state_file = getattr(opened, "_state_file", None) or rig.camera.light_state_file
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(
        target=_camera_child,
        args=(rig, str(state_file), port, sender),
        name="ps-lab-ptpip-camera",
        daemon=True,
    )
    process.start()
    sender.close()

    def stop() -> None:
        if process.is_alive():
            process.terminate()  # SIGTERM: the simulator stops cleanly and reports its frames
        if receiver.poll(10.0):
            try:
                opened.served_frames, opened.served_captures = receiver.recv()
            except EOFError:
                pass
        process.join(10.0)
        if process.is_alive():
            process.kill()
            process.join()

    opened._closers.append(stop)
    if not receiver.poll(120.0):
        raise CameraError("the PTP/IP camera simulator did not start within 120 s")
    try:
        message = receiver.recv()
    except EOFError:
        raise CameraError("the PTP/IP camera simulator exited while starting") from None
    if isinstance(message, str):
        raise CameraError(f"PTP/IP camera simulator: {message}")
    log.info("PTP/IP camera simulator (pid %d) on 127.0.0.1:%d", process.pid, message)
    return PtpIpCamera.address_of("127.0.0.1", int(message))
