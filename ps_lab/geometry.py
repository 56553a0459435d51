"""Pixel geometry shared by the rig file, the run format and calibration: one :class:`Circle`."""

from __future__ import annotations

from typing import NamedTuple


class Circle(NamedTuple):
    """A circle in loaded-image pixels: x = column, y = row, origin at the top-left pixel centre."""

    x: float
    y: float
    radius: float

    @property
    def center(self) -> tuple[float, float]:
        """``(x, y)``, as rig files write it."""
        return (self.x, self.y)
