"""The simulated camera's DNG: LibRaw must read back exactly what the sensor produced."""

from __future__ import annotations

import io

import numpy as np
import pytest
import tifffile

from sim.dng import dng_bytes, read_dng
from sim.sensor import SRGB_TO_XYZ, SensorModel
from station.errors import BadInputError

pytestmark = pytest.mark.no_kernels


@pytest.fixture(scope="module")
def sensor() -> SensorModel:
    return SensorModel()


def test_libraw_returns_the_mosaic_bit_exactly(sensor):
    rng = np.random.default_rng(7)
    mosaic = rng.integers(0, sensor.white_level + 1, size=(120, 160)).astype(np.uint16)
    info = read_dng(dng_bytes(mosaic, sensor))
    assert info.raw_image.dtype == np.uint16
    np.testing.assert_array_equal(info.raw_image, mosaic)


def test_a_sensor_exposure_survives_the_round_trip(sensor):
    radiance = np.random.default_rng(1).uniform(0.0, 1.2, size=(64, 96, 3)).astype(np.float32)
    mosaic = sensor.expose(radiance, 0.01, 100, np.random.default_rng(2))
    np.testing.assert_array_equal(read_dng(dng_bytes(mosaic, sensor)).raw_image, mosaic)


def test_libraw_sees_rggb_and_the_levels(sensor):
    info = read_dng(dng_bytes(np.full((64, 64), 600, np.uint16), sensor))
    assert info.raw_pattern.tolist() == [[0, 1], [3, 2]]  # R G / G2 B
    assert info.black_level == sensor.black_level
    assert info.white_level == sensor.white_level


def test_camera_white_balance_is_the_inverse_as_shot_neutral(sensor):
    info = read_dng(dng_bytes(np.full((64, 64), 600, np.uint16), sensor))
    expected = 1.0 / sensor.camera_neutral()
    np.testing.assert_allclose(info.camera_whitebalance[:3] / info.camera_whitebalance[1], expected, rtol=1e-4)


def test_libraw_colour_matrix_inverts_the_xyz_to_camera_matrix(sensor):
    """LibRaw builds camera->sRGB from ColorMatrix1 by normalising the sRGB->camera rows and inverting."""
    info = read_dng(dng_bytes(np.full((64, 64), 600, np.uint16), sensor))
    srgb_to_camera = sensor.xyz_to_camera @ SRGB_TO_XYZ
    srgb_to_camera /= srgb_to_camera.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(info.color_matrix[:, :3], np.linalg.inv(srgb_to_camera), atol=1e-4)


def test_the_dng_tags_are_the_ones_rig_md_lists(sensor):
    with tifffile.TiffFile(io.BytesIO(dng_bytes(np.zeros((64, 64), np.uint16), sensor, camera_model="bench"))) as tif:
        tags = tif.pages[0].tags
        assert tags[262].value == 32803  # PhotometricInterpretation = CFA
        assert tuple(tags[33421].value) == (2, 2)
        assert bytes(tags[33422].value) == bytes([0, 1, 1, 2])
        assert bytes(tags[50706].value) == bytes([1, 4, 0, 0])
        assert tags[50708].value == "bench"
        assert tags[50778].value == 21
        assert tags[50721].dtype == 10  # SRATIONAL


def test_writer_refuses_a_mosaic_that_is_not_uint16(sensor):
    with pytest.raises(BadInputError, match="uint16"):
        dng_bytes(np.zeros((64, 64), np.float32), sensor)


def test_reader_refuses_garbage_bytes():
    with pytest.raises(BadInputError, match="LibRaw"):
        read_dng(b"not a raw file at all" * 100, source="junk.dng")


def test_reader_refuses_a_dng_without_black_level(sensor):
    """LibRaw decodes it silently with black 0; the reader must not."""
    buffer = io.BytesIO()
    extratags = [
        (33421, 3, 2, (2, 2), True),
        (33422, 1, 4, (0, 1, 1, 2), True),
        (50706, 1, 4, (1, 4, 0, 0), True),
        (50708, 2, 0, "station-sim", True),
        (50717, 4, 1, 16383, True),
    ]
    tifffile.imwrite(buffer, np.full((64, 64), 600, np.uint16), photometric=32803, extratags=extratags, metadata=None)
    with pytest.raises(BadInputError, match="black level"):
        read_dng(buffer.getvalue(), source="noblack.dng")
