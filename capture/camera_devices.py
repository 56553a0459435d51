"""Cameras behind one base class, and the watched-folder camera.

The simulated camera (renders, writes DNG) is :mod:`ps_lab.capture.simulated.simulated_camera`.

Every camera is used the same way::

    with camera:
        frame = camera.capture(run / "frames" / "0001-L01-r0.dng", frame_index=1)

:meth:`CameraDevice.capture` is a template method: it validates the target, logs, times the shot,
calls the driver's ``_do_capture`` hook and checks that a non-empty file arrived. Drivers raise
:class:`~ps_lab.errors.CameraError` with a one-line reason on any failure or timeout.

The gphoto2 driver lives in :mod:`ps_lab.capture.gphoto2_camera` so that this module never
needs python-gphoto2.
"""

from __future__ import annotations

import fnmatch
import logging
import os
import shutil
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

from ps_lab.capture.faults import CAMERA_FAULT_KINDS as FAULT_KINDS
from ps_lab.errors import CameraError, PsLabError
from ps_lab.io.raw import RAW_SUFFIXES, read_exposure

__all__ = [
    "FAULT_KINDS",
    "CameraDevice",
    "CapturedFrame",
    "FolderCamera",
]

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class CapturedFrame:
    """One frame that arrived on disk.

    Attributes
    ----------
    path : Path
        The frame file.
    exposure_s : float
        Exposure time in seconds (as set, or as read from the file).
    started, finished : float
        Epoch seconds around the capture (trigger to file on disk).

    """

    path: Path
    exposure_s: float
    started: float
    finished: float


class CameraDevice(ABC):
    """Abstract camera: :meth:`capture` validates and times, ``_do_capture`` shoots.

    Parameters
    ----------
    timeout_s : float
        How long a capture may take before :class:`CameraError`.

    """

    #: Short driver name used in log lines and in :attr:`settings`.
    driver = "camera"

    def __init__(self, *, timeout_s: float = 30.0) -> None:
        if not timeout_s > 0:
            raise CameraError(f"camera timeout must be positive, got {timeout_s}")
        self.timeout_s = float(timeout_s)
        self.captures = 0  # capture attempts so far (failed ones included)
        self._closed = False

    # -- public API -----------------------------------------------------------------------
    def capture(
        self,
        path: str | os.PathLike[str],
        *,
        frame_index: int | None = None,
        label: str | None = None,
    ) -> CapturedFrame:
        """Shoot one frame into ``path``.

        Parameters
        ----------
        path : path-like
            Target file; its folder must exist. An existing file is replaced.
        frame_index : int, optional
            Index of the frame in the capture plan (a simulated camera seeds its noise with
            it, so a re-shot frame is identical). Defaults to the number of earlier captures.
        label : str, optional
            What the frame is, for log lines and operator prompts (e.g. ``"light 3"``).

        Returns
        -------
        CapturedFrame

        Raises
        ------
        CameraError
            When the camera is closed, the target folder is missing, the capture fails or times
            out, or no non-empty file arrived.

        """
        if self._closed:
            raise CameraError(f"{self.driver} camera is closed")
        path = Path(path)
        if not path.parent.is_dir():
            raise CameraError(f"cannot capture to {path}: folder {path.parent} does not exist")
        if path.is_dir():
            raise CameraError(f"cannot capture to {path}: it is a folder")
        index = self.captures if frame_index is None else int(frame_index)
        if index < 0:
            raise CameraError(f"frame index must be >= 0, got {index}")
        self.captures += 1
        label = label or f"frame {index}"
        log.info("%s camera: capturing %s -> %s", self.driver, label, path)
        started = time.time()
        try:
            exposure = self._do_capture(path, index, label)
        except PsLabError:
            raise
        except OSError as exc:
            raise CameraError(f"capture of {label} to {path} failed: {exc}") from exc
        finished = time.time()
        if not path.is_file():
            raise CameraError(f"{self.driver} camera produced no file at {path}")
        if path.stat().st_size == 0:
            raise CameraError(f"{self.driver} camera produced an empty file at {path}")
        if exposure is None:
            exposure = self._fallback_exposure(path)
        log.debug("%s camera: %s done in %.3f s", self.driver, label, finished - started)
        return CapturedFrame(
            path=path, exposure_s=float(exposure), started=started, finished=finished
        )

    @property
    def settings(self) -> dict[str, Any]:
        """JSON-serialisable description of the settings that shape the frames."""
        return {"driver": self.driver, "timeout_s": self.timeout_s}

    def close(self) -> None:
        """Release the camera; further captures raise :class:`CameraError`. Idempotent."""
        if not self._closed:
            self._closed = True
            self._do_close()

    def __enter__(self) -> CameraDevice:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- driver hooks ---------------------------------------------------------------------
    @abstractmethod
    def _do_capture(self, path: Path, frame_index: int, label: str) -> float | None:
        """Write the frame to ``path``; return its exposure in seconds if the driver knows it."""

    def _do_close(self) -> None:  # noqa: B027 - optional hook, most drivers hold nothing
        """Release driver resources."""

    def _fallback_exposure(self, path: Path) -> float:
        exposure = read_exposure(path) if path.suffix.lower() in RAW_SUFFIXES else None
        if exposure is None:
            log.warning(
                "%s camera: exposure of %s unknown; assuming 1 s (frames are then not rescaled)",
                self.driver,
                path.name,
            )
            return 1.0
        return exposure


# ------------------------------------------------------------------------------------------
# Folder camera
# ------------------------------------------------------------------------------------------


class FolderCamera(CameraDevice):
    """A camera seen through a folder: tethering software or a card reader drops files there.

    Each capture (optionally) prompts the operator, then waits for the next new file in
    ``folder`` whose name matches ``pattern`` and whose size is non-zero and unchanged over
    two consecutive polls, and moves (or copies) it to the target path. Files present when the
    camera is created, hidden files (leading ``.``) and files already taken are ignored.

    Parameters
    ----------
    folder : path-like
        The watched folder; must exist.
    timeout_s : float
        How long to wait for a new file.
    pattern : str or sequence of str
        Glob pattern(s) on the file name (case-insensitive), e.g. ``"*.CR2"``.
    prompt : callable, optional
        Called with a message such as ``"press the shutter for light 3"`` before waiting.
    poll_s : float
        Polling interval.
    copy : bool
        Copy instead of move (leaves the original in the watched folder).
    exposure_s : float, optional
        Nominal exposure; used when the file does not state one.

    """

    driver = "folder"

    def __init__(
        self,
        folder: str | os.PathLike[str],
        *,
        timeout_s: float = 120.0,
        pattern: str | Sequence[str] = "*",
        prompt: Callable[[str], Any] | None = None,
        poll_s: float = 0.2,
        copy: bool = False,
        exposure_s: float | None = None,
    ) -> None:
        super().__init__(timeout_s=timeout_s)
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise CameraError(f"watched folder {self.folder} does not exist")
        self.patterns = (pattern,) if isinstance(pattern, str) else tuple(pattern)
        self.prompt = prompt
        self.poll_s = float(poll_s)
        self.copy = bool(copy)
        self.exposure_s = exposure_s
        self._seen: set[str] = set(self._candidates())

    @property
    def settings(self) -> dict[str, Any]:  # noqa: D102 - documented on the base class
        return {
            **super().settings,
            "folder": str(self.folder),
            "pattern": list(self.patterns),
            "exposure_s": self.exposure_s,
        }

    def _candidates(self) -> list[str]:
        try:
            entries = list(os.scandir(self.folder))
        except OSError as exc:
            raise CameraError(f"cannot list watched folder {self.folder}: {exc}") from exc
        names = []
        for entry in entries:
            if entry.name.startswith(".") or not entry.is_file():
                continue
            lowered = entry.name.lower()
            if any(fnmatch.fnmatchcase(lowered, p.lower()) for p in self.patterns):
                names.append(entry.name)
        return names

    def _do_capture(self, path: Path, frame_index: int, label: str) -> float | None:
        if self.prompt is not None:
            self.prompt(f"press the shutter for {label}")
        deadline = time.monotonic() + self.timeout_s
        sizes: dict[str, int] = {}
        while True:
            new = [name for name in self._candidates() if name not in self._seen]
            stable = []
            for name in new:
                try:
                    size = (self.folder / name).stat().st_size
                except FileNotFoundError:
                    continue
                if size > 0 and sizes.get(name) == size:
                    stable.append(name)
                sizes[name] = size
            if stable:
                name = min(stable, key=lambda n: ((self.folder / n).stat().st_mtime_ns, n))
                break
            if time.monotonic() >= deadline:
                raise CameraError(
                    f"no new file matching {', '.join(self.patterns)} appeared in {self.folder} "
                    f"within {self.timeout_s:g} s for {label}"
                )
            time.sleep(self.poll_s)
        self._seen.add(name)
        source = self.folder / name
        log.info("folder camera: %s arrived for %s", source, label)
        if self.copy:
            shutil.copyfile(source, path)
        else:
            shutil.move(source, path)
        if path.parent.resolve() == self.folder.resolve():
            self._seen.add(path.name)
        if path.suffix.lower() in RAW_SUFFIXES:
            exposure = read_exposure(path)
            if exposure is not None:
                return exposure
        return self.exposure_s
