"""Metric steering on a rendered drive: lateral, heading and spacing errors of the tracker.

A pinhole camera (``torchrow.evaluation.synthetic.render_camera``, exact ground truth) drives
along a row, turns, changes to the next row and reaches the end of the field; the faithful
tracker (reference path) with that camera model reports ``lateral_m``, ``heading_rad`` and
``spacing_m`` per frame. Prints the per-frame errors and their medians (no timing; no data
needed). Accuracy only: informative, the test suite holds a smaller case (tests/test_camera.py).

    python benchmarks/bench_camera.py [--frames-per-leg 6] [--radius 0.03] [--width 320]
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from torchrow import Params
from torchrow.core.camera import CameraModel
from torchrow.evaluation.synthetic import CameraPose, GroundField, camera_path, render_camera
from torchrow.reference import Tracker as RefTracker


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames-per-leg", type=int, default=6)
    ap.add_argument("--radius", type=float, default=0.03, help="mean leaf-clump radius (m)")
    ap.add_argument("--width", type=int, default=320, help="image and working width (4:3 frames)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    w, h = args.width, args.width * 3 // 4
    cam = CameraModel.from_json({"height_m": 1.0, "tilt_deg": 30, "hfov_deg": 70}, (w, h))
    field = GroundField(plant_radius_m=args.radius, row_end_m=6.0, seed=args.seed)
    keys = [CameraPose(0.05, 0.0, 0.0), CameraPose(0.05, 0.12, 0.8),  # along row 0, turning left
            CameraPose(0.25, 0.12, 1.6), CameraPose(0.55, -0.05, 2.4),  # over to row -1
            CameraPose(0.55, 0.0, 6.5)]  # along it past the end of the rows
    poses = camera_path(keys, args.frames_per_leg)
    frames = [render_camera(field, cam, p, frame=i) for i, p in enumerate(poses)]
    res = RefTracker(Params(video_width=w), camera=cam).track([f.image for f in frames])
    lat, head, spac = [], [], []
    print("frame  along  true lat/head/end      got lat/head/spacing       status")
    for i, (r, f) in enumerate(zip(res, frames)):
        got = (r.lateral_m, r.heading_rad, r.spacing_m)
        if None not in got:
            lat.append(abs(r.lateral_m - f.lateral_m))
            head.append(abs(r.heading_rad - f.heading_rad))
            spac.append(abs(r.spacing_m - f.spacing_m))
        txt = "   ---" if None in got else f"{got[0]:+.3f} {math.degrees(got[1]):+6.2f}° {got[2]:.3f}"
        print(f"{i:5d} {f.pose.along_m:6.2f}  {f.lateral_m:+.3f} {math.degrees(f.heading_rad):+6.2f}° "
              f"{f.row_end_m:5.2f}   {txt}   {r.status}")
    if lat:
        print(f"lateral error median {100 * np.median(lat):.2f} cm (max {100 * max(lat):.2f}), heading median "
              f"{math.degrees(np.median(head)):.3f}° (max {math.degrees(max(head)):.3f}), spacing median "
              f"{100 * np.median(spac):.2f} cm; {len(lat)} of {len(res)} frames with metric signals")


if __name__ == "__main__":
    main()
