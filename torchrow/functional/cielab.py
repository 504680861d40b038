"""CIE LAB (D65) by kornia's formula, element-wise in float64: what an exported graph computes
where the shared table (:func:`torchrow.core.tables.lab_table_torch`, read by
:func:`torchrow.functional.vegetation.lab`) is too large to carry.

:func:`lab_formula` gives LAB of whole images; :func:`lab_f` the three cube-root branches of
linear RGB, which :func:`torchrow.functional.vegetation.min_k_table` bounds over blocks of
colours; :func:`linear_lut` the 256-entry sRGB linearisation both start from.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

__all__ = ["lab_formula", "lab_f", "linear_lut"]

# kornia.color.rgb_to_lab constants (sRGB D65), in the order kornia applies them.
_XYZ = ((0.412453, 0.357580, 0.180423), (0.212671, 0.715160, 0.072169), (0.019334, 0.119193, 0.950227))
_WHITE = (0.95047, 1.0, 1.08883)
_LAB_EPS = 0.008856


@functools.lru_cache(maxsize=1)
def linear_lut() -> np.ndarray:
    """sRGB -> linear RGB of the 256 byte values (kornia's formula, float64), ``(256,)``."""
    import kornia

    v = torch.arange(256, dtype=torch.float64) / 255.0
    return kornia.color.rgb_to_linear_rgb(v.view(1, 1, 1, 256).expand(1, 3, 1, 256))[0, 0, 0].numpy().copy()


def lab_f(r: torch.Tensor, g: torch.Tensor, b: torch.Tensor) -> list[torch.Tensor]:
    """``f(X/Xn), f(Y/Yn), f(Z/Zn)`` of linear RGB (float64, broadcastable), kornia's order:
    the XYZ matrix as ``(k0*r + k1*g) + k2*b``, the white-point division, then the cube root
    above ``_LAB_EPS`` and ``7.787*t + 4/29`` below (increasing and continuous, as X, Y and Z
    are in each channel: :func:`torchrow.functional.vegetation.min_k_table` relies on it)."""
    f = []
    for row, white in zip(_XYZ, _WHITE):
        t = (row[0] * r + row[1] * g) + row[2] * b
        t = t / white
        f.append(torch.where(t > _LAB_EPS, torch.pow(t.clamp(min=_LAB_EPS), 1 / 3.0), 7.787 * t + 4.0 / 29.0))
    return f


def lab_formula(images: torch.Tensor, lut: torch.Tensor | None = None) -> torch.Tensor:
    """CIE LAB (D65) of ``uint8 (B, 3, H, W)`` RGB as float64 ``(B, 3, H, W)``, in the graph.

    kornia's ``rgb_to_lab`` written out element-wise: a 256-entry linearisation table, the
    XYZ matrix as ``(k0*r + k1*g) + k2*b``, white-point division, the cube root branch and
    ``L = 116*y - 16``, ``a = 500*(x - y)``, ``b = 200*(y - z)``. Values may differ from the
    shared table by an ulp; the decisions of the vegetation box do not (checked on all
    2**24 colours by :func:`torchrow.onnx.checks.check_lab`).
    """
    if lut is None:
        lut = torch.from_numpy(linear_lut()).to(images.device)
    # a flat index_select exports as one Gather (advanced indexing gave a slower GatherND)
    lin = torch.index_select(lut, 0, images.reshape(-1).to(torch.int64)).view(images.shape)  # (B, 3, H, W)
    r, g, b = lin[:, 0], lin[:, 1], lin[:, 2]
    x, y, z = lab_f(r, g, b)
    return torch.stack([(116.0 * y) - 16.0, 500.0 * (x - y), 200.0 * (y - z)], dim=1)
