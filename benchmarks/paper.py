"""Regenerate the tables of Ikehata et al. (CVPR 2012) on rendered scenes.

A thin script over :mod:`ps_lab.bench.paper` (so that ``ps-lab bench paper`` works from an
installed CLI too). Usage::

    python benchmarks/paper.py [--quick] [--size N] [--light-sets K] [--seed S] [--tables 1,3,4,5]
                               [--markdown] [--json FILE]
"""

from __future__ import annotations

import sys

from ps_lab.bench.paper import (  # noqa: F401  (re-exported for importers of this module)
    PaperConfig,
    format_markdown,
    format_text,
    main,
    run_paper,
    table_images,
    table_noise,
    table_refinement,
)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
