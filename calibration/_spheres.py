"""Which circles are the chrome spheres: found, refined from the rig's hints, or given.

The automatic search (:func:`ps_lab.calibration._circle.circle_candidates`) proposes circular
outlines; each is refined to sub-pixel on the limb and kept when it is seen nearly all round and
shows one small, strong highlight in most frames (:func:`chrome_score`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ps_lab.calibration._circle import (
    Circle,
    CircleFit,
    _edge_points,
    circle_candidates,
    circle_inside_image,
    refine_circle,
)
from ps_lab.errors import CalibrationError


def circle_residual(summary: np.ndarray, circle: Circle) -> float:
    """RMS distance (px) of sub-pixel limb points from ``circle`` (NaN when no limb is visible)."""
    pts, contrast = _edge_points(np.asarray(summary, dtype=np.float32), circle, half_width=4.0)
    ok = np.isfinite(contrast)
    if ok.sum() < 12:
        return float("nan")
    res = np.hypot(pts[ok, 0] - circle.x, pts[ok, 1] - circle.y) - circle.radius
    med = np.median(res)
    keep = np.abs(res - med) <= max(3 * 1.4826 * np.median(np.abs(res - med)), 0.05)
    return float(np.sqrt(np.mean(res[keep] ** 2)))


def chrome_score(images: np.ndarray, circle: Circle, *, max_frames: int = 12) -> float:
    """Share of frames in which the disc shows one small, strong highlight (chrome), 0..1.

    A matte sphere's shading covers a large part of the disc; a chrome sphere's highlight a
    tiny one.

    Parameters
    ----------
    images : ndarray of shape (n, H, W) or (n, H, W, C)
        Linear frames (channels are averaged).
    circle : Circle
        Candidate outline.
    max_frames : int
        Frames looked at (evenly spaced).

    Returns
    -------
    float
    """
    n, h, w = images.shape[:3]
    idx = np.linspace(0, n - 1, min(n, max_frames)).round().astype(int)
    cx, cy, r = circle
    x0, x1 = max(0, int(cx - r)), min(w, int(np.ceil(cx + r)) + 1)
    y0, y1 = max(0, int(cy - r)), min(h, int(np.ceil(cy + r)) + 1)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return 0.0
    yy, xx = np.mgrid[y0:y1, x0:x1]
    disc = np.hypot(xx - cx, yy - cy) <= 0.9 * r
    if disc.sum() < 20:
        return 0.0
    good = 0
    for k in idx:
        crop = np.asarray(images[k, y0:y1, x0:x1], dtype=np.float64)
        v = (crop.mean(axis=-1) if crop.ndim == 3 else crop)[disc]
        med = np.median(v)
        sigma = 1.4826 * np.median(np.abs(v - med))
        peak = v.max()
        if peak - med <= max(10 * sigma, 1e-12):
            continue
        share = np.mean(v >= med + 0.5 * (peak - med))
        good += share < 0.03
    return good / len(idx)


def _find_sphere(
    summary: np.ndarray, stack: np.ndarray, roi: tuple[int, int, int, int] | None
) -> tuple[CircleFit, float]:
    """The best chrome sphere of the automatic search and its chrome score."""
    return _find_spheres(summary, stack, roi)[0]


def _find_spheres(
    summary: np.ndarray, stack: np.ndarray, roi: tuple[int, int, int, int] | None
) -> list[tuple[CircleFit, float]]:
    """Every distinct chrome sphere of the automatic search, best (score, coverage) first."""
    h, w = summary.shape
    ox, oy = 0, 0
    sub = summary
    if roi is not None:
        x, y, rw, rh = roi
        if rw < 8 or rh < 8 or x < 0 or y < 0 or x + rw > w or y + rh > h:
            raise CalibrationError(f"--roi {x},{y},{rw},{rh} does not fit in the {w}x{h} image")
        sub = summary[y : y + rh, x : x + rw]
        ox, oy = x, y
    candidates = circle_candidates(sub)
    if not candidates:
        raise CalibrationError(
            "no chrome sphere found: no circular outline in the images "
            "(pass --sphere CX,CY,R or --roi)"
        )
    found: list[tuple[float, float, CircleFit]] = []
    for cand in candidates:
        start = Circle(cand.x + ox, cand.y + oy, cand.radius)
        try:
            fit = refine_circle(summary, start)
        except CalibrationError:
            continue
        # The limb of the real sphere is seen nearly all round; a spurious circle (noise, a
        # circle through the highlights) collects edge points on a small part of its outline.
        if fit.coverage < 0.5:
            continue
        score = chrome_score(stack, fit.circle)
        if score < 0.5:
            continue
        found.append((score, fit.coverage, fit))
    if not found:
        raise CalibrationError(
            f"no chrome sphere found: {len(candidates)} circular outline(s) checked, none shows a "
            "single small highlight in most frames (pass --sphere CX,CY,R or --roi)"
        )
    found.sort(key=lambda item: item[:2], reverse=True)
    distinct: list[tuple[CircleFit, float]] = []
    for score, _, fit in found:
        c = fit.circle
        # candidates of one sphere refine to (nearly) the same circle
        if all(np.hypot(c.x - o.circle.x, c.y - o.circle.y) > 0.5 * c.radius for o, _ in distinct):
            distinct.append((fit, score))
    return distinct


def chrome_sphere(
    summary: np.ndarray,
    stack: np.ndarray,
    sphere: Sequence[float] | None,
    sphere_hint: Sequence[float] | None,
    roi: Sequence[int] | None,
    warnings: list[str],
) -> tuple[Circle, float, str]:
    """The chrome sphere's circle, its outline residual and where it came from.

    Given (``sphere``), else the rig's nominal circle refined and confirmed (``sphere_hint``),
    else found automatically; then checked to be large enough and inside the image.
    """
    if sphere is not None:
        circle = Circle(*map(float, sphere))
        residual, source = circle_residual(summary, circle), "given"
    else:
        fit = None if sphere_hint is None else _confirm_hint(summary, stack, sphere_hint, warnings)
        source = "rig"
        if fit is None:
            fit, _ = _find_sphere(summary, stack, roi)
            source = "auto"
        circle, residual = fit.circle, fit.residual
    h, w = summary.shape[:2]
    if circle.radius <= 3:
        raise CalibrationError(f"chrome sphere radius {circle.radius:.1f} px is too small")
    if not circle_inside_image(circle, (h, w)):
        raise CalibrationError(
            f"chrome sphere at ({circle.x:.1f}, {circle.y:.1f}) r={circle.radius:.1f} "
            f"is cut by the image border ({w}x{h}): move it fully into view"
        )
    if np.isfinite(residual) and residual > 0.5:
        warnings.append(
            f"sphere outline residual {residual:.2f} px is large: check calibration.png"
        )
    return circle, residual, source


def other_spheres(
    summary: np.ndarray,
    stack: np.ndarray,
    first: Circle,
    source: str,
    given: Sequence[Sequence[float]],
    hints: Sequence[Sequence[float]],
    roi: Sequence[int] | None,
    warnings: list[str],
) -> list[Circle]:
    """The chrome spheres beyond the first: given, refined from hints, or found automatically."""
    others = [chrome_sphere(summary, stack, c, None, None, warnings)[0] for c in given]
    for number, hint in enumerate(hints, start=2):
        # An extra sphere of the rig must be where the rig says: a search would find the first.
        if _confirm_hint(summary, stack, hint, []) is None:
            raise missing_rig_sphere(number, hint)
        others.append(chrome_sphere(summary, stack, None, hint, None, warnings)[0])
    if source == "auto" and not given and not hints:
        fits = _find_spheres(summary, stack, None if roi is None else tuple(roi))
        others = [f.circle for f, _ in fits[1:] if circle_inside_image(f.circle, summary.shape)]
    for c in others:
        if np.hypot(c.x - first.x, c.y - first.y) < first.radius + c.radius:
            who = "--sphere: " if given or source == "given" else ""
            raise CalibrationError(
                f"{who}chrome spheres at ({first.x:.1f}, {first.y:.1f}) and ({c.x:.1f}, "
                f"{c.y:.1f}) overlap: give each sphere once"
            )
    return others


def missing_rig_sphere(number: int, hint: Sequence[float]) -> CalibrationError:
    """The error for the rig's chrome sphere ``number`` (1-based) not found where the rig says."""
    x, y, r = (float(v) for v in hint)
    return CalibrationError(
        f"the rig's chrome sphere {number} (calibration.chrome_spheres in manifest.json) at "
        f"({x:.1f}, {y:.1f}) r={r:.1f} is not in the images (no outline with highlights "
        "there); give the chrome spheres in view with --sphere CX,CY,R, once each"
    )


def given_sphere_without_highlights(circle: Circle) -> CalibrationError:
    """The error for a ``--sphere`` circle in which most frames show no chrome highlight."""
    return CalibrationError(
        f"--sphere {circle.x:g},{circle.y:g},{circle.radius:g}: no chrome sphere there (most "
        "frames show no highlight inside the circle); check the circle (x = column, y = row, "
        "pixels) or leave --sphere out to search"
    )


def _confirm_hint(
    summary: np.ndarray, stack: np.ndarray, sphere_hint: Sequence[float], warnings: list[str]
):
    """The rig's nominal chrome sphere refined on the images, or None (with a warning)."""
    hint = Circle(*map(float, sphere_hint))
    try:
        fit = refine_circle(summary, hint, search_px=max(8.0, 0.15 * hint.radius))
        if fit.coverage < 0.5 or chrome_score(stack, fit.circle) < 0.5:
            raise CalibrationError(
                f"no chrome sphere outline with highlights near ({hint.x:.1f}, "
                f"{hint.y:.1f}) r={hint.radius:.1f}"
            )
    except CalibrationError as exc:
        warnings.append(f"rig's nominal chrome sphere not confirmed ({exc}); searching")
        return None
    if (
        np.hypot(fit.circle.x - hint.x, fit.circle.y - hint.y) > 0.1 * hint.radius
        or abs(fit.circle.radius - hint.radius) > 0.1 * hint.radius
    ):
        warnings.append(
            f"chrome sphere fitted at ({fit.circle.x:.1f}, {fit.circle.y:.1f}) "
            f"r={fit.circle.radius:.1f}, far from the rig's nominal "
            f"({hint.x:.1f}, {hint.y:.1f}) r={hint.radius:.1f}"
        )
    return fit
