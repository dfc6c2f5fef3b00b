"""station.formats and the model-file loader: one validator per format, each naming the file and field."""

from __future__ import annotations

import json
import math
import struct
import zlib

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from station.errors import CheckpointError, FormatError, InputTooLargeError, StationError
from station.formats.colmap import check_colmap_binary
from station.formats.images import ImageLimits, checked_size, open_pil, read_cv2
from station.formats.jsonfile import parse_json, read_json_object
from station.formats.manifest import read_manifest_records
from station.formats.transforms import parse_transforms, pinhole, shared_pinhole
from station.ngs.checkpoint_io import load_infill_file, load_surface_file, load_training_checkpoint
from station.scanfolder import ManifestEntry, ScanFolder, sha256_bytes

pytestmark = pytest.mark.no_kernels

W, H = 64, 48
C2W = np.array([[1.0, 0, 0, 0.1], [0, 0, -1, -2.0], [0, 1, 0, 0.3], [0, 0, 0, 1]])


def transforms(**change) -> dict:
    data = {"fl_x": 60.0, "fl_y": 60.0, "cx": 32.0, "cy": 24.0, "w": W, "h": H,
            "frames": [{"file_path": "images/a.png", "transform_matrix": C2W.tolist()}]}
    data.update(change)
    return data


def test_a_sound_transforms_file_parses_to_one_pinhole_camera_and_rigid_poses():
    doc = parse_transforms(transforms(k1=0.0, camera_model="OPENCV"), "t.json")
    cam = shared_pinhole(doc)
    assert (cam.width, cam.height, cam.fx, cam.cy) == (W, H, 60.0, 24.0)
    np.testing.assert_array_equal(doc.frames[0].c2w_gl, C2W)


@pytest.mark.parametrize("value", [0, -60.0, 1e-30, True, "60", [60], None, math.nan, math.inf, 1e12])
def test_an_implausible_focal_length_is_refused_naming_the_field(value):
    with pytest.raises(FormatError, match=r"t\.json: fl_x: "):
        shared_pinhole(parse_transforms(transforms(fl_x=value), "t.json"))


@pytest.mark.parametrize("rot, why", [(np.diag([1.0, 1, -1]), "mirrored"), (np.eye(3) * 1.5, "scaled"),
                                      (np.zeros((3, 3)), "singular")])
def test_mirrored_scaled_and_singular_poses_are_refused(rot, why):
    mat = C2W.copy()
    mat[:3, :3] = rot
    frames = [{"file_path": "images/a.png", "transform_matrix": mat.tolist()}]
    with pytest.raises(FormatError, match=rf"frames\[0\]\.transform_matrix: upper 3x3 is not a rotation.*{why}"):
        parse_transforms(transforms(frames=frames), "t.json")


@pytest.mark.parametrize("change, field", [({"w": "abc"}, "w"), ({"k1": [1]}, "k1"), ({"k1": 0.1}, "k1"),
                                           ({"frames": [{"file_path": 5}]}, r"frames\[0\]\.file_path"),
                                           ({"frames": [{"file_path": "a.png", "mask_path": 5,
                                                         "transform_matrix": C2W.tolist()}]}, r"frames\[0\]\.mask_path"),
                                           ({"camera_model": "OPENCV_FISHEYE"}, "camera_model")])
def test_wrong_json_types_name_the_field(change, field):
    with pytest.raises(FormatError, match=rf"t\.json: {field}: "):
        parse_transforms(transforms(**change), "t.json")


def test_per_frame_intrinsics_override_the_files_and_differing_ones_need_every_frame_read_alone():
    frames = [{"file_path": "a.png", "transform_matrix": C2W.tolist()},
              {"file_path": "b.png", "transform_matrix": C2W.tolist(), "fl_x": 70.0}]
    doc = parse_transforms(transforms(frames=frames), "t.json")
    assert pinhole(doc.frames[1].camera, "t.json").fx == 70.0 and pinhole(doc.frames[0].camera, "t.json").fx == 60.0
    with pytest.raises(FormatError, match="different intrinsics"):
        shared_pinhole(doc)


@given(st.one_of(st.none(), st.booleans(), st.text(max_size=5), st.lists(st.integers(), max_size=2),
                 st.floats(max_value=0.0), st.floats(min_value=1e9), st.just(math.nan), st.just(1e-30)))
@settings(max_examples=200, deadline=None)
def test_no_malformed_focal_value_survives_the_parser(value):
    for key in ("fl_x", "fl_y"):
        with pytest.raises(FormatError, match=key):
            shared_pinhole(parse_transforms(transforms(**{key: value}), "t.json"))


@given(st.lists(st.floats(-10, 10), min_size=9, max_size=9))
@settings(max_examples=200, deadline=None)
def test_a_pose_passes_only_if_its_upper_3x3_is_a_proper_rotation(values):
    rot = np.reshape(values, (3, 3))
    mat = C2W.copy()
    mat[:3, :3] = rot
    proper = np.allclose(rot.T @ rot, np.eye(3), atol=1e-4) and np.linalg.det(rot) > 0
    frames = [{"file_path": "a.png", "transform_matrix": mat.tolist()}]
    if proper:
        parse_transforms(transforms(frames=frames), "t.json")
    else:
        with pytest.raises(FormatError, match="not a rotation"):
            parse_transforms(transforms(frames=frames), "t.json")


def test_json_nested_100k_deep_non_utf8_and_oversized_files_are_clear_errors(tmp_path):
    with pytest.raises(InputTooLargeError, match="nested"):
        parse_json("[" * 100_000 + "]" * 100_000, "deep.json")
    with pytest.raises(InputTooLargeError, match="nested deeper than 32"):
        parse_json("[" * 40 + "]" * 40, "deep.json")
    with pytest.raises(FormatError, match="bad.json: not UTF-8"):
        parse_json(b'{"a": "\xff"}', "bad.json")
    big = tmp_path / "big.json"
    big.write_text("{}")
    with pytest.raises(InputTooLargeError, match="big.json"):
        from station.formats.jsonfile import read_json_bytes
        read_json_bytes(big, max_bytes=1)
    (tmp_path / "list.json").write_text("[1]")
    with pytest.raises(FormatError, match="top level"):
        read_json_object(tmp_path / "list.json")


def manifest_line(**change) -> str:
    entry = {"file": "raw/a.dng", "sha256": sha256_bytes(b"x"), "elevation_deg": 30.0, "azimuth_deg": 9.0,
             "kind": "shot", "exposure_s": 0.01, "iso": 100, "utc": "", "extra": {}}
    entry.update(change)
    return json.dumps(entry)


@pytest.mark.parametrize("change, field", [({"elevation_deg": math.nan}, "elevation_deg"), ({"elevation_deg": 95.0}, "elevation_deg"),
                                           ({"azimuth_deg": "9"}, "azimuth_deg"), ({"file": 5}, "file"),
                                           ({"iso": [1]}, "iso"), ({"kind": "selfie"}, "kind"), ({"sha256": "ab"}, "sha256"),
                                           ({"extra": [1]}, "extra"), ({"exposure_s": -1}, "exposure_s")])
def test_a_manifest_line_with_a_wrong_field_is_refused_naming_line_and_field(tmp_path, change, field):
    path = tmp_path / "manifest.jsonl"
    path.write_text(manifest_line() + "\n" + manifest_line(**change) + "\n")
    with pytest.raises(FormatError, match=rf"manifest\.jsonl: line 2\.{field}: "):
        read_manifest_records(path)


def test_a_non_utf8_manifest_names_its_line_and_a_good_one_round_trips(tmp_path):
    scan = ScanFolder(tmp_path)
    entry = ManifestEntry("raw/a.dng", sha256_bytes(b"x"), 30.0, 9.0, "plate", 0.01, 100, "")
    scan.write_manifest([entry, entry])
    assert scan.read_manifest() == [entry, entry]
    scan.manifest_path.write_bytes(manifest_line().encode() + b"\n" + b'{"file": "\xff"}\n')
    with pytest.raises(FormatError, match=r"manifest\.jsonl: line 2: not UTF-8"):
        scan.read_manifest()


def png_claiming(path, width: int, height: int) -> None:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\x00" * 16)) + chunk(b"IEND", b""))


def test_an_image_header_over_the_pixel_limit_is_refused_before_decoding(tmp_path, monkeypatch):
    import cv2

    png_claiming(tmp_path / "bomb.png", 30000, 30000)
    monkeypatch.setattr(cv2, "imread", lambda *a: pytest.fail("decoded before the size check"))
    with pytest.raises(InputTooLargeError, match="bomb.png: header claims too many pixels"):
        read_cv2(tmp_path / "bomb.png")
    png_claiming(tmp_path / "wide.png", 70000, 10)
    with pytest.raises(InputTooLargeError, match="wide.png: header says 70000x10 pixels"):
        read_cv2(tmp_path / "wide.png")
    with pytest.raises(InputTooLargeError, match="limit of 1000 pixels"):
        png_claiming(tmp_path / "small.png", 40, 30)
        checked_size(tmp_path / "small.png", limits=ImageLimits(max_pixels=1000))
    assert checked_size(tmp_path / "small.png", limits=ImageLimits(max_pixels=1200)) == (40, 30)


def test_empty_truncated_and_garbage_images_are_clear_errors(tmp_path):
    import cv2

    good = tmp_path / "good.png"
    cv2.imwrite(str(good), np.random.default_rng(0).integers(0, 255, (40, 50, 3), dtype=np.uint8))
    assert read_cv2(good).shape == (40, 50, 3) and open_pil(good).size == (50, 40)
    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "cut.png").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    (tmp_path / "junk.png").write_bytes(bytes(range(256)))
    with pytest.raises(FormatError, match=r"empty.png: frames\[0\]: empty file"):
        read_cv2(tmp_path / "empty.png", "frames[0]")
    for reader in (read_cv2, open_pil):
        with pytest.raises(FormatError, match="cut.png: truncated or corrupt"):
            reader(tmp_path / "cut.png")
        with pytest.raises(FormatError, match="junk.png: not a readable image"):
            reader(tmp_path / "junk.png")


def surface(**change) -> dict:
    n = 5
    params = {"means": torch.zeros(n, 3), "scales": torch.zeros(n, 3), "quats": torch.ones(n, 4),
              "opacities": torch.zeros(n), "sh0": torch.zeros(n, 1, 3), "shN": torch.zeros(n, 3, 3)}
    params.update({k: v for k, v in change.items() if k in params})
    return {"params": params, "downscale": change.get("downscale", 1)}


def test_model_files_load_weights_only_and_garbage_is_a_checkpoint_error(tmp_path):
    path = tmp_path / "surface.pt"
    torch.save(surface(), path)
    assert load_surface_file(path)["params"]["means"].shape == (5, 3)
    whole = path.read_bytes()
    for name, data in {"empty": b"", "half": whole[: len(whole) // 2], "text": b"hello\n", "garbage": bytes(range(256)) * 4}.items():
        path.write_bytes(data)
        with pytest.raises(CheckpointError, match="surface.pt: ") as caught:
            load_surface_file(path)
        assert isinstance(caught.value, StationError) and caught.value.exit_code == 2, name
    torch.save({"params": {}, "downscale": 1, "evil": tmp_path}, path)  # a pickled class
    with pytest.raises(CheckpointError, match="not a torch model file"):
        load_surface_file(path)


@pytest.mark.parametrize("change, field", [({"quats": torch.zeros(5, 3)}, "params.quats"), ({"means": torch.full((5, 3), math.nan)}, "params.means"),
                                           ({"shN": torch.zeros(5, 2, 3)}, "params.shN"), ({"downscale": "2"}, "downscale"),
                                           ({"downscale": 0}, "downscale")])
def test_a_surface_of_the_wrong_layout_is_refused_naming_the_field(tmp_path, change, field):
    torch.save(surface(**change), tmp_path / "surface.pt")
    with pytest.raises(CheckpointError, match=rf"surface\.pt: {field}: "):
        load_surface_file(tmp_path / "surface.pt")


def test_infill_and_training_checkpoints_are_checked_by_layout(tmp_path):
    torch.save({"means": torch.zeros(3, 3), "scales": torch.ones(3), "levels": torch.ones(3)}, tmp_path / "infill.pt")
    with pytest.raises(CheckpointError, match="infill.pt: levels: must hold integers"):
        load_infill_file(tmp_path / "infill.pt")
    torch.save({"config": {}, "step": "5"}, tmp_path / "checkpoint.pt")
    with pytest.raises(CheckpointError, match="checkpoint.pt: step: must be a int"):
        load_training_checkpoint(tmp_path / "checkpoint.pt")


def test_a_colmap_binary_whose_counts_overrun_its_bytes_is_refused_unread(tmp_path):
    cameras = struct.pack("<QiiQQ4d", 1, 1, 1, 64, 48, 60.0, 60.0, 32.0, 24.0)
    (tmp_path / "cameras.bin").write_bytes(cameras)
    check_colmap_binary(tmp_path)
    (tmp_path / "cameras.bin").write_bytes(cameras[:-8])
    with pytest.raises(FormatError, match=r"cameras\.bin: camera 0 params: truncated"):
        check_colmap_binary(tmp_path)
    (tmp_path / "cameras.bin").write_bytes(cameras)
    (tmp_path / "points3D.bin").write_bytes(struct.pack("<Q", 10**15) + bytes(64))
    with pytest.raises(FormatError, match=r"points3D\.bin: num_points3D: states 1000000000000000 records"):
        check_colmap_binary(tmp_path)
