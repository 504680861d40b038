"""Improved mode: the tensor path against the reference on every CRDLD dev and CRBD image.

    python benchmarks/parity_improved.py [--data DIR] [--forward] [--param NAME=JSON ...] [--sets crdld crbd]

Each image's record from :class:`torchrow.engines.detector.CropRowDetector` (batches of 64) is
compared with :func:`torchrow.reference.detect`'s, field for field and bit for bit (``==`` on the
records, floats included). Prints the images and the differing ones per set, and the first
differences. No timing (the reference takes about a second per image: 20-25 minutes for all).
"""

from __future__ import annotations

import argparse
import json

from _common import data_root  # type: ignore[import-not-found]

from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.core.results import record_differences
from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.datasets import CRBD, CRDLD
from torchrow.reference import detect


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--forward", action="store_true", help="the forward-camera setting (FORWARD_CAMERA)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=JSON", help="a Params override")
    ap.add_argument("--sets", nargs="+", choices=("crdld", "crbd"), default=["crdld", "crbd"])
    args = ap.parse_args()
    params = Params(mode="improved", **(FORWARD_CAMERA if args.forward else {}))
    params = params.replace(**{k: json.loads(v) for k, v in (p.split("=", 1) for p in args.param)})
    root = data_root(args.data)
    sets = []
    if "crdld" in args.sets:
        sets += [(f"CRDLD {split}", CRDLD(root, split)) for split in ("train", "test")]
    if "crbd" in args.sets:
        sets.append(("CRBD", CRBD(root)))
    det = CropRowDetector(params)
    print(f"improved mode, {'forward-camera setting' if args.forward else 'default setting'}"
          + (f" with {', '.join(args.param)}" if args.param else ""), flush=True)
    for name, ds in sets:
        n, bad, first = len(ds), 0, []
        for s in range(0, n, 64):
            images = [ds.image(i, None) if isinstance(ds, CRDLD) else ds.image(i) for i in range(s, min(n, s + 64))]
            for i, (img, got) in enumerate(zip(images, det.detect(images).results())):
                want = detect(img, params).to_record()
                if want != got.to_record():
                    bad += 1
                    first += [f"image {s + i}: {d}" for d in record_differences(want, got.to_record())[:2]]
        print(f"{name}: {n} images, {bad} differ", flush=True)
        for line in first[:6]:
            print("  ", line)


if __name__ == "__main__":
    main()
