"""ps_lab.reconstruct: robust photometric-stereo solvers (LS, L1, SBL, R-PCA) and light refinement.

The package imports neither ``ps_lab.capture`` nor ``ps_lab.calibration``.
"""

from ._refine import fit_lights, light_fit_sums, refine_lights
from ._solution import RefinementResult, Solution, SolverInputError
from ._noise import estimate_noise, estimate_noise_model, light_noise_factors
from ._solve import solve
from .methods import METHODS
from .metrics import angular_errors_deg, error_summary

__all__ = [
    "METHODS",
    "RefinementResult",
    "Solution",
    "SolverInputError",
    "angular_errors_deg",
    "error_summary",
    "estimate_noise",
    "estimate_noise_model",
    "fit_lights",
    "light_fit_sums",
    "light_noise_factors",
    "refine_lights",
    "solve",
]
