"""Reference vanishing point with outlier lines and restarts (ALGORITHM.md section 6)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from torchrow.core.params import Params
from torchrow.core.results import HoughLine
from torchrow.core.tables import hough_trig
from torchrow.reference.hough import HoughState, extract_line

__all__ = ["VPSolution", "vanishing_point", "LineSearch", "find_lines"]


@dataclass(frozen=True)
class VPSolution:
    """Weighted least-squares intersection of Hough lines and its residuals."""

    x: float
    y: float
    residuals: np.ndarray  # (n,) float64, e = rho - x cos - y sin
    spread: float  # s = sqrt(sum (w / sum w) e^2)


def vanishing_point(lines: list[HoughLine], params: Params) -> VPSolution | None:
    """Solve ``[[A, C], [C, B]] [x0, y0] = [D, E]`` (thesis eq. 3.3-3.5) by Cramer's rule.

    Sums run over the lines in their held order. Returns ``None`` for fewer than two lines
    or a singular system (``|det| < singular_tol * trace^2``).
    """
    if len(lines) < 2:
        return None
    cos, sin = hough_trig(params.theta_step)
    a = b = c = d = e = wsum = 0.0
    for ln in lines:
        w, co, si, rho = float(ln.weight), cos[ln.theta_index], sin[ln.theta_index], float(ln.rho)
        a += w * co * co
        b += w * si * si
        c += w * si * co
        d += w * rho * co
        e += w * rho * si
        wsum += w
    det = a * b - c * c
    trace = a + b
    if abs(det) < params.singular_tol * trace * trace:
        return None
    x0 = (d * b - c * e) / det
    y0 = (a * e - c * d) / det
    res = np.array([float(ln.rho) - x0 * cos[ln.theta_index] - y0 * sin[ln.theta_index] for ln in lines])
    s2 = 0.0
    for ln, r in zip(lines, res):
        s2 += (float(ln.weight) / wsum) * (r * r)
    return VPSolution(float(x0), float(y0), res, math.sqrt(s2))


@dataclass
class LineSearch:
    """Outcome of sections 5-6: held lines, dropped outliers, rows asked, vanishing point."""

    lines: list[HoughLine]
    outliers: list[HoughLine] = field(default_factory=list)
    n_rows: int = 0
    vp: tuple[float, float] | None = None


def _fill(state: HoughState, held: list[HoughLine], n: int, params: Params) -> int:
    """Extract lines until ``n`` are held; returns the (possibly lowered) target."""
    while len(held) < n:
        line = extract_line(state, held, params)
        if line is None:
            return len(held)
        held.append(line)
    return n


def find_lines(hough_in: np.ndarray, params: Params) -> LineSearch:
    """Sections 5-6: N-maximum extraction with outlier rejection and N-1 restarts.

    A line is an outlier when its residual is the largest (first on ties) and exceeds both
    ``outlier_ratio * s`` and ``outlier_min_px``. It is dropped (its erasure stays, its angle
    is free again) and the held set is refilled. The ``max_outliers``-th outlier for the
    current N restarts from the untouched Hough input with N - 1 rows. ``vp`` is ``None``
    when fewer than two lines remain or the system is singular.
    """
    n = params.n_rows
    outliers: list[HoughLine] = []
    while n >= 2:
        state = HoughState.start(hough_in, params)
        held: list[HoughLine] = []
        dropped = 0
        n = _fill(state, held, n, params)
        while True:
            sol = vanishing_point(held, params)
            if sol is None:
                return LineSearch(held, outliers, n, None)
            err = np.abs(sol.residuals)
            i = int(np.argmax(err))
            if not (err[i] > params.outlier_ratio * sol.spread and err[i] > params.outlier_min_px):
                return LineSearch(held, outliers, n, (sol.x, sol.y))
            outliers.append(held.pop(i))
            dropped += 1
            if dropped == params.max_outliers:
                break  # restart from the untouched input with one row fewer
            n = _fill(state, held, n, params)
        n -= 1
    return LineSearch([], outliers, n, None)
