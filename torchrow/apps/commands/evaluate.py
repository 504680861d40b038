"""``torchrow eval``: detect on CRBD or a CRDLD split and report CRDA (ALGORITHM.md 10.1);
``--out`` is a folder of scores, records, summary and histogram."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torchrow.apps.commands.shared import (
    CLIError,
    add_common,
    add_engine,
    add_evidence,
    add_impl,
    check_device,
    check_engine,
    check_targets,
    evidence_files,
    open_crbd,
    open_crdld,
    open_sink,
    parse_params,
    run_header,
    with_mode,
)

if TYPE_CHECKING:
    from torchrow.apps.evaluate import CRDLDReport, EvalReport

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("eval", help="run on CRBD and report CRDA (official and thesis variant), or on CRDLD "
                                           "(ALGORITHM.md 10.1)")
    p.add_argument("--dataset", choices=("crbd", "crdld"), default="crbd",
                   help="crbd (default): the CRBD benchmark; crdld: a Crop Row Detection Lincoln Dataset split")
    p.add_argument("--data", help="CRBD folder (or a folder holding crbd/); for crdld a split folder (image/, "
                                  "label/), a folder holding train/ and test/, or one holding crdld_dev/; "
                                  "default $TORCHROW_DATA")
    p.add_argument("--split", choices=("test", "train"), default=None,
                   help="--dataset crdld: the split where --data holds train/ and test/ (default test)")
    p.add_argument("--out", default="torchrow-eval",
                   help="folder for scores.csv, detections.jsonl, summary.json, crda_histogram.png "
                        "(default torchrow-eval)")
    p.add_argument("--every", type=int, default=1, help="use every N-th image (default 1: all)")
    p.add_argument("--limit", type=int, default=0, help="at most this many images (default 0: no limit)")
    add_engine(p)
    add_impl(p)
    add_evidence(p)
    add_common(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from torchrow.apps.evaluate import evaluate, evaluate_crdld
    from torchrow.apps.sink import image_key
    from torchrow.evaluation.datasets import CRDLD

    params = with_mode(parse_params(args.param), args)
    device = check_device(args.device)
    if args.impl == "onnx":
        raise CLIError("eval supports --impl tensor|reference; for ONNX use: torchrow detect --impl onnx --model M")
    if args.split is not None and args.dataset != "crdld":
        raise CLIError(f"--split is for --dataset crdld (CRBD has no splits to pick), got --dataset {args.dataset}")
    check_engine(args)
    ds = open_crdld(args.data, args.split or "test") if args.dataset == "crdld" else open_crbd(args.data)
    out = Path(args.out)
    check_targets([Path(ds.root)], [("--out", out)])
    indices = list(range(len(ds)))[:: args.every]
    if args.limit:
        indices = indices[: args.limit]
    masks = evidence_files(args, [ds.names[i] for i in indices], params)
    out.mkdir(parents=True, exist_ok=True)
    sink = open_sink(out / "detections.jsonl", image_key, args.resume,
                     run_header("eval", params, [ds.root, *([args.evidence] if masks is not None else [])],
                                impl=args.impl, engine=args.engine))
    options: dict[str, Any] = dict(progress=not args.quiet, sink=sink, engine=args.engine, address=args.address,
                                   workers=args.workers,
                                   evidence=None if masks is None else dict(zip(indices, masks)))
    report: EvalReport | CRDLDReport
    try:
        if isinstance(ds, CRDLD):
            report = evaluate_crdld(ds, indices, args.impl, params, args.batch_size, device, **options)
        else:
            report = evaluate(ds, indices, args.impl, params, args.batch_size, device, **options)
    finally:
        sink.close(complete=False)
    print(report.format_summary())
    paths = report.write(out, records=False)
    for p in paths[:1] + [sink.path] + paths[1:]:
        print(f"wrote {p}", file=sys.stderr)
    return 0
