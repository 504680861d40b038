"""The lattice tracker (ALGORITHM.md 11.7): tensor = reference, identity, row changes, row end, loss."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math

import cv2
import numpy as np
import pytest
import torch

import torchrow
from torchrow.apps.cli import main
from torchrow.core.camera import CameraModel
from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.core.results import STATUSES, record_differences
from torchrow.evaluation.synthetic import CameraPose, GroundField, camera_path, render_camera
from torchrow.evaluation.tracking import row_moves
from torchrow.reference import Tracker as RefTracker

# a forward camera: the forward-camera setting of ALGORITHM.md 11.3.1 (rows 16-320 px apart, straight or curved)
FORWARD = {"lattice_model": "auto", "lattice_min_spacing": 16, "lattice_max_spacing": 320}
P = Params(video_width=320, mode="improved", **FORWARD)
CAM = {"height_m": 1.0, "tilt_deg": 30, "hfov_deg": 70}


def camera() -> CameraModel:
    return CameraModel.from_json(CAM, (320, 240))


def drive(keys: list[CameraPose], per_leg: int, row_end_m: float | None = None):
    field = GroundField(plant_radius_m=0.03, seed=1, row_end_m=row_end_m)
    return [render_camera(field, camera(), p, frame=i) for i, p in enumerate(camera_path(keys, per_leg))]


def same(ref: list, got: list) -> None:
    assert len(ref) == len(got)
    for r, g in zip(ref, got):
        diff = record_differences(r.to_record(), g.to_record())
        assert not diff, f"frame {r.frame}: {diff[:5]}"


def test_tensor_equals_reference_on_a_rendered_drive() -> None:
    # over to the next row and towards the rows' end; two sequences of different lengths in lock-step
    frames = [f.image for f in drive([CameraPose(0.2, 0.0, 3.0), CameraPose(-0.3, 0.03, 4.0)], 5, row_end_m=6.0)]
    other = frames[::-2]
    got = torchrow.Tracker(P, camera=camera()).track([frames, other])
    same(RefTracker(P, camera=camera()).track(frames), got[0])
    same(RefTracker(P, camera=camera()).track(other), got[1])
    assert all(r.state is not None and r.to_record()["state"] == r.state for r in got[0])


def test_caterra_frames_tensor_equals_reference(data_dir) -> None:
    folder = data_dir / "caterra_video"
    if not folder.is_dir():
        pytest.skip(f"caterra_video not found under {data_dir}")
    items = [(p.name, cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)) for p in sorted(folder.glob("*.jpg"))[:8]]
    params = Params(mode="improved", **FORWARD)
    # the rover's camera sees the horizon (section 1's row 88-123 of 281): with the VP grid
    # counted from it (11.2) the rows are found and tracked; from row 0 every frame is weak
    sky = params.replace(lattice_vp_origin="sky")
    got = torchrow.Tracker(sky).track([items], sources=["c"])[0]
    same(RefTracker(sky).track(items, source="c"), got)
    # acquisition (11.7): frame 0's lattice (a 96 px spacing) is not confirmed by frame 1's whole
    # grid (139 px), frame 1's is by frame 2's, and the lattice is tracked from there
    assert all(r.status == "ok" for r in got)
    assert [r.state for r in got] == ["lost", "lost"] + ["in_row"] * 6
    assert [r.hough_ran for r in got] == [True, True, True] + [False] * 5
    moves = row_moves([r.to_record() for r in got])
    # without it frames 1-3 were redone from frame 0's row (S-bent lattices) and row 0 moved 0.28 spacings on frame 4
    assert len(moves.moves) == 5 and moves.largest.frac < 0.1 and not moves.above()
    assert all(r.state == "lost" for r in torchrow.Tracker(params).track([items[3:5]])[0])


def test_sky_origin_steps_equal_under_every_flow(data_dir) -> None:
    # the exported step's flows compute section 1 on every frame (not only on full searches) and
    # run every refit to its bound: the same steps and states as the eager tracker's
    folder = data_dir / "caterra_video"
    if not folder.is_dir():
        pytest.skip(f"caterra_video not found under {data_dir}")
    from torchrow.core.io import load_image
    from torchrow.core.results import STATUSES
    from torchrow.functional.lattice_tracking import LatticeTrackerState, lattice_advance
    from torchrow.onnx.checks import step_differences

    params = Params(mode="improved", video_width=320, lattice_vp_origin="sky", **FORWARD)
    frames = [load_image(f, 320) for f in sorted(folder.glob("*.jpg"))[:12:3]]
    states = {flow: LatticeTrackerState.empty(1) for flow in ("sync", "always")}
    active = torch.ones(1, dtype=torch.bool)
    for rgb in frames:
        x = torch.from_numpy(rgb).permute(2, 0, 1)[None].contiguous()
        steps = {}
        for flow in states:
            steps[flow], states[flow] = lattice_advance(x, active, states[flow], params, flow)
        assert not step_differences(steps["sync"], steps["always"])
        assert not step_differences(states["sync"], states["always"])
        assert steps["sync"].status.tolist() == [STATUSES.index("ok")]  # the grid counted from the horizon


def test_identity_row_change_and_row_end() -> None:
    # straight along a row, then over to the row on the camera's right, then past the rows' end
    keys = [CameraPose(0.1, 0.0, 0.0), CameraPose(0.1, 0.0, 1.0), CameraPose(-0.45, 0.0, 2.0), CameraPose(-0.45, 0.0, 7.0)]
    frames = drive(keys, 5, row_end_m=6.0)
    res = torchrow.Tracker(P, camera=camera()).track([[f.image for f in frames]])[0]
    bottom = [r.rows[1].x_at(239.0) for r in res]
    # driving straight: row 0 stays the row near the centre, within a few pixels
    assert all(r.row_change == 0 for r in res[:6]) and np.ptp(bottom[:6]) < 3
    # one change, to the right (+1), when the camera has crossed to the next row
    changes = [(i, r.row_change) for i, r in enumerate(res) if r.row_change]
    assert changes == [(changes[0][0], 1)] and 8 <= changes[0][0] <= 11
    for r, f in zip(res, frames):
        if r.state == "row_end_ahead" and r.row_end_m is not None:
            assert abs(r.row_end_m - f.row_end_m) < 1.0
    # from its first report (more than 4 m ahead) to the headland, every frame says the rows end ahead
    states = [r.state for r in res]
    first, past = states.index("row_end_ahead"), states.index("headland")
    # frame 0 acquires (11.7): lost until frame 1's full search confirms its spacing
    assert states == ["lost"] + ["in_row"] * (first - 1) + ["row_end_ahead"] * (past - first) + ["headland"] * (len(res) - past)
    assert past - first >= 6 and frames[first].row_end_m > 4.0
    # the same drive backwards: the change is to the left
    back = torchrow.Tracker(P, camera=camera()).track([[f.image for f in frames[::-1]]])[0]
    assert [r.row_change for r in back if r.row_change] == [-1]
    # stability (11.7): row 0 never moves a quarter spacing between frames, the change included
    for seq in (res, back):
        moves = row_moves([r.to_record() for r in seq])
        assert len(moves.moves) >= 10 and not moves.above()


def test_lost_without_plants_and_full_search_after() -> None:
    soil = render_camera(GroundField(seed=3, row_end_m=0.0), camera(), CameraPose(0.0, 0.0, 5.0)).image
    rows = drive([CameraPose(0.05, 0.0, 0.0), CameraPose(0.05, 0.0, 0.2)], 2)
    seq = [soil, *(f.image for f in rows), soil]
    res = torchrow.Tracker(P).track([seq])[0]
    # frame 0 searches the whole grid; frame 1 follows a loss: a full search of the window
    # around frame 0's grid VP and grid height 1 (11.7), its rows ok but not yet trusted
    # (acquisition); frame 2's full search (the grid near frame 1's VP) confirms them;
    # frame 3 is tracked; frame 4 is tracked, fails, and is searched again in full
    assert [r.status for r in res] == ["weak", "ok", "ok", "ok", "weak"]
    assert [r.state for r in res] == ["lost", "lost", "in_row", "in_row", "lost"]
    assert [(r.hough_ran, r.hough_redo) for r in res] == [(True, False), (True, False), (True, False), (False, False),
                                                          (True, True)]
    same(RefTracker(P).track(seq), res)
    rec = res[0].to_record()
    assert rec["row_end_m"] is None and rec["row_end_y"] is None and rec["row_change"] == 0


def test_lattice_tracker_parameters_and_errors() -> None:
    with pytest.raises(ValueError, match="lattice_vp='search'"):
        torchrow.Tracker(P.replace(lattice_vp="section6"))
    with pytest.raises(ValueError, match="lattice_track_phase_tol"):
        Params(lattice_track_phase_tol=0.6)
    assert torchrow.Tracker(Params(), mode="improved").params == Params(mode="improved")
    # without params the lattice tracker takes the forward-camera setting: a robot's camera looks forward
    forward = Params(mode="improved", **FORWARD_CAMERA)
    assert torchrow.Tracker(mode="improved").params == forward == RefTracker(mode="improved").params
    assert torchrow.Tracker().params == Params() == RefTracker(mode="faithful").params
    # the faithful tracker's records keep their keys
    frames = drive([CameraPose(0.05, 0.0, 0.0)], 1)
    faithful = torchrow.Tracker(Params(video_width=320)).track([[frames[0].image]])[0][0].to_record()
    assert "state" not in faithful and "row_change" not in faithful


@pytest.mark.parametrize("suffix", [".jsonl", ".parquet"])
def test_cli_video_mode_improved(tmp_path, suffix: str) -> None:
    if suffix == ".parquet":
        pytest.importorskip("pyarrow")
    from torchrow.apps.sink import read_records

    d = tmp_path / "frames"
    d.mkdir()
    for i, f in enumerate(drive([CameraPose(0.05, 0.0, 0.0), CameraPose(0.05, 0.0, 0.2)], 2)):
        cv2.imwrite(str(d / f"f{i}.png"), cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
    (tmp_path / "cam.json").write_text(json.dumps(CAM))
    out = tmp_path / f"v{suffix}"
    pics = ["--annotate", str(tmp_path / "pics")] if suffix == ".jsonl" else []  # the lattice frames' pictures
    assert main(["video", str(d), "--out", str(out), "--mode", "improved", "--param", "video_width=320",
                 "--plot", "none", "-q", "--camera", str(tmp_path / "cam.json"), *pics]) == 0
    assert len(list(tmp_path.glob("pics/*.png"))) == (3 if pics else 0)
    recs = list(read_records(out))
    assert [r["state"] for r in recs] == ["lost", "in_row", "in_row"] and [r["row_change"] for r in recs] == [0, 0, 0]
    assert all(abs(r["lateral_m"] - 0.05) < 0.02 and abs(r["heading_rad"]) < math.radians(1) for r in recs)
    assert recs[0]["row_end_m"] is None


def test_prior_arguments_keep_the_default_search() -> None:
    # a full-search prior centred on W/2 is the detector's search, bit for bit
    from torchrow.functional import lattice as flattice
    from torchrow.reference import lattice as rlattice

    img = drive([CameraPose(0.12, 0.02, 0.0)], 1)[0].image
    p = P
    mask = rlattice.green_mask(img, 0, p)
    assert rlattice.fit_lattice(mask, 0, None, p) == rlattice.fit_lattice(mask, 0, None, p, rlattice.LatticePrior(160.0))
    m = torch.from_numpy(mask).unsqueeze(0)
    zero = torch.zeros(1, dtype=torch.int64)
    prior = flattice.LatticePriorBatch(torch.tensor([160.0], dtype=torch.float64), torch.zeros(1, dtype=torch.bool),
                                       torch.zeros((1, 2), dtype=torch.int64), torch.ones(1, dtype=torch.int64))
    a, b = flattice.fit_lattice(m, zero, None, None, p), flattice.fit_lattice(m, zero, None, None, p, prior)
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_a_tracked_comb_too_weak_for_ok_skips_its_refits() -> None:
    # 11.7: a restricted comb below lattice_min_contrast makes the frame weak whatever the refits
    # give, so it is redone in full; its refits are skipped (the rows stay the comb's start), in
    # both paths. At the tracked spacing the comb is strong and the refits run; restricted to
    # twice that spacing, its anti-teeth lie on the rows it skips.
    from torchrow.functional import lattice as flattice
    from torchrow.reference import lattice as rlattice

    img = drive([CameraPose(0.12, 0.02, 0.0)], 1)[0].image
    mask = rlattice.green_mask(img, 0, P)
    full = rlattice.fit_lattice(mask, 0, None, P)
    assert full.contrast >= P.lattice_min_contrast
    m = torch.from_numpy(mask).unsqueeze(0)
    zero = torch.zeros(1, dtype=torch.int64)
    centre = full.coef[0]
    for spacing, refits in ((full.spacing, True), (2 * full.spacing, False)):
        ref = rlattice.fit_lattice(mask, 0, None, P, rlattice.LatticePrior(centre, full.vp, spacing))
        prior = flattice.LatticePriorBatch(torch.tensor([centre], dtype=torch.float64), torch.ones(1, dtype=torch.bool),
                                           torch.tensor([full.vp]), torch.tensor([spacing]))
        got = flattice.fit_lattice(m, zero, None, None, P, prior)
        assert (ref.contrast >= P.lattice_min_contrast) == refits
        assert float(got.contrast[0]) == ref.contrast
        xv, yv = ref.vp
        den = np.float64(mask.shape[0] - 1 - yv)
        start = (np.float64(ref.phase), (np.float64(ref.phase) - xv) / den, 0.0, 0.0,
                 np.float64(ref.spacing), np.float64(ref.spacing) / den, 0.0)
        assert (ref.coef != start) == refits
        assert got.coef[0].tolist() == list(ref.coef) and bool(got.curved[0]) == ref.curved


def test_a_too_weak_tracked_comb_switches_to_the_full_search_on_its_own_mask(monkeypatch) -> None:
    # 11.7: the tensor path switches such a frame to the full search before its refits instead of
    # redoing it: the same step as a full search from the same tracked row (reported as a redo),
    # with one green mask, one refit and one row pass for the frame
    from torchrow.functional import lattice as flattice
    from torchrow.functional.lattice_tracking import LatticeTrackerState, lattice_advance
    from torchrow.onnx.checks import step_differences
    from torchrow.reference import lattice as rlattice

    img = drive([CameraPose(0.12, 0.02, 0.0)], 1)[0].image
    full = rlattice.fit_lattice(rlattice.green_mask(img, 0, P), 0, None, P)
    x = torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()
    one = torch.ones(1, dtype=torch.bool)

    def state(spacing: int, age: int) -> LatticeTrackerState:
        st = LatticeTrackerState.empty(1)
        st.ready, st.has_centre, st.age, st.last = one, one.clone(), torch.tensor([age]), torch.tensor([0])
        st.vp, st.spacing, st.grid_vp = torch.tensor([full.vp]), torch.tensor([spacing]), torch.tensor([full.vp])
        st.centre = torch.tensor([full.coef[0]], dtype=torch.float64)
        return st

    calls = {"green_mask": 0, "refit_lattice": 0, "lattice_rows": 0}

    def counting(name: str):
        fn = getattr(flattice, name)

        def counted(*a, **k):
            calls[name] += 1
            return fn(*a, **k)
        return counted
    for name in calls:
        monkeypatch.setattr(flattice, name, counting(name))
    wide, _ = lattice_advance(x, one, state(full.spacing, P.lattice_track_every), P)  # a scheduled full search
    assert bool(wide.full[0]) and not bool(wide.redo[0]) and wide.status.tolist() == [0]
    calls.update(dict.fromkeys(calls, 0))
    # restricted to twice the spacing the comb's anti-teeth lie on the rows it skips: too weak
    step, _ = lattice_advance(x, one, state(2 * full.spacing, 1), P)
    assert calls == {"green_mask": 1, "refit_lattice": 1, "lattice_rows": 1}
    assert bool(step.redo[0]) and bool(step.full[0])
    assert step_differences(wide, step, tol=0.0) == ["LatticeStep.redo: [False] != [True]"]


def test_a_tracked_full_search_takes_the_window_around_its_grid_vp() -> None:
    # 11.7: a tracked sequence's scheduled full search takes only the grid VPs near its last grid
    # VP (both paths); the next state carries the VP it chose
    from torchrow.functional.lattice_tracking import LatticeTrackerState, lattice_advance
    from torchrow.reference import lattice as rlattice

    img = drive([CameraPose(0.12, 0.02, 0.0)], 1)[0].image
    mask = rlattice.green_mask(img, 0, P)
    full = rlattice.fit_lattice(mask, 0, None, P)
    x = torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()
    one = torch.ones(1, dtype=torch.bool)
    grid = rlattice.vp_grid(img.shape[1], P)
    for around in [full.vp, (0, -250)]:
        st = LatticeTrackerState.empty(1)
        st.ready, st.has_centre, st.last = one, one.clone(), torch.tensor([0])
        st.age, st.spacing = torch.tensor([P.lattice_track_every]), torch.tensor([full.spacing])
        st.vp, st.grid_vp = torch.tensor([full.vp]), torch.tensor([around])
        st.centre = torch.tensor([full.coef[0]], dtype=torch.float64)
        step, new = lattice_advance(x, one, st, P)
        chosen = tuple(step.rows.vp[0].tolist())
        assert bool(step.full[0]) and new.grid_vp[0].tolist() == list(chosen)
        assert chosen in {tuple(v) for v in grid[rlattice.vp_window(img.shape[1], P, around)].tolist()}
        prior = rlattice.LatticePrior(float(full.coef[0]), near=around)
        assert rlattice.fit_lattice(mask, 0, None, P.tracking(), prior).vp == chosen
        # around the whole grid's choice the window finds it again; far from it, a VP of its own
        assert (chosen == full.vp) == (around == full.vp)
        # in lock-step beside a sequence that searches the whole grid (frame 0): each as alone
        both, _ = lattice_advance(torch.cat([x, x]), torch.ones(2, dtype=torch.bool),
                                  LatticeTrackerState(*(torch.cat([a, b]) for a, b in zip(
                                      dataclasses.astuple(st), dataclasses.astuple(LatticeTrackerState.empty(1))))), P)
        alone, _ = lattice_advance(x, one, LatticeTrackerState.empty(1), P)
        assert both.rows.vp.tolist() == [list(chosen), list(full.vp)] == [list(chosen), alone.rows.vp[0].tolist()]


def test_after_a_loss_the_full_search_sweeps_one_grid_height_per_frame() -> None:
    # 11.7: after a frame that was not ok the full search takes the window around the last grid
    # VP of an ok frame and the whole row of grid height frames % len(heights): a loss sweeps
    # the grid in 7 frames at a window's cost per frame; a frame that fails keeps the grid VP
    from torchrow.core.steering import LATTICE_STATES
    from torchrow.functional.lattice_tracking import LatticeTrackerState, lattice_advance
    from torchrow.reference import lattice as rlattice
    from torchrow.reference.lattice_tracking import LatticeSequenceState, LatticeTracker

    img = drive([CameraPose(0.12, 0.02, 0.0)], 1)[0].image
    grey = np.full_like(img, 120)
    mask = rlattice.green_mask(img, 0, P)
    x = torch.from_numpy(np.stack([img, grey])).permute(0, 3, 1, 2).contiguous()
    grid, heights = rlattice.vp_grid(img.shape[1], P), len(P.lattice_vp_heights)
    corner = (0, -250)  # far from the rows' VP: the window alone cannot reach it
    seen = set()
    for frames in range(heights):
        st = LatticeTrackerState.empty(2)
        st.ready, st.frames = torch.ones(2, dtype=torch.bool), torch.full((2,), frames)
        st.last = torch.full((2,), LATTICE_STATES.index("lost"))
        st.vp = st.grid_vp = torch.tensor([corner, corner])
        step, new = lattice_advance(x, torch.ones(2, dtype=torch.bool), st, P)
        chosen = tuple(step.rows.vp[0].tolist())
        assert step.full.tolist() == [True, True] and [STATUSES[c] for c in step.status.tolist()] == ["ok", "invalid"]
        assert chosen in {tuple(v) for v in grid[rlattice.vp_window(img.shape[1], P, corner, 0, frames)].tolist()}
        seen.add(chosen[1])
        prior = rlattice.LatticePrior(img.shape[1] / 2, near=corner, sweep=frames)
        assert rlattice.fit_lattice(mask, 0, None, P.tracking(), prior).vp == chosen
        # the ok frame moves the window's centre; the grey frame keeps it
        assert new.grid_vp.tolist() == [list(chosen), list(corner)]
        for b, frame in enumerate((img, grey)):
            rec, ref = LatticeTracker(P).step(frame, LatticeSequenceState(320, 240, frames=frames, age=1, last="lost",
                                                                           vp=corner, grid_vp=corner))
            assert rec.status == STATUSES[int(step.status[b])] and ref.grid_vp == tuple(new.grid_vp[b].tolist())
    assert len(seen) >= 3  # the swept heights won on several frames


def test_lattice_vp_both_paths_on_adversarial_coefficients() -> None:
    # converging, parallel, diverging, clamped near the bottom, non-finite: one rule in both paths
    from torchrow.functional.lattice_tracking import lattice_vp as tvp
    from torchrow.reference.lattice_tracking import lattice_vp as rvp

    h = 240
    coefs = [[160.0, 0.5, 0, 0, 40.0, 0.2, 0], [100.0, -0.3, 0, 0, 50.0, 0.0, 0], [100.0, -0.3, 0, 0, 50.0, -0.1, 0],
             [10.0, 2.0, 0, 0, 40.0, 1e3, 0], [10.0, 2.0, 0, 0, 40.0, 1e-9, 0], [math.nan, 0.1, 0, 0, 40.0, 0.2, 0],
             [160.5, 0.0, 0, 0, 30.0, 0.1, 0]]
    fallback = (7, -9)
    got = tvp(torch.tensor(coefs, dtype=torch.float64), h, torch.tensor([fallback] * len(coefs)))
    want = [rvp(c, h, fallback) for c in coefs]
    assert [tuple(v) for v in got.tolist()] == want
    assert want[0] == (160 - 100, h - 1 - 200)  # t = -d0 / d1 = -200
    assert want[1][1] == want[2][1] == h - 1 - 8 * h  # not converging upwards: the far VP
    assert want[3][1] == h - 1 - h // 4  # clamped: never within a quarter height of the bottom
    assert want[5] == fallback and want[6] == (160, h - 1 - 300)  # NaN; 160.5 rounds half to even


def test_horizon_in_view_tracks_with_vp_heights_inside_the_image() -> None:
    # a camera tilted 8 deg sees the horizon at image row 57; grid heights on it are admitted and
    # the tracked VP follows the rows (both paths agree; lateral offset and heading hold)
    cam = CameraModel.from_json({"height_m": 1.0, "tilt_deg": 8, "hfov_deg": 70}, (320, 180))
    field = GroundField(plant_radius_m=0.03, seed=2)
    keys = [CameraPose(0.05, 0.0, 0.0), CameraPose(0.05, 0.0, 1.0)]
    frames = [render_camera(field, cam, p, frame=i).image for i, p in enumerate(camera_path(keys, 4))]
    p = Params(video_width=320, mode="improved", lattice_vp_heights=(40, 50, 60, 70), **FORWARD)
    got = torchrow.Tracker(p, camera=cam).track([frames])[0]
    same(RefTracker(p, camera=cam).track(frames), got)
    recs = [r.to_record() for r in got]
    assert [r["state"] for r in recs] == ["lost"] + ["in_row"] * (len(recs) - 1)
    assert sum(not r["hough_ran"] for r in recs) >= 3  # tracked frames: no VP search
    assert all(abs(r["lateral_m"] - 0.05) < 0.03 and abs(r["heading_rad"]) < math.radians(1.5) for r in recs)


def test_frame_state_both_paths_on_every_case() -> None:
    # every status x previous state x row end (none, near the top, mid, bottom quarter) x resolvable row
    from torchrow.core.steering import LATTICE_STATES
    from torchrow.functional.lattice_tracking import frame_state as tstate
    from torchrow.reference.lattice_tracking import frame_state as rstate

    h, p = 240, P
    cases = list(itertools.product(("ok", "weak"), (None, *LATTICE_STATES), (None, 0, 30, 100, 200, 239),
                                   (0, 25, 92, 240), (True, False)))
    want = [rstate(st, last, y, res, h, p, conf) for st, last, y, res, conf in cases]
    got = tstate(torch.tensor([st == "ok" for st, *_ in cases]),
                 torch.tensor([-1 if last is None else LATTICE_STATES.index(last) for _, last, *_ in cases]),
                 torch.tensor([0 if y is None else y for _, _, y, *_ in cases]),
                 torch.tensor([y is not None for _, _, y, *_ in cases]),
                 torch.tensor([res for *_, res, _ in cases]), h, p, torch.tensor([conf for *_, conf in cases]))
    assert [LATTICE_STATES[c] for c in got.tolist()] == want
    assert set(want) == set(LATTICE_STATES)
    # an unconfirmed lattice (acquisition, 11.7) is lost where rows lie ahead, headland where they end
    assert {w for w, c in zip(want, cases) if c[0] == "ok" and not c[4]} == {"lost", "headland"}


def test_confirms_both_paths() -> None:
    # acquisition (11.7): the comb spacings agree within lattice_track_spacing_tol of the last ok lattice's
    from torchrow.functional.lattice_tracking import confirms as tconf
    from torchrow.reference.lattice_tracking import confirms as rconf

    pairs = [(d, prev) for d in (16, 85, 99, 100, 101, 115, 116, 139, 320) for prev in (0, 1, 84, 96, 100, 139)]
    want = [rconf(d, prev, P) for d, prev in pairs]
    got = tconf(torch.tensor([d for d, _ in pairs]), torch.tensor([prev for _, prev in pairs]), P)
    assert got.tolist() == want
    assert rconf(115, 100, P) and not rconf(116, 100, P) and rconf(85, 100, P) and not rconf(84, 100, P)
    assert not rconf(100, 0, P) and not rconf(139, 96, P)
