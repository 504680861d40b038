"""Camera model and metric steering (ALGORITHM.md, "Camera model and steering"): JSON
validation, projection, steering from exact rows, the pinhole renderer, and the tracker's
metres and radians on rendered frames at a known pose."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from torchrow.core.camera import CameraModel, MetricSteering, metric_steering
from torchrow.core.params import Params
from torchrow.core.results import Row
from torchrow.core.steering import FrameResult
from torchrow.evaluation.synthetic import CameraPose, GroundField, render_camera

CAM = {"height_m": 1.0, "tilt_deg": 30, "hfov_deg": 70}


def camera(w: int = 320, h: int = 240, **changes: object) -> CameraModel:
    return CameraModel.from_json({**CAM, **changes}, (w, h))


def exact_rows(cam: CameraModel, pose: CameraPose, spacing: float, ks=range(-2, 3)) -> list[Row]:
    """Image lines of the ground rows ``k`` (field frame of :class:`GroundField`) at ``pose``."""
    inv_t = np.linalg.inv(cam.ground_to_image_matrix()).T
    out = []
    for k in ks:
        li = inv_t @ np.array([-math.sin(pose.heading_rad), math.cos(pose.heading_rad), pose.lateral_m + k * spacing])
        out.append(Row(a=-li[1] / li[0], b=-li[2] / li[0], valid=True))
    return out


@pytest.mark.parametrize(("obj", "message"), [
    ({"tilt_deg": 30, "hfov_deg": 70}, "missing key(s) height_m"),
    ({"height_m": 1.0, "tilt_deg": 30}, "missing key(s) hfov_deg (or fx, fy, cx, cy)"),
    ({**CAM, "roll_deg": 1}, "unknown key(s) ['roll_deg']"),
    ({**CAM, "fx": 300}, "either hfov_deg or fx, fy, cx, cy, got both"),
    ({"height_m": 1.0, "tilt_deg": 30, "fx": 300, "fy": 300}, "missing key(s) cx, cy"),
    ({**CAM, "height_m": float("nan")}, "height_m must be a finite number, got nan"),
    ({**CAM, "height_m": 0}, "height_m must lie in (0, 100], got 0.0"),
    ({**CAM, "tilt_deg": 95}, "tilt_deg must lie in [0, 90], got 95.0"),
    ({**CAM, "tilt_deg": True}, "tilt_deg must be a finite number, got True"),
    ({**CAM, "hfov_deg": 180}, "hfov_deg must be a finite number in (0, 180), got 180"),
    ({"height_m": 1.0, "tilt_deg": 30, "fx": 300, "fy": 300, "cx": 320, "cy": 100}, "cx must lie in [0, 319]"),
    ([1, 2], "expected a JSON object, got list"),
])
def test_json_errors_name_expected_and_actual(obj, message) -> None:
    with pytest.raises(ValueError, match=r"^camera model: ") as err:
        CameraModel.from_json(obj, (320, 240))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_json_file_and_its_errors(tmp_path) -> None:
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({"height_m": 1.2, "tilt_deg": 20, "fx": 400, "fy": 410, "cx": 300, "cy": 200}))
    cam = CameraModel.from_json(path, (640, 480))
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.image_width, cam.image_height) == (400, 410, 300, 200, 640, 480)
    path.write_text("{")
    with pytest.raises(ValueError, match=r"^camera model .*cam\.json: not JSON"):
        CameraModel.from_json(path, (640, 480))
    with pytest.raises(ValueError, match=r"^camera model .*absent\.json: cannot be read"):
        CameraModel.from_json(tmp_path / "absent.json", (640, 480))


def test_fov_intrinsics_and_scaling() -> None:
    cam = camera(640, 480)
    assert cam.fx == cam.fy == pytest.approx(320 / math.tan(math.radians(35)))
    assert (cam.cx, cam.cy) == (319.5, 239.5)
    small = cam.scaled(320, 240)
    assert (small.cx, small.cy, small.fx) == (159.5, 119.5, pytest.approx(cam.fx / 2))
    # a ground point lands where cv2.resize takes its pixel: x' = (x + 0.5)/2 - 0.5
    u, v = cam.ground_to_image(2.0, 0.4)
    us, vs = small.ground_to_image(2.0, 0.4)
    assert (us, vs) == (pytest.approx((u + 0.5) / 2 - 0.5), pytest.approx((v + 0.5) / 2 - 0.5))


def test_projection_round_trip_and_horizon() -> None:
    cam = camera(tilt_deg=20)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0.5, 30, 200), rng.uniform(-5, 5, 200)
    u, v = cam.ground_to_image(x, y)
    assert np.all(v > cam.horizon_v)
    gx, gy = cam.image_to_ground(u, v)
    np.testing.assert_allclose(gx, x, rtol=1e-9)
    np.testing.assert_allclose(gy, y, rtol=1e-9, atol=1e-12)
    # the optical axis meets the ground height/tan(tilt) ahead; above the horizon: no ground
    assert cam.image_to_ground(cam.cx, cam.cy)[0] == pytest.approx(1.0 / math.tan(math.radians(20)))
    assert np.isnan(cam.image_to_ground(100.0, cam.horizon_v - 1)[0])
    assert np.isnan(cam.ground_to_image(-2.0, 0.0)[0])  # behind the camera
    # Y > 0 (left) is left in the image
    assert cam.ground_to_image(3.0, 0.5)[0] < cam.cx < cam.ground_to_image(3.0, -0.5)[0]


@pytest.mark.parametrize(("lateral", "heading"), [(0.12, 0.05), (-0.2, -0.1), (0.0, 0.0), (0.24, 0.3)])
def test_steering_recovers_an_exact_pose(lateral, heading) -> None:
    cam = camera(tilt_deg=25)
    pose = CameraPose(lateral, heading)
    st = metric_steering(exact_rows(cam, pose, 0.5), cam, 240)
    assert st.lateral_m == pytest.approx(lateral, abs=1e-6)
    assert st.heading_rad == pytest.approx(heading, abs=1e-6)
    assert st.spacing_m == pytest.approx(0.5, abs=1e-6)


def test_steering_uses_the_tangent_at_the_bottom_row() -> None:
    cam = camera()
    rows = exact_rows(cam, CameraPose(0.1, -0.06), 0.6)
    y0 = 239.0
    bent = []
    for r in rows:  # x = line(y) + c (y - y0)^2 + e (y - y0)^3: the same tangent at y0
        c2, e3 = 2e-3, -1e-5
        bent.append(Row(a=r.a - 2 * c2 * y0 + 3 * e3 * y0 * y0, b=r.b + c2 * y0 * y0 - e3 * y0 ** 3,
                        c=c2 - 3 * e3 * y0, e=e3, valid=True))
    st = metric_steering(bent, cam, 240)
    assert (st.lateral_m, st.heading_rad, st.spacing_m) == (
        pytest.approx(0.1, abs=1e-6), pytest.approx(-0.06, abs=1e-6), pytest.approx(0.6, abs=1e-6))
    # the pixel signals too: bottom x of the whole polynomial, as for the straight rows
    from torchrow.core.steering import steering

    px, straight = steering(bent, None, 320, 240), steering(rows, None, 320, 240)
    assert straight.lateral_px is not None and px.lateral_px == pytest.approx(straight.lateral_px, abs=1e-6)
    assert px.lateral_frac == pytest.approx(straight.lateral_frac, abs=1e-9)
    # the lattice tracker's central row is a given slot (its tracked row), even where another
    # row lies nearer the centre or the nadir; its neighbours are the slots beside it
    shifted = [Row(a=0.0, b=160.0 + 100.0 * k - 60.0, valid=True) for k in (-1, 0, 1)]  # 0, 100, 200 px
    near, slot = steering(shifted, None, 320, 240), steering(shifted, None, 320, 240, central=1)
    assert (near.lateral_px, slot.lateral_px) == (40.0, -60.0) and slot.lateral_frac == pytest.approx(-0.6)
    mid = metric_steering(rows, cam, 240, central=3)  # rows k = -2..2 lie at 0.1 + 0.6 k m: slot 3 is k = 1
    assert (mid.lateral_m, mid.heading_rad, mid.spacing_m) == (
        pytest.approx(0.7, abs=1e-6), pytest.approx(-0.06, abs=1e-6), pytest.approx(0.6, abs=1e-6))
    assert metric_steering(rows, cam, 240, central=len(rows)) == MetricSteering()  # no such row


def test_steering_central_row_signs_and_missing_rows() -> None:
    cam = camera()
    rows = exact_rows(cam, CameraPose(0.35, 0.0), 0.5)  # nearest row: k = -1, 0.15 m to the camera's left
    st = metric_steering(rows, cam, 240)
    assert st.lateral_m == pytest.approx(-0.15, abs=1e-9)  # the camera is right of that row
    only = metric_steering(rows[2:3], cam, 240)
    assert only.lateral_m == pytest.approx(0.35, abs=1e-9) and only.spacing_m is None
    assert metric_steering([Row(a=0.1, b=150, valid=False)], cam, 240) == MetricSteering()
    assert metric_steering([], cam, 240) == MetricSteering()
    # rows pointing to the camera's left meet left of the image centre, heading > 0
    left = exact_rows(cam, CameraPose(0.0, 0.2), 0.5)
    assert metric_steering(left, cam, 240).heading_rad > 0
    assert -left[2].b / left[2].a < cam.cx or left[2].a * cam.horizon_v + left[2].b < cam.cx


def test_render_camera_truth_and_determinism() -> None:
    cam = camera(160, 120)
    field = GroundField(row_end_m=3.0, seed=4)
    pose = CameraPose(0.1, 0.05, 0.5)
    a, b = render_camera(field, cam, pose), render_camera(field, cam, pose)
    assert a.image.shape == (120, 160, 3) and a.image.dtype == np.uint8 and np.array_equal(a.image, b.image)
    assert (a.lateral_m, a.heading_rad, a.spacing_m, a.row_end_m) == (pytest.approx(0.1), 0.05, 0.5, 2.5)
    assert 0 in a.row_ids and a.row_ids == sorted(a.row_ids)
    assert metric_steering([Row(x, y, True) for x, y in a.rows], cam, 120).lateral_m == pytest.approx(0.1, abs=1e-9)
    img = a.image.astype(int)
    green = (img[:, :, 1] > img[:, :, 0] + 10) & (img[:, :, 1] > img[:, :, 2] + 20)
    # plants along the central row near the camera, bare soil beyond the rows' end
    (ca, cb) = a.rows[a.row_ids.index(0)]
    ys = np.arange(100, 120)
    near_row = green[ys, np.clip(np.rint(ca * ys + cb).astype(int), 0, 159)]
    assert near_row.mean() > 0.6 and green[100:].mean() < 0.5
    _, v_end = cam.ground_to_image(2.5 / math.cos(0.05) + 0.2, 0.0)  # past the end (plus a plant's reach)
    assert not green[: int(v_end) - 1].any()


def test_tracker_metric_steering_on_a_rendered_field() -> None:
    """Faithful tracker, 320 x 240, young plants (6 cm clumps on 50 cm rows): within 2 cm and 1°.

    The reference tracker (the tensor one shares its records, test_tracker.py, and
    ``FrameResult.build``, where the metric signals are made)."""
    from torchrow.engines.tracker import Tracker
    from torchrow.reference.tracking import Tracker as RefTracker

    cam = camera()
    field = GroundField(plant_radius_m=0.03, seed=1)
    pose = [CameraPose(0.1, 0.05, 0.05 * i) for i in range(3)]
    frames = [render_camera(field, cam, p, frame=i) for i, p in enumerate(pose)]
    res = RefTracker(Params(video_width=320), camera=cam).track([f.image for f in frames])
    lat = [abs(r.lateral_m - f.lateral_m) for r, f in zip(res, frames)]
    head = [abs(r.heading_rad - f.heading_rad) for r, f in zip(res, frames)]
    assert np.median(lat) < 0.02 and np.median(head) < math.radians(1)
    assert all(abs(r.spacing_m - 0.5) < 0.05 for r in res)
    rec = res[0].to_record()
    assert rec["lateral_m"] == res[0].lateral_m and rec["spacing_m"] == res[0].spacing_m
    # without a camera model the metric signals are null, the pixel ones stay
    plain = FrameResult.build(res[0], source=None, frame=0, hough_ran=True, hough_redo=False, confidence=1.0,
                              hfov_deg=None).to_record()
    assert plain["lateral_m"] is None and plain["spacing_m"] is None and plain["heading_rad"] is None
    assert plain["lateral_px"] == rec["lateral_px"] is not None
    with pytest.raises(ValueError, match="field of view or a camera model, not both"):
        Tracker(hfov_deg=70, camera=cam)


def test_cli_video_camera(tmp_path, capsys) -> None:
    import cv2

    from torchrow.apps.cli import main
    from torchrow.apps.sink import read_records

    cam = camera(480, 360)  # stored frames 480 x 360, tracked at 320 x 240
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(2):
        f = render_camera(GroundField(plant_radius_m=0.03, seed=2), cam, CameraPose(-0.08, -0.04, 0.05 * i), frame=i)
        cv2.imwrite(str(frames / f"f{i}.png"), cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
    spec = tmp_path / "cam.json"
    spec.write_text(json.dumps(CAM))
    out = tmp_path / "run.jsonl"
    base = ["video", str(frames), "--out", str(out), "--impl", "reference", "--param", "video_width=320",
            "--plot", "none", "--quiet", "--camera", str(spec)]
    assert main(base) == 0
    recs = [r for r in read_records(out) if "frame" in r]
    assert len(recs) == 2
    for r in recs:
        assert r["lateral_m"] == pytest.approx(-0.08, abs=0.03) and r["heading_rad"] == pytest.approx(-0.04, abs=0.02)
        assert r["spacing_m"] == pytest.approx(0.5, abs=0.05)
    capsys.readouterr()
    assert main(base + ["--fov", "70", "--resume"]) == 2
    assert "give --fov or --camera, not both" in capsys.readouterr().err
    spec.write_text(json.dumps({**CAM, "hfov_deg": 0}))
    assert main(base[:-1] + [str(spec), "--out", str(tmp_path / "b.jsonl")]) == 2
    assert "hfov_deg must be a finite number in (0, 180), got 0" in capsys.readouterr().err


def test_camera_path_interpolates_key_poses() -> None:
    from torchrow.evaluation.synthetic import camera_path

    path = camera_path([CameraPose(0.0, 0.0, 0.0), CameraPose(0.5, 0.1, 2.0)], 4)
    assert len(path) == 5 and path[-1] == CameraPose(0.5, 0.1, 2.0)
    assert path[2] == CameraPose(0.25, 0.05, 1.0)
    with pytest.raises(ValueError, match="frames_per_leg >= 1"):
        camera_path([CameraPose()], 0)


def test_batched_steering_equals_the_reference() -> None:
    import torch

    from torchrow.functional.camera import metric_steering as batched

    cam = camera()
    rng = np.random.default_rng(3)
    rows_list = []
    for i in range(12):
        pose = CameraPose(rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2))
        rows = exact_rows(cam, pose, 0.5, ks=range(-3, 3))
        rows = [Row(r.a, r.b, bool(rng.random() > 0.3), c=float(rng.normal(0, 1e-3)), e=float(rng.normal(0, 1e-6)))
                for r in rows]
        rows_list.append(rows[: 6 - i % 4] if i != 5 else [Row(0.0, 100.0, False)] * 6)
    n = max(len(r) for r in rows_list)

    def col(name: str, fill: float) -> torch.Tensor:
        return torch.tensor([[getattr(r, name) for r in rows] + [fill] * (n - len(rows)) for rows in rows_list],
                            dtype=torch.float64)

    valid = torch.tensor([[r.valid for r in rows] + [False] * (n - len(rows)) for rows in rows_list])
    lat, head, spc = batched(col("a", 0.0), col("b", 0.0), col("c", 0.0), col("e", 0.0), valid, cam, 240)
    for i, rows in enumerate(rows_list):
        ref = metric_steering(rows, cam, 240)
        for got, want in ((lat[i], ref.lateral_m), (head[i], ref.heading_rad), (spc[i], ref.spacing_m)):
            assert (math.isnan(float(got)) if want is None else float(got) == pytest.approx(want, abs=1e-9))
