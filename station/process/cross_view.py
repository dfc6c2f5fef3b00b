"""Masks cut again once the views are posed, with the stone's silhouette as the other rings see it.

One view alone cannot always tell a stone's shaded side from its own contact shadow: a pale stone
seen from the lowest ring fades into the shadow below it with no edge at all. The other rings see
that part from above, where it stands against the plate, not beside its shadow. So once the views
are posed, the masks of every other ring carve a visual hull, the hull is projected into the view,
and the view's matte is cut again with that silhouette in the seed and as a prior
(masks.compute_matte). A view's own ring is left out of its hull: its views share the same blind
spot. Rings go lowest first, and each carves with the others' latest masks.

The silhouette comes from a tolerant hull (a voxel stays while few of the views that see it call it
background), since a strict hull is only as good as its worst masks. Seen from the lowest ring that
hull has a roof over a flat-topped stone, so the prior is weaker on the part that may be roof
(`roofed_part`). The hull is trusted only above its lowest tenth: no other ring sees under the stone,
so there it is a skirt over the contact shadow. Only views whose own mask calls background a clear
part of the strict hull's deep silhouette are cut again, because at its edge the hull is no better
than a good mask. docs/method.md gives the measurements behind each choice.

The hull is carved from the masks at the training size, the poses' own; a view is cut again at the
size it was developed, as its first cut was (its silhouette projected there), then averaged down.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from station.process.develop_stage import (
    DevelopReport,
    ProcessSettings,
    flag_implausible_masks,
    training_matte,
    write_training_view,
)
from station.process.images_io import read_exr, read_mask_png
from station.process.masks import fill_holes
from station.formats.transforms import PinholeCamera
from station.process.transforms import read_transforms
from station.process.visual_hull import carve_grid, draw_points, grid_points, surface_voxels, view_bounds
from station.scanfolder import ScanFolder


@dataclass(frozen=True)
class CrossViewSettings:
    enabled: bool = True
    min_views: int = 12  # fewer posed views on the other rings than this: no hull, the masks stay as cut
    coarse_resolution: int = 64  # first carve, over all the cameras can see, to find the stone
    box_margin: float = 0.2  # the fine grid spans the coarse hull's box grown by this fraction a side
    # The silhouette a view is cut again with comes from a hull that keeps a voxel while no more than this share of
    # the views that see it call it background: one ring's masks can all lose the same shaded side, and a strict
    # hull carves it away for every ring. Whether a view needs cutting again is judged on the strict hull.
    max_missing_views: float = 0.05
    max_resolution: int = 160  # fine voxels along each axis; below that, one voxel is about one pixel
    plate_z: float | None = 0.0  # the plate's surface in the pose frame (turntable frame: 0); nothing below is stone
    deep_fraction: float = 0.03  # "well inside" the silhouette: this share of its size (root of its area) from the edge
    max_deep_missed: float = 0.002  # a view's own mask may call this much of that part background; more is a re-cut
    # The hull's lowest part is left out of the silhouette: no other ring sees under the stone, so there the hull
    # is a skirt down to the plate, wider than the stone, and it pulled the contact shadow into the lowest ring's
    # masks. This share of the hull's height, from its floor up, is left to the shot alone (see the module notes).
    untrusted_floor: float = 0.1


@dataclass(frozen=True)
class Hull:
    """Surface voxel centres [N, 3] of a visual hull and the voxel size [3] (metres)."""

    surface: np.ndarray
    voxel: np.ndarray

    def above(self, fraction: float) -> "Hull":
        """The hull without its surface in the lowest `fraction` of its height (z is up, the turntable's axis)."""
        if len(self.surface) == 0 or fraction <= 0.0:
            return self
        z = self.surface[:, 2]
        return Hull(self.surface[z >= z.min() + fraction * np.ptp(z)], self.voxel)


def carve_hull(
    c2ws: list[np.ndarray], masks: list[np.ndarray], intr: PinholeCamera, settings: CrossViewSettings,
    missing_views: float = 0.0,
) -> Hull:
    """The visual hull of `masks`, carved coarse over the whole view box, then about a pixel fine around the stone.
    A voxel stays while no more than `missing_views` (a share) of the views that see it call it background."""
    max_misses = int(missing_views * len(c2ws))
    coarse = grid_points(*view_bounds(c2ws, intr), settings.coarse_resolution)
    inside, _ = carve_grid(c2ws, masks, intr, coarse, max_misses=max_misses)
    if not inside.any():
        return Hull(np.zeros((0, 3)), np.zeros(3))
    step = np.ptp(coarse, axis=0) / (settings.coarse_resolution - 1)
    lo, hi = coarse[inside].min(0) - step, coarse[inside].max(0) + step
    lo, hi = lo - settings.box_margin * (hi - lo), hi + settings.box_margin * (hi - lo)
    if settings.plate_z is not None:
        # the hull's own floor is where the lowest ring's blind spot is: the plate is the true one
        lo[2] = max(lo[2], settings.plate_z)
    distance = np.median([np.linalg.norm(c[:3, 3] - (lo + hi) / 2) for c in c2ws])
    pixel = distance / max(intr.fx, intr.fy)  # the stone's size of one pixel
    resolution = int(np.clip(np.ceil(np.max(hi - lo) / pixel), settings.coarse_resolution, settings.max_resolution))
    fine = grid_points(lo, hi, resolution)
    inside, _ = carve_grid(c2ws, masks, intr, fine, max_misses=max_misses)
    return Hull(fine[surface_voxels(inside, resolution)], (hi - lo) / (resolution - 1))


def project_hull(hull: Hull, c2w: np.ndarray, intr: PinholeCamera) -> np.ndarray:
    """The hull's silhouette [H, W] bool in a view: each surface voxel drawn as 2x2x2 points across its cell,
    holes filled (a solid's silhouette has none; drawn points leave pinholes where the surface is seen face-on)."""
    w2c = np.linalg.inv(c2w)
    offsets = np.stack(np.meshgrid(*[[-0.25, 0.25]] * 3, indexing="ij"), -1).reshape(-1, 3) * hull.voxel
    points = np.ascontiguousarray(hull.surface, dtype=np.float64)
    silhouette = draw_points(points, offsets, np.ascontiguousarray(w2c[:3]), intr.matrix().astype(np.float64),
                             intr.height, intr.width)
    return fill_holes(silhouette)


def looking_down(c2w: np.ndarray) -> float:
    """How far (radians) a camera's optical axis looks down from the horizontal (OpenCV camera, z up)."""
    return float(np.arcsin(np.clip(-c2w[2, 2], -1.0, 1.0)))


def roofed_part(silhouette: np.ndarray, c2w: np.ndarray, hull_views_down: float) -> np.ndarray:
    """The part [H, W] bool of a hull's silhouette in a view that may be a roof over the stone, not the stone.

    A visual hull is only tight where one of its views saw the surface edge-on, and a view that looks down by
    `hull_views_down` (the shallowest of them) sees edge-on no surface that faces up more steeply than that angle
    from the vertical: over the flat top of a stone the hull is a tent of the views' cones. In a view that looks
    down by d, an edge of the silhouette whose outward normal is at angle a from the image's up comes from surface
    that faces up by asin(cos a cos d). The tent's own faces face up no more steeply than the limit, so edges
    beyond it appear where those faces meet, at the tent's peaks, which no view pins down. The part returned is
    every pixel of the silhouette whose nearest edge pixel is such an edge: a wedge under each peak. It is empty
    when this view looks down more steeply than the hull's views.
    """
    limit = np.cos(hull_views_down) / np.cos(looking_down(c2w))
    if limit >= 1.0 or not silhouette.any():
        return np.zeros_like(silhouette, dtype=bool)
    up = c2w[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the world's up in camera coordinates (x right, y down)
    up_in_image = up[:2] / max(float(np.linalg.norm(up[:2])), 1e-12)
    inside = silhouette.astype(np.uint8)
    edge = silhouette & ~cv2.erode(inside, np.ones((3, 3), np.uint8)).astype(bool)
    smooth = cv2.GaussianBlur(inside.astype(np.float32), (0, 0), 2.0)  # the edge's direction over a few pixels
    gx, gy = cv2.Sobel(smooth, cv2.CV_32F, 1, 0), cv2.Sobel(smooth, cv2.CV_32F, 0, 1)
    facing_up = -(gx * up_in_image[0] + gy * up_in_image[1]) / np.maximum(np.hypot(gx, gy), 1e-9)  # cos a
    _, nearest = cv2.distanceTransformWithLabels((~edge).astype(np.uint8), cv2.DIST_L2, 5,
                                                 labelType=cv2.DIST_LABEL_PIXEL)
    roof_label = np.zeros(nearest.max() + 1, dtype=bool)
    roof_label[nearest[edge]] = facing_up[edge] > limit
    return silhouette & roof_label[nearest]


def misses_deep_stone(mask: np.ndarray, silhouette: np.ndarray, settings: CrossViewSettings) -> float:
    """Share of the silhouette's deep part [0, 1] (see `CrossViewSettings.deep_fraction`) that `mask` calls background."""
    depth = max(1, round(settings.deep_fraction * np.sqrt(silhouette.sum())))
    deep = cv2.erode(silhouette.astype(np.uint8), np.ones((2 * depth + 1,) * 2, np.uint8)).astype(bool)
    return float((deep & ~mask).sum() / max(deep.sum(), 1))


def refine_masks_across_rings(
    scan: ScanFolder, develop: DevelopReport, process: ProcessSettings, settings: CrossViewSettings = CrossViewSettings()
) -> dict:
    """Cut again, with its other-ring silhouette, every posed shot whose mask misses deep stone; rewrite their
    images/ and masks/ and the mask flags. Returns what changed, per ring."""
    start = time.perf_counter()
    if not settings.enabled:
        return {"skipped": "disabled"}
    transforms = read_transforms(scan)
    frames = {f.file: f for f in develop.frames if f.kind == "shot" and f.mask_area_fraction is not None}
    by_stem = {Path(f).stem: f for f in frames}
    posed = {by_stem[Path(p.file_path).stem]: p.c2w for p in transforms.frames if Path(p.file_path).stem in by_stem}
    intr = transforms.intrinsics
    masks = {file: read_mask_png(scan.masks_dir / f"{Path(file).stem}.png") for file in posed}
    elevations = sorted({frames[file].elevation_deg for file in posed})
    rings: dict[float, list[tuple[float, str, np.ndarray]]] = {}
    summary = []
    for elevation in elevations:
        own = [file for file in posed if frames[file].elevation_deg == elevation]
        others = [file for file in posed if frames[file].elevation_deg != elevation]
        if len(others) < settings.min_views:
            summary.append({"elevation_deg": elevation, "views": len(own), "skipped": f"{len(others)} views on other rings"})
            continue
        views, their_masks = [posed[f] for f in others], [masks[f] for f in others]
        hull_views_down = min(looking_down(c2w) for c2w in views)

        def trusted_hull(missing_views: float) -> Hull:
            return carve_hull(views, their_masks, intr, settings, missing_views).above(settings.untrusted_floor)

        agreed = trusted_hull(0.0)
        if len(agreed.surface) == 0:
            summary.append({"elevation_deg": elevation, "views": len(own), "skipped": "the other rings' hull is empty"})
            continue
        tolerant: Hull | None = None  # carved when a view first needs it
        plate = read_exr(scan.images_linear_dir / f"{develop.plate_for(elevation)}.exr")
        recut, changed = [], []
        for file in own:
            stem = Path(file).stem
            silhouette = project_hull(agreed, posed[file], intr)
            after = masks[file]
            if misses_deep_stone(masks[file], silhouette, settings) > settings.max_deep_missed:
                if tolerant is None:
                    tolerant = trusted_hull(settings.max_missing_views)
                shot = read_exr(scan.images_linear_dir / f"{stem}.exr")
                # cut at the developed resolution, as the first cut was (training_matte averages it down)
                silhouette = project_hull(tolerant, posed[file], intr.scaled(shot.shape[1], shot.shape[0]))
                roofed = roofed_part(silhouette, posed[file], hull_views_down)
                matte = training_matte(shot, plate, process, silhouette, roofed, develop.flat_field)
                write_training_view(scan, stem, matte)
                after = matte.mask
                recut.append(Path(file).name)
                changed.append(int((masks[file] != after).sum()))
                frames[file].mask_area_fraction = float(after.mean())
                masks[file] = after  # the rings above carve with it
            rings.setdefault(elevation, []).append((frames[file].azimuth_deg, file, after))
        summary.append({"elevation_deg": elevation, "views": len(own), "hull_surface_voxels": len(agreed.surface),
                        "recut": recut, "pixels_changed_mean": round(float(np.mean(changed)), 1) if changed else 0.0})
    flag_implausible_masks(rings, {f.file: f for f in develop.frames}, process.checks)
    return {"rings": summary, "seconds": round(time.perf_counter() - start, 2)}
