"""Improved mode (ALGORITHM.md section 11, torchrow extension): stages, parity, records, CLI."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrow.apps.cli import main
from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.core.results import ImageResult, Row, record_differences
from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.metrics import crda_official, rows_to_U
from torchrow.evaluation.synthetic import rowless_scenes
from torchrow.functional import lattice as flat
from torchrow.reference import detect
from torchrow.reference import lattice as rlat

IMPROVED = Params(mode="improved")
CURVED = IMPROVED.replace(lattice_model="curved")


def _t(images: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()


def _field(h: int = 240, w: int = 320, spacing: float = 90.0, shift: float = 0.0, curve: float = 0.0,
           seed: int = 0, ks: range = range(-3, 4)) -> np.ndarray:
    """Green rows ``ks`` through a VP above the image on brown soil, optionally bent (x += curve * t^2)."""
    rng = np.random.default_rng(seed)
    img = np.empty((h, w, 3), np.uint8)
    img[...] = (120, 90, 60)
    img = np.clip(img.astype(np.int64) + rng.integers(-10, 11, img.shape), 0, 255).astype(np.uint8)
    yv = -60.0
    ys, xs = np.mgrid[0:h, 0:w]
    t = ys - (h - 1.0)
    scale = (ys - yv) / (h - 1 - yv)
    for k in ks:
        xc = w / 2 + shift + (k * spacing) * scale + curve * t * t
        on = np.abs(xs - xc) < 4 * scale + 1
        img[on] = (40, 170, 40)
    return img


def _records_equal(a: ImageResult, b: ImageResult) -> None:
    ra, rb = a.to_record(), b.to_record()
    assert not record_differences(ra, rb)
    assert [(r["k"], r["confidence"]) for r in ra["lattice_rows"]] == [(r["k"], r["confidence"]) for r in rb["lattice_rows"]]
    assert (ra["status"], ra["n_rows"]) == (rb["status"], rb["n_rows"])
    assert ra["image_confidence"] == rb["image_confidence"]
    assert len(ra["rows"]) == len(rb["rows"])
    for x, y in zip(ra["rows"], rb["rows"]):
        assert (x["valid"], x["reason"], x["confidence"]) == (y["valid"], y["reason"], y["confidence"])
        for key in ("a", "b", "c", "e"):
            assert (x[key] is None) == (y[key] is None)
            if x[key] is not None:
                assert abs(x[key] - y[key]) <= 1e-6, key


# --- Params -----------------------------------------------------------------------------

@pytest.mark.parametrize(("change", "field"), [
    ({"mode": "fast"}, "mode"),
    ({"lattice_min_spacing": 100, "lattice_max_spacing": 50}, "lattice_max_spacing"),
    ({"lattice_tolerance": 0.5}, "lattice_tolerance"), ({"lattice_window": 0.0}, "lattice_window"),
    ({"lattice_vp_fallback_y": 10}, "lattice_vp_fallback_y"), ({"lattice_iterations": -1}, "lattice_iterations"),
    ({"lattice_min_confidence": 1.5}, "lattice_min_confidence"),
    ({"lattice_horizon": "horizon"}, "lattice_horizon"),
    ({"lattice_green": "exg"}, "lattice_green"), ({"lattice_comb": "fft"}, "lattice_comb"),
    ({"lattice_vp": "hough"}, "lattice_vp"), ({"lattice_vp_step": 0}, "lattice_vp_step"),
    ({"lattice_vp_cell": 0}, "lattice_vp_cell"), ({"lattice_vp_spacing_step": 0}, "lattice_vp_spacing_step"),
    ({"lattice_vp_heights": ()}, "lattice_vp_heights"), ({"lattice_vp_heights": (-20, 2**21)}, "lattice_vp_heights"),
    ({"lattice_center_degree": 4}, "lattice_center_degree"), ({"lattice_center_degree": 1}, "lattice_center_degree"),
])
def test_params_validate_improved_fields(change, field) -> None:
    with pytest.raises(ValueError, match=f"Params.{field}"):
        Params(**change)


#: A wide comb and a dense VP grid (spacings 12..320 px, VPs every 10 px at 15 heights): inside the bound.
WIDE = {"lattice_min_spacing": 12, "lattice_max_spacing": 320, "lattice_vp_step": 10,
        "lattice_vp_heights": (-10, -20, -30, -40, -50, -60, -75, -90, -110, -130, -155, -180, -215, -250, -300)}


@pytest.mark.parametrize(("change", "field"), [
    ({"lattice_max_spacing": 4096}, "lattice_max_spacing"),  # Q = 8.4e6 candidates
    ({"lattice_min_spacing": 1, "lattice_max_spacing": 186}, "lattice_max_spacing"),  # J = 961 teeth
    ({"lattice_vp_step": 1}, "lattice_vp_step"), ({"lattice_vp_heights": tuple(range(-64, 0))}, "lattice_vp_step"),
    ({**WIDE, "lattice_vp_cell": 1}, "lattice_vp_step"),
])
def test_params_refuse_lattice_tables_over_the_bound(change, field) -> None:
    # ALGORITHM.md 11.2: tables above 2**30 bytes at the largest image max_pixels admits at image_width
    with pytest.raises(ValueError, match=rf"^Params\.{field} makes the improved mode's .* > 2\*\*30 .*; got "):
        Params(mode="improved", **change)
    Params(**change)  # the faithful mode builds no lattice tables
    # the VP grid's bound follows the largest image: max_pixels at 320 x 240 admits the grid
    if field == "lattice_vp_step":
        Params(mode="improved", max_pixels=320 * 240, **change)


def test_params_lattice_bound_admits_the_wide_comb_and_its_formula_holds() -> None:
    from torchrow.core.io import ImageError, check_lattice_size, lattice_params
    from torchrow.core.params import LATTICE_TABLE_BYTES

    for change in (WIDE, {"lattice_min_spacing": 1, "lattice_max_spacing": 185}, {"lattice_vp_cell": 1},
                   {"lattice_vp_step": 3}):
        p = Params(mode="improved", **change)
        assert max(p.lattice_table_bytes(320, p.max_pixels // 320)) <= LATTICE_TABLE_BYTES
    # the formula bounds what the code builds (small sizes: cheap to build)
    p = Params(mode="improved", lattice_min_spacing=5, lattice_max_spacing=60, lattice_vp_step=7, lattice_vp_cell=3)
    comb, vp = p.lattice_table_bytes(64, 48)
    q, j = sum(range(5, 61)), 3 * 64 // 5 + 1
    assert all(a.shape == (q, j) for a in rlat._comb_tables(64, p)[3:]) and comb == q * (64 * j + 400)
    grid, idx = flat.vp_table(48, 64, p, torch.device("cpu"))
    assert 8 * (idx.numel() + grid.shape[0] * (3 * 64 + 8 * 60)) == vp
    assert p.replace(lattice_vp="section6").lattice_table_bytes(64, 48) == (comb, 0)
    # a batch wider than image_width is checked at its own size, before any table is built
    q = Params(mode="improved", lattice_vp_step=4)  # 8 V C = 0.6 GB at 320 x 1638, 1.2 GB at 640 x 819
    check_lattice_size(320, 1638, q)
    for call in (lambda: check_lattice_size(640, 819, q), lambda: lattice_params(640, 819, q),
                 lambda: flat.vp_table(819, 640, q, torch.device("cpu"))):
        with pytest.raises(ImageError, match=r"working size 640x819 needs \d+ bytes of improved-mode tables"):
            call()


def test_vp_search_gather_form_equals_the_scatter(monkeypatch) -> None:
    # the exported graph bins the cells with gathers and one cumulative sum (onnxruntime scatters
    # slowly); the histograms and so the VPs are the scatter's, with and without a moved origin
    masks = torch.from_numpy(np.stack(_search_masks()[:3]))
    origin = torch.tensor([0, 5, 30])
    want = [flat.vp_search(masks, IMPROVED), flat.vp_search(masks, IMPROVED, origin),
            flat.vp_search(masks[1:2], IMPROVED, origin[1:2])]
    flat.vp_gather_table(masks.shape[1], masks.shape[2], IMPROVED, masks.device)  # as to_onnx, before tracing
    # a whole grid at batch 1 (119 VPs) folds its spacings at once while exporting (EXPORT_AT_ONCE_ROWS)
    flat.vp_fold_tables(masks.shape[1], masks.shape[2], IMPROVED, masks.device)
    monkeypatch.setattr(torch.compiler, "is_exporting", lambda: True)  # the form the exporter traces
    got = [flat.vp_search(masks, IMPROVED), flat.vp_search(masks, IMPROVED, origin),
           flat.vp_search(masks[1:2], IMPROVED, origin[1:2])]
    assert all(torch.equal(a, b) for a, b in zip(got, want))
    h, w = masks.shape[1:]
    idx = flat.vp_table(h, w, IMPROVED, torch.device("cpu"))[1]
    cnt = torch.randint(0, 5, (2, idx.shape[1]), dtype=torch.int32)
    scattered = flat._scattered_histograms(cnt, idx.shape[0], w, lambda v0, k: idx[v0:v0 + k])
    assert torch.equal(flat._gathered_histograms(cnt, h, w, IMPROVED), scattered)


def test_vp_search_product_form_equals_the_scatter(monkeypatch) -> None:
    # batches of PRODUCT_MIN_BATCH images or more bin a whole grid by a sparse product on a CPU;
    # its histograms (the tail of zeros included) and so the VPs are the scatter's
    masks = torch.from_numpy(np.stack(_search_masks()[:4]))
    h, w = masks.shape[1:]
    idx = flat.vp_table(h, w, IMPROVED, torch.device("cpu"))[1]
    cnt = torch.randint(0, IMPROVED.lattice_vp_cell**2 + 1, (5, idx.shape[1]), dtype=torch.int32)
    cnt[1] = 0
    scattered = flat._scattered_histograms(cnt, idx.shape[0], w, lambda v0, k: idx[v0:v0 + k])
    product = flat._multiplied_histograms(cnt, h, w, IMPROVED)
    assert product.shape == (5, idx.shape[0], 3 * w + 1 + IMPROVED.lattice_max_spacing)
    assert torch.equal(product[:, :, :3 * w], scattered) and not product[:, :, 3 * w:].any()
    origin = torch.tensor([0, 5, 30, 0])
    want = [flat.vp_search(masks, IMPROVED), flat.vp_search(masks, IMPROVED, origin)]
    monkeypatch.setattr(flat, "PRODUCT_MIN_BATCH", 10**9)
    assert all(torch.equal(a, b) for a, b in zip(want, [flat.vp_search(masks, IMPROVED),
                                                        flat.vp_search(masks, IMPROVED, origin)]))


def test_vp_search_in_slices_equals_one_slice(monkeypatch) -> None:
    # the VP search projects a few VPs at a time (bounded memory); the slicing changes nothing
    masks = _search_masks()[:3]
    want = [rlat.vp_search(m, IMPROVED) for m in masks]
    monkeypatch.setattr(rlat, "VP_SLICE", 1000)
    monkeypatch.setattr(flat, "VP_SLICE", 1000)
    monkeypatch.setattr(flat, "_VP_TABLES", {})
    assert [rlat.vp_search(m, IMPROVED) for m in masks] == want
    got = flat.vp_search(torch.from_numpy(np.stack(masks)), IMPROVED)
    assert [tuple(v) for v in got.tolist()] == want


def test_params_mode_of_the_wrong_kind_is_a_type_error() -> None:
    with pytest.raises(TypeError, match=r"Params\.mode must be a str"):
        Params(mode=1)  # type: ignore[arg-type]


# --- reference stages ---------------------------------------------------------------------

def test_solve_normal_matches_numpy_and_flags_singular() -> None:
    rng = np.random.default_rng(1)
    a = rng.normal(size=(40, 6))
    m, r = a.T @ a, a.T @ rng.normal(size=40)
    z = rlat.solve_normal(m, r, IMPROVED)
    np.testing.assert_allclose(z, np.linalg.solve(m, r), rtol=1e-9)
    zt, singular = flat.solve_normal(torch.from_numpy(m)[None], torch.from_numpy(r)[None], IMPROVED)
    assert not bool(singular[0]) and torch.equal(zt[0], torch.from_numpy(z))
    a[:, 5] = a[:, 4]  # two equal columns: singular
    assert rlat.solve_normal(a.T @ a, a.T @ rng.normal(size=40), IMPROVED) is None


def test_solve_normal_pivots_are_relative_to_their_own_diagonal() -> None:
    # the cubic basis of a 240-row image: diagonal entries from 720 to ~1e16; a pivot test
    # against the largest of them would call this well-posed system singular
    t = np.repeat(np.arange(240.0) - 239, 3)
    k = np.tile([-1.0, 0.0, 1.0], 240)
    phi = np.stack([t**0, t, t**2, t**3, k, k * t, k * t**2], axis=1)
    truth = np.array([160.0, 0.1, 1e-3, 2e-6, 90.0, 0.3, 1e-4])
    m, r = phi.T @ phi, phi.T @ (phi @ truth)
    z = rlat.solve_normal(m, r, IMPROVED)
    assert z is not None
    np.testing.assert_allclose(phi @ z, phi @ truth, atol=1e-6)
    zt, singular = flat.solve_normal(torch.from_numpy(m)[None], torch.from_numpy(r)[None], IMPROVED)
    assert not bool(singular[0]) and torch.equal(zt[0], torch.from_numpy(z))


def _cells_by_pixel(mask: np.ndarray, coef: np.ndarray, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """Section 11.3's cells, the rule applied pixel by pixel (the spec's words, not prefix sums)."""
    h, _w = mask.shape
    cnt = np.zeros((2 * params.lattice_half + 1, h), np.int64)
    sx = np.zeros_like(cnt)
    cc, dd = rlat.centre_spacing(np.arange(h, dtype=np.float64) - (h - 1), coef)
    for y, x in zip(*np.nonzero(mask)):
        if not dd[y] > params.lattice_min_spacing_px:
            continue
        for i, k in enumerate(range(-params.lattice_half, params.lattice_half + 1)):
            centre = cc[y] + np.float64(k) * dd[y]
            half = np.float64(params.lattice_tolerance) * dd[y]
            if centre - half < x < centre + half:
                cnt[i, y] += 1
                sx[i, y] += x
    return cnt, sx


@pytest.mark.parametrize("seed", range(4))
def test_row_cells_are_the_per_pixel_rule_on_both_paths(seed: int) -> None:
    rng = np.random.default_rng(seed)
    h, w = 37, 53
    params = IMPROVED.replace(lattice_half=int(rng.integers(1, 3)))
    mask = rng.random((h, w)) < 0.3
    coefs = [np.array([26.0, 0.05, 1e-3, 2e-5, 12.5, 0.1, 1e-3]),  # ends on exact halves and integers
             np.array([rng.uniform(-20, 70), rng.normal(), rng.normal() * 1e-2, rng.normal() * 1e-4,
                       rng.uniform(1, 30), rng.normal() * 0.2, rng.normal() * 1e-3]),
             np.array([26.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]),  # d(t) <= lattice_min_spacing_px: no cells
             np.array([np.nan, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0]), np.array([1e300, 1e300, 0, 0, 1e300, 0, 0])]
    pre = flat.prefix_sums(torch.from_numpy(mask)[None])
    for coef in coefs:
        want = _cells_by_pixel(mask, coef, params)
        got = rlat.row_cells(rlat.prefix_sums(mask), coef, params)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        cnt, sx = flat.row_cells(pre, torch.from_numpy(coef)[None], params)
        assert np.array_equal(cnt[0].T.numpy(), want[0]) and np.array_equal(sx[0].T.numpy(), want[1])


def _refit_every_iteration(mask: np.ndarray, params: Params) -> np.ndarray:
    """Sections 11.3 and 11.3.1 without the fixed-point stop: every iteration runs unless the
    inliers are too few or the system is singular; ``"auto"`` keeps the curved refit where it
    holds more than ``1 + lattice_curve_gain`` times the straight lattice's inlier pixels (both
    refits from the comb's start)."""
    h, _w = mask.shape
    xv, yv = rlat.vp_search(mask, params)
    d, phase, _, _ = rlat.comb_search(mask, (xv, yv), params)
    den = np.float64(h - 1 - yv)
    coef = np.array([phase, (np.float64(phase) - xv) / den, 0, 0, d, np.float64(d) / den, 0], np.float64)
    pre = rlat.prefix_sums(mask)

    def every(coef: np.ndarray, straight: bool) -> np.ndarray:
        for _ in range(params.lattice_iterations):
            cnt, sx = rlat.row_cells(pre, coef, params)
            sol = None if cnt.sum() < params.lattice_min_points else rlat.solve_normal(
                *rlat.normal_equations(cnt, sx, h, params, straight), params)
            if sol is None:
                break
            coef = np.zeros(rlat.N_COEF)
            coef[params.lattice_coef_index(straight)] = sol
        return coef

    if params.lattice_model == "curved":
        return every(coef, False)
    start = coef
    coef = every(start, True)
    if params.lattice_model == "straight":
        return coef
    bent = every(start, False)
    n_s, n_b = (int(rlat.row_cells(pre, c, params)[0].sum()) for c in (coef, bent))
    return bent if n_b > (1 + params.lattice_curve_gain) * n_s else coef


@pytest.mark.parametrize(("iterations", "model"), [(2, "curved"), (40, "curved"), (40, "auto"), (3, "straight")])
def test_fixed_point_stop_gives_the_result_of_every_iteration(iterations: int, model: str) -> None:
    params = IMPROVED.replace(lattice_iterations=iterations, lattice_model=model)
    images = [_s_field(), _field(curve=0.001, seed=7), _field(spacing=45.0, shift=100.0, seed=3)]
    masks = [rlat.green_mask(img, 0, params) for img in images] + [np.random.default_rng(2).random((240, 320)) < 0.2]
    got = flat.fit_lattice(torch.from_numpy(np.stack(masks)), torch.zeros(len(masks), dtype=torch.int64),
                           None, None, params)[0]
    for i, mask in enumerate(masks):
        want = _refit_every_iteration(mask, params)
        assert np.array_equal(np.array(rlat.fit_lattice(mask, 0, None, params).coef), want)
        assert np.array_equal(got[i].numpy(), want)


def test_tall_images_fall_back_to_a_quadratic_where_cubic_sums_could_overflow() -> None:
    from torchrow.core.io import ImageError, lattice_params

    assert lattice_params(320, 240, IMPROVED) is IMPROVED
    assert lattice_params(640, 578, IMPROVED) is IMPROVED
    assert lattice_params(800, 579, IMPROVED) == IMPROVED.replace(lattice_center_degree=2)
    # section 6's VP: no VP search, whose tables at 4096 x 4096 exceed their bound (ALGORITHM.md 11.5)
    quadratic = IMPROVED.replace(lattice_center_degree=2, lattice_vp="section6", lattice_min_spacing=40,
                                 lattice_max_spacing=180)  # and a comb range whose tables fit at that size
    assert lattice_params(4096, 4096, quadratic).lattice_center_degree == 2
    with pytest.raises(ImageError, match="too large"):
        lattice_params(64, 4096, IMPROVED.replace(lattice_half=64, lattice_cell_grid=2**16))
    mask = np.zeros((600, 120), bool)
    for x0 in (15, 55, 95):  # three slanted stripes
        for y in range(600):
            mask[y, x0 + y // 60:x0 + y // 60 + 4] = True
    fit = rlat.fit_lattice(mask, 0, None, IMPROVED)
    assert fit.found and fit.coef[3] == 0.0
    got = flat.fit_lattice(torch.from_numpy(mask)[None], torch.zeros(1, dtype=torch.int64), None, None, IMPROVED)[0]
    assert np.array_equal(got[0].numpy(), np.array(fit.coef))


def test_otsu_separates_two_populations() -> None:
    exg = np.full((20, 20), -30, np.int64)
    exg[:, :5] = 90
    thr = rlat.otsu_threshold(exg, 0, IMPROVED)
    assert -30 <= thr < 90
    assert rlat.otsu_threshold(exg, 0, IMPROVED.replace(green_floor=95)) == 95


@pytest.mark.parametrize(("spacing", "shift"), [(90.0, 0.0), (70.0, 25.0), (120.0, -40.0)])
def test_comb_and_fit_recover_a_synthetic_lattice(spacing: float, shift: float) -> None:
    img = _field(spacing=spacing, shift=shift)
    mask = rlat.green_mask(img, 0, IMPROVED)
    vp = (160 + shift, -60.0)  # the field's own vanishing point
    d, phase, found, _ = rlat.comb_search(mask, (int(vp[0]), -60), IMPROVED)
    assert found and abs(d - spacing) <= 2
    assert abs(phase - (160 + shift)) <= 0.1 * spacing  # the refit below makes it exact
    rows, conf, _fit, *_ = rlat.improved_rows(img, 0, vp, IMPROVED)
    assert [r.valid for r in rows] == [True] * 3 and conf > 0.75  # the far rows are 14 px apart
    xb = sorted(r.x_at(239.0) for r in rows)
    np.testing.assert_allclose(xb, [160 + shift - spacing, 160 + shift, 160 + shift + spacing], atol=1.5)


def test_curved_lattice_gets_its_curvature() -> None:
    # the rows bend 17 px by the top row, where they are 18 px apart (more would alias)
    img = _field(curve=0.0003)
    rows, _, _fit, *_ = rlat.improved_rows(img, 0, (160.0, -60.0), IMPROVED.replace(lattice_model="curved"))
    assert all(r.valid for r in rows)
    assert all(abs(r.c - 0.0003) < 3e-5 for r in rows)
    y = np.arange(240.0)
    truth = 160 + 0.0003 * (y - 239) ** 2
    assert np.abs(rows[1].x_at(y) - truth).max() < 3


def _s_field(bend: float = 1e-5, spacing: float = 90.0) -> np.ndarray:
    """Rows with an S-bend: ``x += bend * t (t + 120) (t + 239)`` (t = y - 239), 6.6 px to the
    left in the near half and to the right in the far half, as many curved CRBD rows bend."""
    img = np.empty((240, 320, 3), np.uint8)
    img[...] = (120, 90, 60)
    ys, xs = np.mgrid[0:240, 0:320]
    t = ys - 239.0
    scale = (ys + 60.0) / 299.0
    for k in range(-3, 4):
        xc = 160 + (k * spacing) * scale + bend * t * (t + 120) * (t + 239)
        img[np.abs(xs - xc) < 4 * scale + 1] = (40, 170, 40)
    return img


def test_cubic_lattice_follows_an_s_bend_that_a_quadratic_cannot() -> None:
    img = _s_field()
    y = np.arange(240.0)
    truth = 160 + 1e-5 * (y - 239) * (y - 119) * y
    rows, _, fit, *_ = rlat.improved_rows(img, 0, None, IMPROVED)
    assert all(r.valid for r in rows) and fit.coef[3] != 0.0
    assert abs(rows[1].e - 1e-5) < 1e-6
    assert np.abs(rows[1].x_at(y) - truth).max() < 2
    quad, _, qfit, *_ = rlat.improved_rows(img, 0, None, IMPROVED.replace(lattice_center_degree=2))
    assert qfit.coef[3] == 0.0 and all(r.e == 0.0 for r in quad)
    assert np.abs(quad[1].x_at(y) - truth).max() > 4
    got = CropRowDetector(IMPROVED)(_t([img])).results()[0]
    _records_equal(detect(img, IMPROVED), got)


@pytest.mark.parametrize("seed", range(3))
def test_row_polynomials_are_the_lattice_model(seed: int) -> None:
    # section 11.4 expands x_k(y) = c(t) + k d(t), t = y - (H-1), into e y^3 + c y^2 + a y + b
    rng = np.random.default_rng(seed)
    coef = (rng.uniform(100, 200), rng.normal() * 0.3, rng.normal() * 1e-3, rng.normal() * 1e-5,
            rng.uniform(40, 120), rng.normal() * 0.2, rng.normal() * 1e-4)
    fit = rlat.LatticeFit(coef, 90, 160, (160, -60), (100, 120, 140), 240, True)
    rows = rlat.lattice_rows(fit, 240, IMPROVED)
    y = np.arange(240.0)
    cc, dd = rlat.centre_spacing(y - 239, np.array(coef))
    for k, row in zip((-1, 0, 1), rows):
        np.testing.assert_allclose(row.x_at(y), cc + k * dd, atol=1e-6)
        assert row.e == coef[3]


def test_faithful_rows_carry_zero_curvature() -> None:
    res = detect(_field(), Params())
    rec = res.to_record()
    assert all(r["c"] == 0.0 and r["e"] == 0.0 and r["confidence"] is None for r in rec["rows"])
    assert rec["image_confidence"] is None and rec["lattice_rows"] is None
    assert rec["veg_color"] is not None and rec["hough"] is not None  # sections 2-6 ran


# --- metrics -------------------------------------------------------------------------------

def test_metrics_score_curves() -> None:
    class GT:
        height = 240
        c = 0.001 * (np.arange(240.0) - 239) ** 2
        d = np.full(240, 80.0)

    rows = []
    for k in (-1, 0, 1):
        c2, yb = 0.001, 239.0
        rows.append(Row(-2 * c2 * yb, 160 + 80 * k + c2 * yb * yb, True, c=c2))
    res = ImageResult(width=320, height=240, status="ok", rows=rows)
    assert crda_official(res, GT) == pytest.approx(1.0)
    straight = ImageResult(width=320, height=240, status="ok", rows=[Row(r.a, r.b, True) for r in rows])
    assert crda_official(straight, GT) < 0.5
    u = rows_to_U(rows, 240)
    np.testing.assert_allclose(u[:, 1], 160 + GT.c, atol=1e-9)


def test_metrics_score_cubic_rows() -> None:
    e3, yb = 2e-6, 239.0

    class GT:
        height = 240
        c = e3 * (np.arange(240.0) - yb) ** 3
        d = np.full(240, 80.0)

    # x = e (y - Y)^3 + 160 + 80 k, expanded in y
    rows = [Row(3 * e3 * yb * yb, 160 + 80 * k - e3 * yb**3, True, c=-3 * e3 * yb, e=e3) for k in (-1, 0, 1)]
    res = ImageResult(width=320, height=240, status="ok", rows=rows)
    assert crda_official(res, GT) == pytest.approx(1.0)
    np.testing.assert_allclose(rows_to_U(rows, 240)[:, 1], 160 + GT.c, atol=1e-9)
    flat_rows = [Row(r.a, r.b, True, c=r.c) for r in rows]  # the cubic term dropped
    assert crda_official(ImageResult(width=320, height=240, status="ok", rows=flat_rows), GT) < 0.6


# --- tensor path = reference ---------------------------------------------------------------

def _adversarial() -> list[np.ndarray]:
    rng = np.random.default_rng(5)
    blank = np.full((240, 320, 3), 128, np.uint8)
    green = np.zeros((240, 320, 3), np.uint8)
    green[..., 1] = 255
    # salt-and-pepper of 64 colours (full 24-bit noise makes section 2's clustering slow)
    noise = (rng.integers(0, 4, (240, 320, 3)) * 85).astype(np.uint8)
    half = _field(curve=-0.003, spacing=60.0)
    half[:120] = (200, 220, 255)  # sky-like top half
    return [blank, green, noise, half, _field(spacing=45.0, shift=100.0, seed=3)]


def test_tensor_equals_reference_on_adversarial_and_shuffled_batches() -> None:
    images = _adversarial() + [_field(curve=0.001, seed=7)]
    det = CropRowDetector(IMPROVED)
    out = det(_t(images)).results()
    for img, got in zip(images, out):
        _records_equal(detect(img, IMPROVED), got)
    # 11.4: no green pixel below the lattice's top row (grey; uniform green is no greener than
    # its rows' means) -> the comb bins none -> every row invalid (no_support), no lattice rows
    for got in out[:2]:
        assert got.status == "invalid" and got.lattice_rows == []
        assert [(r.valid, r.reason) for r in got.rows] == [(False, "no_support")] * 3
    perm = [3, 0, 5, 1, 4, 2]
    shuffled = det(_t([images[i] for i in perm])).results()
    for j, i in enumerate(perm):
        assert shuffled[j].to_record() == out[i].to_record()


def test_forward_setting_rejects_rows_the_image_does_not_show() -> None:
    """11.4: with spacings up to 320 px a forward camera's lattice can put the central row's
    neighbours outside the image; the forward-camera setting's ``lattice_min_confidence`` (0.02)
    makes such a row invalid (``no_support``), so the image is not ``ok``; both paths."""
    fwd = Params(mode="improved", **FORWARD_CAMERA)
    assert fwd.lattice_min_confidence == 0.02
    images = [_field(ks=range(0, 1)), _field(ks=range(0, 2), spacing=120.0), _field()]
    out = CropRowDetector(fwd)(_t(images)).results()
    for img, got in zip(images, out):
        _records_equal(detect(img, fwd), got)
    assert [g.status for g in out] == ["invalid", "invalid", "ok"]
    assert [(r.valid, r.reason) for r in out[0].rows] == [(False, "no_support"), (True, ""), (False, "no_support")]
    assert [r.valid for r in out[1].rows] == [False, True, True]
    assert out[2].lattice_rows and all(r.confidence >= 0.02 for r in out[2].lattice_rows)
    # without the rule one row of green gave `ok` with three valid rows, two of them on bare soil
    loose = fwd.replace(lattice_min_confidence=0.0)
    got = CropRowDetector(loose)(_t(images[:1])).results()[0]
    _records_equal(detect(images[0], loose), got)
    assert got.status == "ok" and [r.confidence for r in got.rows] == [0.0, 1.0, 0.0]


def test_scenes_without_crop_rows_are_never_ok() -> None:
    """Issue 25: a wall, noise, sky, soil, asphalt, lawns and a road are never ``ok``, in the
    default and the forward-camera setting (the road was, before the forward setting's
    ``lattice_min_confidence``), and both paths agree on them."""
    scenes = rowless_scenes()
    assert len(scenes) == 10 and all(v.shape == (240, 320, 3) and v.dtype == np.uint8 for v in scenes.values())
    assert all(np.array_equal(a, b) for a, b in zip(scenes.values(), rowless_scenes().values()))
    images = list(scenes.values())
    for params in (IMPROVED, Params(mode="improved", **FORWARD_CAMERA)):
        out = CropRowDetector(params)(_t(images)).results()
        for name, img, got in zip(scenes, images, out):
            if name in ("noise", "lawn", "road under sky"):  # the reference on a few: it is the slow path
                _records_equal(detect(img, params), got)
            assert got.status != "ok", (name, params.lattice_model)
    with pytest.raises(ValueError, match="2x2"):
        rowless_scenes(height=1)


def test_row_dominance_counts_cells_where_a_row_beats_its_fuller_gap() -> None:
    # rows -1..1 on three image rows; gaps -1.5..1.5. Image row 0: every row beats both gaps;
    # row 1: row 0 ties its gap (3 vs 3: lit, no win), the others win; row 2: nothing lit
    rows = np.array([[5, 4, 2], [4, 3, 6], [0, 0, 0]], np.int64).T  # (2K+1, H)
    gaps = np.array([[1, 0, 1, 0], [1, 3, 0, 2], [0, 0, 0, 0]], np.int64).T  # (2K+2, H)
    want = 5 / 6
    assert rlat.row_dominance(rows, gaps) == want
    batched = torch.from_numpy(np.stack([rows.T, np.zeros_like(rows.T)]))  # (B, H, 2K+1)
    gaps_t = torch.from_numpy(np.stack([gaps.T, gaps.T]))
    before = (batched.clone(), gaps_t.clone())
    got = flat.row_dominance(batched, gaps_t)
    assert got.dtype == torch.float64 and got.tolist() == [want, 0.0]  # all-zero rows: lit by the gaps, no win
    assert torch.equal(batched, before[0]) and torch.equal(gaps_t, before[1])
    assert flat.row_dominance(batched[:0], gaps_t[:0]).shape == (0,)
    assert rlat.row_dominance(np.zeros((3, 4), np.int64), np.zeros((4, 4), np.int64)) == 0.0  # nothing lit
    assert rlat.gap_offsets(IMPROVED) == flat.gap_offsets(IMPROVED, torch.device("cpu")).tolist() == [-1.5, -0.5, 0.5, 1.5]


def test_rows_across_the_view_are_not_ok_with_the_forward_setting() -> None:
    """Issue 25: a field turned by 90° (its rows run across the image) whose comb is strong
    enough for ``ok`` is not ``ok`` with the forward-camera setting: its rows do not outnumber
    their gaps (11.4's dominance). The upright field stays ``ok``; both paths agree."""
    params = Params(mode="improved", **FORWARD_CAMERA)
    upright = _field(spacing=120.0, ks=range(-8, 9))
    turned = np.ascontiguousarray(np.rot90(_field(h=320, w=240, spacing=120.0, ks=range(-8, 9))))  # 240 x 320 too
    for img, rule_ok in ((upright, True), (turned, False)):
        got = CropRowDetector(params)(_t([img])).results()[0]
        _records_equal(detect(img, params), got)
        dominance = rlat.improved_rows(img, 0, None, params).dominance
        rows = flat.improved_rows(_t([img]), torch.zeros(1, dtype=torch.int64), None, None, params)
        assert rows.dominance.tolist() == [dominance]
        assert detect(img, params.replace(lattice_min_dominance=0.0)).status == "ok"  # contrast and rows pass
        assert (dominance >= params.lattice_min_dominance) == rule_ok
        assert got.status == ("ok" if rule_ok else "weak")
    # without the rule (the default setting) the dominance is not computed, in either path
    assert np.isnan(rlat.improved_rows(upright, 0, None, IMPROVED).dominance)
    assert flat.improved_rows(_t([upright]), torch.zeros(1, dtype=torch.int64), None, None, IMPROVED).dominance.isnan().all()


@pytest.mark.parametrize(("green", "comb"), [("row_mean", "contrast"), ("otsu", "uniform"), ("otsu", "contrast")])
def test_tensor_stages_equal_reference_stages(green: str, comb: str) -> None:
    params = IMPROVED.replace(lattice_green=green, lattice_comb=comb)
    images = _adversarial()
    x = _t(images)
    sky = torch.tensor([0, 0, 0, 120, 30])
    got = flat.green_mask(x, sky, params)
    for i, img in enumerate(images):
        want = rlat.green_mask(img, int(sky[i]), params)
        assert torch.equal(got[i], torch.from_numpy(want))
    vp = torch.tensor([[160.0, -60.0], [150.4, -20.5], [0.0, 0.0], [170.0, 5.0], [float("nan"), -50.0]],
                      dtype=torch.float64)
    has = torch.tensor([True, True, False, True, True])
    v = flat.init_vp(vp, has, 320, params)
    sp, ph, found, contrast = flat.comb_search(got, v, params)
    for i in range(len(images)):
        ref_vp = rlat.init_vp(tuple(vp[i].tolist()) if bool(has[i]) else None, 320, params)
        assert tuple(v[i].tolist()) == ref_vp
        want = rlat.comb_search(got[i].numpy(), ref_vp, params)
        assert (int(sp[i]), int(ph[i]), bool(found[i]), float(contrast[i])) == want


def _search_masks() -> list[np.ndarray]:
    rng = np.random.default_rng(5)
    masks = [rlat.green_mask(img, 0, IMPROVED) for img in _adversarial()]
    masks += [rng.random((240, 320)) < q for q in (0.002, 0.5)]
    edge = np.zeros((240, 320), bool)
    edge[:, -1] = True  # one column at the border: most VPs project it off the bins
    return masks + [edge]


@pytest.mark.parametrize("change", [{}, {"lattice_vp_cell": 3, "lattice_vp_step": 37, "lattice_vp_spacing_step": 5},
                                    {"lattice_vp_cell": 1, "lattice_vp_heights": (-1, -500), "lattice_window": 0.3}])
def test_vp_search_tensor_equals_reference_batched_and_alone(change: dict) -> None:
    params = IMPROVED.replace(**change)
    masks = _search_masks()
    got = flat.vp_search(torch.from_numpy(np.stack(masks)), params)
    assert got.dtype == torch.int64 and got.shape == (len(masks), 2)
    for i, m in enumerate(masks):
        assert tuple(got[i].tolist()) == rlat.vp_search(m, params)
        assert torch.equal(flat.vp_search(torch.from_numpy(m)[None], params)[0], got[i])
    empty = flat.vp_search(torch.zeros((0, 240, 320), dtype=torch.bool), params)
    assert empty.shape == (0, 2)
    # a tracked window (11.7): its spacings at once alone, one by one in the batch (AT_ONCE_ROWS)
    spots = [[160, -40], [0, -250], [320, -20], [100, -90], [250, -130], [40, -60], [-300, 10], [900, -900]]
    near = torch.tensor([spots[i % len(spots)] for i in range(len(masks))])
    got = flat.vp_search(torch.from_numpy(np.stack(masks)), params, None, near)
    for i, m in enumerate(masks):
        assert tuple(got[i].tolist()) == rlat.vp_search(m, params, 0, tuple(near[i].tolist()))
        assert torch.equal(flat.vp_search(torch.from_numpy(m)[None], params, None, near[i:i + 1])[0], got[i])


@pytest.mark.parametrize("change", [{}, {"lattice_min_spacing": 16, "lattice_max_spacing": 320},
                                    {"lattice_min_spacing": 7, "lattice_max_spacing": 97, "lattice_vp_spacing_step": 3,
                                     "lattice_window": 0.3}])
def test_vp_search_fold_peaks_at_once_equal_spacing_by_spacing(change: dict, monkeypatch) -> None:
    # vp_search takes the spacings at once for small batches and spacing by spacing for large
    # ones (a size bound, not a rule): the same integers, on extreme histograms too
    params = IMPROVED.replace(**change)
    rng = np.random.default_rng(5)
    nb = 3 * 320
    hist = torch.from_numpy(rng.integers(0, 60, (3, 4, nb + 1 + params.lattice_max_spacing)).astype(np.int32))
    hist[0, 0] = 0
    hist[0, 1, :] = 0
    hist[0, 1, 17] = 240 * 320  # every pixel in one bin
    hist[0, 2] = torch.arange(hist.shape[2], dtype=torch.int32) % 2 * 100
    hist[:, :, nb:] = 0  # the spill bin dropped, the tail zeros (as vp_search's)
    before = hist.clone()
    tables = flat._fold_tables(nb, 240 * 320, params, hist.device)
    got = flat._peaks_at_once(hist, tables)
    assert got.dtype == torch.int32 and got.shape == (3, 4)
    assert torch.equal(got, flat._peaks_by_spacing(hist, nb, params, 240 * 320))
    assert torch.equal(hist, before)
    assert flat._peaks_at_once(hist[:0], tables).shape == (0, 4)
    wide = flat._fold_tables(nb, 2**30, params, hist.device)  # sums that could pass 2**31: int64
    # the exported graph's forms (float32 fold sums where exact, the extension concatenated)
    monkeypatch.setattr(torch.compiler, "is_exporting", lambda: True)
    for pixels in (240 * 320, 2**24 + 1):
        assert torch.equal(flat._peaks_by_spacing(hist, nb, params, pixels), got)
    for t in (tables, wide):
        assert torch.equal(flat._peaks_at_once(hist, t), got)
    monkeypatch.undo()
    assert wide.wide and not tables.wide and torch.equal(flat._peaks_at_once(hist, wide), got)


def test_vp_window_both_paths_and_its_bounds() -> None:
    # 11.7: a tracked sequence's full search takes the grid VPs around its last grid VP; the
    # window always holds min(2c+1, columns) x min(2r+1, heights) grid VPs, shifted inside the grid
    rng = np.random.default_rng(3)
    ncol, heights = 320 // IMPROVED.lattice_vp_step + 1, np.array(IMPROVED.lattice_vp_heights)
    for _ in range(200):
        cols, rows = int(rng.integers(0, 12)), int(rng.integers(0, 5))
        params = IMPROVED.replace(lattice_track_vp_cols=cols, lattice_track_vp_rows=rows)
        near, origin = (int(rng.integers(-400, 800)), int(rng.integers(-500, 300))), int(rng.integers(0, 200))
        want = rlat.vp_window(320, params, near, origin)
        got = flat.vp_window(torch.tensor([near]), torch.tensor([origin]), 320, params)
        assert got.dtype == torch.int64 and got[0].tolist() == want.tolist()
        nx, ny = min(2 * cols + 1, ncol), min(2 * rows + 1, heights.size)
        grid = rlat.vp_grid(320, params)[want]
        assert want.size == nx * ny and (np.diff(want) > 0).all() and len(set(grid[:, 0])) == nx
        # the nearest grid column and height are inside
        col = min(max(int(np.floor(near[0] / IMPROVED.lattice_vp_step + 0.5)), 0), ncol - 1) * IMPROVED.lattice_vp_step
        assert col in grid[:, 0] and heights[np.argmin(np.abs(heights - (near[1] - origin)))] in grid[:, 1]
        # after a frame that was not ok: one grid height's every column follows, left to right
        sweep = int(rng.integers(0, heights.size))
        wide = rlat.vp_window(320, params, near, origin, sweep)
        assert flat.vp_window(torch.tensor([near]), torch.tensor([origin]), 320, params,
                              torch.tensor([sweep]))[0].tolist() == wide.tolist()
        row = rlat.vp_grid(320, params)[wide[want.size:]]
        assert wide[:want.size].tolist() == want.tolist() and (row[:, 1] == heights[sweep]).all()
        assert row[:, 0].tolist() == list(range(0, 321, IMPROVED.lattice_vp_step))
    with pytest.raises(ValueError, match="sweep must index one of the 7 grid heights, got 7"):
        rlat.vp_window(320, IMPROVED, (0, 0), 0, 7)


def test_windowed_vp_search_both_paths_batched_and_alone() -> None:
    masks = _search_masks()
    near = torch.tensor([[40 * i, -20 - 30 * i] for i in range(len(masks))])
    origin = torch.arange(len(masks)) * 7
    batch = torch.from_numpy(np.stack(masks))
    got = flat.vp_search(batch, IMPROVED, origin, near)
    for i, m in enumerate(masks):
        want = rlat.vp_search(m, IMPROVED, int(origin[i]), tuple(near[i].tolist()))
        assert tuple(got[i].tolist()) == want
        assert torch.equal(flat.vp_search(batch[i:i + 1], IMPROVED, origin[i:i + 1], near[i:i + 1])[0], got[i])
    # a window beyond the grid is the whole grid, the same VP and tie-break
    whole = IMPROVED.replace(lattice_track_vp_cols=99, lattice_track_vp_rows=99)
    everywhere = flat.vp_search(batch, IMPROVED, origin)
    assert torch.equal(flat.vp_search(batch, whole, origin, near), everywhere)
    # with a grid height swept (11.7): its whole row competes beside the window, the first
    # maximum in the window's order; sweeping the height of the whole grid's choice finds it
    # (an empty mask's fallback VP is not on the grid: any height)
    heights = list(IMPROVED.lattice_vp_heights)
    chosen = [heights.index(y - o) if y - o in heights else 0 for (_, y), o in zip(everywhere.tolist(), origin.tolist())]
    for sweep in (torch.arange(len(masks)) % len(heights), torch.tensor(chosen)):
        got = flat.vp_search(batch, IMPROVED, origin, near, sweep)
        for i, m in enumerate(masks):
            want = rlat.vp_search(m, IMPROVED, int(origin[i]), tuple(near[i].tolist()), int(sweep[i]))
            assert tuple(got[i].tolist()) == want
            alone = flat.vp_search(batch[i:i + 1], IMPROVED, origin[i:i + 1], near[i:i + 1], sweep[i:i + 1])
            assert torch.equal(alone[0], got[i])
    # (the border column ties many VPs: there the window's, listed first, wins)
    assert torch.equal(got[:-1], everywhere[:-1]) and not torch.equal(got[-1], everywhere[-1])


def test_vp_origin_both_paths_on_every_case() -> None:
    # with lattice_vp_origin "sky" a horizon is in view from 16 s >= H (H = 240: s >= 15); the
    # grid then counts from s + 40, at most H; sky 0 (no horizon) and "top" count from row 0
    skies = [0, 1, 14, 15, 16, 100, 120, 199, 200, 239, 240]
    cases = [({}, [0, 0, 0, 55, 56, 140, 160, 239, 240, 240, 240]), ({"lattice_vp_origin": "top"}, [0] * 11),
             ({"lattice_vp_sky": -300}, [0] * 11), ({"lattice_vp_sky": 0, "lattice_vp_sky_div": 240}, [0] + skies[1:])]
    for change, want in cases:
        params = IMPROVED.replace(lattice_vp_origin="sky").replace(**change)
        assert [rlat.vp_origin(s, 240, params) for s in skies] == want, change
        assert flat.vp_origin(torch.tensor(skies), 240, params).tolist() == want, change


def _converging(yv: float, spacing: float = 60.0, h: int = 240, w: int = 320) -> np.ndarray:
    """A mask of thin lines through ``(W/2, yv)``, ``spacing`` px apart on the bottom row."""
    ys, xs = np.mgrid[0:h, 0:w]
    scale = (ys - yv) / (h - 1 - yv)
    on = [(np.abs(xs - (w / 2 + k * spacing * scale)) < 2 * scale + 0.5) & (ys > yv) for k in range(-4, 5)]
    return np.logical_or.reduce(on)


def test_vp_search_counts_its_grid_from_the_origin() -> None:
    # lines meeting inside the image (a horizon in view): the grid above the image cannot hold
    # their VP; counted from the origin its first height (origin - 20) does, exactly
    masks = [_converging(yv) for yv in (100, 60, 30)] + [_converging(100)] * 2 + [np.zeros((240, 320), bool)]
    origins = [120, 80, 50, 0, 240, 120]
    got = flat.vp_search(torch.from_numpy(np.stack(masks)), IMPROVED, torch.tensor(origins))
    want = [rlat.vp_search(m, IMPROVED, o) for m, o in zip(masks, origins)]
    assert [tuple(v) for v in got.tolist()] == want
    assert want[:3] == [(160, 100), (160, 60), (160, 30)]
    assert want[3][1] < 0  # from row 0: some height above the image
    # origin H: every row moved out; like an empty mask, the absolute fallback
    assert want[4] == want[5] == (160, IMPROVED.lattice_vp_fallback_y)


def test_vp_search_odd_sizes_and_no_green_fall_back() -> None:
    rng = np.random.default_rng(9)
    for m in (rng.random((37, 53)) < 0.3, np.zeros((5, 7), bool), np.ones((3, 3), bool)):
        want = rlat.vp_search(m, IMPROVED)
        assert tuple(flat.vp_search(torch.from_numpy(m)[None], IMPROVED)[0].tolist()) == want
    assert rlat.vp_search(np.zeros((5, 7), bool), IMPROVED) == (3, IMPROVED.lattice_vp_fallback_y)


@pytest.mark.parametrize("shift", [0.0, 40.0, -100.0])
def test_vp_search_finds_the_vanishing_point_of_a_clean_field(shift: float) -> None:
    # _field's rows meet at (160 + shift, -60), a grid point: the folded comb peaks there
    mask = rlat.green_mask(_field(spacing=70.0, shift=shift), 0, IMPROVED)
    assert rlat.vp_search(mask, IMPROVED) == (int(160 + shift), -60)


def test_searched_vp_replaces_a_wrong_section_6_vp() -> None:
    img = _field(spacing=70.0, shift=40.0)
    good, _, fit_good, *_ = rlat.improved_rows(img, 0, (200.0, -60.0), IMPROVED)
    rows, _, fit, *_ = rlat.improved_rows(img, 0, (40.0, -20.0), IMPROVED)  # section 6 far off
    assert fit.vp == fit_good.vp == (200, -60) and rows == good
    old = IMPROVED.replace(lattice_vp="section6")
    assert rlat.improved_rows(img, 0, (40.0, -20.0), old)[2].vp == (40, -20)


def _stripes(widths: list[int], spacing: int = 60, h: int = 60, w: int = 320) -> np.ndarray:
    """Vertical green stripes centred at 10, 10 + spacing, ... with the given widths, cycled."""
    m = np.zeros((h, w), bool)
    for j, c in enumerate(range(10, w, spacing)):
        half = widths[j % len(widths)] // 2
        m[:, max(c - half, 0):c + half] = True
    return m


@pytest.mark.parametrize("widths", [[40, 10], [30, 12], [20]])
def test_contrast_comb_rejects_the_double_spacing(widths: list[int]) -> None:
    # rows alternating strong and weak: the uniform-excess score prefers twice the spacing
    # (the weak rows fall between its wide teeth), the contrast score puts its anti-teeth on them
    mask = _stripes(widths)
    vp = (160, -10**6)  # projection through a far VP: nearly the identity
    d, phase, found, _ = rlat.comb_search(mask, vp, IMPROVED)
    assert found and d == 60 and abs((phase - 10 + 30) % 60 - 30) <= 6  # on a stripe (they are flat-topped)
    if len(widths) > 1:
        assert rlat.comb_search(mask, vp, IMPROVED.replace(lattice_comb="uniform"))[0] >= 120
    sp, _, _, _ = flat.comb_search(torch.from_numpy(mask)[None], torch.tensor([vp]), IMPROVED)
    assert int(sp[0]) == d


def test_row_mean_green_keeps_merged_far_rows_apart() -> None:
    # far field: every pixel of the top rows is green (leaves of adjacent rows merge), the row
    # centres greener; near field: green rows on soil. One global Otsu keeps the whole top band,
    # the row mean keeps only the centres
    img = np.empty((80, 320, 3), np.uint8)
    img[...] = (120, 90, 60)
    img[:40] = (80, 140, 60)
    for c in range(20, 320, 40):
        img[:40, c - 4:c + 4] = (40, 200, 40)
        img[40:, c - 6:c + 6] = (40, 170, 40)
    otsu = rlat.green_mask(img, 0, IMPROVED.replace(lattice_green="otsu"))
    row = rlat.green_mask(img, 0, IMPROVED)
    assert otsu[:40].all()
    assert row[:40].sum(axis=1).tolist() == [8 * 8] * 40 and row[:40, 20 - 4:20 + 4].all()
    assert np.array_equal(row[40:], otsu[40:])
    assert torch.equal(flat.green_mask(_t([img]), torch.tensor([0]), IMPROVED)[0], torch.from_numpy(row))


def test_lattice_horizon_image_uses_rows_above_section_2_sky() -> None:
    # section 2 may put its horizon inside a sky-less field; "image" (the default) ignores it
    img = _field(curve=0.0003)
    IMPROVED = CURVED  # the bend is visible only far ahead: "auto" would keep straight rows (11.3.1)
    sky = 80
    assert IMPROVED.lattice_horizon == "image" and rlat.horizon_row(sky, IMPROVED) == 0
    old = IMPROVED.replace(lattice_horizon="sky")
    assert rlat.horizon_row(sky, old) == sky
    got = flat.horizon_row(torch.tensor([sky, -1, 0]), IMPROVED)
    assert got.tolist() == [0, 0, 0] and got.dtype == torch.int64
    assert flat.horizon_row(torch.tensor([sky, -1]), old).tolist() == [sky, -1]
    rows, _conf, fit, *_ = rlat.improved_rows(img, sky, (160.0, -60.0), IMPROVED)
    rows_sky, _conf_sky, fit_sky, *_ = rlat.improved_rows(img, sky, (160.0, -60.0), old)
    assert fit.span == 240 and fit_sky.span == 240 - sky
    assert min(fit.support) > 240 - sky  # rows above section 2's horizon support the rows
    # the far rows keep their spacing: at the top row the fitted rows are as far apart as drawn
    top = [r.x_at(0.0) for r in rows]
    truth = [160 + k * 90.0 * 60 / 299 + 0.0003 * 239 ** 2 for k in (-1, 0, 1)]
    np.testing.assert_allclose(top, truth, atol=2.0)
    # both settings: tensor path = reference, stage by stage and end to end
    for params in (IMPROVED, old):
        x = _t([img])
        skies = torch.tensor([sky])
        want = rlat.green_mask(img, rlat.horizon_row(sky, params), params)
        assert torch.equal(flat.green_mask(x, flat.horizon_row(skies, params), params)[0], torch.from_numpy(want))
        assert bool(want[:sky].any()) == (params.lattice_horizon == "image")
        got_rows = flat.improved_rows(x, skies, torch.tensor([[160.0, -60.0]], dtype=torch.float64),
                                      torch.tensor([True]), params)
        ref_rows = rows if params is IMPROVED else rows_sky
        for i, r in enumerate(ref_rows):
            assert float(got_rows.confidence[0, i]) == r.confidence
            assert abs(float(got_rows.a[0, i]) - r.a) <= 1e-6 and abs(float(got_rows.b[0, i]) - r.b) <= 1e-6


@pytest.fixture(scope="module")
def crbd_subset(crbd_dir):
    from torchrow.evaluation.datasets import CRBD

    crbd = CRBD(crbd_dir)
    idx = [4, 133, 213, 274]  # no vegetation colour match, wrong VPs, a sparse field
    return crbd, idx, [crbd.image(i) for i in idx]


@pytest.mark.parametrize("horizon", ["image", "sky"])
def test_tensor_equals_reference_on_crbd_subset_mixed_batch(crbd_subset, horizon) -> None:
    _, _, images = crbd_subset
    params = IMPROVED.replace(lattice_horizon=horizon)
    mixed = images + _adversarial()[:2]
    out = CropRowDetector(params, chunk=3)(_t(mixed)).results()
    for img, got in zip(mixed, out):
        _records_equal(detect(img, params), got)


def test_improved_beats_faithful_on_crbd_subset(crbd_subset) -> None:
    crbd, idx, images = crbd_subset
    imp = [crda_official(detect(im, IMPROVED), crbd.ground_truth(i)) for i, im in zip(idx, images)]
    fai = [crda_official(detect(im, Params()), crbd.ground_truth(i)) for i, im in zip(idx, images)]
    assert np.mean(imp) > np.mean(fai) + 0.1


# --- CLI ------------------------------------------------------------------------------------

def test_cli_mode_improved_detect_and_video_onnx_error(tmp_path, capsys) -> None:
    import cv2

    p = tmp_path / "f.png"
    cv2.imwrite(str(p), cv2.cvtColor(_field(curve=0.001), cv2.COLOR_RGB2BGR))
    out = tmp_path / "o.jsonl"
    assert main(["detect", str(p), "--out", str(out), "-q", "--mode", "improved",
                 "--annotate", str(tmp_path / "ann")]) == 0
    import json

    rec = json.loads(out.read_text().splitlines()[0])
    assert len(rec["rows"]) == 3 and rec["rows"][1]["c"] > 0 and 0 <= rec["image_confidence"] <= 1
    assert (tmp_path / "ann" / "f.png").is_file()
    capsys.readouterr()
    assert main(["detect", str(p), "--out", str(tmp_path / "d.jsonl"), "--mode", "improved", "--impl", "onnx",
                 "--model", str(tmp_path / "none.onnx")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchrow: error:") and "no ONNX export of the improved detector" in err[0]


def test_improved_record_round_trip() -> None:
    res = detect(_field(curve=0.0002), CURVED)
    rec = res.to_record()
    assert ImageResult.from_record(rec).to_record() == rec
    back = ImageResult.from_record(rec)
    assert [r.c for r in back.rows] == [r.c for r in res.rows]
    assert [r.e for r in back.rows] == [r.e for r in res.rows] and any(r.e != 0.0 for r in res.rows)
    assert back.image_confidence == res.image_confidence


@pytest.mark.parametrize("model", ["auto", "straight"])
def test_model_choice_and_weak_status_agree_between_paths(model: str) -> None:
    # sections 11.3.1 and 11.4: the straight lattice, the curved refit kept by the gain rule,
    # and the evidence thresholds give the same records in both paths
    params = IMPROVED.replace(lattice_model=model, lattice_min_contrast=0.3, lattice_min_image_confidence=0.5)
    noise = np.random.default_rng(5).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    images = [_field(), _s_field(), _field(spacing=60.0, shift=30.0, curve=0.002, seed=4), noise]
    got = CropRowDetector(params)(torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous())
    for res, img in zip(got.results([str(i) for i in range(len(images))]), images):
        want = detect(img, params, name=res.name)
        assert res.status == want.status
        assert [(r.valid, r.e == 0.0) for r in res.rows] == [(r.valid, r.e == 0.0) for r in want.rows]
        assert np.allclose([(r.a, r.b, r.c, r.e) for r in res.rows], [(r.a, r.b, r.c, r.e) for r in want.rows],
                           atol=1e-9, rtol=0)
    statuses = [r.status for r in got.results([str(i) for i in range(len(images))])]
    assert statuses[-1] != "ok"  # uniform noise holds no crop rows
    if model == "straight":
        assert all(r.e == 0.0 and r.c == 0.0 for r in detect(images[1], params).rows)


# --- what the improved mode computes and reports -----------------------------------------------

FAITHFUL_ONLY = ("veg_color", "k", "bushy", "hough", "outliers", "vp")


def _both(images: list[np.ndarray], params: Params) -> list[tuple[ImageResult, ImageResult]]:
    got = CropRowDetector(params)(_t(images)).results()
    return [(detect(img, params), g) for img, g in zip(images, got)]


def test_improved_mode_runs_only_the_stages_it_uses(monkeypatch) -> None:
    # lattice_vp "search" needs none of sections 1-6; section 1 only for a grid counted from a
    # horizon in view (lattice_vp_origin "sky") or lattice_horizon "sky"; "section6" needs
    # sections 1-6 (its VP starts the comb). Either way the records null sections 2-6's
    # fields, and sky is the lattice's first row
    import torchrow.engines.detector as engine
    import torchrow.reference.pipeline as pipeline
    from torchrow.reference.sky import sky_row

    calls: list[str] = []

    def spy(module, name: str) -> None:
        real = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, **k: (calls.append(name), real(*a, **k))[1])

    for mod in (pipeline, engine.fsky, engine.fcolor, engine.fvan):
        for name in ("sky_row", "vegetation_color", "find_lines"):
            if hasattr(mod, name):
                spy(mod, name)
    img = (_field(spacing=70.0, seed=2) // 32) * 32 + 16  # few colours: section 2's clustering is quick
    img[:40] = (208, 208, 240)  # a sky band: section 1 puts its row below it
    sky = sky_row(img, IMPROVED)
    assert sky > 0
    for change, want in (({}, set()), ({"lattice_vp_origin": "sky"}, {"sky_row"}), ({"lattice_horizon": "sky"}, {"sky_row"}),
                         ({"lattice_vp": "section6"}, {"sky_row", "vegetation_color", "find_lines"})):
        calls.clear()
        params = IMPROVED.replace(**change)
        ref, got = _both([img], params)[0]
        assert set(calls) == want, change
        _records_equal(ref, got)
        rec = got.to_record()
        assert all(rec[k] is None for k in FAITHFUL_ONLY) and rec["n_rows"] == 3 and rec["lattice_rows"]
        assert rec["sky"] == (sky if params.lattice_horizon == "sky" else 0)
        assert ImageResult.from_record(rec).to_record() == rec


def test_lattice_rows_are_every_visible_row_in_k_order() -> None:
    kss = [range(-1, 2), range(-2, 3), range(-3, 4)]
    assert IMPROVED.lattice_visible_half(320) >= 3
    for ks, (ref, got) in zip(kss, _both([_field(spacing=90.0, ks=ks) for ks in kss], IMPROVED)):
        _records_equal(ref, got)
        assert [r.k for r in got.lattice_rows] == list(ks)
        by_k = {r.k: r for r in got.lattice_rows}
        for k, row in zip((-1, 0, 1), got.rows):  # the three rows are lattice rows -1, 0, 1
            lr = by_k[k]
            assert (lr.a, lr.b, lr.c, lr.e, lr.confidence) == (row.a, row.b, row.c, row.e, row.confidence)
        for r in got.lattice_rows:  # each on its drawn row: x = W/2 + k d (y + 60) / 299
            for y in (0.0, 120.0, 239.0):
                assert abs(r.x_at(y) - (160 + r.k * 90.0 * (y + 60) / 299)) < 3.0, (r.k, y)
            assert 0 < r.confidence <= 1


def test_a_colour_is_refused_where_section_2_does_not_run() -> None:
    img = _field()
    with pytest.raises(ValueError, match="veg_color is only used where section 2 runs"):
        detect(img, IMPROVED, veg_color=(40, 170, 40))
    with pytest.raises(ValueError, match="veg_color is only used where section 2 runs"):
        CropRowDetector(IMPROVED)(_t([img]), veg_color=torch.tensor([40, 170, 40]))


def test_lattice_rows_agree_between_paths_on_crdld(data_dir) -> None:
    from torchrow.evaluation.datasets import CRDLD

    root = data_dir / "crdld_dev" / "test"
    if not (root / "image").is_dir():
        pytest.skip(f"CRDLD not found under {data_dir}")
    ds = CRDLD(root)
    images = [ds.image(i) for i in (0, 7)]
    for ref, got in _both(images, IMPROVED):
        _records_equal(ref, got)
        # forward rows 150-330 px apart at the bottom of a 320-px image: two or three are shown
        assert got.lattice_rows and len(got.lattice_rows) >= 2
