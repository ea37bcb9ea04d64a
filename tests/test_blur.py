"""The compiled Gaussian blur (`render.blur`) gives the bits of the torch convolutions it replaces in
reading (`models.spread.local_mean`, `reading.footprint`), and falls back to them where it does not apply."""

from __future__ import annotations

import pytest
import torch

from meshseal.imaging import gaussian_blur as torch_blur
from meshseal.render.blur import gaussian_blur


@pytest.mark.parametrize("shape", [(1, 2, 9, 7), (1, 3, 40, 33), (2, 4, 17, 64), (1, 22, 61, 58), (3, 2, 1, 5)])
@pytest.mark.parametrize("sigma", [0.35, 0.75, 1.5, 2.0])
def test_the_compiled_blur_gives_the_convolutions_bits(shape, sigma):
    image = torch.rand(shape, generator=torch.Generator().manual_seed(len(shape) + int(10 * sigma)))
    assert torch.equal(gaussian_blur(image, sigma), torch_blur(image, sigma))
    strided = image.transpose(0, 1)  # as `local_mean` hands its planes over
    assert torch.equal(gaussian_blur(strided, sigma), torch_blur(strided, sigma))


def test_where_it_does_not_apply_it_is_the_torch_blur():
    image = torch.rand(1, 3, 12, 12, requires_grad=True)
    blurred = gaussian_blur(image, 1.0)
    blurred.sum().backward()  # gradients: torch's convolutions
    assert image.grad is not None
    one = torch.rand(1, 1, 12, 12)
    assert torch.equal(gaussian_blur(one, 1.0), torch_blur(one, 1.0))
    assert torch.equal(gaussian_blur(one.double(), 1.0), torch_blur(one.double(), 1.0))
    assert gaussian_blur(one, 0.0) is one
