"""Reference sky removal (ALGORITHM.md section 1), NumPy + OpenCV."""

from __future__ import annotations

import cv2
import numpy as np

from torchrow.core.params import Params

__all__ = ["gray", "horizon_mask", "column_median", "sky_mask", "sky_row"]


def gray(rgb: np.ndarray) -> np.ndarray:
    """Section 1.1: OpenCV RGB->gray, ``(9798R + 19235G + 3735B + 16384) >> 15``.

    ``(H, W, 3)`` uint8 RGB -> ``(H, W)`` uint8. (*fix*: RGB, not the thesis' BGR.)
    """
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def horizon_mask(rgb: np.ndarray, params: Params) -> np.ndarray:
    """Sections 1.1-1.3: ``m = erode(laplacian(median(blur(gray))) < 4)``, ``(H, W)`` uint8 0/1."""
    bw, bh = params.sky_blur
    g = cv2.blur(gray(rgb), (bw, bh))
    g = cv2.medianBlur(g, params.sky_median)
    lap = cv2.Laplacian(g, cv2.CV_8U, ksize=1)  # saturating: negative responses become 0
    m = (lap < params.sky_lap_max).astype(np.uint8)
    ew, eh = params.sky_erode
    return cv2.erode(m, np.ones((eh, ew), np.uint8))


def column_median(m: np.ndarray, length: int) -> np.ndarray:
    """Median filter of odd ``length`` along each column with zero padding (``scipy.signal.medfilt``).

    ``(H, W)`` -> ``(H, W)`` of the same dtype.
    """
    h = m.shape[0]
    half = length // 2
    padded = np.concatenate([np.zeros((half,) + m.shape[1:], m.dtype), m,
                             np.zeros((half,) + m.shape[1:], m.dtype)], axis=0)
    windows = np.lib.stride_tricks.sliding_window_view(padded, length, axis=0)  # (H, W, L)
    return np.sort(windows, axis=-1)[..., half][:h]


def sky_mask(rgb: np.ndarray, params: Params) -> np.ndarray:
    """Sections 1.1-1.5: boolean ``(H, W)`` mask of sky pixels."""
    m = horizon_mask(rgb, params)
    filt = column_median(m, params.sky_col_median)
    h = m.shape[0]
    for x in range(m.shape[1]):
        zeros = np.flatnonzero(filt[:, x] == 0)
        ones = np.flatnonzero(filt[:, x] == 1)
        if zeros.size and ones.size and zeros[0] > params.sky_min_zero_row:
            z, o = int(zeros[0]), int(ones[0])
            col = np.zeros(h, np.uint8)
            col[o:z] = 1
            m[:, x] = col
    return (m == 1) & np.all(rgb >= 1, axis=2)


def sky_row(rgb: np.ndarray, params: Params) -> int:
    """Section 1.6: the horizon row ``sky``; rows ``y < sky`` are ignored downstream.

    Scanning from the bottom up, the first row with more than ``W/2`` sky pixels, else 0;
    0 as well if that row lies in the lower half (``sky > H/2``).
    """
    h, w = rgb.shape[:2]
    counts = sky_mask(rgb, params).sum(axis=1)
    sky = 0
    for y in range(h - 1, -1, -1):
        if counts[y] > w / 2:
            sky = y
            break
    return 0 if sky > h / 2 else sky
