"""Batched constrained RANSAC, one row per held line (ALGORITHM.md section 7).

All ``B x S`` rows are processed at once. Each row's support is the set of vegetation pixels
in a band around its Hough line; at most ``max(ransac_max_points, ransac_subsample)`` of them
are kept (the subsampling rule bounds the count statically), and all ``T`` hypotheses of the
shared table are scored against them in chunks of hypotheses so memory stays bounded.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, fields

import torch

from torchrow.core.params import Params
from torchrow.core.results import REASONS, STATUSES
from torchrow.core.tables import hypothesis_table
from torchrow.functional import _exact
from torchrow.functional.hough import active_width, cacheable, pixel_list, trig

__all__ = ["RowFit", "RowMoments", "Rows", "fit_rows", "score_hypotheses", "exact_counts", "padded_points",
           "validate_rows", "ransac_band", "image_status", "BandPoints", "kept_points", "list_band_points", "band_member",
           "subsample_plan", "max_kept", "principal_direction", "REASON_CODES", "SCORE_BUDGET", "hypotheses"]

#: Reason codes of :attr:`Rows.reason`, indices into :data:`torchrow.core.results.REASONS`.
REASON_CODES = {r: i for i, r in enumerate(REASONS)}

#: Elements per scoring temporary ``(B, S, T_chunk, P)``: 1M (8 MB of float64, a few alive),
#: small enough to stay in cache between the passes over it.
SCORE_BUDGET = 1 << 20
#: The same bound on an accelerator, where one launch should cover many hypotheses:
#: 2**27 elements (1 GiB of float64) scores a batch of 1024 images in ~30 chunks.
DEVICE_SCORE_BUDGET = 1 << 27


class _Fields:
    def astuple(self) -> tuple:
        """The fields in order (what a :func:`~torchrow.functional._flow.branch` passes)."""
        return tuple(getattr(self, f.name) for f in fields(self))  # type: ignore[arg-type]


@dataclass
class RowFit(_Fields):
    """Steps 7.1-7.5 of every row slot, before the validity rules: the batched
    :class:`torchrow.reference.ransac.RowFit`, ``(B, S)`` each.

    ``cx, cy`` float64 weighted inlier centroid (px), ``dx, dy`` float64 unit direction
    (``dy > 0``, or ``dx > 0`` where ``dy = 0``), ``hypothesis`` int64 winning index into the
    shared table (-1: none), ``support`` bool (where the reference returns ``None``: False).
    """

    cx: torch.Tensor
    cy: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    hypothesis: torch.Tensor
    support: torch.Tensor


@dataclass
class RowMoments(_Fields):
    """What an exported graph returns of step 7.5 instead of the direction (ONNX has no
    ``atan2``): weighted centroid ``cx, cy`` and scatter moments ``sxx, syy, sxy`` (float64),
    ``hypothesis`` int64, ``support`` bool, ``(B, S)`` each. :meth:`direction` finishes it."""

    cx: torch.Tensor
    cy: torch.Tensor
    sxx: torch.Tensor
    syy: torch.Tensor
    sxy: torch.Tensor
    hypothesis: torch.Tensor
    support: torch.Tensor

    def direction(self, trig_free: bool = False) -> RowFit:
        """The :class:`RowFit` (principal direction by :func:`principal_direction`)."""
        dx, dy = principal_direction(self.sxx, self.syy, self.sxy, trig_free=trig_free)
        return RowFit(self.cx, self.cy, dx, dy, self.hypothesis, self.support)


@dataclass
class Rows(_Fields):
    """Rows after step 7.6 (the batched list of :class:`torchrow.core.results.Row`),
    ``(B, S)`` each: ``x = a*y + b`` (float64, NaN without support), ``valid``/``reason``
    (int64 code into REASONS), ``hypothesis`` (int64, -1 when none), ``present`` (bool: the
    slot holds a row at all)."""

    a: torch.Tensor
    b: torch.Tensor
    valid: torch.Tensor
    reason: torch.Tensor
    hypothesis: torch.Tensor
    present: torch.Tensor


#: Former name of :class:`Rows`.
RowFits = Rows


@dataclass
class BandPoints(_Fields):
    """Steps 7 and 7.2 of every row slot: the kept pixels ``px, py`` float64 ``(B, S, P)``
    (row-major, padding at the end), ``n_keep`` and ``v_keep`` int64 ``(B, S)`` (kept
    pixels, VP weight) and ``n`` int64 ``(B, S)`` (pixels in the band before subsampling)."""

    px: torch.Tensor
    py: torch.Tensor
    n_keep: torch.Tensor
    v_keep: torch.Tensor
    n: torch.Tensor


def kept_points(member: torch.Tensor, lin: torch.Tensor, width: int, params: Params,
                size: int | None = None) -> BandPoints:
    """Step 7.2 on band members ``member`` bool ``(B, S, K)`` at raster indices ``lin``
    int64 (broadcastable, row-major): the one selection of the eager and exported fits.

    ``size``: the static ``P`` of an exported graph (at least :func:`max_kept`); ``None``
    (eager) takes the smallest ``P`` that holds every row's kept pixels (a host sync).
    """
    n, n_keep, v_keep, key = subsample_plan(member, lin, params)
    big = torch.iinfo(torch.int64).max
    if size is None:
        size = min(member.shape[2], max(params.ransac_max_points, params.ransac_subsample),
                   active_width(n_keep.flatten()))
    sel = torch.topk(key, size, dim=2, largest=False, sorted=True).indices if size > 0 else key[..., :0]
    rank_ok = torch.arange(size, device=member.device) < n_keep.unsqueeze(2)
    chosen = torch.where(rank_ok, torch.gather(lin.expand_as(member), 2, sel), torch.full_like(sel, big))
    chosen = torch.sort(chosen, dim=2).values  # back to row-major order; padding last
    chosen = torch.where(chosen == big, torch.zeros_like(chosen), chosen)
    return BandPoints((chosen % width).to(torch.float64), (chosen // width).to(torch.float64), n_keep, v_keep, n)


def list_band_points(idx: torch.Tensor, count: torch.Tensor, theta: torch.Tensor, rho: torch.Tensor,
                     band: torch.Tensor, width: int, params: Params, cos: torch.Tensor, sin: torch.Tensor,
                     track: tuple[torch.Tensor, torch.Tensor] | None = None, size: int | None = None) -> BandPoints:
    """Steps 7 (band) and 7.2 (subsample) on a compact pixel list: the kept pixels of every
    row, row-major. The one band-point rule of the eager and the exported fits.

    ``idx`` int64 ``(B, K)``: raster indices, each image's ``count`` int64 ``(B,)`` pixels
    first in raster order (:func:`~torchrow.functional.hough.pixel_list`, possibly cut to
    ``K`` columns when no image has more); ``cos``/``sin`` the shared float64 tables;
    ``size`` as :func:`kept_points`. With ``track = (a, b)`` (float64 ``(B, S)``, video mode)
    the band is around the row ``x = a*y + b`` instead of the Hough line (:func:`band_member`).
    """
    live = torch.arange(idx.shape[1], device=idx.device) < count.unsqueeze(1)  # (B, K)
    xs, ys = (idx % width).to(torch.float64), (idx // width).to(torch.float64)
    member = band_member(xs.unsqueeze(1), ys.unsqueeze(1), theta, rho, band, cos, sin, track) & live.unsqueeze(1)
    return kept_points(member, idx.unsqueeze(1), width, params, size)


def _band_points(veg: torch.Tensor, theta: torch.Tensor, rho: torch.Tensor, band: torch.Tensor,
                 params: Params, track: tuple[torch.Tensor, torch.Tensor] | None = None) -> BandPoints:
    """:func:`list_band_points` on the compacted vegetation pixels ``veg`` bool ``(B, H, W)``
    (the list cut to the largest count: a host sync)."""
    idx, count = pixel_list(veg)
    cos, sin = trig(params, veg.device)
    return list_band_points(idx[:, :active_width(count)], count, theta, rho, band, veg.shape[2], params, cos, sin,
                            track)


def band_member(xs: torch.Tensor, ys: torch.Tensor, theta: torch.Tensor, rho: torch.Tensor, band: torch.Tensor,
                cos: torch.Tensor, sin: torch.Tensor, track: tuple[torch.Tensor, torch.Tensor] | None = None
                ) -> torch.Tensor:
    """Step 7's band test of pixels ``xs, ys`` float64 ``(1 or B, 1, K)``: bool ``(B, S, K)``.

    Around the Hough line ``(theta, rho)`` int64 ``(B, S)`` (``cos``/``sin`` the shared
    float64 tables): ``abs((x*cos + y*sin) - rho) <= band/2``; with ``track = (a, b)``
    float64 ``(B, S)`` around the row ``x = a*y + b`` instead:
    ``((x - a*y) - b)**2 <= (band/2)**2 * (1 + a*a)`` (no square root decides). ``band``
    int64 ``(B,)`` px. Shared by the eager and the exportable paths.
    """
    half = (band.to(torch.float64) / 2).view(-1, 1, 1)
    if track is None:
        dist = ((xs * cos[theta].unsqueeze(2) + ys * sin[theta].unsqueeze(2)) - rho.to(torch.float64).unsqueeze(2)).abs()
        return dist <= half
    ta, tb = (t.to(torch.float64).unsqueeze(2) for t in track)  # (B, S, 1)
    r = (xs - ta * ys) - tb
    return r * r <= (half * half) * (1.0 + ta * ta)


def max_kept(params: Params) -> int:
    """Static bound on step 7.2's kept pixels ``n'`` of a row, over every band size ``n``:
    ``n`` itself while ``n + n//2 <= ransac_max_points``, else ``(ransac_subsample*n) //
    (n + n//2)``, which is largest for the smallest such ``n`` (it decreases towards
    ``2*ransac_subsample/3``). With the defaults 467, not 700."""
    direct = 0
    while (direct + 1) + (direct + 1) // 2 <= params.ransac_max_points:
        direct += 1
    sub = max((params.ransac_subsample * n) // (n + n // 2) for n in range(direct + 1, direct + 4))
    return max(direct, sub)


def subsample_plan(member: torch.Tensor, lin: torch.Tensor, params: Params):
    """Step 7.2's counts and selection keys for band members ``member`` bool ``(B, S, K)`` at
    raster indices ``lin`` int64 (broadcastable to it, row-major).

    Returns ``n`` (pixels in the band), ``n_keep``, ``v_keep`` int64 ``(B, S)`` and ``key``
    int64 ``(B, S, K)``: the ``n_keep`` smallest keys are the kept pixels (the raster index,
    or the hash ``(i * subsample_hash) & 0xFFFFFFFF`` when subsampling; non-members get
    ``int64 max``).
    """
    n = _exact.count(member)
    v = n // 2
    sub = n + v > params.ransac_max_points
    n_keep = torch.where(sub, (params.ransac_subsample * n) // torch.clamp(n + v, min=1), n)
    v_keep = torch.where(sub, params.ransac_subsample - n_keep, v)
    key = torch.where(sub.unsqueeze(2), (lin * params.subsample_hash) & 0xFFFFFFFF, lin)
    key = key.masked_fill(~member, torch.iinfo(torch.int64).max)  # a scalar fill: no (B, S, K) constant in a graph
    return n, n_keep, v_keep, key


def _pick(px: torch.Tensor, py: torch.Tensor, i: torch.Tensor, n_keep: torch.Tensor, vp: torch.Tensor):
    """Coordinates of point index ``i`` (B, S, T): pixel ``i`` if ``i < n'``, else the VP."""
    is_vp = i >= n_keep.unsqueeze(2)
    j = torch.where(is_vp, torch.zeros_like(i), i)
    x = torch.where(is_vp, vp[:, 0].view(-1, 1, 1), torch.gather(px, 2, j))
    y = torch.where(is_vp, vp[:, 1].view(-1, 1, 1), torch.gather(py, 2, j))
    return x, y


def _inliers(px, py, vx, vy, x1, y1, x2, y2, thr: float):
    """Inlier test of pixels ``(B, S, T, P)`` and the VP ``(B, S, T)`` for the lines through
    ``(x1, y1), (x2, y2)`` ``(B, S, T)``: ``|(x2-x1)(y-y1) - (y2-y1)(x-x1)| < thr*sqrt(...)``."""
    dx, dy = x2 - x1, y2 - y1
    lim = thr * _exact.sqrt(dx * dx + dy * dy)
    dx4, dy4, x14, y14, lim4 = (t.unsqueeze(3) for t in (dx, dy, x1, y1, lim))
    pix = (dx4 * (py.unsqueeze(2) - y14) - dy4 * (px.unsqueeze(2) - x14)).abs() < lim4
    vpi = (dx * (vy.view(-1, 1, 1) - y1) - dy * (vx.view(-1, 1, 1) - x1)).abs() < lim
    return pix, vpi


def hypotheses(params: Params, device: torch.device) -> torch.Tensor:
    """The RANSAC hypothesis table (:func:`torchrow.core.tables.hypothesis_table`) as float64
    ``(T, 2)`` on ``device``, cached per seed, trial count and device (see :func:`cacheable`)."""
    key = (params.seed, params.ransac_trials, str(device))
    if key not in _TABLES or not cacheable():
        made = torch.tensor(hypothesis_table(params.seed, params.ransac_trials), device=device)
        if not cacheable():
            return made
        _TABLES[key] = made
    return _TABLES[key]


_TABLES: dict = {}

#: Relative margin around the inlier threshold inside which a hypothesis through the VP is
#: re-tested with the spec's exact expression. The fast cross product and the spec's
#: expression each differ from the real value by a few float64 ulps of the terms' magnitude;
#: 1e-12 of that magnitude is thousands of times wider.
MARGIN = 1e-12

#: How many scoring chunks needed the exact fallback (diagnostics for benchmarks).
FALLBACKS = {"chunks": 0, "total": 0}


def _pixel_inliers(pts, px, py, x1, y1, dx, dy, lim, uses_vp, bsz: int, s: int, p: int) -> torch.Tensor:
    """Pixel inliers ``(B, S, T, P)`` of the hypotheses through ``(x1, y1)`` with direction
    ``(dx, dy) = (x2 - x1, y2 - y1)`` and threshold ``lim`` (``(B, S, T)`` each).

    The cross product ``dx*y - dy*x + (dy*x1 - dx*y1)`` is one batched matmul. For two pixel
    picks every term is a small integer, so any evaluation order (fused or not) is exact and
    equals the spec's ``(x2-x1)(y-y1) - (y2-y1)(x-x1)``. For picks involving the float VP the
    matmul may differ from the spec's rounding by a few ulps, so points within
    :data:`MARGIN` of the threshold are re-tested with the spec's expression (rare: the
    fallback runs only for chunks that have such a point; it never changes a result).
    """
    k = dy * x1 - dx * y1
    t = dx.shape[2]
    coef = torch.stack([dx, -dy, k], dim=3).view(bsz * s, t, 3)  # (BS, T, 3)
    cross = torch.bmm(coef, pts).view(bsz, s, t, p).abs_()  # (B, S, T, P)
    scale = dx.abs() * (py.abs().amax(2, keepdim=True) + y1.abs()) + dy.abs() * (
        px.abs().amax(2, keepdim=True) + x1.abs()) + k.abs() + 1.0
    margin = torch.where(uses_vp, MARGIN * scale, torch.zeros_like(scale))
    inl = cross < (lim - margin).unsqueeze(3)
    unsure = (cross < (lim + margin).unsqueeze(3)) != inl
    if bool(unsure.any()):
        FALLBACKS["chunks"] += 1
        FALLBACKS["total"] += int(unsure.sum())
        exact = (dx.unsqueeze(3) * (py.unsqueeze(2) - y1.unsqueeze(3))
                 - dy.unsqueeze(3) * (px.unsqueeze(2) - x1.unsqueeze(3))).abs() < lim.unsqueeze(3)
        inl = torch.where(unsure, exact, inl)
    return inl


def padded_points(px: torch.Tensor, py: torch.Tensor, valid_pt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Kept points ``(B, S, P)`` with NaN in the padding slots (``~valid_pt``): a NaN
    coordinate fails every inlier comparison, so padding never counts."""
    nan = torch.full_like(px, float("nan"))
    return torch.where(valid_pt, px, nan), torch.where(valid_pt, py, nan)


def exact_counts(qx: torch.Tensor, qy: torch.Tensor):
    """The spec's pixel-inlier count of step 7.4 for :func:`score_hypotheses`, evaluated as
    written (no matmul, no fallback): ``qx, qy`` float64 ``(B, S, P)`` NaN-padded points."""
    qx4, qy4 = qx.unsqueeze(2), qy.unsqueeze(2)  # (B, S, 1, P)

    def counts(x1, y1, dx, dy, lim, sure):
        pix = (dx.unsqueeze(3) * (qy4 - y1.unsqueeze(3)) - dy.unsqueeze(3) * (qx4 - x1.unsqueeze(3))).abs() \
            < lim.unsqueeze(3)
        return _exact.count(pix)

    return counts


def score_hypotheses(px: torch.Tensor, py: torch.Tensor, n_keep: torch.Tensor, v_keep: torch.Tensor,
                     vp: torch.Tensor, u: torch.Tensor, chunk: int, thr: float, counts) -> tuple[torch.Tensor,
                                                                                               torch.Tensor]:
    """Steps 7.3-7.4, the one scoring loop of the eager and the exported fits: every
    hypothesis of the shared table ``u`` float64 ``(T, 2)``, in chunks of ``chunk``.

    ``px, py`` float64 ``(B, S, P)`` kept points, ``n_keep``/``v_keep`` int64 ``(B, S)``,
    ``vp`` float64 ``(B, 2)``. ``counts(x1, y1, dx, dy, lim, uses_vp)`` (all ``(B, S, T)``)
    returns the pixel-inlier count int64 ``(B, S, T)`` of each hypothesis (``uses_vp``: a
    real hypothesis through the VP, the only kind whose test rounds); the eager fit passes a
    batched matmul with an exact fallback, the exported graph :func:`exact_counts`.

    Returns ``best_score`` int64 ``(B, S)`` (-1: every hypothesis degenerate) and the first
    best hypothesis ``best_t`` int64 ``(B, S)``; an earlier chunk wins ties.
    """
    dev = px.device
    total = (n_keep + v_keep).to(torch.float64).unsqueeze(2)  # (B, S, 1)
    nk = n_keep.unsqueeze(2)
    vx, vy = vp[:, 0].view(-1, 1, 1), vp[:, 1].view(-1, 1, 1)
    best_score = torch.full(n_keep.shape, -2, dtype=torch.int64, device=dev)
    best_t = torch.zeros(n_keep.shape, dtype=torch.int64, device=dev)
    for t0 in range(0, u.shape[0], chunk):
        uc = u[t0:t0 + chunk]
        i1 = torch.floor(uc[:, 0].view(1, 1, -1) * total).to(torch.int64)
        i2 = torch.floor(uc[:, 1].view(1, 1, -1) * total).to(torch.int64)
        degenerate = (i1 == i2) | ((i1 >= nk) & (i2 >= nk))
        uses_vp = (i1 >= nk) | (i2 >= nk)
        x1, y1 = _pick(px, py, i1, n_keep, vp)
        x2, y2 = _pick(px, py, i2, n_keep, vp)
        dx, dy = x2 - x1, y2 - y1
        lim = thr * _exact.sqrt(dx * dx + dy * dy)  # (B, S, T), as in the spec
        vpi = (dx * (vy - y1) - dy * (vx - x1)).abs() < lim
        score = counts(x1, y1, dx, dy, lim, uses_vp & ~degenerate) + vpi.to(torch.int64) * v_keep.unsqueeze(2)
        score = score.masked_fill(degenerate, -1)
        carg = torch.argmax(score, dim=2)  # first maximum within the chunk
        cmax = score.gather(2, carg.unsqueeze(2)).squeeze(2)
        better = cmax > best_score  # strict: an earlier chunk wins ties
        best_score = torch.where(better, cmax, best_score)
        best_t = torch.where(better, carg + t0, best_t)
    return best_score, best_t


def fit_rows(veg: torch.Tensor, theta: torch.Tensor, rho: torch.Tensor, present: torch.Tensor,
             vp: torch.Tensor, band: torch.Tensor, params: Params,
             track: tuple[torch.Tensor, torch.Tensor] | None = None) -> RowFit:
    """Steps 7.1-7.5 for every row of every image.

    Parameters
    ----------
    veg : bool (B, H, W) vegetation mask (bushy-removed, not the Canny edges).
    theta, rho : int64 (B, S) held Hough lines; ``present`` bool (B, S) marks them.
    vp : float64 (B, 2) vanishing point (rows of images without one must not be present).
    band : int64 (B,) RANSAC band width (px) per image.
    track : optional ``(a, b)`` float64 (B, S): video mode, the band is around the previous
        frame's row ``x = a*y + b`` (see :func:`_band_points`); ``theta``/``rho`` are ignored.

    Returns
    -------
    RowFit

    Memory: ``(B, S, K)`` band temporaries (K = most vegetation pixels in an image) plus
    scoring chunks of :data:`SCORE_BUDGET` float64 elements.
    """
    dev = veg.device
    px, py, n_keep, v_keep, n = _band_points(veg, theta, rho, band, params, track).astuple()
    p = px.shape[2]
    support = present & (n + n // 2 >= params.ransac_min_points)
    if p == 0:  # no band has a pixel (e.g. an all-soil batch): no row has support
        z = torch.zeros(theta.shape, dtype=torch.float64, device=dev)
        return RowFit(z, z, z, z.clone().fill_(1.0), torch.full_like(theta, -1), torch.zeros_like(present))
    u = hypotheses(params, dev)  # (T, 2)
    total = (n_keep + v_keep).to(torch.float64)  # (B, S)
    valid_pt = torch.arange(p, device=dev) < n_keep.unsqueeze(2)  # (B, S, P)
    bsz, s = theta.shape
    qx, qy = padded_points(px, py, valid_pt)
    pts = torch.stack([qy, qx, torch.ones_like(qx)], dim=2).view(bsz * s, 3, p)  # (BS, 3, P)
    budget = SCORE_BUDGET if dev.type == "cpu" else DEVICE_SCORE_BUDGET

    def counts(x1, y1, dx, dy, lim, sure):
        # only real hypotheses through the VP need the margin (degenerate ones are discarded)
        return _pixel_inliers(pts, px, py, x1, y1, dx, dy, lim, sure & present.unsqueeze(2), bsz, s, p).sum(dim=3)

    best_score, best_t = score_hypotheses(px, py, n_keep, v_keep, vp, u, max(1, budget // max(1, bsz * s * p)),
                                          params.ransac_threshold, counts)
    support = support & (best_score >= 0)
    # refit on the inliers of the best hypothesis
    cx, cy, sxx, syy, sxy = best_moments(u, best_t, total, px, py, n_keep, v_keep, valid_pt, vp,
                                         params.ransac_threshold)
    dx, dy = principal_direction(sxx, syy, sxy)
    hyp = torch.where(support, best_t, torch.full_like(best_t, -1))
    return RowFit(cx, cy, dx, dy, hyp, support)


def best_moments(u, best_t, total, px, py, n_keep, v_keep, valid_pt, vp, thr: float):
    """Step 7.5 up to the scatter: weighted centroid ``cx, cy`` and scatter ``sxx, syy, sxy``
    (float64 ``(B, S)``) of the inliers of hypothesis ``best_t`` of the table ``u``.

    ``total`` float64 ``(B, S)`` = ``n' + v'``; ``px, py`` float64 ``(B, S, P)`` kept points,
    ``valid_pt`` bool ``(B, S, P)``; the VP ``(B, 2)`` weighs ``v_keep`` when it is an inlier.
    Shared by the eager and the exportable (:mod:`.static`) paths.
    """
    ub = u[best_t]  # (B, S, 2)
    i1 = torch.floor(ub[..., 0] * total).to(torch.int64).unsqueeze(2)
    i2 = torch.floor(ub[..., 1] * total).to(torch.int64).unsqueeze(2)
    x1, y1 = _pick(px, py, i1, n_keep, vp)
    x2, y2 = _pick(px, py, i2, n_keep, vp)
    pix, vpi = _inliers(px, py, vp[:, 0], vp[:, 1], x1, y1, x2, y2, thr)
    wpix = (pix.squeeze(2) & valid_pt).to(torch.float64)  # (B, S, P)
    wvp = vpi.squeeze(2).to(torch.float64) * v_keep.to(torch.float64)  # (B, S)
    vx, vy = vp[:, 0].view(-1, 1), vp[:, 1].view(-1, 1)
    wsum = wpix.sum(2) + wvp
    safe = torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    cx = ((wpix * px).sum(2) + wvp * vx) / safe
    cy = ((wpix * py).sum(2) + wvp * vy) / safe
    ex, ey = px - cx.unsqueeze(2), py - cy.unsqueeze(2)
    evx, evy = vx - cx, vy - cy
    sxx = (wpix * ex * ex).sum(2) + wvp * evx * evx
    syy = (wpix * ey * ey).sum(2) + wvp * evy * evy
    sxy = (wpix * ex * ey).sum(2) + wvp * evx * evy
    return cx, cy, sxx, syy, sxy


def principal_direction(sxx: torch.Tensor, syy: torch.Tensor, sxy: torch.Tensor, trig_free: bool = False):
    """Unit principal direction ``(dx, dy)`` of the weighted scatter, dy > 0 (dx > 0 when dy = 0).

    The spec's ``phi = atan2(2*sxy, sxx - syy) / 2``, ``(cos phi, sin phi)``. ``trig_free=True``
    (the exportable tracker step: ONNX has no ``Atan2``) takes the same eigenvector in closed
    form, ``(2*sxy, r - d)`` if ``d <= 0`` else ``(r + d, 2*sxy)`` with ``d = sxx - syy``,
    ``r = sqrt(d**2 + (2*sxy)**2)`` (no cancellation in either branch; ``d`` and ``2*sxy``
    first scaled by the larger magnitude), normalised; it agrees to a few ulps
    (``atan2(0, 0) = 0`` gives ``(1, 0)`` in both).
    """
    if trig_free:
        d, e = sxx - syy, 2.0 * sxy
        m = torch.maximum(d.abs(), e.abs())
        m = torch.where(m > 0, m, torch.ones_like(m))
        d, e = d / m, e / m  # scaled to [-1, 1]: squares neither overflow nor underflow
        r = _exact.sqrt(d * d + e * e)
        neg = d <= 0
        vx = torch.where(neg, e, r + d)
        vy = torch.where(neg, r - d, e)
        norm = _exact.sqrt(vx * vx + vy * vy)
        zero = norm == 0
        safe = torch.where(zero, torch.ones_like(norm), norm)
        dx = torch.where(zero, torch.ones_like(vx), vx / safe)
        dy = torch.where(zero, torch.zeros_like(vy), vy / safe)
    else:
        phi = 0.5 * torch.atan2(2.0 * sxy, sxx - syy)
        dx, dy = torch.cos(phi), torch.sin(phi)
    flip = (dy < 0) | ((dy == 0) & (dx < 0))
    return torch.where(flip, -dx, dx), torch.where(flip, -dy, dy)


def validate_rows(fit: RowFit, present: torch.Tensor, height: int, hough_band: torch.Tensor,
                  params: Params, trig_free: bool = False) -> Rows:
    """Step 7.6: validity in row order of the fits ``fit`` where ``present`` bool ``(B, S)``;
    ``hough_band`` int64 (B,) px.

    ``trig_free=True`` (export) decides the two angle rules without ``atan2``, for unit
    directions with ``dy >= 0`` (:func:`principal_direction`): orientations lie in
    ``[0, pi)``, so ``|orient_i - orient_k| < min_angle_diff`` is the angle between the two
    directions, i.e. ``dot > cos(min_angle_diff)``; ``atan2(|dy|, |dx|) < horizon_angle`` is
    ``|dy| < sin(horizon_angle)``. Equal except within rounding of a threshold.
    """
    cx, cy, dx, dy, hyp, support = fit.astuple()
    # (an exported graph has no gradients; a grad-mode region there breaks torch.export's
    # handling of the torch.cond subgraphs around it)
    with contextlib.nullcontext() if torch.compiler.is_exporting() else torch.no_grad():
        a = dx / dy
        b = cx - a * cy
    nan = torch.full_like(a, float("nan"))
    a = torch.where(support, a, nan)
    b = torch.where(support, b, nan)
    if trig_free:
        horizon = dy.abs() < math.sin(params.horizon_angle)
    else:
        orient = torch.atan2(dy, dx)
        horizon = torch.atan2(dy.abs(), dx.abs()) < params.horizon_angle
    x_bottom = a * (height - 1) + b
    bsz, s = a.shape
    reason = torch.zeros((bsz, s), dtype=torch.int64, device=a.device)
    valid = torch.zeros((bsz, s), dtype=torch.bool, device=a.device)
    band = hough_band.to(torch.float64)
    for k in range(s):
        r = torch.zeros((bsz,), dtype=torch.int64, device=a.device)
        if k > 0:  # row 0 has no earlier rows (and an empty reduction is not portable to ONNX runtimes)
            earlier = valid[:, :k]
            if trig_free:
                par = (dx[:, :k] * dx[:, k:k + 1] + dy[:, :k] * dy[:, k:k + 1]) > math.cos(params.min_angle_diff)
            else:
                par = (orient[:, :k] - orient[:, k:k + 1]).abs() < params.min_angle_diff
            close = ((x_bottom[:, :k] - x_bottom[:, k:k + 1]).abs() < band.view(-1, 1)) & earlier
            r = torch.where(close.any(1), torch.full_like(r, REASON_CODES["too_close"]), r)
            r = torch.where((par & earlier).any(1), torch.full_like(r, REASON_CODES["parallel"]), r)
        r = torch.where(horizon[:, k], torch.full_like(r, REASON_CODES["horizon"]), r)
        r = torch.where(support[:, k], r, torch.full_like(r, REASON_CODES["no_support"]))
        r = torch.where(present[:, k], r, torch.zeros_like(r))
        reason[:, k] = r
        valid[:, k] = present[:, k] & (r == 0)
    return Rows(a, b, valid, reason, hyp, present)


def ransac_band(bushy: torch.Tensor, width: int, params: Params) -> torch.Tensor:
    """Step 7's band width per image, int64 ``(B,)`` px, from the bushy flag bool ``(B,)``
    (:meth:`torchrow.core.params.Params.ransac_band_px`): the one band rule of the eager
    detector, the exported graph and the tracker."""
    wide = torch.full(bushy.shape, params.ransac_band_px(width, True), dtype=torch.int64, device=bushy.device)
    return torch.where(bushy, wide, torch.full_like(wide, params.ransac_band_px(width, False)))


def image_status(rows: Rows, has_vp: torch.Tensor | None = None, has_veg: torch.Tensor | None = None) -> torch.Tensor:
    """An image's status code (index into :data:`torchrow.core.results.STATUSES`), int64
    ``(B,)``: ``no_vegetation`` where ``has_veg`` is False, else ``no_vp`` where ``has_vp``
    is False, else ``ok`` when every present row is valid, else ``invalid`` (bool ``(B,)``
    flags; ``None``: not checked). The one status rule of the detectors and the tracker."""
    code = {s: i for i, s in enumerate(STATUSES)}
    all_valid = (rows.valid | ~rows.present).all(dim=1)
    ok = torch.full(all_valid.shape, code["ok"], dtype=torch.int64, device=all_valid.device)
    status = torch.where(all_valid, ok, torch.full_like(ok, code["invalid"]))
    if has_vp is not None:
        status = torch.where(has_vp, status, torch.full_like(status, code["no_vp"]))
    if has_veg is not None:
        status = torch.where(has_veg, status, torch.full_like(status, code["no_vegetation"]))
    return status
