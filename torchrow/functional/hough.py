"""Batched Hough voting and peak extraction (ALGORITHM.md section 5).

Voting is a scatter-add (``index_add_``) of the votes of a compact pixel list: the pixels of
each image's mask are moved to the front of a ``(B, K)`` index list by a stable sort (no
``nonzero``), and votes are accumulated in chunks of that list. A chunk loop stops as soon as
no image has pixels left in it (the only host synchronisation, an early exit that never
changes a result). The accumulator row of each (pixel, angle) comes from the shared constant
table :func:`torchrow.core.tables.rho_index_table` (``rint(x*c_j + y*s_j) + D``, computed once with
NumPy as the reference computes it), so no float arithmetic decides a vote here.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from torchrow.core.params import Params
from torchrow.core.tables import hough_pickable, hough_trig, near_angle, near_horizontal, rho_index_table, rho_offset
from torchrow.functional import _exact
from torchrow.functional._checks import check_masks
from torchrow.functional._flow import branch, check_flow, choose, keep

__all__ = ["HoughState", "Voter", "EagerVoter", "StaticVoter", "pickable_angles", "erase_bound", "pixel_list", "compact",
           "trig", "rho_table", "line_distance", "accumulate", "votes", "excluded_angles", "peak",
           "VoteTables", "vote_tables", "prefix_votes"]

#: Pixels per chunk when accumulating votes: bounds the ``(chunk, n_theta)`` int32 index
#: temporary to ``180 * 65536 * 4`` bytes (47 MB).
CHUNK = 65536


def trig(params: Params, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Shared ``(cos, sin)`` of the Hough angles as float64 ``(n_theta,)`` tensors on ``device``."""
    key = ("trig", params.theta_step, str(device))
    if key not in _CACHE or torch.compiler.is_exporting():
        c, s = hough_trig(params.theta_step)
        made = (torch.tensor(c, dtype=torch.float64, device=device), torch.tensor(s, dtype=torch.float64, device=device))
        if not cacheable():
            return made
        _CACHE[key] = made
    return _CACHE[key]


def cacheable() -> bool:
    """Whether a constant tensor built now may be cached for later calls: not while
    ``torch.export`` traces (it would hand traced tensors to later eager calls)."""
    return not torch.compiler.is_exporting()


def rho_table(height: int, width: int, params: Params, device: torch.device) -> torch.Tensor:
    """Flat accumulator offset of every pixel for every angle within one image's accumulator,
    ``j*(2D+1) + rho_index``, as ``(H*W, n_theta)`` int32 on ``device``.

    Built from the shared :func:`torchrow.core.tables.rho_index_table` (``rint(x*c_j + y*s_j) + D``),
    a constant, so voting does no float arithmetic and an exported graph votes exactly.
    720 bytes per pixel: 55 MB at 320x240, 885 MB at 1280x960 (the last two sizes are kept).
    """
    key = ("rho", height, width, params.theta_step, str(device))
    if key not in _CACHE or not cacheable():
        for k in [k for k in _CACHE if k[0] == "rho"][:-1]:
            _CACHE.pop(k, None)  # another thread may have dropped it already
        n_rho = 2 * rho_offset(height, width) + 1
        t = torch.from_numpy(rho_index_table(height, width, params.theta_step).astype(np.int32))
        t += torch.arange(t.shape[0], dtype=torch.int32).view(-1, 1) * n_rho
        t = t.T.contiguous().to(device)  # pixel-major: one pixel's cells are one row
        if not cacheable():
            return t
        _CACHE[key] = t
    return _CACHE[key]


_CACHE: dict = {}


def pixel_list(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Raster positions of each image's mask pixels, moved to the front.

    Parameters
    ----------
    mask : bool (B, H, W)

    Returns
    -------
    idx : int64 (B, H*W), the flat raster indices ``y*W + x`` of the mask pixels first, in
        raster order, then the others.
    count : int64 (B,), the number of mask pixels.

    A stable partition by prefix sums and one scatter (every slot written once): linear
    time, where a stable sort of the row was ``n log n`` (measured 5x faster here).
    """
    b, h, w = mask.shape
    n = h * w
    flat = mask.reshape(b, n)
    dev = mask.device
    if n == 0:
        return torch.zeros((b, 0), dtype=torch.int64, device=dev), torch.zeros(b, dtype=torch.int64, device=dev)
    # int32 prefix sums over bytes: 5x faster than a bool cumsum into int64 (n < 2**31)
    on = torch.cumsum(flat.to(torch.int32) if torch.compiler.is_exporting() else flat.view(torch.uint8), dim=1,
                      dtype=torch.int32)
    count = on[:, -1:].clone()  # on is decremented in place below
    pos = torch.arange(n, device=dev)
    other = (pos.to(torch.int32) - on).add_(count)  # other pixels: after all mask pixels, in order
    slot = torch.where(flat, on.sub_(1), other).to(torch.int64)  # mask pixel: slot on-1
    idx = torch.empty((b, n), dtype=torch.int64, device=dev)
    idx.scatter_(1, slot, pos.expand(b, n))  # a permutation: every slot written once
    return idx, count.squeeze(1).to(torch.int64)


def active_width(count: torch.Tensor) -> int:
    """Largest count in the batch: the loop bound of a chunk loop (host sync, early exit only)."""
    return int(count.max()) if count.numel() else 0


def line_distance(xs: torch.Tensor, ys: torch.Tensor, cos_j: torch.Tensor, sin_j: torch.Tensor,
                  rho: torch.Tensor) -> torch.Tensor:
    """``|x*c_j + y*s_j - rho|`` in float64, broadcasting ``(B, 1)`` line parameters over ``(B, K)``."""
    return ((xs.to(torch.float64) * cos_j + ys.to(torch.float64) * sin_j) - rho).abs()


def compact(select: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Positions of the True entries of a 1-D bool tensor, in order, without ``nonzero``.

    A prefix sum gives every selected entry its slot; one scatter (no reduction) writes the
    positions there. Returns ``(positions int64 (n,), n)``; ``n`` is read to the host (the loop
    bound of the caller).
    """
    slot = torch.cumsum(select, 0, dtype=torch.int64) - 1
    n = int(slot[-1]) + 1 if slot.numel() else 0
    dest = torch.where(select, slot, torch.full_like(slot, n))
    out = torch.empty(n + 1, dtype=torch.int64, device=select.device)
    out.scatter_(0, dest, torch.arange(select.numel(), device=select.device))
    return out[:n], n


def accumulate(acc: torch.Tensor, idx: torch.Tensor, select: torch.Tensor, sign: int,
               table: torch.Tensor) -> None:
    """Add ``sign`` votes of the selected list entries into ``acc`` in place.

    ``acc`` int32 ``(B, n_theta, 2D+1)``; ``idx`` int64 ``(B, K)`` raster pixel indices;
    ``select`` bool ``(B, K)``; ``table`` from :func:`rho_table`. The selected entries of the
    whole batch are compacted into one list first (:func:`compact`; its length is the loop
    bound, the one host synchronisation), so padding costs nothing; votes are then
    added in chunks of :data:`CHUNK` pixels, each pixel's 180 cells read as one table row.
    """
    b, n_theta, n_rho = acc.shape
    k = idx.shape[1]
    order, n = compact(select.reshape(b * k))
    flat_acc = acc.view(-1)
    flat_idx = idx.reshape(b * k)
    one = torch.full((1,), sign, dtype=torch.int32, device=acc.device)
    for start in range(0, n, CHUNK):
        sel = order[start:min(start + CHUNK, n)]
        cells = table.index_select(0, flat_idx[sel]) + ((sel // k).to(torch.int32) * (n_theta * n_rho)).unsqueeze(1)
        flat_acc.index_add_(0, cells.view(-1), one.expand(cells.numel()))


def votes(mask: torch.Tensor, params: Params) -> torch.Tensor:
    """Hough accumulator of bool ``(B, H, W)`` masks: int32 ``(B, n_theta, 2D+1)``.

    Note the layout: angle before rho (the reference's NumPy accumulator is ``(2D+1, n_theta)``).
    """
    check_masks(mask, "hough input")
    b, h, w = mask.shape
    d = rho_offset(h, w)
    acc = torch.zeros((b, params.n_theta, 2 * d + 1), dtype=torch.int32, device=mask.device)
    idx, count = pixel_list(mask)
    live = torch.arange(idx.shape[1], device=mask.device) < count.unsqueeze(1)
    accumulate(acc, idx, live, 1, rho_table(h, w, params, mask.device))
    return acc


def excluded_angles(held_theta: torch.Tensor, held_valid: torch.Tensor, params: Params) -> torch.Tensor:
    """Step 5.1: bool ``(B, n_theta)`` of angles that cannot be picked.

    ``held_theta`` int64 ``(B, S)`` angle indices of held lines, ``held_valid`` bool ``(B, S)``.
    """
    dev = held_theta.device
    deg = torch.arange(params.n_theta, device=dev) * params.theta_step
    ex = near_horizontal(deg, params.horizontal_excl)
    near = near_angle(deg.view(1, 1, -1), (held_theta * params.theta_step).unsqueeze(-1), params.angle_excl)
    return ex.unsqueeze(0) | (near & held_valid.unsqueeze(-1)).any(dim=1)


def peak(acc: torch.Tensor, excluded: torch.Tensor,
         angles: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Step 5.2: the maximum cell over allowed angles; ties -> smallest rho index, then theta.

    ``acc`` int32 ``(B, A, 2D+1)`` holds the votes of the angle indices ``angles`` int64
    ``(A,)`` (default: all ``n_theta`` angles, ``A = n_theta``), ``excluded`` bool
    ``(B, n_theta)``. Returns ``(theta_index, rho_index, votes)`` each int64 ``(B,)``;
    votes 0 means no line. Angles missing from ``angles`` are never picked.
    """
    n_theta = excluded.shape[1]
    if angles is None:
        angles = torch.arange(n_theta, device=acc.device)
    else:
        excluded = excluded.index_select(1, angles)
    # torch.max(dim) does not promise the first index on ties; argmax does.
    colarg = torch.argmax(acc, dim=2)  # (B, A): smallest rho index of each angle's max
    colmax = acc.gather(2, colarg.unsqueeze(2)).squeeze(2).to(torch.int64).masked_fill(excluded, 0)
    best = colmax.max(dim=1, keepdim=True).values
    key = colarg * n_theta + angles.view(1, -1)
    key = key.masked_fill(colmax != best, torch.iinfo(torch.int64).max)
    flat = key.min(dim=1).values
    w = best.squeeze(1)
    return flat % n_theta, flat // n_theta, w


@dataclass
class HoughState:
    """Per-image Hough input and votes during extraction (erasures persist until a restart).

    ``idx``/``count``: the compact pixel list of the original input; ``alive`` bool ``(B, K)``
    marks list entries not yet erased; ``acc`` int32 ``(B, n_theta, 2D+1)`` holds the votes of
    the alive pixels, ``acc0`` those of the untouched input.
    """

    idx: torch.Tensor
    count: torch.Tensor
    alive: torch.Tensor
    acc: torch.Tensor
    acc0: torch.Tensor
    width: int
    d: int
    table: torch.Tensor

    @classmethod
    def start(cls, mask: torch.Tensor, params: Params) -> HoughState:
        check_masks(mask, "hough input")
        b, h, w = mask.shape
        d = rho_offset(h, w)
        table = rho_table(h, w, params, mask.device)
        idx, count = pixel_list(mask)
        k = active_width(count)
        idx = idx[:, :k]  # entries past the largest count are never mask pixels
        acc = torch.zeros((b, params.n_theta, 2 * d + 1), dtype=torch.int32, device=mask.device)
        alive = torch.arange(k, device=mask.device) < count.unsqueeze(1)
        accumulate(acc, idx, alive, 1, table)
        return cls(idx, count, alive, acc, acc.clone(), w, d, table)

    def reset(self, which: torch.Tensor) -> None:
        """Restore the untouched input and votes for images where ``which`` (bool ``(B,)``)."""
        self.acc = torch.where(which.view(-1, 1, 1), self.acc0, self.acc)
        self.alive = torch.where(which.view(-1, 1), torch.arange(self.alive.shape[1], device=which.device)
                                 < self.count.unsqueeze(1), self.alive)

    def erase(self, theta: torch.Tensor, rho: torch.Tensor, active: torch.Tensor, params: Params) -> None:
        """Step 5.3 for images where ``active``: erase alive pixels within ``hough_band/2`` of
        line ``(theta, rho)`` and remove their votes."""
        cos, sin = trig(params, self.acc.device)
        xs, ys = self.idx % self.width, self.idx // self.width
        band = params.hough_band_px(self.width)
        dist = line_distance(xs, ys, cos[theta].unsqueeze(1), sin[theta].unsqueeze(1),
                             rho.to(torch.float64).unsqueeze(1))
        hit = self.alive & (dist <= band / 2) & active.unsqueeze(1)
        self.alive = self.alive & ~hit
        accumulate(self.acc, self.idx, hit, -1, self.table)


class Voter(Protocol):
    """How :func:`torchrow.functional.vanishing.find_lines` keeps Hough votes
    (:class:`EagerVoter`, :class:`StaticVoter`).

    ``state`` is a tuple (of tensors, for a static voter: it passes through ``torch.cond``);
    ``init`` is what a restart needs.
    """

    @property
    def angles(self) -> torch.Tensor | None:
        """int64 ``(A,)``: the angle indices :meth:`votes` holds (``None``: all ``n_theta``)."""

    @property
    def d(self) -> int:
        """``D`` of the accumulator (a cell's rho is its index minus ``D``); set by :meth:`start`."""

    def start(self, hin: torch.Tensor) -> tuple[tuple, Any]:
        """``(state, init)`` of the Hough input bool ``(B, H, W)``, every pixel voted."""

    def votes(self, state: tuple) -> torch.Tensor:
        """int32 ``(B, A, 2D+1)``: the votes of the pixels not yet erased."""

    def erase(self, state: tuple, init: Any, theta: torch.Tensor, rho: torch.Tensor, active: torch.Tensor) -> tuple:
        """Step 5.3: the state after erasing the band of line ``(theta, rho)`` int64 ``(B,)`` where ``active``."""

    def reset(self, state: tuple, init: Any, which: torch.Tensor) -> tuple:
        """The state of a restart (every pixel voted again) where ``which`` bool ``(B,)``."""


class EagerVoter:
    """The eager :class:`Voter` of :func:`torchrow.functional.vanishing.find_lines`: a
    :class:`HoughState` (compact pixel list, host-synchronised chunk loops)."""

    angles = None

    def __init__(self, params: Params) -> None:
        self.params = params

    def start(self, hin: torch.Tensor) -> tuple[tuple, None]:
        hs = HoughState.start(hin, self.params)
        self.d = hs.d
        return (hs,), None

    def votes(self, state: tuple) -> torch.Tensor:
        return state[0].acc

    def erase(self, state: tuple, init: None, theta: torch.Tensor, rho: torch.Tensor,
              active: torch.Tensor) -> tuple:
        if bool(active.any()):
            state[0].erase(theta, rho, active, self.params)
        return state

    def reset(self, state: tuple, init: None, which: torch.Tensor) -> tuple:
        if bool(which.any()):
            state[0].reset(which)
        return state


def pickable_angles(params: Params) -> np.ndarray:
    """Angle indices ``j`` with ``|j*theta_step - 90| >= horizontal_excl``, int64 ``(A,)``: the
    only ones step 5.1 ever lets be a peak, so the only ones a static voter votes for."""
    return hough_pickable(params.theta_step, params.horizontal_excl).copy()


@functools.lru_cache(maxsize=8)
def _erase_bound(height: int, width: int, theta_step: int, horizontal_excl: int, n_theta: int, band: int) -> int:
    ys, xs = np.divmod(np.arange(height * width, dtype=np.int64), width)
    cos, sin = hough_trig(theta_step)
    d = rho_offset(height, width)
    rho = np.arange(-d, d + 1, dtype=np.float64)
    half = band / 2 + 1e-6  # slack: the band test rounds |p - rho|, these bounds round p +- half
    best = 0
    for j in hough_pickable(theta_step, horizontal_excl):
        p = np.sort(xs * cos[j] + ys * sin[j])
        best = max(best, int((np.searchsorted(p, rho + half, "right") - np.searchsorted(p, rho - half, "left")).max()))
    return best


def erase_bound(height: int, width: int, params: Params) -> int:
    """Static bound on the pixels one erase of step 5.3 can remove at this working size: the
    most pixels of the image within ``hough_band/2`` (plus 1e-6 px of slack) of any line of
    a pickable angle and integer rho, counted on the sorted projections ``x*c_j + y*s_j``."""
    return _erase_bound(height, width, params.theta_step, params.horizontal_excl, params.n_theta,
                        params.hough_band_px(width))


class StaticVoter(nn.Module):
    """Static-shape :class:`Voter` of the exportable graphs.

    * ``scatter_free=False`` (onnxruntime): as :class:`HoughState`, the state is the Hough
      input's compact pixel list (:func:`pixel_list`, ``(B, H*W)``, kept in ``init``) with
      ``alive`` bool ``(B, H*W)`` marking its entries not yet erased, and ``acc`` int32
      ``(B, A, 2D+1)`` over the pickable angles (:func:`pickable_angles`). Votes are added
      once (``ScatterElements`` with ``reduction="add"``) in chunks of :attr:`chunk` list
      entries, each chunk in a :func:`~torchrow.functional._flow.branch` that skips it when
      no image has pixels left there. An erase tests only the first :attr:`tier` list
      entries when every image's list fits there (on CRBD and the Caterra video the Hough
      input is about 9% of the image; :attr:`tier` is an eighth), the whole list otherwise,
      and subtracts the votes of the erased pixels only, compacted into :func:`erase_bound`
      slots. The rho index is the spec's expression ``rint((x*c_j) + (y*s_j)) + D`` in
      float64 (no fused multiply-add; equal to the shared table, which a test checks), so no
      table of ``H*W x A`` entries is stored.
    * ``scatter_free=True`` (runtimes without a scatter reduction, e.g. TensorRT): the state
      is the raster alive mask bool ``(B, H*W)``; no accumulator is kept; each peak re-votes
      the alive mask by prefix sums of constant permutations
      (:func:`prefix_votes`).

    Memory (``B`` images): the accumulator twice, ``B*A*(2D+1)*4`` bytes (0.4 MB per image
    at 320x240), the pixel list (``8*H*W`` bytes per image), plus a chunk's ``(B, chunk, A)``
    int64 cell indices (2.1 MB per image with the default ``chunk`` of 2048; 8.6 MB past the
    first :attr:`tier` entries, where chunks are 4x longer).
    """

    # buffers (``register_buffer`` below); the scatter-free tables exist only when scatter_free
    angles: torch.Tensor
    cos: torch.Tensor
    sin: torch.Tensor
    cos_a: torch.Tensor
    sin_a: torch.Tensor
    xs: torch.Tensor
    ys: torch.Tensor
    cell0: torch.Tensor
    order: torch.Tensor
    ends: torch.Tensor
    run_empty: torch.Tensor

    def __init__(self, height: int, width: int, params: Params, flow: str = "loop", scatter_free: bool = False,
                 chunk: int = 2048, tier: int | None = None) -> None:
        super().__init__()
        self.params = params
        self.height, self.width = int(height), int(width)
        self.flow = check_flow(flow)
        self.scatter_free = bool(scatter_free)
        self.chunk = int(chunk)
        self.d = rho_offset(self.height, self.width)
        self.n_rho = 2 * self.d + 1
        ang = pickable_angles(params)
        self.register_buffer("angles", torch.from_numpy(ang), persistent=False)
        c, s = hough_trig(params.theta_step)
        self.register_buffer("cos", torch.tensor(c, dtype=torch.float64), persistent=False)
        self.register_buffer("sin", torch.tensor(s, dtype=torch.float64), persistent=False)
        self.register_buffer("cos_a", torch.tensor(np.asarray(c)[ang], dtype=torch.float64), persistent=False)
        self.register_buffer("sin_a", torch.tensor(np.asarray(s)[ang], dtype=torch.float64), persistent=False)
        ys, xs = np.divmod(np.arange(self.height * self.width, dtype=np.int64), self.width)
        self.register_buffer("xs", torch.from_numpy(xs.astype(np.float64)), persistent=False)
        self.register_buffer("ys", torch.from_numpy(ys.astype(np.float64)), persistent=False)
        self.register_buffer("cell0", torch.arange(len(ang), dtype=torch.int64) * self.n_rho + self.d,
                             persistent=False)
        self.bound = min(self.height * self.width, erase_bound(self.height, self.width, params))
        n = self.height * self.width
        self.tier = max(1, min(n, int(tier) if tier is not None else max(self.bound, n // 8)))
        if self.scatter_free:
            t = vote_tables(self.height, self.width, params)
            self.register_buffer("order", t.order, persistent=False)
            self.register_buffer("ends", t.ends, persistent=False)
            self.register_buffer("run_empty", t.empty, persistent=False)

    # -- voting -------------------------------------------------------------------------------
    def _coords(self, pix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """float64 ``(x, y)`` of raster indices ``pix`` int64: integer ``%`` and ``//`` (a
        gather from the coordinate buffers exports as a several times slower ``GatherND``)."""
        return (pix % self.width).to(torch.float64), (pix // self.width).to(torch.float64)

    def _add(self, acc: torch.Tensor, pix: torch.Tensor, wgt: torch.Tensor) -> torch.Tensor:
        """``acc`` plus ``wgt`` int32 ``(B, C)`` votes of the raster pixels ``pix`` int64 ``(B, C)``."""
        bsz, c = pix.shape
        x, y = self._coords(pix)
        x, y = x.unsqueeze(2), y.unsqueeze(2)
        cell = torch.round(x * self.cos_a + y * self.sin_a).to(torch.int64) + self.cell0  # (B, C, A)
        upd = wgt.unsqueeze(2).expand(bsz, c, self.cos_a.shape[0])
        return acc.reshape(bsz, -1).scatter_add(1, cell.reshape(bsz, -1), upd.reshape(bsz, -1)).view(acc.shape)

    def _accumulate(self, acc: torch.Tensor, pix: torch.Tensor, count: torch.Tensor, sign: int,
                    chunk: int | None = None, fine: int | None = None) -> torch.Tensor:
        """Add ``sign`` votes of the first ``count`` (B,) entries of the list ``pix`` (B, K),
        chunk by chunk; chunks past every image's count are skipped (per :attr:`flow`), in
        blocks of 8 chunks first so that a skip copies the accumulator once, not per chunk
        (the later blocks sit in the first one's branch).

        ``fine``: entries up to this go in chunks of ``chunk``, later ones (which only images
        with more pixels than that have) in chunks of 4 x ``chunk``: fewer branches to trace,
        export and skip, where a chunk rarely runs.
        """
        k = pix.shape[1]
        top = count.max()
        chunk = chunk or self.chunk
        fine = k if fine is None else min(k, fine)
        edges = list(range(0, fine, chunk)) + list(range(fine, k, 4 * chunk)) + [k]
        spans = list(itertools.pairwise(edges))

        def chunks(acc, i0: int, i1: int):
            for i in range(i0, i1):
                c0, c1 = spans[i]

                def add(acc, c0=c0, c1=c1):
                    wgt = (torch.arange(c0, c1, device=acc.device) < count.unsqueeze(1)).to(torch.int32) * sign
                    return (self._add(acc, pix[:, c0:c1], wgt),)

                acc, = branch(self.flow, top > c0, add, keep, (acc,)) if i > i0 else add(acc)
            return (acc,)

        def blocks(acc):
            for i0 in range(8, len(spans), 8):
                i1 = min(i0 + 8, len(spans))
                acc, = branch(self.flow, top > spans[i0][0], lambda acc, i0=i0, i1=i1: chunks(acc, i0, i1), keep,
                              (acc,))
            return (acc,)

        # the first block's own branch holds the later blocks' too: no pixels at all (a
        # tracked frame's empty Hough input) is one skip, not one per block
        return branch(self.flow, top > 0, lambda acc: blocks(*chunks(acc, 0, min(8, len(spans)))), keep, (acc,))[0]

    def start(self, hin: torch.Tensor) -> tuple[tuple, tuple]:
        """Votes of ``hin`` bool ``(B, H, W)``: the state ``(alive, acc)`` (scatter-free:
        ``(alive,)`` over the raster) and ``init``, what an erase and a restart read: the
        untouched state, then the pixel list and counts."""
        bsz = hin.shape[0]
        if self.scatter_free:
            alive = hin.reshape(bsz, -1)
            return (alive,), (alive,)
        pix, count = pixel_list(hin)
        alive = torch.arange(pix.shape[1], device=hin.device) < count.unsqueeze(1)
        acc = torch.zeros((bsz, self.angles.shape[0], self.n_rho), dtype=torch.int32, device=hin.device)
        acc = self._accumulate(acc, pix, count, 1, fine=self.tier)
        return (alive, acc), (alive, acc, pix, count)

    def votes(self, state: tuple) -> torch.Tensor:
        if self.scatter_free:
            t = VoteTables(self.angles, self.order, self.ends, self.run_empty, self.n_rho, self.d)
            return prefix_votes(state[0], t)
        return state[1]

    def erase(self, state: tuple, init: tuple, theta: torch.Tensor, rho: torch.Tensor,
              active: torch.Tensor) -> tuple:
        """Step 5.3 (the spec's expression, as :meth:`HoughState.erase`) where ``active``."""
        band = self.params.hough_band_px(self.width)
        cos, sin, r = self.cos[theta].unsqueeze(1), self.sin[theta].unsqueeze(1), rho.to(torch.float64).unsqueeze(1)
        if self.scatter_free:
            alive = state[0]
            hit = alive & (line_distance(self.xs.unsqueeze(0), self.ys.unsqueeze(0), cos, sin, r) <= band / 2)
            return (alive & ~(hit & active.unsqueeze(1)),)
        pix, count = init[2], init[3]
        k = self.height * self.width  # static: a loop carry's own sizes are symbolic while exporting

        def over(n: int):
            """The erase over the first ``n`` list entries (exact when no image has more)."""
            def run(alive, acc):
                p = pix[:, :n]
                here = alive[:, :n]
                hit = here & (line_distance(*self._coords(p), cos, sin, r) <= band / 2) & active.unsqueeze(1)
                alive = torch.cat([here & ~hit, alive[:, n:]], 1) if n < k else here & ~hit
                # the erased entries, compacted into erase_bound slots by a TopK of the 0/1
                # mask (their order does not change a sum; a permutation scatter would fold
                # a list-sized constant into every step)
                sel = torch.topk(hit.to(torch.int32), min(self.bound, n), dim=1).indices
                # smaller chunks than the first vote: on CRBD an erase removes 214 pixels
                # (median; 569 at most) and the first vote counts ~2200 (median; 5300 at most)
                return alive, self._accumulate(acc, p.gather(1, sel), _exact.count(hit), -1, max(1, self.chunk // 8),
                                               fine=self.chunk // 2)
            return run

        if self.tier >= k:
            return tuple(over(k)(*state))
        return choose(self.flow, count.max() <= self.tier, over(self.tier), over(k), tuple(state))

    def reset(self, state: tuple, init: tuple, which: torch.Tensor) -> tuple:
        """Restore the untouched input (and its votes) where ``which`` bool ``(B,)``."""
        return tuple(torch.where(which.view((-1,) + (1,) * (s.dim() - 1)), s0, s)
                     for s, s0 in zip(state, init[:len(state)]))


# ------------------------------------------------------------------------------------------
# The scatter-free vote of StaticVoter (constant tables per working size)
# ------------------------------------------------------------------------------------------

@dataclass
class VoteTables:
    """Constant tables of the scatter-free vote, for one working size.

    ``angles`` int64 ``(A,)``: the pickable angle indices (``|j*step - 90| >= horizontal_excl``;
    the others are never peaks, so they are never voted). ``order`` int32 ``(A*H*W,)``: per
    angle, the raster pixel indices sorted by rho index (stable), concatenated.
    ``ends`` int64 ``(A*(2D+1),)``: per angle ``a`` and rho index ``r``, the flat position
    ``a*H*W + e - 1`` of the run end in the angles' concatenated prefix sums, ``e`` the number
    of pixels whose rho index is ``<= r`` (0 where ``e = 0``); ``empty`` bool ``(A*(2D+1),)``
    marks ``e = 0`` (no pixel yet: the sum is 0). ``n_rho = 2D+1``, ``d = D``.
    """

    angles: torch.Tensor
    order: torch.Tensor
    ends: torch.Tensor
    empty: torch.Tensor
    n_rho: int
    d: int


@functools.lru_cache(maxsize=2)
def _vote_arrays(height: int, width: int, theta_step: int, horizontal_excl: int):
    idx = rho_index_table(height, width, theta_step)  # (n_theta, HW)
    angles = hough_pickable(theta_step, horizontal_excl).copy()  # torch.from_numpy needs it writable
    d = rho_offset(height, width)
    n_rho = 2 * d + 1
    sub = idx[angles].astype(np.int64)
    order = np.argsort(sub, axis=1, kind="stable")
    ends = np.stack([np.cumsum(np.bincount(s, minlength=n_rho)) for s in sub])
    empty = ends == 0
    ends = np.maximum(ends - 1, 0) + np.arange(len(angles), dtype=np.int64)[:, None] * (height * width)
    return (angles, order.reshape(-1).astype(np.int32), ends.reshape(-1).astype(np.int64), empty.reshape(-1),
            n_rho, d)


def vote_tables(height: int, width: int, params: Params, device: torch.device | str = "cpu") -> VoteTables:
    """The :class:`VoteTables` of a ``width x height`` working size (cached)."""
    angles, order, ends, empty, n_rho, d = _vote_arrays(height, width, params.theta_step, params.horizontal_excl)
    dev = torch.device(device)
    return VoteTables(torch.from_numpy(angles).to(dev), torch.from_numpy(order).to(dev),
                      torch.from_numpy(ends).to(dev), torch.from_numpy(empty).to(dev), n_rho, d)


def prefix_votes(alive: torch.Tensor, tables: VoteTables) -> torch.Tensor:
    """Hough votes of the pickable angles without a scatter: bool ``(B, H*W)`` -> int32
    ``(B, A, 2D+1)``, equal to :func:`votes` at those angles.

    No scatter: gather the mask in each angle's rho order, prefix-sum it, read the sums at
    the constant run ends, difference along rho.
    """
    b, hw = alive.shape
    n_ang = tables.angles.shape[0]
    g = torch.index_select(alive.to(torch.int32), 1, tables.order).view(b, n_ang, hw)
    cs = torch.cumsum(g, dim=2, dtype=torch.int32)
    # one flat index_select with the constant run ends reads all cells, and a constant mask
    # zeroes the cells before an angle's first pixel: no per-step (B, A, 2D+1) index or
    # zero constants in the graph, no copy of the prefix sums
    upto = torch.index_select(cs.view(b, n_ang * hw), 1, tables.ends).masked_fill(tables.empty, 0)
    upto = upto.view(b, n_ang, tables.n_rho)
    return upto - torch.cat([torch.zeros_like(upto[:, :, :1]), upto[:, :, :-1]], dim=2)
