"""`station process`: develop, mask and pose one scan folder, cut the masks again across rings, then mark
the stage done.

The rig model comes from, in order: the calibrated station model (`rig_model`, the path the station
config names), the nominal rig recorded in scan.json, or none at all (pure SfM, for scans made elsewhere).
"""

from __future__ import annotations

from pathlib import Path

from station.errors import BadInputError
from station.process.cross_view import CrossViewSettings, refine_masks_across_rings
from station.process.develop_stage import ProcessSettings, develop_scan
from station.process.poses import PoseSettings, pose_scan
from station.process.rig_model import RigModel
from station.rig_geometry import RigGeometry
from station.scanfolder import ScanFolder


def station_rig_model(scan: ScanFolder, rig_model: Path | None) -> RigModel | None:
    """The best rig prior for this scan, or None when the scan carries no rig at all."""
    if rig_model is not None:
        if not rig_model.is_file():
            raise BadInputError(f"{rig_model}: rig model file not found; write it with `station calibrate`")
        return RigModel.load(rig_model)
    if not scan.scan_json.exists():
        return None
    record = scan.read_scan_json()
    if not isinstance(record.get("rig"), dict) or not isinstance(record.get("plan"), dict):
        return None
    return RigModel.nominal(RigGeometry.from_dict(record["rig"]), list(record["plan"]["elevations_deg"]))


def process_scan(
    scan_root: Path | ScanFolder,
    develop: ProcessSettings = ProcessSettings(),
    poses: PoseSettings = PoseSettings(),
    rig_model: Path | None = None,
    cross_view: CrossViewSettings = CrossViewSettings(),
) -> dict:
    """Develop + masks, then poses, then the masks again with the other rings' silhouettes; returns (and
    records in stages/process.json) the reports."""
    scan = scan_root if isinstance(scan_root, ScanFolder) else ScanFolder(scan_root)
    if not scan.root.is_dir():
        raise BadInputError(f"{scan.root}: scan folder not found")
    prior = station_rig_model(scan, rig_model)  # a missing rig model is refused before the long develop
    developed = develop_scan(scan, develop)
    if not developed.usable_shots:
        raise BadInputError(f"{scan.root}: no usable shot after develop; see the per-frame flags in stages/")
    posed = pose_scan(scan, poses, prior)
    masks_across_rings = refine_masks_across_rings(scan, developed, develop, cross_view)
    flags = sorted({flag for frame in developed.frames for flag in frame.flags} | set(posed.flags))
    result = {"develop": developed.to_json(), "poses": posed.to_dict(), "masks_across_rings": masks_across_rings,
              "flags": flags}
    result["develop"]["usable_shots"] = len(developed.usable_shots)
    scan.mark_done("process", result)
    return result
