"""``torchrow demo``: the reference detector on a built-in synthetic field (no data needed),
scored against the field's true rows and drawn to a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from torchrow.apps.commands.shared import add_common, parse_params

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("demo", help="detect rows on a built-in synthetic field (no data needed)")
    p.add_argument("--out", default="torchrow-demo.png", help="annotated image (default torchrow-demo.png)")
    add_common(p)
    p.set_defaults(func=run)


def _fmt_vp(vp: tuple[float, float] | None) -> str:
    return "none" if vp is None else f"({vp[0]:.1f}, {vp[1]:.1f})"


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from torchrow.apps.annotate import draw_result, save_rgb
    from torchrow.evaluation.datasets import GroundTruth
    from torchrow.evaluation.metrics import crda_official
    from torchrow.evaluation.synthetic import demo_field
    from torchrow.reference import detect

    params = parse_params(args.param)
    field = demo_field()
    res = detect(field.image, params, name="synthetic-demo")
    h = field.image.shape[0]
    n = len(field.crp)
    gt = GroundTruth(field.crp[:, 0].copy(), field.crp[:, 1].copy(), h - n, h)
    score = crda_official(res, gt)
    ys = np.arange(h - n, h, dtype=np.float64)
    gt_lines = [(ys, field.crp[:, 0] + j * field.crp[:, 1] + field.image.shape[1] / 2) for j in range(-3, 4)]
    out = Path(args.out)
    save_rgb(out, draw_result(field.image, res, ground_truth=gt_lines))
    valid = sum(r.valid for r in res.rows)
    print(f"synthetic field {field.image.shape[1]}x{h}: status {res.status}, {valid}/{len(res.rows)} valid rows, "
          f"vanishing point {_fmt_vp(res.vp)} (true {_fmt_vp(field.vp)}), CRDA (sigma 0.1) {score:.3f}")
    print(f"annotated image: {out}")
    return 0

