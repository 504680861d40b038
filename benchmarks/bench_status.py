"""Honest status of the improved mode's forward-camera setting: ``ok`` shares and wrong ``ok`` images
against one of its status thresholds (ALGORITHM.md 11.4: ``lattice_min_dominance``, the table
under *Rows across the view*; ``lattice_min_confidence``, under *Rows the image does not show*).

    python benchmarks/bench_status.py [--data DIR] [--split train] [--vary lattice_min_dominance]
        [--thresholds 0 0.5 0.55 0.6 0.65 0.7] [--setting forward|default] [--set FIELD=VALUE ...]

Detects (tensor path, ``Params(mode="improved", **FORWARD_CAMERA)``, or the improved mode's
default setting with ``--setting default`` (the table under *The default setting's status on a
forward camera*), the ``--set`` fields fixed, each threshold as the ``--vary`` field) a CRDLD
split, the CRBD images of the same split, both turned by 90° each way
(CRDLD: every ``--turn-every``-th image), and ten made-up images without crop rows
(:func:`torchrow.evaluation.synthetic.rowless_scenes`). The thresholds never change the fit;
below ``lattice_min_confidence`` a row is invalid (``no_support``) and no longer scored (10.1).
Prints, per threshold, the CRDLD ``ok`` share, the share of ``ok`` images scoring below 0.2 at
sigma 0.1, the sigma 0.1 mean, and the ``ok`` shares of the other sets. No timing.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import numpy as np

from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.engines.runner import run
from torchrow.evaluation.crdld import LOW_SCORE, score
from torchrow.evaluation.datasets import CRBD, CRDLD
from torchrow.evaluation.synthetic import rowless_scenes
from torchrow.reference.pipeline import prepare

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data_root


def _detect(images: list[np.ndarray], params: Params, desc: str) -> list[dict]:
    items = [(str(i), functools.partial(prepare, im, params)) for i, im in enumerate(images)]
    out: list[dict] = [{}] * len(images)
    for k, _, res, _ in run(items, "tensor", params, desc=desc):
        out[k] = res.to_record()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="data folder holding crdld_dev/ and crbd/ (default TORCHROW_DATA)")
    ap.add_argument("--split", default="train", choices=("train", "test"))
    ap.add_argument("--vary", default="lattice_min_dominance",
                    choices=("lattice_min_dominance", "lattice_min_confidence", "lattice_min_contrast"))
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.0, 0.5, 0.55, 0.6, 0.65, 0.7])
    ap.add_argument("--turn-every", type=int, default=10, help="turn every N-th CRDLD image (default 10)")
    ap.add_argument("--setting", default="forward", choices=("forward", "default"),
                    help="the forward-camera setting (default) or the improved mode's default one")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="further Params fields held fixed, e.g. lattice_min_confidence=0.02")
    args = ap.parse_args()
    root = data_root(args.data)
    fixed = {k: float(v) for k, v in (item.split("=", 1) for item in args.set)}
    params = Params(mode="improved", **{**(FORWARD_CAMERA if args.setting == "forward" else {}), **fixed})
    ds = CRDLD(root / "crdld_dev", args.split)
    crbd = CRBD(root)
    fields = [ds.image(i, None) for i in range(len(ds))]  # stored size: turned before the resize
    truths = [ds.ground_truth(i) for i in range(len(ds))]
    crbd_split = [crbd.image(i) for i in crbd.indices(args.split)]
    turned_crdld = [np.ascontiguousarray(np.rot90(fields[i], k)) for i in range(0, len(ds), args.turn_every) for k in (1, 3)]
    turned_crbd = [np.ascontiguousarray(np.rot90(im, k)) for im in crbd_split for k in (1, 3)]
    fake = rowless_scenes()
    sets = {"crdld": fields, "crbd": crbd_split, "turned crdld": turned_crdld, "turned crbd": turned_crbd,
            "made up": list(fake.values())}
    print(f"CRDLD {args.split} ({len(ds)}), CRBD {args.split} ({len(crbd_split)}), turned CRDLD ({len(turned_crdld)}), "
          f"turned CRBD ({len(turned_crbd)}), made up ({len(fake)}); {args.setting} setting {fixed or ''}\n")
    lines = [f"| `{args.vary}` | CRDLD `ok` | of those below 0.2 | sigma 0.1 mean | turned CRBD `ok` | "
             f"turned CRDLD `ok` | CRBD {args.split} `ok` | made-up `ok` |", "|---|---|---|---|---|---|---|---|"]
    for th in args.thresholds:
        p = params.replace(**{args.vary: th})
        recs = {name: _detect(images, p, f"{name}, {th:g}") for name, images in sets.items()}
        s = np.array([score(r, t).sigma01 for r, t in zip(recs["crdld"], truths)])
        ok = np.array([r["status"] == "ok" for r in recs["crdld"]])
        keep = np.isfinite(s)
        s, ok = s[keep], ok[keep]
        low = float((s[ok] < LOW_SCORE).mean()) if ok.any() else 0.0
        share = {name: f"{np.mean([r['status'] == 'ok' for r in got]):.1%}" for name, got in recs.items()}
        made = sum(r["status"] == "ok" for r in recs["made up"])
        lines.append(f"| {th:g} | {ok.mean():.1%} | {low:.1%} | {s.mean():.4f} | {share['turned crbd']} | "
                     f"{share['turned crdld']} | {share['crbd']} | {made} of {len(fake)} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
