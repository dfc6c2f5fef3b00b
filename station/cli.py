"""The `station` command: thin wrappers that parse, call one function, and print the outcome."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from station import __version__
from station.cli_batch import batch_app
from station.cli_rig import calibrate, rig_app
from station.cli_serve import serve
from station.cli_support import (
    TRAINING_WIDTH_HELP,
    configure_logging,
    emit,
    err_console,
    exits_on_station_errors,
    parse_size,
    progress_reporter,
)
from station.errors import BadInputError, GateFailedError
from station.pipeline import run_stage

DEMO_SENSOR = (640, 480)  # simulated sensor size for `station demo`: masks are cut at this size ...
DEMO_TRAINING_WIDTH = 320  # ... and averaged down to the training images' (a camera finer than training)

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Turntable capture-to-asset station.")


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging.")) -> None:
    configure_logging(verbose)


@app.command()
def version() -> None:
    """Print the software version."""
    typer.echo(__version__)


@app.command()
@exits_on_station_errors
def scan(
    out: Path = typer.Option(..., "--out", help="Scan folder to create or resume."),
    sim: bool = typer.Option(False, "--sim", help="Scan on the simulated rig."),
    stone: Optional[str] = typer.Option(None, "--stone", help="Simulated stone: mesh path, seed, or look:seed."),
    port: Optional[str] = typer.Option(None, "--port", help="Turntable URL (grbl:///dev/ttyUSB0), device or pyserial URL."),
    camera: Optional[str] = typer.Option(None, "--camera", help="ptp, gphoto2, sim, or a camera URL (gphoto2://usb:001,004)."),
    config: Optional[Path] = typer.Option(None, "--config", help="station.toml describing the rig (docs/operator.md)."),
    elevations: Optional[int] = typer.Option(None, "--elevations", min=1),
    azimuths: Optional[int] = typer.Option(None, "--azimuths", min=1),
    size: str = typer.Option("320x240", "--size", help="Simulated sensor size WxH."),
    time_scale: float = typer.Option(0.05, "--time-scale", help="Simulated motion/exposure time factor."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Shoot (or resume) a 6x40 hemisphere scan: plates first, then every shot; nothing is ever re-shot twice."""
    from station.cli_scan import run_hardware_scan, run_sim_scan
    from station.config import load_config

    width, height = parse_size(size)
    started = time.monotonic()
    with progress_reporter("scan") as progress:
        if sim:
            summary = run_sim_scan(out, stone, elevations or 6, azimuths or 40, (width, height), time_scale, progress)
        elif port or config:
            rig_config = load_config(config).with_overrides(port=port, camera=camera, elevations=elevations, azimuths=azimuths)
            summary = run_hardware_scan(out, rig_config, progress)
        else:
            raise BadInputError("scan: give --sim, or --config station.toml / --port DEVICE for a real rig")
    result = {
        "scan": str(out),
        "frames": summary.total,
        "shot_now": len(summary.shot),
        "verified_from_before": len(summary.skipped_verified),
        "reshot_corrupt": len(summary.reshot_corrupt),
        "recoveries": summary.recoveries,
        "seconds": round(time.monotonic() - started, 2),
    }
    emit(result, as_json, lambda r: err_console.print(
        f"scan {r['scan']}: {r['frames']} frames ({r['shot_now']} shot now, {r['verified_from_before']} kept) in {r['seconds']} s"
    ))


@app.command("process")
@exits_on_station_errors
def process_command(
    scan_dir: Path = typer.Argument(..., help="Scan folder with raw/ and manifest.jsonl."),
    training_width: Optional[int] = typer.Option(None, "--training-width", help=TRAINING_WIDTH_HELP),
    config: Optional[Path] = typer.Option(None, "--config", help="station.toml whose rig_model poses the scan."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Develop the raws, cut the masks and pose the images (writes images/, masks/, poses/)."""
    from station.config import load_config

    result = run_stage(scan_dir, "process", _process_params(training_width, load_config(config).rig_model_path()))
    emit(result, as_json, lambda r: err_console.print(
        f"process {scan_dir}: {r['develop']['usable_shots']} images, posed by {r['poses']['method']} "
        f"({len(r['poses']['registered'])} registered), flags: {', '.join(r['flags']) or 'none'}"
    ))


@app.command("import")
@exits_on_station_errors
def import_command(
    src: Path = typer.Argument(..., help="Posed dataset to bring in."),
    fmt: str = typer.Option(..., "--format", help="nerfstudio, colmap, idr or middlebury."),
    out: Path = typer.Option(..., "--out", help="Scan folder to create at the posed stage."),
    masks: str = typer.Option("none", "--masks", help="For a source without masks: none, or dark-backdrop."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Bring an existing posed dataset (images, optional masks, cameras) into a scan folder."""
    from dataclasses import asdict

    from station.process.importers import ImportSettings, import_dataset

    if fmt not in ("nerfstudio", "colmap", "idr", "middlebury"):
        raise BadInputError(f"--format {fmt!r}: expected nerfstudio, colmap, idr or middlebury")
    report = import_dataset(src, fmt, out, ImportSettings(masks=masks))  # type: ignore[arg-type]
    emit(asdict(report), as_json, lambda r: err_console.print(f"imported {src} into {out}"))


def _process_params(training_width: int | None, rig_model: Path | None = None) -> dict:
    """Only what differs from the defaults, so the key matches the batch's for a plain process."""
    return {**({"training_width": training_width} if training_width is not None else {}),
            **({"rig_model": str(rig_model)} if rig_model is not None else {})}


def _export_params(stl: bool = False, reference: Path | None = None) -> dict:
    """Only what differs from the defaults, so the key matches the batch's for a plain export."""
    return {**({"stl": True} if stl else {}), **({"reference_mesh": str(reference)} if reference else {})}


def _train_with_progress(scan_dir: Path, method: str, preset: str):
    with progress_reporter("train") as progress:
        return run_stage(scan_dir, "train", {"method": method, "preset": preset}, progress)


@app.command()
@exits_on_station_errors
def train(
    scan_dir: Path = typer.Argument(..., help="Posed scan folder."),
    method: str = typer.Option("ngs", "--method", help="3dgs, alpha or ngs."),
    preset: str = typer.Option("fast", "--preset", help="fast or paper."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Train the splat model (an interrupted run resumes from its checkpoint, if the posed views are unchanged)."""
    from dataclasses import asdict

    report = _train_with_progress(scan_dir, method, preset)
    emit(asdict(report), as_json, lambda r: err_console.print(f"trained {scan_dir} ({method}, {preset})"))


@app.command()
@exits_on_station_errors
def sos(
    scan_dir: Path = typer.Argument(..., help="Trained scan folder (its infill is used)."),
    splat: Optional[Path] = typer.Option(None, "--splat", help="Score this INRIA PLY instead of the scan's model."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Surface Opacity Score and the starred metrics on the held-out views; writes transmittance maps."""
    from station.ngs.sos import evaluate_scan

    result = evaluate_scan(scan_dir, splat)
    result.pop("views", None)
    emit(result, as_json, lambda r: err_console.print(
        f"SOS {r['sos']:.3f}  PSNR {r['psnr']:.2f} dB  PSNR* {r['psnr_star']:.2f} dB  SSIM {r['ssim']:.3f}"
    ))


@app.command("export")
@exits_on_station_errors
def export_command(
    scan_dir: Path = typer.Argument(..., help="Trained scan folder."),
    stl: bool = typer.Option(False, "--stl", help="Also write asset/mesh.stl for printing."),
    reference: Optional[Path] = typer.Option(None, "--reference", help="A true mesh to score the asset's mesh against."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Splats, watertight mesh, metrics, the SOS gate and the report; exit 1 if the gate fails."""
    _verdict(run_stage(scan_dir, "export", _export_params(stl, reference)), as_json)


def _verdict(report, as_json: bool) -> None:
    """Print the export's verdict; a failed gate is exit 1 (GateFailedError), after the verdict is out."""
    result = {"scan": str(report.scan_root), "pass": report.passed, "gate": report.gate.to_json(),
              "files": {k: str(v) for k, v in report.files.items()}, "seconds": round(report.seconds, 1)}
    emit(result, as_json, lambda r: err_console.print(report.gate.summary()))
    if not report.passed:
        raise GateFailedError(f"{report.scan_root}: the asset failed the quality gate; see asset/QUARANTINED.txt")


def run_pipeline(scan_dir: Path, method: str, preset: str, reference: Path | None = None,
                 training_width: int | None = None, rig_model: Path | None = None):
    """process -> train -> export on the stage table; process and train are skipped when finished under the same key."""
    from station.pipeline import run_pipeline as walk

    params = {"process": _process_params(training_width, rig_model), "train": {"method": method, "preset": preset},
              "export": _export_params(reference=reference)}
    with progress_reporter("run") as progress:
        return walk(scan_dir, params, progress, say=err_console.print)


@app.command()
@exits_on_station_errors
def run(
    scan_dir: Path = typer.Argument(..., help="Scan folder; resumes where it stopped."),
    method: str = typer.Option("ngs", "--method"),
    preset: str = typer.Option("fast", "--preset"),
    training_width: Optional[int] = typer.Option(None, "--training-width", help=TRAINING_WIDTH_HELP),
    config: Optional[Path] = typer.Option(None, "--config", help="station.toml whose rig_model poses the scan."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """process + train + export; stages already done are skipped. Exit 1 if the gate fails."""
    from station.config import load_config

    rig_model = load_config(config).rig_model_path()
    _verdict(run_pipeline(scan_dir, method, preset, training_width=training_width, rig_model=rig_model), as_json)


@app.command()
@exits_on_station_errors
def demo(
    out: Path = typer.Option(Path("demo-out"), "--out", help="Folder for the demo scan and its asset."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """The main job on embedded defaults: the simulated rig scans a stone, then process, train, export, gate."""
    from station.cli_scan import run_sim_scan
    from station.ngs.warmup import start_kernel_warmup

    scan_dir = out / "scan"
    started = time.monotonic()
    start_kernel_warmup()  # compiles training's kernels on the core the scan leaves free (a fresh install's minute)
    with progress_reporter("scan") as progress:
        run_sim_scan(scan_dir, None, 6, 40, DEMO_SENSOR, 0.05, progress)
    err_console.print(f"scan: {time.monotonic() - started:.0f} s")
    # The simulator knows the true stone: the demo scores its mesh against it.
    report = run_pipeline(scan_dir, "ngs", "fast", reference=scan_dir / "sim_truth" / "mesh.ply",
                          training_width=DEMO_TRAINING_WIDTH)
    err_console.print(f"demo finished in {time.monotonic() - started:.0f} s; asset in {scan_dir / 'asset'}")
    _verdict(report, as_json)


app.command("serve")(serve)
app.add_typer(batch_app, name="batch")
app.add_typer(rig_app, name="rig")
app.command("calibrate")(calibrate)
