"""Crop Row Detection Accuracy (CRDA), ALGORITHM.md section 10. NumPy only.

Two scores:

* :func:`crda` / :func:`crda_official`: CRBD's official measure (the authors' ``CRDA.m``),
  m = 3 adjacent rows, sigma = 0.1, groups of m taken out of 9 adjacent ground-truth rows.
  Reproduces the published TMGEM figures on CRBD (mean 0.746 / median 0.767 at sigma 0.1,
  0.935 / 0.963 at sigma 0.3).
* :func:`crda_thesis`: the thesis' variant (sigma = 0.3, every valid row matched on each
  image row to the nearest of 13 ground-truth rows, normalised by the number of rows asked).

Conventions: ``u``/``x`` is the 0-based column of the working image (px), ``v``/``y`` the
0-based image row; a detected row is ``x = e*y**3 + c*y**2 + a*y + b`` (``c`` = ``e`` = 0: a line). Ground truth gives, for image
rows ``v0 .. h-1`` (``v0 = h - len(c)``), the offset ``c_v`` of the central crop row from the
image centre ``W/2`` and the spacing ``d_v`` between rows, so ground-truth row ``k`` lies
at ``u*_k(v) = c_v + k*d_v + W/2``.

The per-row matching score is ``s(u, u*, d) = max(1 - ((u* - u) / (sigma*d))**2, 0)``: 1 for
an exact hit, 0 at a horizontal distance of ``sigma*d`` or more; NaN (empty slot) scores 0.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any, Protocol

import numpy as np

__all__ = ["match_score", "crda", "rows_to_U", "crda_official", "crda_thesis", "summarize"]


class _RowLike(Protocol):
    a: float
    b: float
    valid: bool
    c: float
    e: float


def match_score(u_gt: np.ndarray, u: np.ndarray, d: np.ndarray, sigma: float) -> np.ndarray:
    """Elementwise ``max(1 - ((u_gt - u) / (sigma*d))**2, 0)``, NaN -> 0.

    Parameters
    ----------
    u_gt, u, d : array_like, broadcastable, float64
        Ground-truth x (px), detected x (px, NaN = nothing detected), row spacing (px).
    sigma : float
        Tolerance as a fraction of ``d``.

    Returns
    -------
    numpy.ndarray
        Scores in ``[0, 1]``, the broadcast shape.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (np.asarray(u_gt, np.float64) - np.asarray(u, np.float64)) / (sigma * np.asarray(d, np.float64))
        s = 1.0 - t * t
    return np.where(s > 0.0, s, 0.0)  # NaN compares False -> 0


def _gt_arrays(c: Any, d: Any) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(c, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    if c.ndim != 1 or d.shape != c.shape:
        raise ValueError(f"c and d must be 1-D of equal length, got shapes {c.shape} and {d.shape}")
    return c, d


def crda(U: Any, c: Any, d: Any, m: int = 3, sigma: float = 0.1, adjacent: int = 9,
         width: float = 320) -> float:
    """Official CRDA of one image (CRBD's ``CRDA.m``, ALGORITHM.md section 10).

    For each shift ``s`` in ``-(adjacent-m)//2 .. (adjacent-m)//2`` (-3..3 by default) the
    score is the mean, over image rows ``v = v0 .. h-1`` and the m slots ``k = 0 .. m-1``,
    of ``match_score(u*, U[v, k], d_v)`` with
    ``u* = c_v + (s + k - (m-1)/2) * d_v + width/2``, i.e. slot 0 is compared with the
    ground-truth row left of the central one. CRDA is the largest score over the shifts
    (and at least 0).

    Parameters
    ----------
    U : array_like, shape (h, m), float64
        Detected x (px, 0-based column) of m adjacent crop rows, left to right, for every
        image row ``0 .. h-1``. NaN marks an empty slot (scores 0).
    c, d : array_like, shape (h - v0,), float64
        Ground truth for image rows ``v0 .. h-1`` with ``v0 = h - len(c)``: central-row
        offset from ``width/2`` (px) and row spacing (px).
    m : int
        Number of evaluated rows (odd).
    sigma : float
        Tolerance as a fraction of the row spacing.
    adjacent : int
        Number of adjacent ground-truth rows (``adjacent - m + 1`` groups of m).
    width : float
        Image width (px); ground-truth ``c`` is relative to ``width/2``.

    Returns
    -------
    float
        CRDA in ``[0, 1]``; 0.0 when the ground truth is empty.

    Raises
    ------
    ValueError
        On inconsistent shapes, even ``m``, ``adjacent < m`` or ``sigma <= 0``.
    """
    if m < 1 or m % 2 == 0:
        raise ValueError(f"m must be a positive odd number, got {m}")
    if adjacent < m:
        raise ValueError(f"adjacent ({adjacent}) must be at least m ({m})")
    if not sigma > 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    U = np.asarray(U, dtype=np.float64)
    if U.ndim != 2 or U.shape[1] != m:
        raise ValueError(f"U must have shape (h, {m}), got {U.shape}")
    c, d = _gt_arrays(c, d)
    h, n = U.shape[0], c.shape[0]
    if n > h:
        raise ValueError(f"ground truth has {n} rows but U only {h}")
    if n == 0:
        return 0.0
    v0 = h - n
    half = (adjacent - m) // 2
    shifts = np.arange(-half, half + 1, dtype=np.float64)[:, None, None]  # (S, 1, 1)
    k = (np.arange(m) - (m - 1) // 2).astype(np.float64)[None, None, :]  # (1, 1, m)
    cc, dd = c[None, :, None], d[None, :, None]  # (1, n, 1)
    u_gt = cc + (shifts + k) * dd + width / 2  # (S, n, m), same order as CRDA.m
    s = match_score(u_gt, U[None, v0:, :], dd, sigma)
    per_shift = s.sum(axis=(1, 2)) / (m * n)
    return float(max(per_shift.max(), 0.0))


def _finite_valid(rows: Iterable[_RowLike]) -> list[tuple[float, float, float, float]]:
    """``(a, b, c, e)`` of the valid rows with finite coefficients (``c``, ``e`` = 0 when absent)."""
    out = []
    for r in rows:
        c, e = float(getattr(r, "c", 0.0)), float(getattr(r, "e", 0.0))
        if r.valid and all(math.isfinite(v) for v in (r.a, r.b, c, e)):
            out.append((float(r.a), float(r.b), c, e))
    return out


def _x_of(a: float, b: float, c: float, e: float, y: np.ndarray) -> np.ndarray:
    """``x = e*y**3 + c*y**2 + a*y + b``; exactly ``a*y + b`` for a straight row (``c == e == 0``)."""
    if c == 0.0 and e == 0.0:
        return a * y + b
    x = (c * y) * y + a * y + b
    return x if e == 0.0 else x + ((e * y) * y) * y


def rows_to_U(rows: Iterable[_RowLike], height: int, m: int = 3, width: float = 320) -> np.ndarray:
    """Pick the method's m adjacent rows for CRDA and sample them on every image row.

    Valid rows (finite ``a``, ``b``) are sorted by their x at the bottom image row
    ``y = height - 1``. With ``n >= m`` valid rows, the m consecutive ones whose middle row
    is nearest ``width/2`` (at the bottom row) fill the m slots. With ``n < m``, the row
    nearest ``width/2`` goes to the middle slot ``(m-1)/2`` and the others keep their order
    left and right of it; slots left over are NaN (and rows that would fall outside the m
    slots are dropped, possible only for m >= 5). Ties in distance go to the leftmost row.

    Parameters
    ----------
    rows : iterable of Row
        Objects with ``a``, ``b`` (``x = a*y + b``, working-image px) and ``valid``.
    height : int
        Image height h (px).
    m : int
        Number of slots (odd).
    width : float
        Image width (px).

    Returns
    -------
    numpy.ndarray, shape (height, m), float64
        ``U[y, k] = e_k * y**3 + c_k * y**2 + a_k * y + b_k`` for ``y = 0 .. height-1``; NaN columns for empty slots.
    """
    if m < 1 or m % 2 == 0:
        raise ValueError(f"m must be a positive odd number, got {m}")
    U = np.full((int(height), m), np.nan, dtype=np.float64)
    lines = _finite_valid(rows)
    if not lines or height <= 0:
        return U
    n, half = len(lines), (m - 1) // 2
    y = np.arange(int(height), dtype=np.float64)
    yb = np.float64(height - 1)
    bottom = np.array([_x_of(a, b, c, e, yb) for a, b, c, e in lines], dtype=np.float64)
    order = np.argsort(bottom, kind="stable")
    dist = np.abs(bottom[order] - width / 2)
    lo, hi = (half, n - 1 - half) if n >= m else (0, n - 1)
    mid = lo + int(np.argmin(dist[lo:hi + 1]))
    for j in range(n):
        slot = half + j - mid
        if 0 <= slot < m:
            a, b, c, e = lines[order[j]]
            U[:, slot] = _x_of(a, b, c, e, y)
    return U


def _check_sizes(result: Any, gt: Any) -> None:
    if int(result.height) != int(gt.height):
        raise ValueError(f"result is {result.width}x{result.height} but the ground truth is for "
                         f"images of height {gt.height}; run the detector at the ground truth's size")


_NO_ROWS = ("no_vp", "no_vegetation", "error")


def crda_official(result: Any, gt: Any, sigma: float = 0.1, m: int = 3, adjacent: int = 9) -> float:
    """Official CRDA of a detector result (the headline score).

    Parameters
    ----------
    result, gt, sigma, m, adjacent : see :func:`crda`.

    Returns
    -------
    float
        CRDA in ``[0, 1]``: :func:`crda` of :func:`rows_to_U`; 0.0 when the image produced
        no valid row (statuses ``no_vp``, ``no_vegetation``, ``error``, or every row invalid).

    Raises
    ------
    ValueError
        If the result's height differs from the ground truth's.
    """
    if result.status in _NO_ROWS or not _finite_valid(result.rows):
        return 0.0
    _check_sizes(result, gt)
    U = rows_to_U(result.rows, int(result.height), m=m, width=result.width)
    return crda(U, gt.c, gt.d, m=m, sigma=sigma, adjacent=adjacent, width=result.width)


def crda_thesis(result: Any, gt: Any, sigma: float = 0.3, candidates: int = 13,
                nearest: str = "image_row") -> float:
    """The thesis' CRDA variant (how its median 0.816 was computed).

    Each valid row ``x = a*y + b`` is compared, on every image row ``v = v0 .. h-1``, with
    the ``candidates`` ground-truth rows ``u*_j(v) = c_v + j*d_v + W/2``,
    ``j = -(candidates//2) .. candidates//2`` (-6..6). With ``nearest="image_row"`` (the
    default) the row's score is ``mean_v max_j match_score(u*_j(v), x(v), d_v)``: on each
    image row it is matched to the nearest ground-truth row there (all candidates share
    ``d_v``, so nearest = best score). This is what the thesis code computes (it sums
    ``match_score`` over all ground-truth rows, and with sigma < 0.5 at most one of them is
    non-zero) and it reproduces the figures in ``data/README.md`` (mean 0.776 / median 0.824
    on the 40-image thesis sample). ``nearest="row"`` instead keeps one candidate for the
    whole row, ``max_j mean_v match_score``; it never scores higher (0.749 / 0.818 on that
    sample). The sum over valid rows is divided by ``max(result.n_rows, 1)`` (rows asked
    after restarts), so a missing row counts 0; several rows may match the same
    ground-truth row.

    Parameters
    ----------
    result : ImageResult
        Detector output; rows in working-image px, ``result.width`` x ``result.height``.
    gt : GroundTruth
        ``c``, ``d`` (shape ``(height - v0,)``), ``height`` (must equal ``result.height``).
    sigma : float
        Tolerance as a fraction of the row spacing.
    candidates : int
        Number of ground-truth rows (odd), centred on the central row.
    nearest : {"image_row", "row"}
        Where the nearest ground-truth row is chosen (see above).

    Returns
    -------
    float
        Score in ``[0, n_valid / max(n_rows, 1)]`` (at most 1 when the valid rows are among
        the rows asked); 0.0 without valid rows.

    Raises
    ------
    ValueError
        If the result's height differs from the ground truth's, or for an unknown
        ``nearest``.
    """
    if nearest not in ("image_row", "row"):
        raise ValueError(f"nearest must be 'image_row' or 'row', got {nearest!r}")
    lines = _finite_valid(result.rows) if result.status not in _NO_ROWS else []
    if not lines:
        return 0.0
    _check_sizes(result, gt)
    c, d = _gt_arrays(gt.c, gt.d)
    n = c.size
    if n == 0:
        return 0.0
    v = np.arange(int(gt.height) - n, int(gt.height), dtype=np.float64)  # (n,)
    j = np.arange(-(candidates // 2), candidates // 2 + 1, dtype=np.float64)[:, None]  # (J, 1)
    u_gt = c[None, :] + j * d[None, :] + result.width / 2  # (J, n)
    total = 0.0
    for a, b, curv, cubic in lines:  # (c above is the ground truth's column array)
        x = _x_of(a, b, curv, cubic, v)  # (n,)
        s = match_score(u_gt, x[None, :], d[None, :], sigma)  # (J, n)
        if nearest == "image_row":
            total += float(s.max(axis=0).sum() / n)
        else:
            total += float((s.sum(axis=1) / n).max())
    return total / max(int(result.n_rows), 1)


def summarize(scores: Sequence[float] | np.ndarray) -> dict[str, float | int]:
    """``{"mean", "median", "n"}`` of per-image scores (NaN mean/median when empty)."""
    a = np.asarray(list(scores), dtype=np.float64).ravel()
    if a.size == 0:
        return {"mean": float("nan"), "median": float("nan"), "n": 0}
    return {"mean": float(a.mean()), "median": float(np.median(a)), "n": int(a.size)}
