"""The NGS infill fills the object's inside and never shows in front of its surface."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from station.errors import BadInputError
from station.ngs.infill import (Camera, InfillConfig, build_infill, candidate_cells, depth_prune_mask, hull_equations,
                                surface_depths)
from station.rig_geometry import look_at_c2w

RADIUS = 1.0


def sphere_surface(centre=(0.0, 0.0, 0.0), count: int = 500, radius: float = RADIUS) -> dict[str, torch.Tensor]:
    """Opaque isotropic Gaussians on a Fibonacci sphere, dense enough to hide its inside."""
    i = np.arange(count) + 0.5
    phi = np.arccos(1 - 2 * i / count)
    theta = math.pi * (1 + 5**0.5) * i
    pts = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1) * radius
    spacing = radius * math.sqrt(4 * math.pi / count)
    quats = torch.zeros(count, 4)
    quats[:, 0] = 1
    return {
        "means": torch.tensor(pts + np.asarray(centre), dtype=torch.float32),
        "quats": quats,
        "scales": torch.full((count, 3), spacing),
        "opacities": torch.full((count,), 0.99),
    }


def join(*parts: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


def ring_cameras(distance: float = 6.0, size: int = 32, focal: float = 40.0) -> list[Camera]:
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], dtype=torch.float32)
    cams = []
    for elev, count in ((15.0, 10), (60.0, 4)):
        for k in range(count):
            az = 2 * math.pi * k / count + 0.3
            e = math.radians(elev)
            eye = distance * np.array([math.cos(e) * math.cos(az), math.cos(e) * math.sin(az), math.sin(e)])
            c2w = look_at_c2w(eye, np.zeros(3))
            cams.append(Camera(torch.tensor(np.linalg.inv(c2w), dtype=torch.float32), K, size, size))
    return cams


def noise_at(points: list[list[float]], scale: float = 0.05, opacity: float = 0.01) -> dict[str, torch.Tensor]:
    n = len(points)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    return {"means": torch.tensor(points), "quats": quats, "scales": torch.full((n, 3), scale),
            "opacities": torch.full((n,), opacity)}


TINY = InfillConfig(levels=(8, 16), erosion_iters=(2, 2), prune_downscale=1)


def test_depth_pruning_marks_noise_in_front_of_the_surface_and_keeps_noise_behind_it():
    cams = ring_cameras()
    noise = noise_at([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3], [2.0, 0.5, 0.2], [0.3, -1.6, 0.1]])
    marked = depth_prune_mask(noise, cams, surface_depths(sphere_surface(), cams, 0.5))
    assert marked.tolist() == [False, False, True, True]


def test_noise_inside_a_diffuse_surface_layer_is_pruned_unless_the_surface_starts_at_its_first_faint_gaussian():
    """DTU's dark cavities: faint surface Gaussians lie in front of where the surface turns opaque."""
    cams = ring_cameras()
    faint = sphere_surface(radius=1.6)
    faint["opacities"] = torch.full_like(faint["opacities"], 0.01)
    noise = noise_at([[0.0, 0.0, 1.4], [0.0, 0.0, 0.0]])  # between the shells; deep inside both
    surface = join(faint, sphere_surface())
    assert depth_prune_mask(noise, cams, surface_depths(surface, cams, 0.5)).tolist() == [True, False]
    assert depth_prune_mask(noise, cams, surface_depths(surface, cams, 1 / 255)).tolist() == [False, False]


def test_noise_behind_a_still_half_transparent_surface_is_kept_for_the_noise_to_make_it_opaque():
    cams = ring_cameras()
    see_through = sphere_surface()
    see_through["opacities"] = torch.full_like(see_through["opacities"], 0.05)
    noise = noise_at([[0.0, 0.0, 0.0], [0.0, 0.0, 1.4]])  # inside; outside in front
    assert depth_prune_mask(noise, cams, surface_depths(see_through, cams, 0.5)).tolist() == [False, True]


def test_infill_of_a_sphere_lies_strictly_inside_it():
    infill = build_infill(sphere_surface(), ring_cameras(), TINY)
    assert len(infill) > 20
    radii = infill.means.norm(dim=-1) + 3 * infill.scales  # the noise's 3-sigma extent
    assert float(radii.max()) < RADIUS


def test_a_far_floater_does_not_stretch_the_hull_and_empty_the_infill():
    alone = build_infill(sphere_surface(), ring_cameras(), TINY)
    floater = noise_at([[0.0, -10.0, 4.0]], scale=0.05, opacity=0.5)
    with_floater = build_infill(join(sphere_surface(), floater), ring_cameras(), TINY)
    assert len(with_floater) == len(alone) > 20
    assert torch.equal(with_floater.means, alone.means)


def test_depth_pruning_removes_hull_noise_between_two_spheres():
    surface = join(sphere_surface((-1.5, 0, 0)), sphere_surface((1.5, 0, 0)))
    def inside_a_sphere(means: torch.Tensor) -> torch.Tensor:
        left = (means - torch.tensor([-1.5, 0, 0])).norm(dim=-1) < RADIUS
        right = (means - torch.tensor([1.5, 0, 0])).norm(dim=-1) < RADIUS
        return left | right

    cfg = InfillConfig(levels=(8, 16), erosion_iters=(1, 1), prune_downscale=1)
    unpruned = build_infill(surface, ring_cameras(), InfillConfig(**{**cfg.__dict__, "depth_prune": False}))
    assert not bool(inside_a_sphere(unpruned.means).all())  # the hull bridges the gap
    pruned = build_infill(surface, ring_cameras(), cfg)
    assert len(pruned) >= 8
    assert bool(inside_a_sphere(pruned.means).all())


def test_finer_levels_nest_inside_coarser_cells_without_overlap():
    infill = build_infill(sphere_surface(), ring_cameras(), InfillConfig(levels=(8, 16), erosion_iters=(0, 0), depth_prune=False))
    coarse = infill.means[infill.levels == 8]
    fine = infill.means[infill.levels == 16]
    h_coarse = 2 * float(infill.scales[infill.levels == 8][0])
    # no fine cell centre lies inside a coarse noise cell: coverage is exact on nested grids
    d = (fine[:, None, :] - coarse[None, :, :]).abs().max(dim=-1).values  # [F, C] Chebyshev distance
    assert float(d.min()) >= h_coarse / 2 - 1e-5
    # fine centres sit exactly a quarter coarse cell off a coarse grid line
    offsets = torch.remainder((fine - coarse[0]) / (h_coarse / 2), 1.0)
    torch.testing.assert_close(offsets, torch.full_like(offsets, 0.5), atol=1e-3, rtol=0)


def test_levels_that_do_not_nest_are_refused():
    with pytest.raises(BadInputError, match="multiple"):
        build_infill(sphere_surface(), ring_cameras(), InfillConfig(levels=(8, 12), erosion_iters=(1, 1)))


def test_column_hull_test_agrees_with_testing_every_cell_against_every_facet():
    points = np.random.default_rng(1).normal(size=(200, 3)) * [1.0, 0.6, 0.3]
    planes = hull_equations(points)
    covered = np.zeros((12, 12, 12), dtype=bool)
    covered[:6, :6, :6] = True
    origin, h = points.min(axis=0) - 0.1, float((points.max(axis=0) - points.min(axis=0)).max() + 0.2) / 12
    cells = np.argwhere(~covered)
    centres = origin + (cells + 0.5) * h
    brute = cells[(centres @ planes[:, :3].T + planes[:, 3] <= 1e-12).all(axis=1)]
    found = candidate_cells(covered, origin, h, planes)
    assert len(brute) > 20
    assert sorted(map(tuple, found.tolist())) == sorted(map(tuple, brute.tolist()))
