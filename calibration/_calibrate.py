"""Light calibration from a chrome sphere: the stages of :func:`calibrate`.

Frames -> the chrome sphere(s) (:mod:`._spheres`) -> one highlight per frame and sphere ->
mirror-law directions, or LED positions from several spheres -> matte-sphere intensities -> the
preview.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ps_lab.calibration._circle import Circle, circle_inside_image, refine_circle, summary_image
from ps_lab.calibration._highlight import Highlight, locate_highlight, share_source_radius
from ps_lab.calibration._intensity import fit_light_intensities, led_intensities_at_origin
from ps_lab.calibration._mirror_geometry import light_directions_from_highlights
from ps_lab.calibration._positions import (
    MIN_RAY_ANGLE_DEG,
    Triangulation,
    ray_sigmas,
    reflected_rays,
    triangulate_lights,
)
from ps_lab.calibration._spheres import (
    LimbImages,
    chrome_score,
    chrome_sphere,
    given_sphere_without_highlights,
    missing_rig_sphere,
    other_spheres,
)
from ps_lab.errors import CalibrationError
from ps_lab.geometry import Camera


@dataclass
class Calibration:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    circle : Circle
        Chrome sphere outline ``(x, y, radius)`` in pixels.
    residual : float
        RMS distance (pixels) of the limb edge points from ``circle``; NaN if not measurable.
    circle_source : str
        ``"given"``, ``"rig"`` (nominal circle refined) or ``"auto"``.
    highlights : ndarray of shape (n, 2)
        Sub-pixel highlight positions ``(x, y)``.
    light_directions : ndarray of shape (n, 3)
        Unit vectors toward the lights, camera frame x right, y up, z toward the camera.
    light_intensities : ndarray of shape (n, 3)
        Relative intensity per light and colour channel (mean 1; all ones without a matte sphere).
    warnings : list of str
    matte_circle : Circle or None
    source_radius_deg : ndarray of shape (n,)
        Angular radius of each light estimated from its highlight's extent (0 when unresolved).
    names : list of str
        Frame names (light order).
    preview : ndarray of shape (h, w) or None
        Per-pixel maximum over frames of the sphere's surroundings (for the picture).
    preview_origin : (int, int)
        ``(x0, y0)`` of ``preview`` in the image.
    circles : list of Circle
        Every chrome sphere used (``circle`` first).
    triangulation : Triangulation or None
        With two or more chrome spheres: the rays, LED positions (scene frame of
        :mod:`ps_lab.geometry`, pixel units), miss distances; ``light_directions`` then point
        from the scene origin toward the positions.
    anisotropy : float
        The LEDs' ``cos^mu`` exponent used for the near-light intensities.
    image_shape : (H, W) or None
    pixel_size : float or None
        Millimetres per pixel (for reports only; positions stay in pixels).
    limb_points : list of ndarray of shape (m, 2)
        Per sphere (``circles`` order), the edge points its outline was fitted to: the part of
        the outline that is really the sphere's edge (drawn in calibration.png).
    uncertainty_deg : ndarray of shape (n,) or None
        Standard uncertainty of each light direction (degrees): the highlight's position
        uncertainty and the circle's, propagated through the mirror law.
    estimators : list of str
        Per light, the highlight estimator used (``"centroid"`` or ``"core"``).
    outline_source : str
        What the limb was fitted on: ``"frames"`` or ``"outline frame"``.
    metadata : dict
        Free-form facts recorded in calibration.json (the image encoding, the probes).
    intensity_source : str
        How ``light_intensities`` were obtained (``calibration.json``).
    object_outline : float or None
        Height of the object's outline above the spheres' plane (pixels) when stated
        (``object_outline.txt``); None: ``ps-lab reconstruct`` finds it.
    camera : Camera or None
        With LED positions and a focal length: the perspective camera they were triangulated
        through (``camera.txt``: ``f cx cy`` in pixels), which near-light solving then uses.

    """

    circle: Circle
    residual: float
    circle_source: str
    highlights: np.ndarray
    light_directions: np.ndarray
    light_intensities: np.ndarray
    warnings: list[str] = field(default_factory=list)
    matte_circle: Circle | None = None
    source_radius_deg: np.ndarray | None = None
    names: list[str] = field(default_factory=list)
    preview: np.ndarray | None = None
    preview_origin: tuple[int, int] = (0, 0)
    circles: list[Circle] = field(default_factory=list)
    triangulation: Triangulation | None = None
    anisotropy: float = 0.0
    image_shape: tuple[int, int] | None = None
    pixel_size: float | None = None
    limb_points: list[np.ndarray] = field(default_factory=list)
    uncertainty_deg: np.ndarray | None = None
    estimators: list[str] = field(default_factory=list)
    outline_source: str = "frames"
    metadata: dict = field(default_factory=dict)
    intensity_source: str = "all ones (no matte target)"
    object_outline: float | None = None
    camera: Camera | None = None
    led_model: Any = None  # calibration._leds.LedModel (ps-lab calibrate --flat-field)

    @property
    def light_positions(self) -> np.ndarray | None:
        """(n, 3) LED positions (scene frame, pixels; NaN rows: too far), None with one sphere."""
        return None if self.triangulation is None else self.triangulation.positions


def _as_stack(images: np.ndarray) -> np.ndarray:
    arr = np.asarray(images)
    if arr.ndim == 3:
        arr = arr[..., None]
    if arr.ndim != 4 or arr.shape[-1] not in (1, 3):
        raise CalibrationError(
            f"calibration needs frames of shape (n, H, W) or (n, H, W, C) with C = 1 or 3, "
            f"got {arr.shape}"
        )
    if arr.shape[0] < 1:
        raise CalibrationError("no frames to calibrate")
    return arr


def _frame_luma(
    stack: np.ndarray, j: int, rows: slice = slice(None), cols: slice = slice(None)
) -> np.ndarray:
    return np.asarray(stack[j, rows, cols], dtype=np.float32).mean(axis=-1)


def _infer_saturated(stack: np.ndarray) -> np.ndarray | None:
    # Without a sensor mask, clipping shows as a plateau at the stack's maximum.
    top = float(stack.max())
    if top <= 0:
        return None
    sat = np.empty(stack.shape[:3], dtype=bool)
    for j in range(stack.shape[0]):
        sat[j] = np.any(stack[j] >= top * (1.0 - 1e-6), axis=-1)
    return sat if sat.sum() > stack.shape[0] else None


def _frame_label(j: int, names: Sequence[str] | None) -> str:
    if names is not None and j < len(names):
        return f"light {j + 1} ({names[j]})"
    return f"light {j + 1}"


def calibrate(
    images: np.ndarray,
    *,
    sphere: tuple[float, float, float] | None = None,
    sphere_hint: tuple[float, float, float] | None = None,
    roi: tuple[int, int, int, int] | None = None,
    matte_sphere: tuple[float, float, float] | None = None,
    matte_hint: tuple[float, float, float] | None = None,
    saturated: np.ndarray | None = None,
    safe_radius: float = 0.9,
    focal_length_px: float | None = None,
    principal_point: tuple[float, float] | None = None,
    names: Sequence[str] | None = None,
    progress: Callable[[int], None] | None = None,
    extra_spheres: Sequence[Sequence[float]] = (),
    extra_sphere_hints: Sequence[Sequence[float]] = (),
    anisotropy: float = 0.0,
    pixel_size: float | None = None,
    outline: np.ndarray | None = None,
    led_intensities: str | np.ndarray = "equal",
    object_outline: str | float | None = None,
    outline_name: str = "outline frame",
) -> Calibration:
    """Calibrate light directions (and intensities) from a chrome sphere seen in every frame.

    With two or more chrome spheres (``extra_spheres`` / ``extra_sphere_hints``, or several found
    by the automatic search) each light is also placed in 3-D: the least-squares intersection of
    its reflected rays (:func:`triangulate_lights`); directions then point from the scene origin
    to the positions and the matte sphere is fitted under the near-light model.

    Parameters
    ----------
    images : ndarray of shape (n, H, W) or (n, H, W, C)
        Linear frames, one per light (dark-subtracted), C = 1 or 3.
    sphere : (cx, cy, r), optional
        Chrome sphere circle in pixels, used as given (only its residual is measured).
    sphere_hint : (cx, cy, r), optional
        Nominal circle (e.g. from the rig file), refined to sub-pixel on the images.
    roi : (x, y, w, h), optional
        Restrict the automatic search to this rectangle.
    matte_sphere, matte_hint : (cx, cy, r), optional
        Matte sphere circle used as given / refined; with either, intensities are fitted.
    saturated : ndarray of shape (n, H, W), bool, optional
        Sensor clipping mask; inferred from a plateau at the maximum when omitted.
    safe_radius : float
        Highlights beyond this share of the radius are rejected.
    focal_length_px : float, optional
        Focal length / pixel pitch for the perspective correction (None: orthographic).
    principal_point : (x, y), optional
        Optical axis in pixels; default the image centre.
    names : sequence of str, optional
        Frame names for messages.
    progress : callable, optional
        Called with 1 after each frame's highlight (of every sphere).
    extra_spheres, extra_sphere_hints : sequence of (cx, cy, r)
        More chrome spheres, used as given / refined.
    anisotropy : float
        The LEDs' ``cos^mu`` exponent (near-light intensities).
    pixel_size : float, optional
        Millimetres per pixel, recorded for the report.
    outline : ndarray of shape (H, W) or (H, W, C), optional
        A frame in which the spheres' outlines are visible (room light, PSBox's ``ref.JPG``):
        the outlines are found and fitted on it instead of on the frames.
    led_intensities : {"equal", "origin"} or ndarray of shape (n,) or (n, 3)
        Without a matte sphere, with LED positions: the LEDs' intensity model
        (:func:`._intensity.led_intensities_at_origin`; default identical LEDs). Ignored with a
        matte sphere and with one chrome sphere (then all ones, or the array as given).
    object_outline : "table", float or None
        Where the object's outline lies (near lights): ``"table"`` on the table the chrome
        spheres rest on (their mean radius below the spheres' plane), or a height in pixels
        above that plane; None: not stated.

    Returns
    -------
    Calibration

    Raises
    ------
    CalibrationError
        No sphere found, sphere cut by the border, a frame without a usable highlight, all
        frames saturated, a degenerate matte fit.

    """
    stack, saturated = _prepare_frames(images, saturated)
    n, h, w, _ = stack.shape
    summary = summary_image(stack)
    limb = _limb_images(summary, stack, outline, outline_name)
    warnings: list[str] = []
    try:
        circle, residual, source, points = chrome_sphere(
            limb, stack, sphere, sphere_hint, roi, warnings
        )
        if source == "auto" and sphere_hint is not None and extra_sphere_hints:
            raise missing_rig_sphere(1, sphere_hint)  # the search would find another of the rig's
        found_others = other_spheres(
            limb, stack, circle, source, extra_spheres, extra_sphere_hints, roi, warnings
        )
    except CalibrationError as exc:
        if outline is None:
            raise
        # The outlines were looked for on the outline frame: it is the file at fault.
        raise CalibrationError(f"{outline_name}: {exc} (outlines are fitted on this frame)") from None
    others = [c for c, _ in found_others]
    try:
        found = _highlights(stack, circle, saturated, safe_radius, names, progress)
    except CalibrationError as exc:
        if source == "given" and "saturated" not in str(exc) and chrome_score(stack, circle) < 0.5:
            raise given_sphere_without_highlights(circle) from None
        raise
    highlights = np.array([[hl.x, hl.y] for hl in found])
    warnings.extend(_second_blob_warnings(found, names))
    if focal_length_px is not None and principal_point is None:
        principal_point = ((w - 1) / 2.0, (h - 1) / 2.0)

    def to_directions(hl: np.ndarray, c: Circle) -> np.ndarray:
        return light_directions_from_highlights(
            hl, c, focal_length_px=focal_length_px, principal_point=principal_point
        )

    directions = to_directions(highlights, circle)
    uncertainty = direction_uncertainty(
        highlights, np.array([hl.uncertainty_px for hl in found]), circle,
        circle_uncertainty_px(residual, len(points)), to_directions,
    )
    triangulation = None
    camera = None
    if focal_length_px is not None:
        camera = Camera(float(focal_length_px), tuple(map(float, principal_point)))  # type: ignore[arg-type]
    if others:
        triangulation = _triangulate(
            stack, circle, highlights, others, saturated, safe_radius, names, progress, warnings,
            uncertainty,
            camera,
        )
        directions = triangulation.light_directions
    matte_circle, intensities = _matte_intensities(
        stack, summary, directions, saturated, matte_sphere, matte_hint, warnings,
        None if triangulation is None else triangulation.positions, anisotropy,
    )
    intensity_source = (
        "matte sphere fit" if matte_circle is not None else "all ones (no matte target)"
    )
    if matte_circle is None and triangulation is not None:
        intensities, intensity_source = led_intensities_at_origin(
            triangulation.positions, led_intensities
        )
    elif matte_circle is None and not isinstance(led_intensities, str):
        intensities, intensity_source = led_intensities_at_origin(
            np.full((n, 3), np.nan), led_intensities
        )
    if isinstance(object_outline, str):
        if object_outline != "table":
            raise CalibrationError(f"object outline {object_outline!r}: give table or a number")
        outline_height = -float(np.mean([c.radius for c in [circle, *others]]))
    else:
        outline_height = None if object_outline is None else float(object_outline)
    preview, preview_origin = _preview(stack, circle)
    return Calibration(
        circle=circle,
        residual=float(residual),
        circle_source=source,
        highlights=highlights,
        light_directions=directions,
        light_intensities=intensities,
        warnings=warnings,
        matte_circle=matte_circle,
        source_radius_deg=np.array([hl.source_radius_deg for hl in found]),
        names=list(names) if names is not None else [f"frame {j + 1}" for j in range(n)],
        preview=preview,
        preview_origin=preview_origin,
        circles=[circle, *others],
        triangulation=triangulation,
        anisotropy=float(anisotropy),
        image_shape=(h, w),
        pixel_size=pixel_size,
        limb_points=[points, *(p for _, p in found_others)],
        uncertainty_deg=uncertainty,
        estimators=[hl.estimator for hl in found],
        outline_source="frames" if outline is None else "outline frame",
        intensity_source=intensity_source,
        object_outline=outline_height,
        camera=camera if triangulation is not None else None,
    )


def _limb_images(
    summary: np.ndarray, stack: np.ndarray, outline: np.ndarray | None, name: str
) -> LimbImages:
    if outline is None:
        return LimbImages(summary, stack)
    frame = np.asarray(outline, dtype=np.float32)
    if frame.ndim == 3:
        frame = frame.mean(axis=-1)
    if frame.shape != summary.shape:
        raise CalibrationError(
            f"{name} is {frame.shape[1]}x{frame.shape[0]}, the frames are "
            f"{summary.shape[1]}x{summary.shape[0]}"
        )
    frame = np.nan_to_num(frame, nan=0.0, posinf=0.0, neginf=0.0)
    top, bottom = float(frame.max()), float(frame.min())
    if top <= 0 or top - bottom <= 1e-3 * top:
        what = "black" if top <= 0 else f"blank (every pixel {top:.4g})"
        raise CalibrationError(
            f"{name} is {what}: no sphere outline to fit (a frame with room light, in which the "
            "spheres' edges show)"
        )
    return LimbImages(frame, None)


def circle_uncertainty_px(residual: float, n_points: int) -> float:
    """Standard uncertainty of a fitted circle's centre (px) from its edge residual.

    A circle's centre from m points spread round the outline has variance 2 s^2 / m; edge
    points of neighbouring rays (about a pixel apart) share the limb's blur and texture, so
    m is counted as a quarter of the points.
    """
    if not np.isfinite(residual) or n_points < 3:
        return 0.0
    return float(residual * np.sqrt(2.0 / max(n_points / 4.0, 1.0)))


def direction_uncertainty(
    highlights: np.ndarray,
    highlight_px: np.ndarray,
    circle: Circle,
    circle_px: float,
    to_directions: Callable[[np.ndarray, Circle], np.ndarray],
) -> np.ndarray:
    """Per-light direction uncertainty (degrees) by finite differences of the mirror law.

    A highlight shift of ``highlight_px`` and a centre shift of ``circle_px``, each along x and
    y, are propagated; the four angular changes add in quadrature (a circle shift moves every
    highlight's normal the opposite way).
    """
    base = to_directions(highlights, circle)
    total = np.zeros(len(highlights))
    for dx, dy in ((1.0, 0.0), (0.0, 1.0)):
        step = np.array([dx, dy])
        moved = to_directions(highlights + step * highlight_px[:, None], circle)
        total += _angles(base, moved) ** 2
        if circle_px > 0:
            shifted = Circle(circle.x + dx * circle_px, circle.y + dy * circle_px, circle.radius)
            total += _angles(base, to_directions(highlights, shifted)) ** 2
    return np.sqrt(total)


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


# --- the stages of calibrate() ----------------------------------------------------------------


def _prepare_frames(
    images: np.ndarray, saturated: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Frames as a finite (n, H, W, C) stack, and their saturation mask (given or inferred)."""
    stack = _as_stack(images)
    n, h, w, _ = stack.shape
    if not np.all(np.isfinite(stack)):
        stack = np.nan_to_num(stack, nan=0.0, posinf=0.0, neginf=0.0)
    if saturated is None:
        return stack, _infer_saturated(stack)
    saturated = np.asarray(saturated, dtype=bool)
    if saturated.shape != (n, h, w):
        raise CalibrationError(f"saturation mask shape {saturated.shape} != frames {(n, h, w)}")
    return stack, saturated


def _triangulate(
    stack: np.ndarray,
    circle: Circle,
    highlights: np.ndarray,
    others: list[Circle],
    saturated: np.ndarray | None,
    safe_radius: float,
    names: Sequence[str] | None,
    progress: Callable[[int], None] | None,
    warnings: list[str],
    uncertainty: np.ndarray | None = None,
    camera: Camera | None = None,
) -> Triangulation:
    """Every light's reflected ray on every sphere, intersected; warnings for far lights.

    A light is placed only when its rays are further apart than both the baseline limit of
    :func:`triangulate_lights` and three times the light's direction uncertainty: rays that
    disagree within their noise say nothing about the distance.
    """
    shape = stack.shape[1:3]
    origins, directions, sigmas = [], [], []
    for c, hl in [(circle, highlights), *((c, None) for c in others)]:
        if hl is None:
            try:
                found = _highlights(stack, c, saturated, safe_radius, names, progress)
            except CalibrationError as exc:
                # The rig's spheres were confirmed to be chrome: this one is a given --sphere.
                if "saturated" not in str(exc) and chrome_score(stack, c) < 0.5:
                    raise given_sphere_without_highlights(c) from None
                raise
            hl = np.array([[f.x, f.y] for f in found])
        o, d = reflected_rays(hl, c, shape, camera)
        origins.append(o)
        directions.append(d)
        # equal pixel precision on every sphere (the highlights' own uncertainty measures their
        # shape's asymmetry more than their noise): the weights follow the geometry
        sigmas.append(ray_sigmas(hl, c))
    result = triangulate_lights(
        np.array(origins),
        np.array(directions),
        sigmas=np.array(sigmas),
        min_angle_deg=MIN_RAY_ANGLE_DEG
        if uncertainty is None
        else np.maximum(MIN_RAY_ANGLE_DEG, 3.0 * uncertainty),
    )
    for j in np.flatnonzero(result.too_far):
        warnings.append(
            f"{_frame_label(j, names)}: its rays are {result.spread_deg[j]:.2f} deg apart, too "
            "close to parallel to place the light (too far for the spheres' baseline); it is "
            "treated as a directional light"
        )
    return result


def _highlights(
    stack: np.ndarray,
    circle: Circle,
    saturated: np.ndarray | None,
    safe_radius: float,
    names: Sequence[str] | None,
    progress: Callable[[int], None] | None,
) -> list[Highlight]:
    """One highlight per frame, or a CalibrationError naming the first frame without one."""
    n, h, w, _ = stack.shape
    found: list[Highlight | None] = []
    problems: list[tuple[int, str]] = []
    saturated_frames = 0
    # Highlights are searched on the sphere's bounding box only (frames may be tens of MP).
    bx0, by0 = max(0, int(circle.x - circle.radius) - 3), max(0, int(circle.y - circle.radius) - 3)
    bx1 = min(w, int(np.ceil(circle.x + circle.radius)) + 4)
    by1 = min(h, int(np.ceil(circle.y + circle.radius)) + 4)
    box = (slice(by0, by1), slice(bx0, bx1))
    local = Circle(circle.x - bx0, circle.y - by0, circle.radius)
    for j in range(n):
        try:
            hl = locate_highlight(
                _frame_luma(stack, j, *box),
                local,
                saturated=None if saturated is None else saturated[j][box],
                safe_radius=safe_radius,
            )
            second = hl.second_blob
            if second is not None:
                second = (second[0] + bx0, second[1] + by0, second[2])
            found.append(replace(hl, x=hl.x + bx0, y=hl.y + by0, second_blob=second,
                                 centroid=(hl.centroid[0] + bx0, hl.centroid[1] + by0)))
        except CalibrationError as exc:
            found.append(None)
            problems.append((j, str(exc)))
            saturated_frames += "saturated" in str(exc)
        if progress is not None:
            progress(1)
    if saturated_frames == n:
        raise CalibrationError(
            f"all {n} frames are saturated over the chrome sphere: "
            "shorten the exposure or dim the lights"
        )
    problems.extend(_dim_highlights(found))
    if problems:
        problems.sort()
        j, msg = problems[0]
        more = f" (and {len(problems) - 1} more frame(s) failed)" if len(problems) > 1 else ""
        raise CalibrationError(f"{_frame_label(j, names)}: {msg}{more}")
    # no None left: every one is a problem above
    return share_source_radius(found, circle)  # type: ignore[arg-type]


def _dim_highlights(found: list[Highlight | None]) -> list[tuple[int, str]]:
    """Drop (set to None) highlights far dimmer than the typical one; return their problems."""
    problems: list[tuple[int, str]] = []
    contrasts = np.array([hl.contrast for hl in found if hl is not None])
    if not len(contrasts):
        return problems
    typical = float(np.median(contrasts))
    for j, hl in enumerate(found):
        if hl is not None and hl.contrast < 0.05 * typical:
            found[j] = None
            problems.append(
                (
                    j,
                    f"no highlight: its peak is {hl.contrast / typical:.1%} of the typical "
                    "highlight "
                    "(light off or blocked?)",
                )
            )
    return problems


def _second_blob_warnings(found: list[Highlight], names: Sequence[str] | None) -> list[str]:
    warnings = []
    for j, hl in enumerate(found):
        if hl.second_blob is not None:
            sx, sy, share = hl.second_blob
            warnings.append(
                f"{_frame_label(j, names)}: second bright spot at ({sx:.1f}, {sy:.1f}) "
                f"with {share:.0%} "
                "of the highlight's energy ignored (inter-reflection?)"
            )
    return warnings


def _matte_intensities(
    stack: np.ndarray,
    summary: np.ndarray,
    directions: np.ndarray,
    saturated: np.ndarray | None,
    matte_sphere: Sequence[float] | None,
    matte_hint: Sequence[float] | None,
    warnings: list[str],
    light_positions: np.ndarray | None = None,
    anisotropy: float = 0.0,
) -> tuple[Circle | None, np.ndarray]:
    """The matte sphere's circle and the lights' relative intensities (ones without a sphere)."""
    n, h, w, _ = stack.shape
    if matte_sphere is None and matte_hint is None:
        return None, np.ones((n, 3))
    if matte_sphere is not None:
        matte_circle = Circle(*map(float, matte_sphere))
    else:
        hint = Circle(*map(float, matte_hint))  # type: ignore[arg-type]
        try:
            # A matte sphere's limb is dim in the median (grazing shading); the maximum over
            # frames shows it as a step.
            bright = summary_image(stack, reduce="max")
            search = max(8.0, 0.15 * hint.radius)
            matte_circle = refine_circle(bright, hint, search_px=search).circle
        except CalibrationError as exc:
            warnings.append(
                f"matte sphere outline not refined ({exc}); using the rig's nominal circle"
            )
            matte_circle = hint
    if not circle_inside_image(matte_circle, (h, w), margin=0.0):
        raise CalibrationError(
            f"matte sphere at ({matte_circle.x:.1f}, {matte_circle.y:.1f}) "
            f"r={matte_circle.radius:.1f} "
            "is cut by the image border"
        )
    intensities, extra = fit_light_intensities(
        stack,
        directions,
        matte_circle,
        saturated=saturated,
        light_positions=light_positions,
        anisotropy=anisotropy,
    )
    warnings.extend(extra)
    return matte_circle, intensities


def _preview(stack: np.ndarray, circle: Circle) -> tuple[np.ndarray, tuple[int, int]]:
    """The brightest value over frames around the chrome sphere (for calibration.png)."""
    n, h, w, _ = stack.shape
    pad = int(np.ceil(0.15 * circle.radius)) + 4
    x0, x1 = (
        max(0, int(circle.x - circle.radius) - pad),
        min(w, int(circle.x + circle.radius) + pad + 1),
    )
    y0, y1 = (
        max(0, int(circle.y - circle.radius) - pad),
        min(h, int(circle.y + circle.radius) + pad + 1),
    )
    preview = np.max(
        [_frame_luma(stack, j, slice(y0, y1), slice(x0, x1)) for j in range(n)], axis=0
    )
    return preview, (x0, y0)
