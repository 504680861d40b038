"""Local vs Ray engine: overhead, 1 vs 2 actors, equality on all CRBD images; the per-core
time split used by docs/fleet_sizing.md (decoding, detection, record output).

1. All 281 CRBD images through ``torchrow.engines.runner.run`` (local engine, tensor path, batch 64)
   and through ``torchrow.engines.distributed.run`` on a local Ray cluster with 1 and 2 actors of one
   CPU each (cluster start timed apart; each Ray run includes its actors' start). Every
   record must equal the local engine's (the script exits 1 otherwise).
2. Per-core split (one thread): JPEG decode + resize per image, detection per image
   (CropRowDetector, one torch thread, batch 8), JSON record + flushed write per record.
3. Video (unless --no-video): the 100 Caterra frames as 4 sources of 25 frames, local
   (lock-step batch of 4) vs Ray (the same batch in one task: records must be equal; and
   one task per source, whose float64 rows may differ in a last bit, counted).

    python benchmarks/bench_engines.py [--data ../shared/data] [--quick] [--no-video] [--no-write]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import torch
from _common import append_results, data_root  # type: ignore[import-not-found]

from torchrow import Params
from torchrow.core.io import load_image
from torchrow.engines.runner import run
from torchrow.evaluation.datasets import CRBD


def _records(stream) -> list[str]:
    return [json.dumps(res.to_record()) for _, _, res, _ in stream]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data")
    ap.add_argument("--quick", action="store_true", help="64 images, no video")
    ap.add_argument("--no-video", action="store_true")
    ap.add_argument("--no-write", action="store_true", help="do not append to RESULTS.md")
    args = ap.parse_args()
    root = data_root(args.data)
    crbd = CRBD(root / "crbd")
    params = Params()
    paths = [crbd.image_path(i) for i in range(len(crbd))][: 64 if args.quick else None]
    items = [(p.name, partial(load_image, p, params.image_width)) for p in paths]
    n = len(items)
    rows: list[tuple[str, float, str]] = []
    ok = True

    t0 = time.perf_counter()
    local = _records(run(items, "tensor", params, 64, progress=False))
    t_local = time.perf_counter() - t0
    rows.append((f"local engine, tensor, {torch.get_num_threads()} threads", t_local, "reference for equality"))

    import ray

    from torchrow.engines import distributed

    t0 = time.perf_counter()
    ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False)
    t_start = time.perf_counter() - t0
    for workers in (1, 2):
        t0 = time.perf_counter()
        got = _records(distributed.run(items, "tensor", params, 64, progress=False, workers=workers))
        dt = time.perf_counter() - t0
        same = got == local
        ok &= same
        rows.append((f"ray engine, {workers} actor(s) x 1 CPU", dt,
                     f"{'identical' if same else 'DIFFERENT'} records ({sum(a == b for a, b in zip(got, local))}/{n})"))

    # per-core split, one thread
    torch.set_num_threads(1)
    import cv2

    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    rgbs = [load_image(p, params.image_width) for p in paths]
    t_dec = (time.perf_counter() - t0) / n
    from torchrow.engines.detector import CropRowDetector

    det = CropRowDetector(params, workers=1)
    import numpy as np

    t0 = time.perf_counter()
    results = []
    for s in range(0, n, 8):
        batch = torch.from_numpy(np.stack(rgbs[s:s + 8])).permute(0, 3, 1, 2).contiguous()
        results += det(batch).results([p.name for p in paths[s:s + 8]])
    t_det = (time.perf_counter() - t0) / n
    from torchrow.apps.sink import RecordSink

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        with RecordSink(Path(tmp) / "r.jsonl") as sink:
            for r in results:
                sink.write(r.to_record())
        t_io = (time.perf_counter() - t0) / n
    per = t_dec + t_det + t_io

    video_rows: list[tuple[str, float, str]] = []
    if not (args.quick or args.no_video):
        frames = sorted((root / "caterra_video").glob("rgb*.jpg"))
        with tempfile.TemporaryDirectory() as tmp:
            srcs = []
            for k in range(4):
                d = Path(tmp) / f"part{k}"
                d.mkdir()
                for f in frames[25 * k:25 * (k + 1)]:
                    os.symlink(f, d / f.name)
                srcs.append(str(d))
            from torchrow.core.frames import open_source
            from torchrow.engines.runner import track

            torch.set_num_threads(os.cpu_count() or 1)
            t0 = time.perf_counter()
            loc = sorted(json.dumps(res.to_record()) for _, res, _ in track(
                [open_source(s) for s in srcs], srcs, "tensor", params, 8))
            t_vl = time.perf_counter() - t0
            t0 = time.perf_counter()
            dis = sorted(json.dumps(rec) for _, rec in distributed.track(srcs, srcs, "tensor", params))
            t_vr = time.perf_counter() - t0
            same = loc == dis
            ok &= same
            t0 = time.perf_counter()
            one = sorted(json.dumps(rec) for _, rec in distributed.track(srcs, srcs, "tensor", params, batch_size=1))
            t_v1 = time.perf_counter() - t0
            n_diff = sum(a != b for a, b in zip(loc, one))  # last-bit differences of another batching
            video_rows = [("video local, 4 sources lock-step", t_vl, f"{len(loc)} frames"),
                          ("video ray, the local batch in one task", t_vr,
                           f"{'identical' if same else 'DIFFERENT'} records"),
                          ("video ray --batch-size 1, one task per source", t_v1,
                           f"{n_diff} of {len(one)} records differ in a last bit")]
    ray.shutdown()

    lines = ["| run | wall s | images/s | note |", "|---|---|---|---|"]
    for name, dt, note in rows:
        lines.append(f"| {name} | {dt:.1f} | {n / dt:.1f} | {note} |")
    for name, dt, note in video_rows:
        lines.append(f"| {name} | {dt:.1f} | {100 / dt:.1f} frames/s | {note} |")
    lines.append(f"| Ray cluster start ({os.cpu_count()} CPUs) | {t_start:.1f} | | once per run |")
    lines += ["", f"Per core (one thread), per image at 320x240: decode+resize {1e3 * t_dec:.1f} ms, detection "
                  f"{1e3 * t_det:.1f} ms, record+flushed write {1e3 * t_io:.2f} ms; total {1e3 * per:.1f} ms = "
                  f"{3600 / per:,.0f} images per hour per core."]
    body = "\n".join(lines)
    print(body)
    if not args.no_write:
        append_results(f"Engines: local vs Ray ({n} CRBD images)", "python benchmarks/bench_engines.py"
                       + (" --quick" if args.quick else ""), body)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
