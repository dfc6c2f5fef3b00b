"""The `station` command: thin wrappers that parse, call one function, and map errors to exit codes."""

from __future__ import annotations

import typer

from station import __version__

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Turntable capture-to-asset station.")


@app.command()
def version() -> None:
    """Print the software version."""
    typer.echo(__version__)
