"""Malformed datasets, through ``ps-lab reconstruct`` as a user runs it.

Images all black, NaN or saturated; light tables that are coplanar, too short or not numbers;
``filenames.txt`` naming missing or escaping files; masks and frames of the wrong size, headers
claiming 40000 x 40000 pixels, truncated or mixed-depth images, links that loop. Each is refused
before any work, exit 2, one ``error:`` line naming the offending file (README, "Failure
behaviour"; the table's engine is ``tests/helpers/bad_input.py``).
"""

from __future__ import annotations

import os
import shutil
import struct
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import tifffile
from helpers.bad_input import (
    NOT_UTF8,
    CaseTable,
    MiB,
    ds_name,
    fill_images,
    forge_png_size,
    image_files,
    lacks,
    png_chunk,
    read_rows,
    succeeded,
    write_lines,
    write_png16,
)


CASES = CaseTable()
case = CASES.case


# Group 1: bad input accepted silently -----------------------------------------------------------


@case("g1-all-zero-png", ds_name)
def _(w):
    fill_images(w.png(), np.zeros_like)
    return ["reconstruct", str(w.ds)]


@case("g1-nan-npy", lambda w: (str(w.root / "npy"),))
def _(w):
    fill_images(w.copy("npy"), lambda a: np.full_like(a, np.nan))
    return ["reconstruct", str(w.root / "npy")]


@case("g1-nan-float-tiff", lambda w: (str(w.root / "tiff"),))
def _(w):
    fill_images(w.copy("tiff"), lambda a: np.full_like(a, np.nan))
    return ["reconstruct", str(w.root / "tiff")]


@case("g1-all-saturated", ds_name)
def _(w):
    fill_images(w.png(), lambda a: np.full_like(a, 65535))
    return ["reconstruct", str(w.ds), "--method", "ls"]


@case("g1-mask-on-black-background", lambda w: (str(w.ds), "mask.png"))
def _(w):
    ds = w.png()
    mask = np.zeros((16, 16), np.uint8)
    mask[0, 0] = 255  # a corner of the background: every image is black there
    cv2.imwrite(str(ds / "mask.png"), mask)
    return ["reconstruct", str(ds)]


# Group 4: the right file named, early ----------------------------------------------------------


def light_table_case(id: str, rows_of: Callable[[np.ndarray], np.ndarray], also_corrupt=True):
    @case(
        id,
        lambda w: ("light_directions.txt",),
        check=lambda w, r, line: lacks(line, "003.png"),
    )
    def _(w):
        ds = w.png()
        write_lines(ds / "light_directions.txt", rows_of(read_rows(ds / "light_directions.txt")))
        if also_corrupt:  # the lights must be refused before any frame is read
            (ds / "003.png").write_bytes(b"not a png")
        return ["reconstruct", str(ds)]


def _coplanar(rows):
    rows = rows.copy()
    rows[:, 1] = 0.0  # every light in the x-z plane through the origin
    return rows


light_table_case("g4-lights-coplanar", _coplanar)
light_table_case("g4-lights-identical", lambda rows: np.repeat(rows[:1], len(rows), axis=0))
light_table_case("g4-lights-antiparallel", lambda rows: np.array([[0, 0, 1], [0, 0, -1]] * 4))


def _lp_instead_of_light_directions(ds: Path, rows: np.ndarray, names: list[str]) -> Path:
    """Replace light_directions.txt and filenames.txt by a RelightLab ``dirs.lp``."""
    (ds / "light_directions.txt").unlink()
    (ds / "filenames.txt").unlink()
    lp = ds / "dirs.lp"
    lines = [f"{n} {x} {y} {z}\n" for n, (x, y, z) in zip(names, rows, strict=True)]
    lp.write_text(f"{len(names)}\n" + "".join(lines))
    return lp


@case("x-lp-lists-more-images-than-the-folder", ("dirs.lp", "009.png", "010.png"))
def _(w):
    ds = w.png()
    rows = read_rows(ds / "light_directions.txt")
    names = [f.name for f in image_files(ds)] + ["009.png", "010.png"]
    _lp_instead_of_light_directions(ds, np.vstack([rows, rows[:2]]), names)
    return ["reconstruct", str(ds)]


@case("x-lp-coplanar", ("dirs.lp", "one plane"), check=lambda w, r, line: lacks(line, "003"))
def _(w):
    ds = w.png()
    rows = _coplanar(read_rows(ds / "light_directions.txt"))
    _lp_instead_of_light_directions(ds, rows, [f.name for f in image_files(ds)])
    (ds / "003.png").write_bytes(b"not a png")  # refused before any frame is read
    return ["reconstruct", str(ds)]


@case("g4-two-lights-two-images", ("light_directions.txt",))
def _(w):
    ds = w.png()
    write_lines(ds / "light_directions.txt", read_rows(ds / "light_directions.txt")[:2])
    write_lines(ds / "light_intensities.txt", read_rows(ds / "light_intensities.txt")[:2])
    (ds / "filenames.txt").write_text("001.png\n002.png\n")
    return ["reconstruct", str(ds)]


@case(
    "g4-first-image-wrong-size", ("001.png",), check=lambda w, r, line: lacks(line, "mask.png")
)
def _(w):
    ds = w.png()
    write_png16(ds / "001.png", np.full((20, 20), 1000))
    return ["reconstruct", str(ds)]


@case(
    "g4-first-image-forged-header",
    ("001.png",),
    check=lambda w, r, line: lacks(line, "mask.png"),
)
def _(w):
    ds = w.png()
    forge_png_size(ds / "001.png", 20, 16)
    return ["reconstruct", str(ds)]


@case(
    "g4-dark-frame-wrong-size", ("dark.png",), check=lambda w, r, line: lacks(line, "001.png")
)
def _(w):
    ds = w.png()
    write_png16(ds / "dark.png", np.zeros((12, 12)))
    return ["reconstruct", str(ds)]


@case(
    "g4-image-is-a-folder",
    ("005.png",),
    check=lambda w, r, line: lacks(line, "does not exist"),
)
def _(w):
    ds = w.png()
    (ds / "005.png").unlink()
    (ds / "005.png").mkdir()
    return ["reconstruct", str(ds)]


@case("g4-truncated-png", ("003.png",))
def _(w):
    ds = w.png()
    raw = (ds / "003.png").read_bytes()
    (ds / "003.png").write_bytes(raw[: len(raw) // 2])
    return ["reconstruct", str(ds)]


@case("g5-unreadable-dataset-folder", ds_name, root_ok=False)
def _(w):
    w.png().chmod(0)
    return ["reconstruct", str(w.ds)]


# Group 7: sizes claimed by headers -------------------------------------------------------------

HUGE = 40000


def _small_rss(w, result, line) -> None:
    assert result.max_rss < 600 * MiB, f"peak RSS {result.max_rss / MiB:.0f} MiB"


@case("g7-png-header-40000-all", ("001.png",), check=_small_rss)
def _(w):
    ds = w.png()
    for file in image_files(ds):
        forge_png_size(file, HUGE, HUGE)
    forge_png_size(ds / "mask.png", HUGE, HUGE)
    (ds / "normal_gt.npy").unlink()
    return ["reconstruct", str(ds)]


@case("g7-png-header-40000-third", ("003.png",), check=_small_rss)
def _(w):
    ds = w.png()
    forge_png_size(ds / "003.png", HUGE, HUGE)
    return ["reconstruct", str(ds)]


@case("g7-mask-header-40000", ("mask.png",), check=_small_rss)
def _(w):
    ds = w.png()
    forge_png_size(ds / "mask.png", HUGE, HUGE)
    return ["reconstruct", str(ds)]


@case("g7-npy-header-40000", ("001.npy",), check=_small_rss)
def _(w):
    ds = w.copy("npy")
    header = {"descr": "<f4", "fortran_order": False, "shape": (HUGE, HUGE)}
    with (ds / "001.npy").open("wb") as stream:
        np.lib.format.write_array_header_1_0(stream, header)
        stream.write(b"\0" * 1024)
    return ["reconstruct", str(ds)]


@case("g7-tiff-header-40000", ("001.tif", "001.tiff"), check=_small_rss)
def _(w):
    ds = w.copy("tiff")
    first = image_files(ds)[0]
    with tifffile.TiffFile(first, mode="r+b") as tif:  # claim 40000x40000, keep 16x16 data
        tif.pages[0].tags["ImageWidth"].overwrite(HUGE)
        tif.pages[0].tags["ImageLength"].overwrite(HUGE)
    return ["reconstruct", str(ds)]


@case("g7-pfm-header-40000", ("001.pfm",), check=_small_rss)
def _(w):
    ds = w.png()
    (ds / "001.pfm").write_bytes(b"Pf\n40000 40000\n-1.0\n" + b"\0" * 4096)
    names = (ds / "filenames.txt").read_text().replace("001.png", "001.pfm")
    (ds / "filenames.txt").write_text(names)
    return ["reconstruct", str(ds)]


@case("g7-normal-gt-header-huge", ("normal_gt.npy",), check=_small_rss)
def _(w):
    ds = w.png()
    header = {"descr": "<f4", "fortran_order": False, "shape": (HUGE, HUGE, 3)}
    with (ds / "normal_gt.npy").open("wb") as stream:
        np.lib.format.write_array_header_1_0(stream, header)
    return ["reconstruct", str(ds)]


# Inputs the issue did not list -----------------------------------------------------------------


@case("x-empty-folder", lambda w: (str(w.root / "empty"),))
def _(w):
    (w.root / "empty").mkdir()
    return ["reconstruct", str(w.root / "empty")]


@case("x-missing-folder", lambda w: (str(w.root / "nowhere"),))
def _(w):
    return ["reconstruct", str(w.root / "nowhere")]


@case("x-dataset-is-a-file", lambda w: (str(w.ds / "001.png"),))
def _(w):
    return ["reconstruct", str(w.png() / "001.png")]


@case("x-only-light-directions", lambda w: (str(w.root / "lonely"),))
def _(w):
    (w.root / "lonely").mkdir()
    (w.root / "lonely" / "light_directions.txt").write_text("0 0 1\n")
    return ["reconstruct", str(w.root / "lonely")]


@case("x-symlink-loop-image", ("001.png",))
def _(w):
    ds = w.png()
    (ds / "001.png").unlink()
    os.symlink("001.png", ds / "001.png")
    return ["reconstruct", str(ds)]


@case("x-symlink-loop-dataset", lambda w: (str(w.root / "loop"),))
def _(w):
    os.symlink("loop", w.root / "loop")
    return ["reconstruct", str(w.root / "loop")]


for _name in ("light_directions.txt", "mask.png", "filenames.txt", "light_intensities.txt"):

    @case(f"x-folder-instead-of-{_name}", (_name,))
    def _(w, name=_name):
        ds = w.png()
        (ds / name).unlink()
        (ds / name).mkdir()
        return ["reconstruct", str(ds)]


@case("x-mask-wrong-size", ("mask.png",))
def _(w):
    ds = w.png()
    cv2.imwrite(str(ds / "mask.png"), np.full((8, 8), 255, np.uint8))
    return ["reconstruct", str(ds)]


@case("x-mask-empty", ("mask.png",))
def _(w):
    ds = w.png()
    cv2.imwrite(str(ds / "mask.png"), np.zeros((16, 16), np.uint8))
    return ["reconstruct", str(ds)]


@case("x-mask-garbage", ("mask.png",))
def _(w):
    ds = w.png()
    (ds / "mask.png").write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(64))
    return ["reconstruct", str(ds)]


def text_case(id: str, name: str, content: bytes | Callable[[bytes], bytes]):
    @case(id, (name,))
    def _(w):
        ds = w.png()
        path = ds / name
        path.write_bytes(content(path.read_bytes()) if callable(content) else content)
        return ["reconstruct", str(ds)]


text_case("x-lights-row-nan", "light_directions.txt", lambda b: b"nan 0 1\n" + b.split(b"\n", 1)[1])
text_case("x-lights-row-inf", "light_directions.txt", lambda b: b"inf 0 1\n" + b.split(b"\n", 1)[1])
text_case("x-lights-two-columns", "light_directions.txt", b"0 1\n" * 8)
text_case("x-lights-four-columns", "light_directions.txt", b"0 0 1 1\n" * 8)
text_case("x-lights-empty", "light_directions.txt", b"")
text_case("x-lights-words", "light_directions.txt", b"left up front\n" * 8)
text_case("x-lights-not-utf8", "light_directions.txt", b"\xff\xfe\x00 0 1\n" * 8)
text_case("x-lights-zero-row", "light_directions.txt", lambda b: b"0 0 0\n" + b.split(b"\n", 1)[1])
text_case("x-lights-40-rows", "light_directions.txt", lambda b: b * 5)
text_case("x-lights-7-rows", "light_directions.txt", lambda b: b"\n".join(b.split(b"\n")[1:]))
text_case(
    "x-intensities-zero", "light_intensities.txt", lambda b: b"0 0 0\n" + b.split(b"\n", 1)[1]
)
text_case(
    "x-intensities-negative",
    "light_intensities.txt",
    lambda b: b"-1 -1 -1\n" + b.split(b"\n", 1)[1],
)
text_case(
    "x-intensities-nan", "light_intensities.txt", lambda b: b"nan 1 1\n" + b.split(b"\n", 1)[1]
)
text_case("x-intensities-wrong-count", "light_intensities.txt", b"1 1 1\n" * 3)
text_case("x-filenames-missing-file", "filenames.txt", lambda b: b.replace(b"004.png", b"404.png"))
text_case("x-filenames-duplicate", "filenames.txt", lambda b: b.replace(b"004.png", b"003.png"))
text_case("x-filenames-not-utf8", "filenames.txt", b"\xff\xfe001.png\n")
text_case("x-filenames-empty", "filenames.txt", b"\n\n")
text_case("x-filenames-names-mask", "filenames.txt", lambda b: b.replace(b"004.png", b"mask.png"))
text_case(
    "x-filenames-escapes-folder",
    "filenames.txt",
    lambda b: b.replace(b"004.png", b"../../etc/passwd"),
)


@case("x-nine-images-eight-lights", ("light_directions.txt", "filenames.txt", "009.png"))
def _(w):
    ds = w.png()
    shutil.copy(ds / "008.png", ds / "009.png")
    (ds / "filenames.txt").write_text((ds / "filenames.txt").read_text() + "009.png\n")
    return ["reconstruct", str(ds)]


@case("x-tiff-five-channels", ("001.tif", "001.tiff"))
def _(w):
    ds = w.copy("tiff")
    tifffile.imwrite(
        image_files(ds)[0],
        np.ones((16, 16, 5), np.float32),
        photometric="minisblack",
        planarconfig="contig",
    )
    return ["reconstruct", str(ds)]


@case("x-8-and-16-bit-mixed", ("002.png",))
def _(w):
    ds = w.png()
    image = cv2.imread(str(ds / "002.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(ds / "002.png"), (image // 257).astype(np.uint8))
    return ["reconstruct", str(ds)]


@case("x-colour-and-grey-mixed", ("002.png",))
def _(w):
    ds = w.png()
    image = cv2.imread(str(ds / "002.png"), cv2.IMREAD_UNCHANGED)
    write_png16(ds / "002.png", np.dstack([image] * 3))
    return ["reconstruct", str(ds)]


@case("x-images-of-mixed-sizes", ("004.png",))
def _(w):
    ds = w.png()
    write_png16(ds / "004.png", np.full((16, 17), 1000))
    return ["reconstruct", str(ds)]


@case("x-unreadable-image", ("003.png",), root_ok=False)
def _(w):
    ds = w.png()
    (ds / "003.png").chmod(0)
    return ["reconstruct", str(ds)]


@case("x-normal-gt-wrong-shape", ("normal_gt.npy",))
def _(w):
    ds = w.png()
    np.save(ds / "normal_gt.npy", np.zeros((8, 8, 3), np.float32))
    return ["reconstruct", str(ds)]


@case("x-normal-gt-nan", ("normal_gt.npy",))
def _(w):
    ds = w.png()
    np.save(ds / "normal_gt.npy", np.full((16, 16, 3), np.nan, np.float32))
    return ["reconstruct", str(ds)]


@case("s3-dataset-not-utf8", (), code=0, check=succeeded)
def _(w):
    return ["reconstruct", str(w.copy("png", NOT_UTF8)), "--out", str(w.root / "out")]


# s6: lines that were wrong or not one -----------------------------------------------------------


def _cut_idat(path: Path) -> None:
    """Halve the compressed stream of a PNG, keeping every chunk's CRC valid and IEND."""
    raw = path.read_bytes()
    out, at = raw[:8], 8
    while at < len(raw):
        (length,) = struct.unpack(">I", raw[at : at + 4])
        kind, data = raw[at + 4 : at + 8], raw[at + 8 : at + 8 + length]
        out += png_chunk(kind, data[: len(data) // 2] if kind == b"IDAT" else data)
        at += 12 + length
    path.write_bytes(out)


@case("s6-png16-stream-cut-short", ("003.png",),
      check=lambda w, r, line: lacks(r.stderr, "libpng error"))
def _(w):
    ds = w.copy("png")
    _cut_idat(ds / "003.png")
    return ["reconstruct", str(ds)]


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "g1-all-zero-png",
    "g1-nan-float-tiff",
    "g1-nan-npy",
    "g4-dark-frame-wrong-size",
    "g4-first-image-forged-header",
    "g4-first-image-wrong-size",
    "g4-image-is-a-folder",
    "g4-lights-coplanar",
    "g4-lights-identical",
    "g4-truncated-png",
    "g4-two-lights-two-images",
    "g7-mask-header-40000",
    "g7-npy-header-40000",
    "g7-png-header-40000-all",
    "g7-png-header-40000-third",
    "g7-tiff-header-40000",
    "s6-png16-stream-cut-short",
    "x-8-and-16-bit-mixed",
    "x-empty-folder",
    "x-filenames-duplicate",
    "x-folder-instead-of-mask.png",
    "x-images-of-mixed-sizes",
    "x-intensities-zero",
    "x-lights-not-utf8",
    "x-lights-row-nan",
    "x-lp-coplanar",
    "x-lp-lists-more-images-than-the-folder",
    "x-symlink-loop-image",
    "x-tiff-five-channels",
}
test_bad_input = CASES.test(CI_CASES)
