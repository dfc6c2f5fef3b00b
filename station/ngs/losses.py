"""Training losses: 0.8 L1 + 0.2 D-SSIM on the mask's crop, and the alpha losses.

The image term looks only at the mask's bounding box (the view's target: image times coverage, on
black) so the empty turntable surround does not dilute the gradient. The alpha terms are what stop false
transparency without NGS: L_bg pushes alpha to 0 off the object, L_fg pushes it to 1 on the
object's eroded interior (eroded so that soft mask edges are not forced opaque).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from station.ngs import _ssim_kernels

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


@dataclass
class LossConfig:
    ssim_lambda: float = 0.2
    bg_weight: float = 1.0  # L_bg; 0 switches it off
    fg_weight: float = 1.0  # L_fg (the ablations' L_f); 0 switches it off
    crop_threshold: float = 0.1


def _gaussian_taps(device: torch.device | str = "cpu") -> torch.Tensor:
    coords = torch.arange(SSIM_WINDOW, dtype=torch.float32, device=device) - SSIM_WINDOW // 2
    g = torch.exp(-(coords**2) / (2 * SSIM_SIGMA**2))
    return g / g.sum()


_TAPS = _gaussian_taps().numpy()


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H,W,C] images in [0,1] ('valid' windows, as fused-ssim in training), differentiable in
    `a`. On the CPU it runs the numba kernels: one pass each way instead of a graph of image-sized torch ops."""
    fits = a.shape[0] >= SSIM_WINDOW and a.shape[1] >= SSIM_WINDOW
    if a.device.type == "cpu" and fits and not b.requires_grad:
        return _FusedSSIM.apply(a, b)
    return ssim_torch(a, b)


def ssim_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """`ssim` in plain torch: the reference the numba kernels are tested against, and the path on a GPU.

    The five local moments go through one grouped convolution, and the Gaussian window is separable:
    two 11-tap passes cost a fifth of one 11x11 pass, forward and backward."""
    x = a.permute(2, 0, 1)[None]  # [1, C, H, W]
    y = b.permute(2, 0, 1)[None]
    channels = x.shape[1]
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [1, 5C, H, W]
    taps = _gaussian_taps(x.device).to(x.dtype)
    moments = F.conv2d(stack, taps.view(1, 1, -1, 1).expand(5 * channels, 1, -1, 1), groups=5 * channels)
    moments = F.conv2d(moments, taps.view(1, 1, 1, -1).expand(5 * channels, 1, 1, -1), groups=5 * channels)
    mu_x, mu_y, xx, yy, xy = moments.split(channels, dim=1)
    sxx, syy, sxy = xx - mu_x**2, yy - mu_y**2, xy - mu_x * mu_y
    c1, c2 = _ssim_kernels.C1, _ssim_kernels.C2
    value = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return value.mean()


class _FusedSSIM(torch.autograd.Function):
    """`ssim` on the CPU: one numba pass forward, one backward, instead of a graph of image-sized torch ops."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        x, y = (t.detach().permute(2, 0, 1).contiguous().numpy() for t in (a, b))  # [C, H, W]
        taps = _TAPS.astype(x.dtype)
        total, *derivatives = _ssim_kernels.ssim_fwd(x, y, taps)
        ctx.state = (x, y, taps, derivatives)
        return a.new_tensor(total / derivatives[0].size)

    @staticmethod
    def backward(ctx, grad_value: torch.Tensor):
        x, y, taps, derivatives = ctx.state
        grad = _ssim_kernels.ssim_bwd(float(grad_value) / derivatives[0].size, x, y, taps, *derivatives)
        return torch.from_numpy(grad).permute(1, 2, 0), None


def mask_bbox(mask: torch.Tensor, threshold: float) -> tuple[slice, slice]:
    """Rows/cols slice of the mask > threshold box, grown to at least one SSIM window."""
    height, width = mask.shape
    ys, xs = torch.nonzero(mask > threshold, as_tuple=True)
    if len(ys) == 0:
        return slice(0, height), slice(0, width)
    bounds = []
    for lo, hi, size in ((int(ys.min()), int(ys.max()) + 1, height), (int(xs.min()), int(xs.max()) + 1, width)):
        need = min(SSIM_WINDOW, size)
        if hi - lo < need:
            lo = min(max((lo + hi) // 2 - need // 2, 0), size - need)
            hi = lo + need
        bounds.append(slice(lo, hi))
    return bounds[0], bounds[1]


def erode_mask(mask: torch.Tensor) -> torch.Tensor:
    """One 3x3 min filter: M_e, the mask's interior. [H,W] -> [H,W]."""
    return -F.max_pool2d(-mask[None, None], kernel_size=3, stride=1, padding=1)[0, 0]


@dataclass(frozen=True)
class MaskRegions:
    """What the losses read off a view's mask, fixed for the whole run: worked out once per view, not per step."""

    crop: tuple[slice, slice]  # the mask's bounding box (`mask_bbox`)
    interior: torch.Tensor  # [H, W] the eroded mask (`erode_mask`)


def mask_regions(mask: torch.Tensor, cfg: LossConfig) -> MaskRegions:
    return MaskRegions(mask_bbox(mask, cfg.crop_threshold), erode_mask(mask))


def image_loss(render: torch.Tensor, target: torch.Tensor, crop: tuple[slice, slice] | None,
               cfg: LossConfig) -> torch.Tensor:
    """0.8 L1 + 0.2 (1 - SSIM) on `crop` (the mask's box; None: the whole image); `target` is the object
    alone on black (View.target)."""
    if crop is not None:
        rows, cols = crop
        render, target = render[rows, cols], target[rows, cols]
    l1 = (render - target).abs().mean()
    return (1 - cfg.ssim_lambda) * l1 + cfg.ssim_lambda * (1 - ssim(render, target))


def alpha_losses(alpha: torch.Tensor, mask: torch.Tensor, cfg: LossConfig, fg_alpha: torch.Tensor | None = None,
                 interior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """L_bg = sum max(a-M,0)(1-M)/sum(1-M); L_fg = sum (1-a')M_e/sum M_e, a' = fg_alpha or alpha. All [H,W].

    M is the stone's coverage, fractional on its edge pixels, where the right alpha is M itself: L_bg
    charges only the alpha beyond it, so it does not pull the rim below its coverage (with a 0/1 mask
    this is ngs.md's sum a(1-M)/sum(1-M) exactly)."""
    terms: dict[str, torch.Tensor] = {}
    if cfg.bg_weight > 0:
        background = 1 - mask
        stray = (alpha - mask).clamp_min(0)
        terms["bg"] = cfg.bg_weight * (stray * background).sum() / background.sum().clamp_min(1e-6)
    if cfg.fg_weight > 0:
        interior = erode_mask(mask) if interior is None else interior
        seen = alpha if fg_alpha is None else fg_alpha
        terms["fg"] = cfg.fg_weight * ((1 - seen) * interior).sum() / interior.sum().clamp_min(1e-6)
    return terms


def total_loss(
    render: torch.Tensor, alpha: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None, cfg: LossConfig,
    fg_alpha: torch.Tensor | None = None, regions: MaskRegions | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """render/target [H,W,3], alpha [H,W], mask [H,W] or None (then only the image term).

    fg_alpha: the alpha L_fg judges when it is not the rendered one (NGS: the surface's own share).
    regions: `mask_regions(mask, cfg)`, when the caller keeps them per view."""
    if mask is not None and regions is None:
        regions = mask_regions(mask, cfg)
    terms = {"image": image_loss(render, target, None if regions is None else regions.crop, cfg)}
    if mask is not None:
        terms.update(alpha_losses(alpha, mask, cfg, fg_alpha, regions.interior))
    loss = torch.stack(list(terms.values())).sum()
    return loss, {name: float(value.detach()) for name, value in terms.items()}
