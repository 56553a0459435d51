"""Locating the specular highlight of one light on the chrome sphere, to sub-pixel accuracy."""

from __future__ import annotations

from dataclasses import dataclass, replace

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
        Angular radius of the light estimated from the blob's second moments (0 when unresolved;
        NaN when the highlight lies too near the sphere's centre to tell the source from the blur:
        :func:`share_source_radius` then gives it the other frames' median).
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
    centroid : (float, float)
        The blob's weighted centroid before the extended-source correction.

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
    centroid: tuple[float, float] = (float("nan"), float("nan"))


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
    the anti-aliased fringe and is unbiased for a blob that is symmetric before sampling (a
    symmetric blur moves no centroid). A light of angular radius ``a`` images as the mirror map
    of a cap of directions; the map keeps areas, so the centroid is the cap's mean image position,
    pulled toward the centre by about ``rho a^2 / 8`` (:func:`_corrected`, to second order in
    ``a``). ``a`` comes from the blob's second moments, the blur's part taken out: the blur widens
    the blob alike in every direction, the mirror stretches the cap tangentially over radially by
    ``1 / cos^2(theta)`` (:func:`_source_radius`). The former isotropic estimate read the blur as
    source size and over-corrected: +0.012 px outward on a 40 px sphere, 0.13 % / 0.34 % (mean /
    worst) of the dome radius in LED positions, 4x the uncorrected centroid's (docs/solvers.md,
    "Near lights").

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
    source = _source_radius(cov, mx - cx, my - cy, r)
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
            sin_b = float(np.sqrt(max(4.0 * (lam - 1.0 / 12.0), 0.0)) / r)
            source = 2.0 * float(np.arcsin(min(sin_b, 1.0)))
            spread = _core_spread(img, level, contrast, blob, xx, yy)
    noise_px = sigma * np.sqrt(np.sum(dxw * dxw + dyw * dyw)) / max(total, 1e-30)
    hx, hy = _corrected(mx, my, circle, source if np.isfinite(source) else 0.0)
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
        source_radius_deg=float(np.degrees(source)),
        centroid=(mx, my),
        second_blob=second,
        estimator=estimator,
        uncertainty_px=float(max(noise_px, spread)),
    )


# A streaked highlight (scratches, star-shaped diffraction spikes, an asymmetric flare) pulls
# the half-peak centroid away from the bright core; on compact blobs (rendered discs, 40-150 px
# spheres, peaks 0.8x-20x white) the two agree within 0.6 px. Beyond this offset the core is used.
STREAK_OFFSET_PX = 1.0
# Below this sin^2 of the normal's angle from the view the cap's foreshortening is too small to
# tell it from the blur (theta < 26.6 deg, 1 - cos(theta) < 0.11): the source radius is left to
# the other frames.
MIN_SIN2_THETA = 0.2


def _source_radius(cov: np.ndarray, dx: float, dy: float, r: float) -> float:
    """Angular radius ``a`` (radians) of the light whose highlight has covariance ``cov``, or NaN.

    ``(dx, dy)``: the centroid's offset from the sphere's centre (pixels), at the normal's angle
    ``theta`` from the view. The mirror maps a direction cap of radius ``a`` to an ellipse of
    semi-axes ``a r / (2 cos theta)`` (tangential) and ``a r cos(theta) / 2`` (radial). The blur
    widens both alike: by a constant width where the highlight is clipped to a plateau, so the
    standard deviations' difference ``(a r / 4)(1 / cos theta - cos theta)`` is kept exactly; by
    a constant variance where it is not, so the difference shrinks and ``a`` errs small (where
    the blur dominates the blob, the source is small).
    """
    rho2 = dx * dx + dy * dy
    sin2 = rho2 / (r * r)
    if sin2 < MIN_SIN2_THETA or sin2 >= 1.0:
        return float("nan")
    e = np.array([dx, dy]) / np.sqrt(rho2)
    t = np.array([-e[1], e[0]])
    sd_r = np.sqrt(max(float(e @ cov @ e), 0.0))
    sd_t = np.sqrt(max(float(t @ cov @ t), 0.0))
    cos_theta = np.sqrt(1.0 - sin2)
    return float(4.0 * max(sd_t - sd_r, 0.0) / (r * (1.0 / cos_theta - cos_theta)))


def _corrected(mx: float, my: float, circle: Circle, source: float) -> tuple[float, float]:
    """The mirror point of a light of angular radius ``source`` whose blob centroid is (mx, my).

    The mirror maps directions to the image with constant area (``dA / dOmega = r^2 / 4``), so
    the blob's centroid is the mean of the image position ``f`` over the source's cap of
    directions: ``f + (a^2 / 8) lap f`` to second order, where for ``f`` the radial image
    coordinate ``rho = r sin(theta)`` (reflected direction at ``2 theta`` from the view)
    ``lap f = r (1 - 3 sin^2 theta - 1 / cos^2 theta) / (4 sin theta)`` (``-rho`` near the
    centre: the ``cos(a / 2)`` shrink of a cap of normals).
    """
    cx, cy, r = circle
    rho = float(np.hypot(mx - cx, my - cy))
    if source <= 0 or rho <= 0:
        return mx, my
    s = min(rho / r, 0.999)
    lap = r * (1.0 - 3.0 * s * s - 1.0 / (1.0 - s * s)) / (4.0 * s)
    scale = (rho - source * source / 8.0 * lap) / rho
    return cx + (mx - cx) * scale, cy + (my - cy) * scale


def share_source_radius(found: list[Highlight], circle: Circle) -> list[Highlight]:
    """Highlights whose source radius is unresolved (NaN) get the median of the others.

    The lights of one rig are alike in angular size; a highlight near the sphere's centre cannot
    measure it (see :func:`_source_radius`) but needs little correction (about
    ``rho a^2 / 8``).
    """
    radii = np.array([hl.source_radius_deg for hl in found])
    known = radii[np.isfinite(radii)]
    share = float(np.median(known)) if known.size else 0.0
    out = []
    for hl in found:
        if np.isfinite(hl.source_radius_deg):
            out.append(hl)
            continue
        mx, my = hl.centroid
        x, y = _corrected(mx, my, circle, np.radians(share))
        out.append(replace(hl, x=float(x), y=float(y), source_radius_deg=share))
    return out


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
    # On the core's bounding box: the distances, the opening (never larger than the core) and
    # its pieces are those of the whole frame, at the box's cost rather than the frame's.
    rows, cols = np.flatnonzero(core.any(axis=1)), np.flatnonzero(core.any(axis=0))
    box = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    part = core[box]
    dist = ndimage.distance_transform_edt(np.pad(part, 1))[1:-1, 1:-1]
    widest = np.unravel_index(int(np.argmax(dist)), dist.shape)
    if dist[widest] >= 2.0:
        opened = ndimage.binary_opening(part, structure=_disc(0.5 * dist[widest]))
        labels, _ = ndimage.label(opened, structure=_EIGHT)
        if labels[widest]:
            core = np.zeros_like(core)
            core[box] = labels == labels[widest]
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
