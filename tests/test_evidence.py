"""Row evidence given by the caller (ALGORITHM.md 11.1.1, torchrow's own): the resize rule, the
mask on both paths, and the errors."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrow.core.io import evidence_mask, lattice_params
from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.core.results import record_differences
from torchrow.engines.detector import CropRowDetector
from torchrow.functional import lattice as flat
from torchrow.reference import detect
from torchrow.reference import lattice as rlat

IMPROVED = Params(mode="improved")
FORWARD = Params(mode="improved", **FORWARD_CAMERA)


def _t(images: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()


def _stripes(h: int = 240, w: int = 320, spacing: float = 70.0, shift: float = 0.0, yv: float = -80.0) -> np.ndarray:
    """A row mask ``bool (H, W)``: straight rows 5 px wide at the bottom through ``(W/2 + shift, yv)``."""
    ys, xs = np.mgrid[0:h, 0:w]
    scale = (ys - yv) / (h - 1 - yv)
    u = (xs - (w / 2 + shift)) / scale / spacing
    return np.abs(u - np.round(u)) * spacing < 2.5


def _grey(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    """Grey noise without any green: the green mask finds nothing in it."""
    rng = np.random.default_rng(seed)
    return np.repeat(rng.integers(90, 140, (h, w, 1), dtype=np.uint8), 3, axis=2)


# --- the resize rule ----------------------------------------------------------------------

@settings(max_examples=30, deadline=None)
@given(h0=st.integers(1, 40), w0=st.integers(1, 40), h=st.integers(1, 40), w=st.integers(1, 40), seed=st.integers(0, 99))
def test_evidence_mask_takes_the_source_pixel_under_each_centre(h0, w0, h, w, seed) -> None:
    src = np.random.default_rng(seed).integers(0, 3, (h0, w0)).astype(np.uint8)
    before = src.copy()
    got = evidence_mask(src, w, h)
    assert got.dtype == np.bool_ and got.shape == (h, w)
    for i in range(h):
        for j in range(w):
            y0 = int(np.floor((i + 0.5) * h0 / h))
            x0 = int(np.floor((j + 0.5) * w0 / w))
            assert got[i, j] == (src[y0, x0] != 0)
    np.testing.assert_array_equal(src, before)


def test_evidence_mask_dtypes_and_layouts() -> None:
    m = np.zeros((4, 6), bool)
    m[1, 2] = True
    same = evidence_mask(m, 6, 4)
    np.testing.assert_array_equal(same, m)
    same[0, 0] = True
    assert not m[0, 0]  # a copy, never a view of the caller's array
    f = np.array([[0.0, np.nan], [0.5, -1.0]])
    np.testing.assert_array_equal(evidence_mask(f, 2, 2), [[False, False], [True, True]])
    np.testing.assert_array_equal(evidence_mask(m[..., None].astype(np.uint8) * 255, 6, 4), m)


@pytest.mark.parametrize(("bad", "kind"), [([[1, 0]], TypeError), (np.zeros((2, 2, 3)), ValueError),
                                       (np.zeros((0, 4)), ValueError), (np.zeros(5), ValueError),
                                       (np.array([["a", "b"]]), ValueError)])
def test_evidence_mask_refuses_what_is_no_mask(bad, kind) -> None:
    with pytest.raises(kind, match="evidence"):
        evidence_mask(bad, 4, 4)


# --- both paths -----------------------------------------------------------------------------

@pytest.mark.parametrize("params", [IMPROVED, FORWARD], ids=["default", "forward"])
def test_the_green_mask_given_as_evidence_changes_nothing(params) -> None:
    images = [_grey(seed=s) for s in (1, 2)]
    for im, rows in zip(images, [_stripes(), _stripes(spacing=60.0, shift=20.0)]):
        im[rows] = (40, 170, 40)  # green rows on grey soil
    masks = [rlat.green_mask(im, rlat.horizon_row(0, params), params) for im in images]
    det = CropRowDetector(params)
    plain = det(_t(images)).results()
    given_ = det(_t(images), evidence=torch.from_numpy(np.stack(masks))).results()
    for a, b, im, m in zip(plain, given_, images, masks):
        assert not record_differences(a.to_record(), b.to_record())
        assert not record_differences(detect(im, params).to_record(), detect(im, params, evidence=m).to_record())


def test_rows_follow_the_evidence_and_both_paths_agree() -> None:
    # no green at all: only the given mask can show rows; batched with an empty mask and noise
    images = [_grey(seed=s) for s in range(3)]
    rng = np.random.default_rng(5)
    masks = [_stripes(shift=12.0), np.zeros((240, 320), bool), rng.random((240, 320)) < 0.05]
    before = [m.copy() for m in masks]
    ev = torch.from_numpy(np.stack(masks))
    got = CropRowDetector(FORWARD)(_t(images), evidence=ev).results()
    for im, m, b, g in zip(images, masks, before, got):
        ref = detect(im, FORWARD, evidence=m)
        assert not record_differences(ref.to_record(), g.to_record())
        np.testing.assert_array_equal(m, b)
    assert detect(images[0], FORWARD).status != "ok"  # the green mask sees nothing there
    rows = [r for r in got[0].rows if r.valid]
    assert got[0].status == "ok" and len(rows) == 3
    ys = np.array([120.0, 239.0])
    truth = [(320 / 2 + 12.0 + k * 70.0 * (ys - -80.0) / (239 + 80.0)) for k in (-1, 0, 1)]
    for r, x in zip(sorted(rows, key=lambda r: r.a * 239 + r.b), truth):
        assert np.abs(r.a * ys + r.b - x).max() < 3.0
    assert got[1].status != "ok" and got[2].status != "ok"


def test_a_list_of_masks_at_the_images_own_size_is_resized_alike() -> None:
    big = _grey(480, 640)
    mask = _stripes(480, 640, spacing=140.0).astype(np.uint8) * 255
    det = CropRowDetector(FORWARD)
    got = det.detect([big], evidence=[mask]).results()[0]
    ref = detect(big, FORWARD, evidence=mask)
    assert not record_differences(ref.to_record(), got.to_record())
    assert got.status == "ok"


def test_evidence_clears_the_rows_above_the_horizon_on_both_paths() -> None:
    rng = np.random.default_rng(3)
    ev = rng.random((3, 20, 16)) < 0.5
    sky = np.array([0, 7, 20])
    images = torch.zeros((3, 3, 20, 16), dtype=torch.uint8)
    got = flat.row_evidence(images, torch.from_numpy(sky), IMPROVED, torch.from_numpy(ev))
    for b in range(3):
        rgb = np.zeros((20, 16, 3), np.uint8)
        np.testing.assert_array_equal(got[b].numpy(), rlat.row_evidence(rgb, int(sky[b]), IMPROVED, ev[b]))
        assert not got[b, :sky[b]].any()
    assert ev[2].any()  # the caller's mask is left as it was


def test_evidence_is_refused_where_it_has_no_use_or_no_fit() -> None:
    img = _grey()
    m = _stripes()
    faithful = Params()
    with pytest.raises(ValueError, match="only used by mode 'improved'"):
        detect(img, faithful, evidence=m)
    with pytest.raises(ValueError, match="only used by mode 'improved'"):
        CropRowDetector(faithful)(_t([img]), evidence=torch.from_numpy(m[None]))
    det = CropRowDetector(FORWARD)
    with pytest.raises(ValueError, match=r"evidence: expected a bool tensor of the images' \(B, H, W\)"):
        det(_t([img]), evidence=torch.from_numpy(m[None, :, :100]))
    with pytest.raises(ValueError, match="evidence: expected a bool tensor"):
        det(_t([img]), evidence=torch.from_numpy(m[None]).to(torch.uint8))
    many = CropRowDetector(FORWARD, chunk=1, workers=2)  # the chunks must not drop a surplus mask
    with pytest.raises(ValueError, match=r"\(2, 240, 320\), got torch.bool \(3, 240, 320\)"):
        many(_t([img, img]), evidence=torch.from_numpy(np.stack([m, m, m])))
    with pytest.raises(ValueError, match="expected a list of 2 arrays"):
        det.detect([img, img], evidence=[m])
    with pytest.raises(TypeError, match="with a tensor of images expected a bool tensor"):
        det.detect(_t([img]), evidence=[m])
    with pytest.raises(ValueError, match="evidence: expected a bool array of the working size"):
        rlat.improved_rows(img, 0, None, lattice_params(320, 240, FORWARD), evidence=m[:, :10])


# --- the lattice tracker (11.7) ---------------------------------------------------------------

TRACK = Params(mode="improved", video_width=320)


def _bottom_x(rec: dict, y: float = 239.0) -> float:
    row = rec["rows"][len(rec["rows"]) // 2]  # the central row
    return row["e"] * y ** 3 + row["c"] * y ** 2 + row["a"] * y + row["b"]


def test_the_tracker_follows_the_evidence_on_both_paths() -> None:
    from torchrow.engines.tracker import Tracker
    from torchrow.reference import Tracker as RefTracker

    # two green-less sequences in lock-step, their rows only in the masks: one drifts 3 px per
    # frame, the other 4 px the other way, its mask moved by half a spacing on frame 3
    frames = [_grey(seed=i) for i in range(5)]
    drift = [_stripes(shift=3.0 * i) for i in range(5)]
    lost = [_stripes(spacing=90.0, shift=-4.0 * i + (45.0 if i == 3 else 0.0)) for i in range(5)]
    before = [m.copy() for m in drift]
    tracker, state, got = Tracker(TRACK), None, []
    for i in range(5):
        recs, state = tracker.step([frames[i], frames[i]], state, evidence=[drift[i], lost[i]])
        got.append([r.to_record() for r in recs])
    for seq, masks in ((0, drift), (1, lost)):
        ref, rstate = RefTracker(TRACK), None
        for i in range(5):
            r, rstate = ref.step(frames[i], rstate, evidence=masks[i])
            assert not record_differences(r.to_record(), got[i][seq]), f"sequence {seq}, frame {i}"
    assert all(m is not b and np.array_equal(m, b) for m, b in zip(drift, before))
    a = [g[0] for g in got]
    assert all(r["status"] == "ok" for r in a)
    assert [r["state"] for r in a][2:] == ["in_row"] * 3
    # the central row moves with the mask (3 px per frame at the bottom)
    assert [round(_bottom_x(r) - 160.0) for r in a] == [0, 3, 6, 9, 12]
    b = [g[1] for g in got]
    # frame 3: the tracked pass fails on the mask moved by half a spacing, the full search finds it
    assert [r["hough_redo"] for r in b] == [False, False, False, True, False]
    assert b[3]["status"] == "ok" and round(_bottom_x(b[3])) == 160 - 12 + 45
    # without the masks these frames hold no green: nothing to track
    plain, _ = Tracker(TRACK).step([frames[0]])
    assert plain[0].status == "invalid"


def test_the_tracker_refuses_evidence_it_cannot_use() -> None:
    from torchrow.engines.tracker import Tracker
    from torchrow.reference import Tracker as RefTracker

    frame, mask = _grey(), _stripes()
    faithful = Params(video_width=320)
    with pytest.raises(ValueError, match="only used by mode 'improved'"):
        Tracker(faithful).step([frame], evidence=[mask])
    with pytest.raises(ValueError, match="only used by mode 'improved'"):
        RefTracker(faithful).step(frame, evidence=mask)
    with pytest.raises(ValueError, match="one per image"):
        Tracker(TRACK).step([frame, frame], evidence=[mask])
    with pytest.raises(TypeError, match="bool tensor"):
        Tracker(TRACK).step(_t([frame]), evidence=[mask])
    with pytest.raises(ValueError, match=r"\(B, H, W\)"):
        Tracker(TRACK)(_t([frame]), evidence=torch.from_numpy(mask)[None, :-1])


# --- masks from files: the runner and the command line -------------------------------------------------


def _mask_folder(tmp_path):
    """Three green-less images and their row masks on disk: ``a.png`` (mask ``a.png``), ``b.jpg``
    (mask ``b.png``) and ``c.png`` at 640x480 with its mask at half that size (``c.png``)."""
    import cv2

    imgs, masks = tmp_path / "img", tmp_path / "masks"
    imgs.mkdir()
    masks.mkdir()
    cv2.imwrite(str(imgs / "a.png"), _grey(seed=1))
    cv2.imwrite(str(imgs / "b.jpg"), _grey(seed=2))
    cv2.imwrite(str(imgs / "c.png"), _grey(480, 640, seed=3))
    cv2.imwrite(str(masks / "a.png"), _stripes(shift=12.0).astype(np.uint8) * 255)
    cv2.imwrite(str(masks / "b.png"), _stripes(spacing=90.0, shift=-20.0).astype(np.uint8) * 255)
    cv2.imwrite(str(masks / "c.png"), _stripes().astype(np.uint8) * 255)
    return imgs, masks


def test_the_runner_detects_each_image_with_its_own_evidence(tmp_path) -> None:
    import functools

    from torchrow.core.io import load_image, load_with_evidence
    from torchrow.engines.runner import run

    imgs, masks = _mask_folder(tmp_path)
    plain = functools.partial(load_image, imgs / "a.png", 320)
    items = [("a", functools.partial(load_with_evidence, imgs / "a.png", masks / "a.png", 320)), ("plain", plain),
             ("b", functools.partial(load_with_evidence, imgs / "b.jpg", masks / "b.png", 320))]
    for impl in ("tensor", "reference"):
        # batch size 2: the first batch would hold a and plain, but never mixes evidence with none
        got = [(rgb, res.to_record()) for _, rgb, res, _ in run(items, impl, FORWARD, batch_size=2, progress=False)]
        for (name, loader), (rgb, rec) in zip(items, got):
            loaded = loader()
            image, ev = (loaded, None) if name == "plain" else loaded
            np.testing.assert_array_equal(rgb, image)
            assert not record_differences(detect(image, FORWARD, name=name, evidence=ev).to_record(), rec), (impl, name)
        assert [r["status"] for _, r in got] == ["ok", "invalid", "ok"]
    # evidence has no use in the faithful mode: an error record per image, the run goes on
    faithful = [res for _, _, res, _ in run(items[:1], "tensor", Params(), progress=False)]
    assert faithful[0].status == "error" and "only used by mode 'improved'" in faithful[0].error


def test_detect_and_eval_read_a_mask_folder(tmp_path, capsys) -> None:
    import cv2

    from torchrow.apps.cli import main
    from torchrow.core.io import evidence_mask, load_image

    imgs, masks = _mask_folder(tmp_path)
    recs = {}
    for impl in ("tensor", "reference"):
        out = tmp_path / f"{impl}.jsonl"
        assert main(["detect", str(imgs), "--out", str(out), "--forward", "--evidence", str(masks), "--impl", impl,
                     "-q"]) == 0
        recs[impl] = [json.loads(line) for line in out.read_text().splitlines()]
    for a, b in zip(*recs.values()):
        assert not record_differences(a, b)
    assert [(r["name"], r["status"]) for r in recs["tensor"]] == [("a.png", "ok"), ("b.jpg", "ok"), ("c.png", "ok")]
    # c.png's mask is half its size: the same rows as the full-size mask at the working size
    c = load_image(imgs / "c.png", 320)
    want = detect(c, FORWARD, name="c.png", evidence=evidence_mask(cv2.imread(str(masks / "c.png"), 0), 320, 240))
    assert not record_differences(want.to_record(), recs["tensor"][2])
    capsys.readouterr()
    argv = ["detect", str(imgs), "--out", str(tmp_path / "x.jsonl"), "-q"]
    assert main(argv + ["--evidence", str(masks)]) == 2  # the faithful mode reads no mask
    assert "improved mode only" in capsys.readouterr().err
    (masks / "b.png").unlink()
    assert main(argv + ["--forward", "--evidence", str(masks)]) == 2
    err = capsys.readouterr().err
    assert "no mask for 1 of 3 image(s)" in err and "b.png or" in err and not (tmp_path / "x.jsonl").exists()
    # a mask of another aspect is that image's error record; the others are detected
    cv2.imwrite(str(masks / "b.png"), np.zeros((100, 20), np.uint8))
    assert main(argv + ["--forward", "--evidence", str(masks)]) == 0
    got = [json.loads(line) for line in (tmp_path / "x.jsonl").read_text().splitlines()]
    assert [r["status"] for r in got] == ["ok", "error", "ok"] and "not the aspect" in got[1]["error"]


def test_eval_reads_a_mask_folder(tmp_path, capsys) -> None:
    # CRDLD's own labels as the evidence: the lattice follows them
    import cv2

    from torchrow.apps.cli import main

    split = tmp_path / "crdld" / "test"
    (split / "image").mkdir(parents=True)
    (split / "label").mkdir()
    for n, shift in ((0, 0.0), (1, 15.0)):
        cv2.imwrite(str(split / "image" / f"{n}.jpg"), _grey(320, 320, seed=n))
        cv2.imwrite(str(split / "label" / f"{n}.jpg"), _stripes(320, 320, shift=shift).astype(np.uint8) * 255)
    out = tmp_path / "eval"
    argv = ["eval", "--dataset", "crdld", "--data", str(tmp_path / "crdld"), "--out", str(out), "-q", "--forward"]
    assert main(argv + ["--evidence", str(split / "label")]) == 0
    text = capsys.readouterr().out
    assert "statuses: ok 2" in text
    with open(out / "scores.csv") as fh:
        assert [float(r["crdld_sigma0.1"]) > 0.8 for r in csv.DictReader(fh)] == [True, True]
    assert main(argv + ["--resume"]) == 2  # a resume without the masks is another run
    assert "written by another run: sources" in capsys.readouterr().err
