"""Forward-camera views off to the side and rolled: what the improved mode and its row model do
when the vanishing point leaves the top centre (ALGORITHM.md 11.6, *Views off to the side*).

    python benchmarks/bench_crdld_views.py [--data DIR] [--split train] [--step 5]

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

A second table tries the row model that the first one asks for on the detector's own output: a
prototype (numpy, this script only; not a stage of either path) of 11.3's straight refit with
projective spacing, ``x (1 + g k) = c0 + c1 t + k (d0 + d1 t)``, solved as a linear least
squares for each ``g`` of a grid (-0.3 .. 0.3 by 0.01), the ``g`` whose rows lie nearest the
cell means in x kept (one observation per cell, the cell mean, as 11.3), its cells
``lattice_tolerance`` times the local spacing ``(d(t) - g c(t)) / (1 + g k)^2`` each side of
``(c(t) + k d(t)) / (1 + g k)``, up to ``lattice_iterations`` steps started from the detector's
three rows (their straight lattice through the bottom and
the middle image rows, ``g = 0``), against the same refit with ``g`` held at 0; its rows keep the
detector's status and validity. On the green mask as the detector runs it, and on the label
evidence.

No timing. Choose nothing on the test split with it: it reads labels.
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
ROLL_GRID = np.linspace(-0.3, 0.3, 61)  # the prototype's g, searched at each step


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


def start_lattice(rows: list[dict], height: int) -> tuple[float, ...] | None:
    """``(c0, c1, d0, d1, g = 0)``: the straight lattice through a record's three rows at the bottom
    and the middle image rows (working px); None unless it has three rows."""
    if len(rows) != 3:
        return None

    def x(r: dict, y: float) -> float:
        return ((r["e"] * y + r["c"]) * y + r["a"]) * y + r["b"]

    y0, y1 = height - 1, (height - 1) // 2
    t1 = y1 - y0
    cb, ct = x(rows[1], y0), x(rows[1], y1)
    db, dt = (x(rows[2], y0) - x(rows[0], y0)) / 2, (x(rows[2], y1) - x(rows[0], y1)) / 2
    return cb, (ct - cb) / t1, db, (dt - db) / t1, 0.0


def projective_refit(mask: np.ndarray, lat: tuple[float, ...], params: Params, free_g: bool) -> tuple[float, ...]:
    """The prototype refit of the module docstring on a working-size ``bool (H, W)`` mask:
    ``(c0, c1, d0, d1, g)`` after up to ``lattice_iterations`` steps (``g`` held at 0 unless ``free_g``)."""
    from torchrow.reference.lattice import prefix_sums

    counts, pre_x = prefix_sums(mask)
    h, w = mask.shape
    t = np.arange(h, dtype=np.float64) - (h - 1)
    yy = np.arange(h)
    for _ in range(params.lattice_iterations):
        c0, c1, d0, d1, g = lat
        c, d = c0 + c1 * t, d0 + d1 * t
        design, target = [], []
        for k in (-1, 0, 1):
            den = 1 + g * k
            spacing = (d - g * c) / (den * den)
            good = spacing > params.lattice_min_spacing_px
            centre, half = (c + k * d) / den, params.lattice_tolerance * spacing
            x0 = np.clip(np.floor(np.where(good, centre - half, 0.0)) + 1, 0, w).astype(np.int64)
            x1 = np.maximum(np.clip(np.ceil(np.where(good, centre + half, 0.0)), 0, w).astype(np.int64), x0)
            n = counts[yy, x1] - counts[yy, x0]
            keep = good & (n > 0)
            xm = (pre_x[yy, x1] - pre_x[yy, x0])[keep] / n[keep]
            cols = [np.ones_like(xm), t[keep], np.full_like(xm, k), k * t[keep]]
            design.append(np.stack(cols, axis=1))
            target.append(xm)
        a, b = np.concatenate(design), np.concatenate(target)
        if len(b) < 5 or np.linalg.matrix_rank(a) < a.shape[1]:
            break
        kk = a[:, 2]
        best = (np.inf, lat)
        for gg in (ROLL_GRID if free_g else (0.0,)):
            den = 1 + gg * kk
            if den.min() <= 0.25:
                continue
            sol = np.linalg.lstsq(a, b * den, rcond=None)[0]
            err = float((((a @ sol) / den - b) ** 2).sum())
            if err < best[0]:
                best = (err, (*map(float, sol), float(gg)))
        new = best[1]
        if np.allclose(new, lat, rtol=0, atol=1e-9):
            break
        lat = new
    return lat


def projective_rows(lat: tuple[float, ...], like: list[dict], height: int) -> list[dict]:
    """Rows ``k = -1, 0, 1`` of ``(c0, c1, d0, d1, g)`` as record rows, valid where ``like``'s are."""
    c0, c1, d0, d1, g = lat
    out = []
    for k, old in zip((-1, 0, 1), like):
        den = 1 + g * k
        x0, s = (c0 + k * d0) / den, (c1 + k * d1) / den
        out.append(dict(a=s, b=x0 - s * (height - 1), c=0.0, e=0.0, valid=bool(old["valid"])))
    return out


def detector_scores(det, images: list[np.ndarray], truths: list[CRDLDTruth],
                    evidence: list[np.ndarray] | None) -> tuple[float, float, float, float, float]:
    """Sigma 0.1 mean, ``ok`` share, share of the ``ok`` images below 0.2, and the sigma 0.1 means
    of the prototype refit with ``g`` held at 0 and with ``g`` free, from the detector's rows."""
    from torchrow.core.io import evidence_mask, lattice_params
    from torchrow.reference.lattice import row_evidence
    from torchrow.reference.pipeline import prepare

    recs = [r.to_record() for r in det.detect(images, evidence=evidence).results()]
    s, s0, sg = [], [], []
    for j, (r, tr) in enumerate(zip(recs, truths)):
        size, status = (r["width"], r["height"]), str(r["status"])
        s.append(score_image(r["rows"], status, tr, 0.1, size))
        lat = start_lattice(r["rows"], size[1])
        if lat is None:
            s0.append(s[-1])
            sg.append(s[-1])
            continue
        fp = lattice_params(*size, det.params)
        ev = None if evidence is None else evidence_mask(evidence[j], *size)
        mask = row_evidence(prepare(images[j], det.params), 0, fp, ev)
        for out, free_g in ((s0, False), (sg, True)):
            rows = projective_rows(projective_refit(mask, lat, fp, free_g), r["rows"], size[1])
            out.append(score_image(rows, status, tr, 0.1, size))
    ok = np.array([r["status"] == "ok" for r in recs])
    a = np.array(s)
    low = float((a[ok] < LOW_SCORE).mean()) if ok.any() else float("nan")
    return float(a.mean()), float(ok.mean()), low, float(np.mean(s0)), float(np.mean(sg))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None)
    ap.add_argument("--split", default="train", choices=("train", "test"))
    ap.add_argument("--step", type=int, default=5, help="every STEP-th image (default 5)")
    args = ap.parse_args()

    from torchrow.core.io import lattice_params, working_size
    from torchrow.engines.detector import CropRowDetector
    from torchrow.reference.lattice import green_mask

    ds = CRDLD(data_root(args.data), args.split)  # a data folder, its crdld_dev/ or a split folder
    params = Params(mode="improved", **FORWARD_CAMERA)
    det = CropRowDetector(params)
    idx = list(range(0, len(ds), args.step))
    raw = []
    for i in idx:
        rgb = ds.image(i, None)
        green = green_mask(rgb, 0, lattice_params(rgb.shape[1], rgb.shape[0], params)).astype(np.uint8) * 255
        raw.append((rgb, cv2.imread(str(ds.label_path(i)), cv2.IMREAD_GRAYSCALE), green))
    print(f"CRDLD {args.split}, every {args.step}th image ({len(idx)}), forward-camera setting, tensor path; "
          "sigma 0.1 mean over the images with a scored labelled line")
    head = ("| view | images | lattice fitted to the labels | rolled lattice fitted to the labels | green mask "
            "| `ok` | `ok` below 0.2 | green mask moved | label evidence | `ok` |\n|---|---|---|---|---|---|---|---|---|---|")
    lines, proto = [head], ["| view | green mask: detector | refit, g = 0 | refit, g free | label evidence: detector "
                            "| refit, g = 0 | refit, g free |\n|---|---|---|---|---|---|---|"]
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
        green = detector_scores(det, images, truths, None)
        moved = detector_scores(det, images, truths, greens)
        label = detector_scores(det, images, truths, masks)
        lines.append(f"| {name} | {len(images)} | {m[:, 0].mean():.3f} | {m[:, 1].mean():.3f} | {green[0]:.3f} | "
                     f"{green[1]:.1%} | {green[2]:.1%} | {moved[0]:.3f} | {label[0]:.3f} | {label[1]:.1%} |")
        proto.append(f"| {name} | {green[0]:.3f} | {green[3]:.3f} | {green[4]:.3f} | {label[0]:.3f} | "
                     f"{label[3]:.3f} | {label[4]:.3f} |")
        print(lines[-1], file=sys.stderr, flush=True)
    print("\n".join(lines))
    print("\nThe prototype refit with projective spacing, from the detector's rows (sigma 0.1 mean)\n")
    print("\n".join(proto))


if __name__ == "__main__":
    main()
