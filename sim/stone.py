"""Stones for the simulated rig: procedural rocks and the real scanned meshes.

A stone is a watertight mesh in the turntable frame (metres, centred on the axis, lowest point on
z=0) plus an albedo that is a function of 3D position, so its texture is the same from every view.
The looks include the cases that make vanilla 3DGS go falsely transparent: surfaces with little or
no texture, a repeated pattern, a stone as pale as the backdrop, and a specular sheen.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import trimesh

from station.errors import BadInputError

Look = Literal["grey", "dark", "pale", "speckled", "textureless", "patterned"]
LOOKS: tuple[str, ...] = ("grey", "dark", "pale", "speckled", "textureless", "patterned")

# The backdrop's neutral grey (linear sRGB reflectance); the 'pale' look sits right next to it.
BACKDROP_ALBEDO = np.array([0.55, 0.55, 0.54])

Albedo = Callable[[np.ndarray], np.ndarray]  # points [N, 3] (turntable frame, m) -> linear rgb [N, 3]


@dataclass
class Stone:
    """A stone sitting on the plate: geometry, view-independent albedo, specular sheen (0 = matte)."""

    mesh: trimesh.Trimesh
    albedo: Albedo
    sheen: float
    name: str


class FourierNoise:
    """Smooth seeded 3D noise: a sum of random plane waves, roughly in [-1, 1].

    Plane waves are cheap, vectorised and evaluate at any 3D point, which is all a
    view-independent texture needs.
    """

    def __init__(self, rng: np.random.Generator, n_waves: int, wavelength_m: float):
        directions = rng.normal(size=(n_waves, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        # spread the frequencies over an octave and a half so the noise does not look periodic
        freq = (2.0 * np.pi / wavelength_m) * rng.uniform(0.6, 1.8, size=(n_waves, 1))
        self.k = (directions * freq).T.astype(np.float32)  # [3, W]
        self.phase = rng.uniform(0.0, 2.0 * np.pi, size=n_waves).astype(np.float32)  # [W]
        self.amp = np.float32(np.sqrt(2.0 / n_waves))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] -> [N] float32 (float32 is plenty for a texture and halves the cost)."""
        return self.amp * np.sin(points.astype(np.float32) @ self.k + self.phase).sum(axis=1)


def _look_albedo(look: str, rng: np.random.Generator) -> Albedo:
    """Rock-like albedo with low-contrast texture; each look returns a closure over its noise."""
    if look not in LOOKS:
        raise BadInputError(f"stone look {look!r} is not one of {', '.join(LOOKS)}")
    tint = 1.0 + rng.uniform(-0.04, 0.04, size=3)
    coarse = FourierNoise(rng, 16, wavelength_m=0.03)
    fine = FourierNoise(rng, 32, wavelength_m=0.004)

    if look == "grey":
        base = np.array([0.32, 0.30, 0.27]) * tint
        return lambda p: base * (1.0 + 0.10 * coarse(p) + 0.06 * fine(p))[:, None]
    if look == "dark":
        base = np.array([0.075, 0.07, 0.065]) * tint
        return lambda p: base * (1.0 + 0.10 * coarse(p) + 0.08 * fine(p))[:, None]
    if look == "pale":
        base = BACKDROP_ALBEDO * (1.0 + rng.uniform(-0.02, 0.02, size=3))
        return lambda p: base * (1.0 + 0.03 * coarse(p) + 0.02 * fine(p))[:, None]
    if look == "speckled":
        base = np.array([0.36, 0.34, 0.32]) * tint
        speck = FourierNoise(rng, 64, wavelength_m=0.003)

        def speckled(p: np.ndarray) -> np.ndarray:
            s = speck(p)
            grains = np.where(s > 1.3, -0.45, np.where(s < -1.4, 0.3, 0.0))  # sparse dark and light grains
            return base * (1.0 + 0.06 * coarse(p) + grains)[:, None]

        return speckled
    if look == "textureless":
        base = np.array([0.40, 0.39, 0.37]) * tint
        return lambda p: base * (1.0 + 0.01 * coarse(p))[:, None]
    # patterned: the same motif repeated on a 1 cm lattice, so feature matches are ambiguous
    base = np.array([0.30, 0.29, 0.27]) * tint
    period = 0.01

    def patterned(p: np.ndarray) -> np.ndarray:
        w = 2.0 * np.pi / period
        motif = np.sin(w * p[:, 0]) * np.sin(w * p[:, 1]) * np.sin(w * p[:, 2])
        return base * (1.0 + 0.25 * np.sign(motif) * np.minimum(1.0, 4.0 * np.abs(motif)))[:, None]

    return patterned


def rest_on_plate(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Centre the bounding box on the turntable axis and put the lowest point on z=0."""
    lo, hi = mesh.bounds
    mesh = mesh.copy()
    mesh.apply_translation([-(lo[0] + hi[0]) / 2.0, -(lo[1] + hi[1]) / 2.0, -lo[2]])
    return mesh


def procedural_stone(seed: int, size_m: float = 0.08, look: Look = "grey", sheen: float = 0.0) -> Stone:
    """An irregular, watertight rock of longest extent `size_m`, fully determined by `seed`.

    A subdivided icosphere displaced along its radii stays star-shaped, so it cannot
    self-intersect: watertightness survives any displacement.
    """
    if not (0.005 <= size_m <= 0.5):
        raise BadInputError(f"stone size {size_m} m is outside 0.005..0.5 m")
    if not (0.0 <= sheen <= 1.0):
        raise BadInputError(f"stone sheen {sheen} is outside 0..1")
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    unit = sphere.vertices  # [V, 3] on the unit sphere
    lumps = FourierNoise(rng, 12, wavelength_m=2.2)
    bumps = FourierNoise(rng, 24, wavelength_m=0.7)
    radius = 1.0 + 0.16 * lumps(unit) + 0.035 * bumps(unit)  # [V]
    # facets: a few flattened cuts, as on a broken rock
    for normal in rng.normal(size=(rng.integers(2, 5), 3)):
        normal /= np.linalg.norm(normal)
        cos = unit @ normal
        cut = rng.uniform(0.75, 0.9)
        radius = np.where(cos > cut, np.minimum(radius, radius * cut / np.maximum(cos, 1e-6)), radius)
    vertices = unit * radius[:, None] * rng.uniform([0.85, 0.6, 0.45], [1.0, 0.85, 0.7])
    # rocks rest on their flat side: spin freely about z, tilt only a little
    tilt = trimesh.transformations.rotation_matrix(rng.uniform(-0.25, 0.25), [1.0, 0.0, 0.0])
    spin = trimesh.transformations.rotation_matrix(rng.uniform(0.0, 2.0 * np.pi), [0.0, 0.0, 1.0])
    vertices = vertices @ (spin @ tilt)[:3, :3].T
    mesh = trimesh.Trimesh(vertices=vertices, faces=sphere.faces, process=False)
    mesh.apply_scale(size_m / mesh.extents.max())
    mesh = rest_on_plate(mesh)
    return Stone(mesh=mesh, albedo=_look_albedo(look, rng), sheen=float(sheen), name=f"procedural-{look}-{seed}")


def load_stone_mesh(
    path: Path | str, look: Look = "grey", target_size_m: float | None = None, seed: int = 0, sheen: float = 0.0
) -> Stone:
    """A real scanned stone (already in metres), rested on the plate, wearing a procedural look."""
    path = Path(path)
    if not path.is_file():
        raise BadInputError(f"{path}: stone mesh not found")
    try:
        mesh = trimesh.load_mesh(path, process=True)
    # trimesh's parsers fail in many ways on a bad file (a mislabelled STL even reaches for an
    # optional text-encoding module); all of them mean "not a mesh we can use"
    except (ValueError, KeyError, IndexError, TypeError, AttributeError, EOFError, ImportError, struct.error) as exc:
        raise BadInputError(f"{path}: cannot read a mesh ({exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise BadInputError(f"{path}: holds no triangle mesh")
    if target_size_m is not None:
        if not (0.005 <= target_size_m <= 0.5):
            raise BadInputError(f"target size {target_size_m} m is outside 0.005..0.5 m")
        mesh.apply_scale(target_size_m / mesh.extents.max())
    if not (0.005 <= mesh.extents.max() <= 0.5):
        raise BadInputError(
            f"{path}: stone is {mesh.extents.max():.4g} units across; expected metres (0.005..0.5), "
            "pass target_size_m to rescale"
        )
    rng = np.random.default_rng(seed)
    return Stone(mesh=rest_on_plate(mesh), albedo=_look_albedo(look, rng), sheen=float(sheen), name=path.stem)
