"""Convert any appearance model to RelightLab's ``rbf`` web layout (for OpenLIME), measured.

RelightLab's layout holds PTM, HSH, RBF and bilinear fits; ps-lab's default model (``ps``: the
normal and albedo plus gloss terms) and its other models are none of these. On export such a
model is **relit** at a set of light directions and the pictures are stored as OpenLIME's RBF
interpolation reads them (:mod:`ps_lab.appearance.relightlab`): a mean picture and ``P`` principal
components over the lights, each pixel ``P`` coefficients, relit at a light ``l`` as
``Σ_i w_i(l) (μ_i + Σ_p x_p E_{p,i})`` with normalised Gaussian weights of width σ.

The lights and σ are chosen by what reproduces the model best: the capture's lights or a dense
dome (:func:`dome`), σ from a grid around the lights' spacing, each candidate scored on a
pixel sample against the model itself at dome lights it was not sampled at (between the lowest
captured elevation and the zenith). The score, and the final conversion's, is the issue's
metric: PSNR of the grey (channel mean of linear RGB), sRGB-encoded, 8-bit peak, per picture,
mean over the pictures, in the object's pixels.

Pure functions of arrays; :func:`convert_to_rbf` takes a callable that relights the model.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ps_lab.appearance.relightlab import quantise_rbf_basis
from ps_lab.io.encoding import linear_to_srgb

__all__ = [
    "PLANES",
    "RbfConversion",
    "convert_to_rbf",
    "dome",
    "grey_psnr",
    "pca_basis",
    "rbf_predict",
]

#: Principal components stored (9 JPEGs of three planes: 27 numbers per pixel, as the default
#: ``ps`` model and HSH order 3 in colour).
PLANES = 27
#: Dome lights sampled when the capture's are not used, and dome lights scored on.
DOME_LIGHTS = 200
TEST_LIGHTS = 48
#: Pixels the choice and the score are measured on (a seeded sample of the picture).
SAMPLE_PIXELS = 20000
#: σ candidates, times the median spacing of the sampled lights.
SIGMA_FACTORS = (0.5, 0.7, 1.0, 1.4, 2.0)
#: Lowest elevation's z when the capture's lights are unknown.
DEFAULT_Z_MIN = 0.2

#: Relights the model: lights (m, 3) and flat pixel indices (N,) or None (all) -> (m, N, 3),
#: linear, exposed (0 outside the object).
Relight = Callable[[np.ndarray, np.ndarray | None], np.ndarray]


@dataclass(frozen=True)
class RbfConversion:
    """An ``rbf`` layout of a model, quantised as written, and how well it reproduces it."""

    lights: np.ndarray  # (n, 3)
    sigma: float
    mean_bytes: np.ndarray  # (n, 3) uint8
    eigen_bytes: np.ndarray  # (P, n, 3) uint8
    ranges: np.ndarray  # (P,)
    mean: np.ndarray  # (n, 3) decoded
    eigen: np.ndarray  # (P, n, 3) decoded
    lights_source: str  # "capture" or "dome"
    psnr: float  # on the sample, before the coefficients' 8-bit planes
    test_lights: np.ndarray  # (t, 3)

    def coefficients(self, pictures: np.ndarray) -> np.ndarray:
        """Each pixel's coefficients on the decoded basis (least squares).

        Parameters
        ----------
        pictures : ndarray of shape (n, N, 3)
            The model relit at :attr:`lights` (exposed).

        Returns
        -------
        ndarray of shape (N, P), float64

        """
        n, count, _ = pictures.shape
        centred = np.asarray(pictures, np.float64) - self.mean[:, None, :]
        rows = centred.transpose(1, 0, 2).reshape(count, n * 3)  # light-major, as the design
        return rows @ self.projection.T

    @property
    def projection(self) -> np.ndarray:
        """The least-squares projection onto the decoded components, (P, 3n)."""
        cached = self.__dict__.get("_projection")
        if cached is None:
            cached = np.linalg.pinv(self.eigen.reshape(len(self.eigen), -1).T)
            object.__setattr__(self, "_projection", cached)
        return cached


def dome(count: int, z_min: float, offset: float = 0.5) -> np.ndarray:
    """``count`` unit directions spread evenly (in solid angle) over the cap ``z ≥ z_min``.

    A Fibonacci spiral; another ``offset`` in (0, 1) gives a set between the first's points.

    Returns
    -------
    ndarray of shape (count, 3), float64

    """
    i = np.arange(count, dtype=np.float64)
    z = 1.0 - (1.0 - z_min) * (i + offset) / count
    phi = i * math.pi * (3.0 - math.sqrt(5.0)) + 2.0 * math.pi * offset
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def pca_basis(pictures: np.ndarray, planes: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and principal components of each pixel's pictures over the lights.

    Parameters
    ----------
    pictures : ndarray of shape (n, N, 3)
        N pixels' colours at n lights.
    planes : int
        Components kept (at most 3n).

    Returns
    -------
    mean : ndarray of shape (n, 3)
    eigen : ndarray of shape (P, n, 3)
        Orthonormal over the 3n values, largest variance first.

    """
    n, count, _ = pictures.shape
    flat = np.asarray(pictures, np.float64).transpose(1, 0, 2).reshape(count, n * 3)
    mean = flat.mean(axis=0)
    centred = flat - mean
    scatter = centred.T @ centred
    values, vectors = np.linalg.eigh(scatter)
    order = np.argsort(values)[::-1][: min(planes, n * 3)]
    eigen = vectors[:, order].T.reshape(-1, n, 3)
    return mean.reshape(n, 3), eigen


def rbf_predict(
    mean: np.ndarray, eigen: np.ndarray, coefficients: np.ndarray, lights: np.ndarray,
    sigma: float, at: np.ndarray,
) -> np.ndarray:
    """The pictures an ``rbf`` layout relights at the lights ``at``.

    Parameters
    ----------
    mean : ndarray of shape (n, 3)
    eigen : ndarray of shape (P, n, 3)
    coefficients : ndarray of shape (N, P)
    lights : ndarray of shape (n, 3)
    sigma : float
    at : ndarray of shape (t, 3)

    Returns
    -------
    ndarray of shape (t, N, 3), float64

    """
    d2 = np.sum((at[:, None, :] - lights[None, :, :]) ** 2, axis=2)  # (t, n)
    logw = -d2 / (sigma * sigma)
    weights = np.exp(logw - logw.max(axis=1, keepdims=True))
    weights /= weights.sum(axis=1, keepdims=True)
    base = weights @ mean.reshape(len(lights), 3)  # (t, 3)
    components = np.einsum("tn,pnc->tpc", weights, eigen)  # (t, P, 3)
    return base[:, None, :] + np.einsum("np,tpc->tnc", coefficients, components)


def grey_psnr(pictures: np.ndarray, reference: np.ndarray) -> float:
    """Mean over the pictures of the PSNR (8-bit peak) of the sRGB-encoded grey.

    Parameters
    ----------
    pictures, reference : ndarray of shape (t, N, 3)
        Linear, exposed (clipped to 0..1 as a screen shows them).

    Returns
    -------
    float
        dB; ``inf`` when every picture is exact.

    """
    def grey(x):
        return 255.0 * linear_to_srgb(np.clip(np.asarray(x, np.float64), 0, 1).mean(axis=2))

    error = np.mean((grey(pictures) - grey(reference)) ** 2, axis=1)  # (t,)
    with np.errstate(divide="ignore"):
        scores = 10.0 * np.log10(255.0**2 / error)
    return float(np.mean(scores))


def convert_to_rbf(
    relight: Relight,
    size: int,
    inside: np.ndarray,
    captured: np.ndarray | None,
    *,
    planes: int = PLANES,
    seed: int = 0,
) -> RbfConversion:
    """Choose the lights and σ of the ``rbf`` layout that reproduce a model best.

    Parameters
    ----------
    relight : callable
        ``relight(lights (m, 3), pixels (N,) or None) -> (m, N, 3)``, linear and exposed.
    size : int
        Pixels in the picture (flat indices ``0 .. size − 1``).
    inside : ndarray of shape (size,), bool
        The object's pixels (scored); the others are sampled too (they must relight dark).
    captured : ndarray of shape (n, 3) or None
        The capture's light directions (a candidate set, and their lowest elevation bounds the
        scored lights).
    planes : int
        Principal components.
    seed : int
        Seed of the pixel sample.

    Returns
    -------
    RbfConversion

    """
    rng = np.random.default_rng(seed)
    pixels = np.sort(rng.choice(size, min(size, SAMPLE_PIXELS), replace=False))
    scored = np.asarray(inside, bool)[pixels]
    if not scored.any():
        scored[:] = True
    candidates: list[tuple[str, np.ndarray]] = []
    z_min = DEFAULT_Z_MIN
    if captured is not None and len(captured) >= 3:
        unit = captured / np.linalg.norm(captured, axis=1, keepdims=True)
        z_min = float(np.clip(unit[:, 2].min(), 0.0, 0.95))
        candidates.append(("capture", unit))
    candidates.append(("dome", dome(max(DOME_LIGHTS, len(candidates[0][1]) if candidates else 0),
                                    max(0.0, z_min - 0.05))))
    test = dome(TEST_LIGHTS, z_min, offset=0.25)
    truth = relight(test, pixels)[:, scored]
    best = None
    for source, lights in candidates:
        pictures = relight(lights, pixels)
        mean, eigen = pca_basis(pictures, planes)
        mean_bytes, eigen_bytes, ranges, decoded_mean, decoded = quantise_rbf_basis(mean, eigen)
        trial = RbfConversion(lights, 1.0, mean_bytes, eigen_bytes, ranges, decoded_mean,
                              decoded, source, -math.inf, test)
        coefficients = trial.coefficients(pictures)[scored]
        spacing = _spacing(lights)
        for factor in SIGMA_FACTORS:
            sigma = factor * spacing
            predicted = rbf_predict(decoded_mean, decoded, coefficients, lights, sigma, test)
            score = grey_psnr(predicted, truth)
            if best is None or score > best.psnr:
                best = RbfConversion(lights, sigma, mean_bytes, eigen_bytes, ranges,
                                     decoded_mean, decoded, source, score, test)
    assert best is not None
    return best


def _spacing(lights: np.ndarray) -> float:
    """Median distance from each light to its nearest neighbour."""
    d2 = np.sum((lights[:, None, :] - lights[None, :, :]) ** 2, axis=2)
    np.fill_diagonal(d2, np.inf)
    return float(np.median(np.sqrt(d2.min(axis=1))))
