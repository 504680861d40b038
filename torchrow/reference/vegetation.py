"""Reference vegetation mask and Hough input (ALGORITHM.md sections 3 and 4).

Every neighbourhood operation here runs on the region below the horizon as if it were the
whole image (rows above ``sky`` are outside, with OpenCV's border rule for the operation),
as the thesis code did by cropping.
"""

from __future__ import annotations

import cv2
import numpy as np

from torchrow.core.params import Params
from torchrow.core.tables import rgb_to_lab

__all__ = ["raw_mask", "remove_bushy", "density", "hough_input", "adapt_k", "raw_fraction"]


def raw_mask(rgb: np.ndarray, color: tuple[int, int, int], k: float, sky: int) -> np.ndarray:
    """Section 3.2: inclusive LAB box ``c - k <= lab <= c + k`` on all three channels.

    ``(H, W, 3)`` uint8 RGB -> ``(H, W)`` bool, rows ``y < sky`` False.
    """
    lab = rgb_to_lab(rgb)
    c = rgb_to_lab(np.asarray(color, np.uint8))
    lo, hi = c - k, c + k
    raw = np.all((lo <= lab) & (lab <= hi), axis=2)
    raw[:sky] = False
    return raw


def raw_fraction(raw: np.ndarray, sky: int) -> float:
    """Fraction of ``raw`` pixels below the horizon (section 3.3, video mode)."""
    below = raw[sky:]
    return float(below.sum()) / below.size if below.size else 0.0


def adapt_k(rgb: np.ndarray, color: tuple[int, int, int], sky: int, info0: float,
            params: Params) -> tuple[int, np.ndarray]:
    """Section 3.3, video mode: adapt the LAB half-width ``k`` to the frame-0 fraction ``info0``.

    Returns ``(k, raw mask at k)``.
    """
    k = params.video_k_start
    raw = raw_mask(rgb, color, k, sky)
    while raw_fraction(raw, sky) > params.video_shrink_above * info0 and k > params.video_k_min:
        k -= 1
        raw = raw_mask(rgb, color, k, sky)
    while raw_fraction(raw, sky) < params.video_grow_below * info0 and k < params.video_k_max:
        k += 1
        raw = raw_mask(rgb, color, k, sky)
    return k, raw


def remove_bushy(raw: np.ndarray, sky: int, params: Params) -> np.ndarray:
    """Section 3.4: ``veg = raw AND NOT erode(raw)`` (2 wide, 3 high, default anchor).

    The kernel covers columns ``x-1..x`` and rows ``y-1..y+1``; outside the region below
    the horizon nothing erodes. ``(H, W)`` bool -> ``(H, W)`` bool.
    """
    ew, eh = params.bushy_erode
    region = raw[sky:].astype(np.uint8)
    veg = np.zeros_like(raw)
    if region.size:
        eroded = cv2.erode(region, np.ones((eh, ew), np.uint8))
        veg[sky:] = (region == 1) & (eroded == 0)
    return veg


def density(veg: np.ndarray, sky: int) -> float:
    """Section 4: ones in ``veg`` / pixels below the horizon."""
    below = veg[sky:]
    return float(below.sum()) / below.size if below.size else 0.0


def hough_input(veg: np.ndarray, sky: int, params: Params) -> tuple[np.ndarray, bool]:
    """Section 4: the Hough input and the bushy flag.

    Bushy (density > ``bushy_ratio``): ``cv2.Canny(veg*255, 100, 200)`` (L1 gradient) on
    the region below the horizon; otherwise ``veg`` itself. Returns ``((H, W) bool, bushy)``.
    """
    bushy = density(veg, sky) > params.bushy_ratio
    if not bushy:
        return veg.copy(), False
    out = np.zeros_like(veg)
    region = veg[sky:].astype(np.uint8) * 255
    if region.size:
        out[sky:] = cv2.Canny(region, params.canny_low, params.canny_high, L2gradient=False) > 0
    return out, True
