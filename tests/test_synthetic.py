"""Tests of the synthetic field generator (torchrow.evaluation.synthetic)."""

from __future__ import annotations

import itertools
import math
import re

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchrow.evaluation.synthetic import FieldSpec, SyntheticField, demo_field, render, render_batch, save, sequence, write_crp

CLEAN = dict(weeds=0.0, shadows=0.0, plant_density=1.0)


def green(img: np.ndarray, ys: np.ndarray, xs: np.ndarray, margin: int = 15) -> np.ndarray:
    """Boolean per sample: G clearly above R and B at pixel (round(x), y)."""
    xi = np.rint(xs).astype(int)
    px = img[ys.astype(int), xi].astype(int)
    return (px[:, 1] > px[:, 0] + margin) & (px[:, 1] > px[:, 2] + margin)


def near_samples(f: SyntheticField, j_index: int, offset: float = 0.0, s_min: float = 0.5,
                 edge: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Image rows and x of row ``j_index`` (+ offset * spacing) where the scale is >= s_min."""
    W, H = f.spec.width, f.spec.height
    v = np.arange(f.sky, H)
    s = (v - f.vp[1]) / ((H - 1) - f.vp[1])
    x = f.centers[j_index] + offset * f.crp[:, 1]
    ok = (s >= s_min) & (x >= edge) & (x <= W - 1 - edge)
    return v[ok], x[ok]


def check_gt(f: SyntheticField) -> None:
    """Ground truth self-consistency: crp, centers, rows and vp agree."""
    spec = f.spec
    W, H = spec.width, spec.height
    v = np.arange(f.sky, H, dtype=np.float64)
    assert f.crp.shape == (H - spec.sky_rows, 2) and f.crp.dtype == np.float64
    assert np.all(np.isfinite(f.crp))
    assert np.all(f.crp[:, 1] > 0)
    assert f.sky == spec.sky_rows == f.v0
    assert len(f.rows) == len(f.row_ids) == f.centers.shape[0]
    assert f.centers.shape[1] == H - f.sky
    assert f.row_ids == sorted(f.row_ids)
    for j, cx, (a, b) in zip(f.row_ids, f.centers, f.rows):
        # CRBD model: row j at W/2 + c_v + j * d_v
        np.testing.assert_allclose(cx, W / 2 + f.crp[:, 0] + j * f.crp[:, 1], atol=1e-9)
        # every straight row passes through the vanishing point
        assert a * f.vp[1] + b == pytest.approx(f.vp[0], abs=1e-7)
        # the centre enters the image
        assert np.any((cx >= 0) & (cx <= W - 1))
        if spec.curvature == 0:
            np.testing.assert_allclose(cx, a * v + b, atol=1e-9)
    # spacing: linear in v, zero at the vanishing point, spacing_px on the bottom row
    np.testing.assert_allclose(f.crp[:, 1], spec.spacing_px * (v - f.vp[1]) / ((H - 1) - f.vp[1]),
                               rtol=1e-12)
    assert f.crp[-1, 1] == pytest.approx(spec.spacing_px)
    assert f.lateral_px == pytest.approx(spec.lateral_offset_px, abs=1e-9)
    if spec.curvature == 0 and 0 in f.row_ids:
        a0, b0 = f.rows[f.row_ids.index(0)]
        np.testing.assert_allclose(f.crp[:, 0], a0 * v + b0 - W / 2, atol=1e-9)
    for j in f.row_ids:
        np.testing.assert_allclose(f.x_at(j, v), f.centers[f.row_ids.index(j)], atol=1e-9)


# ----------------------------------------------------------------------------------------
def test_default_field_shapes_and_defaults():
    f = render(FieldSpec())
    assert isinstance(f, SyntheticField)
    assert f.image.shape == (240, 320, 3) and f.image.dtype == np.uint8
    assert f.image.flags.c_contiguous
    assert f.crp.shape == (240, 2)
    assert f.sky == 0
    vx, vy = f.vp
    assert vx == pytest.approx(160 + 8) and vy == pytest.approx(-96)
    assert f.heading_px == pytest.approx(8.0)
    assert f.heading_rad == pytest.approx(math.atan2(8.0, 0.75 * 320))
    assert -2 in f.row_ids and 2 in f.row_ids and 0 in f.row_ids
    assert f.crp[-1, 0] == pytest.approx(0.0, abs=1e-9)
    check_gt(f)
    # a plausible field: mostly brown soil with a sizeable share of green plants
    g = green(f.image, *np.nonzero(np.ones(f.image.shape[:2], bool)))
    assert 0.05 < g.mean() < 0.45
    assert np.array_equal(demo_field().image, f.image)


def test_deterministic_and_seed_sensitive():
    spec = FieldSpec(seed=7, weeds=0.5, shadows=0.03, plant_density=0.7, sky_rows=30)
    a, b = render(spec), render(spec)
    assert a.image.tobytes() == b.image.tobytes()
    assert a.crp.tobytes() == b.crp.tobytes()
    c = render(spec.replace(seed=8))
    assert c.image.tobytes() != a.image.tobytes()
    np.testing.assert_array_equal(c.crp, a.crp)  # geometry does not depend on the seed
    # the frame index only drives the sensor noise
    quiet = spec.replace(noise=0.0)
    assert np.array_equal(render(quiet).image, render(quiet.replace(frame=3)).image)
    assert not np.array_equal(render(spec).image, render(spec.replace(frame=3)).image)


def test_rows_green_and_interrows_not_green():
    for spec in (FieldSpec(**CLEAN),
                 FieldSpec(**CLEAN, seed=3, lateral_offset_px=-25.0, vp=(120.0, -60.0)),
                 FieldSpec(**CLEAN, seed=4, curvature=30.0, sky_rows=40),
                 FieldSpec(**CLEAN, seed=5, spacing_px=80.0, plant_width_px=16.0)):
        f = render(spec)
        check_gt(f)
        n_checked = 0
        for i, j in enumerate(f.row_ids):
            ys, xs = near_samples(f, i)
            if ys.size < 20:
                continue
            n_checked += 1
            assert green(f.image, ys, xs).mean() >= 0.8, (spec, j)
            ys, xs = near_samples(f, i, offset=0.5)
            if ys.size:
                assert green(f.image, ys, xs).mean() <= 0.05, (spec, j)
        assert n_checked >= 3


def test_ground_truth_is_the_centre_of_the_drawn_rows():
    """Per image row, the green pixels of a row are centred on the true centre (no bias)."""
    for spec in (FieldSpec(**CLEAN, seed=1), FieldSpec(**CLEAN, seed=2, curvature=-25.0,
                                                     lateral_offset_px=15.0, sky_rows=20)):
        f = render(spec)
        img = f.image.astype(int)
        is_green = (img[..., 1] > img[..., 0] + 15) & (img[..., 1] > img[..., 2] + 15)
        offsets = []
        for i in range(len(f.row_ids)):
            ys, xs = near_samples(f, i, s_min=0.4, edge=40)
            for y, x in zip(ys, xs):
                half = 0.5 * f.crp[y - f.sky, 1]
                lo, hi = int(math.ceil(x - half)), int(math.floor(x + half))
                cols = np.flatnonzero(is_green[y, lo:hi + 1]) + lo
                if cols.size >= 3:
                    offsets.append(cols.mean() - x)
        assert len(offsets) > 100
        assert abs(np.mean(offsets)) < 0.5
        assert np.percentile(np.abs(offsets), 90) < 4.0


def test_crp_length_follows_sky():
    for sky in (0, 1, 25, 60, 119):
        f = render(FieldSpec(sky_rows=sky, seed=sky))
        assert f.crp.shape == (240 - sky, 2)
        check_gt(f)
        if sky > 1:
            top = f.image[: sky - 1].reshape(-1, 3).astype(int)
            assert np.mean(top[:, 2] > top[:, 0]) > 0.95  # bluish sky


@pytest.mark.parametrize("size", [(320, 240), (640, 480), (1280, 960), (321, 203), (64, 48)])
def test_sizes(size):
    w, h = size
    spec = FieldSpec.at_size(w, h, **CLEAN, seed=11)
    f = render(spec)
    assert f.image.shape == (h, w, 3) and f.image.dtype == np.uint8
    assert f.crp.shape == (h, 2)
    check_gt(f)
    i0 = f.row_ids.index(0)
    ys, xs = near_samples(f, i0)
    assert ys.size > 10
    assert green(f.image, ys, xs).mean() >= 0.9
    if w > 640:
        return
    # a plain spec of this size (unscaled lengths) renders too
    g = render(FieldSpec(width=w, height=h, seed=2, sky_rows=h // 5))
    assert g.image.shape == (h, w, 3) and g.crp.shape == (h - h // 5, 2)
    check_gt(g)


def test_n_rows_and_missing_rows():
    f = render(FieldSpec(**CLEAN, n_rows=3))
    assert f.row_ids == [-1, 0, 1]
    full = render(FieldSpec(**CLEAN))
    i2 = full.row_ids.index(2)
    ys, xs = near_samples(full, i2)
    assert green(full.image, ys, xs).mean() >= 0.9
    assert green(f.image, ys, xs).mean() <= 0.05  # row 2 is not drawn
    m = render(FieldSpec(**CLEAN, missing_rows=(0,)))
    assert m.row_ids == full.row_ids  # ground truth unchanged
    ys, xs = near_samples(m, m.row_ids.index(0))
    assert green(m.image, ys, xs).mean() <= 0.05
    ys, xs = near_samples(m, m.row_ids.index(1))
    assert green(m.image, ys, xs).mean() >= 0.9


def test_weeds_add_green_between_rows():
    clean = render(FieldSpec(**CLEAN, seed=1))
    weedy = render(FieldSpec(seed=1, weeds=3.0))
    def mid_green(f: SyntheticField) -> float:
        vals = [green(f.image, *near_samples(f, i, offset=0.5, s_min=0.3)).mean()
                for i in range(len(f.row_ids)) if near_samples(f, i, 0.5, 0.3)[0].size]
        return float(np.mean(vals))
    assert mid_green(weedy) > mid_green(clean) + 0.01


def test_plant_density_creates_gaps():
    def cover(density: float) -> float:
        vals = []
        for seed in range(3):
            f = render(FieldSpec(**{**CLEAN, "plant_density": density}, seed=seed))
            for i in range(len(f.row_ids)):
                ys, xs = near_samples(f, i)
                if ys.size >= 20:
                    vals.append(green(f.image, ys, xs).mean())
        return float(np.mean(vals))
    full, half = cover(1.0), cover(0.5)
    assert full > 0.9
    assert 0.25 < half < 0.8


def test_write_crp_format(tmp_path):
    f = render(FieldSpec(sky_rows=12))
    p = write_crp(tmp_path / "x" / "a.crp", f.crp)
    text = p.read_text()
    lines = text.splitlines()
    assert text.endswith("\n")
    assert len(lines) == 240 - 12
    assert all(re.fullmatch(r"-?\d+\.\d{6}\t-?\d+\.\d{6}", ln) for ln in lines)
    np.testing.assert_allclose(np.loadtxt(p), f.crp, atol=5e-7)
    with pytest.raises(ValueError):
        write_crp(tmp_path / "b.crp", np.zeros((3, 3)))


def test_save_roundtrip(tmp_path):
    f = render(FieldSpec(seed=2))
    img_path, crp_path = save(f, tmp_path / "out", "synth_000")
    assert img_path.name == "synth_000.png" and crp_path.name == "synth_000.crp"
    back = cv2.cvtColor(cv2.imread(str(img_path)), cv2.COLOR_BGR2RGB)
    assert np.array_equal(back, f.image)
    np.testing.assert_allclose(np.loadtxt(crp_path), f.crp, atol=5e-7)
    jpg, _ = save(f, tmp_path / "out", "synth_001", ext=".JPG")
    assert jpg.suffix == ".JPG"
    back = cv2.cvtColor(cv2.imread(str(jpg)), cv2.COLOR_BGR2RGB)
    assert back.shape == f.image.shape
    assert np.abs(back.astype(int) - f.image.astype(int)).mean() < 8


def test_render_batch():
    specs = [FieldSpec(seed=s) for s in range(3)]
    batch = render_batch(specs)
    assert batch.shape == (3, 3, 240, 320) and batch.dtype == np.uint8
    for i, s in enumerate(specs):
        assert np.array_equal(batch[i], render(s).image.transpose(2, 0, 1))
    with pytest.raises(ValueError):
        render_batch([FieldSpec(), FieldSpec(width=321)])
    with pytest.raises(ValueError):
        render_batch([])


def test_sequence_ground_truth_follows_motion():
    spec = FieldSpec(seed=4, lateral_offset_px=-10.0)
    drift, dpsi = 2.5, 0.01
    frames = sequence(spec, 8, drift_px_per_frame=drift, heading_rad_per_frame=dpsi, gap=(3, 5))
    assert len(frames) == 8
    psi0 = math.atan2(spec.vanishing_point[0] - 160, spec.focal)
    for k, f in enumerate(frames):
        check_gt(f)
        assert f.lateral_px == pytest.approx(-10.0 + k * drift, abs=1e-9)
        assert f.crp[-1, 0] == pytest.approx(-10.0 + k * drift, abs=1e-9)
        assert f.heading_rad == pytest.approx(psi0 + k * dpsi, abs=1e-12)
        assert f.heading_px == pytest.approx(f.vp[0] - 160)
        assert f.heading_px == pytest.approx(spec.focal * math.tan(psi0 + k * dpsi))
        assert f.vp[1] == pytest.approx(spec.vanishing_point[1])
        assert f.spec.frame == k
        assert (0 in f.spec.missing_rows) == (3 <= k < 5)
        ys, xs = near_samples(f, f.row_ids.index(0))
        g = green(f.image, ys, xs).mean()
        assert (g <= 0.05) if 3 <= k < 5 else (g >= 0.75)
    for a, b in itertools.pairwise(frames):
        assert not np.array_equal(a.image, b.image)
    # heading moves the vanishing point right, drift moves the rows right
    assert frames[-1].vp[0] > frames[0].vp[0]
    assert np.all(frames[-1].centers[frames[-1].row_ids.index(0), -5:]
                  > frames[0].centers[frames[0].row_ids.index(0), -5:])
    # seed override
    assert sequence(spec, 1, seed=9)[0].spec.seed == 9
    assert sequence(spec, 0) == []


def test_sequence_static_camera_is_static():
    spec = FieldSpec(noise=0.0, seed=3)
    frames = sequence(spec, 3, drift_px_per_frame=0.0, heading_rad_per_frame=0.0,
                      speed_px_per_frame=0.0)
    assert all(np.array_equal(frames[0].image, f.image) for f in frames)
    assert np.array_equal(frames[0].image, render(spec).image)
    moving = sequence(spec, 2, drift_px_per_frame=0.0, speed_px_per_frame=6.0)
    assert not np.array_equal(moving[0].image, moving[1].image)
    np.testing.assert_array_equal(moving[0].crp, moving[1].crp)  # rows do not move


def test_spec_validation():
    with pytest.raises(ValueError, match="vp"):
        FieldSpec(vp=(160.0, 10.0))  # below the first ground row without sky
    with pytest.raises(ValueError, match="vp"):
        FieldSpec(sky_rows=30, vp=(160.0, 30.0))
    FieldSpec(sky_rows=30, vp=(160.0, 29.5))
    with pytest.raises(ValueError, match="plant_color"):
        FieldSpec(plant_color=(120, 130, 60))
    with pytest.raises(ValueError, match="sky_rows"):
        FieldSpec(sky_rows=239)
    with pytest.raises(ValueError, match="plant_density"):
        FieldSpec(plant_density=0.0)
    with pytest.raises(ValueError, match="width"):
        FieldSpec(width=8)
    with pytest.raises(ValueError, match="seed"):
        FieldSpec(seed=-1)
    with pytest.raises(ValueError, match="spacing_px"):
        FieldSpec(spacing_px=float("nan"))


def test_spec_fields_follow_the_params_rule_machinery():
    """FieldSpec checks its fields with :class:`torchrow.core.params.Rule`, as Params does: a value
    of the wrong kind is a TypeError naming the field; lists become tuples, numbers their kind."""
    with pytest.raises(TypeError, match=r"FieldSpec\.width must be an integer, not float"):
        FieldSpec(width=20.0)
    with pytest.raises(ValueError, match=r"FieldSpec\.soil_color must be an \(R, G, B\) triple"):
        FieldSpec(soil_color=(1, 2))
    spec = FieldSpec(soil_color=[1, 2, 3], missing_rows=[2], spacing_px=60, width=np.int64(320))
    assert spec == FieldSpec(soil_color=(1, 2, 3), missing_rows=(2,)) and hash(spec) == hash(FieldSpec(
        soil_color=(1, 2, 3), missing_rows=(2,)))
    assert type(spec.spacing_px) is float and type(spec.width) is int


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32),
    width=st.integers(40, 400),
    height=st.integers(30, 300),
    sky_frac=st.floats(0.0, 0.45),
    spacing=st.floats(15.0, 150.0),
    lateral=st.floats(-80.0, 80.0),
    curvature=st.floats(-40.0, 40.0),
    vp_dx=st.floats(-200.0, 200.0),
    vp_above=st.floats(0.5, 400.0),
    weeds=st.floats(0.0, 1.5),
    density=st.floats(0.2, 1.0),
    plant_width=st.floats(1.0, 30.0),
    travel=st.floats(-500.0, 2000.0),
)
def test_property_render_never_fails(seed, width, height, sky_frac, spacing, lateral, curvature,
                                     vp_dx, vp_above, weeds, density, plant_width, travel):
    sky = int(sky_frac * height)
    spec = FieldSpec(width=width, height=height, seed=seed, sky_rows=sky, spacing_px=spacing,
                     lateral_offset_px=lateral, curvature=curvature,
                     vp=(width / 2 + vp_dx, sky - vp_above), weeds=weeds, plant_density=density,
                     plant_width_px=plant_width, travel_px=travel, shadows=0.02)
    f = render(spec)
    assert f.image.shape == (height, width, 3) and f.image.dtype == np.uint8
    check_gt(f)
    assert f.vp == (width / 2 + vp_dx, sky - vp_above)
    assert np.array_equal(render(spec).image, f.image)
