"""Honest status of the improved mode's forward-camera setting: ``ok`` shares and wrong ``ok`` images
against ``lattice_min_confidence`` (ALGORITHM.md 11.4, the table under *Rows the image does not show*).

    python benchmarks/bench_status.py [--data DIR] [--split train] [--thresholds 0 0.01 0.02 0.05 0.08]

Detects once (tensor path, ``Params(mode="improved", **FORWARD_CAMERA)`` with
``lattice_min_confidence=0``) on a CRDLD split, the CRBD training images, both turned by 90°
each way (CRDLD: every ``--turn-every``-th image), and ten made-up images without crop rows
(:func:`torchrow.evaluation.synthetic.rowless_scenes`); then
applies each threshold to the records. That is exact: the threshold decides only which rows are
valid (a row's confidence below it: ``no_support``) and so the status, never the fit. A row
made invalid is no longer scored (10.1). Prints, per threshold, the CRDLD ``ok`` share, the share
of ``ok`` images scoring below 0.2 at sigma 0.1, the sigma 0.1 mean, and the ``ok`` shares of the turned
and made-up sets. No timing.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import cv2
import numpy as np

from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.engines.runner import run
from torchrow.evaluation.crdld import LOW_SCORE, score
from torchrow.evaluation.datasets import CRBD, CRDLD
from torchrow.evaluation.synthetic import rowless_scenes
from torchrow.reference.pipeline import prepare

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data_root


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise SystemExit(f"cannot read {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _detect(images: list[np.ndarray], params: Params, desc: str) -> list[dict]:
    items = [(str(i), functools.partial(prepare, im, params)) for i, im in enumerate(images)]
    out: list[dict] = [{}] * len(images)
    for k, _, res, _ in run(items, "tensor", params, desc=desc):
        out[k] = res.to_record()
    return out


def _apply(rec: dict, threshold: float) -> dict:
    """The record as ``lattice_min_confidence = threshold`` makes it (rows and status only)."""
    rows = [dict(r, valid=bool(r.get("valid")) and (r.get("confidence") or 0.0) >= threshold)
            for r in rec.get("rows") or []]
    status = rec.get("status")
    if rows and status in ("ok", "weak") and not all(r["valid"] for r in rows):
        status = "invalid"
    return dict(rec, rows=rows, status=status)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="data folder holding crdld_dev/ and crbd/ (default TORCHROW_DATA)")
    ap.add_argument("--split", default="train", choices=("train", "test"))
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.0, 0.01, 0.02, 0.05, 0.08])
    ap.add_argument("--turn-every", type=int, default=10, help="turn every N-th CRDLD image (default 10)")
    args = ap.parse_args()
    root = data_root(args.data)
    params = Params(mode="improved", **FORWARD_CAMERA).replace(lattice_min_confidence=0.0)
    ds = CRDLD(root / "crdld_dev", args.split)
    crbd = CRBD(root)
    fields = [_read(ds.image_path(i)) for i in range(len(ds))]
    truths = [ds.ground_truth(i) for i in range(len(ds))]
    crbd_train = [crbd.image(i) for i in crbd.indices("train")]
    turned_crdld = [np.ascontiguousarray(np.rot90(fields[i], k)) for i in range(0, len(ds), args.turn_every) for k in (1, 3)]
    turned_crbd = [np.ascontiguousarray(np.rot90(im, k)) for im in crbd_train for k in (1, 3)]
    fake = rowless_scenes()
    sets = {"crdld": fields, "crbd": crbd_train, "turned crdld": turned_crdld, "turned crbd": turned_crbd,
            "made up": list(fake.values())}
    recs = {name: _detect(images, params, name) for name, images in sets.items()}
    print(f"CRDLD {args.split} ({len(ds)}), CRBD training ({len(crbd_train)}), turned CRDLD ({len(turned_crdld)}), "
          f"turned CRBD ({len(turned_crbd)}), made up ({len(fake)}); forward-camera setting\n")
    print("| `lattice_min_confidence` | CRDLD `ok` | of those below 0.2 | sigma 0.1 mean | turned CRBD `ok` | "
          "turned CRDLD `ok` | CRBD train `ok` | made-up `ok` |")
    print("|---|---|---|---|---|---|---|---|")
    for th in args.thresholds:
        got = [_apply(r, th) for r in recs["crdld"]]
        s = np.array([score(r, t).sigma01 for r, t in zip(got, truths)])
        ok = np.array([r["status"] == "ok" for r in got])
        keep = np.isfinite(s)
        s, ok = s[keep], ok[keep]
        low = float((s[ok] < LOW_SCORE).mean()) if ok.any() else 0.0

        def share(name: str, th: float = th) -> str:
            return f"{np.mean([_apply(r, th)['status'] == 'ok' for r in recs[name]]):.1%}"

        made = sum(_apply(r, th)["status"] == "ok" for r in recs["made up"])
        print(f"| {th:g} | {ok.mean():.1%} | {low:.1%} | {s.mean():.4f} | {share('turned crbd')} | "
              f"{share('turned crdld')} | {share('crbd')} | {made} of {len(fake)} |")


if __name__ == "__main__":
    main()
