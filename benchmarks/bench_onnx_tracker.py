"""Exported tracker step in onnxruntime vs the torch tracker, side by side in one run.

Exports the tracker step (default parameters, the Caterra working size 500x281, batch 1)
unless ``--model`` is given, then steps :class:`torchrow.Tracker` and
:class:`torchrow.onnx.runtime.OnnxTracker` through the same Caterra frames, compares every field of
every step and state (:func:`torchrow.onnx.checks.step_differences`: discrete fields equal,
floats within 1e-9) and times both. Appends model size, export time, frames/s and the parity
count to RESULTS.md.

    python benchmarks/bench_onnx_tracker.py [--data ../shared/data] [--frames N] [--model M] [--no-write]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import append_results, data_root  # type: ignore[import-not-found]

import torchrow
from torchrow import Params
from torchrow.core.io import load_image
from torchrow.onnx.checks import step_differences
from torchrow.onnx.export import to_onnx
from torchrow.onnx.metadata import model_info
from torchrow.onnx.runtime import OnnxTracker


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--frames", type=int, default=0, help="at most this many frames (default all 100)")
    ap.add_argument("--model", default=None, help="an exported tracker model (default: export one now)")
    ap.add_argument("--no-control-flow", action="store_true",
                    help="export without If: both branches run on every frame, masks choose")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    files = sorted((data_root(args.data) / "caterra_video").glob("*.jpg"))
    if args.frames:
        files = files[:args.frames]
    tmp = tempfile.TemporaryDirectory()
    if args.model:
        path, t_export = Path(args.model), float("nan")
        params = model_info(path)["params"]
    else:
        params = Params()
        h = load_image(files[0], params.video_width).shape[0]
        t0 = time.perf_counter()
        path = to_onnx(Path(tmp.name) / "tracker.onnx", height=h, width=params.video_width, batch=1, params=params,
                       tracker=True, control_flow=not args.no_control_flow)
        t_export = time.perf_counter() - t0
    info = model_info(path)
    frames = [torch.from_numpy(load_image(f, params.video_width)).permute(2, 0, 1).unsqueeze(0).contiguous()
              for f in files]
    t0 = time.perf_counter()
    onnx_tracker = OnnxTracker(path)
    t_open = time.perf_counter() - t0
    # onnxruntime seconds per frame after frame 0: Hough frames, tracked frames. Frame 0 is
    # reported apart: the session's first run (allocations) plus the host's colour clustering
    lat = {True: [], False: []}
    first = 0.0
    torch_tracker = torchrow.Tracker(info["params"])
    t_onnx = t_torch = 0.0
    bad, hough = 0, 0
    st_t = st_o = None
    for t, x in enumerate(frames):
        t0 = time.perf_counter()
        step_o, st_o = onnx_tracker(x, st_o)
        t1 = time.perf_counter()
        step_t, st_t = torch_tracker(x, st_t)
        t2 = time.perf_counter()
        t_onnx += t1 - t0
        t_torch += t2 - t1
        diff = step_differences(step_t, step_o) + step_differences(st_t, st_o)
        bad += bool(diff)
        hough += int(step_t.hough_ran[0])
        if t == 0:
            first = t1 - t0
        else:
            lat[bool(step_t.hough_ran[0])].append(t1 - t0)
        if diff:
            print(f"frame {t}: " + "; ".join(diff)[:300])
    n = len(frames)
    hgt, wid = info["height"], info["width"]
    ops = ", ".join(f"{k} {v}" for k, v in sorted(info["ops"].items()))
    import resource

    def ms(v: list) -> str:
        return f"mean {np.mean(v) * 1e3:.0f} ms, worst {np.max(v) * 1e3:.0f} ms" if v else "none"

    print(f"onnxruntime: frame 0 (first run, host colour) {first * 1e3:.0f} ms; then Hough frames "
          f"({len(lat[True])}) {ms(lat[True])}; tracked frames ({len(lat[False])}) {ms(lat[False])}; "
          f"session open {t_open:.1f} s; peak RSS "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10:.0f} MiB (this process: torch too)")
    lines = [f"### {n} Caterra frames ({wid}x{hgt}), one sequence (B = 1), default parameters", "",
             "| | ms / frame | frames / s |", "|---|---|---|",
             f"| torch tracker (`torchrow.Tracker.forward`) | {t_torch / n * 1e3:.0f} | {n / t_torch:.2f} |",
             f"| onnxruntime {__import__('onnxruntime').__version__} (`OnnxTracker`, CPU EP, basic optimisations) | "
             f"{t_onnx / n * 1e3:.0f} | {n / t_onnx:.2f} |", "",
             f"The Hough stage ran on {hough} of {n} frames; "
             + ("the graph skips it on the others (ONNX `If`)." if info["control_flow"] else
                "the graph runs it (masked) on every frame (exported without `If`)."), "",
             f"Model: {info['size'] / 2**20:.1f} MiB, opset {info['opset']}, {info['exporter']}, "
             f"{sum(info['ops'].values())} nodes; export time "
             + (f"{t_export:.0f} s" if t_export == t_export else "not measured (--model given)") + ".",
             "", f"Parity: {n - bad} of {n} frames identical (every step and state field; floats within 1e-9).",
             "", f"Ops: {ops}."]
    print("\n".join(lines))
    if not args.no_write:
        cmd = "python benchmarks/bench_onnx_tracker.py" + (f" --frames {args.frames}" if args.frames else "") + (
            " --model MODEL" if args.model else "") + (" --no-control-flow" if args.no_control_flow else "")
        append_results("ONNX export: tracker step, onnxruntime vs torch", cmd, "\n".join(lines))


if __name__ == "__main__":
    main()
