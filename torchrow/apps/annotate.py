"""Pictures of detection results: rows, vanishing point, horizon, invalid rows marked, and the
improved mode's other visible lattice rows (thin)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from torchrow.core.results import ImageResult, LatticeRow

__all__ = ["draw_result", "draw_status", "save_rgb", "legend", "legend_entries", "row_top", "GT_COLOR"]

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


LABEL_BG = (0, 0, 0)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _text_box(img: np.ndarray, text: str, org: tuple[int, int], color, scale: float = 0.5) -> tuple[int, int]:
    """Text on a black box with its baseline-left corner at ``org`` (clipped into the picture);
    returns the box's ``(width, height)``."""
    (tw, th), base = cv2.getTextSize(text, FONT, scale, 1)
    x = int(np.clip(org[0], 2, max(2, img.shape[1] - tw - 6)))
    y = int(np.clip(org[1], th + 4, img.shape[0] - base - 2))
    cv2.rectangle(img, (x - 3, y - th - 3), (x + tw + 3, y + base + 1), LABEL_BG, -1)
    cv2.putText(img, text, (x, y), FONT, scale, color, 1, cv2.LINE_AA)
    return tw + 6, th + base + 4


def legend(width: int, entries: Sequence[tuple[str, tuple[int, int, int], str]]) -> np.ndarray:
    """A black strip, ``width`` px wide, explaining the marks of a picture.

    ``entries`` are ``(kind, rgb, text)`` with kind ``"line"``, ``"thin"`` (a 1-px line),
    ``"cross"``, ``"arrow"`` or ``"box"`` (a filled square). Entries flow left to right and wrap onto new lines.
    Returns ``(h, width, 3)`` uint8 RGB.
    """
    pad, sw, gap, line_h = 8, 26, 18, 22
    placed: list[tuple[int, int, tuple]] = []
    x, y = pad, 0
    for entry in entries:
        (tw, _), _ = cv2.getTextSize(entry[2], FONT, 0.45, 1)
        need = sw + 6 + tw
        if x > pad and x + need > width - pad:
            x, y = pad, y + 1
        placed.append((x, y, entry))
        x += need + gap
    strip = np.zeros(((max(p[1] for p in placed) + 1 if placed else 0) * line_h + 6, width, 3), np.uint8)
    for x, row, (kind, color, text) in placed:
        yc = 3 + row * line_h + line_h // 2
        if kind == "cross":
            cv2.drawMarker(strip, (x + sw // 2, yc), color, cv2.MARKER_CROSS, 12, 2, cv2.LINE_AA)
        elif kind == "arrow":
            cv2.arrowedLine(strip, (x, yc), (x + sw, yc), color, 2, cv2.LINE_AA, tipLength=0.4)
        elif kind == "box":
            cv2.rectangle(strip, (x + sw // 2 - 7, yc - 7), (x + sw // 2 + 7, yc + 7), color, -1)
        else:
            cv2.line(strip, (x, yc), (x + sw, yc), color, 1 if kind == "thin" else 2, cv2.LINE_AA)
        cv2.putText(strip, text, (x + sw + 6, yc + 5), FONT, 0.45, (235, 235, 235), 1, cv2.LINE_AA)
    return strip


def legend_entries(result: ImageResult, ground_truth: bool = False) -> list[tuple[str, tuple[int, int, int], str]]:
    """The legend of :func:`draw_result` for this result (only marks that the picture shows)."""
    entries: list[tuple[str, tuple[int, int, int], str]] = []
    if any(r.valid for r in result.rows):
        entries.append(("line", VALID, "detected row"))
    if any(not r.valid for r in result.rows):
        entries.append(("line", INVALID, "invalid row (reason at its foot)"))
    if _other_lattice_rows(result):
        entries.append(("thin", VALID, "other visible row of the lattice"))
    if ground_truth:
        entries.append(("thin", GT_COLOR, "ground truth"))
    if result.sky > 0:  # improved mode: the lattice's first row, which is section 1's or 0
        entries.append(("line", HORIZON, "horizon (rows above ignored)"))
    if result.vp is not None and all(math.isfinite(v) for v in result.vp):
        inside = 0 <= result.vp[0] < result.width and 0 <= result.vp[1] < result.height
        entries.append(("cross", VP_COLOR, "vanishing point") if inside else
                       ("arrow", VP_COLOR, "towards the vanishing point (outside the picture)"))
    return entries


def _other_lattice_rows(result: ImageResult) -> list[LatticeRow]:
    """The improved mode's visible lattice rows beyond the ``2K+1`` reported as ``rows``."""
    half = (len(result.rows) - 1) // 2
    return [r for r in result.lattice_rows or [] if abs(r.k) > half]


def row_top(result: ImageResult, height: int) -> float:
    """First image row a picture draws the rows from: below the horizon, and below the
    vanishing point when it lies inside the picture (rows cross there and mean nothing above).
    The improved mode's records have no section-6 VP: there the outermost reported rows'
    crossing counts, the lowest image row above which they are no longer at least 1 px apart
    in the order they have on the bottom row."""
    top = float(max(result.sky, 0))
    if result.vp is not None and all(math.isfinite(v) for v in result.vp) and result.vp[1] < height - 1:
        top = max(top, float(result.vp[1]))
    elif result.vp is None and len(result.rows) >= 2 and height > 1:
        first, last = result.rows[0], result.rows[-1]
        coefs = (first.a, first.b, first.c, first.e, last.a, last.b, last.c, last.e)
        if all(v is not None and math.isfinite(v) for v in coefs):
            ys = np.arange(height - 1, -1, -1, dtype=np.float64)
            gap = np.asarray(last.x_at(ys)) - np.asarray(first.x_at(ys))
            apart = np.sign(gap[0]) * gap >= 1.0
            if apart[0] and not apart.all():
                top = max(top, float(ys[int(np.argmin(apart))] + 1))
    return top


def draw_result(rgb: np.ndarray, result: ImageResult, scale: int = 2,
                ground_truth: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
                with_legend: bool = True, thin_rows: bool = False) -> np.ndarray:
    """Annotated copy of a working image, upscaled by ``scale`` for legibility.

    Parameters
    ----------
    rgb : ``(H, W, 3)`` uint8 RGB working image (the one the result refers to).
    result : the detection on it.
    scale : integer upscaling of the picture (drawing stays sharp).
    ground_truth : optional list of ``(ys, xs)`` polylines drawn thin in white.
    with_legend : append a strip below the picture that explains every mark on it.
    thin_rows : draw the valid rows 1 px wide like the other lattice rows (the lattice
        tracker's frames, :func:`torchrow.apps.video.draw_frame`, emphasise one row instead).

    Returns
    -------
    ``(scale*H + legend, scale*W, 3)`` uint8 RGB. Valid rows solid cyan, invalid rows red with
    their reason written at their foot, the improved mode's other visible lattice rows thin
    cyan, the horizon yellow, the vanishing point a magenta
    cross (an arrow at the border when it lies outside the picture), the status in the
    top-left corner. Rows are drawn from :func:`row_top` down.
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
    y_top = row_top(result, h)
    ys = np.linspace(y_top, h - 1, 48)
    for lr in _other_lattice_rows(result):
        pts = np.stack([np.asarray(lr.x_at(ys)) * s, ys * s], 1)
        if np.isfinite(pts).all():
            cv2.polylines(img, [pts.round().astype(np.int32)], False, VALID, 1, cv2.LINE_AA)
    labels: list[tuple[int, str]] = []
    for i, row in enumerate(result.rows):
        seg = _segment(row.a, row.b, y_top, h - 1, s)
        if seg is None:
            if not row.valid:
                labels.append((w * scale // 2, f"row {i}: {row.reason}"))
            continue
        (x0, y0), (x1, y1) = seg
        color = VALID if row.valid else INVALID
        width = 1 if thin_rows and row.valid else th
        if (row.c != 0.0 or row.e != 0.0) and math.isfinite(row.c) and math.isfinite(row.e):  # a curve: a polyline
            ys = np.linspace(y_top, h - 1, 48)
            pts = np.stack([np.asarray(row.x_at(ys)) * s, ys * s], 1).round().astype(np.int32)
            cv2.polylines(img, [pts], False, color, width, cv2.LINE_AA)
            x1 = int(pts[-1, 0])
        else:
            cv2.line(img, (x0, y0), (x1, y1), color, width, cv2.LINE_AA)
        if not row.valid:
            labels.append((x1, f"row {i}: {row.reason}"))
    for j, (x, text) in enumerate(sorted(labels)):
        _text_box(img, text, (x - 30, h * scale - 8 - 22 * (j % 3)), INVALID)
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
    draw_status(img, result)
    if with_legend:
        img = np.concatenate([img, legend(img.shape[1], legend_entries(result, bool(ground_truth)))], 0)
    return img


def draw_status(img: np.ndarray, result: ImageResult) -> None:
    """The status label of :func:`draw_result` in the top-left corner of ``img`` (in place)."""
    label = f"{result.status}  valid rows {sum(r.valid for r in result.rows)}/{len(result.rows)}"
    _text_box(img, label, (6, 20), (255, 255, 255))


def save_rgb(path, rgb: np.ndarray) -> None:
    """Write an RGB uint8 image, encoded by OpenCV (format from the extension).

    The file itself is written by Python, not ``cv2.imwrite``: OpenCV takes a name as UTF-8
    and crashes the process on one that is not (a file name of arbitrary bytes)."""
    from pathlib import Path

    suffix = Path(path).suffix
    try:
        ok, buf = cv2.imencode(suffix, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    except cv2.error:
        ok = False
    if not ok:
        raise OSError(f"could not write image {path}: OpenCV cannot encode {suffix or 'a name without suffix'!r}")
    Path(path).write_bytes(buf.tobytes())
