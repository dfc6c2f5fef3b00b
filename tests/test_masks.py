"""Masks from a clean plate: shadow- and drift-robust seed, graph cut against the plate, cleaning, self-check."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage, sparse
from scipy.sparse.csgraph import maximum_flow

from station.errors import BadInputError
from station.process import masks
from station.process.images_io import read_exr, read_mask_png, read_png16
from station.process.masks import (_MAX_NATS, _NATS_TO_CAPACITY, Matte, MaskSettings, check_masks, column_medians,
                                   compute_mask,
                                   compute_matte, fill_holes, min_cut, shadow_field, unmix)
from station.scanfolder import ManifestEntry, ScanFolder, atomic_write_bytes, sha256_bytes


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def backdrop(h: int = 240, w: int = 320) -> np.ndarray:
    """A vignetted grey backdrop with a lab gradient, linear RGB [H, W, 3]."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / ((h / 2) ** 2 + (w / 2) ** 2)
    level = 0.5 * (1.0 - 0.35 * r2) * (1.0 + 0.1 * yy / h)
    return np.repeat(level[..., None], 3, axis=2) * np.array([1.0, 1.0, 0.97], dtype=np.float32)


def ellipse(h: int = 240, w: int = 320, cy: float = 120, cx: float = 160, ry: float = 45, rx: float = 60) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1.0


def synthetic_pair(
    look: str, seed: int = 0, shading: float = 0.35, shadow_rows: float = 12.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(shot, plate, true mask): stone over backdrop with a soft contact shadow, noise, 1.5% drift.

    `shading` is how much brighter the stone's top is than its middle (and its bottom darker).
    `shadow_rows` is the contact shadow's vertical scale: a low camera squeezes it into a few rows.
    """
    rng = np.random.default_rng(seed)
    base = backdrop()
    stone = ellipse()
    yy, xx = np.mgrid[0:240, 0:320]
    shade = 1.0 + shading * (120 - yy) / 45  # lit from above
    albedo = {"dark": 0.08, "pale": 0.56, "speckled": 0.36}[look]
    colour = np.array([1.0, 0.97, 0.93]) if look != "pale" else np.array([1.0, 1.0, 0.97])
    stone_rgb = (albedo * shade)[..., None] * colour
    if look == "speckled":
        grains = rng.random((240, 320)) < 0.08
        stone_rgb = stone_rgb * np.where(grains, 0.5, 1.0)[..., None]
    # contact shadow: darkens the backdrop just below the stone, keeping its chroma
    shadow = 1.0 - 0.6 * np.exp(-(((yy - 165) / shadow_rows) ** 2 + ((xx - 160) / 70.0) ** 2))
    shot = np.where(stone[..., None], stone_rgb, base * shadow[..., None])
    plate = base * 1.015
    noise = lambda img: img + rng.normal(0, 0.004, img.shape) * np.sqrt(np.maximum(img, 0) / 0.5)
    return noise(shot).astype(np.float32), noise(plate).astype(np.float32), stone


@pytest.mark.parametrize(("look", "shading"), [("dark", 0.35), ("pale", 0.03), ("speckled", 0.35)])
def test_mask_ignores_contact_shadow_and_exposure_drift(look: str, shading: float) -> None:
    shot, plate, truth = synthetic_pair(look, shading=shading)
    mask = compute_mask(shot, plate)
    assert iou(mask, truth) >= 0.98


def test_the_cut_ends_at_the_round_that_moves_at_most_its_settled_share_of_the_stone(monkeypatch) -> None:
    shot, plate, truth = synthetic_pair("speckled", seed=4)
    cuts: list[np.ndarray] = []  # each round's cut, in order
    real_min_cut = masks.min_cut

    def recorded_min_cut(*args) -> np.ndarray:
        cuts.append(real_min_cut(*args))
        return cuts[-1]

    monkeypatch.setattr(masks, "min_cut", recorded_min_cut)

    def rounds(settled_fraction: float) -> tuple[int, np.ndarray]:
        cuts.clear()
        mask = compute_mask(shot, plate, MaskSettings(settled_fraction=settled_fraction))
        return len(cuts), mask

    assert rounds(0.0)[0] == 3  # only a fixed point ends it early; this shot has none in three rounds
    second = cuts[1]
    share = np.count_nonzero(second != cuts[0]) / np.count_nonzero(second)  # what the second round moved
    assert 0 < share < 0.01
    assert rounds(0.999 * share)[0] == 3
    count, mask = rounds(share)
    assert count == 2 and iou(mask, truth) >= 0.98
    assert rounds(1.0)[0] == 1  # any first cut settles


def colour_chart(h: int = 240, w: int = 320, x0: int = 218, y0: int = 90) -> np.ndarray:
    """A reflectance pattern [H, W, 3]: a 6 x 4 patch chart with a black frame, 1 elsewhere."""
    rng = np.random.default_rng(7)
    pattern = np.ones((h, w, 3), np.float32)
    pattern[y0:y0 + 42, x0:x0 + 62] = 0.1  # the frame
    for row in range(4):
        for col in range(6):
            y, x = y0 + 2 + 10 * row, x0 + 2 + 10 * col
            pattern[y:y + 8, x:x + 8] = rng.uniform(0.15, 1.8, 3)
    return pattern


@pytest.mark.parametrize("look", ["dark", "speckled"])
def test_a_colour_chart_the_stone_touches_stays_out_of_the_mask(look: str) -> None:
    """The chart stands still, so it is in the plate too; its sharp edges are no reason to call it stone."""
    shot, plate, truth = synthetic_pair(look)
    chart = colour_chart()  # its left edge hides behind the stone's right flank
    shot = np.where(truth[..., None], shot, shot * chart).astype(np.float32)
    plate = (plate * chart).astype(np.float32)
    mask = compute_mask(shot, plate)
    assert (mask & ~truth & (chart[..., 0] != 1)).sum() <= 10
    assert iou(mask, truth) >= 0.98


@pytest.mark.parametrize("look", ["dark", "speckled"])
def test_contact_shadow_below_a_stone_seen_from_a_low_camera_stays_out_of_the_mask(look: str) -> None:
    # squeezed into a few rows, the shadow deepens steeply right up to the stone's lowest edge
    shot, plate, truth = synthetic_pair(look, shadow_rows=5.0)
    mask = compute_mask(shot, plate)
    below = np.zeros_like(truth)
    below[166:] = True  # the stone's lowest row is 165
    assert (mask & below).sum() <= 20
    assert iou(mask, truth) >= 0.98


def coverage_ellipse(cy: float = 120, cx: float = 160, ry: float = 45.3, rx: float = 60.7, s: int = 4) -> np.ndarray:
    """The stone's coverage [240, 320] of each pixel, from s x s samples, for an anti-aliased edge."""
    yy, xx = (np.mgrid[0:240 * s, 0:320 * s] + 0.5) / s - 0.5
    inside = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1.0
    return inside.reshape(240, s, 320, s).mean(axis=(1, 3))


def with_noise(image: np.ndarray, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (image + rng.normal(0, 0.004, image.shape) * np.sqrt(np.maximum(image, 0) / 0.5)).astype(np.float32)


def brown_stone_over_a_steep_contact_shadow() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(shot, plate, true mask, rows below the stone): the shadow halves the plate within 2 rows of the stone.

    That is the wedge under a rounded base seen from the lowest ring: far steeper than any
    plane the shadow field fits around the stone, so by brightness alone it passes for stone.
    """
    coverage = coverage_ellipse()
    yy, xx = np.mgrid[0:240, 0:320]
    lowest = 120 + 45.3 * np.sqrt(np.clip(1 - ((xx - 160) / 60.7) ** 2, 0, 1))  # the stone's lowest row per column
    rows_below = yy - lowest
    wedge = np.where((rows_below > -2) & (np.abs(xx - 160) < 60), 1 - 0.6 * np.exp(-np.maximum(rows_below, 0) / 2), 1)
    soft = 1 - 0.15 * np.exp(-(((yy - 165) / 14.0) ** 2) - ((xx - 160) / 70.0) ** 2)
    brown = np.array([0.30, 0.24, 0.17])
    a = coverage[..., None]
    shot = a * brown + (1 - a) * backdrop() * (wedge * soft)[..., None]
    return with_noise(shot), with_noise(backdrop() * 1.015, seed=1), coverage >= 0.5, yy > np.ceil(lowest)


def test_a_steep_contact_shadow_under_a_stone_of_its_own_colour_is_told_apart_by_colour() -> None:
    # the shadow keeps the plate's colour and the stone does not, so the shadow field may learn from
    # plate-coloured pixels next to the stone; a grey stone gets no such licence (its rim is grey too)
    shot, plate, truth, below = brown_stone_over_a_steep_contact_shadow()
    mask = compute_mask(shot, plate)
    assert (mask & below).sum() <= 60  # half a row across the stone's 120 columns
    assert iou(mask, truth) >= 0.98
    by_brightness_only = compute_mask(shot, plate, MaskSettings(max_plate_coloured_stone=-1.0))
    assert (by_brightness_only & below).sum() >= 150


def test_edge_pixels_are_stone_where_the_stone_covers_at_least_half_of_them() -> None:
    # a dark stone's edge pixels all differ from the plate far more than from the stone, so the cut
    # alone takes every one of them; unmixing each against plate and stone reads its coverage
    coverage = coverage_ellipse()
    dark = np.array([0.08, 0.078, 0.074])
    shot = with_noise(coverage[..., None] * dark + (1 - coverage[..., None]) * backdrop())
    plate = with_noise(backdrop() * 1.015, seed=1)
    truth = coverage >= 0.5
    edge_pixels = int(((coverage > 0) & (coverage < 1)).sum())
    assert (compute_mask(shot, plate) != truth).sum() <= 0.05 * edge_pixels
    assert (compute_mask(shot, plate, MaskSettings(matte_boundary=False)) != truth).sum() >= 0.25 * edge_pixels


def test_the_matte_gives_edge_pixels_their_coverage_and_the_stone_its_own_colour_there() -> None:
    # training matches the stone alone on black: at an edge pixel that is coverage x stone colour,
    # while the shot also holds (1 - coverage) of the plate, which no multi-view model can fit
    coverage = coverage_ellipse()
    dark = np.array([0.08, 0.078, 0.074], dtype=np.float32)
    shot = with_noise(coverage[..., None] * dark + (1 - coverage[..., None]) * backdrop())
    plate = with_noise(backdrop() * 1.015, seed=1)
    matte = compute_matte(shot, plate)
    edge = (coverage > 0.05) & (coverage < 0.95)
    assert np.median(np.abs(matte.alpha[edge] - coverage[edge])) <= 0.1
    assert np.array_equal(matte.mask, compute_mask(shot, plate))
    assert np.all(matte.alpha[matte.mask] >= 0.5) and np.all(matte.alpha[coverage == 0] <= 0.5)
    assert np.all(matte.alpha[cv2.erode(matte.mask.astype(np.uint8), np.ones((3, 3))) > 0] == 1.0)
    alone = matte.alpha[..., None] * matte.foreground  # what the splats should render on black
    shot_masked = matte.mask[..., None] * shot  # what a 0/1 mask asked of them
    truth = coverage[..., None] * dark
    assert np.abs(alone - truth)[edge].mean() <= 0.6 * np.abs(shot_masked - truth)[edge].mean()
    plate_pixels = matte.alpha == 0
    assert plate_pixels.sum() > 0.8 * (coverage == 0).sum()
    assert np.all(matte.foreground[plate_pixels] == shot[plate_pixels])  # left as shot


def test_a_barely_covered_edge_pixel_takes_the_stones_colour_not_the_noise_divided_by_its_coverage() -> None:
    # solved for the stone's colour alone, the mix divides the shot's noise by the coverage: colours neither
    # stone nor plate has; with the solid stone beside it as a prior, the estimate stays the stone's
    coverage = coverage_ellipse(s=16).astype(np.float32)
    brown = np.array([0.30, 0.24, 0.17], dtype=np.float32)
    plate = backdrop()
    shot = with_noise(coverage[..., None] * brown + (1 - coverage[..., None]) * plate)
    colour = unmix(shot, plate, coverage, MaskSettings())
    thin, most = (coverage > 0) & (coverage < 0.15), (coverage > 0.85) & (coverage < 1)
    assert thin.sum() > 50 and most.sum() > 50
    assert np.abs(colour[thin] - brown).max() <= 0.03
    assert np.abs(colour[most] - brown).max() <= 0.03
    solid_or_absent = (coverage == 0) | (coverage == 1)
    assert np.array_equal(colour[solid_or_absent], shot[solid_or_absent])
    solved_alone = (shot - (1 - coverage[..., None]) * plate) / np.maximum(coverage, 1e-6)[..., None]
    assert np.abs(solved_alone[thin] - brown).max() >= 0.3


def test_a_matte_averaged_down_to_the_training_width_keeps_coverage_and_the_stones_own_colour() -> None:
    # a camera finer than the training images: a training pixel's coverage is the share of its
    # sub-pixels the stone covers, and its colour is the stone's alone, none of the plate's
    s = 8
    yy, xx = (np.mgrid[0:480 * s, 0:640 * s] + 0.5) / s - 0.5
    inside = ((yy - 240) / 90.6) ** 2 + ((xx - 320) / 121.4) ** 2 <= 1.0
    fine = inside.reshape(480, s, 640, s).mean(axis=(1, 3)).astype(np.float32)
    stone, backdrop_rgb = np.array([0.3, 0.2, 0.1], np.float32), np.array([0.5, 0.5, 0.48], np.float32)
    shot = fine[..., None] * stone + (1 - fine[..., None]) * backdrop_rgb
    partial = (fine > 0) & (fine < 1)
    matte = Matte(alpha=fine, foreground=np.where(partial[..., None], stone, shot).astype(np.float32))

    coarse = matte.downscaled(320)

    truth = cv2.resize(fine, (320, 240), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(coarse.alpha, truth, atol=1e-5)
    assert np.array_equal(coarse.mask, truth >= 0.5)
    edge = (coarse.alpha > 0) & (coarse.alpha < 1)
    assert edge.sum() > 300
    np.testing.assert_allclose(coarse.foreground[edge], np.tile(stone, (int(edge.sum()), 1)), atol=1e-5)
    plate_only = coarse.alpha == 0
    np.testing.assert_allclose(coarse.foreground[plate_only], np.tile(backdrop_rgb, (int(plate_only.sum()), 1)), atol=1e-5)
    assert matte.downscaled(640) is matte  # never upscaled


@pytest.mark.xfail(
    strict=True,
    reason="IoU 0.70: the lower half of this stone is smooth, grey and darker than the plate, so a smooth "
    "shadow field explains it as well as the stone does; only the edge to the shadow below tells them apart. "
    "The other rings' silhouette recovers it (test_cross_view.py)",
)
def test_pale_stone_whose_shaded_side_is_darker_than_the_backdrop() -> None:
    shot, plate, truth = synthetic_pair("pale", shading=0.15)
    assert iou(compute_mask(shot, plate), truth) >= 0.98


def test_shadow_field_continues_a_shadow_slope_under_the_stone() -> None:
    yy = np.mgrid[0:60, 0:80][0].astype(np.float32)
    darkening = -0.02 * yy  # log ratio: the shadow deepens down the frame
    background = np.ones((60, 80), dtype=bool)
    background[20:40, 30:50] = False  # where the stone hides the plate
    field = shadow_field(darkening, background, sigma_px=4.0)
    np.testing.assert_allclose(field[20:40, 30:50], darkening[20:40, 30:50], atol=0.005)


def reference_shadow_field(log_ratio: np.ndarray, background: np.ndarray, sigma_px: float) -> np.ndarray:
    """The shadow field the plain way: per pixel, numpy's float64 solve of its Gaussian-weighted plane fit."""
    radius = int(np.ceil(4 * sigma_px))
    offsets = np.arange(-radius, radius + 1, dtype=np.float64)
    dy, dx = np.meshgrid(offsets, offsets, indexing="ij")
    window = np.exp(-0.5 * (dx**2 + dy**2) / sigma_px**2)
    design = np.stack([np.ones_like(dx), dx, dy], axis=-1)  # [K, K, 3]: intercept and the two slopes
    weight = np.pad(background.astype(np.float64), radius)
    value = np.pad(np.where(background, log_ratio, 0.0).astype(np.float64), radius)
    field = np.zeros(background.shape)
    for y, x in np.ndindex(*background.shape):
        w = window * weight[y:y + 2 * radius + 1, x:x + 2 * radius + 1]
        if not w.sum() > 1e-3:
            continue
        normal = np.einsum("ij,ija,ijb->ab", w, design, design) + np.diag([0.0, 1.0, 1.0]) * 1e-2 * sigma_px**2 * w.sum()
        rhs = np.einsum("ij,ija->a", w * value[y:y + 2 * radius + 1, x:x + 2 * radius + 1], design)
        field[y, x] = min(np.linalg.solve(normal, rhs)[0], 0.0)
    return field


def test_shadow_field_matches_a_float64_solve_where_background_is_a_thin_line_or_a_few_far_pixels() -> None:
    # the hard cases of the plane fit: background along one line (the ridge alone keeps the normal equations
    # solvable) and pixels only just in reach (weight near the cut-off); the moments are filtered in float32
    yy, xx = np.mgrid[0:36, 0:44]
    darkening = (-0.5 - 0.02 * yy + 0.01 * xx).astype(np.float32)
    background = np.zeros((36, 44), dtype=bool)
    background[np.arange(36), np.arange(36) + 4] = True  # a diagonal line
    background[2, 40] = background[33, 1] = True  # and two strays far from it
    field = shadow_field(darkening, background, sigma_px=3.0)
    reference = reference_shadow_field(darkening, background, sigma_px=3.0)
    assert (reference < 0).sum() > 0.8 * reference.size  # the fit reaches most of the frame
    np.testing.assert_allclose(field, reference, atol=2e-4)  # log units: far below any plate's noise


def reference_cut_graph(evidence: np.ndarray, features: np.ndarray, smoothness: float,
                        fixed_background: np.ndarray) -> sparse.csr_array:
    """The graph cut's graph the plain way: numpy pair lists into scipy's COO (source n, sink n + 1)."""
    h, w = evidence.shape
    n = h * w
    index = np.arange(n).reshape(h, w)
    flat = features.reshape(n, -1).astype(np.float64)
    pairs = []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = index[: h - dy, max(0, -dx): w - max(0, dx)].ravel()
        b = index[dy:, max(0, dx): w + min(0, dx)].ravel()
        pairs.append((a, b, ((flat[a] - flat[b]) ** 2).sum(axis=1), np.hypot(dy, dx)))
    beta = 1.0 / (2.0 * np.mean(np.concatenate([p[2] for p in pairs])) + 1e-12)
    rows, cols, capacity = [], [], []
    for a, b, squared, distance in pairs:
        weight = np.rint(_NATS_TO_CAPACITY * smoothness * np.exp(-beta * squared) / distance) + 1
        rows += [a, b]
        cols += [b, a]
        capacity += [weight, weight]
    nats = np.clip(evidence.ravel(), -_MAX_NATS, _MAX_NATS)
    to_background = np.where(fixed_background.ravel(), np.rint(_NATS_TO_CAPACITY * (_MAX_NATS + 8 * smoothness)) + 8,
                             np.rint(_NATS_TO_CAPACITY * np.maximum(-nats, 0.0)))
    rows += [np.full(n, n), index.ravel()]
    cols += [index.ravel(), np.full(n, n + 1)]
    capacity += [np.rint(_NATS_TO_CAPACITY * np.maximum(nats, 0.0)), to_background]
    return sparse.csr_array((np.concatenate(capacity).astype(np.int32), (np.concatenate(rows), np.concatenate(cols))),
                            shape=(n + 2, n + 2))


@pytest.mark.parametrize("case", ["disc", "no stone", "all stone but the frame", "textureless"])
def test_the_graph_cut_is_a_minimum_cut_of_the_plain_graph(case: str) -> None:
    rng = np.random.default_rng(3)
    h, w = 41, 53
    yy, xx = np.mgrid[0:h, 0:w]
    disc = (yy - 20) ** 2 + (xx - 27) ** 2 < 12**2
    evidence = {"disc": np.where(disc, 2.0, -2.0) + rng.normal(0, 2.5, (h, w)), "no stone": -np.ones((h, w)),
                "all stone but the frame": np.full((h, w), 60.0), "textureless": np.where(disc, 5.0, -5.0)}[case]
    features = rng.normal(0, 1, (h, w, 3)).astype(np.float32) + 4 * disc[..., None]
    features = np.zeros_like(features) if case == "textureless" else features
    frame = np.ones((h, w), bool)
    frame[1:-1, 1:-1] = False

    stone = min_cut(evidence, features, 9.0, frame)

    graph = reference_cut_graph(evidence, features, 9.0, frame)
    best = maximum_flow(graph, h * w, h * w + 1).flow_value
    source_side = np.append(stone.ravel(), [True, False])
    coo = graph.tocoo()
    cut = coo.data[source_side[coo.row] & ~source_side[coo.col]].astype(np.int64).sum()
    assert cut == best
    assert not stone[frame].any()
    assert {"no stone": not stone.any(), "all stone but the frame": stone[~frame].all()}.get(case, iou(stone, disc) > 0.8)


def test_fill_holes_fills_what_scipy_fills_to_the_pixel() -> None:
    """Holes only 8-connected to the outside are holes (the background is 4-connected), and a region open to the
    frame's edge is not a hole."""
    rng = np.random.default_rng(0)
    ring = np.zeros((9, 9), dtype=bool)
    ring[2:7, 2:7], ring[3:6, 3:6] = True, False
    open_at_edge = ring.copy()
    open_at_edge[4, :3] = False
    corner_leak = ring.copy()
    corner_leak[2, 2] = False  # the hole touches the outside at a corner only
    cases = [ring, open_at_edge, corner_leak, np.zeros((5, 7), bool), np.ones((5, 7), bool), np.ones((1, 1), bool),
             *(rng.random((48, 64)) < share for share in (0.3, 0.55, 0.6, 0.7, 0.9))]
    for mask in cases:
        np.testing.assert_array_equal(fill_holes(mask), ndimage.binary_fill_holes(mask))
    assert fill_holes(ring).sum() == 25 and fill_holes(corner_leak).sum() == 24


def test_frames_larger_than_the_working_size_are_masked_there_and_resized_back() -> None:
    shot, plate, truth = synthetic_pair("speckled")
    big_shot, big_plate = (cv2.resize(x, (640, 480), interpolation=cv2.INTER_NEAREST) for x in (shot, plate))
    big_truth = cv2.resize(truth.astype(np.uint8), (640, 480), interpolation=cv2.INTER_NEAREST).astype(bool)
    mask = compute_mask(big_shot, big_plate, MaskSettings(max_working_side=320))
    assert mask.shape == (480, 640) and mask.dtype == bool
    assert iou(mask, big_truth) >= 0.98


def test_shot_equal_to_plate_gives_an_empty_mask_that_the_check_flags() -> None:
    _, plate, _ = synthetic_pair("dark")
    rng = np.random.default_rng(3)
    shot = (plate * 0.99 + rng.normal(0, 0.003, plate.shape)).astype(np.float32)
    mask = compute_mask(shot, plate)
    assert mask.mean() < 0.002
    (check,) = check_masks([mask], ["empty.png"])
    assert not check.ok and "empty" in check.reasons[0]


def test_mismatched_shot_and_plate_sizes_are_refused() -> None:
    with pytest.raises(BadInputError):
        compute_mask(np.zeros((10, 10, 3), np.float32), np.zeros((12, 10, 3), np.float32))


def test_check_passes_a_plausible_ring() -> None:
    ring = [ellipse(rx=60 + 3 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    checks = check_masks(ring, [f"v{i}" for i in range(8)])
    assert all(c.ok for c in checks), [c.reasons for c in checks]


def test_check_flags_area_jump_border_contact_and_full_frame() -> None:
    ring = [ellipse() for _ in range(6)]
    ring[2] = ellipse(rx=20, ry=15)  # a view lost most of the stone
    ring[4] = ellipse(cx=20)  # cut by the left frame edge
    full = np.ones((240, 320), dtype=bool)
    checks = check_masks(ring + [full], [f"v{i}" for i in range(7)])
    assert any("jumps" in r for r in checks[2].reasons)
    assert any("border" in r for r in checks[4].reasons)
    assert any("fills the frame" in r for r in checks[6].reasons)
    assert checks[1].ok and checks[3].ok


# -- simulated stone world (sim/) -------------------------------------------------------------

sim_scene = pytest.importorskip("sim.scene")


def _sim_pair(look: str, elevation: float, folder: Path, size: tuple[int, int] = (640, 480)):
    from sim.dng import dng_bytes
    from sim.sensor import SensorModel
    from sim.stone import procedural_stone
    from station.process.develop import DevelopSettings, develop_raw
    from station.rig_geometry import RigGeometry

    sensor = SensorModel()
    world = sim_scene.World(procedural_stone(3, look=look), rig=RigGeometry().scaled(*size))
    shot = sim_scene.render(world, elevation, 90.0, stone_present=True)
    plate = sim_scene.render(world, elevation, 90.0, stone_present=False)
    rng = np.random.default_rng(1)
    out = []
    for radiance, name in ((shot.radiance, "shot"), (plate.radiance * 1.015, "plate")):
        data = dng_bytes(sensor.expose(radiance, 0.01, 100, rng), sensor)
        path = folder / f"{look}-{name}.dng"
        path.write_bytes(data)
        out.append(develop_raw(path, DevelopSettings()).linear)
    return out[0], out[1], shot.mask


def _true_mask(seed: int, look: str, size: tuple[int, int], elevation: float, azimuth: float) -> np.ndarray:
    """The true mask of a procedural stone seen at `size`, 16 samples a pixel."""
    from sim.stone import procedural_stone
    from station.rig_geometry import RigGeometry

    world = sim_scene.World(procedural_stone(seed, look=look), rig=RigGeometry().scaled(*size))
    return sim_scene.render(world, elevation, azimuth, stone_present=True, supersample=4).mask


@pytest.mark.slow
@pytest.mark.parametrize("look", ["dark", "pale", "speckled"])
def test_sim_stone_mask_iou_meets_the_issue_target(look: str, tmp_path: Path) -> None:
    # as a scan on a camera finer than the training images is masked: cut at 640x480, averaged to 320x240
    shot, plate, _ = _sim_pair(look, 45.0, tmp_path)
    assert iou(compute_matte(shot, plate).downscaled(320).mask, _true_mask(3, look, (320, 240), 45.0, 90.0)) >= 0.98


def _small_scan(folder: Path, size: tuple[int, int] = (320, 240)) -> tuple[ScanFolder, dict[str, tuple[float, float]]]:
    """A plate and four shots of a dark stone at 40 deg (one at twice the exposure) and a corrupt raw;
    with the (elevation, azimuth) of each shot."""
    from sim.dng import dng_bytes
    from sim.sensor import SensorModel
    from sim.stone import procedural_stone
    from station.rig_geometry import RigGeometry

    scan = ScanFolder(folder)
    sensor = SensorModel()
    world = sim_scene.World(procedural_stone(7, look="dark"), rig=RigGeometry().scaled(*size))
    rng = np.random.default_rng(0)
    entries, views = [], {}
    for azimuth in (None, 0.0, 90.0, 180.0, 270.0):
        out = sim_scene.render(world, 40.0, azimuth or 0.0, stone_present=azimuth is not None)
        exposure = 0.01 if azimuth != 90.0 else 0.02  # one frame shot at twice the exposure
        data = dng_bytes(sensor.expose(out.radiance, exposure, 100, rng), sensor)
        name = f"raw/{'plate' if azimuth is None else f'shot_{int(azimuth):03d}'}.dng"
        atomic_write_bytes(scan.root / name, data)
        kind = "plate" if azimuth is None else "shot"
        entries.append(ManifestEntry(name, sha256_bytes(data), 40.0, azimuth or 0.0, kind, exposure, 100, ""))
        if azimuth is not None:
            views[Path(name).stem] = (40.0, azimuth)
    corrupt = b"II*\x00" + b"\x00" * 64
    atomic_write_bytes(scan.root / "raw/broken.dng", corrupt)
    entries.append(ManifestEntry("raw/broken.dng", sha256_bytes(corrupt), 40.0, 45.0, "shot", 0.01, 100, ""))
    scan.write_manifest(entries)
    return scan, views


@pytest.mark.slow
def test_develop_scan_writes_images_exrs_and_masks_and_flags_a_corrupt_raw(tmp_path: Path) -> None:
    from station.process.develop_stage import develop_scan

    scan, views = _small_scan(tmp_path / "scan")
    report = develop_scan(scan)

    frames = {f.file: f for f in report.frames}
    assert any(flag.startswith("unreadable") for flag in frames["raw/broken.dng"].flags)
    assert frames["raw/shot_090.dng"].exposure_scale == pytest.approx(0.5)
    linear = {}
    for stem, (elevation, azimuth) in views.items():
        assert read_png16(scan.images_dir / f"{stem}.png").shape == (240, 320, 3)
        linear[stem] = read_exr(scan.images_linear_dir / f"{stem}.exr")
        assert iou(read_mask_png(scan.masks_dir / f"{stem}.png"), _true_mask(7, "dark", (320, 240), elevation, azimuth)) >= 0.97
    # exposure normalisation: the doubled exposure lands on the same backdrop level
    corner = (slice(0, 20), slice(0, 20))
    ratio = linear["shot_090"][corner].mean() / linear["shot_000"][corner].mean()
    assert ratio == pytest.approx(1.0, abs=0.03)
    assert len(report.usable_shots) == 4


@pytest.mark.slow
def test_develop_scan_cuts_masks_at_the_cameras_size_and_averages_them_down_to_the_training_width(tmp_path: Path) -> None:
    from station.process.develop_stage import ProcessSettings, develop_scan

    scan, views = _small_scan(tmp_path / "scan", size=(640, 480))
    report = develop_scan(scan, ProcessSettings(training_width=320))

    assert len(report.usable_shots) == 4
    for stem, (elevation, azimuth) in views.items():
        assert read_png16(scan.images_dir / f"{stem}.png").shape == (240, 320, 3)
        assert read_exr(scan.images_linear_dir / f"{stem}.exr").shape == (480, 640, 3)  # radiometry as developed
        mask = read_mask_png(scan.masks_dir / f"{stem}.png")
        assert iou(mask, _true_mask(7, "dark", (320, 240), elevation, azimuth)) >= 0.98


def test_develop_scan_in_worker_processes_writes_what_one_process_writes(tmp_path: Path) -> None:
    from station.process.develop_stage import ProcessSettings, develop_scan

    reports = {}
    for workers in (1, 2):
        scan, _ = _small_scan(tmp_path / f"scan{workers}")
        report = develop_scan(scan, ProcessSettings(workers=workers)).to_json()
        timeless = {k: v for k, v in report.items() if k not in ("seconds", "matte_seconds")}
        reports[workers] = json.dumps(timeless).replace(f"scan{workers}", "scan")  # a flag names the broken raw
    assert reports[2] == reports[1]
    for folder in ("images", "masks", "images_linear"):
        one, two = sorted((tmp_path / "scan1" / folder).iterdir()), sorted((tmp_path / "scan2" / folder).iterdir())
        assert [f.name for f in two] == [f.name for f in one] and len(one) >= 4
        assert all(a.read_bytes() == b.read_bytes() for a, b in zip(one, two)), folder


def test_shots_are_developed_in_as_many_processes_as_omp_num_threads_allows(monkeypatch) -> None:
    from station.process.workers import available_cores

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert available_cores() == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert available_cores() == len(os.sched_getaffinity(0))


def test_a_training_width_below_one_pixel_is_refused() -> None:
    from station.process.develop_stage import ProcessSettings

    with pytest.raises(BadInputError, match="training width 0"):
        ProcessSettings(training_width=0)


@pytest.mark.slow
def test_a_speckled_stone_cut_at_twice_the_training_size_beats_a_cut_at_the_training_size(tmp_path: Path) -> None:
    # cut at the training size itself, the stone's one-pixel rim, shaded near the plate's colour, is
    # read as background; cut on a camera twice as fine, the doubtful rim is half as wide
    truth = _true_mask(3, "speckled", (320, 240), 45.0, 90.0)
    fine_shot, fine_plate, _ = _sim_pair("speckled", 45.0, tmp_path, size=(640, 480))
    shot, plate, _ = _sim_pair("speckled", 45.0, tmp_path, size=(320, 240))

    averaged = iou(compute_matte(fine_shot, fine_plate).downscaled(320).mask, truth)
    assert averaged >= iou(compute_mask(shot, plate), truth) + 0.005  # measured: 0.985 against 0.972


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_column_medians_equal_numpys_median_to_the_bit(dtype):
    rng = np.random.default_rng(4)
    for rows in (1, 2, 3, 10, 11, 61_596):
        values = rng.normal(size=(rows, 3)).astype(dtype)
        values[rows // 3] = values[0]  # ties
        np.testing.assert_array_equal(column_medians(values), np.median(values, axis=0))
        assert column_medians(values).dtype == dtype
