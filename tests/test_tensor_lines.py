"""Tensor Hough voting, line search (sections 5-6) and RANSAC (section 7) vs the reference,
stage by stage, on real CRBD masks and on adversarial ones.

The inputs of each stage come from the reference's previous stage, so a failure points at
the stage under test, not at an upstream difference.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchrow.core.io import load_image
from torchrow.core.params import Params
from torchrow.core.results import REASONS
from torchrow.functional import hough as th
from torchrow.functional import ransac as tr
from torchrow.functional import vanishing as tvan
from torchrow.reference import color as rcolor
from torchrow.reference import hough as rh
from torchrow.reference import ransac as rr
from torchrow.reference import sky as rsky
from torchrow.reference import vanishing as rvan
from torchrow.reference import vegetation as rv

P = Params()
HYP = settings(deadline=None, max_examples=60, suppress_health_check=[HealthCheck.too_slow])


def _masks(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Reference sections 1-4: (veg, hough input, bushy)."""
    sky = rsky.sky_row(rgb, P)
    color, _ = rcolor.vegetation_color(rgb, P)
    veg = rv.remove_bushy(rv.raw_mask(rgb, color, P.veg_tol, sky), sky, P)
    hin, bushy = rv.hough_input(veg, sky, P)
    return veg, hin, bushy


def _adversarial_masks(h: int = 240, w: int = 320) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    empty = np.zeros((h, w), bool)
    full = np.ones((h, w), bool)
    noise = rng.random((h, w)) < 0.05
    one = empty.copy()
    one[h // 2, w // 3] = True
    lines = empty.copy()  # three exact lines through one point, one outlier line
    ys = np.arange(h)
    for a, b in ((-0.6, 250.0), (0.0, 160.0), (0.6, 70.0), (0.05, 20.0)):
        xs = np.rint(a * ys + b).astype(int)
        ok = (xs >= 0) & (xs < w)
        lines[ys[ok], xs[ok]] = True
    horizontal = empty.copy()
    horizontal[100:103, :] = True
    return [empty, full, noise, one, lines, horizontal]


@pytest.fixture(scope="module")
def crbd_masks(crbd_dir: Path) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    files = sorted((crbd_dir / "Images").glob("crop_row_*"))[::20]
    return [_masks(load_image(f, P.image_width)) for f in files]


# --- pixel lists -------------------------------------------------------------------------

@HYP
@given(st.integers(0, 4), st.integers(0, 9), st.integers(0, 11), st.floats(0.0, 1.0), st.integers(0, 2**31 - 1))
def test_pixel_list_is_a_stable_partition(b: int, h: int, w: int, density: float, seed: int) -> None:
    mask = torch.from_numpy(np.random.default_rng(seed).random((b, h, w)) < density)
    idx, count = th.pixel_list(mask)
    flat = mask.reshape(b, h * w)
    assert idx.dtype == torch.int64 and count.dtype == torch.int64 and idx.shape == (b, h * w)
    assert torch.equal(count, flat.sum(dim=1))
    assert torch.equal(idx, torch.sort((~flat).to(torch.uint8), dim=1, stable=True).indices)


# --- votes -------------------------------------------------------------------------------

def _check_votes(masks: list[np.ndarray]) -> None:
    got = th.votes(torch.from_numpy(np.stack(masks)), P)
    for i, m in enumerate(masks):
        ref = rh.votes(m, P)  # (2D+1, n_theta)
        assert np.array_equal(got[i].numpy().T, ref), f"mask {i}"


def test_votes_adversarial_equal_reference() -> None:
    _check_votes(_adversarial_masks())
    _check_votes([m[:37, :53] for m in _adversarial_masks()])  # odd size


@pytest.mark.data
def test_votes_crbd_equal_reference(crbd_masks) -> None:
    _check_votes([hin for _, hin, _ in crbd_masks])


def test_votes_bad_input() -> None:
    with pytest.raises((TypeError, ValueError)):
        th.votes(torch.zeros(2, 5, 5, dtype=torch.float32), P)
    with pytest.raises((TypeError, ValueError)):
        th.votes(torch.zeros(5, 5, dtype=torch.bool), P)


# --- line search -------------------------------------------------------------------------

def _check_lines(masks: list[np.ndarray]) -> None:
    got = tvan.find_lines(torch.from_numpy(np.stack(masks)), P)
    for i, m in enumerate(masks):
        ref = rvan.find_lines(m, P)
        held = [(int(got.theta[i, j]), int(got.rho[i, j]), int(got.weight[i, j]))
                for j in range(got.theta.shape[1]) if bool(got.valid[i, j])]
        assert held == [(ln.theta_index, ln.rho, ln.weight) for ln in ref.lines], f"mask {i}: held lines"
        out = [(int(got.out_theta[i, j]), int(got.out_rho[i, j]), int(got.out_weight[i, j]))
               for j in range(got.out_theta.shape[1]) if bool(got.out_valid[i, j])]
        assert out == [(ln.theta_index, ln.rho, ln.weight) for ln in ref.outliers], f"mask {i}: outliers"
        assert int(got.n_rows[i]) == ref.n_rows, f"mask {i}: n_rows"
        assert bool(got.has_vp[i]) == (ref.vp is not None), f"mask {i}: has_vp"
        if ref.vp is not None:
            assert abs(float(got.vp[i, 0]) - ref.vp[0]) <= 1e-6 and abs(float(got.vp[i, 1]) - ref.vp[1]) <= 1e-6


def test_find_lines_adversarial_equal_reference() -> None:
    masks = _adversarial_masks()
    _check_lines(masks)
    _check_lines(masks[::-1])  # batch order does not matter


@pytest.mark.data
def test_find_lines_crbd_equal_reference(crbd_masks) -> None:
    _check_lines([hin for _, hin, _ in crbd_masks])


def test_find_lines_empty_batch() -> None:
    got = tvan.find_lines(torch.zeros((0, 12, 16), dtype=torch.bool), P)
    assert got.theta.shape == (0, P.n_rows) and got.vp.shape == (0, 2)


# --- RANSAC ------------------------------------------------------------------------------

def _check_rows(cases: list[tuple[np.ndarray, np.ndarray, bool]]) -> int:
    """RANSAC on the reference's own lines and VP; returns how many rows were compared."""
    searches = [rvan.find_lines(hin, P) for _, hin, _ in cases]
    s = P.n_rows
    b = len(cases)
    theta = torch.zeros((b, s), dtype=torch.int64)
    rho = torch.zeros((b, s), dtype=torch.int64)
    present = torch.zeros((b, s), dtype=torch.bool)
    vp = torch.zeros((b, 2), dtype=torch.float64)
    band = torch.zeros(b, dtype=torch.int64)
    for i, ((veg, _, bushy), sr) in enumerate(zip(cases, searches)):
        band[i] = P.ransac_band_px(veg.shape[1], bushy)
        if sr.vp is None:
            continue
        vp[i] = torch.tensor(sr.vp)
        for j, ln in enumerate(sr.lines):
            theta[i, j], rho[i, j], present[i, j] = ln.theta_index, ln.rho, True
    veg = torch.from_numpy(np.stack([c[0] for c in cases]))
    h, w = veg.shape[1:]
    fit = tr.fit_rows(veg, theta, rho, present, vp, band, P)
    rows = tr.validate_rows(fit, present, h, torch.full_like(band, P.hough_band_px(w)), P)
    compared = 0
    for i, ((vm, _, bushy), sr) in enumerate(zip(cases, searches)):
        if sr.vp is None:
            assert not bool(rows.present[i].any())
            continue
        fits = [rr.fit_row(vm, ln, sr.vp, P.ransac_band_px(w, bushy), P) for ln in sr.lines]
        ref = rr.validate_rows(fits, h, w, P)
        assert int(rows.present[i].sum()) == len(ref)
        for j, r in enumerate(ref):
            label = f"image {i} row {j}"
            assert int(rows.hypothesis[i, j]) == r.hypothesis, label
            assert bool(rows.valid[i, j]) == r.valid and REASONS[int(rows.reason[i, j])] == r.reason, label
            for got, want in ((float(rows.a[i, j]), r.a), (float(rows.b[i, j]), r.b)):
                if np.isfinite(want):
                    assert abs(got - want) <= 1e-6 * max(1.0, abs(want)), label
                else:
                    assert not np.isfinite(got) and np.isnan(got) == np.isnan(want), label
            compared += 1
    return compared


def test_ransac_adversarial_equal_reference() -> None:
    cases = [(m, m, False) for m in _adversarial_masks()]
    assert _check_rows(cases) >= 3  # the line mask gives rows


@pytest.mark.data
def test_ransac_crbd_equal_reference(crbd_masks) -> None:
    assert _check_rows(crbd_masks) >= 4 * len(crbd_masks)


def test_ransac_vp_margin_fallback_is_exact(monkeypatch) -> None:
    """With a huge margin every hypothesis through the VP takes the spec's exact expression:
    the results must not move (the fast path and the fallback agree)."""
    cases = [(m, m, False) for m in _adversarial_masks()]
    before = _check_rows(cases)
    monkeypatch.setattr(tr, "MARGIN", 1e3)
    tr.FALLBACKS.update(chunks=0, total=0)
    assert _check_rows(cases) == before
    assert tr.FALLBACKS["total"] > 0


def test_export_tracing_does_not_poison_constant_caches() -> None:
    """Tables built while ``torch.export`` traces are traced tensors: they must not be cached
    for later eager calls (regression: eager detection after an ONNX export failed)."""
    th._CACHE.clear()
    tr._TABLES.clear()

    class Uses(torch.nn.Module):
        def forward(self, theta: torch.Tensor) -> torch.Tensor:
            c, _ = th.trig(P, theta.device)
            return c[theta] + tr.hypotheses(P, theta.device)[: theta.shape[0], 0]

    torch.export.export(Uses(), (torch.zeros(3, dtype=torch.int64),), strict=False)
    c, _ = th.trig(P, torch.device("cpu"))
    assert float(c[0]) == 1.0 and float(tr.hypotheses(P, torch.device("cpu"))[0, 0]) >= 0.0
