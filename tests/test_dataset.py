"""Image readers and dataset loading: round trips with known values for every format and layout."""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
import tifffile

from ps_lab.errors import DatasetError
from ps_lab.io.dataset import load_dataset, load_frames
from ps_lab.io.dng import write_dng
from ps_lab.io.images import read_image, read_pfm, write_pfm
from ps_lab.io.light_files import read_light_directions


def write_png_rgb(path: Path, rgb: np.ndarray) -> None:
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def lambertian_sphere(shape: tuple[int, int], lights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normals (H, W, 3) of a centred sphere and shading (n, H, W) = max(n.l, 0)."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 0.45 * min(h, w)
    nx = (x - (w - 1) / 2) / r
    ny = -(y - (h - 1) / 2) / r
    inside = nx**2 + ny**2 < 1
    nz = np.sqrt(np.clip(1 - nx**2 - ny**2, 0, None))
    normals = np.where(inside[..., None], np.stack([nx, ny, nz], axis=-1), 0.0)
    shading = np.clip(np.einsum("hwk,nk->nhw", normals, lights), 0, None)
    return normals, shading


def upper_lights(n: int, rng: np.random.Generator) -> np.ndarray:
    theta = np.radians(rng.uniform(10, 60, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)


# --- readers ---------------------------------------------------------------------------------


def test_png_8bit_grey_scaled_by_type_max(tmp_path, rng):
    raw = rng.integers(0, 256, (7, 9), dtype=np.uint8)
    raw[2, 3] = 255
    cv2.imwrite(str(tmp_path / "a.png"), raw)
    image = read_image(tmp_path / "a.png")
    assert image.data.dtype == np.float32 and image.data.shape == (7, 9, 1)
    np.testing.assert_allclose(image.data[..., 0], raw / 255.0, rtol=1e-6)
    np.testing.assert_array_equal(image.saturated, raw == 255)


def test_png_16bit_colour_is_rgb(tmp_path, rng):
    rgb = rng.integers(0, 65535, (5, 6, 3), dtype=np.uint16)
    rgb[1, 1, 2] = 65535  # saturated blue only
    write_png_rgb(tmp_path / "c.png", rgb)
    image = read_image(tmp_path / "c.png")
    np.testing.assert_allclose(image.data, rgb / 65535.0, rtol=1e-6)
    assert image.saturated[1, 1] and image.saturated.sum() == (rgb == 65535).any(axis=2).sum()


def test_tiff_16bit_lzw_from_opencv(tmp_path, rng):
    rgb = rng.integers(0, 65000, (6, 4, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "a.tif"), np.ascontiguousarray(rgb[..., ::-1]))
    image = read_image(tmp_path / "a.tif")
    np.testing.assert_allclose(image.data, rgb / 65535.0, rtol=1e-6)


def test_tiff_uncompressed_16bit_and_float(tmp_path, rng):
    rgb = rng.integers(0, 65535, (6, 4, 3), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "b.tiff", rgb, photometric="rgb")
    np.testing.assert_allclose(read_image(tmp_path / "b.tiff").data, rgb / 65535.0, rtol=1e-6)
    values = rng.normal(0.5, 2.0, (6, 4)).astype(np.float32)
    values[0, 0] = np.nan
    tifffile.imwrite(tmp_path / "f.tif", values)
    image = read_image(tmp_path / "f.tif")
    np.testing.assert_array_equal(image.data[1:, :, 0], values[1:])  # floats kept as stored
    assert image.saturated[0, 0] and image.saturated.sum() == 1 and image.data[0, 0, 0] == 0


def test_pfm_round_trip_and_orientation(tmp_path, rng):
    rgb = rng.normal(size=(5, 7, 3)).astype(np.float32)
    write_pfm(tmp_path / "a.pfm", rgb)
    np.testing.assert_array_equal(read_pfm(tmp_path / "a.pfm"), rgb)
    # A hand-written big-endian grey PFM: positive scale, bottom row stored first.
    grey = np.arange(6, dtype=np.float32).reshape(2, 3)
    body = np.ascontiguousarray(grey[::-1]).astype(">f4").tobytes()
    (tmp_path / "b.pfm").write_bytes(b"Pf\n3 2\n1.0\n" + body)
    image = read_image(tmp_path / "b.pfm")
    np.testing.assert_array_equal(image.data[..., 0], grey)
    assert not image.saturated.any()


def test_npy_float_and_integer(tmp_path, rng):
    values = rng.random((4, 5, 3)).astype(np.float32)
    np.save(tmp_path / "a.npy", values)
    np.testing.assert_array_equal(read_image(tmp_path / "a.npy").data, values)
    counts = rng.integers(0, 65536, (4, 5), dtype=np.uint16)
    np.save(tmp_path / "b.npy", counts)
    np.testing.assert_allclose(
        read_image(tmp_path / "b.npy").data[..., 0], counts / 65535.0, rtol=1e-6
    )


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("bad.png", b"not an image"),
        ("bad.tif", b"II*\x00garbage"),
        ("bad.pfm", b"PX\n1 1\n-1\n"),
        ("short.pfm", b"PF\n4 4\n-1.0\n" + b"\0" * 10),
        ("bad.npy", b"\x93NUMPY broken"),
        ("bad.dng", b"this is not a RAW file at all" * 10),
        ("bad.nef", b""),
    ],
)
def test_corrupt_files_raise_naming_the_file(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(DatasetError, match=name):
        read_image(tmp_path / name)


def test_truncated_png_raises(tmp_path, rng):
    cv2.imwrite(str(tmp_path / "t.png"), rng.integers(0, 65535, (32, 32), dtype=np.uint16))
    data = (tmp_path / "t.png").read_bytes()
    (tmp_path / "t.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="t.png"):
        read_image(tmp_path / "t.png")


def write_test_dng(
    path: Path, scene: np.ndarray, *, black: int = 512, white: int = 16383, exposure_s=None
):
    """A DNG whose 2x2 RGGB blocks all sample the (H, W, 3) linear scene (values in 0..1)."""
    counts = np.clip(np.rint(black + scene * (white - black)), 0, white).astype(np.uint16)
    h, w = scene.shape[:2]
    mosaic = np.empty((2 * h, 2 * w), dtype=np.uint16)
    mosaic[0::2, 0::2] = counts[..., 0]
    mosaic[0::2, 1::2] = counts[..., 1]
    mosaic[1::2, 0::2] = counts[..., 1]
    mosaic[1::2, 1::2] = counts[..., 2]
    write_dng(path, mosaic, black_level=black, white_level=white, exposure_s=exposure_s)
    return (counts.astype(np.float64) - black) / (white - black)


def test_dng_through_read_image(tmp_path, rng):
    scene = rng.random((12, 16, 3)) * 0.9
    scene[2, 2, 1] = 1.5  # clips at the white level
    expected = write_test_dng(tmp_path / "f.dng", scene, exposure_s=0.25)
    image = read_image(tmp_path / "f.dng")
    np.testing.assert_allclose(image.data, expected, atol=1e-6)
    assert image.saturated[2, 2] and image.saturated.sum() == 1
    assert image.exposure_s == pytest.approx(0.25)
    data = (tmp_path / "f.dng").read_bytes()
    (tmp_path / "cut.dng").write_bytes(data[: len(data) // 3])
    with pytest.raises(DatasetError, match="cut.dng"):
        read_image(tmp_path / "cut.dng")


# --- image folders ---------------------------------------------------------------------------


def make_diligent(folder: Path, rng: np.random.Generator, n: int = 12, shape=(32, 32)) -> dict:
    """A DiLiGenT-style object folder: 16-bit RGB PNGs, shuffled filenames.txt, per-channel
    intensities, mask.png and Normal_gt.mat."""
    folder.mkdir(parents=True)
    lights = upper_lights(n, rng)
    intensities = rng.uniform(0.5, 1.5, (n, 3))
    albedo = np.array([0.6, 0.4, 0.3])
    normals, shading = lambertian_sphere(shape, lights)
    names = [f"{i + 1:03d}.png" for i in range(n)]
    order = rng.permutation(n)  # light k is stored in file names[order[k]]
    for k in range(n):
        rgb = shading[k][..., None] * albedo * intensities[k]
        write_png_rgb(folder / names[order[k]], np.rint(rgb * 40000).astype(np.uint16))
    (folder / "filenames.txt").write_text("\n".join(names[order[k]] for k in range(n)) + "\n")
    np.savetxt(folder / "light_directions.txt", lights)
    np.savetxt(folder / "light_intensities.txt", intensities)
    mask = (np.linalg.norm(normals, axis=2) > 0).astype(np.uint8) * 255
    cv2.imwrite(str(folder / "mask.png"), mask)
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": normals})
    return {
        "lights": lights,
        "intensities": intensities,
        "albedo": albedo,
        "normals": normals,
        "shading": shading,
        "order": order,
        "names": names,
    }


def test_diligent_folder_loads_without_conversion(tmp_path, rng):
    truth = make_diligent(tmp_path / "ballPNG", rng)
    data = load_dataset(tmp_path / "ballPNG")
    n = len(truth["lights"])
    assert data.images.shape == (n, 32, 32) and data.images.dtype == np.float32
    assert data.names == [truth["names"][truth["order"][k]] for k in range(n)]
    np.testing.assert_allclose(data.light_directions, truth["lights"], atol=1e-9)
    np.testing.assert_allclose(data.light_intensities, truth["intensities"], atol=1e-9)
    np.testing.assert_allclose(data.normal_gt, truth["normals"])
    np.testing.assert_array_equal(data.mask, np.linalg.norm(truth["normals"], axis=2) > 0)
    # Intensity division makes each observation albedo.mean() * shading (up to 16-bit rounding).
    expected = truth["shading"] * truth["albedo"].mean() * 40000 / 65535
    np.testing.assert_allclose(data.images, expected, atol=2e-5)
    assert data.valid.all()


def test_colour_channel_rule(tmp_path, rng):
    n, shape = 4, (3, 5)
    folder = tmp_path / "colour"
    folder.mkdir()
    lights = upper_lights(n, rng)
    intensities = rng.uniform(0.5, 2.0, (n, 3))
    frames = rng.uniform(0.1, 1.0, (n, *shape, 3)).astype(np.float32)
    for i in range(n):
        np.save(folder / f"{i}.npy", frames[i])
    np.savetxt(folder / "light_directions.txt", lights)
    np.savetxt(folder / "light_intensities.txt", intensities)
    divided = frames / intensities[:, None, None, :]
    for channel, expected in [
        ("r", divided[..., 0]),
        ("g", divided[..., 1]),
        ("b", divided[..., 2]),
        ("mean", divided.mean(axis=-1)),
    ]:
        np.testing.assert_allclose(
            load_dataset(folder, channel=channel).images, expected, rtol=1e-5
        )
    with pytest.raises(DatasetError, match="channel"):
        load_dataset(folder, channel="x")


def test_grey_images_single_intensity_column_and_thresholds(tmp_path, rng):
    n = 5
    folder = tmp_path / "grey"
    folder.mkdir()
    raw = rng.integers(0, 256, (n, 4, 6), dtype=np.uint8)
    raw[0, 0, 0] = 255
    for i in range(n):
        cv2.imwrite(str(folder / f"img{i}.png"), raw[i])
    np.savetxt(folder / "light_directions.txt", upper_lights(n, rng))
    scale = rng.uniform(0.5, 2.0, n)
    np.savetxt(folder / "light_intensities.txt", scale[:, None])
    data = load_dataset(folder, shadow_threshold=0.2)
    expected = raw / 255.0 / scale[:, None, None]
    np.testing.assert_allclose(data.images, expected, rtol=1e-5)
    np.testing.assert_array_equal(data.valid, (raw < 255) & (expected > 0.2))
    assert data.mask.all() and data.normal_gt is None


def test_sorted_order_is_numeric_and_skips_non_frames(tmp_path, rng):
    folder = tmp_path / "d"
    folder.mkdir()
    n = 11
    for i in range(n):
        np.save(folder / f"img{i}.npy", np.full((3, 3), float(i), dtype=np.float32))
    np.save(folder / "normal_gt.npy", np.tile([0.0, 0.0, 1.0], (3, 3, 1)))
    cv2.imwrite(str(folder / "mask.png"), np.full((3, 3), 255, np.uint8))
    cv2.imwrite(str(folder / "calibration.png"), np.zeros((5, 5), np.uint8))
    (folder / "recon").mkdir()
    np.save(folder / "recon" / "normals.npy", np.zeros((3, 3, 3)))
    np.savetxt(folder / "light_directions.txt", upper_lights(n, rng))
    data = load_dataset(folder)
    assert data.names == [f"img{i}.npy" for i in range(n)]
    np.testing.assert_array_equal(data.images[:, 1, 1], np.arange(n))
    assert data.normal_gt is not None


def test_non_unit_light_rows_are_normalised_with_a_warning(tmp_path, rng, caplog):
    lights = upper_lights(4, rng)
    scaled = lights * np.array([[1.0], [2.0], [1.0], [0.5]])
    np.savetxt(tmp_path / "light_directions.txt", scaled)
    with caplog.at_level(logging.WARNING, logger="ps_lab"):
        result = read_light_directions(tmp_path / "light_directions.txt", 4)
    np.testing.assert_allclose(result, lights, atol=1e-9)
    assert any(
        "not unit length" in r.getMessage() and "2, 4" in r.getMessage() for r in caplog.records
    )


def test_dark_frame_in_image_folder_is_subtracted(tmp_path, rng):
    folder = tmp_path / "d"
    folder.mkdir()
    frames = rng.uniform(0.2, 0.8, (3, 4, 4)).astype(np.float32)
    dark = rng.uniform(0.0, 0.05, (4, 4)).astype(np.float32)
    for i in range(3):
        np.save(folder / f"{i}.npy", frames[i] + dark)
    np.save(folder / "dark.npy", dark)
    np.savetxt(folder / "light_directions.txt", upper_lights(3, rng))
    loaded = load_frames(folder)
    assert loaded.names == ["0.npy", "1.npy", "2.npy"] and loaded.manifest is None
    np.testing.assert_allclose(loaded.images[..., 0], frames, atol=1e-6)


# --- capture runs ----------------------------------------------------------------------------


def make_run(
    run: Path,
    rng: np.random.Generator,
    *,
    n: int = 4,
    repeat: int = 2,
    shape=(6, 5),
    writer: str = "png",
) -> dict:
    """A capture run by hand: dark frame, `repeat` frames per light at varying exposures."""
    (run / "frames").mkdir(parents=True)
    h, w = shape
    dark_rate = rng.uniform(0.0, 0.02, (h, w, 3))  # dark signal per second
    radiance = rng.uniform(0.05, 0.3, (n, h, w, 3))  # signal per second per light
    radiance[1, 0, 0, 0] = 10.0  # clips in every repeat
    records = []

    def add(kind: str, lights: list[int], rep: int, exposure: float, linear: np.ndarray):
        index = len(records)
        stem = f"{index:04d}-" + ("dark" if kind == "dark" else f"L{lights[0]:02d}-r{rep}")
        if writer == "png":
            name = f"frames/{stem}.png"
            counts = np.clip(np.rint(linear * 65535), 0, 65535).astype(np.uint16)
            write_png_rgb(run / name, counts)
            stored = counts / 65535.0
        else:
            name = f"frames/{stem}.dng"
            stored = write_test_dng(run / name, linear, exposure_s=exposure)
        digest = hashlib.sha256((run / name).read_bytes()).hexdigest()
        records.append(
            {
                "index": index,
                "kind": kind,
                "lights": lights,
                "repeat": rep,
                "file": name,
                "exposure_s": exposure,
                "started": "2026-01-01T00:00:00",
                "finished": "2026-01-01T00:00:01",
                "sha256": digest,
            }
        )
        return stored

    dark_exposure = 0.5
    dark_stored = add("dark", [], 0, dark_exposure, dark_rate * dark_exposure)
    expected = np.zeros((n, h, w, 3))
    saturated = np.zeros((n, h, w), dtype=bool)
    common = None
    for light in range(1, n + 1):
        for rep in range(repeat):
            exposure = 1.0 if rep == 0 else 2.0 if light % 2 else 1.5
            common = common or exposure
            stored = add(
                "light", [light], rep, exposure, (radiance[light - 1] + dark_rate) * exposure
            )
            saturated[light - 1] |= np.any(stored >= 1.0, axis=-1)
            corrected = (stored - dark_stored * exposure / dark_exposure) * common / exposure
            expected[light - 1] += corrected / repeat
    manifest = {
        "format": "ps-lab-run",
        "version": 1,
        "ps_lab_version": "0.1.0",
        "rig": {},
        "camera_settings": {},
        "plan": {"lights": list(range(1, n + 1)), "repeat": repeat},
        "frames": records,
    }
    (run / "manifest.json").write_text(json.dumps(manifest))
    return {"expected": expected, "saturated": saturated, "radiance": radiance, "n": n}


def test_capture_run_frames_dark_exposure_repeats(tmp_path, rng):
    truth = make_run(tmp_path / "run", rng)
    frames = load_frames(tmp_path / "run")
    assert frames.manifest is not None and frames.manifest["format"] == "ps-lab-run"
    assert frames.names == [f"{1 + 2 * k:04d}-L{k + 1:02d}-r0.png" for k in range(truth["n"])]
    np.testing.assert_allclose(frames.images, truth["expected"], atol=1e-6)
    np.testing.assert_array_equal(frames.saturated, truth["saturated"])
    assert frames.saturated[1, 0, 0]
    # Unsaturated pixels recover the radiance (per second) times the first light frame's exposure.
    ok = ~truth["saturated"]
    np.testing.assert_allclose(frames.images[ok], truth["radiance"][ok], atol=2e-4)


def test_capture_run_dataset_needs_calibration_then_loads(tmp_path, rng):
    run = tmp_path / "run"
    truth = make_run(run, rng)
    with pytest.raises(
        DatasetError, match=r"is not calibrated: run `ps-lab calibrate .*run` first"
    ):
        load_dataset(run)
    n = truth["n"]
    np.savetxt(run / "light_directions.txt", upper_lights(n, rng))
    np.savetxt(run / "light_intensities.txt", np.ones((n, 3)) * 2.0)
    (run / "simulation").mkdir()
    normals = np.zeros((6, 5, 3))
    normals[..., 2] = 1.0
    np.save(run / "simulation" / "normal_gt.npy", normals)
    mask = np.zeros((6, 5), np.uint8)
    mask[1:4, 1:4] = 255
    cv2.imwrite(str(run / "simulation" / "mask.png"), mask)
    data = load_dataset(run)
    np.testing.assert_allclose(data.images, truth["expected"].mean(axis=-1) / 2.0, atol=1e-6)
    np.testing.assert_array_equal(data.valid, ~truth["saturated"])
    np.testing.assert_array_equal(data.mask, mask > 0)
    np.testing.assert_array_equal(data.normal_gt, normals)


def test_capture_run_with_dng_frames(tmp_path, rng):
    truth = make_run(tmp_path / "run", rng, n=3, repeat=2, shape=(12, 12), writer="dng")
    frames = load_frames(tmp_path / "run")
    np.testing.assert_allclose(frames.images, truth["expected"], atol=1e-5)
    np.testing.assert_array_equal(frames.saturated, truth["saturated"])


def test_capture_run_detects_a_changed_frame(tmp_path, rng):
    make_run(tmp_path / "run", rng, n=2, repeat=1)
    frame = tmp_path / "run" / "frames" / "0001-L01-r0.png"
    write_png_rgb(frame, np.zeros((6, 5, 3), np.uint16))
    with pytest.raises(DatasetError, match="0001-L01-r0.png.*sha256"):
        load_frames(tmp_path / "run")


def test_capture_run_missing_light_frame(tmp_path, rng):
    make_run(tmp_path / "run", rng, n=3, repeat=1)
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    manifest["frames"] = [f for f in manifest["frames"] if f["lights"] != [2]]
    (tmp_path / "run" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="manifest.json.*light\\(s\\) 2"):
        load_frames(tmp_path / "run")
