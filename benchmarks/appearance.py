"""Appearance-fit benchmark: speed and peak memory of the streamed fit on a large capture.

Builds the reconstruction's file-backed observation store of a synthetic capture (a glossy
sphere, ``--megapixels`` × ``--lights``, banded by the default memory model of ``ps-lab
reconstruct --memory-budget``) and the result's ``normals.npy`` / ``albedo.npy``, then runs the
reconstruction's appearance stage (:func:`ps_lab.appearance.fit.fit_appearance_bands`)
exactly as the pipeline calls it, and reports its wall time, pixel rate and peak resident memory
(``VmHWM`` of this process, reset with ``/proc/self/clear_refs`` after the store is built).
``--bands K`` fits only the first K bands' rows (the mask covers them alone; the coefficient file
is still the full image size) and projects the full time from the rate.

``--glossy-capture DIR`` instead writes the glossy coloured stand-in of a real RTI capture used in
docs/results.md (a relief with a coloured albedo, Cook-Torrance gloss, cast shadows, 72 lights
within 70 degrees of the view, noise, sRGB JPEG quality 92) for ``ps-lab bench relight DIR``.
Usage::

    python benchmarks/appearance.py [--megapixels 12] [--lights 96] [--model ps]
                                    [--memory-budget 1GB] [--bands K] [--folder DIR]
    python benchmarks/appearance.py --glossy-capture DIR
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from ps_lab.appearance.fit import fit_appearance_bands
from ps_lab.io.bands import ObservationStore, plan_bands
from ps_lab.io.files import allocate_npy, write_npy_rows
from ps_lab.reconstruct.options import band_pixels, parse_memory_size


def _status(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    return 0


def _reset_peak() -> None:
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _lights(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(math.cos(math.radians(60)), 1.0, n)
    phi = rng.uniform(0, 2 * math.pi, n)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _rows(width: int, height: int, start: int, stop: int):
    cx, cy, radius = (width - 1) / 2, (height - 1) / 2, 0.48 * min(width, height)
    x = (np.arange(width) - cx) / radius
    y = -(np.arange(start, stop) - cy) / radius
    nx, ny = np.meshgrid(x, y)
    r2 = nx * nx + ny * ny
    inside = r2 < 0.98
    normals = np.stack([nx, ny, np.sqrt(np.clip(1 - r2, 0, None))], axis=-1)
    normals[~inside] = 0
    return normals.astype(np.float32), inside


def run(megapixels: float, lights: int, model: str, budget: str, bands: int | None,
        folder: Path) -> dict:
    width = int(round(math.sqrt(megapixels * 1e6 * 1.5)))
    height = int(round(megapixels * 1e6 / width))
    directions = _lights(lights)
    half = directions + np.array([0, 0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    _, disc = _rows(width, height, 0, height)
    plan = plan_bands(disc, band_pixels(parse_memory_size(budget), lights))
    if bands is not None:
        plan = plan[:bands]
        disc[plan[-1].row_stop:] = False
        plan = plan_bands(disc, band_pixels(parse_memory_size(budget), lights))
    built = time.perf_counter()
    normal_offset = allocate_npy(folder / "normals.npy", (height, width, 3))
    albedo_offset = allocate_npy(folder / "albedo.npy", (height, width))
    store = ObservationStore(plan, lights, disc, folder=folder)
    for band in plan:
        normals, inside = _rows(width, height, band.row_start, band.row_stop)
        inside &= disc[band.row_start:band.row_stop]
        normals[~inside] = 0
        albedo = np.where(inside, 0.6, 0.0).astype(np.float32)
        write_npy_rows(folder / "normals.npy", normal_offset, band.row_start, normals)
        write_npy_rows(folder / "albedo.npy", albedo_offset, band.row_start, albedo)
        n = normals[inside].astype(np.float64)
        shade = np.maximum(directions @ n.T, 0)
        gloss = np.maximum(half @ n.T, 0) ** 40 * (shade > 0)
        obs = (0.6 * shade + 0.3 * gloss).astype(np.float32)
        for i in range(lights):
            store.write(i, band, obs[i], np.ones(obs.shape[1], bool))
    build_seconds = time.perf_counter() - built
    _reset_peak()
    before = _status("VmRSS")
    started = time.perf_counter()
    with store:
        record = fit_appearance_bands(store, folder, model, directions)
        pixels = store.pixels
    seconds = time.perf_counter() - started
    peak = _status("VmHWM")
    total_pixels = int(_rows(width, height, 0, height)[1].sum())
    return {
        "size": f"{width}x{height}",
        "lights": lights,
        "model": model,
        "budget": budget,
        "bands": len(plan),
        "band_pixels": max(b.pixel_count for b in plan),
        "fitted_pixels": pixels,
        "mask_pixels": total_pixels,
        "seconds": seconds,
        "pixels_per_second": pixels / seconds,
        "projected_seconds": seconds * total_pixels / max(pixels, 1),
        "rss_before_gib": before / 2**30,
        "peak_rss_gib": peak / 2**30,
        "build_seconds": build_seconds,
        "coefficients_per_pixel": record["coefficients_per_pixel"],
        "file_gib": (folder / "appearance.npz").stat().st_size / 2**30,
    }


def glossy_capture(out: Path, seed: int = 7) -> None:
    """Write the glossy coloured sRGB JPEG stand-in capture into ``out``."""
    import cv2

    from ps_lab import render
    from ps_lab.io.encoding import linear_to_srgb

    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    height, width = 160, 200
    yy, xx = np.mgrid[0:height, 0:width]
    albedo = np.stack([0.55 + 0.3 * np.sin(xx / 13.0), 0.35 + 0.2 * np.cos(yy / 9.0),
                       0.25 + 0.15 * np.sin((xx + yy) / 17.0)], axis=-1)
    surface = render.relief_surface((height, width), seed=4, albedo=albedo)
    n = 72
    z = rng.uniform(math.cos(math.radians(70)), 1.0, n)
    phi = rng.uniform(0, 2 * math.pi, n)
    r = np.sqrt(1 - z * z)
    lights = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    images = render.render(surface, lights, specular=0.5, roughness=0.25, cast_shadows=True,
                           noise_sigma=0.003, noise_fraction=1.0, rng=rng)
    scale = 0.85 / np.percentile(images, 99.9)
    for i, image in enumerate(images):
        encoded = np.rint(linear_to_srgb(np.clip(image * scale, 0, 1)) * 255).astype(np.uint8)
        cv2.imwrite(str(out / f"{i + 1:03d}.jpg"), np.ascontiguousarray(encoded[..., ::-1]),
                    [cv2.IMWRITE_JPEG_QUALITY, 92])
    np.savetxt(out / "light_directions.txt", lights)
    cv2.imwrite(str(out / "mask.png"), surface.mask.astype(np.uint8) * 255)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--megapixels", type=float, default=12.0)
    parser.add_argument("--lights", type=int, default=96)
    parser.add_argument("--model", default="ps")
    parser.add_argument("--memory-budget", default="1GB")
    parser.add_argument("--bands", type=int, default=None)
    parser.add_argument("--folder", type=Path, default=None)
    parser.add_argument("--glossy-capture", type=Path, default=None)
    args = parser.parse_args()
    if args.glossy_capture is not None:
        glossy_capture(args.glossy_capture)
        return
    folder = args.folder or Path(tempfile.mkdtemp(prefix="ps-lab-appearance-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        result = run(args.megapixels, args.lights, args.model, args.memory_budget, args.bands,
                     folder)
    finally:
        if args.folder is None:
            shutil.rmtree(folder, ignore_errors=True)
    for key, value in result.items():
        print(f"{key:24s} {value:.4g}" if isinstance(value, float) else f"{key:24s} {value}")


if __name__ == "__main__":
    main()
