"""What limits the forward-camera score: row models fitted to the labels, and how far the
green mask's own evidence pulls a lattice away from them (ALGORITHM.md 11.6).

    python benchmarks/bench_crdld_limits.py [--data DIR] [--split train] [--step 1]

On every ``--step``-th image (default every one) of a CRDLD split with at least two labelled lines, at the working
width (320), scored with 10.1's sigma 0.1 score (``torchrow.evaluation.crdld.score_image``):

- *own lines*: a straight line least-squares-fitted to each labelled line;
- *pencil*: the lines through the labels' least-squares vanishing point (the point nearest, in
  x, to every fitted line), each line's bottom position fitted alone;
- *lattice*: 11.3's straight model ``x = c0 + c1 t + k (d0 + d1 t)`` least-squares-fitted to
  every labelled point (``k`` the line's index from the central labelled line), rows equally
  spaced on each image row;
- *rolled lattice*: the same pencil with projective spacing, ``x (1 + g k) = c0 + c1 t + k (d0 +
  d1 t)`` (equal spacing on the ground seen by a rolled camera), ``g`` searched on a grid;
- *lattice + N refits*: 11.3's straight refit (``torchrow.reference.lattice.refine``, the
  forward-camera setting) run N times from the labels' lattice on the image's green mask;
- *comb at the labels' VP*: 11.2's comb through the labels' lattice VP (rounded), with and
  without the straight refits after it;
- *detector*: the improved mode's forward-camera setting (tensor path), as it runs.

Choose nothing on the test split with it: it reads labels.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.evaluation.crdld import CRDLDTruth, score_image
from torchrow.evaluation.datasets import CRDLD

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data_root

WIDTH = 320
ROLLS = np.linspace(-0.3, 0.3, 121)


def label_points(fits: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                 central: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points of :func:`own_lines` in one list: ``t``, ``x`` and the line's index ``k`` from the
    central line (float64, one entry per point)."""
    t = np.concatenate([f[0] for f in fits])
    x = np.concatenate([f[1] for f in fits])
    k = np.concatenate([np.full(len(f[0]), j - central, np.float64) for j, f in enumerate(fits)])
    return t, x, k


def straight_rows(lines: list[tuple[float, float]], height: int) -> list[dict]:
    """Row dicts for lines ``x = x0 + s t`` (``t = y - (H-1)``)."""
    y1 = height - 1
    return [dict(a=s, b=x0 - s * y1, c=0.0, e=0.0, valid=True) for x0, s in lines]


def lattice_lines(coef: np.ndarray, roll: float = 0.0, kmax: int = 8) -> list[tuple[float, float]]:
    """``(x at the bottom, slope)`` of rows ``-kmax .. kmax`` of ``(c0, c1, d0, d1)`` with roll ``g``
    (or of 11.3's seven coefficients, straight: their ``c0, c1, d0, d1``)."""
    c0, c1, d0, d1 = coef[[0, 1, 4, 5]] if len(coef) == 7 else coef
    return [((c0 + k * d0) / (1 + roll * k), (c1 + k * d1) / (1 + roll * k))
            for k in range(-kmax, kmax + 1) if 1 + roll * k > 0]


def fit_lattice(t: np.ndarray, x: np.ndarray, k: np.ndarray, roll: float) -> tuple[np.ndarray, float]:
    """Least squares of ``x (1 + g k) = c0 + c1 t + k (d0 + d1 t)``: coefficients and the
    squared x residual of the rows they give."""
    a = np.stack([np.ones_like(t), t, k, k * t], axis=1)
    coef = np.linalg.lstsq(a, x * (1 + roll * k), rcond=None)[0]
    pred = (a @ coef) / (1 + roll * k)
    return coef, float(((pred - x) ** 2).sum())


def best_roll(t: np.ndarray, x: np.ndarray, k: np.ndarray) -> float:
    """The ``g`` of :data:`ROLLS` whose :func:`fit_lattice` leaves the least squared x residual,
    every labelled line's denominator ``1 + g k`` kept above 0.25."""
    rolls = [r for r in ROLLS if (1 + r * k).min() > 0.25]
    return min(rolls, key=lambda r: fit_lattice(t, x, k, r)[1])


def own_lines(truth: CRDLDTruth, width: int, height: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per labelled line its points at the working size, ``t = y - (H-1)`` and ``x``, and its
    straight least-squares fit ``(slope, x at the bottom)``."""
    out = []
    for ln in truth.lines:
        t = ln[:, 0] * (height / truth.height) - (height - 1)
        x = ln[:, 1] * (width / truth.width)
        out.append((t, x, np.polyfit(t, x, 1)))
    return out


def pencil_lines(fits: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> list[tuple[float, float]]:
    """Each line of :func:`own_lines` through the labels' least-squares VP, its bottom x fitted alone."""
    # VP (tv, xv) nearest in x to every line x = x0 + s t: xv - s tv = x0
    a = np.array([[1.0, -f[2][0]] for f in fits])
    xv, tv = np.linalg.lstsq(a, np.array([f[2][1] for f in fits]), rcond=None)[0]
    out = []
    for ty, xx, _ in fits:
        u = (ty - tv) / (0.0 - tv)  # x = xv + (x0 - xv) u: 1 on the bottom row, 0 at the VP
        x0 = float(np.dot(u, xx - xv * (1 - u)) / max(np.dot(u, u), 1e-12))
        out.append((x0, (x0 - xv) / (-tv)))
    return out


def image_scores(truth: CRDLDTruth, rgb: np.ndarray, params: Params, det) -> dict[str, float]:
    """Every table line's score on one image (``rgb``: the working image); empty where the
    labels hold fewer than two lines."""
    from torchrow.core.io import lattice_params
    from torchrow.reference import lattice as rl

    if len(truth.lines) < 2 or truth.central < 0:
        return {}
    h, w = rgb.shape[:2]
    fp = lattice_params(w, h, params)
    out: dict[str, float] = {}

    def put(name: str, rows: list[dict], status: str = "ok") -> None:
        out[name] = score_image(rows, status, truth, 0.1, (w, h))

    fits = own_lines(truth, w, h)
    t, x, k = label_points(fits, truth.central)
    put("own lines", straight_rows([(x0, slope) for _, _, (slope, x0) in fits], h))
    put("pencil", straight_rows(pencil_lines(fits), h))
    coef, _ = fit_lattice(t, x, k, 0.0)
    put("lattice", straight_rows(lattice_lines(coef), h))
    g = best_roll(t, x, k)
    put("rolled lattice", straight_rows(lattice_lines(fit_lattice(t, x, k, g)[0], g), h))

    mask = rl.green_mask(rgb, 0, fp)
    pre = rl.prefix_sums(mask)
    start = np.array([coef[0], coef[1], 0.0, 0.0, coef[2], coef[3], 0.0])
    for n in (1, 3, 20):
        c7 = rl.refine(pre, start, h, dataclasses.replace(fp, lattice_iterations=n), straight=True)[0]
        put(f"lattice + {n} refit" + ("s" if n > 1 else ""), straight_rows(lattice_lines(c7), h))
    # the labels' lattice VP: where d(t) = 0
    tv = -coef[2] / coef[3] if coef[3] != 0 else -10.0 * h
    vp = (int(round(coef[0] + coef[1] * tv)), int(round(tv + (h - 1))))
    d, phase, found, _ = rl.comb_search(mask, vp, fp, None)
    if found and vp[1] < h - 1:
        s = (h - 1) - vp[1]
        c7 = np.array([phase, (phase - vp[0]) / s, 0.0, 0.0, d, d / s, 0.0])
        put("comb at the labels' VP", straight_rows(lattice_lines(c7), h))
        c7 = rl.refine(pre, c7, h, fp, straight=True)[0]
        put("comb at the labels' VP + 20 refits", straight_rows(lattice_lines(c7), h))
    else:
        put("comb at the labels' VP", [], "invalid")
        put("comb at the labels' VP + 20 refits", [], "invalid")
    rec = det.detect([rgb]).results()[0].to_record()
    put("detector", rec["rows"], str(rec["status"]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None)
    ap.add_argument("--split", default="train", choices=("train", "test"))
    ap.add_argument("--step", type=int, default=1, help="every STEP-th image (default all)")
    args = ap.parse_args()

    from torchrow.engines.detector import CropRowDetector
    from torchrow.reference.pipeline import prepare

    ds = CRDLD(data_root(args.data), args.split)  # a data folder, its crdld_dev/ or a split folder
    params = Params(mode="improved", **FORWARD_CAMERA)
    det = CropRowDetector(params)
    names = ["own lines", "pencil", "lattice", "rolled lattice", "lattice + 1 refit", "lattice + 3 refits",
             "lattice + 20 refits", "comb at the labels' VP", "comb at the labels' VP + 20 refits", "detector"]
    scores: dict[str, list[float]] = {n: [] for n in names}
    for i in range(0, len(ds), args.step):
        got = image_scores(ds.ground_truth(i), prepare(ds.image(i, None), params), params, det)
        for name, value in got.items():
            scores[name].append(value)
    n = len(scores["detector"])
    print(f"CRDLD {args.split} (images {0}, {args.step}, {2 * args.step}, ...), those with two or more labelled lines: "
          f"{n} images, sigma 0.1 mean")
    print("| rows scored | sigma 0.1 |\n|---|---|")
    for name in names:
        print(f"| {name} | {np.nanmean(scores[name]):.3f} |")


if __name__ == "__main__":
    main()
