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
    consensus_circle,
    refine_circle,
    summary_image,
)
from ps_lab.errors import CalibrationError


def circle_residual(summary: np.ndarray, circle: Circle, *, with_points: bool = False):
    """RMS distance (px) of sub-pixel limb points from ``circle`` (NaN when no limb is visible).

    With ``with_points`` also the limb points measured, ``(m, 2)``.
    """
    pts, contrast = _edge_points(np.asarray(summary, dtype=np.float32), circle, half_width=4.0)
    ok = np.isfinite(contrast)
    if ok.sum() < 12:
        return (float("nan"), np.empty((0, 2))) if with_points else float("nan")
    res = np.hypot(pts[ok, 0] - circle.x, pts[ok, 1] - circle.y) - circle.radius
    med = np.median(res)
    keep = np.abs(res - med) <= max(3 * 1.4826 * np.median(np.abs(res - med)), 0.05)
    value = float(np.sqrt(np.mean(res[keep] ** 2)))
    return (value, pts[ok][keep]) if with_points else value


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


# An outline fitted with a larger RMS residual than this is not one clean circle (a stand, a
# holder, reflections of the room at the limb): the part that is one circle is fitted instead.
CLEAN_RESIDUAL_PX = 0.5


class LimbImages:
    """The images a sphere's limb is fitted on: the frames' median (and, lazily, maximum), or
    an outline frame taken with room light.

    Parameters
    ----------
    summary : ndarray of shape (H, W)
        Per-pixel median of the frames (:func:`summary_image`), or the outline frame.
    stack : ndarray of shape (n, H, W, C), optional
        The frames, for the per-pixel maximum (None with an outline frame).
    """

    def __init__(self, summary: np.ndarray, stack: np.ndarray | None = None) -> None:
        self.summary = summary
        self._stack = stack
        self._maximum: np.ndarray | None = None

    def images(self) -> list[np.ndarray]:
        """The median first, then the maximum over frames (where the rig's lights may catch
        the limb the median misses)."""
        if self._stack is None:
            return [self.summary]
        if self._maximum is None:
            self._maximum = summary_image(self._stack, reduce="max")
        return [self.summary, self._maximum]


def fit_limb(limb: LimbImages, fit: CircleFit) -> CircleFit:
    """``fit`` when it is one clean circle, else the consensus fit of the part that is.

    The consensus (:func:`consensus_circle`) is tried on each limb image; the one on which the
    larger share of the outline agrees with one circle wins.
    """
    if not np.isfinite(fit.residual) or fit.residual <= CLEAN_RESIDUAL_PX:
        return fit
    best = fit
    best_cover = -1.0
    for image in limb.images():
        try:
            candidate = consensus_circle(image, fit.circle)
        except CalibrationError:
            continue
        if candidate.coverage > best_cover:
            best, best_cover = candidate, candidate.coverage
    return best


def _find_sphere(
    limb: LimbImages, stack: np.ndarray, roi: tuple[int, int, int, int] | None
) -> tuple[CircleFit, float]:
    """The best chrome sphere of the automatic search and its chrome score."""
    return _find_spheres(limb, stack, roi)[0]


def _find_spheres(
    limb: LimbImages, stack: np.ndarray, roi: tuple[int, int, int, int] | None
) -> list[tuple[CircleFit, float]]:
    """Every distinct chrome sphere of the automatic search, best (score, coverage) first.

    Circles nested in a better one (around a star-shaped highlight, a reflection inside the
    sphere) and circles overlapping a better one are dropped: spheres at one depth never
    overlap in the image.
    """
    summary = limb.summary
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
        found.append((score, fit.coverage, fit_limb(limb, fit)))
    if not found:
        raise CalibrationError(
            f"no chrome sphere found: {len(candidates)} circular outline(s) checked, none shows a "
            "single small highlight in most frames (pass --sphere CX,CY,R or --roi)"
        )
    found.sort(key=lambda item: item[:2], reverse=True)
    distinct: list[tuple[CircleFit, float]] = []
    for score, _, fit in found:
        c = fit.circle
        inside = [i for i, (o, _) in enumerate(distinct) if _nested(o.circle, c)]
        if inside:
            # A chrome sphere holding circles already kept (found around its highlights or
            # reflections): the sphere replaces them.
            for i in reversed(inside):
                del distinct[i]
            distinct.insert(inside[0], (fit, score))
            continue
        if all(not _overlap(c, o.circle) for o, _ in distinct):
            distinct.append((fit, score))
    return distinct


def _nested(inner: Circle, outer: Circle) -> bool:
    """Whether ``inner`` lies inside ``outer`` (2 % of the outer radius to spare)."""
    return (
        outer.radius > inner.radius
        and np.hypot(inner.x - outer.x, inner.y - outer.y) + inner.radius <= 1.02 * outer.radius
    )


def _overlap(a: Circle, b: Circle) -> bool:
    return bool(np.hypot(a.x - b.x, a.y - b.y) < 0.98 * (a.radius + b.radius))


def chrome_sphere(
    limb: LimbImages,
    stack: np.ndarray,
    sphere: Sequence[float] | None,
    sphere_hint: Sequence[float] | None,
    roi: Sequence[int] | None,
    warnings: list[str],
) -> tuple[Circle, float, str, np.ndarray]:
    """The chrome sphere's circle, its outline residual, where it came from, the limb points.

    Given (``sphere``), else the rig's nominal circle refined and confirmed (``sphere_hint``),
    else found automatically; then checked to be large enough and inside the image. The limb
    points ``(m, 2)`` are the edge points the circle was fitted to (or measured against).
    """
    summary = limb.summary
    if sphere is not None:
        circle = Circle(*map(float, sphere))
        residual, points = circle_residual(summary, circle, with_points=True)
        source = "given"
    else:
        fit = None if sphere_hint is None else _confirm_hint(limb, stack, sphere_hint, warnings)
        source = "rig"
        if fit is None:
            fit, _ = _find_sphere(limb, stack, roi)
            source = "auto"
        circle, residual, points = fit.circle, fit.residual, fit.edge_points
        if fit.coverage < 0.8:
            warnings.append(
                f"sphere outline: {fit.coverage:.0%} of it is one clean circle (a stand, a "
                "holder or reflections hide the rest); the fit uses that part: check "
                "calibration.png (cyan)"
            )
    h, w = summary.shape[:2]
    if circle.radius <= 3:
        raise CalibrationError(f"chrome sphere radius {circle.radius:.1f} px is too small")
    if not circle_inside_image(circle, (h, w)):
        raise CalibrationError(
            f"chrome sphere at ({circle.x:.1f}, {circle.y:.1f}) r={circle.radius:.1f} "
            f"is cut by the image border ({w}x{h}): move it fully into view"
        )
    if np.isfinite(residual) and residual > 2 * CLEAN_RESIDUAL_PX:
        warnings.append(
            f"sphere outline residual {residual:.2f} px is large: check calibration.png"
        )
    return circle, residual, source, points


def other_spheres(
    limb: LimbImages,
    stack: np.ndarray,
    first: Circle,
    source: str,
    given: Sequence[Sequence[float]],
    hints: Sequence[Sequence[float]],
    roi: Sequence[int] | None,
    warnings: list[str],
) -> list[tuple[Circle, np.ndarray]]:
    """The chrome spheres beyond the first (circle, limb points): given, refined from hints,
    or found automatically (nested and overlapping circles dropped)."""
    others = [chrome_sphere(limb, stack, c, None, None, warnings) for c in given]
    for number, hint in enumerate(hints, start=2):
        # An extra sphere of the rig must be where the rig says: a search would find the first.
        if _confirm_hint(limb, stack, hint, []) is None:
            raise missing_rig_sphere(number, hint)
        others.append(chrome_sphere(limb, stack, None, hint, None, warnings))
    found = [(c, pts) for c, _, _, pts in others]
    if source == "auto" and not given and not hints:
        fits = _find_spheres(limb, stack, None if roi is None else tuple(roi))
        found = [
            (f.circle, f.edge_points)
            for f, _ in fits[1:]
            if circle_inside_image(f.circle, limb.summary.shape) and not _overlap(f.circle, first)
        ]
    for c, _ in found:
        if np.hypot(c.x - first.x, c.y - first.y) < first.radius + c.radius:
            who = "--sphere: " if given or source == "given" else ""
            raise CalibrationError(
                f"{who}chrome spheres at ({first.x:.1f}, {first.y:.1f}) and ({c.x:.1f}, "
                f"{c.y:.1f}) overlap: give each sphere once"
            )
    return found


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
    limb: LimbImages, stack: np.ndarray, sphere_hint: Sequence[float], warnings: list[str]
):
    """The rig's nominal chrome sphere refined on the images, or None (with a warning)."""
    hint = Circle(*map(float, sphere_hint))
    try:
        fit = refine_circle(limb.summary, hint, search_px=max(8.0, 0.15 * hint.radius))
        if fit.coverage < 0.5 or chrome_score(stack, fit.circle) < 0.5:
            raise CalibrationError(
                f"no chrome sphere outline with highlights near ({hint.x:.1f}, "
                f"{hint.y:.1f}) r={hint.radius:.1f}"
            )
    except CalibrationError as exc:
        warnings.append(f"rig's nominal chrome sphere not confirmed ({exc}); searching")
        return None
    fit = fit_limb(limb, fit)
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
