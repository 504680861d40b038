"""Command line: ``torchrow detect | eval | score | demo | video`` (also ``python -m torchrow``).

Errors in arguments or paths print one line (``torchrow: error: ...``) and exit with 2; a
file that cannot be read inside a run gets an ``error`` record and the run goes on.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from torchrow import __version__
from torchrow.core.io import IMAGE_EXTENSIONS
from torchrow.core.params import Params

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
            what = "expects NAME=VALUE" if not sep else f"has no field {name!r}"
            raise CLIError(f"--param {what} (got {item!r}); valid names: {', '.join(sorted(fields))}")
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


def _replace_params(params: Params, option: str, **changes: object) -> Params:
    """``params.replace(**changes)`` for a command-line option: a value outside its rule is one line."""
    try:
        return params.replace(**changes)
    except (ValueError, TypeError) as exc:
        raise CLIError(f"{option}: {exc}") from None


def _collect_images(inputs: Sequence[str]) -> list[Path]:
    """Image files of the inputs (folders: their images sorted by name), each file once."""
    paths: list[Path] = []
    seen: set[str] = set()
    for raw in inputs:
        p = Path(raw)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_EXTENSIONS)
            if not found:
                raise CLIError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in folder {p}")
        elif p.is_file():
            found = [p]
        else:
            raise CLIError(f"no such file or folder: {p}")
        for q in found:  # the same file named twice (a.jpg and dir/ holding it) is one input
            key = os.path.realpath(q)
            if key not in seen:
                seen.add(key)
                paths.append(q)
    return paths


def _record_names(paths: Sequence[Path]) -> list[str]:
    """Record names: each file's path relative to the common folder of all inputs, ``/``-separated.

    Unique per input (``s1/x.jpg``, ``s2/x.jpg``); for the files of one folder, or one
    file, this is the file name, as before.
    """
    if not paths:
        return []
    absolute = [os.path.abspath(p) for p in paths]
    root = os.path.commonpath([os.path.dirname(a) for a in absolute])
    return [Path(os.path.relpath(a, root)).as_posix() for a in absolute]


def _annotation_names(names: Sequence[str], bags: Sequence[str] = ()) -> list[str]:
    """Annotated-picture paths (relative to ``--annotate``) for record names: the name with
    its suffix replaced by ``.png``; where two names would meet (``x.jpg``, ``x.png``), or a
    name would meet a bag frame's picture (``BAG_FRAME.png``, :func:`_bag_picture`; ``bags``:
    the bags' record names), the whole name plus ``.png`` (``x.jpg.png``, ``x.png.png``), so
    pictures never overwrite each other."""
    import re

    stems = [Path(n).with_suffix(".png").as_posix() for n in names]
    taken: dict[str, int] = {}
    for s in stems:
        taken[s] = taken.get(s, 0) + 1
    frame = re.compile("|".join(re.escape(b) + r"_\d{6,}\.png" for b in bags)) if bags else None
    return [s if taken[s] == 1 and not (frame and frame.fullmatch(s)) else n + ".png" for n, s in zip(names, stems)]


def _bag_picture(bag: str, frame: int) -> str:
    """Annotated-picture path (relative to ``--annotate``) of a bag frame: ``BAG_FRAME.png``,
    ``bag`` being the bag's record name (:func:`_record_names` of the bags)."""
    return f"{bag}_{frame:06d}.png"


def _check_targets(inputs: Sequence[Path], targets: Sequence[tuple[str, Path]]) -> None:
    """Refuse output targets that are inputs or lie inside an input folder (``CLIError``).

    Called at the start of a command, before any output is opened. ``inputs``: the files and
    folders the command reads; ``targets``: ``(option, path)`` of everything it will write.
    Paths are compared after resolving symbolic links, and existing files by identity
    (device and inode), so a hard link or another spelling of an input is caught too.
    """
    def ident(p: Path) -> tuple[int, int] | None:
        try:
            st = p.stat()
        except OSError:
            return None
        return st.st_dev, st.st_ino

    files, folders = {}, []
    for p in inputs:
        real = Path(os.path.realpath(p))
        if real.is_dir():
            folders.append(real)
        else:
            files[real] = ident(real)
    ids = {i for i in files.values() if i is not None}
    written: dict[Path, str] = {}
    for flag, target in targets:
        real = Path(os.path.realpath(target))
        if real in written and written[real] != flag:
            raise CLIError(f"{written[real]} and {flag} are the same file {target}; give them different names")
        written[real] = flag
        if real in files or (real.is_file() and ident(real) in ids):
            raise CLIError(f"{flag} {target} is an input; torchrow never writes over its inputs")
        for f in folders:
            if real == f or f in real.parents:
                raise CLIError(f"{flag} {target} is inside the input folder {f}; write the output elsewhere")


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


def _check_engine(args: argparse.Namespace, onnx_workers: bool = False) -> None:
    """``--engine ray`` needs Ray Data; ``--address`` only goes with it, ``--workers`` too unless
    ``onnx_workers`` (``detect --impl onnx``: concurrent onnxruntime runs here)."""
    if args.workers is not None and args.workers < 1:
        raise CLIError(f"--workers must be >= 1, got {args.workers}")
    if args.engine != "ray":
        if args.address:
            raise CLIError("--address is only used with --engine ray")
        if args.workers and not (onnx_workers and getattr(args, "impl", None) == "onnx"):
            raise CLIError("--workers is only used with --engine ray" + (" or --impl onnx" if onnx_workers else ""))
        return
    try:
        import ray
        import ray.data
    except ImportError:
        raise CLIError("--engine ray needs Ray Data: pip install 'torchrow[ray]'") from None
    if getattr(args, "annotate", None):
        raise CLIError("--annotate needs --engine local (the Ray engine returns records, not images)")
    if not ray.is_initialized():  # an initialised Ray is used as it is (torchrow.engines.distributed.init)
        from torchrow.engines.distributed import check_address

        try:
            check_address(args.address)
        except ValueError as exc:
            raise CLIError(str(exc)) from None


def _out_targets(out: Path) -> list[tuple[str, Path]]:
    """``("--out", path)`` for everything a sink on ``out`` writes (journal, temporary file, header)."""
    from torchrow.apps.sink import output_paths

    return [("--out", p) for p in output_paths(out)]


def _run_header(command: str, params: Params, sources: Sequence[str | Path], **info: object) -> dict:
    """What a run is, for ``--resume`` (torchrow.apps.sink): the command, every parameter (the
    mode is one) and the sources as resolved paths (any order) are compared; ``info`` (impl,
    engine, the names as spelled) is kept for the reader. Impl, engine and batch size are not
    compared: their records agree (README, "Identical results")."""
    return {"command": command, "params": dataclasses.asdict(params),
            "sources": sorted({os.path.realpath(s) for s in sources}),
            "info": {"torchrow": __version__, **info}}


def _open_sink(out: Path, key, resume: bool, header: dict | None = None):
    """The streaming writer of ``--out`` (torchrow.apps.sink), locked, with its run header;
    ``--resume`` keeps what is there if the header matches."""
    from torchrow.apps.sink import RecordSink, SinkError

    if out.parent and not out.parent.exists():
        raise CLIError(f"output folder does not exist: {out.parent}")
    if out.suffix.lower() == ".parquet":
        try:
            import pyarrow.parquet  # noqa: F401
        except ImportError:
            raise CLIError("--out *.parquet needs pyarrow: pip install pyarrow (or 'torchrow[ray]')") from None
    try:
        return RecordSink(out, key, resume=resume, header=header)
    except SinkError as exc:
        raise CLIError(f"cannot --resume: {exc}" if resume else str(exc)) from None


def _split_bags(inputs: Sequence[str], topic: str | None) -> tuple[list[str], list]:
    """ROS bag inputs (opened, ``topic`` chosen) apart from image files and folders; the same
    bag named twice (another spelling, a link) is one input, as for files."""
    from torchrow.core.rosbag import BagError, is_bag, open_bag

    others, bags = [], []
    seen: set[str] = set()
    for raw in inputs:
        if is_bag(raw):
            if os.path.realpath(raw) in seen:
                continue
            seen.add(os.path.realpath(raw))
            try:
                bags.append(open_bag(raw, topic))
            except BagError as exc:
                raise CLIError(str(exc)) from None
        else:
            others.append(raw)
    if topic is not None and not bags:
        raise CLIError("--topic applies to ROS bag inputs only (a rosbag2 folder or a .bag file)")
    return others, bags


def _check_foxglove(args: argparse.Namespace) -> bool:
    """``--mcap`` / ``--serve`` (torchrow.apps.foxglove): the SDK installed, the local engine, no
    ``--resume`` with ``--mcap``; parses ``--serve`` in place. True when either is asked."""
    serve = getattr(args, "serve", None)
    asked = [flag for flag, v in (("--mcap", args.mcap), ("--serve", serve)) if v is not None]
    if not asked:
        return False
    from torchrow.apps.foxglove import MISSING, available, parse_serve

    what = " and ".join(asked)
    if not available():
        raise CLIError(f"{what} {MISSING}")
    if args.engine == "ray":
        raise CLIError(f"{what} needs --engine local (the Ray engine returns records, not frames)")
    if args.mcap is not None and args.resume:
        raise CLIError("--resume cannot continue an MCAP recording; run without --resume, or without --mcap")
    if args.mcap is not None and not Path(args.mcap).parent.is_dir():
        raise CLIError(f"folder of --mcap does not exist: {Path(args.mcap).parent}")
    if serve is not None:
        try:
            args.serve = parse_serve(serve)
        except ValueError as exc:
            raise CLIError(str(exc)) from None
        if not args.serve_wait >= 0:
            raise CLIError(f"--serve-wait must be >= 0 seconds, got {args.serve_wait}")
    return True


def _open_recorder(args: argparse.Namespace, labels: list[str], fps: list[float]):
    """The Foxglove recorder of ``--mcap`` / ``--serve`` (checked by ``_check_foxglove``)."""
    from torchrow.apps.foxglove import Recorder

    return Recorder(labels, fps, Path(args.mcap) if args.mcap is not None else None,
                    getattr(args, "serve", None), getattr(args, "serve_wait", 0.0))


def cmd_detect(args: argparse.Namespace) -> int:
    import functools

    from torchrow.apps.annotate import draw_result, save_rgb
    from torchrow.apps.sink import image_key
    from torchrow.core.io import load_image

    params = _with_mode(_parse_params(args.param), args)
    device = _check_device(args.device)
    model = _check_model(args)
    if model is not None:
        _onnx_host_threads()
    _check_engine(args, onnx_workers=True)
    others, bags = _split_bags(args.inputs, args.topic)
    paths = _collect_images(others) if others else []
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
    names = _record_names(paths)
    # bag frames are named BAG#FRAME, BAG the bag's path relative to the bags' common folder,
    # so that two bags of one file name (dayA/cam.bag, dayB/cam.bag) keep apart
    bag_names = _record_names([b.path for b in bags])
    ann = Path(args.annotate) if args.annotate else None
    ann_paths = [ann / n for n in _annotation_names(names, bag_names)] if ann is not None else []
    foxglove = _check_foxglove(args)
    _check_targets([*map(Path, args.inputs), *paths, *([Path(model)] if model else [])],
                   _out_targets(out) + ([("--annotate", ann)] if ann is not None else [])
                   + [("--annotate", a) for a in ann_paths] + ([("--mcap", Path(args.mcap))] if args.mcap else []))
    sink = _open_sink(out, image_key, args.resume, _run_header("detect", params, args.inputs, impl=args.impl,
                                                                 engine=args.engine))
    if ann is not None:
        ann.mkdir(parents=True, exist_ok=True)
    # --mcap: the image files are one sequence, each bag another
    fox = _open_recorder(args, (["images"] if paths else []) + _Annotator._stems(bags),
                         [_Annotator.DEFAULT_FPS] * (bool(paths) + len(bags))) if foxglove else None

    def inputs():
        """(name, loader, annotated picture, extra record keys, (sequence, index, source of
        the frame's bytes)); bag frames after the files."""
        for j, (p, name) in enumerate(zip(paths, names)):
            yield (name, functools.partial(load_image, p, params.image_width, params.max_pixels),
                   ann_paths[j] if ann is not None else None, None, (0, j, p))
        for s, (b, bag) in enumerate(zip(bags, bag_names), bool(paths)):
            for f in b.frames(params.image_width, params.max_pixels):
                yield (f"{bag}#{f.frame:06d}", f, ann / _bag_picture(bag, f.frame) if ann is not None else None,
                       {"source": b.name, "frame": f.frame, "stamp_ns": f.stamp_ns}, (s, f.frame, f))

    meta: dict[int, tuple[Path | None, dict | None, tuple]] = {}

    def todo():
        k = 0
        for name, loader, picture, extra, origin in inputs():
            if name in sink:  # --resume: already in --out
                continue
            meta[k] = (picture, extra, origin)
            k += 1
            yield name, loader

    total = max(0, len(paths) + sum(b.length for b in bags) - len(sink.done))
    common = dict(impl=args.impl, params=params, batch_size=args.batch_size, device=device,
                  progress=not args.quiet, model=model, total=total)
    if args.engine == "ray":
        from torchrow.engines.distributed import run as ray_run

        stream = ray_run(todo(), workers=args.workers, address=args.address, **common)
    else:
        from torchrow.engines.runner import run

        stream = run(todo(), workers=args.workers if args.impl == "onnx" else None, **common)
    counts: dict[str, int] = {}
    with sink, (fox or contextlib.nullcontext()):
        for i, rgb, res, _ in stream:
            picture, extra, origin = meta.pop(i)
            rec = res.to_record()
            if extra:
                rec = {"name": rec.pop("name"), **extra, **rec}
            if fox is not None:
                rec = fox.frame(*origin[:2], rec, rgb, origin[2])
            sink.write(rec)
            counts[res.status] = counts.get(res.status, 0) + 1
            if picture is not None and rgb is not None:
                picture.parent.mkdir(parents=True, exist_ok=True)
                save_rgb(picture, draw_result(rgb, res))
    summary = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    kept = f"; {len(sink.done)} kept from the earlier run" if args.resume else ""
    print(f"torchrow: {sink.written} image(s) -> {out} ({summary}){kept}", file=sys.stderr)
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

        from torchrow.onnx.metadata import model_meta

        info = model_meta(model)
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


def _onnx_host_threads() -> None:
    """One torch thread for the host side of an onnxruntime run (colour clustering,
    records): torch's OpenMP workers, spinning after each parallel region, would take the
    cores from onnxruntime's own pool (measured: ``OnnxDetector`` 72 ms per CRBD image with
    2 torch threads on 2 cores, 51 ms with 1; the host work itself is no slower on one)."""
    import torch

    torch.set_num_threads(1)


def cmd_export(args: argparse.Namespace) -> int:
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError:
        raise CLIError("export needs onnx and onnxscript: pip install 'torchrow[onnx]'") from None
    from torchrow.onnx.export import to_onnx
    from torchrow.onnx.metadata import model_info

    params = _parse_params(args.param)
    if args.tracker:
        width = args.width if args.width is not None else params.video_width
        if args.height is None:
            raise CLIError("--tracker needs --height: the frames' working height at width "
                           f"{width} (e.g. 281 for 1280x720 video at the default video_width 500)")
        height = args.height
        if width != params.video_width:
            params = _replace_params(params, "--width", video_width=width)
    else:
        width = args.width if args.width is not None else 320
        height = args.height if args.height is not None else 240
        if width != params.image_width:
            params = _replace_params(params, "--width", image_width=width)
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
    what = "tracker step: frames + k_table + active + state" if args.tracker else "images + veg_lab"
    print(f"torchrow: exported {out} in {time.perf_counter() - t0:.0f} s: {info['size'] / 2**20:.1f} MiB, "
          f"{what}, uint8 frames ({args.batch}, 3, {height}, {width}), "
          f"opset {info['opset']}, {sum(info['ops'].values())} nodes")
    print(f"ops: {ops}")
    return 0


def _open_crbd(data: str | None):
    from torchrow.evaluation.datasets import CRBD

    try:
        return CRBD(data)
    except FileNotFoundError as exc:
        if data is None:
            raise CLIError("no CRBD data: pass --data CRBD_DIR or set TORCHROW_DATA") from None
        raise CLIError(f"{str(exc).splitlines()[0]} (--data {data})") from None


def _open_crdld(data: str | None, split: str):
    from torchrow.evaluation.datasets import CRDLD

    try:
        return CRDLD(data, split)
    except FileNotFoundError as exc:
        if data is None:
            raise CLIError("no CRDLD data: pass --data CRDLD_DIR or set TORCHROW_DATA") from None
        raise CLIError(f"{str(exc).splitlines()[0]} (--data {data})") from None


def cmd_eval(args: argparse.Namespace) -> int:
    from torchrow.apps.evaluate import evaluate, evaluate_crdld

    params = _with_mode(_parse_params(args.param), args)
    device = _check_device(args.device)
    if args.impl == "onnx":
        raise CLIError("eval supports --impl tensor|reference; for ONNX use: torchrow detect --impl onnx --model M")
    if args.split is not None and args.dataset != "crdld":
        raise CLIError(f"--split is for --dataset crdld (CRBD has no splits to pick), got --dataset {args.dataset}")
    _check_engine(args)
    ds = _open_crdld(args.data, args.split or "test") if args.dataset == "crdld" else _open_crbd(args.data)
    _check_targets([Path(ds.root)], [("--out", Path(args.out))])
    indices = list(range(len(ds)))[:: args.every]
    if args.limit:
        indices = indices[: args.limit]
    from torchrow.apps.sink import image_key

    Path(args.out).mkdir(parents=True, exist_ok=True)
    sink = _open_sink(Path(args.out) / "detections.jsonl", image_key, args.resume,
                      _run_header("eval", params, [ds.root], impl=args.impl, engine=args.engine))
    try:
        run = evaluate_crdld if args.dataset == "crdld" else evaluate
        report = run(ds, indices, args.impl, params, args.batch_size, device,
                     progress=not args.quiet, sink=sink, engine=args.engine, address=args.address,
                     workers=args.workers)
    finally:
        sink.close(complete=False)
    print(report.format_summary())
    paths = report.write(Path(args.out), records=False)
    for p in paths[:1] + [sink.path] + paths[1:]:
        print(f"wrote {p}", file=sys.stderr)
    return 0


def cmd_score(args: argparse.Namespace) -> int:
    import numpy as np

    from torchrow.apps.evaluate import score_tmg_files
    from torchrow.evaluation.metrics import summarize

    crbd = _open_crbd(args.data)
    results = Path(args.results)
    if not results.is_dir():
        raise CLIError(f"results folder not found: {results}")
    ext = args.ext if args.ext.startswith(".") else "." + args.ext
    present = sum((results / f"{crbd[i].stem}{ext}").is_file() for i in range(len(crbd)))
    if present == 0:
        raise CLIError(f"no result files (<image name>{ext}) for the {len(crbd)} CRBD images in {results}")
    scores = score_tmg_files(crbd, results, ext, progress=not args.quiet)
    missing = len(crbd) - present
    note = f"; {missing} image(s) without a result file scored 0" if missing else ""
    for label, col in (("sigma 0.1", 1), ("sigma 0.3", 2)):
        s = summarize(np.array([r[col] for r in scores]))
        print(f"CRDA {label}: mean {s['mean']:.3f}  median {s['median']:.3f}  (n={s['n']}{note})")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from torchrow.apps.annotate import draw_result, save_rgb
    from torchrow.evaluation.datasets import GroundTruth
    from torchrow.evaluation.metrics import crda_official
    from torchrow.evaluation.synthetic import demo_field
    from torchrow.reference import detect

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


def _open_sources(raw: Sequence[str], topic: str | None = None):
    from torchrow.core.frames import open_source
    from torchrow.core.io import ImageError
    from torchrow.core.rosbag import is_bag

    if topic is not None and not any(is_bag(r) for r in raw):
        raise CLIError("--topic applies to ROS bag sources only (a rosbag2 folder or a .bag file)")
    out = []
    seen: set[str] = set()
    for r in raw:
        if os.path.realpath(r) in seen:  # the same source named twice is one input
            continue
        seen.add(os.path.realpath(r))
        try:
            out.append(open_source(r, topic=topic))
        except (FileNotFoundError, ImageError) as exc:
            raise CLIError(str(exc)) from None
    return out


class _Annotator:
    """Writes annotated frames: one video per source (``OUT.mp4``: H.264; ``OUT.avi``: MJPG) or
    PNGs in a folder. A video's frame rate is ``fps`` if given, else its source's (a video file's
    own rate; ``DEFAULT_FPS`` for a folder of frames)."""

    VIDEO = (".mp4", ".avi", ".mov", ".mkv", ".m4v")
    DEFAULT_FPS = 10.0

    def __init__(self, target: str | None, sources: list, fps: float | None = None) -> None:
        self.target = Path(target) if target else None
        self.is_video = self.target is not None and self.target.suffix.lower() in self.VIDEO
        self.writers: dict[int, object] = {}
        self.size: dict[int, tuple[int, int]] = {}
        self.fps = [fps or getattr(s, "fps", None) or self.DEFAULT_FPS for s in sources]
        self.stems = self._stems(sources)
        if self.target is not None:
            folder = self.target.parent if self.is_video else self.target
            if self.is_video and not folder.exists():
                raise CLIError(f"folder of --annotate does not exist: {folder}")
            folder.mkdir(parents=True, exist_ok=True)

    def _video_path(self, i: int) -> Path:
        assert self.target is not None
        return self._video_paths(self.target, self.stems)[i]

    @staticmethod
    def _video_paths(target: Path, stems: list[str]) -> list[Path]:
        """One video per source: ``target`` itself for one source, ``STEM_<source>.SUFFIX`` for several."""
        if len(stems) == 1:
            return [target]
        return [target.with_name(f"{target.stem}_{stem}{target.suffix}") for stem in stems]

    @classmethod
    def targets(cls, target: str, sources: list) -> list[Path]:
        """What ``--annotate target`` writes to, without creating anything: the folder of
        PNGs, or the video file of every source."""
        t = Path(target)
        if t.suffix.lower() not in cls.VIDEO:
            return [t]
        return cls._video_paths(t, cls._stems(sources))

    @staticmethod
    def _stems(sources: list) -> list[str]:
        stems: list[str] = []
        for i, s in enumerate(sources):
            stem = s.path.stem or f"source{i}"
            stems.append(stem if stem not in stems else f"{stem}_{i}")
        return stems

    def write(self, i: int, res, rgb) -> None:
        from torchrow.apps.annotate import save_rgb
        from torchrow.apps.video import VideoWriter, draw_frame, error_frame

        if self.target is None:
            return
        if rgb is not None:
            img = draw_frame(rgb, res)
            self.size.setdefault(i, (img.shape[1], img.shape[0]))
        elif i in self.size:  # same size as the drawn frames, so that a video keeps its timing
            img = error_frame(*self.size[i], f"frame {res.frame}: {res.error}", scale=1)
        else:
            return
        if not self.is_video:
            save_rgb(self.target / f"{self.stems[i]}_{res.frame:05d}.png", img)
            return
        if i not in self.writers:
            self.writers[i] = VideoWriter(self._video_path(i), self.fps[i])
        self.writers[i].write(img)  # type: ignore[attr-defined]

    def close(self) -> None:
        for vw in self.writers.values():
            vw.close()  # type: ignore[attr-defined]


def _check_plot(plot: Path) -> None:
    """``--plot`` must name a format matplotlib writes (checked before the run, not after it)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    kinds = FigureCanvasAgg(Figure()).get_supported_filetypes()
    if plot.suffix.lower().lstrip(".") not in kinds:
        raise CLIError(f"--plot {plot}: matplotlib cannot write {plot.suffix or 'a file without a suffix'}; "
                       f"use one of {', '.join('.' + k for k in sorted(kinds))}")
    if not plot.parent.exists():
        raise CLIError(f"folder of --plot does not exist: {plot.parent}")


def cmd_video(args: argparse.Namespace) -> int:
    from torchrow.apps.video import central_jumps, plot_tracks
    from torchrow.core.progress import progress

    args.model_kind = "tracker"
    model = _check_model(args)
    if model is not None:
        _onnx_host_threads()
    params = _with_mode(_parse_params(args.param), args)
    if args.hough_every is not None:
        if model is not None:
            raise CLIError("--hough-every cannot change an exported model; export one with --param hough_every=N")
        if args.hough_every < 1:
            raise CLIError(f"--hough-every must be >= 1, got {args.hough_every}")
        params = _replace_params(params, "--hough-every", hough_every=args.hough_every)
    if args.fov is not None and not 0 < args.fov < 180:
        raise CLIError(f"--fov must lie in (0, 180) degrees, got {args.fov}")
    device = _check_device(args.device)
    _check_engine(args)
    sources = _open_sources(args.sources, args.topic)
    camera = None
    if args.camera is not None:
        from torchrow.engines.runner import load_camera

        if args.fov is not None:
            raise CLIError("give --fov or --camera, not both (the camera model has its own field of view)")
        try:
            camera = load_camera(args.camera, sources)
        except ValueError as exc:
            raise CLIError(str(exc)) from None
    onnx = None
    if model is not None:
        if args.engine == "ray":
            raise CLIError("--impl onnx runs with --engine local")
        from torchrow.engines.runner import source_size
        from torchrow.onnx.runtime import OnnxTracker

        onnx = OnnxTracker(model, hfov_deg=args.fov, camera=camera)
        params = onnx.params
        for s in sources:  # the model's working size, checked before anything is written
            size = source_size(s, params)
            if size is not None and size != (onnx.height, onnx.width):
                raise CLIError(f"{s.name}: frames of working size {size[1]}x{size[0]}; the model {model} takes "
                               f"{onnx.width}x{onnx.height} (export one with --tracker --height {size[0]})")
    out = Path(args.out)
    plot = None if args.plot == "none" else Path(args.plot) if args.plot else out.with_suffix(".png")
    from torchrow.apps.sink import frame_key, read_records

    if plot is not None:
        _check_plot(plot)
    if args.fps is not None and not args.fps > 0:
        raise CLIError(f"--fps must be > 0, got {args.fps}")
    targets = _out_targets(out) + ([("--plot", plot)] if plot is not None else [])
    if args.annotate:
        targets += [("--annotate", t) for t in _Annotator.targets(args.annotate, sources)]
    foxglove = _check_foxglove(args)
    if args.mcap is not None:
        targets.append(("--mcap", Path(args.mcap)))
    _check_targets([s.path for s in sources], targets)
    real = [os.path.realpath(s.path) for s in sources]
    sink = _open_sink(out, frame_key, args.resume, _run_header(
        "video", params, real, impl=args.impl, engine=args.engine, names=dict(zip(real, (s.name for s in sources)))))
    ann = _Annotator(args.annotate, sources, args.fps)
    fox = None
    if foxglove:
        from torchrow.apps.foxglove import FrameOrigins

        fox = _open_recorder(args, _Annotator._stems(sources), ann.fps)
        origins = [FrameOrigins(s) for s in sources]
    # a source spelled otherwise than in the run being resumed (cat20, /abs/cat20) keeps that
    # run's name, so that its frames are found and its records stay under one name
    before = ((sink.previous_header or {}).get("info") or {}).get("names") or {}
    names = [before.get(r, s.name) for r, s in zip(real, sources)]
    done: dict[str, set[int]] = {}
    for src, frame in sink.done:
        done.setdefault(src, set()).add(frame)
    # --resume: a batch of sources (runner.track_batches) with a record for each frame is not
    # tracked again; any other batch is tracked from frame 0 (the tracker's state needs it, and
    # the same batch gives the same bits) and its written frames are skipped
    todo = list(range(len(sources)))
    if args.resume:
        from torchrow.engines.runner import track_batches

        # all(...) stops at the first frame without a record: the bag's stated message count
        # (metadata, possibly wrong) sizes nothing
        complete = [all(t in done.get(names[i], ()) for t in range(s.length)) for i, s in enumerate(sources)]
        todo = [i for batch in track_batches(sources, args.impl, params, args.batch_size, onnx=onnx)
                if not all(complete[j] for j in batch) for i in batch]
    if args.engine == "ray":
        from torchrow.engines.distributed import track as ray_track

        stream = ((todo[b], rec, None, None) for b, rec in ray_track(
            [sources[i].path for i in todo], [names[i] for i in todo], args.impl, params, device, args.fov,
            args.topic, skip={b: done.get(names[i], set()) for b, i in enumerate(todo)},
            batch_size=args.batch_size, address=args.address, camera=camera))
    else:
        from torchrow.engines.runner import track

        stream = ((todo[b], None, res, rgb) for b, res, rgb in track(
            [sources[i] for i in todo], [names[i] for i in todo], args.impl, params, args.batch_size, device,
            args.fov, onnx=onnx, camera=camera))
    counts: dict[str, int] = {}
    total = sum(sources[i].length for i in todo)
    bar = progress(total, "video", enabled=not args.quiet, unit="frame")
    try:
        with sink, (fox or contextlib.nullcontext()):
            for i, rec, res, rgb in stream:
                bar.update(1)
                if rec is None:
                    if (names[i], res.frame) in sink:
                        continue
                    rec = res.to_record()
                    ann.write(i, res, rgb)
                    if fox is not None:
                        rec = fox.frame(i, res.frame, rec, rgb, origins[i](res.frame))
                sink.write(rec)
                counts[rec["status"]] = counts.get(rec["status"], 0) + 1
    finally:
        bar.close()
        ann.close()
    n = sum(counts.values())
    summary = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    kept = f"; {len(sink.done)} kept from the earlier run" if args.resume else ""
    print(f"torchrow: {n} frame(s) of {len(sources)} source(s) -> {out} ({summary}){kept}"
          + (f"; plot {plot}" if plot else ""), file=sys.stderr)
    if plot is None:
        return 0
    # the plot and the summary read the records back from --out (the run itself keeps none)
    by_source: dict[str, list[dict]] = {nm: [] for nm in names}
    for rec in read_records(out):
        rec.pop("hough", None)
        rec.pop("outliers", None)
        by_source.setdefault(rec.get("source"), []).append(rec)
    for recs in by_source.values():
        recs.sort(key=lambda r: r["frame"])
    plot_tracks(by_source, plot)
    for src, recs in by_source.items():
        jumps = central_jumps(recs)
        hough = sum(1 for r in recs if r.get("hough_ran"))

        def worst(key: str, jumps: dict = jumps) -> str:
            return f"{max(jumps[key]):.1f} px" if jumps[key] else "n/a"

        print(f"  {src}: Hough on {hough} of {len(recs)} frames; largest move of the central row at the "
              f"bottom: {worst('tracked')} into a tracked frame, {worst('hough')} into a Hough frame",
              file=sys.stderr)
    return 0


def _fmt_vp(vp) -> str:
    return "none" if vp is None else f"({vp[0]:.1f}, {vp[1]:.1f})"


def _with_mode(params: Params, args: argparse.Namespace) -> Params:
    """Apply ``--mode`` (faithful | improved, ALGORITHM.md section 11) to the parameters."""
    mode = getattr(args, "mode", None)
    if mode is None:
        return params
    if mode == "improved" and getattr(args, "impl", None) == "onnx":
        raise CLIError("--mode improved has no ONNX export yet; use --impl tensor or reference")
    if mode == "improved" and args.command == "video":
        raise CLIError("--mode improved is not available for video yet: the tracker is faithful only, and the "
                       "lattice's CRBD geometry (vanishing point above the image, rows 40-180 px apart) does not "
                       "hold for a camera that sees the horizon (ALGORITHM.md 11.5)")
    return params.replace(mode=mode)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="torchrow", description="Crop-row detection (ALGORITHM.md), "
                                 "reference and batched tensor implementations.")
    ap.add_argument("--version", action="version", version=f"torchrow {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--param", action="append", metavar="NAME=VALUE",
                       help="override a Params field, e.g. --param n_rows=4 (repeatable)")
        p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")

    def impl(p: argparse.ArgumentParser, batch: int = 64, item: str = "image",
             export: str = "torchrow export onnx") -> None:
        p.add_argument("--impl", choices=("tensor", "reference", "onnx"), default="tensor",
                       help=f"batched tensor path (default), the per-{item} reference, or an exported ONNX "
                            "model in onnxruntime (--model)")
        p.add_argument("--model", help=f"ONNX file for --impl onnx ({export})")
        p.add_argument("--batch-size", type=int, default=batch,
                       help=f"{item}s per batch for --impl tensor (default {batch})")
        p.add_argument("--device", default=None,
                       help="torch device for --impl tensor (cpu, cuda, cuda:1; default cpu)")
        mode(p)

    def engine(p: argparse.ArgumentParser) -> None:
        p.add_argument("--engine", choices=("local", "ray"), default="local",
                       help="run here (default) or on a Ray cluster (pip install 'torchrow[ray]')")
        p.add_argument("--address", default=None,
                       help="--engine ray: cluster to join (auto, HOST:6379, ray://HOST:10001); default: "
                            "$RAY_ADDRESS, else a local cluster with this machine's CPUs")
        p.add_argument("--workers", type=int, default=None,
                       help="--engine ray: detector actors (default: the cluster's CPUs); detect --impl onnx: "
                            "concurrent onnxruntime runs, one thread each (default: this machine's cores, at most 4)")
        p.add_argument("--resume", action="store_true",
                       help="keep the records already in --out, skip their inputs, append the rest")

    def mode(p: argparse.ArgumentParser) -> None:
        p.add_argument("--mode", choices=("faithful", "improved"), default=None,
                       help="faithful: the thesis' algorithm (default); improved: curved rows on a spacing "
                            "lattice (ALGORITHM.md section 11, a torchrow extension)")

    p = sub.add_parser("detect", help="detect rows in images, write one JSON record per file")
    p.add_argument("inputs", nargs="+", metavar="IMAGE_OR_DIR_OR_BAG")
    p.add_argument("--out", required=True, help="JSONL output file (or .parquet)")
    p.add_argument("--topic", default=None, help="image topic of the ROS bag inputs (default: the only one)")
    engine(p)
    p.add_argument("--annotate", metavar="DIR", help="write annotated PNGs to DIR")
    p.add_argument("--mcap", metavar="OUT.mcap", default=None,
                   help="also write the images, rows and signals as a Foxglove MCAP recording "
                        "(pip install 'torchrow[foxglove]')")
    impl(p)
    common(p)
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser("eval", help="run on CRBD and report CRDA (official and thesis variant), or on CRDLD "
                                    "(ALGORITHM.md 10.1)")
    p.add_argument("--dataset", choices=("crbd", "crdld"), default="crbd",
                   help="crbd (default): the CRBD benchmark; crdld: a Crop Row Detection Lincoln Dataset split")
    p.add_argument("--data", help="CRBD folder (or a folder holding crbd/); for crdld a split folder (image/, "
                                  "label/), a folder holding train/ and test/, or one holding crdld_dev/; "
                                  "default $TORCHROW_DATA")
    p.add_argument("--split", choices=("test", "train"), default=None,
                   help="--dataset crdld: the split where --data holds train/ and test/ (default test)")
    p.add_argument("--out", default="torchrow-eval",
                   help="folder for scores.csv, detections.jsonl, summary.json, crda_histogram.png "
                        "(default torchrow-eval)")
    p.add_argument("--every", type=int, default=1, help="use every N-th image (default 1: all)")
    p.add_argument("--limit", type=int, default=0, help="at most this many images (default 0: no limit)")
    engine(p)
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
                       description="Track crop rows through folders of frames (sorted by name), video files or ROS bags; "
                                   "several sources are tracked as a batch of sequences. Writes one JSON record "
                                   "per frame and a PNG plot of rows and steering signals over time.")
    p.add_argument("sources", nargs="+", metavar="SOURCE",
                   help="folder of frames, video file, or ROS bag (rosbag2 folder, ROS 1 .bag)")
    p.add_argument("--out", required=True, help="JSONL output file (or .parquet; plot next to it, .png)")
    p.add_argument("--topic", default=None, help="image topic of the ROS bag sources (default: the only one)")
    engine(p)
    p.add_argument("--annotate", metavar="OUT.mp4|DIR", help="annotated video (per source) or folder of PNGs")
    p.add_argument("--hough-every", dest="hough_every", type=int, default=None, metavar="K",
                   help="run the Hough stage every K frames (default: Params.hough_every, 5)")
    p.add_argument("--fps", type=float, default=None,
                   help="frame rate of the frames (annotated video, MCAP times and --serve pace of sources "
                        "without stamps; default: the source's; 10 for a folder of frames)")
    p.add_argument("--mcap", metavar="OUT.mcap", default=None,
                   help="also write the frames, rows and signals as a Foxglove MCAP recording "
                        "(pip install 'torchrow[foxglove]')")
    p.add_argument("--serve", metavar="[HOST:]PORT", default=None,
                   help="show the run live in Foxglove: a WebSocket server on HOST (default 127.0.0.1), "
                        "frames paced at the source's rate")
    p.add_argument("--serve-wait", dest="serve_wait", type=float, default=10.0, metavar="SEC",
                   help="--serve: wait up to SEC seconds for a first client before tracking (default 10)")
    p.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="horizontal field of view of the frames, for heading_rad (null without it)")
    p.add_argument("--camera", metavar="CAMERA.json", default=None,
                   help="camera model (height_m, tilt_deg, and hfov_deg or fx, fy, cx, cy in source pixels): "
                        "records gain lateral_m, spacing_m and the ground heading_rad (README: video)")
    p.add_argument("--plot", default=None, help="plot file (default: --out with suffix .png); 'none': no plot")
    impl(p, batch=8, item="sequence", export="a tracker step: torchrow export onnx --tracker")
    common(p)
    p.set_defaults(func=cmd_video)

    p = sub.add_parser("export", help="export the image-mode detector or the tracker step (see README: ONNX export)")
    esub = p.add_subparsers(dest="format", required=True)
    p = esub.add_parser("onnx", help="static-shape ONNX graph (torch dynamo exporter)")
    p.add_argument("--out", required=True, help="output .onnx file")
    p.add_argument("--tracker", action="store_true",
                   help="export the video tracker step (frame + state -> rows + new state) instead of the detector")
    p.add_argument("--no-control-flow", action="store_true",
                   help="no ONNX Loop or If: every line-search step to the static bound (and, tracker, both "
                        "branches) runs, masks choose (slower, same results)")
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
    except ValueError as exc:  # a Parquet output that cannot be written (torchrow.apps.sink.SinkError)
        from torchrow.apps.sink import SinkError

        if not isinstance(exc, SinkError):
            raise
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
