"""Pictures a person reads without the code, and CLI wording (issue 14)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from torchrow.apps.annotate import INVALID, VALID, draw_result, legend_entries, row_top
from torchrow.apps.cli import main
from torchrow.apps.video import VideoWriter, draw_frame
from torchrow.core.results import ImageResult, LatticeRow, Row


def _result(**kw) -> ImageResult:
    base = dict(width=80, height=60, status="invalid", sky=10, vp=(40.0, 20.0),
                rows=[Row(a=0.5, b=20.0, valid=True, reason=""), Row(a=-0.5, b=60.0, valid=False, reason="horizon")])
    base.update(kw)
    return ImageResult(**base)


def test_legend_names_every_mark_shown():
    res = _result()
    texts = [e[2] for e in legend_entries(res, ground_truth=True)]
    assert any("detected row" in t for t in texts) and any("invalid" in t for t in texts)
    assert any("horizon" in t for t in texts) and any("ground truth" in t for t in texts)
    assert any(t == "vanishing point" for t in texts)
    outside = legend_entries(_result(vp=(40.0, -300.0), sky=0, rows=[Row(a=0.1, b=5.0, valid=True, reason="")]))
    texts = [e[2] for e in outside]
    assert not any("horizon" in t or "invalid" in t for t in texts)
    assert any("outside the picture" in t for t in texts)
    # improved mode: sky is the lattice's first row, and its other visible rows are drawn thin
    lattice = [LatticeRow(k, 0.1 * k, 40.0 + 20 * k, 0.0, 0.0, 0.5) for k in (-2, -1, 0, 1)]
    improved = [e[2] for e in legend_entries(_result(image_confidence=0.8, lattice_rows=lattice))]
    assert "horizon (rows above ignored)" in improved and "other visible row of the lattice" in improved
    three = [Row(a=0.1 * k, b=40.0 + 20 * k, valid=True, reason="") for k in (-1, 0, 1)]
    alone = [e[2] for e in legend_entries(_result(image_confidence=0.8, rows=three, lattice_rows=lattice[1:]))]
    assert "other visible row of the lattice" not in alone


def test_picture_has_legend_strip_and_rows_start_below_vp():
    rgb = np.full((60, 80, 3), 90, np.uint8)
    res = _result()
    img = draw_result(rgb, res, scale=2)
    assert img.shape[1] == 160 and img.shape[0] > 120 and img.dtype == np.uint8
    assert np.array_equal(draw_result(rgb, res, scale=2, with_legend=False).shape, (120, 160, 3))
    assert row_top(res, 60) == 20.0  # vanishing point inside, below the horizon
    assert row_top(_result(vp=(40.0, -50.0)), 60) == 10.0  # outside: the horizon
    # improved mode (no section-6 VP): where the outermost rows come within 1 px; rows through
    # (40, 24) with 15 px between neighbours at the bottom row 59 are 30 px apart there, 1 px
    # apart 7/6 rows below the VP, so rows are drawn from row 26 on
    fan = [Row(a=15.0 * k / 35.0, b=40.0 - 15.0 * k * 24.0 / 35.0, valid=True, reason="") for k in (-1, 0, 1)]
    assert row_top(_result(vp=None, sky=0, rows=fan), 60) == 26.0
    assert row_top(_result(vp=None, sky=0, rows=fan[:1]), 60) == 0.0  # one row: nothing to cross
    parallel = [Row(a=0.0, b=20.0 * k + 40.0, valid=True, reason="") for k in (-1, 0, 1)]
    assert row_top(_result(vp=None, sky=5, rows=parallel), 60) == 5.0  # never within 1 px: the horizon
    pic = draw_result(rgb, res, scale=2, with_legend=False)
    above = pic[: 2 * 20 - 2]  # nothing of either row above the vanishing point
    assert not np.any(np.all(above == VALID, axis=2)) and not np.any(np.all(above == INVALID, axis=2))
    assert np.all(rgb == 90)  # input untouched


def test_video_frame_without_fov_has_no_placeholder(monkeypatch):
    import cv2

    from torchrow.core.steering import FrameResult

    seen: list[str] = []
    real = cv2.putText
    monkeypatch.setattr(cv2, "putText", lambda img, text, *a, **k: (seen.append(text), real(img, text, *a, **k))[1])
    base = _result()
    fields = {k: getattr(base, k) for k in ImageResult.__dataclass_fields__}
    res = FrameResult(**fields, frame=3, confidence=0.5, heading_px=-4.0, heading_rad=None, lateral_px=2.0,
                      lateral_frac=0.1)
    img = draw_frame(np.full((60, 80, 3), 90, np.uint8), res)
    assert img.shape[1] == 160 and img.shape[0] > 120
    assert [t for t in seen if t.startswith("heading")] == ["heading -4.0 px"]
    assert "lateral offset +2.0 px / +0.10 rows" in seen and not any(t.endswith("/ -") for t in seen)
    # a frame with an invalid row and no VP has the same size: a video keeps its first frame's size
    rows = [dataclasses.replace(r, valid=False) for r in res.rows]
    other = dataclasses.replace(res, rows=rows, vp=None, lateral_px=None, lateral_frac=None)
    assert draw_frame(np.full((60, 80, 3), 90, np.uint8), other).shape == img.shape


def _lattice_frame(**kw):
    """A lattice tracker frame (160x90 working image): rows k = -1, 0, 1 of 3 visible lattice rows."""
    from torchrow.core.steering import FrameResult

    rows = [Row(a=0.4 * k, b=80.0 + 40 * k, valid=True, reason="") for k in (-1, 0, 1)]
    lattice = [LatticeRow(k, 0.4 * k, 80.0 + 40 * k, 0.0, 0.0, 0.8) for k in (-1, 0, 1)]
    base = dict(width=160, height=90, status="ok", rows=rows, lattice_rows=lattice, frame=7, confidence=0.8,
                lateral_px=0.0, lateral_frac=0.0, lateral_m=0.0, heading_rad=0.05, spacing_m=0.5,
                state="in_row", row_change=0)
    base.update(kw)
    return FrameResult(**base)


def test_lattice_frame_shows_state_row_id_and_row_change(monkeypatch):
    import cv2

    from torchrow.apps.video import STATE_COLORS, TRACKED
    from torchrow.core.steering import RowId

    seen: list[str] = []
    real = cv2.putText
    monkeypatch.setattr(cv2, "putText", lambda img, text, *a, **k: (seen.append(text), real(img, text, *a, **k))[1])
    rgb = np.full((90, 160, 3), 90, np.uint8)

    def badge(img: np.ndarray, color) -> bool:  # the state badge (its colour is in the legend too)
        return bool(np.all(img[:180] == color, axis=2).any())

    ids = RowId()
    assert [ids.update(c) for c in (0, 1, None, 0, -1, -1)] == [0, 1, 1, 1, 0, -1]
    steady = draw_frame(rgb, _lattice_frame(), row_id=0)
    assert steady.shape[:2][1] == 320 and steady.shape[0] > 180 and badge(steady, STATE_COLORS["in_row"])
    assert "row 0" in seen and "IN ROW" in seen and "heading +2.9 deg" in seen
    # row 0 (x = 80 px) thick and pink; row 1 (x = 0.4 * y + 120 px) thin cyan
    assert np.all(steady[150, 150:170] == TRACKED, axis=1).sum() >= 3
    assert (np.abs(steady[150, 290:310].astype(int) - VALID).sum(axis=1) < 120).sum() in (1, 2)
    change = draw_frame(rgb, _lattice_frame(row_change=1), row_id=1)
    assert "ROW CHANGE row 0 -> row +1" in seen and "row +1" in seen
    assert np.all(change[2, :] == TRACKED) and not np.all(steady[2, :] == TRACKED)  # the frame's border flashes
    seen.clear()
    end = draw_frame(rgb, _lattice_frame(state="row_end_ahead", row_end_y=60, row_end_m=4.2), row_id=1)
    assert "ROW END 4.2 m" in seen and badge(end, STATE_COLORS["row_end_ahead"])
    assert np.all(end[120] == STATE_COLORS["row_end_ahead"], axis=1).sum() > 40  # the dashed mark at image row 60
    draw_frame(rgb, _lattice_frame(state="row_end_ahead", row_end_y=30, lateral_m=None, heading_rad=None,
                                   spacing_m=None))
    assert "ROW END y=30 px" in seen and "row 0 (tracked)" in seen
    lost = draw_frame(rgb, _lattice_frame(status="weak", state="lost", lateral_px=None, lateral_m=None))
    assert badge(lost, STATE_COLORS["lost"]) and not np.all(lost[:180] == TRACKED, axis=2).any()
    # one legend for every frame: the frames of a video keep one size
    assert steady.shape == change.shape == end.shape == lost.shape


def test_lattice_plot_written(tmp_path: Path):
    from torchrow.apps.video import plot_tracks
    from torchrow.core.steering import FrameResult

    recs = [_lattice_frame(frame=i, row_change=int(i == 2), hough_ran=i in (0, 3),
                           state="row_end_ahead" if i >= 3 else "in_row", row_end_y=20 if i >= 3 else None,
                           row_end_m=3.0 - 0.5 * i if i >= 3 else None).to_record() for i in range(5)]
    recs.append(FrameResult.failed_frame("s", 5, "f5.png", "unreadable").to_record())
    # a source with a camera model (metres, degrees) and one without (pixels)
    plot_tracks({"s": recs, "t": [dict(r, lateral_m=None, heading_rad=None, row_end_m=None) for r in recs]},
                tmp_path / "plot.png")
    assert (tmp_path / "plot.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("suffix", [".mp4", ".avi"])
def test_video_writer_codec_and_rate(tmp_path: Path, suffix: str):
    av = pytest.importorskip("av")
    path = tmp_path / f"v{suffix}"
    vw = VideoWriter(path, fps=12.5)
    for i in range(6):
        vw.write(np.full((31, 45, 3), 20 * i, np.uint8))  # odd size: padded for H.264
    vw.close()
    with av.open(str(path)) as c:
        s = c.streams.video[0]
        assert s.codec_context.name == ("h264" if suffix == ".mp4" else "mjpeg")
        assert abs(float(s.average_rate or s.guessed_rate) - 12.5) < 1e-6
        assert sum(1 for _ in c.decode(video=0)) == 6
    with pytest.raises(ValueError, match="fps"):
        VideoWriter(path, fps=0)


def test_bad_param_lists_valid_names(capsys):
    assert main(["demo", "--param", "nrows=3"]) == 2
    err = capsys.readouterr().err
    assert "'nrows'" in err and "n_rows" in err and "valid names" in err and len(err.strip().splitlines()) == 1


def test_data_errors_name_the_cli_words(monkeypatch, tmp_path: Path, capsys):
    monkeypatch.delenv("TORCHROW_DATA", raising=False)
    monkeypatch.chdir(tmp_path)
    for argv in (["eval"], ["score", "--results", "."]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "--data" in err and "TORCHROW_DATA" in err and "root=" not in err


@pytest.mark.data
def test_eval_without_out_leaves_its_report(crbd_dir, monkeypatch, tmp_path: Path, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--data", str(crbd_dir), "--every", "140", "-q", "--impl", "reference"]) == 0
    assert (tmp_path / "torchrow-eval" / "summary.json").is_file()
    assert "torchrow-eval" in capsys.readouterr().err


def test_progress_plain_lines_when_not_a_terminal():
    import io

    from torchrow.core.progress import PlainProgress, progress

    buf = io.StringIO()  # not a terminal
    bar = progress(100, "detect", unit="image", file=buf)
    assert isinstance(bar, PlainProgress)
    with bar:
        for _ in range(100):
            bar.update(1)
    text = buf.getvalue()
    assert "\r" not in text and text.count("\n") <= 12
    assert text.splitlines()[0] == "detect: started, 100 image(s)" and "100/100" in text.splitlines()[-1]
    silent = io.StringIO()
    with progress(10, "x", enabled=False, file=silent) as s:
        s.update(10)
    assert silent.getvalue() == ""


def test_central_jumps_leave_out_row_change_frames():
    from torchrow.apps.video import central_jumps

    def rec(frame, x, **kw):  # one valid vertical row at bottom x (a = 0, b = x)
        return {"frame": frame, "width": 100, "height": 50, "status": "ok", "hough_ran": False,
                "rows": [{"a": 0.0, "b": x, "valid": True}], **kw}

    steady = [rec(0, 50.0), rec(1, 52.0), rec(2, 20.0, row_change=1), rec(3, 21.0)]
    jumps = central_jumps(steady)
    assert jumps["tracked"] == [2.0, 1.0]  # the relabelled frame 2 is no jump of row 0
    assert central_jumps(steady[:3] + [rec(3, 60.0)])["tracked"] == [2.0, 40.0]
    # a bent row (the improved mode's): its bottom x is the whole polynomial's, x(49) = 74.01
    bent = {"a": 0.0, "b": 50.0, "c": 0.01, "e": 0.0, "valid": True}
    assert central_jumps([rec(0, 50.0), {**rec(1, 0.0), "rows": [bent]}])["tracked"] == [pytest.approx(24.01)]
