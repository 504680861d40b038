"""Stability of a tracked sequence without labels: how far row 0 moves from frame to frame.

The lattice tracker's criterion for real video, where nothing is labelled (ALGORITHM.md 11.7,
*Stability*): between consecutive frames row 0 moves by less than a quarter of the row spacing,
except on a frame that reports a row change. :func:`row_moves` measures it on the
records of ``torchrow video --mode improved`` (dicts as written to JSONL, or as
:meth:`FrameResult.to_record` returns them), independently of the tracker's own state.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from torchrow.core.results import Row

__all__ = ["bottom_x", "RowMove", "RowMoves", "row_moves"]

#: The share of the row spacing row 0 may move between two frames (ALGORITHM.md 11.7, *Stability*).
QUARTER = 0.25


def bottom_x(row: Mapping[str, Any], height: int) -> float | None:
    """Bottom-row x (px, working image) of a record's row: ``x = e y^3 + c y^2 + a y + b`` at
    ``y = height - 1``; ``None`` for an invalid row or one without finite coefficients (``c`` and
    ``e`` null or absent count as 0, as in faithful records)."""
    if not row.get("valid") or row.get("a") is None or row.get("b") is None:
        return None
    x = float(Row(a=row["a"], b=row["b"], valid=True, c=row.get("c") or 0.0, e=row.get("e") or 0.0).x_at(
        float(height - 1)))
    return x if math.isfinite(x) else None


@dataclass(frozen=True)
class RowMove:
    """Row 0's move into frame ``frame`` from the frame before it.

    ``px``: ``|x_0(t) - x_k(t-1)|`` at the bottom row, with ``k`` = the frame's ``row_change`` (its
    row 0 is the previous frame's row ``k``); ``spacing``: the bottom-row spacing of frame ``t``
    around row 0 (px; the mean of the gaps to rows -1 and +1 where both are valid, else the one
    that is); ``frac = px / spacing``; ``full``: frame ``t`` ran the full search (``hough_ran``)."""

    frame: int
    px: float
    spacing: float
    frac: float
    full: bool


@dataclass(frozen=True)
class RowMoves:
    """:func:`row_moves` of one sequence: ``moves`` in frame order; ``pairs`` = consecutive frame
    pairs seen; ``skipped`` = those not measured (a frame without a valid row 0 or neighbour, a
    frame not ``in_row``/``row_end_ahead``, or a gap in the frame numbers)."""

    moves: tuple[RowMove, ...]
    pairs: int
    skipped: int

    def above(self, share: float = QUARTER) -> tuple[RowMove, ...]:
        """The moves of more than ``share`` of the row spacing."""
        return tuple(m for m in self.moves if m.frac > share)

    @property
    def median(self) -> float:
        """Median ``frac`` (NaN without a move)."""
        return float(np.median([m.frac for m in self.moves])) if self.moves else math.nan

    @property
    def largest(self) -> RowMove | None:
        """The move with the largest ``frac`` (the first on ties), ``None`` without a move."""
        return max(self.moves, key=lambda m: m.frac) if self.moves else None


_TRACKING = ("in_row", "row_end_ahead")


def _row0(rec: Mapping[str, Any]) -> tuple[list[float | None], int] | None:
    rows = rec.get("rows") or []
    if rec.get("state") not in _TRACKING or len(rows) % 2 != 1:
        return None
    h = int(rec.get("height") or 0)
    return [bottom_x(r, h) for r in rows], len(rows) // 2


def row_moves(records: Iterable[Mapping[str, Any]]) -> RowMoves:
    """How far row 0 moves between consecutive frames of one lattice-tracker sequence.

    ``records``: one source's records in frame order (the lattice tracker's: ``state``,
    ``row_change``, ``rows`` with row 0 in the middle slot). A pair ``(t-1, t)`` is measured when
    the frame numbers follow each other, both frames are ``in_row`` or ``row_end_ahead``, row 0
    of frame ``t`` and row ``row_change`` of frame ``t-1`` are valid, and frame ``t`` has a valid
    row -1 or +1 (the spacing). A frame that reports a row change is measured against the row it
    names, so a deliberate change is not a move; a move of more than a quarter spacing anywhere
    counts against the tracker (:meth:`RowMoves.above`).
    """
    moves: list[RowMove] = []
    pairs = skipped = 0
    for prev, cur in itertools.pairwise(records):
        pairs += 1
        a, b = _row0(prev), _row0(cur)
        step = prev.get("frame") is not None and cur.get("frame") == prev["frame"] + 1
        if a is None or b is None or not step:
            skipped += 1
            continue
        (xp, kp), (xc, kc) = a, b
        ch = int(cur.get("row_change") or 0)
        was = xp[kp + ch] if 0 <= kp + ch < len(xp) else None
        now = xc[kc]
        side = [xc[j] for j in (kc - 1, kc + 1) if 0 <= j < len(xc)]
        gaps = [abs(x - now) for x in side if x is not None] if now is not None else []
        if was is None or now is None or not gaps or sum(gaps) == 0:
            skipped += 1
            continue
        d = sum(gaps) / len(gaps)
        px = abs(now - was)
        moves.append(RowMove(int(cur["frame"]), px, d, px / d, bool(cur.get("hough_ran"))))
    return RowMoves(tuple(moves), pairs, skipped)
