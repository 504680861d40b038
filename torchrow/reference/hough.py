"""Reference Hough voting and N-maximum extraction (ALGORITHM.md section 5)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchrow.core.params import Params
from torchrow.core.results import HoughLine
from torchrow.core.tables import hough_trig, near_angle, near_horizontal, rho_offset

__all__ = ["rho_offset", "line_distance", "votes", "excluded_angles", "HoughState", "extract_line"]


def line_distance(xs: np.ndarray, ys: np.ndarray, j: int, rho: int, params: Params) -> np.ndarray:
    """``|x*c_j + y*s_j - rho|`` in float64 for pixel coordinates ``xs, ys`` (int arrays)."""
    c, s = hough_trig(params.theta_step)
    return np.abs((xs * c[j] + ys * s[j]) - rho)


def votes(mask: np.ndarray, params: Params) -> np.ndarray:
    """Hough accumulator of a ``(H, W)`` bool mask: ``(2D + 1, n_theta)`` int64.

    Every pixel votes for each angle ``j`` at ``rho = round(x*c_j + y*s_j)`` (round half to
    even, no fused multiply-add), row ``rho + D``.
    """
    h, w = mask.shape
    d = rho_offset(h, w)
    c, s = hough_trig(params.theta_step)
    ys, xs = np.nonzero(mask)
    acc = np.zeros((2 * d + 1, len(c)), np.int64)
    if xs.size:
        rho = np.rint(xs[:, None] * c[None, :] + ys[:, None] * s[None, :]).astype(np.int64)
        np.add.at(acc, (rho + d, np.broadcast_to(np.arange(len(c)), rho.shape)), 1)
    return acc


def excluded_angles(held: list[HoughLine], params: Params) -> np.ndarray:
    """Step 5.1: ``(n_theta,)`` bool of angles that cannot be picked.

    ``|theta - 90deg| < horizontal_excl`` and ``|theta - theta_h| < angle_excl`` for every held
    line, on the integer-degree grid, no wrap-around at 0/180.
    """
    deg = np.arange(params.n_theta) * params.theta_step
    ex = near_horizontal(deg, params.horizontal_excl)
    for line in held:
        ex |= near_angle(deg, line.theta_index * params.theta_step, params.angle_excl)
    return ex


@dataclass
class HoughState:
    """Hough input and accumulator during extraction; erasures persist until a restart."""

    mask: np.ndarray  # (H, W) bool, current Hough input
    acc: np.ndarray  # (2D+1, n_theta) int64, votes of ``mask``
    d: int

    @classmethod
    def start(cls, mask: np.ndarray, params: Params) -> HoughState:
        return cls(mask.copy(), votes(mask, params), rho_offset(*mask.shape))


def extract_line(state: HoughState, held: list[HoughLine], params: Params) -> HoughLine | None:
    """Steps 5.1-5.3: pick the next peak, erase its band from the input and remove its votes.

    Returns the line, or ``None`` when the maximum over the allowed angles is 0.
    """
    acc = state.acc.copy()
    acc[:, excluded_angles(held, params)] = 0
    flat = int(np.argmax(acc))  # first maximum in row-major order: smallest rho, then theta
    r_idx, j = divmod(flat, acc.shape[1])
    w = int(acc[r_idx, j])
    if w == 0:
        return None
    line = HoughLine(j, r_idx - state.d, w, params.theta_step)
    band = params.hough_band_px(state.mask.shape[1])
    ys, xs = np.nonzero(state.mask)
    hit = line_distance(xs, ys, j, line.rho, params) <= band / 2
    erased = np.zeros_like(state.mask)
    erased[ys[hit], xs[hit]] = True
    state.mask[erased] = False
    state.acc -= votes(erased, params)
    return line
