"""Reference improved mode (ALGORITHM.md section 11, torchrow extension): the row lattice.

Replaces section 7 when ``Params.mode == "improved"``. Three stages, named as in
:mod:`torchrow.functional.lattice`:

* :func:`green_mask`: excess green ``2G - R - B`` above its Otsu threshold (11.1), or the
  caller's row mask in its place (:func:`row_evidence`, 11.1.1);
* :func:`comb_search`: equally spaced straight rows through the (rounded) vanishing point,
  found by a comb on the pixels projected onto the bottom image row (11.2);
* :func:`fit_lattice`: rows ``x = c(t) + k*d(t)``, ``c`` cubic (or quadratic) and ``d``
  quadratic in ``t = y - (H-1)``, refit by least squares on the mean x of each row's pixels on each
  image row (11.3), with a confidence per row (11.4).

Every sum that decides a discrete output adds integers (exact in float64), so the order of
summation does not matter and the tensor path gets the same bits.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from torchrow.core.io import lattice_params
from torchrow.core.params import LATTICE_ROLL_SCALE, LATTICE_WARP_MARGIN, LATTICE_WARP_SCALE, VP_SLICE, Params
from torchrow.core.results import ImageResult, LatticeRow, Row

__all__ = ["LatticeFit", "LatticePrior", "LatticeStart", "comb_near", "spacing_near",
           "horizon_row", "excess_green", "otsu_threshold", "green_mask", "row_evidence", "init_vp", "vp_grid",
           "vp_cells", "vp_origin", "vp_window", "vp_search", "comb_search", "comb_start", "warp_rate", "warped",
           "solve_normal", "prefix_sums", "centre_spacing", "row_cells",
           "normal_equations", "cell_means", "projective_rows", "roll_rhs", "row_moments", "roll_choice", "refine", "fit_lattice",
           "improved_status", "lattice_rows", "row_polynomial",
           "visible_rows", "row_dominance", "gap_offsets", "improved_rows", "ImprovedRows", "N_COEF", "improved_result"]

#: Coefficients ``(c0, c1, c2, c3, d0, d1, d2)`` of ``x = c(t) + k d(t)``, ``c(t) = c0 + c1 t + c2 t^2 +
#: c3 t^3`` (``c3`` = 0 with ``lattice_center_degree`` 2), ``d(t) = d0 + d1 t + d2 t^2``.
N_COEF = 7
#: Excess green ``2G - R - B`` of uint8 RGB lies in ``[-510, 510]``.
EXG_OFFSET = 510
EXG_BINS = 2 * EXG_OFFSET + 1


@dataclass(frozen=True)
class LatticePrior:
    """The lattice tracker's prior for one frame (section 11.7).

    ``centre``: bottom-row x (px) the central row is chosen nearest to (``W/2`` without a tracked
    row). ``vp``/``spacing``: on a tracked frame the VP the comb uses (the previous frame's
    lattice VP, not searched) and the previous comb spacing; ``None`` = a full search (the VP
    grid searched, the comb unrestricted). ``near``: on a full search of a tracked sequence its
    last grid VP, whose :func:`vp_window` of the grid is searched (``None``: the whole grid).
    ``sweep``: with ``near``, after a frame that was not ``ok``, the grid height (an index into
    ``lattice_vp_heights``) whose whole row of VPs is searched too, after the window."""

    centre: float
    vp: tuple[int, int] | None = None
    spacing: int | None = None
    near: tuple[int, int] | None = None
    sweep: int | None = None


def spacing_near(d: np.ndarray | int, previous: int, params: Params) -> np.ndarray:
    """Section 11.7: spacings ``d`` within ``lattice_track_spacing_tol`` of ``previous``, ``abs(d -
    d') <= lattice_track_spacing_tol * d'`` (float64), bool like ``d``: the tracked comb's candidates
    (:func:`comb_near`) and the tracker's acquisition (``lattice_tracking.confirms``)."""
    return np.abs(np.asarray(d - previous).astype(np.float64)) <= np.float64(params.lattice_track_spacing_tol) * np.float64(
        previous)


def comb_near(d: np.ndarray, p: np.ndarray, width: int, prior: LatticePrior, params: Params) -> np.ndarray:
    """Section 11.7: the comb candidates ``(d, p)`` (``(Q,)`` int64) kept on a tracked frame, bool:
    ``abs(d - d') <= lattice_track_spacing_tol * d'`` and, with ``P = p - W``, ``o = (c - P) - d
    round_half_even((c - P) / d)`` (the offset of the tooth nearest the tracked row's ``c``),
    ``abs(o) <= lattice_track_phase_tol * d`` (float64, this order)."""
    df = d.astype(np.float64)
    rel = (np.float64(prior.centre) - (p - width).astype(np.float64))
    off = rel - df * np.rint(rel / df)
    assert prior.spacing is not None
    return spacing_near(d, prior.spacing, params) & (np.abs(off) <= np.float64(params.lattice_track_phase_tol) * df)


@dataclass(frozen=True)
class LatticeFit:
    """The fitted lattice of one image.

    ``coef`` = ``(c0, c1, c2, c3, d0, d1, d2)`` (px, px/px, px/px^2, ...) of
    ``x = (c0 + c1 t + c2 t^2 + c3 t^3) + k (d0 + d1 t + d2 t^2)``, ``t = y - (H-1)``; ``k`` = row index relative
    to the central row. ``spacing``/``phase``: the comb's bottom-row spacing and the central
    row's bottom-row x (px, integers). ``vp``: the rounded vanishing point the comb used.
    ``support``: image rows holding an inlier of each row, ``(2K+1,)``; ``span``: image rows
    where a row can have support; ``found``: the comb saw at least one pixel. ``contrast``: the
    comb's best score per binned pixel (11.2; 0 without pixels); ``curved``: the curved refit
    was kept (11.3.1). ``lit``: per image row, the number of rows ``-K .. K`` with an inlier there
    (section 11.7's row end). ``roll``: the projective spacing ``g`` of 11.3.2 (row ``k`` lies at
    ``(c(t) + k d(t)) / (1 + g k)``; 0: equally spaced rows).
    """

    coef: tuple[float, ...]
    spacing: int
    phase: int
    vp: tuple[int, int]
    support: tuple[int, ...]
    span: int
    found: bool
    contrast: float = 0.0
    curved: bool = True
    lit: tuple[int, ...] = ()
    roll: float = 0.0


def horizon_row(sky: int, params: Params) -> int:
    """Section 11.1: the first image row the lattice uses, ``0`` or section 2's ``sky``.

    ``Params.lattice_horizon`` ``"image"`` (default) uses every row: section 2 puts a horizon
    60-85 rows down into sky-less field images, and the far rows above it are where the
    quadratic rows need data most; sky pixels are not green, so the mask drops them anyway.
    """
    return 0 if params.lattice_horizon == "image" else sky


def excess_green(rgb: np.ndarray) -> np.ndarray:
    """``2G - R - B`` of ``(H, W, 3)`` uint8 RGB, ``(H, W)`` int64 in ``[-510, 510]``."""
    x = rgb.astype(np.int64)
    return 2 * x[..., 1] - x[..., 0] - x[..., 2]


def otsu_threshold(exg: np.ndarray, sky: int, params: Params) -> int:
    """Section 11.1: Otsu's threshold of the excess green below the horizon.

    Over the histogram of ``e = exg + 510`` (1021 integer bins) with counts ``n_i``:
    ``N_j = sum_{i<=j} n_i``, ``M_j = sum_{i<=j} i n_i``, totals ``N``, ``M``; the
    between-class criterion ``(M N_j - N M_j)^2 / (N_j (N - N_j))`` (float64, this order;
    ``-1`` where a class is empty) is largest at ``j*`` (first on ties). Pixels with
    ``e > j*`` are green, so the threshold is ``max(j* - 510, green_floor)``.
    """
    below = exg[sky:].ravel() + EXG_OFFSET
    hist = np.bincount(below, minlength=EXG_BINS).astype(np.int64)
    cnt = np.cumsum(hist)
    mom = np.cumsum(hist * np.arange(EXG_BINS, dtype=np.int64))
    n, m = cnt[-1], mom[-1]
    other = n - cnt
    num = (m * cnt - n * mom).astype(np.float64)
    den = (cnt * other).astype(np.float64)
    ok = (cnt > 0) & (other > 0)
    crit = np.where(ok, (num * num) / np.where(ok, den, 1.0), -1.0)
    return max(int(np.argmax(crit)) - EXG_OFFSET, params.green_floor)


def green_mask(rgb: np.ndarray, sky: int, params: Params) -> np.ndarray:
    """Section 11.1: ``exg > otsu_threshold`` below the horizon, ``(H, W)`` bool.

    With ``lattice_green == "row_mean"`` (default) a pixel must also lie above the mean excess
    green of its image row, ``W * e > sum_x e`` (int64): far rows, where the leaves of adjacent
    crop rows merge above a global threshold, keep their row structure.
    """
    exg = excess_green(rgb)
    mask = exg > otsu_threshold(exg, sky, params)
    if params.lattice_green == "row_mean":
        mask &= np.int64(exg.shape[1]) * exg > exg.sum(axis=1, keepdims=True)
    mask[:sky] = False
    return mask


def row_evidence(rgb: np.ndarray, sky: int, params: Params, evidence: np.ndarray | None = None) -> np.ndarray:
    """The mask section 11 fits, ``(H, W)`` bool: :func:`green_mask` (11.1), or the caller's
    ``evidence`` (11.1.1: ``(H, W)`` bool at the working size) with the rows above ``sky`` cleared.

    Raises ``ValueError`` if ``evidence`` is not a bool array of the image's size.
    """
    if evidence is None:
        return green_mask(rgb, sky, params)
    if not isinstance(evidence, np.ndarray) or evidence.dtype != np.bool_ or evidence.shape != rgb.shape[:2]:
        got = f"{evidence.dtype} {evidence.shape}" if isinstance(evidence, np.ndarray) else type(evidence).__name__
        raise ValueError(f"evidence: expected a bool array of the working size {rgb.shape[:2]}, got {got}")
    mask = evidence.copy()
    mask[:sky] = False
    return mask


def init_vp(vp: tuple[float, float] | None, width: int, params: Params) -> tuple[int, int]:
    """Section 11.2: the vanishing point the comb uses, rounded to whole pixels.

    Section 6's VP rounded half to even, unless there is none or it lies below image row
    ``lattice_vp_max_y`` (a VP inside the field is a wrong one): then ``(W // 2,
    lattice_vp_fallback_y)``.
    """
    if vp is None or not (vp[1] <= params.lattice_vp_max_y) or not math.isfinite(vp[0]):
        return width // 2, params.lattice_vp_fallback_y
    return int(np.rint(np.float64(vp[0]))), int(np.rint(np.float64(vp[1])))


def vp_grid(width: int, params: Params) -> np.ndarray:
    """Section 11.2: the search's candidate VPs in search order, ``(V, 2)`` int64 ``(xv, yv)``.

    Heights ``lattice_vp_heights`` in their order (outer), and at each height
    ``xv = 0, s, 2s, ... <= W`` with ``s = lattice_vp_step`` (inner).
    """
    xs = np.arange(0, width + 1, params.lattice_vp_step, dtype=np.int64)
    ys = np.array(params.lattice_vp_heights, dtype=np.int64)
    return np.stack([np.tile(xs, ys.size), np.repeat(ys, xs.size)], axis=1)


def vp_cells(height: int, width: int, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """Centres ``(yc, xc)`` (float64, ``(C,)``, row-major) of the search's square cells of side
    ``s = lattice_vp_cell``: cell ``(i, j)`` covers rows ``s i .. s i + s - 1`` and columns
    ``s j .. s j + s - 1`` (clipped to the image), centre ``(s i + (s-1)/2, s j + (s-1)/2)``."""
    s = params.lattice_vp_cell
    hc, wc = -(-height // s), -(-width // s)
    yc = np.repeat(np.arange(hc, dtype=np.float64) * s + (s - 1) / 2, wc)
    xc = np.tile(np.arange(wc, dtype=np.float64) * s + (s - 1) / 2, hc)
    return yc, xc


def vp_origin(sky: int, height: int, params: Params) -> int:
    """Section 11.2: the image row the VP grid's heights count from, ``0`` or, with a horizon in
    view, ``min(sky + lattice_vp_sky, H)``.

    A horizon is in view when ``lattice_vp_origin == "sky"`` and section 1's row ``sky`` has
    ``sky > 0`` and ``lattice_vp_sky_div * sky >= H``: the rows of a level field converge on the
    horizon, which lies at or below the last row of sky (trees and buildings rise above it).
    """
    if params.lattice_vp_origin != "sky" or sky <= 0 or params.lattice_vp_sky_div * sky < height:
        return 0
    return min(max(sky + params.lattice_vp_sky, 0), height)


def vp_window(width: int, params: Params, near: tuple[int, int], origin: int = 0, sweep: int | None = None) -> np.ndarray:
    """Section 11.7: the indices into :func:`vp_grid` that a full search of a tracked sequence
    takes, ``(n,)`` int64, around its last grid VP ``near`` (image pixels), ascending (the grid's
    order); with ``sweep`` (a grid height's index) the ``ncol`` VPs of that height follow, left
    to right (``n + ncol`` indices; those inside the window appear twice).

    With ``step = lattice_vp_step``, ``ncol = W // step + 1`` columns and ``nh`` heights: the
    nearest column ``c = clip((2 x + step) // (2 step), 0, ncol - 1)`` (integers) and the first
    height ``i`` of ``lattice_vp_heights`` nearest to ``y - origin``; the window takes
    ``nx = min(2 lattice_track_vp_cols + 1, ncol)`` columns from ``clip(c - lattice_track_vp_cols,
    0, ncol - nx)`` and ``ny = min(2 lattice_track_vp_rows + 1, nh)`` heights (in their listed
    order) from ``clip(i - lattice_track_vp_rows, 0, nh - ny)``: always ``nx ny`` grid VPs.
    """
    step = params.lattice_vp_step
    ncol, heights = width // step + 1, np.array(params.lattice_vp_heights, dtype=np.int64)
    nx, ny = min(2 * params.lattice_track_vp_cols + 1, ncol), min(2 * params.lattice_track_vp_rows + 1, heights.size)
    c = min(max((2 * int(near[0]) + step) // (2 * step), 0), ncol - 1)
    i = int(np.argmin(np.abs(heights - (int(near[1]) - origin))))
    x0 = min(max(c - params.lattice_track_vp_cols, 0), ncol - nx)
    y0 = min(max(i - params.lattice_track_vp_rows, 0), heights.size - ny)
    win = ((y0 + np.arange(ny, dtype=np.int64))[:, None] * ncol + x0 + np.arange(nx, dtype=np.int64)).ravel()
    if sweep is None:
        return win
    if not 0 <= sweep < heights.size:
        raise ValueError(f"sweep must index one of the {heights.size} grid heights, got {sweep}")
    return np.concatenate([win, sweep * ncol + np.arange(ncol, dtype=np.int64)])


def vp_search(mask: np.ndarray, params: Params, origin: int = 0, near: tuple[int, int] | None = None,
              sweep: int | None = None) -> tuple[int, int]:
    """Section 11.2: the grid VP whose folded contrast comb is strongest (``lattice_vp == "search"``).

    ``origin`` (:func:`vp_origin`): the search runs on the mask's rows ``origin .. H-1`` moved
    up to rows ``0 .. H-1-origin`` (the rows below are empty) and adds ``origin`` to the VP's
    row, so the grid's heights count from row ``origin``. ``near`` (section 11.7, a tracked
    sequence's last grid VP; ``sweep``: the grid height swept after a frame that was not ``ok``):
    only the grid VPs of :func:`vp_window` are candidates, in its order.

    The green pixels are counted in cells (:func:`vp_cells`). For each VP of :func:`vp_grid`,
    every cell with ``yc - yv > lattice_vp_margin`` projects its count through the VP onto the
    bottom row, ``X = xv + ((xc - xv) * ((H-1) - yv)) / (yc - yv)`` (float64, this order),
    into bin ``floor(X) + W`` when ``-W <= floor(X) < 2W`` (``3W`` bins, ``n`` counts binned).
    For the spacings ``d = lattice_min_spacing, + lattice_vp_spacing_step, ... <=
    lattice_max_spacing``, the histogram is folded modulo ``d`` (``F[r]`` = sum of bins ``b``
    with ``b mod d = r``); with ``h = floor(d * lattice_window)`` the tooth of phase ``p``
    holds ``F[(p-h) mod d] + ... + F[(p+h) mod d]`` and its anti-tooth is the tooth of phase
    ``(p + d // 2) mod d``. The VP scores ``max_{d,p} (tooth - anti-tooth) / n`` (integer
    numerator and denominator, one float64 division); the highest wins, the first on ties.
    Without a binned count at any VP: ``(W // 2, lattice_vp_fallback_y)``.
    """
    h, w = mask.shape
    s = params.lattice_vp_cell
    hc, wc = -(-h // s), -(-w // s)
    padded = np.zeros((hc * s, wc * s), np.int64)
    padded[:h - origin, :w] = mask[origin:]
    cnt = padded.reshape(hc, s, wc, s).sum(axis=(1, 3)).ravel()
    yc, xc = vp_cells(h, w, params)
    occupied = cnt > 0  # only counted cells are binned
    yc, xc, cnt = yc[occupied], xc[occupied], cnt[occupied]
    grid = vp_grid(w, params)
    if near is not None:
        grid = grid[vp_window(w, params, near, origin, sweep)]
    nb = 3 * w
    hist = np.zeros((grid.shape[0], nb), np.int64)
    step = max(1, VP_SLICE // max(cnt.size, 1))  # VPs per slice: the projections stay ~VP_SLICE entries
    for v0 in range(0, grid.shape[0], step):
        xv = grid[v0:v0 + step, :1].astype(np.float64)
        yv = grid[v0:v0 + step, 1:].astype(np.float64)
        proj = xv + ((xc - xv) * (np.float64(h - 1) - yv)) / (yc - yv)
        b = np.floor(proj)
        keep = ((yc - yv) > params.lattice_vp_margin) & (b >= -w) & (b < 2 * w)
        np.add.at(hist[v0:v0 + step].reshape(-1), np.nonzero(keep)[0] * nb + b[keep].astype(np.int64) + w,
                  np.broadcast_to(cnt, keep.shape)[keep])
    total = hist.sum(axis=1)
    if not (total > 0).any():
        return w // 2, params.lattice_vp_fallback_y
    best = np.full(grid.shape[0], np.iinfo(np.int64).min, np.int64)
    for d in range(params.lattice_min_spacing, params.lattice_max_spacing + 1, params.lattice_vp_spacing_step):
        teeth = -(-nb // d)
        fold = np.concatenate([hist, np.zeros((grid.shape[0], teeth * d - nb), np.int64)], axis=1)
        fold = fold.reshape(grid.shape[0], teeth, d).sum(axis=1)
        hw = int(math.floor(d * params.lattice_window))
        ext = np.concatenate([fold[:, d - hw:], fold, fold[:, :hw + 1]], axis=1)  # F[p - hw .. p + hw] circularly
        cs = np.concatenate([np.zeros((grid.shape[0], 1), np.int64), np.cumsum(ext, axis=1)], axis=1)
        tooth = cs[:, 2 * hw + 1:2 * hw + 1 + d] - cs[:, :d]
        best = np.maximum(best, (tooth - np.roll(tooth, -(d // 2), axis=1)).max(axis=1))
    seen = total > 0
    value = np.where(seen, best.astype(np.float64) / np.maximum(total, 1).astype(np.float64), -np.inf)
    q = int(np.argmax(value))
    return int(grid[q, 0]), int(grid[q, 1]) + origin


def _comb_tables(width: int, params: Params) -> tuple[np.ndarray, ...]:
    """:func:`_comb_tables_for` of ``params``' spacing range and window."""
    return _comb_tables_for(width, params.lattice_min_spacing, params.lattice_max_spacing, params.lattice_window)


# The tables depend on the image width and three parameters only; every image of a folder or a
# video needs the same ones. One set is kept (read-only; at most half of 11.5's 2**30-byte bound).
@functools.lru_cache(maxsize=1)
def _comb_tables_for(width: int, min_spacing: int, max_spacing: int, window: float) -> tuple[np.ndarray, ...]:
    """All ``(spacing, phase)`` candidates in search order and their tooth windows.

    Bottom-row x is binned on ``[-W, 2W)`` (bin ``floor(X) + W``, ``3W`` bins). Candidate
    spacing ``d`` (``lattice_min_spacing .. lattice_max_spacing``), phase ``p = 0 .. d-1``:
    teeth at bins ``p + j d < 3W``, each covering bins ``[p + j d - h, p + j d + h]`` with
    ``h = floor(d * lattice_window)``, clipped to the bins; anti-teeth likewise at bins
    ``p + j d + d // 2 < 3W``. Returns ``d, p, h`` ``(Q,)`` and the cumulative-sum indices
    ``lo, hi, alo, ahi`` ``(Q, J)`` of the teeth and anti-teeth (``lo == hi`` for absent ones), int64.
    """
    nb = 3 * width
    ds, ps, hs, wins = [], [], [], []
    jmax = nb // min_spacing + 1

    def windows(centres: np.ndarray, h: int) -> np.ndarray:
        out = np.zeros((2, jmax), np.int64)
        out[0, :centres.size] = np.clip(centres - h, 0, nb)
        out[1, :centres.size] = np.clip(centres + h + 1, 0, nb)
        return out

    for d in range(min_spacing, max_spacing + 1):
        h = int(math.floor(d * window))
        for p in range(d):
            anti = np.arange(p + d // 2, nb, d)
            wins.append(np.concatenate([windows(np.arange(p, nb, d), h), windows(anti, h)]))
            ds.append(d)
            ps.append(p)
            hs.append(h)
    w = np.stack(wins)
    out = (np.array(ds), np.array(ps), np.array(hs), w[:, 0], w[:, 1], w[:, 2], w[:, 3])
    for a in out:
        a.flags.writeable = False
    return out


def warp_rate(warp: int, width: int) -> np.float64:
    """Section 11.3.2: the comb's warp ``j`` as ``gamma = j / ((LATTICE_WARP_SCALE / 2) W)`` per
    pixel (float64, one division of integers)."""
    return np.float64(warp) / np.float64(LATTICE_WARP_SCALE // 2 * width)


def warped(x: np.ndarray, gamma: np.float64, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Section 11.3.2: bottom-row positions ``x`` (float64) under the comb's projective warp,
    ``x' = x0 + (x - x0) / (1 - gamma (x - x0))`` with ``x0 = W / 2`` (float64, this order), and
    where it is defined (``1 - gamma (x - x0) > 0``), bool. Rows at ``(c + k d) / (1 + g k)`` are
    equally spaced under the warp whose pole ``x0 + 1 / gamma`` is their limit ``d / g``."""
    x0 = np.float64(width) / np.float64(2.0)
    t = x - x0
    den = np.float64(1.0) - gamma * t
    ok = den > 0
    return x0 + t / np.where(ok, den, np.float64(1.0)), ok


def bottom_bins(xs: np.ndarray, ys: np.ndarray, vp: tuple[int, int], height: int,
                width: int, params: Params, warp: int = 0) -> np.ndarray:
    """Bin of each pixel's projection through the VP onto the bottom row (section 11.2).

    Pixels with ``y - yv > lattice_vp_margin`` project to
    ``X = xv + ((x - xv) * (H-1 - yv)) / (y - yv)`` (float64, this order); with ``warp`` ``j != 0``
    (11.3.2) ``X`` is replaced by :func:`warped` ``X`` for ``gamma =`` :func:`warp_rate` and pixels
    where the warp is undefined are dropped; bin ``floor(X) + W``, kept when in ``[0, 3W)``.
    Returns the kept bins, int64.
    """
    xv, yv = vp
    sel = (ys - yv) > params.lattice_vp_margin
    xs, ys = xs[sel].astype(np.float64), ys[sel].astype(np.float64)
    proj = np.float64(xv) + ((xs - np.float64(xv)) * np.float64(height - 1 - yv)) / (ys - np.float64(yv))
    defined = np.ones(proj.shape, bool)
    if warp != 0:
        proj, defined = warped(proj, warp_rate(warp, width), width)
    b = np.floor(proj)
    keep = defined & (b >= -width) & (b < 2 * width)
    return b[keep].astype(np.int64) + width


def comb_search(mask: np.ndarray, vp: tuple[int, int], params: Params,
                prior: LatticePrior | None = None, warp: int = 0) -> tuple[int, int, bool, float]:
    """Section 11.2: bottom-row spacing and central phase of the rows through ``vp``.

    Histogram the bins of :func:`bottom_bins`; candidate ``q`` captures ``cap_q`` pixels in
    its teeth and ``anti_q`` in its anti-teeth. With ``lattice_comb == "contrast"`` (default) it
    scores ``cap_q - anti_q`` (an integer): a comb at twice the true spacing puts its anti-teeth
    on the rows it skips, so harmonics lose. With ``"uniform"`` it scores ``cap_q - (n (2h+1)) / d``
    (float64; ``n`` = binned pixels): the excess over a uniform spread. The best (first on ties)
    gives ``d`` and ``p``; the central
    row is the tooth nearest ``W/2``: ``phase = p - W + d * round_half_even((W/2 - (p - W)) / d)``.
    Returns ``(d, phase, found, contrast)``, ``contrast`` = the best score divided by the
    number of binned pixels (float64; the evidence of 11.4's status); without pixels
    ``(lattice_min_spacing, W // 2, False, 0.0)``. ``prior`` (section 11.7): the central row is
    the tooth nearest ``prior.centre`` instead of ``W/2``, and with ``prior.spacing`` only the
    candidates of :func:`comb_near` compete (the others score ``-inf``). ``warp`` ``j``: the
    comb on the warped bottom row of 11.3.2 (:func:`bottom_bins`), the centre warped alike; its
    spacing and phase are the warped row's.
    """
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    bins = bottom_bins(xs, ys, vp, h, w, params, warp)
    if bins.size == 0:
        return params.lattice_min_spacing, w // 2, False, 0.0
    hist = np.bincount(bins, minlength=3 * w).astype(np.int64)
    cs = np.concatenate([[0], np.cumsum(hist)])
    d, p, hw, lo, hi, alo, ahi = _comb_tables(w, params)
    cap = (cs[hi] - cs[lo]).sum(axis=1)
    if params.lattice_comb == "contrast":
        score = (cap - (cs[ahi] - cs[alo]).sum(axis=1)).astype(np.float64)
    else:
        score = cap.astype(np.float64) - (bins.size * (2 * hw + 1)).astype(np.float64) / d.astype(np.float64)
    centre = np.float64(w) / 2 if prior is None else np.float64(prior.centre)
    if warp != 0:
        centre = warped(np.array([centre]), warp_rate(warp, w), w)[0][0]
    if prior is not None and prior.spacing is not None:
        score = np.where(comb_near(d, p, w, prior, params), score, -np.inf)
    q = int(np.argmax(score))
    d_q, p_q = int(d[q]), int(p[q]) - w
    k0 = int(np.rint((centre - np.float64(p_q)) / np.float64(d_q)))
    return d_q, p_q + k0 * d_q, True, float(score[q] / np.float64(bins.size))


class LatticeStart(NamedTuple):
    """:func:`comb_start`'s result (the tensor path's ``LatticeStartBatch`` for one image): the
    straight start ``coef`` (7,) float64 through ``vp``, the comb's ``spacing``, ``phase``, ``found``
    and ``contrast`` (:func:`comb_search`), the curved refit's start ``bent`` (7,) float64 and the
    straight start's projective spacing ``roll`` (11.3.2; 0 without a warp)."""

    coef: np.ndarray
    spacing: int
    phase: int
    found: bool
    vp: tuple[int, int]
    contrast: float
    bent: np.ndarray
    roll: float


def comb_start(mask: np.ndarray, vp: tuple[int, int], params: Params, prior: LatticePrior | None = None) -> LatticeStart:
    """Section 11.2's comb through ``vp`` and 11.3's starts from it (:class:`LatticeStart`).

    Without a warp: ``c(t) = phase + ((phase - xv) / (H-1 - yv)) t``, ``d(t) = d + (d / (H-1 - yv)) t``
    (straight rows through the VP), ``g = 0``, ``bent = coef``. With ``lattice_comb_warps`` (11.3.2)
    the comb also runs on each warp ``j`` of :meth:`Params.lattice_warps` in that order (not where
    ``prior`` restricts it: a tracked frame's comb is the bottom row's), and the first highest
    ``contrast`` wins, a warp over the unwarped comb only by more than ``LATTICE_WARP_MARGIN`` of
    the unwarped comb's ``|contrast|``. A warp's teeth ``P + k d'`` (``gamma =`` :func:`warp_rate`, ``x0 = W / 2``)
    are the rows ``(c + k D) / (1 + g k)`` with ``u = 1 + gamma (P - x0)``, ``a = (P - x0) / u``,
    ``s = d' / u``, ``g = gamma s``, ``D = s + g x0``, ``c = x0 + a`` (float64, this order): the
    straight start ``c(t) = c + ((c - xv) / (H-1 - yv)) t``, ``d(t) = D + ((D - g xv) / (H-1 - yv)) t``
    (the rows' pencil through the VP) with that ``g``; ``bent`` takes the central row's own
    spacing ``D - g c`` in place of ``D`` with ``g = 0`` (the curved refit is equally spaced).
    """
    h, w = mask.shape
    xv, yv = vp
    den = np.float64(h - 1 - yv)
    restricted = prior is not None and prior.spacing is not None
    best, warp = comb_search(mask, vp, params, prior), 0
    for j in params.lattice_warps()[1:] if not restricted else ():
        got = comb_search(mask, vp, params, prior, j)
        bar = best[3] if warp != 0 else best[3] + LATTICE_WARP_MARGIN * abs(best[3])
        if got[2] and (not best[2] or got[3] > bar):
            best, warp = got, j
    d, phase, found, contrast = best
    p, sp = np.float64(phase), np.float64(d)
    coef = np.array([p, (p - np.float64(xv)) / den, 0.0, 0.0, sp, sp / den, 0.0], np.float64)
    if warp == 0:
        return LatticeStart(coef, d, phase, found, vp, contrast, coef, 0.0)
    gamma = warp_rate(warp, w)
    x0 = np.float64(w) / np.float64(2.0)
    u = np.float64(1.0) + gamma * (p - x0)
    a = (p - x0) / u
    s = sp / u
    g = gamma * s
    dd = s + g * x0
    c = x0 + a
    own = dd - g * c
    coef = np.array([c, (c - np.float64(xv)) / den, 0.0, 0.0, dd, (dd - g * np.float64(xv)) / den, 0.0], np.float64)
    bent = np.array([c, (c - np.float64(xv)) / den, 0.0, 0.0, own, own / den, 0.0], np.float64)
    return LatticeStart(coef, d, phase, found, vp, contrast, bent, float(g))


def solve_normal(m: np.ndarray, r: np.ndarray, params: Params) -> np.ndarray | None:
    """Gaussian elimination without pivoting of the SPD system ``m z = r`` (``n x n``, float64).

    Row ``i`` is eliminated with pivot ``m[i, i]`` in index order; the system is singular
    (``None``) when a pivot is ``<= lattice_pivot_tol * max(m[i, i], 1)``, its own diagonal
    entry before elimination (the basis' entries range from 1 to ``t^6``, so one scale for all
    rows would call every cubic system singular). Written scalar by scalar so that the tensor
    path evaluates the same operations.
    """
    n = len(r)
    a = [[float(m[i, j]) for j in range(n)] for i in range(n)]
    z = [float(v) for v in r]
    scale = [max(a[i][i], 1.0) for i in range(n)]
    for i in range(n):
        piv = a[i][i]
        if not piv > params.lattice_pivot_tol * scale[i]:
            return None
        for j in range(i + 1, n):
            f = a[j][i] / piv
            for k in range(i, n):
                a[j][k] = a[j][k] - f * a[i][k]
            z[j] = z[j] - f * z[i]
    out = [0.0] * n
    for i in range(n - 1, -1, -1):
        s = z[i]
        for k in range(i + 1, n):
            s = s - a[i][k] * out[k]
        out[i] = s / a[i][i]
    return np.array(out, np.float64)


def centre_spacing(t: np.ndarray, coef: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``c(t) = ((c0 + c1 t) + c2 t^2) + c3 t^3`` and ``d(t) = (d0 + d1 t) + d2 t^2`` (px, float64,
    this order; ``t^2 = t t``, ``t^3 = t^2 t``)."""
    c0, c1, c2, c3, d0, d1, d2 = (np.float64(v) for v in coef)
    tt = t * t
    return ((c0 + c1 * t) + c2 * tt) + c3 * (tt * t), (d0 + d1 * t) + d2 * tt


def prefix_sums(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per image row, the count and the x sum of the mask's pixels left of each column: two
    ``(H, W+1)`` int64 (entry ``j`` covers columns ``0 .. j-1``). Built once per image; every
    refit step reads them."""
    h, w = mask.shape
    m = mask.astype(np.int64)
    pre = np.zeros((h, w + 1), np.int64)
    pre_x = np.zeros((h, w + 1), np.int64)
    pre[:, 1:] = np.cumsum(m, axis=1)
    pre_x[:, 1:] = np.cumsum(m * np.arange(w, dtype=np.int64), axis=1)
    return pre, pre_x


def projective_rows(cc: np.ndarray, dd: np.ndarray, k: float, g: float) -> tuple[np.ndarray, np.ndarray, np.float64]:
    """Section 11.3.2: row ``k``'s centre ``(c(t) + k d(t)) / u`` and own spacing ``(d(t) - g c(t)) /
    (u u)`` on every image row (float64, this order) and ``u = 1 + g k``."""
    kf, gf = np.float64(k), np.float64(g)
    u = np.float64(1.0) + gf * kf
    return (cc + kf * dd) / u, (dd - gf * cc) / (u * u), u


def row_cells(pre: tuple[np.ndarray, np.ndarray], coef: np.ndarray, params: Params,
              ks: Sequence[float] | None = None, roll: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Section 11.3: inlier count and sum of x per lattice row and image row, two ``(2K+1, H)`` int64
    (rows ``k = -K .. K``; ``ks``: these rows instead, ``(len(ks), H)``).

    On image row ``y`` (``t = y - (H-1)``) where ``d(t) > lattice_min_spacing_px``, the inliers
    of row ``k`` are the mask pixels with ``lo < x < hi``: ``centre = c(t) + k d(t)``,
    ``half = lattice_tolerance * d(t)``, ``lo = centre - half``, ``hi = centre + half`` (float64,
    this order), i.e. the columns ``floor(lo) + 1 .. ceil(hi) - 1`` clipped to the image. The
    counts and sums are differences of the mask's :func:`prefix_sums` (integers).

    ``roll`` ``g != 0`` (11.3.2): ``u = 1 + g k``, ``centre = (c(t) + k d(t)) / u``, ``half =
    lattice_tolerance * ((d(t) - g c(t)) / (u u))`` (the local spacing), and the row is assigned
    where that spacing exceeds ``lattice_min_spacing_px`` and ``u > 0`` (with ``g = 0`` the same
    values as above).
    """
    counts, pre_x = pre
    h, w = counts.shape[0], counts.shape[1] - 1
    cc, dd = centre_spacing(np.arange(h, dtype=np.float64) - np.float64(h - 1), coef)
    ok = dd > params.lattice_min_spacing_px
    half = np.float64(params.lattice_tolerance) * dd
    yy = np.arange(h)
    ks = range(-params.lattice_half, params.lattice_half + 1) if ks is None else ks
    cnt = np.zeros((len(ks), h), np.int64)
    sx = np.zeros_like(cnt)
    g = np.float64(roll)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for i, k in enumerate(ks):
            if roll:
                centre, local, u = projective_rows(cc, dd, k, g)
                half = np.float64(params.lattice_tolerance) * local
                ok = (local > params.lattice_min_spacing_px) & (u > 0)
            else:
                centre = cc + np.float64(k) * dd
            lo, hi = centre - half, centre + half
            good = ok & np.isfinite(lo) & np.isfinite(hi)
            x0 = np.clip(np.floor(np.where(good, lo, 0.0)) + 1, 0, w).astype(np.int64)
            x1 = np.clip(np.ceil(np.where(good, hi, 0.0)), 0, w).astype(np.int64)
            x1 = np.where(good, np.maximum(x1, x0), x0)
            cnt[i] = counts[yy, x1] - counts[yy, x0]
            sx[i] = pre_x[yy, x1] - pre_x[yy, x0]
    return cnt, sx


def normal_equations(cnt: np.ndarray, sx: np.ndarray, height: int,
                     params: Params, straight: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Section 11.3: the least-squares system of one observation per occupied cell.

    Cell ``(k, y)`` with ``n > 0`` inliers observes ``x = q / G`` with ``q = round_half_even((G *
    sum x) / n)`` (float64 division; ``G = lattice_cell_grid``), basis ``phi`` =
    :meth:`Params.lattice_basis` (``1, t, t^2 (, t^3), k, k t, k t^2``; ``1, t, k, k t`` when
    ``straight``). ``M = sum phi phi^T`` and
    ``r = sum q phi`` are summed in int64 (exact; :func:`torchrow.core.io.lattice_params`
    keeps them in range), then ``M`` is converted to float64 and ``r`` to float64 divided by ``G``.
    """
    k, t, q = cell_means(cnt, sx, height, params)
    phi = np.stack([t**p * k**e for p, e in params.lattice_basis(straight)], axis=1)  # (cells, n) int64
    m = (phi[:, :, None] * phi[:, None, :]).sum(axis=0)
    r = (phi * q[:, None]).sum(axis=0)
    return m.astype(np.float64), r.astype(np.float64) / np.float64(params.lattice_cell_grid)


def cell_means(cnt: np.ndarray, sx: np.ndarray, height: int,
               params: Params) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Section 11.3's observations: per occupied cell ``(k, y)`` (``n > 0``, in row-major order),
    ``k``, ``t = y - (H-1)`` and ``q = round_half_even((G * sum x) / n)`` (float64 division),
    three int64 arrays."""
    kk, yy = np.nonzero(cnt > 0)
    n = cnt[kk, yy].astype(np.float64)
    q = np.rint((np.float64(params.lattice_cell_grid) * sx[kk, yy].astype(np.float64)) / n).astype(np.int64)
    return kk.astype(np.int64) - params.lattice_half, yy.astype(np.int64) - (height - 1), q


def roll_rhs(obs: tuple[np.ndarray, np.ndarray, np.ndarray], params: Params) -> np.ndarray:
    """Section 11.3.2: ``r1 = sum q k phi`` over the straight basis (int64 sums), float64 divided
    by ``G``: the right-hand side whose solution ``z1`` moves the straight solution with ``g``.
    ``obs``: :func:`cell_means`."""
    k, t, q = obs
    phi = np.stack([t**p * k**e for p, e in params.lattice_basis(True)], axis=1)
    return (phi * (q * k)[:, None]).sum(axis=0).astype(np.float64) / np.float64(params.lattice_cell_grid)


def row_moments(obs: tuple[np.ndarray, np.ndarray, np.ndarray], params: Params) -> np.ndarray:
    """Section 11.3.2: per lattice row ``k = -K .. K`` the sums over its occupied cells of ``1, t,
    t^2, q, q^2, q t``, ``(2K+1, 6)`` int64, from :func:`cell_means`' ``obs``."""
    k, t, q = obs
    parts = np.stack([np.ones_like(t), t, t * t, q, q * q, q * t], axis=1)
    out = np.zeros((2 * params.lattice_half + 1, 6), np.int64)
    np.add.at(out, k + params.lattice_half, parts)
    return out


def roll_choice(z0: np.ndarray, z1: np.ndarray, moments: np.ndarray, params: Params) -> tuple[float, np.ndarray]:
    """Section 11.3.2: the projective spacing ``g`` of :meth:`Params.lattice_rolls` whose rows lie
    nearest the cell means in x, and its straight solution ``z0 + g z1`` (``c0, c1, d0, d1``).

    For each ``g = i / 100`` (float64): ``z = z0 + g z1``; per row ``k`` (in order), ``u = 1 + g k``,
    ``a = c0 + k d0``, ``b = c1 + k d1``, and with the row's :func:`row_moments` (float64)
    ``S_k = (Q2 / (G G) - (2 (a Q1 + b QT)) / (G u)) + (((a a) N + (2 (a b)) T1) + (b b) T2) / (u u)``,
    the sum over the row's cells of ``(q / G - (a + b t) / u)^2``; ``E = S_-K + ... + S_K``. The
    first smallest ``E`` wins (NaN counts as infinite), so both paths choose the same ``g``.
    """
    grid = np.float64(params.lattice_cell_grid)
    two = np.float64(2.0)
    errs, sols = [], []
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for i in params.lattice_rolls():
            g = np.float64(i) / np.float64(LATTICE_ROLL_SCALE)
            z = z0 + g * z1
            err = np.float64(0.0)
            for j, k in enumerate(range(-params.lattice_half, params.lattice_half + 1)):
                n, t1, t2, q1, q2, qt = (np.float64(v) for v in moments[j])
                kf = np.float64(k)
                u = np.float64(1.0) + g * kf
                a = z[0] + kf * z[2]
                b = z[1] + kf * z[3]
                err = err + ((q2 / (grid * grid) - (two * (a * q1 + b * qt)) / (grid * u))
                             + (((a * a) * n + (two * (a * b)) * t1) + (b * b) * t2) / (u * u))
            errs.append(np.inf if np.isnan(err) else err)
            sols.append(z)
    best = int(np.argmin(np.array(errs, np.float64)))
    return float(np.float64(params.lattice_rolls()[best]) / np.float64(LATTICE_ROLL_SCALE)), sols[best]


def refine(pre: tuple[np.ndarray, np.ndarray], coef: np.ndarray, height: int, params: Params,
           straight: bool, roll: float = 0.0) -> tuple[np.ndarray, float]:
    """Section 11.3: up to ``lattice_iterations`` least-squares refits of ``coef`` (7,) float64;
    returns the coefficients and the projective spacing ``g`` (11.3.2; the start's ``roll``, 0
    unless a warped comb gave one, until a straight refit searches it).

    Each iteration takes the inlier cells of :func:`row_cells` and solves
    :func:`normal_equations` in the straight or curved basis; a straight refit with
    ``lattice_roll_grid > 0`` solves it for :func:`roll_rhs` too and keeps :func:`roll_choice`'s
    ``g``, whose cells the next iteration takes. With fewer than
    ``lattice_min_points`` inlier pixels or a singular system the coefficients stay (and the
    iterations stop); cells equal to the previous iteration's would give the same coefficients
    again, so the iterations stop there too (a fixed point: the result is that of running all
    of them).
    """
    where = params.lattice_coef_index(straight)
    search = straight and params.lattice_roll_grid > 0
    last = None
    for _ in range(params.lattice_iterations):
        cnt, sx = row_cells(pre, coef, params, roll=roll)
        if int(cnt.sum()) < params.lattice_min_points:
            break
        if last is not None and np.array_equal(cnt, last[0]) and np.array_equal(sx, last[1]):
            break
        m, r = normal_equations(cnt, sx, height, params, straight)
        sol = solve_normal(m, r, params)
        if sol is None:
            break
        if search:  # the same m, so the same pivots: never singular here
            obs = cell_means(cnt, sx, height, params)
            z1 = solve_normal(m, roll_rhs(obs, params), params)
            assert z1 is not None
            roll, sol = roll_choice(sol, z1, row_moments(obs, params), params)
        coef = np.zeros(N_COEF, np.float64)
        coef[where] = sol
        last = (cnt, sx)
    return coef, roll


def fit_lattice(mask: np.ndarray, sky: int, vp: tuple[float, float] | None, params: Params,
                prior: LatticePrior | None = None, origin: int = 0) -> LatticeFit:
    """Sections 11.2-11.4 on a green mask: comb start, then the refits of 11.3 and 11.3.1.

    Starts: :func:`comb_start`'s (straight rows through the VP; with a warped comb, 11.3.2, the
    straight start's projective spacing too). ``lattice_model`` ``"curved"``: one curved
    :func:`refine` from the curved start. ``"straight"``: one straight refine. ``"auto"`` (default):
    a straight and a curved refine, each from its start, the curved one kept only where its inlier
    pixels exceed ``(1 + lattice_curve_gain)`` times the straight lattice's (float64), so
    straight rows stay straight unless the pixels demand a bend. ``prior``: section 11.7's
    tracked frame (its VP instead of the search, the comb restricted; no refits where the comb's
    contrast is below ``lattice_min_contrast``: the frame is redone). ``origin``: the VP grid's
    (:func:`vp_origin`).
    """
    h, w = mask.shape
    params = lattice_params(w, h, params)  # cubic where the int64 sums allow it, else quadratic
    if params.lattice_vp == "search":
        v = prior.vp if prior is not None and prior.vp is not None else vp_search(
            mask, params, origin, None if prior is None else prior.near, None if prior is None else prior.sweep)
    else:
        v = init_vp(vp, w, params)
    begun = comb_start(mask, v, params, prior)
    d, phase, found, contrast, coef, bent = begun.spacing, begun.phase, begun.found, begun.contrast, begun.coef, begun.bent
    mask = mask.copy()
    mask[:max(sky, 0)] = False
    pre = prefix_sums(mask)
    curved = params.lattice_model == "curved"
    start = bent if curved else coef
    # a tracked frame (11.7) whose comb is too weak for `ok` (11.4) is redone in full whatever
    # its refits give: they are skipped
    skip = prior is not None and prior.spacing is not None and contrast < params.lattice_min_contrast
    coef, roll = (start, 0.0) if skip else refine(pre, start, h, params, straight=not curved, roll=0.0 if curved else begun.roll)
    if params.lattice_model == "auto":
        # from the comb's start too: started from the straight fit, the curved refit keeps the
        # straight fit's cells where a bend has already lost the far pixels
        bent = bent if skip else refine(pre, bent, h, params, straight=False)[0]
        n_straight = int(row_cells(pre, coef, params, roll=roll)[0].sum())
        n_bent = int(row_cells(pre, bent, params)[0].sum())
        if np.float64(n_bent) > (np.float64(1.0) + np.float64(params.lattice_curve_gain)) * np.float64(n_straight):
            coef, curved, roll = bent, True, 0.0
    cnt, _ = row_cells(pre, coef, params, roll=roll)
    support = tuple(int(s) for s in (cnt > 0).sum(axis=1))
    span = h - max(sky, 0)
    lit = tuple(int(s) for s in (cnt > 0).sum(axis=0))
    return LatticeFit(tuple(float(c) for c in coef), d, phase, v, support, span, found, contrast, curved, lit, roll)


def row_polynomial(coef: Sequence[float], k: int, height: int, roll: float = 0.0) -> tuple[float, float, float, float]:
    """Section 11.4: lattice row ``k`` as ``x = e*y^3 + c*y^2 + a*y + b``, returns ``(a, b, c, e)``.

    With ``Y = H-1``, ``s = c1 + k d1``, ``u = c2 + k d2``: ``e = c3``, ``c = u - (3 e) Y``,
    ``a = (s - (2 u) Y) + (3 e) (Y Y)``, ``b = (((c0 + k d0) - s Y) + u (Y Y)) - e (Y Y Y)``
    (float64, this order); with a projective spacing ``roll`` ``g != 0`` (11.3.2) each of them
    then divided by ``1 + g k``.
    """
    c0, c1, c2, c3, d0, d1, d2 = (np.float64(v) for v in coef)
    yb = np.float64(height - 1)
    kf = np.float64(k)
    slope = c1 + kf * d1
    curv = c2 + kf * d2
    three = np.float64(3.0) * c3
    a = (slope - (np.float64(2.0) * curv) * yb) + three * (yb * yb)
    b = (((c0 + kf * d0) - slope * yb) + curv * (yb * yb)) - c3 * (yb * yb * yb)
    c = curv - three * yb
    if roll:
        u = np.float64(1.0) + np.float64(roll) * kf
        return float(a / u), float(b / u), float(c / u), float(c3 / u)
    return float(a), float(b), float(c), float(c3)


def lattice_rows(fit: LatticeFit, height: int, params: Params) -> list[Row]:
    """Section 11.4: rows ``k = -K .. K`` as ``x = e*y^3 + c*y^2 + a*y + b`` (:func:`row_polynomial`)
    with a confidence.

    Confidence = image rows holding an inlier of the row / image rows below the horizon. A
    row is valid iff the comb found pixels and its confidence is ``>= lattice_min_confidence``
    (reason ``no_support`` otherwise).
    """
    rows = []
    for i in range(2 * params.lattice_half + 1):
        a, b, c, e = row_polynomial(fit.coef, i - params.lattice_half, height, fit.roll)
        conf = float(np.float64(fit.support[i]) / np.float64(max(fit.span, 1)))
        ok = fit.found and conf >= params.lattice_min_confidence
        rows.append(Row(a, b, ok, "" if ok else "no_support", -1, c, conf, e))
    return rows


def gap_offsets(params: Params) -> list[float]:
    """The ``2K+2`` gaps beside rows ``-K .. K``: ``k = -K-1/2 .. K+1/2`` (gap ``j`` between rows
    ``j-1`` and ``j``; section 11.4's dominance)."""
    return [j - (params.lattice_half + 0.5) for j in range(2 * params.lattice_half + 2)]


def row_dominance(rows: np.ndarray, gaps: np.ndarray) -> float:
    """Section 11.4: the share of lit cells where a row's inliers outnumber the fuller of its two
    gaps'. ``rows (2K+1, H)`` are the cells of rows ``-K .. K`` (:func:`row_cells`), ``gaps (2K+2,
    H)`` those of :func:`gap_offsets`. Cell ``(k, y)`` is lit where ``n + m > 0`` and wins where
    ``n > m`` (``m`` = the larger of its gaps' counts on image row ``y``); wins / max(lit, 1)
    (float64)."""
    m = np.maximum(gaps[:-1], gaps[1:])
    lit = int(((rows + m) > 0).sum())
    return float(np.float64(int((rows > m).sum())) / np.float64(max(lit, 1)))


def visible_rows(mask: np.ndarray, top: int, fit: LatticeFit, params: Params) -> tuple[list[LatticeRow], float]:
    """Section 11.4: every row of the fitted lattice that the image shows, ``k`` ascending, and
    the dominance of rows ``-K .. K`` (:func:`row_dominance`, from the same cells; NaN, not
    computed, where ``lattice_min_dominance`` is 0).

    Rows ``k = -K_v .. K_v`` (:meth:`Params.lattice_visible_half`) take their inliers by the cells
    of 11.3 (:func:`row_cells` on the green pixels of rows ``y >= top``); a row is reported when the
    comb found pixels, its centre ``c(t) + k d(t)`` (float64, this order) lies in ``[0, W-1]`` on
    some image row ``y >= top`` with ``d(t) >= lattice_min_spacing``, and its confidence (as in
    :func:`lattice_rows`) is above 0 and ``>= lattice_min_confidence``.
    """
    h, w = mask.shape
    kv = params.lattice_visible_half(w)
    ks = range(-kv, kv + 1)
    below = np.arange(h) >= top
    coef = np.array(fit.coef, np.float64)
    half = params.lattice_half
    gaps = params.reads_dominance()
    cells, _ = row_cells(prefix_sums(mask & below[:, None]), coef, params, [*ks, *gap_offsets(params)] if gaps else ks,
                         fit.roll)
    cnt = cells[:2 * kv + 1]
    dominance = row_dominance(cnt[kv - half:kv + half + 1], cells[2 * kv + 1:]) if gaps else float("nan")
    cc, dd = centre_spacing(np.arange(h, dtype=np.float64) - np.float64(h - 1), coef)
    # a row counts as shown only where the rows are resolvable: near the VP they all converge inside the image
    defined = below & (dd >= np.float64(params.lattice_min_spacing))
    span = np.float64(max(fit.span, 1))
    g = np.float64(fit.roll)
    out = []
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for i, k in enumerate(ks):
            if fit.roll:  # 11.3.2: the row's own spacing, and no row beyond the pole 1 + g k = 0
                centre, local, u = projective_rows(cc, dd, k, g)
                defined = below & (u > 0) & (local >= np.float64(params.lattice_min_spacing))
            else:
                centre = cc + np.float64(k) * dd
            inside = bool((defined & (centre >= 0) & (centre <= w - 1)).any())
            support = int((cnt[i] > 0).sum())
            conf = float(np.float64(support) / span)
            if fit.found and inside and support > 0 and conf >= params.lattice_min_confidence:
                out.append(LatticeRow(k, *row_polynomial(fit.coef, k, h, fit.roll), conf))
    return out, dominance


def improved_status(rows: list[Row], contrast: float, image_confidence: float, params: Params,
                    dominance: float) -> str:
    """Section 11.4: ``invalid`` if a row is invalid, else ``weak`` unless the comb's contrast is
    ``>= lattice_min_contrast``, the image confidence ``>= lattice_min_image_confidence`` and the
    rows' dominance (:func:`row_dominance`) ``>= lattice_min_dominance`` (float64 comparisons),
    else ``ok``."""
    if not all(r.valid for r in rows):
        return "invalid"
    strong = (contrast >= params.lattice_min_contrast and image_confidence >= params.lattice_min_image_confidence
              and (not params.reads_dominance() or dominance >= params.lattice_min_dominance))
    return "ok" if strong else "weak"


class ImprovedRows(NamedTuple):
    """:func:`improved_rows`' result: the ``2K+1`` rows of :func:`lattice_rows`, the image
    confidence (mean of theirs), the fit, every visible row and the rows' dominance
    (:func:`visible_rows`)."""

    rows: list[Row]
    image_confidence: float
    fit: LatticeFit
    visible: list[LatticeRow]
    dominance: float


def improved_rows(rgb: np.ndarray, sky: int, vp: tuple[float, float] | None, params: Params,
                  prior: LatticePrior | None = None, grid_sky: int | None = None,
                  evidence: np.ndarray | None = None) -> ImprovedRows:
    """Section 11 on one working image.

    ``sky`` is section 1's row (0 where :meth:`Params.runs_sky` is false: not used); the
    lattice starts at :func:`horizon_row` and the VP grid at :func:`vp_origin` of ``grid_sky``
    (``None``: ``sky``; the lattice tracker passes ``sky = 0`` and its full searches' row).
    ``vp``: section 6's, for ``lattice_vp="section6"``. ``prior``: section 11.7's.
    ``evidence``: the caller's row mask, ``(H, W)`` bool at the working size, in place of the
    green mask (11.1.1; :func:`row_evidence`).
    """
    top = horizon_row(sky, params)
    mask = row_evidence(rgb, top, params, evidence)
    origin = vp_origin(sky if grid_sky is None else grid_sky, rgb.shape[0], params)
    fit = fit_lattice(mask, top, vp, params, prior, origin)
    rows = lattice_rows(fit, rgb.shape[0], params)
    conf = sum(r.confidence for r in rows) / len(rows)  # in row order, as the tensor path
    return ImprovedRows(rows, conf, fit, *visible_rows(mask, top, fit, params))


def improved_result(imp: ImprovedRows, width: int, height: int, top: int, params: Params,
                    name: str | None = None) -> ImageResult:
    """Section 11.4's record of one image from :func:`improved_rows` (the detector's and the
    lattice tracker's): status by :func:`improved_status`, sections 2-6's fields null."""
    return ImageResult(width=width, height=height,
                       status=improved_status(imp.rows, imp.fit.contrast, imp.image_confidence, params, imp.dominance),
                       sky=top, veg_color=None, k=None, bushy=None,
                       n_rows=len(imp.rows),  # the rows asked: 2K + 1
                       hough=None, outliers=None, vp=None, rows=imp.rows, name=name,
                       image_confidence=imp.image_confidence, lattice_rows=imp.visible)
