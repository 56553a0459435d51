"""`ps-lab simulate` end to end through the CLI."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

from ps_lab.cli import app
from ps_lab.render import PNG16_PEAK, relief_surface, render, sphere_surface

runner = CliRunner()


def _read(path):
    if path.suffix == ".png":
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if path.suffix == ".tiff":
        return tifffile.imread(path)
    return np.load(path)


@pytest.mark.parametrize(
    ("image_format", "suffix", "dtype"),
    [("png16", ".png", np.uint16), ("tiff32", ".tiff", np.float32), ("npy", ".npy", np.float32)],
)
def test_simulate_writes_a_consistent_dataset(tmp_path, image_format, suffix, dtype):
    out = tmp_path / "ds"
    args = [
        "simulate",
        str(out),
        "--scene",
        "relief",
        "--lights",
        "7",
        "--size",
        "40",
        "--seed",
        "3",
        "--format",
        image_format,
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    names = (out / "filenames.txt").read_text().split()
    assert names == [f"{i:03d}{suffix}" for i in range(1, 8)]
    images = np.array([_read(out / name) for name in names])
    assert images.shape == (7, 40, 40) and images.dtype == dtype
    lights = np.loadtxt(out / "light_directions.txt")
    assert lights.shape == (7, 3)
    np.testing.assert_allclose(np.linalg.norm(lights, axis=1), 1.0, atol=1e-8)
    assert np.all(lights[:, 2] > 0)
    np.testing.assert_array_equal(np.loadtxt(out / "light_intensities.txt"), np.ones((7, 3)))
    mask = cv2.imread(str(out / "mask.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (40, 40) and set(np.unique(mask)) == {0, 255}
    normals = np.load(out / "normal_gt.npy")
    assert normals.shape == (40, 40, 3) and normals.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(normals[mask > 0], axis=-1), 1.0, atol=1e-6)
    assert np.all(normals[mask == 0] == 0)
    assert np.all(images[:, mask == 0] == 0)
    # The images are the renderer's, up to the documented png16 scale.
    expected = render(relief_surface((40, 40), seed=3), lights)
    meta = json.loads((out / "simulation.json").read_text())
    if image_format == "png16":
        scale = meta["png16_scale"]
        assert images.max() == round(PNG16_PEAK * 65535)
        np.testing.assert_allclose(images / scale, expected, atol=1.0 / scale)
    else:
        assert meta["png16_scale"] is None
        np.testing.assert_allclose(images, expected, atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]  # no staging folder left behind


def test_simulate_sphere_noise_and_specular(tmp_path):
    out = tmp_path / "sphere"
    args = [
        "simulate",
        str(out),
        "--lights",
        "5",
        "--size",
        "32",
        "--format",
        "npy",
        "--specular",
        "0.5",
        "--roughness",
        "0.2",
        "--noise-fraction",
        "0.5",
        "--noise-sigma",
        "0.1",
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    images = np.array([np.load(out / f"00{i}.npy") for i in range(1, 6)])
    lights = np.loadtxt(out / "light_directions.txt")
    diffuse = render(sphere_surface((32, 32)), lights)
    mask = sphere_surface((32, 32)).mask
    changed = ~np.isclose(images, diffuse, atol=1e-6)[:, mask]
    # Half the observations are noisy; specular adds some more differences on top.
    assert 0.45 < changed.mean() < 0.8


def test_simulate_refuses_a_non_empty_output_folder(tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    result = runner.invoke(app, ["simulate", str(out), "--lights", "4", "--size", "16"])
    assert result.exit_code == 2
    assert "not empty" in result.output and "taken" in result.output
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_simulate_accepts_an_existing_empty_folder(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    result = runner.invoke(app, ["simulate", str(out), "--lights", "3", "--size", "16"])
    assert result.exit_code == 0, result.output
    assert (out / "normal_gt.npy").is_file() and (out / "003.png").is_file()


def test_simulate_rejects_bad_options(tmp_path):
    result = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--lights", "2"])
    assert result.exit_code == 2
    assert not (tmp_path / "x").exists()
    result = runner.invoke(app, ["simulate", str(tmp_path / "y"), "--scene", "cube"])
    assert result.exit_code == 2
    assert not (tmp_path / "y").exists()
