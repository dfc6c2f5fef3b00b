"""The simulated softbox world and its CPU ray caster.

Frames: the stone and the grey plate turn together, so the world frame is the turntable frame
(station.rig_geometry). The softbox light, the backdrop and the colour chart stand still in the lab,
so in the turntable frame they turn by -azimuth; a point p in the turntable frame is Rz(azimuth)·p in
the lab. Light is mostly uniform with a mild key, which is how a softbox station looks and what makes
textureless stones hard. The stone is ray cast with embree (through trimesh); plate, backdrop and
chart are analytic. The lens's distortion bends the rays (sim/lens.py); its vignetting and the noise
belong to the sensor (sim/sensor.py), not here.

Pixel convention: pixel (row i, col j) covers [j, j+1) x [i, i+1) in the coordinates K uses, so its
centre is (j + 0.5, i + 0.5), as in COLMAP and gsplat.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Callable, Protocol

import math

import numpy as np
from numba import njit, prange
from scipy.ndimage import gaussian_filter

from sim.dng import dng_bytes
from sim.lens import SimLens
from sim.sensor import SensorModel
from sim.stone import Stone
from station.errors import BadInputError
from station.rig_geometry import RigGeometry, camera_to_turntable, rotation_z

_EPS = 1e-9


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product [N, 3] x [N, 3] -> [N] (einsum: much faster than sum(a * b, axis=1))."""
    return np.einsum("ij,ij->i", a, b)


# ColorChecker 24 (after Nov 2014) as linear sRGB reflectances, row-major from 'dark skin' to 'black':
# colour-science's xyY (D50) -> XYZ -> sRGB with Bradford adaptation, clipped at 0 (cyan's red is -0.04).
CHART_LINEAR_SRGB = np.array([
    [0.1737, 0.0788, 0.0529], [0.5598, 0.2774, 0.2109], [0.1042, 0.1889, 0.3289], [0.1057, 0.1508, 0.0508],
    [0.2274, 0.2124, 0.4264], [0.1153, 0.5074, 0.4111], [0.7459, 0.2021, 0.0299], [0.0587, 0.1012, 0.3877],
    [0.5601, 0.0802, 0.1146], [0.1092, 0.0420, 0.1381], [0.3328, 0.4974, 0.0426], [0.7710, 0.3579, 0.0204],
    [0.0210, 0.0475, 0.2841], [0.0461, 0.2920, 0.0615], [0.4462, 0.0364, 0.0406], [0.8417, 0.5744, 0.0047],
    [0.5223, 0.0778, 0.2893], [0.0000, 0.2337, 0.3772], [0.8795, 0.8850, 0.8342], [0.5845, 0.5922, 0.5845],
    [0.3577, 0.3671, 0.3653], [0.1901, 0.1909, 0.1898], [0.0859, 0.0887, 0.0898], [0.0314, 0.0315, 0.0323],
])  # [24, 3]
CHART_SURROUND = 0.03  # the chart's black frame


@dataclass(frozen=True)
class ChartPlacement:
    """A 4x6 patch chart standing still in the lab, beside and behind the plate.

    By default it sits right of the stone in the image and faces the camera at 15 deg tilt, so it is
    in frame (plates included) from 0 to about 35 deg; higher tilts look down past it.
    """

    centre_lab: tuple[float, float, float] = (-0.20, 0.12, 0.02)
    facing_elevation_deg: float = 15.0
    patch_m: float = 0.012
    gap_m: float = 0.003

    @cached_property
    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Centre, normal, right and down unit vectors of the chart, lab frame."""
        centre = np.asarray(self.centre_lab, dtype=float)
        e = np.deg2rad(self.facing_elevation_deg)
        eye = np.array([0.45 * np.cos(e), 0.0, 0.04 + 0.45 * np.sin(e)])
        normal = (eye - centre) / np.linalg.norm(eye - centre)
        right = np.cross(np.array([0.0, 0.0, 1.0]), normal)
        right /= np.linalg.norm(right)
        return centre, normal, right, np.cross(normal, right)

    @property
    def normal_lab(self) -> np.ndarray:
        return self.frame[1]

    def patch_centres_lab(self) -> np.ndarray:
        """[24, 3] patch centres in the lab frame, in CHART_LINEAR_SRGB order."""
        centre, _, right, down = self.frame
        pitch = self.patch_m + self.gap_m
        rows, cols = np.divmod(np.arange(24), 6)
        return centre + ((cols - 2.5) * pitch)[:, None] * right + ((rows - 1.5) * pitch)[:, None] * down

    def intersect(self, eye: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (inf = miss) [N] and reflectance [N, 3] of rays from `eye` (lab frame) against the card."""
        centre, normal, right, down = self.frame
        pitch = self.patch_m + self.gap_m
        margin = self.gap_m / pitch
        t = np.full(len(dirs), np.inf)
        rgb = np.zeros((len(dirs), 3))
        # only rays inside the cone around the card can hit it: one cheap test for all rays
        to_card = centre - eye
        distance = float(np.linalg.norm(to_card))
        half_diagonal = np.hypot(3.0, 2.0) * pitch + self.gap_m
        cone = np.cos(np.arctan2(half_diagonal, np.sqrt(max(distance**2 - half_diagonal**2, _EPS))))
        ray = np.flatnonzero(dirs @ (to_card / distance).astype(dirs.dtype) > cone - 1e-6)
        facing = dirs[ray] @ normal
        ray, facing = ray[facing < -_EPS], facing[facing < -_EPS]
        dist = ((centre - eye) @ normal) / facing
        local = eye - centre + dirs[ray] * dist[:, None]  # [M, 3] hit point relative to the card centre
        u, v = local @ right / pitch + 3.0, local @ down / pitch + 2.0  # patch units from the card corner
        on_card = (u >= -margin) & (u <= 6.0 + margin) & (v >= -margin) & (v <= 4.0 + margin)
        ray, u, v = ray[on_card], u[on_card], v[on_card]
        t[ray] = dist[on_card]
        col, row = np.clip(np.floor(u), 0, 5).astype(int), np.clip(np.floor(v), 0, 3).astype(int)
        in_patch = (u - np.floor(u) > margin) & (v - np.floor(v) > margin) & (u > 0) & (v > 0) & (u < 6) & (v < 4)
        rgb[ray] = np.where(in_patch[:, None], CHART_LINEAR_SRGB[row * 6 + col], CHART_SURROUND)
        return t, rgb


@dataclass
class World:
    """Everything in front of the camera. `stone_present` is what the operator toggles for plates.

    Derived data (contact shadow, normals, bounds) is cached on first use: make a new World to
    change the stone rather than assigning a new one.
    """

    stone: Stone
    rig: RigGeometry = field(default_factory=RigGeometry)
    stone_present: bool = True
    lens: SimLens = field(default_factory=SimLens)  # its distortion decides where each pixel looks
    plate_radius_m: float = 0.15
    plate_albedo: float = 0.30
    backdrop_radius_m: float = 1.5
    backdrop_level: float = 0.55
    light_level: float = 1.0
    key_direction_lab: tuple[float, float, float] = (0.35, 0.45, 0.82)  # towards the key softbox
    key_strength: float = 0.30  # mild: most light is the uniform dome
    chart: ChartPlacement | None = field(default_factory=ChartPlacement)
    contact_shadow_grid: int = 96
    contact_shadow_reach_m: float = 0.04

    @cached_property
    def stone_bound(self) -> tuple[np.ndarray, float]:
        """Bounding sphere (centre, radius) used to skip rays that cannot reach the stone."""
        lo, hi = self.stone.mesh.bounds
        centre = (lo + hi) / 2.0
        return centre, float(np.linalg.norm(self.stone.mesh.vertices - centre, axis=1).max()) * 1.001

    @cached_property
    def contact_occlusion(self) -> np.ndarray:
        """[G, G] how open the sky is above each plate point (1 = open, 0 = under the stone).

        Computed once with occlusion rays, in the turntable frame where stone and plate are both
        still. A hit counts less the farther away it is, like ambient occlusion, so the shadow stays a
        soft contact shadow instead of long streaks towards the horizon.
        """
        g = self.contact_shadow_grid
        axis = np.linspace(-self.plate_radius_m, self.plate_radius_m, g)
        xx, yy = np.meshgrid(axis, axis, indexing="ij")
        points = np.stack([xx.ravel(), yy.ravel(), np.full(g * g, 1e-4)], axis=1)  # [P, 3]
        directions = _cosine_hemisphere(48)  # [D, 3]
        origins = np.repeat(points, len(directions), axis=0)  # [P*D, 3]
        rays = np.tile(directions, (len(points), 1))
        tri = self.stone.mesh.ray.intersects_first(origins, rays)
        hit = tri >= 0
        corners = self.stone.mesh.vertices[self.stone.mesh.faces[tri[hit]]]
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        dist = _dot(corners[:, 0] - origins[hit], normal) / _dot(rays[hit], normal)
        weight = np.zeros(len(rays))
        weight[hit] = np.clip(1.0 - dist / self.contact_shadow_reach_m, 0.0, 1.0)
        return gaussian_filter(1.0 - weight.reshape(g * g, -1).mean(axis=1).reshape(g, g), sigma=0.7)

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        return np.asarray(self.stone.mesh.vertex_normals)  # [V, 3]


@dataclass
class RenderOut:
    radiance: np.ndarray  # [H, W, 3] float32, scene-referred linear sRGB primaries
    mask: np.ndarray  # [H, W] bool, stone covers at least half the pixel
    depth: np.ndarray  # [H, W] float32, camera z-depth of the stone (m), 0 where no stone
    alpha: np.ndarray  # [H, W] float32, stone coverage of the pixel
    stone: np.ndarray  # [H, W, 3] float32, the stone alone on black: its radiance premultiplied by its coverage


def _cosine_hemisphere(n: int) -> np.ndarray:
    """[n, 3] deterministic cosine-weighted directions about +z (Fibonacci spiral)."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], axis=1)


@lru_cache(maxsize=8)
def _camera_frame_rays(rig: RigGeometry, lens: SimLens, supersample: int) -> np.ndarray:
    """[H*s * W*s, 3] float32 unit ray directions in the camera frame, through the lens; the same for every pose."""
    s = supersample
    xs = (np.arange(rig.width * s) + 0.5) / s
    ys = (np.arange(rig.height * s) + 0.5) / s
    px, py = np.meshgrid(xs, ys)
    seen = lens.pixel_directions(rig.intrinsics(), px.ravel(), py.ravel())  # [R, 2]
    cam = np.column_stack([seen, np.ones(len(seen))])  # [R, 3]
    cam = (cam / np.sqrt(_dot(cam, cam))[:, None]).astype(np.float32)
    cam.flags.writeable = False  # shared by every render through the cache
    return cam


def camera_rays(rig: RigGeometry, c2w: np.ndarray, supersample: int,
                lens: SimLens = SimLens.ideal()) -> tuple[np.ndarray, np.ndarray]:
    """The eye [3] and unit ray directions [H*s * W*s, 3] (float32) in world frame, row-major over the
    supersampled grid."""
    rays = _camera_frame_rays(rig, lens, supersample)
    return c2w[:3, 3].astype(np.float32), rays @ c2w[:3, :3].T.astype(np.float32)


def _irradiance(world: World, normals: np.ndarray, key: np.ndarray) -> np.ndarray:
    """[N] softbox irradiance: a bright dome (more from above) plus a mild key."""
    dome = 0.62 + 0.23 * normals[:, 2]
    return world.light_level * (dome + world.key_strength * np.clip(normals @ key, 0.0, None))


def _shade_stone(world: World, eye: np.ndarray, dirs: np.ndarray, tri: np.ndarray, t: np.ndarray, key) -> np.ndarray:
    """[N, 3] radiance of stone hits: albedo x irradiance, plus a view-dependent sheen."""
    mesh = world.stone.mesh
    points = eye + dirs * t[:, None]  # [N, 3]
    corners = mesh.vertices[mesh.faces[tri]]  # [N, 3, 3]
    bary = _barycentric(corners, points)  # [N, 3]
    normals = np.einsum("nk,nkd->nd", bary, world.vertex_normals[mesh.faces[tri]])
    normals /= np.sqrt(_dot(normals, normals))[:, None] + _EPS
    radiance = world.stone.albedo(points) * _irradiance(world, normals, key)[:, None]
    if world.stone.sheen > 0.0:
        half = key - dirs
        half /= np.sqrt(_dot(half, half))[:, None] + _EPS
        reflect_z = dirs[:, 2] - 2.0 * _dot(dirs, normals) * normals[:, 2]
        highlight = 1.5 * np.clip(_dot(normals, half), 0.0, None) ** 40
        dome = 0.15 * (0.5 + 0.5 * reflect_z)  # the softbox's own mirror image
        radiance = radiance + (world.stone.sheen * world.light_level * (highlight + dome))[:, None]
    return radiance


def _barycentric(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[N, 3] barycentric coordinates of points on their triangles [N, 3, 3]."""
    e1, e2, ep = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], points - corners[:, 0]
    d11, d12, d22 = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
    dp1, dp2 = _dot(ep, e1), _dot(ep, e2)
    den = d11 * d22 - d12 * d12 + _EPS * _EPS
    v = (d22 * dp1 - d12 * dp2) / den
    w = (d11 * dp2 - d12 * dp1) / den
    return np.stack([1.0 - v - w, v, w], axis=1)


def _box_down(samples: np.ndarray, h: int, w: int, s: int) -> np.ndarray:
    """Mean over each pixel's s x s subsamples: [H*s * W*s, ...] -> [H, W, ...] float32."""
    flat = np.ascontiguousarray(samples.reshape(len(samples), -1), dtype=np.float32)
    return _box_mean(flat, h, w, s).reshape(h, w, *samples.shape[1:])


@njit(parallel=True, cache=True)
def _box_mean(samples, h, w, s):
    out = np.zeros((h * w, samples.shape[1]), dtype=np.float32)
    for row in prange(h):
        for col in range(w):
            for c in range(samples.shape[1]):
                total = 0.0
                for i in range(s):
                    base = ((row * s + i) * w + col) * s
                    for j in range(s):
                        total += samples[base + j, c]
                out[row * w + col, c] = total / (s * s)
    return out


@njit(parallel=True, cache=True)
def _backdrop_and_plate(eye, dirs, to_lab, backdrop_radius, backdrop_level, plate_radius, plate_level, occlusion):
    """Radiance [R, 3] and distance [R] of each ray's first hit on the backdrop sphere or the plate disk.

    The backdrop is a sphere about the origin, lit from within, with a gentle gradient fixed in the lab; the
    plate is a grey disk at z=0 turning with the stone, darkened near the stone by its contact occlusion
    (`occlusion` [G, G] over the plate, bilinear, edges held; [1, 1] of ones when the stone is away).
    """
    n = dirs.shape[0]
    radiance = np.empty((n, 3), dtype=np.float32)
    best = np.empty(n, dtype=np.float32)
    ex, ey, ez = eye[0], eye[1], eye[2]
    c = ex * ex + ey * ey + ez * ez - backdrop_radius * backdrop_radius
    g = occlusion.shape[0]
    for r in prange(n):
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        b = dx * ex + dy * ey + dz * ez
        t = -b + math.sqrt(max(b * b - c, 0.0))
        px, py, pz = ex + dx * t, ey + dy * t, ez + dz * t
        lab_x = (to_lab[0, 0] * px + to_lab[0, 1] * py + to_lab[0, 2] * pz) / backdrop_radius
        lab_y = (to_lab[1, 0] * px + to_lab[1, 1] * py + to_lab[1, 2] * pz) / backdrop_radius
        lab_z = (to_lab[2, 0] * px + to_lab[2, 1] * py + to_lab[2, 2] * pz) / backdrop_radius
        level = backdrop_level * (1.0 + 0.12 * lab_z + 0.06 * lab_y - 0.04 * lab_x)
        radiance[r, 0], radiance[r, 1], radiance[r, 2] = level, level, 0.98 * level
        best[r] = t
        if dz < -_EPS:
            t_plate = -ez / dz
            hx, hy = ex + dx * t_plate, ey + dy * t_plate
            if hx * hx + hy * hy <= plate_radius * plate_radius:
                gx = min(max((hx + plate_radius) / (2.0 * plate_radius) * (g - 1), 0.0), g - 1.0)
                gy = min(max((hy + plate_radius) / (2.0 * plate_radius) * (g - 1), 0.0), g - 1.0)
                i0, j0 = min(int(gx), g - 2) if g > 1 else 0, min(int(gy), g - 2) if g > 1 else 0
                fx, fy = gx - i0, gy - j0
                i1, j1 = min(i0 + 1, g - 1), min(j0 + 1, g - 1)
                openness = ((1 - fx) * ((1 - fy) * occlusion[i0, j0] + fy * occlusion[i0, j1])
                            + fx * ((1 - fy) * occlusion[i1, j0] + fy * occlusion[i1, j1]))
                light = plate_level * (0.25 + 0.75 * openness)
                radiance[r, 0], radiance[r, 1], radiance[r, 2] = light, light, light
                best[r] = t_plate
    return radiance, best


def hit_stone(world: World, eye: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangle id (-1 = miss) [N] and distance (inf = miss) [N] of rays from `eye`.

    Only rays that pass the stone's bounding sphere go to embree (trimesh's RayMeshIntersector).
    """
    centre, radius = world.stone_bound
    to_c = centre - eye
    along = dirs @ to_c
    near = to_c @ to_c - along**2 <= radius**2
    tri = np.full(len(dirs), -1, dtype=np.int64)
    t = np.full(len(dirs), np.inf)
    if near.any():
        tri[near] = world.stone.mesh.ray.intersects_first(np.broadcast_to(eye, (int(near.sum()), 3)), dirs[near])
    hit = tri >= 0
    if hit.any():
        corners = world.stone.mesh.vertices[world.stone.mesh.faces[tri[hit]]]
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        t[hit] = _dot(corners[:, 0] - eye, normal) / _dot(dirs[hit], normal)
    return tri, t


def render(
    world: World, elevation_deg: float, azimuth_deg: float, stone_present: bool | None = None, supersample: int = 2
) -> RenderOut:
    """Render the view at (tilt, turn). `stone_present=None` follows the world's flag (plates: False)."""
    if not 1 <= supersample <= 8:
        raise BadInputError(f"supersample {supersample} is outside 1..8")
    present = world.stone_present if stone_present is None else stone_present
    rig, s = world.rig, supersample
    c2w = camera_to_turntable(elevation_deg, azimuth_deg, rig)
    eye, dirs = camera_rays(rig, c2w, s, world.lens)  # [3], [R, 3]
    to_lab = rotation_z(azimuth_deg).astype(np.float32)  # turntable -> lab
    key = np.asarray(world.key_direction_lab, dtype=np.float32)
    key = to_lab.T @ (key / np.linalg.norm(key))  # the lab's key light in the turntable frame

    occlusion = world.contact_occlusion if present else np.ones((1, 1))
    plate_level = world.plate_albedo * float(_irradiance(world, np.array([[0.0, 0.0, 1.0]]), key)[0])
    radiance, best = _backdrop_and_plate(eye, dirs, to_lab, world.backdrop_radius_m,
                                         world.backdrop_level * world.light_level, world.plate_radius_m,
                                         plate_level, occlusion)

    if world.chart is not None:
        t_chart, rgb = world.chart.intersect(to_lab @ eye, dirs @ to_lab.T)
        front = np.flatnonzero(t_chart < best)
        if len(front):
            normal = (to_lab.T @ world.chart.normal_lab)[None, :]  # lab -> turntable
            radiance[front] = rgb[front] * _irradiance(world, normal, key)[:, None]
            best[front] = t_chart[front]

    covered = np.zeros(len(dirs), dtype=bool)
    depth = np.zeros(len(dirs), dtype=np.float32)
    if present:
        tri, t_stone = hit_stone(world, eye, dirs)
        covered = t_stone < best
        hits = np.flatnonzero(covered)
        if len(hits):
            radiance[hits] = _shade_stone(world, eye, dirs[hits], tri[hits], t_stone[hits], key)
            depth[hits] = t_stone[hits] * (dirs[hits] @ c2w[:3, 2])

    h, w = rig.height, rig.width
    alpha = _box_down(covered.astype(np.float32), h, w, s)
    depth_px = _box_down(depth, h, w, s) / np.maximum(alpha, 1.0 / (s * s))
    return RenderOut(
        radiance=_box_down(radiance, h, w, s).astype(np.float32),
        mask=alpha >= 0.5,
        depth=np.where(alpha > 0, depth_px, 0.0).astype(np.float32),
        alpha=alpha.astype(np.float32),
        stone=_box_down(radiance * covered[:, None], h, w, s).astype(np.float32),
    )


class CaptureSettingsLike(Protocol):
    exposure_s: float
    iso: int


@dataclass
class FrameSource:
    """Renders what the simulated camera sees at the turntable's current pose, as DNG bytes.

    Keeps the last render so the caller can write the matching sim_truth frame without re-rendering.
    """

    world: World
    turntable_position: Callable[[], tuple[float, float]]  # -> (x_deg = azimuth, y_deg = elevation)
    sensor: SensorModel
    seed: int
    supersample: int = 2
    count: int = 0
    last: RenderOut | None = None
    last_pose: tuple[float, float] | None = None  # (elevation_deg, azimuth_deg)

    def __call__(self, settings: CaptureSettingsLike) -> tuple[bytes, str]:
        azimuth, elevation = self.turntable_position()
        self.count += 1
        out = render(self.world, elevation, azimuth, supersample=self.supersample)
        rng = np.random.default_rng([self.seed, self.count])
        mosaic = self.sensor.expose(out.radiance, settings.exposure_s, settings.iso, rng)
        self.last, self.last_pose = out, (elevation, azimuth)
        return dng_bytes(mosaic, self.sensor), f"SIM_{self.count:05d}.DNG"


def frame_source(
    world: World, turntable_position: Callable[[], tuple[float, float]], sensor: SensorModel, seed: int
) -> FrameSource:
    """The simulated PTP camera's shutter: render, expose, encode. Noise differs per shot, seeded."""
    return FrameSource(world=world, turntable_position=turntable_position, sensor=sensor, seed=seed)

