"""glTF 2.0 binary (GLB) with `KHR_gaussian_splatting`: the Khronos splat container.

Per the extension: one primitive with `mode` 0 (POINTS), `POSITION`, and the attributes
`KHR_gaussian_splatting:ROTATION` (VEC4 float, unit quaternion x,y,z,w),
`KHR_gaussian_splatting:SCALE` (VEC3 float, linear, as the ratified text and PlayCanvas'
splat-transform write it), `KHR_gaussian_splatting:OPACITY` (SCALAR float in [0, 1]) and
`KHR_gaussian_splatting:SH_DEGREE_l_COEF_n` (VEC3 float, RGB per coefficient), plus `COLOR_0` as
the fallback for viewers without the extension, which then draw a coloured point cloud. glTF is
+Y up, metres: the turntable frame (+Z up) is rotated on the way in and out to where PlayCanvas'
splat-transform puts a PLY-convention splat (docs/formats.md), so splat.glb and mesh.glb overlay.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from station.errors import BadInputError
from station.export.splat_model import TURNTABLE_TO_YUP, SplatModel, logit, quat_normalize

EXT = "KHR_gaussian_splatting"
_GLB_MAGIC = 0x46546C67  # "glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_FLOAT = 5126
_ARRAY_BUFFER = 34962
_TYPE_WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
_SH_PER_DEGREE = {1: 3, 2: 5, 3: 7}


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """glTF vertex colours are linear; the splat's DC colour is display sRGB."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _attributes(m: SplatModel) -> list[tuple[str, str, np.ndarray]]:
    q = quat_normalize(m.quats)
    attrs = [
        ("POSITION", "VEC3", m.means),
        ("COLOR_0", "VEC4", np.concatenate([_srgb_to_linear(m.rgb()), m.opacity()[:, None]], axis=1)),
        (f"{EXT}:ROTATION", "VEC4", q[:, [1, 2, 3, 0]]),
        (f"{EXT}:SCALE", "VEC3", np.exp(m.scales_log.astype(np.float64))),
        (f"{EXT}:OPACITY", "SCALAR", m.opacity()[:, None]),
        (f"{EXT}:SH_DEGREE_0_COEF_0", "VEC3", m.sh_dc),
    ]
    start = 0
    for degree in range(1, m.sh_degree + 1):
        for coef in range(_SH_PER_DEGREE[degree]):
            attrs.append((f"{EXT}:SH_DEGREE_{degree}_COEF_{coef}", "VEC3", m.sh_rest[:, start + coef]))
        start += _SH_PER_DEGREE[degree]
    return attrs


def encode_glb(model: SplatModel) -> bytes:
    """GLB bytes of a turntable-frame model, written +Y up."""
    m = model.rotated(TURNTABLE_TO_YUP)
    blobs, views, accessors, attributes, offset = [], [], [], {}, 0
    for index, (name, kind, values) in enumerate(_attributes(m)):
        blob = np.ascontiguousarray(values, dtype="<f4").tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob), "target": _ARRAY_BUFFER})
        accessor = {"bufferView": index, "componentType": _FLOAT, "count": m.num, "type": kind}
        if name == "POSITION":  # glTF requires bounds on POSITION
            accessor["min"] = values.min(axis=0).astype(float).tolist() if m.num else [0.0] * 3
            accessor["max"] = values.max(axis=0).astype(float).tolist() if m.num else [0.0] * 3
        accessors.append(accessor)
        attributes[name] = index
        blobs.append(blob)
        offset += len(blob)  # float32 blobs keep 4-byte alignment
    gltf = {
        "asset": {"version": "2.0", "generator": "station"},
        "extensionsUsed": [EXT],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "splat"}],
        "meshes": [
            {
                "primitives": [
                    {
                        "attributes": attributes,
                        "mode": 0,
                        "extensions": {EXT: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}},
                    }
                ]
            }
        ],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": accessors,
    }
    json_bytes = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    json_bytes += b" " * (-len(json_bytes) % 4)
    bin_bytes = b"".join(blobs)
    bin_bytes += b"\x00" * (-len(bin_bytes) % 4)
    total = 12 + 8 + len(json_bytes) + 8 + len(bin_bytes)
    return b"".join(
        [
            struct.pack("<III", _GLB_MAGIC, 2, total),
            struct.pack("<II", len(json_bytes), _CHUNK_JSON),
            json_bytes,
            struct.pack("<II", len(bin_bytes), _CHUNK_BIN),
            bin_bytes,
        ]
    )


def _chunks(data: bytes, source: Path) -> tuple[dict, bytes]:
    if len(data) < 20:
        raise BadInputError(f"{source}: too short for a GLB header")
    magic, version, total = struct.unpack_from("<III", data)
    if magic != _GLB_MAGIC or version != 2:
        raise BadInputError(f"{source}: not a glTF 2.0 binary (magic 0x{magic:08x}, version {version})")
    if total > len(data):
        raise BadInputError(f"{source}: truncated GLB: header says {total} bytes, file holds {len(data)}")
    json_len, json_type = struct.unpack_from("<II", data, 12)
    if json_type != _CHUNK_JSON or 20 + json_len > total:
        raise BadInputError(f"{source}: GLB's first chunk is not a complete JSON chunk")
    try:
        gltf = json.loads(data[20 : 20 + json_len])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadInputError(f"{source}: GLB JSON chunk does not parse ({exc})") from exc
    pos = 20 + json_len
    if pos + 8 > total:
        raise BadInputError(f"{source}: GLB has no binary chunk")
    bin_len, bin_type = struct.unpack_from("<II", data, pos)
    if bin_type != _CHUNK_BIN or pos + 8 + bin_len > total:
        raise BadInputError(f"{source}: GLB's binary chunk is missing or truncated")
    return gltf, data[pos + 8 : pos + 8 + bin_len]


def decode_glb(data: bytes, source: Path) -> SplatModel:
    """Turntable-frame model of a GLB holding one `KHR_gaussian_splatting` POINTS primitive."""
    gltf, binary = _chunks(data, source)
    try:
        primitive = next(
            p for mesh in gltf.get("meshes", []) for p in mesh.get("primitives", []) if EXT in p.get("extensions", {})
        )
    except StopIteration:
        raise BadInputError(f"{source}: no primitive carries {EXT}") from None
    attrs = primitive.get("attributes", {})

    def read(name: str, kind: str) -> np.ndarray:
        try:
            acc = gltf["accessors"][attrs[name]]
            view = gltf["bufferViews"][acc["bufferView"]]
            if acc["componentType"] != _FLOAT or acc["type"] != kind:
                raise BadInputError(f"{source}: {name} must be float {kind} (quantised accessors are not read)")
            start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
            width = _TYPE_WIDTH[kind]
            count = int(acc["count"])
            if start + count * width * 4 > len(binary) or view.get("byteStride", width * 4) != width * 4:
                raise BadInputError(f"{source}: {name} runs past the binary chunk or is interleaved")
            return np.frombuffer(binary, "<f4", count=count * width, offset=start).reshape(count, width)
        except (KeyError, IndexError, TypeError) as exc:
            raise BadInputError(f"{source}: attribute {name} is missing or malformed ({exc!r})") from exc

    means = read("POSITION", "VEC3")
    rest, degree = [], 0
    while degree < 3 and f"{EXT}:SH_DEGREE_{degree + 1}_COEF_0" in attrs:
        degree += 1
        rest += [read(f"{EXT}:SH_DEGREE_{degree}_COEF_{c}", "VEC3") for c in range(_SH_PER_DEGREE[degree])]
    xyzw = read(f"{EXT}:ROTATION", "VEC4").astype(np.float64)
    scale = read(f"{EXT}:SCALE", "VEC3").astype(np.float64)
    opacity = read(f"{EXT}:OPACITY", "SCALAR")[:, 0].astype(np.float64)
    counts = {len(a) for a in [means, xyzw, scale, opacity, *rest]}
    if len(counts) != 1:
        raise BadInputError(f"{source}: splat attributes disagree on the number of points {sorted(counts)}")
    if np.any(scale <= 0) or np.any((opacity < 0) | (opacity > 1)):
        raise BadInputError(f"{source}: SCALE must be positive and OPACITY within [0, 1]")
    try:
        model = SplatModel(
            means=means,
            scales_log=np.log(scale),
            quats=xyzw[:, [3, 0, 1, 2]],
            opacity_logit=logit(opacity),
            sh_dc=read(f"{EXT}:SH_DEGREE_0_COEF_0", "VEC3"),
            sh_rest=np.stack(rest, axis=1) if rest else np.zeros((len(means), 0, 3), np.float32),
        )
    except BadInputError as exc:
        raise BadInputError(f"{source}: {exc}") from exc
    return model.rotated(TURNTABLE_TO_YUP.T)
