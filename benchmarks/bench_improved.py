"""Improved mode (ALGORITHM.md section 11): accuracy, robustness, parity and cost.

One command (needs the CRBD data, ``TORCHROW_DATA`` or ``../shared/data``)::

    python benchmarks/bench_improved.py            # everything
    python benchmarks/bench_improved.py --skip-perturb --skip-time
    python benchmarks/bench_improved.py --limit 8 --skip-perturb   # a quick check that it runs

Prints markdown tables: official CRDA (sigma 0.1 and 0.3, m 3) of the improved and faithful
modes and TMGEM on the 56 TMGEM training images, the 225 test images and all 281, straight
and curved apart, with the ground-truth oracles; the improved mode on perturbed copies of the
test images (mirrored, exposure, gamma, blur, JPEG); tensor-vs-reference parity in improved
mode on all 281 images; and tensor time per image at batch 64, faithful and improved, beside
the OpenCV floor of ``bench_tensor.py`` (one ``cv2.HoughLines`` voting pass per image), with the
improved mode's stages.
Tuning was done on the training images only; the test figures are reported, never tuned on.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from bench_tensor import opencv_floor  # type: ignore[import-not-found]

from torchrow.core.params import Params
from torchrow.core.results import record_differences
from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.datasets import CRBD
from torchrow.evaluation.metrics import crda, crda_official
from torchrow.reference import detect


def _data() -> Path:
    env = os.environ.get("TORCHROW_DATA")
    return Path(env) / "crbd" if env else Path(__file__).resolve().parents[1].parent / "shared" / "data" / "crbd"


def _batch(images: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()


def _tensor_results(images: list[np.ndarray], params: Params, bs: int = 64):
    det = CropRowDetector(params)
    out = []
    for s in range(0, len(images), bs):
        out += det(_batch(images[s:s + bs])).results()
    return out


def _oracle(gt, deg: int) -> np.ndarray:
    v = np.arange(gt.v0, gt.height, dtype=np.float64)
    y = np.arange(gt.height, dtype=np.float64)
    return np.stack([np.polyval(np.polyfit(v, gt.c + k * gt.d + 160, deg), y) for k in (-1, 0, 1)], 1)


PERTURB = {
    "mirrored": lambda im: np.ascontiguousarray(im[:, ::-1]),
    "exposure x0.6": lambda im: np.clip(im.astype(np.float64) * 0.6, 0, 255).round().astype(np.uint8),
    "exposure x1.4": lambda im: np.clip(im.astype(np.float64) * 1.4, 0, 255).round().astype(np.uint8),
    "gamma 0.7": lambda im: (255 * (im / 255.0) ** 0.7).round().astype(np.uint8),
    "gamma 1.5": lambda im: (255 * (im / 255.0) ** 1.5).round().astype(np.uint8),
    "blur 5x5": lambda im: cv2.GaussianBlur(im, (5, 5), 0),
    "JPEG q30": lambda im: cv2.cvtColor(cv2.imdecode(cv2.imencode(".jpg", cv2.cvtColor(im, cv2.COLOR_RGB2BGR),
                                                                  [cv2.IMWRITE_JPEG_QUALITY, 30])[1], 1),
                                        cv2.COLOR_BGR2RGB),
}


def _mirror_gt(gt):
    """Ground truth of the mirrored image: the central offset changes sign (px from W/2).

    The mirrored column is ``W-1-x``; relative to ``W/2`` that is ``-c - 1``.
    """
    return type(gt)(-gt.c - 1.0, gt.d, gt.v0, gt.height)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-perturb", action="store_true")
    ap.add_argument("--skip-parity", action="store_true")
    ap.add_argument("--skip-time", action="store_true")
    ap.add_argument("--perturb-every", type=int, default=1, help="use every N-th test image for perturbations")
    ap.add_argument("--limit", type=int, default=None,
                    help="only the first N images (checks that the script runs; its figures mean nothing)")
    args = ap.parse_args()
    crbd = CRBD(_data())
    n = len(crbd) if args.limit is None else min(args.limit, len(crbd))
    images = [crbd.image(i) for i in range(n)]
    imp, fai = Params(mode="improved"), Params()
    res_imp = _tensor_results(images, imp)
    res_fai = _tensor_results(images, fai)
    tm = [crbd.tmgem_set(i) for i in range(n)]
    rs = [crbd.row_set(i) for i in range(n)]
    cols = {"improved": [], "faithful": [], "TMGEM": [], "oracle straight": [], "oracle quadratic": []}
    for sig in (0.1, 0.3):
        for i in range(n):
            gt = crbd.ground_truth(i)
            cols["improved"].append(crda_official(res_imp[i], gt, sigma=sig))
            cols["faithful"].append(crda_official(res_fai[i], gt, sigma=sig))
            cols["TMGEM"].append(crda(crbd.tmgem(i), gt.c, gt.d, sigma=sig))
            cols["oracle straight"].append(crda(_oracle(gt, 1), gt.c, gt.d, sigma=sig))
            cols["oracle quadratic"].append(crda(_oracle(gt, 2), gt.c, gt.d, sigma=sig))
    subsets = {"train (56)": [i for i in range(n) if tm[i] == 0],
               "test (225)": [i for i in range(n) if tm[i] != 0],
               "test straight": [i for i in range(n) if tm[i] != 0 and rs[i] == 1],
               "test curved": [i for i in range(n) if tm[i] != 0 and rs[i] == 2],
               "all (281)": list(range(n)),
               "all straight": [i for i in range(n) if rs[i] == 1],
               "all curved": [i for i in range(n) if rs[i] == 2]}
    print("### Official CRDA (m 3), mean / median\n")
    print("| subset | n | sigma | " + " | ".join(cols) + " |")
    print("|---|---|---|" + "---|" * len(cols))
    for sig_i, sig in enumerate((0.1, 0.3)):
        for name, idx in subsets.items():
            cells = []
            for v in cols.values():
                a = np.asarray(v[sig_i * n:(sig_i + 1) * n])[idx]
                cells.append(f"{a.mean():.3f} / {np.median(a):.3f}")
            print(f"| {name} | {len(idx)} | {sig} | " + " | ".join(cells) + " |")
    if not args.skip_perturb:
        test = subsets["test (225)"][::args.perturb_every]
        base = np.asarray(cols["improved"][:n])[test]
        print(f"\n### Improved mode on perturbed test images ({len(test)} images), official CRDA sigma 0.1\n")
        print("| perturbation | mean | median | change of mean |")
        print("|---|---|---|---|")
        print(f"| none | {base.mean():.3f} | {np.median(base):.3f} | - |")
        for name, f in PERTURB.items():
            out = _tensor_results([f(images[i]) for i in test], imp)
            s = np.array([crda_official(r, _mirror_gt(crbd.ground_truth(i)) if name == "mirrored"
                                        else crbd.ground_truth(i)) for r, i in zip(out, test)])
            print(f"| {name} | {s.mean():.3f} | {np.median(s):.3f} | {s.mean() - base.mean():+.3f} |")
    if not args.skip_parity:
        bad = 0
        worst = 0.0
        for i in range(n):
            a, b = detect(images[i], imp).to_record(), res_imp[i].to_record()
            same = not record_differences(a, b)  # every field, the visible lattice rows too
            for x, y in zip(a["rows"] + a["lattice_rows"], b["rows"] + b["lattice_rows"]):
                same &= x["confidence"] == y["confidence"]
                for k in ("a", "b", "c", "e"):
                    if x[k] is not None and y[k] is not None:
                        worst = max(worst, abs(x[k] - y[k]))
            bad += not same
        print(f"\n### Parity, improved mode, all {n} CRBD images: {n - bad} identical, {bad} differ; "
              f"largest |a|,|b|,|c|,|e| difference {worst:.3g} px (rows and visible lattice rows)")
    if not args.skip_time:
        sample = images[:64]
        batch = _batch(sample)
        print(f"\n### Tensor path, batch {len(sample)}, beside the OpenCV floor (ms / image, best of 3)\n")
        print("| | ms / image | x floor |")
        print("|---|---|---|")
        floor = min(opencv_floor(sample) for _ in range(3)) * 1e3
        print(f"| OpenCV floor (one cv2.HoughLines voting pass) | {floor:.2f} | 1.00 |")
        times = {}
        stages: dict[str, float] = {}
        for name, p in (("faithful", fai), ("improved", imp)):
            det = CropRowDetector(p)
            det(batch[:8])
            best = float("inf")
            for _ in range(3):
                t0 = time.perf_counter()
                det(batch)
                best = min(best, time.perf_counter() - t0)
            times[name] = best / len(sample) * 1e3
            print(f"| {name} | {times[name]:.2f} | {times[name] / floor:.2f} |")
            if name == "improved":
                stages = det(batch, profile=True).timings
        print(f"\nimproved / faithful: **{times['improved'] / times['faithful']:.2f}x**; improved / floor: "
              f"**{times['improved'] / floor:.2f}x**")
        print("improved, per stage (profiled run, ms / image): "
              + ", ".join(f"{k} {v / len(sample) * 1e3:.2f}" for k, v in stages.items()))

if __name__ == "__main__":
    main()
