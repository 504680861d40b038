"""Tests of ``torchrow.core.params.Params`` (ALGORITHM.md "Parameters") and ``torchrow.core.io``
(section 0: loading, conversion to 8-bit RGB, resizing to the working width)."""

from __future__ import annotations

import dataclasses
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchrow.core.io import ImageError, load_image, resize_to_width, to_rgb8, working_size
from torchrow.core.params import Params

# ----------------------------------------------------------------------------------------
# Params
# ----------------------------------------------------------------------------------------

# The table at the top of ALGORITHM.md (bands derived from W are checked separately).
SPEC_DEFAULTS = {
    "n_rows": 5,
    "hough_every": 5,
    "bushy_ratio": 0.1,
    "crda_sigma": 0.3,
    "horizon_angle": 0.2,
    "min_angle_diff": 0.1,
    "color_tol": 6,
    "n_colors": 10,
    "veg_tol": 4,
    "max_outliers": 5,
    "outlier_ratio": 1.25,
    "outlier_min_px": 20,
    "theta_step": 1,
    "horizontal_excl": 25,
    "angle_excl": 10,
    "track_band": 10,
    "ransac_trials": 1000,
    "ransac_threshold": 1.0,
    "ransac_min_points": 20,
    "ransac_max_points": 700,
    "ransac_subsample": 500,
    "seed": 0,
    "image_width": 320,
    "video_width": 500,
    # constants the spec writes inline in the stages
    "sky_blur": (9, 3),
    "sky_median": 5,
    "sky_lap_max": 4,
    "sky_erode": (9, 3),
    "sky_col_median": 19,
    "sky_min_zero_row": 20,
    "bushy_erode": (2, 3),
    "canny_low": 100,
    "canny_high": 200,
    "video_k_start": 4,
    "video_k_min": 3,
    "video_k_max": 13,
    "video_shrink_above": 2.0,
    "video_grow_below": 1.2,
    "singular_tol": 1e-9,
    "subsample_hash": 2654435761,
}


def test_defaults_equal_the_spec_table():
    p = Params()
    for name, value in SPEC_DEFAULTS.items():
        assert getattr(p, name) == value, name
    assert p.hough_band is None and p.ransac_band is None and p.ransac_band_bushy is None
    assert p.n_theta == 180


def test_derived_bands():
    p = Params()
    assert p.hough_band_px(320) == 10
    assert p.ransac_band_px(320, False) == 16
    assert p.ransac_band_px(320, True) == 32
    assert p.hough_band_px(500) == 16  # int(500 / 30) truncates
    assert p.ransac_band_px(500, False) == 25 and p.ransac_band_px(500, True) == 50
    assert p.hough_band_px(29) == 0
    q = Params(hough_band=7, ransac_band=3, ransac_band_bushy=9)
    assert q.hough_band_px(320) == 7 and q.ransac_band_px(320, False) == 3 and q.ransac_band_px(320, True) == 9


@pytest.mark.parametrize(("field", "value"), [
    ("n_rows", 0),
    ("n_rows", -3),
    ("veg_tol", -1),
    ("color_tol", -1),
    ("color_tol", float("nan")),
    ("color_tol", float("inf")),
    ("theta_step", 7),
    ("theta_step", 0),
    ("sky_median", 4),
    ("sky_col_median", 18),
    ("ransac_threshold", 0.0),
    ("crda_sigma", 0.0),
    ("ransac_subsample", 701),
    ("hough_band", -1),
    ("sky_blur", (9,)),
    ("sky_erode", (0, 3)),
    ("video_k_start", 14),
    ("image_width", 0),
    ("seed", -1),
    # issue 11: keys would tie (0, even) or overflow the 32-bit hash, and the paths disagreed
    ("subsample_hash", 0),
    ("subsample_hash", 2**32),
    ("subsample_hash", 2**70),
    ("subsample_hash", 2654435760),
    # issue 11: parameters whose tensor-path cost explodes have a documented range
    ("sky_median", 31),
    ("sky_median", 255),
    ("sky_blur", (1000, 1000)),
    ("color_tol", 0.0),
    ("image_width", 4000 + 97),
    ("video_width", 10**6),
    ("max_pixels", 0),
    ("max_pixels", 1 << 30),
    ("ransac_trials", 10**9),
    ("n_colors", 10**9),
    ("n_rows", 1000),
    ("video_k_max", 10**9),
    # issue 26: values outside int64 (tensor path) or absurdly large ones (a loop per unit)
    ("ransac_min_points", 2**63),
    ("angle_excl", 2**63),
    ("horizontal_excl", 2**63),
    ("track_band", 2**63),
    ("track_band", 20000),
    ("hough_every", 10**30),
    ("bushy_ratio", 1e30),
    ("bushy_ratio", 10**30),
    ("outlier_min_px", 10**400),
    ("hough_band", 10**30),
])
def test_invalid_values_raise_naming_the_field(field, value):
    with pytest.raises(ValueError) as info:
        Params(**{field: value})
    msg = str(info.value)
    assert field in msg
    assert "\n" not in msg


@pytest.mark.parametrize(("field", "value"), [
    ("n_rows", 2.5),
    ("n_rows", True),
    ("veg_tol", True),
    ("ransac_band", 2.5),
    ("subsample_hash", 1.5),
    ("subsample_hash", "x"),
    ("color_tol", "6"),
    ("sky_blur", 9),
    ("sky_blur", (9, 3.0)),
])
def test_wrong_kinds_raise_type_error_naming_the_field(field, value):
    with pytest.raises(TypeError) as info:
        Params(**{field: value})
    assert field in str(info.value) and "\n" not in str(info.value)


def test_values_are_normalised_so_equal_params_hash_equal():
    import numpy as np

    p = Params(n_rows=np.int64(4), sky_blur=[9, 3], subsample_hash=np.uint32(2654435761))
    assert type(p.n_rows) is int and p.sky_blur == (9, 3) and type(p.subsample_hash) is int
    assert p == Params(n_rows=4) and hash(p) == hash(Params(n_rows=4))


def test_replace_validates_and_copies():
    p = Params()
    q = p.replace(n_rows=3, veg_tol=6)
    assert (q.n_rows, q.veg_tol) == (3, 6) and (p.n_rows, p.veg_tol) == (5, 4)
    with pytest.raises(ValueError, match="n_rows"):
        p.replace(n_rows=0)
    assert Params(theta_step=2).n_theta == 90


def test_params_frozen_and_hashable():
    p = Params()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.n_rows = 3  # type: ignore[misc]
    assert p == Params() and hash(p) == hash(Params())
    assert p != Params(n_rows=4)


def test_every_numeric_field_has_a_bound_within_int64_and_float64():
    """Issue 26: no integer (or float) of any size reaches the tensor path; ``10**30`` is refused
    by every numeric field, naming it."""
    from torchrow.core.params import _RULES

    for f in dataclasses.fields(Params):
        rule = _RULES[f.name]
        if rule.kind == "choice":
            continue
        assert rule.lo is not None and rule.hi is not None and -(2**63) <= rule.lo <= rule.hi < 2**63, f.name
        bad = (10**30, 10**30) if rule.kind == "pair" else (10**30,) if rule.kind == "ints" else 10**30
        with pytest.raises(ValueError, match=f.name):
            Params(**{f.name: bad})


def test_float_fields_hold_floats():
    p = Params(bushy_ratio=0, color_tol=6)
    assert type(p.bushy_ratio) is float and type(p.color_tol) is float and p == Params(bushy_ratio=0.0, color_tol=6.0)


def test_valid_edge_values_are_accepted():
    Params(veg_tol=0, bushy_ratio=0.0, color_tol=1.0, theta_step=180, sky_median=15, subsample_hash=1, n_rows=1, seed=2**63 - 1,
           ransac_subsample=700, video_k_min=4, video_k_start=4, video_k_max=4)


# ----------------------------------------------------------------------------------------
# to_rgb8 conversion rules
# ----------------------------------------------------------------------------------------

def test_to_rgb8_rules():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    out = to_rgb8(rgb)
    assert out.dtype == np.uint8 and out.shape == (5, 7, 3) and np.array_equal(out, rgb)
    grey = rgb[:, :, 0]
    assert np.array_equal(to_rgb8(grey), np.repeat(grey[:, :, None], 3, 2))
    assert np.array_equal(to_rgb8(grey[:, :, None]), np.repeat(grey[:, :, None], 3, 2))
    rgba = np.dstack([rgb, rng.integers(0, 256, (5, 7), dtype=np.uint8)])
    assert np.array_equal(to_rgb8(rgba), rgb)  # alpha dropped, no compositing
    assert to_rgb8(rgb[:, ::-1]).flags.c_contiguous


def test_to_rgb8_uint16_rule_exhaustive():
    v = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    out = to_rgb8(v)
    assert out.shape == (256, 256, 3) and out.dtype == np.uint8
    exact = np.floor(v.astype(np.float64) / 257 + 0.5)  # (v + 128) // 257 = round(v / 257)
    assert np.array_equal(out[:, :, 0], exact.astype(np.uint8))
    w = np.arange(256, dtype=np.uint16)
    assert np.array_equal(to_rgb8((w * 257).reshape(1, -1))[0, :, 0], w.astype(np.uint8))  # inverse of v*257


@pytest.mark.parametrize("bad", [
    np.zeros((0, 4, 3), np.uint8),
    np.zeros((4, 0), np.uint8),
    np.zeros((4, 4, 3), np.float32),
    np.zeros((4, 4, 3), np.int16),
    np.zeros((4, 4, 2), np.uint8),
    np.zeros((4,), np.uint8),
    np.zeros((1, 4, 4, 3), np.uint8),
    [[1, 2, 3]],
])
def test_to_rgb8_rejects(bad):
    with pytest.raises(ImageError) as info:
        to_rgb8(bad)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------------------
# Resizing
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize(("w0", "h0"), [(640, 480), (333, 257), (1280, 720), (100, 77), (321, 999)])
def test_resize_rule(w0, h0):
    rgb = np.random.default_rng(w0).integers(0, 256, (h0, w0, 3), dtype=np.uint8)
    h = int(h0 * 320 / w0)
    out = resize_to_width(rgb, 320)
    assert out.shape == (h, 320, 3)
    assert np.array_equal(out, cv2.resize(rgb, (320, h), interpolation=cv2.INTER_AREA))
    assert working_size(w0, h0, 320) == (320, h)


def test_resize_truncates_the_height():
    # 257 * 320 / 333 = 246.97: int() truncates to 246 (rounding would give 247)
    assert working_size(333, 257, 320) == (320, 246)
    assert working_size(1280, 720, 500) == (500, 281)  # 281.25


def test_resize_is_a_no_op_at_the_working_width():
    rgb = np.zeros((17, 320, 3), np.uint8)
    assert resize_to_width(rgb, 320) is rgb
    assert working_size(320, 17, 320) == (320, 17)


def test_resize_too_flat_raises():
    with pytest.raises(ImageError):
        working_size(1000, 1, 320)


# ----------------------------------------------------------------------------------------
# load_image
# ----------------------------------------------------------------------------------------

def _one_line(exc: BaseException) -> bool:
    return bool(str(exc)) and "\n" not in str(exc)


def test_load_missing_file(tmp_path):
    with pytest.raises(ImageError) as info:
        load_image(tmp_path / "nope.jpg")
    assert _one_line(info.value)
    with pytest.raises(ImageError):
        load_image(tmp_path)  # a directory is not a file


def test_load_empty_file(tmp_path):
    p = tmp_path / "empty.jpg"
    p.write_bytes(b"")
    with pytest.raises(ImageError) as info:
        load_image(p)
    assert _one_line(info.value)


def test_load_garbage_file(tmp_path):
    p = tmp_path / "garbage.png"
    p.write_bytes(b"this is not an image\n" * 10)
    with pytest.raises(ImageError) as info:
        load_image(p)
    assert _one_line(info.value)


def _write_jpg(path: Path, rgb: np.ndarray) -> None:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    path.write_bytes(buf.tobytes())


def test_load_truncated_jpeg(tmp_path):
    src = tmp_path / "full.jpg"
    _write_jpg(src, np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8))
    trunc = tmp_path / "trunc.jpg"
    trunc.write_bytes(src.read_bytes()[:300])
    with pytest.raises(ImageError) as info:
        load_image(trunc)
    assert _one_line(info.value)


@pytest.mark.data
def test_load_truncated_real_jpeg(crbd_dir, tmp_path):
    src = sorted((crbd_dir / "Images").glob("crop_row_001.*"))[0]
    trunc = tmp_path / "trunc.JPG"
    trunc.write_bytes(src.read_bytes()[:300])
    with pytest.raises(ImageError) as info:
        load_image(trunc)
    assert _one_line(info.value)


def test_load_both_extension_cases(tmp_path):
    rgb = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    lower = tmp_path / "a.jpg"
    _write_jpg(lower, rgb)
    upper = tmp_path / "b.JPG"
    shutil.copy(lower, upper)
    a, b = load_image(lower), load_image(upper)
    assert a.shape == (48, 64, 3) and a.dtype == np.uint8 and np.array_equal(a, b)
    ref = cv2.cvtColor(cv2.imread(str(lower), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.array_equal(a, ref)  # RGB order, not OpenCV's BGR


def test_load_png_is_rgb_and_lossless(tmp_path):
    rgb = np.random.default_rng(2).integers(0, 256, (30, 40, 3), dtype=np.uint8)
    p = tmp_path / "x.png"
    cv2.imwrite(str(p), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert np.array_equal(load_image(p), rgb)


def test_load_grey_rgba_and_16_bit_png(tmp_path):
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    grey = rgb[:, :, 0]
    cv2.imwrite(str(tmp_path / "g.png"), grey)
    assert np.array_equal(load_image(tmp_path / "g.png"), np.repeat(grey[:, :, None], 3, 2))
    alpha = rng.integers(0, 256, (30, 40), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), np.dstack([cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), alpha]))
    assert np.array_equal(load_image(tmp_path / "a.png"), rgb)
    rgb16 = np.clip(rgb.astype(np.int64) * 257 + rng.integers(-128, 129, rgb.shape), 0, 65535).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "w.png"), cv2.cvtColor(rgb16, cv2.COLOR_RGB2BGR))
    assert np.array_equal(load_image(tmp_path / "w.png"), rgb)


def test_load_with_width_resizes(tmp_path):
    rgb = np.random.default_rng(4).integers(0, 256, (257, 333, 3), dtype=np.uint8)
    p = tmp_path / "r.png"
    cv2.imwrite(str(p), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    out = load_image(p, width=320)
    assert out.shape == (246, 320, 3)
    assert np.array_equal(out, cv2.resize(rgb, (320, 246), interpolation=cv2.INTER_AREA))
    assert np.array_equal(load_image(str(p)), rgb)  # str paths work, no width: untouched


@pytest.mark.data
def test_load_crbd_both_extension_cases(crbd_dir):
    images = sorted((crbd_dir / "Images").iterdir())
    upper = next(p for p in images if p.suffix == ".JPG")
    lower = next(p for p in images if p.suffix == ".jpg")
    for p in (upper, lower):
        img = load_image(p, width=320)
        assert img.shape == (240, 320, 3) and img.dtype == np.uint8
        ref = cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        assert np.array_equal(img, ref)  # already 320 wide: no resize


def _jpeg_with_exif_orientation(rgb: np.ndarray, orientation: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    data = buf.tobytes()
    tiff = b"MM\x00\x2a\x00\x00\x00\x08" + struct.pack(">H", 1)
    tiff += struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack(">I", 0)
    app1 = b"Exif\x00\x00" + tiff
    return data[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + data[2:]


def test_load_applies_exif_orientation_like_cv2_imread(tmp_path):
    rgb = np.zeros((20, 40, 3), np.uint8)
    rgb[:, :20] = 255
    p = tmp_path / "rotated.jpg"
    p.write_bytes(_jpeg_with_exif_orientation(rgb, 6))  # 6: rotate 90 degrees clockwise to view
    ref = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)
    assert ref.shape == (40, 20, 3)  # OpenCV's reader honours the tag
    assert np.array_equal(load_image(p), ref)
