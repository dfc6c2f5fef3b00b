"""poses/colmap/: the posed scan as a COLMAP model (cameras, images, points3D) for COLMAP, Meshroom and nerfstudio.

It is written from what training reads: the pinhole camera of the (undistorted) images and the
poses of transforms.json, so the model agrees with the images beside it. When SfM tracks exist
their observations are carried over, undistorted to that pinhole, so the model can seed COLMAP's
dense stereo; otherwise (imported scans, visual-hull clouds) the points come without tracks.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pycolmap

from station.process.lens import Lens, undistort_points
from station.process.transforms import Transforms
from station.scanfolder import ScanFolder, atomic_write_bytes

CAMERA_ID = 1


def _pixels(xy: np.ndarray, lens: Lens | None, target: np.ndarray) -> np.ndarray:
    """Observations [N, 2] of the source camera moved onto the pinhole `target` (K)."""
    if lens is None or not lens.distorted or not len(xy):
        return xy
    n = undistort_points(lens, xy)
    return n @ target[:2, :2].T + target[:2, 2]


def colmap_model(transforms: Transforms, points: tuple[np.ndarray, np.ndarray],
                 tracks: pycolmap.Reconstruction | None = None, lens: Lens | None = None) -> pycolmap.Reconstruction:
    """A PINHOLE reconstruction of `transforms`; `tracks` (same frame, camera `lens`) lends its observations."""
    intr = transforms.intrinsics
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=intr.width, height=intr.height,
                                                    params=[intr.fx, intr.fy, intr.cx, intr.cy], camera_id=CAMERA_ID))
    source = {im.name: im for im in tracks.images.values() if im.has_pose} if tracks is not None else {}
    new_id: dict[int, int] = {}  # source image id -> exported image id
    for i, frame in enumerate(transforms.frames, start=1):
        name = Path(frame.file_path).name
        image = pycolmap.Image(name=name, camera_id=CAMERA_ID, image_id=i)
        if name in source:
            old = source[name]
            xy = _pixels(np.array([p.xy for p in old.points2D]).reshape(-1, 2), lens, intr.matrix())
            image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in xy])
            new_id[old.image_id] = i
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.linalg.inv(frame.c2w)[:3, :4]))
    if tracks is not None and tracks.num_points3D():
        for point in tracks.points3D.values():
            track = pycolmap.Track()
            for element in point.track.elements:
                if element.image_id in new_id:
                    track.add_element(new_id[element.image_id], element.point2D_idx)
            if track.length() >= 2:
                rec.add_point3D(point.xyz, track, point.color)
    else:
        for xyz, rgb in zip(*points):
            rec.add_point3D(np.asarray(xyz, np.float64), pycolmap.Track(), np.asarray(rgb, np.uint8))
    return rec


def write_colmap_model(scan: ScanFolder, rec: pycolmap.Reconstruction) -> Path:
    """Binary cameras/images/points3D into poses/colmap/, each file written atomically."""
    target = scan.poses_dir / "colmap"
    with tempfile.TemporaryDirectory(prefix="station-colmap-") as tmp:
        rec.write(tmp)
        for path in sorted(Path(tmp).iterdir()):
            atomic_write_bytes(target / path.name, path.read_bytes())
    return target
