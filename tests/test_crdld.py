"""CRDLD: ground truth from label masks, the score, the reader's layouts and ``eval --dataset crdld``."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchrow.apps.cli import main
from torchrow.core.results import Row
from torchrow.evaluation.crdld import CUT_PX, central_mae, extract_lines, score, score_image, summarize, truth_from_mask
from torchrow.evaluation.datasets import CRDLD


def _vertical_mask(xs, size: int = 160, thickness: int = 3) -> np.ndarray:
    """Vertical lines (odd thickness: every run's centre is exactly x) on a black square mask."""
    m = np.zeros((size, size), np.uint8)
    for x in xs:
        cv2.line(m, (x, 0), (x, size - 1), 255, thickness)
    return m


def _rows(xs, scale: float = 1.0, valid: bool = True) -> list[Row]:
    return [Row(a=0.0, b=x * scale, valid=valid) for x in xs]


def test_converging_lines_are_linked_and_cut_where_they_merge() -> None:
    # a 128 px mask of three lines meeting at (64, 10), scored on a 256 px image: the mask is scaled first
    m = np.zeros((128, 128), np.uint8)
    for xb in (16, 64, 112):
        cv2.line(m, (xb, 127), (64, 10), 255, 2)
    lines = extract_lines(m, 256, 256)
    assert len(lines) == 3
    vp = np.array([128.0, 20.0])  # the meeting point at 256 px
    bottoms = np.array([32.0, 128.0, 224.0])
    for line, xb in zip(lines, bottoms):  # left to right, each on its drawn line
        y, x = line[:, 0], line[:, 1]
        assert np.all(np.diff(y) == 1)
        true_x = vp[0] + (xb - vp[0]) * (y - vp[1]) / (255 - vp[1])
        assert np.max(np.abs(x - true_x)) < 2.0  # one mask pixel, scaled by 2
    # neighbours are (y - 20) * 96 / 235 px apart: within CUT_PX above y = 20 + 12 * 235 / 96
    truth = truth_from_mask(m, 256, 256)
    cut_expected = 20 + CUT_PX * 235 / 96
    assert abs(truth.cut - cut_expected) <= 3
    assert min(line[0, 0] for line in lines) == truth.cut + 1
    assert truth.central == 1 and truth.scored == (0, 1, 2)


def test_perfect_detection_scores_one_and_sigma_d_off_scores_zero() -> None:
    xs = (40, 80, 120)  # d = 40 px everywhere
    truth = truth_from_mask(_vertical_mask(xs), 160, 160)
    assert truth.cut == -1 and truth.central == 1
    assert score_image(_rows(xs), "ok", truth) == 1.0
    # rows found at half the working size score the same once scaled back to the image
    assert score_image(_rows(xs, 0.5), "ok", truth, working_size=(80, 80)) == 1.0
    for sigma in (0.1, 0.3):
        off = _rows([x + sigma * 40 for x in xs])
        assert score_image(off, "ok", truth, sigma=sigma) == 0.0
        half = _rows([x + sigma * 20 for x in xs])
        assert score_image(half, "ok", truth, sigma=sigma) == pytest.approx(0.75)


def test_no_valid_row_or_error_scores_zero_and_empty_truth_is_undefined() -> None:
    xs = (40, 80, 120)
    truth = truth_from_mask(_vertical_mask(xs), 160, 160)
    assert score_image([], "no_vp", truth) == 0.0
    assert score_image(_rows(xs, valid=False), "invalid", truth) == 0.0
    assert score_image(_rows(xs), "error", truth) == 0.0
    assert np.isnan(central_mae([], "no_vp", truth))
    empty = truth_from_mask(np.zeros((32, 32), np.uint8), 160, 160)
    assert empty.lines == () and empty.n_pairs == 0
    assert np.isnan(score_image(_rows(xs), "ok", empty))
    single = truth_from_mask(_vertical_mask((80,)), 160, 160)  # one line: no spacing to score against
    assert len(single.lines) == 1 and np.isnan(score_image(_rows((80,)), "ok", single))


def test_only_the_central_line_and_its_neighbours_count() -> None:
    xs = (20, 50, 80, 110, 140)
    truth = truth_from_mask(_vertical_mask(xs), 160, 160)
    assert truth.central == 2 and truth.scored == (1, 2, 3)
    assert score_image(_rows((50, 80, 110)), "invalid", truth) == 1.0
    assert score_image(_rows((20, 140)), "ok", truth) == 0.0
    # uneven spacing: d is the mean of both sides where both exist
    uneven = truth_from_mask(_vertical_mask((40, 80, 140)), 160, 160)
    assert [float(np.nanmax(uneven.spacing[k])) for k in range(3)] == [40.0, 50.0, 60.0]


def test_central_mae_and_record_scores() -> None:
    xs = (40, 80, 120)
    truth = truth_from_mask(_vertical_mask(xs), 160, 160)
    assert central_mae(_rows([83]), "ok", truth) == pytest.approx(3.0)
    rec = {"status": "ok", "width": 80, "height": 80,
           "rows": [{"a": 0.0, "b": x / 2, "c": 0.0, "e": 0.0, "valid": True} for x in xs] +
                   [{"a": None, "b": None, "c": 0.0, "e": 0.0, "valid": False}]}
    s = score(rec, truth)
    assert (s.sigma01, s.sigma03, s.central_mae) == (1.0, 1.0, 0.0)
    summary = summarize(["ok", "error"], [s, score({"status": "error"}, truth)])
    assert (summary.mean01, summary.ok_fraction, summary.ok_low_fraction) == (0.5, 0.5, 0.0)
    assert summary.statuses == {"error": 1, "ok": 1}


def _write_split(split: Path, numbers=(0, 1, 2, 10), size: int = 64) -> None:
    (split / "image").mkdir(parents=True)
    (split / "label").mkdir()
    img = np.full((size, size, 3), (40, 70, 110), np.uint8)  # brown soil (BGR) ...
    for x in (size // 4, size // 2, 3 * size // 4):
        img[size // 4:, x - 2:x + 2] = (40, 160, 50)  # ... with green rows below a horizon
    for n in numbers:
        cv2.imwrite(str(split / "image" / f"{n}.jpg"), img)
        cv2.imwrite(str(split / "label" / f"{n}.jpg"), _vertical_mask((8, 16, 24), 32, 1))


def test_reader_layouts_order_and_errors(tmp_path: Path, monkeypatch) -> None:
    data = tmp_path / "data"
    for split in ("train", "test"):
        _write_split(data / "crdld_dev" / split)
    top = data / "crdld_dev"
    ds = CRDLD(top / "train")
    assert ds.names == ["0.jpg", "1.jpg", "2.jpg", "10.jpg"] and ds.root == top / "train"
    assert CRDLD(top, "test").root == top / "test"
    monkeypatch.setenv("TORCHROW_DATA", str(data))
    assert CRDLD(split="train").root == top / "train"
    assert ds.image(3).shape == (320, 320, 3) and ds.image(3, None).shape == (64, 64, 3)
    truth = ds.ground_truth(1)  # a 32 px label, scaled to the 64 px image
    assert truth.width == 64 and len(truth.lines) == 3
    assert [round(float(line[:, 1].mean())) for line in truth.lines] == [16, 32, 48]
    item = ds[-1]
    assert item.name == "10.jpg" and item.label_path == top / "train" / "label" / "10.jpg"
    with pytest.raises(FileNotFoundError, match=r"not a CRDLD folder .*image/N\.jpg and label/N\.jpg"):
        CRDLD(tmp_path)
    (top / "test" / "label" / "2.jpg").unlink()
    with pytest.raises(FileNotFoundError, match=r"1 label\(s\) missing, e\.g\. for image/2\.jpg"):
        CRDLD(top, "test")
    with pytest.raises(ValueError, match="unknown CRDLD split 'val'"):
        CRDLD(top, "val")


def test_cli_eval_crdld_writes_the_report(tmp_path: Path, capsys) -> None:
    _write_split(tmp_path / "crdld" / "test", numbers=(0, 1))
    out = tmp_path / "eval"
    argv = ["eval", "--dataset", "crdld", "--data", str(tmp_path / "crdld"), "--out", str(out), "-q",
            "--impl", "reference", "--param", "image_width=64"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "CRDLD test: 2 images, 2 with a scorable label" in text and "score sigma 0.3" in text
    assert "ok images scoring below 0.2" in text
    for f in ("scores.csv", "detections.jsonl", "summary.json", "crda_histogram.png"):
        assert (out / f).is_file()
    with open(out / "scores.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["name"] for r in rows] == ["0.jpg", "1.jpg"]
    assert "tmgem_sigma0.1" not in rows[0] and all(0.0 <= float(r["crdld_sigma0.1"]) <= 1.0 for r in rows)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset"] == "crdld" and summary["n"] == 2 and sum(summary["statuses"].values()) == 2
    # --resume scores the streamed records again without detecting (seconds unknown)
    assert main(argv + ["--resume"]) == 0
    with open(out / "scores.csv") as fh:
        again = list(csv.DictReader(fh))
    assert [r["crdld_sigma0.1"] for r in again] == [r["crdld_sigma0.1"] for r in rows]
    assert all(r["seconds"] == "nan" for r in again)
    capsys.readouterr()
    assert main(["eval", "--split", "train", "--out", str(out), "-q"]) == 2  # --split is CRDLD's
    assert "--split is for --dataset crdld" in capsys.readouterr().err


@pytest.mark.data
def test_three_real_test_images(data_dir: Path) -> None:
    root = data_dir / "crdld_dev" / "test"
    if not (root / "label").is_dir():
        pytest.skip(f"CRDLD not found under {data_dir}")
    ds = CRDLD(root)
    for i in (0, 1, 2):
        truth = ds.ground_truth(i)
        assert (truth.width, truth.height) == (512, 512)
        assert len(truth.lines) >= 3 and truth.n_pairs > 500 and truth.cut < 256
        fit = [Row(*np.polyfit(line[:, 0], line[:, 1], 1), valid=True) for line in truth.lines]
        assert score_image(fit, "ok", truth) > 0.95  # the labels are near-straight
        shifted = [Row(r.a, r.b + 60.0, True) for r in fit]
        assert score_image(shifted, "ok", truth) < score_image(fit, "ok", truth)
