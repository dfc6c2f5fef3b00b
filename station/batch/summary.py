"""The morning summary: per scan, its verdict, how long each stage took, where each attempt ran, and what
went wrong and of which kind (the machinery under a stage, or the stage itself).

Built from the job store alone (jobs and the stage log), so it can be printed or written at any
time, even while a batch still runs. The HTML file is self-contained (inline CSS, no scripts,
no external links): it can be mailed or opened from a USB stick.
"""

from __future__ import annotations

import html
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rich.console import Console
from rich.table import Table
from rich.text import Text

from station.batch.stages import STAGE_NAMES
from station.batch.store import JobStore
from station.scanfolder import atomic_write_text

# What a failure says about the scan, for the reader of the summary
FAILURE_KIND = {
    "lost": "infrastructure: the node or worker under the stage failed; run again as it was",
    "diverged": "the training itself diverged",
    "out_of_memory": "the stage itself ran out of memory",
    "died": "the stage process was killed (out of memory?)",
    "bad_input": "bad input",
    "disk_full": "disk full",
    "timeout": "over its time budget",
}


@dataclass
class ScanRow:
    scan: str
    state: str
    stage: str | None
    verdict: str | None
    reason: str | None
    attempts: int
    stage_seconds: dict[str, float] = field(default_factory=dict)  # last finished run of each stage
    skipped: list[str] = field(default_factory=list)  # stages found finished and verified
    failures: list[str] = field(default_factory=list)  # "train (diverged: ..., preset tiny, on NODE): ..."
    nodes: dict[str, list[str]] = field(default_factory=dict)  # per stage, each attempt: "NODE finished|lost|..."
    wall_seconds: float | None = None  # first stage start to the last event

    @property
    def name(self) -> str:
        return Path(self.scan).name


@dataclass
class Summary:
    queue: str
    generated_utc: str
    rows: list[ScanRow]

    def counts(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for row in self.rows:
            label = row.verdict if row.state == "done" and row.verdict else row.state
            counts[label] = counts.get(label, 0) + 1
        return counts

    def to_json(self) -> dict:
        return {"queue": self.queue, "generated_utc": self.generated_utc, "counts": self.counts(),
                "scans": [asdict(row) for row in self.rows]}


def build_summary(store: JobStore) -> Summary:
    rows = []
    for job in store.jobs():
        row = ScanRow(job.scan, job.state, job.stage, job.verdict, job.reason, job.attempts)
        events = store.stage_events(job.id)
        for event in events:
            detail = json.loads(event["detail"] or "{}")
            if event["event"] in ("finished", "failed", "abandoned") and detail.get("node"):
                ended = detail.get("kind") if event["event"] == "failed" else event["event"]
                row.nodes.setdefault(event["stage"], []).append(f"{detail['node']} {ended}")
            if event["event"] == "finished":
                row.stage_seconds[event["stage"]] = detail.get("seconds", 0.0)
            elif event["event"] == "skipped" and event["stage"] not in row.skipped:
                row.skipped.append(event["stage"])
            elif event["event"] == "failed":
                kind = str(detail.get("kind"))
                what = f"{kind}: {FAILURE_KIND[kind]}" if kind in FAILURE_KIND else kind
                preset = f", preset {detail['preset']}" if detail.get("preset") else ""
                node = f", on {detail['node']}" if detail.get("node") else ""
                message = str(detail.get("message")).replace(f"{job.scan}/", "")  # the row names the scan
                row.failures.append(f"{event['stage']} ({what}{preset}{node}): {message}")
        starts = [e["at"] for e in events if e["event"] == "started"]
        if starts:
            row.wall_seconds = round(events[-1]["at"] - min(starts), 1)
        rows.append(row)
    return Summary(str(store.path), time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), rows)


def _verdict(row: ScanRow) -> str:
    return row.verdict.upper() if row.state == "done" and row.verdict else row.state


def print_summary(summary: Summary, console: Console) -> None:
    """A table of verdicts and stage times, then each scan's reason on its own (long) line."""
    table = Table(title=f"batch {summary.queue}: " + ", ".join(f"{n} {k}" for k, n in summary.counts().items()))
    for column in ("scan", "verdict", "stage", *STAGE_NAMES, "wall", "fails"):
        table.add_column(column, no_wrap=column != "scan")
    for row in summary.rows:
        times = [f"{row.stage_seconds[s]:.0f} s" if s in row.stage_seconds else ("kept" if s in row.skipped else "-")
                 for s in STAGE_NAMES]
        wall = "-" if row.wall_seconds is None else f"{row.wall_seconds:.0f} s"
        cells = (row.name, _verdict(row), row.stage or "-", *times, wall, str(len(row.failures)))
        table.add_row(*(Text(cell) for cell in cells))  # Text: a "[...]" in a name is not markup
    console.print(table)
    used = {entry.rsplit(" ", 1)[0] for row in summary.rows for entries in row.nodes.values() for entry in entries}
    for row in summary.rows:
        lines = [f"{row.name}: {row.reason}"] if row.reason else []
        lines += [f"{row.name}: {failure}" for failure in row.failures]
        if row.nodes and (len(used) > 1 or row.failures):  # one machine: where is no news
            lines.append(f"{row.name} ran on: {where(row)}")
        for line in lines:  # one line each, however long: grep and copy work on it
            console.print(line, highlight=False, markup=False, soft_wrap=True)


def where(row: ScanRow) -> str:
    """Each stage's attempts and their nodes, in stage order: "train on A (lost), then B; export on B"."""
    def attempts(stage: str) -> str:
        parts = [entry.rsplit(" ", 1) for entry in row.nodes[stage]]
        return ", then ".join(node if ended == "finished" else f"{node} ({ended})" for node, ended in parts)

    return "; ".join(f"{stage} on {attempts(stage)}" for stage in STAGE_NAMES if stage in row.nodes)


_CSS = """
body { font: 14px/1.4 system-ui, sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; width: 100%; }
th, td { border-bottom: 1px solid #ddd; padding: 4px 8px; text-align: left; vertical-align: top; }
th { background: #f4f4f4; }
.pass { color: #0a6b2d; font-weight: bold; } .quarantined, .parked { color: #a11; font-weight: bold; }
.running, .queued { color: #8a5a00; } .num { text-align: right; white-space: nowrap; }
ul { margin: 0; padding-left: 1.2em; } small { color: #666; }
"""


def summary_html(summary: Summary) -> str:
    e = html.escape
    counts = ", ".join(f"{n} {e(k)}" for k, n in summary.counts().items()) or "no scans"
    head = "".join(f"<th>{e(c)}</th>" for c in ("scan", "verdict", "stage", *STAGE_NAMES, "wall", "reason", "failures",
                                                "ran on"))
    body = []
    for row in summary.rows:
        verdict = _verdict(row)
        cells = [f"<td title='{e(row.scan)}'>{e(row.name)}</td>",
                 f"<td class='{e(verdict.lower())}'>{e(verdict)}</td>", f"<td>{e(row.stage or '-')}</td>"]
        for stage in STAGE_NAMES:
            text = f"{row.stage_seconds[stage]:.1f} s" if stage in row.stage_seconds else (
                "kept" if stage in row.skipped else "-")
            cells.append(f"<td class='num'>{text}</td>")
        cells.append(f"<td class='num'>{'-' if row.wall_seconds is None else f'{row.wall_seconds:.0f} s'}</td>")
        cells.append(f"<td>{e(row.reason or '')}</td>")
        failures = "".join(f"<li>{e(f)}</li>" for f in row.failures)
        cells.append(f"<td>{f'<ul>{failures}</ul>' if failures else ''}</td>")
        cells.append(f"<td><small>{e(where(row))}</small></td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<title>station batch summary</title><style>{_CSS}</style></head><body>"
        f"<h1>Batch summary</h1><p>{counts}<br><small>queue {e(summary.queue)}; "
        f"generated {e(summary.generated_utc)}</small></p>"
        f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table></body></html>\n"
    )


def write_summary_html(summary: Summary, path: Path) -> None:
    atomic_write_text(path, summary_html(summary))
