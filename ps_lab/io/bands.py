"""Streamed loading: captures of any size in bounded memory (``docs/scale.md``).

:func:`plan_bands` cuts the image into row bands, and :func:`stage_observations` reads each frame
once and stores its mask pixels band by band in an :class:`ObservationStore` (same scaling as
:func:`ps_lab.io.dataset.load_dataset`, bit for bit); :class:`ps_lab.io.truth.NormalTruth` reads
ground truth band by band.
"""

from __future__ import annotations

import io
import logging
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.dataset import (
    DatasetHeader,
    iter_frames,
    observe,
)
from ps_lab.io.files import preallocate

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class Band:
    """A block of whole image rows solved together.

    Attributes
    ----------
    index : int
    row_start, row_stop : int
        Image rows ``row_start:row_stop``.
    pixel_start : int
        Index of the band's first mask pixel among all mask pixels (row-major order).
    pixel_count : int
        Mask pixels in the band.

    """

    index: int
    row_start: int
    row_stop: int
    pixel_start: int
    pixel_count: int


def plan_bands(mask: np.ndarray, max_pixels: int) -> list[Band]:
    """Cut the image into row bands of at most ``max_pixels`` mask pixels each.

    A band is closed before it would exceed ``max_pixels`` mask pixels or ``4 * max_pixels``
    image pixels (so that per-band image buffers stay bounded when the mask is sparse); every band
    holds at least one row.

    Parameters
    ----------
    mask : ndarray of shape (H, W), bool
    max_pixels : int
        Positive.

    Returns
    -------
    list of Band
        Covering rows 0..H in order.

    """
    height, width = mask.shape
    max_pixels = max(int(max_pixels), 1)
    max_rows = max(4 * max_pixels // max(width, 1), 1)
    per_row = np.count_nonzero(mask, axis=1)
    bands: list[Band] = []
    start, count, pixel_start = 0, 0, 0
    for row in range(height):
        rows = row - start
        if rows > 0 and (count + per_row[row] > max_pixels or rows >= max_rows):
            bands.append(Band(len(bands), start, row, pixel_start, count))
            start, pixel_start, count = row, pixel_start + count, 0
        count += int(per_row[row])
    bands.append(Band(len(bands), start, height, pixel_start, count))
    return bands


class ObservationStore:
    """Masked observations (float32) and their validity (packed bits), stored band by band.

    Layout: for each band, the ``(n, P_band)`` float32 observations light after light, then the
    packed validity bits of each light (``ceil(P_band / 8)`` bytes per light) and, with
    ``colours`` = C > 0, the ``(n, P_band, C)`` float32 colour observations (each channel divided
    by the light's intensity for it; :meth:`read_colour`), so that one band's block is read
    contiguously. The backing is a temporary file, or a bytes buffer in memory when
    the store is small: the code is the same. Use as a context manager or call :meth:`close`,
    which deletes the file.

    Attributes
    ----------
    bands : list of Band
    n_lights : int
    shape : (H, W)
    mask : ndarray of shape (H, W), bool
    path : Path or None
        The backing file (None in memory).
    colours : int
        Colour channels staged beside the solve channel (0: none).
    sample_observations : ndarray of shape (n, m), float32
        Observations of ``m`` evenly spaced mask pixels (for the solvers' noise estimate).
    sample_valid : ndarray of shape (n, m), bool
    sample_colour : ndarray of shape (n, m, colours), float32
        The sample's colour observations (no channels without colour).

    """

    def __init__(
        self,
        bands: list[Band],
        n_lights: int,
        mask: np.ndarray,
        *,
        folder: Path | None = None,
        in_memory: bool = False,
        sample_pixels: int = 20000,
        path: Path | None = None,
        colours: int = 0,
    ) -> None:
        self.bands = bands
        self.colours = int(colours)
        self._colour_offsets: list[int] = []
        self.n_lights = n_lights
        self.mask = mask
        self.shape = mask.shape
        self.pixels = sum(band.pixel_count for band in bands)
        self._offsets: list[tuple[int, int]] = []
        offset = 0
        for band in bands:
            values = offset
            offset += n_lights * band.pixel_count * 4
            self._offsets.append((values, offset))
            offset += n_lights * _packed_size(band.pixel_count)
            self._colour_offsets.append(offset)
            offset += n_lights * band.pixel_count * self.colours * 4
        self.nbytes = offset
        self.path: Path | None = None
        self._owned = path is None
        if path is not None:
            # Another process's store (a worker of ps-lab reconstruct --scheduler): opened for
            # update, never created, so a late task cannot recreate a store already removed.
            self.path = Path(path)
            try:
                self._stream = open(self.path, "r+b")  # noqa: SIM115 - closed by close()
            except OSError as exc:
                raise DatasetError(
                    f"{self.path}: cannot open the staging file ({exc.strerror}); "
                    "workers need the output folder on a filesystem they share"
                ) from None
        elif in_memory:
            self._stream = io.BytesIO()
        else:
            handle, name = tempfile.mkstemp(
                prefix="ps-lab-observations-", suffix=".bin", dir=folder
            )
            self.path = Path(name)
            # Full size, reserved (a full disk fails here): other processes may fill any band.
            try:
                preallocate(handle, 0, self.nbytes)
            except BaseException:
                os.close(handle)
                self.path.unlink(missing_ok=True)
                raise
            self._stream = os.fdopen(handle, "w+b")
        # The noise sample: the same pixels the solvers would pick among all mask pixels.
        p = self.pixels
        take = np.linspace(0, p - 1, min(p, sample_pixels)).round().astype(np.int64) if p else []
        self.sample_index = np.unique(take).astype(np.int64)
        self.sample_observations = np.zeros((n_lights, self.sample_index.size), np.float32)
        self.sample_valid = np.zeros((n_lights, self.sample_index.size), bool)
        # the sample's colour observations (n, m, C), for fits in colour (appearance models)
        self.sample_colour = np.zeros((n_lights, self.sample_index.size, self.colours), np.float32)

    def __enter__(self) -> ObservationStore:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Release the backing buffer and delete the backing file (when this store made it)."""
        self._stream.close()
        if self.path is not None and self._owned:
            self.path.unlink(missing_ok=True)

    def write(
        self,
        light: int,
        band: Band,
        observations: np.ndarray,
        valid: np.ndarray,
        colour: np.ndarray | None = None,
    ) -> None:
        """Store one light's observations (P_band,) float32 and validity (P_band,) of a band.

        ``colour`` (P_band, C): its colour observations, when the store keeps colour.
        """
        values, bits = self._offsets[band.index]
        count = band.pixel_count
        if self.colours and colour is not None:
            self._stream.seek(self._colour_offsets[band.index] + light * count * self.colours * 4)
            self._stream.write(np.ascontiguousarray(colour, dtype=np.float32).data)
        self._stream.seek(values + light * count * 4)
        self._stream.write(np.ascontiguousarray(observations, dtype=np.float32).data)
        self._stream.seek(bits + light * _packed_size(count))
        self._stream.write(np.packbits(valid).data)
        lo, hi = np.searchsorted(self.sample_index, [band.pixel_start, band.pixel_start + count])
        local = self.sample_index[lo:hi] - band.pixel_start
        self.sample_observations[light, lo:hi] = observations[local]
        self.sample_valid[light, lo:hi] = valid[local]
        if self.colours and colour is not None:
            self.sample_colour[light, lo:hi] = colour[local]

    def write_frame(
        self,
        light: int,
        observations: np.ndarray,
        valid: np.ndarray,
        colour: np.ndarray | None = None,
    ) -> None:
        """Store one light's observations and validity, both (H, W), band by band (mask pixels).

        ``colour`` (H, W, C): the colour observations, when the store keeps colour.
        """
        for band in self.bands:
            rows = slice(band.row_start, band.row_stop)
            inside = self.mask[rows]
            part = None if colour is None else colour[rows][inside]
            self.write(light, band, observations[rows][inside], valid[rows][inside], part)

    def read_colour(self, band: Band) -> np.ndarray | None:
        """One band's colour observations (n, P_band, C) float32 (None: no colour staged)."""
        if not self.colours:
            return None
        colour = np.empty((self.n_lights, band.pixel_count, self.colours), np.float32)
        self._stream.seek(self._colour_offsets[band.index])
        self._read_exactly(colour)
        return colour

    def read(self, band: Band) -> tuple[np.ndarray, np.ndarray]:
        """One band's observations (n, P_band) float32 and validity (n, P_band) bool."""
        values, bits = self._offsets[band.index]
        count = band.pixel_count
        observations = np.empty((self.n_lights, count), np.float32)
        packed = np.empty((self.n_lights, _packed_size(count)), np.uint8)
        self._stream.seek(values)
        self._read_exactly(observations)
        self._stream.seek(bits)
        self._read_exactly(packed)
        valid = np.unpackbits(packed, axis=1, count=count).view(bool)
        return observations, valid

    def _read_exactly(self, array: np.ndarray) -> None:
        if array.size == 0:
            return
        view = memoryview(array.reshape(-1).view(np.uint8))
        done = 0
        while done < len(view):
            got = self._stream.readinto(view[done:])
            if not got:
                raise DatasetError(f"{self.path or 'observation store'}: staging data truncated")
            done += got


def _packed_size(count: int) -> int:
    return (count + 7) // 8


def stage_observations(
    header: DatasetHeader,
    mask: np.ndarray,
    bands: list[Band],
    *,
    channel: str = "mean",
    shadow_threshold: float | None = None,
    folder: Path | None = None,
    in_memory: bool = False,
    sample_pixels: int = 20000,
    progress: Callable[[int], None] | None = None,
    colours: int = 0,
) -> ObservationStore:
    """Read every frame once, one at a time, and store its mask pixels band by band.

    The per-light scaling, colour rule and validity rule are those of :func:`load_dataset`
    (:func:`iter_frames` then :func:`observe`), so ``store.read(band)`` equals
    ``load_dataset(...).images[:, rows][:, mask]`` bit for bit.

    Parameters
    ----------
    header : DatasetHeader
        From :func:`open_dataset` (with the image size).
    mask : ndarray of shape (H, W), bool
    bands : list of Band
        From :func:`plan_bands`.
    channel, shadow_threshold
        As for :func:`load_dataset`.
    folder : Path or None
        Where the temporary file goes (default: the system's temporary folder).
    in_memory : bool
        Keep the store in a memory buffer instead of a file.
    sample_pixels : int
        Size of the noise-estimation sample (see :class:`ObservationStore`).
    progress : callable or None
        ``progress(1)`` after each light.
    colours : int
        Also stage this many colour channels (3 for colour frames, 0: none; see
        :class:`ObservationStore`).

    Returns
    -------
    ObservationStore
        The caller closes it (it is closed here if reading fails).

    """
    store = ObservationStore(
        bands,
        len(header.names),
        mask,
        folder=folder,
        in_memory=in_memory,
        sample_pixels=sample_pixels,
        colours=colours,
    )
    try:
        _stage_frames(store, header, iter_frames(header.plan), channel, shadow_threshold, progress)
    except BaseException:
        store.close()
        raise
    return store


def stage_lights(
    header: DatasetHeader,
    mask: np.ndarray,
    bands: list[Band],
    lights: list[int],
    path: Path,
    *,
    common_exposure: float | None,
    channel: str = "mean",
    shadow_threshold: float | None = None,
    sample_pixels: int = 20000,
    colours: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stage some lights into an existing store file (one task of a distributed pass 1).

    The frames are read as :func:`stage_observations` reads them (same bits) and written into
    the file another process created with :class:`ObservationStore` (``path``); lights go to
    disjoint parts of the file, so several processes can stage at once, and staging a light twice
    writes the same bytes.

    Parameters
    ----------
    header, mask, bands, channel, shadow_threshold, sample_pixels, colours
        As for :func:`stage_observations` (the same values as the process that made the store).
    lights : list of int
        Light indices to stage.
    path : Path
        The store file.
    common_exposure : float or None
        :func:`ps_lab.io.dataset.reference_exposure` of the plan, found once by the caller.

    Returns
    -------
    sample_observations : ndarray of shape (len(lights), m), float32
    sample_valid : ndarray of shape (len(lights), m), bool
        These lights' rows of the store's noise sample.
    sample_colour : ndarray of shape (len(lights), m, colours), float32
        Their colour observations.

    """
    frames = iter_frames(header.plan, lights, common_exposure=common_exposure)
    with ObservationStore(
        bands, len(header.names), mask, sample_pixels=sample_pixels, path=path, colours=colours
    ) as store:
        _stage_frames(store, header, frames, channel, shadow_threshold, None, lights)
        return (
            store.sample_observations[lights],
            store.sample_valid[lights],
            store.sample_colour[lights],
        )


def _stage_frames(store, header, frames, channel, shadow_threshold, progress, lights=None) -> None:
    """Observe each frame of ``frames`` (lights ``lights``, default all) and store it."""
    height, width = store.shape
    indices = range(store.n_lights) if lights is None else lights
    for i, (frame, clipped) in zip(indices, frames, strict=True):
        if frame.shape[:2] != (height, width):
            file = header.plan.light_files[i][0]
            raise DatasetError(
                f"{file}: image size {frame.shape[1]}x{frame.shape[0]} differs from the "
                f"first image ({width}x{height})"
            )
        observations, valid = observe(
            frame, clipped, header.light_intensities[i], channel, shadow_threshold
        )
        colour = None
        if store.colours and frame.ndim == 3 and frame.shape[-1] >= store.colours:
            # each channel divided by the light's intensity for it (the rule of observe)
            scale = np.asarray(header.light_intensities[i], np.float32)[: store.colours]
            colour = frame[..., : store.colours] / scale
        del frame, clipped
        store.write_frame(i, observations, valid, colour)
        del observations, valid, colour
        if progress is not None:
            progress(1)
