"""Finding the chrome sphere's outline to sub-pixel accuracy.

A light's zenith angle is twice the sphere-normal angle at its highlight, so a 1-px error in the
circle of a 100-px sphere costs more than a degree: everything here aims at ~0.01 px.

Pipeline: a summary image in which the sphere is a plain disc (the per-pixel median over frames
removes the highlights, which are each lit in one frame only), a coarse Hough circle, then a
geometric least-squares circle fit to sub-pixel edge points found along radial profiles as the
half-way crossing between the local inside and outside levels of the anti-aliased limb.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from scipy import ndimage

from ps_lab.errors import CalibrationError
from ps_lab.geometry import Circle


class CircleFit(NamedTuple):
    """Result of :func:`refine_circle`.

    Attributes
    ----------
    circle : Circle
        The fitted circle.
    residual : float
        RMS distance of the inlier edge points from the circle, pixels.
    edge_points : ndarray of shape (m, 2)
        Inlier edge points ``(x, y)``.
    coverage : float
        Share of the radial profiles that gave a valid inlier edge point (0..1).

    """

    circle: Circle
    residual: float
    edge_points: np.ndarray
    coverage: float


def luminance(images: np.ndarray) -> np.ndarray:
    """Mean over colour channels.

    Parameters
    ----------
    images : ndarray of shape (..., H, W, C) or (..., H, W)
        With ``C`` in {1, 3} when a channel axis is present (the caller says so by passing 4-D
        stacks or 3-D single frames with C last).

    Returns
    -------
    ndarray of shape (..., H, W), float32

    """
    return np.asarray(images, dtype=np.float32).mean(axis=-1)


def summary_image(
    images: np.ndarray, *, max_frames: int = 24, reduce: str = "median", band_rows: int = 256
) -> np.ndarray:
    """Per-pixel median (or maximum) of the luminance over evenly spaced frames.

    Computed in row bands, so only a band of the selected frames is ever copied.

    Parameters
    ----------
    images : ndarray of shape (n, H, W) or (n, H, W, C)
        Linear frames (channels are averaged).
    max_frames : int
        Frames used (evenly spaced), to bound time and memory.
    reduce : {"median", "max"}
        The median shows a chrome sphere as a plain disc (each highlight is lit in few frames);
        the maximum shows a matte sphere's limb as a step.
    band_rows : int
        Rows per band.

    Returns
    -------
    ndarray of shape (H, W), float32
    """
    n, h = images.shape[0], images.shape[1]
    idx = np.linspace(0, n - 1, min(n, max_frames)).round().astype(int)
    out = np.empty(images.shape[1:3], dtype=np.float32)
    for r0 in range(0, h, band_rows):
        band = np.asarray(images[idx, r0 : r0 + band_rows], dtype=np.float32)
        if band.ndim == 4:
            band = band.mean(axis=-1)
        out[r0 : r0 + band_rows] = (
            np.median(band, axis=0) if reduce == "median" else band.max(axis=0)
        )
    return out


def noise_sigma(image: np.ndarray) -> float:
    """Robust estimate of the pixel noise from horizontal neighbour differences (MAD)."""
    diff = np.diff(np.asarray(image, dtype=np.float64), axis=1).ravel()
    return float(1.4826 * np.median(np.abs(diff - np.median(diff))) / np.sqrt(2.0))


def _to_uint8(image: np.ndarray) -> np.ndarray:
    # Log tone map with a noise floor: a dim chrome sphere next to a bright matte target must
    # still give Canny edges, while the background noise must not.
    img = np.asarray(image, dtype=np.float64)
    lo = np.percentile(img, 1.0)
    img = img - lo
    hi = np.percentile(img, 99.9)
    if not np.isfinite(hi) or hi <= 0:
        return np.zeros(img.shape, dtype=np.uint8)
    eps = max(3.0 * noise_sigma(img), 1e-3 * hi)
    mapped = np.log1p(np.clip(img, 0, hi) / eps) / np.log1p(hi / eps)
    return np.round(255 * mapped).astype(np.uint8)


def circle_candidates(
    summary: np.ndarray,
    *,
    min_radius: float = 8.0,
    max_radius: float | None = None,
    max_candidates: int = 12,
) -> list[Circle]:
    """Coarse circle candidates: round bright blobs, then OpenCV's gradient Hough transform.

    The blob candidates (Otsu threshold of the tone-mapped summary, round connected components)
    catch a dim sphere on a noisy background, where noise edges outvote it in the Hough
    accumulator; Hough candidates catch spheres that touch other objects.

    Parameters
    ----------
    summary : ndarray of shape (H, W)
        Summary image (any scale; tone-mapped to 8 bit here).
    min_radius, max_radius : float
        Radius range in pixels (``max_radius`` default: half the smaller image side).
    max_candidates : int
        At most this many Hough candidates.

    Returns
    -------
    list of Circle
        Blob candidates first, then Hough candidates strongest first; empty when none was found.

    """
    h, w = summary.shape
    scale = min(1.0, 1200.0 / max(h, w))
    img8 = _to_uint8(summary)
    if scale < 1.0:
        img8 = cv2.resize(img8, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    img8 = cv2.GaussianBlur(cv2.medianBlur(img8, 5), (0, 0), 1.5)
    if max_radius is None:
        max_radius = min(h, w) / 2.0
    lo = max(3, int(min_radius * scale))
    hi = max(lo + 2, int(np.ceil(max_radius * scale)))

    def to_image(x: float, y: float, r: float) -> Circle:
        return Circle(
            float((x + 0.5) / scale - 0.5), float((y + 0.5) / scale - 0.5), float(r / scale)
        )

    found: list[Circle] = []
    _, binary = cv2.threshold(img8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    count, _, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
    for i in range(1, count):
        area = stats[i, cv2.CC_STAT_AREA]
        bw, bh = stats[i, cv2.CC_STAT_WIDTH], stats[i, cv2.CC_STAT_HEIGHT]
        r = np.sqrt(area / np.pi)
        # Round: fills its bounding square like a disc does (pi/4), and is not elongated.
        if lo <= r <= hi and 0.6 < area / (bw * bh) < 0.95 and 0.8 < bw / bh < 1.25:
            found.append(to_image(centroids[i][0], centroids[i][1], r))
    circles = cv2.HoughCircles(
        img8,
        cv2.HOUGH_GRADIENT,
        dp=1,
        minDist=max(4.0, lo),
        param1=60,
        param2=25,
        minRadius=lo,
        maxRadius=hi,
    )
    if circles is not None:
        found.extend(to_image(c[0], c[1], c[2]) for c in circles[0][:max_candidates])
    return found


def fit_circle(points: np.ndarray) -> Circle:
    """Geometric least-squares circle through points (algebraic start, Gauss-Newton).

    Parameters
    ----------
    points : ndarray of shape (m, 2)
        ``(x, y)`` points, ``m >= 3``, not collinear.

    Returns
    -------
    Circle

    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 3:
        raise CalibrationError("circle fit needs at least 3 edge points")
    mean = pts.mean(axis=0)
    scale = np.sqrt(((pts - mean) ** 2).sum(axis=1).mean())
    if scale <= 0:
        raise CalibrationError("circle fit: all edge points coincide")
    p = (pts - mean) / scale
    # Kasa: x^2 + y^2 + D x + E y + F = 0, on normalised coordinates.
    a = np.column_stack([p[:, 0], p[:, 1], np.ones(len(p))])
    b = -(p**2).sum(axis=1)
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    if rank < 3:
        raise CalibrationError("circle fit: edge points are degenerate")
    cx, cy = -sol[0] / 2, -sol[1] / 2
    r = np.sqrt(max(cx * cx + cy * cy - sol[2], 1e-12))
    for _ in range(20):
        dx, dy = p[:, 0] - cx, p[:, 1] - cy
        d = np.hypot(dx, dy)
        d = np.where(d > 0, d, 1e-12)
        res = d - r
        jac = np.column_stack([-dx / d, -dy / d, -np.ones_like(d)])
        step = np.linalg.lstsq(jac, -res, rcond=None)[0]
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
        if np.abs(step).max() < 1e-12:
            break
    return Circle(float(cx * scale + mean[0]), float(cy * scale + mean[1]), float(abs(r) * scale))


def _edge_points(
    image: np.ndarray, circle: Circle, half_width: float, step: float = 0.25
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel limb crossings along rays from the circle centre.

    Returns
    -------
    points : ndarray of shape (K, 2)
        Edge point per ray (NaN where the ray gave none).
    contrast : ndarray of shape (K,)
        |inside − outside| level per ray (NaN where none).

    """
    h, w = image.shape
    cx, cy, r = circle
    k = int(max(64, min(2048, np.ceil(2 * np.pi * r))))
    theta = (np.arange(k) + 0.5) * (2 * np.pi / k)
    rho = np.arange(max(r - half_width, 1.0), r + half_width + step / 2, step)
    cos, sin = np.cos(theta)[:, None], np.sin(theta)[:, None]
    xs, ys = cx + rho[None, :] * cos, cy + rho[None, :] * sin
    inside_image = (
        (xs.min(axis=1) >= 0)
        & (xs.max(axis=1) <= w - 1)
        & (ys.min(axis=1) >= 0)
        & (ys.max(axis=1) <= h - 1)
    )
    prof = ndimage.map_coordinates(image, [ys.ravel(), xs.ravel()], order=1, mode="nearest")
    prof = prof.reshape(xs.shape).astype(np.float64)
    # Polarity (sphere brighter or darker than its surroundings) is decided over all rays.
    n_in = max(2, int(round(1.5 / step)))
    polarity = np.sign(np.median(prof[:, :n_in].mean(axis=1) - prof[:, -n_in:].mean(axis=1)))
    if polarity == 0:
        polarity = 1.0
    smooth = ndimage.gaussian_filter1d(prof, sigma=0.5 / step, axis=1, mode="nearest")
    grad = -polarity * np.gradient(smooth, axis=1)
    lo_off, hi_off = int(round(1.5 / step)), int(round(3.0 / step))
    m = len(rho)
    # The strongest edge along each ray, away from the ends so that both levels can be measured.
    valid_range = np.zeros(m, dtype=bool)
    valid_range[hi_off : m - hi_off] = True
    g = np.where(valid_range[None, :], grad, -np.inf)
    peak = np.argmax(g, axis=1)
    usable = inside_image & np.isfinite(g[np.arange(k), peak]) & (m > 2 * hi_off)
    peak = np.clip(peak, hi_off, m - hi_off - 1)
    rows = np.arange(k)[:, None]
    inner = np.median(prof[rows, peak[:, None] + np.arange(-hi_off, -lo_off + 1)], axis=1)
    outer = np.median(prof[rows, peak[:, None] + np.arange(lo_off, hi_off + 1)], axis=1)
    usable &= polarity * (inner - outer) > 0
    mid = 0.5 * (inner + outer)
    seg = polarity * (prof[rows, peak[:, None] + np.arange(-lo_off, lo_off + 1)] - mid[:, None])
    # Crossing from inside (> 0) to outside (< 0) closest to the gradient peak.
    cross = (seg[:, :-1] >= 0) & (seg[:, 1:] < 0)
    dist = np.where(cross, np.abs(np.arange(2 * lo_off) + 0.5 - lo_off)[None, :], np.inf)
    c = np.argmin(dist, axis=1)
    usable &= np.isfinite(dist[np.arange(k), c])
    a, b = seg[np.arange(k), c], seg[np.arange(k), c + 1]
    frac = a / np.where(a - b != 0, a - b, 1.0)
    radius = rho[np.clip(peak - lo_off + c, 0, m - 1)] + frac * step
    points = np.column_stack([cx + radius * cos[:, 0], cy + radius * sin[:, 0]])
    points[~usable] = np.nan
    contrast = np.where(usable, np.abs(inner - outer), np.nan)
    return points, contrast


def refine_circle(
    image: np.ndarray,
    circle: Circle,
    *,
    search_px: float | None = None,
    iterations: int = 3,
    min_coverage: float = 0.3,
) -> CircleFit:
    """Sub-pixel circle fit to the limb of a disc near ``circle``.

    Parameters
    ----------
    image : ndarray of shape (H, W)
        Summary image in which the sphere is a disc brighter (or darker) than its surroundings.
    circle : Circle
        Starting estimate (Hough, the rig file's nominal circle, ...).
    search_px : float, optional
        How far (pixels) from the starting outline to look for the limb on the first pass;
        default ``max(6, 0.1 * radius)``.
    iterations : int
        Resample the profiles around the refined circle this many times.
    min_coverage : float
        Minimum share of rays that must give an inlier edge point.

    Returns
    -------
    CircleFit

    Raises
    ------
    CalibrationError
        When too few edge points are found.

    """
    img = np.asarray(image, dtype=np.float32)
    half = search_px if search_px is not None else max(6.0, 0.1 * circle.radius)
    current = circle
    for it in range(iterations):
        pts, contrast = _edge_points(img, current, half_width=half + 3.0)
        ok = np.isfinite(contrast)
        n_rays = len(contrast)
        if ok.sum() < max(12, min_coverage * n_rays):
            raise CalibrationError(
                f"no clear sphere outline near circle ({current.x:.1f}, {current.y:.1f}) "
                f"r={current.radius:.1f}: only {ok.sum()} of {n_rays} radial profiles cross an edge"
            )
        # Weak edges (occluders, reflections of the rig) are not the limb.
        ok &= contrast >= 0.3 * np.median(contrast[ok])
        inliers = ok.copy()
        fit = current
        for _ in range(5):
            fit = fit_circle(pts[inliers])
            res = np.hypot(pts[:, 0] - fit.x, pts[:, 1] - fit.y) - fit.radius
            mad = 1.4826 * np.median(np.abs(res[inliers]))
            new = ok & (np.abs(res) <= max(3.0 * mad, 0.05))
            if np.array_equal(new, inliers):
                break
            inliers = new
        if inliers.sum() < max(12, min_coverage * n_rays):
            raise CalibrationError(
                f"sphere outline near ({current.x:.1f}, {current.y:.1f}) r={current.radius:.1f} is "
                f"too irregular: {inliers.sum()} of {n_rays} edge points fit one circle"
            )
        current = fit
        half = 1.5 if it == 0 else 1.0
    res = np.hypot(pts[inliers, 0] - current.x, pts[inliers, 1] - current.y) - current.radius
    return CircleFit(current, float(np.sqrt(np.mean(res**2))), pts[inliers], float(inliers.mean()))


def circle_inside_image(circle: Circle, shape: tuple[int, int], margin: float = 1.0) -> bool:
    """Whether the disc lies inside the image with ``margin`` pixels to spare."""
    h, w = shape
    x, y, r = circle
    return bool(
        x - r >= -0.5 + margin
        and y - r >= -0.5 + margin
        and x + r <= w - 0.5 - margin
        and y + r <= h - 0.5 - margin
    )


def _circumcircles(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Circles through point triples ``p`` of shape (m, 3, 2): centres x, y and radii (NaN if
    collinear)."""
    ax, ay = p[:, 0, 0], p[:, 0, 1]
    bx, by = p[:, 1, 0] - ax, p[:, 1, 1] - ay
    cx, cy = p[:, 2, 0] - ax, p[:, 2, 1] - ay
    d = 2.0 * (bx * cy - by * cx)
    d = np.where(np.abs(d) > 1e-9, d, np.nan)
    b2, c2 = bx * bx + by * by, cx * cx + cy * cy
    ux = (cy * b2 - by * c2) / d
    uy = (bx * c2 - cx * b2) / d
    return ax + ux, ay + uy, np.hypot(ux, uy)


def consensus_circle(
    image: np.ndarray,
    circle: Circle,
    *,
    search_px: float | None = None,
    tolerance_px: float = 1.0,
    trials: int = 2000,
    seed: int = 0,
) -> CircleFit:
    """Circle fit to the part of an outline that is really one circle (stands, reflections).

    Real rigs hide part of a sphere's limb (its stand, a holder) and show edges near it that
    are not the limb (the room and the rig reflected in the sphere, the stand's rim). Edge
    points are taken along radial profiles in a wide band around ``circle`` (as in
    :func:`refine_circle`); the circle through three of them that the most points agree with
    (within ``tolerance_px``; seeded random triples, RANSAC) picks the rays whose edge is the
    limb, and a geometric least-squares fit to those rays' edge points, resampled twice around
    the new circle, is the result.

    Parameters
    ----------
    image : ndarray of shape (H, W)
        Summary image.
    circle : Circle
        Starting estimate.
    search_px : float, optional
        Half-width of the band searched for the limb; default ``max(10, 0.025 * radius)``.
    tolerance_px : float
        Distance from the consensus circle within which an edge point counts as the limb.
    trials : int
        Random triples tried.
    seed : int
        Seed of the triples (the fit is deterministic).

    Returns
    -------
    CircleFit
        ``coverage`` is the share of the outline used; ``used`` the rays used (for the picture).

    Raises
    ------
    CalibrationError
        Too few edge points, or no circle that a tenth of the outline agrees with.

    """
    img = np.asarray(image, dtype=np.float32)
    half = search_px if search_px is not None else max(10.0, 0.025 * circle.radius)
    pts, contrast = _edge_points(img, circle, half_width=half + 3.0)
    ok = np.isfinite(contrast)
    k = len(contrast)
    if ok.sum() < 12:
        raise CalibrationError(
            f"no clear sphere outline near circle ({circle.x:.1f}, {circle.y:.1f}) "
            f"r={circle.radius:.1f}: only {ok.sum()} of {k} radial profiles cross an edge"
        )
    p = pts[ok]
    rng = np.random.default_rng(seed)
    triples = p[rng.integers(0, len(p), size=(trials, 3))]
    tx, ty, tr = _circumcircles(triples)
    near = (
        np.isfinite(tr)
        & (np.abs(tr - circle.radius) <= half)
        & (np.hypot(tx - circle.x, ty - circle.y) <= half)
    )
    if not near.any():
        raise CalibrationError(
            f"no circle fits the outline near ({circle.x:.1f}, {circle.y:.1f}) "
            f"r={circle.radius:.1f}"
        )
    tx, ty, tr = tx[near], ty[near], tr[near]
    votes = np.zeros(len(tx), dtype=np.int64)
    for start in range(0, len(tx), 256):
        part = slice(start, start + 256)
        d = np.hypot(p[None, :, 0] - tx[part, None], p[None, :, 1] - ty[part, None])
        votes[part] = (np.abs(d - tr[part, None]) <= tolerance_px).sum(axis=1)
    best = int(np.argmax(votes))
    current = Circle(float(tx[best]), float(ty[best]), float(tr[best]))
    res = np.hypot(pts[:, 0] - current.x, pts[:, 1] - current.y) - current.radius
    limb = ok & (np.abs(res) <= tolerance_px)  # the rays whose edge is the limb
    for _ in range(4):
        inliers = ok & (np.abs(res) <= tolerance_px) & limb
        if inliers.sum() < max(12, 0.1 * len(limb)):
            raise CalibrationError(
                f"sphere outline near ({circle.x:.1f}, {circle.y:.1f}) r={circle.radius:.1f}: "
                f"only {inliers.sum()} of {len(limb)} edge points fit one circle"
            )
        current = fit_circle(pts[inliers])
        # Resample the limb rays' profiles around the new circle (same rays when k is unchanged).
        pts, contrast = _edge_points(img, current, half_width=tolerance_px + 3.0)
        if len(contrast) != len(limb):
            old = len(limb)
            limb = limb[(np.arange(len(contrast)) * old) // len(contrast)]
        ok = np.isfinite(contrast)
        res = np.hypot(pts[:, 0] - current.x, pts[:, 1] - current.y) - current.radius
    used = ok & (np.abs(res) <= tolerance_px) & limb
    res = res[used]
    return CircleFit(current, float(np.sqrt(np.mean(res**2))), pts[used], float(used.mean()))
