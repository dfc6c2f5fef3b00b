"""asset/viewer.html: the splat and the mesh in one self-contained page an operator opens from disk.

The page inlines a prebuilt three.js + Spark bundle (station/export/viewer/, built by `npm run build`
there, which ./dev runs) and the asset's splat.spz and mesh.glb as base64, so it needs no network and
no web server: browsers refuse module imports and fetch() on file:// pages, but run inline scripts.
A Python install without node gets the bundle as package data of the wheel; a source checkout where
it was never built writes no viewer and says so in the metrics.
"""

from __future__ import annotations

import base64
import html
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from station.export.splat_model import TURNTABLE_TO_YUP
from station.scanfolder import atomic_write_text

BUNDLE = Path(__file__).parent / "viewer" / "dist" / "viewer.js"
BUILD_HINT = "run ./dev test once, or `npm ci && npm run build` in station/export/viewer"


@dataclass
class ViewerCamera:
    """A look-at camera in the glTF frame (+Y up, metres), as three.js takes it."""

    position: list[float]
    target: list[float]
    fovY: float  # degrees

    @staticmethod
    def framing(lo: np.ndarray, hi: np.ndarray, elevation_deg: float = 20.0, fov_deg: float = 35.0) -> "ViewerCamera":
        """A camera in front of a turntable-frame box [lo, hi], looking at its centre from `elevation_deg`."""
        centre = (np.asarray(lo, float) + np.asarray(hi, float)) / 2
        radius = float(np.linalg.norm(np.asarray(hi, float) - lo)) / 2
        distance = 1.3 * radius / np.sin(np.radians(fov_deg) / 2)
        e = np.radians(elevation_deg)
        eye = centre + distance * np.array([0.0, -np.cos(e), np.sin(e)])  # in front: turntable -y
        return ViewerCamera((TURNTABLE_TO_YUP @ eye).tolist(), (TURNTABLE_TO_YUP @ centre).tolist(), fov_deg)


def bundle_text() -> str | None:
    """The built viewer script, or None when it was never built here."""
    return BUNDLE.read_text(encoding="utf-8") if BUNDLE.is_file() else None


def viewer_html(title: str, bundle: str, splat_spz: bytes, mesh_glb: bytes | None, camera: ViewerCamera) -> str:
    asset = {
        "splat": base64.b64encode(splat_spz).decode("ascii"),
        "mesh": base64.b64encode(mesh_glb).decode("ascii") if mesh_glb is not None else None,
        "camera": asdict(camera),
    }
    script = bundle.replace("</script", "<\\/script")  # the bundle is inlined inside a <script> element
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}: splat and mesh</title>
<style>body{{margin:0;background:#111;color:#ddd;font:14px sans-serif}}#bar{{position:fixed;top:8px;left:8px}}
label{{margin-right:12px}}#view{{width:100vw;height:100vh}}</style></head>
<body><div id="bar"><b>{html.escape(title)}</b> &nbsp;
<label><input type="checkbox" id="show-splat" checked> splat</label>
<label><input type="checkbox" id="show-mesh"> mesh</label> drag to orbit, scroll to zoom</div>
<div id="view"></div>
<script type="application/json" id="station-asset">{json.dumps(asset)}</script>
<script>{script}</script>
<script>
(async () => {{
  const asset = JSON.parse(document.getElementById("station-asset").textContent);
  const view = document.getElementById("view");
  const shown = await StationViewer.render(view, {{
    splat: {{bytes: StationViewer.decodeBase64(asset.splat), type: "spz"}},
    glb: asset.mesh ? StationViewer.decodeBase64(asset.mesh) : null,
    camera: asset.camera, width: view.clientWidth, height: view.clientHeight, interactive: true,
  }});
  const toggle = (name) => {{
    const box = document.getElementById("show-" + name);
    const apply = () => shown.show(name, box.checked);
    box.addEventListener("change", apply);
    apply();
  }};
  toggle("splat");
  toggle("mesh");
  window.stationViewer = shown;
  document.body.dataset.ready = "1";
}})();
</script></body></html>
"""


def write_viewer(path: Path, title: str, splat_spz: Path, mesh_glb: Path | None, lo: np.ndarray, hi: np.ndarray) -> str:
    """Write viewer.html beside the asset's files; returns what the metrics record about it."""
    bundle = bundle_text()
    if bundle is None:
        return f"not written: the viewer bundle is not built ({BUILD_HINT})"
    mesh = Path(mesh_glb).read_bytes() if mesh_glb is not None and Path(mesh_glb).is_file() else None
    page = viewer_html(title, bundle, Path(splat_spz).read_bytes(), mesh, ViewerCamera.framing(lo, hi))
    atomic_write_text(Path(path), page)
    return "written"
