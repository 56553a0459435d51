"""Damaged image metadata, OpenEXR frames and ``.lp`` light files (the formats labs bring).

Damaged colour metadata is not an error: the format's documented default applies (a JPEG is
sRGB) with one ``warning:`` line naming the file. A truncated or forged OpenEXR frame is refused
before OpenEXR reads it; a ``.lp`` name that matches several files or rows, a row that overflows
or has the wrong count, is named with its line. The surfaces are called in one process with many
variants, and through ``ps-lab reconstruct`` (the table) as a user runs it. The PTP/IP
responder's hostile initiators are in ``tests/test_ptpip_camera.py``.
"""

from __future__ import annotations

import json
import logging
import shutil
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest
import tifffile
from helpers.bad_input import CaseTable, Workspace, named, png_chunk
from helpers.hostile import Result, temporary_leftovers

from ps_lab.errors import DatasetError
from ps_lab.io import encoding as encoding_module
from ps_lab.io import images as images_module
from ps_lab.io.encoding import image_encoding, srgb_to_linear
from ps_lab.io.images import is_supported, read_image
from ps_lab.io.light_files import lp_directions_for, lp_image_files, read_lp_rows


CASES = CaseTable(timeout=180, quiet_stdout=True)
case = CASES.case


# --- damaged metadata, built byte by byte ------------------------------------------------------


def segment(marker: int, body: bytes) -> bytes:
    """A JPEG marker segment: FF marker, big-endian length (itself included), body."""
    return bytes([0xFF, marker]) + struct.pack(">H", len(body) + 2) + body


def with_segments(jpeg: bytes, *segments: bytes) -> bytes:
    """``jpeg`` with ``segments`` inserted after its SOI marker."""
    return jpeg[:2] + b"".join(segments) + jpeg[2:]


def exif_block(space: int = 1, *, count: int = 1, sub_ifd: int = 26, cut: int | None = None,
               order: bytes = b"II") -> bytes:  # fmt: skip
    """An APP1 EXIF body: IFD0 at 8 with the Exif IFD pointer, the Exif IFD with ColorSpace."""
    o = "<" if order == b"II" else ">"
    ifd0 = struct.pack(o + "HHHII", 1, 0x8769, 4, 1, sub_ifd) + struct.pack(o + "I", 0)
    sub = struct.pack(o + "HHHIHH", count, 0xA001, 3, 1, space, 0) + struct.pack(o + "I", 0)
    tiff = order + struct.pack(o + "HI", 42, 8) + ifd0 + sub
    return b"Exif\0\0" + (tiff if cut is None else tiff[:cut])


def icc_profile(curve: bytes, *, tags: tuple[bytes, ...] = (b"rTRC", b"gTRC", b"bTRC")) -> bytes:
    """An ICC profile holding ``curve`` as each tone curve (one shared tag body)."""
    offset = 128 + 4 + 12 * len(tags)
    table = b"".join(struct.pack(">4sII", t, offset, len(curve)) for t in tags)
    profile = bytearray(128) + struct.pack(">I", len(tags)) + table + curve
    profile[:4] = struct.pack(">I", len(profile))
    return bytes(profile)


def curv(gamma: float | None = None, table: tuple[int, ...] = ()) -> bytes:
    """An ICC ``curv`` tag: a gamma (u8.8) or a table of u16 values."""
    if gamma is not None:
        return b"curv" + bytes(4) + struct.pack(">IH", 1, round(gamma * 256)) + b"\0\0"
    return b"curv" + bytes(4) + struct.pack(f">I{len(table)}H", len(table), *table)


def para(function: int, *params: float) -> bytes:
    """An ICC ``para`` tag: function type and s15.16 parameters (g, a, b, c, d, e, f)."""
    values = b"".join(struct.pack(">i", round(v * 65536)) for v in params)
    return b"para" + bytes(4) + struct.pack(">HH", function, 0) + values


def icc_segment(profile: bytes, number: int = 1, total: int = 1) -> bytes:
    return segment(0xE2, b"ICC_PROFILE\0" + bytes([number, total]) + profile)


GAMMA_18 = icc_profile(curv(1.8))
SRGB_PARA = icc_profile(para(3, 2.4, 1 / 1.055, 0.055 / 1.055, 1 / 12.92, 0.04045))

# name -> the segments that damage a JPEG's metadata (each must decode as sRGB, with a warning)
DAMAGED_JPEG: dict[str, tuple[bytes, ...]] = {
    "exif-empty": (segment(0xE1, b"Exif\0\0"),),
    "exif-truncated-ifd": (segment(0xE1, exif_block(cut=20)),),
    "exif-ifd-count-past-the-end": (segment(0xE1, exif_block(count=500)),),
    "exif-ifd-offset-outside": (segment(0xE1, exif_block(sub_ifd=99_999)),),
    "exif-ifd-loops-to-ifd0": (segment(0xE1, exif_block(sub_ifd=8)),),
    "exif-no-byte-order": (segment(0xE1, b"Exif\0\0XX" + bytes(30)),),
    "exif-colour-space-undefined": (segment(0xE1, exif_block(space=7)),),
    "icc-empty-chunk": (segment(0xE2, b"ICC_PROFILE\0"),),
    "icc-truncated-tag-table": (icc_segment(GAMMA_18[:140]),),
    "icc-tag-table-count-past-the-end": (
        icc_segment(GAMMA_18[:128] + struct.pack(">I", 10_000) + GAMMA_18[132:]),
    ),
    "icc-tag-offset-outside": (
        icc_segment(GAMMA_18[:136] + struct.pack(">I", 1 << 30) + GAMMA_18[140:]),
    ),
    "icc-chunk-missing": (icc_segment(GAMMA_18, 2, 2),),
    "icc-no-tone-curves": (icc_segment(icc_profile(curv(1.8), tags=(b"desc",))),),
    "icc-zero-slope": (icc_segment(icc_profile(para(3, 2.4, 0.0, 0.05, 0.04, 0.04))),),
    "icc-negative-gamma": (icc_segment(icc_profile(para(0, -2.2))),),
    "icc-zero-gamma-para": (icc_segment(icc_profile(para(0, 0.0))),),
    "icc-zero-gamma-curv": (icc_segment(icc_profile(curv(0.0))),),
    "icc-non-monotonic-table": (icc_segment(icc_profile(curv(table=(0, 60000, 1000, 65535)))),),
    "icc-flat-table": (icc_segment(icc_profile(curv(table=(30000, 30000)))),),
    "icc-negative-slope": (icc_segment(icc_profile(para(1, 2.2, -1.0, 1.0))),),
    "icc-unknown-para-function": (icc_segment(icc_profile(para(9, 2.2))),),
    "icc-curv-table-cut-short": (icc_segment(icc_profile(curv(table=(0, 65535))[:14])),),
    "exif-and-icc-both-damaged": (segment(0xE1, b"Exif\0\0"), icc_segment(GAMMA_18[:140])),
}


def grey_jpeg(level: int = 128, size: int = 8) -> bytes:
    ok, encoded = cv2.imencode(".jpg", np.full((size, size, 3), level, np.uint8),
                               [cv2.IMWRITE_JPEG_QUALITY, 100])  # fmt: skip
    assert ok
    return encoded.tobytes()


@pytest.fixture
def warnings_logged(caplog):
    caplog.set_level(logging.WARNING)
    encoding_module._WARNED.clear()  # a file warns once per process: fresh for each test
    return caplog


@pytest.mark.parametrize("damage", sorted(DAMAGED_JPEG))
def test_damaged_jpeg_metadata_is_srgb_with_one_warning(damage, tmp_path, warnings_logged):
    path = tmp_path / f"{damage}.jpg"
    path.write_bytes(with_segments(grey_jpeg(), *DAMAGED_JPEG[damage]))
    image = read_image(path)
    assert image.encoding == "srgb"
    # JPEG at quality 100 of a flat grey: every value 128 +- 1 count
    np.testing.assert_allclose(image.data, srgb_to_linear(np.float32(128 / 255)), atol=0.005)
    read_image(path)  # a second reading (a second pass) warns no more
    records = [r for r in warnings_logged.records if r.levelno == logging.WARNING]
    assert len(records) == 1, [r.getMessage() for r in records]
    message = records[0].getMessage()
    assert message.startswith(f"{path}: ") and "decoded as srgb (JPEG default)" in message
    assert "\n" not in message


@pytest.mark.parametrize(
    ("segments", "label"),
    [
        ((), "srgb (JPEG default)"),
        ((segment(0xE1, exif_block(1)),), "srgb (EXIF)"),
        ((segment(0xE1, exif_block(1, order=b"MM")),), "srgb (EXIF)"),
        ((segment(0xE1, exif_block(0xFFFF)),), "srgb (JPEG default)"),  # uncalibrated
        ((icc_segment(GAMMA_18),), "icc (ICC profile)"),
        ((icc_segment(GAMMA_18[:70], 1, 2), icc_segment(GAMMA_18[70:], 2, 2)), "icc (ICC profile)"),
        ((icc_segment(SRGB_PARA),), "srgb (ICC profile)"),
        ((icc_segment(icc_profile(para(0, 1.0))),), "linear (ICC profile)"),
    ],
    ids=["none", "exif-srgb", "exif-big-endian", "exif-uncalibrated", "icc-gamma-1.8",
         "icc-in-two-chunks", "icc-srgb-para", "icc-linear"],  # fmt: skip
)
def test_sound_jpeg_metadata_is_used_without_a_warning(segments, label, tmp_path, warnings_logged):
    path = tmp_path / "sound.jpg"
    path.write_bytes(with_segments(grey_jpeg(), *segments))
    assert image_encoding(path).label == label
    assert not warnings_logged.records


def _png_with(tmp_path: Path, name: str, *chunks: bytes, depth16: bool = False) -> Path:
    image = np.full((4, 4), 32768 if depth16 else 128, np.uint16 if depth16 else np.uint8)
    raw = cv2.imencode(".png", image)[1].tobytes()
    path = tmp_path / name
    path.write_bytes(raw[:33] + b"".join(chunks) + raw[33:])
    return path


@pytest.mark.parametrize(
    ("chunks", "label", "warned"),
    [
        ((png_chunk(b"iCCP", b"p\0\0" + b"not zlib"),), "linear (no metadata)", True),
        ((png_chunk(b"iCCP", b"p\0\0" + zlib.compress(GAMMA_18[:140])),), "linear (no metadata)",
         True),
        ((png_chunk(b"iCCP", b"p\0\0" + zlib.compress(icc_profile(para(0, -2.2)))),
          png_chunk(b"sRGB", b"\0")), "srgb (PNG sRGB chunk)", True),
        ((png_chunk(b"gAMA", struct.pack(">I", 0)),), "linear (no metadata)", True),
        ((png_chunk(b"gAMA", b"\0\0"),), "linear (no metadata)", True),
        ((png_chunk(b"gAMA", struct.pack(">I", 45455)),), "gamma 2.2 (PNG gAMA chunk)", False),
        ((png_chunk(b"iCCP", b"p\0\0" + zlib.compress(GAMMA_18)),), "icc (ICC profile)", False),
    ],
    ids=["iccp-not-zlib", "iccp-truncated", "iccp-bad-curve-then-srgb", "gama-zero",
         "gama-short", "gama-sound", "iccp-sound"],  # fmt: skip
)
def test_png_metadata_damage_keeps_the_png_rules_and_warns(chunks, label, warned, tmp_path,
                                                           warnings_logged):  # fmt: skip
    path = _png_with(tmp_path, "frame.png", *chunks)
    assert image_encoding(path).label == label
    messages = [r.getMessage() for r in warnings_logged.records]
    assert len(messages) == int(warned), messages
    assert all(m.startswith(f"{path}: ") for m in messages)


def test_sixteen_bit_png_ignores_a_damaged_profile(tmp_path, warnings_logged):
    path = _png_with(tmp_path, "deep.png", png_chunk(b"iCCP", b"p\0\0junk"), depth16=True)
    assert image_encoding(path).label == "linear (16-bit)"
    assert not warnings_logged.records


# --- OpenEXR -----------------------------------------------------------------------------------


def write_exr(path: Path, height: int = 40, width: int = 30, compression=None, tiled=False):
    rng = np.random.default_rng(7)
    channels = {c: rng.random((height, width)).astype(np.float16) for c in "RGB"}
    header = {"type": OpenEXR.tiledimage if tiled else OpenEXR.scanlineimage,
              "compression": compression or OpenEXR.ZIP_COMPRESSION}  # fmt: skip
    if tiled:
        tiles = OpenEXR.TileDescription()
        tiles.xSize, tiles.ySize, tiles.mode = 16, 16, OpenEXR.ONE_LEVEL
        header["tiles"] = tiles
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def forge_data_window(path: Path, box: tuple[int, int, int, int]) -> None:
    raw = bytearray(path.read_bytes())
    at = raw.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    raw[at : at + 16] = struct.pack("<4i", *box)
    path.write_bytes(bytes(raw))


def _exr_cut(path: Path, keep: float) -> None:
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * keep)])


def _exr_cut_in_header(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:60])


def _exr_cut_in_offsets(path: Path) -> None:
    raw = path.read_bytes()
    path.write_bytes(raw[: raw.index(b"\0\0", raw.index(b"type")) + 8])


EXR_DAMAGE: dict[str, Callable[[Path], None]] = {
    "truncated-two-thirds": lambda p: _exr_cut(p, 2 / 3),
    "truncated-last-byte": lambda p: _exr_cut(p, 1 - 1e-4),
    "truncated-in-the-header": _exr_cut_in_header,
    "truncated-in-the-offset-table": _exr_cut_in_offsets,
    "data-window-3.6-tib": lambda p: forge_data_window(p, (0, 0, 999_999, 999_999)),
    "data-window-wide-same-chunks": lambda p: forge_data_window(p, (0, 0, (1 << 30), 39)),
    "data-window-inverted": lambda p: forge_data_window(p, (10, 10, 0, 0)),
    "data-window-overflowing": lambda p: forge_data_window(p, (-(1 << 31), 0, (1 << 31) - 1, 39)),
    "not-exr": lambda p: p.write_bytes(b"v/1\x01" + bytes(40)),
}


@pytest.mark.parametrize("damage", sorted(EXR_DAMAGE))
@pytest.mark.parametrize("layout", ["scanline-zip", "scanline-none", "tiled"])
def test_damaged_exr_is_refused_before_openexr_reads_it(damage, layout, tmp_path, monkeypatch,
                                                        capfd):  # fmt: skip
    path = tmp_path / "frame.exr"
    none = OpenEXR.NO_COMPRESSION if layout == "scanline-none" else None
    write_exr(path, compression=none, tiled=layout == "tiled")
    EXR_DAMAGE[damage](path)

    def no_openexr(*args, **kwargs):
        raise AssertionError("OpenEXR was asked to read a file whose layout is broken")

    monkeypatch.setattr(images_module.OpenEXR, "File", no_openexr)
    with pytest.raises(DatasetError) as refused:
        read_image(path)
    message = str(refused.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    assert capfd.readouterr() == ("", "")


@pytest.mark.parametrize("layout", ["scanline-zip", "scanline-none", "tiled"])
def test_sound_exr_reads_silently(layout, tmp_path, capfd):
    path = tmp_path / "frame.exr"
    none = OpenEXR.NO_COMPRESSION if layout == "scanline-none" else None
    write_exr(path, compression=none, tiled=layout == "tiled")
    assert read_image(path).data.shape == (40, 30, 3)
    assert capfd.readouterr() == ("", "")


def test_exr_larger_than_the_memory_is_refused_before_openexr(tmp_path, monkeypatch):
    path = tmp_path / "frame.exr"
    write_exr(path)
    monkeypatch.setattr(images_module, "available_memory", lambda: 10_000)
    monkeypatch.setattr(images_module.OpenEXR, "File", None)  # never reached
    with pytest.raises(DatasetError, match=r"frame.exr: image of 30x40 pixels would need"):
        read_image(path)


# --- .lp light files ---------------------------------------------------------------------------

# name: (files in the folder, the .lp's rows after its count line, expected: rows of the
# directions in image order, or the error's text after "dirs.lp: ")
LP_TABLE: dict[str, tuple[tuple[str, ...], tuple[str, ...], object]] = {
    "two-folders-same-name": (("a/001.png", "b/001.png", "c.png"),
                              ("a/001.png 0 0 1", "b\\001.png 1 0 1", "c.png 0 1 1"), (0, 1, 2)),
    "two-extensions-same-stem": (("001.png", "001.tif", "c.png"),
                                 ("001.png 0 0 1", "001.tif 1 0 1", "c.png 0 1 1"), (0, 1, 2)),
    "stem-fallback-unambiguous": (("image01.png", "image02.png", "image03.png"),
                                  ("jpg/Image01.JPG 0 0 1", "jpg/Image02.JPG 1 0 1",
                                   "jpg/Image03.JPG 0 1 1"), (0, 1, 2)),
    "stem-matches-two-extensions": (("001.png", "001.tif", "c.png", "d.png"),
                                    ("001.jpg 0 0 1", "c.png 1 0 1", "d.png 0 1 1"),
                                    "line 2: 001.jpg is not there and matches 2 files"),
    "two-rows-one-file": (("001.png", "c.png", "d.png"),
                          ("001.png 0 0 1", "001.jpg 1 0 1", "c.png 0 1 1"),
                          "lines 2 and 3 (001.png and 001.jpg) are both the image 001.png"),
    "folders-flattened": (("001.png", "c.png", "d.png"),
                          ("a/001.png 0 0 1", "b/001.png 1 0 1", "c.png 0 1 1"),
                          "lines 2 and 3 (a/001.png and b/001.png) are both the image 001.png"),
    "row-overflows": (("a.png", "b.png", "c.png"),
                      ("a.png 1e200 1e200 1e200", "b.png 0 0 1", "c.png 0 1 1"),
                      "line 2: light direction too long to normalise"),
    "row-infinite": (("a.png", "b.png", "c.png"), ("a.png 1 0 1", "b.png 1e999 0 1", "c.png 0 1 1"),
                     "line 3: a value is NaN or infinite"),
    "row-nan": (("a.png", "b.png", "c.png"), ("a.png 1 0 1", "b.png 0 0 1", "c.png nan 1 1"),
                "line 4: a value is NaN or infinite"),
    "row-four-numbers": (("a.png", "b.png", "c.png"),
                         ("a.png 1 0 1 5", "b.png 0 0 1", "c.png 0 1 1"),
                         "line 2: expected 'filename x y z', got 4 numbers"),
    "row-two-numbers": (("a.png", "b.png", "c.png"), ("a.png 1 0", "b.png 0 0 1", "c.png 0 1 1"),
                        "line 2: expected 'filename x y z'"),
    "row-zero-length": (("a.png", "b.png", "c.png"), ("a.png 0 0 0", "b.png 0 0 1", "c.png 0 1 1"),
                        "line 2: light direction has zero length"),
}
LP_DIRECTIONS = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]]) / np.array([1, 2**0.5, 2**0.5])[:, None]


@pytest.mark.parametrize("name", sorted(LP_TABLE))
def test_lp_matches_by_path_and_names_the_line(name, tmp_path):
    files, rows, expected = LP_TABLE[name]
    for file in files:
        (tmp_path / file).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / file).write_bytes(b"an image")
    lp = tmp_path / "dirs.lp"
    lp.write_text(f"{len(rows)}\n" + "\n".join(rows) + "\n")

    def resolve() -> np.ndarray:
        names, _, lines = read_lp_rows(lp)
        return lp_directions_for(lp, lp_image_files(lp, names, is_supported, lines))

    if isinstance(expected, str):
        with pytest.raises(DatasetError) as refused:
            resolve()
        assert str(refused.value).startswith(f"{lp}: {expected}"), str(refused.value)
    else:
        np.testing.assert_allclose(resolve(), LP_DIRECTIONS[list(expected)], atol=1e-12)


# m: damaged metadata decodes as the documented default, with one warning naming the file


def _srgb_with_one_warning(w: Workspace, result: Result, line: str | None) -> None:
    """A result, decoded as sRGB, and one warning line naming the damaged JPEG."""
    assert not temporary_leftovers(w.home), "temporary files left behind"
    assert result.code == 0, result.stderr
    assert "Traceback" not in result.stderr
    warnings = [line for line in result.lines if line.startswith("warning:")]
    assert len(warnings) == 1 and len(result.lines) == 1, result.stderr
    assert str(w.root / "jpeg" / "001.jpg") in warnings[0], warnings[0]
    metrics = json.loads((w.root / "out" / "metrics.json").read_text())
    assert metrics["encoding"].startswith("srgb"), metrics["encoding"]


def _damage_first_jpeg(w: Workspace, damage: str) -> Path:
    ds = w.copy("jpeg")
    first = ds / "001.jpg"
    first.write_bytes(with_segments(first.read_bytes(), *DAMAGED_JPEG[damage]))
    return ds


for _damage in ("exif-truncated-ifd", "exif-empty", "icc-truncated-tag-table", "icc-zero-slope",
                "icc-negative-gamma"):  # fmt: skip

    @case(f"m-jpeg-{_damage}", named("jpeg", "001.jpg"), code=0, check=_srgb_with_one_warning)
    def _(w, damage=_damage):
        return ["reconstruct", str(_damage_first_jpeg(w, damage)), "--method", "ls", "--out",
                str(w.root / "out")]  # fmt: skip


# e: OpenEXR frames


@case("e-exr-truncated", named("exr", "003.exr"))
def _(w):
    _exr_cut(w.copy("exr") / "003.exr", 2 / 3)
    return ["reconstruct", str(w.root / "exr"), "--method", "ls", "--out", str(w.root / "out")]


@case("e-exr-forged-data-window", named("exr", "002.exr"))
def _(w):
    forge_data_window(w.copy("exr") / "002.exr", (0, 0, 999_999, 999_999))
    return ["reconstruct", str(w.root / "exr"), "--method", "ls", "--out", str(w.root / "out")]


# l: .lp light files


def _lp_rows(w: Workspace, edit: Callable[[list[str]], list[str]]) -> Path:
    ds = w.copy("lp")
    lines = (ds / "dirs.lp").read_text().splitlines()
    (ds / "dirs.lp").write_text("\n".join(edit(lines)) + "\n")
    return ds


@case("l-lp-two-rows-one-image", named("lp", "dirs.lp"))
def _(w):
    ds = _lp_rows(w, lambda lines: [lines[0], lines[1], lines[1].replace("001.png", "001.jpg", 1),
                                    *lines[3:]])  # fmt: skip
    return ["reconstruct", str(ds), "--method", "ls", "--out", str(w.root / "out")]


@case("l-lp-stem-matches-two-files", named("lp", "dirs.lp"))
def _(w):
    ds = _lp_rows(w, lambda lines: [lines[0], lines[1].replace("001.png", "001.jpg", 1),
                                    *lines[2:]])  # fmt: skip
    shutil.copy(ds / "001.png", ds / "001.tif")
    return ["reconstruct", str(ds), "--method", "ls", "--out", str(w.root / "out")]


@case("l-lp-row-overflows", named("lp", "dirs.lp"))
def _(w):
    ds = _lp_rows(w, lambda lines: [*lines[:3], "003.png 1e200 1e200 1e200", *lines[4:]])
    return ["reconstruct", str(ds), "--method", "ls", "--out", str(w.root / "out")]


@case("l-lp-row-four-numbers", named("lp", "dirs.lp"))
def _(w):
    ds = _lp_rows(w, lambda lines: [*lines[:2], lines[2] + " 0.5", *lines[3:]])
    return ["reconstruct", str(ds), "--method", "ls", "--out", str(w.root / "out")]


@pytest.mark.parametrize(
    ("profile", "label", "warned"),
    [(GAMMA_18, "icc (ICC profile)", False), (GAMMA_18[:140], "linear (no metadata)", True),
     (icc_profile(para(3, 2.4, 0.0, 0.05, 0.04, 0.04)), "linear (no metadata)", True)],
    ids=["sound", "truncated", "zero-slope"],
)
def test_tiff_profile_damage_keeps_the_tiff_rule_and_warns(profile, label, warned, tmp_path,
                                                           warnings_logged):  # fmt: skip
    path = tmp_path / "frame.tif"
    tifffile.imwrite(path, np.full((4, 4), 128, np.uint8),
                     extratags=[(34675, 7, len(profile), profile, True)])  # fmt: skip
    assert image_encoding(path).label == label
    messages = [r.getMessage() for r in warnings_logged.records]
    assert len(messages) == int(warned) and all(m.startswith(f"{path}: ") for m in messages)


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "e-exr-forged-data-window",
    "e-exr-truncated",
    "l-lp-row-overflows",
    "l-lp-two-rows-one-image",
    "m-jpeg-exif-truncated-ifd",
    "m-jpeg-icc-zero-slope",
}
test_bad_input = CASES.test(CI_CASES)
