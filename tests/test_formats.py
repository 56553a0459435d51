"""Formats labs bring and expect: ``.lp`` files as RelightLab / AliceVision write them, EXR
images, mesh.ply with normals, units and axes, DirectX normal maps.

Each case is built from a real DiLiGenT object when ../shared/data is present (else from a
simulated one) and compared with the same images read through ``light_directions.txt``: the
observations and lights must be identical, not merely close.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest
from plyfile import PlyData
from typer.testing import CliRunner

from ps_lab.cli import app
from ps_lab.errors import DatasetError
from ps_lab.io.dataset import load_dataset, open_dataset
from ps_lab.io.images import read_image
from ps_lab.io.light_files import read_light_directions, read_lp, write_dome
from ps_lab.io.normal_maps import read_normals_exr
from ps_lab.render.simulate import SimulationSettings, write_simulated_dataset

runner = CliRunner()
DILIGENT_CAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "diligent-8bit" / "cat"


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    """An image folder with light_directions.txt: DiLiGenT cat (first 24 lights) or a simulation."""
    root = tmp_path_factory.mktemp("formats") / "source"
    if (DILIGENT_CAT / "light_directions.txt").exists():
        root.mkdir()
        lights = read_light_directions(DILIGENT_CAT / "light_directions.txt")[:24]
        np.savetxt(root / "light_directions.txt", lights)
        for k in range(1, 25):
            shutil.copy(DILIGENT_CAT / f"{k:03d}.png", root / f"{k:03d}.png")
        shutil.copy(DILIGENT_CAT / "mask.png", root / "mask.png")
    else:
        write_simulated_dataset(root, SimulationSettings(scene="sphere", lights=24, size=48))
        (root / "filenames.txt").unlink()
        (root / "light_intensities.txt").unlink()
    return root


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix == ".png" and p.stem.isdigit())


def _lp_folder(source: Path, tmp_path: Path, name: str = "dirs.lp", *, subfolder: str = "",
               rename=lambda stem: stem, extension=".png", bom=False, newline="\n",
               extra: str = "") -> Path:
    """Copy ``source`` without light_directions.txt, with an .lp naming its images."""
    folder = tmp_path / "rti"
    (folder / subfolder).mkdir(parents=True)
    lights = read_light_directions(source / "light_directions.txt")
    rows = [str(len(lights))]
    for image, light in zip(_images(source), lights, strict=True):
        target = folder / subfolder / f"{rename(image.stem)}.png"
        shutil.copy(image, target)
        written = (Path(subfolder) / f"{rename(image.stem)}{extension}").as_posix()
        rows.append(f"{written} " + " ".join(repr(float(x)) for x in light))
    shutil.copy(source / "mask.png", folder / "mask.png")
    text = newline.join(rows) + newline + extra
    (folder / name).write_bytes(("\ufeff" if bom else "").encode() + text.encode("utf-8"))
    return folder


# Both readers normalise each row; the .lp holds the already-normalised directions, and
# normalising a unit vector again moves each component by at most 2 ulp (|x| <= 1): 4 eps.
LIGHT_RENORMALISED = 4 * np.finfo(np.float64).eps


def _same_as_source(folder: Path, source: Path) -> None:
    expected = load_dataset(source)
    got = load_dataset(folder)
    np.testing.assert_allclose(
        got.light_directions, expected.light_directions, rtol=0, atol=LIGHT_RENORMALISED
    )
    np.testing.assert_array_equal(got.images, expected.images)  # the same PNG files


def test_lp_with_bom_crlf_other_extension_and_case(source, tmp_path, caplog):
    # Written on Windows for JPEGs (Image_001.JPG), read beside the PNGs image_001.png.
    folder = _lp_folder(
        source, tmp_path, "Dirs.LP", rename=lambda s: f"image_{s}", extension=".JPG",
        bom=True, newline="\r\n", extra="\r\n# exported by a dome\r\nextra 0 0 1\r\n",
    )
    lp = folder / "Dirs.LP"
    text = lp.read_text(encoding="utf-8-sig").replace("image_", "Image_")
    lp.write_bytes(b"\xef\xbb\xbf" + text.encode())
    with caplog.at_level(logging.WARNING, logger="ps_lab.io.dataset"):
        _same_as_source(folder, source)
    assert any("1 line(s) after the 24 counted images ignored" in r.getMessage()
               for r in caplog.records)


def test_lp_images_in_a_subfolder(source, tmp_path):
    folder = _lp_folder(source, tmp_path, subfolder="jpg", rename=lambda s: f"Name_{int(s):04d}")
    _same_as_source(folder, source)
    # End to end: ps-lab reconstruct reads the folder as it is.
    result = runner.invoke(app, ["reconstruct", str(folder), "--method", "ls"])
    assert result.exit_code == 0, result.output


def test_two_lp_files_are_named(source, tmp_path):
    folder = _lp_folder(source, tmp_path)
    shutil.copy(folder / "dirs.lp", folder / "old.LP")
    with pytest.raises(DatasetError) as error:
        open_dataset(folder)
    assert str(error.value) == (
        f"{folder}: 2 .lp light files (dirs.lp, old.LP): keep one, or write light_directions.txt"
    )


def test_lp_listing_more_images_than_the_folder_has_is_refused_in_one_line(source, tmp_path):
    folder = _lp_folder(source, tmp_path)
    lp = folder / "dirs.lp"
    names, _ = read_lp(lp)
    (folder / names[-1]).unlink()
    (folder / names[-2]).unlink()
    result = runner.invoke(app, ["reconstruct", str(folder), "--method", "ls"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        f"error: {lp}: lists 24 images but 2 are not in {folder} ({names[-2]}, {names[-1]})"
    ]


def test_lp_with_fewer_rows_than_its_count(source, tmp_path):
    folder = _lp_folder(source, tmp_path)
    lp = folder / "dirs.lp"
    lines = lp.read_text().splitlines()
    lp.write_text("\n".join(lines[:-3]) + "\n")
    with pytest.raises(DatasetError, match=r"dirs.lp: says 24 images but lists 21$"):
        open_dataset(folder)


def test_coplanar_lp_lights_name_the_file(source, tmp_path):
    folder = _lp_folder(source, tmp_path)
    lp = folder / "dirs.lp"
    names, _ = read_lp(lp)
    angles = np.linspace(0, np.pi, len(names))
    rows = [f"{n} {np.cos(a):.6f} 0 {np.sin(a):.6f}" for n, a in zip(names, angles, strict=True)]
    lp.write_text("\n".join([str(len(names)), *rows]) + "\n")
    result = runner.invoke(app, ["reconstruct", str(folder), "--method", "ls"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        f"error: {lp}: all 24 lights lie in one plane through the object: they must span 3 "
        "directions (normals out of that plane cannot be recovered)"
    ]


def _write_exr(path: Path, rgb: np.ndarray, dtype) -> None:
    header = {"type": OpenEXR.scanlineimage, "compression": OpenEXR.PIZ_COMPRESSION}
    channels = {c: np.ascontiguousarray(rgb[..., k].astype(dtype)) for k, c in enumerate("RGB")}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def test_an_exr_folder_reads_like_its_pngs(source, tmp_path):
    # Half-float EXR as a renderer or a RAW converter writes them (separate R, G, B channels):
    # 8-bit values / 255 are exact in float32 and within 2^-11 relative in float16.
    folder = tmp_path / "exr"
    folder.mkdir()
    for name in ("light_directions.txt", "mask.png"):
        shutil.copy(source / name, folder / name)
    for image in _images(source):
        data = read_image(image).data
        rgb = np.repeat(data, 3, axis=2) if data.shape[2] == 1 else data
        kind = np.float16 if image.stem < "013" else np.float32
        _write_exr(folder / f"{image.stem}.exr", rgb, kind)
    expected, got = load_dataset(source), load_dataset(folder)
    np.testing.assert_array_equal(got.light_directions, expected.light_directions)
    half = slice(0, 12)
    np.testing.assert_allclose(got.images[half], expected.images[half], rtol=2**-11, atol=2**-24)
    # float32 EXR: each channel stored rounded (<= 2^-24 relative), their mean rounded again,
    # against the PNG's mean rounded once: at most 3 roundings of 2^-24 apart.
    np.testing.assert_allclose(got.images[12:], expected.images[12:], rtol=3 * 2**-24, atol=0)
    grey = folder / "grey.exr"
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Y": np.ones((4, 5), np.float32)}) as exr:
        exr.write(str(grey))
    assert read_image(grey).data.shape == (4, 5, 1)
    broken = folder / "broken.exr"
    broken.write_bytes(b"v/1\x01" + bytes(40))
    with pytest.raises(DatasetError, match="broken.exr: corrupt or unreadable OpenEXR file"):
        read_image(broken)


def test_mesh_has_vertex_normals_and_says_its_units_and_axes(tmp_path):
    data = tmp_path / "relief"
    write_simulated_dataset(data, SimulationSettings(scene="relief", lights=12, size=48))
    out = tmp_path / "out"
    result = runner.invoke(
        app,
        ["reconstruct", str(data), "--method", "ls", "--out", str(out), "--depth", "poisson",
         "--normal-map", "directx"],
    )
    assert result.exit_code == 0, result.output
    normals = np.load(out / "normals.npy")
    depth = np.load(out / "depth.npy")
    ply = PlyData.read(str(out / "mesh.ply"))
    vertex = ply["vertex"].data
    stored = np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], axis=1)
    np.testing.assert_array_equal(stored, normals[np.isfinite(depth)])
    comments = " | ".join(ply.comments)
    assert "units: pixel widths" in comments
    assert "axes: x right, y up, z toward the camera (z = -depth)" in comments
    # DirectX normal maps: green is -y; normals.npy keeps the camera frame (y up).
    flipped = normals * np.array([1, -1, 1], np.float32)
    np.testing.assert_array_equal(read_normals_exr(out / "normals.exr"), flipped)
    picture = cv2.imread(str(out / "normal16.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    mask = np.linalg.norm(normals, axis=2) > 0.5
    expected = np.rint((flipped[mask] + 1) * 0.5 * 65535)
    np.testing.assert_array_equal(picture[mask], expected)


def test_dome_file_for_relightlab(tmp_path):
    # Two LEDs placed, one too far (NaN): lights3d positions as given, the far one on the dome
    # along its direction; directions are the unit positions.
    positions = np.array([[300.0, 0, 400], [0, -240, 320], [np.nan] * 3])
    directions = np.array([[0.6, 0, 0.8], [0, -0.6, 0.8], [0, 0, 1.0]])
    write_dome(tmp_path / "lights.dome", positions, directions, image_width=640)
    dome = json.loads((tmp_path / "lights.dome").read_text())
    assert dome["lightConfiguration"] == "lights3d" and dome["imageWidth"] == 640
    assert dome["domeDiameter"] == pytest.approx(900.0)  # twice the median distance, 450
    placed = np.array([[p["x"], p["y"], p["z"]] for p in dome["positions3d"]])
    np.testing.assert_allclose(placed, [[300, 0, 400], [0, -240, 320], [0, 0, 450]])
    toward = np.array([[p["x"], p["y"], p["z"]] for p in dome["directions"]])
    np.testing.assert_allclose(toward, directions, atol=1e-12)
    on_sphere = np.array([[p["x"], p["y"], p["z"]] for p in dome["positionsSphere"]])
    np.testing.assert_allclose(np.linalg.norm(on_sphere, axis=1), 450.0)
