"""What every CLI command shares: typed errors to exit codes, JSON output, progress display."""

from __future__ import annotations

import functools
import json
import logging
import sys
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from station.errors import BadInputError, StationError

err_console = Console(stderr=True)
TRAINING_WIDTH_HELP = ("Width of the training images and masks, area-averaged from the masks cut on the developed raws; "
                       "default: as developed.")


def exits_on_station_errors(command: Callable) -> Callable:
    """Turn a StationError into its exit code and a one-line operator message on stderr."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except StationError as exc:
            err_console.print(f"[bold red]error:[/] {exc}", highlight=False)
            raise typer.Exit(exc.exit_code) from exc

    return wrapper


def emit(result: dict[str, Any], as_json: bool, human: Callable[[dict[str, Any]], None]) -> None:
    if as_json:
        sys.stdout.write(json.dumps(result, indent=2, default=str) + "\n")
    else:
        human(result)


@contextmanager
def progress_reporter(description: str) -> Iterator[Callable[[int, int, str], None]]:
    """A progress bar on a terminal; plain log lines otherwise (batch logs, CI)."""
    if sys.stderr.isatty():
        with Progress(
            TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            TextColumn("{task.fields[what]}"), console=err_console,
        ) as bar:
            task = bar.add_task(description, total=None, what="")

            def update(done: int, total: int, what: str) -> None:
                bar.update(task, completed=done, total=total, what=what)

            yield update
    else:
        log = logging.getLogger("station")
        last = [-1]

        def update(done: int, total: int, what: str) -> None:
            step = max(total // 20, 1)
            if done == total or done // step != last[0]:
                last[0] = done // step
                log.info("%s: %d/%d %s", description, done, total, what)

        yield update


def configure_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def parse_size(size: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError as exc:
        raise BadInputError(f"--size {size!r}: expected WIDTHxHEIGHT, e.g. 320x240") from exc
    if width < 16 or height < 16 or width % 2 or height % 2:
        raise BadInputError(f"--size {size!r}: both sides must be even and at least 16 pixels (Bayer 2x2 cells)")
    return width, height
