"""Regenerate the tables of Ikehata et al. (CVPR 2012) on rendered scenes.

A thin script over ``ps-lab bench paper`` (:mod:`ps_lab.bench.paper`), the one entry point of the
experiments; it takes the same options. Usage::

    python benchmarks/paper.py [--quick] [--size N] [--light-sets K] [--seed S] [--tables 1,3,4,5]
                               [--markdown] [--json FILE]
"""

from __future__ import annotations

import sys

from ps_lab.cli import app

if __name__ == "__main__":
    sys.exit(app(["bench", "paper", *sys.argv[1:]]))
