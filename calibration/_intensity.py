"""Relative light intensities: from a matte (Lambertian) sphere, or the LEDs' intensity model."""

from __future__ import annotations

import numpy as np

from ps_lab.calibration._circle import Circle
from ps_lab.errors import CalibrationError
from ps_lab.geometry import near_light_vectors, scene_points


def sphere_normals(
    shape: tuple[int, int], circle: Circle, *, inner: float = 0.9
) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic normals of a sphere inside ``inner`` of its radius.

    Parameters
    ----------
    shape : (H, W)
        Image size.
    circle : Circle
        Sphere outline.
    inner : float
        Share of the radius to keep (the limb is steep, blurred and inter-reflecting).

    Returns
    -------
    index : tuple of two ndarrays of shape (m,)
        Row and column indices of the pixels used.
    normals : ndarray of shape (m, 3)

    """
    h, w = shape
    cx, cy, r = circle
    yy, xx = np.mgrid[0:h, 0:w]
    nx, ny = (xx - cx) / r, -(yy - cy) / r
    keep = nx * nx + ny * ny <= inner * inner
    rows, cols = np.nonzero(keep)
    nx, ny = nx[keep], ny[keep]
    nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, 1.0))
    return (rows, cols), np.column_stack([nx, ny, nz])


def fit_light_intensities(
    images: np.ndarray,
    light_directions: np.ndarray,
    circle: Circle,
    *,
    saturated: np.ndarray | None = None,
    min_shading: float = 0.15,
    min_pixels: int = 50,
    light_positions: np.ndarray | None = None,
    anisotropy: float = 0.0,
) -> tuple[np.ndarray, list[str]]:
    """Relative intensity per light and channel from a matte sphere.

    Model per light ``j`` and channel ``c``: ``I = e[j, c] * (n · l_j) + b[j, c]`` on the sphere
    pixels with ``n · l_j >= min_shading`` (the offset ``b`` absorbs residual ambient light and
    inter-reflections). The albedo of the target is absorbed in ``e``; assuming a grey target
    the intensities are normalised by one global scale so that their mean over lights and
    channels is 1, which keeps the colour balance of the lights.

    Parameters
    ----------
    images : ndarray of shape (n, H, W, C)
        Linear frames, C = 1 or 3.
    light_directions : ndarray of shape (n, 3)
        Calibrated unit directions.
    circle : Circle
        The matte sphere's outline.
    saturated : ndarray of shape (n, H, W), bool, optional
        Clipped pixels, excluded from the fit.
    min_shading : float
        Smallest ``n · l`` used (attached shadows and the terminator are excluded).
    min_pixels : int
        A light with fewer usable pixels gets the mean intensity and a warning.
    light_positions : ndarray of shape (n, 3), optional
        LED positions (scene frame of :mod:`ps_lab.geometry`; NaN rows: directional). Then
        ``n . l_j`` becomes ``n . L_j(X)`` of :func:`ps_lab.geometry.near_light_vectors` at each
        pixel's sphere point X (the sphere's centre in the spheres' plane): ``e`` is the
        intensity at the scene origin, as the near-light solvers use it.
    anisotropy : float
        The LEDs' ``cos^mu`` exponent (with ``light_positions``).

    Returns
    -------
    intensities : ndarray of shape (n, 3)
    warnings : list of str

    """
    n, h, w, c = images.shape
    (rows, cols), normals = sphere_normals((h, w), circle)
    if len(rows) < min_pixels:
        raise CalibrationError(
            f"matte sphere r={circle.radius:.1f} px is too small to fit intensities"
        )
    out = np.full((n, c), np.nan)
    warnings: list[str] = []
    if light_positions is None:
        vectors = np.broadcast_to(np.asarray(light_directions, dtype=np.float64), (len(rows), n, 3))
    else:
        cx, cy, r = circle
        points = scene_points((h, w), [cy], [cx], 0.0) + r * normals
        vectors = near_light_vectors(
            points, light_positions, light_directions, anisotropy=anisotropy
        )
    for j in range(n):
        shading = np.einsum("mk,mk->m", normals, vectors[:, j])
        use = shading >= min_shading * np.linalg.norm(vectors[:, j], axis=1)
        if saturated is not None:
            use &= ~saturated[j][rows, cols]
        if use.sum() < min_pixels:
            warnings.append(
                f"light {j + 1}: only {int(use.sum())} usable matte-sphere pixels; "
                "its intensity is set to the mean"
            )
            continue
        s = shading[use]
        a = np.column_stack([s, np.ones_like(s)])
        vals = np.asarray(images[j][rows[use], cols[use]], dtype=np.float64)  # (m, C)
        coef = np.linalg.lstsq(a, vals, rcond=None)[0]
        out[j] = coef[0]
    if not np.isfinite(out).any():
        raise CalibrationError("matte sphere: no light gave a usable intensity fit")
    if np.any(out[np.isfinite(out)] <= 0):
        bad = sorted({j + 1 for j in np.nonzero(np.any(out <= 0, axis=1))[0]})
        raise CalibrationError(
            f"matte sphere: non-positive intensity fitted for light(s) {bad}: "
            "is the matte circle right?"
        )
    fill = np.nanmean(out, axis=0)
    out = np.where(np.isfinite(out), out, fill[None, :])
    out /= out.mean()
    if c == 1:
        out = np.repeat(out, 3, axis=1)
    return out, warnings


LED_INTENSITY_MODELS = ("equal", "origin")


def led_intensities_at_origin(
    light_positions: np.ndarray, model: str | np.ndarray = "equal"
) -> tuple[np.ndarray, str]:
    """Each LED's intensity at the scene origin (``e_j`` of the near-light model), no matte target.

    A point source of radiant intensity ``I_j`` (its axis aimed at the origin O, so its
    ``cos^mu`` emission is 1 there) gives O the irradiance ``I_j / |P_j - O|^2``:

    - ``"equal"`` (default): identical LEDs, equal radiant intensity, ``e_j ∝ 1 / |P_j|^2``;
    - ``"origin"``: equal irradiance at O, ``e_j = 1`` (what "all ones" meant before);
    - an array (n,) or (n, 3): each LED's relative radiant intensity (a per-LED file),
      ``e_j ∝ I_j / |P_j|^2``.

    Lights without a position (NaN rows: directional) get the mean of the placed ones (times
    their ``I_j`` for an array). The result is normalised to mean 1 over lights and channels.

    Parameters
    ----------
    light_positions : ndarray of shape (n, 3)
        Scene-frame LED positions (pixels), NaN rows for directional lights.
    model : {"equal", "origin"} or ndarray of shape (n,) or (n, 3)
        The intensity model, or each LED's relative radiant intensity.

    Returns
    -------
    intensities : ndarray of shape (n, 3)
    source : str
        What they are, for ``calibration.json``.
    """
    pos = np.asarray(light_positions, dtype=np.float64).reshape(-1, 3)
    n = pos.shape[0]
    if isinstance(model, str):
        if model not in LED_INTENSITY_MODELS:
            raise CalibrationError(
                f"unknown LED intensity model {model!r} (choose equal, origin or a file)"
            )
        radiant = np.ones((n, 3))
        if model == "origin":
            return radiant, "equal irradiance at the scene origin (no matte target)"
        source = "identical LEDs: equal radiant intensity, 1/d^2 to the scene origin"
    else:
        radiant = np.asarray(model, dtype=np.float64).reshape(n, -1)
        radiant = np.repeat(radiant, 3, axis=1) if radiant.shape[1] == 1 else radiant
        if radiant.shape != (n, 3) or not np.all(np.isfinite(radiant)) or np.any(radiant <= 0):
            raise CalibrationError(f"LED intensities must be {n} positive rows (1 or 3 values)")
        source = "per-LED radiant intensities from a file, 1/d^2 to the scene origin"
    placed = np.all(np.isfinite(pos), axis=1)
    falloff = np.ones(n)
    if placed.any():
        falloff[placed] = 1.0 / np.einsum("nk,nk->n", pos[placed], pos[placed])
        falloff[~placed] = falloff[placed].mean()
    out = radiant * falloff[:, None]
    return out / out.mean(), source
