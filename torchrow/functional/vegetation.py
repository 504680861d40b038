"""Batched vegetation mask and Hough input (ALGORITHM.md sections 3 and 4).

Tensor counterpart of :mod:`torchrow.reference.vegetation`; every image's result equals the
reference's bit for bit, whatever else shares the batch.

Region rule. Every neighbourhood operation after sky removal (the bushy-region erosion and
Canny) treats the rows ``y >= sky[b]`` as if they were the whole image, as the reference does
by cropping. Since ``sky`` differs per image, nothing is cropped here: the rows above the
horizon are *replaced* (by the region's top row for Sobel's replicated border, by ``True``
for the erosion's non-eroding border, by ``0`` for the magnitude that non-maximum
suppression reads) and the whole ``(B, H, W)`` batch is then processed with ordinary
full-image borders. Rows above the horizon are ``False`` in every output mask.

Canny. :func:`canny_binary` reproduces ``cv2.Canny(region*255, low, high, L2gradient=False)``
(aperture 3) of OpenCV's ``modules/imgproc/src/canny.cpp``:

* ``dx``/``dy``: 3x3 Sobel (``[-1 0 1] x [1 2 1]ᵀ`` and its transpose) in ``CV_16S`` with
  ``BORDER_REPLICATE`` (``aaa|abcd|ddd``) on all four sides of the region;
* magnitude ``m = |dx| + |dy|`` (int); for non-maximum suppression the magnitude buffer is
  bordered by **zeros** (the row above the first row, the row below the last row and the
  columns left and right of the image are 0), not replicated;
* direction by the fixed-point tangent test with ``CANNY_SHIFT = 15`` and
  ``TG22 = int(tan(22.5°)·2**15 + 0.5) = 13573``: ``Y = |dy| << 15``, ``T22 = |dx|·TG22``,
  ``T67 = T22 + (|dx| << 16)``; ``Y < T22`` -> horizontal: keep iff ``m > m[y, x-1]`` and
  ``m >= m[y, x+1]``; else ``Y > T67`` -> vertical: keep iff ``m > m[y-1, x]`` and
  ``m >= m[y+1, x]``; else diagonal with ``s = -1`` if ``dx`` and ``dy`` have opposite signs
  (``(dx ^ dy) < 0``) else ``+1``: keep iff ``m > m[y-1, x-s]`` and ``m > m[y+1, x+s]``
  (both strict). A candidate also needs ``m > low``;
* kept pixels with ``m > high`` are strong, the others weak; hysteresis grows strong edges
  into 8-connected weak pixels (the map's one-pixel frame is "never an edge").

On a 0/255 image ``|dx|`` and ``|dy|`` are multiples of 255, so every non-zero magnitude is
``>= 255``; with ``low, high < 255`` (the defaults 100, 200) every kept pixel is strong and
hysteresis adds nothing. Hysteresis is still implemented (a masked 8-neighbour dilation
iterated to a fixed point) and runs only when the thresholds admit a multiple of 255 in
``(low, high]``, a decision on the parameters alone.

Memory (``N = B*H*W`` pixels). :func:`lab` returns ``24 N`` bytes and holds at most one
chunk of ``_CHUNK_PIXELS = 2**18`` pixels of temporaries on top (int32 codes + the gathered
``(n, 3)`` float64 values, 28 B/pixel, ~7 MiB). :func:`raw_mask` and :func:`adapt_k` never
hold the LAB of the whole batch: peak is the output (``N`` bytes) plus one chunk (~8 MiB).
:func:`canny_binary` holds about twelve int8/uint8 temporaries the size of the padded grid
``(B, H+2, W+2)`` (~12 B/pixel, ~60 MB at B=64 and 320x240); :func:`remove_bushy` about
four (~4 B/pixel). :func:`hough_input` runs Canny on every image and selects per image. The
LAB table itself is the shared 400 MB memory map on the CPU (a 400 MB copy per accelerator
device, made once by :func:`torchrow.core.tables.lab_table_torch`).

Speed notes (CPU): masks are combined as 0/1 ``uint8`` views of the ``bool`` tensors, the
neighbourhood operations run as contiguous 1-D slices of a flattened padded grid, and the
large temporaries are reused in place; PyTorch's ``bool`` logic, broadcast ``where`` and
strided slices were each 5-30x slower, and every fresh multi-MB temporary costs page
faults.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from torchrow.core.params import Params
from torchrow.core.tables import lab_table_torch, rgb_code
from torchrow.functional._checks import as_u8, below_horizon, check_images, check_masks, check_params, check_rows, clamp_sky
from torchrow.functional.cielab import lab_f, linear_lut
from torchrow.functional.kernels import CANNY_SHIFT, TG22, canny_binary

__all__ = [
    "CANNY_SHIFT",
    "TG22",
    "lab",
    "raw_mask",
    "raw_fraction",
    "adapt_k",
    "min_k_table",
    "remove_bushy",
    "canny_binary",
    "density",
    "hough_input",
    "VegetationMask",
    "HoughInput",
]

# OpenCV canny.cpp fixed-point direction test (implementation constants of cv2.Canny, not
# parameters of the algorithm): tan(22.5°) in Q15, rounded half up.


# Pixels per chunk of the LAB gather (bounds the temporaries of lab/raw_mask/adapt_k).
_CHUNK_PIXELS = 1 << 18


# ----------------------------------------------------------------------------------------
# Input guards and small helpers
# ----------------------------------------------------------------------------------------

def _check_color(color: torch.Tensor, batch: int) -> None:
    if not isinstance(color, torch.Tensor) or color.shape != (batch, 3) or color.dtype != torch.uint8:
        got = (f"{color.dtype} {tuple(color.shape)}" if isinstance(color, torch.Tensor)
               else type(color).__name__)
        raise ValueError(f"color: expected a uint8 tensor of shape ({batch}, 3), got {got}")


def _check_vector(t: torch.Tensor, batch: int, name: str, allow_int: bool) -> None:
    ok = isinstance(t, torch.Tensor) and t.shape == (batch,) and t.dtype != torch.bool and (
        t.dtype.is_floating_point or (allow_int and not t.dtype.is_complex))
    if not ok:
        got = f"{t.dtype} {tuple(t.shape)}" if isinstance(t, torch.Tensor) else type(t).__name__
        kind = "an integer or float" if allow_int else "a float"
        raise ValueError(f"{name}: expected {kind} tensor of shape ({batch},), got {got}")


def _pack(images: torch.Tensor) -> torch.Tensor:
    """``uint8 (b, 3, H, W)`` -> int32 ``(b*H*W,)`` colour codes (:func:`~torchrow.core.tables.rgb_code`)."""
    return rgb_code(*(images[:, c].to(torch.int32) for c in range(3))).reshape(-1)


def _chunks(batch: int, pixels: int) -> tuple[range, int]:
    """Chunk starts over the batch and the chunk length (at most ``_CHUNK_PIXELS`` pixels)."""
    step = max(1, _CHUNK_PIXELS // max(1, pixels))
    return range(0, batch, step), step


def _box(color: torch.Tensor, k: torch.Tensor, table: torch.Tensor):
    """``(lo, hi)`` = ``(c - k, c + k)``, float64 ``(B, 1, 3)``, ``c`` = LAB of ``color``."""
    c = table.index_select(0, _pack(color.reshape(-1, 3, 1, 1)))  # (B, 3)
    kk = k.to(device=c.device, dtype=torch.float64).view(-1, 1)
    return (c - kk).unsqueeze(1), (c + kk).unsqueeze(1)


def _inside(vals: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """``all(lo <= vals <= hi)`` over the 3 channels: ``(n, P, 3)`` f64 -> 0/1 uint8 ``(n, P)``.

    ``lo``/``hi`` are ``(n, 1, 3)``. Each comparison is exactly the reference's
    ``(c - k <= lab) & (lab <= c + k)``; one channel at a time (a contiguous inner loop over
    pixels instead of a broadcast inner loop of length 3, ~5x faster on the CPU).
    """
    acc: torch.Tensor | None = None
    for ch in range(3):
        v = vals[..., ch]
        a = torch.le(lo[:, :, ch], v).view(torch.uint8)
        a.bitwise_and_(torch.le(v, hi[:, :, ch]).view(torch.uint8))
        acc = a if acc is None else acc.bitwise_and_(a)
    assert acc is not None  # three channels
    return acc


def _fraction(mask: torch.Tensor, sky: torch.Tensor) -> torch.Tensor:
    """Ones of ``mask`` in rows ``y >= sky`` divided by the number of such pixels (0 if none)."""
    _, h, w = mask.shape
    count = (as_u8(mask) & below_horizon(sky, h)).sum(dim=(1, 2), dtype=torch.int64)
    return k_fractions(count.view(-1, 1), sky, h, w).view(-1)


# ----------------------------------------------------------------------------------------
# Section 3: LAB, raw mask, adaptive k
# ----------------------------------------------------------------------------------------

def lab(images: torch.Tensor) -> torch.Tensor:
    """CIE LAB of every pixel by a gather from the shared table.

    Parameters
    ----------
    images : torch.Tensor
        ``uint8 (B, 3, H, W)`` RGB.

    Returns
    -------
    torch.Tensor
        ``float64 (B, 3, H, W)`` (L*, a*, b*), on the input's device; bit-identical to
        :func:`torchrow.core.tables.rgb_to_lab` (both read :func:`torchrow.core.tables.lab_table`).

    Notes
    -----
    Gathers chunk by chunk over the batch; peak memory is the output (24 B/pixel) plus one
    chunk of at most ``2**18`` pixels of temporaries (28 B/pixel, ~7 MiB).
    """
    check_images(images)
    b, _, h, w = images.shape
    out = torch.empty((b, 3, h, w), dtype=torch.float64, device=images.device)
    if b == 0:
        return out
    table = lab_table_torch(images.device)
    starts, step = _chunks(b, h * w)
    for b0 in starts:
        chunk = images[b0:b0 + step]
        vals = table.index_select(0, _pack(chunk)).view(chunk.shape[0], h, w, 3)
        out[b0:b0 + step] = vals.permute(0, 3, 1, 2)
    return out


def raw_mask(images: torch.Tensor, color: torch.Tensor, k: torch.Tensor,
             sky: torch.Tensor) -> torch.Tensor:
    """Section 3.2: pixels inside the inclusive LAB box around the vegetation colour.

    ``raw = (c - k <= lab) & (lab <= c + k)`` on all three channels, in float64 and in
    exactly this form (``c - k`` and ``c + k`` rounded first, as the reference), with rows
    ``y < sky[b]`` set to False.

    Parameters
    ----------
    images : torch.Tensor
        ``uint8 (B, 3, H, W)`` RGB.
    color : torch.Tensor
        ``uint8 (B, 3)`` vegetation colour (RGB) per image.
    k : torch.Tensor
        ``(B,)`` box half-width, integer or float dtype (converted to float64).
    sky : torch.Tensor
        ``int (B,)`` horizon rows (clamped to ``[0, H]``).

    Returns
    -------
    torch.Tensor
        ``bool (B, H, W)``.

    Notes
    -----
    The LAB of the batch is never held whole: peak memory is the output plus one chunk of
    at most ``2**18`` pixels (~8 MiB of temporaries).
    """
    check_images(images)
    b, _, h, w = images.shape
    _check_color(color, b)
    _check_vector(k, b, "k", allow_int=True)
    check_rows(sky, b)
    dev = images.device
    out = torch.zeros((b, h, w), dtype=torch.bool, device=dev)
    if b == 0:
        return out
    table = lab_table_torch(dev)
    lo, hi = _box(color.to(dev), k, table)
    starts, step = _chunks(b, h * w)
    for b0 in starts:
        chunk = images[b0:b0 + step]
        n = chunk.shape[0]
        vals = table.index_select(0, _pack(chunk)).view(n, h * w, 3)
        lo_c, hi_c = lo[b0:b0 + n], hi[b0:b0 + n]
        as_u8(out[b0:b0 + n]).copy_(_inside(vals, lo_c, hi_c).view(n, h, w))
    as_u8(out).bitwise_and_(below_horizon(clamp_sky(sky, h, dev), h))
    return out


def raw_fraction(raw: torch.Tensor, sky: torch.Tensor) -> torch.Tensor:
    """Section 3.3: fraction of ``raw`` pixels below the horizon.

    Parameters
    ----------
    raw : torch.Tensor
        ``bool (B, H, W)``.
    sky : torch.Tensor
        ``int (B,)`` horizon rows (clamped to ``[0, H]``).

    Returns
    -------
    torch.Tensor
        ``float64 (B,)``: ``count(raw[b, sky:]) / ((H - sky) * W)`` (one IEEE division, as
        the reference's ``float(sum) / size``); 0 when no row lies below the horizon.
    """
    check_masks(raw, "raw")
    check_rows(sky, raw.shape[0])
    return _fraction(raw, clamp_sky(sky, raw.shape[1], raw.device))


def _min_k(lab: torch.Tensor, c: torch.Tensor, k_min: int, k_max: int) -> torch.Tensor:
    """Smallest integer ``k`` in ``[k_min, k_max]`` whose box holds each pixel (``k_max + 1``: none).

    ``lab`` float64 (n, 3, P) (channel-major), ``c`` float64 (n, 3) -> int64 (n, P).
    Section 3.2's test ``c - k <= lab <= c + k`` is monotone in ``k`` (``fl(c - k)`` cannot
    grow and ``fl(c + k)`` cannot shrink as ``k`` grows), so per channel the smallest
    admitting ``k`` is a binary search of ``lab`` in the exact bounds ``fl(c + k)``
    (ascending) and ``-fl(c - k)`` (ascending; negation is exact) of every ``k``: the same
    float64 comparisons as :func:`raw_mask`, without a pass per
    ``k``. The raw mask at any ``k`` is then ``min_k <= k``. (The exported tracker step
    looks these values up in :func:`min_k_table` instead of searching.)
    """
    n, _, p = lab.shape
    ks = torch.arange(k_min, k_max + 1, device=lab.device, dtype=torch.float64)
    out = torch.zeros((n, p), dtype=torch.int64, device=lab.device)
    for ch in range(3):
        cc = c[:, ch:ch + 1]  # (n, 1)
        hi = cc + ks  # (n, K) ascending: v <= c + k
        neg_lo = -(cc - ks)  # (n, K) ascending: c - k <= v  <=>  -(c - k) >= -v
        v = lab[:, ch].contiguous()
        j_hi = torch.searchsorted(hi, v, side="left")  # first k with c + k >= v
        j_lo = torch.searchsorted(neg_lo, -v, side="left")  # first k with -(c - k) >= -v
        out = torch.maximum(out, torch.maximum(j_hi, j_lo))
    return out + k_min


_TABLE_BLOCK = 8  # colours per channel in one block of :func:`min_k_table`'s pruning (8**3 = 512)
_TABLE_MARGIN = 1e-6  # LAB units; the blocks' bounds are widened by this (values are ~1e-13 off the formula)


def _block_lab_bounds(device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds of section 3.2's LAB over each block of ``_TABLE_BLOCK**3`` colours: float64
    ``(n, n, n, 3)`` low and high, ``n = 256 // _TABLE_BLOCK``, indexed by the blocks' R, G, B.

    LAB is kornia's formula (the shared table's): X, Y and Z grow with each linearised
    channel (all matrix coefficients are positive) and the cube-root branch ``f`` is
    increasing and continuous, so over a block ``f(X), f(Y), f(Z)`` lie between their values
    at the block's lowest and highest corner, and ``L = 116 f(Y) - 16``,
    ``a = 500 (f(X) - f(Y))``, ``b = 200 (f(Y) - f(Z))`` between the combinations of those.
    """
    lin = torch.from_numpy(linear_lut()).to(device)
    n, s = 256 // _TABLE_BLOCK, _TABLE_BLOCK
    ends = []
    for first in (0, s - 1):
        v = lin[first::s]  # (n,) the blocks' lowest (or highest) byte per channel
        ends.append(lab_f(v.view(n, 1, 1), v.view(1, n, 1), v.view(1, 1, n)))
    (xl, yl, zl), (xh, yh, zh) = ends
    lo = torch.stack([116.0 * yl - 16.0, 500.0 * (xl - yh), 200.0 * (yl - zh)], dim=-1) - _TABLE_MARGIN
    hi = torch.stack([116.0 * yh - 16.0, 500.0 * (xh - yl), 200.0 * (yh - zl)], dim=-1) + _TABLE_MARGIN
    return lo, hi


def min_k_table(color: torch.Tensor, params: Params) -> torch.Tensor:
    """Section 3.2's smallest admitting ``k`` of every 24-bit colour, for each vegetation colour.

    A video fixes its vegetation colour on frame 0 (section 8), so each pixel's smallest
    admitting ``k`` (:func:`_min_k`, the quantity adaptive ``k`` counts) is a function of its
    colour alone: ``table[s, (R<<16)|(G<<8)|B] = min_k - video_k_min``, ``n_k =
    video_k_max - video_k_min + 1`` where no ``k`` admits the colour. A frame's segmentation
    is then one lookup per pixel (the exported tracker step takes this table instead of
    computing LAB in the graph). Only colours of blocks whose LAB bounds
    (:func:`_block_lab_bounds`) meet the largest box are evaluated (:func:`_min_k` on the
    shared table's LAB, so the values are the eager path's by construction); every other
    colour lies outside every box.

    Parameters
    ----------
    color : torch.Tensor
        ``uint8 (S, 3)`` vegetation colours (section 2).
    params : Params
        Uses ``video_k_min`` and ``video_k_max`` (``n_k`` must fit in uint8).

    Returns
    -------
    torch.Tensor
        ``uint8 (S, 2**24)`` on ``color``'s device: 16 MiB per colour (about 30 ms each on
        this 2-core CPU for a green crop colour).
    """
    check_params(params)
    if not (isinstance(color, torch.Tensor) and color.dim() == 2):
        got = f"{color.dtype} {tuple(color.shape)}" if isinstance(color, torch.Tensor) else type(color).__name__
        raise ValueError(f"color: expected a uint8 tensor of shape (S, 3), got {got}")
    _check_color(color, color.shape[0])
    k_min, k_max = params.video_k_min, params.video_k_max
    n_k = k_max - k_min + 1
    if n_k > 255:
        raise ValueError(f"min_k_table stores k - video_k_min in uint8: video_k_max - video_k_min must be < 255, "
                         f"got {n_k - 1}")
    dev = color.device
    table = lab_table_torch(dev)
    s = color.shape[0]
    out = torch.full((s, 1 << 24), n_k, dtype=torch.uint8, device=dev)
    if s == 0:
        return out
    lo, hi = _block_lab_bounds(dev)
    c = table.index_select(0, _pack(color.reshape(-1, 3, 1, 1))).view(s, 3)
    step = torch.arange(_TABLE_BLOCK, device=dev)
    offs = rgb_code(step.view(-1, 1, 1), step.view(1, -1, 1), step.view(1, 1, -1)).reshape(-1)
    for i in range(s):
        # blocks whose LAB range meets the box at k_max in every channel
        meet = ((hi >= c[i] - k_max) & (lo <= c[i] + k_max)).all(dim=-1)
        blocks = torch.nonzero(meet) * _TABLE_BLOCK  # (m, 3) lowest bytes
        if blocks.shape[0] == 0:
            continue
        base = rgb_code(blocks[:, 0], blocks[:, 1], blocks[:, 2])
        codes = (base.view(-1, 1) + offs.view(1, -1)).reshape(-1)
        lab = table.index_select(0, codes).t().unsqueeze(0)  # (1, 3, m * 512)
        out[i, codes] = (_min_k(lab, c[i:i + 1], k_min, k_max)[0] - k_min).to(torch.uint8)
    return out


def k_fractions(counts: torch.Tensor, sky: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Raw fraction of every ``k`` from its pixel count: float64 ``(B, n_k)``.

    ``counts`` int ``(B, n_k)`` pixels below the horizon in the raw mask of each ``k``;
    ``sky`` int64 ``(B,)`` clamped horizon rows. One IEEE division, as :func:`raw_fraction`.
    """
    size = (height - sky) * width
    frac = counts.to(torch.float64) / size.clamp(min=1).to(torch.float64).view(-1, 1)
    return torch.where((size > 0).view(-1, 1), frac, torch.zeros_like(frac))


def choose_k(frac: torch.Tensor, info0: torch.Tensor, params: Params) -> torch.Tensor:
    """Section 3.3's two loops on the fraction table ``frac`` float64 ``(B, n_k)`` (column
    ``j``: ``k = video_k_min + j``): int64 ``(B,)``.

    Static bounds (``k_start - k_min`` and ``k_max - k_min`` steps); images whose condition
    failed keep their ``k`` (the condition then stays false, so this equals the reference's
    early exits).
    """
    k_min, k_max, k_start = params.video_k_min, params.video_k_max, params.video_k_start
    info0 = info0.to(device=frac.device, dtype=torch.float64)
    shrink = params.video_shrink_above * info0
    grow = params.video_grow_below * info0
    k = torch.full(frac.shape[:1], k_start, dtype=torch.int64, device=frac.device)

    def frac_at(kk: torch.Tensor) -> torch.Tensor:
        return frac.gather(1, (kk - k_min).view(-1, 1)).view(-1)

    for _ in range(k_start - k_min):
        k = k - ((frac_at(k) > shrink) & (k > k_min)).to(torch.int64)
    for _ in range(k_max - k_min):
        k = k + ((frac_at(k) < grow) & (k < k_max)).to(torch.int64)
    return k


def adapt_k(images: torch.Tensor, color: torch.Tensor, sky: torch.Tensor, info0: torch.Tensor,
            params: Params) -> tuple[torch.Tensor, torch.Tensor]:
    """Section 3.3, video mode: adapt the LAB half-width ``k`` to the frame-0 fraction.

    Start at ``k = video_k_start``; while ``fraction > video_shrink_above * info0`` and
    ``k > video_k_min``: ``k -= 1``; then while ``fraction < video_grow_below * info0`` and
    ``k < video_k_max``: ``k += 1``. The fraction (:func:`raw_fraction`) of every integer
    ``k`` in ``[video_k_min, video_k_max]`` is computed once in one pass over the pixels
    (each pixel's smallest admitting ``k``, :func:`_min_k`, then a cumulative histogram; the
    raw mask at any ``k`` is ``min_k <= k``), then both loops run on that table
    (:func:`choose_k`).

    Parameters
    ----------
    images : torch.Tensor
        ``uint8 (B, 3, H, W)`` RGB.
    color : torch.Tensor
        ``uint8 (B, 3)`` vegetation colour.
    sky : torch.Tensor
        ``int (B,)`` horizon rows.
    info0 : torch.Tensor
        ``float64 (B,)`` raw fraction at ``k = video_k_start`` on frame 0.
    params : Params
        Uses ``video_k_start``, ``video_k_min``, ``video_k_max``, ``video_shrink_above``,
        ``video_grow_below``.

    Returns
    -------
    k : torch.Tensor
        ``int64 (B,)``.
    raw : torch.Tensor
        ``bool (B, H, W)``, :func:`raw_mask` at that ``k``.
    """
    check_params(params)
    check_images(images)
    b, _, h, w = images.shape
    _check_color(color, b)
    check_rows(sky, b)
    _check_vector(info0, b, "info0", allow_int=False)
    dev = images.device
    k_min, k_max = params.video_k_min, params.video_k_max
    n_k = k_max - k_min + 1
    skyc = clamp_sky(sky, h, dev)
    below = below_horizon(skyc, h).expand(b, h, w).reshape(b, h * w).to(torch.bool)
    kstar = torch.full((b, h * w), k_max + 1, dtype=torch.int64, device=dev)
    if b > 0:
        table = lab_table_torch(dev)
        c = table.index_select(0, _pack(color.to(dev).reshape(-1, 3, 1, 1))).view(b, 3)
        starts, step = _chunks(b, h * w)
        for b0 in starts:
            chunk = images[b0:b0 + step]
            lab = table.index_select(0, _pack(chunk)).view(chunk.shape[0], h * w, 3).transpose(1, 2)
            kstar[b0:b0 + step] = _min_k(lab, c[b0:b0 + step], k_min, k_max)
    # counts[b, j] = pixels below the horizon with kstar <= k_min + j (kstar = k_max + 1: never)
    n_bins = b * (n_k + 1)
    lin = torch.where(below, torch.arange(b, device=dev).view(-1, 1) * (n_k + 1) + (kstar - k_min), n_bins)
    counts = torch.bincount(lin.view(-1), minlength=n_bins + 1)[:n_bins].view(b, n_k + 1)[:, :n_k].cumsum(dim=1)
    k = choose_k(k_fractions(counts, skyc, h, w), info0, params)
    return k, ((kstar <= k.view(-1, 1)) & below).view(b, h, w)


# ----------------------------------------------------------------------------------------
# Section 3.4: bushy-region removal
# ----------------------------------------------------------------------------------------

def remove_bushy(raw: torch.Tensor, sky: torch.Tensor, params: Params) -> torch.Tensor:
    """Section 3.4: ``veg = raw AND NOT erode(raw)`` on the region below the horizon.

    The erosion is ``cv2.erode`` with a ``params.bushy_erode = (width, height)`` rectangle
    of ones and OpenCV's default anchor ``(width // 2, height // 2)``: for (2, 3) the kernel
    covers columns ``x-1..x`` and rows ``y-1..y+1``. Pixels outside the region (the rows
    above ``sky[b]`` and outside the image) never erode (OpenCV's default constant border
    for erosion is the maximum value).

    Parameters
    ----------
    raw : torch.Tensor
        ``bool (B, H, W)``; its rows above the horizon are ignored.
    sky : torch.Tensor
        ``int (B,)`` horizon rows (clamped to ``[0, H]``).
    params : Params
        Uses ``bushy_erode``.

    Returns
    -------
    torch.Tensor
        ``bool (B, H, W)``, False above the horizon.
    """
    check_params(params)
    check_masks(raw, "raw")
    b, h, w = raw.shape
    check_rows(sky, b)
    if b == 0:
        return torch.zeros_like(raw)
    below = below_horizon(clamp_sky(sky, h, raw.device), h)
    ew, eh = params.bushy_erode
    ax, ay = ew // 2, eh // 2
    # Outside the region is 1 (never erodes): rows above the horizon and the padding.
    src = as_u8(raw) | (below ^ 1)
    pad = F.pad(src, (ax, ew - 1 - ax, ay, eh - 1 - ay), value=1)
    hp, wp = pad.shape[1:]
    flat = pad.reshape(-1)
    # On the flattened padded grid the kernel offsets are constants dy*wp + dx; position
    # p = y*wp + x of pad holds the window whose top-left corner is pad[y, x].
    n = flat.numel() - ((eh - 1) * wp + (ew - 1))
    eroded = flat[0:n].clone()
    for dy in range(eh):
        for dx in range(ew):
            if dy or dx:
                eroded.bitwise_and_(flat[dy * wp + dx:dy * wp + dx + n])
    # concatenation, not a slice assignment into ones (an exported ScatterND, 3x slower)
    full = torch.cat([eroded, torch.ones(flat.numel() - n, dtype=torch.uint8, device=raw.device)])
    eroded = full.view(b, hp, wp)[:, 0:h, 0:w]
    veg = (eroded ^ 1).bitwise_and_(as_u8(raw)).bitwise_and_(below)
    return veg.view(torch.bool)


# ----------------------------------------------------------------------------------------
# Section 4: Canny and the Hough input
# ----------------------------------------------------------------------------------------


def density(veg: torch.Tensor, sky: torch.Tensor) -> torch.Tensor:
    """Section 4: ones of ``veg`` below the horizon / pixels below the horizon.

    Parameters
    ----------
    veg : torch.Tensor
        ``bool (B, H, W)``.
    sky : torch.Tensor
        ``int (B,)`` horizon rows.

    Returns
    -------
    torch.Tensor
        ``float64 (B,)``; 0 when no row lies below the horizon.
    """
    check_masks(veg, "veg")
    check_rows(sky, veg.shape[0])
    return _fraction(veg, clamp_sky(sky, veg.shape[1], veg.device))


def hough_input(veg: torch.Tensor, sky: torch.Tensor,
                params: Params) -> tuple[torch.Tensor, torch.Tensor]:
    """Section 4: the Hough input and the bushy flag.

    Parameters
    ----------
    veg : torch.Tensor
        ``bool (B, H, W)`` bushy-removed vegetation mask.
    sky : torch.Tensor
        ``int (B,)`` horizon rows.
    params : Params
        Uses ``bushy_ratio``, ``canny_low``, ``canny_high``.

    Returns
    -------
    hough : torch.Tensor
        ``bool (B, H, W)``: :func:`canny_binary` where ``density > bushy_ratio``, else
        ``veg`` itself (a copy).
    bushy : torch.Tensor
        ``bool (B,)``.
    """
    check_params(params)
    check_masks(veg, "veg")
    check_rows(sky, veg.shape[0])
    bushy = density(veg, sky) > params.bushy_ratio
    edges = canny_binary(veg, sky, params)
    sel = bushy.view(-1, 1, 1).view(torch.uint8)
    out = (as_u8(edges) & sel).bitwise_or_(as_u8(veg) & (sel ^ 1))
    return out.view(torch.bool), bushy


# ----------------------------------------------------------------------------------------
# Modules
# ----------------------------------------------------------------------------------------

class VegetationMask(nn.Module):
    """Sections 3.2 and 3.4 as a module: raw LAB box mask, then bushy-region removal.

    ``forward(images uint8 (B,3,H,W), color uint8 (B,3), sky int (B,), k=None)`` ->
    ``veg bool (B,H,W)``; ``k`` defaults to ``params.veg_tol`` for every image (image mode).
    """

    def __init__(self, params: Params | None = None) -> None:
        super().__init__()
        self.params = params if params is not None else Params()
        check_params(self.params)

    def forward(self, images: torch.Tensor, color: torch.Tensor, sky: torch.Tensor,
                k: torch.Tensor | None = None) -> torch.Tensor:
        check_images(images)
        if k is None:
            k = torch.full((images.shape[0],), self.params.veg_tol, dtype=torch.int64,
                           device=images.device)
        raw = raw_mask(images, color, k, sky)
        return remove_bushy(raw, sky, self.params)


class HoughInput(nn.Module):
    """Section 4 as a module: ``forward(veg bool (B,H,W), sky int (B,))`` -> ``(hough, bushy)``."""

    def __init__(self, params: Params | None = None) -> None:
        super().__init__()
        self.params = params if params is not None else Params()
        check_params(self.params)

    def forward(self, veg: torch.Tensor, sky: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return hough_input(veg, sky, self.params)
