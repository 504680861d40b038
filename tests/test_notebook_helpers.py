"""Helpers behind the notebooks (torchrow.apps.notebook_helpers), on synthetic fields: no data needed."""

from __future__ import annotations

import numpy as np
import pytest

from torchrow import Params
from torchrow.apps.notebook_helpers import find_data_root, gt_polylines, result_summary, show_grid, stage_pictures
from torchrow.evaluation.datasets import GroundTruth
from torchrow.evaluation.synthetic import FieldSpec, render


def test_find_data_root(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHROW_DATA", str(tmp_path / "x"))
    assert find_data_root() == tmp_path / "x"
    monkeypatch.delenv("TORCHROW_DATA")
    repo = tmp_path / "repo"
    (repo / "notebooks").mkdir(parents=True)
    (repo / "pyproject.toml").write_text("")
    with pytest.raises(FileNotFoundError, match="TORCHROW_DATA"):
        find_data_root(repo / "notebooks")
    (tmp_path / "shared" / "data").mkdir(parents=True)
    assert find_data_root(repo / "notebooks") == tmp_path / "shared" / "data"


def test_gt_polylines_inside_image():
    gt = GroundTruth(c=np.zeros(4), d=np.full(4, 100.0), v0=6, height=10)
    lines = gt_polylines(gt, 320, shifts=range(-3, 4))
    assert len(lines) == 3  # x = 60, 160, 260; the others fall outside [0, 319]
    for ys, xs in lines:
        assert ys.tolist() == [6, 7, 8, 9] and ((xs >= 0) & (xs <= 319)).all()


def test_stage_pictures_and_grid():
    import matplotlib

    matplotlib.use("Agg")
    fld = render(FieldSpec(seed=5))
    h, w = fld.image.shape[:2]
    gt = GroundTruth(c=fld.crp[:, 0], d=fld.crp[:, 1], v0=fld.sky, height=h)
    pics = stage_pictures(fld.image, Params(), gt=gt)
    assert pics["input"].shape == (h, w, 3) and pics["detection"].shape[1:] == (2 * w, 3) and pics["detection"].shape[0] > 2 * h
    for k in ("raw mask", "vegetation", "hough input"):
        assert pics[k].shape == (h, w) and pics[k].dtype == bool
    assert pics["hough votes"].shape[0] == 180 and pics["hough votes"].sum() > 0
    assert (pics["colour"] == np.array(pics["result"].veg_color, np.uint8)).all()
    fixed = stage_pictures(fld.image, Params(), veg_color=pics["result"].veg_color)
    assert fixed["result"].to_record() == pics["result"].to_record()
    assert "valid rows" in result_summary(pics["result"])
    fig = show_grid([pics["input"], pics["raw mask"], pics["hough votes"]], ["a", "b", "c"], ncols=2)
    assert len(fig.axes) == 4
    import matplotlib.pyplot as plt

    plt.close(fig)
