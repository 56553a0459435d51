"""Locating the specular highlight of one light on the chrome sphere, to sub-pixel accuracy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ps_lab.calibration._circle import Circle
from ps_lab.errors import CalibrationError


@dataclass(frozen=True)
class Highlight:
    """One frame's highlight.

    Attributes
    ----------
    x, y : float
        Sub-pixel position (pixel coordinates), corrected for the extended-source bias.
    contrast : float
        Peak minus the sphere's median level (same units as the frame).
    area : int
        Pixels of the highlight blob (at half of the peak contrast).
    saturated : bool
        Whether the blob contains saturated pixels.
    source_radius_deg : float
        Angular radius of the light estimated from the blob's second moments (0 when unresolved).
    second_blob : tuple of (x, y, share) or None
        The strongest rejected secondary blob (inter-reflection) and its energy relative to the
        highlight.
    estimator : str
        ``"centroid"`` (weighted centroid of the half-peak blob) or ``"core"`` (a streaked
        blob, whose centroid lies more than ``STREAK_OFFSET_PX`` from its core: the centroid
        of the core above 0.9 of the peak contrast, its streaks opened away).
    uncertainty_px : float
        Standard uncertainty of the position (pixels): the noise propagated through the
        centroid and its spread over nearby thresholds, whichever is larger.

    """

    x: float
    y: float
    contrast: float
    area: int
    saturated: bool
    source_radius_deg: float
    second_blob: tuple[float, float, float] | None
    estimator: str = "centroid"
    uncertainty_px: float = 0.0


_EIGHT = np.ones((3, 3), dtype=bool)


def locate_highlight(
    frame: np.ndarray,
    circle: Circle,
    *,
    saturated: np.ndarray | None = None,
    safe_radius: float = 0.9,
    min_snr: float = 10.0,
    max_saturated_share: float = 0.2,
) -> Highlight:
    """Find the mirror highlight of one light inside the chrome sphere.

    The highlight is the blob above half of the peak contrast (8-connected) with the most energy;
    its position is the centroid of (value − sphere level) over the blob grown by 2 px, which keeps
    the anti-aliased fringe and is unbiased for a blob that is symmetric before sampling. The
    image of a light of angular radius ``a`` is the orthographic projection of a spherical cap of
    normals of half-angle ``b = a / 2``; the area-weighted centroid of that projection lies at
    ``cos(b)`` times the projected cap centre (exact), which is corrected here with ``b`` from the
    blob's second moments.

    Parameters
    ----------
    frame : ndarray of shape (H, W)
        Linear luminance of one frame.
    circle : Circle
        The chrome sphere's outline.
    saturated : ndarray of shape (H, W), bool, optional
        Clipped pixels; they are treated as a plateau at the frame's maximum.
    safe_radius : float
        Highlights farther than ``safe_radius * radius`` from the centre are rejected (the light is
        nearly behind the sphere, where the normal, hence the direction, is ill-conditioned).
    min_snr : float
        Peak contrast must exceed this many noise sigmas.
    max_saturated_share : float
        Frames with more than this share of the sphere saturated are rejected.

    Returns
    -------
    Highlight

    Raises
    ------
    CalibrationError
        No highlight, highlight outside the safe radius, or the sphere saturated.

    """
    # One pass over one frame (~85 lines): the blob, its centroid and the checks share the
    # same local arrays; the steps are the docstring's, in order.
    h, w = frame.shape
    cx, cy, r = circle
    x0, x1 = max(0, int(np.floor(cx - r)) - 1), min(w, int(np.ceil(cx + r)) + 2)
    y0, y1 = max(0, int(np.floor(cy - r)) - 1), min(h, int(np.ceil(cy + r)) + 2)
    img = np.asarray(frame[y0:y1, x0:x1], dtype=np.float64)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    dist = np.hypot(xx - cx, yy - cy)
    # Stay clear of the anti-aliased limb; the safe radius is checked on the result.
    disc = dist <= r - 1.5
    if disc.sum() < 20:
        raise CalibrationError(f"sphere radius {r:.1f} px is too small to locate highlights")
    sat = None
    if saturated is not None:
        sat = np.asarray(saturated[y0:y1, x0:x1], dtype=bool) & (dist <= r)
        share = sat.sum() / max(1, (dist <= r).sum())
        if share > max_saturated_share:
            raise CalibrationError(
                f"{100 * share:.0f}% of the chrome sphere is saturated: shorten the exposure or "
                "dim the light"
            )
        # Clipped pixels keep their values: with 2x2 binned RAW a block is flagged when any one
        # photosite clipped, and its binned value still measures how much of it is lit.
    values = img[disc]
    level = float(np.median(values))
    sigma = float(1.4826 * np.median(np.abs(values - level)))
    peak = float(values.max())
    contrast = peak - level
    floor = max(min_snr * sigma, 1e-6 * max(abs(peak), 1e-30))
    if not np.isfinite(contrast) or contrast <= floor:
        raise CalibrationError(
            f"no highlight on the chrome sphere (peak {contrast:.3g} above the sphere level, "
            f"noise {sigma:.2g}): is the light on and in front of the sphere?"
        )
    blobs = disc & (img >= level + 0.5 * contrast)
    labels, count = ndimage.label(blobs, structure=_EIGHT)
    weight = img - level
    energy = ndimage.sum_labels(np.clip(weight, 0, None), labels, index=np.arange(1, count + 1))
    order = np.argsort(energy)[::-1]
    main = order[0] + 1
    blob = labels == main
    second = None
    if count > 1:
        j = order[1] + 1
        share = float(energy[order[1]] / energy[order[0]])
        if share >= 0.02:
            sy, sx = ndimage.center_of_mass(np.clip(weight, 0, None) * (labels == j))
            second = (float(sx + x0), float(sy + y0), share)
    # Grow by 2 px for the anti-aliased fringe, but never into another blob.
    window = ndimage.binary_dilation(blob, structure=_EIGHT, iterations=2) & (dist <= r - 0.5)
    window &= (labels == 0) | blob
    wts = weight[window]
    total = wts.sum()
    mx = float((wts * xx[window]).sum() / total)
    my = float((wts * yy[window]).sum() / total)
    # Extended source: second moments of the blob give the cap half-angle b (tangential
    # semi-axis a = r sin b of a uniform ellipse, variance a^2 / 4; minus the pixel box 1/12).
    dxw, dyw = xx[window] - mx, yy[window] - my
    cov = (
        np.array(
            [
                [np.sum(wts * dxw * dxw), np.sum(wts * dxw * dyw)],
                [np.sum(wts * dxw * dyw), np.sum(wts * dyw * dyw)],
            ]
        )
        / total
    )
    lam = float(np.linalg.eigvalsh(cov)[-1])
    sin_b = np.sqrt(max(4.0 * (lam - 1.0 / 12.0), 0.0)) / r
    cos_b = np.sqrt(max(1.0 - min(sin_b, 1.0) ** 2, 1e-6))
    estimator = "centroid"
    spread = _threshold_spread(img, level, contrast, disc, (0.4, 0.5, 0.6), xx, yy)
    core = _core_centroid(img, level, contrast, blob, xx, yy, 0.9)
    if core is not None:
        offset = float(np.hypot(core[0] - mx, core[1] - my))
        if offset > STREAK_OFFSET_PX:
            estimator = "core"
            mx, my, lam = core
            # The core is the (clipped) cap's image: the same cos(b) bias as the centroid, b
            # from the core's tangential extent (the streaks would inflate the blob's).
            sin_b = np.sqrt(max(4.0 * (lam - 1.0 / 12.0), 0.0)) / r
            cos_b = np.sqrt(max(1.0 - min(sin_b, 1.0) ** 2, 1e-6))
            spread = _core_spread(img, level, contrast, blob, xx, yy)
    noise_px = sigma * np.sqrt(np.sum(dxw * dxw + dyw * dyw)) / max(total, 1e-30)
    hx, hy = cx + (mx - cx) / cos_b, cy + (my - cy) / cos_b
    rel = np.hypot(hx - cx, hy - cy) / r
    if rel > safe_radius:
        raise CalibrationError(
            f"highlight at {rel:.2f} of the radius lies outside the safe radius {safe_radius:.2f} "
            "(light nearly behind the sphere)"
        )
    return Highlight(
        x=float(hx),
        y=float(hy),
        contrast=contrast,
        area=int(blob.sum()),
        saturated=bool(sat is not None and (sat & blob).any()),
        source_radius_deg=float(2.0 * np.degrees(np.arcsin(min(sin_b, 1.0)))),
        second_blob=second,
        estimator=estimator,
        uncertainty_px=float(max(noise_px, spread)),
    )


# A streaked highlight (scratches, star-shaped diffraction spikes, an asymmetric flare) pulls
# the half-peak centroid away from the bright core; on compact blobs (rendered discs, 40-150 px
# spheres, peaks 0.8x-20x white) the two agree within 0.6 px. Beyond this offset the core is used.
STREAK_OFFSET_PX = 1.0
def _disc(radius: float) -> np.ndarray:
    r = max(1, int(round(radius)))
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    return x * x + y * y <= r * r + 0.5


def _core_centroid(
    img: np.ndarray,
    level: float,
    contrast: float,
    blob: np.ndarray,
    xx: np.ndarray,
    yy: np.ndarray,
    share: float,
) -> tuple[float, float, float] | None:
    """Centroid ``(x, y)`` and largest second moment of the highlight's core.

    The core is the blob above ``share`` of the peak contrast, opened by a disc of half its
    inscribed radius, the piece holding the widest point (unweighted: a clipped core is a
    plateau).
    """
    core = blob & (img >= level + share * contrast)
    if not core.any():
        return None
    dist = ndimage.distance_transform_edt(np.pad(core, 1))[1:-1, 1:-1]
    widest = np.unravel_index(int(np.argmax(dist)), dist.shape)
    if dist[widest] >= 2.0:
        opened = ndimage.binary_opening(core, structure=_disc(0.5 * dist[widest]))
        labels, _ = ndimage.label(opened, structure=_EIGHT)
        if labels[widest]:
            core = labels == labels[widest]
    x, y = xx[core].astype(np.float64), yy[core].astype(np.float64)
    lam = float(np.linalg.eigvalsh(np.cov(np.vstack([x, y]), bias=True))[-1]) if len(x) > 1 else 0
    return float(x.mean()), float(y.mean()), lam


def _core_spread(img, level, contrast, blob, xx, yy) -> float:
    found = [_core_centroid(img, level, contrast, blob, xx, yy, s) for s in (0.8, 0.9, 0.95)]
    pts = np.array([p[:2] for p in found if p is not None])
    return float(0.5 * np.hypot(*np.ptp(pts, axis=0))) if len(pts) > 1 else 0.0


def _threshold_spread(img, level, contrast, disc, shares, xx, yy) -> float:
    """Half the spread of the weighted blob centroid over thresholds (a sensitivity measure)."""
    pts = []
    for share in shares:
        labels, count = ndimage.label(disc & (img >= level + share * contrast), structure=_EIGHT)
        if not count:
            continue
        w = np.clip(img - level, 0, None)
        energy = ndimage.sum_labels(w, labels, index=np.arange(1, count + 1))
        sel = labels == int(np.argmax(energy)) + 1
        top = energy.max()
        pts.append((np.sum(w[sel] * xx[sel]) / top, np.sum(w[sel] * yy[sel]) / top))
    pts = np.array(pts)
    return float(0.5 * np.hypot(*np.ptp(pts, axis=0))) if len(pts) > 1 else 0.0
