"""OpenCV-exact image kernels on batched tensors, bit-identical to the ``cv2`` calls the
reference makes: RGB->gray, box blur, median blur (a sorting network), Laplacian, rectangular
erosion, running column median, and binary Canny. The stages (:mod:`.sky`, :mod:`.vegetation`)
compose them; tests compare each against OpenCV itself.

Shapes: images ``uint8 (B, 3, H, W)``; planes ``uint8 (B, H, W)``; masks ``bool (B, H, W)``.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

from torchrow.core.params import Params
from torchrow.functional._checks import as_u8, below_horizon, check_images, check_masks, check_params, check_rows, clamp_sky
from torchrow.functional._flow import int_max

__all__ = [
    "MEDIAN_CHUNK_PIXELS_CPU",
    "MEDIAN_CHUNK_PIXELS",
    "gray",
    "box_blur",
    "median_blur",
    "laplacian",
    "erode_rect",
    "column_median",
    "CANNY_SHIFT",
    "TG22",
    "canny_binary",
]


#: Padded pixels handled per chunk by :func:`median_blur` on the CPU (small enough for the
#: ~30 uint8 temporaries of a chunk to stay in cache) and on other devices (few, large
#: kernels). Peak extra memory is about 30 bytes per chunk pixel: ~4 MB / ~250 MB.
MEDIAN_CHUNK_PIXELS_CPU = 1 << 17


MEDIAN_CHUNK_PIXELS = 1 << 23


_GRAY_R, _GRAY_G, _GRAY_B, _GRAY_SHIFT = 9798, 19235, 3735, 15


_BLUR_SHIFT, _BLUR_FIXED_MAX_AREA = 23, 256


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


@functools.cache
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
    ab: list = [("a", i) for i in range(k)] + pad + [("b", i) for i in range(k)] + pad
    pair = _select_program(ab, _merge_pairs(2, nc), list(range(2 * k)))
    m = k // 2
    npair = _pow2(2 * k)
    nblocks = _pow2(m)
    wires: list = []
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
        nb, rows = int_max(1, budget // image_px), h
    else:
        nb, rows = 1, int_max(1, budget // row_px - 2 * r)
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
    b, _h, w = m.shape
    half = length // 2
    acc = torch.uint8 if length <= 255 else torch.int32
    zeros = torch.zeros((b, half, w), dtype=acc, device=m.device)
    ones = torch.cat([zeros, (m if m.dtype == torch.bool else m != 0).to(acc), zeros], dim=1)
    out = _window_sum(ones, length, 1) > half  # at least half + 1 ones in the window
    return out if m.dtype == torch.bool else out.to(m.dtype)


CANNY_SHIFT = 15


TG22 = int(0.4142135623730950488016887242097 * (1 << CANNY_SHIFT) + 0.5)  # 13573


def _small_direction_rule() -> tuple[int, int, int, int]:
    """Small-integer form of OpenCV's direction test on a 0/1 image.

    On ``src = 255 * mask`` the Sobel-3 derivatives are ``255 * d`` with ``d`` in
    ``[-4, 4]``, so ``|dx|, |dy| = 255 * ax, 255 * ay`` with ``ax, ay`` in ``0..4``. The
    fixed-point tests ``Y < T22`` and ``Y > T67`` (module docstring) are evaluated here,
    literally, for all 25 pairs and are shown to equal ``5*ay < 2*ax`` (horizontal) and
    ``2*ay > 5*ax`` (vertical), which :func:`canny_binary` evaluates in int8. Returns the
    coefficients ``(5, 2, 2, 5)``; raises if the equivalence failed (it cannot).
    """
    h_num, h_den, v_num, v_den = 5, 2, 2, 5
    for ax in range(5):
        for ay in range(5):
            x, y = 255 * ax, (255 * ay) << CANNY_SHIFT
            tg22x = x * TG22
            horiz = y < tg22x
            vert = not horiz and y > tg22x + (x << (CANNY_SHIFT + 1))
            if horiz != (h_num * ay < h_den * ax) or vert != (v_num * ay > v_den * ax):
                raise AssertionError(f"direction rule differs at |dx|/255={ax}, |dy|/255={ay}")
    return h_num, h_den, v_num, v_den


_H_NUM, _H_DEN, _V_NUM, _V_DEN = _small_direction_rule()


def _replicate(t: torch.Tensor) -> torch.Tensor:
    """Pad ``(B, H, W)`` by one pixel on every side, replicating the edge (``aaa|abcd|ddd``)."""
    t = torch.cat([t[:, :1], t, t[:, -1:]], dim=1)
    return torch.cat([t[:, :, :1], t, t[:, :, -1:]], dim=2)


def _dilate8(t: torch.Tensor) -> torch.Tensor:
    p = F.pad(t, (1, 1, 1, 1), value=False)
    h, w = t.shape[1:]
    rows = p[:, 0:h] | p[:, 1:h + 1] | p[:, 2:h + 2]
    return rows[:, :, 0:w] | rows[:, :, 1:w + 1] | rows[:, :, 2:w + 2]


def canny_binary(veg: torch.Tensor, sky: torch.Tensor, params: Params) -> torch.Tensor:
    """``cv2.Canny(region * 255, canny_low, canny_high, L2gradient=False) > 0`` per image.

    ``region`` = the rows ``y >= sky[b]`` of ``veg``, treated as the whole image (OpenCV's
    borders at its top row, not at row 0). Bit-exact with OpenCV's ``canny.cpp``; the rules
    (Sobel with replicated border, zero-bordered magnitude for non-maximum suppression, the
    Q15 tangent test and its ``>``/``>=`` comparisons, hysteresis) are listed in the module
    docstring.

    Parameters
    ----------
    veg : torch.Tensor
        ``bool (B, H, W)`` binary mask; its rows above the horizon are ignored.
    sky : torch.Tensor
        ``int (B,)`` horizon rows (clamped to ``[0, H]``).
    params : Params
        Uses ``canny_low`` and ``canny_high`` (swapped if ``low > high``, as OpenCV).

    Returns
    -------
    torch.Tensor
        ``bool (B, H, W)`` edges, False above the horizon.
    """
    check_params(params)
    check_masks(veg, "veg")
    b, h, w = veg.shape
    check_rows(sky, b)
    dev = veg.device
    low, high = sorted((int(params.canny_low), int(params.canny_high)))
    skyc = clamp_sky(sky, h, dev)
    below = below_horizon(skyc, h)
    if b == 0:
        return torch.zeros_like(veg)
    # Rows above the horizon take the value of the region's top row, so that a replicated
    # image border reproduces the region's replicated border for rows >= sky.
    vu8 = as_u8(veg)
    top = vu8.gather(1, skyc.clamp(max=h - 1).view(b, 1, 1).expand(b, 1, w))  # (B, 1, W)
    # Work on the flattened padded grid (B, H+2, W+2): every neighbour is a constant offset
    # (+-1, +-r, +-r+-1 with r = W+2), so each step below is one contiguous 1-D operation,
    # done in place where possible (fresh multi-MB temporaries cost page faults on the CPU).
    # Values are on the 0/1 scale (see _small_direction_rule): OpenCV's divided by 255.
    r = w + 2
    src = (vu8 & below).bitwise_or_(top & (below ^ 1))
    grid = _replicate(src).view(torch.int8).reshape(-1)
    total = grid.numel()
    n = total - 2 * (r + 1)  # positions r+1 .. total-r-2 cover every interior pixel

    def g(off: int) -> torch.Tensor:
        return grid[r + 1 + off:r + 1 + off + n]

    # Sobel 3x3 with replicated border (the grid's padding and the rows above the horizon
    # carry the replicated values): dx = [-1 0 1] x [1 2 1]^T, dy its transpose; in [-4, 4].
    dx = g(1 - r) + g(1 + r)
    for off in (1, 1):
        dx += g(off)
    for off in (-1 - r, r - 1, -1, -1):
        dx -= g(off)
    dy = g(r - 1) + g(r + 1)
    for off in (r, r):
        dy += g(off)
    for off in (-r - 1, 1 - r, -r, -r):
        dy -= g(off)
    same = torch.bitwise_xor(dx, dy).ge_(0).view(torch.bool).view(torch.uint8)  # s = +1
    ax, ay = dx.abs_(), dy.abs_()
    t1, t2 = torch.mul(ay, _H_NUM), torch.mul(ax, _H_DEN)
    horiz = (t1 < t2).view(torch.uint8)  # (|dy|<<15) < |dx|*TG22
    torch.mul(ay, _V_NUM, out=t1)
    torch.mul(ax, _V_DEN, out=t2)
    vert = (t1 > t2).view(torch.uint8)  # (|dy|<<15) > |dx|*TG22 + (|dx|<<16)
    del t1, t2
    # L1 magnitude in [0, 8], zero on the grid's frame and above the horizon (NMS border).
    mag = torch.zeros(total, dtype=torch.int8, device=dev)
    m = mag[r + 1:r + 1 + n]
    torch.add(ax, ay, out=m)
    mag2 = mag.view(b, h + 2, r)
    # the frame holds values computed across image boundaries: clear it (zero_(), not "= 0",
    # which would trace to lifted scalar constants that an exported program with torch.cond
    # subgraphs cannot re-decompose)
    mag2[:, 0].zero_()
    mag2[:, h + 1].zero_()
    mag2[:, :, 0].zero_()
    mag2[:, :, r - 1].zero_()
    mag2[:, 1:h + 1].bitwise_and_(below.view(torch.int8).neg())  # 0 or all ones
    del ax, ay, dx, dy
    tmp = torch.empty(n, dtype=torch.bool, device=dev)
    tmp_u8 = tmp.view(torch.uint8)

    def both(op1, off1: int, op2, off2: int) -> torch.Tensor:
        """``(m op1 m[off1]) & (m op2 m[off2])`` as a fresh 0/1 uint8 tensor."""
        out = op1(m, mag[r + 1 + off1:r + 1 + off1 + n]).view(torch.uint8)
        op2(m, mag[r + 1 + off2:r + 1 + off2 + n], out=tmp)
        return out.bitwise_and_(tmp_u8)

    keep = both(torch.gt, -1, torch.ge, 1).bitwise_and_(horiz)  # m > left, m >= right
    keep.bitwise_or_(both(torch.gt, -r, torch.ge, r).bitwise_and_(vert))  # m > up, m >= down
    # Diagonal, both strict: s = +1 -> (y-1, x-1), (y+1, x+1); s = -1 -> (y-1, x+1), (y+1, x-1).
    diag = horiz.bitwise_or_(vert).bitwise_xor_(1)
    d_pos = both(torch.gt, -r - 1, torch.gt, r + 1).bitwise_and_(same)
    d_neg = both(torch.gt, 1 - r, torch.gt, r - 1).bitwise_and_(same.bitwise_xor_(1))
    keep.bitwise_or_(d_pos.bitwise_or_(d_neg).bitwise_and_(diag))
    del d_pos, d_neg, diag, vert, same
    # m * 255 > low  <=>  m > low // 255 for integer m >= 0 (same for high).
    torch.gt(m, low // 255, out=tmp)
    keep.bitwise_and_(tmp_u8)
    torch.gt(m, high // 255, out=tmp)

    def to_image(flat: torch.Tensor) -> torch.Tensor:
        # concatenation, not a slice assignment into zeros (an exported ScatterND, 3x slower)
        zero = torch.zeros(r + 1, dtype=torch.uint8, device=dev)
        full = torch.cat([zero, flat, zero])  # n = total - 2 * (r + 1)
        return full.view(b, h + 2, r)[:, 1:h + 1, 1:w + 1].contiguous().view(torch.bool)

    edges = to_image(tmp_u8 & keep)
    cand = to_image(keep)
    # Weak edges exist only if some multiple of 255 (the possible magnitudes) is in (low, high].
    if high // 255 > low // 255:
        weak = cand & ~edges
        for _ in range(h * w):  # static bound; stops at the fixed point
            grown = edges | (weak & _dilate8(edges))
            if torch.equal(grown, edges):
                break
            edges = grown
    return edges
