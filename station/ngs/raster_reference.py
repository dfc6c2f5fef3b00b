"""Plain-torch Gaussian rasteriser: the readable ground truth the compiled backends are tested against.

It follows gsplat's conventions exactly (EWA projection with the 1.3x frustum clamp of the Jacobian,
0.3 px low-pass on the 2D covariance, radius = ceil(3 sigma), 16 px tiles, alpha = min(0.99, o exp(-s)),
skip alpha < 1/255, stop before a Gaussian that would bring transmittance to <= 1e-4), but composites
densely: every pixel considers every Gaussian whose tile rectangle covers the pixel's tile, in depth
order. Autograd gives every gradient, including the pose gradient. Memory is O(C * H * W * N), so it is
meant for small scenes.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from station.ngs.conventions import ALPHA_MAX, ALPHA_MIN, EPS2D, SH_C0, SH_C1, SH_C2, SH_C3, T_STOP, TILE


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] wxyz (any norm) -> [N, 3, 3]."""
    w, x, y, z = torch.unbind(quats / quats.norm(dim=-1, keepdim=True), dim=-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(quats.shape[:-1] + (3, 3))


def project(means: Tensor, quats: Tensor, scales: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int,
            near_plane: float, far_plane: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """EWA-project Gaussians into every camera -> means2d [C,N,2], conics [C,N,3], depths [C,N], radii [C,N].

    radii are 0 for culled Gaussians (depth outside (near, far], non-positive determinant, off-image).
    """
    R = quat_to_rotmat(quats)                                           # [N, 3, 3]
    M = R * scales[:, None, :]                                          # [N, 3, 3]
    covars = M @ M.transpose(-1, -2)                                    # [N, 3, 3]
    Rw, tw = viewmats[:, :3, :3], viewmats[:, :3, 3]                    # [C, 3, 3], [C, 3]
    means_c = torch.einsum("cij,nj->cni", Rw, means) + tw[:, None, :]   # [C, N, 3]
    covars_c = torch.einsum("cij,njk,clk->cnil", Rw, covars, Rw)        # [C, N, 3, 3]
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]                       # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    x, y, z = means_c.unbind(-1)                                        # [C, N]
    lim_x_pos = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * height / fy)
    tx = z * torch.minimum(torch.maximum(x / z, -lim_x_neg), lim_x_pos)
    ty = z * torch.minimum(torch.maximum(y / z, -lim_y_neg), lim_y_pos)
    zeros = torch.zeros_like(z)
    J = torch.stack([fx / z, zeros, -fx * tx / (z * z), zeros, fy / z, -fy * ty / (z * z)], dim=-1)
    J = J.reshape(z.shape + (2, 3))                                     # [C, N, 2, 3]
    cov2d = J @ covars_c @ J.transpose(-1, -2)                          # [C, N, 2, 2]
    a = cov2d[..., 0, 0] + EPS2D
    b = 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0])
    c = cov2d[..., 1, 1] + EPS2D
    det = a * c - b * b
    det_safe = det.clamp(min=1e-10)
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)  # [C, N, 3]
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)           # [C, N, 2]
    half = 0.5 * (a + c)
    v1 = half + torch.sqrt(torch.clamp(half * half - det, min=0.01))
    radius = torch.ceil(3.0 * torch.sqrt(v1.detach().clamp(min=0)))
    valid = (det > 0) & (z > near_plane) & (z < far_plane)
    u, v = means2d.detach().unbind(-1)
    inside = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
    radii = torch.where(valid & inside, radius, torch.zeros_like(radius)).to(torch.int32)
    return means2d, conics, z, radii


def camera_centres(viewmats: Tensor) -> Tensor:
    """[C, 4, 4] world-to-camera -> [C, 3] camera centres in world (differentiable)."""
    R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
    return -torch.einsum("cji,cj->ci", R, t)


def eval_sh(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Real SH colour, gsplat/3DGS basis: dirs [..., 3] (any norm), coeffs [..., K, 3] -> [..., 3] (+0.5, >= 0)."""
    d = dirs / dirs.norm(dim=-1, keepdim=True)
    x, y, z = d[..., 0:1], d[..., 1:2], d[..., 2:3]
    out = SH_C0 * coeffs[..., 0, :]
    if degree >= 1:
        out = out - SH_C1 * y * coeffs[..., 1, :] + SH_C1 * z * coeffs[..., 2, :] - SH_C1 * x * coeffs[..., 3, :]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out = (out + SH_C2[0] * x * y * coeffs[..., 4, :] + SH_C2[1] * y * z * coeffs[..., 5, :]
               + SH_C2[2] * (2 * zz - xx - yy) * coeffs[..., 6, :] + SH_C2[3] * x * z * coeffs[..., 7, :]
               + SH_C2[4] * (xx - yy) * coeffs[..., 8, :])
    if degree >= 3:
        out = (out + SH_C3[0] * y * (3 * xx - yy) * coeffs[..., 9, :] + SH_C3[1] * x * y * z * coeffs[..., 10, :]
               + SH_C3[2] * y * (4 * zz - xx - yy) * coeffs[..., 11, :]
               + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[..., 12, :]
               + SH_C3[4] * x * (4 * zz - xx - yy) * coeffs[..., 13, :] + SH_C3[5] * z * (xx - yy) * coeffs[..., 14, :]
               + SH_C3[6] * x * (xx - 3 * yy) * coeffs[..., 15, :])
    return torch.clamp_min(out + 0.5, 0.0)


def tile_rects(means2d: Tensor, radii: Tensor, width: int, height: int) -> Tensor:
    """Tiles each Gaussian touches, gsplat's isect rule: [N, 2], [N] -> [N, 4] (tx0, ty0, tx1, ty1), half-open."""
    tw, th = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    r = radii.to(means2d.dtype)
    u, v = means2d.detach().unbind(-1)
    tx0 = torch.floor((u - r) / TILE).clamp(0, tw)
    tx1 = torch.ceil((u + r) / TILE).clamp(0, tw)
    ty0 = torch.floor((v - r) / TILE).clamp(0, th)
    ty1 = torch.ceil((v + r) / TILE).clamp(0, th)
    rect = torch.stack([tx0, ty0, tx1, ty1], dim=-1).long()
    return torch.where((radii > 0)[:, None], rect, torch.zeros_like(rect))


def _dense_alphas(means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor, width: int,
                  height: int) -> tuple[Tensor, Tensor]:
    """One camera, Gaussians in the given order: alphas [H*W, N] and where they pass the skip rule [H*W, N]."""
    rect = tile_rects(means2d, radii, width, height)                        # [N, 4]
    ys, xs = torch.meshgrid(torch.arange(height, device=means2d.device), torch.arange(width, device=means2d.device),
                            indexing="ij")
    px = xs.reshape(-1, 1).to(means2d.dtype) + 0.5                          # [P, 1]
    py = ys.reshape(-1, 1).to(means2d.dtype) + 0.5
    ptx, pty = xs.reshape(-1, 1) // TILE, ys.reshape(-1, 1) // TILE
    in_rect = (ptx >= rect[:, 0]) & (ptx < rect[:, 2]) & (pty >= rect[:, 1]) & (pty < rect[:, 3])  # [P, N]
    dx, dy = means2d[:, 0] - px, means2d[:, 1] - py                           # [P, N]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    alpha = torch.clamp_max(opacities * torch.exp(-sigma), ALPHA_MAX)
    return alpha, in_rect & (sigma >= 0) & (alpha >= ALPHA_MIN)


def _dense_weights(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor,
                   width: int, height: int) -> tuple[Tensor, Tensor, Tensor]:
    """One camera: depth order [N] and per-pixel compositing weights [H*W, N] (in that order), final T [H*W]."""
    order = torch.sort(depths.detach(), stable=True).indices                 # [N]
    alpha, valid = _dense_alphas(means2d[order], conics[order], opacities[order], radii[order], width, height)
    alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
    next_T = torch.cumprod(1 - alpha, dim=-1)                               # [P, N] transmittance after i
    keep = valid & (next_T.detach() > T_STOP)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    T_after = torch.cumprod(1 - alpha, dim=-1)
    T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], dim=-1)
    return order, alpha * T_before, T_after[:, -1] if T_after.shape[1] else alpha.new_ones(height * width)


def rasterize(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor,
              width: int, height: int, background: Tensor | None) -> tuple[Tensor, Tensor]:
    """One camera: [N,2], [N,3], [N,D], [N], [N], [N] -> colours [H,W,D], alpha [H,W,1]."""
    order, w, T_final = _dense_weights(means2d, conics, opacities, depths, radii, width, height)
    img = w @ colors[order]                                                 # [P, D]
    if background is not None:
        img = img + T_final[:, None] * background
    return img.reshape(height, width, -1), (1 - T_final).reshape(height, width, 1)


def median_depth(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor,
                 width: int, height: int, alpha_level: float | Tensor = 0.5) -> Tensor:
    """One camera: depth of the Gaussian that takes alpha to `alpha_level` (a number, or [H, W] per pixel) or
    above, per pixel [H, W]; +inf where none does."""
    with torch.no_grad():
        order, w, _ = _dense_weights(means2d, conics, opacities, depths, radii, width, height)
        if w.shape[1] == 0:
            return torch.full((height, width), math.inf, dtype=means2d.dtype, device=means2d.device)
        level = torch.as_tensor(alpha_level, dtype=w.dtype, device=w.device).expand(height, width).reshape(-1, 1)
        crossed = torch.cumsum(w, dim=-1) >= level                            # [P, N]: 1 - T_after >= level
        first = torch.argmax(crossed.to(torch.int8), dim=-1)                   # [P]
        out = depths[order][first]
        out = torch.where(crossed.any(dim=-1), out, torch.full_like(out, math.inf))
    return out.reshape(height, width)


def seen_in_front(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor,
                  width: int, height: int, limit: Tensor) -> Tensor:
    """One camera: [N] bool, Gaussians some pixel sees (skip rule, no stop rule) at a depth below its `limit`
    [H, W]."""
    with torch.no_grad():
        _, valid = _dense_alphas(means2d, conics, opacities, radii, width, height)
        return (valid & (depths[None, :] < limit.reshape(-1, 1))).any(dim=0)
