"""The training SSIM: the numba kernels against the plain-torch reference, in value and gradient, on hard images."""

from __future__ import annotations

import pytest
import torch

from station.ngs.losses import SSIM_WINDOW, _FusedSSIM, image_loss, LossConfig, ssim, ssim_torch


def _images(height: int, width: int, channels: int = 3, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(height, width, channels, generator=g, dtype=torch.float64)
    return a, (0.7 * a + 0.3 * torch.rand(height, width, channels, generator=g, dtype=torch.float64)).clamp(0, 1)


def _value_and_grad(fn, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    a = a.detach().clone().requires_grad_()
    value = fn(a, b)
    value.backward()
    return value.detach(), a.grad


HARD = {
    "random": _images(37, 29),
    "one window": _images(SSIM_WINDOW, SSIM_WINDOW),
    "identical": (_images(20, 24)[0], _images(20, 24)[0]),
    "black": (torch.zeros(16, 18, 3, dtype=torch.float64), torch.zeros(16, 18, 3, dtype=torch.float64)),
    "saturated against black": (torch.ones(16, 18, 3, dtype=torch.float64), torch.zeros(16, 18, 3, dtype=torch.float64)),
    "textureless, two levels": (torch.full((15, 21, 3), 0.4, dtype=torch.float64),
                                torch.full((15, 21, 3), 0.6, dtype=torch.float64)),
    "one channel": _images(14, 30, channels=1),
}


@pytest.mark.parametrize("case", HARD)
def test_the_cpu_ssim_equals_the_torch_reference_in_value_and_gradient(case):
    a, b = HARD[case]
    value, grad = _value_and_grad(ssim, a, b)
    ref_value, ref_grad = _value_and_grad(ssim_torch, a, b)
    assert torch.isfinite(grad).all()
    torch.testing.assert_close(value, ref_value, rtol=0, atol=1e-12)
    torch.testing.assert_close(grad, ref_grad, rtol=0, atol=1e-12)


def test_identical_images_score_one_with_no_gradient():
    a, _ = _images(20, 24)
    value, grad = _value_and_grad(ssim, a, a)
    assert float(value) == pytest.approx(1.0, abs=1e-12)
    assert float(grad.abs().max()) < 1e-12


def test_the_cpu_ssim_gradient_passes_a_float64_gradcheck():
    a, b = _images(13, 12, channels=2, seed=3)
    assert torch.autograd.gradcheck(lambda x: _FusedSSIM.apply(x, b), (a.requires_grad_(),), eps=1e-6, atol=1e-8)


def test_float32_training_images_match_the_reference_to_float32_precision():
    a, b = (t.float() for t in _images(60, 80))
    value, grad = _value_and_grad(ssim, a, b)
    ref_value, ref_grad = _value_and_grad(ssim_torch, a, b)
    assert value.dtype == grad.dtype == torch.float32
    torch.testing.assert_close(value, ref_value, rtol=0, atol=1e-6)
    torch.testing.assert_close(grad, ref_grad, rtol=0, atol=1e-5 * float(ref_grad.abs().max()))


def test_the_image_loss_on_a_crop_sends_the_ssim_gradient_to_the_crop_only():
    """The loss slices the render to the mask's box (a non-contiguous view); the gradient lands inside it."""
    render, target = _images(40, 50)
    crop = (slice(5, 30), slice(10, 45))
    fused = _value_and_grad(lambda r, t: image_loss(r, t, crop, LossConfig()), render, target)
    outside = torch.ones(40, 50, dtype=torch.bool)
    outside[crop] = False
    assert float(fused[1][outside].abs().max()) == 0.0
    rows, cols = crop
    reference = _value_and_grad(lambda r, t: 0.8 * (r[rows, cols] - t[rows, cols]).abs().mean()
                                + 0.2 * (1 - ssim_torch(r[rows, cols], t[rows, cols])), render, target)
    torch.testing.assert_close(fused[0], reference[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(fused[1], reference[1], rtol=0, atol=1e-12)
