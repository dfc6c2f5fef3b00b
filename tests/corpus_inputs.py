"""Malformed inputs for the untrusted-input corpus (tests/test_untrusted_corpus.py), built in the test.

Each `Case` copies a valid base folder into its own folder, breaks one thing, and returns the CLI
arguments that read it and a word the error message must name (the file or field). `outside` is a
folder beside the case that the case may link to but nothing may write into.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sqlite3
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


def _surface(**change) -> dict:
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


def _write(data: bytes) -> Callable[[Path, Path], None]:
    return lambda path, _: path.write_bytes(data)


def _truncate(fraction: float) -> Callable[[Path, Path], None]:
    return lambda path, _: truncated(path, fraction)


def _garbage(size: int = 4096) -> Callable[[Path, Path], None]:
    return lambda path, _: garbage(path, size)


def _link_out(path: Path, outside: Path) -> None:
    relink(path, outside / f"moved_{path.name}")


MODEL_FILE_BAD = {
    "empty": _write(b""), "text": _write(b"hello, not a model\n"), "garbage": _garbage(),
    "half": _truncate(0.5), "ninety_percent": _truncate(0.9),
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
        Case("train", "transforms_symlinked_out", posed_file_case("poses/transforms.json", _link_out), "transforms.json"),
        Case("train", "image_empty", posed_file_case("images/f03.png", _write(b"")), "f03.png"),
        Case("train", "image_truncated", posed_file_case("images/f03.png", _truncate(0.5)), "f03.png"),
        Case("train", "image_garbage", posed_file_case("images/f03.png", _garbage()), "f03.png"),
        Case("train", "image_huge_header", posed_file_case("images/f03.png", lambda p, _: huge_png(p)), "f03.png"),
        Case("train", "image_wrong_size", posed_file_case("images/f03.png", _resized), "f03.png"),
        Case("train", "image_symlinked_out", posed_file_case("images/f03.png", _link_out), "f03.png"),
        Case("train", "mask_truncated", posed_file_case("masks/f02.png", _truncate(0.3)), "f02.png"),
        Case("train", "mask_huge_header", posed_file_case("masks/f02.png", lambda p, _: huge_png(p, 40000, 40000)), "f02.png"),
        Case("train", "cloud_garbage", posed_file_case("poses/cloud.ply", _garbage()), "cloud.ply"),
    ]
    ckpt = "model/checkpoint.pt"
    cases += [Case("train", f"checkpoint_{name}", posed_file_case(ckpt, torch_file_then(_checkpoint_like(), spoil)),
                   "checkpoint.pt") for name, spoil in MODEL_FILE_BAD.items()]
    wrong = {"list": [1, 2, 3], "no_model": {k: v for k, v in _checkpoint_like().items() if k != "model"},
             "step_text": {**_checkpoint_like(), "step": "5"},
             "model_shapes": {**_checkpoint_like(), "model": {**_checkpoint_like()["model"], "quats": torch.zeros(3, 4)}},
             "generator_bytes": {**_checkpoint_like(), "generator": torch.zeros(4, dtype=torch.uint8)}}
    cases += [Case("train", f"checkpoint_{name}", posed_file_case(ckpt, torch_file(obj)), "checkpoint.pt")
              for name, obj in wrong.items()]
    cases.append(Case("train", "checkpoint_pickled_class", posed_file_case(ckpt, _pickled_code), "checkpoint.pt"))
    return cases


# sos and export: model/surface.pt, model/infill.pt, --splat PLY -------------------------------------
def model_cases(command: str) -> list[Case]:
    cases = [Case(command, f"surface_{name}", posed_file_case("model/surface.pt", spoil, command), "surface.pt")
             for name, spoil in MODEL_FILE_BAD.items()]
    wrong = {"list": [1], "no_params": {"downscale": 1}, "params_shapes": _surface(quats=torch.zeros(8, 3)),
             "params_nan": _surface(means=torch.full((8, 3), math.nan)), "downscale_text": _surface(downscale="2"),
             "downscale_zero": _surface(downscale=0), "sh_bases": _surface(shN=torch.zeros(8, 2, 3)),
             "no_gaussians": _surface(**{k: torch.zeros((0, *s)) for k, s in
                                         (("means", (3,)), ("scales", (3,)), ("quats", (4,)), ("opacities", ()),
                                          ("sh0", (1, 3)), ("shN", (0, 3)))})}
    cases += [Case(command, f"surface_{name}", posed_file_case("model/surface.pt", torch_file(obj), command), "surface.pt")
              for name, obj in wrong.items()]
    infill = {"garbage": _garbage(), "truncated": _truncate(0.6), "empty": _write(b""),
              "shapes": torch_file({"means": torch.zeros(4, 3), "scales": torch.zeros(5), "levels": torch.zeros(4, dtype=torch.long)}),
              "float_levels": torch_file({"means": torch.zeros(4, 3), "scales": torch.ones(4), "levels": torch.zeros(4)})}
    cases += [Case(command, f"infill_{name}", posed_file_case("model/infill.pt", spoil, command), "infill.pt")
              for name, spoil in infill.items()]
    cases.append(Case(command, "surface_symlinked_out", posed_file_case("model/surface.pt", _link_out, command), "surface.pt"))
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


# import: nerfstudio, COLMAP and IDR sources --------------------------------------------------------
def import_case(fmt: str, spoil: Callable[[Path, Path], None]) -> Builder:
    def build(case: Path, outside: Path, bases: Bases) -> list[str]:
        src = copy_base(getattr(bases, fmt), case / "src")
        spoil(src, outside)
        return ["import", str(src), "--format", fmt, "--out", str(case / "scan")]
    return build


def _ns_json(keys: tuple, value) -> Callable[[Path, Path], None]:
    return lambda src, _: edit_json(src / "transforms.json", lambda d: set_path(d, keys, value))


def _in(rel: str, spoil: Callable[[Path, Path], None]) -> Callable[[Path, Path], None]:
    return lambda src, outside: spoil(src / rel, outside)


def _colmap_images_in_parent(src: Path, _: Path) -> None:
    """The model at the source's top, images/ only in the folder above: must not be looked for there."""
    for file in (src / "sparse" / "0").iterdir():
        shutil.move(str(file), src / file.name)
    shutil.move(str(src / "images"), src.parent / "images")


def _npz(change: Callable[[dict], None]) -> Callable[[Path, Path], None]:
    def spoil(src: Path, _: Path) -> None:
        path = src / "cameras.npz"
        arrays = dict(np.load(path))
        change(arrays)
        np.savez(path, **arrays)
    return spoil


def import_cases() -> list[Case]:
    ns = {
        "focal_zero": _ns_json(("fl_x",), 0), "focal_negative": _ns_json(("fl_x",), -3), "focal_true": _ns_json(("fl_x",), True),
        "focal_tiny": _ns_json(("fl_x",), 1e-30), "fl_y_nan": _ns_json(("fl_y",), math.nan), "cx_negative_far": _ns_json(("cx",), -1e6),
        "w_text": _ns_json(("w",), "abc"), "k1_list": _ns_json(("k1",), [1]), "k2_text": _ns_json(("k2",), "x"),
        "mask_path_int": _ns_json(("frames", 0, "mask_path"), 5), "matrix_mirrored": _ns_json(("frames", 1, "transform_matrix"),
                                                                                            np.diag([-1.0, 1, 1, 1]).tolist()),
        "matrix_singular": _ns_json(("frames", 1, "transform_matrix"), np.zeros((4, 4)).tolist()),
        "file_path_escape": _ns_json(("frames", 1, "file_path"), "../outside/img.png"),
        "not_utf8": _in("transforms.json", _write(b'{"frames": "\xc3\x28"}')),
        "nested_100k": _in("transforms.json", lambda p, _: p.write_text(nested())),
        "transforms_symlinked_out": _in("transforms.json", _link_out),
        "image_empty": _in("train/r_1.png", _write(b"")), "image_truncated": _in("train/r_1.png", _truncate(0.4)),
        "image_first_truncated": _in("train/r_0.png", _truncate(0.4)),
        "image_huge_header": _in("train/r_0.png", lambda p, _: huge_png(p)),
        "image_symlinked_out": _in("train/r_2.png", _link_out), "image_folder_symlinked_out": _in("train", _link_out),
    }
    cases = [Case("import", f"nerfstudio_{name}", import_case("nerfstudio", spoil), "transforms.json" if "image" not in name else "r_")
             for name, spoil in ns.items()]
    colmap = {
        "images_only_in_parent": (_colmap_images_in_parent, "images"),
        "images_symlinked_out": (_in("images", _link_out), "images"),
        "image_symlinked_out": (_in("images/img01.png", _link_out), "img01.png"),
        "model_symlinked_out": (_in("sparse/0/cameras.bin", _link_out), "cameras.bin"),
        "cameras_garbage": (_in("sparse/0/cameras.bin", _garbage(200)), "sparse"),
        "images_bin_truncated": (_in("sparse/0/images.bin", _truncate(0.5)), "sparse"),
        "image_empty": (_in("images/img00.png", _write(b"")), "img00.png"),
        "image_huge_header": (_in("images/img02.png", lambda p, _: huge_png(p)), "img02.png"),
    }
    cases += [Case("import", f"colmap_{name}", import_case("colmap", spoil), names) for name, (spoil, names) in colmap.items()]
    idr = {
        "image_symlinked_out": (_in("image/000001.png", _link_out), "000001.png"),
        "image_folder_symlinked_out": (_in("image", _link_out), "image"),
        "npz_symlinked_out": (_in("cameras.npz", _link_out), "cameras.npz"),
        "npz_garbage": (_in("cameras.npz", _garbage()), "cameras.npz"),
        "npz_truncated": (_in("cameras.npz", _truncate(0.5)), "cameras.npz"),
        "world_mat_singular": (_npz(lambda a: a.__setitem__("world_mat_1", np.zeros((4, 4)))), "world_mat_1"),
        "world_mat_nan": (_npz(lambda a: a.__setitem__("world_mat_2", np.full((4, 4), np.nan))), "world_mat_2"),
        "world_mat_text": (_npz(lambda a: a.__setitem__("world_mat_0", np.array([["a"] * 4] * 4))), "world_mat_0"),
        "world_mat_mirrored": (_npz(lambda a: a.__setitem__("world_mat_1", a["world_mat_1"] @ np.diag([1.0, 1, -1, 1]))), "cameras.npz"),
        "world_mat_missing": (_npz(lambda a: a.pop("world_mat_2")), "world_mat_2"),
        "image_empty": (_in("image/000000.png", _write(b"")), "000000.png"),
        "mask_truncated": (_in("mask/001.png", _truncate(0.3)), "001.png"),
    }
    cases += [Case("import", f"idr_{name}", import_case("idr", spoil), names) for name, (spoil, names) in idr.items()]
    return cases


# process: manifest.jsonl and raws ------------------------------------------------------------------
def manifest_case(change: Callable[[list[dict]], None] | None = None, data: bytes | None = None) -> Builder:
    def build(case: Path, outside: Path, bases: Bases) -> list[str]:
        copy_base(bases.captured, case)
        path = case / "manifest.jsonl"
        if data is not None:
            path.write_bytes(data)
        else:
            lines = [json.loads(line) for line in path.read_text().splitlines()]
            change(lines)
            path.write_text("".join(json.dumps(line) + "\n" for line in lines))
        return ["process", str(case)]
    return build


def _field(index: int, key: str, value) -> Callable[[list[dict]], None]:
    return lambda lines: lines[index].__setitem__(key, value)


def process_cases() -> list[Case]:
    fields = {
        "elevation_nan": _field(0, "elevation_deg", math.nan), "elevation_text": _field(1, "elevation_deg", "abc"),
        "elevation_out_of_range": _field(0, "elevation_deg", 400.0), "azimuth_inf": _field(2, "azimuth_deg", math.inf),
        "file_int": _field(0, "file", 5), "file_escape": _field(1, "file", "../../outside/raw.dng"),
        "kind_unknown": _field(0, "kind", "selfie"), "iso_list": _field(1, "iso", [1]), "iso_true": _field(1, "iso", True),
        "exposure_negative": _field(2, "exposure_s", -1.0), "sha_short": _field(0, "sha256", "abc"),
        "extra_list": _field(0, "extra", [1]), "utc_number": _field(0, "utc", 5),
        "line_list": lambda lines: lines.__setitem__(0, [1, 2]), "missing_file": lambda lines: lines[0].pop("file"),
    }
    cases = [Case("process", f"manifest_{name}", manifest_case(change), "manifest.jsonl") for name, change in fields.items()]
    raw = {"not_utf8": b'{"file": "raw/\xff.dng"}\n', "nested_100k": nested().encode() + b"\n",
           "truncated_line": b'{"file": "raw/e0_a000.dng", "sha2', "binary": bytes(range(256))}
    cases += [Case("process", f"manifest_{name}", manifest_case(data=data), "manifest.jsonl") for name, data in raw.items()]
    return cases


# batch and serve: the job store, gate verdicts -----------------------------------------------------
def _queue_with(case: Path, scans: list[Path]) -> Path:
    from station.batch.store import JobStore

    queue = case / "queue.sqlite"
    store = JobStore(queue)
    for scan in scans:
        store.add(scan)
    return queue


def _corrupt_page(queue: Path, page: int = 2) -> None:
    """Keep the SQLite header, break a later page (the issue's malformed page)."""
    with sqlite3.connect(queue) as db:
        page_size = db.execute("PRAGMA page_size").fetchone()[0]
    data = bytearray(queue.read_bytes())
    start = page_size * (page - 1)
    data[start: start + page_size] = bytes(np.random.default_rng(page).integers(0, 256, page_size, dtype=np.uint8))
    queue.write_bytes(bytes(data))


def batch_case(args: Callable[[Path, Path], list[str]], command: str = "batch") -> Builder:
    def build(case: Path, outside: Path, bases: Bases) -> list[str]:
        case.mkdir()
        return [command, *args(case, outside)]
    return build


def batch_cases() -> list[Case]:
    def garbage_queue(case: Path, command: str) -> list[str]:
        garbage(case / "queue.sqlite", 8192)
        return [command, "--queue", str(case / "queue.sqlite")]

    def broken_page(case: Path, command: str) -> list[str]:
        scans = [case / f"s{i}" for i in range(40)]
        for scan in scans:
            (scan / "stages").mkdir(parents=True)
            (scan / "stages" / "capture.json").write_text("{}")
        queue = _queue_with(case, scans)
        _corrupt_page(queue)
        return [command, "--queue", str(queue)]

    cases = [Case("batch", f"{kind}_{command}", batch_case(lambda c, o, k=kind, m=command: (
        garbage_queue if k == "garbage_queue" else broken_page)(c, m)), "queue.sqlite")
        for kind in ("garbage_queue", "broken_page") for command in ("status", "summary")]
    cases += [
        Case("batch", "add_to_garbage_queue", batch_case(lambda c, o: (garbage(c / "q.sqlite", 5000),
             (c / "s" / "stages").mkdir(parents=True), (c / "s" / "stages" / "capture.json").write_text("{}"),
             ["add", str(c / "s"), "--queue", str(c / "q.sqlite")])[-1]), "q.sqlite"),
        Case("batch", "add_not_a_scan", batch_case(lambda c, o: ["add", str(c / "nothing"), "--queue", str(c / "q.sqlite")]), "nothing"),
        Case("batch", "queue_is_a_folder", batch_case(lambda c, o: ((c / "q.sqlite").mkdir(),
             ["status", "--queue", str(c / "q.sqlite")])[-1]), "q.sqlite"),
        Case("batch", "time_budget_text", batch_case(lambda c, o: ["run", "--queue", str(c / "q.sqlite"), "--time-budget", "train=abc"]),
             "time-budget"),
        Case("batch", "disk_budget_unknown_stage", batch_case(lambda c, o: ["run", "--queue", str(c / "q.sqlite"), "--disk-budget", "bake=1"]),
             "disk-budget"),
        Case("batch", "retry_garbage_queue", batch_case(lambda c, o: (garbage(c / "q.sqlite"),
             ["retry", str(c), "--queue", str(c / "q.sqlite")])[-1]), "q.sqlite"),
    ]
    return cases


def serve_cli_cases() -> list[Case]:
    bad = {"size_text": ["--size", "big"], "size_odd": ["--size", "33x17"], "size_tiny": ["--size", "2x2"],
           "camera_unknown": ["--camera", "webcam"], "sim_and_device": ["--sim", "--device", "loop://"]}
    names = {"size_text": "--size", "size_odd": "--size", "size_tiny": "--size", "camera_unknown": "--camera",
             "sim_and_device": "--sim"}
    return [Case("serve", name, batch_case(lambda c, o, a=args: a + ["--queue", str(c / "q.sqlite"), "--out-dir", str(c / "scans")],
                                           "serve"), names[name]) for name, args in bad.items()]


GATE_BAD = {  # asset/gate.json of a queued scan, as the dashboard's queue view reads it
    "garbage": lambda p, o: garbage(p, 300), "not_utf8": lambda p, o: p.write_bytes(b'{"pass": "\xff"}'),
    "nested_100k": lambda p, o: p.write_text(nested()), "top_list": lambda p, o: p.write_text("[true]"),
    "pass_text": lambda p, o: p.write_text('{"pass": "yes", "checks": []}'),
    "checks_dict": lambda p, o: p.write_text('{"pass": true, "checks": {"a": 1}}'),
    "symlinked_out": lambda p, o: (p.write_text('{"pass": true, "checks": []}'), relink(p, o / "gate.json")),
    "huge": lambda p, o: p.write_bytes(b" " * (2 << 20)),
}
