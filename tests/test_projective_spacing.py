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


# -- the comb with a projective warp (11.3.2): dense fields seen by a rolled camera --------------

WARPED = ROLLED.replace(lattice_comb_warps=6)


@pytest.mark.parametrize("g", [-0.15, 0.1])
def test_the_warp_spaces_projective_rows_equally_on_both_paths(g: float) -> None:
    c, d, w = 130.0, 55.0, 320
    xs = np.array([(c + k * d) / (1 + g * k) for k in range(-4, 5)])
    gamma = np.float64(g) / (np.float64(d) - np.float64(g) * (w / 2))  # its pole x0 + 1 / gamma is their limit d / g
    got, ok = rlat.warped(xs, gamma, w)
    assert ok.all() and np.ptp(np.diff(got)) < 1e-9 * np.abs(got).max()
    tgot, tok = flat.warped(torch.from_numpy(xs), float(gamma), w)
    assert tok.all() and np.array_equal(tgot.numpy(), got)
    assert rlat.warped(np.array([w / 2 + 2 / gamma]), gamma, w)[1].tolist() == [False]  # beyond the pole
    assert flat.warp_rate(3, w) == rlat.warp_rate(3, w) == 3 / (10 * w)


def _dense_mask(g: float, h: int = 240, w: int = 320, vp: tuple[int, int] = (160, -40)) -> tuple[np.ndarray, list]:
    """Thin rows ``k = -6..6`` of a rolled camera, ``(c(t) + k d(t)) / (1 + g k)`` through ``vp``,
    the central row at x 170 and 40 px from its neighbours at the bottom; and the bottom x of each."""
    t_v = vp[1] - (h - 1)
    c0, d0 = 170.0, 40.0 + g * 170.0
    c1, d1 = (vp[0] - c0) / t_v, (g * vp[0] - d0) / t_v
    t = np.arange(h, dtype=np.float64) - (h - 1)
    mask = np.zeros((h, w), bool)
    for k in range(-6, 7):
        x = np.rint((c0 + c1 * t + k * (d0 + d1 * t)) / (1 + g * k)).astype(int)
        ok = (x >= 0) & (x < w) & (t > t_v + 30)
        mask[np.arange(h)[ok], x[ok]] = True
    return mask, [(c0 + k * d0) / (1 + g * k) for k in (-1, 0, 1)]


@pytest.mark.parametrize("g", [-0.06, 0.05])
def test_a_warped_comb_starts_on_a_dense_rolled_field_on_both_paths(g: float) -> None:
    mask, truth = _dense_mask(g)
    vp = (160, -40)
    params = WARPED.replace(lattice_model="straight")

    def bottom(coef: np.ndarray, roll: float) -> list[float]:
        return [(coef[0] + k * coef[4]) / (1 + roll * k) for k in (-1, 0, 1)]

    start = rlat.comb_start(mask, vp, params)
    coef, bent, roll = start.coef, start.bent, start.roll
    unwarped = rlat.comb_start(mask, vp, params.replace(lattice_comb_warps=0))
    plain, zero = unwarped.coef, unwarped.roll
    assert zero == 0.0 and roll == pytest.approx(g, abs=0.03)
    warped_err = max(abs(a - b) for a, b in zip(bottom(coef, roll), truth))
    plain_err = max(abs(a - b) for a, b in zip(bottom(plain, 0.0), truth))
    assert warped_err < 4.0 < plain_err, (warped_err, plain_err)
    assert bent[4] == pytest.approx(coef[4] - roll * coef[0]) and bent[5] == pytest.approx(bent[4] / (239 + 40))
    got = flat.comb_start(torch.from_numpy(mask)[None], torch.tensor([vp]), params)
    assert np.array_equal(got.coef[0].numpy(), coef) and np.array_equal(got.bent[0].numpy(), bent)
    assert float(got.roll[0]) == roll
    # a tracked frame's restricted comb is the bottom row's: no warp
    prior = rlat.LatticePrior(170.0, vp, 40)
    assert rlat.comb_start(mask, vp, params, prior).roll == 0.0
    tprior = flat.LatticePriorBatch(torch.tensor([170.0], dtype=torch.float64), torch.tensor([True]),
                                    torch.tensor([vp]), torch.tensor([40]))
    assert float(flat.comb_start(torch.from_numpy(mask)[None], torch.tensor([vp]), params, tprior).roll[0]) == 0.0


@pytest.mark.parametrize(("contrasts", "won"), [
    ({0: 1.0, -1: 1.10, 1: 1.14, -2: 1.149}, 0),  # no warp beats the unwarped comb by the margin
    ({0: 1.0, -1: 1.10, 1: 1.16, -2: 1.155, 2: 1.16}, 1),  # then the first highest, by any amount
    ({0: 1.0, -1: 1.20, 1: 1.10}, -1),
    ({0: -0.5, -1: -0.45, 1: -0.42}, 1),  # a margin of |contrast|: above -0.5 + 0.075 only
    ({-1: 0.01}, -1),  # an unwarped comb that binned nothing loses to any that did
], ids=["within", "first-highest", "first", "negative", "unwarped-empty"])
def test_a_warp_wins_only_by_the_margin_on_both_paths(monkeypatch, contrasts: dict, won: int) -> None:
    """Each warp ``j``'s comb finds spacing ``20 + j`` with the listed contrast (not listed: it
    binned nothing); both paths' :func:`comb_start` pick the same warp."""
    def one(m, v, p, prior=None, j=0, table=None):
        return 20 + j, 32, j in contrasts, contrasts.get(j, 0.0)

    def batched(m, v, p, prior=None, j=0, table=None):
        s, ph, f, c = one(m, v, p, prior, j)
        ones = torch.ones(m.shape[0], dtype=torch.int64)
        return ones * s, ones * ph, ones.bool() & f, ones.double() * c

    monkeypatch.setattr(rlat, "comb_search", one)
    monkeypatch.setattr(flat, "comb_search", batched)
    mask, vp, params = np.zeros((40, 64), bool), (32, -10), WARPED.replace(lattice_comb_warps=2)
    want = rlat.comb_start(mask, vp, params)
    got = flat.comb_start(torch.from_numpy(mask)[None], torch.tensor([vp]), params)
    assert want.spacing == 20 + won and (want.roll == 0.0) == (won == 0)
    assert int(got.spacing[0]) == want.spacing and float(got.roll[0]) == want.roll
    assert np.array_equal(got.coef[0].numpy(), want.coef)


def _dense_field(degrees: float, seed: int = 0, shift: float = 0.0) -> np.ndarray:
    """Thirteen green rows 30 px apart at the bottom, through a VP in the image (a forward camera
    seeing the horizon), turned about the centre and enlarged so that no corner is uncovered."""
    rng = np.random.default_rng(seed)
    vp = (W / 2, 60.0)
    img = np.clip(np.array([120, 90, 60]) + rng.integers(-10, 11, (H, W, 3)), 0, 255).astype(np.uint8)
    img[:50] = (200, 210, 230)  # sky
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    for k in range(-6, 7):
        xb = W / 2 + shift + k * 30.0
        a = (xb - vp[0]) / ((H - 1) - vp[1])
        img[(ys > vp[1] + 8) & (np.abs(xs - (xb + a * (ys - (H - 1)))) < 1 + 3 * (ys - vp[1]) / H)] = (40, 170, 40)
    return _turn_filled(img, degrees, cv2.INTER_NEAREST)


def _turn_filled(img: np.ndarray, degrees: float, interp: int) -> np.ndarray:
    """``img`` turned about its centre and enlarged until no corner is uncovered (a rolled camera's
    view; ``benchmarks/bench_crdld_views.py``'s ``turn_filled``)."""
    h, w = img.shape[:2]
    th = np.radians(abs(degrees))
    m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), degrees, float(np.cos(th) + (w / h) * np.sin(th)))
    return cv2.warpAffine(img, m, (w, h), flags=interp, borderMode=cv2.BORDER_REPLICATE)


def test_a_dense_rolled_field_on_both_paths(data_dir) -> None:
    """Synthetic and rover frames rolled by a few degrees: detector (batched and alone) and
    lattice tracker give the reference's records with the warped comb."""
    synthetic = [_dense_field(6.0, seed=i, shift=4.0 * i) for i in range(3)]
    det = CropRowDetector(WARPED)
    batch = [r.to_record() for r in det.detect(synthetic).results()]
    for img, got in zip(synthetic, batch):
        assert detect(img, WARPED).to_record() == got
    assert det.detect(synthetic[1:2]).results()[0].to_record() == batch[1]
    folder = data_dir / "caterra_video"
    if not folder.is_dir():
        pytest.skip(f"caterra_video not found under {data_dir}")
    frames = [_turn_filled(cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB), 5.0, cv2.INTER_LINEAR)
              for p in sorted(folder.glob("*.jpg"))[:6]]
    params = WARPED.replace(video_width=500)
    got = torchrow.Tracker(params).track([frames])[0]
    want = RefTracker(params).track(frames)
    for r, g in zip(want, got):
        assert not record_differences(r.to_record(), g.to_record())
    # turned by 5 degrees, the equally spaced comb starts no lattice the tracker can confirm;
    # the warped one does, and the tracked frames' restricted comb keeps it
    assert [r.state for r in got][2:] == ["in_row"] * 4 and not all(r.hough_ran for r in got)
    assert all(r.state == "lost" for r in torchrow.Tracker(params.replace(lattice_comb_warps=0)).track([frames])[0])


def test_warps_need_the_roll_search() -> None:
    assert WARPED.lattice_warps() == (0, -1, 1, -2, 2, -3, 3, -4, 4, -5, 5, -6, 6)
    assert ROLLED.lattice_warps() == (0,)
    with pytest.raises(ValueError, match=r"lattice_comb_warps.*lattice_roll_grid"):
        WARPED.replace(lattice_roll_grid=0)
    with pytest.raises(ValueError, match="lattice_comb_warps"):
        ROLLED.replace(lattice_comb_warps=20)
