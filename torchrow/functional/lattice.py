"""Batched improved mode (ALGORITHM.md section 11, torchrow extension): the row lattice.

Mirror of :mod:`torchrow.reference.lattice`, stage by stage and with the same names. Every
sum that decides a discrete output adds integers (exact in float64 whatever the order), every
other float is the reference's expression in its order, so the results are identical.

Memory: a few ``(B, H, W)`` int64/float64/bool temporaries (about 40 bytes per pixel,
~200 MB for a batch of 64 images of 320x240: the mask, the VP search's cells, the comb's
projections, the refit's two prefix sums) plus ``(B, 3W)`` comb histograms. Section 11.2's
tables (``V``, ``C``, ``Q`` as in :meth:`Params.lattice_table_bytes`, which ``Params`` bounds):
the VP search's ``(V, C)`` bin table, ``8 V C`` bytes once per size and grid; per image its
``(V, 3W + 1 + lattice_max_spacing)`` int32 histograms and one spacing's folds, ``4 V (3W + 8
lattice_max_spacing)``, the comb's scores ``16 Q`` and its tooth windows, ``24 W`` per distinct
tooth half-width. Measured peak RSS of :class:`~torchrow.engines.detector.CropRowDetector`
(the whole detection, CPU: chunks of 12 images on 2 workers) for a batch of 64 images of
320x240: 0.6 GiB with the defaults, 0.8-1.0 GiB with spacings 12..320, ``lattice_vp_step``
10 and 15 VP heights; one image of 320x1638 (the largest ``max_pixels`` admits): 1.3 and 1.6 GiB.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F

from torchrow.core.io import check_lattice_size, lattice_params
from torchrow.core.params import LATTICE_ROLL_SCALE, LATTICE_WARP_MARGIN, LATTICE_WARP_SCALE, VP_SLICE, Params
from torchrow.core.results import STATUSES
from torchrow.functional._checks import below_horizon
from torchrow.functional._flow import branch, int_max, repeat

__all__ = ["LatticeRows", "LatticePriorBatch", "spacing_near", "improved_batch", "horizon_row", "excess_green", "ImprovedStart",
           "improved_start", "improved_finish", "vp_gather_table", "vp_window", "otsu_threshold", "green_mask", "init_vp",
           "row_evidence", "check_evidence", "vp_table", "vp_origin", "vp_search", "comb_table", "comb_search",
           "warp_rate", "warped",
           "solve_normal", "prefix_sums",
           "centre_spacing", "row_cells", "monomial_tables", "cell_means", "projective_rows", "roll_terms", "roll_choice",
           "normal_equations", "refine", "LatticeStartBatch",
           "lattice_start", "comb_start", "refit_lattice", "fit_lattice", "lattice_rows", "row_polynomials",
           "visible_rows", "VisibleRows", "row_dominance", "gap_offsets", "improved_rows", "improved_status", "LatticeFitBatch"]

N_COEF = 7
EXG_OFFSET = 510
EXG_BINS = 2 * EXG_OFFSET + 1


@dataclass
class LatticeRows:
    """Rows of the improved mode, ``(B, R)`` with ``R = 2*lattice_half + 1``: ``x = e*y**3 + c*y**2 +
    a*y + b`` (float64), ``valid`` bool, ``confidence`` float64; ``image_confidence`` ``(B,)``
    float64; ``coef`` ``(B, 7)`` float64 (``c0, c1, c2, c3, d0, d1, d2``); ``spacing``/``phase``/
    ``found`` ``(B,)`` (the comb); ``vp`` ``(B, 2)`` int64 (the rounded VP it used); ``contrast``
    ``(B,)`` float64 (the comb's best score per binned pixel), ``curved`` ``(B,)`` bool (11.3.1) and
    ``dominance`` ``(B,)`` float64 (11.4, :func:`row_dominance`; NaN where ``lattice_min_dominance`` is 0);
    ``visible_*``: every visible row, the fields of :class:`VisibleRows` (a dataclass of tensors
    only, so that :func:`~torchrow.core.results.concat_batches` joins chunks); ``lit`` ``(B, H)``
    int64: per image row, the rows ``-K .. K`` with an inlier there (section 11.7's row end); ``roll``
    ``(B,)`` float64: the projective spacing ``g`` of 11.3.2 (0 where ``lattice_roll_grid`` is 0)."""

    a: torch.Tensor
    b: torch.Tensor
    c: torch.Tensor
    e: torch.Tensor
    valid: torch.Tensor
    confidence: torch.Tensor
    image_confidence: torch.Tensor
    coef: torch.Tensor
    spacing: torch.Tensor
    phase: torch.Tensor
    found: torch.Tensor
    vp: torch.Tensor
    contrast: torch.Tensor
    curved: torch.Tensor
    dominance: torch.Tensor
    visible_a: torch.Tensor
    visible_b: torch.Tensor
    visible_c: torch.Tensor
    visible_e: torch.Tensor
    visible_confidence: torch.Tensor
    visible_present: torch.Tensor
    lit: torch.Tensor
    roll: torch.Tensor


class LatticePriorBatch(NamedTuple):
    """Section 11.7's prior per image (:class:`torchrow.reference.lattice.LatticePrior`): ``centre``
    ``(B,)`` float64, the bottom-row x the central row is chosen nearest to; ``restrict`` ``(B,)``
    bool, a tracked frame (else a full search); ``vp`` ``(B, 2)`` int64, the VP the comb uses
    there (the previous frame's lattice VP, not searched), and ``spacing`` ``(B,)`` int64, the
    previous comb spacing (both read where ``restrict``); ``windowed`` ``(B,)`` bool or ``None``
    (all false): a full search of a tracked sequence, which takes :func:`vp_window` of the grid
    around ``near`` ``(B, 2)`` int64, its last grid VP (the reference's ``LatticePrior.near``;
    read where ``windowed`` and not ``restrict``); ``sweep`` ``(B,)`` int64 or ``None`` (all -1):
    where ``>= 0`` (a windowed search after a frame that was not ``ok``) the grid height whose
    row of VPs is searched too (:func:`vp_window`; ``LatticePrior.sweep``)."""

    centre: torch.Tensor
    restrict: torch.Tensor
    vp: torch.Tensor
    spacing: torch.Tensor
    windowed: torch.Tensor | None = None
    near: torch.Tensor | None = None
    sweep: torch.Tensor | None = None


class LatticeFitBatch(NamedTuple):
    """:func:`fit_lattice`'s result per image: ``coef (B, 7)`` float64, the comb's ``spacing``,
    ``phase`` ``(B,)`` int64 and ``found`` ``(B,)`` bool, ``vp`` ``(B, 2)`` int64 (the VP the comb
    used), the final cells' counts ``cnt (B, H, R)`` int64, the comb's ``contrast`` ``(B,)``
    float64 (best score per binned pixel, 0 without pixels), ``curved`` ``(B,)`` bool (the
    curved refit was kept, 11.3.1) and ``roll`` ``(B,)`` float64, the projective spacing ``g`` of
    11.3.2 (0 where ``lattice_roll_grid`` is 0: equally spaced rows)."""

    coef: torch.Tensor
    spacing: torch.Tensor
    phase: torch.Tensor
    found: torch.Tensor
    vp: torch.Tensor
    cnt: torch.Tensor
    contrast: torch.Tensor
    curved: torch.Tensor
    roll: torch.Tensor


def horizon_row(sky: torch.Tensor, params: Params) -> torch.Tensor:
    """Section 11.1 per image: the first row the lattice uses, ``(B,)`` like ``sky`` (0 or ``sky``)."""
    return torch.zeros_like(sky) if params.lattice_horizon == "image" else sky


def excess_green(images: torch.Tensor) -> torch.Tensor:
    """``2G - R - B`` of ``uint8 (B, 3, H, W)``: ``int64 (B, H, W)`` in ``[-510, 510]``."""
    x = images.to(torch.int64)
    return 2 * x[:, 1] - x[:, 0] - x[:, 2]


def _below(sky: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """``(B, H, W)`` bool: rows ``y >= sky``."""
    return below_horizon(sky.to(torch.int64), h, as_bool=True).expand(-1, h, w)


def otsu_threshold(exg: torch.Tensor, sky: torch.Tensor, params: Params) -> torch.Tensor:
    """Section 11.1 per image: ``(B,)`` int64, the reference's criterion on integer sums."""
    bsz, h, w = exg.shape
    below = _below(sky, h, w)
    hist = torch.zeros((bsz, EXG_BINS), dtype=torch.int64, device=exg.device)
    hist.scatter_add_(1, (exg + EXG_OFFSET).flatten(1), below.flatten(1).to(torch.int64))
    cnt = torch.cumsum(hist, dim=1)
    mom = torch.cumsum(hist * torch.arange(EXG_BINS, dtype=torch.int64, device=exg.device), dim=1)
    n, m = cnt[:, -1:], mom[:, -1:]
    other = n - cnt
    num = (m * cnt - n * mom).to(torch.float64)
    den = (cnt * other).to(torch.float64)
    ok = (cnt > 0) & (other > 0)
    crit = torch.where(ok, (num * num) / torch.where(ok, den, torch.ones_like(den)), torch.full_like(den, -1.0))
    j = torch.argmax(crit, dim=1)  # first maximum
    return torch.clamp(j - EXG_OFFSET, min=params.green_floor)


def green_mask(images: torch.Tensor, sky: torch.Tensor, params: Params) -> torch.Tensor:
    """Section 11.1: ``exg > otsu`` below the horizon (and, with ``lattice_green ==
    "row_mean"``, ``W * exg > `` its image row's sum), ``(B, H, W)`` bool."""
    exg = excess_green(images)
    thr = otsu_threshold(exg, sky, params)
    mask = (exg > thr.view(-1, 1, 1)) & _below(sky, exg.shape[1], exg.shape[2])
    if params.lattice_green == "row_mean":
        mask = mask & (exg.shape[2] * exg > exg.sum(dim=2, keepdim=True))
    return mask


def init_vp(vp: torch.Tensor, has_vp: torch.Tensor, width: int, params: Params) -> torch.Tensor:
    """Section 11.2: ``(B, 2)`` int64, section 6's VP rounded half to even, or the fallback."""
    trusted = has_vp & (vp[:, 1] <= params.lattice_vp_max_y) & torch.isfinite(vp[:, 0])
    safe = torch.where(trusted.unsqueeze(1), vp, torch.zeros_like(vp))
    rounded = torch.round(safe).to(torch.int64)
    fallback = torch.tensor([width // 2, params.lattice_vp_fallback_y], dtype=torch.int64, device=vp.device)
    return torch.where(trusted.unsqueeze(1), rounded, fallback.expand_as(rounded))


_VP_TABLES: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}


def _grid_key(height: int, width: int, params: Params, device: torch.device) -> tuple:
    """What the VP grid's tables depend on: the sizes, the grid's fields and the device."""
    return (height, width, params.lattice_vp_step, params.lattice_vp_heights, params.lattice_vp_cell,
            params.lattice_vp_margin, str(device))


def _cell_centres(height: int, width: int, params: Params, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The VP search's cell centres ``(yc, xc)``, ``(C,)`` float64 each, row-major
    (:func:`torchrow.reference.lattice.vp_cells`)."""
    s = params.lattice_vp_cell
    hc, wc = -(-height // s), -(-width // s)
    yc = (torch.arange(hc, dtype=torch.float64, device=device) * s + (s - 1) / 2).repeat_interleave(wc)
    xc = (torch.arange(wc, dtype=torch.float64, device=device) * s + (s - 1) / 2).repeat(hc)
    return yc, xc


def _bins(vps: torch.Tensor, yc: torch.Tensor, xc: torch.Tensor, height: int, width: int,
          params: Params) -> torch.Tensor:
    """Every cell's bin under each VP of ``vps (..., 2)`` int64 in that VP's histogram,
    ``(..., C)`` int64 (``3W``: not binned): the reference's expression in float64, elementwise,
    so the same bits for any batch of VPs."""
    xv = vps[..., :1].to(torch.float64)
    yv = vps[..., 1:].to(torch.float64)
    b = torch.floor(xv + ((xc - xv) * (float(height - 1) - yv)) / (yc - yv))
    keep = ((yc - yv) > params.lattice_vp_margin) & (b >= -width) & (b < 2 * width)
    return torch.where(keep, b + width, torch.full_like(b, 3 * width)).to(torch.int64)


def vp_table(height: int, width: int, params: Params, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The search's grid ``(V, 2)`` int64 (:func:`torchrow.reference.lattice.vp_grid`'s order) and
    the bin of every cell under every grid VP in that VP's own histogram of ``3W + 1`` bins,
    ``(V, C)`` int64 (bin ``3W`` where a cell is not binned, a spill bin). It depends on the
    sizes and the grid only, so it is built once (float64, the reference's expression,
    ``VP_SLICE`` (VP, cell) pairs at a time) and cached:
    ``8 V C`` bytes, 18 MB at 320x240; sizes whose tables exceed the bound of
    :meth:`Params.lattice_table_bytes` raise :class:`~torchrow.core.io.ImageError` first."""
    key = _grid_key(height, width, params, device)
    table = _VP_TABLES.get(key)
    if table is None:
        check_lattice_size(width, height, params)
        yc, xc = _cell_centres(height, width, params, device)
        xs = torch.arange(0, width + 1, params.lattice_vp_step, dtype=torch.int64, device=device)
        hs = torch.tensor(params.lattice_vp_heights, dtype=torch.int64, device=device)
        grid = torch.stack([xs.repeat(hs.numel()), hs.repeat_interleave(xs.numel())], dim=1)
        idx = torch.empty((grid.shape[0], yc.numel()), dtype=torch.int64, device=device)
        step = max(1, VP_SLICE // max(yc.numel(), 1))  # VPs per slice: bounded float64 temporaries
        for v0 in range(0, grid.shape[0], step):
            idx[v0:v0 + step] = _bins(grid[v0:v0 + step], yc, xc, height, width, params)
        table = (grid, idx)
        if not torch.compiler.is_exporting():  # never cache a tensor traced by torch.export
            _VP_TABLES[key] = table
    return table


def _scattered_histograms(cnt: torch.Tensor, nv: int, width: int,
                          bins: Callable[[int, int], torch.Tensor]) -> torch.Tensor:
    """The VP search's histograms ``(B, V, 3W)`` int32 of ``nv`` VPs from the cell counts
    ``cnt (B, C)`` int32, scattered along ``bins(v0, k)``, the bins of VPs ``v0 .. v0+k-1``:
    ``(k, C)`` int64 for every image (:func:`vp_table`'s rows, broadcast with stride 0, so nothing
    is repeated) or ``(B, k, C)`` per image (a window, :func:`vp_window`); ``VP_SLICE`` (image,
    VP, cell) triples per scatter."""
    bsz, ncell = cnt.shape
    nb = 3 * width
    step = int_max(1, VP_SLICE // int_max(bsz * ncell, 1))
    parts = []
    for v0 in range(0, nv, step):
        k = min(step, nv - v0)
        at = bins(v0, k)
        parts.append(torch.zeros((bsz, k, nb + 1), dtype=torch.int32, device=cnt.device).scatter_add_(
            2, at.unsqueeze(0).expand(bsz, k, ncell) if at.dim() == 2 else at, cnt.unsqueeze(1).expand(bsz, k, ncell)))
    return torch.cat(parts, dim=1)[:, :, :nb] if len(parts) > 1 else parts[0][:, :, :nb]


#: :func:`vp_search` bins a whole grid's cells by a sparse product (:func:`_multiplied_histograms`)
#: from this many images per call on a CPU, by a scatter below: on one thread at 320x240 (119 VPs)
#: the product (its transpose included) took 3.8 / 5.0 / 6.6 / 7.4 ms at batch 1 / 4 / 8 / 12, the
#: scatter 1.9 / 7.0 / 12.8 / 18.0.
PRODUCT_MIN_BATCH = 4


def _hist_bins(width: int, params: Params) -> int:
    """The length of the VP search's histograms as the folds read them: the ``3W`` bins, then
    ``1 + lattice_max_spacing`` zeros (the spill bin's place and what a fold's last tooth reaches)."""
    return 3 * width + 1 + params.lattice_max_spacing


def _float32_exact(pixels: int) -> bool:
    """Whether float32 holds every sum of an image's pixel counts exactly: each is an integer of at
    most its ``pixels``, exact up to ``2**24``."""
    return pixels <= 2**24


_VP_PRODUCT_TABLES: dict[tuple, torch.Tensor] = {}


def vp_product_table(height: int, width: int, params: Params, device: torch.device) -> torch.Tensor:
    """:func:`vp_table`'s bins as a sparse CSR matrix of ones ``(V M, C)``, ``M = 3W + 1
    + lattice_max_spacing``: row ``v M + b`` holds the cells that VP ``v`` bins in ``b`` (the rows
    from ``3W`` on are empty: the spill bin dropped, the zeros a fold's last tooth reaches).
    float32, where every sum of counts is exact (at most ``2**24`` pixels), else float64.
    Built once per size and cached (``12 N + 8 V M`` bytes,
    ``N`` the (VP, cell) pairs binned: 2.8 MB at 320x240)."""
    key = _grid_key(height, width, params, device) + (params.lattice_max_spacing,)
    table = _VP_PRODUCT_TABLES.get(key)
    if table is None:
        dtype = torch.float32 if _float32_exact(height * width) else torch.float64
        idx = vp_table(height, width, params, device)[1]
        nv, ncell = idx.shape
        nb, nbp = 3 * width, _hist_bins(width, params)
        order = torch.argsort(idx, dim=1, stable=True)  # row-major: by VP, then bin, then cell
        bins = torch.gather(idx, 1, order)
        binned = bins < nb
        rows = (torch.arange(nv, dtype=torch.int64, device=device).view(-1, 1) * nbp + bins)[binned]
        crow = torch.zeros(nv * nbp + 1, dtype=torch.int64, device=device)
        crow[1:] = torch.cumsum(torch.bincount(rows, minlength=nv * nbp), 0)
        with warnings.catch_warnings():  # torch calls its sparse CSR layout beta
            warnings.simplefilter("ignore", UserWarning)
            table = torch.sparse_csr_tensor(crow, order[binned], torch.ones(rows.numel(), dtype=dtype, device=device),
                                            (nv * nbp, ncell))
        _VP_PRODUCT_TABLES[key] = table
    return table


def _multiplied_histograms(cnt: torch.Tensor, height: int, width: int, params: Params) -> torch.Tensor:
    """:func:`_scattered_histograms` of the whole grid followed by ``1 + lattice_max_spacing``
    zeros, ``(B, V, 3W + 1 + lattice_max_spacing)`` int32, as one product of :func:`vp_product_table` with the cell counts
    ``cnt (B, C)`` int32: the same integers, as every sum of counts is an integer of at most the
    image's pixels, exact in float32 up to ``2**24`` pixels (float64 beyond). Sparse kernels
    multiply a few columns at once where a scatter adds one (image, VP, cell) triple at a time:
    from :data:`PRODUCT_MIN_BATCH` images on it is faster on a CPU. Peak memory: the product and
    the histograms, ``8 V M`` bytes per image (1 MB at 320x240), and the cached table."""
    bsz = cnt.shape[0]
    table = vp_product_table(height, width, params, cnt.device)
    nbp = _hist_bins(width, params)
    nv = table.shape[0] // nbp
    out = torch.sparse.mm(table, cnt.t().to(table.dtype)).view(nv, nbp, bsz)
    return torch.empty((bsz, nv, nbp), dtype=torch.int32, device=cnt.device).copy_(out.permute(2, 0, 1))


_VP_GATHER_TABLES: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}


def vp_gather_table(height: int, width: int, params: Params, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`vp_table`'s bins as a gather: ``order (1 + N,)`` int64, the cell index ``C`` (a zero
    count appended to the cells) and then, VP by VP, the ``N`` (VP, cell) pairs it bins, each VP's
    cells sorted by bin; ``ends (V (3W + 1),)`` int64, per VP and bin ``b = 0 .. 3W`` the position
    in ``order`` of the last pair binned below ``b`` (the leading zero where none). So VP ``v``'s
    bin ``b`` holds ``S[ends[v, b + 1]] - S[ends[v, b]]`` of the cumulative sum ``S`` of the counts
    taken in that order. Built once per size from :func:`vp_table` and cached (``8 N`` bytes, about
    ``8 V C``: 48 MB at 500x281); only the exported step uses it (:func:`vp_search`)."""
    return _export_table(_VP_GATHER_TABLES, "vp_gather_table", height, width, params, device,
                         lambda: _gather_order(vp_table(height, width, params, device)[1], width))


def _gather_order(idx: torch.Tensor, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`vp_gather_table` built from :func:`vp_table`'s bins ``idx (V, C)`` int64."""
    nv, ncell = idx.shape
    nb = 3 * width
    device = idx.device
    order = torch.argsort(idx, dim=1, stable=True)
    bins = torch.gather(idx, 1, order)
    binned = bins < nb  # the spill bin sorts last
    count = binned.sum(dim=1)
    start = torch.cumsum(count, 0) - count + 1  # after the leading zero
    below = torch.searchsorted(bins, torch.arange(nb + 1, device=device).expand(nv, nb + 1).contiguous())
    ends = (start.unsqueeze(1) + torch.minimum(below, count.unsqueeze(1)) - 1).reshape(-1)
    return torch.cat([torch.full((1,), ncell, dtype=torch.int64, device=device), order[binned]]), ends


_VP_WINDOW_TABLES: dict[tuple, torch.Tensor] = {}


def vp_window_table(height: int, width: int, params: Params, device: torch.device) -> torch.Tensor:
    """:func:`vp_table`'s bins in the smallest integer type that holds ``3W`` (int16 up to ``W =
    10922``, else int32), ``(V, C)``: the table an exported graph takes a tracked window's rows from
    (:func:`vp_window`, then widened to int64), ``2 V C`` bytes (13 MB at 500x281) where the int64
    table would be 51 MB. Built once per size from :func:`vp_table` and cached; only the exported
    step uses it (eagerly the window takes :func:`vp_table`'s rows), and like
    :func:`vp_gather_table` it must be built before an export traces the search."""
    return _export_table(_VP_WINDOW_TABLES, "vp_window_table", height, width, params, device,
                         lambda: vp_table(height, width, params, device)[1].to(
                             torch.int16 if 3 * width < 2**15 else torch.int32))


def _export_table(cache: dict, name: str, height: int, width: int, params: Params, device: torch.device,
                  build: Callable[[], Any]) -> Any:
    """A table only the exported graph uses, from ``cache`` or ``build()`` (cached): built eagerly
    before an export traces the search (:func:`torchrow.onnx.export.to_onnx` does; traced, its
    sizes could depend on the table's values), so while exporting a missing one is an error."""
    key = _grid_key(height, width, params, device)
    table = cache.get(key)
    if table is None:
        if torch.compiler.is_exporting():
            raise RuntimeError(f"{name}({height}, {width}, ...) must be built eagerly before an export traces "
                               "the VP search (torchrow.onnx.to_onnx does)")
        table = cache[key] = build()
    return table


def _gathered_histograms(cnt: torch.Tensor, height: int, width: int, params: Params) -> torch.Tensor:
    """:func:`_scattered_histograms` of the whole grid as gathers and one cumulative sum (:func:`vp_gather_table`),
    the same integers. onnxruntime's ``ScatterElements`` spent about 7 ns per (VP, cell) pair
    (45 ms at 500x281, single thread), ``GatherElements`` and ``CumSum`` about 1 ns each."""
    order, ends = vp_gather_table(height, width, params, cnt.device)
    bsz = cnt.shape[0]
    nv, nb = ends.shape[0] // (3 * width + 1), 3 * width
    s = params.lattice_vp_cell
    # every pair's count is at most s*s: the running sum stays below 2**31 in int32 where it can
    wide = (order.shape[0] - 1) * s * s >= 2**31
    cells = torch.cat([cnt, torch.zeros((bsz, 1), dtype=cnt.dtype, device=cnt.device)], dim=1)
    taken = torch.gather(cells, 1, order.unsqueeze(0) if bsz == 1 else order.unsqueeze(0).expand(bsz, -1))
    run = torch.cumsum(taken, dim=1, dtype=torch.int64 if wide else torch.int32)
    at = torch.gather(run, 1, ends.unsqueeze(0) if bsz == 1 else ends.unsqueeze(0).expand(bsz, -1)).view(bsz, nv, nb + 1)
    return (at[:, :, 1:] - at[:, :, :-1]).to(torch.int32)


def _fold_peak(fold: torch.Tensor, d: int, params: Params) -> torch.Tensor:
    """The best tooth minus anti-tooth of ``(B, V, d)`` int32 folds over the phases, ``(B, V)``.

    With ``h = floor(d lattice_window)`` and ``a = d // 2``, phase ``p``'s tooth minus its
    anti-tooth (the tooth of ``p + a``) is the sum of ``g[i] = fold[i] - fold[(i + a) mod d]`` over
    the circular window ``p - h .. p + h``: a difference of one cumulative sum ``C`` of ``g``
    circularly extended (one circular pad of the fold, which starts one bin early: that bin adds
    to every entry of ``C`` and so to none of the differences, integers). While exporting the
    extension is a concatenation of the fold's slices, the same integers: onnxruntime's circular
    ``Pad`` cost about 70 us per spacing at 500x281 (11 ms of a whole grid's 153 spacings), where
    eagerly the concatenation cost up to 3x the pad at batch 64."""
    hw = int(math.floor(d * params.lattice_window))
    a = d // 2
    n = d + 2 * hw + 1
    if torch.compiler.is_exporting():
        ext = torch.cat([fold[..., d - hw - 1:], fold, fold[..., :a + hw + 1]], dim=-1)
    else:
        ext = F.pad(fold, (hw + 1, a + hw + 1), mode="circular")
    # g[i] = e[i] - e[i + a]: a tooth minus its anti-tooth is a window sum of g, one difference of
    # its cumulative sum (shorter than the teeth's own, d + 2h + 1 entries instead of d + a + 2h + 2)
    cs = torch.cumsum(ext[..., :n] - ext[..., a:a + n], dim=-1, dtype=torch.int32)
    return (cs[..., 2 * hw + 1:] - cs[..., :d]).amax(dim=-1)  # C[p + 2h + 1] - C[p], p = 0 .. d - 1


def _top_spacings(params: Params) -> tuple[range, list[int]]:
    """The VP search's spacings and those folded from the histograms, not from a double's fold."""
    spacings = range(params.lattice_min_spacing, params.lattice_max_spacing + 1, params.lattice_vp_spacing_step)
    return spacings, [d for d in spacings if 2 * d not in spacings]


def _summed(hist: torch.Tensor, pixels: int) -> torch.Tensor:
    """The histograms ``hist`` int32 of images of ``pixels`` pixels as :func:`_top_fold` sums them:
    while exporting float32 where that is exact (``pixels <= 2**24``: every partial sum is an
    integer no larger than the VP's binned pixels), else themselves. onnxruntime's float32
    ``ReduceSum`` took 7 ms of a whole grid's top folds at 500x281 where int32 took 18 ms; eagerly
    float32 is no faster, so eager sums stay int32."""
    return hist.to(torch.float32) if torch.compiler.is_exporting() and _float32_exact(pixels) else hist


def _top_fold(summed: torch.Tensor, nb: int, d: int) -> torch.Tensor:
    """The fold of spacing ``d`` of the first ``nb`` bins of :func:`_summed`'s ``(B, V, >= nb + d -
    1)`` histograms (zeros past ``nb``), ``(B, V, d)`` int32: bin ``r`` sums the bins ``= r mod d``."""
    bsz, nv = summed.shape[:2]
    teeth = -(-nb // d)
    return summed[:, :, :teeth * d].view(bsz, nv, teeth, d).sum(dim=2, dtype=summed.dtype).to(torch.int32)


def _peaks_by_spacing(hist: torch.Tensor, nb: int, params: Params, pixels: int) -> torch.Tensor:
    """:func:`vp_search`'s best fold peak over the spacings, ``(B, V)`` int32, of ``hist (B, V,
    3W + 1 + lattice_max_spacing)`` int32 of images of ``pixels`` pixels, spacing by spacing: one
    spacing's folds at a time, what large batches of large grids take (:func:`_peaks_at_once` for
    small ones)."""
    bsz, nv = hist.shape[:2]
    best = torch.full((bsz, nv), -(2**31) + 1, dtype=torch.int32, device=hist.device)
    spacings, tops = _top_spacings(params)
    summed = _summed(hist, pixels)
    for d in tops:
        fold = _top_fold(summed, nb, d)
        while True:
            best = torch.maximum(best, _fold_peak(fold, d, params))
            if d % 2 or d // 2 not in spacings:
                break
            d //= 2
            fold = fold[..., :d] + fold[..., d:]  # bins = r mod d are those = r or r + d mod 2d
    return best


class _FoldTables(NamedTuple):
    """:func:`_peaks_at_once`'s index tables, int64. ``halve[l]``: ``(lo, hi)`` into the folds of
    level ``l`` (level 0: the top spacings', each folded from the histograms; level ``l + 1``:
    the halves of level ``l``'s even spacings whose half is searched), ``fold_{d/2}[p] =
    fold_d[p] + fold_d[p + d/2]``; ``ext``: into all levels' folds concatenated, per spacing its
    fold circularly extended from ``-h - 1`` to ``d + h - 1`` (``d + 2h + 1`` entries; :func:`_fold_peak`'s
    ``h``); ``lo``, ``hi`` ``(L,)``: per spacing and phase ``p < d`` the entries ``p`` and ``p + 2h
    + 1`` of its extension, so that a tooth is a difference of the extension's cumulative sum;
    ``anti`` ``(L,)``: per spacing and phase the tooth of phase ``(p + d // 2) mod d``
    (``L`` = the sum of the spacings); ``wide``: that cumulative sum needs int64; ``nb`` and
    ``tops``: the bins folded and the top spacings, level 0's order; ``pixels``: the images'."""

    nb: int
    pixels: int
    tops: tuple[int, ...]
    halve: tuple[tuple[torch.Tensor, torch.Tensor], ...]
    ext: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    anti: torch.Tensor
    wide: bool


_FOLD_TABLES: dict[tuple, _FoldTables] = {}

#: :func:`vp_search` takes the spacings at once (:func:`_peaks_at_once`) up to this many
#: (image, VP) pairs, spacing by spacing beyond. ``python benchmarks/bench_vp_fold.py`` (500x281,
#: spacings 16..320, windows of 15 VPs, a search after a loss 41; two runs), the time at once
#: over the time spacing by spacing: on one CPU thread 0.88-0.91 at 30 pairs (two windows),
#: 0.97-1.06 at 41-45, 1.33-1.46 at 82 (two searches after a loss); on two threads (the CLI's
#: setting) 0.62-0.85 at 30-45 pairs, 1.06-1.15 at 82; a whole grid at batch 1 (182 VPs) 2.7-4.7.
AT_ONCE_ROWS = 48

#: :data:`AT_ONCE_ROWS` while exporting: onnxruntime pays more for each of the loop's hundreds of
#: small nodes than eager torch pays for each operation, so the bound lies higher. On one
#: onnxruntime thread with torchrow's session options (``benchmarks/bench_vp_fold.py``) a search
#: after a loss (41 pairs) took 14.3 ms at once against 16.8 spacing by spacing and a whole grid
#: (182 VPs) 48.8 against 47.6: linear between the two, they cost the same near 136 pairs. The
#: at-once form also spares the export the loop's unrolling, about 150 s per search.
EXPORT_AT_ONCE_ROWS = 128


def _fold_tables(nb: int, pixels: int, params: Params, device: torch.device) -> _FoldTables:
    """:class:`_FoldTables` for ``nb`` histogram bins of images of ``pixels`` pixels, built once per
    size and spacings (``8 (L + sum(d + 2h + 1))`` bytes and the halvings', 1 MB at 500x281 with
    spacings 16..320; about 20 ms to build) and cached. An exported graph holds them as
    constants, built before the export traces the search (:func:`vp_fold_tables`): traced inside
    a branch of the step, their index lists (4840 entries at 500x281) would be constants made there."""
    key = (nb, pixels, params.lattice_min_spacing, params.lattice_max_spacing, params.lattice_vp_spacing_step,
           params.lattice_window, str(device))
    tables = _FOLD_TABLES.get(key)
    if tables is not None:
        return tables
    if torch.compiler.is_exporting():
        raise RuntimeError(f"vp_fold_tables(...) for {pixels}-pixel images {nb // 3} px wide must be built eagerly "
                           "before an export traces the VP search (torchrow.onnx.to_onnx does)")

    def table(t: list[int]) -> torch.Tensor:
        return torch.tensor(t, dtype=torch.int64, device=device)

    spacings, tops = _top_spacings(params)
    levels, halve = [list(tops)], []
    while True:
        lo: list[int] = []
        hi: list[int] = []
        nxt = []
        off = 0
        for d in levels[-1]:
            if d % 2 == 0 and d // 2 in spacings:
                lo += range(off, off + d // 2)
                hi += range(off + d // 2, off + d)
                nxt.append(d // 2)
            off += d
        if not nxt:
            break
        halve.append((table(lo), table(hi)))
        levels.append(nxt)
    ext: list[int] = []
    anti: list[int] = []
    lo, hi = [], []
    off = 0
    for d in (d for level in levels for d in level):
        hw = int(math.floor(d * params.lattice_window))
        start = len(ext)
        ext += (off + (i - hw - 1) % d for i in range(d + 2 * hw + 1))
        lo += range(start, start + d)
        hi += range(start + 2 * hw + 1, start + 2 * hw + 1 + d)
        anti += (off + (p + d // 2) % d for p in range(d))
        off += d
    # every extension sums to at most twice its fold's total, at most the image's pixels
    wide = 2 * len(spacings) * pixels >= 2**31
    tables = _FoldTables(nb, pixels, tuple(tops), tuple(halve), table(ext), table(lo), table(hi), table(anti), wide)
    if len(_FOLD_TABLES) >= 8:  # a few sizes at a time (about 20 ms to build one)
        _FOLD_TABLES.clear()
    _FOLD_TABLES[key] = tables
    return tables


def vp_fold_tables(height: int, width: int, params: Params, device: torch.device) -> _FoldTables:
    """The tables of :func:`_peaks_at_once` (a tracked window's VP search) for ``height x width``
    images: what :func:`vp_search` uses, built and cached eagerly; an export of the tracker step
    builds them first (:func:`torchrow.onnx.to_onnx`), as :func:`vp_gather_table`."""
    return _fold_tables(3 * width, height * width, params, device)


def _peaks_at_once(hist: torch.Tensor, tables: _FoldTables) -> torch.Tensor:
    """:func:`_peaks_by_spacing`'s integers with the spacings at once: one sum per top spacing (the
    folds of the histograms), then the halvings one level at a time, one circular extension, one
    cumulative sum and the teeth and anti-teeth as index selections (:class:`_FoldTables`), about
    3 tensor operations per top spacing and 20 in all in place of 10 per spacing. A tracked
    sequence's windowed search at batch 1 (15 VPs) costs its operations, not its data; the
    extension is ``4 B V sum(d + 2h + 1)`` bytes (1.9 MB at 500x281, 15 VPs, spacings 16..320),
    and beyond a few dozen (image, VP) pairs the spacing-by-spacing loop, whose working set is
    one spacing's folds, is faster (:data:`AT_ONCE_ROWS`).
    ``hist (B, V, 3W + 1 + lattice_max_spacing)`` int32 -> ``(B, V)`` int32."""
    bsz, nv = hist.shape[:2]
    # spacings and phases first: each selection copies rows of B V entries
    summed = _summed(hist, tables.pixels)
    level = torch.cat([_top_fold(summed, tables.nb, d) for d in tables.tops], dim=2).view(
        bsz * nv, sum(tables.tops)).t().contiguous()
    folds = [level]
    for lo, hi in tables.halve:
        level = level.index_select(0, lo) + level.index_select(0, hi)
        folds.append(level)
    ext = torch.cat(folds, dim=0).index_select(0, tables.ext)
    cs = torch.cumsum(ext, dim=0, dtype=torch.int64 if tables.wide else torch.int32)
    tooth = cs.index_select(0, tables.hi) - cs.index_select(0, tables.lo)
    return (tooth - tooth.index_select(0, tables.anti)).amax(dim=0).to(torch.int32).view(bsz, nv)


def vp_origin(sky: torch.Tensor, height: int, params: Params) -> torch.Tensor:
    """Section 11.2: the row the VP grid's heights count from, ``(B,)`` int64 from section 1's
    ``sky (B,)`` (:func:`torchrow.reference.lattice.vp_origin`): 0, or ``min(sky +
    lattice_vp_sky, H)`` where a horizon is in view (``sky > 0``, ``lattice_vp_sky_div * sky >= H``)."""
    sky = sky.to(torch.int64)
    if params.lattice_vp_origin != "sky":
        return torch.zeros_like(sky)
    seen = (sky > 0) & (params.lattice_vp_sky_div * sky >= height)
    return torch.where(seen, torch.clamp(sky + params.lattice_vp_sky, min=0, max=height), torch.zeros_like(sky))


def vp_window(near: torch.Tensor, origin: torch.Tensor | None, width: int, params: Params,
              sweep: torch.Tensor | None = None) -> torch.Tensor:
    """Section 11.7: per image the indices into :func:`vp_table`'s grid (ascending) that a full
    search of a tracked sequence takes around its last grid VP ``near (B, 2)`` int64, ``(B, n)``
    int64 with ``n = min(2 lattice_track_vp_cols + 1, W // lattice_vp_step + 1) min(2
    lattice_track_vp_rows + 1, len(lattice_vp_heights))``; ``origin (B,)`` int64 as
    :func:`vp_search`'s (``None``: zeros). With ``sweep (B,)`` int64 (a grid height's index
    per image, each in range) the ``W // lattice_vp_step + 1`` VPs of that height follow, left to
    right: ``(B, n + W // lattice_vp_step + 1)``. :func:`torchrow.reference.lattice.vp_window`'s
    integers."""
    bsz, dev = near.shape[0], near.device
    step, rx, ry = params.lattice_vp_step, params.lattice_track_vp_cols, params.lattice_track_vp_rows
    ncol = width // step + 1
    heights = torch.tensor(params.lattice_vp_heights, dtype=torch.int64, device=dev)
    nx, ny = min(2 * rx + 1, ncol), min(2 * ry + 1, heights.numel())
    c = torch.clamp(torch.div(2 * near[:, 0] + step, 2 * step, rounding_mode="floor"), min=0, max=ncol - 1)
    rel = near[:, 1] if origin is None else near[:, 1] - origin
    i = torch.argmin((heights.view(1, -1) - rel.view(-1, 1)).abs(), dim=1)  # the first on ties, as numpy's
    x0 = torch.clamp(c - rx, min=0, max=ncol - nx)
    y0 = torch.clamp(i - ry, min=0, max=heights.numel() - ny)
    rows = y0.view(-1, 1, 1) + torch.arange(ny, dtype=torch.int64, device=dev).view(1, -1, 1)
    win = (rows * ncol + x0.view(-1, 1, 1) + torch.arange(nx, dtype=torch.int64, device=dev).view(1, 1, -1)).view(
        bsz, ny * nx)
    if sweep is None:
        return win
    return torch.cat([win, sweep.view(-1, 1) * ncol + torch.arange(ncol, dtype=torch.int64, device=dev).view(1, -1)], dim=1)


def vp_search(mask: torch.Tensor, params: Params, origin: torch.Tensor | None = None,
              near: torch.Tensor | None = None, sweep: torch.Tensor | None = None) -> torch.Tensor:
    """Section 11.2 (``lattice_vp == "search"``): per image the grid VP whose folded contrast
    comb is strongest, ``(B, 2)`` int64; see :func:`torchrow.reference.lattice.vp_search`.
    ``origin (B,)`` int64 (:func:`vp_origin`; ``None``: zeros): each image's rows ``origin .. H-1``
    are searched moved up to row 0 (one gather of the mask) and ``origin`` is added to the VP's row.
    ``near (B, 2)`` int64 (section 11.7, tracked sequences' last grid VPs; ``None``: the whole
    grid) and ``sweep (B,)`` int64 (with ``near``: a grid height each, swept after a frame that
    was not ``ok``; ``None``: none): each
    image searches its own :func:`vp_window` of the grid, ``n`` VPs in place of ``V``, their bins
    the table's rows (eagerly :func:`vp_table`, while exporting :func:`vp_window_table`, the same
    integers in int16, so that the graph holds a quarter of the int64 table).

    The cell counts are scattered into ``(B, V, 3W + 1)`` int32 histograms along the bins
    (``VP_SLICE`` (image, VP, cell) triples per scatter, through :func:`vp_table`'s bins; the
    table and the counts broadcast with stride 0, nothing repeated; a whole grid of at least
    :data:`PRODUCT_MIN_BATCH` images on a CPU as one sparse product instead,
    :func:`_multiplied_histograms`, the same integers), then folded per spacing (a
    spacing whose double is searched too is folded from that fold, ``2d`` values instead of
    ``3W``): all spacings at once for at most ``AT_ONCE_ROWS`` (image, VP) pairs, while exporting
    ``EXPORT_AT_ONCE_ROWS`` (:func:`_peaks_at_once`: a tracked sequence's window and its
    wider window after a loss), spacing by spacing beyond
    (:func:`_peaks_by_spacing`); every sum is an integer below ``2**31`` (int64 where
    it could pass), so the scores are the reference's. Peak memory: the histograms twice, ``8 V (3W + d_max)`` bytes per image
    (1 MB at 320x240), plus the table; the spacings at once about 0.5 MB more per (image, VP) pair
    at 500x281 with spacings 16..320 (the folds, their extension, its cumulative sum and the
    teeth: 68 MB at ``EXPORT_AT_ONCE_ROWS`` pairs). (Repeating the counts for a flat scatter cost 9-10 % of
    the search eagerly, best of interleaved runs at batch 1, 16 and 64.) While exporting
    (``torch.compiler.is_exporting()``) the histograms come from :func:`_gathered_histograms`
    instead, the same integers without a scatter (ALGORITHM.md 11.5); it adds ``8 N`` bytes per
    image for the counts in the gather order and their running sum (``N`` the (VP, cell) pairs
    binned: 48 MB at 500x281, batch 1) and the cached gather table, ``8 N`` bytes once.
    """
    bsz, h, w = mask.shape
    dev = mask.device
    grid, idx = vp_table(h, w, params, dev)
    win = None if near is None else vp_window(near, origin, w, params, sweep)  # (B, n)
    if win is not None:
        grid = grid[win]  # (B, n, 2)
    if origin is not None:
        rows = torch.arange(h, device=dev).view(1, h) + origin.view(-1, 1)  # (B, H): the source row
        inside = (rows < h).view(bsz, h, 1)
        src = torch.clamp(rows, max=h - 1).view(bsz, h, 1).expand(bsz, h, w)
        mask = torch.gather(mask, 1, src) & inside
    s = params.lattice_vp_cell
    hc, wc = -(-h // s), -(-w // s)
    nv, ncell = grid.shape[-2], hc * wc
    padded = F.pad(mask.to(torch.int32), (0, wc * s - w, 0, hc * s - h))
    # a cell's rows first, then its columns: two contiguous reductions (one over both axes at
    # once strided through the image, 10x slower at batch 12)
    cnt = padded.view(bsz, hc, s, wc * s).sum(dim=2, dtype=torch.int32).view(bsz, hc, wc, s).sum(
        dim=3, dtype=torch.int32).view(bsz, ncell)
    nb = 3 * w
    if win is not None and torch.compiler.is_exporting():
        # an exported graph holds the table in int16 (vp_window_table), a quarter of the int64 one
        small = vp_window_table(h, w, params, dev)
        hist = _scattered_histograms(cnt, nv, w, lambda v0, k: small[win[:, v0:v0 + k]].to(torch.int64))
    elif win is not None:
        hist = _scattered_histograms(cnt, nv, w, lambda v0, k: idx[win[:, v0:v0 + k]])
    elif torch.compiler.is_exporting():
        hist = _gathered_histograms(cnt, h, w, params)
    elif dev.type == "cpu" and bsz >= PRODUCT_MIN_BATCH:
        hist = _multiplied_histograms(cnt, h, w, params)
    else:
        hist = _scattered_histograms(cnt, nv, w, lambda v0, k: idx[v0:v0 + k])
    if hist.shape[2] == nb:
        # the spill bin dropped, zeros appended: a fold's last tooth may reach past 3W
        tail = torch.zeros((bsz, nv, _hist_bins(w, params) - nb), dtype=torch.int32, device=dev)
        hist = torch.cat([hist, tail], dim=2)
    total = hist.sum(dim=2, dtype=torch.int64)
    if bsz * nv <= (EXPORT_AT_ONCE_ROWS if torch.compiler.is_exporting() else AT_ONCE_ROWS):
        best = _peaks_at_once(hist, _fold_tables(nb, h * w, params, dev))
    else:
        best = _peaks_by_spacing(hist, nb, params, h * w)
    seen = total > 0
    value = torch.where(seen, best.to(torch.float64) / torch.clamp(total, min=1).to(torch.float64),
                        torch.full_like(total, -math.inf, dtype=torch.float64))
    first = torch.argmax(value, dim=1)  # first maximum: the grid's order
    pick = grid[first] if near is None else torch.gather(grid, 1, first.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)
    if origin is not None:
        pick = pick + torch.stack([torch.zeros_like(origin), origin], dim=1)
    fallback = torch.tensor([w // 2, params.lattice_vp_fallback_y], dtype=torch.int64, device=dev)
    return torch.where(seen.any(dim=1, keepdim=True), pick, fallback.expand_as(pick))


class _CombTable(NamedTuple):
    """:func:`comb_table`'s tables for one working width."""

    d: torch.Tensor  # (Q,) int64: candidate q's spacing, in spacing then phase order
    p: torch.Tensor  # (Q,) int64: candidate q's bin phase
    hws: torch.Tensor  # (G,) int64: the distinct tooth half-widths, ascending
    chunks: tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], ...]  # (group, tooth, anti) per chunk

    def flat(self) -> tuple[torch.Tensor, ...]:
        """The tables as one flat tuple of tensors (a ``torch.cond`` branch's operands)."""
        return (self.d, self.p, self.hws, *(t for chunk in self.chunks for t in chunk))

    @classmethod
    def from_flat(cls, tensors: tuple[torch.Tensor, ...]) -> _CombTable:
        """The inverse of :meth:`flat`."""
        rest = tensors[3:]
        return cls(tensors[0], tensors[1], tensors[2],
                   tuple((rest[i], rest[i + 1], rest[i + 2]) for i in range(0, len(rest), 3)))


_COMB_TABLES: dict[tuple, _CombTable] = {}

#: Spacings whose teeth :func:`comb_search` scatters at once: one scatter (and one for the
#: anti-teeth) per chunk, not per tooth half-width (an exported comb holds a few scatters, not
#: ~60 at 500 px); it bounds the memory of the windows scattered.
COMB_CHUNK = 64


def comb_table(width: int, params: Params, device: torch.device) -> _CombTable:
    """The comb's candidate tables for ``width``-px images, built once per size, spacing range and
    window, and cached (:class:`_CombTable`). The spacings, in ascending order, fall into chunks
    of at most :data:`COMB_CHUNK`; per chunk ``group (r,)`` int64 (each spacing's half-width, an
    index into ``hws``), ``tooth (r 3W,)`` int64 (the candidate each bin's tooth window counts
    towards, ``off_d + b mod d``, row by row) and ``anti (r 3W,)`` int64 (the candidate each bin's
    window counts against as an anti-tooth, ``off_d + (b - d//2) mod d`` for ``b >= d//2``, else
    the spill index ``Q``). ``16 n_d 3W`` bytes (7 MB at 500 px, spacings 16..320)."""
    key = (width, params.lattice_min_spacing, params.lattice_max_spacing, params.lattice_window, str(device))
    table = _COMB_TABLES.get(key)
    if table is None:
        nb = 3 * width
        spacings = list(range(params.lattice_min_spacing, params.lattice_max_spacing + 1))
        hw_of = [int(math.floor(d * params.lattice_window)) for d in spacings]
        hws = sorted(set(hw_of))
        b = torch.arange(nb, dtype=torch.int64, device=device)
        q = sum(spacings)
        off = 0
        dq, pq, tooth, anti = [], [], [], []
        for d in spacings:
            dq.append(torch.full((d,), d, dtype=torch.int64, device=device))
            pq.append(torch.arange(d, dtype=torch.int64, device=device))
            tooth.append(off + b % d)
            anti.append(torch.where(b >= d // 2, off + (b - d // 2) % d, torch.full_like(b, q)))
            off += d
        chunks = []
        for lo in range(0, len(spacings), COMB_CHUNK):
            rows = range(lo, min(lo + COMB_CHUNK, len(spacings)))
            teeth = torch.cat([tooth[i] for i in rows])
            chunks.append((torch.tensor([hws.index(hw_of[i]) for i in rows], dtype=torch.int64, device=device),
                           teeth, torch.cat([anti[i] for i in rows])))
        table = _CombTable(torch.cat(dq), torch.cat(pq), torch.tensor(hws, dtype=torch.int64, device=device),
                           tuple(chunks))
        if not torch.compiler.is_exporting():  # never cache a tensor traced by torch.export
            _COMB_TABLES.clear()  # one size at a time: a video or a batch has one working size
            _COMB_TABLES[key] = table
    return table


def spacing_near(d: torch.Tensor, previous: torch.Tensor, params: Params) -> torch.Tensor:
    """:func:`torchrow.reference.lattice.spacing_near`: int64 spacings ``d`` within
    ``lattice_track_spacing_tol`` of ``previous`` (broadcast), bool."""
    return (d - previous).to(torch.float64).abs() <= params.lattice_track_spacing_tol * previous.to(torch.float64)


def warp_rate(warp: int, width: int) -> float:
    """:func:`torchrow.reference.lattice.warp_rate`: the comb's warp ``j`` per pixel (a Python float
    holding the reference's float64)."""
    return float(warp) / float(LATTICE_WARP_SCALE // 2 * width)


def warped(x: torch.Tensor, gamma: float, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`torchrow.reference.lattice.warped`: float64 bottom-row positions under the comb's
    projective warp (the same operations in the same order) and where it is defined, bool."""
    x0 = float(width) / 2.0
    t = x - x0
    den = 1.0 - gamma * t
    ok = den > 0
    return x0 + t / torch.where(ok, den, 1.0), ok


def comb_search(mask: torch.Tensor, vp: torch.Tensor, params: Params, prior: LatticePriorBatch | None = None,
                warp: int = 0, table: _CombTable | None = None):
    """Section 11.2 per image: ``(spacing, phase, found, contrast)``, each ``(B,)`` (int64, int64,
    bool, float64; ``contrast`` = the best score per binned pixel, 0 without pixels).

    Every candidate is scored at once: each bin's tooth window (the pixels within the tooth
    half-width of it, one prefix-sum difference per distinct half-width) is scatter-added to the
    candidate whose teeth it is on and, with ``lattice_comb == "contrast"``, subtracted from the one
    whose anti-teeth (``d // 2`` bins on) it is on (:func:`comb_table`; integer sums, so the scores
    are the reference's; one scatter per :data:`COMB_CHUNK` spacings). ``prior`` (section 11.7):
    the central row is the tooth nearest ``prior.centre``, and where ``prior.restrict`` only the
    candidates of :func:`torchrow.reference.lattice.comb_near` compete. ``warp`` ``j``: the comb
    on the bottom row under 11.3.2's warp (:func:`warped`), the centre warped alike. ``table``:
    this width's :func:`comb_table`, where the caller holds it (a traced graph then builds it
    once for all of its combs, not once per call). Peak memory per image: the
    ``(Q + 1)`` int64 scores and float64 masks, ``32 Q`` bytes (1.6 MB at 500 px, spacings
    16..320), the ``(G, 3W)`` windows and a chunk's ``(COMB_CHUNK, 3W)`` int64 windows (0.8 MB
    at 500 px).
    """
    bsz, h, w = mask.shape
    dev = mask.device
    nb = 3 * w
    xv = vp[:, 0].to(torch.float64).view(-1, 1, 1)
    yv_i = vp[:, 1].view(-1, 1, 1)
    ys = torch.arange(h, device=dev).view(1, h, 1)
    xs = torch.arange(w, device=dev, dtype=torch.float64).view(1, 1, w)
    sel = mask & ((ys - yv_i) > params.lattice_vp_margin)
    yv = yv_i.to(torch.float64)
    dy = ys.to(torch.float64) - yv
    proj = xv + ((xs - xv) * ((h - 1) - yv)) / torch.where(sel, dy, 1.0)  # a scalar: no folded (B, H, W) constant
    if warp != 0:
        proj, defined = warped(proj, warp_rate(warp, w), w)
        sel = sel & defined
    b = torch.floor(proj)
    keep = sel & (b >= -w) & (b < 2 * w)
    bins = torch.where(keep, b, 0.0).to(torch.int64) + w
    hist = torch.zeros((bsz, nb), dtype=torch.int64, device=dev)
    hist.scatter_add_(1, bins.flatten(1), keep.flatten(1).to(torch.int64))
    n = keep.flatten(1).sum(dim=1)  # (B,)
    cs = torch.cat([torch.zeros((bsz, 1), dtype=torch.int64, device=dev), torch.cumsum(hist, dim=1)], dim=1)
    d_all, p_all, hws, chunks = comb_table(w, params, dev) if table is None else table
    centre = torch.arange(nb, device=dev)
    lo = torch.clamp(centre.view(1, -1) - hws.view(-1, 1), 0, nb)
    hi = torch.clamp(centre.view(1, -1) + hws.view(-1, 1) + 1, 0, nb)
    win = cs[:, hi] - cs[:, lo]  # (B, G, 3W): pixels in the tooth of each half-width centred on each bin
    acc = torch.zeros((bsz, d_all.numel() + 1), dtype=torch.int64, device=dev)  # + the anti-teeth's spill
    contrasted = params.lattice_comb == "contrast"
    against = torch.zeros_like(acc) if contrasted else None
    for group, tooth, anti in chunks:
        src = torch.index_select(win, 1, group).reshape(bsz, -1)  # (B, r 3W): each spacing's tooth windows
        acc.scatter_add_(1, tooth.view(1, -1).expand(bsz, -1), src)
        if against is not None:
            against.scatter_add_(1, anti.view(1, -1).expand(bsz, -1), src)
    if against is not None:
        acc = acc - against
    d_f = d_all.to(torch.float64)
    if contrasted:
        allsc = acc[:, :-1].to(torch.float64)
    else:
        hw_d = torch.floor(d_f * params.lattice_window).to(torch.int64)
        expect = (n.view(-1, 1) * (2 * hw_d + 1)).to(torch.float64) / d_f
        allsc = acc[:, :-1].to(torch.float64) - expect
    if prior is not None:
        target = prior.centre.to(torch.float64).view(-1, 1)
        d_prev = prior.spacing.view(-1, 1)
        rel = target - (p_all - w).to(torch.float64).view(1, -1)
        off = rel - d_f * torch.round(rel / d_f)
        near = spacing_near(d_all, d_prev, params) & (off.abs() <= params.lattice_track_phase_tol * d_f)
        near = near | ~prior.restrict.view(-1, 1)
        allsc = torch.where(near, allsc, -math.inf)
    q = torch.argmax(allsc, dim=1)  # first maximum: spacing, then phase order
    best = torch.gather(allsc, 1, q.unsqueeze(1)).squeeze(1)
    d_q = d_all[q]
    p_q = p_all[q] - w
    centre = torch.full((bsz,), float(w) / 2, dtype=torch.float64, device=dev) if prior is None else prior.centre
    if warp != 0:
        centre = warped(centre, warp_rate(warp, w), w)[0]
    k0 = torch.round((centre - p_q.to(torch.float64)) / d_q.to(torch.float64)).to(torch.int64)
    found = n > 0
    spacing = torch.where(found, d_q, torch.full_like(d_q, params.lattice_min_spacing))
    phase = torch.where(found, p_q + k0 * d_q, torch.full_like(d_q, w // 2))
    contrast = torch.where(found, best / torch.clamp(n, min=1).to(torch.float64), torch.zeros_like(best))
    return spacing, phase, found, contrast


def solve_normal(m: torch.Tensor, r: torch.Tensor, params: Params,
                 pinned: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched :func:`torchrow.reference.lattice.solve_normal`: ``m (B, n, n)``, ``r (B, n)``.

    Returns ``(z (B, n), singular (B,) bool)``; ``z`` is meaningless where singular.
    ``pinned (B, n)`` bool: unknowns whose rows and columns of ``m`` are the identity's and whose
    ``r`` is 0 (a smaller basis embedded in this one); their pivots are never singular.

    The systems are tiny (7x7), so on a CPU the cost is the number of tensor operations, not
    their size, and in the detector's thread pool each operation's dispatch holds the GIL. Hence
    ``r`` rides along as column ``n`` of ``m`` (the same expression per entry), the pivots are
    tested once at the end, on the final diagonal (the reference stops at the first bad one; a
    later pivot computed from a bad one only matters where the system is singular anyway), and
    the back substitution reads every entry from one ``unbind``: about 110 operations for
    ``n = 7``, half as many as testing and reading entry by entry.
    """
    bsz, n = r.shape
    scale = torch.clamp(torch.diagonal(m, dim1=1, dim2=2), min=1.0)
    a = torch.cat([m, r.unsqueeze(2)], dim=2)  # (B, n, n + 1)
    # below[i] (1, n, 1): the rows j > i, which pivot i eliminates
    below = torch.ones((n, n), dtype=torch.bool, device=m.device).triu(1).view(n, 1, n, 1).unbind(0)
    for i in range(n - 1):
        # whole-matrix steps, no slice assignment (an exported graph would scatter): rows below
        # the pivot take the reference's f * a[i][k] subtracted from a[j][k] (a multiplication,
        # then a subtraction, each rounded), so the same bits in every entry right of column i;
        # the entries up to column i, never read again, take whatever the same formula gives; row i
        # stays as it is from here on, so the final diagonal holds every pivot
        row = a[:, i:i + 1, :]
        f = a[:, :, i:i + 1] / row[:, :, i:i + 1]
        a = torch.where(below[i], a - f * row, a)
    bad = ~(torch.diagonal(a, dim1=1, dim2=2) > params.lattice_pivot_tol * scale)
    if pinned is not None:
        bad = bad & ~pinned
    entry = a.reshape(bsz, n * (n + 1)).unbind(1)
    out = list(entry[:n])
    for i in range(n - 1, -1, -1):
        acc = entry[i * (n + 1) + n]
        for k in range(i + 1, n):
            acc = acc - entry[i * (n + 1) + k] * out[k]
        out[i] = acc / entry[i * (n + 2)]
    return torch.stack(out, dim=1), bad.any(dim=1)


def prefix_sums(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image row, the count and the x sum of the mask's pixels left of each column:
    two ``(B, H, W+1)`` int64 (entry ``j`` covers columns ``0 .. j-1``)."""
    bsz, h, w = mask.shape
    m = mask.to(torch.int64)
    zero = torch.zeros((bsz, h, 1), dtype=torch.int64, device=mask.device)
    xs = torch.arange(w, dtype=torch.int64, device=mask.device)
    return (torch.cat([zero, torch.cumsum(m, dim=2)], dim=2),
            torch.cat([zero, torch.cumsum(m * xs, dim=2)], dim=2))


def centre_spacing(t: torch.Tensor, coef: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched :func:`torchrow.reference.lattice.centre_spacing`: ``t (1, H, 1)``, ``coef (B, 7)`` ->
    ``c(t)``, ``d(t)`` ``(B, H, 1)`` float64."""
    c0, c1, c2, c3, d0, d1, d2 = coef.reshape(-1, N_COEF, 1, 1).unbind(1)  # one operation, not seven
    tt = t * t
    return ((c0 + c1 * t) + c2 * tt) + c3 * (tt * t), (d0 + d1 * t) + d2 * tt


def _image_rows(height: int, device: torch.device) -> torch.Tensor:
    """``t = y - (H-1)`` of every image row, ``(1, H, 1)`` float64 (section 11.3)."""
    return (torch.arange(height, device=device, dtype=torch.float64) - (height - 1)).view(1, height, 1)


def projective_rows(cc: torch.Tensor, dd: torch.Tensor, k: torch.Tensor,
                    g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batched :func:`torchrow.reference.lattice.projective_rows` (section 11.3.2): centres ``(c + k d)
    / u``, own spacings ``(d - g c) / (u u)`` and ``u = 1 + g k``, float64, broadcast over the
    shapes of ``c(t)``, ``d(t)`` (``cc``, ``dd``), the rows ``k`` and the spacings ``g``."""
    u = 1.0 + g * k
    return (cc + k * dd) / u, (dd - g * cc) / (u * u), u


def row_cells(pre: tuple[torch.Tensor, torch.Tensor], coef: torch.Tensor, params: Params,
              ks: torch.Tensor | None = None, t: torch.Tensor | None = None, roll: torch.Tensor | None = None):
    """Batched :func:`torchrow.reference.lattice.row_cells` from :func:`prefix_sums`: inlier count
    and x sum per image row and lattice row, ``(B, H, R)`` int64 each (rows ``k = -K .. K``;
    ``ks``: these rows instead, ``(R,)`` float64). ``coef (B, L, 7)`` (``L`` lattices per
    image): ``(B, L, H, R)`` each. ``t``: :func:`_image_rows` of the height, where the caller has it.
    ``roll``: the projective spacing ``g`` of 11.3.2 per lattice, ``(B,)`` or ``(B, L)`` float64
    (``None``: equal spacing; ``g = 0`` gives the same cells).

    Each lattice row's inliers on an image row are one interval of columns, so a refit step
    reads ``2R`` prefix-sum entries per image row instead of every pixel: ``O(B H L R)``.
    """
    cum, cum_x = pre
    h, w = cum.shape[1], cum.shape[2] - 1
    per_image = coef.dim() == 2
    lat = coef.unsqueeze(1) if per_image else coef
    bsz, nl = lat.shape[:2]
    if t is None:
        t = _image_rows(h, coef.device)
    cc, dd = centre_spacing(t, lat.reshape(bsz * nl, N_COEF))  # (B L, H, 1)
    # lattice-major within an image row, so that one gather per prefix sum serves every lattice
    cc = cc.view(bsz, nl, h).transpose(1, 2).unsqueeze(3)
    dd = dd.view(bsz, nl, h).transpose(1, 2).unsqueeze(3)  # (B, H, L, 1)
    if ks is None:
        ks = torch.arange(-params.lattice_half, params.lattice_half + 1, device=coef.device, dtype=torch.float64)
    k = ks.view(1, 1, 1, -1)
    if roll is None:
        ok = dd > params.lattice_min_spacing_px
        half = params.lattice_tolerance * dd
        centre = cc + k * dd  # (B, H, L, R)
    else:
        centre, local, u = projective_rows(cc, dd, k, roll.reshape(bsz, 1, nl, 1))
        half = params.lattice_tolerance * local
        ok = (local > params.lattice_min_spacing_px) & (u > 0)
    lo, hi = centre - half, centre + half
    good = ok & torch.isfinite(lo) & torch.isfinite(hi)
    zero = torch.zeros_like(lo)
    x0 = torch.clamp(torch.floor(torch.where(good, lo, zero)) + 1, 0, w).to(torch.int64)
    x1 = torch.clamp(torch.ceil(torch.where(good, hi, zero)), 0, w).to(torch.int64)
    x1 = torch.where(good, torch.maximum(x1, x0), x0)
    nr = x0.shape[3]
    x0, x1 = x0.reshape(bsz, h, nl * nr), x1.reshape(bsz, h, nl * nr)
    cnt = torch.gather(cum, 2, x1) - torch.gather(cum, 2, x0)
    sx = torch.gather(cum_x, 2, x1) - torch.gather(cum_x, 2, x0)
    if per_image:
        return cnt, sx
    return (cnt.view(bsz, h, nl, nr).transpose(1, 2).contiguous(),
            sx.view(bsz, h, nl, nr).transpose(1, 2).contiguous())


def monomial_tables(height: int, rows: int, params: Params, straight: bool,
                    device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The cells' monomials for :func:`normal_equations` on ``height`` image rows and ``rows``
    lattice rows: every distinct ``t^a k^b`` of the basis' products ``(M, H R)`` int64, the
    basis itself ``(n, H R)`` (times ``t^0 k^0``, so among them) and the entry of ``m`` each
    product fills, ``(n n,)`` int64. They depend on the sizes only: a refit computes them once,
    not per step."""
    t = (torch.arange(height, device=device, dtype=torch.int64) - (height - 1)).view(height, 1)
    k = (torch.arange(rows, device=device, dtype=torch.int64) - params.lattice_half).view(1, rows)
    basis = params.lattice_basis(straight)
    monos = sorted({(p1 + p2, e1 + e2) for p1, e1 in basis for p2, e2 in basis})
    where = [monos.index((p1 + p2, e1 + e2)) for p1, e1 in basis for p2, e2 in basis]
    mono = torch.stack([((t**p) * (k**e)).view(height * rows) for p, e in monos])
    return mono, mono[[monos.index(f) for f in basis]], torch.tensor(where, device=device)


def cell_means(cnt: torch.Tensor, sx: torch.Tensor, params: Params) -> tuple[torch.Tensor, torch.Tensor]:
    """Section 11.3's observations from ``(B, H, R)`` int64 cells: ``occ`` bool (``n > 0``) and
    ``q = round_half_even((G * sum x) / n)`` int64 (float64 division; 0 where not occupied)."""
    occ = cnt > 0
    q = torch.round((float(params.lattice_cell_grid) * sx.to(torch.float64))
                    / torch.where(occ, cnt, torch.ones_like(cnt)).to(torch.float64))
    return occ, torch.where(occ, q.to(torch.int64), torch.zeros_like(cnt))


def roll_terms(cnt: torch.Tensor, sx: torch.Tensor, params: Params,
               phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Section 11.3.2 (:func:`torchrow.reference.lattice.roll_rhs` and ``row_moments``) from
    ``(B, H, R)`` int64 cells: ``r1 = sum q k phi`` over the basis ``phi (n, H R)`` int64
    (:func:`monomial_tables`), float64 divided by ``G``, ``(B, n)``; and per lattice row the sums of
    ``1, t, t^2, q, q^2, q t`` over its occupied cells, ``(B, R, 6)`` int64."""
    bsz, h, r = cnt.shape
    occ, q = cell_means(cnt, sx, params)
    k = torch.arange(r, device=cnt.device, dtype=torch.int64) - params.lattice_half
    qk = (q * k).view(bsz, 1, h * r)
    r1 = (qk * phi.unsqueeze(0)).sum(dim=2).to(torch.float64) / float(params.lattice_cell_grid)
    t = (torch.arange(h, device=cnt.device, dtype=torch.int64) - (h - 1)).view(1, h, 1)
    o = occ.to(torch.int64)
    moments = torch.stack([o, o * t, o * (t * t), q, q * q, q * t], dim=3).sum(dim=1)  # int64: exact in any order
    return r1, moments


def roll_choice(z0: torch.Tensor, z1: torch.Tensor, moments: torch.Tensor, params: Params,
                index: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched :func:`torchrow.reference.lattice.roll_choice`: ``z0``, ``z1`` ``(B, n)`` float64
    solutions whose entries ``index`` are ``c0, c1, d0, d1``, ``moments (B, 2K+1, 6)`` int64
    (:func:`roll_terms`). Returns ``g (B,)`` float64 and ``z0 + g z1`` ``(B, n)``. Memory: ``(B, N, n)``
    float64, ``N`` the grid's size (61 at ``lattice_roll_grid`` 30)."""
    gs = torch.tensor(params.lattice_rolls(), dtype=torch.float64, device=z0.device) / float(LATTICE_ROLL_SCALE)
    z = z0.unsqueeze(1) + gs.view(1, -1, 1) * z1.unsqueeze(1)  # (B, N, n)
    zc0, zc1, zd0, zd1 = (z[:, :, i].unsqueeze(2) for i in index)
    grid = float(params.lattice_cell_grid)
    n, t1, t2, q1, q2, qt = moments.to(torch.float64).unsqueeze(1).unbind(3)  # (B, 1, R) each
    ks = torch.arange(-params.lattice_half, params.lattice_half + 1, dtype=torch.float64, device=z0.device)
    # every row at once, (B, N, R), then summed row by row in the reference's order
    u = 1.0 + gs.view(1, -1, 1) * ks
    a = zc0 + ks * zd0
    b = zc1 + ks * zd1
    per_row = ((q2 / (grid * grid) - (2.0 * (a * q1 + b * qt)) / (grid * u))
               + (((a * a) * n + (2.0 * (a * b)) * t1) + (b * b) * t2) / (u * u))
    err = torch.zeros_like(per_row[:, :, 0])
    for j in range(per_row.shape[2]):
        err = err + per_row[:, :, j]
    best = torch.argmin(torch.where(torch.isnan(err), torch.full_like(err, float("inf")), err), dim=1)
    return gs[best], torch.gather(z, 1, best.view(-1, 1, 1).expand(-1, 1, z.shape[2])).squeeze(1)


def normal_equations(cnt: torch.Tensor, sx: torch.Tensor, params: Params, straight: bool = False,
                     tables: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched :func:`torchrow.reference.lattice.normal_equations` from ``(B, H, R)`` int64 cells.

    Returns ``m (B, n, n)`` and ``r (B, n)`` float64 (int64 sums, then converted), ``n`` = the
    size of :meth:`Params.lattice_basis` (``straight``: the straight basis of 11.3.1). An entry
    of ``m`` is the sum of one monomial ``t^a k^b`` over the occupied cells, and many entries
    share one, so each distinct monomial is summed once (18 for the cubic basis instead of 49
    entries: integer sums, the same values). ``tables``: :func:`monomial_tables` for these
    sizes (``None``: computed here). Memory: ``(B, 18, H R)`` int64.
    """
    _, h, r = cnt.shape
    occ, q = cell_means(cnt, sx, params)
    grid = params.lattice_cell_grid
    mono, phi, where = tables if tables is not None else monomial_tables(h, r, params, straight, cnt.device)
    n = phi.shape[0]
    o = occ.to(torch.int64).view(-1, 1, h * r)
    sums = (o * mono.unsqueeze(0)).sum(dim=2)  # (B, M)
    m = sums[:, where].view(-1, n, n)
    rr = (q.view(-1, 1, h * r) * phi.unsqueeze(0)).sum(dim=2)
    return m.to(torch.float64), rr.to(torch.float64) / float(grid)


def refine(pre: tuple[torch.Tensor, torch.Tensor], coef: torch.Tensor, params: Params,
           straight: tuple[bool, ...], flow: str = "sync", start: torch.Tensor | None = None,
           roll: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Batched :func:`torchrow.reference.lattice.refine` of ``L`` lattices per image at once:
    ``coef (B, L, 7)`` float64, lattice ``l`` refitted in the straight basis where
    ``straight[l]``, after up to ``lattice_iterations`` refits each. A lattice stops when it
    has too few inliers, a singular system, or cells equal to its previous step's (a fixed
    point); the loop ends once every lattice has stopped. Returns the refined ``coef (B, L, 7)``,
    its inlier counts ``(B, L, H, R)`` int64 (:func:`row_cells`) and the projective spacing ``g``
    ``(B, L)`` float64 of 11.3.2 (straight lattices search it where ``lattice_roll_grid > 0``, by
    :func:`roll_choice` on a second right-hand side of the same system; ``None`` where it is 0).
    The search adds ``(B L, 6, H, R)`` int64 moments and ``(B L, N, 7)`` float64 solutions per step
    (``N`` = ``2 lattice_roll_grid + 1``) and solves twice as many systems.

    Lattices of both bases share one loop: a straight lattice solves the curved system with its
    extra unknowns pinned to 0 (identity rows and columns), which performs the straight
    system's eliminations on the same values in the same order (the pinned rows contribute
    exact zeros), so the same bits as a separate straight refit; one loop instead of one per
    basis runs the larger of the lattices' step counts, not their sum (eager steps, and the
    nodes an exported ``Loop`` executes).
    ``flow`` (:mod:`torchrow.functional._flow`): how the end is found (eager ``"sync"``;
    ``"loop"``: one ONNX ``Loop`` in an exported graph; ``"always"``: every refit, masked);
    results never depend on it. ``start`` ``(B,)`` bool: the images whose lattices refit at all
    (``None``: every image); the others keep ``coef``. ``roll`` ``(B,)`` float64: the straight
    lattices' starting ``g`` (a warped comb's, 11.3.2; ``None``: 0)."""
    bsz, nl = coef.shape[:2]
    all_straight = all(straight)
    basis = params.lattice_basis(all_straight)
    where = params.lattice_coef_index(all_straight)
    place = torch.tensor([where.index(i) if i in where else len(where) for i in range(N_COEF)], device=coef.device)
    small = [set(params.lattice_basis(True)) if s else set(basis) for s in straight]
    pin = [[f not in sm for f in basis] for sm in small]  # (L, n)
    pinned = None
    if any(map(any, pin)):
        pinned = torch.tensor(pin, device=coef.device).unsqueeze(0).expand(bsz, nl, len(basis)).reshape(bsz * nl, -1)
        pin2 = pinned.unsqueeze(2) | pinned.unsqueeze(1)
        eye = torch.eye(len(basis), dtype=torch.float64, device=coef.device)

    searched = params.lattice_roll_grid > 0 and any(straight)
    if searched:
        # c0, c1, d0, d1 in the solution; only straight lattices move g (11.3.2)
        index = [where.index(i) for i in (0, 1, 4, 5)]
        rolled = torch.tensor(straight, device=coef.device).view(1, nl).expand(bsz, nl).reshape(bsz * nl, 1)

    def stopped(coef, cnt, sx, active, *roll):
        return ~active.any()

    # the carry holds lattices with their cells, so that the stop test precedes the solve
    def refit(coef, cnt, sx, active, *roll):
        h, r = cnt.shape[2:]
        flat_cnt, flat_sx = cnt.view(bsz * nl, h, r), sx.view(bsz * nl, h, r)
        m, rhs = normal_equations(flat_cnt, flat_sx, params, all_straight, tables)
        if pinned is not None:
            m = torch.where(pin2, eye, m)
            rhs = torch.where(pinned, torch.zeros_like(rhs), rhs)
        if searched:  # z1: the same systems with the second right-hand side, in the same operations
            r1, moments = roll_terms(flat_cnt, flat_sx, params, tables[1])
            if pinned is not None:
                r1 = torch.where(pinned, torch.zeros_like(r1), r1)
            both, singular = solve_normal(torch.cat([m, m]), torch.cat([rhs, r1]), params,
                                          None if pinned is None else torch.cat([pinned, pinned]))
            sol, z1 = both[:bsz * nl], both[bsz * nl:]
            singular = singular[:bsz * nl]
            g, moved = roll_choice(sol, z1, moments, params, index)
            sol = torch.where(rolled, moved, sol)
            g = torch.where(rolled.view(-1), g, torch.zeros_like(g))
        else:
            sol, singular = solve_normal(m, rhs, params, pinned)
        if pinned is not None:
            sol = torch.where(pinned, torch.zeros_like(sol), sol)
        active = active & ~singular.view(bsz, nl)
        if where != list(range(N_COEF)):  # a smaller basis: its unknowns to their coefficients, the others 0
            sol = torch.cat([sol, torch.zeros_like(sol[:, :1])], dim=1)[:, place]
        coef = torch.where(active.unsqueeze(2), sol.view(bsz, nl, N_COEF), coef)
        if searched:
            roll = (torch.where(active, g.view(bsz, nl), roll[0]),)
        cnt2, sx2 = row_cells(pre, coef, params, ks, t, roll[0] if searched else None)
        same = (cnt2 == cnt).flatten(2).all(dim=2) & (sx2 == sx).flatten(2).all(dim=2)
        return (coef, cnt2, sx2, active & (cnt2.sum(dim=(2, 3)) >= params.lattice_min_points) & ~same, *roll)

    t = _image_rows(pre[0].shape[1], coef.device)
    ks = torch.arange(-params.lattice_half, params.lattice_half + 1, device=coef.device, dtype=torch.float64)
    zero_roll = torch.zeros((bsz, nl), dtype=torch.float64, device=coef.device)
    if roll is not None:  # the straight lattices start from the warped comb's g, the curved ones from 0
        bent_l = torch.tensor([not s for s in straight], device=coef.device).view(1, nl)
        zero_roll = torch.where(bent_l, zero_roll, roll.view(bsz, 1).to(torch.float64))
    roll0: tuple[torch.Tensor, ...] = (zero_roll,) if searched else ()
    cnt, sx = row_cells(pre, coef, params, ks, t, zero_roll if searched else None)
    tables = monomial_tables(cnt.shape[2], cnt.shape[3], params, all_straight, coef.device)
    active = cnt.sum(dim=(2, 3)) >= params.lattice_min_points
    if start is not None:
        active = active & start.unsqueeze(1)
    out = repeat(flow, params.lattice_iterations, stopped, refit, (coef, cnt, sx, active, *roll0))
    return out[0], out[1], (out[4] if searched else None)


class LatticeStartBatch(NamedTuple):
    """:func:`lattice_start`'s result per image: the straight start ``coef (B, 7)`` float64 through
    the VP ``vp (B, 2)`` int64 the comb used, and the comb's ``spacing``, ``phase`` ``(B,)``
    int64, ``found`` ``(B,)`` bool and ``contrast`` ``(B,)`` float64 (11.2). With
    ``lattice_comb_warps`` (11.3.2) also the curved refit's start ``bent (B, 7)`` float64 and the
    straight start's projective spacing ``roll (B,)`` float64; ``None`` without (``coef`` and 0)."""

    coef: torch.Tensor
    spacing: torch.Tensor
    phase: torch.Tensor
    found: torch.Tensor
    vp: torch.Tensor
    contrast: torch.Tensor
    bent: torch.Tensor | None = None
    roll: torch.Tensor | None = None


def lattice_start(mask: torch.Tensor, vp: torch.Tensor | None, has_vp: torch.Tensor | None, params: Params,
                  prior: LatticePriorBatch | None = None, flow: str = "sync",
                  origin: torch.Tensor | None = None) -> LatticeStartBatch:
    """Section 11.2 per image: the VP (the grid search, section 6's, or ``prior.vp`` where
    ``prior.restrict``), the comb through it and the straight start of 11.3. ``params`` as
    :func:`lattice_params` gives them for the mask's size; ``flow``, ``origin`` as
    :func:`fit_lattice`."""
    bsz, _, w = mask.shape
    dev = mask.device
    counted = params.lattice_vp_origin == "sky"  # else every origin is 0: no gather of the mask
    if origin is None:
        origin = torch.zeros((bsz,), dtype=torch.int64, device=dev)
    if params.lattice_vp == "search" and prior is not None:
        windowed = torch.zeros_like(prior.restrict) if prior.windowed is None else prior.windowed
        near = prior.vp if prior.near is None else prior.near
        swept = prior.sweep is not None  # else no sequence sweeps: no such branch
        sweep = torch.full_like(prior.spacing, -1) if prior.sweep is None else prior.sweep

        def whole(mask, vp, near, sweep, origin):
            return (vp_search(mask, params, origin if counted else None),)

        def window(mask, vp, near, sweep, origin):
            return (vp_search(mask, params, origin if counted else None, near),)

        def wider(mask, vp, near, sweep, origin):  # the window and a grid height (the others' results are not kept)
            return (vp_search(mask, params, origin if counted else None, near, torch.clamp(sweep, min=0)),)

        def keep(mask, vp, near, sweep, origin):
            return (vp.clone(),)

        def search(mask, restrict, windowed, vp, near, sweep, origin):
            # sequences without a grid VP (frame 0) search the whole grid, the others their window,
            # and after a frame that was not ok a grid height too (11.7): each when some image needs it
            args = (mask, vp, near, sweep, origin)
            full = branch(flow, (~restrict & ~windowed).any(), whole, keep, args)[0]
            part = branch(flow, (~restrict & windowed & (sweep < 0)).any(), window, keep, args)[0]
            if swept:
                part = torch.where((sweep < 0).view(-1, 1), part,
                                   branch(flow, (~restrict & windowed & (sweep >= 0)).any(), wider, keep, args)[0])
            return (torch.where(restrict.view(-1, 1), vp, torch.where(windowed.view(-1, 1), part, full)),)

        # the grid search, skipped when every image is tracked (11.7)
        v = branch(flow, (~prior.restrict).any(), search,
                   lambda mask, restrict, windowed, vp, near, sweep, origin: (vp.clone(),),
                   (mask, prior.restrict, windowed, prior.vp, near, sweep, origin))[0]
    elif params.lattice_vp == "search":
        v = vp_search(mask, params, origin if counted else None)
    elif vp is None or has_vp is None:
        raise ValueError(f"lattice_vp={params.lattice_vp!r} needs section 6's vp and has_vp, got None")
    else:
        v = init_vp(vp, has_vp, w, params)
    return comb_start(mask, v, params, prior, flow)


def comb_start(mask: torch.Tensor, vp: torch.Tensor, params: Params,
               prior: LatticePriorBatch | None = None, flow: str = "sync") -> LatticeStartBatch:
    """Section 11.2's comb through ``vp (B, 2)`` int64 (:func:`comb_search`) and 11.3's starts from
    it (:func:`torchrow.reference.lattice.comb_start`: with ``lattice_comb_warps`` the comb on
    each warp too, where ``prior`` does not restrict it, one :func:`comb_search` per warp; the
    first highest contrast wins per image, a warp over the unwarped comb only by
    ``LATTICE_WARP_MARGIN``; skipped by ``flow`` where every image is restricted, a lattice
    tracker's tracked frames). The warps' combs run one after another and share one
    :func:`comb_table`: the peak memory is one :func:`comb_search`'s, the time that many times
    its."""
    h, w = mask.shape[1:]
    table = comb_table(w, params, mask.device)
    spacing, phase, found, contrast = comb_search(mask, vp, params, prior, table=table)
    den = ((h - 1) - vp[:, 1]).to(torch.float64)
    ph = phase.to(torch.float64)
    sp = spacing.to(torch.float64)
    zero = torch.zeros_like(ph)
    xv = vp[:, 0].to(torch.float64)
    coef = torch.stack([ph, (ph - xv) / den, zero, zero, sp, sp / den, zero], dim=1)
    if params.lattice_comb_warps == 0:
        return LatticeStartBatch(coef, spacing, phase, found, vp, contrast)
    free = torch.ones_like(found) if prior is None else ~prior.restrict
    known = () if prior is None else (prior.centre, prior.restrict, prior.spacing)
    # the table passes as operands, not as a closure: an exported ``If`` then reads the one copy
    flat = table.flat()

    def warps(mask, vp, free, spacing, phase, found, contrast, *rest):
        warp = torch.zeros_like(spacing)
        known, got = rest[:len(rest) - len(flat)], rest[len(rest) - len(flat):]
        own = None if not known else LatticePriorBatch(known[0], known[1], vp, known[2])  # the fields comb_search reads
        tab = _CombTable.from_flat(got)
        for j in params.lattice_warps()[1:]:
            s_j, p_j, f_j, c_j = comb_search(mask, vp, params, own, j, tab)
            bar = torch.where(warp != 0, contrast, contrast + LATTICE_WARP_MARGIN * contrast.abs())
            better = free & f_j & (~found | (c_j > bar))
            spacing, phase = torch.where(better, s_j, spacing), torch.where(better, p_j, phase)
            found, contrast = found | better, torch.where(better, c_j, contrast)
            warp = torch.where(better, torch.full_like(warp, j), warp)
        return spacing, phase, found, contrast, warp

    def none(mask, vp, free, spacing, phase, found, contrast, *rest):
        return spacing.clone(), phase.clone(), found.clone(), contrast.clone(), torch.zeros_like(spacing)

    spacing, phase, found, contrast, warp = branch(flow, free.any(), warps, none,
                                                   (mask, vp, free, spacing, phase, found, contrast, *known, *flat))
    gamma = warp.to(torch.float64) / float(LATTICE_WARP_SCALE // 2 * w)
    x0 = float(w) / 2.0
    p = phase.to(torch.float64)
    sw = spacing.to(torch.float64)
    u = 1.0 + gamma * (p - x0)
    a = (p - x0) / u
    s = sw / u
    g = gamma * s
    dd = s + g * x0
    c = x0 + a
    own = dd - g * c
    rolled = warp != 0  # elsewhere the comb's spacing and phase are those ``coef`` was built from
    start = torch.stack([c, (c - xv) / den, zero, zero, dd, (dd - g * xv) / den, zero], dim=1)
    bent = torch.stack([c, (c - xv) / den, zero, zero, own, own / den, zero], dim=1)
    return LatticeStartBatch(torch.where(rolled.unsqueeze(1), start, coef), spacing, phase, found, vp, contrast,
                             torch.where(rolled.unsqueeze(1), bent, coef), torch.where(rolled, g, zero))


def refit_lattice(mask: torch.Tensor, sky: torch.Tensor, start: LatticeStartBatch, params: Params,
                  prior: LatticePriorBatch | None = None, flow: str = "sync") -> LatticeFitBatch:
    """Sections 11.3-11.3.1 per image from :func:`lattice_start`'s ``start``: the refits of the
    green pixels of rows ``y >= sky`` (``sky (B,)``, the lattice's first row). ``params``,
    ``prior`` and ``flow`` as :func:`fit_lattice`."""
    bsz = mask.shape[0]
    h = mask.shape[1]
    coef = start.coef
    pre = prefix_sums(mask & below_horizon(sky.to(torch.int64), h, as_bool=True))
    # a tracked frame whose comb is too weak for `ok` is redone in full whatever its refits
    # give (11.4, 11.7): its refits are skipped, since a redone frame is the tracker's slowest
    go = None if prior is None else ~(prior.restrict & (start.contrast < params.lattice_min_contrast))
    is_curved = params.lattice_model == "curved"
    bent = coef if start.bent is None else start.bent
    if params.lattice_model == "auto":
        # straight and curved from the comb's starts, refined together (one loop)
        both, cells, rolls = refine(pre, torch.stack([coef, bent], dim=1), params, straight=(True, False), flow=flow,
                                    start=go, roll=start.roll)
        n_straight = cells[:, 0].sum(dim=(1, 2)).to(torch.float64)
        n_bent = cells[:, 1].sum(dim=(1, 2)).to(torch.float64)
        curved = n_bent > (1.0 + params.lattice_curve_gain) * n_straight
        coef = torch.where(curved.unsqueeze(1), both[:, 1], both[:, 0])
        cnt = torch.where(curved.view(-1, 1, 1), cells[:, 1], cells[:, 0])
        roll = torch.zeros_like(n_bent) if rolls is None else torch.where(curved, rolls[:, 1], rolls[:, 0])
    else:
        one, cells, rolls = refine(pre, (bent if is_curved else coef).unsqueeze(1), params, straight=(not is_curved,),
                                   flow=flow, start=go, roll=None if is_curved else start.roll)
        coef, cnt = one[:, 0], cells[:, 0]
        curved = torch.full((bsz,), is_curved, dtype=torch.bool, device=mask.device)
        roll = torch.zeros_like(start.contrast) if rolls is None else rolls[:, 0]
    return LatticeFitBatch(coef, start.spacing, start.phase, start.found, start.vp, cnt, start.contrast, curved, roll)


def fit_lattice(mask: torch.Tensor, sky: torch.Tensor, vp: torch.Tensor | None, has_vp: torch.Tensor | None,
                params: Params, prior: LatticePriorBatch | None = None, flow: str = "sync",
                origin: torch.Tensor | None = None) -> LatticeFitBatch:
    """Sections 11.2-11.3.1 per image (:func:`torchrow.reference.lattice.fit_lattice`):
    :func:`lattice_start`, then :func:`refit_lattice`.

    The cells (count and x sum of the inliers per image row and lattice row) are integer sums,
    so the normal equations equal the reference's bit for bit. Memory: two ``(B, H, W+1)``
    int64 prefix sums (about 40 MB each for 64 images of 320x240) besides the mask; a step's
    own temporaries are ``(B, L, H, 2K+1)`` and the normal equations' ``(B L, 18, H (2K+1))``
    int64 (``L`` = 2 lattices with ``"auto"``, else 1). ``prior``: section 11.7's (the lattice tracker);
    ``flow``: how the grid search (which tracked images skip) and :func:`refine` skip work
    (:mod:`torchrow.functional._flow`; results never depend on it). ``origin (B,)``: the VP
    grid's (:func:`vp_origin`; ``None``: zeros).
    """
    _, h, w = mask.shape
    params = lattice_params(w, h, params)  # cubic where the int64 sums allow it, else quadratic
    return refit_lattice(mask, sky, lattice_start(mask, vp, has_vp, params, prior, flow, origin), params, prior, flow)


def _span(top: torch.Tensor, height: int) -> torch.Tensor:
    """Section 11.4's denominator of a row's confidence: image rows from ``top`` down, at least 1,
    ``(B,)`` float64."""
    return torch.clamp(height - torch.clamp(top.to(torch.int64), min=0), min=1).to(torch.float64)


def row_polynomials(coef: torch.Tensor, ks: torch.Tensor, height: int,
                    roll: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batched :func:`torchrow.reference.lattice.row_polynomial`: rows ``ks`` (``(R,)`` float64) of
    the lattices ``coef (B, 7)`` as ``(a, b, c, e)``, ``(B, R)`` float64 each; ``roll (B,)`` float64:
    11.3.2's ``g`` (each divided by ``1 + g k``; ``None``: equal spacing)."""
    c0, c1, c2, c3, d0, d1, d2 = (coef[:, i].unsqueeze(1) for i in range(N_COEF))
    kv = ks.unsqueeze(0)
    yb = float(height - 1)
    slope = c1 + kv * d1
    curv = c2 + kv * d2
    three = 3.0 * c3
    a = (slope - (2.0 * curv) * yb) + three * (yb * yb)
    b = (((c0 + kv * d0) - slope * yb) + curv * (yb * yb)) - c3 * (yb * yb * yb)
    if roll is not None:  # x / 1.0 is x: g = 0 keeps the bits
        u = 1.0 + roll.unsqueeze(1) * kv
        return a / u, b / u, (curv - three * yb) / u, c3 / u
    return a, b, curv - three * yb, c3.expand_as(curv).clone()


class VisibleRows(NamedTuple):
    """:func:`visible_rows`: rows ``k = -K_v .. K_v`` as ``(B, 2 K_v + 1)`` float64 ``a, b, c, e``
    (``x = e*y**3 + c*y**2 + a*y + b``) and ``confidence``, and ``present`` bool (the rows reported)."""

    a: torch.Tensor
    b: torch.Tensor
    c: torch.Tensor
    e: torch.Tensor
    confidence: torch.Tensor
    present: torch.Tensor


def gap_offsets(params: Params, device: torch.device) -> torch.Tensor:
    """The ``2K+2`` gaps beside rows ``-K .. K``, ``k = -K-1/2 .. K+1/2`` as ``(2K+2,)`` float64
    (section 11.4's dominance: gap ``j`` lies between rows ``j-1`` and ``j``)."""
    half = params.lattice_half
    return torch.arange(2 * half + 2, device=device, dtype=torch.float64) - (half + 0.5)


def row_dominance(rows: torch.Tensor, gaps: torch.Tensor) -> torch.Tensor:
    """Section 11.4 (:func:`torchrow.reference.lattice.row_dominance`): ``(B,)`` float64, the share
    of lit cells where a row's inliers outnumber the fuller of its two gaps'.

    ``rows (B, H, 2K+1)`` int64 are the cells of rows ``-K .. K`` (:func:`row_cells`), ``gaps (B, H,
    2K+2)`` those of :func:`gap_offsets`. A cell ``(y, k)`` is lit where ``n + m > 0`` and wins where
    ``n > m``, with ``n`` the row's count and ``m`` the larger of its gaps' on image row ``y``;
    dominance = wins / max(lit, 1) (integers, one float64 division).
    """
    m = torch.maximum(gaps[:, :, :-1], gaps[:, :, 1:])
    lit = ((rows + m) > 0).sum(dim=(1, 2))
    wins = (rows > m).sum(dim=(1, 2))
    return wins.to(torch.float64) / torch.clamp(lit, min=1).to(torch.float64)


def visible_rows(mask: torch.Tensor, top: torch.Tensor, coef: torch.Tensor, found: torch.Tensor,
                 params: Params, roll: torch.Tensor | None = None) -> tuple[VisibleRows, torch.Tensor]:
    """Section 11.4 (:func:`torchrow.reference.lattice.visible_rows`): every row of the fitted
    lattices ``coef (B, 7)`` that its image shows, over the static bound ``K_v`` of
    :meth:`Params.lattice_visible_half` with a mask, and the dominance ``(B,)`` float64 of rows
    ``-K .. K`` (:func:`row_dominance`; their gaps' cells join the same pass; NaN, not computed,
    where ``lattice_min_dominance`` is 0). ``mask (B, H, W)`` bool is the
    green mask, ``top (B,)`` the first image row, ``roll (B,)`` 11.3.2's ``g`` (``None``: 0; each
    row then resolvable where its own spacing is, and only while ``1 + g k > 0``). Memory: two ``(B, H, W+1)`` int64 prefix sums
    (the fit's are gone by then) and ``(B, H, 2 K_v + 2 K + 3)`` cells."""
    _, h, w = mask.shape
    dev = mask.device
    kv = params.lattice_visible_half(w)
    half = params.lattice_half
    ks = torch.arange(-kv, kv + 1, device=dev, dtype=torch.float64)
    below = torch.arange(h, device=dev).view(1, h) >= top.to(torch.int64).view(-1, 1)  # (B, H)
    gaps = params.reads_dominance()
    cells, _ = row_cells(prefix_sums(mask & below.unsqueeze(2)), coef, params,
                         torch.cat([ks, gap_offsets(params, dev)]) if gaps else ks, roll=roll)
    cnt = cells[:, :, :2 * kv + 1]
    if gaps:
        dominance = row_dominance(cnt[:, :, kv - half:kv + half + 1], cells[:, :, 2 * kv + 1:])
    else:
        dominance = torch.full((mask.shape[0],), float("nan"), dtype=torch.float64, device=dev)
    t = (torch.arange(h, device=dev, dtype=torch.float64) - (h - 1)).view(1, h, 1)
    cc, dd = centre_spacing(t, coef)
    # a row counts as shown only where the rows are resolvable: near the VP they all converge inside the image
    if roll is None:
        centre = cc + ks.view(1, 1, -1) * dd  # (B, H, R)
        defined = below.unsqueeze(2) & (dd >= float(params.lattice_min_spacing))
    else:
        centre, local, u = projective_rows(cc, dd, ks.view(1, 1, -1), roll.view(-1, 1, 1))
        defined = below.unsqueeze(2) & (u > 0) & (local >= float(params.lattice_min_spacing))
    inside = (defined & (centre >= 0) & (centre <= w - 1)).any(dim=1)
    support = (cnt > 0).sum(dim=1)
    conf = support.to(torch.float64) / _span(top, h).unsqueeze(1)
    present = found.unsqueeze(1) & inside & (support > 0) & (conf >= params.lattice_min_confidence)
    return VisibleRows(*row_polynomials(coef, ks, h, roll), conf, present), dominance


class ImprovedStart(NamedTuple):
    """:func:`improved_start`: the green ``mask (B, H, W)`` bool of rows ``y >= top``, the
    lattice's first row ``top (B,)`` int64, the parameters the fit runs with
    (:func:`~torchrow.core.io.lattice_params` of the working size) and the comb's ``start``."""

    mask: torch.Tensor
    top: torch.Tensor
    fit_params: Params
    start: LatticeStartBatch


def row_evidence(images: torch.Tensor, sky: torch.Tensor, params: Params,
                 evidence: torch.Tensor | None = None) -> torch.Tensor:
    """The mask section 11 fits, ``bool (B, H, W)``: :func:`green_mask` (11.1), or the caller's
    ``evidence`` (11.1.1: ``bool (B, H, W)`` at the working size, on the images' device) with
    the rows above ``sky (B,)`` cleared. Never modifies ``evidence``.

    Raises ``ValueError`` if ``evidence`` is not a bool tensor of the images' ``(B, H, W)``.
    """
    if evidence is None:
        return green_mask(images, sky, params)
    check_evidence(images, evidence)
    rows = torch.arange(images.shape[2], device=images.device).view(1, -1, 1)
    return evidence.to(images.device) & (rows >= sky.view(-1, 1, 1))


def check_evidence(images: torch.Tensor, evidence: torch.Tensor) -> None:
    """Require ``evidence`` to be a bool tensor of the images' ``(B, H, W)`` (11.1.1), else ``ValueError``."""
    want = (images.shape[0], images.shape[2], images.shape[3])
    if not isinstance(evidence, torch.Tensor) or evidence.dtype != torch.bool or tuple(evidence.shape) != want:
        got = f"{evidence.dtype} {tuple(evidence.shape)}" if isinstance(evidence, torch.Tensor) else type(evidence).__name__
        raise ValueError(f"evidence: expected a bool tensor of the images' (B, H, W) {want}, got {got}")


def improved_start(images: torch.Tensor, sky: torch.Tensor, vp: torch.Tensor | None, has_vp: torch.Tensor | None,
                   params: Params, prior: LatticePriorBatch | None = None, flow: str = "sync",
                   grid_sky: torch.Tensor | None = None, evidence: torch.Tensor | None = None) -> ImprovedStart:
    """The first half of :func:`improved_rows` (sections 11.1-11.2): the mask (:func:`row_evidence`)
    and :func:`lattice_start`. Arguments as :func:`improved_rows`."""
    h, w = images.shape[2], images.shape[3]
    top = horizon_row(sky, params)
    mask = row_evidence(images, top, params, evidence)
    fparams = lattice_params(w, h, params)  # cubic where the int64 sums allow it, else quadratic
    origin = vp_origin(sky if grid_sky is None else grid_sky, h, params)
    return ImprovedStart(mask, top, fparams, lattice_start(mask, vp, has_vp, fparams, prior, flow, origin))


def improved_finish(begun: ImprovedStart, params: Params, prior: LatticePriorBatch | None = None,
                    flow: str = "sync") -> LatticeRows:
    """The second half of :func:`improved_rows` (sections 11.3-11.4): :func:`refit_lattice` from
    ``begun.start`` and :func:`lattice_rows`."""
    fit = refit_lattice(begun.mask, begun.top, begun.start, begun.fit_params, prior, flow)
    return lattice_rows(begun.mask, begun.top, fit, params)


def improved_rows(images: torch.Tensor, sky: torch.Tensor, vp: torch.Tensor | None, has_vp: torch.Tensor | None,
                  params: Params, prior: LatticePriorBatch | None = None, flow: str = "sync",
                  grid_sky: torch.Tensor | None = None, evidence: torch.Tensor | None = None) -> LatticeRows:
    """Section 11 on ``uint8 (B, 3, H, W)`` working images; ``vp (B, 2)`` float64 with ``has_vp``:
    section 6's, for ``lattice_vp="section6"`` (``None`` otherwise).

    ``sky (B,)`` is section 1's row (zeros where :meth:`Params.runs_sky` is false: not used);
    the lattice starts at :func:`horizon_row` and the VP grid at :func:`vp_origin` of
    ``grid_sky`` (``None``: ``sky``; the lattice tracker passes zero ``sky`` and its full
    searches' rows). ``prior``: section 11.7's (the lattice tracker); ``flow``: :func:`fit_lattice`'s.
    ``evidence``: the caller's row mask, ``bool (B, H, W)``, in place of the green mask (11.1.1).
    :func:`improved_start`, then :func:`improved_finish` (the lattice tracker acts between them).
    """
    return improved_finish(improved_start(images, sky, vp, has_vp, params, prior, flow, grid_sky, evidence),
                           params, prior, flow)


def lattice_rows(mask: torch.Tensor, top: torch.Tensor, fit: LatticeFitBatch, params: Params) -> LatticeRows:
    """Section 11.4 per image: the rows ``-K .. K`` of the fitted lattice ``fit``
    (:func:`fit_lattice`), their confidences and every visible row, from the green ``mask (B, H,
    W)`` bool of rows ``y >= top`` (``top (B,)``)."""
    h = mask.shape[1]
    coef, spacing, phase, found, v, cnt, contrast, curved, fit_roll = fit
    roll = fit_roll if params.lattice_roll_grid else None  # else the equally spaced rule's operations
    support = (cnt > 0).sum(dim=1).to(torch.float64)  # (B, R)
    conf = support / _span(top, h).unsqueeze(1)
    ks = torch.arange(-params.lattice_half, params.lattice_half + 1, device=mask.device, dtype=torch.float64)
    a, b, c, e = row_polynomials(coef, ks, h, roll)
    valid = found.unsqueeze(1) & (conf >= params.lattice_min_confidence)
    img_conf = conf[:, 0]
    for i in range(1, conf.shape[1]):
        img_conf = img_conf + conf[:, i]
    img_conf = img_conf / float(conf.shape[1])
    vis, dominance = visible_rows(mask, top, coef, found, params, roll)
    return LatticeRows(a, b, c, e, valid, conf, img_conf, coef, spacing, phase, found, v, contrast, curved,
                       dominance, *vis, lit=(cnt > 0).sum(dim=2),
                       roll=fit_roll)


def improved_status(rows: LatticeRows, status: torch.Tensor, params: Params) -> torch.Tensor:
    """Section 11.4 (:func:`torchrow.reference.lattice.improved_status`): ``status`` codes
    ``(B,)`` from the row rule, with ``ok`` turned ``weak`` where the comb's contrast is below
    ``lattice_min_contrast``, the image confidence below ``lattice_min_image_confidence`` or the
    rows' dominance below ``lattice_min_dominance``."""
    code = {s: i for i, s in enumerate(STATUSES)}
    strong = (rows.contrast >= params.lattice_min_contrast) & (rows.image_confidence >= params.lattice_min_image_confidence)
    if params.reads_dominance():  # else it is not computed (NaN)
        strong = strong & (rows.dominance >= params.lattice_min_dominance)
    return torch.where((status == code["ok"]) & ~strong, torch.full_like(status, code["weak"]), status)


def as_row_fits(rows: LatticeRows):
    """The lattice rows as section 7's :class:`~torchrow.functional.ransac.Rows` (all present;
    reason ``no_support`` where invalid, hypothesis -1)."""
    from torchrow.functional.ransac import REASON_CODES, Rows

    reason = torch.where(rows.valid, torch.zeros_like(rows.a, dtype=torch.int64),
                         torch.full_like(rows.a, REASON_CODES["no_support"], dtype=torch.int64))
    return Rows(rows.a, rows.b, rows.valid, reason, torch.full_like(reason, -1),
                   torch.ones_like(rows.valid))


def curve_fields(rows: LatticeRows) -> dict[str, torch.Tensor]:
    """The :class:`~torchrow.engines.detector.BatchResult` fields only the improved mode has."""
    return {"row_c": rows.c, "row_e": rows.e, "row_confidence": rows.confidence, "image_confidence": rows.image_confidence,
            **{f"lattice_{f}": getattr(rows, f"visible_{f}") for f in VisibleRows._fields}}


def improved_batch(curved: LatticeRows, status: torch.Tensor, top: torch.Tensor, params: Params, width: int,
                   height: int, timings: dict[str, float] | None = None):
    """Section 11.4's :class:`~torchrow.core.batch.BatchResult` of a batch from :func:`improved_rows`
    (the detector's and the lattice tracker's): sections 2-6's fields null, ``sky`` = ``top``."""
    from torchrow.core.batch import LINE_FIELDS, BatchResult

    rows = as_row_fits(curved)
    bsz = rows.a.shape[0]
    absent = dict.fromkeys([f for f in LINE_FIELDS if f != "n_rows"] + ["k", "bushy"])  # sections 2-6
    return BatchResult.build(
        width, height, params.theta_step, rows=rows, status=status, sky=top.to(torch.int64), veg_color=None,
        n_rows=torch.full((bsz,), rows.a.shape[1], dtype=torch.int64, device=rows.a.device),
        timings={} if timings is None else timings, **absent, **curve_fields(curved))
