"""Streamed loading: captures of any size in bounded memory (``docs/scale.md``).

:func:`plan_bands` cuts the image into row bands, and :func:`stage_observations` reads each frame
once (decoding the next frames in other threads) and stores its mask pixels band by band in an
:class:`ObservationStore`, as compact as the source allows: an 8- or 16-bit capture as its codes
(one or two bytes per sample), anything else as linear float32 with a saturation bit. Reading a
band turns it into the solvers' observations (:func:`ps_lab.io.coding.observe_block`: the same
scaling as :func:`ps_lab.io.dataset.load_dataset`, bit for bit);
:class:`ps_lab.io.truth.NormalTruth` reads ground truth band by band.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.coding import Coding, ObserveRule, float_coding, observe_block, observe_rule
from ps_lab.io.coded_frames import (
    NotCodedError,
    check_coded_geometry,
    frame_coding,
    read_coded_light,
)
from ps_lab.io.dataset import DatasetHeader, iter_frames
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
    """A capture's mask pixels, band by band, as stored values; observations when read.

    Layout: for each band, the ``(n, P_band, C)`` values of its pixels light after light (codes
    of ``coding``, or linear float32), then, for float values only, the packed saturation bits of
    each light (``ceil(P_band / 8)`` bytes per light), so that one band's block is read
    contiguously and each light's part of it is written by one process. :meth:`read` applies
    the observe rule (``rule``: each channel divided by the light's intensity, the channels
    combined, validity), :meth:`read_colour` gives the colour observations. The backing is a
    temporary file, or numpy arrays in memory: the code is the same. Use as a context manager or
    call :meth:`close`, which deletes the file.

    Attributes
    ----------
    bands : list of Band
    n_lights : int
    shape : (H, W)
    mask : ndarray of shape (H, W), bool
    coding : Coding
        What the values are (default: linear float32, one channel).
    rule : ObserveRule
        The colour and validity rules (default: intensities 1, channel mean, no threshold).
    path : Path or None
        The backing file (None in memory).
    colours : int
        Colour channels :meth:`read_colour` gives (0: none; 3 needs three-channel values).
    sample_observations : ndarray of shape (n, m), float32
        Observations of ``m`` evenly spaced mask pixels (for the solvers' noise estimate).
    sample_valid : ndarray of shape (n, m), bool
    sample_colour : ndarray of shape (n, m, colours), float32
        The sample's colour observations (no channels without colour).
    nbytes : int
        Bytes the values take (memory or file).

    """

    def __init__(
        self,
        bands: list[Band],
        n_lights: int,
        mask: np.ndarray,
        *,
        coding: Coding | None = None,
        rule: ObserveRule | None = None,
        folder: Path | None = None,
        in_memory: bool = False,
        sample_pixels: int = 20000,
        path: Path | None = None,
        colours: int = 0,
        threads: int | None = None,
    ) -> None:
        self.bands = bands
        self.n_lights = n_lights
        self.mask = mask
        self.shape = mask.shape
        self.coding = coding if coding is not None else float_coding(1)
        self.rule = rule if rule is not None else observe_rule(np.ones((n_lights, 3)))
        self.colours = int(colours) if self.coding.channels == 3 else 0
        self.threads = max(1, int(threads) if threads else min(os.cpu_count() or 1, 4))
        self.pixels = sum(band.pixel_count for band in bands)
        self._lights = np.arange(n_lights, dtype=np.int64)
        channels, itemsize = self.coding.channels, self.coding.itemsize
        self._bits = not self.coding.coded
        self._offsets: list[tuple[int, int]] = []
        offset = 0
        for band in bands:
            values = offset
            offset += n_lights * band.pixel_count * channels * itemsize
            self._offsets.append((values, offset))
            if self._bits:
                offset += n_lights * _packed_size(band.pixel_count)
        self.nbytes = offset
        self.path: Path | None = None
        self._owned = path is None
        self._arrays: list[tuple[np.ndarray, np.ndarray | None]] | None = None
        self._stream = None
        self._last: tuple[int, np.ndarray, np.ndarray | None] | None = None
        self._buffers: dict[str, np.ndarray] = {}  # observe(reuse=True)'s, per output
        # what staging and reading cost (metrics.json's timings)
        self.stats = {"file_bytes": 0, "decode_seconds": 0.0, "observe_seconds": 0.0,
                      "observed_bytes": 0}
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
            self._arrays = [
                (np.zeros((n_lights, band.pixel_count, channels), self.coding.dtype),
                 np.zeros((n_lights, _packed_size(band.pixel_count)), np.uint8)
                 if self._bits else None)
                for band in bands
            ]
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
        """Release the backing buffers and delete the backing file (when this store made it)."""
        self._arrays = None
        self._last = None
        self._buffers = {}
        if self._stream is not None:
            self._stream.close()
        if self.path is not None and self._owned:
            self.path.unlink(missing_ok=True)

    def write(self, light: int, band: Band, values: np.ndarray,
              valid: np.ndarray | None = None) -> None:
        """Store one light's values (P_band, C) (or (P_band,)) of a band, and their validity.

        ``valid`` (P_band,) bool: False where saturated (float values only; codes carry their
        saturation). The sample's observations of these pixels are observed here.
        """
        count = band.pixel_count
        values = np.asarray(values).reshape(count, self.coding.channels)
        saturated = None
        if self._bits:
            saturated = (np.zeros(count, bool) if valid is None
                         else np.logical_not(np.asarray(valid, bool).reshape(count)))
        self._put(light, band, values, saturated)
        self._observe_sample(light, band, values, saturated)

    def write_frame(self, light: int, values: np.ndarray, valid: np.ndarray | None = None) -> None:
        """Store one light's frame: values (H, W, C) (or (H, W)) and validity (H, W), by band."""
        channels = self.coding.channels
        values = np.asarray(values)
        if values.ndim == 2:
            values = values[:, :, None]
        for band in self.bands:
            rows = slice(band.row_start, band.row_stop)
            inside = self.mask[rows]
            whole = band.pixel_count == inside.size
            part = (values[rows].reshape(-1, channels) if whole
                    else values[rows][inside])
            ok = None
            if valid is not None:
                ok = valid[rows].reshape(-1) if whole else valid[rows][inside]
            self.write(light, band, part, ok)

    def _put(self, light, band, values, saturated) -> None:
        self._last = None
        if self._arrays is not None:
            stored, bits = self._arrays[band.index]
            stored[light] = values
            if bits is not None:
                bits[light] = np.packbits(saturated)
            return
        start, bits_at = self._offsets[band.index]
        count = band.pixel_count
        row = count * self.coding.channels * self.coding.itemsize
        self._stream.seek(start + light * row)
        self._stream.write(np.ascontiguousarray(values, dtype=self.coding.dtype).data)
        if self._bits:
            self._stream.seek(bits_at + light * _packed_size(count))
            self._stream.write(np.packbits(saturated).data)

    def _observe_sample(self, light, band, values, saturated) -> None:
        lo, hi = np.searchsorted(self.sample_index, [band.pixel_start,
                                                      band.pixel_start + band.pixel_count])
        if hi <= lo:
            return
        local = self.sample_index[lo:hi] - band.pixel_start
        obs, valid, colour = observe_block(
            values[local][None], None if saturated is None else saturated[local][None],
            self.coding, self.rule, np.array([light]), bool(self.colours))
        self.sample_observations[light, lo:hi] = obs[0]
        self.sample_valid[light, lo:hi] = valid[0]
        if colour is not None:
            self.sample_colour[light, lo:hi] = colour[0]

    def values(self, band: Band) -> tuple[np.ndarray, np.ndarray | None]:
        """One band's stored values (n, P_band, C) and saturation (n, P_band) (None: codes)."""
        if self._last is not None and self._last[0] == band.index:
            return self._last[1], self._last[2]
        count = band.pixel_count
        if self._arrays is not None:
            stored, bits = self._arrays[band.index]
        else:
            start, bits_at = self._offsets[band.index]
            stored = np.empty((self.n_lights, count, self.coding.channels), self.coding.dtype)
            self._stream.seek(start)
            self._read_exactly(stored)
            bits = None
            if self._bits:
                bits = np.empty((self.n_lights, _packed_size(count)), np.uint8)
                self._stream.seek(bits_at)
                self._read_exactly(bits)
        saturated = (None if bits is None
                     else np.unpackbits(bits, axis=1, count=count).view(bool))
        self._last = (band.index, stored, saturated)
        return stored, saturated

    def observe(self, band: Band, colour: bool = False, reuse: bool = False
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """One band's observations (n, P), validity (n, P) and, with ``colour``, (n, P, 3).

        ``reuse``: into the store's own buffers (sized for the largest band), valid until the
        next ``reuse`` call: a band after band loop then touches no fresh memory (a fresh
        array costs a page fault per 4 KiB, ten times the decoding itself).
        """
        started = time.perf_counter()
        try:
            return self._observe(band, colour, reuse)
        finally:
            self.stats["observe_seconds"] += time.perf_counter() - started
            start, stop = self._offsets[band.index]
            self.stats["observed_bytes"] += stop - start

    def _observe(self, band, colour, reuse=False):
        stored, saturated = self.values(band)
        want = bool(colour) and bool(self.colours)
        n = self.n_lights
        pieces = np.array_split(np.arange(n), min(self.threads, n)) if n else []
        if not reuse and (len(pieces) <= 1 or band.pixel_count < 4096):
            return observe_block(stored, saturated, self.coding, self.rule, self._lights, want)
        obs = self._buffer("obs", (n, band.pixel_count), np.float32, reuse)
        valid = self._buffer("valid", (n, band.pixel_count), np.bool_, reuse)
        out = self._buffer("colour", (n, band.pixel_count, 3), np.float32, reuse) if want else None
        if len(pieces) <= 1:
            pieces = [np.arange(n)] if n else []

        def one(lights):
            a, b = lights[0], lights[-1] + 1
            observe_block(stored[a:b], None if saturated is None else saturated[a:b],
                          self.coding, self.rule, lights, want,
                          out=(obs[a:b], valid[a:b], None if out is None else out[a:b]))

        if len(pieces) == 1:
            one(pieces[0])
        elif pieces:
            with ThreadPoolExecutor(len(pieces)) as pool:
                list(pool.map(one, pieces))
        return obs, valid, out

    def _buffer(self, name: str, shape: tuple, dtype, reuse: bool) -> np.ndarray:
        """A C-ordered array of ``shape``: the start of the store's buffer ``name`` (``reuse``)."""
        size = int(np.prod(shape))
        if not reuse:
            return np.empty(shape, dtype)
        found = self._buffers.get(name)
        if found is None:  # sized for the largest band: shape[1] is the band's pixels
            largest = max((band.pixel_count for band in self.bands), default=0)
            found = np.empty(int(np.prod((shape[0], largest, *shape[2:]))), dtype)
            self._buffers[name] = found
        return found[:size].reshape(shape)

    def read(self, band: Band) -> tuple[np.ndarray, np.ndarray]:
        """One band's observations (n, P_band) float32 and validity (n, P_band) bool."""
        obs, valid, _ = self.observe(band)
        return obs, valid

    def read_colour(self, band: Band) -> np.ndarray | None:
        """One band's colour observations (n, P_band, C) float32 (None: no colour staged)."""
        if not self.colours:
            return None
        return self.observe(band, colour=True)[2]

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
    coding: Coding | None = None,
    threads: int | None = None,
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
        Keep the store in memory instead of a file.
    sample_pixels : int
        Size of the noise-estimation sample (see :class:`ObservationStore`).
    progress : callable or None
        ``progress(1)`` after each light.
    colours : int
        Also give colour observations (3 for colour frames, 0: none; see
        :class:`ObservationStore`).
    coding : Coding or None
        :func:`ps_lab.io.coded_frames.frame_coding` of the header's plan (found here when None).
    threads : int or None
        Frames decoded at once (default: the cores, at most 4).

    Returns
    -------
    ObservationStore
        The caller closes it (it is closed here if reading fails).

    """
    coding = coding if coding is not None else frame_coding(header.plan)
    try:
        return _stage(header, mask, bands, coding, channel, shadow_threshold, folder, in_memory,
                      sample_pixels, progress, colours, threads)
    except NotCodedError as exc:
        # a frame unlike light 1's (another bit depth or transfer curve): stage as decoded
        log.info("staging as linear float32: %s", exc)
        return _stage(header, mask, bands, float_coding(coding.channels), channel,
                      shadow_threshold, folder, in_memory, sample_pixels, progress, colours,
                      threads)


def _stage(header, mask, bands, coding, channel, shadow_threshold, folder, in_memory,
           sample_pixels, progress, colours, threads) -> ObservationStore:
    store = ObservationStore(
        bands,
        len(header.names),
        mask,
        coding=coding,
        rule=observe_rule(header.light_intensities, channel, shadow_threshold),
        folder=folder,
        in_memory=in_memory,
        sample_pixels=sample_pixels,
        colours=colours,
        threads=threads,
    )
    try:
        if coding.coded:
            frames = _prefetched(header, store.threads, store.stats)
        else:
            plan = header.plan
            store.stats["file_bytes"] = sum(
                f.stat().st_size for f in [*plan.dark_files, *(f for fs in plan.light_files
                                                                 for f in fs)])
            frames = ((frame, ~clipped) for frame, clipped in iter_frames(header.plan))
        _stage_frames(store, header, frames, progress)
    except BaseException:
        store.close()
        raise
    return store


def _timed_read(plan, light: int):
    started = time.perf_counter()
    coded = read_coded_light(plan, light)
    return coded, time.perf_counter() - started, coded.file.stat().st_size


def _prefetched(header: DatasetHeader, workers: int, stats: dict
                ) -> Iterator[tuple[np.ndarray, None]]:
    """Each light's codes, in light order, decoded up to ``workers`` frames ahead in threads."""
    n = len(header.names)
    reference: list = []
    with ThreadPoolExecutor(max(1, workers)) as pool:
        pending: deque = deque()
        following = iter(range(n))
        for i in following:
            pending.append(pool.submit(_timed_read, header.plan, i))
            if len(pending) > workers:
                break
        while pending:
            coded, seconds, size = pending.popleft().result()
            stats["decode_seconds"] += seconds
            stats["file_bytes"] += size
            nxt = next(following, None)
            if nxt is not None:
                pending.append(pool.submit(_timed_read, header.plan, nxt))
            yield _checked_codes(header, coded, reference), None


def _checked_codes(header, coded, reference: list) -> np.ndarray:
    """The codes of ``coded`` (light ``coded.light``) after checking them against the first."""
    if not reference:
        reference.append(coded)
    else:
        check_coded_geometry(coded, reference[0])
    return coded.frame.codes


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
    channels: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stage some lights into an existing store file (one task of a distributed pass 1).

    The frames are read as :func:`stage_observations` reads them in float (same bits) and
    written into the file another process created with :class:`ObservationStore` (``path``, with
    :func:`ps_lab.io.coding.float_coding` of the frames' channels); lights go to disjoint parts
    of the file, so several processes can stage at once, and staging a light twice writes the
    same bytes.

    Parameters
    ----------
    header, mask, bands, channel, shadow_threshold, sample_pixels, colours
        As for :func:`stage_observations` (the same values as the process that made the store).
    channels : int
        Channels of the frames (the store's :class:`ps_lab.io.coding.Coding`).
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
        bands, len(header.names), mask, sample_pixels=sample_pixels, path=path, colours=colours,
        coding=float_coding(channels),
        rule=observe_rule(header.light_intensities, channel, shadow_threshold),
    ) as store:
        _stage_frames(store, header, ((f, ~c) for f, c in frames), None, lights)
        return (
            store.sample_observations[lights],
            store.sample_valid[lights],
            store.sample_colour[lights],
        )


def _stage_frames(store, header, frames, progress, lights=None) -> None:
    """Store each frame of ``frames``: (values, valid or None) of ``lights`` (default all)."""
    height, width = store.shape
    indices = range(store.n_lights) if lights is None else lights
    for i, (frame, valid) in zip(indices, frames, strict=True):
        if frame.shape[:2] != (height, width):
            file = header.plan.light_files[i][0]
            raise DatasetError(
                f"{file}: image size {frame.shape[1]}x{frame.shape[0]} differs from the "
                f"first image ({width}x{height})"
            )
        store.write_frame(i, frame, valid)
        del frame, valid
        if progress is not None:
            progress(1)

