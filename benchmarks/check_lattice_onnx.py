"""The exported lattice tracker step (improved mode) against torch on every Caterra frame:
``python benchmarks/check_lattice_onnx.py [--data DIR] [--model M.onnx | --out M.onnx] [--top]
[--frames N] [--cover FIRST:N ...] [--roll-grid N] [--comb-warps N] [--turn DEG] [--rounds R]
[--compare OTHER.onnx ...]``.

Exports the step at the real working size (500x281, the forward-camera setting
``Params(mode="improved", video_width=500, lattice_model="auto", lattice_min_spacing=16,
lattice_max_spacing=320, lattice_vp_origin="sky")``, batch 1; or uses ``--model``). The VP grid
counts from the camera's horizon (ALGORITHM.md 11.2), the frames pass as ``ok`` and are
tracked, with redos and scheduled full searches (section 1 inside a graph ``If``); with
``--top`` (the grid above the image) every frame is ``weak``, so every frame runs the full search;
``--cover 30:8`` darkens frames 30-37 (a lens covered: a loss, and the search after it).
``--roll-grid 30`` exports and tracks with ``lattice_roll_grid`` 30 (ALGORITHM.md 11.3.2),
``--comb-warps 6`` with ``lattice_comb_warps`` 6 as well (the warped comb of 11.3.2), and
``--turn 12`` turns every frame by 12 degrees about its centre (a rolled camera; black corners).
Tracks the frames with :class:`torchrow.Tracker` and with
:class:`~torchrow.onnx.runtime.OnnxTracker`, and compares the records (discrete values equal,
floats within 1e-4) and every field of every step and state (floats within 1e-9). Prints the
export time, the model's size and op census, and frames/s of onnxruntime on one and on two
intra-op threads and of torch eager on one thread (the host's frame loop included, frames
read beforehand), and per kind of frame (tracked, a scheduled full search, a tracked frame
redone in full, a full search after a frame that was not ``ok``; the full searches take the
grid's window of ALGORITHM.md 11.7, after a loss with one grid height more, frame 0 the whole
grid) the median and the slowest: each frame's time
is its fastest over ``--rounds`` passes over the sequence,
the passes of all runs interleaved, so that the VM's drift hits every run alike; ``--compare
OTHER.onnx ...`` times other exports of the same step beside it (e.g. an earlier commit's).
Run from the repository root.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data_root

import torchrow
from torchrow import Params
from torchrow.core.io import load_image
from torchrow.core.params import FORWARD_CAMERA
from torchrow.core.results import record_differences
from torchrow.onnx.checks import step_differences
from torchrow.onnx.export import to_onnx
from torchrow.onnx.metadata import model_info
from torchrow.onnx.runtime import OnnxTracker

PARAMS = Params(mode="improved", video_width=500, **FORWARD_CAMERA)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--model", default=None, help="an exported lattice tracker step (default: export one)")
    ap.add_argument("--out", default=None, help="keep the exported model here")
    ap.add_argument("--top", action="store_true", help="the VP grid counted from row 0 (every frame weak)")
    ap.add_argument("--frames", type=int, default=None, help="the first N frames only")
    ap.add_argument("--cover", nargs="*", default=[], metavar="FIRST:N", help="darken frames FIRST..FIRST+N-1")
    ap.add_argument("--rounds", type=int, default=3, help="passes per run; each frame's fastest counts")
    ap.add_argument("--compare", nargs="*", default=[], help="other exports of the step, timed beside it")
    ap.add_argument("--roll-grid", type=int, default=0, help="Params.lattice_roll_grid (11.3.2)")
    ap.add_argument("--comb-warps", type=int, default=0, help="Params.lattice_comb_warps (11.3.2; needs --roll-grid)")
    ap.add_argument("--turn", type=float, default=0.0, help="turn every frame by DEG about its centre")
    args = ap.parse_args()
    params = (PARAMS.replace(lattice_vp_origin="top") if args.top else PARAMS).replace(lattice_roll_grid=args.roll_grid,
                                                                                         lattice_comb_warps=args.comb_warps)
    files = sorted((data_root(args.data) / "caterra_video").glob("*.jpg"))[:args.frames]
    frames = [load_image(f, params.video_width) for f in files]
    if args.turn:
        import cv2

        fh, fw = frames[0].shape[:2]
        turn = cv2.getRotationMatrix2D(((fw - 1) / 2, (fh - 1) / 2), args.turn, 1.0)
        frames = [cv2.warpAffine(f, turn, (fw, fh)) for f in frames]
    for item in args.cover:
        first, _, n = item.partition(":")
        for i in range(int(first), min(int(first) + int(n), len(frames))):
            frames[i] = np.full_like(frames[i], 30)
    h, w = frames[0].shape[:2]
    print(f"{len(frames)} Caterra frames at {w}x{h}", flush=True)
    tmp = tempfile.TemporaryDirectory()
    if args.model is None:
        path = Path(args.out) if args.out else Path(tmp.name) / "lattice.onnx"
        t0 = time.perf_counter()
        to_onnx(path, height=h, width=w, batch=1, params=params, tracker=True,
                progress=lambda phase: print(f"  export: {phase} ({time.perf_counter() - t0:.0f} s)", flush=True))
        print(f"export: {time.perf_counter() - t0:.0f} s", flush=True)
    else:
        path = Path(args.model)
    info = model_info(path)
    print(f"model: {info['size'] / 2**20:.1f} MiB, {sum(info['ops'].values())} nodes; "
          + ", ".join(f"{k} {v}" for k, v in sorted(info["ops"].items())), flush=True)
    if info["params"] != params or (info["height"], info["width"], info["batch"]) != (h, w, 1):
        raise SystemExit(f"{path} was not exported with this script's parameters, size and batch 1")

    x = [torch.from_numpy(f).permute(2, 0, 1).unsqueeze(0).contiguous() for f in frames]
    eager = torchrow.Tracker(params, workers=1)
    ort = OnnxTracker(path, threads=1)
    st_e = st_o = None
    step_problems, record_problems, tracked, redo = [], [], 0, 0
    states: dict = {}
    kinds: list[str] = []  # per frame: tracked, full (a scheduled full search), redone or after a loss
    lost = False  # the previous frame's status was not ok
    for t, xt in enumerate(x):
        step_e, st_e = eager(xt, st_e)
        step_o, st_o = ort(xt, st_o)
        diff = step_differences(step_e, step_o) + step_differences(st_e, st_o)
        step_problems += [f"frame {t}: {d}" for d in diff]
        rec_e = eager.results(step_e, st_e, w, h)[0]
        rec_o = ort.results(step_o, st_o, w, h)[0]
        assert rec_e is not None and rec_o is not None
        record_problems += [f"frame {t}: {d}" for d in record_differences(rec_e.to_record(), rec_o.to_record(), 1e-4)]
        tracked += int(not bool(step_e.full[0]))
        redo += int(bool(step_e.redo[0]))
        kinds.append("redone" if bool(step_e.redo[0]) else "after a loss" if lost else "full" if bool(step_e.full[0])
                     else "tracked")
        lost = rec_e.status != "ok"
        states[rec_e.state] = states.get(rec_e.state, 0) + 1
    print(f"parity: {len(x)} frames ({tracked} tracked, {redo} redone in full; states {states}); records differing: "
          f"{len({p.split(':')[0] for p in record_problems})}; steps/states differing: "
          f"{len({p.split(':')[0] for p in step_problems})}", flush=True)
    for p in (record_problems + step_problems)[:10]:
        print("  ", p[:300])

    def step_of(run):
        return lambda xt, st: run(xt, st)[1]

    runs = {}
    for threads in (1, 2):
        for m in [path] + [Path(c) for c in args.compare]:
            name = "this export" if m == path else m.name
            runs[f"onnxruntime, {name}, {threads} thread(s)"] = (step_of(OnnxTracker(m, threads=threads)), threads)
    runs["torch eager, 1 thread"] = (step_of(eager), 1)
    runs["torch eager, 2 threads"] = (step_of(eager), 2)  # the CLI's setting on a 2-core CPU
    for step, threads in runs.values():
        torch.set_num_threads(threads)
        step(x[0], None)  # a first run allocates
    best = {name: [float("inf")] * len(x) for name in runs}
    for _ in range(args.rounds):
        for name, (step, threads) in runs.items():
            torch.set_num_threads(threads)
            st = None
            for t, xt in enumerate(x):
                t0 = time.perf_counter()
                st = step(xt, st)
                best[name][t] = min(best[name][t], time.perf_counter() - t0)
    for name, b in best.items():
        by_kind = []
        for kind in ("tracked", "full", "redone", "after a loss"):
            ms = sorted(1000 * b[t] for t in range(1, len(x)) if kinds[t] == kind)
            if ms:
                by_kind.append(f"{kind} {len(ms)}: median {ms[len(ms) // 2]:.1f}, max {ms[-1]:.1f}")
        print(f"{name}: {len(x) / sum(b):.1f} frames/s ({1000 * sum(b) / len(x):.1f} ms/frame), "
              f"frame 0 (the whole grid) {1000 * b[0]:.1f} ms, "
              f"worst after frame 0 {1000 * max(b[1:], default=0.0):.1f} ms; ms per frame after frame 0: "
              + "; ".join(by_kind), flush=True)


if __name__ == "__main__":
    main()
