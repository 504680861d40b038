"""What several commands share: argument groups, ``--param`` parsing, input expansion and
record names, output checks, ``--out`` / ``--resume`` (the run header and the record sink),
engine, device and model checks, the Foxglove recorder, the datasets of ``eval`` and
``score``, and the one-line error.

A user error raises :class:`CLIError`; :func:`torchrow.apps.cli.main` prints it with
:func:`print_error` and exits with :data:`ERROR_STATUS`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from torchrow import __version__
from torchrow.core.io import IMAGE_EXTENSIONS
from torchrow.core.params import FORWARD_CAMERA, Params

if TYPE_CHECKING:
    from torchrow.apps.foxglove import Recorder
    from torchrow.apps.sink import Key, RecordSink
    from torchrow.core.frames import FrameSource
    from torchrow.core.rosbag import BagSource
    from torchrow.evaluation.datasets import CRBD, CRDLD

__all__ = [
    "CLIError", "ERROR_STATUS", "DEFAULT_FPS", "print_error",
    "add_common", "add_engine", "add_impl", "add_mode", "add_evidence", "evidence_files",
    "parse_params", "replace_params", "setting_hint", "tracks", "with_mode",
    "collect_images", "record_names", "annotation_names", "bag_picture", "source_stems", "split_bags",
    "check_targets", "check_device", "check_engine", "check_model", "onnx_host_threads",
    "out_targets", "run_header", "open_sink", "check_foxglove", "open_recorder", "open_crbd", "open_crdld",
]

ERROR_STATUS = 2
"""Exit status of a user error (arguments, paths, an output that cannot be written)."""

DEFAULT_FPS = 10.0
"""Frame rate of a sequence whose source states none (a folder of frames, the image files of
``detect``): annotated videos and Foxglove recordings."""


class CLIError(Exception):
    """A user error: reported as one line, exit status :data:`ERROR_STATUS`."""


def print_error(message: object) -> int:
    """Print ``torchrow: error: MESSAGE`` on stderr; returns :data:`ERROR_STATUS`."""
    print(f"torchrow: error: {message}", file=sys.stderr)
    return ERROR_STATUS


# ---------------------------------------------------------------- argument groups


def add_common(p: argparse.ArgumentParser) -> None:
    """``--param`` and ``--quiet``: every command."""
    p.add_argument("--param", action="append", metavar="NAME=VALUE",
                   help="override a Params field, e.g. --param n_rows=4 (repeatable)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def add_mode(p: argparse.ArgumentParser) -> None:
    """``--mode`` and ``--forward`` (applied by :func:`with_mode`)."""
    p.add_argument("--mode", choices=("faithful", "improved"), default=None,
                   help="faithful: the thesis' algorithm (default); improved: curved rows on a spacing "
                        "lattice (ALGORITHM.md section 11, a torchrow extension)")
    p.add_argument("--forward", action=argparse.BooleanOptionalAction, default=None,
                   help="the improved mode's forward-camera setting, for a camera that sees the horizon: "
                        + ", ".join(f"{k}={v}" for k, v in FORWARD_CAMERA.items())
                        + " (implies --mode improved; --param overrides it). The lattice tracker's default "
                          "(video, export --tracker: a robot's camera looks forward); --no-forward: the "
                          "improved mode's default setting (a camera looking down at the field, as CRBD's)")


def add_impl(p: argparse.ArgumentParser, batch: int = 64, item: str = "image",
             export: str = "torchrow export onnx") -> None:
    """``--impl``, ``--model``, ``--batch-size``, ``--device`` and ``--mode``; ``batch``: the default
    batch size, ``item``: what a batch holds, ``export``: how to write a ``--model``."""
    p.add_argument("--impl", choices=("tensor", "reference", "onnx"), default="tensor",
                   help=f"batched tensor path (default), the per-{item} reference, or an exported ONNX "
                        "model in onnxruntime (--model)")
    p.add_argument("--model", help=f"ONNX file for --impl onnx ({export})")
    p.add_argument("--batch-size", type=int, default=batch,
                   help=f"{item}s per batch for --impl tensor (default {batch})")
    p.add_argument("--device", default=None,
                   help="torch device for --impl tensor (cpu, cuda, cuda:1; default cpu)")
    add_mode(p)


def add_engine(p: argparse.ArgumentParser) -> None:
    """``--engine``, ``--address``, ``--workers`` (checked by :func:`check_engine`) and ``--resume``."""
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


def add_evidence(p: argparse.ArgumentParser) -> None:
    """``--evidence DIR`` (checked and resolved by :func:`evidence_files`)."""
    p.add_argument("--evidence", metavar="DIR", default=None,
                   help="row masks to fit in place of the green mask (improved mode, ALGORITHM.md 11.1.1), e.g. a "
                        "segmentation network's: image NAME's mask is DIR/NAME with its suffix replaced by .png, "
                        "else DIR/NAME; non-zero pixels are crop rows; any size of the image's aspect")


def evidence_files(args: argparse.Namespace, names: Sequence[str], params: Params) -> list[Path] | None:
    """The mask file of each record name with ``--evidence`` (:func:`add_evidence`), in order;
    ``None`` without it. Every mask must exist before the run starts (a missing one is a
    :class:`CLIError` naming it), so a long run never ends with holes; an unreadable one becomes
    its image's ``error`` record."""
    if args.evidence is None:
        return None
    if params.mode != "improved":
        raise CLIError(f"--evidence is read by the improved mode only (--mode improved or --forward); "
                       f"got mode {params.mode}")
    if getattr(args, "impl", None) == "onnx":
        raise CLIError("--evidence works with --impl tensor or reference; the ONNX detector takes images only")
    folder = Path(args.evidence)
    if not folder.is_dir():
        raise CLIError(f"--evidence: no such folder: {folder}")
    found: list[Path] = []
    missing: list[str] = []
    for name in names:
        tries = [folder / Path(name).with_suffix(".png"), folder / name]
        hit = next((t for t in tries if t.is_file()), None)
        if hit is None:
            missing.append(" or ".join(dict.fromkeys(map(str, tries))))
        else:
            found.append(hit)
    if missing:
        raise CLIError(f"--evidence {folder}: no mask for {len(missing)} of {len(names)} image(s); "
                       f"the first: {missing[0]}")
    return found


# ---------------------------------------------------------------- parameters


def parse_params(items: Sequence[str] | None) -> Params:
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


def replace_params(params: Params, option: str, **changes: object) -> Params:
    """``params.replace(**changes)`` for a command-line option: a value outside its rule is one line."""
    try:
        return params.replace(**changes)
    except (ValueError, TypeError) as exc:
        raise CLIError(f"{option}: {exc}") from None


def tracks(args: argparse.Namespace) -> bool:
    """Whether the command runs or exports the tracker (``video``, ``export --tracker``)."""
    return args.command == "video" or (args.command == "export" and bool(getattr(args, "tracker", False)))


def setting_hint(params: Params, counts: dict[str, int]) -> str | None:
    """A line for a run in improved mode whose images were mostly not ``ok`` with the VP grid
    above the image (``lattice_vp_origin="top"``, the default setting): the forward-camera setting,
    whose grid counts from the horizon (ALGORITHM.md 11.2), is what a camera that sees the horizon
    needs. ``None`` otherwise."""
    n = sum(counts.values())
    if params.mode != "improved" or params.lattice_vp_origin == "sky" or n == 0 or 2 * counts.get("ok", 0) >= n:
        return None
    return (f"torchrow: {n - counts.get('ok', 0)} of {n} not ok with the vanishing-point grid above the image "
            "(the improved mode's default setting); for a camera that sees the horizon use --forward")


def with_mode(params: Params, args: argparse.Namespace) -> Params:
    """Apply ``--mode`` (faithful | improved, ALGORITHM.md section 11) and ``--forward``
    (:data:`~torchrow.core.params.FORWARD_CAMERA` where no ``--param`` names the field) to the
    parameters. The tracker's improved mode takes ``--forward`` unless ``--no-forward`` is given
    (:func:`tracks`)."""
    mode = getattr(args, "mode", None)
    forward = getattr(args, "forward", None)
    if forward is not None and mode == "faithful":
        raise CLIError(f"--{'' if forward else 'no-'}forward is a setting of the improved mode; leave out "
                       "--mode faithful")
    if forward is None and (mode or params.mode) == "improved" and tracks(args):
        forward = True  # the lattice tracker runs on a robot's camera, which looks forward (README: video)
    if forward and getattr(args, "impl", None) != "onnx":  # an exported model brings its own (check_model)
        given = {item.partition("=")[0] for item in getattr(args, "param", None) or []}
        params = replace_params(params, "--forward", **{k: v for k, v in FORWARD_CAMERA.items() if k not in given})
    if forward is not None:
        mode = "improved"
    if mode is None:
        return params
    if mode == "improved" and getattr(args, "impl", None) == "onnx" and args.command != "video":
        raise CLIError("--mode improved: no ONNX export of the improved detector (only of its tracker step, for "
                       "torchrow video); use --impl tensor or reference")
    if mode == "improved" and args.command == "video":
        try:  # the lattice tracker's own conditions (ALGORITHM.md 11.7)
            from torchrow.reference.lattice_tracking import check_lattice_tracker

            check_lattice_tracker(params.replace(mode=mode))
        except ValueError as exc:
            raise CLIError(f"--mode improved: {exc}") from None
    return params.replace(mode=mode)


# ---------------------------------------------------------------- inputs and their names


def collect_images(inputs: Sequence[str]) -> list[Path]:
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


def record_names(paths: Sequence[Path]) -> list[str]:
    """Record names: each file's path relative to the common folder of all inputs, ``/``-separated.

    Unique per input (``s1/x.jpg``, ``s2/x.jpg``); for the files of one folder, or one
    file, this is the file name.
    """
    if not paths:
        return []
    absolute = [os.path.abspath(p) for p in paths]
    root = os.path.commonpath([os.path.dirname(a) for a in absolute])
    return [Path(os.path.relpath(a, root)).as_posix() for a in absolute]


def annotation_names(names: Sequence[str], bags: Sequence[str] = ()) -> list[str]:
    """Annotated-picture paths (relative to ``--annotate``) for record names: the name with
    its suffix replaced by ``.png``; where two names would meet (``x.jpg``, ``x.png``), or a
    name would meet a bag frame's picture (``BAG_FRAME.png``, :func:`bag_picture`; ``bags``:
    the bags' record names), the whole name plus ``.png`` (``x.jpg.png``, ``x.png.png``), so
    pictures never overwrite each other."""
    stems = [Path(n).with_suffix(".png").as_posix() for n in names]
    taken: dict[str, int] = {}
    for s in stems:
        taken[s] = taken.get(s, 0) + 1
    frame = re.compile("|".join(re.escape(b) + r"_\d{6,}\.png" for b in bags)) if bags else None
    return [s if taken[s] == 1 and not (frame and frame.fullmatch(s)) else n + ".png" for n, s in zip(names, stems)]


def bag_picture(bag: str, frame: int) -> str:
    """Annotated-picture path (relative to ``--annotate``) of a bag frame: ``BAG_FRAME.png``,
    ``bag`` being the bag's record name (:func:`record_names` of the bags)."""
    return f"{bag}_{frame:06d}.png"


def source_stems(sources: Sequence[FrameSource | BagSource]) -> list[str]:
    """One distinct label per source (file or folder stem; ``_INDEX`` added on a repeat):
    annotated video names and Foxglove sequence labels."""
    stems: list[str] = []
    for i, s in enumerate(sources):
        stem = s.path.stem or f"source{i}"
        stems.append(stem if stem not in stems else f"{stem}_{i}")
    return stems


def split_bags(inputs: Sequence[str], topic: str | None) -> tuple[list[str], list[BagSource]]:
    """ROS bag inputs (opened, ``topic`` chosen) apart from image files and folders; the same
    bag named twice (another spelling, a link) is one input, as for files."""
    from torchrow.core.rosbag import BagError, is_bag, open_bag

    others: list[str] = []
    bags: list[BagSource] = []
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


# ---------------------------------------------------------------- checks before a run


def check_targets(inputs: Sequence[Path], targets: Sequence[tuple[str, Path]]) -> None:
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

    files: dict[Path, tuple[int, int] | None] = {}
    folders: list[Path] = []
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


def check_device(device: str | None) -> str | None:
    """``--device`` as torch spells it (``None``: the default); a bad name or an absent CUDA is one line."""
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


def check_engine(args: argparse.Namespace, onnx_workers: bool = False) -> None:
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


def check_model(args: argparse.Namespace, kind: str = "detector") -> str | None:
    """``--model`` for ``--impl onnx``: present, readable, a torchrow ``kind`` export (detector
    or tracker) of the mode ``--mode`` names (if given; the model's own otherwise), onnxruntime
    installed; ``None`` for the other implementations."""
    model: str | None = getattr(args, "model", None)
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
    if info["kind"] != kind:
        cmd = "detect" if kind == "detector" else "video"
        how = "without --tracker" if kind == "detector" else "--tracker"
        raise CLIError(f"{model} is a torchrow {info['kind']} model; {cmd} needs a {kind} model "
                       f"(torchrow export onnx {how})")
    mode = getattr(args, "mode", None)
    if mode is not None and mode != info["mode"]:
        raise CLIError(f"--mode {mode}: {model} was exported in {info['mode']} mode (export one with "
                       f"--mode {mode}{' --tracker' if kind == 'tracker' else ''}, or leave out --mode)")
    if args.param:
        raise CLIError("--param cannot change an exported model; export one with those --param values")
    forward = getattr(args, "forward", None)
    has = all(info["params"].__dict__[k] == v for k, v in FORWARD_CAMERA.items())
    if forward is not None and forward != has:
        raise CLIError(f"--{'' if forward else 'no-'}forward: {model} was exported "
                       f"{'without' if forward else 'with'} the forward-camera setting (export one with "
                       f"--mode improved --{'' if forward else 'no-'}forward{' --tracker' if kind == 'tracker' else ''}, "
                       "or leave the option out)")
    want = info["params"].image_width if kind == "detector" else info["params"].video_width
    if want != info["width"]:
        raise CLIError(f"model {model} takes {info['width']}x{info['height']} images but its working width is {want}")
    return model


def onnx_host_threads() -> None:
    """One torch thread for the host side of an onnxruntime run (colour clustering,
    records): torch's OpenMP workers, spinning after each parallel region, would take the
    cores from onnxruntime's own pool (measured: ``OnnxDetector`` 72 ms per CRBD image with
    2 torch threads on 2 cores, 51 ms with 1; the host work itself is no slower on one)."""
    import torch

    torch.set_num_threads(1)


# ---------------------------------------------------------------- --out, --resume and the run header


def out_targets(out: Path) -> list[tuple[str, Path]]:
    """``("--out", path)`` for everything a sink on ``out`` writes (journal, temporary file, header)."""
    from torchrow.apps.sink import output_paths

    return [("--out", p) for p in output_paths(out)]


def run_header(command: str, params: Params, sources: Sequence[str | Path], **info: object) -> dict:
    """What a run is, for ``--resume`` (torchrow.apps.sink): the command, every parameter (the
    mode is one) and the sources as resolved paths (any order) are compared; ``info`` (impl,
    engine, the names as spelled) is kept for the reader. Impl, engine and batch size are not
    compared: their records agree (README, "Identical results")."""
    return {"command": command, "params": dataclasses.asdict(params),
            "sources": sorted({os.path.realpath(s) for s in sources}),
            "info": {"torchrow": __version__, **info}}


def open_sink(out: Path, key: Key, resume: bool, header: dict | None = None) -> RecordSink:
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


# ---------------------------------------------------------------- Foxglove


def check_foxglove(args: argparse.Namespace) -> bool:
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


def open_recorder(args: argparse.Namespace, labels: list[str], fps: list[float]) -> Recorder:
    """The Foxglove recorder of ``--mcap`` / ``--serve`` (checked by :func:`check_foxglove`):
    one sequence per label, each at its frame rate."""
    from torchrow.apps.foxglove import Recorder

    return Recorder(labels, fps, Path(args.mcap) if args.mcap is not None else None,
                    getattr(args, "serve", None), getattr(args, "serve_wait", 0.0))


# ---------------------------------------------------------------- datasets


def open_crbd(data: str | None) -> CRBD:
    """The CRBD dataset of ``--data`` (default ``$TORCHROW_DATA``); a missing one is one line."""
    from torchrow.evaluation.datasets import CRBD

    try:
        return CRBD(data)
    except FileNotFoundError as exc:
        if data is None:
            raise CLIError("no CRBD data: pass --data CRBD_DIR or set TORCHROW_DATA") from None
        raise CLIError(f"{str(exc).splitlines()[0]} (--data {data})") from None


def open_crdld(data: str | None, split: str) -> CRDLD:
    """The CRDLD ``split`` of ``--data`` (default ``$TORCHROW_DATA``); a missing one is one line."""
    from torchrow.evaluation.datasets import CRDLD

    try:
        return CRDLD(data, split)
    except FileNotFoundError as exc:
        if data is None:
            raise CLIError("no CRDLD data: pass --data CRDLD_DIR or set TORCHROW_DATA") from None
        raise CLIError(f"{str(exc).splitlines()[0]} (--data {data})") from None
