"""Pixel codes to light: code tables, and the observe rule fused over a block of observations.

An 8- or 16-bit file stores integer codes; light is a function of the code alone (the file's
transfer curve, :mod:`ps_lab.io.encoding`), so a table of ``2**bits`` values per channel
(:func:`code_table`) decodes a frame by lookup, bit for bit what decoding every pixel gives. The
observation store (:mod:`ps_lab.io.bands`) keeps a capture as its codes (one or two bytes per
sample, the source's size) and turns a band into the solvers' observations only when it is read,
with :func:`observe_block`: per light, the colour rule (each channel divided by the light's
intensity for it, then the channels averaged or one kept), the validity rule (not saturated; above
the shadow threshold when one is given) and the colour observations, in one pass (numba, in
:mod:`ps_lab.io._coding_kernel`, imported on the first call: reading frames needs no numba).

:func:`combine` is the same colour rule on whole frames (numpy), written as the same float32
operations in the same order, so a frame observed here or in the store gives the same bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CHANNEL_MODES", "Coded", "Coding", "code_table", "combine", "observe_block",
           "observe_rule"]

#: ``channel`` values: average the divided channels, or keep one.
CHANNEL_MODES = {"mean": -1, "r": 0, "g": 1, "b": 2}


@dataclass(frozen=True)
class Coding:
    """How stored values become light.

    Attributes
    ----------
    dtype : numpy dtype
        ``uint8`` or ``uint16`` (codes) or ``float32`` (linear values as decoded).
    channels : int
        1 (grey) or 3 (RGB).
    table : ndarray of shape (2**bits, channels), float32, or None
        Linear light of each code per channel (codes); None for linear float values.
    clip : int
        Codes at or above it in any channel are saturated (codes only).

    """

    dtype: np.dtype
    channels: int
    table: np.ndarray | None = None
    clip: int = 0

    @property
    def itemsize(self) -> int:
        """Bytes per stored sample."""
        return np.dtype(self.dtype).itemsize

    @property
    def coded(self) -> bool:
        """Values are integer codes (decoded by ``table``)."""
        return self.table is not None


@dataclass(frozen=True)
class Coded:
    """An 8- or 16-bit file as stored: its codes and how they map to light.

    Attributes
    ----------
    codes : ndarray of shape (H, W, C), uint8 or uint16
        C = 1 or 3, colour in RGB order.
    coding : Coding
        The code table (per channel) of the file's transfer curve and the saturation level.
    bit_depth : int
    encoding : str
        The transfer curve's name (``image_encoding``'s answer).
    """

    codes: np.ndarray
    coding: Coding
    bit_depth: int
    encoding: str = "linear"
    exposure_s: float | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the image."""
        return self.codes.shape[:2]

    @property
    def channels(self) -> int:
        """Channels per pixel (1 or 3)."""
        return self.codes.shape[2]


def float_coding(channels: int) -> Coding:
    """The coding of linear float32 values (RAW, float files, dark-subtracted frames)."""
    return Coding(np.dtype(np.float32), int(channels))


def code_table(bits: int, channels: int, decode) -> np.ndarray:
    """The linear light of every code: ``decode(code / top)`` per channel, float32.

    Parameters
    ----------
    bits : int
        8 or 16.
    channels : int
    decode : callable
        ``decode(values (L, 1, C) float32 in [0, 1]) -> (L, 1, C) float32`` (an encoding's
        :meth:`~ps_lab.io.encoding.Encoding.decode`, or the identity for linear files).

    Returns
    -------
    ndarray of shape (2**bits, channels), float32
        Values of codes scaled exactly as the readers scale a pixel: ``code * float32(1 / top)``.
    """
    top = (1 << int(bits)) - 1
    codes = np.arange(top + 1, dtype=np.float64)
    values = np.multiply(codes, np.float32(1.0 / top), dtype=np.float32)
    values = np.array(np.broadcast_to(values[:, None, None], (top + 1, 1, channels)))
    return np.array(np.asarray(decode(values), np.float32)[:, 0, :], order="C")


@dataclass(frozen=True)
class ObserveRule:
    """The per-light constants of the colour and validity rules (:func:`observe_rule`)."""

    divisors: np.ndarray  # (n, 3) float32: each channel's intensity (colour observations)
    weights: np.ndarray  # (n, 3) float32: 1 / (3 I) (mean of three channels)
    grey: np.ndarray  # (n,) float32: the divisor of a grey frame (or of the kept channel)
    mode: int  # CHANNEL_MODES
    threshold: float  # observations at or below it are invalid (with ``use_threshold``)
    use_threshold: bool


def observe_rule(intensities: np.ndarray, channel: str = "mean",
                 shadow_threshold: float | None = None) -> ObserveRule:
    """The constants of :func:`combine` for every light.

    Parameters
    ----------
    intensities : ndarray of shape (n, 3)
        Each light's RGB intensity.
    channel : {"mean", "r", "g", "b"}
    shadow_threshold : float or None
    """
    intensity = np.asarray(intensities, dtype=np.float64).reshape(-1, 3)
    mode = CHANNEL_MODES[channel]
    grey = intensity.mean(axis=1) if mode < 0 else intensity[:, mode]
    return ObserveRule(
        divisors=np.ascontiguousarray(intensity.astype(np.float32)),
        weights=np.ascontiguousarray((1.0 / (3.0 * intensity)).astype(np.float32)),
        grey=np.ascontiguousarray(grey.astype(np.float32)),
        mode=mode,
        threshold=float(np.float32(shadow_threshold)) if shadow_threshold is not None else 0.0,
        use_threshold=shadow_threshold is not None,
    )


def combine(image: np.ndarray, intensity: np.ndarray, channel: str = "mean") -> np.ndarray:
    """Divide each channel by the light's intensity, then reduce to one value per pixel.

    Parameters
    ----------
    image : ndarray of shape (..., C), float32
        C = 1 or 3.
    intensity : ndarray of shape (3,)
    channel : {"mean", "r", "g", "b"}

    Returns
    -------
    ndarray of shape (...), float32
        ``(c0 w0 + c1 w1) + c2 w2`` with ``w = float32(1 / (3 I))`` (mean), ``c_k / float32(I_k)``
        (one channel), ``c / float32(mean(I) or I_k)`` (grey): the operations of
        :func:`observe_block`, so both give the same bits.
    """
    rule = observe_rule(np.asarray(intensity, np.float64).reshape(1, 3), channel)
    image = np.asarray(image, dtype=np.float32)
    if image.shape[-1] == 1:
        return image[..., 0] / rule.grey[0]
    if rule.mode >= 0:
        return image[..., rule.mode] / rule.divisors[0, rule.mode]
    w = rule.weights[0]
    return (image[..., 0] * w[0] + image[..., 1] * w[1]) + image[..., 2] * w[2]


def observe_block(values: np.ndarray, saturated: np.ndarray | None, coding: Coding,
                  rule: ObserveRule, lights: np.ndarray, colour: bool, out=None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Observations, validity and colour observations of a block of stored values.

    Parameters
    ----------
    values : ndarray of shape (n, P, C)
        Stored values of ``coding`` (codes or linear float32) of n lights, in light order.
    saturated : ndarray of shape (n, P), bool, or None
        Saturation of float values (None for codes: a code at or above ``coding.clip`` in any
        channel is saturated).
    coding : Coding
    rule : ObserveRule
        Of all the capture's lights.
    lights : ndarray of shape (n,), int
        Which of the rule's lights the rows of ``values`` are.
    colour : bool
        Also return the colour observations (C = 3 only).
    out : tuple of ndarray or None
        ``(observations, valid, colour or None)`` to fill (C-ordered, of the shapes returned).

    Returns
    -------
    observations : ndarray of shape (n, P), float32
    valid : ndarray of shape (n, P), bool
    colour : ndarray of shape (n, P, 3), float32, or None
    """
    n, p, c = values.shape
    want = bool(colour) and c == 3
    if out is None:
        obs, valid = np.empty((n, p), np.float32), np.empty((n, p), np.bool_)
        out = np.empty((n, p, 3) if want else (0, 0, 3), np.float32)
    else:
        obs, valid, out = out
        out = out if want else np.empty((0, 0, 3), np.float32)
    table = coding.table if coding.table is not None else np.zeros((1, c), np.float32)
    sat = saturated if saturated is not None else np.zeros((0, 0), np.bool_)
    if n and p:
        from ps_lab.io._coding_kernel import _observe  # numba: loaded when observing

        _observe(np.ascontiguousarray(values), sat, coding.table is not None, table,
                 int(coding.clip), rule.divisors, rule.weights, rule.grey, rule.mode,
                 np.float32(rule.threshold), rule.use_threshold,
                 np.ascontiguousarray(lights, np.int64), obs, valid, want, out)
    return obs, valid, (out if want else None)
