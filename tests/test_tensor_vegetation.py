"""Tensor vegetation mask and Hough input (ALGORITHM.md sections 3-4) vs the reference.

Every check is bit for bit: the batched :mod:`torchrow.functional.vegetation` against
:mod:`torchrow.reference.vegetation` (which crops the region below the horizon) and, where
the spec names an OpenCV call, against that call (``cv2.Canny``, ``cv2.erode``) directly.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchrow.core.io import load_image
from torchrow.core.params import Params
from torchrow.core.tables import rgb_to_lab
from torchrow.functional import vegetation as tv
from torchrow.reference import color as rcolor
from torchrow.reference import sky as rsky
from torchrow.reference import vegetation as rv

P = Params()
HYP = settings(deadline=None, max_examples=80, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Run this module's tensor ops on one thread (restored afterwards).

    Results do not depend on the thread count; on a shared, oversubscribed CPU PyTorch's
    OpenMP barriers made these tests up to 10x slower with 2 threads.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ----------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------

def to_tensor(imgs: list[np.ndarray]) -> torch.Tensor:
    """List of ``(H, W, 3)`` uint8 -> ``uint8 (B, 3, H, W)``."""
    return torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()


def longs(values) -> torch.Tensor:
    return torch.tensor(list(values), dtype=torch.int64)


def cv_canny_region(mask: np.ndarray, sky: int, low: int = P.canny_low,
                    high: int = P.canny_high) -> np.ndarray:
    """``cv2.Canny`` on the crop below ``sky``, pasted back (rows above False)."""
    out = np.zeros(mask.shape, bool)
    region = mask[sky:].astype(np.uint8) * 255
    if region.size:
        out[sky:] = cv2.Canny(region, low, high, L2gradient=False) > 0
    return out


def cv_bushy_region(raw: np.ndarray, sky: int, size: tuple[int, int]) -> np.ndarray:
    """``raw & ~cv2.erode(raw)`` on the crop, default anchor and border, pasted back."""
    ew, eh = size
    out = np.zeros(raw.shape, bool)
    region = raw[sky:].astype(np.uint8)
    if region.size:
        er = cv2.erode(region, np.ones((eh, ew), np.uint8))
        out[sky:] = (region == 1) & (er == 0)
    return out


def random_masks(rng: np.random.Generator, b: int, h: int, w: int) -> np.ndarray:
    """Binary masks of mixed kinds: salt-and-pepper at random densities and smooth blobs."""
    out = np.empty((b, h, w), bool)
    for i in range(b):
        if i % 2 == 0:
            out[i] = rng.random((h, w)) < rng.uniform(0.02, 0.95)
        else:
            n = cv2.GaussianBlur(rng.random((h, w)), (0, 0), rng.uniform(0.4, 3.0))
            out[i] = n > np.quantile(n, rng.uniform(0.1, 0.9))
    return out


def random_images(rng: np.random.Generator, b: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Random RGB images built from a small palette of near colours, and a colour per image.

    The palette makes LAB-box masks non-trivial (many pixels near the chosen colour).
    """
    imgs = np.empty((b, h, w, 3), np.uint8)
    cols = np.empty((b, 3), np.uint8)
    for i in range(b):
        base = rng.integers(0, 256, 3)
        palette = np.clip(base + rng.integers(-12, 13, (32, 3)), 0, 255).astype(np.uint8)
        imgs[i] = palette[rng.integers(0, 32, (h, w))]
        noise = rng.random((h, w)) < 0.2
        imgs[i][noise] = rng.integers(0, 256, (int(noise.sum()), 3))
        cols[i] = palette[rng.integers(0, 32)]
    return imgs, cols


# ----------------------------------------------------------------------------------------
# CRBD inputs, computed once per session with the reference stages
# ----------------------------------------------------------------------------------------

@pytest.fixture(scope="session")
def crbd_inputs(crbd_dir: Path):
    """Every 3rd CRBD image at width 320 with the reference's ``sky_row`` and
    ``vegetation_color`` (~0.15 s an image; ``TORCHROW_TEST_FULL=1``: every image)."""
    full = os.environ.get("TORCHROW_TEST_FULL") == "1"
    paths = sorted(p for p in (crbd_dir / "Images").iterdir()
                   if p.name.startswith("crop_row_") and p.suffix.lower() == ".jpg")
    paths = paths if full else paths[::3]
    imgs = [load_image(p, P.image_width) for p in paths]
    shapes = {im.shape for im in imgs}
    assert len(shapes) == 1, shapes
    skies = [rsky.sky_row(im, P) for im in imgs]
    cols = [rcolor.vegetation_color(im, P)[0] for im in imgs]
    return imgs, cols, skies


# ----------------------------------------------------------------------------------------
# LAB and raw mask
# ----------------------------------------------------------------------------------------

def test_lab_equals_shared_rgb_to_lab():
    rng = np.random.default_rng(0)
    imgs = rng.integers(0, 256, (3, 17, 23, 3), dtype=np.uint8)
    out = tv.lab(to_tensor(list(imgs)))
    assert out.shape == (3, 3, 17, 23) and out.dtype == torch.float64
    assert np.array_equal(out.permute(0, 2, 3, 1).numpy(), rgb_to_lab(imgs))
    assert tv.lab(torch.zeros((0, 3, 4, 5), dtype=torch.uint8)).shape == (0, 3, 4, 5)


def test_lab_and_raw_mask_chunked_equal_unchunked(monkeypatch):
    rng = np.random.default_rng(1)
    imgs, cols = random_images(rng, 5, 9, 11)
    x, c = to_tensor(list(imgs)), torch.from_numpy(cols)
    k, s = longs([4, 5, 6, 7, 13]), longs([0, 3, 9, 1, 8])
    whole_lab, whole_raw = tv.lab(x), tv.raw_mask(x, c, k, s)
    info0 = torch.tensor([0.1, 0.0, 0.5, 0.02, 0.3], dtype=torch.float64)
    whole_k = tv.adapt_k(x, c, s, info0, P)
    monkeypatch.setattr(tv, "_CHUNK_PIXELS", 2 * 9 * 11)  # chunks of 2 images
    assert torch.equal(tv.lab(x), whole_lab)
    assert torch.equal(tv.raw_mask(x, c, k, s), whole_raw)
    kk, rr = tv.adapt_k(x, c, s, info0, P)
    assert torch.equal(kk, whole_k[0]) and torch.equal(rr, whole_k[1])


@pytest.mark.parametrize("k", [0, 3, 4, 4.5, 13])
def test_raw_mask_random_images_vs_reference(k):
    rng = np.random.default_rng(int(k * 10) + 3)
    imgs, cols = random_images(rng, 6, 13, 19)
    skies = [0, 1, 5, 12, 13, 7]  # 13 = H: nothing below the horizon
    kt = torch.full((6,), k, dtype=torch.float64 if isinstance(k, float) else torch.int64)
    out = tv.raw_mask(to_tensor(list(imgs)), torch.from_numpy(cols), kt, longs(skies))
    assert out.shape == (6, 13, 19) and out.dtype == torch.bool
    for i in range(6):
        ref = rv.raw_mask(imgs[i], tuple(int(v) for v in cols[i]), k, skies[i])
        assert np.array_equal(out[i].numpy(), ref), i
    assert out[:, :1].sum() < out.sum() or out.sum() == 0


def test_raw_mask_box_boundary_float_k():
    """``k`` set exactly to a pixel's LAB offset (and one ulp either side) on each channel.

    Here ``c - k <= lab`` and ``|lab - c| <= k`` can round differently; the tensor path
    must fall the reference's way on every one.
    """
    rng = np.random.default_rng(7)
    n = 40
    img = rng.integers(0, 256, (n, 1, 1, 3), dtype=np.uint8)
    col = np.clip(img[:, 0, 0].astype(np.int64) + rng.integers(-3, 4, (n, 3)), 0, 255).astype(np.uint8)
    lab_p = rgb_to_lab(img[:, 0, 0])
    lab_c = rgb_to_lab(col)
    ks = []
    for i in range(n):
        d = np.abs(lab_p[i] - lab_c[i]).max()
        ks += [d, np.nextafter(d, np.inf), np.nextafter(d, -np.inf)]
    ks = np.array(ks)
    imgs = np.repeat(img, 3, axis=0)
    cols = np.repeat(col, 3, axis=0)
    out = tv.raw_mask(to_tensor(list(imgs)), torch.from_numpy(cols), torch.from_numpy(ks),
                      torch.zeros(3 * n, dtype=torch.int64))
    ref = [rv.raw_mask(imgs[i], tuple(int(v) for v in cols[i]), float(ks[i]), 0)[0, 0]
           for i in range(3 * n)]
    assert out[:, 0, 0].tolist() == ref
    assert 0 < sum(ref) < 3 * n


@pytest.mark.data
def test_raw_mask_crbd_vs_reference(crbd_inputs):
    imgs, cols, skies = crbd_inputs
    x, c, s = to_tensor(imgs), torch.tensor(cols, dtype=torch.uint8), longs(skies)
    for k in (P.veg_tol, 9):
        out = tv.raw_mask(x, c, torch.full((len(imgs),), k), s)
        for i, im in enumerate(imgs):
            assert np.array_equal(out[i].numpy(), rv.raw_mask(im, cols[i], k, skies[i])), (i, k)
        assert out.sum() > 0


# ----------------------------------------------------------------------------------------
# Fractions
# ----------------------------------------------------------------------------------------

def test_raw_fraction_and_density_vs_reference():
    rng = np.random.default_rng(2)
    masks = random_masks(rng, 6, 10, 7)
    skies = [0, 3, 9, 10, 5, 1]
    m, s = torch.from_numpy(masks), longs(skies)
    fr, de = tv.raw_fraction(m, s), tv.density(m, s)
    assert fr.dtype == torch.float64 and fr.shape == (6,)
    for i in range(6):
        assert fr[i].item() == rv.raw_fraction(masks[i], skies[i])
        assert de[i].item() == rv.density(masks[i], skies[i])
    assert fr[3].item() == 0.0  # sky == H: empty region


# ----------------------------------------------------------------------------------------
# Bushy-region removal
# ----------------------------------------------------------------------------------------

def test_remove_bushy_vs_reference_and_cv2_erode():
    rng = np.random.default_rng(3)
    for h, w in [(1, 1), (1, 9), (9, 1), (2, 2), (3, 3), (7, 11), (40, 33), (240, 320)]:
        masks = random_masks(rng, 6, h, w)
        skies = [0, h // 2, h - 1, h, int(rng.integers(0, h + 1)), 0]
        out = tv.remove_bushy(torch.from_numpy(masks), longs(skies), P)
        assert out.shape == (6, h, w) and out.dtype == torch.bool
        for i in range(6):
            ref = rv.remove_bushy(masks[i], skies[i], P)
            assert np.array_equal(out[i].numpy(), ref), (h, w, i)
            assert np.array_equal(ref, cv_bushy_region(masks[i], skies[i], P.bushy_erode))


@pytest.mark.parametrize("size", [(1, 1), (2, 3), (3, 3), (4, 2), (2, 5), (5, 4)])
def test_remove_bushy_other_kernels_vs_cv2_erode(size):
    rng = np.random.default_rng(sum(size))
    params = P.replace(bushy_erode=size)
    masks = random_masks(rng, 4, 21, 17)
    skies = [0, 4, 20, 11]
    out = tv.remove_bushy(torch.from_numpy(masks), longs(skies), params)
    for i in range(4):
        assert np.array_equal(out[i].numpy(), cv_bushy_region(masks[i], skies[i], size)), i


def test_remove_bushy_kernel_geometry():
    """A single hole: the (2 wide, 3 high) kernel keeps pixels in columns x, x+1, rows y-1..y+1."""
    raw = np.ones((7, 7), bool)
    raw[3, 3] = False
    out = tv.remove_bushy(torch.from_numpy(raw)[None], longs([0]), P)[0].numpy()
    expected = np.zeros((7, 7), bool)
    expected[2:5, 3:5] = True
    expected[3, 3] = False
    assert np.array_equal(out, expected)
    # Rows above the horizon are outside: they never erode the first region row.
    raw = np.ones((5, 4), bool)
    raw[1] = False  # above the horizon (sky = 2): must be ignored
    out = tv.remove_bushy(torch.from_numpy(raw)[None], longs([2]), P)[0].numpy()
    assert not out.any()


# ----------------------------------------------------------------------------------------
# Canny
# ----------------------------------------------------------------------------------------

CANNY_SIZES = [(1, 1), (1, 2), (1, 17), (17, 1), (2, 1), (2, 2), (2, 3), (3, 2), (3, 3), (4, 4),
               (5, 5), (5, 9), (9, 5), (7, 13), (31, 2), (2, 31), (64, 64), (121, 161), (240, 320)]


@pytest.mark.parametrize("shape", CANNY_SIZES)
def test_canny_binary_equals_cv2_canny(shape):
    h, w = shape
    rng = np.random.default_rng(h * 1000 + w)
    masks = random_masks(rng, 8, h, w)
    out = tv.canny_binary(torch.from_numpy(masks), torch.zeros(8, dtype=torch.int64), P)
    assert out.shape == (8, h, w) and out.dtype == torch.bool
    for i in range(8):
        ref = cv2.Canny(masks[i].astype(np.uint8) * 255, P.canny_low, P.canny_high, L2gradient=False) > 0
        assert np.array_equal(out[i].numpy(), ref), (shape, i)


@pytest.mark.parametrize("shape", [(3, 3), (9, 5), (40, 60), (240, 320)])
def test_canny_binary_region_rule_vs_reference_crop(shape):
    h, w = shape
    rng = np.random.default_rng(h + 7 * w)
    b = 10
    masks = random_masks(rng, b, h, w)
    skies = [0, 1, h // 3, h // 2, h - 2, h - 1, h, *rng.integers(0, h + 1, 3).tolist()]
    skies = [max(0, min(h, s)) for s in skies]
    out = tv.canny_binary(torch.from_numpy(masks), longs(skies), P)
    for i in range(b):
        assert np.array_equal(out[i].numpy(), cv_canny_region(masks[i], skies[i])), (shape, i, skies[i])
        assert not out[i, :skies[i]].any()


@pytest.mark.parametrize(("low", "high"), [(100, 200), (200, 100), (1, 1), (0, 0), (254, 255), (255, 510),
                                      (100, 300), (100, 600), (300, 800), (500, 1200), (1000, 2000)])
def test_canny_thresholds_and_hysteresis_equal_cv2(low, high):
    """Other thresholds, including ones where weak edges exist and hysteresis decides."""
    params = P.replace(canny_low=low, canny_high=high)
    rng = np.random.default_rng(low + high)
    masks = random_masks(rng, 12, 37, 53)
    skies = [0, 0, 0, 0, 5, 17, 36, 0, 2, 9, 0, 30]
    out = tv.canny_binary(torch.from_numpy(masks), longs(skies), params)
    for i in range(12):
        assert np.array_equal(out[i].numpy(), cv_canny_region(masks[i], skies[i], low, high)), i


def test_canny_hysteresis_is_exercised():
    """Check the premise: with high=600 weak edges do matter, with the defaults they do not."""
    rng = np.random.default_rng(11)
    masks = random_masks(rng, 20, 37, 53).astype(np.uint8) * 255
    with_weak = sum(not np.array_equal(cv2.Canny(m, 100, 600), cv2.Canny(m, 600, 600)) for m in masks)
    assert with_weak > 0
    # Defaults: every non-zero L1 magnitude on a 0/255 image is >= 255 > high, so the result
    # equals Canny with low = high = 1 (no weak pixel can exist).
    for m in masks:
        assert np.array_equal(cv2.Canny(m, 100, 200), cv2.Canny(m, 1, 1))


def test_canny_opencv_thread_count_and_ipp_do_not_matter():
    """cv2.Canny takes an IPP path in some configurations; the result must not change."""
    rng = np.random.default_rng(12)
    masks = random_masks(rng, 6, 60, 80)
    out = tv.canny_binary(torch.from_numpy(masks), torch.zeros(6, dtype=torch.int64), P).numpy()
    threads, ipp = cv2.getNumThreads(), cv2.ipp.useIPP()
    try:
        for n_threads in (1, 2):
            for use_ipp in (True, False):
                cv2.setNumThreads(n_threads)
                cv2.ipp.setUseIPP(use_ipp)
                for i in range(6):
                    assert np.array_equal(out[i], cv2.Canny(masks[i].astype(np.uint8) * 255, 100, 200) > 0)
    finally:
        cv2.setNumThreads(threads)
        cv2.ipp.setUseIPP(ipp)


def test_canny_nms_direction_cases():
    """Hand-made cases of the three directions and the asymmetric > / >= comparisons."""
    # A vertical step edge two pixels wide of magnitude: horizontal gradient, the left pixel of
    # an equal pair wins (m > left, m >= right).
    m = np.zeros((5, 6), bool)
    m[:, 3:] = True
    out = tv.canny_binary(torch.from_numpy(m)[None], longs([0]), P)[0].numpy()
    ref = cv2.Canny(m.astype(np.uint8) * 255, 100, 200) > 0
    assert np.array_equal(out, ref)
    assert ref[:, 2].all() and not ref[:, 3].any()
    # The transpose: vertical gradient, the upper pixel wins.
    out = tv.canny_binary(torch.from_numpy(np.ascontiguousarray(m.T))[None], longs([0]), P)[0].numpy()
    ref = cv2.Canny(np.ascontiguousarray(m.T).astype(np.uint8) * 255, 100, 200) > 0
    assert np.array_equal(out, ref)
    assert ref[2].all() and not ref[3].any()
    # Diagonal edges of both orientations.
    for tri in (np.tri(9, 9, 0, bool), np.fliplr(np.tri(9, 9, 0, bool)).copy()):
        out = tv.canny_binary(torch.from_numpy(tri)[None], longs([0]), P)[0].numpy()
        assert np.array_equal(out, cv2.Canny(tri.astype(np.uint8) * 255, 100, 200) > 0)


def test_tg22_constant():
    assert tv.TG22 == 13573 and tv.CANNY_SHIFT == 15


@HYP
@given(h=st.integers(1, 12), w=st.integers(1, 12), seed=st.integers(0, 2**32 - 1),
       density=st.floats(0.0, 1.0), data=st.data())
def test_property_canny_and_erosion_random_sky(h, w, seed, density, data):
    rng = np.random.default_rng(seed)
    b = 3
    masks = rng.random((b, h, w)) < density
    skies = [data.draw(st.integers(0, h)) for _ in range(b)]
    m, s = torch.from_numpy(masks), longs(skies)
    canny = tv.canny_binary(m, s, P)
    veg = tv.remove_bushy(m, s, P)
    for i in range(b):
        assert np.array_equal(canny[i].numpy(), cv_canny_region(masks[i], skies[i]))
        assert np.array_equal(veg[i].numpy(), rv.remove_bushy(masks[i], skies[i], P))
        hin, bushy = rv.hough_input(rv.remove_bushy(masks[i], skies[i], P), skies[i], P)
        got, got_b = tv.hough_input(veg[i:i + 1], s[i:i + 1], P)
        assert np.array_equal(got[0].numpy(), hin) and bool(got_b[0]) == bushy


# ----------------------------------------------------------------------------------------
# Hough input and the full stage on CRBD
# ----------------------------------------------------------------------------------------

def test_hough_input_random_vs_reference_mixed_batch():
    rng = np.random.default_rng(5)
    masks = random_masks(rng, 8, 30, 40)
    masks[0] = rng.random((30, 40)) < 0.02  # sparse: not bushy
    masks[1] = False  # empty
    skies = [0, 3, 10, 29, 30, 0, 15, 1]
    m, s = torch.from_numpy(masks), longs(skies)
    veg = tv.remove_bushy(m, s, P)
    out, bushy = tv.hough_input(veg, s, P)
    assert out.dtype == torch.bool and bushy.dtype == torch.bool and bushy.shape == (8,)
    flags = []
    for i in range(8):
        v = rv.remove_bushy(masks[i], skies[i], P)
        ref, b = rv.hough_input(v, skies[i], P)
        assert np.array_equal(out[i].numpy(), ref) and bool(bushy[i]) == b, i
        flags.append(b)
    assert any(flags) and not all(flags)
    # Masks that are not zero above the horizon: those rows are ignored by density and
    # Canny, and copied through unchanged for a non-bushy image (as the reference).
    out, bushy = tv.hough_input(m, s, P)
    for i in range(8):
        ref, b = rv.hough_input(masks[i], skies[i], P)
        assert np.array_equal(out[i].numpy(), ref) and bool(bushy[i]) == b, i


@pytest.mark.data
def test_crbd_full_stage_and_canny_vs_reference(crbd_inputs):
    """raw -> remove_bushy -> hough_input at several k (larger k makes bushy images)."""
    imgs, cols, skies = crbd_inputs
    x, c, s = to_tensor(imgs), torch.tensor(cols, dtype=torch.uint8), longs(skies)
    n_bushy = 0
    for k in (P.veg_tol, 8, 13):
        kt = torch.full((len(imgs),), k)
        raw = tv.raw_mask(x, c, kt, s)
        veg = tv.remove_bushy(raw, s, P)
        hin, bushy = tv.hough_input(veg, s, P)
        canny_raw = tv.canny_binary(raw, s, P)  # denser real masks for Canny
        for i in range(len(imgs)):
            r = raw[i].numpy()
            v = rv.remove_bushy(r, skies[i], P)
            assert np.array_equal(veg[i].numpy(), v), (i, k)
            ref, b = rv.hough_input(v, skies[i], P)
            assert np.array_equal(hin[i].numpy(), ref) and bool(bushy[i]) == b, (i, k)
            assert np.array_equal(canny_raw[i].numpy(), cv_canny_region(r, skies[i])), (i, k)
            assert np.array_equal(tv.canny_binary(veg[i:i + 1], s[i:i + 1], P)[0].numpy(),
                                  cv_canny_region(v, skies[i])), (i, k)
        n_bushy += int(bushy.sum())
    assert n_bushy > 0


@pytest.mark.data
def test_crbd_adapt_k_vs_reference(crbd_inputs):
    imgs, cols, skies = crbd_inputs
    idx = list(range(0, len(imgs), 6))
    sub = [imgs[i] for i in idx]
    x, s = to_tensor(sub), longs(skies[i] for i in idx)
    c = torch.tensor([cols[i] for i in idx], dtype=torch.uint8)
    k0 = torch.full((len(idx),), P.video_k_start)
    info_self = tv.raw_fraction(tv.raw_mask(x, c, k0, s), s)
    # Scale info0 to drive both loops: shrink (info0 small), stay, grow (info0 large).
    scales = torch.tensor([0.2, 0.45, 1.0, 1.3, 3.0, 50.0] * len(idx), dtype=torch.float64)[:len(idx)]
    for info0 in (info_self, info_self * scales, info_self * 0.0, info_self * 2.0):
        k, raw = tv.adapt_k(x, c, s, info0, P)
        assert k.dtype == torch.int64 and raw.dtype == torch.bool
        for j, i in enumerate(idx):
            kr, rr = rv.adapt_k(imgs[i], cols[i], skies[i], float(info0[j]), P)
            assert int(k[j]) == kr and np.array_equal(raw[j].numpy(), rr), (i, float(info0[j]))


def test_adapt_k_random_vs_reference_all_branches():
    rng = np.random.default_rng(9)
    imgs, cols = random_images(rng, 8, 16, 20)
    skies = [0, 2, 8, 15, 0, 3, 16, 1]
    x, c, s = to_tensor(list(imgs)), torch.from_numpy(cols), longs(skies)
    base = tv.raw_fraction(tv.raw_mask(x, c, torch.full((8,), 4), s), s)
    seen = set()
    for scale in (0.0, 0.1, 0.3, 0.5, 0.9, 1.0, 1.5, 3.0, 1e3):
        info0 = base * scale
        k, raw = tv.adapt_k(x, c, s, info0, P)
        for i in range(8):
            kr, rr = rv.adapt_k(imgs[i], tuple(int(v) for v in cols[i]), skies[i], float(info0[i]), P)
            assert int(k[i]) == kr and np.array_equal(raw[i].numpy(), rr), (scale, i)
            seen.add(kr)
    assert P.video_k_min in seen and P.video_k_max in seen and len(seen) >= 4


# ----------------------------------------------------------------------------------------
# Batch invariance, empty batches, immutability, modules, errors
# ----------------------------------------------------------------------------------------

def test_empty_batch():
    x = torch.zeros((0, 3, 8, 9), dtype=torch.uint8)
    c = torch.zeros((0, 3), dtype=torch.uint8)
    s = torch.zeros(0, dtype=torch.int64)
    m = torch.zeros((0, 8, 9), dtype=torch.bool)
    assert tv.raw_mask(x, c, s, s).shape == (0, 8, 9)
    assert tv.raw_fraction(m, s).shape == (0,)
    assert tv.density(m, s).shape == (0,)
    assert tv.remove_bushy(m, s, P).shape == (0, 8, 9)
    assert tv.canny_binary(m, s, P).shape == (0, 8, 9)
    h, b = tv.hough_input(m, s, P)
    assert h.shape == (0, 8, 9) and b.shape == (0,)
    k, r = tv.adapt_k(x, c, s, torch.zeros(0, dtype=torch.float64), P)
    assert k.shape == (0,) and r.shape == (0, 8, 9)
    assert tv.VegetationMask(P)(x, c, s).shape == (0, 8, 9)


def test_modules():
    rng = np.random.default_rng(15)
    imgs, cols = random_images(rng, 4, 20, 25)
    x, c, s = to_tensor(list(imgs)), torch.from_numpy(cols), longs([0, 3, 7, 19])
    vm, hm = tv.VegetationMask(P), tv.HoughInput(P)
    assert isinstance(vm, torch.nn.Module) and isinstance(hm, torch.nn.Module)
    veg = vm(x, c, s)
    k = torch.full((4,), P.veg_tol)
    assert torch.equal(veg, tv.remove_bushy(tv.raw_mask(x, c, k, s), s, P))
    k2 = longs([3, 5, 7, 9])
    assert torch.equal(vm(x, c, s, k2), tv.remove_bushy(tv.raw_mask(x, c, k2, s), s, P))
    h, b = hm(veg, s)
    h2, b2 = tv.hough_input(veg, s, P)
    assert torch.equal(h, h2) and torch.equal(b, b2)
    assert tv.VegetationMask().params == Params()


def test_errors_on_wrong_shapes_and_dtypes():
    x = torch.zeros((2, 3, 4, 5), dtype=torch.uint8)
    c = torch.zeros((2, 3), dtype=torch.uint8)
    s = torch.zeros(2, dtype=torch.int64)
    k = torch.full((2,), 4)
    m = torch.zeros((2, 4, 5), dtype=torch.bool)
    info0 = torch.zeros(2, dtype=torch.float64)
    with pytest.raises(ValueError):
        tv.lab(x.float())
    with pytest.raises(ValueError):
        tv.lab(x[0])
    with pytest.raises(TypeError):
        tv.lab(x.numpy())
    with pytest.raises(ValueError):
        tv.raw_mask(x, c.long(), k, s)
    with pytest.raises(ValueError):
        tv.raw_mask(x, c[:1], k, s)
    with pytest.raises(ValueError):
        tv.raw_mask(x, torch.zeros((2, 4), dtype=torch.uint8), k, s)
    with pytest.raises(ValueError):
        tv.raw_mask(x, c, k[:1], s)
    with pytest.raises(ValueError):
        tv.raw_mask(x, c, k.bool(), s)
    with pytest.raises(ValueError):
        tv.raw_mask(x, c, k, s.double())
    with pytest.raises(ValueError):
        tv.raw_mask(x, c, k, s[:1])
    with pytest.raises(ValueError):
        tv.remove_bushy(m.to(torch.uint8), s, P)
    with pytest.raises(ValueError):
        tv.remove_bushy(m[0], s, P)
    with pytest.raises(ValueError):
        tv.canny_binary(m.float(), s, P)
    with pytest.raises(ValueError):
        tv.canny_binary(m, s.float(), P)
    with pytest.raises(TypeError):
        tv.canny_binary(m, s, {"canny_low": 100})
    with pytest.raises(ValueError):
        tv.hough_input(m, s[:1], P)
    with pytest.raises(ValueError):
        tv.density(m.long(), s)
    with pytest.raises(ValueError):
        tv.raw_fraction(m, s.float())
    with pytest.raises(ValueError):
        tv.adapt_k(x, c, s, info0.long(), P)
    with pytest.raises(ValueError):
        tv.adapt_k(x, c, s, info0[:1], P)
    with pytest.raises(TypeError):
        tv.adapt_k(x, c, s, info0, None)




@pytest.mark.parametrize(("k_min", "k_max"), [(3, 13), (1, 20), (0, 5)])
def test_min_k_equals_the_box_test_at_every_bound(k_min: int, k_max: int):
    """The binary search's smallest admitting k equals section 3.2's box test
    ``fl(c - k) <= v <= fl(c + k)`` tried at every k, on random LAB values and on values
    exactly at, and one ulp either side of, every bound ``fl(c +- k)``, and at the colour itself."""
    gen = torch.Generator().manual_seed(0)
    n, p = 3, 4000
    c = torch.rand((n, 3), generator=gen, dtype=torch.float64) * 200 - 100
    c[0] = torch.tensor([50.123456789, -3.3, 7.0], dtype=torch.float64)
    lab = torch.rand((n, 3, p), generator=gen, dtype=torch.float64) * 256 - 128
    ks = torch.arange(k_min, k_max + 1, dtype=torch.float64)
    for i in range(n):
        for ch in range(3):
            b = torch.cat([c[i, ch] + ks, c[i, ch] - ks])
            at = torch.cat([b, torch.nextafter(b, b + 1), torch.nextafter(b, b - 1), c[i, ch].view(1)])
            # the other channels at the colour itself, so that this channel's bound decides
            span = slice(ch * 1000, ch * 1000 + at.numel())
            lab[i, :, span] = c[i].view(3, 1)
            lab[i, ch, span] = at
    before = lab.clone()
    eager = tv._min_k(lab, c, k_min, k_max)
    boxes = torch.stack([((c.unsqueeze(2) - k <= lab) & (lab <= c.unsqueeze(2) + k)).all(dim=1)
                         for k in range(k_min, k_max + 1)], dim=2)  # (n, P, n_k)
    none = torch.full(boxes.shape[:2] + (1,), True)
    expected = torch.cat([boxes, none], dim=2).to(torch.int8).argmax(dim=2) + k_min  # first admitting k
    assert torch.equal(eager, expected)
    assert torch.equal(lab, before)
    assert {int(eager.min()), int(eager.max())} == {k_min, k_max + 1}


@pytest.mark.parametrize("rgb", [(80, 120, 60), (0, 0, 0), (255, 255, 255), (128, 128, 128)])
def test_min_k_table_equals_min_k_of_every_colour(rgb):
    """The pruned table (only blocks whose LAB bounds meet the largest box are evaluated) ==
    _min_k of all 2**24 colours of the shared table, for a crop green, the two ends of the
    cube and a grey (boxes touching L = 0, L = 100 and a = b = 0)."""
    from torchrow.core.tables import lab_table_torch, pack_rgb

    p = Params()
    color = torch.tensor([rgb], dtype=torch.uint8)
    got = tv.min_k_table(color, p)
    assert got.shape == (1, 1 << 24) and got.dtype == torch.uint8
    table = lab_table_torch("cpu")
    c = table[int(pack_rgb(color.numpy())[0])].view(1, 3)
    n_k = p.video_k_max - p.video_k_min + 1
    full = torch.empty(1 << 24, dtype=torch.uint8)
    step = 1 << 21
    for i in range(0, 1 << 24, step):
        full[i:i + step] = (tv._min_k(table[i:i + step].t().unsqueeze(0), c, p.video_k_min, p.video_k_max)[0]
                            - p.video_k_min).to(torch.uint8)
    assert torch.equal(got[0], full)
    assert 0 < int((full < n_k).sum()) < (1 << 24) // 4  # the pruning had both kinds of block


def test_min_k_table_batch_empty_and_errors():
    p = Params()
    two = tv.min_k_table(torch.tensor([[80, 120, 60], [40, 90, 30]], dtype=torch.uint8), p)
    one = tv.min_k_table(torch.tensor([[40, 90, 30]], dtype=torch.uint8), p)
    assert torch.equal(two[1], one[0]) and not torch.equal(two[0], two[1])
    assert tv.min_k_table(torch.zeros((0, 3), dtype=torch.uint8), p).shape == (0, 1 << 24)
    with pytest.raises(ValueError, match=r"color: expected a uint8 tensor of shape \(S, 3\), got torch.uint8 \(3,\)"):
        tv.min_k_table(torch.zeros(3, dtype=torch.uint8), p)
    with pytest.raises(ValueError, match="uint8"):
        tv.min_k_table(torch.zeros((1, 3), dtype=torch.int64), p)
    with pytest.raises(ValueError, match="video_k_max - video_k_min must be < 255"):
        tv.min_k_table(torch.zeros((1, 3), dtype=torch.uint8), Params(video_k_min=0, video_k_start=0, video_k_max=255))
