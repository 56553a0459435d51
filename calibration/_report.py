"""Calibration outputs: DiLiGenT light tables, ``calibration.json`` and ``calibration.png``.

All files are written into a hidden temporary folder inside the output folder and moved into place
only once every one of them is complete, so a failure leaves no partial output (and earlier
calibration files stay untouched until the new ones are ready).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from ps_lab.calibration._calibrate import Calibration
from ps_lab.errors import CalibrationError
from ps_lab.io.files import staged_files
from ps_lab.io.lights import write_lp

CALIBRATION_FORMAT = "ps-lab-calibration"
OUTPUT_FILES = (
    "light_directions.txt",
    "light_intensities.txt",
    "calibration.json",
    "calibration.png",
    "lights.lp",
)

_GREEN = (80, 220, 80)
_RED = (60, 60, 255)
_YELLOW = (40, 220, 255)
_GREY = (150, 150, 150)
_WHITE = (235, 235, 235)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def zenith_azimuth_deg(light_directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zenith (from the view axis +z) and azimuth (from +x toward +y) of unit directions, degrees.

    Parameters
    ----------
    light_directions : ndarray of shape (n, 3)
        Unit directions.

    Returns
    -------
    zenith, azimuth : ndarrays of shape (n,)

    """
    d = np.asarray(light_directions, dtype=np.float64)
    zenith = np.degrees(np.arccos(np.clip(d[:, 2], -1.0, 1.0)))
    azimuth = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0
    return zenith, azimuth


def calibration_record(calibration: Calibration) -> dict:
    """Return the content of ``calibration.json`` (plain JSON types)."""
    cal = calibration
    zen, azi = zenith_azimuth_deg(cal.light_directions)
    lights = []
    for j in range(len(cal.light_directions)):
        lights.append(
            {
                "light": j + 1,
                "frame": cal.names[j] if j < len(cal.names) else None,
                "highlight": [round(float(v), 4) for v in cal.highlights[j]],
                "direction": [round(float(v), 7) for v in cal.light_directions[j]],
                "zenith_deg": round(float(zen[j]), 3),
                "azimuth_deg": round(float(azi[j]), 3),
                "intensity": [round(float(v), 6) for v in cal.light_intensities[j]],
                "source_radius_deg": (
                    None
                    if cal.source_radius_deg is None
                    else round(float(cal.source_radius_deg[j]), 3)
                ),
            }
        )
    record = {
        "format": CALIBRATION_FORMAT,
        "version": 1,
        "frame": "camera: x right, y up, z toward the camera; directions point toward the lights",
        "pixel_convention": "x = column, y = row, origin at the centre of the top-left pixel",
        "chrome_sphere": {
            "center": [round(cal.circle.x, 4), round(cal.circle.y, 4)],
            "radius": round(cal.circle.radius, 4),
            "residual_px": None if not np.isfinite(cal.residual) else round(cal.residual, 4),
            "source": cal.circle_source,
        },
        "matte_sphere": None
        if cal.matte_circle is None
        else {
            "center": [round(cal.matte_circle.x, 4), round(cal.matte_circle.y, 4)],
            "radius": round(cal.matte_circle.radius, 4),
        },
        "intensities": "matte sphere fit"
        if cal.matte_circle is not None
        else "all ones (no matte target)",
        "lights": lights,
        "warnings": list(cal.warnings),
    }
    return record


def _tone_map(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, dtype=np.float64)
    img = img - np.percentile(img, 1.0)
    hi = max(float(np.percentile(img, 99.9)), 1e-12)
    body = max(
        float(np.percentile(img[img > 0], 50.0)) if np.any(img > 0) else hi * 1e-3, hi * 1e-4
    )
    # Log scale anchored on the sphere's body, so the outline and the highlights both show.
    mapped = np.log1p(np.clip(img, 0, hi) / (0.5 * body)) / np.log1p(hi / (0.5 * body))
    return np.round(255 * np.clip(mapped, 0, 1)).astype(np.uint8)


def _text(
    img: np.ndarray, text: str, org: tuple[int, int], color=_WHITE, scale: float = 0.45
) -> None:
    cv2.putText(img, text, (org[0] + 1, org[1] + 1), _FONT, scale, (0, 0, 0), 2, cv2.LINE_AA)
    cv2.putText(img, text, org, _FONT, scale, color, 1, cv2.LINE_AA)


def calibration_picture(calibration: Calibration, *, panel: int = 520) -> np.ndarray:
    """Draw the picture a user checks before trusting a calibration.

    The sphere with its outline and numbered highlights, beside a polar plot of the light
    directions (radius = zenith angle, circles at 30, 60, 90 degrees).

    Parameters
    ----------
    calibration : Calibration
        The result to show.
    panel : int
        Height in pixels of each panel.

    Returns
    -------
    ndarray of shape (panel + 40, width, 3), uint8 (BGR)

    """
    # One drawing routine (~100 lines): both panels share the scale, fonts and colours, and
    # reading it top to bottom is reading the picture left to right.
    cal = calibration
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px
    one = 1 << shift
    # Left: the sphere (maximum over frames), scaled to the panel.
    if cal.preview is not None and cal.preview.size:
        crop = _tone_map(cal.preview)
        x0, y0 = cal.preview_origin
    else:
        size = int(2 * cal.circle.radius + 20)
        crop = np.zeros((size, size), np.uint8)
        x0, y0 = int(cal.circle.x - size / 2), int(cal.circle.y - size / 2)
    ch, cw = crop.shape
    scale = panel / ch
    left = cv2.resize(
        crop,
        (max(1, round(cw * scale)), panel),
        interpolation=cv2.INTER_NEAREST if scale >= 1 else cv2.INTER_AREA,
    )
    left = cv2.cvtColor(left, cv2.COLOR_GRAY2BGR)

    def to_left(x: float, y: float) -> tuple[int, int]:
        # Pixel centres: image x maps to (x - x0 + 0.5) * scale - 0.5 in the resized panel.
        return (
            round(((x - x0 + 0.5) * scale - 0.5) * one),
            round(((y - y0 + 0.5) * scale - 0.5) * one),
        )

    c = cal.circle
    cv2.circle(
        left, to_left(c.x, c.y), round(c.radius * scale * one), _GREEN, 1, cv2.LINE_AA, shift
    )
    cx, cy = to_left(c.x, c.y)
    cv2.drawMarker(left, (cx >> shift, cy >> shift), _GREEN, cv2.MARKER_CROSS, 10, 1, cv2.LINE_AA)
    for j, (hx, hy) in enumerate(cal.highlights):
        px, py = to_left(hx, hy)
        cv2.circle(left, (px, py), 4 * one, _RED, 1, cv2.LINE_AA, shift)
        _text(left, str(j + 1), ((px >> shift) + 5, (py >> shift) - 4), _YELLOW, 0.38)

    # Right: polar plot of the directions, x right and y up as seen from the camera.
    right = np.full((panel, panel, 3), 24, np.uint8)
    zen, azi = zenith_azimuth_deg(cal.light_directions)
    zmax = max(90.0, float(np.ceil(zen.max() / 10.0) * 10.0)) if len(zen) else 90.0
    centre = panel / 2.0
    rad = panel / 2.0 - 28

    def to_polar(z: float, a: float) -> tuple[int, int]:
        rr = z / zmax * rad
        return (
            round((centre + rr * np.cos(np.radians(a))) * one),
            round((centre - rr * np.sin(np.radians(a))) * one),
        )

    for z in (30, 60, 90):
        cv2.circle(
            right,
            (round(centre * one), round(centre * one)),
            round(z / zmax * rad * one),
            _GREY,
            1,
            cv2.LINE_AA,
            shift,
        )
        _text(
            right,
            f"{z}",
            (
                round(centre + z / zmax * rad * 0.707) + 2,
                round(centre - z / zmax * rad * 0.707) - 2,
            ),
            _GREY,
            0.4,
        )
    ic = round(centre)
    cv2.line(right, (ic - round(rad), ic), (ic + round(rad), ic), (70, 70, 70), 1)
    cv2.line(right, (ic, ic - round(rad)), (ic, ic + round(rad)), (70, 70, 70), 1)
    _text(right, "+x", (ic + round(rad) + 2, ic + 4), _GREY, 0.4)
    _text(right, "+y", (ic - 8, ic - round(rad) - 6), _GREY, 0.4)
    for j in range(len(zen)):
        px, py = to_polar(zen[j], azi[j])
        cv2.circle(right, (px, py), 4 * one, _YELLOW, -1, cv2.LINE_AA, shift)
        _text(right, str(j + 1), ((px >> shift) + 6, (py >> shift) - 4), _WHITE, 0.38)

    gap = np.full((panel, 8, 3), 0, np.uint8)
    body = np.hstack([left, gap, right])
    header = np.full((40, body.shape[1], 3), 0, np.uint8)
    res = "n/a" if not np.isfinite(cal.residual) else f"{cal.residual:.3f} px"
    _text(
        header,
        f"chrome sphere ({c.x:.2f}, {c.y:.2f}) r={c.radius:.2f} [{cal.circle_source}], "
        f"residual {res}",
        (8, 16),
        _WHITE,
        0.45,
    )
    _text(
        header,
        f"{len(zen)} lights; zenith {zen.min():.1f}-{zen.max():.1f} deg (circles: 30/60/90)"
        + (f"; {len(cal.warnings)} warning(s)" if cal.warnings else ""),
        (8, 34),
        _WHITE,
        0.45,
    )
    return np.vstack([header, body])


def write_calibration(calibration: Calibration, out_dir: Path) -> dict[str, Path]:
    """Write the four calibration files into ``out_dir`` (created if needed), all or nothing.

    Parameters
    ----------
    calibration : Calibration
        The result to write.
    out_dir : Path
        Output folder.

    Returns
    -------
    dict
        File name → final path for ``light_directions.txt``, ``light_intensities.txt``,
        ``calibration.json`` and ``calibration.png``.

    Raises
    ------
    CalibrationError
        When the folder cannot be written (nothing is left behind).

    """
    out = Path(out_dir)
    try:
        with staged_files(out, prefix=".calibrate-") as staging:
            np.savetxt(staging / "light_directions.txt", calibration.light_directions, fmt="%.9f")
            np.savetxt(
                staging / "light_intensities.txt", calibration.light_intensities, fmt="%.9f"
            )
            # The same directions for RTI tools (RelightLab, RTIBuilder): "filename x y z".
            write_lp(staging / "lights.lp", list(calibration.names), calibration.light_directions)
            record = calibration_record(calibration)
            (staging / "calibration.json").write_text(
                json.dumps(record, indent=2) + "\n", encoding="utf-8"
            )
            if not cv2.imwrite(str(staging / "calibration.png"), calibration_picture(calibration)):
                raise OSError("PNG encoder failed")
    except OSError as exc:
        raise CalibrationError(
            f"{out}: cannot write calibration outputs ({exc.strerror or exc})"
        ) from None
    return {name: out / name for name in OUTPUT_FILES}
