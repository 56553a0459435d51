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
from ps_lab.io.codecs import imwrite
from ps_lab.io.files import staged_files
from ps_lab.io.led_model import FLAT_FIELD, LIGHT_AXES, write_flat_field
from ps_lab.io.light_files import write_dome, write_lp

CALIBRATION_FORMAT = "ps-lab-calibration"
OUTPUT_FILES = (
    "light_directions.txt",
    "light_intensities.txt",
    "calibration.json",
    "calibration.png",
    "lights.lp",
)
# Written with two or more chrome spheres (LED positions); removed from the output folder otherwise,
# so an earlier near-light calibration cannot outlive a new one.
POSITION_FILES = (
    "light_positions.txt", "light_anisotropy.txt", "object_outline.txt", "camera.txt",
    LIGHT_AXES, FLAT_FIELD,
)
#: The LED positions as a RelightLab dome (``ps_lab.io.light_files.write_dome``).
DOME_FILE = "lights.dome"
_RAY_COLOURS = ((255, 170, 60), (60, 170, 255), (200, 90, 230), (90, 230, 200))

_GREEN = (80, 220, 80)
_RED = (60, 60, 255)
_YELLOW = (40, 220, 255)
_CYAN = (230, 200, 40)
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
                "uncertainty_deg": (
                    None
                    if cal.uncertainty_deg is None
                    else round(float(cal.uncertainty_deg[j]), 4)
                ),
                "highlight_estimator": cal.estimators[j] if j < len(cal.estimators) else None,
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
            "outline_fitted_on": cal.outline_source,
            "limb_points_used": int(len(cal.limb_points[0])) if cal.limb_points else None,
        },
        "matte_sphere": None
        if cal.matte_circle is None
        else {
            "center": [round(cal.matte_circle.x, 4), round(cal.matte_circle.y, 4)],
            "radius": round(cal.matte_circle.radius, 4),
        },
        "intensities": cal.intensity_source,
        "object_outline_px": cal.object_outline,
        "lights": lights,
        "warnings": list(cal.warnings),
    }
    record.update(cal.metadata)
    if cal.triangulation is not None:
        record["light_positions"] = _positions_record(cal)
    return record


def _positions_record(cal: Calibration) -> dict:
    """LED positions, per light ray miss and spread, in pixels (and mm with a pixel size)."""
    tri = cal.triangulation
    assert tri is not None

    def rounded(values) -> list:
        return [None if not np.isfinite(v) else round(float(v), 4) for v in np.ravel(values)]

    per_light = []
    for j in range(len(tri.positions)):
        entry = {
            "light": j + 1,
            "position": rounded(tri.positions[j]),
            "ray_miss_px": rounded([tri.miss[j]])[0],
            "ray_spread_deg": round(float(tri.spread_deg[j]), 4),
            "too_far": bool(tri.too_far[j]),
        }
        if cal.pixel_size:
            entry["position_mm"] = rounded(tri.positions[j] * cal.pixel_size)
        per_light.append(entry)
    return {
        "frame": "scene: x right, y up, z toward the camera, pixel units; origin at the image "
        "centre in the spheres' plane (through the chrome spheres' centres)",
        "chrome_spheres": [
            {"center": [round(c.x, 4), round(c.y, 4)], "radius": round(c.radius, 4)}
            for c in cal.circles
        ],
        "pixel_size_mm": cal.pixel_size,
        "anisotropy": cal.anisotropy,
        "mean_ray_miss_px": rounded([np.nanmean(tri.miss)])[0] if np.isfinite(tri.miss).any()
        else None,
        "lights": per_light,
    }


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
    # The part of the outline the circle was fitted to (the rest: stand, holder, reflections).
    if cal.limb_points and len(cal.limb_points[0]):
        for x, y in cal.limb_points[0][:: max(1, len(cal.limb_points[0]) // 720)]:
            px, py = to_left(x, y)
            cv2.circle(left, (px, py), 2 * one, _CYAN, -1, cv2.LINE_AA, shift)
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
        f"residual {res}; cyan: outline used"
        + (f" ({cal.outline_source})" if cal.outline_source != "frames" else ""),
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
            picture = calibration_picture(calibration)
            names = list(OUTPUT_FILES)
            if calibration.triangulation is not None:
                picture = _stack_pictures(picture, positions_picture(calibration))
                np.savetxt(
                    staging / POSITION_FILES[0], calibration.triangulation.positions, fmt="%.6f"
                )
                names.append(POSITION_FILES[0])
                if calibration.image_shape is not None:  # the LEDs for RelightLab
                    write_dome(
                        staging / DOME_FILE,
                        calibration.triangulation.positions,
                        calibration.light_directions,
                        calibration.image_shape[1],
                        led_model=None if calibration.led_model is None else {
                            "axes": calibration.led_model.beams.axes,
                            "mu": calibration.led_model.beams.mu,
                            "outputs": calibration.led_model.beams.outputs},
                    )
                    names.append(DOME_FILE)
                if calibration.led_model is not None:  # per-LED beams and the flat-field
                    beams = calibration.led_model.beams
                    np.savetxt(staging / POSITION_FILES[1], beams.mu[:, None], fmt="%.6f")
                    np.savetxt(staging / LIGHT_AXES, beams.axes, fmt="%.9f")
                    write_flat_field(staging / FLAT_FIELD, calibration.led_model.flat)
                    names += [POSITION_FILES[1], LIGHT_AXES, FLAT_FIELD]
                elif calibration.anisotropy:
                    count = len(calibration.light_directions)
                    anisotropy = np.full((count, 1), calibration.anisotropy)
                    np.savetxt(staging / POSITION_FILES[1], anisotropy, fmt="%.6f")
                    names.append(POSITION_FILES[1])
                if calibration.object_outline is not None:
                    np.savetxt(staging / POSITION_FILES[2], [calibration.object_outline],
                               fmt="%.6f")
                    names.append(POSITION_FILES[2])
                if calibration.camera is not None:
                    f, (cx, cy) = calibration.camera
                    np.savetxt(staging / POSITION_FILES[3], [[f, cx, cy]], fmt="%.6f",
                               header="focal length and principal point (x, y), pixels")
                    names.append(POSITION_FILES[3])
            if not imwrite(staging / "calibration.png", picture):
                raise OSError("PNG encoder failed")
        for name in (*POSITION_FILES, DOME_FILE):
            if name not in names:
                (out / name).unlink(missing_ok=True)
    except OSError as exc:
        raise CalibrationError(
            f"{out}: cannot write calibration outputs ({exc.strerror or exc})"
        ) from None
    return {name: out / name for name in names}


def _stack_pictures(top: np.ndarray, bottom: np.ndarray) -> np.ndarray:
    width = max(top.shape[1], bottom.shape[1])

    def pad(img: np.ndarray) -> np.ndarray:
        return np.pad(img, ((0, 0), (0, width - img.shape[1]), (0, 0)))

    return np.vstack([pad(top), np.zeros((8, width, 3), np.uint8), pad(bottom)])


def positions_picture(calibration: Calibration, *, panel: int = 520) -> np.ndarray:
    """The rays and LED positions seen from above (x, y) and from the side (x, z).

    Each chrome sphere's rays in its own colour run from its highlight points to the positions
    (yellow, numbered); a light too far to place keeps its rays only, drawn long. The grey
    rectangle is the image's footprint in the spheres' plane; the scale bar is in mm with a pixel
    size, else in pixels.

    Returns
    -------
    ndarray of shape (panel + 24, 2 * panel + 8, 3), uint8 (BGR)
    """
    cal = calibration
    tri = cal.triangulation
    assert tri is not None and cal.image_shape is not None
    h, w = cal.image_shape
    pos, ok = tri.positions, ~tri.too_far
    corners = np.array([[-(w - 1) / 2, -(h - 1) / 2, 0.0], [(w - 1) / 2, (h - 1) / 2, 0.0]])
    extent = 1.1 * float(np.abs(np.vstack([corners, pos[ok]])).max())
    unit, factor = ("mm", float(cal.pixel_size)) if cal.pixel_size else ("px", 1.0)
    panels = []
    for title, axis, label in (("from above (x, y)", 1, "+y"), ("from the side (x, z)", 2, "+z")):
        img = np.full((panel, panel, 3), 24, np.uint8)
        scale = (panel / 2.0 - 24) / extent
        base = panel / 2.0
        if axis == 2:  # the side view starts at the spheres' plane, near the bottom
            base = panel - 40.0
            top = max(float(pos[ok, 2].max()) if ok.any() else 1.0, 1.0)
            scale = min(scale, (base - 20.0) / top)

        def at(p, base=base, scale=scale, axis=axis) -> tuple[int, int]:
            return (round(panel / 2 + scale * p[0]), round(base - scale * p[axis]))

        cv2.line(img, (0, round(base)), (panel, round(base)), (70, 70, 70), 1)
        cv2.line(img, (panel // 2, 0), (panel // 2, panel), (70, 70, 70), 1)
        _text(img, "+x", (panel - 24, round(base) - 6), _GREY, 0.4)
        _text(img, label, (panel // 2 + 6, 14), _GREY, 0.4)
        cv2.rectangle(img, at(corners[0]), at(corners[1]), _GREY, 1)
        for c in cal.circles:
            centre = (c.x - (w - 1) / 2, (h - 1) / 2 - c.y, 0.0)
            cv2.circle(img, at(centre), max(2, round(c.radius * scale)), _GREEN, 1, cv2.LINE_AA)
        for k in range(tri.origins.shape[0]):
            colour = _RAY_COLOURS[k % len(_RAY_COLOURS)]
            for j in range(tri.origins.shape[1]):
                end = pos[j] if ok[j] else tri.origins[k, j] + 2 * extent * tri.directions[k, j]
                cv2.line(img, at(tri.origins[k, j]), at(end), colour, 1, cv2.LINE_AA)
        for j in np.flatnonzero(ok):
            x, y = at(pos[j])
            cv2.circle(img, (x, y), 3, _YELLOW, -1, cv2.LINE_AA)
            _text(img, str(j + 1), (x + 5, y - 4), _WHITE, 0.35)
        target = extent * factor / 3
        step = 10 ** np.floor(np.log10(target))
        bar = max(m * step for m in (1, 2, 5) if m * step <= target)
        length = round(bar / factor * scale)
        cv2.line(img, (10, panel - 12), (10 + length, panel - 12), _WHITE, 2)
        _text(img, f"{bar:g} {unit}", (14 + length, panel - 8), _WHITE, 0.38)
        head = np.zeros((24, panel, 3), np.uint8)
        _text(head, title, (8, 16), _WHITE, 0.45)
        panels.append(np.vstack([head, img]))
    return np.hstack([panels[0], np.zeros((panel + 24, 8, 3), np.uint8), panels[1]])
