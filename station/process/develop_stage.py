"""The develop-and-mask stage over a whole scan folder.

Reads manifest.jsonl, takes one white balance for the scan from its neutral plates, measures the
lens's vignetting on the plates (photometry.py) and takes it out of the training images, scales
every frame to a common exposure (the manifest's, then each shot's to its ring's plate on the
static backdrop), optionally corrects colour against a chart seen in a plate,
and writes images/<stem>.png (16-bit sRGB), images_linear/<stem>.exr (half linear, the shot as
developed; plates too, so the masks can be cut again after posing) and masks/<stem>.png for every
shot. The mask holds the stone's coverage (255 inside, fractions on its edge), and images/ hold the
stone's own colour on those edge pixels, unmixed from the plate with the stone beside them as a prior
(masks.unmix): an image times its mask is the stone alone on black, the form training matches. The matte is cut at the developed
resolution and, when `ProcessSettings.training_width` is narrower, area-averaged down to it for
images/ and masks/ (images_linear/ stays as developed): a camera finer than the training images
gives masks finer than one training pixel. Frames that cannot be used are not fatal: each frame's
report carries its flags (unreadable, black, saturated, clipped highlights, implausible
mask), so an unattended run finishes and says exactly which views are suspect. Shots are developed and
matted in worker processes, one per core this process may use (workers.py).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Literal

import numpy as np

from station.errors import BadInputError, ScanFolderError
from station.process.colour import ChartNotFoundError, locate_and_fit_chart, white_balance_from_linear
from station.process.develop import Developed, DevelopSettings, WhiteBalance, develop_raw
from station.process.images_io import write_exr_half, write_mask_png, write_png16
from station.process.masks import MaskCheckSettings, MaskSettings, Matte, check_masks, compute_matte
from station.process.photometry import FlatField, FlatFieldSettings, exposure_to_plate, fit_flat_field
from station.process.workers import map_in_workers
from station.scanfolder import ManifestEntry, ScanFolder


@dataclass(frozen=True)
class ProcessSettings:
    develop: DevelopSettings = DevelopSettings()
    masks: MaskSettings = MaskSettings()
    checks: MaskCheckSettings = MaskCheckSettings()
    white_balance: Literal["plate", "as_shot"] = "plate"
    use_chart: bool = True  # correct colour against a ColorChecker found in a plate
    max_chart_delta_e: float = 6.0  # a chart fit worse than this is ignored (mis-located, too small)
    training_width: int | None = None  # images/ and masks/ are area-averaged down to this width; None: as developed
    flat_field: bool = True  # measure the lens's vignetting on the plates and divide it out
    flat_field_fit: FlatFieldSettings = FlatFieldSettings()
    exposure_to_plate: bool = True  # scale each shot to its ring's plate on the backdrop (shutter scatter)
    workers: int = 0  # processes developing and masking shots at once; 0: one per core this process may use

    def __post_init__(self) -> None:
        if self.training_width is not None and self.training_width < 1:
            raise BadInputError(f"training width {self.training_width}: must be a positive number of pixels")
        if self.workers < 0:
            raise BadInputError(f"workers {self.workers}: must be 0 (one per core) or a positive count")


@dataclass
class FrameReport:
    file: str
    kind: str
    elevation_deg: float
    azimuth_deg: float
    flags: list[str] = field(default_factory=list)
    clipped_fraction: float | None = None
    exposure_scale: float | None = None  # from the manifest's exposure time and ISO
    plate_gain: float | None = None  # then to the ring's plate on the backdrop: the shutter's own error
    mask_area_fraction: float | None = None


@dataclass
class DevelopReport:
    frames: list[FrameReport]
    white_balance: WhiteBalance
    colour_source: str  # "chart", or the camera matrix's source ("file", "libraw_table", "none")
    chart_delta_e00: tuple[float, float] | None  # (before, after) mean ΔE00 on the chart, if used
    plates: dict[float, str]  # elevation -> stem of the developed plate in images_linear/
    seconds: float
    matte_seconds: float = 0.0  # of `seconds`, the share spent cutting and unmixing the mattes
    flat_field: FlatField = FlatField()  # the lens's vignetting as measured on the plates (none: not measured)
    vignetting_stops: float | None = None  # the light it says the corners lose; None: not measured

    @property
    def usable_shots(self) -> list[FrameReport]:
        bad = {"unreadable", "black", "saturated", "no_plate"}
        return [f for f in self.frames if f.kind == "shot" and not bad.intersection(_flag_names(f.flags))]

    def to_json(self) -> dict:
        return asdict(self)

    def plate_for(self, elevation_deg: float) -> str:
        """Stem of the developed plate a shot at this elevation is masked against."""
        return self.plates[nearest_elevation(self.plates, elevation_deg)]


def nearest_elevation(elevations: Iterable[float], elevation_deg: float) -> float:
    """The plate elevation closest to a shot's (one plate per ring; a missing one borrows its neighbour's)."""
    return min(elevations, key=lambda e: abs(e - elevation_deg))


def flag_implausible_masks(
    rings: dict[float, list[tuple[float, str, np.ndarray]]], reports: dict[str, FrameReport], settings: MaskCheckSettings
) -> None:
    """Replace each frame's mask flags with `check_masks`' verdict on its ring of (azimuth, file, mask)."""
    for ring in rings.values():
        ring.sort(key=lambda item: item[0])
        for check in check_masks([m for _, _, m in ring], [f for _, f, _ in ring], settings):
            report = reports[check.name]
            report.flags = [f for f in report.flags if not f.startswith("mask:")]
            report.flags += [f"mask: {reason}" for reason in check.reasons]


def training_matte(
    shot: np.ndarray, plate: np.ndarray, settings: ProcessSettings,
    silhouette: np.ndarray | None = None, roofed: np.ndarray | None = None, flat: FlatField = FlatField(),
) -> Matte:
    """The matte a developed shot trains with: cut at the developed resolution, then averaged down to the
    training width (the first cut and the cut across rings alike).

    The cut sees the light as the sensor got it (the matte's noise model is photon noise against the plate's
    level); only the stone's colour is flat-fielded, by `flat`.
    """
    matte = compute_matte(shot, plate, settings.masks, silhouette, roofed)
    matte = Matte(matte.alpha, flat.correct(matte.foreground))
    return matte if settings.training_width is None else matte.downscaled(settings.training_width)


def write_training_view(scan: ScanFolder, stem: str, matte: Matte) -> None:
    """images/<stem>.png (the stone's own colour) and masks/<stem>.png (its coverage) from a training matte."""
    write_png16(scan.images_dir / f"{stem}.png", matte.foreground)
    write_mask_png(scan.masks_dir / f"{stem}.png", matte.alpha)


def _flag_names(flags: list[str]) -> set[str]:
    return {flag.split(":", 1)[0] for flag in flags}


def _exposure(entry: ManifestEntry) -> float:
    return entry.exposure_s * entry.iso if entry.exposure_s > 0 and entry.iso > 0 else 0.0


def _scan_white_balance(scan: ScanFolder, plates: list[ManifestEntry]) -> WhiteBalance:
    """Median of the per-plate backdrop balances: one balance for the whole scan, so colours agree."""
    camera = DevelopSettings(demosaic="LINEAR", output_space="camera", max_width=640)
    gains = []
    for entry in plates:
        path = scan.resolve_inside(entry.file)
        unit = develop_raw(path, camera, WhiteBalance((1.0, 1.0, 1.0), source="unit"))
        gains.append(white_balance_from_linear(unit.linear, source=entry.file).gains)
    median = np.median(np.array(gains), axis=0)
    return WhiteBalance((float(median[0]), 1.0, float(median[2])), source=f"median of {len(gains)} backdrop plates")


def develop_scan(scan: ScanFolder, settings: ProcessSettings = ProcessSettings()) -> DevelopReport:
    """Develop and mask every shot of `scan`; see the module docstring for what is written."""
    start = time.perf_counter()
    entries = scan.read_manifest()
    if not entries:
        raise ScanFolderError(f"{scan.manifest_path}: no frames listed")
    stems = [Path(e.file).stem for e in entries]
    if len(set(stems)) != len(stems):
        raise ScanFolderError(f"{scan.manifest_path}: two frames share a file stem; outputs would collide")
    reports = {e.file: FrameReport(e.file, e.kind, e.elevation_deg, e.azimuth_deg) for e in entries}
    readable = []
    for entry in entries:
        if not scan.verify_entry(entry):
            reports[entry.file].flags.append("unreadable: missing, or bytes differ from the manifest checksum")
        else:
            readable.append(entry)
    plates = [e for e in readable if e.kind == "plate"]
    if not plates:
        raise ScanFolderError(f"{scan.root}: no readable plate frame; masks need one empty plate per elevation")
    wb = _scan_white_balance(scan, plates) if settings.white_balance == "plate" else None
    exposures = [_exposure(e) for e in readable if _exposure(e) > 0]
    reference = float(np.median(exposures)) if exposures else 0.0

    def develop(entry: ManifestEntry) -> Developed | None:
        developed = _develop_frame(scan, entry, settings, wb, reference)
        if isinstance(developed, str):
            reports[entry.file].flags.append(developed)
            return None
        _record_frame(reports[entry.file], _FrameFacts.of(*developed))
        return developed[0]

    developed_plates, plate_stems = {}, {}
    for entry in plates:
        if (frame := develop(entry)) is not None:
            developed_plates[entry.elevation_deg], plate_stems[entry.elevation_deg] = frame, Path(entry.file).stem
    if not developed_plates:
        raise ScanFolderError(f"{scan.root}: no plate frame could be developed")
    flat = FlatField()
    if settings.flat_field:
        flat = fit_flat_field([p.linear for p in developed_plates.values()], settings.flat_field_fit)
    correction, colour_source, chart_de = None, next(iter(developed_plates.values())).matrix_source, None
    if settings.use_chart:
        for plate in developed_plates.values():
            try:
                fit = locate_and_fit_chart(flat.correct(plate.linear))
            except ChartNotFoundError:
                continue
            if fit.delta_e_after <= settings.max_chart_delta_e and fit.delta_e_after < fit.delta_e_before:
                correction, colour_source = fit.matrix.astype(np.float32), "chart"
                chart_de = (fit.delta_e_before, fit.delta_e_after)
                break
    plate_linear = {}
    for elevation, plate in developed_plates.items():
        plate_linear[elevation] = plate.linear if correction is None else np.clip(plate.linear @ correction.T, 0.0, None)
        write_exr_half(scan.images_linear_dir / f"{plate_stems[elevation]}.exr", plate_linear[elevation])

    shots = [e for e in readable if e.kind == "shot"]
    context = _ShotContext(scan, settings, wb, reference, correction, plate_linear, flat)
    rings: dict[float, list[tuple[float, str, np.ndarray]]] = {}
    matte_seconds = 0.0
    for entry, shot in zip(shots, map_in_workers(_develop_shot, shots, context, _set_shot_context, settings.workers)):
        report = reports[entry.file]
        if shot.unreadable is not None:
            report.flags.append(shot.unreadable)
            continue
        _record_frame(report, shot.frame)
        report.flags += shot.flags
        report.plate_gain, report.mask_area_fraction = shot.plate_gain, float(shot.mask.mean())
        matte_seconds += shot.matte_seconds
        rings.setdefault(entry.elevation_deg, []).append((entry.azimuth_deg, entry.file, shot.mask))

    flag_implausible_masks(rings, reports, settings.checks)
    used_wb = wb or WhiteBalance((1.0, 1.0, 1.0), source="as shot, per frame")
    return DevelopReport(
        frames=[reports[e.file] for e in entries],
        white_balance=used_wb,
        colour_source=colour_source,
        chart_delta_e00=chart_de,
        plates=plate_stems,
        seconds=time.perf_counter() - start,
        matte_seconds=matte_seconds,
        flat_field=flat,
        vignetting_stops=flat.corner_stops if settings.flat_field else None,
    )


def _develop_frame(
    scan: ScanFolder, entry: ManifestEntry, settings: ProcessSettings, wb: WhiteBalance | None, reference: float
) -> tuple[Developed, float] | str:
    """The frame developed and scaled to the scan's common exposure, with that scale; or why it could not be read."""
    try:
        frame = develop_raw(scan.resolve_inside(entry.file), settings.develop, wb)
    except BadInputError as exc:
        return f"unreadable: {exc}"
    scale = reference / _exposure(entry) if reference > 0 and _exposure(entry) > 0 else 1.0
    frame.linear *= np.float32(scale)
    return frame, scale


def _record_frame(report: FrameReport, facts: _FrameFacts) -> None:
    report.flags += facts.flags
    report.clipped_fraction, report.exposure_scale = facts.clipped_fraction, facts.exposure_scale


@dataclass(frozen=True)
class _ShotContext:
    """What every shot's develop and matte share, handed once to each worker process."""

    scan: ScanFolder  # the stage's view of it: its output folders may be staged siblings
    settings: ProcessSettings
    white_balance: WhiteBalance | None
    reference_exposure: float
    correction: np.ndarray | None  # the chart's colour matrix, when one was fitted
    plate_linear: dict[float, np.ndarray]
    flat: FlatField


@dataclass(frozen=True)
class _FrameFacts:
    """What a frame's report keeps of its develop."""

    flags: list[str]
    clipped_fraction: float
    exposure_scale: float

    @staticmethod
    def of(frame: Developed, exposure_scale: float) -> _FrameFacts:
        return _FrameFacts(list(frame.flags), frame.clipped_fraction, exposure_scale)


@dataclass(frozen=True)
class _ShotResult:
    unreadable: str | None
    frame: _FrameFacts | None = None
    flags: list[str] = field(default_factory=list)  # beyond the develop's own
    plate_gain: float | None = None
    mask: np.ndarray | None = None  # [H, W] bool at the training size
    matte_seconds: float = 0.0


_shot_context: _ShotContext | None = None


def _set_shot_context(context: _ShotContext) -> None:
    global _shot_context
    _shot_context = context


def _develop_shot(entry: ManifestEntry) -> _ShotResult:
    """Develop one shot, cut its matte against its ring's plate and write its three files (in a worker process,
    or in this one)."""
    context = _shot_context
    settings, scan = context.settings, context.scan
    developed = _develop_frame(scan, entry, settings, context.white_balance, context.reference_exposure)
    if isinstance(developed, str):
        return _ShotResult(unreadable=developed)
    frame = developed[0]
    flags = []
    plate_elev = nearest_elevation(context.plate_linear, entry.elevation_deg)
    if abs(plate_elev - entry.elevation_deg) > 1e-3:
        flags.append(f"no_plate: none at {entry.elevation_deg} deg, masked against {plate_elev} deg")
    correction = context.correction
    linear = frame.linear if correction is None else np.clip(frame.linear @ correction.T, 0.0, None)
    plate_gain = None
    if settings.exposure_to_plate and abs(plate_elev - entry.elevation_deg) <= 1e-3:
        plate_gain = exposure_to_plate(linear, context.plate_linear[plate_elev])
        linear *= np.float32(plate_gain)
    stem = Path(entry.file).stem
    started = time.perf_counter()
    matte = training_matte(linear, context.plate_linear[plate_elev], settings, flat=context.flat)
    matte_seconds = time.perf_counter() - started
    write_training_view(scan, stem, matte)
    write_exr_half(scan.images_linear_dir / f"{stem}.exr", linear)
    return _ShotResult(None, _FrameFacts.of(*developed), flags, plate_gain, matte.mask, matte_seconds)
