"""Forward-camera views off to the side and rolled: what the improved mode and its row model do
when the vanishing point leaves the top centre (ALGORITHM.md 11.6, *Views off to the side*).

    python benchmarks/bench_crdld_views.py [--data DIR] [--split train] [--step 5] [--time]
    python benchmarks/bench_crdld_views.py [--data DIR] --caterra 0 5 12

Every ``--step``-th image of a CRDLD split and its label mask, each seen as it is, moved
sideways by 30 % or 60 % of the width with the uncovered columns black (the same rows at the
same scale, the vanishing point near a side edge or beyond it: an off-centre crop of a wider
view, or, roughly, a camera turned towards one side), and rolled about the image centre by
-30, -15, 15 and 30 degrees (a camera on a side slope; black corners). The label mask is
transformed alike (nearest neighbour), and the ground truth is read from it as 10.1 reads any
mask. Columns (10.1's score at sigma 0.1, each at the working width):

- *images*: those whose moved labels give a scored pair (two or more lines);
- *lattice* and *rolled lattice*: the row models least-squares-fitted to the labels
  (``bench_crdld_limits.py``): rows equally spaced on each image row, and the same pencil with
  projective spacing ``x (1 + g k) = c0 + c1 t + k (d0 + d1 t)``, ``g`` searched;
- *green mask*: the improved mode's forward-camera setting (tensor path) as it runs, its
  ``ok`` share and the share of its ``ok`` images scoring below 0.2;
- *green mask moved*: the green mask of the image as taken (11.1 at the stored size), moved
  or rolled with it and given as 11.1.1's evidence: the same plant pixels, so the change from
  *as taken* is the search's and the row model's, not the black columns' (which lower 11.1's
  Otsu threshold and row means);
- *label evidence*: the same with the label mask given as 11.1.1's evidence (what the search
  and the row model do once the evidence is right).

Each detector column is run three times: the forward-camera setting as it is, with
``lattice_roll_grid`` 30 (11.3.2: the straight refit searches a projective spacing ``g`` of
-0.3 .. 0.3 by 0.01), the row model that the lattice columns ask for, and with that and
``lattice_comb_warps`` 6 (11.3.2: the comb also on the bottom row warped projectively, a start
with its own ``g``).

``--caterra DEG ...`` only tracks the 100 rover frames of ``caterra_video`` (about twelve rows in
view) turned by each DEG about their centre with the lattice tracker
(forward-camera setting, ``video_width`` 500), the three ways, and counts its states and ``ok`` frames.
The turned frames are enlarged about the centre until no corner is uncovered
(:func:`turn_filled`: what a rolled camera with a narrower view sees). Black corners would be
an artifact of the test, not of a rolled camera, and they move section 1's sky row: turned 12°
with black corners, 3 of the 9 frames 0, 12, .., 96 get no sky row and their VP grid starts above
the image.
``--time`` only times the three detectors side by side on the images as taken (tensor path, batch 64,
``--rounds`` interleaved rounds, each run's best; run it with nothing else on the machine). Choose
nothing on the test split with it: it reads labels.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.evaluation.crdld import LOW_SCORE, CRDLDTruth, score_image, truth_from_mask
from torchrow.evaluation.datasets import CRDLD

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data_root
from bench_crdld_limits import best_roll, fit_lattice, label_points, lattice_lines, own_lines, straight_rows

View = Callable[[np.ndarray, int], np.ndarray]
ROLL_GRID = 30  # lattice_roll_grid of the second detector (11.3.2): g = -0.3 .. 0.3 by 0.01
COMB_WARPS = 6  # lattice_comb_warps of the third (11.3.2): the comb on 13 warps, -0.3 .. 0.3 of W/2 by 0.05


def shift(share: float) -> View:
    """Moved sideways by ``share`` of the width (right where positive), same size, the columns
    it uncovers black: the same rows at the same scale, the vanishing point moved with them."""
    def view(a: np.ndarray, interp: int) -> np.ndarray:
        w = a.shape[1]
        n = int(round(abs(share) * w))
        out = np.zeros_like(a)
        if share > 0:
            out[:, n:] = a[:, :w - n]
        else:
            out[:, :w - n] = a[:, n:]
        return out
    return view


def roll(degrees: float) -> View:
    """Turned by ``degrees`` (counter-clockwise) about the image centre, same size, black corners."""
    def view(a: np.ndarray, interp: int) -> np.ndarray:
        h, w = a.shape[:2]
        m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), degrees, 1.0)
        return cv2.warpAffine(a, m, (w, h), flags=interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return view


VIEWS: dict[str, View] = {
    "as taken": lambda a, interp: a,
    "moved left 30 %": shift(-0.3), "moved right 30 %": shift(0.3),
    "moved left 60 %": shift(-0.6), "moved right 60 %": shift(0.6),
    "rolled -30°": roll(-30), "rolled -15°": roll(-15), "rolled 15°": roll(15), "rolled 30°": roll(30),
}


def model_scores(truth: CRDLDTruth, w: int, h: int) -> tuple[float, float]:
    """Sigma 0.1 scores of the lattice and the rolled lattice least-squares-fitted to the labels,
    at the working size ``w x h``."""
    fits = own_lines(truth, w, h)
    t, x, k = label_points(fits, truth.central)
    coef, _ = fit_lattice(t, x, k, 0.0)
    plain = score_image(straight_rows(lattice_lines(coef), h), "ok", truth, 0.1, (w, h))
    g = best_roll(t, x, k)
    rolled = score_image(straight_rows(lattice_lines(fit_lattice(t, x, k, g)[0], g), h), "ok", truth, 0.1, (w, h))
    return plain, rolled


def detector_scores(det, images: list[np.ndarray], truths: list[CRDLDTruth],
                    evidence: list[np.ndarray] | None) -> tuple[float, float, float]:
    """Sigma 0.1 mean, ``ok`` share and the share of the ``ok`` images below 0.2."""
    recs = [r.to_record() for r in det.detect(images, evidence=evidence).results()]
    s = np.array([score_image(r["rows"], str(r["status"]), tr, 0.1, (r["width"], r["height"]))
                  for r, tr in zip(recs, truths)])
    ok = np.array([r["status"] == "ok" for r in recs])
    low = float((s[ok] < LOW_SCORE).mean()) if ok.any() else float("nan")
    return float(s.mean()), float(ok.mean()), low


def turn_filled(a: np.ndarray, degrees: float) -> np.ndarray:
    """``a`` turned by ``degrees`` (counter-clockwise) about its centre and enlarged by
    ``cos |θ| + (W/H) sin |θ|``, the least scale that leaves no corner of the view uncovered."""
    h, w = a.shape[:2]
    th = np.radians(abs(degrees))
    m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), degrees, float(np.cos(th) + (w / h) * np.sin(th)))
    return cv2.warpAffine(a, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def caterra_states(root: Path, degrees: list[float]) -> None:
    """The lattice tracker's states on the Caterra frames turned by each of ``degrees``
    (:func:`turn_filled`), with equal spacing, with ``lattice_roll_grid`` ``ROLL_GRID``, and with that
    and ``lattice_comb_warps`` ``COMB_WARPS``."""
    from collections import Counter

    import torchrow
    from torchrow.core.io import load_image

    params = Params(mode="improved", video_width=500, **FORWARD_CAMERA)
    frames = [load_image(f, params.video_width) for f in sorted((root / "caterra_video").glob("*.jpg"))]
    print("| turned | `lattice_roll_grid` | `lattice_comb_warps` | frames | `ok` | states |\n|---|---|---|---|---|---|")
    for deg in degrees:
        seen = [turn_filled(f, deg) for f in frames] if deg else frames
        for grid, warps in ((0, 0), (ROLL_GRID, 0), (ROLL_GRID, COMB_WARPS)):
            recs = torchrow.Tracker(params.replace(lattice_roll_grid=grid, lattice_comb_warps=warps)).track([seen])[0]
            states = ", ".join(f"{k} {v}" for k, v in sorted(Counter(r.state for r in recs).items()))
            print(f"| {deg:g}° | {grid} | {warps} | {len(recs)} | {sum(r.status == 'ok' for r in recs)} | {states} |",
                  flush=True)


def time_detectors(dets: tuple, images: list[np.ndarray], rounds: int) -> None:
    """ms per image of each detector at batch 64, best of ``rounds`` interleaved rounds."""
    import time

    import torch

    x = [images[i:i + 64] for i in range(0, len(images) - 63, 64)]  # whole batches, resized by the detector
    n = 64 * len(x)
    for det in dets:
        det.detect(x[0]).results()  # warm-up: tables, thread pool
    best = [float("inf")] * len(dets)
    for _ in range(rounds):
        for j, det in enumerate(dets):
            t0 = time.perf_counter()
            for xb in x:
                det.detect(xb).results()
            best[j] = min(best[j], (time.perf_counter() - t0) * 1e3 / n)
    print(f"{n} images as taken, batch 64, best of {rounds}: equal spacing {best[0]:.1f} ms / image, "
          f"lattice_roll_grid {ROLL_GRID} {best[1]:.1f} ms / image ({best[1] / best[0]:.2f}x), and "
          f"lattice_comb_warps {COMB_WARPS} {best[2]:.1f} ms / image ({best[2] / best[0]:.2f}x), torch "
          f"{torch.__version__}, {torch.get_num_threads()} threads")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None)
    ap.add_argument("--split", default="train", choices=("train", "test"))
    ap.add_argument("--step", type=int, default=5, help="every STEP-th image (default 5)")
    ap.add_argument("--time", action="store_true", help="only time the three detectors on the images as taken")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--caterra", nargs="*", type=float, default=None, metavar="DEG",
                    help="only track the Caterra frames turned by each DEG")
    args = ap.parse_args()
    if args.caterra is not None:
        caterra_states(data_root(args.data), args.caterra)
        return

    from torchrow.core.io import lattice_params, working_size
    from torchrow.engines.detector import CropRowDetector
    from torchrow.reference.lattice import green_mask

    ds = CRDLD(data_root(args.data), args.split)  # a data folder, its crdld_dev/ or a split folder
    params = Params(mode="improved", **FORWARD_CAMERA)
    dets = (CropRowDetector(params), CropRowDetector(params.replace(lattice_roll_grid=ROLL_GRID)),
            CropRowDetector(params.replace(lattice_roll_grid=ROLL_GRID, lattice_comb_warps=COMB_WARPS)))
    idx = list(range(0, len(ds), args.step))
    if args.time:
        time_detectors(dets, [ds.image(i, None) for i in idx], args.rounds)
        return
    raw = []
    for i in idx:
        rgb = ds.image(i, None)
        green = green_mask(rgb, 0, lattice_params(rgb.shape[1], rgb.shape[0], params)).astype(np.uint8) * 255
        raw.append((rgb, cv2.imread(str(ds.label_path(i)), cv2.IMREAD_GRAYSCALE), green))
    print(f"CRDLD {args.split}, every {args.step}th image ({len(idx)}), forward-camera setting, tensor path; "
          "sigma 0.1 mean over the images with a scored labelled line; each detector column as "
          f"'equal spacing / lattice_roll_grid {ROLL_GRID} / and lattice_comb_warps {COMB_WARPS}'")
    lines = ["| view | images | lattice fitted to the labels | rolled lattice fitted to the labels | green mask "
             "| `ok` | `ok` below 0.2 | green mask moved | label evidence | `ok` |\n|---|---|---|---|---|---|---|---|---|---|"]
    for name, view in VIEWS.items():
        images, masks, greens, truths, models = [], [], [], [], []
        for rgb, lab, grn in raw:
            im, mk = view(rgb, cv2.INTER_LINEAR), view(lab, cv2.INTER_NEAREST)
            h, w = im.shape[:2]
            truth = truth_from_mask(mk, w, h)
            if len(truth.lines) < 2 or truth.central < 0 or np.isnan(score_image([], "ok", truth)):
                continue  # no scored (line, row) pair
            images.append(im)
            masks.append(mk)
            greens.append(view(grn, cv2.INTER_NEAREST))
            truths.append(truth)
            models.append(model_scores(truth, *working_size(w, h, params.image_width)))
        m = np.array(models)
        green, moved, label = ([detector_scores(det, images, truths, ev) for det in dets]
                               for ev in (None, greens, masks))

        def two(runs: list[tuple[float, float, float]], j: int, fmt: str) -> str:
            return " / ".join("-" if np.isnan(r[j]) else format(r[j], fmt) for r in runs)  # "-": no image ok

        lines.append(f"| {name} | {len(images)} | {m[:, 0].mean():.3f} | {m[:, 1].mean():.3f} | {two(green, 0, '.3f')} | "
                     f"{two(green, 1, '.0%')} | {two(green, 2, '.0%')} | {two(moved, 0, '.3f')} | "
                     f"{two(label, 0, '.3f')} | {two(label, 1, '.0%')} |")
        print(lines[-1], file=sys.stderr, flush=True)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
