"""Reference implementation vs the thesis code on the thesis' 40-image CRBD sample.

The thesis code cannot run here (it is not part of torchrow); its per-image wall times were
recorded on a 2-core machine like this one and ship with the data
(``thesis_baseline/thesis_code_sample.jsonl``). This script times ``torchrow.reference.detect``
on the same images in this run, scores both with the same CRDA code, and appends a section to
``benchmarks/RESULTS.md``.

    python benchmarks/bench_reference.py [--data ../shared/data] [--no-write]
"""

from __future__ import annotations

import argparse
import json
import statistics as st
import time

import numpy as np
from _common import append_results, data_root  # type: ignore[import-not-found]

from torchrow import ImageResult, Params, Row
from torchrow.evaluation.datasets import CRBD
from torchrow.evaluation.metrics import crda_official, crda_thesis
from torchrow.reference import detect


def _thesis_result(rec: dict, h: int = 240, w: int = 320) -> ImageResult:
    """Thesis lines ``[x_top, y_top, x_bottom, y_bottom]`` as an ImageResult of valid rows."""
    rows = []
    for x0, y0, x1, y1 in rec["lines"]:
        a = (x1 - x0) / (y1 - y0)
        rows.append(Row(a, x0 - a * y0, True))
    return ImageResult(w, h, "ok" if rows else "no_vp", n_rows=len(rows), rows=rows, name=rec["name"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--repeat", type=int, default=3, help="timed repetitions per image (min is kept)")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    root = data_root(args.data)
    crbd = CRBD(root)
    base = [json.loads(line) for line in (root / "thesis_baseline" / "thesis_code_sample.jsonl").read_text().splitlines()]
    index = {n.lower(): i for i, n in enumerate(crbd.names)}
    params = Params()
    detect(crbd.image(0), params)  # warm-up: LAB table mapped, caches filled

    ours_t, ours_o, ours_v, th_o, th_v, th_t = [], [], [], [], [], []
    for rec in base:
        i = index[rec["name"].lower()]
        rgb, gt = crbd.image(i), crbd.ground_truth(i)
        best = float("inf")
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            res = detect(rgb, params)
            best = min(best, time.perf_counter() - t0)
        ours_t.append(best)
        ours_o.append(crda_official(res, gt))
        ours_v.append(crda_thesis(res, gt))
        th = _thesis_result(rec)
        th_o.append(crda_official(th, gt))
        th_v.append(crda_thesis(th, gt))
        th_t.append(rec["wall_s"])

    ratio = st.median(th_t) / st.median(ours_t)
    lines = [
        "| | official CRDA mean / median | thesis variant mean / median | s / image median (mean, max) |",
        "|---|---|---|---|",
        f"| torchrow.reference | {np.mean(ours_o):.3f} / {np.median(ours_o):.3f} | {np.mean(ours_v):.3f} / "
        f"{np.median(ours_v):.3f} | {st.median(ours_t):.3f} ({st.mean(ours_t):.3f}, {max(ours_t):.3f}) |",
        f"| thesis code (recorded) | {np.mean(th_o):.3f} / {np.median(th_o):.3f} | {np.mean(th_v):.3f} / "
        f"{np.median(th_v):.3f} | {st.median(th_t):.1f} ({st.mean(th_t):.1f}, {max(th_t):.1f}) |",
        "",
        f"Median speed-up of the reference over the thesis code: **{ratio:.0f}x** "
        f"(reference timed in this run, best of {args.repeat}; thesis times as recorded).",
    ]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        append_results("Reference vs thesis code, 40-image CRBD sample (001, 008, ..., 274)",
                       "python benchmarks/bench_reference.py", text)


if __name__ == "__main__":
    main()
