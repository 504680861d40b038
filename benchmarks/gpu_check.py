"""GPU parity and throughput of the tensor detector (issue 4 and 6; run where a GPU is lent).

1. Parity: all CRBD images through ``CropRowDetector(device=DEV)`` and through the CPU
   tensor path (itself identical to the reference, see the test suite). Every record field
   is compared: discrete outputs exactly, vanishing point and rows within 1e-6 px. Every
   difference is counted per field and listed by image, never hidden (ALGORITHM.md,
   "Identical results": on a GPU, float rounding that flips a discrete output is reported).
2. Throughput: a batch of ``--batch`` images (CRBD repeated) timed end to end on the
   device, after a warm-up, with a device synchronisation; plus one per-stage profile.
3. Latency: ``--latency`` single-image calls (batch 1, CRBD images in turn), median and
   worst, as a robot calls the detector on each frame.
4. Video (issue 27): the first ``--video`` Caterra frames tracked by ``torchrow.Tracker`` in
   the improved mode's forward-camera setting at 500 px (as ``check_lattice_onnx.py``), one
   sequence (batch 1), on the CPU and on the device: records compared (discrete values
   equal, floats within 1e-4), and the device's time per frame (host loop included).

Each of ``--modes`` (default: the faithful and the improved mode, default parameters) runs
1-3; 4 runs once.

Without a GPU, ``--device cpu`` runs the same script as a dry run (parity of the threaded
CPU path against the single-threaded one).

Usage: ``python benchmarks/gpu_check.py [--device cuda] [--batch 1024] [--reps 3] [--latency 50]
[--modes faithful improved] [--video 40] [--data DIR]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import append_results, data_root

from torchrow.core.io import load_image
from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.core.results import record_differences
from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.datasets import CRBD


def compare(cpu: list, dev: list) -> dict[str, list[str]]:
    """Field -> names of images whose record differs, by ALGORITHM.md's "Identical results"
    (:func:`~torchrow.core.results.record_differences`: discrete values equal, floats within
    1e-6 px)."""
    diffs: dict[str, list[str]] = {}
    for c, d in zip(cpu, dev):
        fields = {line.split(":")[0].lstrip(".").split(".")[0].split("[")[0]
                  for line in record_differences(c.to_record(), d.to_record())}
        for key in sorted(fields):
            diffs.setdefault(key or "record", []).append(c.name)
    return diffs


def check_mode(mode: str, batch: torch.Tensor, names: list[str], args: argparse.Namespace) -> list[str]:
    """Parity, throughput and latency of one mode on ``args.device``; the report's lines."""
    params = Params(mode=mode)
    cpu = CropRowDetector(params, workers=1)(batch).results(names)
    dev_det = CropRowDetector(params, device=args.device)
    t0 = time.perf_counter()
    dev = dev_det(batch).results(names)
    first_s = time.perf_counter() - t0
    diffs = compare(cpu, dev)

    reps = -(-args.batch // len(names))
    big = batch.repeat(reps, 1, 1, 1)[:args.batch].to(args.device)
    sync = (lambda: torch.cuda.synchronize()) if args.device.startswith("cuda") else (lambda: None)
    if args.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    dev_det(big)
    sync()
    times = []
    for _ in range(args.reps):
        t0 = time.perf_counter()
        dev_det(big)
        sync()
        times.append(time.perf_counter() - t0)
    best = min(times)
    peak = torch.cuda.max_memory_allocated() / 2**30 if args.device.startswith("cuda") else float("nan")
    stages = dev_det(big, profile=True).timings

    singles = batch.to(args.device)
    lat = []
    for i in range(args.latency + 3):
        one = singles[i % len(names)][None]
        sync()
        t0 = time.perf_counter()
        dev_det(one)
        sync()
        if i >= 3:  # the first calls build tables and warm the allocator
            lat.append(time.perf_counter() - t0)

    lines = [f"### {mode} mode", "",
             f"Parity on all {len(names)} CRBD images against the CPU tensor path "
             f"(first call, including table uploads: {first_s:.1f} s).", ""]
    if diffs:
        lines.append("| field | images differing | examples |")
        lines.append("|---|---|---|")
        for key, who in sorted(diffs.items()):
            lines.append(f"| {key} | {len(who)} | {', '.join(str(w) for w in who[:5])} |")
    else:
        lines.append("Every record field equal (discrete exactly, VP and rows within 1e-6 px): 0 differences.")
    lines += ["", f"Batch {args.batch}: best of {args.reps}: {best:.3f} s = **{args.batch / best:.0f} images/s** "
              f"(all runs: {', '.join(f'{t:.3f}' for t in times)} s); peak allocated {peak:.1f} GiB.", "",
              "Per stage (s, one profiled run): " + ", ".join(f"{k} {v:.3f}" for k, v in stages.items())]
    if lat:
        lines += ["", f"Batch 1 ({len(lat)} calls after 3 warm-up calls): median {1e3 * float(np.median(lat)):.1f} ms, "
                  f"worst {1e3 * max(lat):.1f} ms."]
    return lines


def check_video(root: Path, args: argparse.Namespace) -> list[str]:
    """Tracker parity and per-frame time on the first ``args.video`` Caterra frames."""
    import torchrow

    params = Params(mode="improved", video_width=500, **FORWARD_CAMERA)
    files = sorted((root / "caterra_video").glob("*.jpg"))[:args.video]
    frames = [torch.from_numpy(load_image(f, params.video_width)).permute(2, 0, 1)[None].contiguous() for f in files]
    h, w = frames[0].shape[-2:]
    sync = (lambda: torch.cuda.synchronize()) if args.device.startswith("cuda") else (lambda: None)

    def track(tracker, device):
        st, recs, times = None, [], []
        for x in frames:
            x = x.to(device)
            sync()
            t0 = time.perf_counter()
            step, st = tracker(x, st)
            sync()
            times.append(time.perf_counter() - t0)
            recs.append(tracker.results(step, st, w, h)[0].to_record())
        return recs, times

    cpu, _ = track(torchrow.Tracker(params, workers=1), "cpu")
    dev_tr = torchrow.Tracker(params, device=args.device)
    track(dev_tr, args.device)  # tables, allocator
    dev, times = track(dev_tr, args.device)
    differing = [i for i, (a, b) in enumerate(zip(cpu, dev)) if record_differences(a, b, 1e-4)]
    later = times[1:]
    return ["### video: lattice tracker, improved forward-camera setting", "",
            f"{len(frames)} Caterra frames at {w}x{h}, one sequence: records differing from the CPU tracker: "
            f"{len(differing)}" + (f" (frames {differing[:10]})" if differing else "") + ".", "",
            f"Device, second pass: {len(frames) / sum(times):.1f} frames/s; per frame median "
            f"{1e3 * float(np.median(times)):.1f} ms, worst after frame 0 {1e3 * max(later, default=0.0):.1f} ms."]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--latency", type=int, default=50, help="single-image calls timed (0: none)")
    ap.add_argument("--modes", nargs="*", default=["faithful", "improved"], choices=["faithful", "improved"])
    ap.add_argument("--video", type=int, default=40, help="Caterra frames tracked (0: none)")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("no CUDA device visible to torch: run with --device cpu for a dry run")
    root = data_root(args.data)
    crbd = CRBD(root / "crbd")
    names = list(crbd.names)
    imgs = [load_image(crbd.image_path(i), Params().image_width) for i in range(len(names))]
    batch = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else "CPU (dry run)"
    lines = [f"Device: {name}."]
    print(lines[0], flush=True)
    parts = [lambda mode=mode: check_mode(mode, batch, names, args) for mode in args.modes]
    if args.video:
        parts.append(lambda: check_video(root, args))
    for part in parts:  # each printed as it ends: a run cut short keeps what it measured
        new = [""] + part()
        print("\n".join(new), flush=True)
        lines += new
    body = "\n".join(lines)
    if not args.no_write:
        append_results(f"GPU check ({name})", "python benchmarks/" + " ".join([Path(__file__).name] + sys.argv[1:]), body)


if __name__ == "__main__":
    main()
