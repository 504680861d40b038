"""Command line: ``torchrow detect | eval | score | demo | video`` (also ``python -m torchrow``).

Errors in arguments or paths print one line (``torchrow: error: ...``) and exit with 2; a
file that cannot be read inside a run gets an ``error`` record and the run goes on.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Sequence

from . import __version__
from .io import IMAGE_EXTENSIONS
from .params import Params

__all__ = ["main"]


class CLIError(Exception):
    """A user error: reported as one line, exit status 2."""


def _parse_params(items: Sequence[str] | None) -> Params:
    """``NAME=VALUE`` pairs -> Params (values parsed as JSON, else kept as strings)."""
    fields = {f.name: f for f in dataclasses.fields(Params)}
    changes: dict[str, object] = {}
    for item in items or []:
        name, sep, raw = item.partition("=")
        if not sep or name not in fields:
            raise CLIError(f"--param expects NAME=VALUE with NAME one of Params' fields; got {item!r}")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        if isinstance(value, list):
            value = tuple(value)
        changes[name] = value
    try:
        return Params(**changes)  # type: ignore[arg-type]
    except (ValueError, TypeError) as exc:
        raise CLIError(str(exc)) from None


def _collect_images(inputs: Sequence[str]) -> list[Path]:
    paths: list[Path] = []
    for raw in inputs:
        p = Path(raw)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_EXTENSIONS)
            if not found:
                raise CLIError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in folder {p}")
            paths.extend(found)
        elif p.is_file():
            paths.append(p)
        else:
            raise CLIError(f"no such file or folder: {p}")
    return paths


def _check_device(device: str | None) -> str | None:
    if device is None:
        return None
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError as exc:
        raise CLIError(f"bad --device {device!r}: {exc}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CLIError(f"--device {device}: torch sees no CUDA device here")
    return str(dev)


def cmd_detect(args: argparse.Namespace) -> int:
    from .annotate import draw_result, save_rgb
    from .io import load_image
    from .runner import run

    params = _parse_params(args.param)
    device = _check_device(args.device)
    model = _check_model(args)
    paths = _collect_images(args.inputs)
    if model is not None:
        from .export import model_info

        info = model_info(model)
        params = info["params"]
        try:
            first = load_image(paths[0], params.image_width)
        except Exception:  # an unreadable first file gets its error record later
            first = None
        if first is not None and first.shape[:2] != (info["height"], info["width"]):
            raise CLIError(f"model {model} takes {info['width']}x{info['height']} images; {paths[0].name} is "
                           f"{first.shape[1]}x{first.shape[0]} at working width {params.image_width} "
                           f"(export a model with --width {first.shape[1]} --height {first.shape[0]})")
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        raise CLIError(f"output folder does not exist: {out.parent}")
    ann = Path(args.annotate) if args.annotate else None
    if ann is not None:
        ann.mkdir(parents=True, exist_ok=True)
    counts: dict[str, int] = {}
    items = [(p.name, (lambda p=p: load_image(p, params.image_width))) for p in paths]
    with open(out, "w") as fh:
        for i, rgb, res, _ in run(items, args.impl, params, args.batch_size, device, progress=not args.quiet,
                                  model=model):
            path = paths[i]
            fh.write(json.dumps(res.to_record()) + "\n")
            fh.flush()
            counts[res.status] = counts.get(res.status, 0) + 1
            if ann is not None and rgb is not None:
                save_rgb(ann / f"{path.stem}.png", draw_result(rgb, res))
    summary = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    print(f"torchrow: {len(paths)} image(s) -> {out} ({summary})", file=sys.stderr)
    return 0


def _check_model(args: argparse.Namespace) -> str | None:
    """``--model`` for ``--impl onnx``: present, readable, a torchrow export, onnxruntime installed."""
    model = getattr(args, "model", None)
    if args.impl != "onnx":
        if model:
            raise CLIError("--model is only used with --impl onnx")
        return None
    if not model:
        raise CLIError("--impl onnx needs --model MODEL.onnx (write one with: torchrow export onnx --out MODEL.onnx)")
    if not Path(model).is_file():
        raise CLIError(f"ONNX model not found: {model}")
    try:
        import onnxruntime  # noqa: F401

        from .export import model_info

        info = model_info(model)
    except ImportError:
        raise CLIError("--impl onnx needs onnxruntime: pip install 'torchrow[onnx]'") from None
    except Exception as exc:  # a corrupt or foreign file: one line, not a traceback
        raise CLIError(f"cannot read ONNX model {model}: {exc}") from None
    kind = getattr(args, "model_kind", "detector")
    if info["kind"] != kind:
        cmd = "detect" if kind == "detector" else "video"
        how = "without --tracker" if kind == "detector" else "--tracker"
        raise CLIError(f"{model} is a torchrow {info['kind']} model; {cmd} needs a {kind} model "
                       f"(torchrow export onnx {how})")
    if args.param:
        raise CLIError("--param cannot change an exported model; export one with those --param values")
    want = info["params"].image_width if kind == "detector" else info["params"].video_width
    if want != info["width"]:
        raise CLIError(f"model {model} takes {info['width']}x{info['height']} images but its working width is {want}")
    return model


def cmd_export(args: argparse.Namespace) -> int:
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError:
        raise CLIError("export needs onnx and onnxscript: pip install 'torchrow[onnx]'") from None
    from .export import model_info, to_onnx

    params = _parse_params(args.param)
    if args.tracker:
        width = args.width if args.width is not None else params.video_width
        if args.height is None:
            raise CLIError("--tracker needs --height: the frames' working height at width "
                           f"{width} (e.g. 281 for 1280x720 video at the default video_width 500)")
        height = args.height
        if width != params.video_width:
            params = params.replace(video_width=width)
    else:
        width = args.width if args.width is not None else 320
        height = args.height if args.height is not None else 240
        if width != params.image_width:
            params = params.replace(image_width=width)
    out = Path(args.out)
    if not out.parent.is_dir():
        raise CLIError(f"output folder does not exist: {out.parent}")
    import time

    t0 = time.perf_counter()
    try:
        def phase(name: str) -> None:  # an export takes minutes: say which phase runs
            if not args.quiet:
                print(f"torchrow: export: {name} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

        to_onnx(out, height=height, width=width, batch=args.batch, params=params, opset=args.opset,
                tracker=args.tracker, control_flow=not args.no_control_flow, scatter_free=args.scatter_free,
                progress=phase)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    info = model_info(out)
    ops = ", ".join(f"{k} {v}" for k, v in sorted(info["ops"].items()))
    what = "tracker step: frames + veg_lab + active + state" if args.tracker else "images + veg_lab"
    print(f"torchrow: exported {out} in {time.perf_counter() - t0:.0f} s: {info['size'] / 2**20:.1f} MiB, "
          f"{what}, uint8 frames ({args.batch}, 3, {height}, {width}), "
          f"opset {info['opset']}, {sum(info['ops'].values())} nodes")
    print(f"ops: {ops}")
    return 0


def _open_crbd(data: str | None):
    from .datasets import CRBD

    try:
        return CRBD(data)
    except FileNotFoundError as exc:
        raise CLIError(str(exc).splitlines()[0]) from None


def cmd_eval(args: argparse.Namespace) -> int:
    from .evaluate import evaluate

    params = _parse_params(args.param)
    device = _check_device(args.device)
    if args.impl == "onnx":
        raise CLIError("eval supports --impl tensor|reference; for ONNX use: torchrow detect --impl onnx --model M")
    crbd = _open_crbd(args.data)
    indices = list(range(len(crbd)))[:: args.every]
    if args.limit:
        indices = indices[: args.limit]
    report = evaluate(crbd, indices, args.impl, params, args.batch_size, device, progress=not args.quiet)
    print(report.format_summary())
    if args.out:
        for p in report.write(Path(args.out)):
            print(f"wrote {p}", file=sys.stderr)
    return 0


def cmd_score(args: argparse.Namespace) -> int:
    import numpy as np

    from .evaluate import score_tmg_files
    from .metrics import summarize

    crbd = _open_crbd(args.data)
    results = Path(args.results)
    if not results.is_dir():
        raise CLIError(f"results folder not found: {results}")
    ext = args.ext if args.ext.startswith(".") else "." + args.ext
    scores = score_tmg_files(crbd, results, ext, progress=not args.quiet)
    for label, col in (("sigma 0.1", 1), ("sigma 0.3", 2)):
        s = summarize(np.array([r[col] for r in scores]))
        print(f"CRDA {label}: mean {s['mean']:.3f}  median {s['median']:.3f}  (n={s['n']})")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from .annotate import draw_result, save_rgb
    from .datasets import GroundTruth
    from .metrics import crda_official
    from .reference import detect
    from .synthetic import demo_field

    params = _parse_params(args.param)
    field = demo_field()
    res = detect(field.image, params, name="synthetic-demo")
    h = field.image.shape[0]
    n = len(field.crp)
    gt = GroundTruth(field.crp[:, 0].copy(), field.crp[:, 1].copy(), h - n, h)
    score = crda_official(res, gt)
    ys = np.arange(h - n, h, dtype=np.float64)
    gt_lines = [(ys, field.crp[:, 0] + j * field.crp[:, 1] + field.image.shape[1] / 2) for j in range(-3, 4)]
    out = Path(args.out)
    save_rgb(out, draw_result(field.image, res, ground_truth=gt_lines))
    valid = sum(r.valid for r in res.rows)
    print(f"synthetic field {field.image.shape[1]}x{h}: status {res.status}, {valid}/{len(res.rows)} valid rows, "
          f"vanishing point {_fmt_vp(res.vp)} (true {_fmt_vp(field.vp)}), CRDA (sigma 0.1) {score:.3f}")
    print(f"annotated image: {out}")
    return 0


def _open_sources(raw: Sequence[str]):
    from .io import ImageError
    from .video import open_source

    out = []
    for r in raw:
        try:
            out.append(open_source(r))
        except (FileNotFoundError, ImageError) as exc:
            raise CLIError(str(exc)) from None
    return out


def _first_size(src, width: int) -> tuple[int, int] | None:
    """Working (H, W) of a source's first readable frame (None if none is readable)."""
    from .video import load_item

    for item in src:
        got = load_item(item, width)
        if got.rgb is not None:
            return got.rgb.shape[:2]
    return None


class _Annotator:
    """Writes annotated frames: one video per source (``OUT.mp4``) or PNGs in a folder."""

    VIDEO = (".mp4", ".avi", ".mov", ".mkv", ".m4v")

    def __init__(self, target: str | None, sources: list, fps: float = 10.0) -> None:
        self.target = Path(target) if target else None
        self.is_video = self.target is not None and self.target.suffix.lower() in self.VIDEO
        self.writers: dict[int, object] = {}
        self.size: dict[int, tuple[int, int]] = {}
        self.fps = fps
        stems: list[str] = []
        for i, s in enumerate(sources):
            stem = s.path.stem or f"source{i}"
            stems.append(stem if stem not in stems else f"{stem}_{i}")
        self.stems = stems
        self.n = len(sources)
        if self.target is not None:
            folder = self.target.parent if self.is_video else self.target
            if self.is_video and not folder.exists():
                raise CLIError(f"folder of --annotate does not exist: {folder}")
            folder.mkdir(parents=True, exist_ok=True)

    def _video_path(self, i: int) -> Path:
        assert self.target is not None
        if self.n == 1:
            return self.target
        return self.target.with_name(f"{self.target.stem}_{self.stems[i]}{self.target.suffix}")

    def write(self, i: int, res, rgb) -> None:
        import cv2

        from .annotate import save_rgb
        from .video import draw_frame, error_frame

        if self.target is None:
            return
        if rgb is not None:
            img = draw_frame(rgb, res)
            self.size.setdefault(i, (rgb.shape[1], rgb.shape[0]))
        elif i in self.size:
            img = error_frame(*self.size[i], f"frame {res.frame}: {res.error}")
        else:
            return
        if not self.is_video:
            save_rgb(self.target / f"{self.stems[i]}_{res.frame:05d}.png", img)
            return
        if i not in self.writers:
            path = self._video_path(i)
            fourcc = cv2.VideoWriter_fourcc(*("mp4v" if path.suffix.lower() in (".mp4", ".m4v", ".mov") else "MJPG"))
            vw = cv2.VideoWriter(str(path), fourcc, self.fps, (img.shape[1], img.shape[0]))
            if not vw.isOpened():
                raise CLIError(f"cannot write video {path}")
            self.writers[i] = vw
        self.writers[i].write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))

    def close(self) -> None:
        for vw in self.writers.values():
            vw.release()


def cmd_video(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from .video import central_jumps, plot_tracks

    args.model_kind = "tracker"
    model = _check_model(args)
    params = _parse_params(args.param)
    if args.hough_every is not None:
        if model is not None:
            raise CLIError("--every cannot change an exported model; export one with --param hough_every=N")
        if args.hough_every < 1:
            raise CLIError(f"--every must be >= 1, got {args.hough_every}")
        params = params.replace(hough_every=args.hough_every)
    if args.fov is not None and not 0 < args.fov < 180:
        raise CLIError(f"--fov must lie in (0, 180) degrees, got {args.fov}")
    device = _check_device(args.device)
    sources = _open_sources(args.sources)
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        raise CLIError(f"output folder does not exist: {out.parent}")
    plot = Path(args.plot) if args.plot else out.with_suffix(".png")
    ann = _Annotator(args.annotate, sources)
    names = [s.name for s in sources]
    if args.impl == "onnx":
        from .export import OnnxTracker

        tracker = OnnxTracker(model, hfov_deg=args.fov)
        for s in sources:  # the model's working size, checked before any frame is tracked
            size = _first_size(s, tracker.params.video_width)
            if size is not None and size != (tracker.height, tracker.width):
                raise CLIError(f"{s.name}: frames of working size {size[1]}x{size[0]}; the model {model} takes "
                               f"{tracker.width}x{tracker.height} (export one with --tracker --height {size[0]})")
        step = tracker.batch
        runs = [(lambda lo=lo: ((lo + b, r, rgb) for b, r, rgb in tracker.track_iter(
            sources[lo:lo + step], names[lo:lo + step]))) for lo in range(0, len(sources), step)]
    elif args.impl == "reference":
        from .reference import Tracker as RefTracker

        ref = RefTracker(params, hfov_deg=args.fov)
        runs = [(lambda i=i: ((i, r, rgb) for r, rgb in ref.track_iter(sources[i], names[i])))
                for i in range(len(sources))]
    else:
        from .tracker import Tracker

        tracker = Tracker(params, device=device, hfov_deg=args.fov)
        groups: dict[object, list[int]] = {}
        for i, s in enumerate(sources):  # one working size per batch
            groups.setdefault(_first_size(s, params.video_width), []).append(i)
        batches = [g[j:j + args.batch_size] for g in groups.values() for j in range(0, len(g), args.batch_size)]

        def run_batch(batch: list[int]):
            for b, r, rgb in tracker.track_iter([sources[i] for i in batch], [names[i] for i in batch]):
                yield batch[b], r, rgb

        runs = [(lambda batch=batch: run_batch(batch)) for batch in batches]
    by_source: dict[str, list[dict]] = {n: [] for n in names}
    counts: dict[str, int] = {}
    total = sum(s.length for s in sources)
    bar = tqdm(total=total, desc="video", file=sys.stderr, disable=args.quiet, unit="frame")
    try:
        with open(out, "w") as fh:
            for run in runs:
                for i, res, rgb in run():
                    rec = res.to_record()
                    fh.write(json.dumps(rec) + "\n")
                    by_source[names[i]].append(rec)
                    counts[res.status] = counts.get(res.status, 0) + 1
                    ann.write(i, res, rgb)
                    bar.update(1)
    finally:
        bar.close()
        ann.close()
    for recs in by_source.values():
        recs.sort(key=lambda r: r["frame"])
    plot_tracks(by_source, plot)
    n = sum(counts.values())
    summary = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    print(f"torchrow: {n} frame(s) of {len(sources)} source(s) -> {out} ({summary}); plot {plot}", file=sys.stderr)
    for src, recs in by_source.items():
        jumps = central_jumps(recs)
        hough = sum(1 for r in recs if r.get("hough_ran"))

        def worst(key: str) -> str:
            return f"{max(jumps[key]):.1f} px" if jumps[key] else "n/a"

        print(f"  {src}: Hough on {hough} of {len(recs)} frames; largest move of the central row at the "
              f"bottom: {worst('tracked')} into a tracked frame, {worst('hough')} into a Hough frame",
              file=sys.stderr)
    return 0


def _fmt_vp(vp) -> str:
    return "none" if vp is None else f"({vp[0]:.1f}, {vp[1]:.1f})"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="torchrow", description="Crop-row detection (ALGORITHM.md), "
                                 "reference and batched tensor implementations.")
    ap.add_argument("--version", action="version", version=f"torchrow {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--param", action="append", metavar="NAME=VALUE",
                       help="override a Params field, e.g. --param n_rows=4 (repeatable)")
        p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")

    def impl(p: argparse.ArgumentParser) -> None:
        p.add_argument("--impl", choices=("tensor", "reference", "onnx"), default="tensor",
                       help="batched tensor path (default), the per-image reference, or an exported ONNX "
                            "model in onnxruntime (--model)")
        p.add_argument("--model", help="ONNX file for --impl onnx (torchrow export onnx)")
        p.add_argument("--batch-size", type=int, default=64, help="images per batch for --impl tensor")
        p.add_argument("--device", default=None, help="torch device for --impl tensor (cpu, cuda, cuda:1)")

    p = sub.add_parser("detect", help="detect rows in images, write one JSON record per file")
    p.add_argument("inputs", nargs="+", metavar="IMAGE_OR_DIR")
    p.add_argument("--out", required=True, help="JSONL output file")
    p.add_argument("--annotate", metavar="DIR", help="write annotated PNGs to DIR")
    impl(p)
    common(p)
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser("eval", help="run on CRBD and report CRDA (official and thesis variant)")
    p.add_argument("--data", help="CRBD folder (or a folder holding crbd/); default $TORCHROW_DATA")
    p.add_argument("--out", help="folder for scores.csv, detections.jsonl, summary.json, crda_histogram.png")
    p.add_argument("--every", type=int, default=1, help="use every N-th image (default 1)")
    p.add_argument("--limit", type=int, default=0, help="at most this many images")
    impl(p)
    common(p)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("score", help="score external CRBD result files (.tmg format)")
    p.add_argument("--data", help="CRBD folder; default $TORCHROW_DATA")
    p.add_argument("--results", required=True, help="folder of result files named like the images")
    p.add_argument("--ext", default=".tmg", help="result file extension (default .tmg)")
    common(p)
    p.set_defaults(func=cmd_score)

    p = sub.add_parser("video", help="track rows through frame sequences (ALGORITHM.md section 8)",
                       description="Track crop rows through folders of frames (sorted by name) or video files; "
                                   "several sources are tracked as a batch of sequences. Writes one JSON record "
                                   "per frame and a PNG plot of rows and steering signals over time.")
    p.add_argument("sources", nargs="+", metavar="SOURCE", help="folder of frames or video file")
    p.add_argument("--out", required=True, help="JSONL output file (plot next to it, .png)")
    p.add_argument("--annotate", metavar="OUT.mp4|DIR", help="annotated video (per source) or folder of PNGs")
    p.add_argument("--every", dest="hough_every", type=int, default=None, metavar="K",
                   help="run the Hough stage every K frames (default: Params.hough_every = 5)")
    p.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="horizontal field of view of the frames, for heading_rad (null without it)")
    p.add_argument("--plot", default=None, help="plot file (default: --out with suffix .png)")
    p.add_argument("--impl", choices=("tensor", "reference", "onnx"), default="tensor",
                   help="batched tensor tracker (default), the per-sequence reference, or an exported tracker "
                        "step in onnxruntime (--model)")
    p.add_argument("--model", help="tracker-step ONNX file for --impl onnx (torchrow export onnx --tracker)")
    p.add_argument("--batch-size", type=int, default=8, help="sequences per batch for --impl tensor")
    p.add_argument("--device", default=None, help="torch device for --impl tensor (cpu, cuda, cuda:1)")
    common(p)
    p.set_defaults(func=cmd_video)

    p = sub.add_parser("export", help="export the image-mode detector or the tracker step (see README: ONNX export)")
    esub = p.add_subparsers(dest="format", required=True)
    p = esub.add_parser("onnx", help="static-shape ONNX graph (torch dynamo exporter)")
    p.add_argument("--out", required=True, help="output .onnx file")
    p.add_argument("--tracker", action="store_true",
                   help="export the video tracker step (frame + state -> rows + new state) instead of the detector")
    p.add_argument("--no-control-flow", action="store_true",
                   help="no ONNX If: every line-search step (and, tracker, both branches) runs, masks choose "
                        "(slower, same results)")
    p.add_argument("--scatter-free", action="store_true",
                   help="vote without ScatterElements(reduction=add), for runtimes that lack it (TensorRT); "
                        "slower on a CPU, same results")
    p.add_argument("--height", type=int, default=None,
                   help="working height (detector default 240; required with --tracker)")
    p.add_argument("--width", type=int, default=None,
                   help="working width (detector default 320; tracker default video_width, 500)")
    p.add_argument("--batch", type=int, default=1, help="static batch size (default 1)")
    p.add_argument("--opset", type=int, default=18, help="ONNX opset, >= 18 (default 18)")
    common(p)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("demo", help="detect rows on a built-in synthetic field (no data needed)")
    p.add_argument("--out", default="torchrow-demo.png", help="annotated image (default torchrow-demo.png)")
    common(p)
    p.set_defaults(func=cmd_demo)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if getattr(args, "every", 1) < 1 or getattr(args, "limit", 0) < 0 or getattr(args, "batch_size", 1) < 1:
        ap.exit(2, "torchrow: error: --every and --batch-size must be >= 1, --limit >= 0\n")
    try:
        return int(args.func(args) or 0)
    except CLIError as exc:
        print(f"torchrow: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("torchrow: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        print(f"torchrow: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
