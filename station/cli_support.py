"""What every CLI command shares: typed errors to exit codes, JSON output, progress display."""

from __future__ import annotations

import errno
import functools
import json
import logging
import sys
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import click
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from station.errors import INTERNAL_EXIT_CODE, BadInputError, DiskFullError, StationError

log = logging.getLogger("station")
err_console = Console(stderr=True)
TRAINING_WIDTH_HELP = ("Width of the training images and masks, area-averaged from the masks cut on the developed raws; "
                       "default: as developed.")


def as_station_error(exc: Exception) -> StationError | None:
    """The typed error an exception stands for: itself, a full disk's DiskFullError, or None (a bug)."""
    if isinstance(exc, StationError):
        return exc
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        where = f"{exc.filename}: " if exc.filename else ""
        return DiskFullError(f"{where}the disk is full ({exc.strerror}); free some space and run again")
    return None


def exits_on_station_errors(command: Callable) -> Callable:
    """Turn every error into a one-line operator message on stderr and its exit code: a StationError's
    own, 3 for a full disk, INTERNAL_EXIT_CODE for anything unexpected (its traceback only with --verbose)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (click.exceptions.Exit, click.exceptions.Abort, click.ClickException):
            raise
        except Exception as exc:  # noqa: BLE001 - the top-level handler: nothing leaves as a bare traceback
            known = as_station_error(exc)
            if known is not None:
                err_console.print(f"[bold red]error:[/] {known}", highlight=False)
                raise typer.Exit(known.exit_code) from exc
            log.debug("unexpected error", exc_info=exc)
            first = (str(exc).strip().splitlines() or [""])[0]
            first = first if len(first) <= 160 else first[:157] + "..."
            err_console.print(f"[bold red]error:[/] unexpected {type(exc).__name__}: {first} "
                              "(a fault in station; run again with --verbose for the traceback)", highlight=False)
            raise typer.Exit(INTERNAL_EXIT_CODE) from exc

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
