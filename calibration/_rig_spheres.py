"""The nominal spheres and LED exponent that a capture run's rig snapshot records."""

from __future__ import annotations

import numpy as np

from ps_lab.calibration._circle import Circle
from ps_lab.errors import CalibrationError
from ps_lab.io.run import calibration_target


def _circle_from_record(record: object, what: str) -> Circle | None:
    if record is None:
        return None
    try:
        (x, y), r = record["center"], record["radius"]  # type: ignore[index]
        circle = Circle(float(x), float(y), float(r))
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(
            f"manifest rig snapshot: calibration.{what} must be "
            f"{{center = [x, y], radius = r}}, got {record!r}"
        ) from None
    if not all(np.isfinite(circle)) or circle.radius <= 0:
        raise CalibrationError(
            f"manifest rig snapshot: calibration.{what} is not a valid circle: {record!r}"
        )
    return circle


def rig_chrome_spheres(manifest: dict | None) -> list[Circle]:
    """Every nominal chrome sphere of a capture run's rig snapshot (first = ``chrome_sphere``)."""
    cal = calibration_target(manifest)
    if not isinstance(cal, dict):
        return []
    records = cal.get("chrome_spheres")
    if isinstance(records, list) and records:
        return [_circle_from_record(r, "chrome_spheres") for r in records]  # type: ignore[misc]
    first = _circle_from_record(cal.get("chrome_sphere"), "chrome_sphere")
    return [] if first is None else [first]


def rig_anisotropy(manifest: dict | None) -> float:
    """The LEDs' ``cos^mu`` exponent from a capture run's rig snapshot (0 when absent)."""
    controller = ((manifest or {}).get("rig") or {}).get("controller") or {}
    value = controller.get("anisotropy", 0.0) if isinstance(controller, dict) else 0.0
    return float(value) if isinstance(value, int | float) else 0.0


def rig_object_outline(manifest: dict | None) -> str | float | None:
    """Where the rig file says the object's outline lies (``[calibration] object_outline``)."""
    value = (calibration_target(manifest) or {}).get("object_outline")
    return value if isinstance(value, str | int | float) and not isinstance(value, bool) else None


def rig_led_intensities(manifest: dict | None) -> str:
    """The rig file's LED intensity model without a matte target (``"equal"`` when absent)."""
    value = (calibration_target(manifest) or {}).get("led_intensities")
    return value if isinstance(value, str) else "equal"


def rig_circles(manifest: dict | None) -> tuple[Circle | None, Circle | None]:
    """Nominal chrome and matte sphere circles from a capture run's rig snapshot.

    Parameters
    ----------
    manifest : dict or None
        Parsed ``manifest.json`` (``manifest["rig"]["calibration"]["chrome_sphere"]`` etc.).

    Returns
    -------
    chrome, matte : Circle or None

    """
    cal = calibration_target(manifest)
    if not isinstance(cal, dict):
        return None, None
    return (
        _circle_from_record(cal.get("chrome_sphere"), "chrome_sphere"),
        _circle_from_record(cal.get("matte_sphere"), "matte_sphere"),
    )
