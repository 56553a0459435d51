"""One light set from several chrome probes calibrated apart (separate folders of the same lights).

Probes cropped into separate folders share the lights but not a pixel frame (the crops' offsets
are unknown), so their rays cannot be intersected: each probe gives directions, and the light
set is their inverse-variance weighted mean. Each probe's disagreement with it is reported per
light; when the probes disagree beyond their noise the lights are near (the direction differs
across the rig), which a directional set cannot model: a warning says to put the probes in one
frame, where LED positions are triangulated (:mod:`._positions`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from ps_lab.calibration._calibrate import Calibration
from ps_lab.errors import CalibrationError

# Probes whose disagreement is within this many combined standard uncertainties agree.
AGREEMENT_SIGMAS = 3.0


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def combine_probes(calibrations: Sequence[Calibration], labels: Sequence[str]) -> Calibration:
    """Merge per-probe calibrations of the same lights into one light set.

    Parameters
    ----------
    calibrations : sequence of Calibration
        One per probe, the same number of lights in the same order.
    labels : sequence of str
        A name per probe (its folder), for the records.

    Returns
    -------
    Calibration
        The first probe's record (circle, highlights, picture) with ``light_directions`` the
        weighted mean, ``uncertainty_deg`` its uncertainty, and ``metadata["probes"]``: per probe
        its circle, directions, per-light disagreement with the mean; per light the largest
        disagreement and whether it lies beyond the probes' noise.

    Raises
    ------
    CalibrationError
        Different numbers of lights, or a probe calibrated with LED positions.

    """
    if len(calibrations) < 2:
        return calibrations[0]
    n = len(calibrations[0].light_directions)
    for cal, label in zip(calibrations, labels, strict=True):
        if len(cal.light_directions) != n:
            raise CalibrationError(
                f"{label}: {len(cal.light_directions)} lights, {labels[0]} has {n}: the probes "
                "must be photographed under the same lights"
            )
    dirs = np.array([c.light_directions for c in calibrations])  # (k, n, 3)
    sigma = np.array(
        [
            c.uncertainty_deg if c.uncertainty_deg is not None else np.full(n, 0.1)
            for c in calibrations
        ]
    )
    sigma = np.maximum(sigma, 0.01)
    weights = 1.0 / sigma**2
    mean = np.einsum("kn,knc->nc", weights, dirs)
    mean /= np.linalg.norm(mean, axis=1, keepdims=True)
    combined_sigma = 1.0 / np.sqrt(weights.sum(axis=0))
    disagreement = _angles(dirs, mean[None])  # (k, n)
    # Per light, the worst pair of probes, against its expected spread (the two probes'
    # uncertainties in quadrature).
    pairs = [(a, b) for a in range(len(dirs)) for b in range(a + 1, len(dirs))]
    spread = np.array([_angles(dirs[a], dirs[b]) for a, b in pairs])
    noise = np.array([np.sqrt(sigma[a] ** 2 + sigma[b] ** 2) for a, b in pairs])
    beyond = np.any(spread > AGREEMENT_SIGMAS * noise, axis=0)
    pairwise, expected = spread.max(axis=0), noise.max(axis=0)
    first = calibrations[0]
    warnings = [f"{labels[0]}: {w}" for w in first.warnings]
    for cal, label in zip(calibrations[1:], labels[1:], strict=True):
        warnings.extend(f"{label}: {w}" for w in cal.warnings)
    if beyond.mean() > 0.5:
        warnings.append(
            f"the probes disagree beyond their noise on {int(beyond.sum())} of {n} lights "
            f"(mean {pairwise.mean():.2f} deg, expected {expected.mean():.2f} deg): the lights "
            "may be near; photograph the probes in one frame to place them (LED positions)"
        )
    metadata = dict(first.metadata)
    metadata["probes"] = {
        "labels": list(labels),
        "circles": [list(map(float, c.circle)) for c in calibrations],
        "directions": dirs.round(6).tolist(),
        "disagreement_deg": disagreement.round(4).tolist(),
        "pairwise_deg": {"mean": float(pairwise.mean()), "max": float(pairwise.max())},
        "beyond_noise": beyond.tolist(),
        "light_model": "directional",
    }
    return replace(
        first,
        light_directions=mean,
        uncertainty_deg=combined_sigma,
        warnings=warnings,
        metadata=metadata,
    )
