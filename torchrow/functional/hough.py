"""Batched Hough voting and peak extraction (ALGORITHM.md section 5).

Voting is a scatter-add (``index_add_``) of the votes of a compact pixel list: the pixels of
each image's mask are moved to the front of a ``(B, K)`` index list by a stable sort (no
``nonzero``), and votes are accumulated in chunks of that list. A chunk loop stops as soon as
no image has pixels left in it (the only host synchronisation, an early exit that never
changes a result). The accumulator row of each (pixel, angle) comes from the shared constant
table :func:`torchrow.shared.rho_index_table` (``rint(x*c_j + y*s_j) + D``, computed once with
NumPy as the reference computes it), so no float arithmetic decides a vote here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..params import Params
from ..shared import hough_trig, rho_index_table, rho_offset
from ._checks import check_masks

__all__ = ["HoughState", "pixel_list", "trig", "rho_table", "line_distance", "accumulate", "votes",
           "excluded_angles", "peak"]

#: List entries processed per chunk when accumulating votes; bounds the ``(n_theta, B, chunk)``
#: int32 index temporaries to ``180 * B * 2048 * 4`` bytes (~94 MB at B = 64).
CHUNK = 2048


def trig(params: Params, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Shared ``(cos, sin)`` of the Hough angles as float64 ``(n_theta,)`` tensors on ``device``."""
    key = ("trig", params.theta_step, str(device))
    if key not in _CACHE:
        c, s = hough_trig(params.theta_step)
        _CACHE[key] = (torch.tensor(c, dtype=torch.float64, device=device),
                       torch.tensor(s, dtype=torch.float64, device=device))
    return _CACHE[key]


def rho_table(height: int, width: int, params: Params, device: torch.device) -> torch.Tensor:
    """Accumulator row of every pixel for every angle, ``(n_theta, H*W)`` int16/int32 on
    ``device``: the shared :func:`torchrow.shared.rho_index_table` (a constant, so voting
    does no float arithmetic and an exported graph votes exactly)."""
    key = ("rho", height, width, params.theta_step, str(device))
    if key not in _CACHE:
        if len([k for k in _CACHE if k[0] == "rho"]) >= 4:
            for k in [k for k in _CACHE if k[0] == "rho"]:
                del _CACHE[k]
        _CACHE[key] = torch.from_numpy(rho_index_table(height, width, params.theta_step).copy()).to(device)
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
    """
    flat = mask.reshape(mask.shape[0], mask.shape[1] * mask.shape[2])
    idx = torch.sort((~flat).to(torch.uint8), dim=1, stable=True).indices
    return idx, flat.sum(dim=1)


def active_width(count: torch.Tensor) -> int:
    """Largest count in the batch: the loop bound of a chunk loop (host sync, early exit only)."""
    return int(count.max()) if count.numel() else 0


def line_distance(xs: torch.Tensor, ys: torch.Tensor, cos_j: torch.Tensor, sin_j: torch.Tensor,
                  rho: torch.Tensor) -> torch.Tensor:
    """``|x*c_j + y*s_j - rho|`` in float64, broadcasting ``(B, 1)`` line parameters over ``(B, K)``."""
    return ((xs.to(torch.float64) * cos_j + ys.to(torch.float64) * sin_j) - rho).abs()


def accumulate(acc: torch.Tensor, pix: torch.Tensor, weight: torch.Tensor, table: torch.Tensor) -> None:
    """Add ``weight`` votes of raster pixels ``pix`` into ``acc`` in place.

    ``acc`` int32 ``(B, n_theta, 2D+1)``; ``pix`` int64 ``(B, C)``; ``weight`` int32 ``(B, C)``;
    ``table`` from :func:`rho_table`. Index order (theta, image, pixel) keeps consecutive
    writes inside one accumulator row, which is what makes the scatter cache-friendly.
    """
    b, n_theta, n_rho = acc.shape
    c = pix.shape[1]
    if c == 0 or b == 0:
        return
    rows = table.index_select(1, pix.reshape(-1)).view(n_theta, b, c).to(torch.int32)
    base = (torch.arange(b, device=acc.device, dtype=torch.int32).view(1, b, 1) * n_theta
            + torch.arange(n_theta, device=acc.device, dtype=torch.int32).view(n_theta, 1, 1)) * n_rho
    acc.view(-1).index_add_(0, (rows + base).view(-1), weight.unsqueeze(0).expand(n_theta, b, c).reshape(-1))


def _vote_list(acc: torch.Tensor, idx: torch.Tensor, count: torch.Tensor, sign: int,
               table: torch.Tensor) -> None:
    """Add ``sign`` votes for the first ``count[b]`` entries of ``idx[b]``, chunk by chunk."""
    n = active_width(count)
    for start in range(0, n, CHUNK):
        sl = idx[:, start:min(start + CHUNK, n)]
        live = (torch.arange(start, start + sl.shape[1], device=idx.device) < count.unsqueeze(1))
        accumulate(acc, sl, live.to(torch.int32) * sign, table)


def votes(mask: torch.Tensor, params: Params) -> torch.Tensor:
    """Hough accumulator of bool ``(B, H, W)`` masks: int32 ``(B, n_theta, 2D+1)``.

    Note the layout: angle before rho (the reference's NumPy accumulator is ``(2D+1, n_theta)``).
    """
    check_masks(mask, "hough input")
    b, h, w = mask.shape
    d = rho_offset(h, w)
    acc = torch.zeros((b, params.n_theta, 2 * d + 1), dtype=torch.int32, device=mask.device)
    idx, count = pixel_list(mask)
    _vote_list(acc, idx, count, 1, rho_table(h, w, params, mask.device))
    return acc


def excluded_angles(held_theta: torch.Tensor, held_valid: torch.Tensor, params: Params) -> torch.Tensor:
    """Step 5.1: bool ``(B, n_theta)`` of angles that cannot be picked.

    ``held_theta`` int64 ``(B, S)`` angle indices of held lines, ``held_valid`` bool ``(B, S)``.
    """
    dev = held_theta.device
    deg = torch.arange(params.n_theta, device=dev) * params.theta_step
    ex = (deg - 90).abs() < params.horizontal_excl
    near = ((deg.view(1, 1, -1) - (held_theta * params.theta_step).unsqueeze(-1)).abs() < params.angle_excl)
    return ex.unsqueeze(0) | (near & held_valid.unsqueeze(-1)).any(dim=1)


def peak(acc: torch.Tensor, excluded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Step 5.2: the maximum cell over allowed angles; ties -> smallest rho index, then theta.

    ``acc`` int32 ``(B, n_theta, 2D+1)``, ``excluded`` bool ``(B, n_theta)``. Returns
    ``(theta_index, rho_index, votes)`` each int64 ``(B,)``; votes 0 means no line.
    """
    # torch.max(dim) does not promise the first index on ties; argmax does.
    colarg = torch.argmax(acc, dim=2)  # (B, n_theta): smallest rho index of each angle's max
    colmax = acc.gather(2, colarg.unsqueeze(2)).squeeze(2).to(torch.int64).masked_fill(excluded, 0)
    best = colmax.max(dim=1, keepdim=True).values
    n_theta = acc.shape[1]
    key = colarg * n_theta + torch.arange(n_theta, device=acc.device)
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
    def start(cls, mask: torch.Tensor, params: Params) -> "HoughState":
        check_masks(mask, "hough input")
        b, h, w = mask.shape
        d = rho_offset(h, w)
        table = rho_table(h, w, params, mask.device)
        idx, count = pixel_list(mask)
        k = active_width(count)
        idx = idx[:, :k]  # entries past the largest count are never mask pixels
        acc = torch.zeros((b, params.n_theta, 2 * d + 1), dtype=torch.int32, device=mask.device)
        _vote_list(acc, idx, count, 1, table)
        alive = torch.arange(k, device=mask.device) < count.unsqueeze(1)
        return cls(idx, count, alive, acc, acc.clone(), w, d, table)

    def xy(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.idx % self.width, self.idx // self.width

    def reset(self, which: torch.Tensor) -> None:
        """Restore the untouched input and votes for images where ``which`` (bool ``(B,)``)."""
        self.acc = torch.where(which.view(-1, 1, 1), self.acc0, self.acc)
        self.alive = torch.where(which.view(-1, 1), torch.arange(self.alive.shape[1], device=which.device)
                                 < self.count.unsqueeze(1), self.alive)

    def erase(self, theta: torch.Tensor, rho: torch.Tensor, active: torch.Tensor, params: Params) -> None:
        """Step 5.3 for images where ``active``: erase alive pixels within ``hough_band/2`` of
        line ``(theta, rho)`` and remove their votes."""
        cos, sin = trig(params, self.acc.device)
        xs, ys = self.xy()
        band = params.hough_band_px(self.width)
        dist = line_distance(xs, ys, cos[theta].unsqueeze(1), sin[theta].unsqueeze(1),
                             rho.to(torch.float64).unsqueeze(1))
        hit = self.alive & (dist <= band / 2) & active.unsqueeze(1)
        self.alive = self.alive & ~hit
        order = torch.sort((~hit).to(torch.uint8), dim=1, stable=True).indices
        _vote_list(self.acc, torch.gather(self.idx, 1, order), hit.sum(dim=1), -1, self.table)
