"""The CPU rasteriser agrees with the plain-torch reference, is differentiable everywhere and deterministic."""

import math

import numpy as np
import pytest
import torch

from station.errors import BadInputError
from station.ngs import _kernels
from station.ngs.raster import median_depth, rasterization, seen_in_front, set_num_threads
from station.ngs.raster_reference import project


def random_scene(n: int, width: int, height: int, *, cameras: int = 1, sh_degree: int | None = 3, seed: int = 0,
                 dtype: torch.dtype = torch.float32) -> dict:
    """Gaussians in [-1,1]^3 seen from cameras about 4 units away (OpenCV convention)."""
    g = torch.Generator().manual_seed(seed)
    viewmats = torch.eye(4).repeat(cameras, 1, 1)
    for c in range(cameras):
        angle = 0.3 * c
        viewmats[c, 0, 0], viewmats[c, 0, 2] = math.cos(angle), -math.sin(angle)
        viewmats[c, 2, 0], viewmats[c, 2, 2] = math.sin(angle), math.cos(angle)
        viewmats[c, :3, 3] = torch.tensor([0.1 * c, -0.05, 4.0])
    f = 1.2 * width
    Ks = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]]).repeat(cameras, 1, 1)
    colors = (torch.rand(n, 3, generator=g) if sh_degree is None
              else 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g))
    scene = {
        "means": torch.rand(n, 3, generator=g) * 2 - 1,
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.exp(torch.randn(n, 3, generator=g) * 0.4 - 2.3),
        "opacities": torch.sigmoid(torch.randn(n, generator=g) + 0.5),
        "colors": colors,
        "viewmats": viewmats,
        "Ks": Ks,
    }
    return {k: v.to(dtype) for k, v in scene.items()}


PARAMS = ("means", "quats", "scales", "opacities", "colors", "viewmats")


def render_with_grads(scene: dict, width: int, height: int, backend: str, **kwargs):
    leaves = {k: v.clone().requires_grad_(k in PARAMS) for k, v in scene.items()}
    img, alpha, meta = rasterization(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                     leaves["colors"], leaves["viewmats"], leaves["Ks"], width, height,
                                     backend=backend, **kwargs)
    meta["means2d"].retain_grad()
    weights = torch.linspace(-1, 1, img.numel(), dtype=img.dtype).reshape(img.shape)
    ((img * weights).sum() + (alpha * weights[..., :1]).sum()).backward()
    grads = {k: leaves[k].grad for k in PARAMS}
    grads["means2d"] = meta["means2d"].grad
    return img.detach(), alpha.detach(), meta, grads


def assert_rel_close(actual: torch.Tensor, expected: torch.Tensor, rel: float, name: str) -> None:
    """Max abs error at most rel times the largest magnitude of the expected tensor."""
    scale = expected.abs().max().item()
    err = (actual.double() - expected.double()).abs().max().item()
    assert err <= rel * max(scale, 1e-12), f"{name}: max error {err:.3g} vs scale {scale:.3g}"


@pytest.mark.parametrize("sh_degree,render_mode,with_bg", [(3, "RGB+ED", True), (None, "RGB", False),
                                                           (1, "RGB", True)])
def test_cpu_backend_matches_reference_images_and_gradients(sh_degree, render_mode, with_bg):
    width, height = 40, 36
    scene = random_scene(120, width, height, cameras=2, sh_degree=sh_degree, seed=1)
    kwargs = {"sh_degree": sh_degree, "render_mode": render_mode}
    if with_bg:
        kwargs["backgrounds"] = torch.tensor([[0.2, 0.4, 0.6], [1.0, 0.0, 0.5]])
    ref_scene = {k: v.double() for k, v in scene.items()}
    ref_kwargs = {**kwargs, "backgrounds": kwargs["backgrounds"].double()} if with_bg else kwargs
    img, alpha, meta, grads = render_with_grads(scene, width, height, "cpu", **kwargs)
    ref_img, ref_alpha, ref_meta, ref_grads = render_with_grads(ref_scene, width, height, "torch", **ref_kwargs)
    assert img.dtype == torch.float32 and alpha.mean() > 0.2
    torch.testing.assert_close(img[..., :3].double(), ref_img[..., :3], atol=1e-5, rtol=0)
    torch.testing.assert_close(alpha.double(), ref_alpha, atol=1e-5, rtol=0)
    if render_mode == "RGB+ED":
        torch.testing.assert_close(img[..., 3].double(), ref_img[..., 3], atol=1e-5 * 5.0, rtol=1e-5)
    assert torch.equal(meta["radii"], ref_meta["radii"])
    for name in (*PARAMS, "means2d"):
        assert_rel_close(grads[name], ref_grads[name], 1e-4, name)


def test_gaussians_hidden_behind_opaque_walls_get_no_gradient_and_the_rest_match_the_reference():
    """The projection's backward skips Gaussians that no pixel reached in a view; that changes no gradient."""
    width, height = 40, 36
    scene = random_scene(120, width, height, cameras=2, sh_degree=1, seed=2)
    walls = 3  # three layers at the alpha cap take every pixel behind them below the stopping transmittance
    extra = {"means": torch.tensor([[0.0, 0.0, -1.6 - 0.05 * i] for i in range(walls)]),
             "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(walls, 1),
             "scales": torch.tensor([[20.0, 20.0, 0.01]]).repeat(walls, 1),
             "opacities": torch.full((walls,), 0.999),
             "colors": torch.full((walls, 4, 3), 0.2)}
    scene.update({k: torch.cat([scene[k], v]) for k, v in extra.items()})
    _, alpha, _, grads = render_with_grads(scene, width, height, "cpu", sh_degree=1)
    _, _, _, ref_grads = render_with_grads({k: v.double() for k, v in scene.items()}, width, height, "torch",
                                           sh_degree=1)
    hidden = (grads["means2d"] == 0).all(-1).all(0)  # [N]: reached no pixel in either view
    hidden[-walls:] = False
    assert hidden.sum() > 50 and alpha.min() > 0.98
    for name in ("means", "quats", "scales", "colors"):
        assert (grads[name][hidden] == 0).all()
    for name in ("means", "quats", "scales", "opacities", "colors"):  # the walls' own float32 gradients are coarse
        assert_rel_close(grads[name][:-walls], ref_grads[name][:-walls], 1e-4, name)
    assert_rel_close(grads["means2d"][:, :-walls], ref_grads["means2d"][:, :-walls], 1e-4, "means2d")


@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
def test_extra_channels_composite_with_the_colour_weights_and_agree_with_the_reference(render_mode):
    width, height = 40, 36
    scene = random_scene(120, width, height, cameras=2, sh_degree=1, seed=4)
    flag = (torch.arange(120) % 3 == 0).float()[:, None]                              # [N, 1]
    outputs = {}
    for backend, dtype in (("cpu", torch.float32), ("torch", torch.float64)):
        leaves = {k: v.to(dtype).clone().requires_grad_(k == "opacities") for k, v in scene.items()}
        img, alpha, _ = rasterization(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                      leaves["colors"], leaves["viewmats"], leaves["Ks"], width, height,
                                      sh_degree=1, render_mode=render_mode, extra=flag.to(dtype), backend=backend)
        (img[..., 3].sum() * 2 - alpha.sum()).backward()
        outputs[backend] = (img.detach(), alpha.detach(), leaves["opacities"].grad)
    img, alpha, grad = outputs["cpu"]
    ref_img, ref_alpha, ref_grad = outputs["torch"]
    assert img.shape == (2, height, width, 5 if render_mode == "RGB+ED" else 4)
    torch.testing.assert_close(img[..., :4].double(), ref_img[..., :4], atol=1e-5, rtol=0)
    assert_rel_close(grad, ref_grad, 1e-4, "opacities")
    assert (img[..., 3] <= alpha[..., 0] + 1e-6).all() and img[..., 3].max() > 0.1  # a share of the alpha
    plain, _, _ = rasterization(*(scene[k] for k in ("means", "quats", "scales", "opacities", "colors",
                                                     "viewmats", "Ks")), width, height, sh_degree=1,
                                render_mode=render_mode, backend="cpu")
    torch.testing.assert_close(img[..., :3], plain[..., :3])
    if render_mode == "RGB+ED":
        torch.testing.assert_close(img[..., 4], plain[..., 3])


def test_extra_channels_must_be_one_row_per_gaussian():
    scene = random_scene(10, 16, 16, sh_degree=None)
    with pytest.raises(BadInputError, match="extra must be"):
        rasterization(*(scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")),
                      16, 16, extra=torch.ones(9, 1))


def test_gradcheck_float64_on_a_tiny_scene():
    width, height = 20, 16
    scene = random_scene(4, width, height, sh_degree=2, seed=3, dtype=torch.float64)
    scene["means"][:, :2] *= 0.5
    scene["scales"] = scene["scales"] * 2.0
    inputs = tuple(scene[k].clone().requires_grad_(True) for k in PARAMS)

    def render(means, quats, scales, opacities, colors, viewmats):
        img, alpha, _ = rasterization(means, quats, scales, opacities, colors, viewmats, scene["Ks"], width, height,
                                      sh_degree=2, render_mode="RGB+ED", backend="cpu",
                                      backgrounds=torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64))
        return img, alpha

    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


def test_gradients_are_bitwise_deterministic():
    scene = random_scene(300, 64, 48, seed=2)
    first = render_with_grads(scene, 64, 48, "cpu", sh_degree=3)[3]
    second = render_with_grads(scene, 64, 48, "cpu", sh_degree=3)[3]
    for name in PARAMS:
        assert torch.equal(first[name], second[name]), name


def test_meta_carries_means2d_radii_depths_and_size():
    scene = random_scene(50, 32, 24, cameras=3, seed=4)
    _, alpha, meta, grads = render_with_grads(scene, 32, 24, "auto", sh_degree=3)
    assert alpha.shape == (3, 24, 32, 1)
    assert meta["means2d"].shape == (3, 50, 2) and grads["means2d"].shape == (3, 50, 2)
    assert meta["radii"].shape == (3, 50) and meta["radii"].dtype == torch.int32
    assert meta["depths"].shape == (3, 50) and (meta["width"], meta["height"]) == (32, 24)
    visible = meta["radii"] > 0
    assert visible.any() and (grads["means2d"][~visible] == 0).all()


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_seen_in_front_marks_what_some_pixel_sees_nearer_than_its_limit(backend):
    width, height = 48, 40
    scene = random_scene(150, width, height, seed=5, sh_degree=None, dtype=torch.float64)
    args = (scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["viewmats"][0],
            scene["Ks"][0], width, height)
    m2, conics, depths, radii = project(*(scene[k] for k in ("means", "quats", "scales", "viewmats", "Ks")),
                                        width, height, 0.01, 1e10)
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    dx = m2[0, :, 0] - (xs.reshape(-1, 1) + 0.5)                                      # [P, N]
    dy = m2[0, :, 1] - (ys.reshape(-1, 1) + 0.5)
    c = conics[0]
    sigma = 0.5 * (c[:, 0] * dx * dx + c[:, 2] * dy * dy) + c[:, 1] * dx * dy
    alpha = torch.clamp_max(scene["opacities"] * torch.exp(-sigma), 0.99)
    # the tiles binning gives a Gaussian hold every pixel it reaches here: its 3-sigma radius covers them
    seen = (sigma >= 0) & (alpha >= 1 / 255) & (radii[0] > 0)                           # [P, N]
    limit = 3.0 + 2.0 * torch.rand(height, width, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    expected = (seen & (depths[0] < limit.reshape(-1, 1))).any(dim=0)
    marked = seen_in_front(*args, limit, backend=backend)
    assert 0 < expected.sum() < seen.any(dim=0).sum()  # the limits hide some Gaussians and not others
    assert marked.tolist() == expected.tolist()
    assert seen_in_front(*args, torch.full((height, width), math.inf), backend=backend).tolist() == seen.any(0).tolist()
    assert not seen_in_front(*args, torch.zeros(height, width), backend=backend).any()



def test_median_depth_agrees_with_the_reference_and_is_infinite_where_alpha_stays_below_half():
    scene = random_scene(200, 48, 40, sh_degree=None, seed=5, dtype=torch.float64)
    args = [scene[k] for k in ("means", "quats", "scales", "opacities")] + [scene["viewmats"][0], scene["Ks"][0], 48, 40]
    cpu, reference = median_depth(*args, backend="cpu"), median_depth(*args, backend="torch")
    _, alpha, _ = rasterization(*(scene[k] for k in ("means", "quats", "scales", "opacities", "colors",
                                                     "viewmats", "Ks")), 48, 40, backend="cpu")
    assert torch.equal(torch.isinf(cpu), torch.isinf(reference))
    torch.testing.assert_close(cpu[torch.isfinite(cpu)], reference[torch.isfinite(reference)], atol=1e-9, rtol=0)
    assert torch.equal(torch.isfinite(cpu), alpha[0, ..., 0] >= 0.5)


def test_depth_at_a_per_pixel_alpha_level_agrees_with_the_reference():
    scene = random_scene(200, 48, 40, sh_degree=None, seed=6, dtype=torch.float64)
    args = [scene[k] for k in ("means", "quats", "scales", "opacities")] + [scene["viewmats"][0], scene["Ks"][0], 48, 40]
    levels = torch.linspace(0.01, 0.9, 48 * 40, dtype=torch.float64).reshape(40, 48)
    cpu = median_depth(*args, alpha_level=levels, backend="cpu")
    reference = median_depth(*args, alpha_level=levels, backend="torch")
    assert torch.isfinite(cpu).any() and torch.isinf(cpu).any()
    assert torch.equal(torch.isinf(cpu), torch.isinf(reference))
    torch.testing.assert_close(cpu[torch.isfinite(cpu)], reference[torch.isfinite(reference)], atol=1e-9, rtol=0)
    assert not torch.equal(torch.isfinite(cpu), torch.isfinite(median_depth(*args, backend="cpu")))
    float64 = [sig for sig in _kernels.median_depth_fwd.signatures if sig[0].dtype.name == "float64"]
    assert len(float64) == 1, float64  # a scalar level and a per-pixel one share one compiled kernel


def test_median_depth_sits_on_the_first_opaque_layer_where_expected_depth_does_not():
    """Two stacked layers of flat Gaussians at z = 4 and z = 4.05: the median is on the front one."""
    xs, ys = torch.meshgrid(torch.linspace(-0.6, 0.6, 13), torch.linspace(-0.6, 0.6, 13), indexing="xy")
    layer = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.zeros(169)], -1)
    means = torch.cat([layer + torch.tensor([0, 0, 4.0]), layer + torch.tensor([0, 0, 4.05])])
    n = len(means)
    quats, scales = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.tensor([[0.08, 0.08, 0.005]]).repeat(n, 1)
    opacities, viewmat = torch.full((n,), 0.2), torch.eye(4)  # the front layer alone reaches alpha 0.71
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    median = median_depth(means, quats, scales, opacities, viewmat, K, 32, 32)
    colors, _, _ = rasterization(means, quats, scales, opacities, torch.rand(n, 3), viewmat[None], K[None], 32, 32,
                                 render_mode="RGB+ED")
    centre = (slice(12, 20), slice(12, 20))
    assert torch.allclose(median[centre], torch.tensor(4.0), atol=1e-6)
    assert (colors[0, ..., 3][centre] > 4.01).all()  # a fifth of the way to the back layer


def test_cpu_and_reference_seen_in_front_agree_in_float32():
    scene = random_scene(300, 40, 32, seed=6, sh_degree=None)
    limit = 3.0 + 2.0 * torch.rand(32, 40, generator=torch.Generator().manual_seed(2))
    args = (scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["viewmats"][0],
            scene["Ks"][0], 40, 32, limit)
    cpu, ref = seen_in_front(*args, backend="cpu"), seen_in_front(*args, backend="torch")
    assert cpu.any() and not cpu.all() and torch.equal(cpu, ref)


def test_seen_in_front_refuses_a_depth_map_of_the_wrong_size():
    scene = random_scene(5, 16, 16, sh_degree=None)
    with pytest.raises(BadInputError, match=r"depth must be a \[16, 16\] tensor"):
        seen_in_front(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["viewmats"][0],
                      scene["Ks"][0], 16, 16, torch.zeros(16 * 16))


def test_gsplat_backend_on_cpu_tensors_is_refused():
    scene = random_scene(5, 16, 16, sh_degree=None)
    with pytest.raises(BadInputError, match="CUDA"):
        rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                      scene["viewmats"], scene["Ks"], 16, 16, backend="gsplat")


def test_thread_pools_are_sized_together():
    import numba

    before = (numba.get_num_threads(), torch.get_num_threads())
    try:
        set_num_threads(1)
        assert numba.get_num_threads() == 1 and torch.get_num_threads() == 1
    finally:
        numba.set_num_threads(before[0])
        torch.set_num_threads(before[1])
    with pytest.raises(BadInputError, match="threads must be >= 1"):
        set_num_threads(0)


def test_depth_order_is_a_stable_argsort_with_ties_and_signed_zeros():
    rng = np.random.default_rng(0)
    cases = [rng.normal(3, 1, 5000), np.round(rng.normal(0, 2, 3000), 1), np.array([2.0, -0.0, 0.0, -1e-30, 5.0, -7.0]),
             np.array([]), np.full(9, 0.5), np.array([1.0]), rng.uniform(0.3, 0.31, 4000)]
    for depths in cases:
        for dtype in (np.float32, np.float64):
            d = depths.astype(dtype)
            np.testing.assert_array_equal(_kernels.depth_order(d), np.argsort(d, kind="stable"))


def test_gradients_are_the_same_whether_or_not_the_pose_needs_one():
    """Without a pose gradient the projection's backward skips the pose partials; nothing else may change."""
    scene = random_scene(300, 48, 40, cameras=2)
    runs = []
    for pose in (True, False):
        leaves = {k: v.clone().requires_grad_(k in PARAMS and (pose or k != "viewmats")) for k, v in scene.items()}
        img, alpha, _ = rasterization(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                      leaves["colors"], leaves["viewmats"], leaves["Ks"], 48, 40, sh_degree=3,
                                      backend="cpu")
        weights = torch.linspace(-1, 1, img.numel()).reshape(img.shape)
        ((img * weights).sum() + alpha.sum()).backward()
        runs.append({k: leaves[k].grad for k in PARAMS})
    assert runs[0]["viewmats"].abs().sum() > 0 and runs[1]["viewmats"] is None
    for k in PARAMS[:-1]:
        torch.testing.assert_close(runs[1][k], runs[0][k], rtol=0, atol=0)


def test_gradcheck_float64_of_the_background():
    """The background's gradient is computed only when it needs one; then it must be right."""
    width, height = 20, 16
    scene = random_scene(4, width, height, sh_degree=None, seed=3, dtype=torch.float64)
    background = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64, requires_grad=True)

    def render(bg):
        img, _, _ = rasterization(*(scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats",
                                                       "Ks")), width, height, backend="cpu", backgrounds=bg)
        return img

    assert torch.autograd.gradcheck(render, (background,), eps=1e-6, atol=1e-5, rtol=1e-3)
