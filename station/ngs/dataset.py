"""The posed images a scan folder offers to training: `poses/transforms.json` (nerfstudio).

nerfstudio stores camera-to-world in OpenGL axes (x right, y up, z back); the rasteriser wants
world-to-camera in OpenCV axes (x right, y down, z forward), so we flip y and z explicitly.
Every path the JSON names is untrusted and must resolve inside the scan folder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh

from station.errors import BadInputError, ScanFolderError
from station.scanfolder import ScanFolder

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
MAX_IMAGES = 10_000
MAX_PIXELS = 100_000_000


@dataclass
class View:
    """One posed image. image [H,W,3] float in [0,1]; mask [H,W] in [0,1] or None: the object's coverage,
    fractional on its edge, where the image holds the object's own colour (straight alpha)."""

    name: str
    image: torch.Tensor  # [H, W, 3]
    mask: torch.Tensor | None  # [H, W]
    viewmat: torch.Tensor  # [4, 4] world-to-camera, OpenCV
    K: torch.Tensor  # [3, 3]

    @property
    def target(self) -> torch.Tensor:
        """What a render of the object alone on black should show [H,W,3]: the image times the mask's coverage."""
        return self.image if self.mask is None else self.image * self.mask[..., None]

    @property
    def width(self) -> int:
        return self.image.shape[1]

    @property
    def height(self) -> int:
        return self.image.shape[0]


@dataclass
class SceneData:
    train: list[View]
    test: list[View]
    points: np.ndarray  # [P, 3] sparse cloud
    point_colors: np.ndarray | None  # [P, 3] in [0, 1]
    scene_scale: float


def split_indices(count: int, every: int = 8) -> tuple[list[int], list[int]]:
    """The 7:1 split: every 8th image (0, 8, 16, ...) is held out for testing."""
    test = [i for i in range(count) if i % every == 0]
    train = [i for i in range(count) if i % every != 0]
    return train, test


def scene_scale_of(camera_centres: np.ndarray) -> float:
    """1.1 x the largest distance of a camera centre from the mean centre (gsplat's rule)."""
    centres = np.asarray(camera_centres, dtype=np.float64)
    return float(1.1 * np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())


def read_image(path: Path, field: str, source: Path) -> np.ndarray:
    """8- or 16-bit image file -> float32 in [0,1], RGB [H,W,3] or grey [H,W]."""
    if not path.is_file():
        raise BadInputError(f"{source}: {field} names {path}, which does not exist")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise BadInputError(f"{source}: {field} names {path}, which is not a readable image")
    if data.dtype not in (np.uint8, np.uint16):
        raise BadInputError(f"{source}: {field} {path} has pixel type {data.dtype}, expected 8 or 16 bit")
    scale = float(np.iinfo(data.dtype).max)
    data = data.astype(np.float32) / scale
    if data.ndim == 3:
        data = data[..., :3][..., ::-1]  # OpenCV reads BGR(A)
    return np.ascontiguousarray(data)


def _resize(data: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return data
    height, width = data.shape[:2]
    return cv2.resize(data, (width // factor, height // factor), interpolation=cv2.INTER_AREA)


def _downscaled(image: np.ndarray, mask: np.ndarray | None, factor: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Area-averaged image and mask. With a mask, the object's colour x coverage is averaged and divided
    back, so the image stays the object's own colour where the coarser pixel is partly covered."""
    if mask is None or factor == 1:
        return _resize(image, factor), None if mask is None else _resize(mask, factor)
    covered = _resize(mask, factor)
    premultiplied = _resize(image * mask[..., None], factor)
    straight = premultiplied / np.maximum(covered, 1e-4)[..., None]
    return np.where(covered[..., None] > 1e-4, straight, _resize(image, factor)), covered


def downscaled_view(view: View, factor: int) -> View:
    """The same view `factor` times coarser (load_scene's downscale and the trainer's coarse levels)."""
    if factor == 1:
        return view
    image, mask = _downscaled(view.image.numpy(), None if view.mask is None else view.mask.numpy(), factor)
    K = view.K.clone()
    K[:2] /= factor
    return View(view.name, torch.from_numpy(image), None if mask is None else torch.from_numpy(mask), view.viewmat, K)


def _number(frame: dict, meta: dict, key: str, source: Path) -> float:
    value = frame.get(key, meta.get(key))
    if not isinstance(value, (int, float)) or not math.isfinite(value):
        raise BadInputError(f"{source}: field {key!r} missing or not a finite number")
    return float(value)


def read_points(path: Path, source: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The sparse cloud named by `ply_file_path`: points [P,3] and colours [P,3] or None."""
    try:
        cloud = trimesh.load(path, file_type="ply", process=False)
    except Exception as exc:  # trimesh raises many types on garbage input
        raise BadInputError(f"{source}: ply_file_path {path} is not a readable PLY ({exc})") from exc
    points = np.asarray(getattr(cloud, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if points.ndim != 2 or len(points) < 4 or not np.isfinite(points).all():
        raise BadInputError(f"{source}: ply_file_path {path} holds no usable points (need >= 4 finite)")
    colors = getattr(cloud, "colors", None)
    if colors is not None and len(colors) == len(points):
        colors = np.asarray(colors, dtype=np.float64)[:, :3] / 255.0
    else:
        colors = None
    return points, colors


def load_scene(scan_root: Path, downscale: int = 1, test_every: int = 8, seed: int = 0) -> SceneData:
    """Read transforms.json, images, masks and the sparse cloud of a posed scan folder."""
    scan = ScanFolder(scan_root)
    source = scan.transforms_path
    meta = scan.read_json(source)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise BadInputError(f"{source}: field 'frames' missing or empty")
    if len(frames) > MAX_IMAGES:
        raise BadInputError(f"{source}: {len(frames)} frames exceeds the limit of {MAX_IMAGES}")
    if downscale < 1:
        raise BadInputError(f"downscale factor must be >= 1, got {downscale}")
    views: list[View] = []
    centres = []
    for index, frame in enumerate(frames):
        where = f"{source} frame {index}"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise BadInputError(f"{where}: field 'file_path' missing")
        width, height = int(_number(frame, meta, "w", source)), int(_number(frame, meta, "h", source))
        if width <= 0 or height <= 0 or width * height > MAX_PIXELS:
            raise BadInputError(f"{where}: image size {width}x{height} out of range")
        try:
            c2w_gl = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (KeyError, ValueError, TypeError) as exc:
            raise BadInputError(f"{where}: field 'transform_matrix' missing or not numeric") from exc
        if c2w_gl.shape != (4, 4) or not np.isfinite(c2w_gl).all():
            raise BadInputError(f"{where}: field 'transform_matrix' must be a finite 4x4 matrix")
        try:
            image_path = scan.resolve_inside(frame["file_path"])
            mask_path = scan.resolve_inside(frame["mask_path"]) if frame.get("mask_path") else None
        except ScanFolderError as exc:
            raise BadInputError(f"{where}: {exc}") from exc
        image = read_image(image_path, "file_path", source)
        if image.ndim != 3 or image.shape[:2] != (height, width):
            raise BadInputError(f"{where}: {image_path} is {image.shape}, transforms.json says {width}x{height} RGB")
        mask = None
        if mask_path is not None:
            mask = read_image(mask_path, "mask_path", source)
            mask = mask if mask.ndim == 2 else mask.mean(axis=2)
            if mask.shape != (height, width):
                raise BadInputError(f"{where}: mask {mask_path} is {mask.shape}, expected {(height, width)}")
        K = np.array(
            [
                [_number(frame, meta, "fl_x", source), 0.0, _number(frame, meta, "cx", source)],
                [0.0, _number(frame, meta, "fl_y", source), _number(frame, meta, "cy", source)],
                [0.0, 0.0, 1.0],
            ]
        )
        c2w_cv = c2w_gl @ OPENGL_TO_OPENCV
        centres.append(c2w_cv[:3, 3])
        view = View(
            name=Path(frame["file_path"]).name,
            image=torch.from_numpy(image),
            mask=None if mask is None else torch.from_numpy(mask),
            viewmat=torch.from_numpy(np.linalg.inv(c2w_cv)).float(),
            K=torch.from_numpy(K).float(),
        )
        views.append(downscaled_view(view, downscale))
    scale = scene_scale_of(np.stack(centres))
    if meta.get("ply_file_path"):
        try:
            ply_path = scan.resolve_inside(meta["ply_file_path"])
        except ScanFolderError as exc:
            raise BadInputError(f"{source}: field 'ply_file_path': {exc}") from exc
        points, colors = read_points(ply_path, source)
    else:  # gsplat's "random" init: a cube around the cameras' mean, sized by the scene
        generator = np.random.default_rng(seed)
        points = np.stack(centres).mean(axis=0) + (generator.random((10_000, 3)) * 2 - 1) * scale
        colors = None
    train_ids, test_ids = split_indices(len(views), test_every)
    return SceneData(
        train=[views[i] for i in train_ids],
        test=[views[i] for i in test_ids],
        points=points,
        point_colors=colors,
        scene_scale=scale,
    )

