"""Exported ONNX detector in onnxruntime vs the torch tensor path, side by side in one run.

Exports the image-mode detector (default parameters, 320x240, batch B) unless ``--model``
is given, then times onnxruntime and :class:`torchrow.engines.detector.CropRowDetector` on the same
CRBD images at batch B and checks that their records agree (discrete outputs equal, rows
within 1e-4 px). Appends model size, export time, images/s and the parity count to
RESULTS.md.

    python benchmarks/bench_onnx.py [--data ../shared/data] [--batch 1] [--limit N] [--model M] [--no-write]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import append_results, data_root  # type: ignore[import-not-found]

from torchrow import Params
from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.datasets import CRBD
from torchrow.onnx.export import to_onnx
from torchrow.onnx.metadata import model_info
from torchrow.onnx.runtime import OnnxDetector


def to_batch(imgs: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()


def differences(ref, got, tol: float = 1e-4) -> int:
    """Number of images whose records differ (discrete fields, or rows by more than tol px)."""
    bad = 0
    for a, b in zip(ref, got):
        ra, rb = a.to_record(), b.to_record()
        same = all(ra[k] == rb[k] for k in ra if k != "rows") and len(ra["rows"]) == len(rb["rows"])
        for x, y in zip(ra["rows"], rb["rows"]):
            same &= x["valid"] == y["valid"] and x["reason"] == y["reason"]
            for k in ("a", "b"):
                same &= (x[k] is None and y[k] is None) or (x[k] is not None and y[k] is not None
                                                            and abs(x[k] - y[k]) <= tol)
        bad += not same
    return bad


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--limit", type=int, default=0, help="at most this many CRBD images (default all)")
    ap.add_argument("--model", default=None, help="an exported model (default: export one now)")
    ap.add_argument("--scatter-free", action="store_true", help="export the scatter-free form")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    ds = CRBD(data_root(args.data))
    n = min(len(ds), args.limit) if args.limit else len(ds)
    imgs = [ds.image(i) for i in range(n)]
    tmp = tempfile.TemporaryDirectory()
    if args.model:
        path, t_export = Path(args.model), float("nan")
    else:
        t0 = time.perf_counter()
        path = to_onnx(Path(tmp.name) / "detector.onnx", batch=args.batch, params=Params(),
                       scatter_free=args.scatter_free, progress=lambda ph: print(f"export: {ph}", flush=True))
        t_export = time.perf_counter() - t0
    info = model_info(path)
    bs = info["batch"]
    t0 = time.perf_counter()
    det_onnx = OnnxDetector(path)
    t_open = time.perf_counter() - t0
    det_torch = CropRowDetector(info["params"])
    det_onnx(to_batch(imgs[:1]))  # warm-up
    det_torch(to_batch(imgs[:1]))
    t_onnx = t_torch = 0.0
    bad = 0
    for s in range(0, n, bs):
        x = to_batch(imgs[s:s + bs])
        t0 = time.perf_counter()
        got = det_onnx(x).results()
        t1 = time.perf_counter()
        ref = det_torch(x).results()
        t2 = time.perf_counter()
        t_onnx += t1 - t0
        t_torch += t2 - t1
        bad += differences(ref, got)
    ops = ", ".join(f"{k} {v}" for k, v in sorted(info["ops"].items()))
    lines = [f"### {n} CRBD images (320x240), batch {bs}, default parameters", "",
             "| | ms / image | images / s |", "|---|---|---|",
             f"| torch tensor path (`CropRowDetector`) | {t_torch / n * 1e3:.0f} | {n / t_torch:.2f} |",
             f"| onnxruntime {__import__('onnxruntime').__version__} (CPU EP, basic graph optimisations) | "
             f"{t_onnx / n * 1e3:.0f} | {n / t_onnx:.2f} |", "",
             f"Model: {info['size'] / 2**20:.1f} MiB, opset {info['opset']}, {info['exporter']}, "
             f"{sum(info['ops'].values())} nodes; export time "
             + (f"{t_export:.0f} s" if t_export == t_export else "not measured (--model given)") + ".",
             f"Session open: {t_open:.1f} s; peak RSS of this process (export, torch and onnxruntime): "
             f"{__import__('resource').getrusage(__import__('resource').RUSAGE_SELF).ru_maxrss / 2**10:.0f} MiB.",
             "", f"Parity: {n - bad} of {n} images identical (discrete outputs equal, rows within 1e-4 px).",
             "", f"Ops: {ops}."]
    print("\n".join(lines))
    if not args.no_write:
        cmd = "python benchmarks/bench_onnx.py" + (f" --batch {args.batch}" if args.batch != 1 else "") + (
            f" --limit {args.limit}" if args.limit else "") + (" --model MODEL" if args.model else "") + (
            " --scatter-free" if args.scatter_free else "")
        append_results("ONNX export: onnxruntime vs torch", cmd, "\n".join(lines))


if __name__ == "__main__":
    main()
