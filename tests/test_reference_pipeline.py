"""End-to-end tests of ``torchrow.reference.detect`` (ALGORITHM.md sections 0-9).

Covers: real CRBD images (result structure and invariants), a synthetic field with known
rows, degenerate images, bad inputs, the input conversion rules of ``torchrow.core.io``,
determinism and that the input array is never modified.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchrow.core.io import ImageError, resize_to_width
from torchrow.core.params import Params
from torchrow.core.results import REASONS, STATUSES, ImageResult
from torchrow.reference import detect

P = Params()
CRBD_SAMPLE = (1, 8, 43, 141)


def crbd_image(crbd_dir: Path, number: int) -> np.ndarray:
    hits = [h for h in sorted((crbd_dir / "Images").glob(f"crop_row_{number:03d}.*"))
            if h.suffix.lower() == ".jpg"]
    assert hits, f"crop_row_{number:03d} not found"
    return cv2.cvtColor(cv2.imread(str(hits[0]), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def check_invariants(res: ImageResult, params: Params = P) -> None:
    """What every result must satisfy whatever the image (section 9)."""
    assert res.status in STATUSES and res.status != "error"
    h = res.height
    assert 0 <= res.sky <= h / 2
    assert len(res.veg_color) == 3 and all(0 <= c <= 255 for c in res.veg_color)
    if res.status in ("ok", "invalid"):
        assert 2 <= res.n_rows <= params.n_rows
        assert len(res.rows) == res.n_rows == len(res.hough)
        assert res.vp is not None and all(math.isfinite(v) for v in res.vp)
        assert all(r.reason in REASONS for r in res.rows)
        assert all(r.valid == (r.reason == "") for r in res.rows)
        assert (res.status == "ok") == all(r.valid for r in res.rows)
        for r in res.rows:
            if r.reason == "no_support":
                assert math.isnan(r.a) and math.isnan(r.b) and r.hypothesis == -1
            else:
                assert 0 <= r.hypothesis < params.ransac_trials
            if r.valid:  # a valid row is never horizontal, so x = a*y + b is finite
                assert math.isfinite(r.a) and math.isfinite(r.b)
        excl = params.horizontal_excl
        for ln in res.hough:
            assert abs(ln.theta_index * params.theta_step - 90) >= excl and ln.weight > 0
        # held lines are pairwise at least angle_excl apart (section 5.1)
        js = [ln.theta_index * params.theta_step for ln in res.hough]
        assert all(abs(a - b) >= params.angle_excl for i, a in enumerate(js) for b in js[i + 1:])
    else:
        assert res.rows == [] and res.vp is None
    assert not res.valid or res.status == "ok"


# ----------------------------------------------------------------------------------------
# Real images
# ----------------------------------------------------------------------------------------

@pytest.mark.data
@pytest.mark.parametrize("number", CRBD_SAMPLE)
def test_detect_on_crbd(crbd_dir, number):
    rgb = crbd_image(crbd_dir, number)
    before = rgb.copy()
    res = detect(rgb, name=f"crop_row_{number:03d}")
    assert np.array_equal(rgb, before)  # input never modified
    assert (res.width, res.height) == (320, 240) and res.name == f"crop_row_{number:03d}"
    check_invariants(res)
    assert res.status in ("ok", "invalid")  # these images have clear crop rows
    assert sum(r.valid for r in res.rows) >= 2
    again = detect(rgb, name=f"crop_row_{number:03d}")
    assert again.to_record() == res.to_record()
    assert [r.hypothesis for r in again.rows] == [r.hypothesis for r in res.rows]


@pytest.mark.data
@pytest.mark.parametrize("number", CRBD_SAMPLE)
def test_detect_on_crbd_restart_rule(crbd_dir, number):
    """N is lowered by restarts (max_outliers dropped lines each) or when the Hough peaks run
    out; on these images they never run out, so outliers count the restarts exactly."""
    res = detect(crbd_image(crbd_dir, number))
    lowered = P.n_rows - res.n_rows
    assert lowered >= 0
    assert len(res.outliers) >= P.max_outliers * lowered
    assert len(res.outliers) < P.max_outliers * (lowered + 1)


@pytest.mark.data
def test_detect_resizes_to_the_working_width(crbd_dir):
    rgb = crbd_image(crbd_dir, 8)
    big = cv2.resize(rgb, (640, 480), interpolation=cv2.INTER_LINEAR)
    res = detect(big)
    assert (res.width, res.height) == (320, 240)
    assert res.to_record() == detect(resize_to_width(big, 320)).to_record()


@pytest.mark.data
def test_detect_non_contiguous_input(crbd_dir):
    rgb = crbd_image(crbd_dir, 43)
    flipped = rgb[:, ::-1]
    assert not flipped.flags.c_contiguous
    assert detect(flipped).to_record() == detect(np.ascontiguousarray(flipped)).to_record()


# ----------------------------------------------------------------------------------------
# A synthetic field with known rows
# ----------------------------------------------------------------------------------------

VP = (160.0, -60.0)
BOTTOM_X = (20, 90, 160, 230, 300)


def synthetic_field() -> np.ndarray:
    """Brown soil with five 3-px green rows converging to VP (above the image)."""
    img = np.empty((240, 320, 3), np.uint8)
    img[:] = (120, 90, 60)
    for xb in BOTTOM_X:
        x_top = int(round(VP[0] + (xb - VP[0]) * 60 / 299))  # x at y = 0 on the line VP -> (xb, 239)
        cv2.line(img, (x_top, 0), (xb, 239), (40, 160, 40), 3)
    return img


def test_synthetic_field_rows_are_found():
    res = detect(synthetic_field())
    check_invariants(res)
    assert res.status == "ok" and res.n_rows == 5 and res.outliers == []
    assert res.veg_color == (40, 160, 40) and not res.bushy and res.k == P.veg_tol
    assert abs(res.vp[0] - VP[0]) < 3 and abs(res.vp[1] - VP[1]) < 3
    found = sorted(r.x_at(239.0) for r in res.rows)
    assert all(abs(f - x) <= 3 for f, x in zip(found, BOTTOM_X)), found
    top = sorted(r.x_at(0.0) for r in res.rows)
    expected_top = [VP[0] + (x - VP[0]) * 60 / 299 for x in BOTTOM_X]
    assert all(abs(f - x) <= 3 for f, x in zip(top, expected_top)), top


def test_fewer_rows_asked():
    res = detect(synthetic_field(), P.replace(n_rows=3))
    check_invariants(res, P.replace(n_rows=3))
    assert res.status == "ok" and len(res.rows) == 3
    res = detect(synthetic_field(), P.replace(n_rows=1))
    assert res.status == "no_vp" and res.rows == [] and res.vp is None  # N < 2: no vanishing point


# ----------------------------------------------------------------------------------------
# Input conversion (torchrow.core.io rules)
# ----------------------------------------------------------------------------------------

def test_grey_inputs_are_replicated():
    grey = cv2.cvtColor(synthetic_field(), cv2.COLOR_RGB2GRAY)
    grey[:, ::7] = 200  # some texture so the result is not trivial
    ref = detect(np.repeat(grey[:, :, None], 3, axis=2)).to_record()
    assert detect(grey).to_record() == ref
    assert detect(grey[:, :, None]).to_record() == ref


def test_rgba_drops_alpha():
    rgb = synthetic_field()
    alpha = np.random.default_rng(0).integers(0, 256, rgb.shape[:2], dtype=np.uint8)
    rgba = np.dstack([rgb, alpha])
    assert detect(rgba).to_record() == detect(rgb).to_record()


def test_uint16_is_rounded_to_8_bit():
    rgb = synthetic_field()
    rng = np.random.default_rng(1)
    u16 = np.clip(rgb.astype(np.int64) * 257 + rng.integers(-128, 129, rgb.shape), 0, 65535).astype(np.uint16)
    assert np.array_equal(((u16.astype(np.int64) + 128) // 257).astype(np.uint8), rgb)
    assert detect(u16).to_record() == detect(rgb).to_record()
    # and a 16-bit grey image
    g16 = (rgb[:, :, 1].astype(np.uint16) * 257)
    assert detect(g16).to_record() == detect(np.repeat(rgb[:, :, 1:2], 3, axis=2)).to_record()


# ----------------------------------------------------------------------------------------
# Bad and degenerate inputs
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("bad", [
    np.zeros((0, 0, 3), np.uint8),
    np.zeros((0, 320, 3), np.uint8),
    np.zeros((240, 0), np.uint8),
    np.zeros((24, 32, 3), np.float32),
    np.zeros((24, 32, 3), np.float64),
    np.zeros((24, 32, 3), np.int32),
    np.zeros((24, 32, 2), np.uint8),
    np.zeros((24, 32, 5), np.uint8),
    np.zeros((2, 24, 32, 3), np.uint8),
    np.zeros((320,), np.uint8),
    np.zeros((24, 32, 3), bool),
])
def test_bad_arrays_raise_image_error(bad):
    with pytest.raises(ImageError) as info:
        detect(bad)
    assert isinstance(info.value, ValueError)
    assert "\n" not in str(info.value) and str(info.value)


@pytest.mark.parametrize("bad", [[[[0, 0, 0]]], None, "image.jpg", (1, 2, 3)])
def test_non_arrays_raise_type_error(bad):
    with pytest.raises(TypeError):
        detect(bad)


def test_all_soil_image():
    res = detect(np.full((240, 320, 3), (120, 90, 60), np.uint8))
    check_invariants(res)
    # one colour: it is the vegetation colour, the raw mask is the whole region, and the
    # bushy-region removal leaves nothing (region borders do not erode)
    assert res.status == "no_vegetation" and res.status in STATUSES
    assert res.veg_color == (120, 90, 60) and res.rows == [] and res.n_rows == 0


def test_all_green_image():
    res = detect(np.full((240, 320, 3), (0, 200, 0), np.uint8))
    check_invariants(res)
    assert res.rows == [] and res.status != "ok" and not res.valid
    assert res.status == "no_vegetation"


def test_one_pixel_high_image():
    img = np.random.default_rng(0).integers(0, 256, (1, 320, 3), dtype=np.uint8)
    res = detect(img)
    assert (res.width, res.height) == (320, 1)
    check_invariants(res)
    res = detect(np.full((1, 320, 3), (0, 200, 0), np.uint8))
    check_invariants(res)
    assert res.rows == []


def test_tiny_image_is_upscaled():
    img = np.random.default_rng(0).integers(0, 256, (3, 4, 3), dtype=np.uint8)
    res = detect(img)
    assert (res.width, res.height) == (320, 240)
    check_invariants(res)


def test_too_flat_to_resize_raises_image_error():
    with pytest.raises(ImageError):
        detect(np.zeros((1, 1000, 3), np.uint8))  # int(1 * 320 / 1000) = 0 rows


def test_determinism_and_input_untouched_on_synthetic():
    rgb = synthetic_field()
    before = rgb.copy()
    a = detect(rgb)
    b = detect(rgb)
    assert np.array_equal(rgb, before)
    assert a.to_record() == b.to_record()
    assert [r.hypothesis for r in a.rows] == [r.hypothesis for r in b.rows]
    # a read-only input works (nothing writes into it)
    ro = rgb.copy()
    ro.setflags(write=False)
    assert detect(ro).to_record() == a.to_record()


def test_record_round_trip():
    res = detect(synthetic_field(), name="synthetic")
    rec = res.to_record()
    back = ImageResult.from_record(rec)
    assert back.to_record() == rec
    assert rec["status"] == "ok" and len(rec["rows"]) == 5 and rec["name"] == "synthetic"
