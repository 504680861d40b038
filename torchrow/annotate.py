"""Pictures of detection results: rows, vanishing point, horizon, invalid rows marked."""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

from .results import ImageResult

__all__ = ["draw_result", "save_rgb", "GT_COLOR"]

VALID = (40, 230, 255)  # cyan-ish, readable on green and brown
INVALID = (255, 60, 60)
HORIZON = (255, 220, 0)
VP_COLOR = (255, 0, 255)
GT_COLOR = (255, 255, 255)


def _segment(a: float, b: float, y0: float, y1: float, s: float) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """End points of ``x = a*y + b`` between rows ``y0`` and ``y1``, in pixels scaled by ``s``."""
    if not (math.isfinite(a) and math.isfinite(b)):
        return None
    return ((int(round((a * y0 + b) * s)), int(round(y0 * s))),
            (int(round((a * y1 + b) * s)), int(round(y1 * s))))


def draw_result(rgb: np.ndarray, result: ImageResult, scale: int = 2,
                ground_truth: Sequence[tuple[np.ndarray, np.ndarray]] | None = None) -> np.ndarray:
    """Annotated copy of a working image, upscaled by ``scale`` for legibility.

    Parameters
    ----------
    rgb : ``(H, W, 3)`` uint8 RGB working image (the one the result refers to).
    result : the detection on it.
    scale : integer upscaling of the picture (drawing stays sharp).
    ground_truth : optional list of ``(ys, xs)`` polylines drawn thin in white.

    Returns
    -------
    ``(scale*H, scale*W, 3)`` uint8 RGB. Valid rows solid cyan, invalid rows red with their
    reason, the horizon yellow, the vanishing point a magenta cross (an arrow at the border
    when it lies outside the picture), the status in the corner.
    """
    h, w = rgb.shape[:2]
    img = cv2.resize(rgb, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)
    img = np.ascontiguousarray(img)
    s = float(scale)
    th = max(1, scale)
    if ground_truth:
        for ys, xs in ground_truth:
            pts = np.stack([np.asarray(xs) * s, np.asarray(ys) * s], 1).round().astype(np.int32)
            cv2.polylines(img, [pts], False, GT_COLOR, 1, cv2.LINE_AA)
    if result.sky > 0:
        y = int(result.sky * s)
        cv2.line(img, (0, y), (w * scale - 1, y), HORIZON, th, cv2.LINE_AA)
    y_top = max(result.sky, 0)
    for i, row in enumerate(result.rows):
        seg = _segment(row.a, row.b, y_top, h - 1, s)
        if seg is None:
            continue
        (x0, y0), (x1, y1) = seg
        color = VALID if row.valid else INVALID
        if row.c != 0.0 and math.isfinite(row.c):  # a curve (improved mode): a polyline
            ys = np.linspace(y_top, h - 1, 48)
            pts = np.stack([np.asarray(row.x_at(ys)) * s, ys * s], 1).round().astype(np.int32)
            cv2.polylines(img, [pts], False, color, th, cv2.LINE_AA)
            x1 = int(pts[-1, 0])
        else:
            cv2.line(img, (x0, y0), (x1, y1), color, th, cv2.LINE_AA)
        if not row.valid:
            label = f"{i}:{row.reason}"
            xl = int(np.clip(x1, 2, w * scale - 80))
            cv2.putText(img, label, (xl, h * scale - 6 - 14 * (i % 3)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.4, INVALID, 1, cv2.LINE_AA)
    if result.vp is not None and all(math.isfinite(v) for v in result.vp):
        vx, vy = result.vp[0] * s, result.vp[1] * s
        inside = 0 <= vx < w * scale and 0 <= vy < h * scale
        if inside:
            cv2.drawMarker(img, (int(vx), int(vy)), VP_COLOR, cv2.MARKER_CROSS, 14, 2, cv2.LINE_AA)
        else:
            cx, cy = w * scale / 2, h * scale / 2
            t = min(abs((w * scale / 2 - 8) / (vx - cx)) if vx != cx else 1e9,
                    abs((h * scale / 2 - 8) / (vy - cy)) if vy != cy else 1e9, 1.0)
            ex, ey = cx + (vx - cx) * t, cy + (vy - cy) * t
            sx, sy = cx + (vx - cx) * t * 0.85, cy + (vy - cy) * t * 0.85
            cv2.arrowedLine(img, (int(sx), int(sy)), (int(ex), int(ey)), VP_COLOR, 2, cv2.LINE_AA, tipLength=0.4)
    label = f"{result.status}  valid rows {sum(r.valid for r in result.rows)}/{len(result.rows)}"
    (tw, th_), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    cv2.rectangle(img, (2, 2), (10 + tw, 10 + th_ + base), (0, 0, 0), -1)
    cv2.putText(img, label, (6, 6 + th_), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def save_rgb(path, rgb: np.ndarray) -> None:
    """Write an RGB uint8 image with OpenCV (format from the extension)."""
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write image {path}")
