"""Colour albedo from sRGB JPEG against its linear source, per channel (issue 32).

Usage (from the repository root)::

    .venv/bin/python benchmarks/colour_jpeg.py [FOLDER] [--method ls] [--objects cat pot1] \
        [--work /tmp/colour-jpeg]

For each DiLiGenT object of ``FOLDER`` (default ../shared/data/diligent-8bit; skipped with a
message when absent) the 8-bit linear PNG frames are re-encoded as a camera would: linear value
→ sRGB transfer curve → 8 bits → JPEG quality 95 (OpenCV, 4:2:0 chroma). Both folders are
reconstructed with ``--method`` (same light files, mask and intensities), and the result's
``albedo.npy`` (H×W×3) compared: the JPEG's per-channel mean over the pixels solved in both,
relative to the PNG's (in %), over the mask and over the mask less 4 pixels (one 4:2:0 chroma
block at the outline), and the median of the per-pixel ratios. docs/colour.md holds the table.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from ps_lab.io.encoding import linear_to_srgb
from ps_lab.reconstruct.pipeline import ReconstructOptions, reconstruct_to_folder

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "diligent-8bit"
OBJECTS = ("cat", "pot1", "buddha", "goblet", "harvest")


def as_jpeg(source: Path, target: Path, quality: int = 95) -> None:
    """Re-encode a folder's linear 8-bit PNG frames as sRGB JPEG (light files and mask copied)."""
    target.mkdir(parents=True, exist_ok=True)
    for name in ("light_directions.txt", "light_intensities.txt", "mask.png"):
        shutil.copy(source / name, target / name)
    for png in sorted(source.glob("[0-9][0-9][0-9].png")):
        linear = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64) / 255.0
        encoded = np.rint(linear_to_srgb(linear) * 255).astype(np.uint8)
        cv2.imwrite(str(target / f"{png.stem}.jpg"), np.ascontiguousarray(encoded[..., ::-1]),
                    [cv2.IMWRITE_JPEG_QUALITY, quality])


def compare(source: Path, work: Path, method: str) -> list[tuple]:
    """Rows (object, method, region, pixels, mean difference R G B %, median ratio R G B %)."""
    name = source.name
    jpeg = work / f"{name}-jpeg"
    if not jpeg.exists():
        as_jpeg(source, jpeg)
    albedo = {}
    for kind, folder in (("png", source), ("jpeg", jpeg)):
        out = work / f"{name}-{kind}-{method}"
        reconstruct_to_folder(folder, out, ReconstructOptions(method=method))
        albedo[kind] = np.load(out / "albedo.npy")
    mask = cv2.imread(str(source / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    solved = mask & (albedo["png"].min(axis=-1) > 0) & (albedo["jpeg"].min(axis=-1) > 0)
    inner = cv2.erode(solved.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    rows = []
    for region, use in (("mask", solved), ("mask less 4 px", inner)):
        png, jpg = albedo["png"][use], albedo["jpeg"][use]
        mean = 100 * (jpg.mean(axis=0) / png.mean(axis=0) - 1)
        median = 100 * (np.median(jpg / png, axis=0) - 1)
        rows.append((name, method, region, int(use.sum()), *map(float, mean), *map(float, median)))
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", nargs="?", type=Path, default=DEFAULT)
    parser.add_argument("--method", default="ls")
    parser.add_argument("--objects", nargs="+", default=list(OBJECTS))
    parser.add_argument("--work", type=Path, default=Path("/tmp/ps-lab-colour-jpeg"))
    args = parser.parse_args(argv)
    if not args.folder.is_dir():
        print(f"{args.folder}: no DiLiGenT data; nothing measured", file=sys.stderr)
        return
    print("| object | method | region | pixels | R % | G % | B % | median R % | G % | B % |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.objects:
        for row in compare(args.folder / name, args.work, args.method):
            print("| " + " | ".join(
                f"{x:+.2f}" if isinstance(x, float) else str(x) for x in row) + " |", flush=True)


if __name__ == "__main__":
    main()
