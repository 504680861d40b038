"""Dataset evaluation on CRBD (CRDA) and CRDLD (ALGORITHM.md 10.1): detection, scores per image,
summaries, files and a plot; CRDA of the same CRBD images under several vegetation colours
(:func:`compare_colors`)."""

from __future__ import annotations

import csv
import functools
import json
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchrow.apps.sink import RecordSink, read_records
from torchrow.core.io import Evidenced, ImageError
from torchrow.core.params import Params
from torchrow.core.progress import progress as progress_bar
from torchrow.core.results import ImageResult
from torchrow.engines.runner import run
from torchrow.evaluation import crdld
from torchrow.evaluation.datasets import CRBD, CRDLD
from torchrow.evaluation.metrics import crda, crda_official, crda_thesis, summarize

__all__ = ["EvalRow", "EvalReport", "evaluate", "score_tmg_files", "SUBSETS", "CRDLDRow", "CRDLDReport",
           "evaluate_crdld", "ColorComparison", "compare_colors"]

#: Subsets reported: CRBD's own classification (1 straight, 2 curved).
SUBSETS = ("all", "straight", "curved")

@dataclass
class EvalRow:
    """Scores of one image."""

    name: str
    row_set: int | None
    tmgem_set: int | None
    status: str
    crda_01: float
    crda_03: float
    crda_thesis: float
    tmgem_01: float
    tmgem_03: float
    seconds: float


@dataclass
class EvalReport:
    rows: list[EvalRow] = field(default_factory=list)
    records: list[dict] = field(default_factory=list)

    def summary(self) -> dict[str, dict[str, dict[str, float | int]]]:
        """``{subset: {metric: {mean, median, n}}}`` for subsets all / straight / curved."""
        out: dict[str, dict[str, dict[str, float | int]]] = {}
        for sub in SUBSETS:
            rows = [r for r in self.rows if sub == "all" or r.row_set == (1 if sub == "straight" else 2)]
            out[sub] = {m: summarize([getattr(r, m) for r in rows]) for m in
                        ("crda_01", "crda_03", "crda_thesis", "tmgem_01", "tmgem_03")}
        return out

    def format_summary(self) -> str:
        s = self.summary()
        lines = [f"{'subset':<9} {'n':>4}  {'CRDA s=0.1':>17}  {'CRDA s=0.3':>17}  {'thesis variant':>17}  "
                 f"{'TMGEM s=0.1':>17}",
                 f"{'':<9} {'':>4}  {'mean / median':>17}  {'mean / median':>17}  {'mean / median':>17}  "
                 f"{'mean / median':>17}"]
        for sub in SUBSETS:
            m = s[sub]
            cell = lambda k, m=m: f"{m[k]['mean']:.3f} / {m[k]['median']:.3f}" if m[k]["n"] else "-"  # noqa: E731
            lines.append(f"{sub:<9} {m['crda_01']['n']:>4}  {cell('crda_01'):>17}  {cell('crda_03'):>17}  "
                         f"{cell('crda_thesis'):>17}  {cell('tmgem_01'):>17}")
        return "\n".join(lines)

    def write(self, out_dir: Path, records: bool = True) -> list[Path]:
        """Write ``scores.csv``, ``detections.jsonl``, ``summary.json`` and ``crda_histogram.png``
        (``records=False``: not ``detections.jsonl``, which the run streamed itself)."""
        out_dir.mkdir(parents=True, exist_ok=True)
        paths = [out_dir / "scores.csv", out_dir / "detections.jsonl", out_dir / "summary.json",
                 out_dir / "crda_histogram.png"]
        with open(paths[0], "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["name", "row_set", "tmgem_set", "status", "crda_sigma0.1", "crda_sigma0.3",
                         "crda_thesis", "tmgem_sigma0.1", "tmgem_sigma0.3", "seconds"])
            for r in self.rows:
                wr.writerow([r.name, r.row_set, r.tmgem_set, r.status, f"{r.crda_01:.6f}", f"{r.crda_03:.6f}",
                             f"{r.crda_thesis:.6f}", f"{r.tmgem_01:.6f}", f"{r.tmgem_03:.6f}", f"{r.seconds:.4f}"])
        if records:
            with open(paths[1], "w") as fh:
                for rec in self.records:
                    fh.write(json.dumps(rec) + "\n")
        else:
            paths.pop(1)
        paths[-2].write_text(json.dumps(self.summary(), indent=2) + "\n")
        plot_cumulative([("torchrow", [r.crda_01 for r in self.rows]),
                         ("TMGEM", [r.tmgem_01 for r in self.rows])], paths[-1],
                        title=f"CRBD, official CRDA (sigma 0.1, m 3), {len(self.rows)} images")
        return paths


def plot_cumulative(series: Sequence[tuple[str, Sequence[float]]], path: Path, title: str = "",
                    metric: str = "CRDA") -> None:
    """Normalised cumulative histogram of a score (``metric``, CRDA by default) as CRBD's demo
    draws it: for each value x, the fraction of images scoring at least x."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.linspace(0, 1, 101)
    fig, ax = plt.subplots(figsize=(5.5, 4), dpi=110)
    for label, scores in series:
        s = np.asarray(scores, dtype=np.float64)
        if s.size == 0:
            continue
        frac = (s[None, :] >= x[:, None]).mean(axis=1)
        ax.plot(x, frac, label=f"{label} (mean {s.mean():.3f}, median {np.median(s):.3f})")
    ax.set_xlabel(metric)
    ax.set_ylabel(f"fraction of images with {metric} >= x")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _load_crbd(path: str, width: int, mask: str | None = None) -> np.ndarray | Evidenced:
    """A CRBD image (with its row evidence from ``mask``, :func:`~torchrow.core.io.load_with_evidence`);
    its width must be the working width (the ground truth is in its pixels)."""
    from torchrow.core.io import load_image, load_with_evidence

    got = load_image(path) if mask is None else load_with_evidence(path, mask)
    rgb = got if isinstance(got, np.ndarray) else got.image
    if rgb.shape[1] != width:
        raise ImageError(f"CRBD image is {rgb.shape[1]} px wide but image_width is "
                         f"{width}; the ground truth is in the image's own pixels")
    return got


def _detections(names: Sequence[str], loader: Callable[[int], Callable[[], np.ndarray | Evidenced]],
                indices: Sequence[int],
                impl: str, params: Params, batch_size: int, device: str | None, progress: bool,
                sink: RecordSink | None, engine: str, address: str | None, workers: int | None,
                desc: str) -> list[tuple[int, ImageResult, dict, float]]:
    """``(index, result, record, seconds)`` for every index, in order: detected (streamed to
    ``sink``), or read back from the records ``sink`` already holds (``seconds`` NaN)."""
    prior: dict[str, dict] = {}
    if sink is not None and sink.done:
        wanted = {names[i] for i in indices}
        prior = {r["name"]: r for r in read_records(sink.stream) if r.get("name") in wanted}
    todo = [i for i in indices if names[i] not in prior]
    items = [(names[i], loader(i)) for i in todo]
    if engine == "ray":
        from torchrow.engines.distributed import run as ray_run

        stream: Iterator = ray_run(items, impl, params, batch_size, device, progress, desc=f"{desc} ({impl}, ray)",
                                   workers=workers, address=address)
    else:
        stream = run(items, impl, params, batch_size, device, progress, desc=f"{desc} ({impl})")
    got: dict[int, tuple[ImageResult, dict, float]] = {}
    for k, _, res, seconds in stream:
        rec = res.to_record()
        if sink is not None:
            sink.write(rec)
        got[todo[k]] = (res, rec, seconds)
    out = []
    for i in indices:
        if i in got:
            res, rec, seconds = got.pop(i)
        else:
            rec = prior[names[i]]
            res, seconds = ImageResult.from_record(rec, params.theta_step), float("nan")
        out.append((i, res, rec, seconds))
    return out


def _evidence_of(evidence: Mapping[int, str | Path] | None, indices: Sequence[int]) -> dict[int, str]:
    """The mask file of every index (``{}`` without evidence); ``ValueError`` naming the first
    index without one, before anything runs."""
    if evidence is None:
        return {}
    lacking = [i for i in indices if i not in evidence]
    if lacking:
        raise ValueError(f"evidence: no mask for {len(lacking)} of {len(indices)} image(s), the first index {lacking[0]}")
    return {i: str(evidence[i]) for i in indices}


def evaluate(crbd: CRBD, indices: Sequence[int] | None = None, impl: str = "tensor",
             params: Params | None = None, batch_size: int = 64, device: str | None = None,
             progress: bool = True, sink: RecordSink | None = None, engine: str = "local",
             address: str | None = None, workers: int | None = None,
             evidence: Mapping[int, str | Path] | None = None) -> EvalReport:
    """Detect CRBD images with ``impl`` ("tensor" or "reference") and score each one.

    A file that cannot be read or a detector failure gives an ``error`` record and scores 0;
    the run always goes on. ``seconds`` per image is the batch's wall time divided by its
    size for the tensor path. ``sink``: records are streamed to it as they come; images
    whose record it already holds (``RecordSink(..., resume=True)``) are not detected again
    but scored from that record (``seconds`` NaN). ``engine="ray"`` detects on a Ray cluster
    (:func:`torchrow.engines.distributed.run`, ``address``, ``workers``). ``evidence``: a row-mask
    file per image index (improved mode, ALGORITHM.md 11.1.1, :func:`~torchrow.core.io.load_evidence`),
    fitted in place of the green mask; every index of ``indices`` needs one.
    """
    params = params or Params()
    indices = list(range(len(crbd))) if indices is None else list(indices)
    masks = _evidence_of(evidence, indices)

    def loader(i: int) -> Callable[[], np.ndarray | Evidenced]:
        return functools.partial(_load_crbd, str(crbd.image_path(i)), params.image_width, masks.get(i))

    report = EvalReport()
    for i, res, rec, seconds in _detections(crbd.names, loader, indices, impl, params, batch_size, device,
                                            progress, sink, engine, address, workers, "eval"):
        report.rows.append(_score(crbd, i, res, params, seconds))
        report.records.append(rec)
    return report


def _score(crbd: CRBD, i: int, res: ImageResult, params: Params, seconds: float) -> EvalRow:
    item = crbd[i]
    gt = item.ground_truth
    try:
        tm = crbd.tmgem(i)
        tm01 = crda(tm, gt.c, gt.d, sigma=0.1, width=params.image_width)
        tm03 = crda(tm, gt.c, gt.d, sigma=0.3, width=params.image_width)
    except (OSError, ValueError):
        tm01 = tm03 = float("nan")
    return EvalRow(item.name, item.row_set, item.tmgem_set, res.status,
                   crda_official(res, gt, sigma=0.1), crda_official(res, gt, sigma=0.3),
                   crda_thesis(res, gt, sigma=params.crda_sigma), tm01, tm03, seconds)


def score_tmg_files(crbd: CRBD, results_dir: Path, ext: str = ".tmg",
                    progress: bool = True) -> list[tuple[str, float, float]]:
    """Score external result files in CRBD's ``.tmg`` format (h lines x 3 columns: x of three
    adjacent rows per image row). Returns ``(name, crda sigma 0.1, crda sigma 0.3)``; a missing
    or malformed file scores 0."""
    out = []
    bar = progress_bar(len(crbd), "score", progress, unit="image")
    for i in range(len(crbd)):
        bar.update(1)
        item = crbd[i]
        path = results_dir / f"{item.stem}{ext}"
        gt = item.ground_truth
        try:
            U = np.loadtxt(path, dtype=np.float64, ndmin=2)
            if U.shape != (gt.height, 3):
                raise ValueError(f"{path.name}: expected {gt.height} x 3 values, got {U.shape}")
            s01, s03 = crda(U, gt.c, gt.d, sigma=0.1), crda(U, gt.c, gt.d, sigma=0.3)
        except (OSError, ValueError) as exc:
            print(f"torchrow: warning: {exc}", file=sys.stderr)
            s01 = s03 = 0.0
        out.append((item.name, s01, s03))
    bar.close()
    return out


@dataclass
class CRDLDRow:
    """Scores of one CRDLD image (:func:`torchrow.evaluation.crdld.score`; NaN: undefined)."""

    name: str
    status: str
    sigma01: float
    sigma03: float
    central_mae: float
    seconds: float


@dataclass
class CRDLDReport:
    split: str = ""
    rows: list[CRDLDRow] = field(default_factory=list)
    records: list[dict] = field(default_factory=list)

    def summary(self) -> crdld.CRDLDSummary:
        return crdld.summarize([r.status for r in self.rows],
                               [crdld.CRDLDScore(r.sigma01, r.sigma03, r.central_mae) for r in self.rows])

    def format_summary(self) -> str:
        return self.summary().format(f"CRDLD {self.split}")

    def write(self, out_dir: Path, records: bool = True) -> list[Path]:
        """Write ``scores.csv``, ``detections.jsonl``, ``summary.json`` and ``crda_histogram.png``
        (``records=False``: not ``detections.jsonl``, which the run streamed itself)."""
        out_dir.mkdir(parents=True, exist_ok=True)
        paths = [out_dir / "scores.csv", out_dir / "detections.jsonl", out_dir / "summary.json",
                 out_dir / "crda_histogram.png"]
        with open(paths[0], "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["name", "status", "crdld_sigma0.1", "crdld_sigma0.3", "central_mae_px", "seconds"])
            for r in self.rows:
                wr.writerow([r.name, r.status, f"{r.sigma01:.6f}", f"{r.sigma03:.6f}", f"{r.central_mae:.4f}",
                             f"{r.seconds:.4f}"])
        if records:
            with open(paths[1], "w") as fh:
                for rec in self.records:
                    fh.write(json.dumps(rec) + "\n")
        else:
            paths.pop(1)
        paths[-2].write_text(json.dumps({"dataset": "crdld", "split": self.split, **self.summary().to_dict()},
                                        indent=2) + "\n")
        scored = [r.sigma01 for r in self.rows if np.isfinite(r.sigma01)]
        plot_cumulative([("torchrow", scored)], paths[-1], metric="CRDLD score",
                        title=f"CRDLD {self.split}, sigma 0.1, central row and neighbours, {len(scored)} images")
        return paths


def evaluate_crdld(ds: CRDLD, indices: Sequence[int] | None = None, impl: str = "tensor",
                   params: Params | None = None, batch_size: int = 64, device: str | None = None,
                   progress: bool = True, sink: RecordSink | None = None, engine: str = "local",
                   address: str | None = None, workers: int | None = None,
                   evidence: Mapping[int, str | Path] | None = None) -> CRDLDReport:
    """Detect CRDLD images with ``impl`` ("tensor" or "reference") and score each one
    (ALGORITHM.md 10.1); arguments and resuming as for :func:`evaluate`. Images are resized
    to the working width as ``torchrow detect`` does; the score scales the rows back to the
    image's own pixels; ``evidence`` as for :func:`evaluate`."""
    from torchrow.core.io import load_image, load_with_evidence

    params = params or Params()
    indices = list(range(len(ds))) if indices is None else list(indices)
    masks = _evidence_of(evidence, indices)

    def loader(i: int) -> Callable[[], np.ndarray | Evidenced]:
        if i in masks:
            return functools.partial(load_with_evidence, str(ds.image_path(i)), masks[i], params.image_width,
                                     params.max_pixels)
        return functools.partial(load_image, str(ds.image_path(i)), params.image_width, params.max_pixels)

    report = CRDLDReport(split=ds.split)
    for i, res, rec, seconds in _detections(ds.names, loader, indices, impl, params, batch_size, device,
                                            progress, sink, engine, address, workers, "eval"):
        s = crdld.score(res, ds.ground_truth(i))
        report.rows.append(CRDLDRow(ds.names[i], res.status, s.sigma01, s.sigma03, s.central_mae, seconds))
        report.records.append(rec)
    return report


@dataclass
class ColorComparison:
    """CRDA of the same images under several vegetation-colour choices (:func:`compare_colors`).

    ``names`` image names; ``crda01`` / ``crda03`` ``{arm: float64 (n,)}`` official CRDA at
    sigma 0.1 / 0.3; ``precision`` / ``fraction`` ``{arm: (n,)}`` of the hard raw mask against
    the band target; ``results`` ``{arm: [ImageResult]}``; ``colors`` ``{arm: uint8 (n, 3)}``
    the colour each image was segmented with.
    """

    names: list[str]
    crda01: dict[str, np.ndarray]
    crda03: dict[str, np.ndarray]
    precision: dict[str, np.ndarray]
    fraction: dict[str, np.ndarray]
    results: dict[str, list]
    colors: dict[str, np.ndarray]

    def table(self) -> str:
        """One line per arm: official CRDA sigma 0.1 and 0.3 mean / median, mask precision."""
        lines = [f"{'colour':<22} {'n':>4}  {'CRDA s0.1 mean/median':>22}  {'CRDA s0.3 mean/median':>22}  "
                 f"{'mask precision':>14}  {'mask size':>9}"]
        for arm in self.crda01:
            a, b = self.crda01[arm], self.crda03[arm]
            lines.append(f"{arm:<22} {len(a):>4}  {a.mean():>10.3f} / {np.median(a):<9.3f}  "
                         f"{b.mean():>10.3f} / {np.median(b):<9.3f}  {self.precision[arm].mean():>14.3f}  "
                         f"{self.fraction[arm].mean():>9.3f}")
        return "\n".join(lines)


def compare_colors(crbd: CRBD, indices: Sequence[int], colors: Mapping[str, Sequence[int] | np.ndarray | None],
                   params: Params | None = None, band: float = 0.3, batch_size: int = 32) -> ColorComparison:
    """Detect ``indices`` once per colour choice with the hard pipeline and score them.

    Parameters
    ----------
    crbd : CRBD
    indices : sequence of int
        Images to score (e.g. held-out ``crbd.indices("test")``).
    colors : mapping
        ``{arm name: colour}``: ``None`` = per-image clustering (the default pipeline), or an
        RGB ``uint8`` triple given to every image (``veg_color=``).
    params : Params, optional
    band : float
        Band of :func:`torchrow.nn.calibrate.row_band_target` for the mask precision.
    batch_size : int
        Images per detector call.
    """
    import torch

    from torchrow.engines.detector import CropRowDetector
    from torchrow.functional.vegetation import raw_mask
    from torchrow.nn.calibrate import load_training_set, mask_precision

    p = params or Params()
    if not p.runs_section6():
        raise ValueError(f"compare_colors compares section 2's vegetation colours, which mode {p.mode!r} with "
                         f"lattice_vp {p.lattice_vp!r} does not use")
    det = CropRowDetector(p)
    data = load_training_set(crbd, indices, band)
    out = ColorComparison(data.names, {}, {}, {}, {}, {}, {})
    for arm, color in colors.items():
        res, used, prec, frac = [], [], [], []
        for s0 in range(0, len(indices), batch_size):
            imgs = data.images[s0:s0 + batch_size]
            vc = None if color is None else torch.as_tensor(np.asarray(color), dtype=torch.uint8).reshape(3)
            batch = det(imgs, veg_color=vc)
            res.extend(batch.results(data.names[s0:s0 + batch_size]))
            used.append(batch.veg_color)
            raw = raw_mask(imgs, batch.veg_color, batch.k, batch.sky)
            pr, fr = mask_precision(raw, data.targets[s0:s0 + batch_size], data.regions[s0:s0 + batch_size])
            prec.append(pr)
            frac.append(fr)
        gts = [crbd.ground_truth(i) for i in indices]
        out.results[arm] = res
        out.colors[arm] = torch.cat(used).numpy()
        out.crda01[arm] = np.array([crda_official(r, g, sigma=0.1) for r, g in zip(res, gts)])
        out.crda03[arm] = np.array([crda_official(r, g, sigma=0.3) for r, g in zip(res, gts)])
        out.precision[arm] = np.concatenate(prec)
        out.fraction[arm] = np.concatenate(frac)
    return out
