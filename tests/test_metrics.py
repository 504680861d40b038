"""CRDA (ALGORITHM.md section 10): hand-made cases, a loop oracle, and the CRBD figures."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrow.core.results import ImageResult, Row
from torchrow.evaluation.metrics import crda, crda_official, crda_thesis, match_score, rows_to_U, summarize

NAN = float("nan")


# --- helpers ----------------------------------------------------------------------------
def gt_const(h=240, v0=40, c=0.0, d=40.0):
    n = h - v0
    return np.full(n, c, dtype=np.float64), np.full(n, d, dtype=np.float64)


def perfect_U(c, d, h, m=3, shift=0, width=320):
    """x of GT rows shift-1, shift, shift+1 (m=3) for rows v0..h-1, NaN above."""
    v0 = h - len(c)
    U = np.full((h, m), NAN)
    for k in range(m):
        U[v0:, k] = c + (shift + k - (m - 1) // 2) * d + width / 2
    return U


def crda_loop(U, c, d, m=3, sigma=0.1, adjacent=9, width=320):
    """Plain-loop oracle written from the formula in ALGORITHM.md section 10."""
    h = U.shape[0]
    v0 = h - len(c)
    best = 0.0
    half = (adjacent - m) // 2
    for s in range(-half, half + 1):
        tot = 0.0
        for r in range(len(c)):
            for k in range(m):
                i = k - (m - 1) // 2
                u_star = c[r] + (s + i) * d[r] + width / 2
                u = U[v0 + r, k]
                if math.isnan(u):
                    continue
                t = (u_star - u) / (sigma * d[r])
                tot += max(1.0 - t * t, 0.0)
        best = max(best, tot / (m * len(c)))
    return best


class GT:
    """Minimal stand-in for torchrow.evaluation.datasets.GroundTruth."""

    def __init__(self, c, d, height):
        self.c, self.d, self.height = np.asarray(c, float), np.asarray(d, float), height
        self.v0 = height - len(self.c)


def linear_gt(h=240, v0=30):
    """GT whose rows are straight lines converging above the image: c_v, d_v linear in v."""
    v = np.arange(v0, h, dtype=np.float64)
    c = 5.0 + 0.05 * (v - v0)
    d = 20.0 + 0.25 * (v - v0)
    return GT(c, d, h), v


def gt_rows(gt, v, ks, width=320):
    """Rows x = a*y + b that follow GT rows ks exactly (c, d linear in v)."""
    rows = []
    for k in ks:
        x = gt.c + k * gt.d + width / 2
        a = (x[-1] - x[0]) / (v[-1] - v[0])
        rows.append(Row(a, x[0] - a * v[0], True))
    return rows


# --- crda: hand-made cases ---------------------------------------------------------------
def test_perfect_detection_scores_one():
    c, d = gt_const()
    assert crda(perfect_U(c, d, 240), c, d) == pytest.approx(1.0, abs=1e-12)


def test_offset_of_sigma_d_scores_zero_and_half_sigma_scores_three_quarters():
    c, d = gt_const(d=40.0)  # sigma*d = 4 px
    U = perfect_U(c, d, 240)
    assert crda(U + 4.0, c, d) == pytest.approx(0.0, abs=1e-12)
    assert crda(U + 10.0, c, d) == 0.0
    assert crda(U + 2.0, c, d) == pytest.approx(0.75, abs=1e-12)
    assert crda(U - 2.0, c, d) == pytest.approx(0.75, abs=1e-12)
    assert crda(U + 2.0, c, d, sigma=0.3) == pytest.approx(1 - (2 / 12) ** 2, abs=1e-12)


def test_empty_slot_scores_zero_and_nan_is_handled():
    c, d = gt_const()
    U = perfect_U(c, d, 240)
    U1 = U.copy()
    U1[:, 2] = NAN
    assert crda(U1, c, d) == pytest.approx(2 / 3, abs=1e-12)
    U2 = U.copy()
    U2[140:, :] = NAN  # lower half of the scored rows (40..239) missing
    assert crda(U2, c, d) == pytest.approx(0.5, abs=1e-12)
    assert crda(np.full((240, 3), NAN), c, d) == 0.0
    assert np.isfinite(crda(U1, c, d))


def test_rows_above_v0_are_not_scored():
    c, d = gt_const(v0=100)
    U = perfect_U(c, d, 240)
    U[:100] = 1e6
    assert crda(U, c, d) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("shift", [-3, -1, 0, 2, 3])
def test_shifted_rows_found_by_max_over_s(shift):
    c, d = gt_const()
    assert crda(perfect_U(c, d, 240, shift=shift), c, d) == pytest.approx(1.0, abs=1e-12)


def test_shift_beyond_nine_rows_scores_zero():
    c, d = gt_const()
    # rows 3,4,5 (4 to the right): the best group (2,3,4) is off by one full spacing
    assert crda(perfect_U(c, d, 240, shift=4), c, d) == 0.0
    # with more adjacent ground-truth rows the group is reachable again
    assert crda(perfect_U(c, d, 240, shift=4), c, d, adjacent=11) == pytest.approx(1.0)


def test_half_spacing_offset_scores_zero_not_neighbour():
    c, d = gt_const()
    assert crda(perfect_U(c, d, 240) + 20.0, c, d) == 0.0


def test_other_image_size():
    h, w, v0 = 480, 640, 100
    v = np.arange(v0, h, dtype=np.float64)
    c = 3.0 + 0.1 * (v - v0)
    d = 30.0 + 0.3 * (v - v0)
    U = perfect_U(c, d, h, width=w)
    assert crda(U, c, d, width=w) == pytest.approx(1.0, abs=1e-12)
    # the ground truth is relative to width/2
    assert crda(U - 160.0, c, d, width=320) == pytest.approx(1.0, abs=1e-12)
    assert crda(U, c, d, width=320) < 0.1


def test_m5_and_m1():
    c, d = gt_const()
    assert crda(perfect_U(c, d, 240, m=5, shift=2), c, d, m=5) == pytest.approx(1.0)
    assert crda(perfect_U(c, d, 240, m=5, shift=3), c, d, m=5) == 0.0  # shifts -2..2 only
    assert crda(perfect_U(c, d, 240, m=1, shift=4), c, d, m=1) == pytest.approx(1.0)


def test_empty_ground_truth_and_errors():
    assert crda(np.zeros((240, 3)), np.zeros(0), np.zeros(0)) == 0.0
    c, d = gt_const()
    with pytest.raises(ValueError):
        crda(np.zeros((240, 2)), c, d)
    with pytest.raises(ValueError):
        crda(np.zeros((240, 2)), c, d, m=2)
    with pytest.raises(ValueError):
        crda(np.zeros((100, 3)), c, d)  # more GT rows than image rows
    with pytest.raises(ValueError):
        crda(np.zeros((240, 3)), c, d[:-1])
    with pytest.raises(ValueError):
        crda(np.zeros((240, 3)), c, d, adjacent=1)


def test_match_score():
    s = match_score(np.array([10.0, 10.0, 10.0, 10.0]), np.array([10.0, 11.0, 12.0, NAN]), 20.0, 0.1)
    np.testing.assert_allclose(s, [1.0, 0.75, 0.0, 0.0], atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    h=st.integers(5, 40),
    frac=st.floats(0.0, 1.0),
    m=st.sampled_from([1, 3, 5]),
    sigma=st.sampled_from([0.1, 0.3]),
    seed=st.integers(0, 2**31 - 1),
)
def test_crda_matches_loop_oracle(h, frac, m, sigma, seed):
    rng = np.random.default_rng(seed)
    n = max(1, int(h * frac))
    c = rng.normal(0, 10, n)
    d = rng.uniform(5, 40, n)
    U = perfect_U(c, d, h, m=m, shift=int(rng.integers(-3, 4)))
    U += rng.normal(0, 1.5, U.shape)
    U[rng.random(U.shape) < 0.1] = NAN
    got = crda(U, c, d, m=m, sigma=sigma)
    assert got == pytest.approx(crda_loop(U, c, d, m=m, sigma=sigma), abs=1e-12)
    assert 0.0 <= got <= 1.0


# --- rows_to_U ----------------------------------------------------------------------------
def vert(*xs, valid=True):
    return [Row(0.0, float(x), valid) for x in xs]


def cols(U):
    """The x at the bottom row of each slot (NaN for empty slots)."""
    return [None if math.isnan(x) else x for x in U[-1]]


def test_rows_to_U_five_rows_picks_the_centred_three():
    rows = vert(280, 40, 160, 220, 100) + vert(150, valid=False)
    U = rows_to_U(rows, 240, width=320)
    assert U.shape == (240, 3)
    assert cols(U) == [100, 160, 220]
    # the window's middle must be nearest the centre among feasible middles only
    assert cols(rows_to_U(vert(150, 250, 300, 350, 400), 240, width=320)) == [150, 250, 300]
    assert cols(rows_to_U(vert(10, 30, 50, 200, 300), 240, width=320)) == [50, 200, 300]


def test_rows_to_U_samples_every_image_row_and_sorts_at_the_bottom():
    a_rows = [Row(1.0, 20.0, True), Row(0.0, 200.0, True), Row(-0.5, 240.0, True)]
    U = rows_to_U(a_rows, 240, width=320)
    y = np.arange(240.0)
    # at y = 239: 259, 200, 120.5 -> sorted 120.5, 200, 259
    np.testing.assert_array_equal(U[:, 0], -0.5 * y + 240.0)
    np.testing.assert_array_equal(U[:, 1], 0.0 * y + 200.0)
    np.testing.assert_array_equal(U[:, 2], 1.0 * y + 20.0)


def test_rows_to_U_three_two_one_zero_rows():
    assert cols(rows_to_U(vert(300, 10, 150), 240)) == [10, 150, 300]
    assert cols(rows_to_U(vert(170, 100), 240)) == [100, 170, None]
    assert cols(rows_to_U(vert(150, 250), 240)) == [None, 150, 250]
    assert cols(rows_to_U(vert(5), 240)) == [None, 5, None]
    assert np.isnan(rows_to_U([], 240)).all()
    assert np.isnan(rows_to_U(vert(160, valid=False), 240)).all()
    assert np.isnan(rows_to_U([Row(NAN, NAN, True)], 240)).all()  # non-finite -> ignored


def test_rows_to_U_other_sizes_and_m5():
    U = rows_to_U(vert(100, 330, 600), 480, width=640)
    assert U.shape == (480, 3) and cols(U) == [100, 330, 600]
    assert cols(rows_to_U(vert(330, 400), 480, width=640)) == [None, 330, 400]
    # m=5 with 4 rows, nearest row first: it takes the middle slot, the last row falls off
    assert cols(rows_to_U(vert(160, 200, 240, 280), 240, m=5)) == [None, None, 160, 200, 240]
    assert cols(rows_to_U(vert(10, 100, 160, 200, 240, 280), 240, m=5)) == [10, 100, 160, 200, 240]


def test_rows_to_U_tie_goes_left():
    assert cols(rows_to_U(vert(150, 170), 240)) == [None, 150, 170]


# --- crda_official / crda_thesis --------------------------------------------------------------
def result(rows, n_rows=None, status="ok", width=320, height=240):
    return ImageResult(width=width, height=height, status=status, rows=rows,
                       n_rows=len(rows) if n_rows is None else n_rows)


def test_official_and_thesis_perfect():
    gt, v = linear_gt()
    rows = gt_rows(gt, v, [-2, -1, 0, 1, 2])
    assert crda_official(result(rows), gt) == pytest.approx(1.0, abs=1e-9)
    assert crda_thesis(result(rows), gt) == pytest.approx(1.0, abs=1e-9)
    # a row not found counts 0 in the thesis variant
    assert crda_thesis(result(rows, n_rows=6), gt) == pytest.approx(5 / 6, abs=1e-9)
    # rows shifted by one ground-truth row: still perfect in both
    rows2 = gt_rows(gt, v, [0, 1, 2, 3])
    assert crda_official(result(rows2), gt) == pytest.approx(1.0, abs=1e-9)
    assert crda_thesis(result(rows2), gt) == pytest.approx(1.0, abs=1e-9)


def test_official_partial_and_empty():
    gt, v = linear_gt()
    assert crda_official(result(gt_rows(gt, v, [0, 1])), gt) == pytest.approx(2 / 3, abs=1e-9)
    # invalid rows do not count
    rows = gt_rows(gt, v, [-1, 0, 1])
    rows[2] = Row(rows[2].a, rows[2].b, False, "no_support")
    assert crda_official(result(rows, status="invalid"), gt) == pytest.approx(2 / 3, abs=1e-9)
    assert crda_thesis(result(rows, status="invalid"), gt) == pytest.approx(2 / 3, abs=1e-9)
    for status in ("no_vp", "no_vegetation", "error"):
        assert crda_official(result([], n_rows=5, status=status), gt) == 0.0
        assert crda_thesis(result([], n_rows=5, status=status), gt) == 0.0
    assert crda_official(ImageResult.failed("x", "boom"), gt) == 0.0
    with pytest.raises(ValueError):
        crda_official(result(gt_rows(gt, v, [0]), height=480, width=640), gt)


def test_official_other_image_size():
    gt, v = linear_gt(h=480, v0=60)
    rows = gt_rows(gt, v, [-1, 0, 1, 2], width=640)
    assert crda_official(result(rows, width=640, height=480), gt) == pytest.approx(1.0, abs=1e-9)


def test_thesis_nearest_per_image_row():
    # the central ground-truth row jumps one spacing right halfway down; a vertical row at
    # the centre follows row 0 above and row -1 below
    h, v0, d0 = 240, 40, 40.0
    c = np.where(np.arange(v0, h) < 140, 0.0, d0)
    gt = GT(c, np.full(h - v0, d0), h)
    res = result([Row(0.0, 160.0, True)])
    assert crda_thesis(res, gt) == pytest.approx(1.0)
    assert crda_thesis(res, gt, nearest="row") == pytest.approx(0.5)
    with pytest.raises(ValueError):
        crda_thesis(res, gt, nearest="bogus")


def test_summarize():
    assert summarize([0.0, 1.0, 0.5, 0.25]) == {"mean": 0.4375, "median": 0.375, "n": 4}
    s = summarize([])
    assert s["n"] == 0 and math.isnan(s["mean"]) and math.isnan(s["median"])


# --- real data ------------------------------------------------------------------------------
@pytest.mark.data
def test_tmgem_figures(crbd_dir: Path):
    from torchrow.evaluation.datasets import CRBD

    ds = CRBD(crbd_dir)
    assert len(ds) == 281
    gts = [ds.ground_truth(i) for i in range(len(ds))]
    tm = [ds.tmgem(i) for i in range(len(ds))]
    s1 = summarize([crda(u, g.c, g.d, sigma=0.1) for u, g in zip(tm, gts)])
    s3 = summarize([crda(u, g.c, g.d, sigma=0.3) for u, g in zip(tm, gts)])
    assert s1["n"] == s3["n"] == 281
    assert s1["mean"] == pytest.approx(0.746, abs=1e-3)
    assert s1["median"] == pytest.approx(0.767, abs=1e-3)
    assert s3["mean"] == pytest.approx(0.935, abs=1e-3)
    assert s3["median"] == pytest.approx(0.963, abs=1e-3)


@pytest.mark.data
def test_thesis_baseline_figures(data_dir: Path, crbd_dir: Path):
    """The thesis code's own rows, scored: figures from data/README.md."""
    from torchrow.evaluation.datasets import CRBD

    path = data_dir / "thesis_baseline" / "thesis_code_sample.jsonl"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    ds = CRBD(crbd_dir)
    index = {s.lower(): i for i, s in enumerate(ds.stems)}
    off, off3, th = [], [], []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        rows = []
        for xt, yt, xb, yb in rec["lines"]:
            a = (xb - xt) / (yb - yt)
            rows.append(Row(a, xt - a * yt, True))
        res = result(rows)
        gt = ds.ground_truth(index[Path(rec["name"]).stem.lower()])
        off.append(crda_official(res, gt))
        off3.append(crda_official(res, gt, sigma=0.3))
        th.append(crda_thesis(res, gt))
    assert len(off) == 40
    assert summarize(off)["mean"] == pytest.approx(0.460, abs=1e-3)
    assert summarize(off)["median"] == pytest.approx(0.464, abs=1e-3)
    assert summarize(off3)["mean"] == pytest.approx(0.668, abs=1e-3)
    assert summarize(th)["mean"] == pytest.approx(0.776, abs=1e-3)
    assert summarize(th)["median"] == pytest.approx(0.824, abs=1e-3)
