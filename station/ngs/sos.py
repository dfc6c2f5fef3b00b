"""Held-out evaluation: PSNR/SSIM, the starred metrics with the infill inserted, and SOS.

SOS asks how much of the object's inside (the noise infill, pure green, opacity 1) shows through
the surface (pure red, its own opacities) in each held-out view: T_v = sum(green) / sum(mask),
SOS_v = log10(T_v + 1e-10) / log10(1e-10), so an opaque surface scores 1 and T = 0.1 scores 0.1.
PSNR* drops below PSNR when the infill leaks through the surface's own colours.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch
from skimage.metrics import structural_similarity

from station.errors import BadInputError
from station.ngs.checkpoint_io import load_infill_file, load_surface_file
from station.ngs.dataset import View, load_scene
from station.ngs.gaussians import Gaussians, rgb_to_sh
from station.ngs.infill import Camera, Infill, InfillConfig, build_infill
from station.ngs.inria_ply import read_inria_ply
from station.ngs.raster import rasterization
from station.scanfolder import ScanFolder, atomic_write_bytes, atomic_write_json

EPS = 1e-10
EVAL_INFILL = InfillConfig(levels=(32, 64, 128), erosion_iters=(3, 4, 5))


def sos_of_transmittance(t: float) -> float:
    return math.log10(t + EPS) / math.log10(EPS)


def _render(g: dict[str, torch.Tensor], view: View, sh_degree: int | None, backend: str) -> tuple[np.ndarray, np.ndarray]:
    with torch.no_grad():
        colors, alphas, _ = rasterization(
            g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
            view.viewmat[None], view.K[None], view.width, view.height, sh_degree=sh_degree, backend=backend,
        )  # [1, H, W, 3], [1, H, W, 1]
    return colors[0].clamp(0, 1).cpu().numpy(), alphas[0, ..., 0].cpu().numpy()


def _image_metrics(render: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """PSNR and SSIM of render*mask against gt*mask, render already clamped to [0,1], gt the view's target
    (with a 0/1 mask, ngs.md's rule; with coverage, both sides are the object alone on black, weighted)."""
    a, b = render * mask[..., None], gt * mask[..., None]
    mse = float(np.mean((a - b) ** 2))
    psnr = 10 * math.log10(1.0 / max(mse, 1e-12))
    ssim = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=2)
    return psnr, float(ssim)


def _flat(g: dict[str, torch.Tensor], colors: torch.Tensor) -> dict[str, torch.Tensor]:
    return {"means": g["means"], "quats": g["quats"], "scales": g["scales"], "opacities": g["opacities"], "colors": colors}


def _join(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: torch.cat([a[k], b[k]]) for k in a}


def sos_colours(g: dict[str, torch.Tensor], noise: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The SOS scene: the surface pure red with its own opacities, the infill pure green and opaque."""
    device = g["means"].device
    red = torch.tensor([1.0, 0.0, 0.0], device=device).expand(len(g["means"]), 3)
    green = torch.tensor([0.0, 1.0, 0.0], device=device).expand(len(noise["means"]), 3)
    return _join(_flat(g, red), _flat(noise, green))


def view_transmittance(sos_scene: dict[str, torch.Tensor], view: View, backend: str = "auto"
                       ) -> tuple[float, np.ndarray, np.ndarray]:
    """T_v = sum(green) / sum(mask), the green image, and the mask: the view's, else the SOS render's alpha."""
    sos_rgb, sos_alpha = _render(sos_scene, view, None, backend)
    mask = view.mask.cpu().numpy() if view.mask is not None else sos_alpha
    return float(sos_rgb[..., 1].sum() / max(float(mask.sum()), EPS)), sos_rgb[..., 1], mask


def held_out_sos(surface: dict[str, torch.Tensor], infill: Infill, views: list[View], backend: str = "auto"
                 ) -> tuple[float | None, float | None]:
    """Mean SOS of activated surface parameters over `views`, and the most infill any one view shows: its
    summed green, in pixels' worth of full green. Both None when there is no infill to hide.

    The mean SOS is the gate's figure; the leak says whether what is left could be seen at all, in
    whichever view it is.
    """
    if not views or len(infill) == 0:
        return None, None
    scene = sos_colours(surface, infill.gaussians(1.0))
    scores, leak_px = [], 0.0
    for view in views:
        transmittance, green, _ = view_transmittance(scene, view, backend)
        scores.append(sos_of_transmittance(transmittance))
        leak_px = max(leak_px, float(green.sum()))
    return float(np.mean(scores)), leak_px


def evaluate(surface: Gaussians, infill: Infill, views: list[View], out_dir: Path | None = None,
             backend: str = "auto") -> dict:
    """Metrics on held-out views; writes one 16-bit transmittance PNG per view into out_dir."""
    if not views:
        raise BadInputError("evaluation needs at least one held-out view")
    g = {k: v.detach() for k, v in surface.activated().items()}
    sh_degree = surface.sh_degree
    noise = infill.gaussians(1.0)
    n, m = len(surface), len(infill)
    if m == 0:  # no green to hide: every view would score a meaningless SOS of 1
        raise BadInputError("SOS needs an infill to hide, and this one is empty (the surface spans no volume "
                            "that survives pruning and erosion); retrain, or score with a coarser infill")
    noise_sh = torch.zeros(m, g["colors"].shape[1], 3, device=g["means"].device)
    noise_sh[:, 0] = rgb_to_sh(torch.tensor([0.0, 1.0, 0.0], device=g["means"].device))
    starred = _join(_flat(g, g["colors"]), _flat(noise, noise_sh))
    sos_scene = sos_colours(g, noise)
    rows = []
    for view in views:
        gt = view.target.cpu().numpy()
        render, _ = _render(_flat(g, g["colors"]), view, sh_degree, backend)
        transmittance, green, mask = view_transmittance(sos_scene, view, backend)
        mask_source = "mask" if view.mask is not None else "rendered alpha"
        psnr, ssim = _image_metrics(render, gt, mask)
        star_render, _ = _render(starred, view, sh_degree, backend)
        psnr_star, ssim_star = _image_metrics(star_render, gt, mask)
        rows.append({"view": view.name, "psnr": psnr, "ssim": ssim, "psnr_star": psnr_star, "ssim_star": ssim_star,
                     "transmittance": transmittance, "sos": sos_of_transmittance(transmittance),
                     "mask_source": mask_source})
        if out_dir is not None:
            png = np.round(np.clip(green, 0, 1) * 65535).astype(np.uint16)
            ok, encoded = cv2.imencode(".png", png)
            if ok:
                atomic_write_bytes(Path(out_dir) / f"{Path(view.name).stem}_transmittance.png", encoded.tobytes())
    mean = {key: float(np.mean([r[key] for r in rows])) for key in ("psnr", "ssim", "psnr_star", "ssim_star", "sos")}
    return {**mean, "lpips": "skipped", "lpips_star": "skipped", "num_gaussians": n, "num_infill": m,
            "views": rows}


def load_surface(scan: ScanFolder) -> tuple[Gaussians, int]:
    """The trained surface and the downscale it was trained at."""
    path = scan.resolve_inside("model/surface.pt")
    if not path.is_file():
        raise BadInputError(f"{path}: no trained model; run `station train` first")
    data = load_surface_file(path)
    return Gaussians.from_state_dict(data["params"]), int(data["downscale"])


def scan_infill(scan: ScanFolder, surface: Gaussians, cameras: list[Camera]) -> tuple[Infill, str]:
    """This scan's NGS infill if it has a non-empty one, else one built from the scored surface itself."""
    path = scan.resolve_inside("model/infill.pt")
    if path.is_file():
        infill = Infill.from_state_dict(load_infill_file(path))
        if len(infill):
            return infill, "ngs"
    g = {k: v.detach() for k, v in surface.activated().items()}
    why = "built from the scored splat" + (" (the trained infill is empty)" if path.is_file() else "")
    return build_infill(g, cameras, EVAL_INFILL), why


def _score(scan: ScanFolder, surface: Gaussians, downscale: int, out_name: str) -> dict:
    scene = load_scene(scan.root, downscale=downscale)
    cameras = [Camera(v.viewmat, v.K, v.width, v.height) for v in scene.train]
    infill, source = scan_infill(scan, surface, cameras)
    out_dir = scan.model_dir / out_name
    result = evaluate(surface, infill, scene.test, out_dir)
    result.update(infill_source=source, transmittance_dir=str(out_dir))
    atomic_write_json(out_dir / "sos.json", result)
    return result


def score_splat(scan_root: Path, splat_ply_path: Path) -> dict:
    """SOS and starred metrics of a splat trained elsewhere (INRIA PLY), with this scan's infill."""
    scan = ScanFolder(scan_root)
    surface = read_inria_ply(Path(splat_ply_path))
    downscale = load_surface(scan)[1] if (scan.model_dir / "surface.pt").is_file() else 1
    return _score(scan, surface, downscale, f"sos_{Path(splat_ply_path).stem}")


def evaluate_scan(scan_root: Path, splat: Path | None = None) -> dict:
    """`station sos SCAN [--splat OTHER.ply]`: metrics dict, also written to model/sos*/sos.json."""
    if splat is not None:
        return score_splat(scan_root, splat)
    scan = ScanFolder(scan_root)
    surface, downscale = load_surface(scan)
    return _score(scan, surface, downscale, "sos")
