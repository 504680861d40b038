"""Video-mode tracker: reference vs tensor frames/s, side by side in one run.

1. One sequence: the 100 Caterra frames (500x281 working size), reference
   ``torchrow.reference.Tracker`` vs tensor ``torchrow.Tracker`` (B = 1).
2. A batch of 8 sequences: 8 shifted windows of the Caterra frames (sequence ``b`` is frames
   ``8b .. 8b + L - 1``), so the sequences differ and their Hough frames need not align;
   the reference tracks them one after the other, the tensor tracker in lock-step.

Frames are decoded and resized before timing (the CLI's JPEG decoding is not counted).
The reference/tensor results are also checked to be identical (Hough frames, k, statuses).

    python benchmarks/bench_tracker.py [--data ../shared/data] [--quick] [--no-write]
"""

from __future__ import annotations

import argparse
import time

import torch
from _common import append_results, data_root  # type: ignore[import-not-found]

import torchrow
from torchrow import Params
from torchrow.core.io import load_image
from torchrow.reference import Tracker as RefTracker


def same(ref: list, got: list) -> bool:
    key = [(r.status, r.hough_ran, r.k, r.n_rows) for r in ref]
    return key == [(r.status, r.hough_ran, r.k, r.n_rows) for r in got]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--quick", action="store_true", help="fewer frames (a smoke run)")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--length", type=int, default=25, help="frames per sequence of the batch of 8")
    args = ap.parse_args()
    root = data_root(args.data)
    p = Params()
    files = sorted((root / "caterra_video").glob("rgb*.jpg"))
    n_single = 20 if args.quick else len(files)
    length = 8 if args.quick else args.length
    frames = [load_image(f, p.video_width) for f in files]
    print(f"{len(frames)} Caterra frames at {frames[0].shape[1]}x{frames[0].shape[0]}, torch threads "
          f"{torch.get_num_threads()}", flush=True)

    ref = RefTracker(p)
    ten = torchrow.Tracker(p)
    ten.track([frames[:3]])  # warm-up: LAB table pages, allocator

    rows = []
    # 1. one sequence
    seq = frames[:n_single]
    t0 = time.perf_counter()
    r1 = ref.track(seq)
    t_ref = time.perf_counter() - t0
    t0 = time.perf_counter()
    g1 = ten.track([seq])[0]
    t_ten = time.perf_counter() - t0
    assert same(r1, g1), "tensor and reference trackers differ on the single sequence"
    hough = sum(r.hough_ran for r in r1)
    rows.append(("one sequence (Caterra)", len(seq), t_ref, t_ten))
    print(f"one sequence: reference {len(seq) / t_ref:.2f} frames/s, tensor {len(seq) / t_ten:.2f} frames/s "
          f"(Hough on {hough} frames)", flush=True)

    # 2. batch of 8 shifted sequences
    seqs = [frames[8 * b: 8 * b + length] for b in range(8)]
    n8 = sum(len(s) for s in seqs)
    t0 = time.perf_counter()
    r8 = [ref.track(s) for s in seqs]
    t_ref8 = time.perf_counter() - t0
    t0 = time.perf_counter()
    g8 = ten.track(seqs)
    t_ten8 = time.perf_counter() - t0
    assert all(same(a, b) for a, b in zip(r8, g8)), "tensor and reference trackers differ on the batch"
    rows.append((f"batch of 8 sequences x {length} frames", n8, t_ref8, t_ten8))
    print(f"batch of 8: reference {n8 / t_ref8:.2f} frames/s, tensor {n8 / t_ten8:.2f} frames/s", flush=True)

    body = ["| workload | frames | reference frames/s | tensor frames/s | tensor / reference |",
            "|---|---|---|---|---|"]
    for name, n, tr, tt in rows:
        body.append(f"| {name} | {n} | {n / tr:.2f} | {n / tt:.2f} | **{tr / tt:.2f}x** |")
    body.append("")
    body.append(f"Hough stage on {hough} of {len(seq)} frames of the single sequence (K = {p.hough_every}). "
                "Identical Hough frames, k, statuses and row counts checked in the same run. The machine is "
                "shared (2 cores, other jobs running): timings are noisy.")
    text = "\n".join(body)
    print(text)
    if not args.no_write:
        append_results("Video tracker: reference vs tensor" + (" (quick)" if args.quick else ""),
                       "python benchmarks/bench_tracker.py" + (" --quick" if args.quick else ""), text)


if __name__ == "__main__":
    main()
