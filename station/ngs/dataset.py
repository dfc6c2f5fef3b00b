"""The posed images a scan folder offers to training: `poses/transforms.json` (nerfstudio).

nerfstudio stores camera-to-world in OpenGL axes (x right, y up, z back); the rasteriser wants
world-to-camera in OpenCV axes (x right, y down, z forward), so we flip y and z explicitly.
The file is checked by `station.formats.transforms` (the parser process and import use too) and every
path it names must resolve inside the scan folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh

from station.errors import BadInputError, FormatError, ScanFolderError
from station.formats.images import DEFAULT_LIMITS, ImageLimits, read_cv2
from station.formats.jsonfile import read_json_object
from station.formats.transforms import parse_transforms, pinhole
from station.scanfolder import ScanFolder

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class View:
    """One posed image. image [H,W,3] float in [0,1]; mask [H,W] in [0,1] or None: the object's coverage,
    fractional on its edge, where the image holds the object's own colour (straight alpha)."""

    name: str
    image: torch.Tensor  # [H, W, 3]
    mask: torch.Tensor | None  # [H, W]
    viewmat: torch.Tensor  # [4, 4] world-to-camera, OpenCV
    K: torch.Tensor  # [3, 3]

    @cached_property
    def target(self) -> torch.Tensor:
        """What a render of the object alone on black should show [H,W,3]: the image times the mask's coverage
        (kept: training reads it every step)."""
        return self.image if self.mask is None else self.image * self.mask[..., None]

    @property
    def width(self) -> int:
        return self.image.shape[1]

    @property
    def height(self) -> int:
        return self.image.shape[0]

    def to(self, device: torch.device | str) -> "View":
        return View(self.name, self.image.to(device), None if self.mask is None else self.mask.to(device),
                    self.viewmat.to(device), self.K.to(device))


@dataclass
class SceneData:
    train: list[View]
    test: list[View]
    points: np.ndarray  # [P, 3] sparse cloud
    point_colors: np.ndarray | None  # [P, 3] in [0, 1]
    scene_scale: float

    def to(self, device: torch.device | str) -> "SceneData":
        """The views' tensors on `device`; the cloud stays numpy (it only seeds the model)."""
        return SceneData([v.to(device) for v in self.train], [v.to(device) for v in self.test], self.points,
                         self.point_colors, self.scene_scale)


def split_indices(count: int, every: int = 8) -> tuple[list[int], list[int]]:
    """The 7:1 split: every 8th image (0, 8, 16, ...) is held out for testing."""
    test = [i for i in range(count) if i % every == 0]
    train = [i for i in range(count) if i % every != 0]
    return train, test


def scene_scale_of(camera_centres: np.ndarray) -> float:
    """1.1 x the largest distance of a camera centre from the mean centre (gsplat's rule)."""
    centres = np.asarray(camera_centres, dtype=np.float64)
    return float(1.1 * np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())


def read_image(path: Path, field: str, source: Path, limits: ImageLimits = DEFAULT_LIMITS) -> np.ndarray:
    """8- or 16-bit image file -> float32 in [0,1], RGB [H,W,3] or grey [H,W]; its size is checked from the header first."""
    if not path.is_file():
        raise FormatError(source, field, f"names {path}, which does not exist")
    data = read_cv2(path, field, limits)
    if data.dtype not in (np.uint8, np.uint16):
        raise FormatError(path, field, f"pixel type {data.dtype}, expected 8 or 16 bit")
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
    image, mask = _downscaled(view.image.cpu().numpy(), None if view.mask is None else view.mask.cpu().numpy(), factor)
    K = view.K.clone()
    K[:2] /= factor
    device = view.image.device
    return View(view.name, torch.from_numpy(image).to(device),
                None if mask is None else torch.from_numpy(mask).to(device), view.viewmat, K)


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


def _inside(scan: ScanFolder, value: str, source: Path, field: str) -> Path:
    try:
        return scan.resolve_inside(value)
    except ScanFolderError as exc:
        raise FormatError(source, field, f"{value!r} resolves outside the scan folder") from exc


def load_scene(scan_root: Path, downscale: int = 1, test_every: int = 8, seed: int = 0,
               limits: ImageLimits = DEFAULT_LIMITS) -> SceneData:
    """Read transforms.json (checked by station.formats.transforms), images, masks and the sparse cloud."""
    scan = ScanFolder(scan_root)
    source = scan.resolve_inside("poses/transforms.json")  # a link out of the folder is refused, not followed
    if downscale < 1:
        raise BadInputError(f"downscale factor must be >= 1, got {downscale}")
    doc = parse_transforms(read_json_object(source), source)
    views: list[View] = []
    centres = []
    for index, frame in enumerate(doc.frames):
        where = f"frames[{index}]"
        cam = pinhole(frame.camera, source)
        image_path = _inside(scan, frame.file_path, source, f"{where}.file_path")
        mask_path = None if frame.mask_path is None else _inside(scan, frame.mask_path, source, f"{where}.mask_path")
        image = read_image(image_path, f"{where}.file_path", source, limits)
        if image.ndim != 3 or image.shape[:2] != (cam.height, cam.width):
            raise FormatError(source, f"{where}.file_path", f"{image_path} is {image.shape}, "
                                                            f"transforms.json says {cam.width}x{cam.height} RGB")
        mask = None
        if mask_path is not None:
            mask = read_image(mask_path, f"{where}.mask_path", source, limits)
            mask = mask if mask.ndim == 2 else mask.mean(axis=2)
            if mask.shape != (cam.height, cam.width):
                raise FormatError(source, f"{where}.mask_path", f"{mask_path} is {mask.shape}, "
                                                                f"expected {(cam.height, cam.width)}")
        K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
        c2w_cv = frame.c2w_gl @ OPENGL_TO_OPENCV
        centres.append(c2w_cv[:3, 3])
        view = View(
            name=Path(frame.file_path).name,
            image=torch.from_numpy(image),
            mask=None if mask is None else torch.from_numpy(mask),
            viewmat=torch.from_numpy(np.linalg.inv(c2w_cv)).float(),
            K=torch.from_numpy(K).float(),
        )
        views.append(downscaled_view(view, downscale))
    scale = scene_scale_of(np.stack(centres))
    if doc.ply_file_path:
        ply_path = _inside(scan, doc.ply_file_path, source, "ply_file_path")
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

