"""Hard cases of the rasteriser, each with an asserted outcome, on both the numba and the reference backend."""

import math

import numpy as np
import pytest
import torch

from station.errors import BadInputError
from station.ngs import _kernels, _project_kernels
from station.ngs.conventions import TILE
from station.ngs.raster import rasterization, seen_in_front

BACKENDS = ["cpu", "torch"]


def camera(width: int, height: int, focal: float = 40.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Identity pose (camera at the origin looking down +z) and a centred pinhole."""
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    return torch.eye(4)[None], K[None]


def gaussians(means, scales, opacities, colors=None) -> list[torch.Tensor]:
    means = torch.tensor(means, dtype=torch.float32).reshape(-1, 3)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    scales = torch.tensor(scales, dtype=torch.float32).reshape(-1, 3).expand(n, 3).contiguous()
    opacities = torch.tensor(opacities, dtype=torch.float32).reshape(-1).expand(n).contiguous()
    colors = torch.ones(n, 3) if colors is None else torch.tensor(colors, dtype=torch.float32)
    return [means, quats, scales, opacities, colors]


def render(params, width=24, height=20, backend="cpu", **kwargs):
    viewmats, Ks = camera(width, height)
    return rasterization(*params, viewmats, Ks, width, height, backend=backend, **kwargs)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussians_at_inside_and_behind_the_near_plane_are_culled(backend):
    params = gaussians([[0, 0, 0.5], [0, 0, 0.25], [0, 0, -1.0], [0, 0, 0.0]], [0.05, 0.05, 0.05], [0.9])
    img, alpha, meta = render(params, backend=backend, near_plane=0.5)
    assert meta["radii"].tolist() == [[0, 0, 0, 0]]
    assert (alpha == 0).all() and (img == 0).all()


def test_culled_gaussians_on_behind_and_inside_the_near_plane_get_exactly_zero_gradient():
    """The projection's backward runs its geometry for every Gaussian, drawn or not, and drops the undrawn ones'
    terms: a Gaussian on the camera plane must not put a NaN into them."""
    culled = [[0, 0, 0.0], [0, 0, -1.0], [0, 0, 0.25], [0.3, -0.2, 0.0]]
    params = [p.requires_grad_(True) for p in gaussians(culled + [[0, 0, 2.0]], [0.05, 0.05, 0.05], [0.9])]
    img, alpha, meta = render(params, near_plane=0.5)
    (img.sum() + alpha.sum()).backward()
    assert meta["radii"][0].tolist()[:4] == [0, 0, 0, 0] and meta["radii"][0, 4] > 0
    for name, p in zip(("means", "quats", "scales", "opacities", "colors"), params):
        assert torch.isfinite(p.grad).all(), name
        assert (p.grad[:4] == 0).all(), name
    assert params[0].grad[4].abs().sum() > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_gaussian_just_beyond_the_near_plane_is_drawn(backend):
    params = gaussians([[0, 0, 0.55]], [0.02, 0.02, 0.02], [0.9])
    _, alpha, meta = render(params, backend=backend, near_plane=0.5)
    assert meta["radii"][0, 0] > 0 and alpha.max() > 0.5


@pytest.mark.parametrize("scales", [[0.3, 0.0, 0.3], [0.0, 0.0, 0.4]], ids=["flat", "needle"])
def test_degenerate_covariances_render_finite_and_match_the_reference(scales):
    params = gaussians([[0, 0, 3.0], [0.2, 0.1, 4.0]], scales, [0.8])
    outs = {}
    for backend in BACKENDS:
        leaves = [p.clone().requires_grad_(True) for p in params]
        img, alpha, _ = render(leaves, backend=backend)
        (img.sum() + alpha.sum()).backward()
        outs[backend] = (img.detach(), alpha.detach(), [p.grad for p in leaves])
    img, alpha, grads = outs["cpu"]
    assert alpha.max() > 0.3, "the 0.3 px low-pass keeps a zero-thickness Gaussian visible"
    assert all(torch.isfinite(g).all() for g in grads)
    torch.testing.assert_close(img, outs["torch"][0], atol=1e-5, rtol=0)
    torch.testing.assert_close(alpha, outs["torch"][1], atol=1e-5, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_gaussian_covering_the_whole_image_reaches_every_pixel(backend):
    params = gaussians([[0, 0, 2.0]], [50.0, 50.0, 50.0], [0.5])
    _, alpha, _ = render(params, backend=backend)
    torch.testing.assert_close(alpha, torch.full_like(alpha, 0.5), atol=1e-3, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_alpha_saturates_at_099_and_compositing_stops_before_t_reaches_1e4(backend):
    params = gaussians([[0, 0, 2.0], [0, 0, 2.5], [0, 0, 3.0]], [1.0, 1.0, 1.0], [1.0],
                       colors=[[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    params[3] = torch.tensor([1.0, 0.9, 1.0])
    img, alpha, _ = render(params, width=16, height=16, backend=backend)
    centre = (0, 8, 8)
    # pixel centre (8.5, 8.5) is half a pixel off each mean; 2D variance = (f s / z)^2 + 0.3 low-pass
    a2 = 0.9 * math.exp(-0.5 * 0.5 / ((40 * 1.0 / 2.5) ** 2 + 0.3))
    # the first saturates at 0.99 (opacity 1); after the second T = 0.01 (1 - a2) ~ 1e-3, and the third
    # (alpha 0.99) would bring T below 1e-4, so it is never composited
    torch.testing.assert_close(alpha[centre].double(), torch.tensor([0.99 + 0.01 * a2], dtype=torch.float64),
                               atol=1e-6, rtol=0)
    torch.testing.assert_close(img[centre].double(), torch.tensor([0.99, 0.01 * a2, 0.0], dtype=torch.float64),
                               atol=1e-6, rtol=0)
    # depth pruning asks what lies in front at all: the third counts there although compositing stops before it
    viewmats, Ks = camera(16, 16)
    for limit, seen in ((3.5, [True, True, True]), (2.75, [True, True, False])):
        depth = torch.full((16, 16), limit)
        assert seen_in_front(*params[:4], viewmats[0], Ks[0], 16, 16, depth, backend=backend).tolist() == seen


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_empty_scene_renders_the_background_with_empty_gradients(backend):
    params = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    params = [p.requires_grad_(True) for p in params]
    bg = torch.tensor([[0.1, 0.2, 0.3]])
    img, alpha, meta = render(params, backend=backend, backgrounds=bg)
    img.sum().backward()
    assert (alpha == 0).all() and torch.equal(img, bg.expand(1, 20, 24, 3))
    assert meta["means2d"].shape == (1, 0, 2) and params[0].grad.shape == (0, 3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_single_pixel_image_renders_the_gaussian_in_front_of_it(backend):
    params = gaussians([[0, 0, 2.0], [0, 0, 3.0]], [0.05, 0.05, 0.05], [0.5], colors=[[1, 0, 0], [0, 0, 1]])
    img, alpha, _ = render(params, width=1, height=1, backend=backend)
    assert img.shape == (1, 1, 1, 3)
    torch.testing.assert_close(alpha[0, 0, 0], torch.tensor([0.75]), atol=1e-5, rtol=0)
    torch.testing.assert_close(img[0, 0, 0], torch.tensor([0.5, 0.0, 0.25]), atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "backgrounds"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_or_inf_in_any_input_is_a_bad_input_error_naming_it(name, bad):
    means, quats, scales, opacities, colors = gaussians([[0, 0, 2.0]], [0.1, 0.1, 0.1], [0.5])
    viewmats, Ks = camera(8, 8)
    inputs = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
              "viewmats": viewmats, "Ks": Ks, "backgrounds": torch.zeros(1, 3)}
    inputs[name] = inputs[name].clone()
    inputs[name].view(-1)[0] = bad
    with pytest.raises(BadInputError, match=rf"\b{name}\b contains NaN or inf"):
        rasterization(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"], inputs["colors"],
                      inputs["viewmats"], inputs["Ks"], 8, 8, backgrounds=inputs["backgrounds"])


# The check runs before any backend. float64 renders with the torch reference: the numba backend would compile
# its float64 kernels here only to show that huge values pass.
@pytest.mark.parametrize(("dtype", "backend"), [(torch.float32, "cpu"), (torch.float64, "torch")])
def test_nan_or_inf_anywhere_in_a_million_sh_coefficients_is_found(dtype, backend):
    """Large inputs are checked in parallel chunks: a bad value in the first, a middle or the last one is found,
    and huge but finite values pass."""
    n = 70_000                                                              # 70k x 16 x 3: past the serial limit
    means, quats, scales, opacities, _ = gaussians(np.zeros((n, 3)) + [0, 0, 2.0], [0.01, 0.01, 0.01], [0.5])
    viewmats, Ks = camera(8, 8)
    sh = torch.full((n, 16, 3), torch.finfo(dtype).max, dtype=dtype)
    args = [means.to(dtype), quats.to(dtype), scales.to(dtype), opacities.to(dtype)]
    rasterization(*args, sh, viewmats.to(dtype), Ks.to(dtype), 8, 8, sh_degree=3, backend=backend)
    for at in (0, sh.numel() // 2 + 5, sh.numel() - 1):
        for bad in (float("nan"), float("inf"), -float("inf")):
            spoilt = sh.clone()
            spoilt.view(-1)[at] = bad
            with pytest.raises(BadInputError, match="colors contains NaN or inf"):
                rasterization(*args, spoilt, viewmats.to(dtype), Ks.to(dtype), 8, 8, sh_degree=3, backend=backend)


def test_log_scales_and_opacities_out_of_range_are_refused():
    means, quats, scales, opacities, colors = gaussians([[0, 0, 2.0]], [0.1, 0.1, 0.1], [0.5])
    viewmats, Ks = camera(8, 8)
    with pytest.raises(BadInputError, match="scales must be linear"):
        rasterization(means, quats, -scales, opacities, colors, viewmats, Ks, 8, 8)
    with pytest.raises(BadInputError, match="opacities must lie in"):
        rasterization(means, quats, scales, opacities + 1, colors, viewmats, Ks, 8, 8)


def test_a_zero_quaternion_is_refused_and_one_with_zero_components_is_not():
    means, quats, scales, opacities, colors = gaussians([[0, 0, 2.0], [0.1, 0, 2.0]], [0.1, 0.1, 0.1], [0.5, 0.5])
    viewmats, Ks = camera(8, 8)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -0.0, 1.0]])
    rasterization(means, quats, scales, opacities, colors, viewmats, Ks, 8, 8)
    quats[1] = torch.tensor([0.0, -0.0, 0.0, 0.0])
    with pytest.raises(BadInputError, match="zero quaternion"):
        rasterization(means, quats, scales, opacities, colors, viewmats, Ks, 8, 8)


def test_row_culling_drops_only_rows_that_composite_nothing():
    """The kernels skip the tile rows and strips outside each Gaussian's alpha >= 1/255 ellipse; on thin, tilted,
    huge and barely visible Gaussians that must give the same image, stopping points and gradients as no culling."""
    g = torch.Generator().manual_seed(5)
    n, width, height = 300, 64, 48
    means = torch.rand(n, 3, generator=g) * torch.tensor([2.0, 1.6, 1.0]) + torch.tensor([-1.0, -0.8, 2.5])
    scales = torch.exp(torch.randn(n, 3, generator=g) * 1.2 - 3.0)
    scales[::3, 0] *= 30.0                                                     # needles
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.rand(n, generator=g)
    opacities[::7] = 1.2 / 255.0                                               # barely above the skip threshold
    colors = torch.rand(n, 3, generator=g)
    viewmats, Ks = camera(width, height, focal=50.0)
    campos = torch.zeros(1, 3)
    m2, conics, depths, radii, rgb = _project_kernels.project_fwd(
        means.numpy(), quats.numpy(), scales.numpy(), colors[:, None].numpy(), -1, viewmats.numpy(), Ks.numpy(),
        campos.numpy(), width, height, 0.01, 1e10)
    m2, conics, depths, radii, op, feats = m2[0], conics[0], depths[0], radii[0], opacities.numpy(), colors.numpy()
    bins = _kernels.bin_gaussians(m2, conics, op, radii, depths, width, height)
    tile_offsets, isect_gid, extents = bins
    reach = extents[np.unique(isect_gid)]                                   # half-widths of those binned to a tile
    assert (reach[:, 1] < TILE / 2).mean() > 0.5                           # most skip some rows of their tiles
    assert (reach[:, 0] < _kernels.STRIP / 2).mean() > 0.1                 # and some miss a whole strip
    outputs = {}
    every_row = np.tile(np.array([0, TILE] * _kernels.STRIPS, np.uint8), (len(isect_gid), 1))
    for name, extent in (("culled", extents), ("whole tile", np.full_like(extents, 1e30))):
        img, t_final, n_proc, taken = _kernels.rasterize_fwd(m2, conics, feats, op, tile_offsets, isect_gid, extent, width,
                                                             height, True)
        if name == "whole tile":  # and the backward walks every row, not only those the forward composited in
            taken = every_row
        g_img = np.linspace(-1, 1, img.size, dtype=np.float32).reshape(img.shape)
        slots = _kernels.rasterize_bwd(m2, conics, feats, op, np.zeros(3, np.float32), tile_offsets, isect_gid, taken,
                                       width, height, img, t_final, n_proc, g_img, np.ones_like(t_final), True)
        outputs[name] = (img, t_final, n_proc, slots)
    culled, whole = outputs["culled"], outputs["whole tile"]
    assert (1 - whole[1]).mean() > 0.3
    np.testing.assert_array_equal(culled[2], whole[2])
    np.testing.assert_allclose(culled[0], whole[0], atol=1e-6, rtol=0)
    np.testing.assert_allclose(culled[1], whole[1], atol=1e-6, rtol=0)
    np.testing.assert_allclose(culled[3], whole[3], atol=1e-5 * np.abs(whole[3]).max(), rtol=0)


def test_binning_lists_a_gaussian_in_every_tile_where_a_pixel_can_see_it_and_in_no_tile_it_cannot_reach():
    """Each tile's list holds, front to back, the Gaussians whose alpha >= 1/255 ellipse (sigma <= sig_max) meets the
    rectangle of its pixel centres: never fewer (a pixel would lose one), never one the rectangle misses, sampled
    every 1/8 pixel. Needles, tilted, huge and barely visible Gaussians, and ones straddling the image's edges."""
    g = torch.Generator().manual_seed(11)
    n, width, height = 400, 80, 56
    means = torch.rand(n, 3, generator=g) * torch.tensor([2.6, 2.0, 1.0]) + torch.tensor([-1.3, -1.0, 2.5])
    scales = torch.exp(torch.randn(n, 3, generator=g) * 1.2 - 3.0)
    scales[::3, 0] *= 30.0
    scales[::17] *= 40.0
    opacities = torch.rand(n, generator=g)
    opacities[::7] = 1.2 / 255.0
    viewmats, Ks = camera(width, height, focal=50.0)
    m2, conics, depths, radii, _ = _project_kernels.project_fwd(
        means.numpy(), torch.randn(n, 4, generator=g).numpy(), scales.numpy(), np.zeros((n, 1, 3), np.float32), -1,
        viewmats.numpy(), Ks.numpy(), np.zeros((1, 3), np.float32), width, height, 0.01, 1e10)
    m2, conics, depths, radii, op = m2[0], conics[0], depths[0], radii[0], opacities.numpy()
    tile_offsets, isect_gid, _ = _kernels.bin_gaussians(m2, conics, op, radii, depths, width, height)
    tw, th = -(-width // TILE), -(-height // TILE)
    fine = (np.arange(8 * (TILE - 1) + 1) / 8 + 0.5)[None, :]              # a tile's pixel-centre span, 1/8 pixel apart
    for t in range(tw * th):
        listed = isect_gid[tile_offsets[t]:tile_offsets[t + 1]]
        assert (np.diff(depths[listed]) >= 0).all()
        x, y = (t % tw) * TILE + fine, (t // tw) * TILE + fine.T
        seen = set()
        for i in np.flatnonzero(radii > 0):
            sig_max = _kernels._sig_max(op[i])
            dx, dy = m2[i, 0] - x.astype(np.float64), m2[i, 1] - y.astype(np.float64)
            sigma = 0.5 * (conics[i, 0] * dx * dx + conics[i, 2] * dy * dy) + conics[i, 1] * dx * dy
            on_pixels = sigma[::8, ::8]
            if sig_max >= 0 and (sigma <= sig_max).any():
                seen.add(i)
            if sig_max >= 0 and (on_pixels <= sig_max).any():
                assert i in listed, f"tile {t} drops Gaussian {i}"
        missed_by_the_samples = set(listed.tolist()) - seen
        assert len(missed_by_the_samples) <= 0.02 * len(listed) + 1       # between two samples of the rectangle
    assert len(isect_gid) > 2 * n


def test_the_fast_exp_is_within_1e6_of_exp_and_unbiased_wherever_alpha_can_reach_1_over_255():
    """The float32 kernels' polynomial exp(-sigma) against float64 exp, from sigma 0 to 6 (alpha = 1/255 at full
    opacity is sigma 5.54), and below 1/255 at any sigma past that, however far. An exp biased high by a few 1e-7
    (p(sigma / 8) ** 8, tried) lowered DTU scan65's held-out SOS in every run: real_dtu_scan65_ngs_at_748e147*."""
    radius = np.sqrt(np.concatenate([np.linspace(0, 6, 200_001), np.geomspace(6, 1e6, 1_000)])).astype(np.float32)
    n = radius.size
    alpha, expo = np.empty(n, np.float32), np.empty(n, np.float32)
    # one Gaussian at the origin with conic (2, 0, 2): sigma is the squared distance of each "pixel" on the x axis
    _kernels._alphas(np.float32(0), np.float32(0), np.float32(2), np.float32(0), np.float32(2), np.float32(1), -radius,
                     np.zeros(n, np.float32), alpha, expo, True, np.uint64(0), np.uint64(n))
    sigma = radius.astype(np.float64) ** 2
    near = sigma <= 6
    error = expo[near] / np.exp(-sigma[near]) - 1
    assert np.abs(error).max() < 1e-6 and abs(error.mean()) < 5e-8
    assert (alpha[~near] < 1 / 255).all() and (alpha == np.minimum(expo, np.float32(0.99))).all()


def test_the_compositing_kernels_refuse_fewer_than_the_three_colour_channels():
    """They carry red, green and blue in their own loops, so a two-channel feature array is refused, not misread."""
    m2, conics = np.full((1, 2), 4.0, np.float32), np.array([[1.0, 0.0, 1.0]], np.float32)
    op, two = np.ones(1, np.float32), np.ones((1, 2), np.float32)
    bins = _kernels.bin_gaussians(m2, conics, op, np.ones(1, np.int32), np.ones(1, np.float32), 8, 8)
    with pytest.raises(ValueError, match="three colour channels"):
        _kernels.rasterize_fwd(m2, conics, two, op, bins[0], bins[1], bins[2], 8, 8, True)
    img, t_final, n_proc, taken = _kernels.rasterize_fwd(m2, conics, np.ones((1, 3), np.float32), op, bins[0],
                                                         bins[1], bins[2], 8, 8, True)
    with pytest.raises(ValueError, match="three colour channels"):
        _kernels.rasterize_bwd(m2, conics, two, op, np.zeros(2, np.float32), bins[0], bins[1], taken, 8, 8,
                               img[..., :2].copy(), t_final, n_proc, np.ones((8, 8, 2), np.float32), t_final, True)
