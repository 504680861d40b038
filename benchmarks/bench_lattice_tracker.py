"""Lattice tracker (``--mode improved`` video, ALGORITHM.md 11.7): frames/s at 500x281 and accuracy.

A rendered drive (``torchrow.evaluation.synthetic.render_camera``: camera 1 m high, tilt 30°, 70°
field of view, 50 cm rows; along a row, a turn, over to the next row, on past the rows' end) at
500x281, the working size of ``video_width`` 500:

1. frames/s of the tensor tracker ``torchrow.Tracker(mode="improved")`` for one sequence (with
   each frame's time: tracked frames, full searches, the worst after frame 0) and for a batch
   of 8 sequences in lock-step (8 shifted windows of the drive), and of the reference
   ``torchrow.reference.Tracker(mode="improved")`` on the first frames;
2. the records' accuracy against the renderer's truth: ``lateral_m`` (from the tracked row: the
   planted row nearest the camera on frame 0, moved by each reported row change) and
   ``heading_rad`` error medians (frames more than 1.5 m before the rows' end), the row end error on ``row_end_ahead``
   frames, the states and the row changes.

Frames are rendered before timing. Tensor and reference records are checked to agree.

    python benchmarks/bench_lattice_tracker.py [--frames-per-leg 10] [--reference-frames 5] [--no-write]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from _common import append_results  # type: ignore[import-not-found]

import torchrow
from torchrow import Params
from torchrow.core.camera import CameraModel
from torchrow.core.params import FORWARD_CAMERA
from torchrow.core.results import record_differences
from torchrow.evaluation.synthetic import CameraPose, GroundField, camera_path, render_camera
from torchrow.reference import Tracker as RefTracker

WIDTH, HEIGHT = 500, 281


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames-per-leg", type=int, default=10)
    ap.add_argument("--reference-frames", type=int, default=5, help="frames the (slow) reference tracks")
    ap.add_argument("--radius", type=float, default=0.03, help="mean leaf-clump radius (m)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    cam = CameraModel.from_json({"height_m": 1.0, "tilt_deg": 30, "hfov_deg": 70}, (WIDTH, HEIGHT))
    field = GroundField(plant_radius_m=args.radius, row_end_m=12.0, seed=args.seed)
    keys = [CameraPose(0.05, 0.0, 0.0), CameraPose(0.05, 0.0, 1.5), CameraPose(0.12, 0.08, 3.0),
            CameraPose(-0.2, -0.05, 4.5), CameraPose(-0.45, 0.0, 6.0), CameraPose(-0.45, 0.0, 8.0),
            CameraPose(-0.45, 0.0, 12.5)]
    truth = [render_camera(field, cam, p, frame=i) for i, p in enumerate(camera_path(keys, args.frames_per_leg))]
    frames = [f.image for f in truth]
    p = Params(mode="improved", video_width=WIDTH, **FORWARD_CAMERA)  # the forward-camera setting (11.3.1)
    print(f"{len(frames)} rendered frames at {WIDTH}x{HEIGHT}, torch threads {torch.get_num_threads()}", flush=True)

    ten = torchrow.Tracker(p, camera=cam)
    ten.track([frames[:2]])  # warm-up: the VP table of this size, allocator
    rows = []
    got, per_frame = [], []
    t0 = tick = time.perf_counter()
    for _, rec, _ in ten.track_iter([frames]):
        now = time.perf_counter()
        got.append(rec)
        per_frame.append((now - tick, bool(rec.hough_ran)))
        tick = now
    t1 = time.perf_counter() - t0
    rows.append(("tensor, B = 1", len(frames), t1))
    later = per_frame[1:]
    full = [t for t, f in later if f]
    tracked = [t for t, f in later if not f]
    frame_ms = (f"B = 1 per frame after frame 0: tracked median {1e3 * float(np.median(tracked)):.1f} ms "
                f"({len(tracked)} frames), full search median {1e3 * float(np.median(full)) if full else 0:.1f} ms "
                f"({len(full)} frames), worst {1e3 * max(t for t, _ in later):.1f} ms")
    n = max(2, len(frames) - 7)
    batch = [frames[b:b + n] for b in range(8)]
    t0 = time.perf_counter()
    ten.track(batch)
    rows.append(("tensor, B = 8 in lock-step", 8 * n, time.perf_counter() - t0))
    k = min(args.reference_frames, len(frames))
    t0 = time.perf_counter()
    ref = RefTracker(p, camera=cam).track(frames[:k])
    rows.append(("reference, B = 1", k, time.perf_counter() - t0))
    diff = [d for r, g in zip(ref, got) for d in record_differences(r.to_record(), g.to_record())]
    for name, count, sec in rows:
        print(f"  {name}: {count} frames in {sec:.2f} s, {count / sec:.1f} frames/s")
    print(f"  {frame_ms}")
    print(f"  tensor = reference on the first {k} frames: {not diff}" + (f" ({diff[:3]})" if diff else ""))

    # the truth for the tracked row: the planted row nearest the camera on frame 0, then its
    # neighbour on the right (+1) or left (-1) from each frame that reports a row change
    sp = truth[0].spacing_m
    k = round((truth[0].lateral_m - truth[0].pose.lateral_m) / sp)
    tracked = []
    for r, f in zip(got, truth):
        k += r.row_change or 0
        tracked.append(f.pose.lateral_m + k * sp)
    lat = [abs(r.lateral_m - t) for r, f, t in zip(got, truth, tracked)
           if r.lateral_m is not None and f.row_end_m is not None and f.row_end_m > 1.5]
    head = [abs(r.heading_rad - f.heading_rad) for r, f in zip(got, truth)
            if r.heading_rad is not None and f.row_end_m is not None and f.row_end_m > 1.5]
    end = [abs(r.row_end_m - f.row_end_m) for r, f in zip(got, truth) if r.row_end_m is not None]
    states: dict[str, int] = {}
    for r in got:
        states[str(r.state)] = states.get(str(r.state), 0) + 1
    changes = [(r.frame, r.row_change) for r in got if r.row_change]
    acc = (f"lateral_m error median {100 * float(np.median(lat)):.2f} cm (max {100 * max(lat):.1f}, {len(lat)} frames), "
           f"heading median {math.degrees(float(np.median(head))):.3f}° (max {math.degrees(max(head)):.2f}), "
           + (f"row end median {float(np.median(end)):.2f} m (max {max(end):.2f}, {len(end)} frames), " if end else "")
           + f"states {states}, row changes {changes}")
    print("  " + acc)
    if not args.no_write:
        table = ["| run | frames | s | frames/s |", "|---|---|---|---|"]
        table += [f"| {name} | {count} | {sec:.2f} | {count / sec:.1f} |" for name, count, sec in rows]
        append_results("Lattice tracker (--mode improved video), rendered 500x281 drive",
                       "python benchmarks/bench_lattice_tracker.py " + " ".join(f"--{k.replace('_', '-')} {v}"
                                                                             for k, v in vars(args).items()
                                                                             if k != "no_write"),
                       "\n".join(table + ["", frame_ms, "", acc]))


if __name__ == "__main__":
    main()
