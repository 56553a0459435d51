"""LS, L1, SBL and R-PCA on real objects with ground truth (default: ../shared/data/diligent-8bit).

A thin script over ``ps-lab bench real`` (:mod:`ps_lab.bench.real`); it takes the same options.
Usage::

    python benchmarks/real.py [FOLDER] [--every N] [--markdown] [--json FILE] [--threads T]
"""

from __future__ import annotations

import sys

from ps_lab.cli import app

if __name__ == "__main__":
    sys.exit(app(["bench", "real", *sys.argv[1:]]))
