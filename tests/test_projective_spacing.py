"""Projective spacing of the improved mode's straight rows (ALGORITHM.md 11.3.2, torchrow's own):
the cells' rule, the choice of ``g``, both paths alike, and rows that follow a rolled camera."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
import torch

import torchrow
from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.core.results import record_differences
from torchrow.engines.detector import CropRowDetector
from torchrow.functional import lattice as flat
from torchrow.reference import Tracker as RefTracker
from torchrow.reference import detect
from torchrow.reference import lattice as rlat

ROLLED = Params(mode="improved", **FORWARD_CAMERA).replace(lattice_roll_grid=30)
H, W = 240, 320
VP = (W / 2, -60.0)


def _lines(k: int, spacing: float = 70.0, shift: float = 0.0) -> tuple[float, float]:
    """Row ``k`` of an upright field as ``x = a y + b`` (through ``VP``; ``spacing`` px apart at the
    bottom, moved by ``shift`` px there)."""
    xb = W / 2 + shift + k * spacing
    a = (xb - VP[0]) / ((H - 1) - VP[1])
    return a, xb - a * (H - 1)


def _turned(img: np.ndarray, degrees: float, interp: int) -> np.ndarray:
    m = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), degrees, 1.0)
    return cv2.warpAffine(img, m, (W, H), flags=interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _field(degrees: float, seed: int = 0, shift: float = 0.0) -> np.ndarray:
    """Seven green rows on brown soil through a VP above the image, turned about the centre (a
    camera rolled by ``-degrees``)."""
    rng = np.random.default_rng(seed)
    img = np.clip(np.array([120, 90, 60]) + rng.integers(-10, 11, (H, W, 3)), 0, 255).astype(np.uint8)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    for k in range(-3, 4):
        a, b = _lines(k, shift=shift)
        img[np.abs(xs - (a * ys + b)) < 3 + 3 * (ys + 60) / H] = (40, 170, 40)
    return _turned(img, degrees, cv2.INTER_NEAREST) if degrees else img


def _truth_x(k: int, degrees: float, y: float) -> float:
    """Where row ``k`` of :func:`_field` crosses image row ``y`` of the turned image."""
    a, b = _lines(k)
    m = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), degrees, 1.0)
    p = [m @ np.array([a * yy + b, yy, 1.0]) for yy in (0.0, H - 1.0)]
    (x0, y0), (x1, y1) = p
    return float(x0 + (x1 - x0) * (y - y0) / (y1 - y0))


def _x(row: dict, y: float) -> float:
    """A record row's x on image row ``y`` (working px)."""
    return ((row["e"] * y + row["c"]) * y + row["a"]) * y + row["b"]


def _cells_by_pixel(mask: np.ndarray, coef: np.ndarray, g: float, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """11.3.2's cells, the rule applied pixel by pixel (the spec's words, not prefix sums)."""
    h, _ = mask.shape
    cnt = np.zeros((2 * params.lattice_half + 1, h), np.int64)
    sx = np.zeros_like(cnt)
    cc, dd = rlat.centre_spacing(np.arange(h, dtype=np.float64) - (h - 1), coef)
    for y, x in zip(*np.nonzero(mask)):
        for i, k in enumerate(range(-params.lattice_half, params.lattice_half + 1)):
            u = 1.0 + g * k
            local = (dd[y] - g * cc[y]) / (u * u)
            centre = (cc[y] + k * dd[y]) / u
            if u > 0 and local > params.lattice_min_spacing_px and abs(x - centre) < params.lattice_tolerance * local:
                cnt[i, y] += 1
                sx[i, y] += x
    return cnt, sx


@pytest.mark.parametrize("g", [0.0, 0.13, -0.29])
def test_cells_are_the_per_pixel_rule_on_both_paths(g: float) -> None:
    rng = np.random.default_rng(1)
    params = ROLLED.replace(lattice_half=2)
    mask = rng.random((37, 53)) < 0.3
    pre_t = flat.prefix_sums(torch.from_numpy(mask)[None])
    for coef in (np.array([26.0, 0.05, 0.0, 0.0, 12.5, 0.1, 0.0]),
                 np.array([rng.uniform(-20, 70), rng.normal(), 0, 0, rng.uniform(1, 30), rng.normal() * 0.2, 0])):
        want = _cells_by_pixel(mask, coef, g, params)
        got = rlat.row_cells(rlat.prefix_sums(mask), coef, params, roll=g)
        cnt, sx = flat.row_cells(pre_t, torch.from_numpy(coef)[None], params, roll=torch.tensor([g], dtype=torch.float64))
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        assert np.array_equal(cnt[0].T.numpy(), want[0]) and np.array_equal(sx[0].T.numpy(), want[1])
        if g == 0.0:  # the equally spaced rule's cells, bit for bit
            plain = flat.row_cells(pre_t, torch.from_numpy(coef)[None], params)
            assert torch.equal(plain[0], cnt) and torch.equal(plain[1], sx)


def test_the_refit_recovers_a_drawn_projective_lattice_on_both_paths() -> None:
    # thin rows x = (c0 + c1 t + k (d0 + d1 t)) / (1 + g k) drawn on a mask; a start with g = 0
    h, w, g = 200, 320, -0.12
    coef = np.array([150.0, 0.35, 0.0, 0.0, 60.0, 0.25, 0.0])
    t = np.arange(h, dtype=np.float64) - (h - 1)
    mask = np.zeros((h, w), bool)
    for k in range(-3, 4):
        x = np.rint((coef[0] + coef[1] * t + k * (coef[4] + coef[5] * t)) / (1 + g * k)).astype(int)
        for dx in (-1, 0, 1):
            ok = (x + dx >= 0) & (x + dx < w)
            mask[np.arange(h)[ok], (x + dx)[ok]] = True
    params = ROLLED.replace(lattice_model="straight")
    start = np.array([150.0, 0.3, 0.0, 0.0, 60.0, 0.2, 0.0])
    got, roll = rlat.refine(rlat.prefix_sums(mask), start, h, params, straight=True)
    assert roll == pytest.approx(g, abs=0.011)
    np.testing.assert_allclose(got[[0, 1, 4, 5]], coef[[0, 1, 4, 5]], rtol=0.05, atol=1.0)
    tc, _, troll = flat.refine(flat.prefix_sums(torch.from_numpy(mask)[None]), torch.from_numpy(start).view(1, 1, 7),
                               params, straight=(True,))
    assert troll is not None and float(troll[0, 0]) == roll
    assert np.array_equal(tc[0, 0].numpy(), got)
    equal, eroll = rlat.refine(rlat.prefix_sums(mask), start, h, params.replace(lattice_roll_grid=0), straight=True)
    assert eroll == 0.0 and abs(equal[4] - coef[4]) > abs(got[4] - coef[4])  # g = 0 cannot fit both sides


@pytest.fixture(scope="module")
def fields() -> list[np.ndarray]:
    return [_field(15.0), _field(-20.0, seed=1), _field(0.0, seed=2),
            np.random.default_rng(3).integers(0, 256, (H, W, 3), dtype=np.uint8)]


def test_tensor_path_equals_reference_batched_and_alone(fields: list[np.ndarray]) -> None:
    # "auto": a straight lattice searching g and a curved one with g = 0 in one batched refit
    det = CropRowDetector(ROLLED)
    batch = [r.to_record() for r in det.detect(fields).results()]
    for img, got in zip(fields, batch):
        want = detect(img, ROLLED).to_record()
        assert not record_differences(want, got) and want == got
    assert det.detect(fields[1:2]).results()[0].to_record() == batch[1]


def test_rows_follow_a_rolled_camera(fields: list[np.ndarray]) -> None:
    for img, degrees in ((fields[0], 15.0), (fields[1], -20.0)):
        errs = {}
        for grid in (0, 30):
            rec = detect(img, ROLLED.replace(lattice_roll_grid=grid)).to_record()
            assert rec["status"] == "ok" or not grid  # equally spaced rows on a rolled view may well be weak
            err = []
            for y in (H - 1.0, H / 2):
                xs = [_x(r, y) for r in rec["lattice_rows"]]
                for k in (-1, 0, 1):
                    err.append(min(abs(x - _truth_x(k, degrees, y)) for x in xs))
            errs[grid] = float(np.mean(err))
        assert errs[30] < 0.5 and 3 * errs[30] < errs[0], errs


def test_row_polynomials_divide_by_the_pole_term() -> None:
    coef = (150.0, 0.35, 0.0, 0.0, 60.0, 0.25, 0.0)
    for k in (-2, 1):
        a, b, c, e = rlat.row_polynomial(coef, k, H, -0.1)
        for y in (0.0, 100.0, H - 1.0):
            t = y - (H - 1)
            want = (coef[0] + coef[1] * t + k * (coef[4] + coef[5] * t)) / (1 - 0.1 * k)
            assert ((e * y + c) * y + a) * y + b == pytest.approx(want, abs=1e-9)
    ta = flat.row_polynomials(torch.tensor([coef], dtype=torch.float64), torch.tensor([-2.0, 1.0], dtype=torch.float64),
                              H, torch.tensor([-0.1], dtype=torch.float64))
    assert [float(v) for v in ta[0][0]] == [rlat.row_polynomial(coef, k, H, -0.1)[0] for k in (-2, 1)]


def test_params_refuse_what_the_rule_cannot_do() -> None:
    curved = Params(mode="improved", lattice_roll_grid=10)  # valid; a curved refit never reads it
    img = _field(15.0)
    assert detect(img, curved).to_record() == detect(img, curved.replace(lattice_roll_grid=0)).to_record()
    with pytest.raises(ValueError, match=r"lattice_roll_grid.*lattice_half"):
        ROLLED.replace(lattice_half=4)  # 1 + g k <= 0 on a fitted row
    with pytest.raises(ValueError, match="lattice_roll_grid"):
        ROLLED.replace(lattice_roll_grid=100)


def test_the_lattice_tracker_follows_a_rolled_camera_on_both_paths() -> None:
    # a camera rolled by -12 degrees drifting sideways by 14 px a frame
    frames = [_field(12.0, seed=i, shift=14.0 * i) for i in range(6)]
    params = ROLLED.replace(video_width=W)
    got = torchrow.Tracker(params).track([frames])[0]
    want = RefTracker(params).track(frames)
    for r, g in zip(want, got):
        assert not record_differences(r.to_record(), g.to_record())
    assert [r.state for r in got][1:] == ["in_row"] * 5 and not any(r.row_change for r in got[1:])
    bottom = [_x(r.to_record()["rows"][1], H - 1.0) for r in got[1:]]
    assert all(abs((b - a) - 14.0) < 1.5 for a, b in itertools.pairwise(bottom)), bottom  # the tracked row moves with it
