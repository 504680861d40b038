"""Correctly rounded float64 helpers for comparisons that decide discrete outputs.

``torch.sqrt`` on float64 CPU tensors is not correctly rounded in torch 2.13 (its vectorised
kernel is off by one ulp on about 1.2% of inputs; measured on 2M random values), while the
reference uses ``math.sqrt``/``numpy.sqrt`` (IEEE, correctly rounded). On the CPU this module
therefore takes NumPy's square root of the same memory (no copy); CUDA's float64 ``sqrt`` is
IEEE correctly rounded already.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["sqrt"]


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
