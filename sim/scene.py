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

    def patch_centres_lab(self) -> np.ndarray:
        """[24, 3] patch centres in the lab frame, in CHART_LINEAR_SRGB order."""
        centre, _, right, down = self.frame
        pitch = self.patch_m + self.gap_m
        rows, cols = np.divmod(np.arange(24), 6)
        return centre + ((cols - 2.5) * pitch)[:, None] * right + ((rows - 1.5) * pitch)[:, None] * down

    def in_turntable_frame(self, to_lab: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Centre, normal, right and down of the card in the turntable frame (`to_lab`: turntable -> lab)."""
        return tuple(to_lab.T @ vector for vector in self.frame)  # type: ignore[return-value]


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
    supersampled grid: where render's pixels look, worked out apart from its fused pass, for checking it."""
    rays = _camera_frame_rays(rig, lens, supersample)
    return c2w[:3, 3].astype(np.float32), rays @ c2w[:3, :3].T.astype(np.float32)


def _irradiance(world: World, normals: np.ndarray, key: np.ndarray) -> np.ndarray:
    """[N] softbox irradiance: a bright dome (more from above) plus a mild key."""
    dome = 0.62 + 0.23 * normals[:, 2]
    return world.light_level * (dome + world.key_strength * np.clip(normals @ key, 0.0, None))


@njit(parallel=True, cache=True)
def _environment(eye, camera_frame_rays, rotation, to_lab, backdrop_radius, backdrop_level, plate_radius, plate_level,
                 occlusion, chart_frame, chart_pitch, chart_margin, chart_radiance, chart_surround, stone_centre,
                 stone_radius):
    """Each ray's world direction [R, 3], and the radiance [R, 3] and distance [R] of its first hit on the
    backdrop sphere, the plate disk or the chart; `near` [R]: the ray passes the stone's bounding sphere.

    One pass over the rays for everything analytic. The backdrop is a sphere about the origin, lit from within,
    with a gentle gradient fixed in the lab; the plate is a grey disk at z=0 turning with the stone, darkened near
    the stone by its contact occlusion (`occlusion` [G, G] over the plate, bilinear, edges held; [1, 1] of ones
    when the stone is away). The chart (`chart_frame` [4, 3]: centre, normal, right, down; no rows: no chart) is
    a 6x4 grid of patches of `chart_radiance` [24, 3] in a frame of `chart_surround`.
    """
    n = camera_frame_rays.shape[0]
    dirs = np.empty((n, 3), dtype=np.float32)
    radiance = np.empty((n, 3), dtype=np.float32)
    best = np.empty(n, dtype=np.float32)
    near = np.empty(n, dtype=np.bool_)
    ex, ey, ez = eye[0], eye[1], eye[2]
    c = ex * ex + ey * ey + ez * ez - backdrop_radius * backdrop_radius
    g = occlusion.shape[0]
    to_stone = stone_centre - eye
    to_stone_squared = to_stone[0] * to_stone[0] + to_stone[1] * to_stone[1] + to_stone[2] * to_stone[2]
    has_chart = chart_frame.shape[0] == 4
    for r in prange(n):
        for i in range(3):
            dirs[r, i] = (rotation[i, 0] * camera_frame_rays[r, 0] + rotation[i, 1] * camera_frame_rays[r, 1]
                          + rotation[i, 2] * camera_frame_rays[r, 2])
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
        if has_chart:
            facing = dx * chart_frame[1, 0] + dy * chart_frame[1, 1] + dz * chart_frame[1, 2]
            if facing < -_EPS:
                ox, oy, oz = ex - chart_frame[0, 0], ey - chart_frame[0, 1], ez - chart_frame[0, 2]
                t_chart = -(ox * chart_frame[1, 0] + oy * chart_frame[1, 1] + oz * chart_frame[1, 2]) / facing
                if 0.0 < t_chart < best[r]:
                    lx, ly, lz = ox + dx * t_chart, oy + dy * t_chart, oz + dz * t_chart
                    u = (lx * chart_frame[2, 0] + ly * chart_frame[2, 1] + lz * chart_frame[2, 2]) / chart_pitch + 3.0
                    v = (lx * chart_frame[3, 0] + ly * chart_frame[3, 1] + lz * chart_frame[3, 2]) / chart_pitch + 2.0
                    if -chart_margin <= u <= 6.0 + chart_margin and -chart_margin <= v <= 4.0 + chart_margin:
                        col, row = min(max(math.floor(u), 0), 5), min(max(math.floor(v), 0), 3)
                        in_patch = (u - math.floor(u) > chart_margin and v - math.floor(v) > chart_margin
                                    and 0.0 < u < 6.0 and 0.0 < v < 4.0)
                        for k in range(3):
                            radiance[r, k] = chart_radiance[row * 6 + col, k] if in_patch else chart_surround
                        best[r] = t_chart
        along = dx * to_stone[0] + dy * to_stone[1] + dz * to_stone[2]
        near[r] = to_stone_squared - along * along <= stone_radius * stone_radius
    return dirs, radiance, best, near


@njit(inline="always")
def _row(array, i):
    return array[i, 0], array[i, 1], array[i, 2]


@njit(inline="always")
def _sub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


@njit(inline="always")
def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(parallel=True, cache=True)
def _triangle_distance(eye, dirs, rays, triangles, vertices, faces):
    """[K] distance along each of `rays` to the plane of its triangle (inf where `triangles` is -1: a miss)."""
    t = np.full(rays.shape[0], np.inf)
    origin = (np.float64(eye[0]), np.float64(eye[1]), np.float64(eye[2]))
    for k in prange(rays.shape[0]):
        if triangles[k] < 0:
            continue
        c0 = _row(vertices, faces[triangles[k], 0])
        e1 = _sub(_row(vertices, faces[triangles[k], 1]), c0)
        e2 = _sub(_row(vertices, faces[triangles[k], 2]), c0)
        normal = (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0])
        t[k] = _dot3(_sub(c0, origin), normal) / _dot3(_row(dirs, rays[k]), normal)
    return t


def hit_stone(world: World, eye: np.ndarray, dirs: np.ndarray, near: np.ndarray,
              nearer: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays [K] whose first hit is the stone, its triangle [K] and distance [K]: rays within its bounding
    sphere (`near`) go to embree (trimesh's RayMeshIntersector), and a hit counts where it is before `nearer`."""
    mesh = world.stone.mesh
    candidates = np.flatnonzero(near)
    triangles = mesh.ray.intersects_first(np.broadcast_to(eye, (len(candidates), 3)), dirs[candidates])
    t = _triangle_distance(eye, dirs, candidates, triangles, mesh.vertices, mesh.faces)
    first = t < nearer[candidates]
    return candidates[first], triangles[first], t[first]


@njit(parallel=True, cache=True)
def _stone_light(eye, dirs, rays, triangles, t, vertices, faces, vertex_normals, key, light_level, key_strength,
                 sheen):
    """Per stone hit: the point [K, 3], the irradiance [K] its albedo takes, and the sheen [K] added on top.

    The shading normal is the vertex normals interpolated at the hit; the sheen is a key highlight plus the
    softbox's own mirror image."""
    count = rays.shape[0]
    points = np.empty((count, 3))
    irradiance = np.empty(count)
    glow = np.zeros(count)
    for k in prange(count):
        d = _row(dirs, rays[k])
        f0, f1, f2 = faces[triangles[k], 0], faces[triangles[k], 1], faces[triangles[k], 2]
        p = (eye[0] + d[0] * t[k], eye[1] + d[1] * t[k], eye[2] + d[2] * t[k])
        c0 = _row(vertices, f0)
        e1, e2, ep = _sub(_row(vertices, f1), c0), _sub(_row(vertices, f2), c0), _sub(p, c0)
        d11, d12, d22 = _dot3(e1, e1), _dot3(e1, e2), _dot3(e2, e2)
        dp1, dp2 = _dot3(ep, e1), _dot3(ep, e2)
        den = d11 * d22 - d12 * d12 + _EPS * _EPS
        v = (d22 * dp1 - d12 * dp2) / den
        w = (d11 * dp2 - d12 * dp1) / den
        n0, n1, n2 = _row(vertex_normals, f0), _row(vertex_normals, f1), _row(vertex_normals, f2)
        u = 1.0 - v - w
        normal = (u * n0[0] + v * n1[0] + w * n2[0], u * n0[1] + v * n1[1] + w * n2[1],
                  u * n0[2] + v * n1[2] + w * n2[2])
        length = math.sqrt(_dot3(normal, normal)) + _EPS
        normal = (normal[0] / length, normal[1] / length, normal[2] / length)
        irradiance[k] = light_level * (0.62 + 0.23 * normal[2] + key_strength * max(_dot3(normal, key), 0.0))
        points[k, 0], points[k, 1], points[k, 2] = p
        if sheen > 0.0:
            half = _sub(key, d)
            length = math.sqrt(_dot3(half, half)) + _EPS
            half = (half[0] / length, half[1] / length, half[2] / length)
            reflect_z = d[2] - 2.0 * _dot3(d, normal) * normal[2]
            highlight = 1.5 * max(_dot3(normal, half), 0.0) ** 40
            glow[k] = sheen * light_level * (highlight + 0.15 * (0.5 + 0.5 * reflect_z))
    return points, irradiance, glow


@njit(parallel=True, cache=True)
def _pixels(radiance, stone_rays, stone_depth, h, w, s):
    """The supersampled rays averaged to pixels: radiance [H, W, 3], stone coverage [H, W], the stone's mean
    depth where it covers [H, W] (0 elsewhere) and the stone alone on black [H, W, 3], in one pass."""
    samples = radiance.shape[0]
    covered = np.zeros(samples, dtype=np.bool_)
    depth = np.zeros(samples, dtype=np.float32)
    for k in range(stone_rays.shape[0]):
        covered[stone_rays[k]] = True
        depth[stone_rays[k]] = stone_depth[k]
    image = np.empty((h, w, 3), dtype=np.float32)
    stone = np.empty((h, w, 3), dtype=np.float32)
    alpha = np.empty((h, w), dtype=np.float32)
    depth_px = np.empty((h, w), dtype=np.float32)
    n = s * s
    for row in prange(h):
        for col in range(w):
            total = np.zeros(3)
            on_stone = np.zeros(3)
            hits, depth_sum = 0, 0.0
            for i in range(s):
                base = ((row * s + i) * w + col) * s
                for j in range(s):
                    k = base + j
                    for c in range(3):
                        total[c] += radiance[k, c]
                    if covered[k]:
                        hits += 1
                        depth_sum += depth[k]
                        for c in range(3):
                            on_stone[c] += radiance[k, c]
            for c in range(3):
                image[row, col, c] = total[c] / n
                stone[row, col, c] = on_stone[c] / n
            alpha[row, col] = hits / n
            depth_px[row, col] = depth_sum / hits if hits else 0.0
    return image, alpha, depth_px, stone


def render(
    world: World, elevation_deg: float, azimuth_deg: float, stone_present: bool | None = None, supersample: int = 2
) -> RenderOut:
    """Render the view at (tilt, turn). `stone_present=None` follows the world's flag (plates: False)."""
    if not 1 <= supersample <= 8:
        raise BadInputError(f"supersample {supersample} is outside 1..8")
    present = world.stone_present if stone_present is None else stone_present
    rig, s = world.rig, supersample
    c2w = camera_to_turntable(elevation_deg, azimuth_deg, rig)
    eye = c2w[:3, 3].astype(np.float32)
    to_lab = rotation_z(azimuth_deg).astype(np.float32)  # turntable -> lab
    key = np.asarray(world.key_direction_lab, dtype=np.float32)
    key = to_lab.T @ (key / np.linalg.norm(key))  # the lab's key light in the turntable frame

    occlusion = world.contact_occlusion if present else np.ones((1, 1))
    plate_level = world.plate_albedo * float(_irradiance(world, np.array([[0.0, 0.0, 1.0]]), key)[0])
    chart_frame, chart_pitch, chart_margin, chart_light = np.zeros((0, 3)), 1.0, 0.0, 0.0
    if world.chart is not None:
        chart_frame = np.stack(world.chart.in_turntable_frame(to_lab))
        chart_pitch = world.chart.patch_m + world.chart.gap_m
        chart_margin = world.chart.gap_m / chart_pitch
        chart_light = float(_irradiance(world, chart_frame[1][None, :], key)[0])
    centre, radius = world.stone_bound
    dirs, radiance, best, near = _environment(
        eye, _camera_frame_rays(rig, world.lens, s), c2w[:3, :3].astype(np.float32), to_lab, world.backdrop_radius_m,
        world.backdrop_level * world.light_level, world.plate_radius_m, plate_level, occlusion, chart_frame,
        chart_pitch, chart_margin, CHART_LINEAR_SRGB * chart_light, CHART_SURROUND * chart_light, centre, radius)

    stone_rays, stone_depth = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32)
    if present:
        stone_rays, triangles, t_stone = hit_stone(world, eye, dirs, near, best)
        if len(stone_rays):
            radiance[stone_rays] = _shade_stone(world, eye, dirs, stone_rays, triangles, t_stone, key)
            stone_depth = (t_stone * (dirs[stone_rays] @ c2w[:3, 2])).astype(np.float32)

    image, alpha, depth, stone = _pixels(radiance, stone_rays, stone_depth, rig.height, rig.width, s)
    return RenderOut(radiance=image, mask=alpha >= 0.5, depth=depth, alpha=alpha, stone=stone)


def _shade_stone(world: World, eye: np.ndarray, dirs: np.ndarray, rays: np.ndarray, triangles: np.ndarray,
                 t: np.ndarray, key: np.ndarray) -> np.ndarray:
    """[K, 3] radiance of the stone hits: albedo x irradiance, plus a view-dependent sheen."""
    mesh = world.stone.mesh
    points, irradiance, glow = _stone_light(
        eye, dirs, rays, triangles, t, mesh.vertices, mesh.faces, world.vertex_normals, key, world.light_level,
        world.key_strength, world.stone.sheen)
    return world.stone.albedo(points) * irradiance[:, None] + glow[:, None]


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

