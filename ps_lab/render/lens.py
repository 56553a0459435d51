"""A lens for the synthetic world: radial-tangential distortion applied to rendered frames.

The renderer draws the ideal (pinhole) image; :func:`distort_image` turns it into what a camera
with the lens of a :class:`~ps_lab.io.camera.CameraModel` records: the recorded pixel at ``p_d``
shows the ideal image at ``undistort(p_d)`` (:func:`ps_lab.io.camera.undistort_points`, Newton to
~1e-12 px). Sampling is bicubic, on a grid ``supersample`` times finer than the pixels, averaged
back (each recorded pixel integrates its own footprint rather than reading one point).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from ps_lab.io.camera import CameraModel, undistort_points


@lru_cache(maxsize=2)
def lens_source_positions(camera: CameraModel, shape: tuple[int, int], supersample: int = 1):
    """Where each recorded (sub-)pixel looks in the ideal image (cached: one lens, many frames).

    Returns
    -------
    map_x, map_y : ndarray of shape (H * s, W * s), float32
        Ideal-image column and row of every sub-pixel centre of the recorded frame.
    """
    h, w = shape
    s = int(supersample)
    offsets = (np.arange(s) + 0.5) / s - 0.5
    cols = (np.arange(w)[:, None] + offsets[None, :]).ravel()
    rows = (np.arange(h)[:, None] + offsets[None, :]).ravel()
    grid_c, grid_r = np.meshgrid(cols, rows)
    ideal = undistort_points(camera, np.column_stack([grid_c.ravel(), grid_r.ravel()]))
    return (ideal[:, 0].reshape(grid_c.shape).astype(np.float32),
            ideal[:, 1].reshape(grid_c.shape).astype(np.float32))


def distort_image(
    image: np.ndarray, camera: CameraModel, *, supersample: int = 2, fill: float = 0.0
) -> np.ndarray:
    """The frame a camera with ``camera``'s lens records of the ideal image ``image``.

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, C), float
        The ideal (undistorted) image; C <= 4.
    camera : CameraModel
        Intrinsics and distortion (``image_size`` must be ``(W, H)``).
    supersample : int
        Sub-pixels per pixel side averaged for each recorded pixel.
    fill : float
        Value of recorded pixels that see beyond the ideal image.

    Returns
    -------
    ndarray, same shape and dtype as ``image``
    """
    h, w = image.shape[:2]
    if not camera.has_distortion:
        return image
    map_x, map_y = lens_source_positions(camera, (h, w), supersample)
    data = np.asarray(image, dtype=np.float32)
    squeeze = data.ndim == 3 and data.shape[2] == 1
    src = data[..., 0] if squeeze else data
    fine = cv2.remap(src, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=float(fill))
    s = int(supersample)
    if s > 1:
        fine = fine.reshape(h, s, w, s, *fine.shape[2:]).mean(axis=(1, 3))
    if squeeze:
        fine = fine[..., None]
    return fine.astype(image.dtype, copy=False)
