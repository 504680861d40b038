"""Exact helpers: correctly rounded float64 for comparisons that decide discrete outputs,
and exact counts.

``torch.sqrt`` on float64 CPU tensors is not correctly rounded in torch 2.13 (its vectorised
kernel is off by one ulp on about 1.2% of inputs; measured on 2M random values), while the
reference uses ``math.sqrt``/``numpy.sqrt`` (IEEE, correctly rounded). On the CPU this module
therefore takes NumPy's square root of the same memory (no copy); CUDA's float64 ``sqrt`` is
IEEE correctly rounded already.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["sqrt", "count"]


def sqrt(x: torch.Tensor) -> torch.Tensor:
    """IEEE correctly rounded square root of a float64 tensor (same device, same shape).

    While exporting (``torch.export``/ONNX) this is plain ``torch.sqrt``: the exported ``Sqrt``
    runs in the graph's runtime (onnxruntime's is IEEE correctly rounded).
    """
    if torch.compiler.is_exporting():
        return torch.sqrt(x)
    if x.device.type == "cpu" and x.dtype == torch.float64 and not x.requires_grad:
        return torch.from_numpy(np.sqrt(x.contiguous().numpy()))
    return torch.sqrt(x)


def count(mask: torch.Tensor) -> torch.Tensor:
    """The number of ``True`` along the last dim of a bool tensor ``(..., K)``: int64 ``(...)``.

    While exporting, a float32 matrix product with a ``(K, 1)`` column of ones: every
    partial sum of 0/1 terms is an integer below ``2**24`` (``K`` is at most
    ``Params.max_pixels`` = 2**22 pixels), so any summation order gives the exact count, and
    onnxruntime's float32 ``MatMul`` is several times faster than its ``ReduceSum`` over the
    int64 cast torch would export. Eagerly (where CUDA's TF32 could round a matrix product)
    a plain ``sum``.
    """
    if torch.compiler.is_exporting():
        ones = torch.ones((mask.shape[-1], 1), dtype=torch.float32, device=mask.device)
        return (mask.to(torch.float32) @ ones).squeeze(-1).to(torch.int64)
    return mask.sum(dim=-1)
