"""``torchrow video``: rows tracked through folders of frames, video files and ROS bags
(ALGORITHM.md section 8), one record per frame (``--out``), a plot of rows and steering
signals over time, optionally annotated videos or PNGs and a Foxglove recording or live view."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, cast

from torchrow.apps.commands.shared import (
    DEFAULT_FPS,
    CLIError,
    add_common,
    add_engine,
    add_impl,
    check_device,
    check_engine,
    check_foxglove,
    check_model,
    check_targets,
    onnx_host_threads,
    open_recorder,
    open_sink,
    out_targets,
    parse_params,
    replace_params,
    run_header,
    setting_hint,
    source_stems,
    with_mode,
)

if TYPE_CHECKING:
    import numpy as np

    from torchrow.apps.foxglove import FrameOrigins
    from torchrow.apps.video import VideoWriter
    from torchrow.core.frames import FrameSource
    from torchrow.core.rosbag import BagSource
    from torchrow.core.steering import FrameResult, RowId
    Source = FrameSource | BagSource

__all__ = ["add_parser", "run", "Tracked", "Recorded"]


class Tracked(NamedTuple):
    """A frame the local engine tracked: its result and working image (``None``: unreadable)."""

    source: int  # index into the command's sources
    result: FrameResult
    rgb: np.ndarray | None


class Recorded(NamedTuple):
    """A frame the Ray engine tracked: its record only (no image comes back from the cluster)."""

    source: int  # index into the command's sources
    record: dict


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "video", help="track rows through frame sequences (ALGORITHM.md section 8)",
        description="Track crop rows through folders of frames (sorted by name), video files or ROS bags; "
                    "several sources are tracked as a batch of sequences. Writes one JSON record "
                    "per frame and a PNG plot of rows and steering signals over time.")
    p.add_argument("sources", nargs="+", metavar="SOURCE",
                   help="folder of frames, video file, or ROS bag (rosbag2 folder, ROS 1 .bag)")
    p.add_argument("--out", required=True, help="JSONL output file (or .parquet; plot next to it, .png)")
    p.add_argument("--topic", default=None, help="image topic of the ROS bag sources (default: the only one)")
    add_engine(p)
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
    add_impl(p, batch=8, item="sequence",
             export="a tracker step: torchrow export onnx --tracker, with --mode improved for the improved mode")
    add_common(p)
    p.set_defaults(func=run)


def _open_sources(raw: Sequence[str], topic: str | None = None) -> list[Source]:
    """The sources (each once, however spelled), opened; an unusable one is one line."""
    from torchrow.core.frames import open_source
    from torchrow.core.io import ImageError
    from torchrow.core.rosbag import is_bag

    if topic is not None and not any(is_bag(r) for r in raw):
        raise CLIError("--topic applies to ROS bag sources only (a rosbag2 folder or a .bag file)")
    out: list[Source] = []
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
    own rate; ``DEFAULT_FPS`` for a folder of frames). Lattice tracker frames name their tracked
    row by its running id (:class:`torchrow.core.steering.RowId`, one per source)."""

    VIDEO = (".mp4", ".avi", ".mov", ".mkv", ".m4v")

    def __init__(self, target: str | None, sources: Sequence[Source], fps: float | None = None) -> None:
        self.target = Path(target) if target else None
        self.is_video = self.target is not None and self.target.suffix.lower() in self.VIDEO
        self.writers: dict[int, VideoWriter] = {}
        self.size: dict[int, tuple[int, int]] = {}
        self.row_ids: dict[int, RowId] = {}
        self.fps: list[float] = [fps or getattr(s, "fps", None) or DEFAULT_FPS for s in sources]
        self.stems = source_stems(sources)
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
    def targets(cls, target: str, sources: Sequence[Source]) -> list[Path]:
        """What ``--annotate target`` writes to, without creating anything: the folder of
        PNGs, or the video file of every source."""
        t = Path(target)
        if t.suffix.lower() not in cls.VIDEO:
            return [t]
        return cls._video_paths(t, source_stems(sources))

    def count(self, i: int, res: FrameResult) -> int:
        """Source ``i``'s running row id after frame ``res`` (every frame counts, drawn or not)."""
        from torchrow.core.steering import RowId

        return self.row_ids.setdefault(i, RowId()).update(res.row_change)

    def write(self, i: int, res: FrameResult, rgb: np.ndarray | None) -> None:
        from torchrow.apps.annotate import save_rgb
        from torchrow.apps.video import VideoWriter, draw_frame, error_frame

        row_id = self.count(i, res)
        if self.target is None:
            return
        if rgb is not None:
            img = draw_frame(rgb, res, row_id=row_id)
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
        self.writers[i].write(img)

    def close(self) -> None:
        for vw in self.writers.values():
            vw.close()


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


def run(args: argparse.Namespace) -> int:
    from torchrow.apps.video import central_jumps, moves_line, plot_tracks
    from torchrow.core.progress import progress
    from torchrow.evaluation.tracking import row_moves

    params = with_mode(parse_params(args.param), args)  # an exported model's params replace these below
    model = check_model(args, kind="tracker")
    if model is not None:
        onnx_host_threads()
    if args.hough_every is not None:
        if model is not None:
            raise CLIError("--hough-every cannot change an exported model; export one with --param hough_every=N")
        if args.hough_every < 1:
            raise CLIError(f"--hough-every must be >= 1, got {args.hough_every}")
        params = replace_params(params, "--hough-every", hough_every=args.hough_every)
    if args.fov is not None and not 0 < args.fov < 180:
        raise CLIError(f"--fov must lie in (0, 180) degrees, got {args.fov}")
    device = check_device(args.device)
    check_engine(args)
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
    # OnnxTracker's model attributes (params, height, width) are set when it opens the model,
    # out of the checker's sight
    onnx: Any = None
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
    targets = out_targets(out) + ([("--plot", plot)] if plot is not None else [])
    if args.annotate:
        targets += [("--annotate", t) for t in _Annotator.targets(args.annotate, sources)]
    foxglove = check_foxglove(args)
    if args.mcap is not None:
        targets.append(("--mcap", Path(args.mcap)))
    check_targets([s.path for s in sources], targets)
    real = [os.path.realpath(s.path) for s in sources]
    sink = open_sink(out, frame_key, args.resume, run_header(
        "video", params, real, impl=args.impl, engine=args.engine, names=dict(zip(real, (s.name for s in sources)))))
    ann = _Annotator(args.annotate, sources, args.fps)
    fox = None
    origins: list[FrameOrigins] = []
    if foxglove:
        from torchrow.apps.foxglove import FrameOrigins

        fox = open_recorder(args, source_stems(sources), ann.fps)
        origins = [FrameOrigins(s) for s in sources]
    # a source spelled otherwise than in the run being resumed (cat20, /abs/cat20) keeps that
    # run's name, so that its frames are found and its records stay under one name
    before = ((sink.previous_header or {}).get("info") or {}).get("names") or {}
    names = [before.get(r, s.name) for r, s in zip(real, sources)]
    done: dict[str, set[int]] = {}
    for src, frame in cast("set[tuple[str, int]]", sink.done):  # frame_key: (source, frame)
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
    stream: Iterator[Tracked | Recorded]
    if args.engine == "ray":
        from torchrow.engines.distributed import track as ray_track

        stream = (Recorded(todo[b], rec) for b, rec in ray_track(
            [sources[i].path for i in todo], [names[i] for i in todo], args.impl, params, device, args.fov,
            args.topic, skip={b: done.get(names[i], set()) for b, i in enumerate(todo)},
            batch_size=args.batch_size, address=args.address, camera=camera))
    else:
        from torchrow.engines.runner import track

        stream = (Tracked(todo[b], res, rgb) for b, res, rgb in track(
            [sources[i] for i in todo], [names[i] for i in todo], args.impl, params, args.batch_size, device,
            args.fov, onnx=onnx, camera=camera))
    counts: dict[str, int] = {}
    total = sum(sources[i].length for i in todo)
    bar = progress(total, "video", enabled=not args.quiet, unit="frame")
    try:
        with sink, (fox or contextlib.nullcontext()):
            for item in stream:
                bar.update(1)
                if isinstance(item, Recorded):
                    rec = item.record
                else:
                    i, res, rgb = item
                    if (names[i], res.frame) in sink:
                        ann.count(i, res)  # not drawn again, but its row change counts for the next ones
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
    hint = setting_hint(params, counts)
    if hint:
        print(hint, file=sys.stderr)
    if plot is None:
        return 0
    # the plot and the summary read the records back from --out (the run itself keeps none)
    by_source: dict[str, list[dict]] = {nm: [] for nm in names}
    for rec in read_records(out):
        rec.pop("hough", None)
        rec.pop("outliers", None)
        by_source.setdefault(str(rec.get("source")), []).append(rec)
    for recs in by_source.values():
        recs.sort(key=lambda r: r["frame"])
    plot_tracks(by_source, plot)
    for src, recs in by_source.items():
        jumps = central_jumps(recs)
        hough = sum(1 for r in recs if r.get("hough_ran"))

        def worst(key: str, jumps: dict[str, list[float]] = jumps) -> str:
            return f"{max(jumps[key]):.1f} px" if jumps[key] else "n/a"

        if params.mode == "improved":  # the lattice tracker (ALGORITHM.md 11.7): hough_ran = the full search ran
            print(f"  {src}: full search on {hough} of {len(recs)} frames; "
                  f"{sum(1 for r in recs if r.get('row_change'))} row change(s); {moves_line(row_moves(recs))}",
                  file=sys.stderr)
            continue
        print(f"  {src}: Hough on {hough} of {len(recs)} frames; largest move of the central row at the "
              f"bottom: {worst('tracked')} into a tracked frame, {worst('hough')} into a Hough frame",
              file=sys.stderr)
    return 0
