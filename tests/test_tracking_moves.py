"""torchrow.evaluation.tracking.row_moves: the stability measure of lattice-tracker records (ALGORITHM.md 11.7)."""

from __future__ import annotations

import math

import pytest

from torchrow.evaluation.tracking import QUARTER, bottom_x, row_moves


def rec(frame, bottoms, *, state="in_row", change=0, full=False, height=50):
    """A record whose rows are vertical lines at ``bottoms`` (``None``: an invalid row), row 0 in the middle."""
    rows = [{"a": 0.0, "b": x, "valid": True} if x is not None else {"a": None, "b": None, "valid": False}
            for x in bottoms]
    return {"frame": frame, "height": height, "width": 200, "state": state, "row_change": change,
            "hough_ran": full, "rows": rows}


def test_moves_in_spacings_and_a_row_change_is_no_move():
    recs = [rec(0, [50, 100, 150]), rec(1, [52, 102, 152]),
            # the robot crossed to the right: row 0 is the previous frame's row +1 (152 -> 150)
            rec(2, [100, 150, 200], change=1),
            rec(3, [110, 165, 220], full=True)]  # 15 px of a 55 px spacing: above a quarter
    m = row_moves(recs)
    assert (m.pairs, m.skipped) == (3, 0)
    assert [(x.frame, x.px, x.spacing) for x in m.moves] == [(1, 2.0, 50.0), (2, 2.0, 50.0), (3, 15.0, 55.0)]
    assert [x.frame for x in m.above()] == [3] and m.above()[0].full and m.largest.frame == 3
    assert m.median == pytest.approx(0.04) and m.above(0.3) == ()
    # unlabelled, the same change is a move of a whole spacing
    assert row_moves([recs[1], {**recs[2], "row_change": 0}]).largest.frac == pytest.approx(0.96)


def test_pairs_without_a_tracked_row_0_are_counted_not_measured():
    recs = [rec(0, [50, 100, 150]), rec(1, [50, 100, 150], state="lost"),  # lost: no row 0
            rec(2, [50, 100, 150]), rec(4, [50, 100, 150]),  # a gap in the frames
            rec(5, [50, None, 150]),  # row 0 invalid
            rec(6, [None, 101, 150]), rec(7, [None, 101, 150]),  # one neighbour gives the spacing
            rec(8, [None, 101, None]),  # none: not measured
            rec(9, [50, 100, 150], state="row_end_ahead")]
    m = row_moves(recs)
    assert (m.pairs, m.skipped) == (8, 6)
    assert [(x.frame, x.px, x.spacing) for x in m.moves] == [(7, 0.0, 49.0), (9, 1.0, 50.0)]
    empty = row_moves([])
    assert (empty.pairs, empty.moves, empty.largest) == (0, (), None) and math.isnan(empty.median)


def test_bottom_x_of_bent_and_invalid_rows():
    assert bottom_x({"a": 0.0, "b": 50.0, "c": 0.01, "e": None, "valid": True}, 50) == pytest.approx(74.01)
    assert bottom_x({"a": 1.0, "b": 0.0, "c": 0.0, "e": 1e-3, "valid": True}, 11) == pytest.approx(11.0)
    assert bottom_x({"a": None, "b": None, "valid": False}, 50) is None
    assert bottom_x({"a": float("nan"), "b": 1.0, "valid": True}, 50) is None
    assert QUARTER == 0.25


def test_the_video_summary_line_names_the_moves_above_a_quarter():
    from torchrow.apps.video import moves_line

    recs = [rec(0, [50, 100, 150]), rec(1, [52, 102, 152]), rec(2, [70, 120, 170], full=True),
            rec(3, [70, 120, 170], state="lost")]
    line = moves_line(row_moves(recs))
    assert "at most 0.36 (18.0 px into full-search frame 2)" in line
    assert "1 of 2 above a quarter spacing (frame 2)" in line and "1 frame pair(s) not measured" in line
    assert moves_line(row_moves(recs[2:])).startswith("row 0 moves: none measured (1 of 1 frame pairs")
