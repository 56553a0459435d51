"""Result types and the input error of the solvers."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ps_lab.errors import DatasetError

METHODS = ("auto", "ls", "l1", "sbl", "plls", "plsbl", "rpca")


class SolverInputError(DatasetError, ValueError):
    """Observations, lights or parameters a solver cannot use (shape, NaN, rank, unknown option).

    A :class:`~ps_lab.errors.DatasetError` (the CLI prints one line) and a ``ValueError`` (for
    library callers).
    """


@dataclass(frozen=True)
class Solution:
    """Per-pixel result of a photometric-stereo solver.

    Attributes
    ----------
    normals : ndarray of shape (P, 3)
        Unit normals, camera frame of the lights; zeros where a pixel is unsolvable (fewer than
        three usable observations, or degenerate lights).
    albedo : ndarray of shape (P,)
        Length of the fitted albedo-normal vector, in the units of the observations.
    outliers : ndarray of shape (n, P), bool
        Observations the method treated as corrupted (invalid observations are never flagged).
    iterations : ndarray of shape (P,), int
        Iterations each pixel ran (1 for ``ls``; the global ALM count for ``rpca``).
    params : dict
        The method and every parameter actually used (``lambda`` after auto-estimation, ...).
    """

    normals: np.ndarray
    albedo: np.ndarray
    outliers: np.ndarray
    iterations: np.ndarray
    params: dict = field(default_factory=dict)


@dataclass(frozen=True)
class RefinementResult:
    """Result of :func:`refine_lights`.

    Attributes
    ----------
    solution : Solution
        The solver's result with the final (refined) lights.
    light_directions : ndarray of shape (n, 3)
        Refined unit light directions.
    light_intensities : ndarray of shape (n,)
        Refined relative intensities (the input ones when ``fixed_intensities``).
    history : list of dict
        One entry per refinement iteration: ``iteration``, ``mean_direction_change_deg``,
        ``max_direction_change_deg``, ``mean_intensity_change`` and, when a ground truth was
        given, ``normal_error_deg`` (mean error of the normals solved with the lights *before* that
        iteration's update) plus ``light_error_deg`` when true lights were given. A final entry
        with ``iteration = iterations`` reports the error after the last update.
    """

    solution: Solution
    light_directions: np.ndarray
    light_intensities: np.ndarray
    history: list = field(default_factory=list)
