"""The defaults on a real capture: DiLiGenT cat (8-bit), every 4th mask pixel.

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
    # and better than least squares, which the paper's lambda = 1e-2 (raw) amounts to (7.16
    # against 7.70 here; LS gains most from dropping the dark observations within the noise
    # floor of black: 8.03 before)
    assert default < 0.95 * real.solve_column(cat, "ls")["mean"]


def test_default_beats_the_authors_pl_sbl_and_its_own_sbl(cat):
    # the authors' PL-SBL code at its best lambda: 5.96 deg on all of cat (issue 23); measured
    # here 5.72 (every 4th pixel; all pixels 5.7-5.85), ps-lab's SBL 7.1, PL-SBL 6.1
    default = real.solve_column(cat, "auto")["mean"]
    assert default < 5.96
    assert default < real.solve_column(cat, "sbl")["mean"]


@pytest.mark.xfail(strict=True, reason=(
    "known gap (issue 42): PL-SBL's second fit from SBL's start (5.34 deg on cat) is not used by "
    "the default's choice (5.51); strict: this fails loudly once the default beats it again"))
def test_default_beats_its_own_pl_sbl(cat):
    assert real.solve_column(cat, "auto")["mean"] < real.solve_column(cat, "plsbl")["mean"]
