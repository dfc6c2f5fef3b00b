"""The one entry point for rendering Gaussians: `rasterization()`, and the forward-only `median_depth()` and
`seen_in_front()`.

Backends share gsplat's conventions (see `raster_reference`): "torch" is the dense plain-torch reference,
"cpu" the tile-parallel numba kernels, "gsplat" the CUDA library (imported lazily; untested here, as no
GPU is available). "auto" picks gsplat for CUDA tensors when it is installed (else the reference there), the
numba kernels for CPU tensors; the forward-only per-pixel queries run the numba kernels on host copies on
every device and return their results on the input's device.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Literal

import numba
import numpy as np
import torch
from torch import Tensor

from station.errors import BadInputError
from station.ngs import _kernels, _project_kernels
from station.ngs import raster_reference as ref

Backend = Literal["auto", "cpu", "torch", "gsplat"]
RenderMode = Literal["RGB", "RGB+ED"]


def set_num_threads(threads: int) -> None:
    """Size numba's and torch's thread pools together; left at their defaults they oversubscribe the cores
    and small torch ops slow down 15-30x. numba's first, because starting its OpenMP pool resets torch's count
    to all cores (tests/test_stage_threads.py). Export OMP_WAIT_POLICY=PASSIVE before starting Python to stop
    idle pool threads from spinning."""
    if threads < 1:
        raise BadInputError(f"set_num_threads: threads must be >= 1, got {threads}")
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    torch.set_num_threads(threads)


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """torch's pool at `threads` inside the block, as it was after. With passive waits (OMP_WAIT_POLICY) each
    parallel torch op wakes a sleeping thread, and for ops as small as a training step's the wake-up costs more
    than the second thread saves."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _host(x: Tensor) -> np.ndarray:
    """numpy view for cheap checks: small torch ops cost 15-30x more CPU beside numba's thread pool."""
    return x.detach().cpu().numpy()


EXPONENT_BITS = {np.dtype(np.float32): (np.uint32, np.uint32(0x7F800000)),
                 np.dtype(np.float64): (np.uint64, np.uint64(0x7FF0000000000000))}


def _all_finite(a: np.ndarray) -> bool:
    if a.dtype not in EXPONENT_BITS:
        return bool(np.isfinite(a).all())
    bits, exponent = EXPONENT_BITS[a.dtype]
    return bool(_kernels.all_finite(np.ascontiguousarray(a).reshape(-1).view(bits), exponent))


def _check_finite(name: str, x: Tensor) -> None:
    if not torch.is_tensor(x):
        raise BadInputError(f"rasterization: {name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise BadInputError(f"rasterization: {name} must be a floating-point tensor, got {x.dtype}")
    if not _all_finite(_host(x)):
        raise BadInputError(f"rasterization: {name} contains NaN or inf")


def _validate(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, viewmats: Tensor,
              Ks: Tensor, width: int, height: int, sh_degree: int | None, backgrounds: Tensor | None,
              extra: Tensor | None = None) -> None:
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
             "viewmats": viewmats, "Ks": Ks}
    if backgrounds is not None:
        named["backgrounds"] = backgrounds
    if extra is not None:
        named["extra"] = extra
    for name, x in named.items():
        _check_finite(name, x)
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
    for name, shape in expected.items():
        if tuple(named[name].shape) != shape or n < 0:
            raise BadInputError(f"rasterization: {name} must have shape {shape} for N={n}, got {tuple(named[name].shape)}")
    if extra is not None and (extra.dim() != 2 or extra.shape[0] != n):
        raise BadInputError(f"rasterization: extra must be [N, E] for N={n}, got {tuple(extra.shape)}")
    if sh_degree is None:
        if tuple(colors.shape) != (n, 3):
            raise BadInputError(f"rasterization: colors must be [N, 3] RGB without sh_degree, got {tuple(colors.shape)}")
    else:
        if not 0 <= sh_degree <= 3:
            raise BadInputError(f"rasterization: sh_degree must be 0..3, got {sh_degree}")
        if colors.dim() != 3 or colors.shape[0] != n or colors.shape[2] != 3 or colors.shape[1] < (sh_degree + 1) ** 2:
            raise BadInputError(f"rasterization: colors must be [N, K>={(sh_degree + 1) ** 2}, 3] SH coefficients "
                                f"for sh_degree={sh_degree}, got {tuple(colors.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise BadInputError(f"rasterization: viewmats must be [C, 4, 4], got {tuple(viewmats.shape)}")
    if tuple(Ks.shape) != (viewmats.shape[0], 3, 3):
        raise BadInputError(f"rasterization: Ks must be [C, 3, 3] matching viewmats, got {tuple(Ks.shape)}")
    if backgrounds is not None and tuple(backgrounds.shape) != (viewmats.shape[0], 3):
        raise BadInputError(f"rasterization: backgrounds must be [C, 3], got {tuple(backgrounds.shape)}")
    if int(width) < 1 or int(height) < 1:
        raise BadInputError(f"rasterization: width and height must be >= 1, got {width}x{height}")
    if (_host(scales) < 0).any():
        raise BadInputError("rasterization: scales must be linear and >= 0 (exp() log-scales first)")
    op = _host(opacities)
    if (op < 0).any() or (op > 1).any():
        raise BadInputError("rasterization: opacities must lie in [0, 1]")
    zero = _host(quats) == 0
    if zero.any() and zero.all(axis=-1).any():  # the row test only then: reducing 4-wide rows costs 0.4 ms at 25k
        raise BadInputError("rasterization: quats contains a zero quaternion")


def _resolve_backend(backend: Backend, device: torch.device) -> str:
    if backend not in ("auto", "cpu", "torch", "gsplat"):
        raise BadInputError(f"rasterization: unknown backend {backend!r}")
    if backend == "auto":
        if device.type == "cuda":
            try:
                import gsplat  # noqa: F401
            except ImportError:
                return "torch"
            return "gsplat"
        return "cpu"
    if backend == "gsplat" and device.type != "cuda":
        raise BadInputError("rasterization: backend='gsplat' needs CUDA tensors")
    return backend


def rasterization(
    means: Tensor,        # [N, 3] world
    quats: Tensor,        # [N, 4] wxyz, unnormalised
    scales: Tensor,       # [N, 3] linear scales
    opacities: Tensor,    # [N] in [0, 1]
    colors: Tensor,       # [N, 3] RGB, or [N, K, 3] SH coefficients with sh_degree
    viewmats: Tensor,     # [C, 4, 4] world-to-camera, OpenCV
    Ks: Tensor,           # [C, 3, 3]
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: Tensor | None = None,  # [C, 3]
    render_mode: RenderMode = "RGB",
    extra: Tensor | None = None,  # [N, E] per-Gaussian features composited beside the colour, background 0
    backend: Backend = "auto",
) -> tuple[Tensor, Tensor, dict]:
    """Render C cameras -> colours [C,H,W,3] (then E `extra` channels, then expected depth for "RGB+ED"),
    alphas [C,H,W,1], meta.

    `extra` composites any per-Gaussian quantity with the same weights as the colour, e.g. a 0/1 flag
    gives each pixel the weight of the flagged Gaussians (NGS: how much of the infill shows).

    Expected depth follows gsplat: sum(w_i z_i) / sum(w_i), i.e. normalised by the rendered alpha (0 where
    alpha is 0). meta holds "means2d" [C,N,2] (call .retain_grad() on it before backward for densification
    statistics), "radii" [C,N] int32 (0 = culled), "depths" [C,N], "width", "height".
    """
    _validate(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds, extra)
    if render_mode not in ("RGB", "RGB+ED"):
        raise BadInputError(f"rasterization: unknown render_mode {render_mode!r}")
    width, height = int(width), int(height)
    chosen = _resolve_backend(backend, means.device)
    if chosen == "gsplat":
        return _gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                       near_plane, far_plane, backgrounds, render_mode, extra)
    render, alphas, meta = _render(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                                   near_plane, far_plane, backgrounds, render_mode == "RGB+ED", chosen == "cpu", extra)
    if render_mode == "RGB+ED":
        depth = render[..., -1:] / alphas.clamp(min=1e-10)
        render = torch.cat([render[..., :-1], depth], dim=-1)
    meta.update(width=width, height=height)
    return render, alphas, meta


def _render(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, near_plane,
            far_plane, backgrounds, with_depth: bool, compiled: bool,
            extra: Tensor | None = None) -> tuple[Tensor, Tensor, dict]:
    if compiled:
        coeffs = colors if sh_degree is not None else colors[:, None, :]              # [N, K, 3]
        means2d, conics, depths, radii, sh_rgb = _Project.apply(
            means, quats, scales, coeffs, viewmats, ref.camera_centres(viewmats), Ks, width, height,
            -1 if sh_degree is None else sh_degree, near_plane, far_plane)             # [C,N,2], [C,N,3], [C,N], ...
    else:
        means2d, conics, depths, radii = ref.project(means, quats, scales, viewmats, Ks, width, height,
                                                     near_plane, far_plane)       # [C,N,2], [C,N,3], [C,N], [C,N]
    renders, alphas = [], []
    for c in range(viewmats.shape[0]):
        if sh_degree is None:
            rgb = colors                                                         # [N, 3]
        elif compiled:
            rgb = _camera(sh_rgb, c)                                             # [N, 3]
        else:
            dirs = means - ref.camera_centres(viewmats[c:c + 1])                  # [N, 3]
            rgb = ref.eval_sh(sh_degree, dirs, colors[:, : (sh_degree + 1) ** 2])
        parts = [rgb] + ([extra] if extra is not None else []) + ([depths[c, :, None]] if with_depth else [])
        feats = torch.cat(parts, dim=-1) if len(parts) > 1 else rgb                          # [N, D]
        bg = backgrounds[c] if backgrounds is not None else means.new_zeros(3)             # [3]
        bg = torch.cat([bg, bg.new_zeros(feats.shape[1] - 3)])                              # [D]
        if compiled:
            img, alpha = _Rasterize.apply(_camera(means2d, c), _camera(conics, c), feats, opacities, radii[c],
                                          _camera(depths, c), bg, width, height)
        else:
            img, alpha = ref.rasterize(means2d[c], conics[c], feats, opacities, depths[c], radii[c], width,
                                       height, bg)
        renders.append(img)
        alphas.append(alpha)
    meta = {"means2d": means2d, "radii": radii, "depths": depths}
    if len(renders) == 1:  # views, as in _camera
        return renders[0][None], alphas[0][None], meta
    return torch.stack(renders), torch.stack(alphas), meta


def _camera(per_camera: Tensor, c: int) -> Tensor:
    """Camera c's slice of a [C, ...] tensor; a view when C is 1, where indexing would zero-fill a
    [C, ...] gradient and copy into it on every backward."""
    return per_camera.squeeze(0) if per_camera.shape[0] == 1 else per_camera[c]


class _Project(torch.autograd.Function):
    """Fused numba EWA projection + SH colour for all cameras; hand-derived backward incl. the pose."""

    @staticmethod
    def forward(ctx, means: Tensor, quats: Tensor, scales: Tensor, coeffs: Tensor, viewmats: Tensor,
                campos: Tensor, Ks: Tensor, width: int, height: int, sh_degree: int, near: float, far: float):
        arrays = [t.detach().contiguous().numpy() for t in (means, quats, scales, coeffs)]
        cams = [t.detach().contiguous().numpy() for t in (viewmats, Ks, campos)]
        means2d, conics, depths, radii, colors = _project_kernels.project_fwd(
            *arrays, sh_degree, cams[0], cams[1], cams[2], width, height, near, far)
        ctx.state = (arrays, cams, width, height, sh_degree, radii, colors)
        ctx.mark_non_differentiable(radii_t := torch.from_numpy(radii))
        return (torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths), radii_t,
                torch.from_numpy(colors))

    @staticmethod
    def backward(ctx, g_means2d: Tensor, g_conics: Tensor, g_depths: Tensor, g_radii: Tensor, g_colors: Tensor):
        arrays, cams, width, height, sh_degree, radii, colors = ctx.state
        grads = _project_kernels.project_bwd(
            *arrays, sh_degree, cams[0], cams[1], cams[2], width, height, radii, colors,
            *(g.contiguous().numpy() for g in (g_means2d, g_conics, g_depths, g_colors)),
            ctx.needs_input_grad[4] or ctx.needs_input_grad[5])
        g_means, g_quats, g_scales, g_coeffs, g_viewmats, g_campos = (torch.from_numpy(g) for g in grads)
        # Ks, width, height, sh_degree, near, far get no gradient
        return g_means, g_quats, g_scales, g_coeffs, g_viewmats, g_campos, None, None, None, None, None, None


class _Rasterize(torch.autograd.Function):
    """numba tile compositing for one camera; backward reduces per-intersection gradients per Gaussian."""

    @staticmethod
    def forward(ctx, means2d: Tensor, conics: Tensor, feats: Tensor, opacities: Tensor, radii: Tensor,
                depths: Tensor, background: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
        arrays = [t.detach().contiguous().numpy() for t in (means2d, conics, feats, opacities)]
        fast = means2d.dtype == torch.float32
        bins = _kernels.bin_gaussians(arrays[0], arrays[1], arrays[3], radii.numpy(), depths.detach().numpy(), width,
                                      height)
        img, t_final, n_proc, taken = _kernels.rasterize_fwd(*arrays, bins[0], bins[1], bins[2], width, height, fast)
        bg = background.detach().numpy()
        ctx.state = (arrays, bg, bins, img, t_final, n_proc, taken, width, height, fast)
        img_t = torch.from_numpy(img)
        if bg.any():  # a black background (the trainer's) costs no image-sized ops
            img_t = img_t + torch.from_numpy(t_final)[..., None] * background
        # numpy, not torch, for the small image-sized ops here: beside numba's threads a torch op costs more
        return img_t, torch.from_numpy(1 - t_final)[..., None]                              # [H, W, 1]

    @staticmethod
    def backward(ctx, g_img: Tensor, g_alpha: Tensor):
        arrays, bg, bins, img, t_final, n_proc, taken, width, height, fast = ctx.state
        slots = _kernels.rasterize_bwd(*arrays, bg, bins[0], bins[1], taken, width, height, img, t_final, n_proc,
                                       g_img.contiguous().numpy(), g_alpha[..., 0].contiguous().numpy(), fast)
        g_means2d, g_conics, g_feats, g_opacities = (
            torch.from_numpy(g) for g in _kernels.reduce_per_gaussian(slots, bins[1], arrays[0].shape[0]))
        g_bg = (g_img * torch.from_numpy(t_final)[..., None]).sum((0, 1)) if ctx.needs_input_grad[6] else None
        # radii, depths (order only), width, height get no gradient
        return g_means2d, g_conics, g_feats, g_opacities, None, None, g_bg, None, None


def _gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, near_plane, far_plane,
            backgrounds, render_mode, extra) -> tuple[Tensor, Tensor, dict]:
    """CUDA path through gsplat (imported only here). Untested in this repository: no GPU in CI."""
    import gsplat

    if extra is not None:  # gsplat composites any channel count only for ready colours: evaluate SH here
        rgb = colors if sh_degree is None else torch.stack([
            ref.eval_sh(sh_degree, means - ref.camera_centres(viewmats[c:c + 1]), colors[:, : (sh_degree + 1) ** 2])
            for c in range(viewmats.shape[0])])
        rgb = rgb.expand(viewmats.shape[0], -1, -1)                                                # [C, N, 3]
        colors = torch.cat([rgb, extra.expand(viewmats.shape[0], -1, -1)], dim=-1)                 # [C, N, 3+E]
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(backgrounds.shape[0], extra.shape[1])], -1)
        sh_degree = None
    render, alphas, g_meta = gsplat.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=near_plane,
        far_plane=far_plane, sh_degree=sh_degree, backgrounds=backgrounds, render_mode=render_mode,
        eps2d=ref.EPS2D, packed=False, rasterize_mode="classic", tile_size=ref.TILE)
    radii = g_meta["radii"]
    if radii.dim() == 3:  # gsplat >= 1.5 returns per-axis radii [C, N, 2]
        radii = radii.amax(dim=-1)
    meta = {"means2d": g_meta["means2d"], "radii": radii.int(), "depths": g_meta["depths"],
            "width": width, "height": height}
    return render, alphas, meta


def _one_camera(caller: str, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor,
                K: Tensor, width: int, height: int, backend: Backend) -> str:
    """Validate a single-camera, colourless query; returns the backend to use."""
    if not (torch.is_tensor(viewmat) and tuple(viewmat.shape) == (4, 4)):
        raise BadInputError(f"{caller}: viewmat must be a [4, 4] tensor")
    if not (torch.is_tensor(K) and tuple(K.shape) == (3, 3)):
        raise BadInputError(f"{caller}: K must be a [3, 3] tensor")
    rgb = means.new_zeros(means.shape) if torch.is_tensor(means) and means.dim() == 2 else means
    _validate(means, quats, scales, opacities, rgb, viewmat[None], K[None], width, height, None, None)
    if backend == "auto":  # forward-only queries: the numba kernels on host copies, on any device
        return "cpu"
    return _resolve_backend(backend, means.device)


def _cpu_projected(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor,
                   width: int, height: int, near_plane: float) -> tuple[np.ndarray, ...]:
    """Project for one camera with the numba kernels -> means2d, conics, depths, radii, opacities."""
    gauss = [np.ascontiguousarray(_host(t)) for t in (means, quats, scales)]
    cams = [np.ascontiguousarray(_host(t[None])) for t in (viewmat, K, ref.camera_centres(viewmat[None])[0])]
    m2, conics, depths, radii, _ = _project_kernels.project_fwd(
        *gauss, np.zeros((means.shape[0], 1, 3), gauss[0].dtype), -1, *cams, width, height, near_plane, 1e10)
    return m2[0], conics[0], depths[0], radii[0], np.ascontiguousarray(_host(opacities))


def median_depth(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor, width: int,
    height: int, *, alpha_level: float | Tensor = 0.5, near_plane: float = 0.01, backend: Backend = "auto",
) -> Tensor:
    """Per pixel, the camera z of the Gaussian at which the rendered alpha reaches `alpha_level` (0.5: the
    median; or [H, W], one level a pixel) -> [H, W], +inf where it never does.

    Expected depth blends every Gaussian the ray passes, so on a splat surface several Gaussians deep it
    lies behind the first opaque layer (about 1.4 mm on our simulated stones); the median sits on it.
    Meshing uses it; forward only. Same skip and stop rules as `rasterization`.
    """
    chosen = _one_camera("median_depth", means, quats, scales, opacities, viewmat, K, width, height, backend)
    width, height = int(width), int(height)
    with torch.no_grad():
        if chosen != "cpu":
            m2, conics, depths, radii = ref.project(means, quats, scales, viewmat[None], K[None], width, height,
                                                    near_plane, 1e10)
            return ref.median_depth(m2[0], conics[0], opacities, depths[0], radii[0], width, height, alpha_level)
        m2, conics, depths, radii, opac = _cpu_projected(means, quats, scales, opacities, viewmat, K, width, height,
                                                         near_plane)
        bins = _kernels.bin_gaussians(m2, conics, opac, radii, depths, width, height)
        level = _host(alpha_level) if isinstance(alpha_level, Tensor) else alpha_level
        levels = np.empty((height, width), m2.dtype)  # always writable: a read-only array is another compile
        levels[...] = level
        out = _kernels.median_depth_fwd(m2, conics, opac, depths, bins[0], bins[1], bins[2], width, height, levels,
                                        means.dtype == torch.float32)
        return torch.from_numpy(out).to(means.device)


def seen_in_front(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor, width: int,
    height: int, depth: Tensor, *, near_plane: float = 0.01, backend: Backend = "auto",
) -> Tensor:
    """[N] bool: the Gaussians some pixel sees (alpha >= 1/255, compositing's skip rule) at a camera z below that
    pixel's `depth` [H, W] (+inf: anything there counts).

    NGS depth pruning asks it of the noise against the surface's depth. There is no stop rule: a Gaussian in
    front of the surface counts even where others in front of it have used up the transmittance. Forward only.
    """
    chosen = _one_camera("seen_in_front", means, quats, scales, opacities, viewmat, K, width, height, backend)
    width, height = int(width), int(height)
    if not (torch.is_tensor(depth) and tuple(depth.shape) == (height, width)):
        raise BadInputError(f"seen_in_front: depth must be a [{height}, {width}] tensor")
    with torch.no_grad():
        if chosen != "cpu":
            m2, conics, depths, radii = ref.project(means, quats, scales, viewmat[None], K[None], width, height,
                                                    near_plane, 1e10)
            return ref.seen_in_front(m2[0], conics[0], opacities, depths[0], radii[0], width, height,
                                     depth.to(means.device))
        m2, conics, depths, radii, opac = _cpu_projected(means, quats, scales, opacities, viewmat, K, width, height,
                                                         near_plane)
        limit = np.ascontiguousarray(_host(depth).astype(depths.dtype))
        return torch.from_numpy(_kernels.seen_in_front(m2, conics, opac, radii, depths, width, height, limit)).to(
            means.device)
