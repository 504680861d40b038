"""CRDLD score: a CRDA-style measure for forward-camera crop rows (ALGORITHM.md 10.1, a torchrow
extension). NumPy and OpenCV only; independent of the detector.

The Crop Row Detection Lincoln Dataset (CRDLD) labels each crop row as a white polyline on a
black mask. The score compares detected rows with the labelled lines image row by image row:

* **Ground truth** (:func:`truth_from_mask`): the mask is resized to the image size and
  thresholded (``> 127``); on every image row the centres of the white runs are linked
  bottom-up into one line per labelled row (:data:`LINK_PX`, :data:`MAX_GAP`); lines of fewer
  than :data:`MIN_ROWS` rows are dropped. The lines merge near the vanishing point, so only
  image rows below the lowest row where two adjacent lines come within :data:`CUT_PX` (or
  meet in one run) are kept.
* **Score** (:func:`score_image`): the central labelled line (the one nearest the image
  centre ``W/2`` at its lowest kept row) and its left and right neighbours are scored on
  every kept row ``y``: ``s = max(0, 1 - ((x_det - x_gt) / (sigma*d))**2)`` with ``d`` the
  distance to the adjacent labelled line(s) on that row (the mean of both sides where both
  exist; a row where the line has no labelled neighbour is not scored) and ``x_det`` the
  valid detected row nearest ``x_gt`` on that row. The image score is the mean of ``s`` over
  the scored (line, row) pairs; 0 for an ``error`` status or without a valid detected row;
  NaN when the mask gives no scored pair (fewer than two separated lines).
* **Central error** (:func:`central_mae`): mean ``|x_det - x_gt|`` (px) of the central line
  over the rows ``y >= H/2``.

Conventions: ``x`` is the 0-based column, ``y`` the 0-based image row, both in pixels of the
input image (the ground truth's size). Detected rows ``x = e*y**3 + c*y**2 + a*y + b`` are in
working-image pixels (``width`` x ``height`` of the record) and are scaled to the input image
by ``W/width`` in x and ``H/height`` in y.
"""

from __future__ import annotations

import bisect
import functools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

__all__ = ["CUT_PX", "LINK_PX", "MAX_GAP", "MIN_ROWS", "SIGMAS", "CRDLDTruth", "CRDLDScore",
           "label_mask", "truth_from_mask", "extract_lines", "detected_x", "score_image", "central_mae", "score",
           "LOW_SCORE", "CRDLDSummary", "summarize", "format_table", "match_records"]

#: Adjacent labelled lines closer than this (px) on a row: that row and all above are ignored.
CUT_PX = 12.0
#: Linking slack (px): a run joins a line when its centre lies within half the two runs' widths
#: plus this of the line's predicted x.
LINK_PX = 3.0
#: Image rows a line may miss (JPEG speckle, thin diagonal strokes) before it ends; the gap is
#: filled by linear interpolation.
MAX_GAP = 8
#: Lines with fewer kept rows than this are dropped (specks, stubs cut off by the merge rule).
MIN_ROWS = 10
#: The two tolerances reported, as fractions of the row spacing.
SIGMAS = (0.1, 0.3)

_NO_ROWS = ("error", "no_vp", "no_vegetation")


@dataclass(frozen=True, eq=False)
class CRDLDTruth:
    """Ground truth of one CRDLD image, from its label mask.

    Attributes
    ----------
    lines : tuple of numpy.ndarray, each shape (n_k, 2), float64
        The labelled lines left to right, each as ``(y, x)`` pairs (px) for its kept image rows,
        ``y`` ascending (gaps filled).
    width, height : int
        Image size (px) the lines are in.
    cut : int
        Rows ``y <= cut`` are ignored (adjacent lines within :data:`CUT_PX` there); -1 when no
        lines come that close.
    x : numpy.ndarray, shape (len(lines), height), float64
        ``x[k, y]``: line ``k`` at image row ``y``; NaN where it has no kept row.
    spacing : numpy.ndarray, shape (len(lines), height), float64
        ``d`` of each line and row: distance to the adjacent line(s) on that row (mean of both
        sides where both exist); NaN where the line or both neighbours are absent.
    central : int
        Index of the central line in ``lines``; -1 without lines.
    scored : tuple of int
        Indices of the scored lines: the central one and its neighbours.
    """

    lines: tuple[np.ndarray, ...]
    width: int
    height: int
    cut: int
    x: np.ndarray
    spacing: np.ndarray
    central: int
    scored: tuple[int, ...]

    def __repr__(self) -> str:
        return (f"CRDLDTruth({len(self.lines)} lines, {self.width}x{self.height}, cut={self.cut}, "
                f"central={self.central})")

    @property
    def n_pairs(self) -> int:
        """Number of scored (line, row) pairs; 0 means the image cannot be scored."""
        idx = list(self.scored)
        return int(np.isfinite(self.spacing[idx]).sum()) if idx else 0


@dataclass(frozen=True)
class CRDLDScore:
    """Scores of one image (:func:`score`).

    Attributes
    ----------
    sigma01, sigma03 : float
        :func:`score_image` at sigma 0.1 and 0.3 (NaN when the mask gives no scored pair).
    central_mae : float
        :func:`central_mae` (px); NaN where undefined.
    """

    sigma01: float
    sigma03: float
    central_mae: float


def _runs(binary: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """White runs of every row of a ``(H, W)`` bool image: ``(row, centre, width)`` arrays, in
    row-major order, plus the index where each row's runs start (``(H + 1,)``)."""
    h, w = binary.shape
    padded = np.zeros((h, w + 2), dtype=np.int8)
    padded[:, 1:-1] = binary
    step = np.diff(padded, axis=1)
    rs, starts = np.nonzero(step == 1)
    _, ends = np.nonzero(step == -1)  # row-major like the starts, so they pair up
    centre = (starts + ends - 1) * 0.5
    first = np.searchsorted(rs, np.arange(h + 1))
    return rs, centre, (ends - starts).astype(np.float64), first


def _link(binary: np.ndarray) -> tuple[list[dict[int, float]], list[tuple[int, int, int]]]:
    """Link run centres bottom-up into tracks ``{y: x}``; also the meets ``(y, track, track)``
    where two tracks reached for the same run."""
    _, centre, width, first = _runs(binary)
    tracks: list[dict[int, float]] = []
    recent: list[list[tuple[int, float]]] = []  # per track: its last few (y, x), newest last
    last_w: list[float] = []  # per track: width of its last run
    alive: list[int] = []
    meets: list[tuple[int, int, int]] = []
    for y in range(binary.shape[0] - 1, -1, -1):
        lo, hi = int(first[y]), int(first[y + 1])
        alive = [t for t in alive if recent[t][-1][0] - y <= MAX_GAP + 1]
        if lo == hi:
            continue
        cs, ws = centre[lo:hi].tolist(), width[lo:hi].tolist()  # runs left to right
        widest = max(ws)
        pairs = []
        for t in alive:
            pts = recent[t]
            ty, tx = pts[-1]
            # the line's slope over its last few rows predicts where it continues
            px = tx if len(pts) < 2 else tx + (tx - pts[0][1]) / (pts[0][0] - ty) * (ty - y)
            reach = 0.5 * (widest + last_w[t]) + LINK_PX
            for k in range(bisect.bisect_left(cs, px - reach), bisect.bisect_right(cs, px + reach)):
                dist = abs(cs[k] - px)
                if dist <= 0.5 * (ws[k] + last_w[t]) + LINK_PX:
                    pairs.append((dist, t, k))
        pairs.sort()
        owner: dict[int, int] = {}
        done: set[int] = set()
        met: set[int] = set()
        for _, t, k in pairs:
            if t in done:
                continue
            if k in owner:
                meets.append((y, owner[k], t))
                met.add(t)
                done.add(t)
                continue
            owner[k] = t
            done.add(t)
            tracks[t][y] = cs[k]
            recent[t] = (recent[t] + [(y, cs[k])])[-5:]
            last_w[t] = ws[k]
        # a track that met another one ends there: above, the merged run belongs to the owner
        if met:
            alive = [t for t in alive if t not in met]
        for k in range(len(cs)):
            if k not in owner:
                tracks.append({y: cs[k]})
                recent.append([(y, cs[k])])
                last_w.append(ws[k])
                alive.append(len(tracks) - 1)
    return tracks, meets


def _dense(track: dict[int, float], height: int) -> np.ndarray:
    """A track as ``(height,)`` x per row, gaps linearly filled, NaN outside it."""
    ys = np.fromiter(sorted(track), dtype=np.int64)
    xs = np.array([track[int(y)] for y in ys], dtype=np.float64)
    out = np.full(height, np.nan)
    span = np.arange(ys[0], ys[-1] + 1)
    out[span] = np.interp(span, ys, xs)
    return out


def _order(x: np.ndarray) -> list[int]:
    """Indices of the lines ``x`` (``(L, H)``) left to right: by their mean difference on shared
    rows, else by where the lower one ends against where the upper one starts."""
    def cmp(i: int, j: int) -> int:
        both = np.isfinite(x[i]) & np.isfinite(x[j])
        if both.any():
            diff = float(np.mean(x[i, both] - x[j, both]))
        else:
            yi, yj = np.flatnonzero(np.isfinite(x[i])), np.flatnonzero(np.isfinite(x[j]))
            diff = float(x[i, yi[0]] - x[j, yj[-1]]) if yi[0] > yj[-1] else float(x[i, yi[-1]] - x[j, yj[0]])
        return -1 if diff < 0 else (1 if diff > 0 else 0)

    return sorted(range(x.shape[0]), key=functools.cmp_to_key(cmp))


def _neighbour_gaps(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of every line (``(L, H)``, left to right) to the nearest present line on its
    left and on its right on each row; NaN where there is none."""
    n, h = x.shape
    left, right = np.full((n, h), np.nan), np.full((n, h), np.nan)
    seen = np.full(h, np.nan)
    for k in range(n):
        left[k] = x[k] - seen
        seen = np.where(np.isfinite(x[k]), x[k], seen)
    seen = np.full(h, np.nan)
    for k in range(n - 1, -1, -1):
        right[k] = seen - x[k]
        seen = np.where(np.isfinite(x[k]), x[k], seen)
    return left, right


def label_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """The labelled rows' pixels, ``(height, width)`` bool: the label mask (``(h, w)`` or ``(h, w,
    3)`` uint8, any size; a colour mask's brightest channel) resized to the image (bilinear) and
    thresholded ``> 127`` (ALGORITHM.md 10.1).

    Raises
    ------
    ValueError
        If the mask is not a 2-D (or 3-channel) array or the size is not positive.
    """
    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[2] in (3, 4):
        m = m[..., :3].max(axis=2)  # white on black: any channel tells
    if m.ndim != 2 or m.size == 0:
        raise ValueError(f"label mask must be (h, w) or (h, w, 3), got shape {m.shape}")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if m.shape != (height, width):
        m = cv2.resize(m.astype(np.uint8), (int(width), int(height)), interpolation=cv2.INTER_LINEAR)
    return m > 127


def truth_from_mask(mask: np.ndarray, width: int, height: int) -> CRDLDTruth:
    """Ground truth of one image from its label mask.

    Parameters
    ----------
    mask : numpy.ndarray, shape (h, w) or (h, w, 3), uint8
        Label mask at any size: white polylines (one per crop row) on black.
    width, height : int
        Size (px) of the image the mask labels; the mask is resized to it (bilinear) first.

    Returns
    -------
    CRDLDTruth
        Lines, cut row, per-row spacing and the scored lines (see the module docstring).

    Raises
    ------
    ValueError
        If the mask is not a 2-D (or 3-channel) array or the size is not positive.
    """
    tracks, meets = _link(label_mask(mask, width, height))
    keep = [t for t, tr in enumerate(tracks) if len(tr) >= MIN_ROWS]
    x = np.stack([_dense(tracks[t], height) for t in keep]) if keep else np.empty((0, height))
    order = _order(x)
    x = x[order]
    kept = {keep[i]: j for j, i in enumerate(order)}
    left, _ = _neighbour_gaps(x)
    close = np.flatnonzero(np.any(left < CUT_PX, axis=0))
    found = [int(close[-1])] if close.size else []
    found += [y for y, a, b in meets if a in kept and b in kept]
    cut = max(found, default=-1)
    x[:, : cut + 1] = np.nan
    x = x[np.isfinite(x).sum(axis=1) >= MIN_ROWS]
    left, right = _neighbour_gaps(x)
    with np.errstate(invalid="ignore"):
        spacing = np.where(np.isnan(left), right, np.where(np.isnan(right), left, 0.5 * (left + right)))
    lines = []
    for row in x:
        ys = np.flatnonzero(np.isfinite(row))
        lines.append(np.column_stack([ys.astype(np.float64), row[ys]]))
    central = -1
    scored: tuple[int, ...] = ()
    if lines:
        bottom = np.array([ln[-1, 1] for ln in lines])
        central = int(np.argmin(np.abs(bottom - width / 2)))
        scored = tuple(k for k in (central - 1, central, central + 1) if 0 <= k < len(lines))
    for a in (x, spacing):
        a.flags.writeable = False
    return CRDLDTruth(tuple(lines), int(width), int(height), cut, x, spacing, central, scored)


def extract_lines(mask: np.ndarray, width: int, height: int) -> list[np.ndarray]:
    """The labelled lines of a mask, left to right, each ``(n, 2)`` float64 ``(y, x)`` (px at
    ``width`` x ``height``), rows at and above the merge cut removed (:func:`truth_from_mask`)."""
    return list(truth_from_mask(mask, width, height).lines)


def _coefficients(row: Any) -> tuple[float, float, float, float, bool]:
    """``(a, b, c, e, valid)`` of a Row-like object or a record's row dict (null -> NaN)."""
    def num(v: Any) -> float:
        return float("nan") if v is None else float(v)

    if isinstance(row, Mapping):
        return (num(row.get("a")), num(row.get("b")), num(row.get("c", 0.0)), num(row.get("e", 0.0)),
                bool(row.get("valid", False)))
    return (num(row.a), num(row.b), num(getattr(row, "c", 0.0)), num(getattr(row, "e", 0.0)), bool(row.valid))


def detected_x(rows: Iterable[Any], truth: CRDLDTruth,
               working_size: tuple[int, int] | None = None) -> np.ndarray:
    """x (input-image px) of every valid detected row on every image row of the truth.

    Parameters
    ----------
    rows : iterable of Row-like or dict
        ``a``, ``b``, ``c``, ``e`` (``x = e*y**3 + c*y**2 + a*y + b``, working px) and ``valid``;
        a record's ``rows`` dicts work as they are.
    truth : CRDLDTruth
    working_size : (int, int), optional
        ``(width, height)`` of the image the rows were fitted in; default the truth's size.

    Returns
    -------
    numpy.ndarray, shape (n_valid, truth.height), float64
        Rows with a non-finite coefficient are left out.
    """
    ww, wh = working_size if working_size is not None else (truth.width, truth.height)
    if ww < 1 or wh < 1:
        raise ValueError(f"working size must be positive, got {ww}x{wh}")
    coef = [r[:4] for r in map(_coefficients, rows) if r[4] and all(math.isfinite(v) for v in r[:4])]
    if not coef:
        return np.empty((0, truth.height))
    a, b, c, e = (np.array(v, dtype=np.float64)[:, None] for v in zip(*coef))
    y = np.arange(truth.height, dtype=np.float64)[None, :] * (wh / truth.height)
    return ((e * y + c) * y + a) * y * (truth.width / ww) + b * (truth.width / ww)


def _errors(rows: Iterable[Any], status: str, truth: CRDLDTruth,
            working_size: tuple[int, int] | None) -> np.ndarray | None:
    """``|x_det - x_gt|`` (px) of the nearest valid detected row, ``(len(lines), height)``; None
    when nothing was detected."""
    if status in _NO_ROWS:
        return None
    det = detected_x(rows, truth, working_size)
    if det.shape[0] == 0 or truth.x.shape[0] == 0:
        return None
    return np.min(np.abs(det[None, :, :] - truth.x[:, None, :]), axis=1)


def _crda(err: np.ndarray | None, truth: CRDLDTruth, sigma: float) -> float:
    idx = list(truth.scored)
    d = truth.spacing[idx]
    pairs = np.isfinite(d)
    if not pairs.any():
        return float("nan")
    if err is None:
        return 0.0
    t = err[idx][pairs] / (sigma * d[pairs])
    return float(np.maximum(1.0 - t * t, 0.0).mean())


def _mae(err: np.ndarray | None, truth: CRDLDTruth) -> float:
    if err is None or truth.central < 0:
        return float("nan")
    lower = err[truth.central, int(math.ceil(truth.height / 2)):]
    lower = lower[np.isfinite(lower)]
    return float(lower.mean()) if lower.size else float("nan")


def score_image(rows: Iterable[Any], status: str, truth: CRDLDTruth, sigma: float = 0.1,
                working_size: tuple[int, int] | None = None) -> float:
    """CRDLD score of one image.

    Parameters
    ----------
    rows : iterable of Row-like or dict
        Detected rows (see :func:`detected_x`).
    status : str
        The record's status; ``error`` (and the statuses without rows) score 0.
    truth : CRDLDTruth
    sigma : float
        Tolerance as a fraction of the row spacing ``d``.
    working_size : (int, int), optional
        ``(width, height)`` the rows are in; default the truth's size.

    Returns
    -------
    float
        Mean of ``s`` over the scored (line, row) pairs, in ``[0, 1]``; 0.0 without a valid
        row; NaN when the mask gives no scored pair.
    """
    if not sigma > 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    return _crda(_errors(rows, status, truth, working_size), truth, sigma)


def central_mae(rows: Iterable[Any], status: str, truth: CRDLDTruth,
                working_size: tuple[int, int] | None = None) -> float:
    """Mean absolute error (px) of the central labelled line over image rows ``y >= H/2``:
    ``|x_det - x_gt|`` with the nearest valid detected row. NaN without a valid detected row
    or without central-line rows there."""
    return _mae(_errors(rows, status, truth, working_size), truth)


def score(result: Any, truth: CRDLDTruth) -> CRDLDScore:
    """Both sigmas and the central error of a detector result or record, in one pass.

    Parameters
    ----------
    result : ImageResult or dict
        Detector output (``rows``, ``status``, ``width``, ``height``: the working size) or its
        JSON record.
    truth : CRDLDTruth
    """
    if isinstance(result, Mapping):
        rows, status = result.get("rows") or [], str(result.get("status"))
        size = (int(result.get("width") or 0), int(result.get("height") or 0))
    else:
        rows, status, size = result.rows, str(result.status), (int(result.width), int(result.height))
    err = None if min(size) < 1 else _errors(rows, status, truth, size)  # an error record may have no size
    return CRDLDScore(_crda(err, truth, SIGMAS[0]), _crda(err, truth, SIGMAS[1]), _mae(err, truth))


#: Among ``ok`` images, the summary counts those scoring below this at sigma 0.1 (a wrong pick).
LOW_SCORE = 0.2


@dataclass(frozen=True)
class CRDLDSummary:
    """Summary of a CRDLD run (:func:`summarize`).

    Attributes
    ----------
    n : int
        Images.
    n_scored : int
        Images whose mask gives scored pairs; the means and medians are over these.
    mean01, median01, mean03, median03 : float
        Score at sigma 0.1 and 0.3 (NaN without a scored image).
    mae_mean, mae_median : float
        Central-line MAE (px) over the ``n_mae`` images where it is defined.
    n_mae : int
    statuses : dict of str to int
        Records per status (``missing``: an image without a record).
    ok_fraction : float
        Fraction of the images whose status is ``ok``.
    ok_low_fraction : float
        Among the scored ``ok`` images, the fraction scoring below :data:`LOW_SCORE` at sigma 0.1.
    """

    n: int
    n_scored: int
    mean01: float
    median01: float
    mean03: float
    median03: float
    mae_mean: float
    mae_median: float
    n_mae: int
    statuses: dict[str, int]
    ok_fraction: float
    ok_low_fraction: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN -> None)."""
        def num(v: Any) -> Any:
            return None if isinstance(v, float) and not math.isfinite(v) else v

        return {f: num(getattr(self, f)) for f in self.__dataclass_fields__}

    def format(self, title: str = "CRDLD") -> str:
        """A few lines for a terminal: the scores, the central error and the statuses."""
        def pair(a: float, b: float, unit: str = "", digits: int = 3) -> str:
            return "-" if not math.isfinite(a) else f"mean {a:.{digits}f}{unit}  median {b:.{digits}f}{unit}"

        statuses = ", ".join(f"{k} {v}" for k, v in self.statuses.items()) or "none"
        low = "-" if not math.isfinite(self.ok_low_fraction) else f"{self.ok_low_fraction:.1%}"
        ok = "-" if not math.isfinite(self.ok_fraction) else f"{self.ok_fraction:.1%}"
        return "\n".join([
            f"{title}: {self.n} images, {self.n_scored} with a scorable label",
            f"score sigma 0.1: {pair(self.mean01, self.median01)}",
            f"score sigma 0.3: {pair(self.mean03, self.median03)}",
            f"central row MAE, lower half: {pair(self.mae_mean, self.mae_median, ' px', 1)}  (n={self.n_mae})",
            f"statuses: {statuses}; ok: {ok} of the images; ok images scoring below {LOW_SCORE}: {low}"])


def summarize(statuses: Iterable[str], scores: Iterable[CRDLDScore]) -> CRDLDSummary:
    """Summary of per-image statuses and scores (same order).

    Raises
    ------
    ValueError
        If the two have different lengths.
    """
    st, sc = list(statuses), list(scores)
    if len(st) != len(sc):
        raise ValueError(f"statuses and scores differ in length: {len(st)} and {len(sc)}")
    s01 = np.array([s.sigma01 for s in sc], dtype=np.float64)
    s03 = np.array([s.sigma03 for s in sc], dtype=np.float64)
    mae = np.array([s.central_mae for s in sc], dtype=np.float64)
    scored, has_mae = np.isfinite(s01), np.isfinite(mae)
    ok = np.array([x == "ok" for x in st], dtype=bool)

    def stat(f: Any, a: np.ndarray) -> float:
        return float(f(a)) if a.size else float("nan")

    counts: dict[str, int] = {}
    for x in st:
        counts[x] = counts.get(x, 0) + 1
    ok_scored = ok & scored
    return CRDLDSummary(
        n=len(st), n_scored=int(scored.sum()),
        mean01=stat(np.mean, s01[scored]), median01=stat(np.median, s01[scored]),
        mean03=stat(np.mean, s03[scored]), median03=stat(np.median, s03[scored]),
        mae_mean=stat(np.mean, mae[has_mae]), mae_median=stat(np.median, mae[has_mae]), n_mae=int(has_mae.sum()),
        statuses=dict(sorted(counts.items())), ok_fraction=stat(np.mean, ok.astype(np.float64)),
        ok_low_fraction=stat(np.mean, (s01[ok_scored] < LOW_SCORE).astype(np.float64)))


def format_table(rows: Iterable[tuple[str, CRDLDSummary]]) -> str:
    """Markdown table, one line per ``(label, summary)``."""
    def pair(a: float, b: float, digits: int = 3) -> str:
        return "-" if not math.isfinite(a) else f"{a:.{digits}f} / {b:.{digits}f}"

    out = ["| run | images (scored) | sigma 0.1 mean / median | sigma 0.3 mean / median | "
           "central MAE px mean / median | ok | ok below 0.2 | statuses |",
           "|---|---|---|---|---|---|---|---|"]
    for label, s in rows:
        statuses = ", ".join(f"{k} {v}" for k, v in s.statuses.items())
        low = "-" if not math.isfinite(s.ok_low_fraction) else f"{s.ok_low_fraction:.1%}"
        ok = "-" if not math.isfinite(s.ok_fraction) else f"{s.ok_fraction:.1%}"
        out.append(f"| {label} | {s.n} ({s.n_scored}) | {pair(s.mean01, s.median01)} | "
                   f"{pair(s.mean03, s.median03)} | {pair(s.mae_mean, s.mae_median, 1)} | {ok} | {low} | {statuses} |")
    return "\n".join(out)


def match_records(names: Iterable[str], records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any] | None]:
    """The record of each image name (``12.jpg``): the record named so, else the one whose name
    ends in ``/12.jpg`` (records of ``torchrow detect`` over several folders); None when absent.

    Raises
    ------
    ValueError
        If two records end in the same file name and neither is named exactly so.
    """
    exact: dict[str, Mapping[str, Any]] = {}
    by_base: dict[str, list[Mapping[str, Any]]] = {}
    for rec in records:
        name = str(rec.get("name"))
        exact[name] = rec
        by_base.setdefault(name.rsplit("/", 1)[-1], []).append(rec)
    out: list[Mapping[str, Any] | None] = []
    for n in names:
        if n in exact:
            out.append(exact[n])
            continue
        cands = by_base.get(n, [])
        if len(cands) > 1:
            raise ValueError(f"{len(cands)} records end in {n!r} (e.g. {cands[0].get('name')!r}); "
                             "score the records of one folder at a time")
        out.append(cands[0] if cands else None)
    return out
