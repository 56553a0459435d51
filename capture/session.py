"""Capture sessions: one dark frame, then K frames per light, never losing or mixing up a frame.

A run folder holds ``manifest.json`` and ``frames/``. The session guarantees, at every instant,
even if the process is killed:

* a frame file under its final name is complete: the camera writes it under a temporary name
  (``frames/.partial-<name>``), the session checks that it reads, fsyncs it, renames it and
  fsyncs the folder;
* ``manifest.json`` lists exactly the complete frames: it is rewritten after every frame to a
  temporary file that is fsynced and renamed over the old one (then the folder is fsynced).

A file under a final name that the manifest does not list (the process died between the rename
and the manifest update) and every temporary file are removed when the run is resumed; the
frame is shot again. Frames of the simulated camera depend only on the frame index, so a
resumed run is byte-identical to an uninterrupted one.

Order of one frame (``kind = "light"``): switch the light on and wait for the controller's
reply; wait ``settle_ms``; capture; check the file (RAW: :func:`~ps_lab.io.raw.load_raw`
reads it); switch the light off. A :class:`~ps_lab.errors.CameraError` (timeout, unreadable
file) is retried ``[camera] retries`` times — light off, light on again, capture again; a
controller error stops the run (the driver already retried what the protocol allows).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from ps_lab import __version__
from ps_lab.capture._rig_lens import lens_camera_file
from ps_lab.capture.connect import OpenRig, nominal_directions, open_rig
from ps_lab.capture.plan import CapturePlan, PlannedFrame, make_plan
from ps_lab.capture.rig import Rig, comparable_snapshot, snapshot_differences
from ps_lab.errors import CameraError, DatasetError, PsLabError, RigError
from ps_lab.io.camera import CAMERA_FILE
from ps_lab.io.codecs import imread
from ps_lab.io.files import PARTIAL_PREFIX, json_safe, publish_file, sha256, write_bytes_atomic
from ps_lab.io.light_files import light_table_bytes
from ps_lab.io.raw import is_raw_file, load_raw
from ps_lab.io.run import (
    FRAMES_DIR,
    MANIFEST_NAME,
    NOMINAL_DIRECTIONS,
    RUN_FORMAT,
    RUN_VERSION,
    read_manifest,
    write_manifest,
)

log = logging.getLogger(__name__)

_FRAME_NAME = re.compile(r"^\d{4,}-(dark|L\d+-r\d+)\.\w+$")

__all__ = [
    "CapturePlan",
    "CaptureResult",
    "CaptureSession",
    "PlannedFrame",
    "ProgressCallback",
    "make_plan",
]


class ProgressCallback(Protocol):
    """Called with ``(n, description=...)``: ``n`` frames done; ``description`` names the frame."""

    def __call__(self, n: int = 1, description: str | None = None) -> None: ...  # noqa: D102


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def _iso(epoch_s: float) -> str:
    return datetime.fromtimestamp(epoch_s, tz=UTC).isoformat(timespec="milliseconds")


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold Ctrl-C while the lights are being switched off; deliver it afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[Any] = []
    previous = signal.signal(signal.SIGINT, lambda *args: caught.append(args))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            raise KeyboardInterrupt


# --------------------------------------------------------------------------------------------
# Controller / camera calls (one place that knows the method names of the drivers)
# --------------------------------------------------------------------------------------------


def _lights_on(controller: Any, lights: tuple[int, ...]) -> None:
    controller.switch(lights[0] if len(lights) == 1 else lights)


def _lights_off(controller: Any) -> None:
    controller.all_off()


def _reboots_seen(controller: Any) -> int:
    # A driver that re-handshakes after a reboot restores the lit lights before STATE answers,
    # so only its count of reboots tells that the exposure may have run in the dark. Drivers
    # without the counter (see docs/capture.md) are checked by STATE alone.
    return int(getattr(controller, "reboots_seen", 0))


def _lit(controller: Any) -> frozenset[int]:
    return frozenset(controller.state().lit)


def _capture(camera: Any, path: Path, frame: PlannedFrame) -> Any:
    return camera.capture(path, frame_index=frame.index, label=frame.label)


class _LightLost(CameraError):
    """The controller no longer had the frame's lights lit after the exposure (watchdog, reset)."""


def _verify_frame(path: Path, file_type: str) -> None:
    """Raise :class:`CameraError` unless ``path`` is a readable image of its type."""
    if not path.is_file() or path.stat().st_size == 0:
        raise CameraError(f"the camera left no file at {path.name}")
    if is_raw_file(path):
        try:
            load_raw(path)
        except PsLabError as exc:
            raise CameraError(f"the frame does not read back: {exc}") from None
    else:
        try:
            decoded = imread(path)
        except OSError:
            decoded = None
        if decoded is None:
            raise CameraError(f"the frame {path.name} does not read back as an image")


# --------------------------------------------------------------------------------------------
# Session
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CaptureResult:
    """What a session did."""

    run_dir: Path
    frames_total: int
    frames_captured: int  # in this session
    frames_skipped: int  # already complete (resume)
    retries: int  # camera re-shoots in this session
    elapsed_s: float


class CaptureSession:
    """A capture into one run folder, new or resumed.

    Construction checks the folder and (for ``resume``) the manifest without touching the
    hardware; :meth:`run` opens the rig and shoots the remaining frames.

    Parameters
    ----------
    rig : Rig
        The validated rig (with command-line overrides applied).
    run_dir : Path
        The run folder: new, empty, or (with ``resume``) an existing run.
    lights : sequence of int, optional
        Lights to shoot (1-based). A resumed run keeps its plan: a different selection is refused.
    repeat : int, optional
        Frames per light (default 1; a resumed run keeps its own).
    resume : bool
        Continue the run described by ``run_dir/manifest.json``.
    prompt : callable, optional
        Shows the operator a message such as ``"press the shutter for light 3"`` (folder camera
        with ``prompt = true``).

    """

    def __init__(
        self,
        rig: Rig,
        run_dir: Path,
        *,
        lights: Sequence[int] | None = None,
        repeat: int | None = None,
        resume: bool = False,
        prompt: Callable[[str], Any] | None = None,
    ) -> None:
        self.rig = rig
        self.prompt = prompt
        self.run_dir = Path(run_dir)
        self.resume = resume
        self.manifest: dict[str, Any] = {}
        self.records: list[dict[str, Any]] = []
        self.retries = 0
        self.stopped_reason: str | None = None
        self.opened: OpenRig | None = None  # the rig of the last run(), closed by then
        if resume:
            self._prepare_resume(lights, repeat)
        else:
            self._prepare_new(lights, repeat)

    # -- preparation (no hardware) ----------------------------------------------------------

    def _prepare_new(self, lights: Sequence[int] | None, repeat: int | None) -> None:
        run = self.run_dir
        if run.exists():
            if not run.is_dir():
                raise DatasetError(f"output {run} exists and is not a folder")
            if (run / MANIFEST_NAME).exists():
                raise DatasetError(
                    f"{run} is already a capture run; "
                    "add --resume to continue it or choose another --out"
                )
            if any(run.iterdir()):
                raise DatasetError(
                    f"output folder {run} exists and is not a ps-lab run "
                    f"(not empty, no {MANIFEST_NAME})"
                )
        self.plan = make_plan(
            self.rig.n_lights, lights, 1 if repeat is None else repeat, self.rig.camera.file_type
        )
        self.manifest = self._new_manifest()

    def _prepare_resume(self, lights: Sequence[int] | None, repeat: int | None) -> None:
        run = self.run_dir
        if not run.is_dir():
            raise DatasetError(f"nothing to resume: {run} is not a folder")
        manifest = read_manifest(run)
        old_rig = manifest["rig"]
        new_rig = self.rig.snapshot()
        diffs = snapshot_differences(comparable_snapshot(old_rig), comparable_snapshot(new_rig))
        if diffs:
            raise RigError(
                f"cannot resume {run}: the rig changed since the run started "
                f"({', '.join(diffs[:4])}" + (", ..." if len(diffs) > 4 else "") + ")"
            )
        diffs = snapshot_differences(manifest["camera_settings"], self.rig.camera_settings())
        if diffs:
            raise RigError(f"cannot resume {run}: camera settings changed ({', '.join(diffs)})")
        plan_dict = manifest["plan"]
        try:
            old_lights = [int(i) for i in plan_dict["lights"]]
            old_repeat = int(plan_dict["repeat"])
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{run / MANIFEST_NAME}: malformed plan") from None
        if lights is not None and list(lights) != old_lights:
            raise RigError(
                f"cannot resume {run}: --lights differs from the run's plan ({_ranges(old_lights)})"
            )
        if repeat is not None and repeat != old_repeat:
            raise RigError(
                f"cannot resume {run}: --repeat {repeat} differs from the run's plan ({old_repeat})"
            )
        self.plan = make_plan(self.rig.n_lights, old_lights, old_repeat, self.rig.camera.file_type)
        frames = manifest["frames"]
        if not isinstance(frames, list) or len(frames) > len(self.plan.frames):
            raise DatasetError(f"{run / MANIFEST_NAME}: malformed frame list")
        for record, planned in zip(frames, self.plan.frames, strict=False):
            self._check_record(record, planned)
        self.manifest = manifest
        self.records = list(frames)

    def _check_record(self, record: Any, planned: PlannedFrame) -> None:
        run = self.run_dir
        if (
            not isinstance(record, dict)
            or record.get("index") != planned.index
            or record.get("file") != planned.file
            or record.get("kind") != planned.kind
            or list(record.get("lights", [])) != list(planned.lights)
        ):
            raise DatasetError(
                f"{run / MANIFEST_NAME}: frame {planned.index} does not match the plan"
            )
        path = run / planned.file
        if not path.is_file():
            raise DatasetError(
                f"cannot resume {run}: frame file {planned.file} listed in the manifest is missing"
            )
        if sha256(path) != record.get("sha256"):
            raise DatasetError(
                f"cannot resume {run}: frame file {planned.file} changed since it was captured"
            )

    def _new_manifest(self) -> dict[str, Any]:
        return {
            "format": RUN_FORMAT,
            "version": RUN_VERSION,
            "ps_lab_version": __version__,
            "created": _iso(time.time()),
            "rig": self.rig.snapshot(),
            "camera_settings": self.rig.camera_settings(),
            "plan": self.plan.as_dict(),
            "sessions": [],
            "frames": [],
        }

    # -- state --------------------------------------------------------------------------------

    @property
    def remaining(self) -> tuple[PlannedFrame, ...]:
        """Frames still to shoot, in order."""
        return self.plan.frames[len(self.records) :]

    @property
    def complete(self) -> bool:
        """Whether every planned frame is in the manifest."""
        return not self.remaining

    def lights_note(self) -> str:
        """``"lights off"``, or what to expect when switching off was not confirmed."""
        if self.opened is None or self.opened.lights_off_confirmed:
            return "lights off"
        watchdog = self.rig.controller.watchdog_ms
        if watchdog:
            return (
                "OFF not confirmed: the controller's watchdog switches the lights off "
                f"within {watchdog / 1000:g} s"
            )
        return "OFF not confirmed and the watchdog is disabled: check the lights"

    def status_line(self) -> str:
        """One line: how many frames are saved and how to go on."""
        done, total = len(self.records), len(self.plan.frames)
        line = f"{done} of {total} frames saved in {self.run_dir}"
        if done < total:
            line += "; continue with --resume"
        return line

    def describe_plan(self) -> list[str]:
        """Lines describing the plan (for ``--dry-run``)."""
        n = len(self.plan.frames)
        cam = self.rig.camera
        lines = [
            f"rig {self.rig.name}: controller {self.rig.controller.driver}"
            + (f" on {self.rig.controller.port}" if self.rig.controller.port else "")
            + f", {self.rig.n_lights} lights; camera {cam.driver}, "
            + f"exposure {cam.exposure_s:g} s, {cam.file_type}",
            f"plan: dark frame + lights {_ranges(self.plan.lights)} x {self.plan.repeat} "
            f"= {n} frames",
        ]
        if self.records:
            lines.append(
                f"resume: {len(self.records)} frames complete, {len(self.remaining)} to shoot"
            )
        frames = self.remaining
        for frame in frames[:3]:
            lines.append(f"  {frame.index:4d}  {frame.label:<20s} -> {frame.file}")
        if len(frames) > 4:
            lines.append(f"  ... {len(frames) - 4} more")
        if len(frames) > 3:
            frame = frames[-1]
            lines.append(f"  {frame.index:4d}  {frame.label:<20s} -> {frame.file}")
        return lines

    # -- running ----------------------------------------------------------------------------

    def check(self) -> None:
        """Open the rig (controller handshake, camera ready), switch everything off, close."""
        with open_rig(self.rig, prompt=self.prompt) as opened:
            _lights_off(opened.controller)
            ready = getattr(opened.camera, "check", None)
            if callable(ready):
                ready()

    def run(self, progress: ProgressCallback | None = None) -> CaptureResult:
        """Shoot the remaining frames.

        Parameters
        ----------
        progress : callable, optional
            Called as ``progress(0, description=...)`` before and ``progress(1)`` after each frame.

        Raises
        ------
        PsLabError
            The run stopped: the lights are off, the manifest lists the complete frames, and the
            message says which frame failed and how to continue.
        KeyboardInterrupt
            Ctrl-C: the same guarantees.

        """
        started = time.monotonic()
        skipped = len(self.records)
        captured = 0
        report = progress or (lambda n=1, description=None: None)
        if self.complete:
            return CaptureResult(self.run_dir, len(self.plan.frames), 0, skipped, 0, 0.0)
        # The rig is opened first: a wrong port or a dead controller writes nothing.
        try:
            opened = open_rig(self.rig, prompt=self.prompt)
        except PsLabError as exc:
            if not self.records:
                raise
            raise _reworded(exc, f"{exc}; {self.status_line()}") from None
        self.opened = opened
        frame: PlannedFrame | None = None
        try:
            self._prepare_folder(opened)
            if opened.write_truth is not None:  # a simulator's ground truth (simulation/)
                opened.write_truth(self.run_dir, self.plan.lights)
            self._write_nominal_directions(opened)
            # Within session(), SIGTERM unwinds like Ctrl-C, so the lights go off either way.
            with opened.controller.session():
                _lights_off(opened.controller)
                for frame in self.remaining:
                    report(0, description=_bar_label(frame, self.plan))
                    self._shoot(opened, frame)
                    captured += 1
                    report(1)
            frame = None
        except (PsLabError, OSError) as exc:
            where = f"frame {frame.index} ({frame.label})" if frame is not None else "setup"
            reason = str(exc) if isinstance(exc, PsLabError) else f"cannot write the run: {exc}"
            self.stopped_reason = f"{where}: {reason}"
            with _sigint_deferred():
                self._shutdown(opened)  # first, so that the message can say whether lights are off
            message = (
                f"capture stopped at {where}: {reason}; {self.lights_note()}; {self.status_line()}"
            )
            if isinstance(exc, PsLabError):
                raise _reworded(exc, message) from None
            raise DatasetError(message) from None
        finally:
            with _sigint_deferred():
                self._shutdown(opened)
        return CaptureResult(
            self.run_dir,
            len(self.plan.frames),
            captured,
            skipped,
            self.retries,
            time.monotonic() - started,
        )

    def _prepare_folder(self, opened: OpenRig) -> None:
        run = self.run_dir
        try:
            (run / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"cannot create {run / FRAMES_DIR}: {exc.strerror or exc}") from None
        listed = {Path(r["file"]).name for r in self.records}
        for path in sorted((run / FRAMES_DIR).iterdir()):
            if path.name in listed:
                continue
            if path.name.startswith(PARTIAL_PREFIX) or _FRAME_NAME.match(path.name):
                # A temporary file, or a frame renamed before its manifest update: shot again.
                log.info("removing incomplete frame file %s", path.name)
                path.unlink()
            else:
                log.warning("leaving unknown file %s in %s", path.name, run / FRAMES_DIR)
        stray = run / (PARTIAL_PREFIX + MANIFEST_NAME)
        if stray.exists():
            stray.unlink()
        self.manifest.setdefault("sessions", []).append(
            {
                "started": _iso(time.time()),
                "resumed": self.resume,
                "controller_port": getattr(opened.controller, "port_name", None),
                "camera": json_safe(getattr(opened.camera, "settings", {})),
            }
        )
        self.manifest["frames"] = self.records
        camera_file = lens_camera_file(self.rig.lens, self.rig.source)
        if camera_file is not None:  # the run carries its camera: calibrate and reconstruct
            try:  # undistort its frames with it, whatever becomes of the rig file
                write_bytes_atomic(run / CAMERA_FILE, camera_file.read_bytes())
            except OSError as exc:
                raise RigError(f"[lens] camera: cannot copy {camera_file} into {run}: "
                               f"{exc.strerror or exc}") from None
        write_manifest(run, self.manifest)

    def _write_nominal_directions(self, opened: OpenRig) -> None:
        """Write ``light_directions_nominal.txt`` (plan order) when the rig knows them."""
        nominal = nominal_directions(self.rig, opened.simulation)
        if nominal is not None:
            rows = [i - 1 for i in self.plan.lights]
            write_bytes_atomic(self.run_dir / NOMINAL_DIRECTIONS, light_table_bytes(nominal[rows]))

    def _shoot(self, opened: OpenRig, frame: PlannedFrame) -> None:
        controller, camera = opened.controller, opened.camera
        final = self.run_dir / frame.file
        temp = final.with_name(PARTIAL_PREFIX + final.name)
        settle_s = self.rig.controller.settle_ms / 1000.0
        attempts = 1 + self.rig.camera.retries
        for attempt in range(1, attempts + 1):
            temp.unlink(missing_ok=True)
            try:
                if frame.kind == "light":
                    _lights_on(controller, frame.lights)
                if settle_s:
                    time.sleep(settle_s)
                boots = _reboots_seen(controller)
                shot = _capture(camera, temp, frame)
                # Was the light still on when the exposure ended? A watchdog that fired during a
                # long exposure, or a board that reset, would otherwise leave a dark frame
                # under a light's name.
                lit = _lit(controller)
                if lit != frozenset(frame.lights):
                    shown = " ".join(map(str, sorted(lit))) or "none"
                    raise _LightLost(
                        f"after the exposure the controller reports lights {shown} lit"
                    )
                if _reboots_seen(controller) != boots:
                    raise _LightLost("the controller rebooted during the exposure")
                produced = Path(shot.path)
                if produced != temp:
                    os.replace(produced, temp)
                _verify_frame(temp, self.plan.file_type)
                if frame.kind == "light":
                    _lights_off(controller)
                break
            except (CameraError, DatasetError) as exc:
                if frame.kind == "light":
                    _lights_off(controller)  # a RigError here stops the run
                if attempt == attempts:
                    raise CameraError(
                        f"{exc} (after {attempts} attempt{'s' if attempts > 1 else ''})"
                    ) from None
                self.retries += 1
                log.warning("frame %d (%s): %s; shooting it again", frame.index, frame.label, exc)
        digest = sha256(temp)
        publish_file(temp, final)
        record = {
            "index": frame.index,
            "kind": frame.kind,
            "lights": list(frame.lights),
            "repeat": frame.repeat,
            "file": frame.file,
            "exposure_s": float(shot.exposure_s),
            "started": _iso(shot.started),
            "finished": _iso(shot.finished),
            "sha256": digest,
        }
        if attempt > 1:
            record["attempts"] = attempt
        self.records.append(record)
        self.manifest["frames"] = self.records
        write_manifest(self.run_dir, self.manifest)

    def _shutdown(self, opened: OpenRig) -> None:
        # Closing the controller switches the lights off (and, if it does not answer any more,
        # its watchdog will); closing never raises.
        opened.close()


def _reworded(exc: PsLabError, message: str) -> PsLabError:
    """Return an error of the same family as ``exc`` with ``message`` (exit code stays 2)."""
    for cls in type(exc).__mro__:
        if issubclass(cls, PsLabError):
            try:
                return cls(message)
            except TypeError:  # a subclass with its own constructor
                continue
    return PsLabError(message)


def _bar_label(frame: PlannedFrame, plan: CapturePlan) -> str:
    if frame.kind == "dark":
        return "dark frame"
    width = len(str(plan.n_lights))
    text = f"light {frame.lights[0]:>{width}d}/{plan.n_lights}"
    return text + (f" r{frame.repeat}" if plan.repeat > 1 else "")


def _ranges(values: Sequence[int]) -> str:
    """Format ``[1, 2, 3, 5]`` as ``1-3,5``."""
    parts: list[str] = []
    values = list(values)
    i = 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and values[j + 1] == values[j] + 1:
            j += 1
        parts.append(str(values[i]) if i == j else f"{values[i]}-{values[j]}")
        i = j + 1
    return ",".join(parts)
