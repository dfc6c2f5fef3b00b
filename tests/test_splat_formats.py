"""Splat writers and readers: round trips within each format's quantisation, typed errors on
truncated and garbage files, and an independent reader (@playcanvas/splat-transform) when Node is here."""

from __future__ import annotations

import csv
import gzip
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from station.errors import BadInputError
from station.export import gltf, ply, splat_formats, spz
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
def test_ply_round_trip_is_lossless_with_the_inria_property_order(tmp_path: Path, degree: int):
    model = random_model(degree=degree)
    path = tmp_path / "splat.ply"
    ply.write_ply(path, model)
    header = path.read_bytes().split(b"end_header")[0].decode()
    names = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert names == ply.ply_property_names(degree)
    rest = 3 * ((degree + 1) ** 2 - 1)
    assert names[9 : 9 + rest] == [f"f_rest_{i}" for i in range(rest)] and names[9 + rest] == "opacity"
    back = ply.read_ply(path)
    for name in ("means", "scales_log", "quats", "opacity_logit", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(back, name), getattr(model, name))


def test_ply_f_rest_is_channel_major():
    model = random_model(2, degree=1)
    body = ply.encode_ply(model).split(b"end_header\n", 1)[1]
    row = np.frombuffer(body, "<f4").reshape(2, -1)[0]
    np.testing.assert_array_equal(row[9:12], model.sh_rest[0, :, 0])  # all red coefficients first


def test_splat_round_trip_within_u8_quantisation_and_sorted_by_importance(tmp_path: Path):
    model = random_model(degree=0)
    path = tmp_path / "splat.splat"
    splat_formats.write_splat(path, model)
    assert path.stat().st_size == 32 * model.num
    back = splat_formats.read_splat(path)
    want = model.subset(splat_formats.splat_order(model))
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
    spz.write_spz(path, model)
    raw = gzip.decompress(path.read_bytes())
    assert raw[:4] == b"NGSP" and int.from_bytes(raw[4:8], "little") == 3 and raw[13] == 12
    back = spz.read_spz(path)
    assert_close_model(
        back, model, pos=2.0 / 4096, log_scale=0.5 / 16 + 1e-5, rot=0.02, opacity=0.5 / 255 + 1e-6,
        rgb=0.2820948 * 0.5 / 255 / 0.15 + 1e-5, sh=16 / 128 / 2 * 3 + 1e-3,
    )


def test_glb_round_trip_is_float_exact_and_written_y_up(tmp_path: Path):
    model = random_model(degree=2)
    path = tmp_path / "splat.glb"
    gltf.write_glb(path, model)
    gltf_json, binary = gltf._chunks(path.read_bytes(), path)
    primitive = gltf_json["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 0 and "KHR_gaussian_splatting" in primitive["extensions"]
    assert {"KHR_gaussian_splatting:SH_DEGREE_2_COEF_4", "KHR_gaussian_splatting:SCALE"} <= set(primitive["attributes"])
    position = np.frombuffer(binary, "<f4", count=3 * model.num).reshape(-1, 3)
    np.testing.assert_allclose(position, model.means @ TURNTABLE_TO_YUP.T, atol=1e-7)  # turntable z is glTF y
    back = gltf.read_glb(path)
    assert_close_model(back, model, pos=1e-6, log_scale=1e-5, rot=1e-5, opacity=1e-6, rgb=1e-6, sh=1e-5)


WRITERS = {
    "ply": ply.encode_ply,
    "splat": splat_formats.encode_splat,
    "spz": spz.encode_spz,
    "glb": gltf.encode_glb,
}
READERS = {"ply": ply.read_ply, "splat": splat_formats.read_splat, "spz": spz.read_spz, "glb": gltf.read_glb}


@pytest.mark.parametrize("fmt", sorted(READERS))
def test_truncated_files_raise_bad_input_naming_the_file(tmp_path: Path, fmt: str):
    data = WRITERS[fmt](random_model(50, degree=1))
    path = tmp_path / f"cut.{fmt}"
    path.write_bytes(data[: len(data) - 45] if fmt != "spz" else gzip.compress(gzip.decompress(data)[:-45]))
    with pytest.raises(BadInputError, match=str(path.name)):
        READERS[fmt](path)


@pytest.mark.parametrize("fmt", sorted(READERS))
def test_garbage_files_raise_bad_input_naming_the_file(tmp_path: Path, fmt: str):
    path = tmp_path / f"garbage.{fmt}"
    path.write_bytes(np.random.default_rng(3).integers(0, 256, 32 * 77, dtype=np.uint8).tobytes())
    with pytest.raises(BadInputError, match=str(path.name)):
        READERS[fmt](path)


def test_ply_reader_refuses_ascii_and_non_splat_ply(tmp_path: Path):
    path = tmp_path / "mesh.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    with pytest.raises(BadInputError, match="binary_little_endian"):
        ply.read_ply(path)
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n" + bytes(4))
    with pytest.raises(BadInputError, match="missing properties"):
        ply.read_ply(path)


@pytest.fixture(scope="session")
def splat_transform(tmp_path_factory) -> list[str]:
    """@playcanvas/splat-transform, npm-installed into a temp dir; skips when Node or the network is missing."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("node/npm not installed")
    prefix = tmp_path_factory.mktemp("npm")
    try:
        subprocess.run(
            ["npm", "install", "--no-audit", "--no-fund", "--prefix", str(prefix), "@playcanvas/splat-transform"],
            check=True, capture_output=True, timeout=180,
        )
    except (subprocess.SubprocessError, OSError):
        pytest.skip("npm could not install @playcanvas/splat-transform (offline?)")
    return ["node", str(prefix / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs")]


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
def test_playcanvas_splat_transform_reads_our_files_upright(tmp_path: Path, fmt: str, splat_transform: list[str]):
    model = random_model(60, degree=1)
    path = tmp_path / f"ours.{fmt}"
    path.write_bytes(WRITERS[fmt](model))
    result = subprocess.run([*splat_transform, "-w", "-q", str(path), str(tmp_path / "out.csv")], capture_output=True, timeout=120)
    assert result.returncode == 0, result.stderr.decode()[-2000:]
    got = _as_model(_read_csv(tmp_path / "out.csv"))
    # splat-transform reports everything in the PLY convention. Our PLY is the turntable frame
    # as stored; .splat and SPZ must land y-down there, i.e. upright in PLY-convention viewers.
    if fmt == "ply":
        assert_close_model(got, model, pos=1e-6, log_scale=1e-5, rot=1e-5, opacity=1e-6, rgb=1e-6, sh=1e-6)
    elif fmt == "splat":
        want = model.rotated(TURNTABLE_TO_YDOWN).subset(splat_formats.splat_order(model))
        assert_close_model(got, want, pos=1e-6, log_scale=1e-5, rot=0.05, opacity=0.003, rgb=0.003, sh=None)
    else:
        want = model.rotated(TURNTABLE_TO_YDOWN)
        assert_close_model(got, want, pos=2.0 / 4096, log_scale=0.04, rot=0.02, opacity=0.003, rgb=0.005, sh=0.07)
