"""Command-line options shared by commands, kept apart from any command's heavy imports.

``ps-lab calibrate`` and ``ps-lab reconstruct`` both read frames with ``--encoding``; the option
lives here so that loading one command does not load the other (reconstruct's solvers need numba).
"""

from __future__ import annotations

from typing import Annotated

import typer

from ps_lab._cli_util import choices

Encoding = choices("Encoding", "auto linear srgb", "How integer pixel values map to light.")


EncodingOption = Annotated[
    Encoding,
    typer.Option(
        case_sensitive=False,
        help="How 8-bit frames map to light: auto (the files' ICC/EXIF/PNG metadata; JPEG "
        "without any is sRGB; 16-bit files and 8-bit PNG/TIFF without metadata are linear), "
        "linear, or srgb."
    ),
]
