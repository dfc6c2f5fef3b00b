"""Malformed scan-folder inputs for the untrusted-input corpus (train, sos, export) and the helpers it shares.

Each `Case` copies a valid base folder into its own folder, breaks one thing, and returns the CLI
arguments that read it and a word the error message must name (the file or field). `outside` is a
folder beside the case that the case may link to but nothing may write into.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from PIL import Image

Builder = Callable[[Path, Path, "Bases"], list[str]]


@dataclass(frozen=True)
class Case:
    command: str
    name: str
    build: Builder
    names: str  # what the error message must mention


@dataclass(frozen=True)
class Bases:
    """Valid folders the cases start from (built once per module)."""

    posed: Path  # posed scan folder with images, masks, transforms.json and a cloud
    trained: Path  # `posed` plus model/surface.pt and model/infill.pt
    captured: Path  # scan folder with a manifest and raws (stages/capture.json)
    nerfstudio: Path
    colmap: Path
    idr: Path


def huge_png(path: Path, width: int = 30000, height: int = 30000) -> None:
    """A small PNG whose header claims width x height (the decompression bomb of the issue)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    rows = zlib.compress(b"\x00" + bytes(width * 3), 9) if width <= 100_000 else b""
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", rows) + chunk(b"IEND", b""))


def nested(depth: int = 100_000) -> str:
    return "[" * depth + "]" * depth


def copy_base(base: Path, case: Path) -> Path:
    shutil.copytree(base, case, symlinks=True)
    return case


def edit_json(path: Path, change: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def set_path(data: dict, keys: tuple, value) -> None:
    """data[k0][k1]... = value, where keys may index lists."""
    target = data
    for key in keys[:-1]:
        target = target[key]
    target[keys[-1]] = value


def delete_path(data: dict, keys: tuple) -> None:
    target = data
    for key in keys[:-1]:
        target = target[key]
    del target[keys[-1]]


def truncated(path: Path, fraction: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


def garbage(path: Path, size: int = 4096, seed: int = 0) -> None:
    path.write_bytes(np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes())


def relink(path: Path, target: Path) -> None:
    """Replace `path` by a symlink to `target` (outside the folder under test)."""
    if path.is_dir():
        shutil.copytree(path, target)
    elif path.exists():
        shutil.copy2(path, target)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
    os.symlink(target, path)


# train: poses/transforms.json, images, masks, cloud, checkpoint ------------------------------------
TRANSFORMS_BAD = {  # field path -> malformed value (the focal 0, negative, 1e-30, `true`, ...)
    "focal_zero": (("fl_x",), 0), "focal_negative": (("fl_x",), -50.0), "focal_tiny": (("fl_x",), 1e-30),
    "focal_true": (("fl_x",), True), "focal_text": (("fl_y",), "abc"), "focal_list": (("fl_y",), [1]),
    "focal_nan": (("fl_x",), math.nan), "focal_inf": (("fl_y",), math.inf), "focal_huge": (("fl_x",), 1e12),
    "w_text": (("w",), "abc"), "w_negative": (("w",), -4), "w_fraction": (("w",), 31.5), "h_huge": (("h",), 10**9),
    "cx_nan": (("cx",), math.nan), "cy_far": (("cy",), 1e9), "k1_list": (("k1",), [1]), "k1_distorted": (("k1",), 0.2),
    "camera_model_fisheye": (("camera_model",), "OPENCV_FISHEYE"), "frames_dict": (("frames",), {"a": 1}),
    "frames_empty": (("frames",), []), "frame_number": (("frames", 0), 5),
    "file_path_int": (("frames", 1, "file_path"), 5), "file_path_escape": (("frames", 1, "file_path"), "../../outside/x.png"),
    "file_path_absolute": (("frames", 2, "file_path"), "/etc/passwd"), "file_path_missing": (("frames", 2, "file_path"), "images/nope.png"),
    "mask_path_int": (("frames", 3, "mask_path"), 5), "mask_path_escape": (("frames", 3, "mask_path"), "../outside/m.png"),
    "matrix_text": (("frames", 0, "transform_matrix"), "eye"), "matrix_3x3": (("frames", 0, "transform_matrix"), np.eye(3).tolist()),
    "matrix_mirrored": (("frames", 0, "transform_matrix"), np.diag([1.0, 1.0, -1.0, 1.0]).tolist()),
    "matrix_scaled": (("frames", 0, "transform_matrix"), np.diag([2.0, 2.0, 2.0, 1.0]).tolist()),
    "matrix_singular": (("frames", 0, "transform_matrix"), np.zeros((4, 4)).tolist()),
    "matrix_nan": (("frames", 0, "transform_matrix"), [[math.nan] * 4] * 4),
    "matrix_bools": (("frames", 0, "transform_matrix"), [[True, False, False, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
    "matrix_last_row": (("frames", 0, "transform_matrix"), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [1, 0, 0, 1]]),
    "ply_file_path_int": (("ply_file_path",), 7), "ply_file_path_escape": (("ply_file_path",), "../../etc/hostname"),
}


def transforms_case(keys: tuple, value) -> Builder:
    def build(case: Path, outside: Path, bases: Bases) -> list[str]:
        copy_base(bases.posed, case)
        edit_json(case / "poses" / "transforms.json", lambda d: set_path(d, keys, value))
        return ["train", str(case)]
    return build


def transforms_bytes_case(data: bytes) -> Builder:
    def build(case: Path, outside: Path, bases: Bases) -> list[str]:
        copy_base(bases.posed, case)
        (case / "poses" / "transforms.json").write_bytes(data)
        return ["train", str(case)]
    return build


def posed_file_case(rel: str, spoil: Callable[[Path, Path], None], command: str = "train") -> Builder:
    def build(case: Path, outside: Path, bases: Bases) -> list[str]:
        copy_base(bases.trained if command != "train" else bases.posed, case)
        spoil(case / rel, outside)
        return [command, str(case)]
    return build


def interrupted_train_case(spoil: Callable[[Path, Path], None]) -> Builder:
    """A train run killed mid-way (its record says started, under the key `station train` computes now),
    leaving the checkpoint `spoil` writes in its fresh model folder: the one a resumed run loads."""
    def build(case: Path, outside: Path, bases: Bases) -> list[str]:
        from station.pipeline import output_digest, scan_stage_key, spec, write_started
        from station.scanfolder import ScanFolder

        copy_base(bases.posed, case)
        scan, stage = ScanFolder(case), spec("train")
        upstream = {name: output_digest(scan, spec(name)) for name in stage.reads}
        write_started(scan, "train", scan_stage_key(scan, stage, {"method": "ngs", "preset": "fast"}, upstream))
        spoil(case / ".model.new" / "checkpoint.pt", outside)
        return ["train", str(case)]
    return build


def _resized(path: Path, _: Path) -> None:
    Image.new("RGB", (17, 9)).save(path)


def _deleted_key(key: str) -> Callable[[Path, Path], None]:
    return lambda path, _: edit_json(path, lambda d: delete_path(d, (key,)))


def _checkpoint_like() -> dict:
    n = 8
    params = {"means": torch.zeros(n, 3), "scales": torch.zeros(n, 3), "quats": torch.zeros(n, 4),
              "opacities": torch.zeros(n), "sh0": torch.zeros(n, 1, 3), "shN": torch.zeros(n, 3, 3)}
    return {"config": {}, "step": 5, "seconds": 1.0, "model": params, "optimizers": {}, "strategy": {},
            "strategy_generator": torch.Generator().get_state(), "generator": torch.Generator().get_state(),
            "losses": [], "evals": [], "extensions": [], "resolution": {"checks": []}}


def torch_file(obj) -> Callable[[Path, Path], None]:
    return lambda path, _: (path.parent.mkdir(parents=True, exist_ok=True), torch.save(obj, path))


def torch_file_then(obj, spoil: Callable[[Path, Path], None]) -> Callable[[Path, Path], None]:
    def make(path: Path, outside: Path) -> None:
        torch_file(obj)(path, outside)
        spoil(path, outside)
    return make


def _pickled_code(path: Path, _: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"step": Path("/etc/passwd")}, path)  # a pickled class: weights_only must refuse it


def surface_state(**change) -> dict:
    n = 8
    params = {"means": torch.randn(n, 3), "scales": torch.full((n, 3), -3.0), "quats": torch.tensor([[1.0, 0, 0, 0]] * n),
              "opacities": torch.zeros(n), "sh0": torch.zeros(n, 1, 3), "shN": torch.zeros(n, 0, 3)}
    data = {"params": params, "sh_degree": 0, "scene_scale": 1.0, "downscale": 1, "method": "ngs"}
    for key, value in change.items():
        if key in params:
            params[key] = value
        else:
            data[key] = value
    return data


def write_as(data: bytes) -> Callable[[Path, Path], None]:
    return lambda path, _: path.write_bytes(data)


def cut_to(fraction: float) -> Callable[[Path, Path], None]:
    return lambda path, _: truncated(path, fraction)


def garbage_of(size: int = 4096) -> Callable[[Path, Path], None]:
    return lambda path, _: garbage(path, size)


def link_out(path: Path, outside: Path) -> None:
    relink(path, outside / f"moved_{path.name}")


MODEL_FILE_BAD = {
    "empty": write_as(b""), "text": write_as(b"hello, not a model\n"), "garbage": garbage_of(),
    "half": cut_to(0.5), "ninety_percent": cut_to(0.9),
}


def train_cases() -> list[Case]:
    cases = [Case("train", f"transforms_{name}", transforms_case(keys, value), "transforms.json")
             for name, (keys, value) in TRANSFORMS_BAD.items()]
    cases += [
        Case("train", "transforms_not_utf8", transforms_bytes_case(b'{"fl_x": "\xff\xfe"}'), "transforms.json"),
        Case("train", "transforms_nested_100k", transforms_bytes_case(nested().encode()), "transforms.json"),
        Case("train", "transforms_top_list", transforms_bytes_case(b"[1, 2]"), "transforms.json"),
        Case("train", "transforms_truncated", transforms_bytes_case(b'{"frames": [{"file_path": "ima'), "transforms.json"),
        Case("train", "transforms_empty", transforms_bytes_case(b""), "transforms.json"),
        Case("train", "transforms_missing_fl_x", posed_file_case("poses/transforms.json", _deleted_key("fl_x")), "fl_x"),
        Case("train", "transforms_symlinked_out", posed_file_case("poses/transforms.json", link_out), "transforms.json"),
        Case("train", "image_empty", posed_file_case("images/f03.png", write_as(b"")), "f03.png"),
        Case("train", "image_truncated", posed_file_case("images/f03.png", cut_to(0.5)), "f03.png"),
        Case("train", "image_garbage", posed_file_case("images/f03.png", garbage_of()), "f03.png"),
        Case("train", "image_huge_header", posed_file_case("images/f03.png", lambda p, _: huge_png(p)), "f03.png"),
        Case("train", "image_wrong_size", posed_file_case("images/f03.png", _resized), "f03.png"),
        Case("train", "image_symlinked_out", posed_file_case("images/f03.png", link_out), "f03.png"),
        Case("train", "mask_truncated", posed_file_case("masks/f02.png", cut_to(0.3)), "f02.png"),
        Case("train", "mask_huge_header", posed_file_case("masks/f02.png", lambda p, _: huge_png(p, 40000, 40000)), "f02.png"),
        Case("train", "cloud_garbage", posed_file_case("poses/cloud.ply", garbage_of()), "cloud.ply"),
    ]
    cases += [Case("train", f"checkpoint_{name}", interrupted_train_case(torch_file_then(_checkpoint_like(), spoil)),
                   "checkpoint.pt") for name, spoil in MODEL_FILE_BAD.items()]
    wrong = {"list": [1, 2, 3], "no_model": {k: v for k, v in _checkpoint_like().items() if k != "model"},
             "step_text": {**_checkpoint_like(), "step": "5"},
             "model_shapes": {**_checkpoint_like(), "model": {**_checkpoint_like()["model"], "quats": torch.zeros(3, 4)}},
             "generator_bytes": {**_checkpoint_like(), "generator": torch.zeros(4, dtype=torch.uint8)}}
    cases += [Case("train", f"checkpoint_{name}", interrupted_train_case(torch_file(obj)), "checkpoint.pt")
              for name, obj in wrong.items()]
    cases.append(Case("train", "checkpoint_pickled_class", interrupted_train_case(_pickled_code), "checkpoint.pt"))
    return cases


# sos and export: model/surface.pt, model/infill.pt, --splat PLY -------------------------------------
def model_cases(command: str) -> list[Case]:
    cases = [Case(command, f"surface_{name}", posed_file_case("model/surface.pt", spoil, command), "surface.pt")
             for name, spoil in MODEL_FILE_BAD.items()]
    wrong = {"list": [1], "no_params": {"downscale": 1}, "params_shapes": surface_state(quats=torch.zeros(8, 3)),
             "params_nan": surface_state(means=torch.full((8, 3), math.nan)), "downscale_text": surface_state(downscale="2"),
             "downscale_zero": surface_state(downscale=0), "sh_bases": surface_state(shN=torch.zeros(8, 2, 3)),
             "no_gaussians": surface_state(**{k: torch.zeros((0, *s)) for k, s in
                                         (("means", (3,)), ("scales", (3,)), ("quats", (4,)), ("opacities", ()),
                                          ("sh0", (1, 3)), ("shN", (0, 3)))})}
    cases += [Case(command, f"surface_{name}", posed_file_case("model/surface.pt", torch_file(obj), command), "surface.pt")
              for name, obj in wrong.items()]
    infill = {"garbage": garbage_of(), "truncated": cut_to(0.6), "empty": write_as(b""),
              "shapes": torch_file({"means": torch.zeros(4, 3), "scales": torch.zeros(5), "levels": torch.zeros(4, dtype=torch.long)}),
              "float_levels": torch_file({"means": torch.zeros(4, 3), "scales": torch.ones(4), "levels": torch.zeros(4)})}
    cases += [Case(command, f"infill_{name}", posed_file_case("model/infill.pt", spoil, command), "infill.pt")
              for name, spoil in infill.items()]
    cases.append(Case(command, "surface_symlinked_out", posed_file_case("model/surface.pt", link_out, command), "surface.pt"))
    return cases


def ply_header(props: list[str], count: int, first: str = "") -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", *([first] if first else []), f"element vertex {count}",
             *[f"property float {p}" for p in props], "end_header"]
    return ("\n".join(lines) + "\n").encode()


SPLAT_PROPS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
               "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def splat_case(data: Callable[[], bytes]) -> Builder:
    def build(case: Path, outside: Path, bases: Bases) -> list[str]:
        copy_base(bases.trained, case)
        (case / "other.ply").write_bytes(data())
        return ["sos", str(case), "--splat", str(case / "other.ply")]
    return build


def _splat_body(count: int) -> bytes:
    rec = np.zeros((count, len(SPLAT_PROPS)), np.float32)
    rec[:, 13] = 1.0
    rec[:, 10:13] = -3.0
    return rec.tobytes()


SPLAT_PLY_BAD = {  # `sos --splat OTHER.ply`: the reader is ngs/inria_ply.py (h26's exact-layout fix)
    "garbage": lambda: bytes(range(256)) * 8,
    "empty": lambda: b"",
    "truncated_body": lambda: ply_header(SPLAT_PROPS, 10) + _splat_body(10)[:100],
    "missing_property": lambda: ply_header(SPLAT_PROPS[:-1], 4) + np.zeros((4, 16), np.float32).tobytes(),
    "count_smaller_than_body": lambda: ply_header(SPLAT_PROPS, 4) + _splat_body(8),
    "face_first_body_short": lambda: (ply_header(SPLAT_PROPS, 4, "element face 2\nproperty list uchar int vertex_indices")
                                      + bytes([3, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0]) * 2 + _splat_body(3)),
    "face_list_overrun": lambda: (ply_header(SPLAT_PROPS, 4, "element face 1\nproperty list uchar int vertex_indices")
                                  + bytes([255]) + _splat_body(4)),
    "duplicate_property": lambda: ply_header(SPLAT_PROPS + ["opacity"], 4) + np.zeros((4, 18), np.float32).tobytes(),
    "count_huge": lambda: ply_header(SPLAT_PROPS, 10**12) + _splat_body(4),
}
