"""A small rendered capture with every optional file (dark, intensities, mask, truth)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ps_lab import render
from ps_lab.reconstruct.pipeline import BYTES_PER_OBSERVATION, BYTES_PER_PIXEL

SHAPE = (30, 26)
N_LIGHTS = 12


def write_capture(folder: Path, *, seed: int = 0, colour: bool = False, n: int = N_LIGHTS) -> dict:
    """A rendered glossy sphere as 16-bit PNGs with lights, intensities, dark, mask and truth."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    surface = render.sphere_surface(SHAPE, albedo=(0.8, 0.6, 0.4) if colour else 0.7)
    lights = render.random_light_directions(n, rng)
    images = render.render(surface, lights, specular=0.4, noise_sigma=0.002, rng=rng)
    scale = 0.8 / float(images.max())
    dark = rng.uniform(0.0, 0.01, images.shape[1:]).astype(np.float32)
    for i, image in enumerate(images):
        counts = np.clip(np.rint((image * scale + dark) * 65535), 0, 65535).astype(np.uint16)
        if counts.ndim == 3:
            counts = np.ascontiguousarray(counts[..., ::-1])
        assert cv2.imwrite(str(folder / f"{i:03d}.png"), counts)
    dark_counts = np.rint(dark * 65535).astype(np.uint16)
    if dark_counts.ndim == 3:
        dark_counts = np.ascontiguousarray(dark_counts[..., ::-1])
    cv2.imwrite(str(folder / "dark.png"), dark_counts)
    np.savetxt(folder / "light_directions.txt", lights)
    np.savetxt(folder / "light_intensities.txt", rng.uniform(0.8, 1.2, (n, 3)))
    cv2.imwrite(str(folder / "mask.png"), surface.mask.astype(np.uint8) * 255)
    np.save(folder / "normal_gt.npy", surface.normals)
    return {"surface": surface, "lights": lights}



def budget_for(rows_of_pixels: int, n: int = N_LIGHTS) -> int:
    """A memory budget whose bands hold about this many mask pixels."""
    return rows_of_pixels * (n * BYTES_PER_OBSERVATION + BYTES_PER_PIXEL)
