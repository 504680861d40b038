"""Metric steering of :mod:`torchrow.core.camera`, batched over images (ALGORITHM.md section 12).

The same definitions as :func:`torchrow.core.camera.metric_steering` (central row, neighbours,
signs), for rows held as padded tensors ``(B, R)`` with a validity mask, so that a batched
tracker can steer without leaving the device. Continuous outputs agree with the NumPy
reference within the spec's 1e-6 (float64); which row is central agrees exactly except where
two rows' distances tie within rounding.
"""

from __future__ import annotations

import torch

from torchrow.core.camera import CameraModel

__all__ = ["ground_lines", "metric_steering"]


def ground_lines(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, e: torch.Tensor, valid: torch.Tensor,
                 camera: CameraModel, y0: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ground lines of rows ``x = e·y³ + c·y² + a·y + b``: tangents at image row ``y0``.

    Parameters
    ----------
    a, b, c, e : torch.Tensor
        ``float64 (B, R)`` row coefficients (working px; ``c = e = 0`` for straight rows).
    valid : torch.Tensor
        ``bool (B, R)``.
    camera : CameraModel
        At the working size.
    y0 : float
        Image row of the tangent (the bottom row, ``H - 1``).

    Returns
    -------
    (heading, lateral, ok)
        ``float64 (B, R)`` heading (rad) and the nadir's signed distance (m) of each row's ground
        line, and ``bool (B, R)``: the row is valid and has one
        (:func:`torchrow.core.camera.ground_line`); the others hold 0.
    """
    m = torch.as_tensor(camera.ground_to_image_matrix(), dtype=torch.float64, device=a.device)
    slope = (3.0 * e * y0 + 2.0 * c) * y0 + a
    x0 = (c * y0) * y0 + a * y0 + b + ((e * y0) * y0) * y0
    line = torch.stack([torch.ones_like(slope), -slope, slope * y0 - x0], dim=-1)  # (B, R, 3)
    pqr = line @ m  # Mᵀ·l for every row
    p, q, r = pqr.unbind(-1)
    norm = torch.hypot(p, q)
    ok = (valid & torch.isfinite(slope) & torch.isfinite(x0) & (norm > 0) & (q != 0)
          & (q.abs() > 1e-12 * norm) & bool(y0 > camera.horizon_v))
    sign = torch.where(q < 0, -1.0, 1.0).to(torch.float64)
    safe = torch.where(ok, norm, torch.ones_like(norm))
    heading = torch.where(ok, torch.atan2(-p * sign, q * sign), torch.zeros_like(p))
    lateral = torch.where(ok, (r * sign) / safe, torch.zeros_like(r))
    return heading, lateral, ok


def metric_steering(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, e: torch.Tensor, valid: torch.Tensor,
                    camera: CameraModel, height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``lateral_m``, ``heading_rad``, ``spacing_m`` per image, float64 ``(B,)``, NaN where
    :func:`torchrow.core.camera.metric_steering` gives ``None``.

    Inputs as :func:`ground_lines` (``camera`` at the working size, ``height`` the working
    height ``H``: tangents at ``y = H-1``).
    """
    heading, lat, ok = ground_lines(a, b, c, e, valid, camera, float(height) - 1.0)
    bsz, n = lat.shape
    inf = torch.full_like(lat, float("inf"))
    # the central row: smallest |l|, first in row order on ties (argmin keeps the first)
    cen = torch.where(ok, lat.abs(), inf).argmin(dim=1, keepdim=True)
    # neighbours: next to it in the stable order of l (invalid rows sorted last)
    order = torch.sort(torch.where(ok, lat, inf), dim=1, stable=True).indices
    pos = (order == cen).to(torch.int64).argmax(dim=1, keepdim=True)
    n_ok = ok.sum(dim=1, keepdim=True)
    lat_c = lat.gather(1, cen)
    head_sum = heading.gather(1, cen)
    count = torch.ones_like(lat_c)
    gap_sum = torch.zeros_like(lat_c)
    gaps = torch.zeros_like(lat_c)
    for step in (-1, 1):
        at = pos + step
        has = (at >= 0) & (at < n_ok)
        nb = order.gather(1, at.clamp(0, n - 1))
        head_sum = head_sum + torch.where(has, heading.gather(1, nb), torch.zeros_like(lat_c))
        gap_sum = gap_sum + torch.where(has, (lat.gather(1, nb) - lat_c).abs(), torch.zeros_like(lat_c))
        count = count + has.to(torch.float64)
        gaps = gaps + has.to(torch.float64)
    nan = torch.full_like(lat_c, float("nan"))
    some = n_ok > 0
    lateral = torch.where(some, lat_c, nan)
    head = torch.where(some, head_sum / count, nan)
    spacing = torch.where(some & (gaps > 0), gap_sum / gaps.clamp(min=1.0), nan)
    return lateral.view(bsz), head.view(bsz), spacing.view(bsz)
