"""``torchrow score``: CRDA of another detector's CRBD result files (``.tmg`` format)."""

from __future__ import annotations

import argparse
from pathlib import Path

from torchrow.apps.commands.shared import CLIError, add_common, open_crbd

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("score", help="score external CRBD result files (.tmg format)")
    p.add_argument("--data", help="CRBD folder; default $TORCHROW_DATA")
    p.add_argument("--results", required=True, help="folder of result files named like the images")
    p.add_argument("--ext", default=".tmg", help="result file extension (default .tmg)")
    add_common(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from torchrow.apps.evaluate import score_tmg_files
    from torchrow.evaluation.metrics import summarize

    crbd = open_crbd(args.data)
    results = Path(args.results)
    if not results.is_dir():
        raise CLIError(f"results folder not found: {results}")
    ext = args.ext if args.ext.startswith(".") else "." + args.ext
    present = sum((results / f"{crbd[i].stem}{ext}").is_file() for i in range(len(crbd)))
    if present == 0:
        raise CLIError(f"no result files (<image name>{ext}) for the {len(crbd)} CRBD images in {results}")
    scores = score_tmg_files(crbd, results, ext, progress=not args.quiet)
    missing = len(crbd) - present
    note = f"; {missing} image(s) without a result file scored 0" if missing else ""
    for label, col in (("sigma 0.1", 1), ("sigma 0.3", 2)):
        s = summarize(np.array([r[col] for r in scores]))
        print(f"CRDA {label}: mean {s['mean']:.3f}  median {s['median']:.3f}  (n={s['n']}{note})")
    return 0
