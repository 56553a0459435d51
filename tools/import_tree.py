"""Lay out the ``ps_lab`` namespace as one folder of links, for ``lint-imports``.

grimp (behind import-linter) finds a package's modules by walking its folder, but ps_lab's
sub-packages live in top-level folders mapped by pyproject's ``package-dir`` (``capture/`` is
``ps_lab.capture``). This builds ``OUT/ps_lab/`` from that mapping: links to every entry of
``ps_lab/`` plus one link per mapped sub-package, so that ``PYTHONPATH=OUT lint-imports`` sees the
whole namespace. Usage: ``python tools/import_tree.py OUT`` (the Makefile's test target runs it).
"""

from __future__ import annotations

import shutil
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def build(out: Path) -> None:
    """Replace ``out`` with the link tree of pyproject's ``package-dir`` mapping."""
    mapping = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-dir"
    ]
    shutil.rmtree(out, ignore_errors=True)
    package = out / "ps_lab"
    package.mkdir(parents=True)
    for entry in (ROOT / mapping["ps_lab"]).iterdir():
        if entry.name != "__pycache__":
            (package / entry.name).symlink_to(entry)
    for name, folder in mapping.items():
        parts = name.split(".")
        if len(parts) == 2:  # a sub-package kept in its own top-level folder
            (package / parts[1]).symlink_to(ROOT / folder)


if __name__ == "__main__":
    build(Path(sys.argv[1]).resolve())
