"""`ps-lab reconstruct` (not yet wired)."""

import typer


def register(app: typer.Typer) -> None:
    """Add this module's command(s) to app."""
