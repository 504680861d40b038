"""Steering signals of the video tracker against synthetic ground truth (README figure).

A 500x281 synthetic field (five plant rows) seen by a camera that drifts sideways by
0.8 px/frame and turns by 0.004 rad/frame for 40 frames; the central row has no plants on
frames 20-23. Tracks it with ``torchrow.Tracker`` (K = 5) and plots the estimated and true
``heading_px`` and ``lateral_px``; prints the errors.

    python docs/tracker_steering.py [--out docs/tracker_steering.png]
"""

from __future__ import annotations

import argparse
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import torchrow
from torchrow.evaluation.synthetic import FieldSpec, sequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/tracker_steering.png")
    ap.add_argument("--frames", type=int, default=40)
    args = ap.parse_args()
    spec = FieldSpec.at_size(500, 281, n_rows=5, seed=21)
    gap = (20, 24)
    frames = sequence(spec, args.frames, drift_px_per_frame=0.8, heading_rad_per_frame=0.004, gap=gap)
    hfov = math.degrees(2 * math.atan((spec.width / 2) / spec.focal))  # the renderer's pinhole focal
    res = torchrow.Tracker(hfov_deg=hfov).track([[f.image for f in frames]])[0]
    t = list(range(len(frames)))
    fig, axes = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for ax, key, label in ((axes[0], "heading_px", "heading (px, VP x - W/2)"),
                           (axes[1], "lateral_px", "lateral offset (px, central row x - W/2)")):
        ax.plot(t, [getattr(f, key) for f in frames], "k-", lw=1.5, label="ground truth")
        ax.plot(t, [getattr(r, key) if getattr(r, key) is not None else float("nan") for r in res], "o-", ms=3,
                lw=1, c="tab:blue", label="tracker")
        hough = [i for i, r in enumerate(res) if r.hough_ran]
        ax.plot(hough, [getattr(res[i], key) for i in hough], "s", ms=5, mfc="none", c="tab:orange",
                label="Hough frame")
        ax.axvspan(gap[0] - 0.5, gap[1] - 0.5, color="tab:red", alpha=0.1, label="central row missing")
        ax.set_ylabel(label, fontsize=8)
        ax.legend(fontsize=7, loc="upper left")
    axes[1].set_xlabel("frame")
    fig.suptitle("torchrow.Tracker on a synthetic moving camera (500x281, K=5)", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out, dpi=80)
    out_gap = [i for i in t if not (gap[0] <= i < gap[1] + 5)]  # the gap and the frames until the next Hough run

    def errs(key: str, idx: list[int]) -> list[float]:
        return [abs(getattr(res[i], key) - getattr(frames[i], key)) for i in idx if getattr(res[i], key) is not None]

    rad = [abs(res[i].heading_rad + frames[i].heading_rad) for i in t]  # REP 103 sign vs image sign
    print(f"statuses: {sum(r.status == 'ok' for r in res)}/{len(res)} ok, Hough on {sum(r.hough_ran for r in res)}")
    for key in ("heading_px", "lateral_px"):
        e_all, e_ok = errs(key, t), errs(key, out_gap)
        print(f"{key}: all frames max {max(e_all):.2f} mean {sum(e_all) / len(e_all):.2f} px; "
              f"outside the gap max {max(e_ok):.2f} mean {sum(e_ok) / len(e_ok):.2f} px")
    print(f"heading_rad: max error {max(rad):.4f} rad (hfov {hfov:.2f} deg)")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
