"""Peak RSS of ``torchrow detect`` on single adversarial inputs (issue 11: under 3 GiB).

    python benchmarks/bench_memory.py [--impl tensor reference] [--limit-gib 3]

Each input runs in its own ``python -m torchrow detect`` subprocess under an address-space
limit (``RLIMIT_AS``); the peak RSS is the child's ``ru_maxrss``. Inputs: the issue's 7x900
and 4x3000 PNGs (refused by ``Params.max_pixels``), uniform noise (every colour distinct: the
worst case for colour clustering) at 320x240 and at the largest allowed working size
(320x1638), a synthetic field at 320x1638, and ``--param image_width=4000`` on a field.
Noise at 320x1638 takes minutes in the tensor path on a small CPU.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from torchrow import Params
from torchrow.evaluation.synthetic import FieldSpec, render


def inputs(d: Path) -> list[tuple[str, Path, list[str]]]:
    rng = np.random.default_rng(0)
    h = Params().max_pixels // 320
    out = []

    def save(name: str, img: np.ndarray, extra: list[str] | None = None) -> None:
        p = d / name
        cv2.imwrite(str(p), img)
        out.append((name, p, extra or []))

    save("noise_7x900.png", rng.integers(0, 256, (900, 7, 3), dtype=np.uint8))
    save("noise_4x3000.png", rng.integers(0, 256, (3000, 4, 3), dtype=np.uint8))
    save("noise_320x240.png", rng.integers(0, 256, (240, 320, 3), dtype=np.uint8))
    save(f"field_320x{h}.png", cv2.cvtColor(render(FieldSpec(seed=2, width=320, height=h)).image, cv2.COLOR_RGB2BGR))
    save("field_320x240_w4000.png", cv2.cvtColor(render(FieldSpec(seed=1)).image, cv2.COLOR_RGB2BGR),
         ["--param", "image_width=4000"])
    save(f"noise_320x{h}.png", rng.integers(0, 256, (h, 320, 3), dtype=np.uint8))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--impl", nargs="+", default=["tensor", "reference"])
    ap.add_argument("--limit-gib", type=float, default=3.0)
    args = ap.parse_args()
    limit = int(args.limit_gib * 2**30)
    print("| input | impl | status | peak RSS MiB | s |\n|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for name, path, extra in inputs(d):
            for impl in args.impl:
                before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
                t0 = time.perf_counter()
                r = subprocess.run([sys.executable, "-m", "torchrow", "detect", str(path), "--out", str(d / "r.jsonl"),
                                    "-q", "--impl", impl, *extra], capture_output=True, text=True,
                                   preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (limit, limit)))
                dt = time.perf_counter() - t0
                peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
                # ru_maxrss of children is the largest so far: report it only when it grew
                rss = f"{peak / 1024:.0f}" if peak > before else f"<= {before / 1024:.0f}"
                status = json.loads((d / "r.jsonl").read_text().splitlines()[0])["status"] if r.returncode == 0 \
                    else f"exit {r.returncode}"
                print(f"| {name} {' '.join(extra)} | {impl} | {status} | {rss} | {dt:.1f} |", flush=True)


if __name__ == "__main__":
    main()
