"""Malformed sources for the untrusted-input corpus: import (nerfstudio, COLMAP, IDR), process, batch and serve.

The scan-folder cases (train, sos, export) and the shared helpers are in corpus_inputs.py.
"""

from __future__ import annotations

import json
import math
import shutil
import sqlite3
from pathlib import Path
from typing import Callable

import numpy as np

from corpus_inputs import (Bases, Builder, Case, copy_base, cut_to, edit_json, garbage, garbage_of, huge_png, link_out, nested,
                           relink, set_path, write_as)


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
        "not_utf8": _in("transforms.json", write_as(b'{"frames": "\xc3\x28"}')),
        "nested_100k": _in("transforms.json", lambda p, _: p.write_text(nested())),
        "transforms_symlinked_out": _in("transforms.json", link_out),
        "image_empty": _in("train/r_1.png", write_as(b"")), "image_truncated": _in("train/r_1.png", cut_to(0.4)),
        "image_first_truncated": _in("train/r_0.png", cut_to(0.4)),
        "image_huge_header": _in("train/r_0.png", lambda p, _: huge_png(p)),
        "image_symlinked_out": _in("train/r_2.png", link_out), "image_folder_symlinked_out": _in("train", link_out),
    }
    cases = [Case("import", f"nerfstudio_{name}", import_case("nerfstudio", spoil), "transforms.json" if "image" not in name else "r_")
             for name, spoil in ns.items()]
    colmap = {
        "images_only_in_parent": (_colmap_images_in_parent, "images"),
        "images_symlinked_out": (_in("images", link_out), "images"),
        "image_symlinked_out": (_in("images/img01.png", link_out), "img01.png"),
        "model_symlinked_out": (_in("sparse/0/cameras.bin", link_out), "cameras.bin"),
        "cameras_garbage": (_in("sparse/0/cameras.bin", garbage_of(200)), "sparse"),
        "images_bin_truncated": (_in("sparse/0/images.bin", cut_to(0.5)), "sparse"),
        "image_empty": (_in("images/img00.png", write_as(b"")), "img00.png"),
        "image_huge_header": (_in("images/img02.png", lambda p, _: huge_png(p)), "img02.png"),
    }
    cases += [Case("import", f"colmap_{name}", import_case("colmap", spoil), names) for name, (spoil, names) in colmap.items()]
    idr = {
        "image_symlinked_out": (_in("image/000001.png", link_out), "000001.png"),
        "image_folder_symlinked_out": (_in("image", link_out), "image"),
        "npz_symlinked_out": (_in("cameras.npz", link_out), "cameras.npz"),
        "npz_garbage": (_in("cameras.npz", garbage_of()), "cameras.npz"),
        "npz_truncated": (_in("cameras.npz", cut_to(0.5)), "cameras.npz"),
        "world_mat_singular": (_npz(lambda a: a.__setitem__("world_mat_1", np.zeros((4, 4)))), "world_mat_1"),
        "world_mat_nan": (_npz(lambda a: a.__setitem__("world_mat_2", np.full((4, 4), np.nan))), "world_mat_2"),
        "world_mat_text": (_npz(lambda a: a.__setitem__("world_mat_0", np.array([["a"] * 4] * 4))), "world_mat_0"),
        "world_mat_mirrored": (_npz(lambda a: a.__setitem__("world_mat_1", a["world_mat_1"] @ np.diag([1.0, 1, -1, 1]))), "cameras.npz"),
        "world_mat_missing": (_npz(lambda a: a.pop("world_mat_2")), "world_mat_2"),
        "image_empty": (_in("image/000000.png", write_as(b"")), "000000.png"),
        "mask_truncated": (_in("mask/001.png", cut_to(0.3)), "001.png"),
    }
    cases += [Case("import", f"idr_{name}", import_case("idr", spoil), names) for name, (spoil, names) in idr.items()]
    return cases


# process: manifest.jsonl and raws ------------------------------------------------------------------
EMPTY_SHA256 = "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"


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


def _emptied_raws(case: Path, outside: Path, bases: Bases) -> list[str]:
    """Every raw 0 bytes, with the checksum of 0 bytes in the manifest: it passes verification, then must not decode."""
    argv = manifest_case(lambda lines: [line.update(sha256=EMPTY_SHA256) for line in lines])(case, outside, bases)
    for raw in (case / "raw").iterdir():
        raw.write_bytes(b"")
    return argv


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
    cases.append(Case("process", "raws_not_raw", manifest_case(lambda lines: None), "e0_a000.dng"))  # checksums match
    cases.append(Case("process", "raws_empty", _emptied_raws, "e0_a000.dng"))
    return cases


# batch and serve: the job store, gate verdicts -----------------------------------------------------
def queue_with(case: Path, scans: list[Path]) -> Path:
    from station.batch.store import JobStore

    queue = case / "queue.sqlite"
    store = JobStore(queue)
    for scan in scans:
        store.add(scan)
    return queue


def corrupt_page(queue: Path, page: int = 2) -> None:
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
        queue = queue_with(case, scans)
        corrupt_page(queue)
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
