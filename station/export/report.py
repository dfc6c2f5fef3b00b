"""asset/report.html: one self-contained page an operator can judge a scan from at 8 a.m.

Everything is inlined (PNG images as base64 data URIs, curves as SVG polylines generated here),
so the file can be mailed, archived or opened offline, and nothing can break a link later.
The verdict comes first, in plain words, with what to do about each failed check.
"""

from __future__ import annotations

import base64
import html
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from station.export.gate import GateResult
from station.ngs.conventions import rgb_to_sh
from station.ngs.dataset import SceneData, View
from station.ngs.gaussians import Gaussians
from station.ngs.infill import Infill
from station.ngs.raster import rasterization
from station.scanfolder import atomic_write_text

T_FLOOR = 1e-6  # transmittance shown black; 1 is white, 1e-3 mid-grey


@dataclass
class HeldOutPanel:
    name: str
    photo: np.ndarray  # [H, W, 3] in [0, 1], display-encoded
    render: np.ndarray  # [H, W, 3]
    with_infill: np.ndarray  # [H, W, 3] infill inserted in green
    transmittance: np.ndarray  # [H, W] infill seen through the surface, in [0, 1]


@dataclass
class Panels:
    held_out: list[HeldOutPanel] = field(default_factory=list)
    strip: list[tuple[str, np.ndarray, np.ndarray]] = field(default_factory=list)  # (name, training target, render)


@dataclass
class ReportInputs:
    scan_name: str
    metrics: dict
    gate: GateResult
    train: dict  # model/train_metrics.json, {} when absent
    panels: Panels


def _render(g: dict[str, torch.Tensor], view: View, sh_degree: int | None) -> np.ndarray:
    with torch.no_grad():
        colors, _, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                     view.viewmat[None], view.K[None], view.width, view.height, sh_degree=sh_degree)
    return colors[0].clamp(0, 1).numpy()  # [H, W, 3]


def _with_colours(g: dict[str, torch.Tensor], colors: torch.Tensor) -> dict[str, torch.Tensor]:
    return {**{k: g[k] for k in ("means", "quats", "scales", "opacities")}, "colors": colors}


def _join(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: torch.cat([a[k], b[k]]) for k in a}


def crop_box(view: View, margin: float = 0.15) -> tuple[slice, slice]:
    """Rows and columns around the stone (its mask plus a margin), so panels show the stone, not the studio."""
    if view.mask is None or not bool((view.mask > 0.5).any()):
        return slice(None), slice(None)
    rows, cols = np.nonzero(view.mask.numpy() > 0.5)
    pad = int(margin * max(rows.max() - rows.min(), cols.max() - cols.min())) + 2
    return (slice(max(0, rows.min() - pad), rows.max() + pad + 1), slice(max(0, cols.min() - pad), cols.max() + pad + 1))


def render_panels(surface: Gaussians, infill: Infill, scene: SceneData, n_held_out: int, n_strip: int) -> Panels:
    """Renders for the report: held-out views with infill and transmittance, and a turntable strip."""
    g = {k: v.detach() for k, v in surface.activated().items()}
    n, m = len(surface), len(infill)
    noise = infill.gaussians(1.0)
    green_sh = torch.zeros(m, g["colors"].shape[1], 3)
    green_sh[:, 0] = rgb_to_sh(torch.tensor([0.0, 1.0, 0.0]))
    inserted = _join(_with_colours(g, g["colors"]), _with_colours(noise, green_sh))
    leak_scene = _join(_with_colours(g, torch.tensor([1.0, 0.0, 0.0]).expand(n, 3)),
                       _with_colours(noise, torch.tensor([0.0, 1.0, 0.0]).expand(m, 3)))
    panels = Panels()
    for i in np.linspace(0, len(scene.test) - 1, min(n_held_out, len(scene.test))).astype(int):
        view = scene.test[int(i)]
        box = crop_box(view)
        panels.held_out.append(HeldOutPanel(
            view.name, view.image.numpy()[box], _render(g, view, surface.sh_degree)[box],
            _render(inserted, view, surface.sh_degree)[box], _render(leak_scene, view, None)[..., 1][box],
        ))
    views = scene.train + scene.test
    for i in np.linspace(0, len(views) - 1, min(n_strip, len(views))).astype(int):
        view = views[int(i)]
        box = crop_box(view)
        panels.strip.append((view.name, view.target.numpy()[box], _render(g, view, surface.sh_degree)[box]))
    return panels


def png_data_uri(image: np.ndarray) -> str:
    """[H, W, 3] RGB or [H, W] grey in [0, 1] -> data:image/png;base64 URI."""
    data = np.round(np.clip(image, 0.0, 1.0) * 255).astype(np.uint8)
    if data.ndim == 3:
        data = np.ascontiguousarray(data[..., ::-1])  # OpenCV writes BGR
    ok, encoded = cv2.imencode(".png", data)
    if not ok:
        raise ValueError("PNG encoding failed")
    return "data:image/png;base64," + base64.b64encode(encoded.tobytes()).decode("ascii")


def transmittance_picture(t: np.ndarray) -> np.ndarray:
    """Log scale, so faint leaks show: 1e-6 or less black, 1e-3 mid, 1 white."""
    return np.clip(np.log10(np.maximum(t, T_FLOOR)) / -math.log10(T_FLOOR) + 1.0, 0.0, 1.0)


def svg_curve(xs: list[float], ys: list[float], label: str, unit: str, width: int = 420, height: int = 160) -> str:
    """An inline SVG line chart with min/max labels; log y when the series spans a decade or more."""
    pts = [(x, y) for x, y in zip(xs, ys) if isinstance(y, (int, float)) and math.isfinite(y)]
    if len(pts) < 2:
        return f"<p>{html.escape(label)}: fewer than two points recorded.</p>"
    x = np.array([p[0] for p in pts], float)
    y = np.array([p[1] for p in pts], float)
    log = bool(y.min() > 0 and y.max() / y.min() >= 10)
    yv = np.log10(y) if log else y
    pad = 30
    sx = (x - x.min()) / max(x.max() - x.min(), 1e-12) * (width - 2 * pad) + pad
    sy = height - pad - (yv - yv.min()) / max(yv.max() - yv.min(), 1e-12) * (height - 2 * pad)
    points = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(sx, sy))
    scale = " (log scale)" if log else ""
    return (
        f'<figure><svg width="{width}" height="{height}" role="img" '
        f'aria-label="{html.escape(label)}"><rect width="100%" height="100%" fill="#fafafa" stroke="#ccc"/>'
        f'<polyline fill="none" stroke="#2463a6" stroke-width="2" points="{points}"/>'
        f'<text x="{pad}" y="14" font-size="11">max {y.max():.4g} {html.escape(unit)}</text>'
        f'<text x="{pad}" y="{height - 8}" font-size="11">min {y.min():.4g} · step {x.min():.0f}–{x.max():.0f}</text>'
        f'</svg><figcaption>{html.escape(label)}{scale}</figcaption></figure>'
    )


def _fmt(value: object, digits: int = 4) -> str:
    if isinstance(value, bool) or value is None:
        return {True: "yes", False: "NO", None: "not measured"}[value]
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    if isinstance(value, dict):
        return ", ".join(f"{html.escape(str(k))}: {_fmt(v, digits)}" for k, v in value.items()) or "none"
    if isinstance(value, list):
        return html.escape("; ".join(map(str, value))) or "none"
    return html.escape(str(value))


KEY_FIGURES = [
    ("sos", "", "Surface Opacity Score: 1 = nothing shows through the surface"),
    ("psnr", "dB", "held-out photos vs renders (higher is better; 30+ is good)"),
    ("ssim", "", "held-out structural similarity (skimage, Gaussian window σ=1.5; 1 is perfect)"),
    ("psnr_star", "dB", "PSNR with the infill inserted (drops when the inside leaks)"),
    ("ssim_star", "", "SSIM with the infill inserted"),
    ("lpips", "", "perceptual metric (needs backbone weights; skipped when absent)"),
    ("num_gaussians", "", "surface Gaussians"),
    ("num_infill", "", "infill (noise) Gaussians"),
    ("mesh_volume_m3", "m³", "volume of the watertight mesh"),
    ("infill_volume_m3", "m³", "volume the infill stands for"),
    ("mesh_area_m2", "m²", "mesh surface area"),
    ("mesh_watertight", "", "mesh closed, consistently wound, positive volume (every written file reloaded)"),
    ("mesh_manifold", "", "manifold3d accepts the mesh, no pinched vertices, one body"),
    ("mesh_problems", "", "what is wrong with the mesh"),
    ("outside_hull_fraction", "", "share of Gaussians a mask rejects (floaters)"),
    ("train_seconds", "s", "training time"),
    ("export_seconds", "s", "export time up to the gate"),
]

GEOMETRY_FIGURES = [
    ("volume_rel_error", "", "(mesh volume − true volume) / true volume"),
    ("chamfer_fraction_of_diagonal", "", "Chamfer-L1 as a fraction of the stone's bounding-box diagonal"),
    ("chamfer_l1_m", "m", "mean of accuracy and completeness (point-to-mesh)"),
    ("fscore", "", "F-score at τ = 1% of the diagonal"),
    ("tau_m", "m", "τ"),
    ("bbox_diagonal_m", "m", "true stone's bounding-box diagonal"),
]

STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em;max-width:1200px;color:#222}
.verdict{padding:1em 1.3em;border-radius:6px;color:#fff;font-size:1.3em;margin-bottom:1em}
.pass{background:#1f7a34}.fail{background:#b3261e}
.verdict ul{font-size:.8em;margin:.5em 0 0 0}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:.3em .6em;text-align:left}
td.ok{color:#1f7a34;font-weight:bold}td.bad{color:#b3261e;font-weight:bold}
.row{display:flex;gap:6px;flex-wrap:wrap;align-items:flex-start}.row figure{margin:0}
figcaption{font-size:.8em;color:#555}img{image-rendering:pixelated;width:220px}
"""


def _verdict(gate: GateResult) -> str:
    if gate.passed:
        return '<div class="verdict pass">PASS — this asset may ship. Every quality check passed.</div>'
    items = "".join(f"<li><b>{html.escape(c.name)}</b>: {html.escape(c.reason)}</li>" for c in gate.failures())
    return ('<div class="verdict fail">QUARANTINED — do not ship this asset. '
            f"The files were written for inspection; fix these and re-run:<ul>{items}</ul></div>")


def _table(rows: list[tuple[str, object, str, str]]) -> str:
    body = "".join(f"<tr><td>{html.escape(k)}</td><td>{_fmt(v)}</td><td>{html.escape(u)}</td><td>{html.escape(d)}</td></tr>"
                   for k, v, u, d in rows)
    return f"<table><tr><th>figure</th><th>value</th><th>unit</th><th>meaning</th></tr>{body}</table>"


def _checks(gate: GateResult) -> str:
    body = "".join(
        f'<tr><td>{html.escape(c.name)}</td><td>{_fmt(c.value)}</td><td>{_fmt(c.threshold)}</td>'
        f'<td class="{"ok" if c.passed else "bad"}">{"pass" if c.passed else "FAIL"}</td><td>{html.escape(c.reason)}</td></tr>'
        for c in gate.checks)
    return f"<table><tr><th>check</th><th>value</th><th>threshold</th><th>result</th><th>why</th></tr>{body}</table>"


def _figure(image: np.ndarray, caption: str) -> str:
    return f'<figure><img src="{png_data_uri(image)}" alt="{html.escape(caption)}"><figcaption>{html.escape(caption)}</figcaption></figure>'


def _images(panels: Panels, metrics: dict) -> str:
    per_view = {row.get("view"): row for row in metrics.get("views", [])}
    parts = ["<h2>Turntable strip: the views as training saw them (top) and renders (bottom)</h2>",
             "<p>Each view is the stone alone on black, its colour times its coverage: what the model was fitted to.</p>",
             '<div class="row">' + "".join(_figure(p, name) for name, p, _ in panels.strip) + "</div>",
             '<div class="row">' + "".join(_figure(r, "render") for _, _, r in panels.strip) + "</div>",
             "<h2>Held-out views: where the inside leaks</h2>",
             "<p>Left to right: the photo (never used for training), the render, the render with the infill "
             "inserted in green (green showing through = a see-through surface), and the transmittance map "
             "(log scale: black is opaque, mid-grey lets 0.1% through, white lets everything through).</p>"]
    for p in panels.held_out:
        row = per_view.get(p.name, {})
        note = f"PSNR {_fmt(row.get('psnr'))} dB, SOS {_fmt(row.get('sos'))}" if row else ""
        parts.append(f"<h3>{html.escape(p.name)} {html.escape(note)}</h3><div class=\"row\">"
                     + _figure(p.photo, "photo") + _figure(p.render, "render")
                     + _figure(p.with_infill, "infill inserted")
                     + _figure(transmittance_picture(p.transmittance), "transmittance") + "</div>")
    return "".join(parts)


def _curves(train: dict) -> str:
    losses = train.get("losses") or []
    parts = ["<h2>Training curves</h2>"]
    if not losses:
        return parts[0] + "<p>No training curves: model/train_metrics.json is absent or empty.</p>"
    steps = [row.get("step", i) for i, row in enumerate(losses)]
    keys = [k for k in losses[0] if k not in ("step", "seconds")]
    parts.append('<div class="row">' + "".join(svg_curve(steps, [row.get(k) for row in losses], f"training {k} loss", "")
                                                for k in keys) + "</div>")
    held = train.get("held_out") or []
    if held:
        steps = [r.get("step", i) for i, r in enumerate(held)]
        parts.append('<div class="row">' + svg_curve(steps, [r.get("psnr") for r in held], "held-out PSNR", "dB")
                     + svg_curve(steps, [r.get("sos") for r in held], "held-out SOS (once the infill exists)", "")
                     + "</div>")
        decisions = train.get("extensions") or []
        finished = next((d for d in decisions if d.get("finished_early")), None)
        if finished:
            parts.append(f"<p>Planned {train.get('planned_steps')} steps, ended at step {finished.get('step')}: "
                         f"{html.escape(finished.get('reason', ''))}.</p>")
        elif any(d.get("extend") for d in decisions):
            first = next(d for d in decisions if d.get("extend"))
            parts.append(f"<p>Planned {train.get('planned_steps')} steps, trained {steps[-1]}: extended at step "
                         f"{first.get('step')} ({html.escape(first.get('reason', ''))}), stopped at step "
                         f"{decisions[-1].get('step')} ({html.escape(decisions[-1].get('reason', ''))}).</p>")
    else:
        parts.append("<p>Held-out error was not recorded during training; the final held-out figures are in "
                     "the table above.</p>")
    sh = train.get("sh_degree")
    if isinstance(sh, dict) and sh.get("held_out_psnr"):
        by_degree = ", ".join(f"{value:.2f} dB at degree {degree}" for degree, value in sh["held_out_psnr"].items())
        parts.append(f"<p>View-dependent colour: trained to SH degree {sh.get('trained')}, written at degree "
                     f"{sh.get('kept')}, the lowest within {sh.get('tolerance_db')} dB of the trained degree's "
                     f"held-out PSNR ({by_degree}).</p>")
    resolution = train.get("resolution")
    moves = [c for c in (resolution or {}).get("checks", []) if c.get("move_up")]
    if moves:
        steps = ", ".join(f"1/{c.get('downscale')} until step {c.get('step')} ({html.escape(c.get('reason', ''))})"
                          for c in moves)
        parts.append(f"<p>Resolution: trained at {steps}, then at full resolution.</p>")
    return "".join(parts)


def build_report_html(inputs: ReportInputs) -> str:
    m = inputs.metrics
    geometry = m.get("geometry")
    geo = ""
    if isinstance(geometry, dict):
        geo = ("<h2>Geometry against the known true stone (simulated scan)</h2>"
               + _table([(k, geometry.get(k), u, d) for k, u, d in GEOMETRY_FIGURES]))
    return (
        f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>Scan report: "
        f"{html.escape(inputs.scan_name)}</title><style>{STYLE}</style></head><body>"
        f"<h1>Scan report: {html.escape(inputs.scan_name)}</h1>{_verdict(inputs.gate)}"
        f"<h2>Quality checks</h2>{_checks(inputs.gate)}"
        f"<h2>Key figures</h2>{_table([(k, m.get(k), u, d) for k, u, d in KEY_FIGURES])}{geo}"
        f"{_images(inputs.panels, m)}{_curves(inputs.train)}"
        "<p>Open <a href=\"viewer.html\">viewer.html</a> to orbit the splat and the mesh (offline). "
        "Files in asset/: splat.ply (INRIA), splat.splat, splat.spz, splat.glb (KHR_gaussian_splatting), "
        "infill.ply, mesh.ply and mesh.glb (watertight, metres; frames in docs/formats.md), metrics.json, "
        "gate.json.</p></body></html>"
    )


def write_report(path: Path, inputs: ReportInputs) -> None:
    """asset/report.html, atomically."""
    atomic_write_text(Path(path), build_report_html(inputs))
