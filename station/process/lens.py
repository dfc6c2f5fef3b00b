"""Camera lenses: parsing nerfstudio and COLMAP camera models into one `Lens`, and undistortion.

Training's rasteriser is a pinhole, so a distorted camera is undistorted once, on import or
after self-calibration, into the images training reads: modelling distortion in training would
mean a non-linear projection inside every splat's footprint, for a correction that one remap
per image gives exactly. Coordinates follow nerfstudio and COLMAP: a pixel's centre is at +0.5,
so OpenCV (centres at integers) is handed principal points moved by half a pixel.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

from station.errors import BadInputError
from station.formats.transforms import PinholeCamera

OPENCV_ORDER = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")  # OpenCV's rational model, full length
FISHEYE_ORDER = ("k1", "k2", "k3", "k4")  # Kannala-Brandt, as OpenCV's cv2.fisheye and COLMAP's OPENCV_FISHEYE
NERFSTUDIO_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE")
# COLMAP model -> (our model, names of its parameters after focal length(s) and principal point)
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("PINHOLE", ()),
    "PINHOLE": ("PINHOLE", ()),
    "SIMPLE_RADIAL": ("OPENCV", ("k1",)),
    "RADIAL": ("OPENCV", ("k1", "k2")),
    "OPENCV": ("OPENCV", ("k1", "k2", "p1", "p2")),
    "FULL_OPENCV": ("OPENCV", OPENCV_ORDER),
    "OPENCV_FISHEYE": ("OPENCV_FISHEYE", FISHEYE_ORDER),
}
_ITERATE = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass(frozen=True)
class Lens:
    """PinholeCamera plus distortion: model "PINHOLE", "OPENCV" (Brown-Conrady, rational) or "OPENCV_FISHEYE"."""

    intrinsics: PinholeCamera
    model: str = "PINHOLE"
    coefficients: tuple[float, ...] = ()  # OPENCV_ORDER (8) or FISHEYE_ORDER (4); empty for a pinhole

    @property
    def fisheye(self) -> bool:
        return self.model == "OPENCV_FISHEYE"

    @property
    def distorted(self) -> bool:
        return any(abs(c) > 1e-12 for c in self.coefficients)

    def named(self) -> dict[str, float]:
        return dict(zip(FISHEYE_ORDER if self.fisheye else OPENCV_ORDER, self.coefficients))

    def opencv_k(self) -> np.ndarray:
        """K for OpenCV's integer pixel centres."""
        k = self.intrinsics.matrix()
        k[:2, 2] -= 0.5
        return k

    def scaled(self, width: int, height: int) -> "Lens":
        """Same lens at another image size (distortion acts on normalised coordinates, so it stays)."""
        return Lens(self.intrinsics.scaled(width, height), self.model, self.coefficients)

    def refinable(self) -> "Lens":
        """This lens with distortion terms to refine: a pinhole becomes OPENCV with zero coefficients."""
        return self if self.model != "PINHOLE" else Lens(self.intrinsics, "OPENCV", (0.0,) * len(OPENCV_ORDER))

    def to_colmap(self, camera_id: int = 1, keep_model: bool = False) -> pycolmap.Camera:
        """The COLMAP camera; `keep_model` keeps a zero-distortion OPENCV lens OPENCV (so BA can refine it)."""
        i = self.intrinsics
        if self.fisheye:
            model, params = "OPENCV_FISHEYE", [i.fx, i.fy, i.cx, i.cy, *self.coefficients]
        elif any(abs(c) > 0 for c in self.coefficients[4:]):
            model, params = "FULL_OPENCV", [i.fx, i.fy, i.cx, i.cy, *self.coefficients]
        elif self.distorted or (keep_model and self.model == "OPENCV"):
            model, params = "OPENCV", [i.fx, i.fy, i.cx, i.cy, *self.coefficients[:4]]
        else:
            model, params = "PINHOLE", [i.fx, i.fy, i.cx, i.cy]
        return pycolmap.Camera(model=model, width=i.width, height=i.height, params=params, camera_id=camera_id)

    def to_dict(self) -> dict:
        return {"model": self.model, **self.named()}

    @staticmethod
    def from_dict(intrinsics: PinholeCamera, data: dict, where: str) -> "Lens":
        model = data.get("model", "PINHOLE")
        if model not in ("PINHOLE", "OPENCV", "OPENCV_FISHEYE"):
            raise BadInputError(f"{where}: lens model {model!r} is not one of PINHOLE, OPENCV, OPENCV_FISHEYE")
        return _lens(intrinsics, model, data, where)


def _coefficient(data: dict, key: str, where: str) -> float:
    value = data.get(key, 0.0)
    if value is None:
        return 0.0
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise BadInputError(f"{where}: distortion {key!r} must be a finite number, got {value!r}")
    return float(value)


def _lens(intrinsics: PinholeCamera, model: str, data: dict, where: str) -> Lens:
    if model == "PINHOLE":
        return Lens(intrinsics)
    order = FISHEYE_ORDER if model == "OPENCV_FISHEYE" else OPENCV_ORDER
    return Lens(intrinsics, model, tuple(_coefficient(data, k, where) for k in order))


def split_nerfstudio_lens(data: object, source: object) -> tuple[dict, object]:
    """A transforms.json's lens keys (file-wide, or per frame when every frame agrees) and the document
    without them, for the pinhole parser; frames with different lenses are refused."""
    if not isinstance(data, dict):
        return {}, data  # the pinhole parser refuses it with its own message
    keys = ("camera_model", "k1", "k2", "k3", "k4", "p1", "p2")
    lens = {k: data[k] for k in keys if k in data}
    rest = {k: v for k, v in data.items() if k not in keys}
    if isinstance(data.get("frames"), list):
        per_frame = [{**lens, **{k: f[k] for k in keys if k in f}} for f in data["frames"] if isinstance(f, dict)]
        if len({json.dumps(p, sort_keys=True, default=str) for p in per_frame}) > 1:
            raise BadInputError(f"{source}: frames have different lenses (camera_model, k1.., p1..); "
                                "one shared camera is supported")
        lens = per_frame[0] if per_frame else lens
        rest["frames"] = [{k: v for k, v in f.items() if k not in keys} if isinstance(f, dict) else f
                          for f in data["frames"]]
    return lens, rest


def lens_from_nerfstudio(data: dict, intrinsics: PinholeCamera, where: str) -> Lens:
    """`camera_model` and k1..k4 / p1, p2 of a transforms.json (no model but coefficients: OPENCV)."""
    model = data.get("camera_model")
    if model is None:
        model = "OPENCV" if any(_coefficient(data, k, where) for k in ("k1", "k2", "k3", "p1", "p2")) else "PINHOLE"
    if model not in NERFSTUDIO_MODELS:
        raise BadInputError(f"{where}: camera_model {model!r} is not supported "
                            f"(supported: {', '.join(NERFSTUDIO_MODELS)})")
    if model == "OPENCV":  # nerfstudio's OPENCV is k1, k2, p1, p2 and k3; its k4 belongs to the fisheye
        data = {k: data.get(k) for k in ("k1", "k2", "p1", "p2", "k3")}
    lens = _lens(intrinsics, "PINHOLE" if model == "SIMPLE_PINHOLE" else model, data, where)
    check_unfolded(lens, where)
    return lens


def lens_from_colmap(camera: pycolmap.Camera, where: str) -> Lens:
    """A COLMAP camera of a model in COLMAP_MODELS as a `Lens`; any other model is refused by name."""
    name = camera.model.name
    if name not in COLMAP_MODELS:
        raise BadInputError(f"{where}: camera model {name} is not supported (supported: {', '.join(COLMAP_MODELS)})")
    model, names = COLMAP_MODELS[name]
    k = camera.calibration_matrix()
    intr = PinholeCamera(camera.width, camera.height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    extra = [float(camera.params[i]) for i in camera.extra_params_idxs()]
    lens = _lens(intr, model, dict(zip(names, extra)), where)
    check_unfolded(lens, where)
    return lens


def _radial(lens: Lens, r: np.ndarray) -> np.ndarray:
    """Distorted normalised radius as a function of the undistorted one (fisheye: of the ray angle)."""
    c = lens.coefficients
    if lens.fisheye:
        t2 = r * r
        return r * (1 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3]))))
    r2 = r * r
    num = 1 + r2 * (c[0] + r2 * (c[1] + r2 * c[4]))
    den = 1 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
    return np.where(den > 0, r * num / np.where(den > 0, den, 1.0), -np.inf)


def check_unfolded(lens: Lens, where: str) -> None:
    """Refuse a lens whose radial map turns back inside the image: undistortion would fold it there.

    Tangential terms are left out of the check (they shift, not fold, at any realistic strength).
    """
    if not lens.distorted:
        return
    i = lens.intrinsics
    corners = np.array([[0.0, 0.0], [i.width, 0.0], [0.0, i.height], [i.width, i.height]])
    reach = float(np.max(np.hypot((corners[:, 0] - i.cx) / i.fx, (corners[:, 1] - i.cy) / i.fy)))
    # fisheye: ray angles up to (not reaching) 90 degrees map to a pinhole; otherwise up to ~84 degrees
    r = np.linspace(0.0, np.pi / 2 - 1e-3 if lens.fisheye else 10.0, 20_000)
    g = _radial(lens, r)
    turns = np.flatnonzero(np.diff(g) <= 0)
    top = g[: turns[0] + 1].max() if len(turns) else g.max()
    if top < reach:
        radius = top * i.fx
        terms = {k: v for k, v in lens.named().items() if v}
        raise BadInputError(f"{where}: {lens.model} distortion {terms} folds the image: the radial map "
                            f"turns back {max(radius, 0):.0f} px from the principal point, inside the image "
                            f"(its corners are {reach * i.fx:.0f} px away); undistortion is undefined there")


def undistort_points(lens: Lens, pixels: np.ndarray) -> np.ndarray:
    """Pixels [N, 2] of the distorted image -> normalised pinhole coordinates [N, 2]."""
    pts = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2) - 0.5
    k = lens.opencv_k()
    if lens.fisheye:
        out = cv2.fisheye.undistortPoints(pts, k, np.array(lens.coefficients), criteria=_ITERATE)
    else:
        out = cv2.undistortPoints(pts, k, np.array(lens.coefficients), R=None, P=None, criteria=_ITERATE)
    return out.reshape(-1, 2)


def displacement_px(lens: Lens) -> float:
    """Largest shift distortion gives a pixel on the image border: below a tenth of a pixel, not worth a resample."""
    if not lens.distorted:
        return 0.0
    i = lens.intrinsics
    border = np.array([(u, v) for u in np.linspace(0.5, i.width - 0.5, 9) for v in np.linspace(0.5, i.height - 0.5, 7)
                       if u in (0.5, i.width - 0.5) or v in (0.5, i.height - 0.5)])
    n = undistort_points(lens, border)
    return float(np.max(np.hypot(i.fx * n[:, 0] + i.cx - border[:, 0], i.fy * n[:, 1] + i.cy - border[:, 1])))


def pinhole_for(lens: Lens, samples: int = 256) -> PinholeCamera:
    """The pinhole camera, same size, square pixels, whose every pixel lands inside the distorted image."""
    i = lens.intrinsics
    us, vs = np.linspace(0.5, i.width - 0.5, samples), np.linspace(0.5, i.height - 0.5, samples)
    left, right = np.full(samples, 0.5), np.full(samples, i.width - 0.5)
    top, bottom = np.full(samples, 0.5), np.full(samples, i.height - 0.5)
    edge = {"left": np.column_stack([left, vs]), "right": np.column_stack([right, vs]),
            "top": np.column_stack([us, top]), "bottom": np.column_stack([us, bottom])}
    n = {side: undistort_points(lens, pts) for side, pts in edge.items()}
    x0, x1 = n["left"][:, 0].max(), n["right"][:, 0].min()
    y0, y1 = n["top"][:, 1].max(), n["bottom"][:, 1].min()
    if not (x1 > x0 and y1 > y0):
        raise BadInputError(f"lens {lens.model} {lens.named()}: undistorted image has no interior")
    f = max((i.width - 1) / (x1 - x0), (i.height - 1) / (y1 - y0))
    return PinholeCamera(i.width, i.height, f, f, i.width / 2 - f * (x0 + x1) / 2, i.height / 2 - f * (y0 + y1) / 2)


@dataclass(frozen=True)
class Undistortion:
    """Remap tables from a distorted lens to the pinhole `target`, built once and applied per image."""

    target: PinholeCamera
    map_x: np.ndarray  # [H, W] float32 source column (OpenCV pixel centres) for each target pixel
    map_y: np.ndarray

    def image(self, image: np.ndarray) -> np.ndarray:
        return cv2.remap(image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def mask(self, coverage: np.ndarray) -> np.ndarray:
        """Hard masks stay hard (nearest); coverage masks interpolate linearly, which keeps their area."""
        binary = np.isin(coverage, (0, 255)).all() if coverage.dtype == np.uint8 else coverage.dtype == bool
        flag = cv2.INTER_NEAREST if binary else cv2.INTER_LINEAR
        out = cv2.remap(coverage.astype(np.uint8), self.map_x, self.map_y, flag, borderMode=cv2.BORDER_REPLICATE)
        return out.astype(bool) if coverage.dtype == bool else out


def undistortion(lens: Lens, min_shift_px: float = 0.0) -> Undistortion | None:
    """Remap tables to `pinhole_for(lens)`, or None when distortion moves no pixel more than `min_shift_px`."""
    if not lens.distorted or displacement_px(lens) <= min_shift_px:
        return None
    target = pinhole_for(lens)
    new_k = target.matrix()
    new_k[:2, 2] -= 0.5
    size = (target.width, target.height)
    d = np.array(lens.coefficients)
    if lens.fisheye:
        mx, my = cv2.fisheye.initUndistortRectifyMap(lens.opencv_k(), d, np.eye(3), new_k, size, cv2.CV_32FC1)
    else:
        mx, my = cv2.initUndistortRectifyMap(lens.opencv_k(), d, None, new_k, size, cv2.CV_32FC1)
    return Undistortion(target, mx, my)
