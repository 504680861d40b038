"""CRBD loader: a synthetic copy of the release layout, and the real data where present."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from torchrow.evaluation.datasets import CRBD, CRBDItem, GroundTruth, resolve_data_root


# --- a tiny fake CRBD -------------------------------------------------------------------------
def make_crbd(root: Path, *, classification=True, tmgem=True, size=(64, 48)) -> Path:
    """Three images (numbers 1, 2, 10; mixed extension case), GT with fewer lines than rows."""
    w, h = size
    (root / "Images").mkdir(parents=True)
    (root / "GT data").mkdir()
    rng = np.random.default_rng(0)
    files = {1: "crop_row_001.jpg", 2: "crop_row_002.JPG", 10: "crop_row_010.JPG"}
    for k, name in files.items():
        img = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
        ok, buf = cv2.imencode(".jpg", img)
        assert ok
        (root / "Images" / name).write_bytes(buf.tobytes())
        n = h - 8 if k != 10 else h
        lines = "".join(f"{0.5 * i:.6f}\t{10 + 0.1 * i:.6f}\n" for i in range(n))
        (root / "GT data" / f"crop_row_{k:03d}.crp").write_text(lines)
    (root / "Images" / "notes.txt").write_text("not an image\n")
    if classification:
        # names as in the release: sometimes the case differs from the file on disk
        (root / "Images" / "imageClassification.txt").write_text(
            "crop_row_001.JPG\t1\ncrop_row_002.JPG\t2\ncrop_row_010.JPG\t2")
        (root / "Images" / "imageClassificationTMGEM.txt").write_text(
            "crop_row_001.JPG\t0\ncrop_row_002.jpg\t1\ncrop_row_010.JPG\t2\n")
    if tmgem:
        (root / "TMGEM results").mkdir()
        for k in files:
            (root / "TMGEM results" / f"crop_row_{k:03d}.tmg").write_text(
                "".join(f"{10.0:.6f}\t{20.0 + i:.6f}\t{30.0:.6f}\t\n" for i in range(h)))
    return root


def test_fake_layout_both_extensions_sorted(tmp_path):
    ds = CRBD(make_crbd(tmp_path / "crbd"))
    assert len(ds) == 3
    assert ds.names == ["crop_row_001.jpg", "crop_row_002.JPG", "crop_row_010.JPG"]
    assert ds.stems == ["crop_row_001", "crop_row_002", "crop_row_010"]
    # a data folder holding crbd/ works too
    assert CRBD(tmp_path).names == ds.names
    it = ds[0]
    assert isinstance(it, CRBDItem)
    assert (it.name, it.stem, it.row_set, it.tmgem_set) == ("crop_row_001.jpg", "crop_row_001", 1, 0)
    assert it.image_path == tmp_path / "crbd" / "Images" / "crop_row_001.jpg"
    assert ds[-1].stem == "crop_row_010"
    with pytest.raises(IndexError):
        ds[3]
    with pytest.raises(AttributeError):
        it.name = "x"  # frozen


def test_index_must_be_an_integer(tmp_path):
    """Issue 26.18: CRBD.image(1.5) returned image 1."""
    ds = CRBD(make_crbd(tmp_path))
    for bad in (1.5, 1.0, np.float64(1), "1", True):
        for get in (ds.image, ds.image_path, ds.ground_truth, ds.__getitem__):
            with pytest.raises(TypeError, match="CRBD index must be an integer"):
                get(bad)
    assert ds.image_path(np.int64(1)) == ds.image_path(1) == ds.image_path(-2)


def test_fake_ground_truth_image_and_tmgem(tmp_path):
    ds = CRBD(make_crbd(tmp_path, size=(64, 48)))
    gt = ds.ground_truth(0)
    assert isinstance(gt, GroundTruth)
    assert gt.height == 48 and gt.v0 == 8 and gt.c.shape == gt.d.shape == (40,)
    assert gt.c.dtype == gt.d.dtype == np.float64
    assert gt.c[2] == pytest.approx(1.0) and gt.d[2] == pytest.approx(10.2)
    assert ds.ground_truth(2).v0 == 0
    img = ds.image(1)
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    assert ds.image_size(1) == (64, 48)
    t = ds.tmgem(0)
    assert t.shape == (48, 3) and t.dtype == np.float64 and t[5, 1] == 25.0
    np.testing.assert_allclose(gt.centre_x(1, width=64), gt.c + gt.d + 32)


def test_fake_classification_case_insensitive_and_subsets(tmp_path):
    ds = CRBD(make_crbd(tmp_path))
    assert [ds.row_set(i) for i in range(3)] == [1, 2, 2]
    assert [ds.tmgem_set(i) for i in range(3)] == [0, 1, 2]
    assert ds.indices("all") == [0, 1, 2]
    assert ds.indices("straight") == [0]
    assert ds.indices("curved") == [1, 2]
    assert ds.indices("train") == [0]
    assert ds.indices("test") == [1, 2]
    with pytest.raises(ValueError, match="subset"):
        ds.indices("validation")


def test_fake_missing_optional_files_only_fail_when_asked(tmp_path):
    ds = CRBD(make_crbd(tmp_path, classification=False, tmgem=False))
    assert len(ds) == 3
    it = ds[1]
    assert it.row_set is None and it.tmgem_set is None
    assert ds.ground_truth(1).v0 == 8
    assert ds.image(1).shape == (48, 64, 3)
    assert ds.indices("all") == [0, 1, 2]
    with pytest.raises(FileNotFoundError, match=r"imageClassification\.txt"):
        ds.row_set(0)
    with pytest.raises(FileNotFoundError, match=r"imageClassificationTMGEM\.txt"):
        ds.indices("train")
    with pytest.raises(FileNotFoundError, match=r"crop_row_001\.tmg"):
        ds.tmgem(0)


def test_fake_image_not_listed_in_classification(tmp_path):
    root = make_crbd(tmp_path)
    (root / "Images" / "imageClassification.txt").write_text("crop_row_001.JPG\t1\n")
    ds = CRBD(root)
    assert ds[1].row_set is None
    with pytest.raises(KeyError, match="crop_row_002"):
        ds.row_set(1)
    assert ds.indices("curved") == []


def _one_line_layout_error(excinfo, path):
    msg = str(excinfo.value)
    assert "\n" not in msg
    assert "Images/crop_row_NNN.JPG|jpg" in msg
    assert "GT data/crop_row_NNN.crp" in msg
    assert "TMGEM results/crop_row_NNN.tmg" in msg
    assert str(path) in msg


def test_bad_root_one_line_error(tmp_path):
    for bad in (tmp_path / "does_not_exist", tmp_path):
        with pytest.raises(FileNotFoundError) as ei:
            CRBD(bad)
        _one_line_layout_error(ei, bad)
    empty = tmp_path / "empty"
    (empty / "Images").mkdir(parents=True)
    with pytest.raises(FileNotFoundError) as ei:
        CRBD(empty)
    _one_line_layout_error(ei, empty)


def test_missing_ground_truth_is_a_layout_error(tmp_path):
    root = make_crbd(tmp_path / "crbd")
    (root / "GT data" / "crop_row_002.crp").unlink()
    with pytest.raises(FileNotFoundError) as ei:
        CRBD(root)
    _one_line_layout_error(ei, root)
    assert "crop_row_002.crp" in str(ei.value)


def test_resolve_data_root(monkeypatch, tmp_path):
    monkeypatch.delenv("TORCHROW_DATA", raising=False)
    with pytest.raises(FileNotFoundError) as ei:
        resolve_data_root()
    msg = str(ei.value)
    assert "\n" not in msg and "TORCHROW_DATA" in msg and "root" in msg
    with pytest.raises(FileNotFoundError):
        CRBD()
    assert resolve_data_root(tmp_path) == tmp_path
    monkeypatch.setenv("TORCHROW_DATA", str(tmp_path / "env"))
    assert resolve_data_root() == tmp_path / "env"
    assert resolve_data_root(tmp_path) == tmp_path  # the argument wins
    monkeypatch.setenv("TORCHROW_DATA", "")
    with pytest.raises(FileNotFoundError):
        resolve_data_root()


def test_env_var_resolution_fake(monkeypatch, tmp_path):
    make_crbd(tmp_path / "crbd")
    monkeypatch.setenv("TORCHROW_DATA", str(tmp_path))
    assert len(CRBD()) == 3
    monkeypatch.setenv("TORCHROW_DATA", str(tmp_path / "crbd"))
    assert len(CRBD()) == 3


# --- the real CRBD --------------------------------------------------------------------------
@pytest.mark.data
def test_real_crbd(crbd_dir: Path):
    ds = CRBD(crbd_dir)
    assert len(ds) == 281
    assert ds.stems == [f"crop_row_{k:03d}" for k in range(1, 282)]
    exts = {Path(n).suffix for n in ds.names}
    assert exts == {".JPG", ".jpg"}
    assert ds.names[3] == "crop_row_004.jpg" and ds.names[0] == "crop_row_001.JPG"
    assert len(ds.indices("straight")) == 48
    assert len(ds.indices("curved")) == 233
    assert len(ds.indices("train")) == 56
    assert len(ds.indices("test")) == 225
    assert set(ds.indices("straight")).isdisjoint(ds.indices("curved"))
    gt = ds.ground_truth(0)
    assert (gt.height, gt.v0, len(gt.c)) == (240, 2, 238)
    assert gt.c[0] == pytest.approx(-7.170042) and gt.d[0] == pytest.approx(42.270042)
    assert ds.tmgem(0).shape == (240, 3)
    img = ds.image(3)
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8
    it = ds[2]
    assert it.row_set == 2 and it.tmgem_set == 0 and it.ground_truth.height == 240


@pytest.mark.data
def test_real_crbd_from_data_folder_and_env(data_dir: Path, crbd_dir: Path, monkeypatch):
    assert CRBD(data_dir).root == CRBD(crbd_dir).root
    monkeypatch.setenv("TORCHROW_DATA", str(data_dir))
    assert len(CRBD()) == 281
