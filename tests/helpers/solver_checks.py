"""A vectorised solution against the per-pixel oracle (helpers/solver_oracles.py), run with the
solution's own parameters, within the bounds helpers/tolerances.py derives."""

from __future__ import annotations

import numpy as np

from helpers.solver_oracles import oracle_params, solve_oracle
from helpers.tolerances import PL_ALBEDO, assert_flags_agree, assert_within, solver_bounds


def assert_equals_oracle(sol, y, lights, valid, method):
    """The solution against the per-pixel oracle run with the solution's parameters."""
    normals, albedo, outliers, iterations, statistic = solve_oracle(
        y, lights, method, valid, statistic=True, **oracle_params(sol))
    same = sol.iterations == iterations
    # rounding of the other sums (QR and n x n matrices in the oracle), plus the stopping rule
    # where the iteration counts differ: helpers/tolerances.py, solver_bounds
    bound, margin = solver_bounds(method, sol.params, y, lights, valid, albedo, same)
    assert_within(sol.normals, normals, bound)
    pl = method in ("plls", "plsbl", "auto")
    # |d|x|| <= |dx|; the PL models' albedo also divides by the secant slope (PL_ALBEDO)
    assert_within(sol.albedo, albedo, (PL_ALBEDO if pl else 0.5 * bound) * albedo, "albedo")
    # The same stopping rule: counts differ only where a pixel's deciding step falls within
    # the paths' rounding of tol (those pixels have the stopping bound above).
    assert np.mean(same) > 0.99
    assert_flags_agree(sol.outliers, outliers, statistic, sol.params.get("outlier_threshold"),
                       margin)
    return iterations
