"""The float64 square root used for decisions is the IEEE correctly rounded one."""

import math

import numpy as np
import torch

from torchrow.functional._exact import sqrt


def test_sqrt_is_correctly_rounded_where_torch_is_not() -> None:
    x = np.random.default_rng(0).random(200_000) * 1000
    got = sqrt(torch.from_numpy(x)).numpy()
    assert np.array_equal(got, np.sqrt(x))
    # a case torch's vectorised float64 sqrt rounds the wrong way on some CPUs
    v = math.nextafter(0.25, 0.0)
    assert float(sqrt(torch.tensor([v], dtype=torch.float64))[0]) == math.sqrt(v)


def test_sqrt_keeps_shape_and_device() -> None:
    x = torch.rand(3, 4, 5, dtype=torch.float64).transpose(0, 2)
    out = sqrt(x)
    assert out.shape == x.shape and out.device == x.device
    assert torch.equal(out, torch.from_numpy(np.sqrt(x.numpy())))
