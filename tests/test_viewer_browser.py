"""Issue 26's browser criterion: every exported splat format and mesh.glb, drawn by Spark and three.js
in Debian's Chromium (headless, WebGL through SwiftShader), stand upright where the report's own
renderer puts the stone, agree with each other, and the offline viewer page opens with no network.

The asset is built directly (an egg-shaped splat on the plate, coloured red at the top and blue at the
bottom, and its mesh) so the module runs in well under a minute. Skipped without /usr/bin/chromium
or the built viewer bundle (./dev test builds it).
"""

from __future__ import annotations

import base64
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh
from playwright.sync_api import sync_playwright

from station.export.mesh import write_mesh_files
from station.export.splat_formats import write_splat
from station.export.splat_model import TURNTABLE_TO_YUP, SplatModel
from station.export.viewer_page import BUNDLE, ViewerCamera, bundle_text, write_viewer
from station.ngs.conventions import rgb_to_sh
from station.ngs.raster import rasterization
from station.rig_geometry import look_at_c2w

CHROMIUM = Path("/usr/bin/chromium")
# WebGL through SwiftShader; the rest keep Chromium off this machine's closed network.
CHROMIUM_FLAGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                  "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
                  "--disable-sync"]
WIDTH, HEIGHT = 320, 240
CENTRE = np.array([0.006, 0.0, 0.035])  # off the turntable axis, so a turn about the up axis shows
RADII = np.array([0.03, 0.02, 0.035])  # the egg stands 7 cm tall on the plate (z = 0)
SIGMA = 0.0015
SPLAT_FORMATS = ["ply", "splat", "spz"]

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed (./dev test installs it as root)"),
    pytest.mark.skipif(not BUNDLE.is_file(), reason=f"{BUNDLE} is not built (./dev test builds it with npm)"),
]


def egg_splat(n: int = 6000) -> SplatModel:
    """Opaque Gaussians two sigma inside an ellipsoid's surface, where their summed alpha crosses 0.5
    on the surface itself, as a trained splat's edge sits on the mask's."""
    d = np.random.default_rng(0).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = CENTRE + d * (RADII - 2 * SIGMA)
    height = (means[:, 2] / (2 * RADII[2]))[:, None]
    rgb = height * np.array([1.0, 0.5, 0.5]) + (1 - height) * np.array([0.5, 0.5, 1.0])
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return SplatModel(means, np.full((n, 3), np.log(SIGMA)), quats, np.full(n, 4.0), rgb_to_sh(rgb),
                      np.zeros((n, 0, 3)))


def opencv_camera(camera: ViewerCamera) -> tuple[np.ndarray, np.ndarray]:
    """(world-to-camera OpenCV [4, 4], K [3, 3]) of the viewer's camera, in the turntable frame."""
    eye, target = TURNTABLE_TO_YUP.T @ camera.position, TURNTABLE_TO_YUP.T @ camera.target
    f = (HEIGHT / 2) / np.tan(np.radians(camera.fovY) / 2)
    return np.linalg.inv(look_at_c2w(eye, target)), np.array([[f, 0, WIDTH / 2], [0, f, HEIGHT / 2], [0, 0, 1]])


def project(points: np.ndarray, viewmat: np.ndarray, K: np.ndarray) -> np.ndarray:
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    return (cam @ K.T)[:, :2] / cam[:, 2:3]


def silhouette(image: np.ndarray, level: int) -> np.ndarray:
    return image.max(axis=2) > level


def centroid(mask: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    return np.array([cols.mean(), rows.mean()])


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


@pytest.fixture(scope="module")
def asset(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("asset")
    model = egg_splat()
    for fmt in [*SPLAT_FORMATS, "glb"]:
        write_splat(folder / f"splat.{fmt}", model)
    mesh = trimesh.creation.icosphere(subdivisions=4)
    mesh.apply_scale(RADII)
    mesh.apply_translation(CENTRE)
    write_mesh_files(mesh, folder / "mesh.ply", folder / "mesh.glb")
    lo, hi = model.means.min(axis=0), model.means.max(axis=0)
    assert write_viewer(folder / "viewer.html", "egg", folder / "splat.spz", folder / "mesh.glb", lo, hi) == "written"
    camera = ViewerCamera.framing(lo, hi)
    viewmat, K = opencv_camera(camera)
    # The report's renderer (station.ngs.raster, as report.render_panels calls it) from the same camera.
    g = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in dict(
        means=model.means, quats=model.quats, scales=np.exp(model.scales_log), opacities=model.opacity(),
        colors=model.rgb()).items()}
    _, alphas, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                 torch.as_tensor(viewmat, dtype=torch.float32)[None],
                                 torch.as_tensor(K, dtype=torch.float32)[None], WIDTH, HEIGHT)
    footprint_front = np.array([[CENTRE[0], CENTRE[1] - RADII[1], 0.0]])  # the plate just in front of the stone
    return {"folder": folder, "camera": camera, "report_mask": alphas[0, ..., 0].numpy() > 0.5,
            "plate_row": float(project(footprint_front, viewmat, K)[0, 1])}


@pytest.fixture(scope="module")
def browser():
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS)
        yield chromium
        chromium.close()


@pytest.fixture(scope="module")
def renders(asset: dict, browser) -> dict:
    """Each splat format with Spark, mesh.glb and splat.glb with three's GLTFLoader: image and console errors."""
    page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
    errors: list[str] = []
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.set_content("<!doctype html><html><body style='margin:0'><div id='view'></div></body></html>")
    page.add_script_tag(content=bundle_text())
    camera = {"position": asset["camera"].position, "target": asset["camera"].target, "fovY": asset["camera"].fovY}
    out = {}
    # A loaded machine sorts slowly: the slow-sort render holds each of Spark's sorts back 3 s.
    for name, spark in [(f"splat.{fmt}", {}) for fmt in SPLAT_FORMATS] + [
            ("mesh.glb", {}), ("splat.glb", {}), ("splat.ply", {"sortDelay": 3000})]:
        data = base64.b64encode((asset["folder"] / name).read_bytes()).decode("ascii")
        url = page.evaluate(
            """async ([data, kind, camera, width, height, spark]) => {
                const view = document.getElementById('view');
                const bytes = StationViewer.decodeBase64(data);
                const opts = {camera, width, height, spark};
                if (kind === 'glb') opts.glb = bytes; else opts.splat = {bytes, type: kind};
                const shown = await StationViewer.render(view, opts);
                const url = shown.canvas.toDataURL('image/png');
                shown.dispose();
                return url;
            }""",
            [data, name.split(".")[1], camera, WIDTH, HEIGHT, spark],
        )
        key = f"{name}, slow sort" if spark else name
        png = base64.b64decode(url.split(",", 1)[1])
        (asset["folder"] / f"render_{key.replace(', ', '_')}.png").write_bytes(png)  # kept for a look on failure
        out[key] = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    page.close()
    return {"images": out, "errors": errors}


@pytest.mark.parametrize("fmt", SPLAT_FORMATS)
def test_each_splat_format_stands_upright_where_the_report_renders_it(asset: dict, renders: dict, fmt: str):
    image = renders["images"][f"splat.{fmt}"]
    mask = silhouette(image, 127)
    assert mask.sum() > 0.05 * mask.size, "Spark drew (almost) nothing"
    rows = np.nonzero(mask)[0]
    assert rows.max() <= asset["plate_row"] + 3, "part of the stone is drawn below the plate"
    top, bottom = image[rows.min() + 3, :, :], image[rows.max() - 3, :, :]
    assert top[:, 0].max() > top[:, 2].max() and bottom[:, 2].max() > bottom[:, 0].max(), "red top, blue bottom"
    shift = np.linalg.norm(centroid(mask) - centroid(asset["report_mask"]))
    assert shift < 3.0, f"{fmt}: silhouette centroid {shift:.1f} px from the report render's"
    assert iou(mask, asset["report_mask"]) >= 0.9


@pytest.mark.parametrize("fmt", SPLAT_FORMATS)
def test_splat_and_mesh_silhouettes_agree(renders: dict, fmt: str):
    splat = silhouette(renders["images"][f"splat.{fmt}"], 127)
    mesh = silhouette(renders["images"]["mesh.glb"], 8)
    assert iou(splat, mesh) >= 0.9


def test_a_render_waits_for_sparks_sort_however_slow(renders: dict):
    slow = silhouette(renders["images"]["splat.ply, slow sort"], 127)
    assert slow.sum() > 0.05 * slow.size, "the render was taken before Spark's first sort landed"
    assert iou(slow, silhouette(renders["images"]["splat.ply"], 127)) >= 0.98


def test_splat_glb_without_the_extension_is_a_point_cloud_in_the_same_place(renders: dict):
    points = silhouette(renders["images"]["splat.glb"], 8)
    mesh = silhouette(renders["images"]["mesh.glb"], 8)
    assert points.sum() > 0.02 * points.size, "three's GLTFLoader drew no points"
    assert (points & ~mesh).sum() < 0.05 * points.sum(), "points fall outside the mesh's silhouette"
    assert np.linalg.norm(centroid(points) - centroid(mesh)) < 3.0


def test_no_console_errors_while_rendering(renders: dict):
    assert renders["errors"] == []


def test_the_viewer_page_opens_from_disk_offline_and_toggles_the_mesh(asset: dict, browser):
    page = browser.new_page(viewport={"width": 480, "height": 360})
    errors, requests = [], []
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("request", lambda request: requests.append(request.url))
    page.goto((asset["folder"] / "viewer.html").as_uri())
    page.wait_for_selector("body[data-ready='1']", timeout=120_000)

    def frame() -> np.ndarray:
        page.evaluate("stationViewer.settle(3)")  # SwiftShader draws a frame in a good part of a second
        png = base64.b64decode(page.evaluate("document.querySelector('canvas').toDataURL('image/png')").split(",", 1)[1])
        return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)

    splat_only = frame()
    page.check("#show-mesh")
    page.uncheck("#show-splat")
    mesh_only = frame()
    cv2.imwrite(str(asset["folder"] / "viewer_splat.png"), splat_only)
    cv2.imwrite(str(asset["folder"] / "viewer_mesh.png"), mesh_only)
    page.close()
    assert errors == []
    local = ("file:", "blob:", "data:")  # the page itself, Spark's in-page worker, inlined data
    assert [url for url in requests if not url.startswith(local)] == [], "the viewer reached for the network"
    a, b = silhouette(splat_only, 60), silhouette(mesh_only, 8)
    assert a.sum() > 0.03 * a.size and b.sum() > 0.03 * b.size
    assert iou(a, b) >= 0.85
    tint = lambda image: np.abs(image[..., 2].astype(int) - image[..., 0].astype(int))  # red or blue, not grey
    assert tint(splat_only).max() > 60 and tint(mesh_only).max() < 20, "the toggles did not swap splat for mesh"
