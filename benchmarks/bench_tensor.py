"""Tensor path vs reference, side by side in one run, with an OpenCV floor.

1. All CRBD images: reference per image, tensor at batch 64 (per-stage breakdown), and the
   floor: one single-thread ``cv2.HoughLines`` pass per image over an excess-green mask; then
   the floor, the faithful and the improved mode (batch 64; the improved mode also in chunks of
   8 and 16 beside its default 12) side by side, best of ``--rounds`` (2) rounds.
2. Batch-size scaling on CRBD images (1 to 256).
3. Image-size scaling on synthetic fields (320x240 to 1280x960).
4. Peak memory (max RSS of a fresh process) of one batch of 64 CRBD images.

    python benchmarks/bench_tensor.py [--data ../shared/data] [--quick] [--rounds 2] [--no-write]
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from _common import append_results, data_root  # type: ignore[import-not-found]

from torchrow import Params
from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.datasets import CRBD
from torchrow.evaluation.synthetic import FieldSpec, render
from torchrow.reference import detect


def to_batch(imgs: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()


def opencv_floor(imgs: list[np.ndarray], threshold: int | None = None) -> float:
    """Seconds per image of one single-thread cv2.HoughLines pass over an excess-green mask.

    The mask is excess green ``2G - R - B`` clipped to ``[0, 255]`` and thresholded by Otsu (the
    usual ExG segmentation; on CRBD it keeps about 24 % of the pixels). ``threshold=None`` is
    the floor: a Hough threshold above any possible count (the mask's pixel count + 1), so the
    pass only votes and returns no line. A small threshold returns many lines and costs more;
    it is reported beside for scale only.
    """
    cv2.setNumThreads(1)
    t = 0.0
    for im in imgs:
        t0 = time.perf_counter()
        f = im.astype(np.int16)
        exg = np.clip(2 * f[..., 1] - f[..., 0] - f[..., 2], 0, 255).astype(np.uint8)
        _, mask = cv2.threshold(exg, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        cv2.HoughLines(mask, 1, np.pi / 180, mask.size + 1 if threshold is None else threshold)
        t += time.perf_counter() - t0
    cv2.setNumThreads(-1)
    return t / len(imgs)


def time_tensor(det: CropRowDetector, imgs: list[np.ndarray], bs: int, profile: bool = False):
    total, stages = 0.0, {}
    for s in range(0, len(imgs), bs):
        x = to_batch(imgs[s:s + bs])
        t0 = time.perf_counter()
        out = det(x, profile=profile)
        total += time.perf_counter() - t0
        for k, v in out.timings.items():
            stages[k] = stages.get(k, 0.0) + v
    return total / len(imgs), {k: v / len(imgs) for k, v in stages.items()}


def time_reference(imgs: list[np.ndarray]) -> float:
    t0 = time.perf_counter()
    for im in imgs:
        detect(im)
    return (time.perf_counter() - t0) / len(imgs)


def peak_memory(data: Path, bs: int) -> float:
    """Peak RSS (MiB, VmHWM: getrusage's maxrss would carry the parent's over exec) of a fresh
    process: after a warm-up batch of 1, and after one batch of ``bs`` CRBD images."""
    code = f"""
import numpy as np, torch
def hwm():
    return int(open('/proc/self/status').read().split('VmHWM:')[1].split()[0])
from torchrow.evaluation.datasets import CRBD
from torchrow.engines.detector import CropRowDetector
ds = CRBD({str(data)!r}); imgs = [ds.image(i % len(ds)) for i in range({bs})]
x = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()
det = CropRowDetector(); det(x[:1])
base = hwm()
det(x)
print(base / 1024, hwm() / 1024)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    return float(out[0]), float(out[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--quick", action="store_true", help="fewer images and sizes (a smoke run)")
    ap.add_argument("--rounds", type=int, default=2, help="side-by-side rounds; each run's best counts")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    ds = CRBD(data_root(args.data))
    n = 40 if args.quick else len(ds)
    imgs = [ds.image(i) for i in range(n)]
    det = CropRowDetector(Params())
    det(to_batch(imgs[:2]))  # warm-up: tables, caches
    detect(imgs[0])

    lines = []
    t_ref = time_reference(imgs)
    t_ten, stages = time_tensor(det, imgs, 64, profile=True)
    t_floor = opencv_floor(imgs)
    lines += [f"### All {n} CRBD images (320x240)", "",
              "| | ms / image | images / s | vs reference | vs OpenCV floor |", "|---|---|---|---|---|",
              f"| reference (per image) | {t_ref * 1e3:.1f} | {1 / t_ref:.1f} | 1.0x | {t_ref / t_floor:.1f}x slower |",
              f"| tensor, batch 64 | {t_ten * 1e3:.1f} | {1 / t_ten:.1f} | **{t_ref / t_ten:.2f}x** | "
              f"{t_ten / t_floor:.1f}x slower |",
              f"| OpenCV floor: 1 thread cv2.HoughLines on an ExG mask | {t_floor * 1e3:.1f} | {1 / t_floor:.0f} | - | 1.0x |",
              "", "Tensor per-stage breakdown at batch 64 (ms / image): "
              + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in stages.items()), ""]
    print("\n".join(lines))

    # the floor and both modes side by side, best of 2 rounds (the VM's speed drifts)
    improved = CropRowDetector(Params(mode="improved"))
    improved8 = CropRowDetector(Params(mode="improved"), chunk=8)  # the improved mode's default before 12
    improved16 = CropRowDetector(Params(mode="improved"), chunk=16)
    improved(to_batch(imgs[:2]))
    improved8(to_batch(imgs[:2]))
    improved16(to_batch(imgs[:2]))
    best: dict[str, float] = {}
    for _ in range(args.rounds):
        for name, run in (("floor", lambda: opencv_floor(imgs)), ("floor50", lambda: opencv_floor(imgs, 50)),
                          ("faithful", lambda: time_tensor(det, imgs, 64)[0]),
                          ("improved", lambda: time_tensor(improved, imgs, 64)[0]),
                          ("improved8", lambda: time_tensor(improved8, imgs, 64)[0]),
                          ("improved16", lambda: time_tensor(improved16, imgs, 64)[0])):
            best[name] = min(best.get(name, math.inf), run())
    fl = best["floor"]
    rows = [f"### Side by side: the floor and both modes (all {n} images, best of {args.rounds})", "",
            "| | ms / image | images / s | vs floor |", "|---|---|---|---|",
            f"| floor: `cv2.HoughLines` voting pass, 1 thread | {fl * 1e3:.2f} | {1 / fl:.0f} | 1.00x |",
            f"| same pass, threshold 50 | {best['floor50'] * 1e3:.2f} | {1 / best['floor50']:.0f} | "
            f"{best['floor50'] / fl:.2f}x |",
            f"| tensor path, faithful mode, batch 64 | {best['faithful'] * 1e3:.2f} | {1 / best['faithful']:.1f} | "
            f"**{best['faithful'] / fl:.2f}x** |",
            f"| tensor path, improved mode, batch 64 | {best['improved'] * 1e3:.2f} | {1 / best['improved']:.1f} | "
            f"**{best['improved'] / fl:.2f}x** ({best['improved'] / best['faithful']:.2f}x the faithful mode) |",
            f"| same, chunks of 8 images (default: {improved.chunk}) | {best['improved8'] * 1e3:.2f} | "
            f"{1 / best['improved8']:.1f} | {best['improved8'] / fl:.2f}x |",
            f"| same, chunks of 16 images | {best['improved16'] * 1e3:.2f} | "
            f"{1 / best['improved16']:.1f} | {best['improved16'] / fl:.2f}x |"]
    print("\n".join(rows))
    lines += rows + [""]

    rows = ["### Batch-size scaling (CRBD images, tensor path)", "", "| batch | ms / image | images / s |",
            "|---|---|---|"]
    for bs in ([1, 8, 64] if args.quick else [1, 8, 64, 256]):
        sub = (imgs * (bs // len(imgs) + 1))[: max(bs, min(len(imgs), 2 * bs))]
        t, _ = time_tensor(det, sub, bs)
        rows.append(f"| {bs} | {t * 1e3:.1f} | {1 / t:.1f} |")
        print(rows[-1])
    lines += rows + [""]

    rows = ["### Image-size scaling (synthetic fields, batch 8)", "",
            "| size | reference ms / image | tensor ms / image | ratio |", "|---|---|---|---|"]
    sizes = [(320, 240), (640, 480)] if args.quick else [(320, 240), (640, 480), (1280, 960)]
    for w, h in sizes:
        p = Params(image_width=w, max_pixels=max(w * h, Params().max_pixels))  # 1280x960 is above the default bound
        fields = [render(FieldSpec(seed=s).at_size(w, h)).image for s in range(8)]
        d = CropRowDetector(p)
        d(to_batch(fields[:1]))
        t0 = time.perf_counter()
        for f in fields:
            detect(f, p)
        tr = (time.perf_counter() - t0) / len(fields)
        t0 = time.perf_counter()
        d(to_batch(fields))
        tt = (time.perf_counter() - t0) / len(fields)
        rows.append(f"| {w}x{h} | {tr * 1e3:.1f} | {tt * 1e3:.1f} | {tr / tt:.2f}x |")
        print(rows[-1])
    lines += rows + [""]

    base, peak = peak_memory(ds.root, 64)
    lines += [f"Peak memory, one batch of 64 CRBD images: peak RSS {peak:.0f} MiB "
              f"(after a warm-up batch of 1: {base:.0f} MiB; includes the 64 input images, torch itself and "
              f"the pages of the memory-mapped LAB table that were touched)."]
    print(lines[-1])
    if not args.no_write:
        append_results("Tensor path vs reference" + (" (quick)" if args.quick else ""),
                       "python benchmarks/bench_tensor.py" + (" --quick" if args.quick else ""), "\n".join(lines))


if __name__ == "__main__":
    main()
