"""Stage-by-stage tests of the NumPy/OpenCV reference (ALGORITHM.md sections 1-7).

Every test checks a statement of the specification against an independent computation:
the OpenCV / SciPy / scikit-image / kornia call the spec names, a brute-force loop written
from the spec's formula, or a hand-made input whose answer follows from the text.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.signal
import skimage.color
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchrow.core.params import Params
from torchrow.core.results import HoughLine
from torchrow.core.tables import hough_trig, hypothesis_table, rgb_to_lab
from torchrow.reference import color, hough, ransac, sky, vanishing, vegetation

P = Params()
HYP = settings(deadline=None, max_examples=60, suppress_health_check=[HealthCheck.too_slow])


def crbd_image(crbd_dir: Path, number: int) -> np.ndarray:
    """CRBD image ``crop_row_NNN`` as RGB (extension case varies: .JPG or .jpg)."""
    hits = sorted((crbd_dir / "Images").glob(f"crop_row_{number:03d}.*"))
    hits = [h for h in hits if h.suffix.lower() == ".jpg"]
    assert hits, f"crop_row_{number:03d} not found"
    bgr = cv2.imread(str(hits[0]), cv2.IMREAD_COLOR)
    assert bgr is not None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def skimage_lab(rgb: np.ndarray) -> np.ndarray:
    """scikit-image's LAB of ``(..., 3)`` uint8, as float64 (input scaled to [0, 1])."""
    flat = rgb.reshape(-1, 1, 3).astype(np.float64) / 255.0
    return skimage.color.rgb2lab(flat).reshape(rgb.shape)


# ----------------------------------------------------------------------------------------
# Shared LAB (section 2)
# ----------------------------------------------------------------------------------------

def test_lab_matches_skimage_on_random_colours():
    rgb = np.random.default_rng(1).integers(0, 256, (200_000, 3), dtype=np.uint8)
    lab = rgb_to_lab(rgb)
    assert lab.shape == (200_000, 3) and lab.dtype == np.float64
    assert np.max(np.abs(lab - skimage_lab(rgb))) <= 1e-12


def test_lab_of_primaries_and_extremes():
    ref = skimage_lab(np.array([[0, 0, 0], [255, 255, 255], [0, 255, 0], [255, 0, 0]], np.uint8))
    lab = rgb_to_lab(np.array([[0, 0, 0], [255, 255, 255], [0, 255, 0], [255, 0, 0]], np.uint8))
    assert np.max(np.abs(lab - ref)) <= 1e-12
    assert abs(lab[0, 0]) <= 1e-12 and abs(lab[1, 0] - 100.0) <= 1e-9  # black L=0, white L=100


@pytest.mark.data
def test_lab_matches_skimage_on_crbd_pixels(crbd_dir):
    for number in (1, 4, 141):
        rgb = crbd_image(crbd_dir, number)
        lab = rgb_to_lab(rgb)
        assert lab.shape == rgb.shape
        assert np.max(np.abs(lab - skimage_lab(rgb))) <= 1e-12


@pytest.mark.parametrize("red", [0, 1, 37, 128, 254, 255])
def test_lab_equals_kornia_float64_on_canonical_slab(red):
    import kornia
    import torch

    g, b = np.meshgrid(np.arange(256), np.arange(256), indexing="ij")
    slab = np.stack([np.full((256, 256), red), g, b]).astype(np.float64)  # (3, 256, 256)
    with torch.no_grad():
        ref = kornia.color.rgb_to_lab(torch.from_numpy(slab / 255.0)[None])[0].numpy()
    rgb = np.stack([np.full((256, 256), red), g, b], axis=-1).astype(np.uint8)  # (256, 256, 3)
    ours = rgb_to_lab(rgb)
    assert np.array_equal(ours, np.moveaxis(ref, 0, -1))  # bit for bit


def test_lab_shapes_and_dtype_errors():
    assert rgb_to_lab(np.array([0, 255, 0], np.uint8)).shape == (3,)
    assert rgb_to_lab(np.zeros((2, 3, 4, 3), np.uint8)).shape == (2, 3, 4, 3)
    with pytest.raises(ValueError):
        rgb_to_lab(np.zeros((4, 3), np.float64))
    with pytest.raises(ValueError):
        rgb_to_lab(np.zeros((4, 3), np.uint16))
    with pytest.raises(ValueError):
        rgb_to_lab(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError):
        rgb_to_lab(np.uint8(3))


# ----------------------------------------------------------------------------------------
# Sky removal (section 1)
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (240, 320), (31, 2)])
def test_gray_is_the_15_bit_opencv_formula(shape):
    rgb = np.random.default_rng(sum(shape)).integers(0, 256, shape + (3,), dtype=np.uint8)
    r, g, b = (rgb[..., i].astype(np.int64) for i in range(3))
    expected = (9798 * r + 19235 * g + 3735 * b + 16384) >> 15
    out = sky.gray(rgb)
    assert out.dtype == np.uint8 and out.shape == shape
    assert np.array_equal(out, expected)


def test_gray_uses_rgb_not_bgr_order():
    px = np.array([[[255, 0, 0]]], np.uint8)  # pure red
    assert int(sky.gray(px)[0, 0]) == (9798 * 255 + 16384) >> 15  # 76, not the blue weight's 29


def _medfilt_columns(m: np.ndarray, length: int) -> np.ndarray:
    out = np.empty_like(m)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "kernel_size exceeds volume extent" for short columns
        for x in range(m.shape[1]):
            out[:, x] = scipy.signal.medfilt(m[:, x], length)
    return out


@HYP
@given(
    h=st.integers(1, 45),
    w=st.integers(1, 4),
    binary=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
)
def test_column_median_equals_scipy_medfilt(h, w, binary, seed):
    rng = np.random.default_rng(seed)
    m = rng.integers(0, 2 if binary else 256, (h, w)).astype(np.uint8)
    out = sky.column_median(m, 19)
    assert out.shape == m.shape and out.dtype == m.dtype
    assert np.array_equal(out, _medfilt_columns(m, 19))


@pytest.mark.parametrize("h", [1, 2, 9, 10, 18, 19, 20, 37, 38])
def test_column_median_equals_medfilt_at_edge_heights(h):
    rng = np.random.default_rng(h)
    for m in (np.ones((h, 3), np.uint8), rng.integers(0, 2, (h, 3)).astype(np.uint8),
              rng.integers(0, 256, (h, 3)).astype(np.uint8)):
        assert np.array_equal(sky.column_median(m, 19), _medfilt_columns(m, 19))
    # zero padding: a column of ones shorter than 10 rows is entirely 0 after filtering
    if h < 10:
        assert not sky.column_median(np.ones((h, 2), np.uint8), 19).any()


def test_horizon_mask_equals_the_cv2_calls_written_out():
    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    rgb[:25] = (110, 150, 220)  # a flat region so both values of m occur
    rgb[25:40] //= 8  # low texture band
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    g = cv2.blur(g, (9, 3))
    g = cv2.medianBlur(g, 5)
    lap = cv2.Laplacian(g, cv2.CV_8U, ksize=1)
    m = cv2.erode((lap < 4).astype(np.uint8), np.ones((3, 9), np.uint8))
    out = sky.horizon_mask(rgb, P)
    assert out.dtype == np.uint8 and set(np.unique(out)) <= {0, 1}
    assert 0 < out.sum() < out.size
    assert np.array_equal(out, m)


def _reflect101(a: np.ndarray, ph: int, pw: int) -> np.ndarray:
    return np.pad(a, ((ph, ph), (pw, pw)), mode="reflect")


def test_horizon_mask_steps_from_first_principles():
    """Steps 1.2-1.3 rewritten without OpenCV (the formulas a tensor path must reproduce)."""
    rng = np.random.default_rng(11)
    rgb = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    rgb[:15] = (120, 160, 230)
    rgb[15:25] = rng.integers(100, 104, (10, 50, 3), dtype=np.uint8)
    g = sky.gray(rgb).astype(np.int64)
    # box 9 wide x 3 high, reflect-101 border, round half up of sum/27
    p = _reflect101(g, 1, 4)
    s = sum(p[dy:dy + 40, dx:dx + 50] for dy in range(3) for dx in range(9))
    blur = (s + 13) // 27
    assert np.array_equal(blur, cv2.blur(sky.gray(rgb), (9, 3)))
    # median 5x5 with replicated border
    pe = np.pad(blur, 2, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(pe, (5, 5))
    med = np.sort(win.reshape(40, 50, 25), axis=-1)[..., 12]
    # Laplacian ksize 1 (4-neighbour), reflect-101, saturated into uint8
    q = _reflect101(med, 1, 1)
    lap = np.clip(q[:-2, 1:-1] + q[2:, 1:-1] + q[1:-1, :-2] + q[1:-1, 2:] - 4 * med, 0, 255)
    m = (lap < 4).astype(np.int64)
    # erosion 9 wide x 3 high; outside the image never erodes
    pm = np.pad(m, ((1, 1), (4, 4)), constant_values=1)
    ero = np.min([pm[dy:dy + 40, dx:dx + 50] for dy in range(3) for dx in range(9)], axis=0)
    assert np.array_equal(sky.horizon_mask(rgb, P), ero)


def test_sky_mask_column_rule_on_a_hand_made_m(monkeypatch):
    h, w = 60, 6
    m = np.zeros((h, w), np.uint8)
    m[:30, 0] = 1  # z = 30 > 20, o = 0: column becomes 1 on [0, 30)
    m[:30, 1] = 1
    m[12, 1] = 0  # an isolated hole the median removes: still filled on [0, 30)
    m[:15, 2] = 1  # z = 15 (not > 20): column left as it was after step 3
    m[25:, 3] = 1  # z = 0: left as it was
    m[5:40, 4] = 1  # filtered: z = 0 (padding zeros win at the top): left as it was
    m[:, 5] = 1  # never 0: no z, left as it was
    monkeypatch.setattr(sky, "horizon_mask", lambda rgb, params: m.copy())
    rgb = np.full((h, w, 3), 50, np.uint8)
    out = sky.sky_mask(rgb, P).astype(np.uint8)
    exp = np.zeros((h, w), np.uint8)
    exp[:30, 0] = 1
    exp[:30, 1] = 1
    exp[:15, 2] = 1
    exp[25:, 3] = 1
    exp[5:40, 4] = 1
    exp[:, 5] = 1
    assert np.array_equal(out, exp)
    # step 5: a pixel with any RGB value 0 is never sky
    rgb[3, 0] = (0, 200, 200)
    rgb[4, 5] = (200, 200, 0)
    out = sky.sky_mask(rgb, P)
    assert not out[3, 0] and not out[4, 5] and out[5, 0] and out[5, 5]


def test_sky_row_zero_without_sky():
    rgb = np.random.default_rng(2).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    assert sky.sky_row(rgb, P) == 0


def _horizon_image(rows: int, colour=(100, 150, 230), seed: int = 0) -> np.ndarray:
    rgb = np.random.default_rng(seed).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    rgb[:rows] = colour
    return rgb


def test_sky_row_finds_an_obvious_horizon():
    s = sky.sky_row(_horizon_image(80), P)
    assert 74 <= s <= 80, s
    s = sky.sky_row(_horizon_image(110, seed=3), P)
    assert 104 <= s <= 110, s


def test_sky_row_needs_all_channels_at_least_one():
    assert sky.sky_row(_horizon_image(80, colour=(0, 0, 255)), P) == 0  # R = 0: never sky
    assert 74 <= sky.sky_row(_horizon_image(80, colour=(1, 1, 255)), P) <= 80


def test_sky_row_below_half_height_is_reset_to_zero():
    rgb = _horizon_image(180)
    assert sky.sky_mask(rgb, P)[150].sum() > 160  # the horizon really is found low down...
    assert sky.sky_row(rgb, P) == 0  # ...and the sky > H/2 rule resets it
    # a uniform image is all sky: the bottom row qualifies, H-1 > H/2, so 0
    assert sky.sky_row(np.full((240, 320, 3), 90, np.uint8), P) == 0


def test_sky_row_scan_rule_on_a_hand_made_sky_mask(monkeypatch):
    h, w = 100, 40
    mask = np.zeros((h, w), bool)
    mask[:10] = True
    mask[30, :21] = True  # 21 > W/2: the lowest qualifying row
    mask[45, :20] = True  # exactly W/2: does not qualify
    monkeypatch.setattr(sky, "sky_mask", lambda rgb, params: mask)
    rgb = np.zeros((h, w, 3), np.uint8)
    assert sky.sky_row(rgb, P) == 30
    mask[50, :] = True  # y = 50 = H/2: kept (only sky > H/2 resets)
    assert sky.sky_row(rgb, P) == 50
    mask[51, :] = True  # y = 51 > H/2: reset to 0
    assert sky.sky_row(rgb, P) == 0
    mask[:] = False
    assert sky.sky_row(rgb, P) == 0


@pytest.mark.data
def test_sky_row_on_crbd_lies_in_upper_half(crbd_dir):
    for number in (1, 8, 43, 100, 141, 200, 260):
        rgb = crbd_image(crbd_dir, number)
        h = rgb.shape[0]
        s = sky.sky_row(rgb, P)
        assert isinstance(s, int) and 0 <= s <= h / 2


@pytest.mark.data
def test_sky_row_reproduces_the_thesis_code_on_bgr_input(data_dir, crbd_dir):
    """The thesis code passed RGB to a BGR->gray conversion (the *fix* of step 1.1). Fed the
    channel-swapped image, steps 1.2-1.6 must give the thesis code's own ``height_sky``."""
    import json

    path = data_dir / "thesis_baseline" / "thesis_code_sample.jsonl"
    if not path.is_file():
        pytest.skip("thesis_baseline/thesis_code_sample.jsonl not found")
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    assert len(records) >= 30
    for rec in records:
        number = int(rec["name"].split("_")[-1].split(".")[0])
        rgb = crbd_image(crbd_dir, number)
        assert sky.sky_row(np.ascontiguousarray(rgb[:, :, ::-1]), P) == rec["height_sky"], rec["name"]


# ----------------------------------------------------------------------------------------
# Vegetation colour (section 2)
# ----------------------------------------------------------------------------------------

def test_distinct_colors_order_count_then_first_appearance():
    A, B, C, D = (10, 20, 30), (200, 0, 0), (0, 0, 1), (5, 5, 5)
    rgb = np.array([
        [C, B, A, D],
        [A, B, D, A],
        [D, C, B, B],
    ], np.uint8)  # counts: B 4, A 3, D 3, C 2
    colors, counts = color.distinct_colors(rgb)
    # B (4); then A and D (3 each): A first appears at raster 2, D at 3; then C (2)
    assert [tuple(int(v) for v in c) for c in colors] == [B, A, D, C]
    assert counts.tolist() == [4, 3, 3, 2]
    assert colors.dtype == np.uint8 and counts.dtype == np.int64


def _lab_dist(a, b) -> float:
    la, lb = rgb_to_lab(np.array(a, np.uint8)), rgb_to_lab(np.array(b, np.uint8))
    d = la - lb
    return math.sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2])


def test_cluster_colors_greedy_chain_and_counts():
    A, B, C = (100, 100, 100), (112, 112, 112), (124, 124, 124)
    far = (200, 30, 30)
    assert _lab_dist(A, B) < 6 and _lab_dist(B, C) < 6 and _lab_dist(A, C) >= 6
    colors = np.array([A, B, C, far], np.uint8)
    counts = np.array([10, 7, 5, 3])
    cl = color.cluster_colors(colors, counts, P)
    # A absorbs B; C is not absorbed by A (too far), and B (absorbed) seeds nothing
    assert [(c.seed, c.count) for c in cl] == [(A, 17), (C, 5), (far, 3)]


def test_cluster_colors_only_later_colours_are_absorbed_and_sort_is_stable():
    A, B, C = (100, 100, 100), (112, 112, 112), (124, 124, 124)
    # walk order B, A, C: B is the seed and absorbs both A and C (each closer than 6)
    cl = color.cluster_colors(np.array([B, A, C], np.uint8), np.array([3, 3, 3]), P)
    assert [(c.seed, c.count) for c in cl] == [(B, 9)]
    # walk order C, A, B: C absorbs B only; A becomes its own seed... and does not absorb B
    cl = color.cluster_colors(np.array([C, A, B], np.uint8), np.array([4, 4, 1]), P)
    assert [(c.seed, c.count) for c in cl] == [(C, 5), (A, 4)]
    # equal totals keep walk order (stable sort)
    X, Y, Z = (255, 0, 0), (0, 0, 255), (0, 255, 0)
    cl = color.cluster_colors(np.array([X, Y, Z], np.uint8), np.array([5, 5, 5]), P)
    assert [c.seed for c in cl] == [X, Y, Z]
    cl = color.cluster_colors(np.array([X, Y, Z], np.uint8), np.array([1, 5, 5]), P)
    assert [c.seed for c in cl] == [Y, Z, X]


def test_cluster_colors_distance_test_is_strict():
    A, B = (100, 100, 100), (112, 112, 112)
    d = _lab_dist(A, B)
    colors, counts = np.array([A, B], np.uint8), np.array([2, 1])
    at = color.cluster_colors(colors, counts, P.replace(color_tol=d))
    assert [(c.seed, c.count) for c in at] == [(A, 2), (B, 1)]  # distance == tol: not absorbed
    above = color.cluster_colors(colors, counts, P.replace(color_tol=float(np.nextafter(d, np.inf))))
    assert [(c.seed, c.count) for c in above] == [(A, 3)]


def _naive_clusters(colors: np.ndarray, counts: np.ndarray, tol: float) -> list[tuple[tuple, int]]:
    lab = [rgb_to_lab(np.asarray(c, np.uint8)) for c in colors]
    absorbed = [False] * len(colors)
    out = []
    for i in range(len(colors)):
        if absorbed[i]:
            continue
        total = int(counts[i])
        for j in range(i + 1, len(colors)):
            if absorbed[j]:
                continue
            dl, da, db = (float(lab[j][k]) - float(lab[i][k]) for k in range(3))
            if math.sqrt((dl * dl + da * da) + db * db) < tol:
                absorbed[j] = True
                total += int(counts[j])
        out.append((tuple(int(v) for v in colors[i]), total))
    return sorted(out, key=lambda t: -t[1])


@HYP
@given(
    n=st.integers(1, 30),
    seed=st.integers(0, 2**32 - 1),
    tol=st.sampled_from([2.0, 6.0, 11.5]),
)
def test_cluster_colors_equals_naive_greedy(n, seed, tol):
    rng = np.random.default_rng(seed)
    base = rng.integers(60, 140, 3)
    codes = rng.choice(16**3, size=n, replace=False)  # distinct colours in a small cube
    colors = np.stack([base[0] + codes // 256, base[1] + (codes // 16) % 16, base[2] + codes % 16], 1)
    colors = colors.astype(np.uint8)
    counts = rng.integers(1, 6, len(colors))
    got = [(c.seed, c.count) for c in color.cluster_colors(colors, counts, P.replace(color_tol=tol))]
    assert got == _naive_clusters(colors, counts, tol)
    assert sum(c for _, c in got) == int(counts.sum())


def test_vegetation_color_closest_kept_cluster_to_lime():
    G1, G2 = (0, 205, 0), (40, 255, 30)  # both at RGB distance 50 from lime
    assert _lab_dist(G1, G2) >= 6
    soil, sky_c, lime = (120, 90, 60), (90, 140, 220), (0, 255, 0)
    assert _lab_dist(lime, G1) >= 6

    def image(counts: dict) -> np.ndarray:
        px = [c for c, k in counts.items() for _ in range(k)]
        return np.array(px, np.uint8).reshape(1, -1, 3)

    # tie in RGB distance: the first kept cluster (more pixels) wins
    col, kept = color.vegetation_color(image({soil: 50, G1: 20, G2: 10, sky_c: 5}), P)
    assert col == G1 and [c.seed for c in kept] == [soil, G1, G2, sky_c]
    col, _ = color.vegetation_color(image({soil: 50, G2: 20, G1: 10, sky_c: 5}), P)
    assert col == G2
    # lime itself is closest but its cluster is not among the n_colors kept
    col, kept = color.vegetation_color(image({soil: 50, G1: 20, sky_c: 9, lime: 2}), P.replace(n_colors=3))
    assert col == G1 and lime not in [c.seed for c in kept]
    col, _ = color.vegetation_color(image({soil: 50, G1: 20, sky_c: 9, lime: 2}), P.replace(n_colors=4))
    assert col == lime


def test_vegetation_color_is_a_seed_not_a_mean():
    seed, near = (40, 160, 40), (42, 162, 41)
    assert _lab_dist(seed, near) < 6
    rgb = np.array([[seed] * 5 + [near] * 3 + [(120, 90, 60)] * 10], np.uint8)
    col, kept = color.vegetation_color(rgb, P)
    assert col == seed and kept[1].count == 8


# ----------------------------------------------------------------------------------------
# Vegetation mask and Hough input (sections 3-4)
# ----------------------------------------------------------------------------------------

def _near_colour_image(c, shape=(40, 50), spread=6, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(np.array(c) + rng.integers(-spread, spread + 1, shape + (3,)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize(("k", "sky_rows"), [(4, 0), (4, 7), (2, 0), (3.5, 12), (13, 3)])
def test_raw_mask_equals_cv2_inrange_on_lab(k, sky_rows):
    c = (60, 140, 50)
    rgb = _near_colour_image(c, seed=int(k * 10) + sky_rows)
    lab = rgb_to_lab(rgb)
    cl = rgb_to_lab(np.array(c, np.uint8))
    lo, hi = cl - k, cl + k
    exp = cv2.inRange(lab, tuple(float(v) for v in lo), tuple(float(v) for v in hi)) > 0
    exp[:sky_rows] = False
    raw = vegetation.raw_mask(rgb, c, k, sky_rows)
    assert raw.dtype == bool and raw.shape == rgb.shape[:2]
    assert 0 < raw.sum() < raw.size
    assert np.array_equal(raw, exp)
    assert not raw[:sky_rows].any()


def test_raw_mask_box_is_inclusive():
    c = (60, 140, 50)
    cl = rgb_to_lab(np.array(c, np.uint8))
    for other in [(50, 130, 40), (52, 133, 47), (66, 145, 55), (70, 150, 60)]:
        lo = rgb_to_lab(np.array(other, np.uint8))
        d = lo - cl
        ch = int(np.argmax(np.abs(d)))
        k = float(abs(d[ch]))
        bound = cl[ch] + k if d[ch] > 0 else cl[ch] - k
        if bound == lo[ch]:  # the colour sits exactly on the box boundary
            break
    else:
        pytest.fail("no colour found exactly on the boundary")
    rgb = np.array([[c, other]], np.uint8)
    assert vegetation.raw_mask(rgb, c, k, 0)[0].tolist() == [True, True]  # inclusive
    assert vegetation.raw_mask(rgb, c, k - 1e-9, 0)[0].tolist() == [True, False]
    assert vegetation.raw_mask(rgb, c, 0, 0)[0].tolist() == [True, False]  # k = 0: the colour itself


def test_raw_fraction_counts_below_the_horizon():
    raw = np.zeros((10, 4), bool)
    raw[6:, :2] = True  # 8 pixels, all below a horizon at 6 (16 pixels there)
    assert vegetation.raw_fraction(raw, 6) == 0.5
    assert vegetation.raw_fraction(raw, 0) == 0.2
    assert vegetation.raw_fraction(raw, 10) == 0.0  # nothing below the horizon


def test_adapt_k_follows_the_two_loops():
    """Section 3.3: from k=4, shrink while fraction > 2 info0 (k > 3), then grow while
    fraction < 1.2 info0 (k < 13)."""
    c = (60, 140, 50)
    rgb = _near_colour_image(c, shape=(60, 50), spread=30, seed=4)
    sky_rows = 10
    frac = {k: vegetation.raw_fraction(vegetation.raw_mask(rgb, c, k, sky_rows), sky_rows)
            for k in range(3, 14)}
    assert frac[3] < frac[4] < frac[8] < frac[13] < 1  # a strictly growing fraction

    def expected(info0: float) -> int:
        k = 4
        while frac[k] > 2 * info0 and k > 3:
            k -= 1
        while frac[k] < 1.2 * info0 and k < 13:
            k += 1
        return k

    infos = [0.0, frac[3] / 2.01, frac[4] / 2.01, frac[4] / 1.99, frac[4] / 1.25, frac[4],
             frac[8] / 1.2 * (1 - 1e-9), frac[8] / 1.19, frac[13] / 1.2, 1.0]
    outcomes = []
    for info0 in infos:
        k, raw = vegetation.adapt_k(rgb, c, sky_rows, info0, P)
        assert k == expected(info0), info0
        outcomes.append(k)
        assert np.array_equal(raw, vegetation.raw_mask(rgb, c, k, sky_rows))
    assert outcomes[0] == 3 and outcomes[-1] == 13 and outcomes[4] == 4 and outcomes[6] == 8


@HYP
@given(h=st.integers(1, 20), w=st.integers(1, 20), sky_frac=st.floats(0, 1), p=st.floats(0.2, 0.95),
       seed=st.integers(0, 2**32 - 1))
def test_remove_bushy_equals_raw_and_not_cv2_erode_of_crop(h, w, sky_frac, p, seed):
    rng = np.random.default_rng(seed)
    sky_rows = int(sky_frac * h)
    raw = rng.random((h, w)) < p
    raw[:sky_rows] = False
    veg = vegetation.remove_bushy(raw, sky_rows, P)
    exp = np.zeros_like(raw)
    crop = raw[sky_rows:].astype(np.uint8)
    if crop.size:
        exp[sky_rows:] = (crop == 1) & (cv2.erode(crop, np.ones((3, 2), np.uint8)) == 0)
    assert veg.dtype == bool and np.array_equal(veg, exp)


def test_remove_bushy_anchor_on_hand_made_mask():
    raw = np.ones((5, 5), bool)
    raw[2, 2] = False
    veg = vegetation.remove_bushy(raw, 0, P)
    # a pixel survives iff some pixel of columns x-1..x, rows y-1..y+1 (inside) is 0:
    # the hole at (2, 2) is covered from (1..3, 2..3)
    exp = {(1, 2), (1, 3), (2, 3), (3, 2), (3, 3)}
    assert set(zip(*np.nonzero(veg))) == exp
    # region borders do not erode: a full region leaves nothing
    assert not vegetation.remove_bushy(np.ones((4, 6), bool), 0, P).any()
    # a one-pixel-wide vertical row survives whole; a two-wide one keeps its left column
    raw = np.zeros((6, 6), bool)
    raw[:, 1] = True
    raw[:, 3:5] = True
    veg = vegetation.remove_bushy(raw, 0, P)
    assert veg[:, 1].all() and veg[:, 3].all() and not veg[:, 4].any()


def test_remove_bushy_rows_above_sky_are_outside():
    raw = np.zeros((6, 5), bool)
    raw[2:] = True
    # with the horizon at 2 the region is all ones: nothing survives
    assert not vegetation.remove_bushy(raw, 2, P).any()
    # with the horizon at 0 row 1 is a 0 inside the image: row 2 (kernel covers y-1) survives
    veg = vegetation.remove_bushy(raw, 0, P)
    assert veg[2].all() and not veg[3:].any() and not veg[:2].any()


def test_hough_input_canny_when_bushy_else_mask():
    rng = np.random.default_rng(3)
    h, w, sky_rows = 60, 80, 20
    dense = np.zeros((h, w), bool)
    dense[sky_rows:] = rng.random((h - sky_rows, w)) < 0.3
    hin, bushy = vegetation.hough_input(dense, sky_rows, P)
    exp = np.zeros_like(dense)
    exp[sky_rows:] = cv2.Canny(dense[sky_rows:].astype(np.uint8) * 255, 100, 200, L2gradient=False) > 0
    assert bushy is True and hin.dtype == bool and np.array_equal(hin, exp)
    assert not np.array_equal(hin, dense)

    sparse = np.zeros((h, w), bool)
    sparse[sky_rows:] = rng.random((h - sky_rows, w)) < 0.03
    hin, bushy = vegetation.hough_input(sparse, sky_rows, P)
    assert bushy is False and np.array_equal(hin, sparse) and hin is not sparse


def test_hough_input_density_counts_pixels_below_horizon_and_is_strict():
    h, w, sky_rows = 20, 10, 10  # 100 pixels below the horizon
    veg = np.zeros((h, w), bool)
    veg[15, :10] = True  # density exactly 0.1: not bushy
    assert vegetation.density(veg, sky_rows) == 0.1
    assert vegetation.hough_input(veg, sky_rows, P)[1] is False
    veg[17, 0] = True  # 11 / 100 > 0.1 (but 11 / 200 of the whole image would not be)
    assert vegetation.hough_input(veg, sky_rows, P)[1] is True


# ----------------------------------------------------------------------------------------
# Hough (section 5)
# ----------------------------------------------------------------------------------------

TRIG_C = np.cos(np.deg2rad(np.arange(180, dtype=np.float64)))
TRIG_S = np.sin(np.deg2rad(np.arange(180, dtype=np.float64)))


def _brute_votes(mask: np.ndarray) -> np.ndarray:
    h, w = mask.shape
    d = math.ceil(math.sqrt(h * h + w * w))
    acc = np.zeros((2 * d + 1, 180), np.int64)
    for y, x in zip(*np.nonzero(mask)):
        for j in range(180):
            rho = round(float(x) * float(TRIG_C[j]) + float(y) * float(TRIG_S[j]))  # half to even
            acc[rho + d, j] += 1
    return acc


def test_hough_trig_is_numpy_cos_sin_of_deg2rad():
    c, s = hough_trig(1)
    assert np.array_equal(c, TRIG_C) and np.array_equal(s, TRIG_S)


@HYP
@given(h=st.integers(1, 9), w=st.integers(1, 9), seed=st.integers(0, 2**32 - 1))
def test_votes_equal_brute_force(h, w, seed):
    mask = np.random.default_rng(seed).random((h, w)) < 0.4
    acc = hough.votes(mask, P)
    d = math.ceil(math.sqrt(h * h + w * w))
    assert acc.shape == (2 * d + 1, 180) and acc.dtype == np.int64
    assert np.array_equal(acc, _brute_votes(mask))
    assert (acc.sum(axis=0) == mask.sum()).all()


def test_votes_round_the_float64_value_not_the_exact_one():
    # cos(60 deg) is 0.5000000000000001 and sin(30 deg) 0.49999999999999994 in float64: the
    # spec rounds the float64 expression, so (x=1, y=0) votes rho 1 at 60 deg and
    # (x=0, y=1) votes rho 0 at 30 deg (exact arithmetic would give ties at 0.5)
    assert TRIG_C[60] > 0.5 and TRIG_S[30] < 0.5
    d = hough.rho_offset(2, 2)
    acc = hough.votes(np.array([[False, True], [False, False]]), P)  # (x=1, y=0)
    assert acc[1 + d, 60] == 1
    acc = hough.votes(np.array([[False, False], [True, False]]), P)  # (x=0, y=1)
    assert acc[0 + d, 30] == 1 and acc[1 + d, 90] == 1 and acc[0 + d, 0] == 1


def test_rho_offset_and_accumulator_shape():
    assert hough.rho_offset(240, 320) == 400
    assert hough.rho_offset(3, 4) == 5
    assert hough.rho_offset(1, 1) == 2
    assert hough.votes(np.zeros((240, 320), bool), P).shape == (801, 180)


def test_excluded_angles():
    ex = hough.excluded_angles([], P)
    assert np.flatnonzero(ex).tolist() == list(range(66, 115))
    ex = hough.excluded_angles([HoughLine(10, 0, 1)], P)
    assert np.flatnonzero(ex).tolist() == list(range(1, 20)) + list(range(66, 115))
    ex = hough.excluded_angles([HoughLine(3, 0, 1)], P)  # no wrap to 174..179
    assert np.flatnonzero(ex).tolist() == list(range(0, 13)) + list(range(66, 115))
    ex = hough.excluded_angles([HoughLine(178, 0, 1)], P)  # no wrap to 0..7
    assert np.flatnonzero(ex).tolist() == list(range(66, 115)) + list(range(169, 180))
    ex = hough.excluded_angles([HoughLine(50, 0, 1), HoughLine(130, 0, 1)], P)
    assert np.flatnonzero(ex).tolist() == list(range(41, 60)) + list(range(66, 115)) + list(range(121, 140))


def _state_with(acc: np.ndarray, h=30, w=40) -> hough.HoughState:
    d = hough.rho_offset(h, w)
    assert acc.shape == (2 * d + 1, 180)
    return hough.HoughState(np.zeros((h, w), bool), acc, d)


def test_extract_line_tie_breaking_smallest_rho_then_theta():
    d = hough.rho_offset(30, 40)
    acc = np.zeros((2 * d + 1, 180), np.int64)
    acc[60, 90] = 99  # excluded (horizontal), ignored
    acc[70, 5] = 7
    acc[40, 150] = 7
    acc[40, 20] = 7  # same rho index as (40, 150), smaller theta
    acc[30, 100] = 50  # excluded
    st_ = _state_with(acc.copy())
    line = hough.extract_line(st_, [], P)
    assert (line.theta_index, line.rho, line.weight) == (20, 40 - d, 7)
    # with 20 held, its neighbourhood 11..29 is excluded; the next tie is (40, 150)
    line2 = hough.extract_line(st_, [line], P)
    assert (line2.theta_index, line2.rho, line2.weight) == (150, 40 - d, 7)
    line3 = hough.extract_line(st_, [line, line2], P)
    assert (line3.theta_index, line3.rho) == (5, 70 - d)
    assert hough.extract_line(st_, [line, line2, line3], P) is None  # only excluded / zero cells
    # the accumulator was not altered by the exclusion (empty mask: nothing erased)
    assert np.array_equal(st_.acc, acc)


def test_extract_line_none_when_only_excluded_angles_vote():
    d = hough.rho_offset(30, 40)
    acc = np.zeros((2 * d + 1, 180), np.int64)
    acc[:, 66:115] = 5
    assert hough.extract_line(_state_with(acc), [], P) is None


def test_extract_line_erases_exactly_the_band():
    rng = np.random.default_rng(4)
    h, w = 60, 90  # hough_band = int(90/30) = 3 -> |dist| <= 1.5
    mask = rng.random((h, w)) < 0.05
    mask[:, 40] = True  # a strong vertical line: theta 0, rho 40
    state = hough.HoughState.start(mask, P)
    assert np.array_equal(state.acc, _brute_votes(mask))
    allowed = ~hough.excluded_angles([], P)
    peak = state.acc[:, allowed].max()
    line = hough.extract_line(state, [], P)
    assert (line.theta_index, line.rho, line.weight) == (0, 40, peak)
    xs = np.arange(w)[None, :].repeat(h, 0)
    ys = np.arange(h)[:, None].repeat(w, 1)
    band = np.abs((xs * TRIG_C[0] + ys * TRIG_S[0]) - 40) <= 3 / 2
    assert np.array_equal(state.mask, mask & ~band)
    assert not state.mask[:, 39:42].any() and np.array_equal(state.mask[:, 43:], mask[:, 43:])
    assert np.array_equal(state.acc, _brute_votes(state.mask))


def test_extract_line_erasure_on_an_oblique_line():
    rng = np.random.default_rng(8)
    h, w = 40, 60  # band 2 -> |dist| <= 1
    mask = rng.random((h, w)) < 0.08
    j, rho = 20, 30
    for y in range(h):
        x = int(round((rho - y * TRIG_S[j]) / TRIG_C[j]))
        if 0 <= x < w:
            mask[y, x] = True
    before = mask.copy()
    state = hough.HoughState.start(mask, P)
    line = hough.extract_line(state, [], P)
    assert (line.theta_index, line.rho) == (j, rho)
    assert np.array_equal(mask, before)  # the caller's mask is not modified
    xs = np.arange(w)[None, :].repeat(h, 0)
    ys = np.arange(h)[:, None].repeat(w, 1)
    band = np.abs((xs * TRIG_C[j] + ys * TRIG_S[j]) - rho) <= 1.0
    assert np.array_equal(state.mask, before & ~band)
    assert np.array_equal(state.acc, hough.votes(state.mask, P))


# ----------------------------------------------------------------------------------------
# Vanishing point (section 6)
# ----------------------------------------------------------------------------------------

def test_vp_of_lines_through_a_known_point():
    x0, y0 = 160.25, -50.5
    js = [0, 12, 25, 150, 170]
    lines = [HoughLine(j, x0 * TRIG_C[j] + y0 * TRIG_S[j], w) for j, w in zip(js, [240, 90, 130, 60, 200])]
    sol = vanishing.vanishing_point(lines, P)  # rho given as floats: the solve is linear in rho
    assert abs(sol.x - x0) < 1e-9 and abs(sol.y - y0) < 1e-9
    assert np.max(np.abs(sol.residuals)) < 1e-9 and sol.spread < 1e-9


def test_vp_integer_lines_through_the_origin_and_two_line_intersection():
    sol = vanishing.vanishing_point([HoughLine(0, 0, 5), HoughLine(30, 0, 3), HoughLine(160, 0, 9)], P)
    assert abs(sol.x) < 1e-9 and abs(sol.y) < 1e-9
    # two lines: the exact intersection
    l1, l2 = HoughLine(10, 100, 40), HoughLine(165, -90, 70)
    a = np.array([[TRIG_C[10], TRIG_S[10]], [TRIG_C[165], TRIG_S[165]]])
    x, y = np.linalg.solve(a, [100.0, -90.0])
    sol = vanishing.vanishing_point([l1, l2], P)
    assert abs(sol.x - x) < 1e-9 and abs(sol.y - y) < 1e-9


def test_vp_is_the_weighted_least_squares_solution():
    lines = [HoughLine(0, 160, 240), HoughLine(13, 140, 220), HoughLine(25, 118, 186),
             HoughLine(155, -169, 242), HoughLine(167, -168, 217)]
    sw = np.sqrt([ln.weight for ln in lines])
    a = np.array([[TRIG_C[ln.theta_index], TRIG_S[ln.theta_index]] for ln in lines]) * sw[:, None]
    b = np.array([ln.rho for ln in lines]) * sw
    (x, y), *_ = np.linalg.lstsq(a, b, rcond=None)
    sol = vanishing.vanishing_point(lines, P)
    assert abs(sol.x - x) < 1e-9 and abs(sol.y - y) < 1e-9
    e = np.array([ln.rho - x * TRIG_C[ln.theta_index] - y * TRIG_S[ln.theta_index] for ln in lines])
    w = np.array([ln.weight for ln in lines], float)
    assert np.allclose(sol.residuals, e, atol=1e-9)
    assert abs(sol.spread - math.sqrt(np.sum(w / w.sum() * e * e))) < 1e-9


def test_vp_singular_and_too_few_lines():
    assert vanishing.vanishing_point([HoughLine(5, 10, 100), HoughLine(5, 80, 50)], P) is None
    assert vanishing.vanishing_point([HoughLine(5, 10, 100), HoughLine(5, 80, 50), HoughLine(5, -3, 9)], P) is None
    assert vanishing.vanishing_point([HoughLine(5, 10, 100)], P) is None
    assert vanishing.vanishing_point([], P) is None


def _draw_exact(mask: np.ndarray, j: int, rho: int, y0: int, y1: int) -> None:
    """Pixels of the line (theta j, rho) one per row, each in the accumulator cell of that line."""
    for y in range(y0, y1):
        x = int(round((rho - y * TRIG_S[j]) / TRIG_C[j]))
        if 0 <= x < mask.shape[1]:
            mask[y, x] = True


TRUE_JS = [0, 12, 24, 156, 168]
VP = (160.0, -60.0)


def _fan_with_off_line() -> tuple[np.ndarray, list[tuple[int, int]], tuple[int, int]]:
    """Five lines through VP (one of them short and weak) plus one strong line 60 px off."""
    mask = np.zeros((240, 320), bool)
    true = []
    for j in TRUE_JS:
        rho = int(round(VP[0] * TRIG_C[j] + VP[1] * TRIG_S[j]))
        true.append((j, rho))
        _draw_exact(mask, j, rho, 150 if j == 168 else 0, 240)
    off = (145, int(round(VP[0] * TRIG_C[145] + VP[1] * TRIG_S[145] + 60)))
    _draw_exact(mask, *off, 0, 240)
    return mask, true, off


def test_find_lines_drops_an_off_line():
    mask, true, off = _fan_with_off_line()
    res = vanishing.find_lines(mask, P)
    assert [(o.theta_index, o.rho) for o in res.outliers] == [off]
    assert sorted((ln.theta_index, ln.rho) for ln in res.lines) == sorted(true)
    assert res.n_rows == 5
    assert abs(res.vp[0] - VP[0]) < 1.0 and abs(res.vp[1] - VP[1]) < 1.0
    # the off line was held before the weak true line: the refill was appended last
    assert (res.lines[-1].theta_index, res.lines[-1].rho) == true[-1]
    # the same decision, from the pieces: with the off line held, it has the largest residual
    held = [ln for ln in res.lines[:-1]] + [res.outliers[0]]
    sol = vanishing.vanishing_point(held, P)
    e = np.abs(sol.residuals)
    assert int(np.argmax(e)) == len(held) - 1
    assert e[-1] > P.outlier_ratio * sol.spread and e[-1] > P.outlier_min_px


def test_find_lines_keeps_the_off_line_when_min_px_is_large():
    mask, _, off = _fan_with_off_line()
    res = vanishing.find_lines(mask, P.replace(outlier_min_px=1000.0))
    assert res.outliers == [] and res.n_rows == 5
    assert off in [(ln.theta_index, ln.rho) for ln in res.lines]


def test_find_lines_restart_with_one_row_less():
    mask, true, off = _fan_with_off_line()
    res = vanishing.find_lines(mask, P.replace(max_outliers=1))
    # first outlier = max_outliers-th: restart from the untouched input with N = 4;
    # then the four strong true lines are held and no outlier remains
    assert res.n_rows == 4 and len(res.lines) == 4
    assert [(o.theta_index, o.rho) for o in res.outliers] == [off]
    assert sorted((ln.theta_index, ln.rho) for ln in res.lines) == sorted(true[:4])
    assert all(ln.weight == 240 or ln.weight == 241 for ln in res.lines)  # untouched input
    assert abs(res.vp[0] - VP[0]) < 1.0 and abs(res.vp[1] - VP[1]) < 1.5


def test_find_lines_too_few_lines_no_vp():
    mask = np.zeros((60, 80), bool)
    mask[:, 30] = True  # a single line: extraction stops at 1 line
    res = vanishing.find_lines(mask, P)
    assert res.vp is None and res.n_rows == 1 and len(res.lines) == 1
    res = vanishing.find_lines(np.zeros((60, 80), bool), P)
    assert res.vp is None and res.n_rows == 0 and res.lines == []


# ----------------------------------------------------------------------------------------
# Constrained RANSAC (section 7)
# ----------------------------------------------------------------------------------------

def test_band_points_row_major_and_membership():
    rng = np.random.default_rng(6)
    veg = rng.random((50, 70)) < 0.2
    j, rho, band = 15, 30, 7
    xs, ys = ransac.band_points(veg, j, rho, band, P)
    exp = [(x, y) for y in range(50) for x in range(70)
           if veg[y, x] and abs((x * TRIG_C[j] + y * TRIG_S[j]) - rho) <= band / 2]
    assert list(zip(xs.tolist(), ys.tolist())) == exp
    assert xs.dtype == np.int64 and ys.dtype == np.int64


def _hash(x: int, y: int, w: int) -> int:
    return ((y * w + x) * 2654435761) % 2**32


@pytest.mark.parametrize(("n", "subsampled"), [(466, False), (467, False), (468, True), (600, True), (2000, True)])
def test_subsample_counts_and_smallest_keys(n, subsampled):
    rng = np.random.default_rng(n)
    w = 320
    lin = np.sort(rng.choice(240 * w, n, replace=False))
    ys, xs = lin // w, lin % w
    kx, ky, v = ransac.subsample(xs, ys, w, P)
    if not subsampled:
        assert n + n // 2 <= 700
        assert np.array_equal(kx, xs) and np.array_equal(ky, ys) and v == n // 2
        return
    assert n + n // 2 > 700
    n_keep = (500 * n) // (n + n // 2)
    assert len(kx) == n_keep and v == 500 - n_keep
    keys = sorted(_hash(int(x), int(y), w) for x, y in zip(xs, ys))
    kept_keys = [_hash(int(x), int(y), w) for x, y in zip(kx, ky)]
    assert sorted(kept_keys) == keys[:n_keep]
    lin_kept = ky * w + kx
    assert (np.diff(lin_kept) > 0).all()  # row-major order kept


def _naive_scores(px, py, pw, n_pix, u, thr=1.0):
    total = n_pix + int(pw[n_pix])
    out = []
    for t in range(len(u)):
        i1, i2 = math.floor(u[t, 0] * total), math.floor(u[t, 1] * total)
        if i1 == i2 or (i1 >= n_pix and i2 >= n_pix):
            out.append(-1)
            continue
        a, b = min(i1, n_pix), min(i2, n_pix)
        x1, y1, x2, y2 = float(px[a]), float(py[a]), float(px[b]), float(py[b])
        s = 0
        for k in range(n_pix + 1):
            cross = (x2 - x1) * (float(py[k]) - y1) - (y2 - y1) * (float(px[k]) - x1)
            if abs(cross) < thr * math.sqrt((x2 - x1) ** 2 + (y2 - y1) ** 2):
                s += int(pw[k])
        out.append(s)
    return np.array(out)


def test_hypothesis_table_is_default_rng():
    u = hypothesis_table(0, 1000)
    assert np.array_equal(u, np.random.default_rng(0).random((1000, 2)))
    assert np.array_equal(hypothesis_table(7, 20), np.random.default_rng(7).random((20, 2)))


@pytest.mark.parametrize(("n_pix", "v"), [(3, 1), (4, 2), (12, 6)])
def test_score_hypotheses_equals_naive_and_degenerate_rules(n_pix, v):
    rng = np.random.default_rng(n_pix)
    lin = rng.choice(900, n_pix, replace=False)  # distinct pixels
    px = np.append((lin % 30).astype(float), 12.5)
    py = np.append((lin // 30).astype(float), -40.0)
    pw = np.append(np.ones(n_pix, np.int64), v)
    scores = ransac.score_hypotheses(px, py, pw, n_pix, P)
    u = np.random.default_rng(0).random((1000, 2))
    assert np.array_equal(scores, _naive_scores(px, py, pw, n_pix, u))
    total = n_pix + v
    i1, i2 = np.floor(u[:, 0] * total).astype(int), np.floor(u[:, 1] * total).astype(int)
    degenerate = (i1 == i2) | ((i1 >= n_pix) & (i2 >= n_pix))
    assert degenerate.any() and (~degenerate).any()
    assert (scores[degenerate] == -1).all() and (scores[~degenerate] >= 2).all()  # both picks are inliers
    # both picks VP with different indices is still degenerate (the same point)
    both_vp = (i1 >= n_pix) & (i2 >= n_pix) & (i1 != i2)
    if v >= 2:
        assert both_vp.any() and (scores[both_vp] == -1).all()


def test_inlier_test_is_strict():
    px = np.array([0.0, 0.0, 1.0, -1.0, 0.5, 0.999])
    py = np.array([0.0, 10.0, 5.0, 3.0, 2.0, 7.0])
    inl = ransac.inliers(px, py, 0.0, 0.0, 0.0, 10.0, P)
    assert inl.tolist() == [True, True, False, False, True, True]  # distance exactly 1: outside


def test_refit_recovers_a_line_on_collinear_points():
    ys = np.arange(0.0, 40.0, 2.0)
    xs = 0.5 * ys + 100.0
    cx, cy, dx, dy = ransac.refit(xs, ys, np.ones(len(xs), np.int64))
    assert dy > 0 and abs(math.hypot(dx, dy) - 1) < 1e-12
    fit = ransac.RowFit(cx, cy, dx, dy, 0)
    a, b = fit.as_row()
    assert abs(a - 0.5) < 1e-9 and abs(b - 100.0) < 1e-9
    # orientation: a descending line still gets dy > 0; a horizontal one dx > 0
    cx, cy, dx, dy = ransac.refit(-0.5 * ys + 3, ys, np.ones(len(ys), np.int64))
    assert dy > 0 and dx < 0
    cx, cy, dx, dy = ransac.refit(ys, np.full_like(ys, 7.0), np.ones(len(ys), np.int64))
    assert dy == 0 and dx > 0 and cy == 7.0


def test_refit_is_weighted():
    px = np.array([0.0, 0.0, 0.0, 10.0])
    py = np.array([0.0, 10.0, 20.0, 10.0])
    py[3] = 20.0  # points (0, 0), (0, 10), (0, 20) and (10, 20)
    cx, cy, dx, _ = ransac.refit(px, py, np.array([1, 1, 1, 0]))
    assert abs(dx) < 1e-12 and cx == 0.0 and cy == 10.0  # the zero-weight point is ignored
    cx, cy, dx2, _ = ransac.refit(px, py, np.array([1, 1, 1, 1]))
    assert dx2 > 1e-3 and abs(cx - 2.5) < 1e-12 and abs(cy - 12.5) < 1e-12


def test_fit_row_recovers_a_noiseless_row_through_the_vp():
    veg = np.zeros((240, 320), bool)
    ys = np.arange(0, 240, 2)
    veg[ys, ys // 2 + 100] = True  # x = 0.5 y + 100 exactly
    vp = (50.0, -100.0)  # on the same line
    j = int(round(math.degrees(math.atan2(-1.0, 2.0)) % 180))  # normal of direction (0.5, 1)
    rho = int(round(100 * TRIG_C[j]))
    fit = ransac.fit_row(veg, HoughLine(j, rho, 120), vp, 16, P)
    a, b = fit.as_row()
    assert abs(a - 0.5) < 1e-9 and abs(b - 100.0) < 1e-9
    assert 0 <= fit.hypothesis < 1000


def test_fit_row_no_support():
    veg = np.zeros((240, 320), bool)
    veg[100:113, 40] = True  # n = 13, v = 6: 19 < 20
    assert ransac.fit_row(veg, HoughLine(0, 40, 13), (40.0, -50.0), 16, P) is None
    veg[113, 40] = True  # n = 14, v = 7: 21 >= 20
    assert ransac.fit_row(veg, HoughLine(0, 40, 14), (40.0, -50.0), 16, P) is not None


def _fit(x_bottom: float, a: float, height: int = 240) -> ransac.RowFit:
    """A fit ``x = a*y + b`` through ``x_bottom`` at ``y = H-1`` (direction (a, 1); dyadic ``a``
    keep ``a`` and ``b`` exact)."""
    return ransac.RowFit(x_bottom, height - 1.0, a, 1.0, 0)


def test_validate_rows_reasons_and_order():
    h, w = 240, 320  # hough_band = 10; orientation = atan2(1, a)
    fits = [
        _fit(100.0, 0.0),  # valid, orientation pi/2
        None,  # no_support
        _fit(300.0, 8.0),  # horizon: atan2(1, 8) = 0.124 < 0.2
        _fit(105.0, 0.0625),  # parallel to row 0 (0.062) and too close: parallel first
        _fit(106.0, 0.5),  # 0.46 from row 0, x 6 < 10 away: too_close
        _fit(200.0, -0.25),  # 0.245 from row 0, far: valid
        _fit(290.0, -0.3125),  # 0.058 from row 5 (valid): parallel
        _fit(110.0, 1.0),  # exactly 10 px from row 0 at y = H-1: not too close -> valid
        _fit(250.0, -1.0),  # valid
        _fit(5.0, -8.0),  # horizon (atan2(1, |-8|))
    ]
    rows = ransac.validate_rows(fits, h, w, P)
    assert [r.reason for r in rows] == ["", "no_support", "horizon", "parallel", "too_close",
                                        "", "parallel", "", "", "horizon"]
    assert [r.valid for r in rows] == [r.reason == "" for r in rows]
    assert math.isnan(rows[1].a) and math.isnan(rows[1].b) and rows[1].hypothesis == -1
    for r, f in zip(rows, fits):
        if f is not None:
            assert r.a == f.dx and r.x_at(h - 1.0) == f.cx


def test_validate_rows_compares_only_with_earlier_valid_rows():
    h, w = 240, 320
    fits = [
        _fit(100.0, 5.5),  # horizon (0.180) -> invalid
        _fit(103.0, 4.0),  # 0.245: would be parallel and too close to row 0, but row 0 is invalid
        _fit(250.0, 4.5),  # 0.219: parallel to row 1
        _fit(255.0, 2.0),  # 0.464: 5 px from row 2, which is invalid: valid
        _fit(258.0, 1.0),  # 0.785: 3 px from row 3 (valid): too_close
    ]
    rows = ransac.validate_rows(fits, h, w, P)
    assert [r.reason for r in rows] == ["horizon", "", "parallel", "", "too_close"]


def test_validate_rows_too_close_at_bottom_row_with_hough_band():
    h = 240
    # 9.5 px apart at y = H-1: too close with int(320/30) = 10, not with int(270/30) = 9
    pair = [_fit(100.0, 0.0), _fit(109.5, 1.0)]
    assert ransac.validate_rows(pair, h, 320, P)[1].reason == "too_close"
    assert ransac.validate_rows(pair, h, 270, P)[1].reason == ""
    # 10 px apart at y = H-1 (but 9 at y = H): not too close
    assert ransac.validate_rows([_fit(100.0, 0.0), _fit(110.0, -1.0)], h, 320, P)[1].reason == ""
