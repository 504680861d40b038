"""Batched tensor sky removal (torchrow.functional.sky) against OpenCV and the reference."""

from __future__ import annotations

import time
import warnings

import cv2
import numpy as np
import pytest
import scipy.signal
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchrow.core.io import load_image
from torchrow.core.params import Params
from torchrow.functional import kernels as K
from torchrow.functional import sky as F
from torchrow.reference import sky as R

P = Params()
HYP = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SIZES = [(1, 1), (1, 2), (2, 1), (2, 2), (1, 7), (7, 1), (2, 9), (3, 3), (3, 4), (4, 3), (4, 4),
         (3, 17), (5, 9), (9, 5), (13, 31), (31, 2), (2, 31), (47, 33), (240, 320)]
VALUE_RANGES = [(0, 256), (0, 3), (250, 256), (100, 104)]


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Results never depend on the thread count; one thread keeps these many small tensor
    calls fast on a shared, oversubscribed machine (OpenMP spinning), restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _rng(*key: int) -> np.random.Generator:
    return np.random.default_rng(list(key))


def _planes(b: int, h: int, w: int, lo: int = 0, hi: int = 256, seed: int = 0) -> np.ndarray:
    return _rng(b, h, w, lo, hi, seed).integers(lo, hi, (b, h, w), dtype=np.uint8)


def _to_nchw(rgb: np.ndarray) -> torch.Tensor:
    """``(B, H, W, 3)`` or ``(H, W, 3)`` uint8 NumPy -> ``(B, 3, H, W)`` tensor."""
    a = rgb if rgb.ndim == 4 else rgb[None]
    return torch.from_numpy(np.ascontiguousarray(a.transpose(0, 3, 1, 2)))


def _per_image(fn, planes: np.ndarray) -> np.ndarray:
    return np.stack([fn(p) for p in planes]) if len(planes) else planes.copy()


def _sky_scene(h: int = 240, w: int = 320, rows: int = 80, colour=(100, 150, 230),
               seed: int = 0) -> np.ndarray:
    """Noisy ground under a flat sky of ``rows`` rows with a soft gradient."""
    rng = _rng(h, w, rows, seed)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    grad = (np.arange(rows)[:, None] * 20 // max(rows, 1)).astype(np.int64)
    sky = np.clip(np.array(colour)[None, None, :] + grad[:, :, None], 0, 255)
    rgb[:rows] = np.broadcast_to(sky, (rows, w, 3)).astype(np.uint8)
    return rgb


# ------------------------------------------------------------------------------------------
# border tables
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", range(1, 8))
def test_border_index_is_opencv_border_interpolate(n):
    for mode, cv_mode in (("reflect101", cv2.BORDER_REFLECT_101), ("replicate", cv2.BORDER_REPLICATE)):
        idx = K._border_index(n, 9, 11, mode, torch.device("cpu")).tolist()
        assert idx == [cv2.borderInterpolate(p, n, cv_mode) for p in range(-9, n + 11)]


# ------------------------------------------------------------------------------------------
# gray
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SIZES)
def test_gray_equals_cv2(shape):
    rgb = _rng(*shape).integers(0, 256, (3,) + shape + (3,), dtype=np.uint8)
    out = F.gray(_to_nchw(rgb))
    assert out.dtype == torch.uint8 and out.shape == (3,) + shape
    exp = np.stack([cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) for a in rgb])
    assert np.array_equal(out.numpy(), exp)


def test_gray_formula_and_rgb_order():
    rgb = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]]], np.uint8)
    out = F.gray(_to_nchw(rgb))[0, 0].tolist()
    assert out == [(9798 * 255 + 16384) >> 15, (19235 * 255 + 16384) >> 15, (3735 * 255 + 16384) >> 15, 255]


# ------------------------------------------------------------------------------------------
# box blur
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SIZES)
@pytest.mark.parametrize("ksize", [(9, 3), (3, 9), (1, 7), (5, 5), (4, 5), (2, 2), (4, 4), (8, 2), (17, 16)])
def test_box_blur_equals_cv2(shape, ksize):
    for lo, hi in VALUE_RANGES:
        x = _planes(3, *shape, lo, hi)
        out = F.box_blur(torch.from_numpy(x), ksize)
        assert out.dtype == torch.uint8 and out.shape == x.shape
        assert np.array_equal(out.numpy(), _per_image(lambda a: cv2.blur(a, ksize), x)), (lo, hi)


def _window_sum_images(area_w: int, area_h: int, total: np.ndarray) -> np.ndarray:
    """One ``area_h x area_w`` image per total, its pixels summing to that total."""
    area = area_w * area_h
    q, r = np.divmod(total, area)
    px = q[:, None] + (np.arange(area)[None, :] < r[:, None])
    return px.reshape(-1, area_h, area_w).astype(np.uint8)


@pytest.mark.parametrize("ksize", [(9, 3), (3, 3), (5, 5), (4, 4), (2, 2), (8, 8), (16, 16), (17, 16)])
def test_box_blur_division_for_every_window_sum(ksize):
    """Every possible sum of the window at the centre pixel of a ``h x w`` image, against cv2."""
    kw, kh = ksize
    area = kw * kh
    totals = np.arange(area * 255 + 1)
    imgs = _window_sum_images(kw, kh, totals)
    out = F.box_blur(torch.from_numpy(imgs), ksize)[:, kh // 2, kw // 2].numpy()
    exp = np.array([cv2.blur(a, ksize)[kh // 2, kw // 2] for a in imgs])
    assert np.array_equal(out, exp)
    if ksize == (9, 3):  # ALGORITHM.md: round half up of sum / 27
        assert np.array_equal(out, (totals + 13) // 27)


def test_box_blur_power_of_two_area_reproduces_opencv():
    """OpenCV 5.0 adds one too many for power-of-two areas: a black image blurs to 1 (2 x 1 box)."""
    x = torch.zeros((1, 4, 20), dtype=torch.uint8)
    assert np.array_equal(F.box_blur(x, (2, 1)).numpy()[0], cv2.blur(np.zeros((4, 20), np.uint8), (2, 1)))


# ------------------------------------------------------------------------------------------
# median blur
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SIZES)
@pytest.mark.parametrize("k", [3, 5, 7])
def test_median_blur_equals_cv2(shape, k):
    for lo, hi in VALUE_RANGES:
        x = _planes(3, *shape, lo, hi, seed=k)
        out = F.median_blur(torch.from_numpy(x), k)
        assert out.dtype == torch.uint8 and out.shape == x.shape
        assert np.array_equal(out.numpy(), _per_image(lambda a: cv2.medianBlur(a, k), x)), (lo, hi)


def test_median_of_the_whole_window_is_numpy_median():
    """The centre pixel of a 5x5 image sees exactly its 25 values: many independent windows."""
    rng = _rng(25)
    for lo, hi in ((0, 256), (0, 2), (0, 5), (120, 124)):
        x = rng.integers(lo, hi, (20000, 5, 5), dtype=np.uint8)
        out = F.median_blur(torch.from_numpy(x), 5)[:, 2, 2].numpy()
        assert np.array_equal(out, np.sort(x.reshape(-1, 25), axis=1)[:, 12])


def test_median_selection_network_exhaustive_on_binary_3x3():
    """0-1 principle for the 3x3 network: all 512 binary windows."""
    bits = (np.arange(512)[:, None] >> np.arange(9)[None, :]) & 1
    x = torch.from_numpy(bits.reshape(512, 3, 3).astype(np.uint8))
    assert np.array_equal(F.median_blur(x, 3)[:, 1, 1].numpy(), (bits.sum(axis=1) >= 5).astype(np.uint8))


def test_median_blur_chunking_does_not_change_the_result(monkeypatch):
    x = torch.from_numpy(_planes(5, 37, 23, seed=3))
    full = F.median_blur(x, 5)
    for budget in (1, 27 * 3, 27 * 41, 27 * 41 * 2 + 5):  # row slabs of one image; several images
        monkeypatch.setattr(K, "MEDIAN_CHUNK_PIXELS_CPU", budget)
        assert torch.equal(F.median_blur(x, 5), full)


# ------------------------------------------------------------------------------------------
# Laplacian, erosion, column median
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SIZES)
def test_laplacian_equals_cv2(shape):
    for lo, hi in VALUE_RANGES:
        x = _planes(3, *shape, lo, hi, seed=1)
        out = F.laplacian(torch.from_numpy(x))
        assert out.dtype == torch.uint8 and out.shape == x.shape
        assert np.array_equal(out.numpy(), _per_image(lambda a: cv2.Laplacian(a, cv2.CV_8U, ksize=1), x))


@pytest.mark.parametrize("shape", SIZES)
@pytest.mark.parametrize("ksize", [(9, 3), (2, 3), (3, 2), (1, 1), (4, 4), (1, 5)])
def test_erode_rect_equals_cv2(shape, ksize):
    kernel = np.ones((ksize[1], ksize[0]), np.uint8)
    x = _planes(3, *shape, seed=2)
    out = F.erode_rect(torch.from_numpy(x), ksize)
    assert out.dtype == torch.uint8
    assert np.array_equal(out.numpy(), _per_image(lambda a: cv2.erode(a, kernel), x))
    for p in (0.5, 0.9):
        m = _rng(*shape, int(p * 10)).random((3,) + shape) < p
        out = F.erode_rect(torch.from_numpy(m), ksize)
        assert out.dtype == torch.bool
        exp = _per_image(lambda a: cv2.erode(a.astype(np.uint8), kernel), m)
        assert np.array_equal(out.numpy(), exp.astype(bool))


def _medfilt_columns(m: np.ndarray, length: int) -> np.ndarray:
    out = np.empty_like(m)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for x in range(m.shape[1]):
            out[:, x] = scipy.signal.medfilt(m[:, x], length)
    return out


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (9, 4), (19, 2), (20, 5), (40, 7), (240, 16)])
@pytest.mark.parametrize("length", [1, 3, 19])
def test_column_median_equals_reference_and_scipy(shape, length):
    for p in (0.2, 0.5, 0.8):
        m = (_rng(*shape, length, int(p * 10)).random((3,) + shape) < p).astype(np.uint8)
        out = F.column_median(torch.from_numpy(m), length)
        assert out.dtype == torch.uint8
        ref = _per_image(lambda a: R.column_median(a, length), m)
        assert np.array_equal(out.numpy(), ref)
        assert np.array_equal(ref, _per_image(lambda a: _medfilt_columns(a, length), m))
        outb = F.column_median(torch.from_numpy(m.astype(bool)), length)
        assert outb.dtype == torch.bool and np.array_equal(outb.numpy(), ref.astype(bool))


# ------------------------------------------------------------------------------------------
# hypothesis properties
# ------------------------------------------------------------------------------------------
small = dict(b=st.integers(0, 3), h=st.integers(1, 12), w=st.integers(1, 12),
             seed=st.integers(0, 2**31 - 1), levels=st.sampled_from([2, 4, 256]))


@HYP
@given(**small, kw=st.integers(1, 10), kh=st.integers(1, 10))
def test_property_box_blur_and_erode(b, h, w, seed, levels, kw, kh):
    x = _rng(seed).integers(0, levels, (b, h, w), dtype=np.uint8)
    t = torch.from_numpy(x)
    if kw * kh != 2:  # area 2: OpenCV's scalar loop truncates 256 to 0 (see box_blur's notes)
        assert np.array_equal(F.box_blur(t, (kw, kh)).numpy(), _per_image(lambda a: cv2.blur(a, (kw, kh)), x))
    kernel = np.ones((kh, kw), np.uint8)
    assert np.array_equal(F.erode_rect(t, (kw, kh)).numpy(), _per_image(lambda a: cv2.erode(a, kernel), x))
    assert torch.equal(t, torch.from_numpy(x))


@HYP
@given(**small, k=st.sampled_from([1, 3, 5]))
def test_property_median_and_laplacian(b, h, w, seed, levels, k):
    x = _rng(seed).integers(0, levels, (b, h, w), dtype=np.uint8)
    t = torch.from_numpy(x)
    assert np.array_equal(F.median_blur(t, k).numpy(), _per_image(lambda a: cv2.medianBlur(a, k), x))
    lap = _per_image(lambda a: cv2.Laplacian(a, cv2.CV_8U, ksize=1), x)
    assert np.array_equal(F.laplacian(t).numpy(), lap)


@HYP
@given(**small, length=st.sampled_from([1, 3, 5, 19]))
def test_property_column_median(b, h, w, seed, levels, length):
    m = (_rng(seed).integers(0, levels, (b, h, w)) == 0).astype(np.uint8)
    out = F.column_median(torch.from_numpy(m), length).numpy()
    assert np.array_equal(out, _per_image(lambda a: R.column_median(a, length), m))


@HYP
@given(b=st.integers(0, 3), h=st.integers(1, 40), w=st.integers(1, 24), seed=st.integers(0, 2**31 - 1),
       sky_rows=st.integers(0, 40))
def test_property_sky_mask_and_row(b, h, w, seed, sky_rows):
    rng = _rng(seed)
    rgb = rng.integers(0, 256, (b, h, w, 3), dtype=np.uint8)
    rgb[:, :sky_rows] = rng.integers(90, 93, (b, 1, 1, 3), dtype=np.uint8)  # flat sky on top
    t = _to_nchw(rgb)
    assert np.array_equal(F.horizon_mask(t, P).numpy(),
                          _per_image(lambda a: R.horizon_mask(a, P), rgb).astype(bool).reshape(b, h, w))
    ref = _per_image(lambda a: R.sky_mask(a, P), rgb).reshape(b, h, w)
    assert np.array_equal(F.sky_mask(t, P).numpy(), ref)
    assert F.sky_row(t, P).tolist() == [R.sky_row(a, P) for a in rgb]


# ------------------------------------------------------------------------------------------
# composed stages vs the reference
# ------------------------------------------------------------------------------------------
def _scenes() -> np.ndarray:
    imgs = [_sky_scene(rows=r, seed=r) for r in (0, 30, 80, 110, 150, 200)]
    imgs.append(_sky_scene(rows=80, colour=(0, 0, 255)))  # R = 0: never sky
    imgs.append(_sky_scene(rows=80, colour=(1, 1, 255)))
    imgs.append(np.full((240, 320, 3), (0, 0, 255), np.uint8))  # all blue
    imgs.append(np.zeros((240, 320, 3), np.uint8))  # black
    imgs.append(np.full((240, 320, 3), 90, np.uint8))  # uniform: all sky, reset (sky > H/2)
    return np.stack(imgs)


def test_sky_on_synthetic_scenes_equals_reference():
    rgb = _scenes()
    t = _to_nchw(rgb)
    mask = F.sky_mask(t, P)
    assert mask.dtype == torch.bool and mask.shape == (len(rgb), 240, 320)
    for i, a in enumerate(rgb):
        assert np.array_equal(F.horizon_mask(t[i:i + 1], P)[0].numpy(), R.horizon_mask(a, P).astype(bool))
        assert np.array_equal(mask[i].numpy(), R.sky_mask(a, P)), i
    rows = F.sky_row(t, P)
    ref = [R.sky_row(a, P) for a in rgb]
    assert rows.dtype == torch.int64 and rows.shape == (len(rgb),)
    assert rows.tolist() == ref
    assert ref[2] > 0 and ref[3] > 0  # the scenes do exercise a horizon


@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (5, 1), (2, 2), (3, 4), (4, 3), (21, 9), (22, 30),
                                   (60, 4)])
def test_sky_on_tiny_images_equals_reference(shape):
    rgb = _rng(*shape).integers(0, 256, (4,) + shape + (3,), dtype=np.uint8)
    rgb[1] = 90
    rgb[2, : shape[0] // 2] = (100, 150, 230)
    rgb[3] = 0
    t = _to_nchw(rgb)
    assert np.array_equal(F.sky_mask(t, P).numpy(), np.stack([R.sky_mask(a, P) for a in rgb]))
    assert F.sky_row(t, P).tolist() == [R.sky_row(a, P) for a in rgb]


def test_other_params_follow_the_reference():
    p = Params(sky_blur=(5, 5), sky_median=3, sky_lap_max=6, sky_erode=(3, 5), sky_col_median=9,
               sky_min_zero_row=10)
    rgb = _scenes()[:6]
    t = _to_nchw(rgb)
    assert np.array_equal(F.sky_mask(t, p).numpy(), np.stack([R.sky_mask(a, p) for a in rgb]))
    assert F.sky_row(t, p).tolist() == [R.sky_row(a, p) for a in rgb]


def test_chunking_does_not_change_the_result(monkeypatch):
    rgb = _scenes()
    t = _to_nchw(rgb)
    rows, mask, hor = F.sky_row(t, P), F.sky_mask(t, P), F.horizon_mask(t, P)
    for budget in (1, 240 * 320 * 3, 1 << 30):  # one image per chunk, 3 per chunk, all at once
        monkeypatch.setattr(F, "SKY_CHUNK_PIXELS_CPU", budget)
        assert torch.equal(F.sky_row(t, P), rows)
        assert torch.equal(F.sky_mask(t, P), mask)
        assert torch.equal(F.horizon_mask(t, P), hor)


def test_empty_batch():
    for h, w in ((240, 320), (1, 1)):
        t = torch.zeros((0, 3, h, w), dtype=torch.uint8)
        assert F.sky_row(t, P).shape == (0,) and F.sky_row(t, P).dtype == torch.int64
        assert F.sky_mask(t, P).shape == (0, h, w) and F.sky_mask(t, P).dtype == torch.bool
        assert F.horizon_mask(t, P).shape == (0, h, w)
        assert F.gray(t).shape == (0, h, w)
        g = torch.zeros((0, h, w), dtype=torch.uint8)
        for out in (F.box_blur(g, (9, 3)), F.median_blur(g, 5), F.laplacian(g), F.erode_rect(g, (9, 3)),
                    F.column_median(g, 19)):
            assert out.shape == (0, h, w) and out.dtype == torch.uint8


def test_non_contiguous_input():
    rgb = _scenes()[:3]
    t = _to_nchw(rgb)
    nc = torch.from_numpy(np.ascontiguousarray(rgb)).permute(0, 3, 1, 2)  # channels-last memory
    assert not nc.is_contiguous()
    assert torch.equal(F.sky_mask(nc, P), F.sky_mask(t, P))


def test_sky_row_module():
    mod = F.SkyRow(P)
    assert isinstance(mod, torch.nn.Module)
    t = _to_nchw(_scenes()[:5])
    assert torch.equal(mod(t), F.sky_row(t, P))
    assert torch.equal(F.SkyRow()(t), F.sky_row(t, Params()))
    assert "blur=(9, 3)" in repr(mod)


# ------------------------------------------------------------------------------------------
# input guards
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fn", [F.gray, lambda x: F.sky_row(x, P), lambda x: F.sky_mask(x, P),
                                lambda x: F.horizon_mask(x, P), F.SkyRow(P)])
def test_image_guards(fn):
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        fn(torch.zeros((3, 4, 5), dtype=torch.uint8))
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        fn(torch.zeros((1, 4, 4, 5), dtype=torch.uint8))
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        fn(torch.zeros((1, 3, 0, 5), dtype=torch.uint8))
    with pytest.raises(ValueError, match="uint8"):
        fn(torch.zeros((1, 3, 4, 5), dtype=torch.float32))
    with pytest.raises(TypeError, match=r"torch\.Tensor"):
        fn(np.zeros((1, 3, 4, 5), np.uint8))


def test_plane_guards():
    g = torch.zeros((1, 4, 5), dtype=torch.uint8)
    for fn in (lambda x: F.box_blur(x, (9, 3)), lambda x: F.median_blur(x, 5), F.laplacian,
               lambda x: F.erode_rect(x, (9, 3)), lambda x: F.column_median(x, 19)):
        with pytest.raises(ValueError, match=r"\(B, H, W\)"):
            fn(torch.zeros((4, 5), dtype=torch.uint8))
        with pytest.raises(ValueError, match=r"\(B, H, W\)"):
            fn(torch.zeros((1, 1, 4, 5), dtype=torch.uint8))
        with pytest.raises(ValueError, match=r"\(B, H, W\)"):
            fn(torch.zeros((1, 4, 0), dtype=torch.uint8))
        with pytest.raises(ValueError, match="dtype"):
            fn(torch.zeros((1, 4, 5), dtype=torch.int32))
        with pytest.raises(TypeError, match=r"torch\.Tensor"):
            fn(np.zeros((1, 4, 5), np.uint8))
        fn(g)  # accepted
    for fn in (lambda x: F.box_blur(x, (9, 3)), lambda x: F.median_blur(x, 5), F.laplacian):
        with pytest.raises(ValueError, match="uint8"):
            fn(torch.zeros((1, 4, 5), dtype=torch.bool))
    with pytest.raises(ValueError, match="ksize"):
        F.box_blur(g, (0, 3))
    with pytest.raises(ValueError, match="ksize"):
        F.erode_rect(g, 3)
    with pytest.raises(ValueError, match="odd"):
        F.median_blur(g, 4)
    with pytest.raises(ValueError, match="odd"):
        F.median_blur(g, k=0)
    with pytest.raises(ValueError, match="length"):
        F.column_median(g, 2)


# ------------------------------------------------------------------------------------------
# CRBD: every image, in batches, against the reference
# ------------------------------------------------------------------------------------------
def _crbd_images(crbd_dir) -> tuple[list[str], np.ndarray]:
    paths = sorted(p for p in (crbd_dir / "Images").iterdir()
                   if p.name.startswith("crop_row_") and p.suffix.lower() == ".jpg")
    imgs = [load_image(p, P.image_width) for p in paths]
    assert len({a.shape for a in imgs}) == 1, "CRBD images share one working size"
    return [p.name for p in paths], np.stack(imgs)


@pytest.fixture(scope="module")
def crbd(crbd_dir):
    return _crbd_images(crbd_dir)


@pytest.mark.data
def test_crbd_sky_row_and_mask_equal_reference(crbd):
    names, rgb = crbd
    assert len(names) == 281
    t = _to_nchw(rgb)
    rows = torch.cat([F.sky_row(t[i:i + 64], P) for i in range(0, len(t), 64)])
    masks = torch.cat([F.sky_mask(t[i:i + 64], P) for i in range(0, len(t), 64)])
    bad_rows, bad_masks = [], []
    for i, a in enumerate(rgb):
        ref_mask = R.sky_mask(a, P)
        if not np.array_equal(masks[i].numpy(), ref_mask):
            bad_masks.append(names[i])
        if i % 3 == 0 and int(rows[i]) != R.sky_row(a, P):  # sky_row redoes sky_mask: every 3rd
            bad_rows.append(names[i])
        # the row rule on the (checked) reference mask, for every image
        counts = ref_mask.sum(axis=1)
        y = np.flatnonzero(counts > a.shape[1] / 2)
        sky = int(y[-1]) if y.size else 0
        if int(rows[i]) != (0 if sky > a.shape[0] / 2 else sky):
            bad_rows.append(names[i])
    assert not bad_masks and not bad_rows, (bad_masks, bad_rows)
    assert (rows > 0).sum() > 50  # CRBD has plenty of horizons


@pytest.mark.data
def test_crbd_mixed_batch_equals_per_image(crbd):
    _names, rgb = crbd
    pick = rgb[[0, 7, 42, 100, 200]]
    extra = np.stack([_sky_scene(rows=70), np.full(rgb.shape[1:], (0, 0, 255), np.uint8),
                      np.zeros(rgb.shape[1:], np.uint8), np.full(rgb.shape[1:], (60, 120, 250), np.uint8)])
    mixed = np.concatenate([pick[:2], extra[:2], pick[2:], extra[2:]])
    t = _to_nchw(mixed)
    rows = F.sky_row(t, P)
    mask = F.sky_mask(t, P)
    for i, a in enumerate(mixed):
        assert int(rows[i]) == R.sky_row(a, P) == int(F.sky_row(t[i:i + 1], P)[0])
        assert np.array_equal(mask[i].numpy(), R.sky_mask(a, P))


@pytest.mark.data
def test_crbd_timing_is_reported(crbd, capsys):
    """Not an assertion on speed: prints ms/image for a batch of 64 vs 64 reference calls."""
    _, rgb = crbd
    t = _to_nchw(rgb[:64])
    F.sky_row(t[:2], P)
    t0 = time.perf_counter()
    F.sky_row(t, P)
    tensor_ms = (time.perf_counter() - t0) * 1000 / 64
    t0 = time.perf_counter()
    for a in rgb[:16]:
        R.sky_row(a, P)
    ref_ms = (time.perf_counter() - t0) * 1000 / 16
    with capsys.disabled():
        print(f"\nsky_row: tensor {tensor_ms:.1f} ms/image (batch 64), reference {ref_ms:.1f} ms/image")
