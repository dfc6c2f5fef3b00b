"""Raw develop: linear and reproducible, typed errors for bad raws, flags for unusable frames."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import rawpy
import tifffile

from station.errors import BadInputError
from station.process.colour import (
    black_level_from_neutrals,
    locate_and_fit_chart,
    white_balance_from_linear,
)
from station.process.develop import (
    BayerSpec,
    DevelopSettings,
    WhiteBalance,
    demosaic_bilinear_ea,
    develop_mosaic,
    develop_raw,
    downscale_area,
    estimate_black_level,
    load_bayer,
)
from station.process.images_io import read_exr, read_mask_png, read_png16, write_exr_half, write_mask_png, write_png16

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "raw"
UNIT = WhiteBalance((1.0, 1.0, 1.0), source="unit")
# XYZ -> camera of a Canon G2 (LibRaw's table), a realistic non-identity ColorMatrix1
XYZ_TO_CAM = np.array([[0.9194, -0.2787, -0.1059], [-0.8098, 1.5657, 0.2608], [-0.261, 0.3064, 0.7867]])
RGGB = np.array([[0, 1], [1, 2]])


def _rationals(values) -> list[int]:
    out = []
    for v in np.ravel(values):
        f = Fraction(float(v)).limit_denominator(10000)
        out += [f.numerator, f.denominator]
    return out


def write_dng(path: Path, mosaic: np.ndarray, black: int = 256, white: int = 4095, omit: tuple[int, ...] = ()) -> Path:
    """A minimal DNG 1.4 from an RGGB mosaic (rig.md's tag table); `omit` drops tags by id."""
    tags = [
        (33421, 3, 2, (2, 2), True),
        (33422, 1, 4, (0, 1, 1, 2), True),
        (50706, 1, 4, (1, 4, 0, 0), True),
        (50708, 2, 0, "test-cam", True),
        (50714, 4, 1, black, True),
        (50717, 4, 1, white, True),
        (50721, 10, 9, _rationals(XYZ_TO_CAM), True),
        (50728, 5, 3, _rationals([0.5, 1.0, 0.7]), True),
        (50778, 3, 1, 21, True),
    ]
    tags = [t for t in tags if t[0] not in omit]
    tifffile.imwrite(path, mosaic.astype(np.uint16), photometric=32803, subfiletype=0, extratags=tags, metadata=None)
    return path


def mosaic_of(rgb: np.ndarray, black: int = 256, white: int = 4095, pattern: np.ndarray = RGGB) -> np.ndarray:
    """[H, W, 3] in [0, 1] (1 = white level) -> [H, W] raw values with black level."""
    m = np.zeros(rgb.shape[:2])
    for y in range(2):
        for x in range(2):
            m[y::2, x::2] = rgb[y::2, x::2, pattern[y, x]]
    return np.clip(np.round(m * (white - black) + black), 0, white)


def flat(rgb, h: int = 64, w: int = 96) -> np.ndarray:
    return np.broadcast_to(np.asarray(rgb, dtype=float), (h, w, 3)).copy()


def test_develop_is_linear_in_exposure_and_scaled_to_the_white_level(tmp_path: Path) -> None:
    settings = DevelopSettings(output_space="camera")
    one = develop_raw(write_dng(tmp_path / "a.dng", mosaic_of(flat([0.1, 0.2, 0.15]))), settings, UNIT)
    two = develop_raw(write_dng(tmp_path / "b.dng", mosaic_of(flat([0.2, 0.4, 0.3]))), settings, UNIT)
    np.testing.assert_allclose(one.linear[20:40, 20:40].mean(axis=(0, 1)), [0.1, 0.2, 0.15], atol=1e-3)
    np.testing.assert_allclose(two.linear[20:40, 20:40] / one.linear[20:40, 20:40], 2.0, rtol=0.02)


def test_white_balance_gains_multiply_camera_channels_even_below_one(tmp_path: Path) -> None:
    path = write_dng(tmp_path / "a.dng", mosaic_of(flat([0.2, 0.4, 0.3])))
    out = develop_raw(path, DevelopSettings(output_space="camera"), WhiteBalance((0.5, 1.0, 1.5), "test"))
    np.testing.assert_allclose(out.linear[30, 40], [0.1, 0.4, 0.45], atol=2e-3)


def test_srgb_output_matches_libraws_own_matrix_from_the_dng(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    path = write_dng(tmp_path / "a.dng", mosaic_of(flat(rng.uniform(0.05, 0.5, 3))))
    ours = develop_raw(path, DevelopSettings(), UNIT)
    with rawpy.imread(str(path)) as raw:
        ref = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, adjust_maximum_thr=0.0,
                              user_wb=[1, 1, 1, 1], user_flip=0) / 65535.0
    assert ours.matrix_source == "file"
    np.testing.assert_allclose(ours.linear[30, 40], ref[30, 40], atol=2e-3)


@pytest.mark.parametrize(("omit", "named"), [(50714, "BlackLevel"), (33422, "CFA")])
def test_dng_missing_black_level_or_cfa_pattern_is_refused_by_name(tmp_path: Path, omit: int, named: str) -> None:
    path = write_dng(tmp_path / "bad.dng", mosaic_of(flat([0.2, 0.2, 0.2])), omit=(omit,))
    with pytest.raises(BadInputError, match=rf"bad\.dng.*{named}"):
        develop_raw(path, DevelopSettings(), UNIT)


def test_missing_truncated_and_garbage_raws_raise_bad_input_naming_the_file(tmp_path: Path) -> None:
    good = write_dng(tmp_path / "good.dng", mosaic_of(flat([0.2, 0.2, 0.2])))
    truncated = tmp_path / "truncated.dng"
    truncated.write_bytes(good.read_bytes()[:300])
    garbage = tmp_path / "garbage.cr2"
    garbage.write_bytes(np.random.default_rng(0).bytes(5000))
    for path in (tmp_path / "absent.dng", truncated, garbage):
        with pytest.raises(BadInputError, match=path.name):
            develop_raw(path, DevelopSettings(), UNIT)


def test_black_and_saturated_frames_are_flagged_not_raised(tmp_path: Path) -> None:
    black = develop_raw(write_dng(tmp_path / "k.dng", mosaic_of(flat([0.001] * 3))), DevelopSettings(), UNIT)
    burnt = develop_raw(write_dng(tmp_path / "s.dng", mosaic_of(flat([1.0] * 3))), DevelopSettings(), UNIT)
    part = flat([0.3] * 3)
    part[:, :10] = 1.0  # about 10% of the frame clipped
    clipped = develop_raw(write_dng(tmp_path / "p.dng", mosaic_of(part)), DevelopSettings(), UNIT)
    assert "black" in black.flags
    assert "saturated" in burnt.flags and burnt.clipped_fraction > 0.99
    assert "highlights_clipped" in clipped.flags and clipped.clipped_fraction == pytest.approx(10 / 96, abs=0.01)


def test_area_downscale_averages_instead_of_aliasing() -> None:
    checker = (np.indices((64, 96)).sum(axis=0) % 2).astype(np.float32)
    small = downscale_area(np.repeat(checker[..., None], 3, axis=2), max_width=48)
    assert small.shape == (32, 48, 3)
    np.testing.assert_allclose(small, 0.5, atol=1e-6)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_headerless_bayer_patterns_demosaic_to_the_right_colours(tmp_path: Path, pattern: str) -> None:
    index = {"RGGB": [[0, 1], [1, 2]], "BGGR": [[2, 1], [1, 0]], "GRBG": [[1, 0], [2, 1]], "GBRG": [[1, 2], [0, 1]]}
    mosaic = mosaic_of(flat([0.2, 0.5, 0.8]), black=64, white=4095, pattern=np.array(index[pattern]))
    path = tmp_path / "dump.raw"
    mosaic.astype("<u2").tofile(path)
    spec = BayerSpec(96, 64, pattern, (64.0,) * 4, 4095)
    rgb = demosaic_bilinear_ea(load_bayer(path, spec))
    np.testing.assert_allclose(rgb[30, 40], [0.2, 0.5, 0.8], atol=2e-3)


def test_headerless_bayer_of_the_wrong_size_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "short.raw"
    path.write_bytes(b"\x00" * 100)
    with pytest.raises(BadInputError, match="short.raw"):
        load_bayer(path, BayerSpec(96, 64, "RGGB", (0.0,) * 4, 4095))


def test_white_balance_from_a_neutral_plate_makes_the_backdrop_grey(tmp_path: Path) -> None:
    yy = np.linspace(0.6, 1.0, 64)[:, None, None]  # vignetting-like falloff
    camera_grey = np.array([0.25, 0.5, 0.35])  # a neutral backdrop as a camera with weak R and B sees it
    plate = develop_raw(write_dng(tmp_path / "p.dng", mosaic_of(flat(camera_grey) * yy)),
                        DevelopSettings(output_space="camera"), UNIT)
    wb = white_balance_from_linear(plate.linear, source="p.dng")
    balanced = develop_raw(tmp_path / "p.dng", DevelopSettings(output_space="camera"), wb).linear[40, 40]
    np.testing.assert_allclose(balanced / balanced[1], 1.0, atol=0.01)


def test_images_round_trip_png16_half_exr_and_masks(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    linear = rng.uniform(0, 1, (24, 32, 3)).astype(np.float32)
    write_png16(tmp_path / "a.png", linear)
    write_exr_half(tmp_path / "a.exr", linear * 4.0)  # linear EXR keeps values above 1
    write_mask_png(tmp_path / "m.png", linear[..., 0] > 0.5)
    np.testing.assert_allclose(read_png16(tmp_path / "a.png"), linear, atol=1e-4)
    np.testing.assert_allclose(read_exr(tmp_path / "a.exr"), linear * 4.0, rtol=1e-3)
    with OpenEXR.File(str(tmp_path / "a.exr")) as exr:
        assert exr.channels()["RGB"].pixels.dtype == np.float16
    np.testing.assert_array_equal(read_mask_png(tmp_path / "m.png"), linear[..., 0] > 0.5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.png", "m.png"]  # no temp files left


# -- real raws ---------------------------------------------------------------------------------


@pytest.mark.shared_data
def test_real_canon_crw_develops_like_libraw_srgb() -> None:
    path = DATA / "RAW_CANON_G2.CRW"
    if not path.is_file():
        pytest.skip("shared data absent")
    ours = develop_raw(path, DevelopSettings())
    with rawpy.imread(str(path)) as raw:
        ref = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, adjust_maximum_thr=0.0,
                              use_camera_wb=True, user_flip=0) / 65535.0
    assert ours.matrix_source == "libraw_table" and ours.linear.shape == ref.shape
    np.testing.assert_allclose(ours.linear[800:900, 1000:1100].mean((0, 1)), ref[800:900, 1000:1100].mean((0, 1)),
                               rtol=2e-3)


@pytest.mark.shared_data
def test_real_kodak_kdc_without_colour_matrix_develops_and_says_so() -> None:
    path = DATA / "RAW_KODAK_DC50.KDC"
    if not path.is_file():
        pytest.skip("shared data absent")
    out = develop_raw(path, DevelopSettings(max_width=384))
    assert out.linear.shape == (256, 384, 3) and np.isfinite(out.linear).all()
    assert "no_colour_matrix" in out.flags and out.linear.mean() > 0.01


@pytest.mark.shared_data
def test_real_colorchecker_capture_is_located_and_corrected_to_low_delta_e() -> None:
    path = DATA / "infiniteisp_ColorCheckerRAW_1920x1080_12bit_BGGR.raw"
    if not path.is_file():
        pytest.skip("shared data absent")
    # black level is not stated: develop without one, fit it on the chart's neutrals, develop again
    first = load_bayer(path, BayerSpec(1920, 1080, "BGGR", (0.0,) * 4, 4095))
    uncorrected = develop_mosaic(first, DevelopSettings(output_space="camera"), UNIT)
    r, g, b = black_level_from_neutrals(locate_and_fit_chart(uncorrected.linear).measured) * 4095
    assert all(50 < level < 300 for level in (r, g, b))
    assert max(estimate_black_level(first.data)) < 300  # the percentile estimate agrees in range
    mosaic = load_bayer(path, BayerSpec(1920, 1080, "BGGR", (b, g, g, r), 4095))
    fit = locate_and_fit_chart(develop_mosaic(mosaic, DevelopSettings(output_space="camera"), UNIT).linear)
    print(f"ColorChecker mean dE00: {fit.delta_e_before:.2f} white-balanced -> {fit.delta_e_after:.2f} 3x3 (Cheung)")
    assert fit.delta_e_after < 4.5
    assert fit.delta_e_after < 0.5 * fit.delta_e_before
    assert fit.centres.shape == (24, 2)
    # the white patch (chart reading order 19) is the brightest neutral, so orientation is right
    assert np.argmax(fit.measured[18:24].sum(axis=1)) == 0


def test_simulated_chart_develops_within_delta_e_2_of_truth(tmp_path: Path) -> None:
    scene = pytest.importorskip("sim.scene")
    from sim.dng import dng_bytes
    from sim.sensor import SensorModel
    from sim.stone import procedural_stone
    from station.rig_geometry import RigGeometry

    sensor = SensorModel()
    world = scene.World(procedural_stone(3), rig=RigGeometry().scaled(640, 480))
    plate = scene.render(world, 15.0, 0.0, stone_present=False, supersample=1)
    path = tmp_path / "plate.dng"
    path.write_bytes(dng_bytes(sensor.expose(plate.radiance, 0.01, 100, np.random.default_rng(0)), sensor))
    unit = develop_raw(path, DevelopSettings(output_space="camera"), UNIT)
    wb = white_balance_from_linear(unit.linear, source="plate.dng")
    np.testing.assert_allclose(np.array(wb.gains) * sensor.camera_neutral(), 1.0, atol=0.02)
    fit = locate_and_fit_chart(develop_raw(path, DevelopSettings(), wb).linear)
    # camera matrix + backdrop white balance, exposure scaled on the neutrals; no chart correction
    assert fit.delta_e_before <= 2.0
