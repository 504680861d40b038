"""``torchrow detect``: rows in image files, folders of images and ROS bags, one record per
image (``--out``), optionally annotated pictures (``--annotate``) and a Foxglove recording."""

from __future__ import annotations

import argparse
import contextlib
import functools
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torchrow.apps.commands.shared import (
    DEFAULT_FPS,
    CLIError,
    add_common,
    add_engine,
    add_evidence,
    add_impl,
    annotation_names,
    bag_picture,
    check_device,
    check_engine,
    check_foxglove,
    check_model,
    check_targets,
    collect_images,
    evidence_files,
    onnx_host_threads,
    open_recorder,
    open_sink,
    out_targets,
    parse_params,
    record_names,
    run_header,
    setting_hint,
    source_stems,
    split_bags,
    with_mode,
)

if TYPE_CHECKING:
    import numpy as np

    from torchrow.core.results import ImageResult
    from torchrow.engines.runner import Loader

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("detect", help="detect rows in images, write one JSON record per file")
    p.add_argument("inputs", nargs="+", metavar="IMAGE_OR_DIR_OR_BAG")
    p.add_argument("--out", required=True, help="JSONL output file (or .parquet)")
    p.add_argument("--topic", default=None, help="image topic of the ROS bag inputs (default: the only one)")
    add_engine(p)
    p.add_argument("--annotate", metavar="DIR", help="write annotated PNGs to DIR")
    p.add_argument("--mcap", metavar="OUT.mcap", default=None,
                   help="also write the images, rows and signals as a Foxglove MCAP recording "
                        "(pip install 'torchrow[foxglove]')")
    add_impl(p)
    add_evidence(p)
    add_common(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from torchrow.apps.annotate import draw_result, save_rgb
    from torchrow.apps.sink import image_key
    from torchrow.core.io import load_image, load_with_evidence

    params = with_mode(parse_params(args.param), args)
    device = check_device(args.device)
    model = check_model(args)
    if model is not None:
        onnx_host_threads()
    check_engine(args, onnx_workers=True)
    others, bags = split_bags(args.inputs, args.topic)
    paths = collect_images(others) if others else []
    if model is not None and paths:
        from torchrow.onnx.metadata import model_meta

        info = model_meta(model)
        params = info["params"]
        try:
            first = load_image(paths[0], params.image_width, params.max_pixels)
        except Exception:  # an unreadable first file gets its error record later
            first = None
        if first is not None and first.shape[:2] != (info["height"], info["width"]):
            raise CLIError(f"model {model} takes {info['width']}x{info['height']} images; {paths[0].name} is "
                           f"{first.shape[1]}x{first.shape[0]} at working width {params.image_width} "
                           f"(export a model with --width {first.shape[1]} --height {first.shape[0]})")
    out = Path(args.out)
    names = record_names(paths)
    if args.evidence is not None and bags:
        raise CLIError("--evidence holds masks for image files; ROS bag frames have none (detect the bags without it)")
    masks = evidence_files(args, names, params)
    # bag frames are named BAG#FRAME, BAG the bag's path relative to the bags' common folder,
    # so that two bags of one file name (dayA/cam.bag, dayB/cam.bag) keep apart
    bag_names = record_names([b.path for b in bags])
    ann = Path(args.annotate) if args.annotate else None
    ann_paths = [ann / n for n in annotation_names(names, bag_names)] if ann is not None else []
    foxglove = check_foxglove(args)
    check_targets([*map(Path, args.inputs), *paths, *([Path(model)] if model else [])],
                  out_targets(out) + ([("--annotate", ann)] if ann is not None else [])
                  + [("--annotate", a) for a in ann_paths] + ([("--mcap", Path(args.mcap))] if args.mcap else []))
    # the mask folder is a source: --resume with other masks (or none) is another run
    sink = open_sink(out, image_key, args.resume,
                     run_header("detect", params, [*args.inputs, *([args.evidence] if masks is not None else [])],
                                impl=args.impl, engine=args.engine))
    if ann is not None:
        ann.mkdir(parents=True, exist_ok=True)
    # --mcap: the image files are one sequence, each bag another
    fox = open_recorder(args, (["images"] if paths else []) + source_stems(bags),
                        [DEFAULT_FPS] * (bool(paths) + len(bags))) if foxglove else None

    def inputs() -> Iterator[tuple[str, Loader, Path | None, dict | None, tuple[int, int, object]]]:
        """(name, loader, annotated picture, extra record keys, (sequence, index, source of
        the frame's bytes)); bag frames after the files."""
        for j, (p, name) in enumerate(zip(paths, names)):
            loader = (functools.partial(load_image, p, params.image_width, params.max_pixels) if masks is None
                      else functools.partial(load_with_evidence, p, masks[j], params.image_width, params.max_pixels))
            yield (name, loader,
                   ann_paths[j] if ann is not None else None, None, (0, j, p))
        for s, (b, bag) in enumerate(zip(bags, bag_names), bool(paths)):
            for f in b.frames(params.image_width, params.max_pixels):
                yield (f"{bag}#{f.frame:06d}", f, ann / bag_picture(bag, f.frame) if ann is not None else None,
                       {"source": b.name, "frame": f.frame, "stamp_ns": f.stamp_ns}, (s, f.frame, f))

    meta: dict[int, tuple[Path | None, dict | None, tuple[int, int, object]]] = {}

    def todo() -> Iterator[tuple[str, Loader]]:
        k = 0
        for name, loader, picture, extra, origin in inputs():
            if name in sink:  # --resume: already in --out
                continue
            meta[k] = (picture, extra, origin)
            k += 1
            yield name, loader

    total = max(0, len(paths) + sum(b.length for b in bags) - len(sink.done))
    common: dict[str, Any] = dict(impl=args.impl, params=params, batch_size=args.batch_size, device=device,
                                  progress=not args.quiet, model=model, total=total)
    stream: Iterator[tuple[int, np.ndarray | None, ImageResult, float]]
    if args.engine == "ray":
        from torchrow.engines.distributed import run as ray_run

        stream = ray_run(todo(), workers=args.workers, address=args.address, **common)
    else:
        from torchrow.engines.runner import run as local_run

        stream = local_run(todo(), workers=args.workers if args.impl == "onnx" else None, **common)
    counts: dict[str, int] = {}
    with sink, (fox or contextlib.nullcontext()):
        for i, rgb, res, _ in stream:
            picture, extra, origin = meta.pop(i)
            rec = res.to_record()
            if extra:
                rec = {"name": rec.pop("name"), **extra, **rec}
            if fox is not None:
                rec = fox.frame(origin[0], origin[1], rec, rgb, origin[2])
            sink.write(rec)
            counts[res.status] = counts.get(res.status, 0) + 1
            if picture is not None and rgb is not None:
                picture.parent.mkdir(parents=True, exist_ok=True)
                save_rgb(picture, draw_result(rgb, res))
    summary = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    kept = f"; {len(sink.done)} kept from the earlier run" if args.resume else ""
    print(f"torchrow: {sink.written} image(s) -> {out} ({summary}){kept}", file=sys.stderr)
    hint = setting_hint(params, counts)
    if hint:
        print(hint, file=sys.stderr)
    return 0
