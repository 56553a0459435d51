"""RelightLab / OpenLIME exchange (issue 32): the export read back relights as the fit does."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from ps_lab import render
from ps_lab.cli import app
from ps_lab.io.appearance import Appearance, appearance_basis, evaluate_appearance, write_appearance
from ps_lab.io.relightlab import (
    export_error_bound,
    is_relightlab_folder,
    quantise_plane,
    read_relightlab,
    write_relightlab,
)
from ps_lab.errors import DatasetError

SHAPE = (40, 48)
N_LIGHTS = 30


def _fit(model: str, seed: int = 0):
    """A coloured, glossy relief and its per-pixel least-squares fit of an RTI basis."""
    rng = np.random.default_rng(seed)
    base = render.relief_surface(SHAPE, seed=seed)
    pattern = np.asarray(base.albedo, np.float64)
    pattern = pattern if pattern.ndim == 2 else pattern.mean(axis=-1)
    surface = render.relief_surface(SHAPE, seed=seed,
                                    albedo=pattern[..., None] * np.array([0.9, 0.5, 0.25]))
    lights = render.random_light_directions(N_LIGHTS, rng)
    images = render.render(surface, lights, specular=0.3)  # (n, H, W, 3)
    basis = appearance_basis(model, lights)  # (n, K)
    solution, *_ = np.linalg.lstsq(basis, images.reshape(N_LIGHTS, -1), rcond=None)
    k = basis.shape[1]
    coefficients = solution.reshape(k, *SHAPE, 3).transpose(1, 2, 3, 0).astype(np.float32)
    appearance = Appearance(model, coefficients, {"basis": model, "K": k})
    return surface, lights, appearance


# JPEG at quality 100 with 4:4:4 chroma moves a byte by at most this many levels from the exactly
# quantised value (measured: at most 4, at the sharp mask outline; 1 inside). OpenLIME reads the
# bytes as they decode.
JPEG_LEVELS = 6


@pytest.mark.parametrize("model", ["ptm", "hsh2", "hsh3"])
def test_export_read_back_relights_as_the_fit(tmp_path, model):
    surface, lights, appearance = _fit(model)
    info = write_relightlab(tmp_path, appearance, lights)
    assert is_relightlab_folder(tmp_path)
    on_disk = json.loads((tmp_path / "info.json").read_text())
    assert on_disk["type"] == ("ptm" if model == "ptm" else "hsh")
    assert on_disk["colorspace"] == "rgb"
    assert on_disk["nplanes"] == 3 * appearance.coefficients.shape[3]
    assert len(on_disk["materials"][0]["scale"]) == on_disk["nplanes"]
    assert len(on_disk["lights"]) == 3 * N_LIGHTS
    assert sorted(p.name for p in tmp_path.glob("plane_*.jpg")) == [
        f"plane_{k}.jpg" for k in range(appearance.coefficients.shape[3])
    ]
    # each JPEG's bytes are the exactly quantised planes within JPEG_LEVELS
    exposure = info["ps_lab"]["exposure"]
    for k in range(appearance.coefficients.shape[3]):
        decoded = cv2.imread(str(tmp_path / f"plane_{k}.jpg"))[..., ::-1].astype(int)
        for c in range(3):
            exact, _, _ = quantise_plane(appearance.coefficients[:, :, c, k] * exposure)
            assert np.abs(decoded[..., c] - exact.astype(int)).max() <= JPEG_LEVELS
    read, _ = read_relightlab(tmp_path)
    assert read.model == model and read.coefficients.shape == appearance.coefficients.shape
    normals = surface.normals
    albedo = np.zeros((*SHAPE, 3), np.float32)
    for light in render.random_light_directions(6, np.random.default_rng(9)):
        fitted = evaluate_appearance(appearance, light, normals, albedo)
        relit = evaluate_appearance(read, light, normals, albedo)
        bound = export_error_bound(info, light, levels=0.5 + JPEG_LEVELS)
        error = np.abs(relit - fitted).reshape(-1, 3).max(axis=0)
        assert np.all(error <= bound + 1e-6), (error, bound)


def test_cli_exports_a_result_and_refuses_what_it_cannot(tmp_path):
    surface, lights, appearance = _fit("hsh3")
    result = tmp_path / "result"
    result.mkdir()
    normals = np.where(surface.mask[..., None], surface.normals, 0).astype(np.float32)
    np.save(result / "normals.npy", normals)
    np.save(result / "albedo.npy", np.ones((*SHAPE, 3), np.float32))
    np.savetxt(result / "light_directions.txt", lights)
    (result / "metrics.json").write_text(json.dumps({"method": "ls"}))
    runner = CliRunner()
    out = tmp_path / "export"
    refused = runner.invoke(app, ["view", str(result), "--export", str(out), "--format", "relight"])
    assert refused.exit_code == 2 and "appearance" in refused.output and not out.exists()
    write_appearance(result, appearance)
    done = runner.invoke(app, ["view", str(result), "--export", str(out), "--format", "relight"])
    assert done.exit_code == 0, done.output
    info = json.loads((out / "info.json").read_text())
    np.testing.assert_allclose(np.reshape(info["lights"], (-1, 3)), lights, atol=1e-6)
    read, _ = read_relightlab(out)
    assert read.coefficients.shape == appearance.coefficients.shape
    # a broken plane is one error naming the file
    shutil.copy(out / "info.json", tmp_path / "info.json")
    (out / "plane_3.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(DatasetError, match="plane_3.jpg"):
        read_relightlab(out)
    bad = runner.invoke(app, ["view", str(result), "--export", str(out), "--format", "nope"])
    assert bad.exit_code == 2 and "--format" in bad.output
