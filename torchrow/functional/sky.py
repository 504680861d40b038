"""Batched sky removal (ALGORITHM.md section 1), bit-identical to :mod:`torchrow.reference.sky`.

Every neighbourhood operation reproduces the OpenCV call of the reference exactly, border rule
included, for every image size down to ``1 x 1``:

* :func:`box_blur` = ``cv2.blur`` on uint8: the exact integer window sum divided with
  OpenCV's own fixed-point rule (round half up for the spec's 9 x 3 box),
  ``BORDER_REFLECT_101``;
* :func:`median_blur` = ``cv2.medianBlur``: ``BORDER_REPLICATE`` (medianBlur ignores the
  default border and always replicates), exact median through a min/max selection network;
* :func:`laplacian` = ``cv2.Laplacian(x, cv2.CV_8U, ksize=1)``: kernel
  ``[[0,1,0],[1,-4,1],[0,1,0]]``, ``BORDER_REFLECT_101``, saturated to ``0..255``;
* :func:`erode_rect` = ``cv2.erode`` with a rectangle of ones and OpenCV's default anchor and
  border (pixels outside the image never erode).

``BORDER_REFLECT_101`` is OpenCV's ``borderInterpolate``: ``dcb|abcd|cba`` reflected again
and again when the pad is wider than the image (period ``2 (n - 1)``), and ``0`` (that is,
replicate) on a dimension of length 1. ``torch.nn.functional.pad(mode="reflect")`` covers
neither case, so the border strips here are ``index_select``-ed with such an index table.

All functions take and return tensors on any device, use torch operations only (no
``.item()``, no ``nonzero``, no loop over images) and leave their inputs unmodified. The
composed stages (:func:`horizon_mask`, :func:`sky_mask`, :func:`sky_row`) run over chunks of
whole images whose size depends on the input shape only (:data:`SKY_CHUNK_PIXELS_CPU`: a
few images at a time on the CPU, so that the intermediates stay in cache: 1.8 times faster
than the whole batch of 64 CRBD images at once; :data:`SKY_CHUNK_PIXELS` elsewhere, to
bound memory).
Images never influence each other, so the chunking cannot change a result.
"""

from __future__ import annotations

import functools

import torch
from torch import nn

from ..params import Params
from ._checks import check_images

__all__ = [
    "gray",
    "box_blur",
    "median_blur",
    "laplacian",
    "erode_rect",
    "column_median",
    "horizon_mask",
    "sky_mask",
    "sky_row",
    "SkyRow",
]

#: Padded pixels handled per chunk by :func:`median_blur` on the CPU (small enough for the
#: ~30 uint8 temporaries of a chunk to stay in cache) and on other devices (few, large
#: kernels). Peak extra memory is about 30 bytes per chunk pixel: ~4 MB / ~250 MB.
MEDIAN_CHUNK_PIXELS_CPU = 1 << 17
MEDIAN_CHUNK_PIXELS = 1 << 23
#: Pixels (images x H x W, at least one image) per chunk of the composed stages on the CPU and
#: on other devices. Peak memory is about 40 bytes per chunk pixel (~20 MB / ~670 MB).
SKY_CHUNK_PIXELS_CPU = 1 << 19
SKY_CHUNK_PIXELS = 1 << 24

# OpenCV's COLOR_RGB2GRAY fixed-point weights (15-bit, OpenCV 4.6 and 5.0).
_GRAY_R, _GRAY_G, _GRAY_B, _GRAY_SHIFT = 9798, 19235, 3735, 15
# OpenCV's uint8 box filter: ushort sums and 23-bit fixed-point division up to this area.
_BLUR_SHIFT, _BLUR_FIXED_MAX_AREA = 23, 256


# ----------------------------------------------------------------------------------------------
# input guards and border tables
# ----------------------------------------------------------------------------------------------
def _check_planes(x: torch.Tensor, name: str, dtypes: tuple[torch.dtype, ...] = (torch.uint8,)) -> None:
    """Require a ``(B, H, W)`` tensor with ``H, W >= 1`` (B may be 0) of one of ``dtypes``."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor (B, H, W), got {type(x).__name__}")
    if x.dim() != 3 or x.shape[1] < 1 or x.shape[2] < 1:
        raise ValueError(f"{name}: expected shape (B, H, W) with H, W >= 1, got {tuple(x.shape)}")
    if x.dtype not in dtypes:
        want = " or ".join(str(d) for d in dtypes)
        raise ValueError(f"{name}: expected dtype {want}, got {x.dtype}")


def _check_ksize(ksize: tuple[int, int], name: str) -> tuple[int, int]:
    ok = (isinstance(ksize, (tuple, list)) and len(ksize) == 2
          and all(isinstance(k, int) and not isinstance(k, bool) and k >= 1 for k in ksize))
    if not ok:
        raise ValueError(f"{name}: expected a (width, height) pair of integers >= 1, got {ksize!r}")
    return int(ksize[0]), int(ksize[1])


def _border_index(n: int, before: int, after: int, mode: str, device: torch.device) -> torch.Tensor:
    """OpenCV ``borderInterpolate`` for positions ``-before .. n - 1 + after`` of a length-``n`` axis.

    ``mode`` is ``"reflect101"`` (``BORDER_REFLECT_101``: reflected about the edge pixels,
    repeatedly when the pad exceeds the axis; every position maps to 0 when ``n == 1``) or
    ``"replicate"`` (``BORDER_REPLICATE``). Returns int64 ``(before + n + after,)``.
    """
    p = torch.arange(-before, n + after, device=device, dtype=torch.int64)
    if mode == "replicate" or n == 1:
        return p.clamp(0, n - 1)
    if mode != "reflect101":  # pragma: no cover - internal
        raise ValueError(mode)
    period = 2 * (n - 1)
    p = torch.remainder(p, period)
    return torch.where(p >= n, period - p, p)


def _pad(x: torch.Tensor, top: int, bottom: int, left: int, right: int, mode: str) -> torch.Tensor:
    """Pad the last two dimensions of ``x`` with an OpenCV border rule (see :func:`_border_index`).

    Only the border strips are gathered; the body is copied once by ``torch.cat``.
    """
    for dim, before, after in ((-2, top, bottom), (-1, left, right)):
        if before or after:
            n = x.shape[dim]
            idx = _border_index(n, before, after, mode, x.device)
            parts = [x.index_select(dim, idx[:before]), x, x.index_select(dim, idx[before + n:])]
            x = torch.cat(parts, dim=dim)
    return x


# ----------------------------------------------------------------------------------------------
# 1.1 gray
# ----------------------------------------------------------------------------------------------
def gray(images: torch.Tensor) -> torch.Tensor:
    """OpenCV RGB->gray on uint8: ``(9798 R + 19235 G + 3735 B + 16384) >> 15``.

    Equals ``cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)`` per image (section 1.1; *fix*: RGB order).

    Parameters
    ----------
    images : torch.Tensor
        uint8 ``(B, 3, H, W)`` RGB.

    Returns
    -------
    torch.Tensor
        uint8 ``(B, H, W)`` on the device of ``images``.

    Raises
    ------
    ValueError
        On a wrong shape or dtype.
    """
    check_images(images)
    g = images[:, 0].to(torch.int32).mul_(_GRAY_R)
    g.add_(images[:, 1].to(torch.int32).mul_(_GRAY_G))
    g.add_(images[:, 2].to(torch.int32).mul_(_GRAY_B))
    g.add_(1 << (_GRAY_SHIFT - 1))
    return g.bitwise_right_shift_(_GRAY_SHIFT).to(torch.uint8)


# ----------------------------------------------------------------------------------------------
# 1.2 blur, median, Laplacian
# ----------------------------------------------------------------------------------------------
def _window_sum(x: torch.Tensor, size: int, dim: int) -> torch.Tensor:
    """Sums of ``size`` consecutive entries along ``dim`` (the output is ``size - 1`` shorter).

    Doubling: ``P_2k[y] = P_k[y] + P_k[y + k]``, and the window is the sum of the ``P_k`` of
    the binary digits of ``size`` at increasing offsets, ``log2(size) + popcount(size)``
    additions instead of ``size - 1``. The caller picks a dtype that holds ``size * max(x)``.
    """
    n = x.shape[dim] - size + 1
    parts = []
    p, k, offset, rem = x, 1, 0, size
    while True:
        if rem & 1:
            parts.append(p.narrow(dim, offset, n))
            offset += k
        rem >>= 1
        if not rem:
            break
        m = p.shape[dim] - k
        p = p.narrow(dim, 0, m) + p.narrow(dim, k, m)
        k *= 2
    out = parts[0].clone() if len(parts) == 1 else parts[0] + parts[1]
    for part in parts[2:]:
        out += part
    return out


def _window_min(x: torch.Tensor, size: int, dim: int) -> torch.Tensor:
    """Minima of ``size`` consecutive entries along ``dim`` (the output is ``size - 1`` shorter).

    Sparse table: ``M_2k[y] = min(M_k[y], M_k[y + k])`` up to the largest ``k <= size``, then
    ``min(M_k[y], M_k[y + size - k])`` (the two windows overlap, which a minimum allows).
    """
    n = x.shape[dim] - size + 1
    p, k = x, 1
    while 2 * k <= size:
        m = p.shape[dim] - k
        p = torch.minimum(p.narrow(dim, 0, m), p.narrow(dim, k, m))
        k *= 2
    if k == size:
        return p.narrow(dim, 0, n).clone() if k == 1 else p
    return torch.minimum(p.narrow(dim, 0, n), p.narrow(dim, size - k, n))


def _blur_divisor(area: int) -> tuple[int, int]:
    """OpenCV's fixed-point division by ``area`` for uint8 box filters of ``area <= 256``.

    ``ColumnSum<ushort, uchar>`` (``box_filter.simd.hpp``) computes
    ``((s + delta) * scale) >> 23`` with ``scale = floor(2**23 / area)`` and
    ``delta = area // 2 + 1`` when the dropped fraction is below 0.5, else
    ``scale = floor(2**23 / area) + 1`` and ``delta = area // 2``. Returns ``(delta, scale)``.
    """
    scalef = float(1 << _BLUR_SHIFT) / area
    scale = int(scalef // 1)
    delta = area // 2
    if scalef - scale < 0.5:
        delta += 1
    else:
        scale += 1
    return delta, scale


def _blur_table(area: int, device: torch.device) -> torch.Tensor:
    """uint8 ``(255 * area + 1,)``: ``cv2.blur``'s output for every window sum (see :func:`box_blur`)."""
    s = torch.arange(255 * area + 1, dtype=torch.int64, device=device)
    if area <= _BLUR_FIXED_MAX_AREA:
        delta, scale = _blur_divisor(area)
        out = ((s + delta) * scale) >> _BLUR_SHIFT
    else:
        inv = torch.tensor(1.0 / area, dtype=torch.float32, device=device)
        out = torch.round(s.to(torch.float32) * inv)
    return out.clamp_(0, 255).to(torch.uint8)


def box_blur(gray: torch.Tensor, ksize: tuple[int, int]) -> torch.Tensor:
    """Normalised box filter, equal to ``cv2.blur(gray, ksize)`` on uint8 (section 1.2).

    The window of ``w x h`` pixels has OpenCV's default anchor (column offsets
    ``-(w // 2) .. w - 1 - w // 2``, same for rows); the border is ``BORDER_REFLECT_101``
    (repeated reflection on axes shorter than the pad, replicate on a length-1 axis). The
    exact integer window sum ``s`` is divided as OpenCV does:

    * ``area = w * h <= 256``: OpenCV's fixed point ``((s + delta) * scale) >> 23``
      (:func:`_blur_divisor`), saturated to 255. For the spec's 9 x 3 box this equals
      round-half-up ``(s + 13) // 27`` for every possible sum (checked exhaustively in the
      tests). For a power-of-two area it is *not* a rounding of ``s / area``: OpenCV adds one
      too many (``(s + area/2 + 1) // area``: a black image blurred with a 2 x 1 box gives 1);
      this is reproduced;
    * ``area > 256``: ``round_half_even(float32(s) * float32(1 / area))`` (OpenCV's SIMD path);
    * ``area == 1``: a copy.

    The sums are accumulated in int16 (int32 for ``area > 128``) by doubling and the division
    is a lookup in a ``255 * area + 1`` entry table built with the rule above.

    Known OpenCV deviation not reproduced: with ``area == 2`` and both pixels 255, OpenCV's
    scalar tail loop (the last ``W mod 16`` or so columns, depending on the CPU's SIMD
    width) truncates 256 to 0 instead of saturating; this returns 255 everywhere.

    Parameters
    ----------
    gray : torch.Tensor
        uint8 ``(B, H, W)``.
    ksize : tuple of int
        ``(width, height)`` of the box, as ``cv2.blur``'s ``ksize``.

    Returns
    -------
    torch.Tensor
        uint8 ``(B, H, W)``.
    """
    _check_planes(gray, "gray")
    kw, kh = _check_ksize(ksize, "ksize")
    area = kw * kh
    if area == 1:
        return gray.clone()
    ax, ay = kw // 2, kh // 2
    acc = torch.int16 if 255 * area <= torch.iinfo(torch.int16).max else torch.int32
    x = _pad(gray, ay, kh - 1 - ay, ax, kw - 1 - ax, "reflect101").to(acc)
    s = _window_sum(_window_sum(x, kw, -1), kh, -2)  # exact window sums, (B, H, W)
    table = _blur_table(area, gray.device)  # the division, looked up
    return table.index_select(0, s.reshape(-1).to(torch.int32)).view(s.shape)


def _batcher_pairs(n: int, min_block: int = 1) -> list[tuple[int, int]]:
    """Comparators of Batcher's odd-even merge sort on ``n`` (a power of 2) wires.

    Stages that only sort within blocks of ``min_block`` wires are left out (the caller
    provides blocks that are sorted already).
    """
    pairs = []
    p = 1
    while p < n:
        if p >= min_block:
            k = p
            while k >= 1:
                for j in range(k % p, n - k, 2 * k):
                    for i in range(min(k, n - j - k)):
                        if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                            pairs.append((i + j, i + j + k))
                k //= 2
        p *= 2
    return pairs


def _select_program(wires: list, pairs: list[tuple[int, int]], outputs: list[int]) -> tuple[list, list]:
    """Prune a comparator network to the min/max operations that the ``outputs`` wires need.

    ``wires`` holds input names (``None`` = a constant known to be >= every input, which a
    comparator passes through without an operation). Returns ``(ops, results)``: ``ops`` a
    list of ``(kind, a, b, out)`` with ``kind`` in ``{"min", "max"}`` over value names (inputs
    keep their names, intermediate values are ``("v", n)``), and ``results`` the value name
    of each output wire.
    """
    wires = list(wires)
    raw = []  # (a, b, lo_name, hi_name)
    counter = 0
    for i, j in pairs:
        a, b = wires[i], wires[j]
        if b is None:
            continue  # (a, MAX): already in order
        if a is None:
            wires[i], wires[j] = b, None
            continue
        lo, hi = ("v", counter), ("v", counter + 1)
        counter += 2
        raw.append((a, b, lo, hi))
        wires[i], wires[j] = lo, hi
    results = [wires[o] for o in outputs]
    needed = {r for r in results if r is not None}
    ops = []
    for a, b, lo, hi in reversed(raw):
        use_lo, use_hi = lo in needed, hi in needed
        if not (use_lo or use_hi):
            continue
        if use_lo:
            ops.append(("min", a, b, lo))
        if use_hi:
            ops.append(("max", a, b, hi))
        needed.update((a, b))
    ops.reverse()
    return ops, results


def _pow2(n: int) -> int:
    p = 1
    while p < n:
        p *= 2
    return p


def _merge_pairs(n_blocks: int, block: int) -> list[tuple[int, int]]:
    """Batcher comparators merging ``n_blocks`` (a power of 2) sorted blocks of ``block`` wires."""
    return _batcher_pairs(n_blocks * block, min_block=block)


@functools.lru_cache(maxsize=None)
def _median_programs(k: int) -> tuple:
    """Selection programs for the median of a ``k x k`` window (``k`` odd, ``>= 3``).

    1. ``col``: sort every vertical run of ``k`` pixels (inputs ``("r", i)``; outputs in
       ascending order). Computed once per padded column, shared by the ``k`` windows
       containing it.
    2. ``pair``: merge two horizontally adjacent sorted runs (inputs ``("a", i)``,
       ``("b", i)``) into ``2k`` sorted values, shared by the windows containing both.
    3. ``win``: from the ``k // 2`` merged pairs of a window (inputs ``("p", j, i)``) and its
       last sorted run (inputs ``("c", i)``), the element of rank ``k*k // 2``: the pairs
       are merged as far as ranks ``r - k .. r`` need, then a min-of-max over the ``k + 1``
       ways of splitting the ``r + 1`` smallest between them and the run.

    The networks are Batcher odd-even merge (sort) networks padded with ``+inf`` wires and
    pruned to the ``min``/``max`` operations their outputs need (:func:`_select_program`):
    exact for any totally ordered values. For ``k = 5``: 18 + 26 + 46 operations.
    """
    nc = _pow2(k)
    col = _select_program([("r", i) for i in range(k)] + [None] * (nc - k), _batcher_pairs(nc),
                          list(range(k)))
    pad = [None] * (nc - k)
    wires = [("a", i) for i in range(k)] + pad + [("b", i) for i in range(k)] + pad
    pair = _select_program(wires, _merge_pairs(2, nc), list(range(2 * k)))
    m = k // 2
    npair = _pow2(2 * k)
    nblocks = _pow2(m)
    wires = []
    for j in range(nblocks):
        wires += ([("p", j, i) for i in range(2 * k)] + [None] * (npair - 2 * k)) if j < m else [None] * npair
    # rank r of (A = the m merged pairs, k*k - k sorted values) united with (C = the last
    # sorted run): min over i of max(A[r - i], C[i - 1]), i = 0..k taken from C (the
    # largest of any r + 1 smallest-first picks bounds the rank-r value, the true split
    # attains it), so only ranks r - k .. r of A are needed.
    r = (k * k) // 2
    ops, a_ranks = _select_program(wires, _merge_pairs(nblocks, npair), list(range(r - k, r + 1)))
    ops = list(ops)
    best = a_ranks[k]  # i = 0: A[r]
    for i in range(1, k + 1):
        t, nxt = ("v", 1_000_000 + 2 * i), ("v", 1_000_001 + 2 * i)
        ops.append(("max", a_ranks[k - i], ("c", i - 1), t))
        ops.append(("min", best, t, nxt))
        best = nxt
    win = (ops, [best])
    return col, pair, win


def _run_program(ops, env: dict) -> dict:
    """Run a min/max program on the tensors of ``env`` (value name -> tensor); returns ``env``."""
    last_use: dict = {}
    for idx, (_, a, b, _) in enumerate(ops):
        last_use[a] = idx
        last_use[b] = idx
    for idx, (kind, a, b, out) in enumerate(ops):
        va, vb = env[a], env[b]
        env[out] = torch.minimum(va, vb) if kind == "min" else torch.maximum(va, vb)
        for name in (a, b):  # free intermediates after their last use (bounded memory)
            if last_use.get(name) == idx and name[0] == "v":
                env.pop(name, None)
    return env


def _median_rows(p: torch.Tensor, k: int, h: int, w: int) -> torch.Tensor:
    """Median of the ``k x k`` windows of a padded ``(B, h + k - 1, w + k - 1)`` slab -> ``(B, h, w)``."""
    (col_ops, col_out), (pair_ops, pair_out), (win_ops, win_out) = _median_programs(k)
    m = k // 2
    env = _run_program(col_ops, {("r", i): p[:, i:i + h, :] for i in range(k)})
    cols = [env[name] for name in col_out]  # ascending vertical ranks, (B, h, w + k - 1)
    wp = w + k - 2  # pairs of adjacent padded columns
    env = {("a", i): c[:, :, 0:wp] for i, c in enumerate(cols)}
    env.update({("b", i): c[:, :, 1:wp + 1] for i, c in enumerate(cols)})
    env = _run_program(pair_ops, env)
    pairs = [env[name] for name in pair_out]  # ascending ranks of column pairs, (B, h, wp)
    env = {("p", j, i): q[:, :, 2 * j:2 * j + w] for j in range(m) for i, q in enumerate(pairs)}
    env.update({("c", i): c[:, :, 2 * m:2 * m + w] for i, c in enumerate(cols)})
    env = _run_program(win_ops, env)
    return env[win_out[0]]


def median_blur(x: torch.Tensor, k: int = 5) -> torch.Tensor:
    """Median filter of a ``k x k`` window, equal to ``cv2.medianBlur(x, k)`` (section 1.2).

    ``cv2.medianBlur`` always uses ``BORDER_REPLICATE``; so does this. The median is exact: a
    selection network of ``torch.minimum``/``torch.maximum`` operations (each vertical run of
    ``k`` pixels is sorted once and shared by the ``k`` windows that contain it, adjacent
    sorted runs are merged in pairs, and a pruned Batcher merge network selects rank
    ``k**2 // 2``: 90 ``minimum``/``maximum`` operations per pixel for ``k = 5``). ``k == 1``
    is a copy.

    Parameters
    ----------
    x : torch.Tensor
        uint8 ``(B, H, W)``.
    k : int
        Odd aperture, ``>= 1`` (``cv2.medianBlur``'s ``ksize``).

    Returns
    -------
    torch.Tensor
        uint8 ``(B, H, W)``.

    Notes
    -----
    Memory is bounded whatever the batch size: the work runs in chunks of whole images (or
    of row slabs of one image, when an image is larger than a chunk) of at most
    ``N`` = :data:`MEDIAN_CHUNK_PIXELS_CPU` (CPU) or :data:`MEDIAN_CHUNK_PIXELS` (other
    devices) padded pixels, at least one row. A chunk's temporaries are about
    ``3 * k + 15`` uint8 planes of its size, so the peak extra memory is about
    ``30 * N`` bytes for ``k = 5`` (~4 MB on the CPU, ~250 MB elsewhere), plus the
    uint8 ``(B, H + k - 1, W + k - 1)`` padded input and the output.
    """
    _check_planes(x, "x")
    if not (isinstance(k, int) and not isinstance(k, bool) and k >= 1 and k % 2 == 1):
        raise ValueError(f"k: expected an odd integer >= 1 (median aperture), got {k!r}")
    if k == 1:
        return x.clone()
    b, h, w = x.shape
    r = k // 2
    p = _pad(x, r, r, r, r, "replicate")
    out = torch.empty_like(x)
    if b == 0:
        return out
    budget = MEDIAN_CHUNK_PIXELS_CPU if x.device.type == "cpu" else MEDIAN_CHUNK_PIXELS
    row_px = w + 2 * r
    image_px = (h + 2 * r) * row_px
    if image_px <= budget:
        nb, rows = max(1, budget // image_px), h
    else:
        nb, rows = 1, max(1, budget // row_px - 2 * r)
    for b0 in range(0, b, nb):  # static bounds: they depend on the shape only
        b1 = min(b, b0 + nb)
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            out[b0:b1, y0:y1] = _median_rows(p[b0:b1, y0:y1 + 2 * r], k, y1 - y0, w)
    return out


def laplacian(x: torch.Tensor) -> torch.Tensor:
    """``cv2.Laplacian(x, cv2.CV_8U, ksize=1)`` (section 1.2).

    Kernel ``[[0, 1, 0], [1, -4, 1], [0, 1, 0]]`` with ``BORDER_REFLECT_101`` (a length-1 axis
    replicates, so it adds nothing), saturated to ``0..255`` (negative responses become 0).

    Parameters
    ----------
    x : torch.Tensor
        uint8 ``(B, H, W)``.

    Returns
    -------
    torch.Tensor
        uint8 ``(B, H, W)``.
    """
    _check_planes(x, "x")
    h, w = x.shape[1], x.shape[2]
    p = _pad(x, 1, 1, 1, 1, "reflect101").to(torch.int16)
    c = p[:, 1:h + 1, 1:w + 1]
    lap = p[:, 0:h, 1:w + 1] + p[:, 2:h + 2, 1:w + 1] + p[:, 1:h + 1, 0:w] + p[:, 1:h + 1, 2:w + 2] - 4 * c
    return lap.clamp_(0, 255).to(torch.uint8)


# ----------------------------------------------------------------------------------------------
# 1.3 erosion, 1.4 column median
# ----------------------------------------------------------------------------------------------
def erode_rect(mask: torch.Tensor, ksize: tuple[int, int]) -> torch.Tensor:
    """``cv2.erode(mask, numpy.ones((h, w), numpy.uint8))`` with OpenCV's defaults (section 1.3).

    The output pixel is the minimum over the ``w x h`` rectangle at OpenCV's default anchor:
    columns ``x - w // 2 .. x - w // 2 + w - 1``, rows likewise. Pixels outside the image
    never erode (OpenCV's ``BORDER_CONSTANT`` with ``morphologyDefaultBorderValue()``).

    Parameters
    ----------
    mask : torch.Tensor
        bool or uint8 ``(B, H, W)`` (for uint8 this is grey-level erosion, exact).
    ksize : tuple of int
        ``(width, height)`` of the rectangle.

    Returns
    -------
    torch.Tensor
        ``(B, H, W)`` of the dtype of ``mask``.
    """
    _check_planes(mask, "mask", (torch.bool, torch.uint8))
    kw, kh = _check_ksize(ksize, "ksize")
    fill = 1 if mask.dtype == torch.bool else 255  # the border value: never erodes
    x = mask.to(torch.uint8)
    for dim, k in ((2, kw), (1, kh)):
        if k == 1:
            continue
        shape_b, shape_a = list(x.shape), list(x.shape)
        shape_b[dim], shape_a[dim] = k // 2, k - 1 - k // 2
        xp = torch.cat([torch.full(shape_b, fill, dtype=torch.uint8, device=x.device), x,
                        torch.full(shape_a, fill, dtype=torch.uint8, device=x.device)], dim=dim)
        x = _window_min(xp, k, dim)
    if mask.dtype == torch.bool:
        return x.to(torch.bool)
    return x.clone() if x.data_ptr() == mask.data_ptr() else x.contiguous()


def column_median(m: torch.Tensor, length: int) -> torch.Tensor:
    """Median filter of odd ``length`` down each column with zero padding, for 0/1 masks.

    Equals ``scipy.signal.medfilt`` / :func:`torchrow.reference.sky.column_median` on every
    column **for binary input only** (bool, or uint8 holding only 0 and 1, as section 1.4
    uses it): the filtered value is 1 iff the window (zeros outside the image) holds at
    least ``length // 2 + 1`` ones (window sums by doubling). Other uint8 values give
    meaningless results (every non-zero value counts as a one).

    Parameters
    ----------
    m : torch.Tensor
        bool or uint8 (0/1) ``(B, H, W)``.
    length : int
        Odd window length, ``>= 1``.

    Returns
    -------
    torch.Tensor
        ``(B, H, W)`` of the dtype of ``m``, values 0/1.
    """
    _check_planes(m, "m", (torch.bool, torch.uint8))
    if not (isinstance(length, int) and not isinstance(length, bool) and length >= 1 and length % 2 == 1):
        raise ValueError(f"length: expected an odd integer >= 1, got {length!r}")
    b, h, w = m.shape
    half = length // 2
    acc = torch.uint8 if length <= 255 else torch.int32
    zeros = torch.zeros((b, half, w), dtype=acc, device=m.device)
    ones = torch.cat([zeros, (m if m.dtype == torch.bool else m != 0).to(acc), zeros], dim=1)
    out = _window_sum(ones, length, 1) > half  # at least half + 1 ones in the window
    return out if m.dtype == torch.bool else out.to(m.dtype)


# ----------------------------------------------------------------------------------------------
# 1.1-1.6 composed
# ----------------------------------------------------------------------------------------------
def _chunk_images(images: torch.Tensor) -> int:
    """Images per chunk of the composed stages (depends on the shape and device type only)."""
    budget = SKY_CHUNK_PIXELS_CPU if images.device.type == "cpu" else SKY_CHUNK_PIXELS
    return max(1, budget // (images.shape[2] * images.shape[3]))


def _horizon_mask(images: torch.Tensor, params: Params) -> torch.Tensor:
    g = box_blur(gray(images), params.sky_blur)
    g = median_blur(g, params.sky_median)
    m = laplacian(g) < params.sky_lap_max
    return erode_rect(m, params.sky_erode)


def _sky_mask(images: torch.Tensor, params: Params) -> torch.Tensor:
    m = _horizon_mask(images, params)
    f = column_median(m, params.sky_col_median)
    h = m.shape[1]
    # z = first row where f == 0 (h if none): h - max_y((f[y] == 0) * (h - y)).
    acc = next(d for d in (torch.uint8, torch.int16, torch.int32, torch.int64) if torch.iinfo(d).max >= h)
    weight = torch.arange(h, 0, -1, device=m.device).to(acc).view(1, h, 1)  # h - y
    z = h - ((~f).to(acc) * weight).amax(dim=1, keepdim=True).to(torch.int64)  # (B, 1, W)
    # o = first row where f == 1. The rule needs z > sky_min_zero_row >= 0, so f[0] == 1 and
    # o == 0 whenever it applies: the column becomes 1 exactly on rows y < z.
    rule = (z > params.sky_min_zero_row) & (z < h)  # z < h: a zero exists (and so does a one)
    y = torch.arange(h, device=m.device).view(1, h, 1)
    m = torch.where(rule, y < z, m)
    return m & (images.amin(dim=1) >= 1)


def _sky_row(images: torch.Tensor, params: Params) -> torch.Tensor:
    mask = _sky_mask(images, params)
    h, w = mask.shape[1], mask.shape[2]
    counts = mask.sum(dim=2, dtype=torch.int64)  # (B, H)
    y = torch.arange(h, device=mask.device)
    sky = torch.where(2 * counts > w, y, torch.zeros_like(y)).amax(dim=1)  # bottom-up first: the largest y
    return torch.where(2 * sky > h, torch.zeros_like(sky), sky)


def _by_chunks(fn, images: torch.Tensor, params: Params, out: torch.Tensor) -> torch.Tensor:
    step = _chunk_images(images)
    for b0 in range(0, images.shape[0], step):  # static bounds: they depend on the shape only
        out[b0:b0 + step] = fn(images[b0:b0 + step], params)
    return out


def horizon_mask(images: torch.Tensor, params: Params) -> torch.Tensor:
    """Sections 1.1-1.3: ``erode(laplacian(median(blur(gray))) < sky_lap_max)``.

    Parameters
    ----------
    images : torch.Tensor
        uint8 ``(B, 3, H, W)`` RGB.
    params : Params
        Uses ``sky_blur``, ``sky_median``, ``sky_lap_max``, ``sky_erode``.

    Returns
    -------
    torch.Tensor
        bool ``(B, H, W)`` (the reference returns the same mask as uint8 0/1).
    """
    check_images(images)
    b, _, h, w = images.shape
    out = torch.empty((b, h, w), dtype=torch.bool, device=images.device)
    return _by_chunks(_horizon_mask, images, params, out)


def sky_mask(images: torch.Tensor, params: Params) -> torch.Tensor:
    """Sections 1.1-1.5: the sky pixels.

    With ``m`` = :func:`horizon_mask`, ``f = column_median(m, sky_col_median)``, ``z`` the
    first row of a column where ``f == 0`` and ``o`` the first where ``f == 1``: if both exist
    and ``z > sky_min_zero_row`` the column of ``m`` becomes 1 on rows ``[o, z)`` and 0
    elsewhere, else it stays. A pixel is sky iff ``m`` is 1 there and all three RGB values
    are ``>= 1``.

    Since ``sky_min_zero_row >= 0``, the rule can only apply when ``f[0] == 1`` (``o = 0``);
    ``z`` is found with a max-reduction of ``(f == 0) * (H - y)`` (no ``argmax``, no
    ``nonzero``).

    Parameters
    ----------
    images : torch.Tensor
        uint8 ``(B, 3, H, W)`` RGB.
    params : Params

    Returns
    -------
    torch.Tensor
        bool ``(B, H, W)``.
    """
    check_images(images)
    b, _, h, w = images.shape
    out = torch.empty((b, h, w), dtype=torch.bool, device=images.device)
    return _by_chunks(_sky_mask, images, params, out)


def sky_row(images: torch.Tensor, params: Params) -> torch.Tensor:
    """Section 1.6: the horizon row ``sky`` of every image; rows ``y < sky`` are ignored later.

    Scanning from the bottom up, the first row with more than ``W/2`` sky pixels (the
    integer test ``2 * count > W``), else 0; 0 as well if ``sky > H/2`` (``2 * sky > H``).

    Parameters
    ----------
    images : torch.Tensor
        uint8 ``(B, 3, H, W)`` RGB.
    params : Params

    Returns
    -------
    torch.Tensor
        int64 ``(B,)`` on the device of ``images``.
    """
    check_images(images)
    out = torch.empty((images.shape[0],), dtype=torch.int64, device=images.device)
    return _by_chunks(_sky_row, images, params, out)


class SkyRow(nn.Module):
    """``nn.Module`` wrapper of :func:`sky_row`: ``forward(images uint8 (B,3,H,W)) -> int64 (B,)``."""

    def __init__(self, params: Params | None = None) -> None:
        super().__init__()
        self.params = params if params is not None else Params()

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return sky_row(images, self.params)

    def extra_repr(self) -> str:
        p = self.params
        return (f"blur={p.sky_blur}, median={p.sky_median}, lap_max={p.sky_lap_max}, erode={p.sky_erode}, "
                f"col_median={p.sky_col_median}, min_zero_row={p.sky_min_zero_row}")
