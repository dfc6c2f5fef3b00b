"""Splat writers and readers: round trips within each format's quantisation, typed errors on
truncated, garbage and inconsistent files, and an independent reader (@playcanvas/splat-transform,
from station/export/viewer's npm lock) placing every format's Gaussians where our PLY puts them."""

from __future__ import annotations

import csv
import gzip
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from station.errors import BadInputError
from station.export import dotsplat, gltf, ply
from station.export.splat_formats import FORMATS, read_splat, write_splat
from station.export.splat_model import (
    TURNTABLE_TO_YDOWN,
    TURNTABLE_TO_YUP,
    SplatModel,
    quat_normalize,
    sh_basis,
)


def random_model(n: int = 400, degree: int = 3, seed: int = 0) -> SplatModel:
    rng = np.random.default_rng(seed)
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    return SplatModel(
        means=rng.uniform(-0.1, 0.1, (n, 3)) + [0, 0, 0.1],
        scales_log=rng.uniform(-7.0, -3.0, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        opacity_logit=rng.uniform(-4.0, 4.0, n),
        sh_dc=rng.uniform(-1.5, 1.5, (n, 3)),
        sh_rest=rng.uniform(-0.9, 0.9, (n, k, 3)),
    )


def rotation_of(q: np.ndarray) -> np.ndarray:
    """[N, 3, 3] rotation matrices of wxyz quaternions (for sign-free comparison)."""
    w, x, y, z = quat_normalize(q).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def assert_close_model(got: SplatModel, want: SplatModel, *, pos, log_scale, rot, opacity, rgb, sh):
    np.testing.assert_allclose(got.means, want.means, atol=pos)
    np.testing.assert_allclose(got.scales_log, want.scales_log, atol=log_scale)
    # Compare orientations as R diag(1,2,3) R^T / 3: what a covariance sees, blind to the axis
    # sign flips that readers may legitimately apply to a quaternion.
    def frame(q: np.ndarray) -> np.ndarray:
        r = rotation_of(q)
        return np.einsum("nij,j,nkj->nik", r, np.array([1.0, 2.0, 3.0]) / 3, r)

    np.testing.assert_allclose(frame(got.quats), frame(want.quats), atol=rot)
    np.testing.assert_allclose(got.opacity(), want.opacity(), atol=opacity)
    np.testing.assert_allclose(got.rgb(), want.rgb(), atol=rgb)
    if sh is not None:
        np.testing.assert_allclose(got.sh_rest, want.sh_rest, atol=sh)


def test_rotating_a_model_keeps_covariances_and_view_dependent_colour():
    model = random_model(50)
    rotated = model.rotated(TURNTABLE_TO_YUP)
    r = TURNTABLE_TO_YUP
    s2 = np.exp(2 * model.scales_log.astype(np.float64))
    cov = np.einsum("nij,nj,nkj->nik", rotation_of(model.quats), s2, rotation_of(model.quats))
    cov_rot = np.einsum("nij,nj,nkj->nik", rotation_of(rotated.quats), s2, rotation_of(rotated.quats))
    np.testing.assert_allclose(cov_rot, r @ cov @ r.T, atol=1e-9)
    d = np.random.default_rng(1).normal(size=(5, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    before = np.einsum("pk,nkc->pnc", np.concatenate(sh_basis(d, 3), 1), model.sh_rest)
    after = np.einsum("pk,nkc->pnc", np.concatenate(sh_basis(d @ r.T, 3), 1), rotated.sh_rest)
    np.testing.assert_allclose(after, before, atol=1e-5)


def test_model_refuses_mismatched_shapes_and_nan():
    good = random_model(4, degree=1)
    with pytest.raises(BadInputError, match="scales_log"):
        SplatModel(good.means, good.scales_log[:3], good.quats, good.opacity_logit, good.sh_dc, good.sh_rest)
    with pytest.raises(BadInputError, match="NaN"):
        SplatModel(good.means * np.nan, good.scales_log, good.quats, good.opacity_logit, good.sh_dc, good.sh_rest)
    with pytest.raises(BadInputError, match="sh_rest"):
        SplatModel(good.means, good.scales_log, good.quats, good.opacity_logit, good.sh_dc, np.zeros((4, 5, 3)))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip_is_float_exact_with_the_inria_property_order(tmp_path: Path, degree: int):
    model = random_model(degree=degree)
    path = tmp_path / "splat.ply"
    write_splat(path, model)
    header = path.read_bytes().split(b"end_header")[0].decode()
    names = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert names == ply.ply_property_names(degree)
    rest = 3 * ((degree + 1) ** 2 - 1)
    assert names[9 : 9 + rest] == [f"f_rest_{i}" for i in range(rest)] and names[9 + rest] == "opacity"
    back = read_splat(path)
    # The frame turn is a permutation with signs: positions, scales and opacities come back bit-exact,
    # quaternions and SH bands through a float rotation and back.
    for name in ("means", "scales_log", "opacity_logit", "sh_dc"):
        np.testing.assert_array_equal(getattr(back, name), getattr(model, name))
    np.testing.assert_allclose(back.quats, model.quats, atol=1e-6)
    np.testing.assert_allclose(back.sh_rest, model.sh_rest, atol=1e-5)


def test_ply_f_rest_is_channel_major():
    model = random_model(2, degree=1)
    body = ply.encode_ply(model).split(b"end_header\n", 1)[1]
    row = np.frombuffer(body, "<f4").reshape(2, -1)[0]
    stored = model.rotated(TURNTABLE_TO_YDOWN)
    np.testing.assert_array_equal(row[:3], stored.means[0])  # written y-down: turntable (x, y, z) is (x, -z, y)
    np.testing.assert_array_equal(row[9:12], stored.sh_rest[0, :, 0])  # all red coefficients first


def test_splat_round_trip_within_u8_quantisation_and_sorted_by_importance(tmp_path: Path):
    model = random_model(degree=0)
    path = tmp_path / "splat.splat"
    write_splat(path, model)
    assert path.stat().st_size == 32 * model.num
    back = read_splat(path)
    want = model.subset(dotsplat.splat_order(model))
    # Identify each record by its exact float32 position: the file runs from the most important
    # splat (volume x opacity) to the least.
    index = [int(np.flatnonzero(np.all(model.means == p, axis=1))[0]) for p in back.means]
    importance = (np.exp(model.scales_log.astype(np.float64).sum(1)) * model.opacity())[index]
    assert np.all(np.diff(importance) <= 0)
    assert_close_model(back, want, pos=1e-6, log_scale=1e-5, rot=0.05, opacity=0.5 / 255 + 1e-6, rgb=0.5 / 255 + 1e-6, sh=None)


def test_spz_round_trip_within_spz_quantisation(tmp_path: Path):
    m = random_model(degree=3)
    # SPZ stores SH in [-1, 1); rotating into its +Y-up frame mixes a band's coefficients, so keep
    # them where real splats have them (|c| < 0.5) rather than at the range's edge.
    model = SplatModel(m.means, m.scales_log, m.quats, m.opacity_logit, m.sh_dc, 0.5 * m.sh_rest)
    path = tmp_path / "splat.spz"
    write_splat(path, model)
    raw = gzip.decompress(path.read_bytes())
    assert raw[:4] == b"NGSP" and int.from_bytes(raw[4:8], "little") == 3 and raw[13] == 12
    back = read_splat(path)
    assert_close_model(
        back, model, pos=2.0 / 4096, log_scale=0.5 / 16 + 1e-5, rot=0.02, opacity=0.5 / 255 + 1e-6,
        rgb=0.2820948 * 0.5 / 255 / 0.15 + 1e-5, sh=16 / 128 / 2 * 3 + 1e-3,
    )


def test_glb_round_trip_is_float_exact_and_written_y_up(tmp_path: Path):
    model = random_model(degree=2)
    path = tmp_path / "splat.glb"
    write_splat(path, model)
    gltf_json, binary = gltf._chunks(path.read_bytes(), path)
    primitive = gltf_json["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 0 and "KHR_gaussian_splatting" in primitive["extensions"]
    assert {"KHR_gaussian_splatting:SH_DEGREE_2_COEF_4", "KHR_gaussian_splatting:SCALE"} <= set(primitive["attributes"])
    position = np.frombuffer(binary, "<f4", count=3 * model.num).reshape(-1, 3)
    np.testing.assert_allclose(position, model.means @ TURNTABLE_TO_YUP.T, atol=1e-7)  # turntable z is glTF y
    back = read_splat(path)
    assert_close_model(back, model, pos=1e-6, log_scale=1e-5, rot=1e-5, opacity=1e-6, rgb=1e-6, sh=1e-5)


SUFFIXES = sorted(suffix.lstrip(".") for suffix in FORMATS)


def test_the_table_holds_every_format_and_refuses_an_unknown_suffix(tmp_path: Path):
    assert set(FORMATS) == {".ply", ".splat", ".spz", ".glb"}
    with pytest.raises(BadInputError, match="model.obj: unknown splat format"):
        read_splat(tmp_path / "model.obj")
    with pytest.raises(BadInputError, match="missing.spz: cannot read"):
        read_splat(tmp_path / "missing.spz")


@pytest.mark.parametrize("fmt", SUFFIXES)
def test_truncated_files_raise_bad_input_naming_the_file(tmp_path: Path, fmt: str):
    data = FORMATS[f".{fmt}"].encode(random_model(50, degree=1))
    path = tmp_path / f"cut.{fmt}"
    path.write_bytes(data[: len(data) - 45] if fmt != "spz" else gzip.compress(gzip.decompress(data)[:-45]))
    with pytest.raises(BadInputError, match=str(path.name)):
        read_splat(path)


@pytest.mark.parametrize("fmt", SUFFIXES)
def test_garbage_files_raise_bad_input_naming_the_file(tmp_path: Path, fmt: str):
    path = tmp_path / f"garbage.{fmt}"
    path.write_bytes(np.random.default_rng(3).integers(0, 256, 32 * 77, dtype=np.uint8).tobytes())
    with pytest.raises(BadInputError, match=str(path.name)):
        read_splat(path)


def _ply(elements: list[tuple[str, int, list[str]]], body: bytes) -> bytes:
    header = ["ply", "format binary_little_endian 1.0"]
    for name, count, props in elements:
        header += [f"element {name} {count}", *props]
    return ("\n".join(header + ["end_header"]) + "\n").encode() + body


def _vertex_props() -> list[str]:
    return [f"property float {name}" for name in ply.ply_property_names(0)]


def test_ply_whose_header_counts_fewer_splats_than_the_body_holds_is_refused(tmp_path: Path):
    body = ply.encode_ply(random_model(10, degree=0)).split(b"end_header\n", 1)[1]
    path = tmp_path / "short_count.ply"
    path.write_bytes(_ply([("vertex", 5, _vertex_props())], body))  # 10 splats' bytes, header says 5
    with pytest.raises(BadInputError, match="short_count.ply: PLY body is .* longer than its header promises"):
        read_splat(path)


def test_ply_with_faces_before_the_vertices_reads_the_vertices_not_the_face_bytes(tmp_path: Path):
    model = random_model(6, degree=0)
    vertices = ply.encode_ply(model).split(b"end_header\n", 1)[1]
    faces = b"".join(bytes([3]) + np.array([0, 1, 2], "<i4").tobytes() for _ in range(4))
    face = ("face", 4, ["property list uchar int vertex_indices"])
    path = tmp_path / "face_first.ply"
    path.write_bytes(_ply([face, ("vertex", 6, _vertex_props())], faces + vertices))
    np.testing.assert_array_equal(read_splat(path).means, model.means)
    path.write_bytes(_ply([("vertex", 6, _vertex_props()), face], vertices + faces))  # and after them
    np.testing.assert_array_equal(read_splat(path).means, model.means)
    path.write_bytes(_ply([face, ("vertex", 6, _vertex_props())], faces[:-3] + vertices))
    with pytest.raises(BadInputError, match="face_first.ply: truncated"):
        read_splat(path)


def test_ply_with_a_duplicate_property_or_element_is_refused_naming_it(tmp_path: Path):
    body = ply.encode_ply(random_model(3, degree=0)).split(b"end_header\n", 1)[1]
    path = tmp_path / "dup.ply"
    path.write_bytes(_ply([("vertex", 3, _vertex_props() + ["property float opacity"])], body + bytes(12)))
    with pytest.raises(BadInputError, match="dup.ply: PLY property 'opacity' of element 'vertex' is declared twice"):
        read_splat(path)
    path.write_bytes(_ply([("vertex", 3, _vertex_props()), ("vertex", 0, [])], body))
    with pytest.raises(BadInputError, match="dup.ply: PLY element 'vertex' is declared twice"):
        read_splat(path)


def test_sos_reads_foreign_plys_through_the_same_validator(tmp_path: Path):
    from station.ngs.inria_ply import read_inria_ply

    body = ply.encode_ply(random_model(10, degree=0)).split(b"end_header\n", 1)[1]
    path = tmp_path / "foreign.ply"
    path.write_bytes(_ply([("vertex", 5, _vertex_props())], body))
    with pytest.raises(BadInputError, match="foreign.ply: PLY body is .* longer"):
        read_inria_ply(path)
    write_splat(path, random_model(10, degree=0))  # an asset's splat.ply: y-down, not the scan's frame
    with pytest.raises(BadInputError, match="foreign.ply: a shipped asset splat, written y-down"):
        read_inria_ply(path)


def test_ply_reader_refuses_ascii_and_non_splat_ply(tmp_path: Path):
    path = tmp_path / "mesh.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    with pytest.raises(BadInputError, match="binary_little_endian"):
        read_splat(path)
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n" + bytes(4))
    with pytest.raises(BadInputError, match="missing properties"):
        read_splat(path)


NODE_MODULES = Path(__file__).resolve().parents[1] / "station" / "export" / "viewer" / "node_modules"


def node_tool(*parts: str) -> list[str]:
    """`node <script>` of a package in station/export/viewer's npm lock; skips without node or `npm ci`."""
    script = NODE_MODULES.joinpath(*parts)
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    if not script.is_file():
        pytest.skip(f"{script} missing: run ./dev test (it runs npm ci in station/export/viewer)")
    return ["node", str(script)]


@pytest.fixture(scope="session")
def splat_transform() -> list[str]:
    return node_tool("@playcanvas", "splat-transform", "bin", "cli.mjs")


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    table = np.array(rows[1:], dtype=np.float64)
    return {name: table[:, i] for i, name in enumerate(rows[0])}


def _as_model(columns: dict[str, np.ndarray]) -> SplatModel:
    n = len(columns["x"])
    rest = sorted((k for k in columns if k.startswith("f_rest_")), key=lambda k: int(k.split("_")[-1]))
    k = len(rest) // 3
    sh = np.stack([columns[name] for name in rest], 1).reshape(n, 3, k).transpose(0, 2, 1) if k else np.zeros((n, 0, 3))

    def cols(*names: str) -> np.ndarray:
        return np.stack([columns[name] for name in names], 1)

    return SplatModel(
        cols("x", "y", "z"), cols("scale_0", "scale_1", "scale_2"), cols("rot_0", "rot_1", "rot_2", "rot_3"),
        columns["opacity"], cols("f_dc_0", "f_dc_1", "f_dc_2"), sh,
    )


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["ply", "splat", "spz"])
def test_splat_transform_decodes_every_format_to_the_same_gaussians(tmp_path: Path, fmt: str, splat_transform: list[str]):
    """One convention (docs/formats.md): splat-transform reads each of our files in the PLY frame,
    and the same Gaussian lands at the same place whichever file it came from."""
    model = random_model(60, degree=1)
    path = tmp_path / f"ours.{fmt}"
    write_splat(path, model)
    result = subprocess.run([*splat_transform, "-w", "-q", str(path), str(tmp_path / "out.csv")], capture_output=True, timeout=120)
    assert result.returncode == 0, result.stderr.decode()[-2000:]
    got = _as_model(_read_csv(tmp_path / "out.csv"))
    want = model.rotated(TURNTABLE_TO_YDOWN)  # what our splat.ply stores
    if fmt == "ply":
        assert_close_model(got, want, pos=1e-6, log_scale=1e-5, rot=1e-5, opacity=1e-6, rgb=1e-6, sh=1e-5)
    elif fmt == "splat":
        want = want.subset(dotsplat.splat_order(model))
        assert_close_model(got, want, pos=1e-6, log_scale=1e-5, rot=0.05, opacity=0.003, rgb=0.003, sh=None)
    else:
        assert_close_model(got, want, pos=2.0 / 4096, log_scale=0.04, rot=0.02, opacity=0.003, rgb=0.005, sh=0.07)


@pytest.mark.slow
def test_splat_transform_writes_our_ply_as_a_glb_in_our_glb_frame(tmp_path: Path, splat_transform: list[str]):
    """splat-transform reads no glTF, so the .glb leg runs the other way: its GLB of our PLY must hold
    the Gaussians where our own splat.glb does."""
    model = random_model(60, degree=1)
    write_splat(tmp_path / "ours.ply", model)
    result = subprocess.run([*splat_transform, "-w", "-q", str(tmp_path / "ours.ply"), str(tmp_path / "theirs.glb")],
                            capture_output=True, timeout=120)
    assert result.returncode == 0, result.stderr.decode()[-2000:]
    theirs, _ = gltf._chunks((tmp_path / "theirs.glb").read_bytes(), tmp_path / "theirs.glb")
    position = theirs["accessors"][theirs["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    ours = model.means.astype(np.float64) @ TURNTABLE_TO_YUP.T
    np.testing.assert_allclose(position["min"], ours.min(axis=0), atol=1e-6)
    np.testing.assert_allclose(position["max"], ours.max(axis=0), atol=1e-6)
    back = read_splat(tmp_path / "theirs.glb")  # our reader, their file: back in the turntable frame
    assert_close_model(back, model, pos=1e-6, log_scale=1e-5, rot=1e-5, opacity=1e-6, rgb=1e-6, sh=1e-5)
