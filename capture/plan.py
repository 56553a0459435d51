"""The plan of a capture: which frames, in which order, under which file names."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from ps_lab.errors import RigError
from ps_lab.io.run import FRAMES_DIR


@dataclass(frozen=True)
class PlannedFrame:
    """One frame of the plan: index in the manifest, what is lit, and its file name."""

    index: int
    kind: str  # "dark" | "light"
    lights: tuple[int, ...]
    repeat: int
    file: str  # relative to the run folder

    @property
    def label(self) -> str:
        """Human name of the frame, e.g. ``light 5 (repeat 1)`` or ``dark frame``."""
        if self.kind == "dark":
            return "dark frame"
        lights = ",".join(str(i) for i in self.lights)
        return f"light {lights}" + (f" (repeat {self.repeat})" if self.repeat else "")


@dataclass(frozen=True)
class CapturePlan:
    """Which lights to shoot, how often, and the resulting frame list (dark frame first)."""

    lights: tuple[int, ...]
    repeat: int
    n_lights: int
    file_type: str
    frames: tuple[PlannedFrame, ...] = field(repr=False, default=())

    def as_dict(self) -> dict[str, Any]:
        """Return the plan as stored in the manifest."""
        return {"lights": list(self.lights), "repeat": self.repeat}


def make_plan(
    n_lights: int, lights: Sequence[int] | None, repeat: int, file_type: str
) -> CapturePlan:
    """Build the frame list: frame 0 is the dark frame, then ``repeat`` frames per light.

    Parameters
    ----------
    n_lights : int
        Lights of the rig, numbered 1..n_lights.
    lights : sequence of int or None
        Lights to shoot, in this order; None = all.
    repeat : int
        Frames per light (averaged when the run is loaded).
    file_type : str
        File suffix of the frames, without the dot.

    """
    chosen = tuple(range(1, n_lights + 1)) if lights is None else tuple(int(i) for i in lights)
    if not chosen:
        raise RigError("no lights selected")
    if len(set(chosen)) != len(chosen):
        raise RigError("a light is selected twice")
    bad = [i for i in chosen if not 1 <= i <= n_lights]
    if bad:
        raise RigError(f"light {bad[0]} is not on the rig (lights 1-{n_lights})")
    if not 1 <= repeat <= 1000:
        raise RigError(f"--repeat must be between 1 and 1000, got {repeat}")
    width = max(2, len(str(n_lights)))
    frames = [PlannedFrame(0, "dark", (), 0, f"{FRAMES_DIR}/0000-dark.{file_type}")]
    for light in chosen:
        for r in range(repeat):
            i = len(frames)
            frames.append(
                PlannedFrame(
                    i,
                    "light",
                    (light,),
                    r,
                    f"{FRAMES_DIR}/{i:04d}-L{light:0{width}d}-r{r}.{file_type}",
                )
            )
    return CapturePlan(chosen, repeat, n_lights, file_type, tuple(frames))
