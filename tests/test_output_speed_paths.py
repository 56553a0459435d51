"""The fast paths of the result writer give the values of the plain expressions they replace.

Issue 37: the 4 MP result files are written with cheaper operations (void-item scatters,
channel-wise maxima, banded pictures, RLE OpenEXR, encoders side by side); each is compared
here with the whole-image numpy expression it stands for, bit for bit.
"""

from __future__ import annotations

import threading

import cv2
import numpy as np
import OpenEXR
import pytest

from ps_lab.errors import OutputError
from ps_lab.io.images import read_exr
from ps_lab.io.normal_maps import normal16_picture, to_convention, write_normal16, write_rgb_exr
from ps_lab.reconstruct._outputs import brightest_channel, run_jobs, scatter_rows


@pytest.mark.parametrize("tail", [(), (1,), (3,), (2, 2)])
@pytest.mark.parametrize(("given", "dtype"), [(np.float32, np.float32), (np.float64, np.float32),
                                              (bool, bool)])
def test_scatter_rows_is_boolean_assignment(tail, given, dtype):
    rng = np.random.default_rng(3)
    for shape in ((5, 7), (1, 9), (3, 4)):
        inside = rng.random(shape) > 0.4
        if shape == (3, 4):
            inside[:] = False  # a band without mask pixels
        values = rng.normal(size=(int(inside.sum()), *tail)).astype(given)
        if given is np.float64 and values.size:
            values.flat[0] = np.nan
        want = np.zeros((*shape, *tail), dtype)
        want[inside] = values
        got = scatter_rows(inside, values, dtype)
        assert got.dtype == want.dtype and got.shape == want.shape
        assert got.tobytes() == want.tobytes()


def test_brightest_channel_is_max_over_the_last_axis_bit_for_bit():
    rng = np.random.default_rng(4)
    values = rng.normal(size=(500, 3)).astype(np.float32)
    values[::7, 1] = np.nan
    values[::11] = -0.0
    values[::13, 0] = 0.0
    values[::17] = [np.inf, -np.inf, 1.0]
    assert brightest_channel(values).tobytes() == values.max(axis=-1).tobytes()
    assert brightest_channel(values[:, :1]).tobytes() == values[:, :1].max(axis=-1).tobytes()


def _normal16_whole_image(normals, mask, convention):
    """normal16_picture as it was: one expression on the whole image."""
    normals = to_convention(normals, convention)
    picture = np.clip(np.rint((np.asarray(normals) + 1.0) * 0.5 * 65535.0), 0, 65535)
    picture = picture.astype(np.uint16)
    picture[~np.asarray(mask, bool)] = 0
    return picture


@pytest.mark.parametrize("convention", ["opengl", "directx"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_normal16_by_bands_is_the_whole_image_expression(tmp_path, convention, dtype):
    rng = np.random.default_rng(5)
    normals = rng.normal(size=(150, 37, 3))  # not a multiple of the 64-row bands
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = normals.astype(dtype)
    normals[::9] = 0.0
    edges = np.array([-1.0, 1.0, 0.5, -0.5, 2e-5, -2e-5, 1.5, -1.5], dtype)  # ends, clipping
    normals[:, : edges.size, 0] = edges
    mask = np.linalg.norm(normals, axis=-1) > 0.5
    want = _normal16_whole_image(normals, mask, convention)
    assert np.array_equal(normal16_picture(normals, mask, convention), want)
    write_normal16(tmp_path / "n16.png", normals, mask, convention)
    assert np.array_equal(cv2.imread(str(tmp_path / "n16.png"), cv2.IMREAD_UNCHANGED)[..., ::-1],
                          want)


def test_rgb_exr_is_rle_and_exact_and_leaves_its_input(tmp_path):
    rng = np.random.default_rng(6)
    image = rng.normal(size=(41, 23, 3)).astype(np.float32)
    image[:10] = 0.0
    write_rgb_exr(tmp_path / "a.exr", image)
    with OpenEXR.File(str(tmp_path / "a.exr")) as exr:
        assert exr.header()["compression"] == OpenEXR.RLE_COMPRESSION
    assert read_exr(tmp_path / "a.exr").tobytes() == image.tobytes()
    odd = image.copy()
    odd[1, 2] = [np.nan, np.inf, -np.inf]
    kept = odd.copy()
    write_rgb_exr(tmp_path / "b.exr", odd)
    assert np.array_equal(odd, kept, equal_nan=True)  # the caller's array untouched
    assert read_exr(tmp_path / "b.exr").tobytes() == np.nan_to_num(odd).tobytes()
    write_rgb_exr(tmp_path / "c.exr", image.astype(np.float64)[:, ::-1])  # any layout and type
    assert read_exr(tmp_path / "c.exr").tobytes() == np.ascontiguousarray(image[:, ::-1]).tobytes()


@pytest.mark.parametrize("threads", [1, 3, None])
def test_run_jobs_runs_every_job_and_raises_the_first_failure(threads):
    ran = []
    lock = threading.Lock()

    def job(name, error=None):
        def run():
            with lock:
                ran.append(name)
            if error is not None:
                raise error
        return run

    run_jobs([job("a"), job("b"), job("c")], threads)
    assert sorted(ran) == ["a", "b", "c"]
    ran.clear()
    first, second = OSError(28, "No space left on device"), OutputError("later")
    with pytest.raises(OSError) as caught:
        run_jobs([job("a"), job("b", first), job("c", second), job("d")], threads)
    assert caught.value is first
    assert sorted(ran) == ["a", "b", "c", "d"]
