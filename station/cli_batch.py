"""`station batch`: the overnight queue. Thin commands over station.batch (store, runner, summary).

The queue is one SQLite file: `--queue PATH`, else $STATION_QUEUE, else ./station-queue.sqlite.
`python -m station.cli_batch ...` is the same as `station batch ...`.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from station.batch.store import Job, JobStore, StoreConfig
from station.cli_support import TRAINING_WIDTH_HELP, configure_logging, emit, err_console, exits_on_station_errors
from station.errors import BadInputError, GateFailedError

batch_app = typer.Typer(add_completion=False, no_args_is_help=True,
                        help="Overnight queue: add scans, run them unattended, read the morning summary.")

QUEUE_OPTION = typer.Option(Path("station-queue.sqlite"), "--queue", envvar="STATION_QUEUE",
                            help="The queue's SQLite file.")
JSON_OPTION = typer.Option(False, "--json", help="Machine-readable output on stdout.")


def _store(queue: Path, must_exist: bool = False, config: StoreConfig | None = None) -> JobStore:
    if must_exist and not queue.is_file():
        raise BadInputError(f"{queue}: no queue here; create one with `station batch add`, or pass --queue")
    return JobStore(queue, config)


def _job_dict(job: Job) -> dict:
    return {"scan": job.scan, "state": job.state, "stage": job.stage, "verdict": job.verdict,
            "reason": job.reason, "attempts": job.attempts}


def _stage_values(items: list[str], option: str) -> dict[str, float]:
    """["train=600", ...] -> {"train": 600.0}; stage names and numbers checked."""
    from station.batch.stages import STAGE_NAMES

    values = {}
    for item in items:
        stage, _, number = item.partition("=")
        try:
            value = float(number)
        except ValueError:
            value = -1.0
        if stage not in STAGE_NAMES or value < 0:
            raise BadInputError(f"{option} {item!r}: expected STAGE=NUMBER with STAGE one of {', '.join(STAGE_NAMES)}")
        values[stage] = value
    return values


def summary_path(queue: Path) -> Path:
    """Where `run` writes the morning summary: beside the queue file."""
    return queue.with_name(f"{queue.stem}-summary.html")


@batch_app.command()
@exits_on_station_errors
def add(
    scans: Optional[List[Path]] = typer.Argument(None, help="Scan folders with a finished capture."),
    watch: Optional[List[Path]] = typer.Option(None, "--watch", help="Folder whose finished scans are queued, now and while `run` runs."),
    queue: Path = QUEUE_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Queue scans (once each; adding a queued scan again changes nothing)."""
    from station.batch.runner import add_watched
    from station.scanfolder import ScanFolder

    if not scans and not watch:
        raise BadInputError("batch add: give scan folders, or --watch DIR")
    store = _store(queue)
    for scan in scans or []:
        if not ScanFolder(scan).is_done("capture"):
            raise BadInputError(f"{scan}: not a scan folder with a finished capture (stages/capture.json missing)")
    for folder in watch or []:
        if not folder.is_dir():
            raise BadInputError(f"--watch {folder}: not a folder")
        store.add_watch(folder)
    jobs = [store.add(scan) for scan in scans or []] + add_watched(store)
    result = {"queue": str(queue), "jobs": [_job_dict(job) for job in {job.id: job for job in jobs}.values()]}
    emit(result, as_json, lambda r: err_console.print(f"{len(r['jobs'])} scan(s) in {queue}"))


@batch_app.command()
@exits_on_station_errors
def run(
    workers: int = typer.Option(1, "--workers", min=1, help="Scans worked on at once."),
    threads: int = typer.Option(0, "--threads", min=0, help="CPU threads per stage; 0: the cores shared among the workers."),
    executor: str = typer.Option("local", "--executor", help="local (stage processes here) or ray."),
    ray_address: Optional[str] = typer.Option(None, "--ray-address", help="An existing Ray cluster, HEAD:PORT (token auth: RAY_AUTH_MODE=token, "
                                                  "see docs/batch-ray.md); default: start a local one."),
    forever: bool = typer.Option(False, "--forever", help="Keep waiting for new scans (--watch) instead of stopping when the queue is empty."),
    method: str = typer.Option("ngs", "--method", help="3dgs, alpha or ngs."),
    preset: str = typer.Option("fast", "--preset", help="Training preset (paper, fast, tiny)."),
    training_width: Optional[int] = typer.Option(None, "--training-width", min=1, help=TRAINING_WIDTH_HELP),
    lease: float = typer.Option(60.0, "--lease", min=1.0, help="Seconds a claimed scan stays leased without a heartbeat."),
    max_attempts: int = typer.Option(3, "--max-attempts", min=1, help="Attempts before an erring scan is parked."),
    backoff: float = typer.Option(30.0, "--backoff", min=0.0, help="Seconds before the first retry; doubled each time."),
    poll: float = typer.Option(2.0, "--poll", min=0.05, help="Seconds between looks at an idle queue."),
    time_budget: Optional[List[str]] = typer.Option(None, "--time-budget", help="STAGE=SECONDS, e.g. train=7200."),
    disk_budget: Optional[List[str]] = typer.Option(None, "--disk-budget", help="STAGE=MB free needed to start it."),
    summary: Optional[Path] = typer.Option(None, "--summary", help="Morning summary HTML (default: beside the queue)."),
    queue: Path = QUEUE_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Work the queue until it is empty, then print and write the morning summary.

    Exit 0 when every scan passed, 1 when any was quarantined by the gate or parked."""
    from station.batch.runner import BatchSettings, run_batch, with_budgets
    from station.batch.summary import build_summary, print_summary, write_summary_html
    from station.ngs.preset_names import check_names

    if executor not in ("local", "ray"):
        raise BadInputError(f"--executor {executor!r}: expected local or ray")
    check_names(method, preset)  # an unknown method or preset is refused before any work
    budgets = with_budgets(_stage_values(time_budget or [], "--time-budget"),
                           _stage_values(disk_budget or [], "--disk-budget"))
    settings = BatchSettings(method=method, preset=preset, training_width=training_width, workers=workers,
                             threads=threads, poll_seconds=poll, budgets=budgets)
    store = _store(queue, config=StoreConfig(lease_seconds=lease, max_attempts=max_attempts, backoff_seconds=backoff))
    if executor == "ray":
        from station.batch.ray_executor import RayExecutor, ray_log_path

        engine = RayExecutor(ray_log_path(queue), ray_address,
                             num_cpus=None if ray_address else workers * settings.stage_threads())
    else:
        from station.batch.executors import LocalExecutor

        engine = LocalExecutor()
    run_batch(store, settings, engine, forever=forever)
    report = build_summary(store)
    html_path = summary or summary_path(queue)
    write_summary_html(report, html_path)

    def human(_: dict) -> None:
        print_summary(report, err_console)
        err_console.print(f"summary written to {html_path}")

    emit({**report.to_json(), "summary_html": str(html_path)}, as_json, human)
    if any(row.state == "parked" or (row.state == "done" and row.verdict != "pass") for row in report.rows):
        raise GateFailedError(f"a scan was parked or quarantined; see {html_path}")


@batch_app.command()
@exits_on_station_errors
def status(queue: Path = QUEUE_OPTION, as_json: bool = JSON_OPTION) -> None:
    """Per scan: state, current stage, verdict and reason."""
    store = _store(queue, must_exist=True)
    result = {"queue": str(queue), "jobs": [_job_dict(job) for job in store.jobs()]}

    def human(r: dict) -> None:
        for job in r["jobs"]:
            verdict = f" {job['verdict']}" if job["verdict"] else ""
            reason = f": {job['reason']}" if job["reason"] else ""
            err_console.print(f"{Path(job['scan']).name}: {job['state']}{verdict} ({job['stage'] or '-'}){reason}",
                              highlight=False, markup=False)

    emit(result, as_json, human)


@batch_app.command()
@exits_on_station_errors
def retry(scan: Path = typer.Argument(..., help="A parked, cancelled or finished scan."),
          queue: Path = QUEUE_OPTION, as_json: bool = JSON_OPTION) -> None:
    """Queue a scan again with a fresh set of attempts (finished stages are still kept)."""
    job = _store(queue, must_exist=True).retry(scan)
    emit(_job_dict(job), as_json, lambda r: err_console.print(f"{scan}: {r['state']}"))


@batch_app.command()
@exits_on_station_errors
def cancel(scan: Path = typer.Argument(..., help="A queued or running scan."),
           queue: Path = QUEUE_OPTION, as_json: bool = JSON_OPTION) -> None:
    """Take a scan out of the queue; a running stage is stopped at its next heartbeat."""
    job = _store(queue, must_exist=True).cancel(scan)
    emit(_job_dict(job), as_json, lambda r: err_console.print(f"{scan}: {r['state']}"))


@batch_app.command("summary")
@exits_on_station_errors
def summary_command(html: Optional[Path] = typer.Option(None, "--html", help="Also write the self-contained HTML file here."),
                    queue: Path = QUEUE_OPTION, as_json: bool = JSON_OPTION) -> None:
    """The morning summary: verdicts, stage times and failures per scan."""
    from station.batch.summary import build_summary, print_summary, write_summary_html

    report = build_summary(_store(queue, must_exist=True))
    if html is not None:
        write_summary_html(report, html)
    emit(report.to_json(), as_json, lambda r: print_summary(report, err_console))


if __name__ == "__main__":
    configure_logging(verbose=False)
    batch_app()
