"""CRDLD score of record files (or of a fresh detection) on one CRDLD split.

Score existing ``torchrow detect`` records (one table line per file)::

    python benchmarks/bench_crdld.py --records improved.jsonl faithful.jsonl --data DIR/test

or detect first (tensor path, default parameters unless ``--param``)::

    python benchmarks/bench_crdld.py --data DIR --split train --mode improved faithful

``--data`` is a CRDLD split folder (``image/``, ``label/``), a folder holding ``train/`` and
``test/`` (``--split``), or a data folder holding ``crdld_dev/``; default ``TORCHROW_DATA`` or
``../shared/data``. Prints the table of ALGORITHM.md 10.1: mean / median at sigma 0.1 and 0.3,
the central line's MAE, the fraction of ``ok`` images and, among them, those scoring below
0.2. ``--truth-fit`` adds a line for a straight line least-squares-fitted to every labelled line
(about 0.997 on ``test``: what the metric leaves to a perfect straight-row detector).
Images without a record count as ``missing`` and score 0.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path

import numpy as np

from torchrow.evaluation.crdld import CRDLDScore, format_table, match_records, score, score_image, summarize
from torchrow.evaluation.datasets import CRDLD

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data_root


def _records(path: Path) -> list[dict]:
    with open(path) as fh:
        return [json.loads(line) for line in fh if line.strip()]


def _score_all(ds: CRDLD, records: list[dict | None]) -> tuple[list[str], list[CRDLDScore]]:
    statuses, scores = [], []
    for i, rec in enumerate(records):
        truth = ds.ground_truth(i)
        if rec is None:
            statuses.append("missing")
            scores.append(score({"status": "error"}, truth))
        else:
            statuses.append(str(rec.get("status")))
            scores.append(score(rec, truth))
    return statuses, scores


def _detect(ds: CRDLD, mode: str, params_json: list[str]) -> list[dict | None]:
    from torchrow.core.io import load_image
    from torchrow.core.params import Params
    from torchrow.engines.runner import run

    params = Params(**{k: json.loads(v) for k, v in (p.split("=", 1) for p in params_json)}).replace(mode=mode)
    items = [(n, functools.partial(load_image, ds.image_path(i), params.image_width, params.max_pixels))
             for i, n in enumerate(ds.names)]
    out: list[dict | None] = [None] * len(ds)
    for k, _, res, _ in run(items, "tensor", params, desc=f"detect ({mode})"):
        out[k] = res.to_record()
    return out


def _fit_scores(ds: CRDLD) -> tuple[list[str], list[CRDLDScore]]:
    """A straight line least-squares-fitted to each labelled line, scored as a detection."""
    statuses, scores = [], []
    for i in range(len(ds)):
        truth = ds.ground_truth(i)
        rows = []
        for line in truth.lines:
            a, b = np.polyfit(line[:, 0], line[:, 1], 1)
            rows.append({"a": a, "b": b, "c": 0.0, "e": 0.0, "valid": True})
        statuses.append("ok")
        scores.append(CRDLDScore(score_image(rows, "ok", truth, 0.1), score_image(rows, "ok", truth, 0.3),
                                 float("nan")))
    return statuses, scores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", nargs="+", type=Path, default=[], help="JSONL record files of torchrow detect")
    ap.add_argument("--data", default=None, help="CRDLD split folder, folder of splits, or data folder")
    ap.add_argument("--split", choices=("test", "train"), default="test")
    ap.add_argument("--mode", nargs="+", choices=("faithful", "improved"), default=[],
                    help="detect with these modes (tensor path) instead of / besides --records")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=JSON", help="Params override for --mode")
    ap.add_argument("--truth-fit", action="store_true", help="add the straight-line fit of the labels")
    args = ap.parse_args()
    if not args.records and not args.mode and not args.truth_fit:
        ap.error("give --records FILE..., --mode MODE... or --truth-fit")
    ds = CRDLD(args.data if args.data is not None else data_root(None), args.split)
    t0 = time.perf_counter()
    for i in range(len(ds)):
        ds.ground_truth(i)
    print(f"{ds!r}, split {args.split}: ground truth in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    table = []
    for path in args.records:
        table.append((path.name, summarize(*_score_all(ds, match_records(ds.names, _records(path))))))
    for mode in args.mode:
        table.append((f"detect --mode {mode}", summarize(*_score_all(ds, _detect(ds, mode, args.param)))))
    if args.truth_fit:
        table.append(("straight-line fit of the labels", summarize(*_fit_scores(ds))))
    print(format_table(table))


if __name__ == "__main__":
    main()
