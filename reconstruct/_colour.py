"""Colour albedo: one normal map, a Lambertian-equivalent reflectance per colour channel.

The normals are solved on one channel (``--channel``); the three channels of every frame are
staged beside it (:class:`ps_lab.io.bands.ObservationStore` with ``colours=3``), each divided by
the light's intensity for that channel, and after the normals of a band are known each channel's
albedo is the least-squares scale of the Lambertian shading over the observations the solver kept
(:func:`colour_albedo`). The result's ``albedo.npy`` is then (H, W, 3) linear RGB; ``albedo.png``
is its sRGB picture (:func:`colour_albedo_picture`) and ``albedo.exr`` the float values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ps_lab.io.dataset import DatasetHeader
from ps_lab.io.encoding import linear_to_srgb
from ps_lab.io.images import read_image
from ps_lab.io.normal_maps import write_rgb_exr

# Pixels per chunk of the colour albedo's float64 work arrays.
COLOUR_CHUNK = 8192

__all__ = [
    "colour_albedo",
    "colour_albedo_picture",
    "frame_channels",
    "grey_albedo",
    "write_albedo_exr",
]


def colour_albedo(
    normals: np.ndarray,
    inliers: np.ndarray,
    observations: np.ndarray,
    lights: np.ndarray,
    intensities: np.ndarray | None = None,
) -> np.ndarray:
    """Per-channel Lambertian-equivalent albedo of pixels whose normals are known.

    For pixel p and channel c, with shading ``s_c,i = e_c,i · max(n_p · l_i, 0)`` over the
    inlier observations ``i`` of the pixel::

        albedo_c = Σ_i y_c,i · s_c,i / Σ_i s_c,i²

    the least-squares scale of the Lambertian model ``y = albedo · s`` on the observations the
    solver kept (attached shadows, ``s = 0``, add nothing to either sum). Pure and exact: with
    noise-free Lambertian data it returns the rendered albedo.

    Parameters
    ----------
    normals : ndarray of shape (P, 3)
        Unit normals (zeros where unsolved).
    inliers : ndarray of shape (n, P), bool
        Observations the solver used (valid, not outliers, not shadows).
    observations : ndarray of shape (n, P, C)
        The colour observations (non-finite ones are skipped).
    lights : ndarray of shape (n, 3) or (n, P, 3)
        Light vectors: directions, or directions times relative intensities (the solver's
        vectors); per pixel for near lights.
    intensities : ndarray of shape (n, C) or None
        Each light's intensity per channel (None: ones, the observations are already divided).

    Returns
    -------
    ndarray of shape (P, C), float32
        Zero where a pixel has no inlier with positive shading.

    """
    observations = np.asarray(observations)
    n, p, c = observations.shape
    lights = np.asarray(lights, np.float64)
    albedo = np.zeros((p, c), np.float32)
    for a in range(0, p, COLOUR_CHUNK):  # float64 copies bounded on large bands
        b = min(a + COLOUR_CHUNK, p)
        part = lights if lights.ndim == 2 else lights[:, a:b]
        albedo[a:b] = _chunk_albedo(normals[a:b], inliers[:, a:b], observations[:, a:b], part,
                                    intensities)
    return albedo


def _chunk_albedo(normals, inliers, observations, lights, intensities) -> np.ndarray:
    normals = np.asarray(normals, np.float64)
    n, p, c = observations.shape
    if lights.ndim == 2:
        shading = np.maximum(lights @ normals.T, 0.0)  # (n, P)
    else:
        shading = np.maximum(np.einsum("npk,pk->np", lights, normals), 0.0)
    y = observations.astype(np.float64)
    use = np.asarray(inliers, bool)[:, :, None] & np.isfinite(y)
    s = np.broadcast_to(shading[:, :, None], (n, p, c))
    if intensities is not None:
        s = s * np.asarray(intensities, np.float64).reshape(n, 1, c)
    s = np.where(use, s, 0.0)
    numerator = (np.where(use, y, 0.0) * s).sum(axis=0)
    denominator = (s * s).sum(axis=0)
    return np.divide(numerator, denominator, out=np.zeros((p, c)), where=denominator > 0)


def grey_albedo(albedo: np.ndarray, channel: str) -> np.ndarray:
    """The solve channel's albedo (H, W) from a colour one (H, W, 3); a grey one as it is.

    The colour albedo is linear in the observations, so the ``mean`` channel's albedo is the
    mean of the three.
    """
    albedo = np.asarray(albedo)
    if albedo.ndim == 2:
        return albedo
    if albedo.shape[-1] == 1:
        return albedo[..., 0]
    pick = {"r": 0, "g": 1, "b": 2}
    return albedo.mean(axis=-1) if channel not in pick else albedo[..., pick[channel]]


def frame_channels(header: DatasetHeader) -> int:
    """Colour channels of the dataset's frames: 3 for colour, 1 for grey (reads light 1)."""
    image = read_image(header.plan.light_files[0][0], header.plan.encoding)
    return 3 if image.data.ndim == 3 and image.data.shape[-1] >= 3 else 1


def colour_albedo_picture(
    albedo: np.ndarray, mask: np.ndarray, top: float | None = None
) -> np.ndarray:
    """An 8-bit sRGB picture of a linear colour albedo (H, W, 3).

    One scale for the three channels (so the hue is kept): ``top`` (default the 99th percentile
    of the brightest channel inside the mask) maps to 1, then the sRGB transfer curve.

    Returns
    -------
    ndarray of shape (H, W, 3), uint8, RGB; black outside the mask

    """
    albedo = np.asarray(albedo, np.float32)
    if top is None:
        inside = albedo[mask].max(axis=-1) if mask.any() else np.zeros(0)
        top = float(np.percentile(inside, 99)) if inside.size else 0.0
    picture = np.zeros((*mask.shape, 3), np.uint8)
    if not np.isfinite(top) or top <= 0:
        return picture
    for start in range(0, mask.shape[0], 256):  # bounded float64 copies on large images
        rows = slice(start, start + 256)
        encoded = linear_to_srgb(np.nan_to_num(albedo[rows]) / top)
        block = np.clip(np.rint(encoded * 255.0), 0, 255).astype(np.uint8)
        block[~mask[rows]] = 0
        picture[rows] = block
    return picture


def write_albedo_exr(path: Path, albedo: np.ndarray) -> None:
    """Write a linear colour albedo (H, W, 3) as OpenEXR float channels R, G, B."""
    write_rgb_exr(path, albedo)
