"""Linear RAW loading and DNG writing, checked against mosaics whose content the test controls."""

from __future__ import annotations

import numpy as np
import pytest
import rawpy
import tifffile

from ps_lab.errors import DatasetError
from ps_lab.io.dng import CFA_PATTERNS, write_dng
from ps_lab.io.raw import RAW_SUFFIXES, load_raw

WHITE = 16383
BLACKS = (510, 514, 506, 512)  # per CFA position, row by row


def _mosaic(rng: np.random.Generator, shape=(48, 64)) -> np.ndarray:
    mosaic = rng.integers(400, WHITE + 1, size=shape).astype(np.uint16)
    mosaic[rng.random(shape) < 0.05] = WHITE  # some clipped pixels
    return mosaic


def _expected_half(mosaic: np.ndarray, cfa: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel formula written out independently of the loader (float64)."""
    h, w = mosaic.shape
    out = np.zeros((h // 2, w // 2, 3))
    sat = np.zeros((h // 2, w // 2), bool)
    pattern = CFA_PATTERNS[cfa]
    for i in range(h // 2):
        for j in range(w // 2):
            greens = []
            for k, (dr, dc) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
                raw = float(mosaic[2 * i + dr, 2 * j + dc])
                value = (raw - BLACKS[k]) / (WHITE - BLACKS[k])
                sat[i, j] |= raw >= WHITE
                if pattern[k] == 1:
                    greens.append(value)
                else:
                    out[i, j, pattern[k]] = value
            out[i, j, 1] = np.mean(greens)
    return out, sat


def test_write_dng_reads_back_in_rawpy(tmp_path, rng):
    mosaic = _mosaic(rng)
    path = tmp_path / "frame.dng"
    write_dng(path, mosaic, black_level=BLACKS, white_level=WHITE, exposure_s=0.05)
    with rawpy.imread(str(path)) as raw:
        np.testing.assert_array_equal(raw.raw_image_visible, mosaic)
        assert raw.white_level == WHITE
        colors = raw.raw_colors_visible
        # RGGB: R at (0,0), B at (1,1), greens elsewhere (LibRaw numbers the second green 3).
        assert colors[0, 0] == 0 and colors[1, 1] == 2
        assert {int(colors[0, 1]), int(colors[1, 0])} <= {1, 3}
        blacks = np.asarray(raw.black_level_per_channel)
        for k, (r, c) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            assert blacks[colors[r, c]] == BLACKS[k]
        assert raw.other.shutter_speed == pytest.approx(0.05, rel=1e-6)


@pytest.mark.parametrize("cfa", sorted(CFA_PATTERNS))
def test_half_size_is_exact_linear_formula(tmp_path, rng, cfa):
    mosaic = _mosaic(rng)
    path = tmp_path / f"{cfa}.dng"
    write_dng(path, mosaic, black_level=BLACKS, white_level=WHITE, cfa=cfa, exposure_s=1 / 30)
    loaded = load_raw(path)
    expected, expected_sat = _expected_half(mosaic, cfa)
    assert loaded.image.dtype == np.float32
    assert loaded.image.shape == (24, 32, 3)
    np.testing.assert_allclose(loaded.image, expected, rtol=2e-7, atol=2e-7)
    np.testing.assert_array_equal(loaded.saturated, expected_sat)
    assert loaded.saturated.any() and not loaded.saturated.all()
    assert loaded.white_level == WHITE
    assert loaded.exposure_s == pytest.approx(1 / 30, rel=1e-9)


def test_linear_demosaic_keeps_samples_and_interpolates_linearly(tmp_path, rng):
    mosaic = _mosaic(rng)
    mosaic[mosaic >= WHITE] = WHITE - 1
    mosaic[10, 20] = WHITE
    path = tmp_path / "frame.dng"
    write_dng(path, mosaic, black_level=BLACKS, white_level=WHITE)
    loaded = load_raw(path, demosaic="linear")
    assert loaded.image.shape == (48, 64, 3)
    blacks = np.array(BLACKS, float).reshape(2, 2)
    black_map = np.tile(blacks, (24, 32))
    norm = (mosaic - black_map) / (WHITE - black_map)
    # Measured samples are kept: R at even/even, B at odd/odd.
    np.testing.assert_allclose(loaded.image[0::2, 0::2, 0], norm[0::2, 0::2], rtol=2e-7, atol=2e-7)
    np.testing.assert_allclose(loaded.image[1::2, 1::2, 2], norm[1::2, 1::2], rtol=2e-7, atol=2e-7)
    # Interior R at a B site is the mean of its four diagonal R neighbours.
    i, j = 11, 21
    expected = norm[[i - 1, i - 1, i + 1, i + 1], [j - 1, j + 1, j - 1, j + 1]].mean()
    assert loaded.image[i, j, 0] == pytest.approx(expected, rel=1e-6)
    # G at an R site is the mean of the four edge neighbours.
    i, j = 20, 30
    expected = norm[[i - 1, i + 1, i, i], [j, j, j - 1, j + 1]].mean()
    assert loaded.image[i, j, 1] == pytest.approx(expected, rel=1e-6)
    # The saturation mask covers the 3x3 support of the clipped sample and nothing else.
    assert loaded.saturated[9:12, 19:22].all()
    assert loaded.saturated.sum() == 9
    # A uniform mosaic stays uniform (linear, no bias at the borders).
    flat = np.full((48, 64), 3000, np.uint16)
    write_dng(path, flat, black_level=500, white_level=WHITE)
    np.testing.assert_allclose(
        load_raw(path, demosaic="linear").image, 2500 / (WHITE - 500), rtol=1e-6
    )


def test_exposure_absent_is_none(tmp_path, rng):
    path = tmp_path / "frame.dng"
    write_dng(path, _mosaic(rng), black_level=512, white_level=WHITE)
    assert load_raw(path).exposure_s is None


def test_suffixes_and_bad_mode(tmp_path, rng):
    assert ".dng" in RAW_SUFFIXES and ".cr2" in RAW_SUFFIXES
    path = tmp_path / "frame.dng"
    write_dng(path, _mosaic(rng), black_level=512, white_level=WHITE)
    with pytest.raises(ValueError, match="demosaic"):
        load_raw(path, demosaic="ahd")


@pytest.mark.parametrize("keep", [0.0, 0.1, 0.5, 0.97])
def test_truncated_dng_is_dataset_error(tmp_path, rng, keep):
    good = tmp_path / "good.dng"
    write_dng(good, _mosaic(rng), black_level=512, white_level=WHITE)
    data = good.read_bytes()
    bad = tmp_path / "bad.dng"
    bad.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(DatasetError, match="bad.dng"):
        load_raw(bad)


@pytest.mark.parametrize(
    "content", [b"not a raw file at all\n" * 50, b"\x89PNG\r\n\x1a\n" + bytes(500)]
)
@pytest.mark.parametrize("suffix", [".dng", ".cr2", ".NEF"])
def test_non_raw_content_is_dataset_error(tmp_path, content, suffix):
    bad = tmp_path / f"frame{suffix}"
    bad.write_bytes(content)
    with pytest.raises(DatasetError, match=f"frame{suffix}"):
        load_raw(bad)


def test_missing_file_is_dataset_error(tmp_path):
    with pytest.raises(DatasetError, match="nothere.dng"):
        load_raw(tmp_path / "nothere.dng")


@pytest.mark.parametrize(
    "kwargs, mosaic",
    [
        ({}, np.zeros((24, 24), np.float32)),
        ({}, np.zeros((24, 25), np.uint16)),
        ({}, np.zeros((10, 24), np.uint16)),
        ({"cfa": "XYZW"}, np.zeros((24, 24), np.uint16)),
        ({"black_level": 20000}, np.zeros((24, 24), np.uint16)),
    ],
)
def test_write_dng_rejects_bad_input(tmp_path, kwargs, mosaic):
    args = {"black_level": 512, "white_level": WHITE, **kwargs}
    with pytest.raises(ValueError):
        write_dng(tmp_path / "x.dng", mosaic, **args)


def test_linear_raw_dng_is_rejected_clearly(tmp_path, rng):
    rgb = rng.integers(0, 4000, (32, 32, 3)).astype(np.uint16)
    identity = tuple(x for v in (1, 0, 0, 0, 1, 0, 0, 0, 1) for x in (v * 10000, 10000))
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),
        (50708, "s", 0, "demosaiced", True),
        (50717, "I", 1, (4095,), True),
        (50721, "2i", 9, identity, True),
    ]
    path = tmp_path / "linear.dng"
    tifffile.imwrite(path, rgb, photometric=34892, metadata=None, extratags=tags)
    with pytest.raises(DatasetError, match="linear.dng: unsupported RAW layout"):
        load_raw(path)
