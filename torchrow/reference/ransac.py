"""Reference constrained RANSAC, one row per held line (ALGORITHM.md section 7)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchrow.core.params import Params
from torchrow.core.results import HoughLine, Row
from torchrow.core.tables import hough_trig, hypothesis_table, subsample_key

__all__ = ["RowFit", "band_points", "track_band_points", "subsample", "score_hypotheses", "refit", "fit_row",
           "fit_tracked_row", "validate_rows"]


@dataclass(frozen=True)
class RowFit:
    """A fitted row before the validity rules: direction ``(dx, dy)`` (unit, dy > 0 or
    dx > 0 when dy = 0) through ``(cx, cy)``; ``hypothesis`` = winning index (-1 if none)."""

    cx: float
    cy: float
    dx: float
    dy: float
    hypothesis: int

    def as_row(self) -> tuple[float, float]:
        """``(a, b)`` of ``x = a*y + b`` (inf/nan for a horizontal fit)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.float64(self.dx) / np.float64(self.dy)
            b = np.float64(self.cx) - a * np.float64(self.cy)
        return float(a), float(b)


def band_points(veg: np.ndarray, theta_index: int, rho: float, band: int,
                params: Params) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of ``veg`` with ``|x cos + y sin - rho| <= band/2``, row-major (y, then x).

    Returns ``(xs, ys)`` int64 arrays.
    """
    c, s = hough_trig(params.theta_step)
    ys, xs = np.nonzero(veg)  # row-major already
    keep = np.abs((xs * c[theta_index] + ys * s[theta_index]) - rho) <= band / 2
    return xs[keep].astype(np.int64), ys[keep].astype(np.int64)


def track_band_points(veg: np.ndarray, a: float, b: float, band: int,
                      params: Params) -> tuple[np.ndarray, np.ndarray]:
    """Video mode (section 8): pixels of ``veg`` within ``band/2`` of the row ``x = a*y + b``.

    Membership is the orthogonal distance to the row, squared so no square root decides it:
    ``((x - a*y) - b)**2 <= (band/2)**2 * (1 + a*a)`` (float64, in this operation order; the
    tensor path evaluates the identical expression). Orthogonal, not horizontal, distance:
    the band then has the same width for slanted outer rows as for the central one, as the
    thick line the thesis code drew around the previous row, and as the Hough-line band of
    section 7. Returns ``(xs, ys)`` int64 arrays, row-major (y, then x).
    """
    ys, xs = np.nonzero(veg)  # row-major already
    a64, b64 = np.float64(a), np.float64(b)
    r = (xs.astype(np.float64) - a64 * ys.astype(np.float64)) - b64
    half = np.float64(band) / 2
    keep = r * r <= (half * half) * (np.float64(1.0) + a64 * a64)
    return xs[keep].astype(np.int64), ys[keep].astype(np.int64)


def subsample(xs: np.ndarray, ys: np.ndarray, width: int, params: Params) -> tuple[np.ndarray, np.ndarray, int]:
    """Step 7.2: keep at most ``ransac_subsample`` weighted points.

    With ``n`` pixels and VP weight ``v = n // 2``: if ``n + v > ransac_max_points`` keep the
    ``n' = (500 n) // (n + v)`` pixels of smallest hash key (row-major order preserved) and
    give the VP weight ``500 - n'``. Returns ``(xs, ys, v')``.
    """
    n = xs.size
    v = n // 2
    if n + v <= params.ransac_max_points:
        return xs, ys, v
    n_keep = (params.ransac_subsample * n) // (n + v)
    key = subsample_key(xs, ys, width, params.subsample_hash)
    keep = np.sort(np.argsort(key, kind="stable")[:n_keep])
    return xs[keep], ys[keep], params.ransac_subsample - n_keep


def score_hypotheses(px: np.ndarray, py: np.ndarray, pw: np.ndarray, n_pix: int,
                     params: Params) -> np.ndarray:
    """Step 7.3-7.4: score of every hypothesis of the shared table, ``(T,)`` int64.

    ``px, py, pw``: the ``n' + 1`` points (pixels then the VP) and their weights. Hypothesis
    ``t`` picks ``i_k = floor(U[t, k] * (n' + v'))``, indices ``>= n'`` meaning the VP; it is
    degenerate (score -1) if ``i_1 == i_2`` or both pick the VP.
    """
    u = hypothesis_table(params.seed, params.ransac_trials)
    total = n_pix + int(pw[n_pix])
    scores = np.full(len(u), -1, np.int64)
    for t in range(len(u)):
        i1 = int(math.floor(u[t, 0] * total))
        i2 = int(math.floor(u[t, 1] * total))
        if i1 == i2 or (i1 >= n_pix and i2 >= n_pix):
            continue
        x1, y1 = px[min(i1, n_pix)], py[min(i1, n_pix)]
        x2, y2 = px[min(i2, n_pix)], py[min(i2, n_pix)]
        inl = inliers(px, py, x1, y1, x2, y2, params)
        scores[t] = int(pw[inl].sum())
    return scores


def inliers(px: np.ndarray, py: np.ndarray, x1: float, y1: float, x2: float, y2: float,
            params: Params) -> np.ndarray:
    """``|(x2-x1)(y-y1) - (y2-y1)(x-x1)| < threshold * sqrt((x2-x1)^2 + (y2-y1)^2)`` (float64)."""
    cross = (x2 - x1) * (py - y1) - (y2 - y1) * (px - x1)
    return np.abs(cross) < params.ransac_threshold * math.sqrt((x2 - x1) * (x2 - x1) + (y2 - y1) * (y2 - y1))


def refit(px: np.ndarray, py: np.ndarray, pw: np.ndarray) -> tuple[float, float, float, float]:
    """Step 7.5: weighted total least squares; returns centroid and unit direction.

    Direction = principal eigenvector of the weighted scatter, ``phi = atan2(2 Sxy, Sxx - Syy)/2``,
    oriented with dy > 0 (dx > 0 when dy = 0).
    """
    w = pw.astype(np.float64)
    wsum = w.sum()
    cx = float((w * px).sum() / wsum)
    cy = float((w * py).sum() / wsum)
    ex, ey = px - cx, py - cy
    sxx = float((w * ex * ex).sum())
    syy = float((w * ey * ey).sum())
    sxy = float((w * ex * ey).sum())
    phi = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    dx, dy = math.cos(phi), math.sin(phi)
    if dy < 0 or (dy == 0 and dx < 0):
        dx, dy = -dx, -dy
    return cx, cy, dx, dy


def fit_row(veg: np.ndarray, line: HoughLine, vp: tuple[float, float], band: int,
            params: Params) -> RowFit | None:
    """Steps 7.1-7.5 for one held line; ``None`` when the band lacks support."""
    xs, ys = band_points(veg, line.theta_index, line.rho, band, params)
    return _fit_points(xs, ys, veg.shape[1], vp, params)


def fit_tracked_row(veg: np.ndarray, a: float, b: float, vp: tuple[float, float], band: int,
                    params: Params) -> RowFit | None:
    """Steps 7.1-7.5 for one previous-frame row ``x = a*y + b`` (video mode, section 8).

    The band is :func:`track_band_points`; everything after it (VP weight ``v = n // 2``,
    subsampling, hypotheses, refit) is :func:`fit_row`'s. ``None`` when the band lacks support.
    """
    xs, ys = track_band_points(veg, a, b, band, params)
    return _fit_points(xs, ys, veg.shape[1], vp, params)


def _fit_points(xs: np.ndarray, ys: np.ndarray, w: int, vp: tuple[float, float],
                params: Params) -> RowFit | None:
    """Steps 7.1-7.5 on the band pixels ``(xs, ys)`` (row-major) of an image ``w`` wide."""
    n = xs.size
    if n + n // 2 < params.ransac_min_points:
        return None
    xs, ys, v = subsample(xs, ys, w, params)
    px = np.append(xs.astype(np.float64), vp[0])
    py = np.append(ys.astype(np.float64), vp[1])
    pw = np.append(np.ones(xs.size, np.int64), v)
    scores = score_hypotheses(px, py, pw, xs.size, params)
    t = int(np.argmax(scores))  # first maximum: lowest t on ties
    if scores[t] < 0:
        return None
    u = hypothesis_table(params.seed, params.ransac_trials)
    total = xs.size + v
    i1 = min(int(math.floor(u[t, 0] * total)), xs.size)
    i2 = min(int(math.floor(u[t, 1] * total)), xs.size)
    inl = inliers(px, py, px[i1], py[i1], px[i2], py[i2], params)
    cx, cy, dx, dy = refit(px[inl], py[inl], pw[inl])
    return RowFit(cx, cy, dx, dy, t)


def validate_rows(fits: list[RowFit | None], height: int, width: int, params: Params) -> list[Row]:
    """Step 7.6: validity in row order (``no_support``, ``horizon``, ``parallel``, ``too_close``)."""
    band = params.hough_band_px(width)
    rows: list[Row] = []
    kept: list[tuple[float, float]] = []  # (orientation, x at bottom) of valid rows so far
    for fit in fits:
        if fit is None:
            rows.append(Row(float("nan"), float("nan"), False, "no_support", -1))
            continue
        a, b = fit.as_row()
        orient = math.atan2(fit.dy, fit.dx)
        x_bottom = a * (height - 1) + b
        reason = ""
        if math.atan2(abs(fit.dy), abs(fit.dx)) < params.horizon_angle:
            reason = "horizon"
        elif any(abs(orient - o) < params.min_angle_diff for o, _ in kept):
            reason = "parallel"
        elif any(abs(x_bottom - xb) < band for _, xb in kept):
            reason = "too_close"
        else:
            kept.append((orient, x_bottom))
        rows.append(Row(a, b, reason == "", reason, fit.hypothesis))
    return rows
