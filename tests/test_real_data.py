"""SBL's defaults on a real capture: DiLiGenT cat (8-bit), every 4th mask pixel.

Skipped with a message when the shared data folder (``../shared/data/diligent-8bit`` from the
repository root) is absent. Not timed.
"""

from __future__ import annotations

import pytest

from ps_lab.bench import real

CAT = real.DEFAULT_FOLDER / "cat"


@pytest.fixture(scope="module")
def cat():
    if not real.find_objects(real.DEFAULT_FOLDER) or not CAT.is_dir():
        pytest.skip(f"real data absent: {CAT}")
    return real.load_object(CAT, every=4)


def test_default_sbl_within_2_percent_of_the_best_fixed_lambda(cat):
    default = real.solve_column(cat, "sbl")["mean"]
    fixed = {lam: real.solve_column(cat, f"sbl lam={lam:g}")["mean"] for lam in real.FIXED_LAMBDAS}
    assert default <= 1.02 * min(fixed.values()), (default, fixed)
    # and clearly better than least squares, which the paper's lambda = 1e-2 (raw) amounts to
    assert default < 0.9 * real.solve_column(cat, "ls")["mean"]
