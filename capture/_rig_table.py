"""Typed, validated access to the tables of a rig file.

Every key read is recorded, so a key nobody read is an error naming the file, the table and the
key.
"""

from __future__ import annotations

import math
from typing import Any

from ps_lab.errors import RigError


class _Table:
    """Typed access to one TOML table; every read key is recorded so leftovers are errors."""

    def __init__(self, data: Any, where: str, origin: str) -> None:
        if not isinstance(data, dict):
            raise RigError(f"{origin}: [{where}] must be a table, got {_kind(data)}")
        self.data = data
        self.where = where
        self.origin = origin
        self.used: set[str] = set()

    def error(self, key: str, message: str) -> RigError:
        return RigError(f"{self.origin}: [{self.where}] {key}: {message}")

    def _get(self, key: str, default: Any, required: bool) -> Any:
        self.used.add(key)
        if key not in self.data:
            if required:
                raise self.error(key, "missing (required)")
            return default
        return self.data[key]

    def str(self, key: str, default: Any = None, *, required: bool = False, choices=None) -> Any:
        value = self._get(key, default, required)
        if key in self.data:
            if not isinstance(value, str):
                raise self.error(key, f"expected a string, got {_kind(value)}")
            if choices is not None and value not in choices:
                raise self.error(key, f"unknown value {value!r} (choose from {', '.join(choices)})")
        return value

    def int(
        self, key: str, default: Any = None, *, required: bool = False, lo=None, hi=None
    ) -> Any:
        value = self._get(key, default, required)
        if key in self.data:
            if isinstance(value, bool) or not isinstance(value, int):
                raise self.error(key, f"expected an integer, got {_kind(value)}")
            self._range(key, value, lo, hi)
        return value

    def float(
        self, key: str, default: Any = None, *, required: bool = False, lo=None, hi=None
    ) -> Any:
        value = self._get(key, default, required)
        if key in self.data:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise self.error(key, f"expected a number, got {_kind(value)}")
            if not math.isfinite(value):
                raise self.error(key, "must be finite")
            value = float(value)
            self._range(key, value, lo, hi)
        return value

    def bool(self, key: str, default: bool = False) -> bool:
        value = self._get(key, default, False)
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {_kind(value)}")
        return value

    def vector(self, key: str, length: int, default: Any = None, *, required: bool = False) -> Any:
        value = self._get(key, default, required)
        if key in self.data:
            value = self._vector(key, value, length)
        return value

    def vectors(self, key: str, length: int) -> tuple[tuple[float, ...], ...] | None:
        value = self._get(key, None, False)
        if value is None:
            return None
        if not isinstance(value, list):
            raise self.error(key, f"expected a list of {length}-vectors, got {_kind(value)}")
        return tuple(self._vector(f"{key}[{i}]", v, length) for i, v in enumerate(value))

    def ints(self, key: str) -> tuple[int, ...] | None:
        value = self._get(key, None, False)
        if value is None:
            return None
        if not isinstance(value, list) or not all(
            isinstance(v, int) and not isinstance(v, bool) for v in value
        ):
            raise self.error(key, f"expected a list of integers, got {_kind(value)}")
        return tuple(value)

    def table(self, key: str) -> _Table | None:
        value = self._get(key, None, False)
        if value is None:
            return None
        return _Table(value, f"{self.where}.{key}" if self.where else key, self.origin)

    def tables(self, key: str) -> list[_Table]:
        value = self._get(key, [], False)
        if not isinstance(value, list):
            raise self.error(key, f"expected an array of tables, got {_kind(value)}")
        prefix = f"{self.where}." if self.where else ""
        return [_Table(v, f"{prefix}{key}[{i}]", self.origin) for i, v in enumerate(value)]

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise self.error(
                unknown[0],
                "unknown key" + (f" (also: {', '.join(unknown[1:])})" if unknown[1:] else ""),
            )

    def _range(self, key: str, value: float, lo: float | None, hi: float | None) -> None:
        if lo is not None and value < lo:
            raise self.error(key, f"must be >= {lo}, got {value}")
        if hi is not None and value > hi:
            raise self.error(key, f"must be <= {hi}, got {value}")

    def _vector(self, key: str, value: Any, length: int) -> tuple[float, ...]:
        if (
            not isinstance(value, list)
            or len(value) != length
            or any(isinstance(v, bool) or not isinstance(v, int | float) for v in value)
        ):
            raise self.error(key, f"expected a list of {length} numbers, got {value!r}")
        if not all(math.isfinite(v) for v in value):
            raise self.error(key, f"every number must be finite, got {value!r}")
        return tuple(float(v) for v in value)


def _kind(value: Any) -> str:
    return {
        bool: "a boolean",
        int: "an integer",
        float: "a number",
        str: "a string",
        list: "a list",
        dict: "a table",
    }.get(type(value), type(value).__name__)


def unit_vectors(t: _Table, key: str, count: int) -> tuple[tuple[float, float, float], ...] | None:
    """``t[key]``: ``count`` directions toward the lights, normalised, each above the horizon."""
    vectors = t.vectors(key, 3)
    if vectors is None:
        return None
    if len(vectors) != count:
        raise t.error(key, f"expected {count} directions (one per light), got {len(vectors)}")
    out = []
    for i, v in enumerate(vectors):
        scale = max(abs(c) for c in v)  # scaled first: no overflow for huge components
        norm = scale * math.sqrt(sum((c / scale) ** 2 for c in v)) if scale > 0 else 0.0
        if norm < 1e-9:
            raise t.error(f"{key}[{i}]", "zero vector")
        unit = tuple(c / norm for c in v)
        if unit[2] <= 0.0:
            raise t.error(f"{key}[{i}]", f"points below the horizon (z = {unit[2]:.3g}); a light "
                          "is above the scene, z > 0")
        out.append(unit)
    return tuple(out)  # type: ignore[return-value]


def light_intensities(t: _Table, count: int) -> tuple[tuple[float, ...], ...] | None:
    """``t["intensities"]``: one positive, bounded [r, g, b] row per light (relative to 1)."""
    rows = t.vectors("intensities", 3)
    if rows is None:
        return None
    if len(rows) != count:
        raise t.error(
            "intensities", f"expected {count} [r, g, b] rows (one per light), got {len(rows)}"
        )
    if any(not 0 < v <= MAX_INTENSITY for row in rows for v in row):
        raise t.error("intensities", f"every intensity must be positive and at most "
                      f"{MAX_INTENSITY:g} (relative to 1)")
    return rows


#: Light intensities are relative (1: the rig's nominal LED); beyond this the simulated camera's
#: counts overflow.
MAX_INTENSITY = 1e3
