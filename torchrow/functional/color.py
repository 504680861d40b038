"""Batched vegetation colour by greedy LAB clustering (ALGORITHM.md section 2).

Tensor counterpart of :mod:`torchrow.reference.color`: every image's result equals the
reference's bit for bit, whatever else shares the batch. Three steps:

1. :func:`distinct_colors` -- per image, the distinct colours in *walk order* (count
   descending, ties by first appearance in raster order), padded to the static bound
   ``N = H*W`` with ``valid`` False on the padding. Two stable sorts of the whole batch
   flattened to 1-D, no host sync (details in its docstring).
   :func:`trim_colors` is the one helper that drops padding columns: an explicit host sync
   (it reads the batch's largest distinct count), outside the core op.
2. :func:`cluster_colors` -- the greedy clustering as masked tensor iterations over a flat
   list of the batch's colours: each iteration, every unfinished image takes its first
   not-yet-absorbed colour as seed and absorbs every not-yet-absorbed colour of the same
   image with ``sqrt((dL*dL + da*da) + db*db) < color_tol`` (float64, that order; the
   square root is replaced by the exactly equivalent ``... < T``, see :func:`_sq_threshold`).
   Static upper bound ``N`` iterations. With ``early_exit=True`` (default) each iteration
   reads one integer back to the host (colours left): it ends the loop at 0 and lets the
   list be compacted to the colours left, so the work follows the colours not yet absorbed.
   This stage never runs under ONNX export (the vegetation colour is precomputed there);
   ``early_exit=False`` runs exactly ``N`` iterations with no sync (slow; for tracing).
3. :func:`kept_clusters` -- clusters sorted by total (descending, stable: ties keep seed
   order), the first ``n_colors`` kept, and the kept seed closest to lime ``(0, 255, 0)`` by
   integer squared RGB distance (ties: the first). :func:`vegetation_clusters` /
   :func:`vegetation_color` / :class:`VegetationColor` chain the three, in memory-bounded
   chunks of images (``chunk_pixels``).

LAB values come only from :func:`torchrow.core.tables.lab_table_torch` (the table the reference
reads through :func:`torchrow.core.tables.rgb_to_lab`), never from kornia directly.

Memory (``P`` = pixels in the batch or chunk, ``M`` = its distinct colours, ~0.2 P on CRBD):
:func:`distinct_colors` holds about a dozen int64/bool buffers of ``P`` entries and
:func:`cluster_colors` a ``(6, M)`` float64 list plus a few ``M``-sized temporaries. Peak
resident memory measured on CRBD (320x240, CPU): 16 MB for one image, ~140 MB for a batch of
64 with the default ``chunk_pixels = 2**20`` (13 images per chunk), ~300 MB for the same
batch unchunked (``chunk_pixels=None``). The LAB table is a shared 400 MB read-only memory map on the CPU
(only the pages of colours seen are read) and a 400 MB copy on an accelerator.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from torchrow.core.io import check_color
from torchrow.core.params import Params
from torchrow.core.tables import lab_table_torch, rgb_code
from torchrow.functional._checks import check_images

__all__ = [
    "color_override",
    "LIME",
    "DistinctColors",
    "ColorClusters",
    "KeptClusters",
    "distinct_colors",
    "trim_colors",
    "cluster_colors",
    "sort_clusters",
    "kept_clusters",
    "vegetation_clusters",
    "vegetation_color",
    "VegetationColor",
    "unpack_codes",
]

LIME = (0, 255, 0)

# Pixels per image above which the keys and counts are not guaranteed exact.
_MAX_PIXELS = 2**31
# Sort int32 keys in distinct_colors when they fit (speed only; tests switch it off).
_INT32_KEYS = True
# Compact the list of colours left when at most this fraction of it is still unabsorbed.
_COMPACT_AT = 0.7
# Default working-set bound of vegetation_clusters (pixels per chunk of images).
DEFAULT_CHUNK_PIXELS = 2**20


class DistinctColors(NamedTuple):
    """Distinct colours of each image in walk order, padded to a common width ``N``.

    ``codes`` int64 ``(B, N)`` = ``(R<<16)|(G<<8)|B`` (-1 on padding), ``counts`` int64
    ``(B, N)`` (0 on padding), ``valid`` bool ``(B, N)`` (a prefix of each row).
    """

    codes: torch.Tensor
    counts: torch.Tensor
    valid: torch.Tensor


class ColorClusters(NamedTuple):
    """Clusters of each image, padded to a common width ``K``.

    ``seeds`` int64 ``(B, K)`` packed seed colour (-1 on padding), ``totals`` int64 ``(B, K)``
    (0 on padding), ``valid`` bool ``(B, K)`` (a prefix of each row). The order is the one
    documented by the function that returns it (seed order from :func:`cluster_colors`,
    total descending from :func:`sort_clusters`).
    """

    seeds: torch.Tensor
    totals: torch.Tensor
    valid: torch.Tensor


class KeptClusters(NamedTuple):
    """Vegetation colour and the kept clusters (first ``n_colors`` by total, stable).

    ``color`` uint8 ``(B, 3)``; ``seeds`` uint8 ``(B, n_colors, 3)`` RGB (0 on padding);
    ``counts`` int64 ``(B, n_colors)`` cluster totals (0 on padding); ``valid`` bool
    ``(B, n_colors)``; ``chosen`` int64 ``(B,)``: position of the chosen cluster in the kept
    list (not ``index``, which would shadow ``tuple.index``).
    """

    color: torch.Tensor
    seeds: torch.Tensor
    counts: torch.Tensor
    valid: torch.Tensor
    chosen: torch.Tensor


def unpack_codes(codes: torch.Tensor) -> torch.Tensor:
    """Packed codes ``(...)`` int64 -> uint8 RGB ``(..., 3)`` (negative codes give 0, 0, 0)."""
    c = codes.clamp_min(0)
    return torch.stack([(c >> 16) & 255, (c >> 8) & 255, c & 255], dim=-1).to(torch.uint8)


def distinct_colors(images: torch.Tensor, *, sync: bool = True) -> DistinctColors:
    """Distinct colours of ``uint8 (B, 3, H, W)`` RGB images in walk order (section 2).

    Walk order: count descending, ties by first appearance in raster order, exactly as
    :func:`torchrow.reference.color.distinct_colors`. Padded to the static width ``N = H*W``.
    Use :func:`trim_colors` to drop the common padding (a host sync).

    With ``sync=True`` (default) one host sync reads the batch's number of distinct colours
    ``R`` so that the second sort below runs on the ``R`` colours only (about a fifth of the
    pixels on CRBD) instead of on every pixel; ``sync=False`` keeps static shapes throughout
    (for tracing). Both give identical results (tested).

    Two stable sorts over the whole batch flattened to one dimension (measured 2-3x faster
    than row-wise sorts of a ``(B, HW)`` tensor on the CPU), with int32 keys when they fit:

    1. keys ``(image << 24) | code``: runs are the distinct colours; stability makes the
       first element of a run the colour's first pixel in raster order;
    2. keys ``image*(HW+2) + (HW - count)`` on the first pixels (every other pixel gets
       ``image*(HW+2) + HW + 1``, after all of them): stability orders equal counts by
       first appearance, and image ``b`` fills exactly positions ``[b*HW, (b+1)*HW)``.
    """
    check_images(images)
    b, _, h, w = images.shape
    hw = h * w
    if hw >= _MAX_PIXELS:
        raise ValueError(f"images: at most {_MAX_PIXELS - 1} pixels per image, got {h}x{w}")
    dev = images.device
    m = b * hw
    i64 = torch.int64
    if m == 0:
        e = torch.zeros((b, hw), dtype=i64, device=dev)
        return DistinctColors(e - 1, e, torch.zeros((b, hw), dtype=torch.bool, device=dev))
    # int32 keys when they fit: faster sorts; only the speed depends on the key dtype.
    k1dt = torch.int32 if _INT32_KEYS and b <= 127 else i64  # (image << 24) | code < 2**31
    k2dt = torch.int32 if _INT32_KEYS and b * (hw + 2) < 2**31 else i64
    x = images.reshape(b, 3, hw).to(k1dt)  # a copy: the input is never modified
    codes = rgb_code(x[:, 0], x[:, 1], x[:, 2])  # (B, HW)
    del x
    img = torch.arange(b, device=dev, dtype=k1dt).view(b, 1)
    sv, si = torch.sort((codes | (img << 24)).reshape(m), stable=True)
    start = torch.empty(m, dtype=torch.bool, device=dev)  # first pixel of each colour (sorted order)
    start[0] = True
    torch.ne(sv[1:], sv[:-1], out=start[1:])
    run = torch.cumsum(start, dim=0)
    run -= 1
    if sync:
        del sv
        return _walk_order_compact(codes, si, start, run, b, hw)
    count = torch.bincount(run, minlength=m)[run]  # count of every sorted pixel's colour
    del run
    del sv
    # Second key, per pixel in raster order: first pixels image*(HW+2) + (HW - count), all
    # others image*(HW+2) + HW + 1.
    key = torch.arange(b, device=dev, dtype=i64).mul_(hw + 2).add_(hw + 1).view(b, 1).expand(b, hw)
    key = torch.cat([key.reshape(m), key.new_zeros(1)])  # + a dump slot
    vals = torch.div(si, hw, rounding_mode="floor").mul_(hw + 2).add_(hw).sub_(count)
    del count
    key.scatter_(0, si.masked_fill_(~start, m), vals)  # only first pixels land in [0, m)
    del vals, si, start
    sk, order = torch.sort(key[:m].to(k2dt), stable=True)  # image b -> positions [b*HW, (b+1)*HW)
    del key
    r = sk.view(b, hw).to(i64) - img.to(i64) * (hw + 2)  # HW - count, or HW + 1 off the runs
    valid = r <= hw
    out_counts = torch.where(valid, hw - r, 0)
    out_codes = torch.where(valid, codes.reshape(m)[order].view(b, hw).to(i64), -1)
    return DistinctColors(out_codes, out_counts, valid)


def _walk_order_compact(codes: torch.Tensor, si: torch.Tensor, start: torch.Tensor, run: torch.Tensor,
                        b: int, hw: int) -> DistinctColors:
    """Walk order from the runs of the first sort, sorting only the ``R`` distinct colours.

    ``si`` int64 ``(B*HW,)`` raster indices (``image*HW + pixel``) in the first sort's
    order, ``start`` bool marks each colour's first pixel there (stability: its first
    appearance in raster order), ``run`` int64 the colour's run index. The runs are compacted
    with one scatter (host sync: ``R``), then sorted by the unique key
    ``(image, HW - count, first pixel)``, which is walk order image by image.
    """
    dev = si.device
    i64 = torch.int64
    r = int(run[-1]) + 1  # host sync: distinct colours in the batch
    first = torch.empty(r + 1, dtype=i64, device=dev)
    first.scatter_(0, torch.where(start, run, r), si)  # run starts are unique; the rest -> dump
    first = first[:r]
    cnt = torch.bincount(run, minlength=r)
    img = torch.div(first, hw, rounding_mode="floor")
    pos = first - img * hw
    key = (img * (hw + 1) + (hw - cnt)) * hw + pos  # < 2**63 for B*HW < 2**31 (checked by caller)
    order = torch.sort(key).indices  # keys are unique: no stability needed
    img, cnt, first = img[order], cnt[order], first[order]
    per_image = torch.bincount(img, minlength=b)
    offset = torch.cumsum(per_image, 0) - per_image
    slot = img * hw + (torch.arange(r, device=dev) - offset[img])  # rank within its image
    out_codes = torch.full((b * hw,), -1, dtype=i64, device=dev)
    out_counts = torch.zeros(b * hw, dtype=i64, device=dev)
    out_codes[slot] = codes.reshape(-1)[first].to(i64)
    out_counts[slot] = cnt
    valid = (torch.arange(hw, device=dev) < per_image.unsqueeze(1))
    return DistinctColors(out_codes.view(b, hw), out_counts.view(b, hw), valid)


def trim_colors(colors: DistinctColors) -> DistinctColors:
    """Drop the padding columns common to the whole batch. **Host sync**: reads the largest
    number of distinct colours in the batch. Results of later stages do not change."""
    n = int(colors.valid.sum(dim=1).max()) if colors.valid.shape[0] > 0 else 0
    return DistinctColors(colors.codes[:, :n], colors.counts[:, :n], colors.valid[:, :n])


def _compact(data: torch.Tensor, keep: torch.Tensor, width: int | None, sentinel: float | int
             ) -> tuple[torch.Tensor, int]:
    """Stable partition of the columns of ``data (R, M)``: the ``keep`` columns first.

    The result has ``width`` columns if given, else exactly as many as are kept (reading that
    number is a host sync: the early exit and narrowing of :func:`cluster_colors`). Padding
    columns are zero with the image-id row (the last) set to ``sentinel``.
    """
    r, m = data.shape
    pos = torch.cumsum(keep, dim=0) - 1
    if width is None:
        width = int(pos[-1]) + 1 if m > 0 else 0  # host sync
    tgt = torch.where(keep, pos, width)
    out = torch.zeros((r, width + 1), dtype=data.dtype, device=data.device)
    out[-1].fill_(sentinel)
    out.scatter_(1, tgt.unsqueeze(0).expand(r, m), data)  # kept targets unique; rest -> dump column
    return out[:, :width], width


def _sq_threshold(tol: float) -> float:
    """The float64 ``T`` with ``sqrt(s) < tol  <=>  s < T`` for every float64 ``s >= 0``.

    IEEE ``sqrt`` is correctly rounded, hence monotonic, so ``{s : sqrt(s) < tol}`` is the
    interval ``[0, T)`` with ``T`` the smallest double whose square root is ``>= tol``;
    ``T`` is found by stepping ulps from ``tol*tol`` with Python's (correctly rounded)
    ``math.sqrt``. Comparing the squared distance with ``T`` therefore decides exactly as
    the reference's ``numpy.sqrt(...) < color_tol`` (numpy's float64 sqrt is the correctly
    rounded hardware instruction). ``torch.sqrt`` is deliberately not used: on the CPU
    build here (torch 2.13, MKL) it is *not* correctly rounded -- about 1.2% of random
    float64 inputs differ from numpy by one ulp, e.g. ``sqrt(nextafter(0.25, 0))`` gives
    0.5 instead of 0.5 - 2**-54 -- and it was also slow on small tensors with 2 threads.
    """
    t = tol * tol
    while True:
        p = math.nextafter(t, -math.inf)
        if p >= 0.0 and math.sqrt(p) >= tol:
            t = p
        else:
            break
    while not math.sqrt(t) >= tol:
        t = math.nextafter(t, math.inf)
    return t


def cluster_colors(codes: torch.Tensor, counts: torch.Tensor, valid: torch.Tensor, params: Params,
                   *, early_exit: bool = True) -> ColorClusters:
    """Greedy clustering (section 2) of colours already in walk order, batched.

    ``codes``/``counts`` int64 and ``valid`` bool, all ``(B, N)`` as returned by
    :func:`distinct_colors` (optionally trimmed). Returns the clusters in **seed order**
    (the order the walk creates them), padded to ``K`` columns: ``K`` = the batch's largest
    cluster count with ``early_exit=True``, ``K = N`` otherwise. :func:`sort_clusters` gives
    the reference's order (total descending, stable).

    Layout: the valid colours of all images are one flat list (image by image, each in walk
    order) with a ``rem`` mask of the colours not absorbed yet, so an iteration costs the
    batch's *total* number of colours in the list, with no per-image padding. Per
    iteration, each unfinished image's seed is its first remaining entry (``scatter_reduce``
    amin over the image ids); the seed and every remaining colour of the same image with
    ``(dL*dL + da*da) + db*db < T`` (equivalent to ``sqrt(...) < color_tol``, see
    :func:`_sq_threshold`) are absorbed; totals are summed per image with ``bincount``
    (integer counts in float64: exact whatever the summation order).

    ``early_exit=True``: one host read per iteration (the number of colours left) stops the
    loop at 0, and whenever at most 70% of the list is left it is compacted (stable) to
    exactly the remaining colours, so the work tracks the colours not yet absorbed.
    ``early_exit=False``: fixed width ``B*N``, exactly ``N`` iterations, no host sync.
    """
    if not (isinstance(codes, torch.Tensor) and isinstance(counts, torch.Tensor) and isinstance(valid, torch.Tensor)):
        raise TypeError("cluster_colors: codes, counts and valid must be tensors")
    if codes.dim() != 2 or codes.shape != counts.shape or codes.shape != valid.shape:
        raise ValueError(f"cluster_colors: expected codes, counts, valid of one shape (B, N); got "
                         f"{tuple(codes.shape)}, {tuple(counts.shape)}, {tuple(valid.shape)}")
    if codes.dtype != torch.int64 or counts.dtype != torch.int64 or valid.dtype != torch.bool:
        raise ValueError(f"cluster_colors: expected int64, int64, bool; got {codes.dtype}, {counts.dtype}, {valid.dtype}")
    if bool((((codes < 0) | (codes >= 1 << 24)) & valid).any()):
        raise ValueError("cluster_colors: valid codes must lie in [0, 2**24)")
    b, n = codes.shape
    dev = codes.device
    f64 = torch.float64
    thr = _sq_threshold(float(params.color_tol))
    table = lab_table_torch(dev)
    img = torch.arange(b, device=dev, dtype=torch.int64).view(b, 1).expand(b, n).reshape(b * n)
    flat = torch.stack([torch.where(valid, codes, 0).reshape(-1), counts.reshape(-1), img])
    del img
    # Valid colours first, image by image in walk order (exactly as many with early_exit).
    flat, width = _compact(flat, valid.reshape(-1), None if early_exit else b * n, b)
    lab = table[flat[0]]  # (width, 3) float64: the reference's bits
    # Rows: L, a, b, count, code, image id. float64 is exact for all of them (< 2**53).
    data = torch.cat([lab.T, flat[[1, 0, 2]].to(f64)])
    del lab
    ids = flat[2]  # image of every entry, sorted; padding = b
    del flat
    rem = ids < b  # not absorbed yet
    pos = torch.arange(width, device=dev)
    rec_code: list[torch.Tensor] = []
    rec_total: list[torch.Tensor] = []
    rec_alive: list[torch.Tensor] = []
    for _ in range(n):  # static upper bound: every colour its own cluster
        if width == 0:
            break
        # Seed of each image: its first entry not absorbed yet (entries are in walk order).
        first = torch.full((b + 1,), width, dtype=torch.int64, device=dev)
        first.scatter_reduce_(0, ids, torch.where(rem, pos, width), "amin")
        alive = first[:b] < width
        first.clamp_(max=width - 1)  # finished images (and the padding group) point anywhere
        se = torch.gather(first, 0, ids)  # each entry's seed position
        g = torch.gather(data[:3], 1, se.expand(3, width))  # (3, width): the seed's L, a, b
        d = data[:3] - g
        d.mul_(d)
        near = ((d[0] + d[1]) + d[2]) < thr  # == sqrt((dL*dL + da*da) + db*db) < color_tol
        del g, d
        if thr <= 0.0:  # color_tol == 0: only the seed itself (distance 0 is not < 0)
            hit = torch.zeros(width + 1, dtype=torch.bool, device=dev)
            hit.scatter_(0, torch.where(alive, first[:b], width), True)  # repeated True writes only
            near |= hit[:width]
        near &= rem  # (for thr > 0 the seed is near itself: its distance is exactly 0)
        # Integer counts in float64: the sum is exact whatever the summation order.
        rec_total.append(torch.bincount(ids, weights=data[3] * near, minlength=b + 1)[:b])
        rec_code.append(data[4][first[:b]])
        rec_alive.append(alive)
        rem ^= near  # near is a subset of rem
        if early_exit:
            left = int(rem.sum())  # host sync: early exit, and narrowing when worth it
            if left == 0:
                break
            if left <= _COMPACT_AT * width:
                data, width = _compact(data, rem, left, float(b))
                ids = data[5].to(torch.int64)
                rem = torch.ones(width, dtype=torch.bool, device=dev)
                pos = torch.arange(width, device=dev)
    if not rec_alive:
        e = torch.zeros((b, 0), dtype=torch.int64, device=dev)
        return ColorClusters(e - 1, e.clone(), torch.zeros((b, 0), dtype=torch.bool, device=dev))
    has = torch.stack(rec_alive, 1)
    seeds = torch.where(has, torch.stack(rec_code, 1).to(torch.int64), -1)
    totals = torch.where(has, torch.stack(rec_total, 1).to(torch.int64), 0)
    return ColorClusters(seeds, totals, has)


def sort_clusters(clusters: ColorClusters) -> ColorClusters:
    """Clusters sorted by total count, descending and **stable** (ties keep seed order);
    padding stays last. Equals the order of :func:`torchrow.reference.color.cluster_colors`."""
    seeds, totals, valid = clusters
    k = seeds.shape[1]
    # Unique keys: -total * (K+1) + position for valid clusters, after all of them the padding.
    pos = torch.arange(k, device=seeds.device, dtype=torch.int64).unsqueeze(0)
    key = torch.where(valid, -totals * (k + 1) + pos, pos + 1)
    order = torch.sort(key, dim=1).indices
    return ColorClusters(torch.gather(seeds, 1, order), torch.gather(totals, 1, order), torch.gather(valid, 1, order))


def kept_clusters(clusters: ColorClusters, params: Params) -> KeptClusters:
    """Keep the first ``n_colors`` clusters (total descending, stable) and pick the kept
    seed closest to lime by integer squared RGB distance (ties: the first)."""
    srt = sort_clusters(clusters)
    b, k = srt.seeds.shape
    m = params.n_colors
    dev = srt.seeds.device
    seeds = torch.full((b, m), -1, dtype=torch.int64, device=dev)
    totals = torch.zeros((b, m), dtype=torch.int64, device=dev)
    valid = torch.zeros((b, m), dtype=torch.bool, device=dev)
    j = min(m, k)
    seeds[:, :j], totals[:, :j], valid[:, :j] = srt.seeds[:, :j], srt.totals[:, :j], srt.valid[:, :j]
    rgb = unpack_codes(seeds)  # (B, m, 3) uint8, 0 on padding
    lime = torch.tensor(LIME, dtype=torch.int64, device=dev)
    d = rgb.to(torch.int64) - lime
    d2 = (d * d).sum(dim=-1)
    d2 = torch.where(valid, d2, torch.full_like(d2, 1 << 18))  # > 3 * 255**2
    # Unique keys, so "ties: the first" does not rest on argmin's tie rule.
    key = d2 * (m + 1) + torch.arange(m, device=dev, dtype=torch.int64)
    idx = torch.argmin(key, dim=1) if b > 0 else torch.zeros(0, dtype=torch.int64, device=dev)
    color = torch.gather(rgb, 1, idx.view(b, 1, 1).expand(b, 1, 3)).reshape(b, 3)
    rgb = torch.where(valid.unsqueeze(-1), rgb, torch.zeros_like(rgb))
    return KeptClusters(color, rgb, totals, valid, idx)


def _vegetation_clusters(images: torch.Tensor, params: Params, early_exit: bool) -> KeptClusters:
    colors = distinct_colors(images, sync=early_exit)
    if early_exit:
        colors = trim_colors(colors)
    clusters = cluster_colors(*colors, params, early_exit=early_exit)
    return kept_clusters(clusters, params)


def vegetation_clusters(images: torch.Tensor, params: Params, *, early_exit: bool = True,
                        chunk_pixels: int | None = DEFAULT_CHUNK_PIXELS) -> KeptClusters:
    """Section 2 on ``uint8 (B, 3, H, W)``: the vegetation colour and the kept clusters.

    With ``early_exit=True`` the distinct colours are trimmed (:func:`trim_colors`, one host
    sync) and the clustering narrows to the remaining colours (one host sync per iteration).

    ``chunk_pixels`` bounds the working set: the batch is cut into consecutive chunks of
    ``max(1, chunk_pixels // (H*W))`` images, each processed by the batched ops above, and
    the (static-shape) results are concatenated. Results do not depend on it (every image's
    result is independent of the rest of its batch). ``None`` processes the whole batch in
    one call. On the CPU, large buffers are fresh ``mmap`` allocations whose page faults
    (and cache misses) dominate the elementwise ops and sorts: chunks of about 2**20 pixels
    (13 images of 320x240) ran 1.5-3x faster than one batch of 64 and bound peak memory,
    while still amortising the per-iteration overhead of the clustering loop.
    """
    check_images(images)
    if chunk_pixels is not None and (not isinstance(chunk_pixels, int) or chunk_pixels < 1):
        raise ValueError(f"chunk_pixels must be None or an integer >= 1; got {chunk_pixels!r}")
    b, _, h, w = images.shape
    step = b if chunk_pixels is None else max(1, chunk_pixels // (h * w))
    if b <= step:
        return _vegetation_clusters(images, params, early_exit)
    parts = [_vegetation_clusters(images[i:i + step], params, early_exit) for i in range(0, b, step)]
    return KeptClusters(*(torch.cat(t, 0) for t in zip(*parts)))


def vegetation_color(images: torch.Tensor, params: Params, *, early_exit: bool = True,
                     chunk_pixels: int | None = DEFAULT_CHUNK_PIXELS) -> torch.Tensor:
    """Section 2: vegetation colour ``uint8 (B, 3)`` of ``uint8 (B, 3, H, W)`` RGB images."""
    return vegetation_clusters(images, params, early_exit=early_exit, chunk_pixels=chunk_pixels).color


class VegetationColor(nn.Module):
    """Module form of :func:`vegetation_color`: ``uint8 (B, 3, H, W) -> uint8 (B, 3)``.

    ``forward(images, return_clusters=True)`` returns the :class:`KeptClusters` instead.
    """

    def __init__(self, params: Params | None = None) -> None:
        super().__init__()
        self.params = params if params is not None else Params()

    def forward(self, images: torch.Tensor, return_clusters: bool = False):
        out = vegetation_clusters(images, self.params)
        return out if return_clusters else out.color

    def extra_repr(self) -> str:
        return f"color_tol={self.params.color_tol}, n_colors={self.params.n_colors}"


def color_override(color: object, batch: int, device: torch.device) -> torch.Tensor:
    """Validate a given vegetation colour (:func:`torchrow.core.io.check_color`, the reference's
    rule: integers in [0, 255], any integer dtype or a list) and broadcast it to ``uint8 (B, 3)``."""
    a = check_color(color, batched=True)
    if a.shape == (3,):
        a = np.broadcast_to(a, (batch, 3))
    if a.shape != (batch, 3):
        raise ValueError(f"veg_color must have shape (3,) or (B, 3) = ({batch}, 3), got {a.shape}")
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.uint8)).to(device)
