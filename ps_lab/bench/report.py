"""The paper experiments' results as text, Markdown (for ``docs/results.md``) and JSON."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from ps_lab.bench.paper import METHOD_LABELS, Cell, ErrorTable, PaperResults, RefinementTable

__all__ = ["format_markdown", "format_text", "results_as_dict", "simple_table"]



def _key_text(table: ErrorTable, key: object) -> str:
    if table.key_label == "noise":
        return f"{float(key):.0%}"
    return str(key)


def _error_rows(table: ErrorTable, scene: str) -> tuple[list[str], list[list[str]]]:
    header = [table.key_label]
    for method in table.methods:
        label = METHOD_LABELS.get(method, method)
        header += [f"{label} mean", f"{label} median", f"{label} s"]
    header.append("pixels")
    rows = []
    for key in table.keys:
        row = [_key_text(table, key)]
        for method in table.methods:
            c = table.cell(scene, key, method)
            row += [f"{c.mean:.2f}", f"{c.median:.2f}", f"{c.seconds:.3f}"]
        row.append(f"{table.coverage[(scene, key)]:.0%}")
        rows.append(row)
    return header, rows


def _refinement_rows(table: RefinementTable, scene: str) -> tuple[list[str], list[list[str]]]:
    header = ["iteration"]
    for method in table.methods:
        label = METHOD_LABELS.get(method, method)
        header += [f"{label} normal", f"{label} light"]
    rows = []
    for k in table.iterations:
        row = [str(k)]
        for method in table.methods:
            row += [
                f"{table.normal_error[(scene, k, method)]:.2f}",
                f"{table.light_error[(scene, k, method)]:.2f}",
            ]
        rows.append(row)
    row = ["rot. removed"]
    for method in table.methods:
        row += ["", f"{table.aligned_light_error[(scene, method)]:.2f}"]
    rows.append(row)
    row = ["time s"]
    for method in table.methods:
        row += [f"{table.seconds[(scene, method)]:.2f}", ""]
    rows.append(row)
    return header, rows


def _blocks(table) -> list[tuple[str, list[str], list[list[str]]]]:
    out = []
    for scene in table.scenes:
        if isinstance(table, RefinementTable):
            header, rows = _refinement_rows(table, scene)
        else:
            header, rows = _error_rows(table, scene)
        out.append((f"Table {table.number} ({scene}): {table.title}", header, rows))
    return out


def _aligned(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(h.rjust(w) for h, w in zip(header, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join(lines)


def _markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---:" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _stats_lines(results: PaperResults) -> list[str]:
    lines = []
    for s in results.scene_stats:
        lines.append(
            f"{s.scene}: {s.pixels} px, Cook-Torrance roughness {s.roughness:.3f} "
            f"(peak specular {s.max_specular_ratio:.2f}x the largest Lambertian radiance), "
            f"specular-corrupted observations {np.mean(s.specular_share):.1%} "
            f"(per light set {', '.join(f'{v:.1%}' for v in s.specular_share)}), "
            f"observations in shadow {np.mean(s.shadow_share):.1%}"
        )
    return lines


def format_text(results: PaperResults) -> str:
    """All tables as aligned plain text, with the scene statistics and the run's settings."""
    c = results.config
    parts = [
        f"Paper experiments: {c.size}x{c.size} px, {c.light_sets} light sets of {c.n_lights} "
        f"lights (zenith <= {c.max_zenith_deg:g} deg), seed {c.seed}; errors in degrees, "
        "time in seconds per solve",
        *_stats_lines(results),
    ]
    for table in results.tables:
        for title, header, rows in _blocks(table):
            parts.append("")
            parts.append(title)
            parts.append(_aligned(header, rows))
        parts += [f"  note: {n}" for n in table.notes]
    parts.append("")
    parts.append(f"{results.seconds:.1f} s on {results.machine}")
    return "\n".join(parts)


def format_markdown(results: PaperResults) -> str:
    """All tables as Markdown (the body of the "Paper experiments" section of docs/results.md)."""
    c = results.config
    parts = [
        f"Command: `{c.command_line()}`  ",
        f"Machine: {results.machine}  ",
        f"Started: {results.date}; wall time {results.seconds:.0f} s; "
        f"source {results.revision}  ",
        f"Scenes: {c.size}x{c.size} px; {c.light_sets} light sets of {c.n_lights} lights "
        f"(zenith <= {c.max_zenith_deg:g} deg), seed {c.seed}. "
        "Errors in degrees, time in seconds per solve.",
        "",
        *[f"- {line}" for line in _stats_lines(results)],
    ]
    for table in results.tables:
        for title, header, rows in _blocks(table):
            parts += ["", f"**{title}**", "", _markdown(header, rows)]
        parts += ["", *[f"Note: {n}" for n in table.notes]]
    return "\n".join(parts)


def results_as_dict(results: PaperResults) -> dict:
    """A JSON-ready dict of a run (tuple keys joined with '/')."""

    def flat(d: dict) -> dict:
        return {
            "/".join(str(k) for k in key): (asdict(v) if isinstance(v, Cell) else v)
            for key, v in d.items()
        }

    tables = []
    for t in results.tables:
        if isinstance(t, RefinementTable):
            tables.append(
                {
                    "number": t.number,
                    "title": t.title,
                    "normal_error": flat(t.normal_error),
                    "light_error": flat(t.light_error),
                    "seconds": flat(t.seconds),
                }
            )
        else:
            tables.append(
                {
                    "number": t.number,
                    "title": t.title,
                    "cells": flat(t.cells),
                    "coverage": flat(t.coverage),
                }
            )
    return {
        "config": asdict(results.config),
        "scene_stats": [asdict(s) for s in results.scene_stats],
        "tables": tables,
        "seconds": results.seconds,
        "machine": results.machine,
        "date": results.date,
        "revision": results.revision,
    }


# --------------------------------------------------------------------------------------------
# Script entry point


def simple_table(head: list[str], rows: list[list[str]], *, markdown: bool = False) -> str:
    """One table of text cells: right-aligned columns two spaces apart, or markdown."""
    if markdown:
        out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        out += ["| " + " | ".join(cells) + " |" for cells in rows]
        return "\n".join(out)
    widths = [max(len(r[k]) for r in [head, *rows]) for k in range(len(head))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True))
                     for r in [head, *rows])


def method_table(
    rows: Sequence[Any],
    head: list[str],
    first: Callable[[Any], list[str]],
    cell: Callable[[Any, str, list[str]], str],
    *,
    markdown: bool = False,
) -> str:
    """:func:`simple_table` of one line per row (an object with a ``cells`` dict by column
    name): ``first(row)`` under ``head``, then ``cell(row, name, names)`` for each of the first
    row's column names; "" for no rows."""
    if not rows:
        return ""
    names = list(rows[0].cells)
    lines = [[*first(row), *(cell(row, name, names) for name in names)] for row in rows]
    return simple_table([*head, *names], lines, markdown=markdown)
