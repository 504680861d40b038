"""The VP search's fold peaks with every spacing at once against spacing by spacing, the choice
behind ``AT_ONCE_ROWS`` and ``EXPORT_AT_ONCE_ROWS`` (ALGORITHM.md 11.5):
``python benchmarks/bench_vp_fold.py [--data DIR] [--frames N] [--rounds R] [--no-onnx]``.

On Caterra rover frames at the lattice tracker's working size (500x281, the forward-camera
setting; green masks of section 11.1) times :func:`torchrow.functional.lattice.vp_search` at the
(image, VP) pair counts a tracker meets: tracked windows at batch 1, 2 and 3 (15, 30, 45 pairs), a
search after a loss (the window and one grid height) at batch 1 and 2 (41, 82), and a whole grid
at batch 1 (182). Eagerly on one and on two threads, each form forced per call (the bound set
to 0 or above every count), each batch's fastest of ``--rounds`` runs with both forms
interleaved, summed over the batches (compare the two forms within a row, not the rows). Then
(unless ``--no-onnx``) ``vp_search`` alone exported for the search after a loss and for the
whole grid at batch 1, in each form, on one onnxruntime thread with torchrow's session options
(:func:`torchrow.onnx.runtime.session_options`): the fastest of 30 runs on the
first frame, the two forms' sessions alternating (the spacing-by-spacing exports take about 3
minutes each). Both forms must give the same VPs, eagerly and in onnxruntime. Prints a table;
appends nothing to RESULTS.md. Run from the repository root, with nothing else running.
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
from _common import data_root, environment

from torchrow import Params
from torchrow.core.io import load_image
from torchrow.core.params import FORWARD_CAMERA
from torchrow.functional import lattice as flattice
from torchrow.onnx.runtime import session_options
from torchrow.reference.lattice import green_mask

PARAMS = Params(mode="improved", video_width=500, **FORWARD_CAMERA)
NEAR = (250, -40)  # a grid VP near the top edge, as the rover frames' VPs lie
SWEEP = 3  # the grid height searched beside the window after a loss
NEVER, ALWAYS = 0, 1 << 30


#: (search, batch, windowed, swept) per case
CASES = [("window", 1, True, False), ("window", 2, True, False), ("window", 3, True, False),
         ("after a loss", 1, True, True), ("after a loss", 2, True, True), ("whole grid", 1, False, False)]


def _args(batch: list[torch.Tensor], windowed: bool, swept: bool) -> tuple:
    b = len(batch)
    near = torch.tensor([NEAR] * b) if windowed else None
    sweep = torch.full((b,), SWEEP, dtype=torch.int64) if swept else None
    return torch.stack(batch), near, sweep


def _pairs(h: int, w: int, batch: int, windowed: bool, swept: bool) -> int:
    grid = flattice.vp_table(h, w, PARAMS, torch.device("cpu"))[0]
    cols = w // PARAMS.lattice_vp_step + 1
    n = (flattice.vp_window(torch.tensor([NEAR]), None, w, PARAMS).shape[1] + (cols if swept else 0)) if windowed \
        else grid.shape[0]
    return batch * n


def eager(masks: list[torch.Tensor], rounds: int) -> list[str]:
    h, w = masks[0].shape
    lines = []
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for name, b, windowed, swept in CASES:
            total = {"at once": 0.0, "by spacing": 0.0}
            for i in range(0, len(masks) - b + 1, b):
                mask, near, sweep = _args(masks[i:i + b], windowed, swept)
                best, got = {}, {}
                for r in range(rounds):
                    for form in (("at once", "by spacing") if r % 2 == 0 else ("by spacing", "at once")):
                        flattice.AT_ONCE_ROWS = ALWAYS if form == "at once" else NEVER
                        t0 = time.perf_counter()
                        got[form] = flattice.vp_search(mask, PARAMS, None, near, sweep)
                        best[form] = min(best.get(form, float("inf")), time.perf_counter() - t0)
                if not torch.equal(got["at once"], got["by spacing"]):
                    raise SystemExit(f"{name} at batch {b}: the two forms' VPs differ")
                for form in total:
                    total[form] += best[form] * 1e3
            a, s = total["at once"], total["by spacing"]
            lines.append(f"| eager, {threads} thread(s) | {name} | {b} | {_pairs(h, w, b, windowed, swept)} | "
                         f"{a:.1f} | {s:.1f} | {a / s:.2f} |")
    return lines


def onnx(mask: torch.Tensor) -> list[str]:
    import onnxruntime as ort

    h, w = mask.shape
    dev = torch.device("cpu")
    # the tables an export of the tracker step builds before tracing (torchrow.onnx.to_onnx)
    flattice.vp_gather_table(h, w, PARAMS, dev)
    flattice.vp_window_table(h, w, PARAMS, dev)
    flattice.vp_fold_tables(h, w, PARAMS, dev)
    lines = []
    tmp = tempfile.TemporaryDirectory()
    for name, windowed, swept in (("after a loss", True, True), ("whole grid", False, False)):
        m, near, sweep = _args([mask], windowed, swept)
        args = (m,) if near is None else (m, near, sweep)

        class Search(torch.nn.Module):
            def forward(self, m, near=None, sweep=None):
                return flattice.vp_search(m, PARAMS, None, near, sweep)

        sessions, vps = {}, {}
        for form in ("at once", "by spacing"):
            flattice.EXPORT_AT_ONCE_ROWS = ALWAYS if form == "at once" else NEVER
            path = Path(tmp.name) / f"{name}-{form}.onnx".replace(" ", "_")
            t0 = time.perf_counter()
            torch.onnx.export(Search().eval(), args, str(path), dynamo=True, optimize=True, verbose=False)
            print(f"  onnxruntime {name}, {form}: export {time.perf_counter() - t0:.0f} s", flush=True)
            # opened as torchrow's runners open their models
            sessions[form] = ort.InferenceSession(str(path), session_options(1), providers=["CPUExecutionProvider"])
        feeds = {i.name: a.numpy() for i, a in zip(sessions["at once"].get_inputs(), args)}
        ms = {form: float("inf") for form in sessions}
        for r in range(30):  # the two sessions alternate, so that the VM's drift hits both alike
            for form in (("at once", "by spacing") if r % 2 == 0 else ("by spacing", "at once")):
                t0 = time.perf_counter()
                vps[form] = sessions[form].run(None, feeds)[0]
                ms[form] = min(ms[form], (time.perf_counter() - t0) * 1e3)
        if not np.array_equal(vps["at once"], vps["by spacing"]):
            raise SystemExit(f"onnxruntime, {name}: the two forms' VPs differ")
        a, s = ms["at once"], ms["by spacing"]
        lines.append(f"| onnxruntime, 1 thread | {name} | 1 | {_pairs(h, w, 1, windowed, swept)} | {a:.1f} | {s:.1f} | "
                     f"{a / s:.2f} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None, help="folder holding caterra_video/ (default $TORCHROW_DATA)")
    ap.add_argument("--frames", type=int, default=12, help="rover frames (every 8th from frame 1)")
    ap.add_argument("--rounds", type=int, default=7, help="runs per case and form; the fastest counts")
    ap.add_argument("--no-onnx", action="store_true", help="skip the exported searches")
    args = ap.parse_args()
    files = sorted((data_root(args.data) / "caterra_video").glob("*.jpg"))[1::8][:args.frames]
    masks = [torch.from_numpy(green_mask(load_image(f, PARAMS.video_width), 0, PARAMS)) for f in files]
    if not masks:
        raise SystemExit("no Caterra frames found")
    h, w = masks[0].shape
    print(environment())
    print(f"{len(masks)} Caterra frames at {w}x{h}, spacings {PARAMS.lattice_min_spacing}.."
          f"{PARAMS.lattice_max_spacing}; bounds now: AT_ONCE_ROWS {flattice.AT_ONCE_ROWS}, "
          f"EXPORT_AT_ONCE_ROWS {flattice.EXPORT_AT_ONCE_ROWS}", flush=True)
    lines = ["| run | search | batch | pairs | at once, ms | spacing by spacing, ms | ratio |",
             "|---|---|---|---|---|---|---|"]
    lines += eager(masks, args.rounds)
    print("\n".join(lines), flush=True)
    if not args.no_onnx:
        lines += onnx(masks[0])
        print("\n".join(lines[-2:]))


if __name__ == "__main__":
    main()
