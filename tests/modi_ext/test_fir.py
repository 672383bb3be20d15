"""``modi_ext.fir``: the fast time filters are the FIR of ``FIR_TAPS`` written as a convolution, bit for bit where
the sums run in the same order and to rounding otherwise."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from modi_ext.fir import FIR_TAPS, UP_GAIN, blur_time, downsample_time, upsample_time
from modi_ext.skeletal.reference import blur


def _conv(x: torch.Tensor, pad: tuple[int, int], gain: float = 1.0) -> torch.Tensor:
    k = torch.tensor(FIR_TAPS, dtype=x.dtype)
    k = (k * (gain / k.sum())).flip(0).view(1, 1, -1)
    shape = x.shape[:-1]
    return F.conv1d(F.pad(x.reshape(-1, 1, x.shape[-1]), pad), k).reshape(*shape, -1)


@pytest.mark.parametrize("t", [2, 5, 16])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fast_forms_are_the_filter(t, dtype):
    x = torch.randn(2, 3, 4, t, dtype=dtype, generator=torch.Generator().manual_seed(t))
    tol = dict(rtol=0, atol=1e-6) if dtype == torch.float32 else dict(rtol=0, atol=1e-12)
    torch.testing.assert_close(blur_time(x), _conv(x, (1, 2)), **tol)
    torch.testing.assert_close(downsample_time(x), _conv(x, (1, 1))[..., ::2], **tol)
    zero_inserted = torch.stack([x, torch.zeros_like(x)], -1).flatten(-2)
    torch.testing.assert_close(upsample_time(x), _conv(zero_inserted, (2, 1), UP_GAIN), **tol)


def test_the_reference_blur_reads_the_same_taps():
    x = torch.randn(3, 2, 9, dtype=torch.float64)
    torch.testing.assert_close(blur(x), _conv(x, (2, 1), UP_GAIN), rtol=0, atol=1e-12)


@pytest.mark.parametrize("t", [2, 5, 16])
@pytest.mark.parametrize("fn", [blur_time, downsample_time, upsample_time], ids=lambda f: f.__name__)
def test_gradients_of_any_order(fn, t):
    """Each backward is the adjoint filter pass (itself differentiable): gradcheck and gradgradcheck in float64."""
    x = torch.randn(2, 3, 2, t, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(fn, (x,), eps=1e-6, atol=1e-8)
    assert torch.autograd.gradgradcheck(fn, (x,), eps=1e-6, atol=1e-8)
