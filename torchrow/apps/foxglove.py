"""Foxglove outputs of ``detect`` and ``video``: an MCAP recording (``--mcap``) and a live
WebSocket view (``--serve``), built on the Foxglove SDK (``pip install 'torchrow[foxglove]'``).

Every frame of a sequence is published on three channels (topics under ``/torchrow``, or
``/torchrow/<source>`` when a run has several sequences):

* ``.../image``: ``foxglove.CompressedImage``, the source frame. A JPEG file or a bag's
  ``CompressedImage`` holding a JPEG is passed through byte for byte (original size);
  anything else (PNG files, raw ``Image`` messages, video files) is the working image encoded
  once as JPEG (quality :data:`JPEG_QUALITY`).
* ``.../annotations``: ``foxglove.ImageAnnotations`` in the published image's pixels: each row
  with finite ``a``, ``b`` as a line strip (the curve sampled at :data:`POLYLINE_POINTS`
  working-image rows from :func:`torchrow.apps.annotate.row_top` to ``H - 1``), labelled at
  its foot with its index (and its confidence in improved mode, its reason when invalid), the
  vanishing point as a circle, the horizon as a line on the top edge of row ``sky``, and a
  status line; colours as in the PNG pictures (:mod:`torchrow.apps.annotate`).
* ``.../signals``: JSON with the schema :data:`SIGNALS_SCHEMA` (``torchrow.RowSignals``), the
  record's status, confidence and steering signals, for the Plot panel.

Coordinates. Records are in working-image pixels with ``x`` = column and pixel centres on
integers; Foxglove's image coordinates put the origin at the top-left *corner* of the
top-left pixel. A working point ``(x, y)`` is published at ``((x + 0.5) * sx, (y + 0.5) * sy)``
with ``sx = W_pub / W``, ``sy = H_pub / H`` (1 for an encoded working image), which is also
how ``cv2.INTER_AREA`` maps the working image onto the original. Each annotation message
states the mapping in its ``metadata``: ``scale_x``, ``scale_y``, ``y_top``, ``y_bottom``,
``samples`` (the rows are ``numpy.linspace(y_top, y_bottom, samples)``).

Time. A frame's log time (and the ``timestamp`` of its messages) is its bag message's header
stamp where the source is a ROS bag, else ``round(index * 1e9 / fps)``; the caller writes the
same value into the record as ``stamp_ns``.

Streaming. The MCAP is written in chunks of :data:`CHUNK_BYTES` as the run goes; a killed run
leaves every whole chunk readable (``mcap`` readers read a file without its summary by
streaming it; ``mcap recover`` rewrites one), the last partial chunk is lost.
"""

from __future__ import annotations

import math
import re
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from torchrow.apps.annotate import HORIZON, INVALID, VALID, VP_COLOR, row_top
from torchrow.core.io import header_size
from torchrow.core.results import ImageResult

__all__ = ["MISSING", "JPEG_QUALITY", "POLYLINE_POINTS", "CHUNK_BYTES", "SIGNALS_SCHEMA", "FoxgloveMissing",
           "FrameOrigins", "PublishedImage", "RecordedMessage", "Recorder", "Recording", "ServeAddress", "available",
           "frame_stamp", "image_annotations", "parse_serve", "published_image", "read_mcap", "signals",
           "topic_prefixes", "with_stamp"]

#: The one-line reason given when the SDK is not installed.
MISSING = "needs the Foxglove SDK: pip install 'torchrow[foxglove]'"
#: Quality of the JPEG written where a frame cannot be passed through.
JPEG_QUALITY = 90
#: Points of every row's line strip (curved rows need more than the two of a straight one).
POLYLINE_POINTS = 24
#: Target uncompressed size of an MCAP chunk: what a killed run can lose (about 5 Caterra JPEGs).
CHUNK_BYTES = 1 << 20
#: Once a first client subscribes, how long to wait for the rest of its subscriptions (the
#: Foxglove app subscribes panel by panel) before the first frame.
SETTLE_S = 0.5

_NUM = {"type": ["number", "null"]}

#: JSON schema of the signals channel. Keys a record lacks (``detect`` has no steering;
#: ``lateral_m``, ``spacing_m``, ``state``, ``row_end_m``, ``row_change`` need a camera model and
#: the state machine) are ``null``.
SIGNALS_SCHEMA: dict[str, Any] = {
    "title": "torchrow.RowSignals",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "source": {"type": ["string", "null"]},
        "frame": {"type": "integer", "description": "index of the frame in its sequence"},
        "name": {"type": ["string", "null"]},
        "status": {"type": "string", "description": "ok, invalid, no_vp, no_vegetation or error"},
        "valid_rows": {"type": "integer"},
        "n_rows": {"type": "integer"},
        "hough_ran": {"type": ["boolean", "null"]},
        "confidence": dict(_NUM, description="tracker confidence in [0, 1] (video)"),
        "image_confidence": dict(_NUM, description="improved mode: mean row confidence"),
        "heading_px": dict(_NUM, description="vp_x - W/2 (working px; + = rows head right)"),
        "lateral_px": dict(_NUM, description="central row's bottom x - W/2 (working px; + = row right of centre)"),
        "lateral_frac": dict(_NUM, description="lateral_px / local row spacing"),
        "heading_rad": dict(_NUM, description="yaw error (rad, REP 103: + = turn left); needs a field of view or camera model"),
        "lateral_m": dict(_NUM, description="lateral offset from the central row (m); needs a camera model"),
        "spacing_m": dict(_NUM, description="row spacing on the ground (m); needs a camera model"),
        "state": {"type": ["string", "null"], "description": "tracking state where the record carries one"},
        "row_end_m": dict(_NUM),
        "row_change": {"type": ["integer", "null"]},
    },
}
_FROM_RECORD = ("confidence", "image_confidence", "heading_px", "lateral_px", "lateral_frac", "heading_rad",
                "lateral_m", "spacing_m", "state", "row_end_m", "row_change", "hough_ran")

_JPEG_MAGIC = b"\xff\xd8\xff"


class FoxgloveMissing(ImportError):
    """The Foxglove SDK (``foxglove-sdk``) is not installed."""


def available() -> bool:
    """Whether the Foxglove SDK can be imported."""
    try:
        import foxglove  # noqa: F401
    except ImportError:
        return False
    return True


class ServeAddress(NamedTuple):
    """Where ``--serve`` listens (port 0: one the system picks)."""

    host: str
    port: int


def parse_serve(spec: str) -> ServeAddress:
    """``[HOST:]PORT`` (``[::1]:PORT`` for IPv6); the host defaults to 127.0.0.1 (this machine
    only). Raises ``ValueError`` with a one-line reason."""
    host, sep, port = spec.rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535 or (sep and not host):
        raise ValueError(f"--serve expects [HOST:]PORT with a port in 0..65535, got {spec!r}")
    return ServeAddress(host, int(port))


def topic_prefixes(labels: Sequence[str]) -> list[str]:
    """Topic prefix of each sequence: ``/torchrow`` for a run of one, else
    ``/torchrow/<label>`` (characters other than letters, digits and ``_`` become ``_``;
    a repeated label gets ``_<index>``)."""
    if len(labels) == 1:
        return ["/torchrow"]
    out: list[str] = []
    for i, label in enumerate(labels):
        name = re.sub(r"\W", "_", label, flags=re.ASCII) or f"source{i}"
        out.append(f"/torchrow/{name}" if f"/torchrow/{name}" not in out else f"/torchrow/{name}_{i}")
    return out


def frame_stamp(index: int, fps: float) -> int:
    """Log time (ns) of frame ``index`` of a sequence without stamps at ``fps`` frames per second."""
    return int(round(index * 1e9 / fps))


def with_stamp(rec: dict, stamp_ns: int) -> dict:
    """``rec`` with ``stamp_ns`` after ``frame`` (or ``name``) where it has none; a record that
    has one is returned as it is."""
    if "stamp_ns" in rec:
        return rec
    after = "frame" if "frame" in rec else "name"
    out: dict = {}
    for k, v in rec.items():
        out[k] = v
        if k == after:
            out["stamp_ns"] = stamp_ns
    if "stamp_ns" not in out:
        out["stamp_ns"] = stamp_ns
    return out


@dataclass(frozen=True)
class PublishedImage:
    """A frame as published: encoded bytes, their format and pixel size."""

    data: bytes
    format: str  # "jpeg"
    width: int
    height: int


def published_image(origin: object, rgb: np.ndarray | None, quality: int = JPEG_QUALITY) -> PublishedImage | None:
    """The image published for a frame.

    Parameters
    ----------
    origin : the frame's source where it has encoded bytes: a file ``Path``, or a
        :class:`torchrow.core.rosbag.BagFrame` (its ``data`` when ``compressed``); else ``None``.
    rgb : the working image ``uint8 (H, W, 3)``, or ``None`` for an unreadable frame.

    Returns
    -------
    JPEG bytes of ``origin`` unchanged (size from the header, EXIF orientation applied as
    torchrow decodes it) when they are a JPEG; else ``rgb`` encoded as JPEG; ``None`` when
    neither exists (an unreadable frame of a video file).
    """
    data: bytes | None = None
    if isinstance(origin, Path):
        try:
            with open(origin, "rb") as fh:  # only a JPEG is read whole (a PNG is re-encoded)
                data = fh.read(len(_JPEG_MAGIC))
                if data == _JPEG_MAGIC:
                    data += fh.read()
        except OSError:
            data = None
    elif getattr(origin, "compressed", False):
        data = getattr(origin, "data", None)
    if data is not None and data[:3] == _JPEG_MAGIC:
        try:
            size = header_size(data)
        except Exception:  # a header beyond the decode bound: not published as such
            size = None
        if size is not None:
            return PublishedImage(data, "jpeg", size[0], size[1])
    if rgb is None:
        return None
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        return None
    return PublishedImage(buf.tobytes(), "jpeg", int(rgb.shape[1]), int(rgb.shape[0]))


class FrameOrigins:
    """Where the frames of a video source keep their encoded bytes (the ``origin`` of
    :func:`published_image`): a folder's files, a bag's messages, nothing for a video file.

    A bag is read a second time, in step with the tracker: ``origins(j)`` for increasing ``j``
    (each sequence's records come in frame order) holds one message at a time.
    """

    def __init__(self, source) -> None:
        self.source = source
        self._frames: Iterator[Any] | None = None
        self._held: object = None
        self._index = -1

    def __call__(self, index: int) -> object:
        kind = getattr(self.source, "kind", None)
        if kind == "folder":
            files = self.source.files
            return files[index] if 0 <= index < len(files) else None
        if kind != "rosbag":
            return None
        if index < self._index or self._frames is None:
            self._frames = iter(self.source.frames())
            self._index, self._held = -1, None
        while self._index < index:
            got = next(self._frames, None)
            if got is None:
                return None
            self._held, self._index = got, got.frame
        return self._held if self._index == index else None


def _sdk():
    try:
        import foxglove
        import foxglove.messages as fm
    except ImportError:
        raise FoxgloveMissing(MISSING) from None
    return foxglove, fm


def _color(fm, rgb: tuple[int, int, int], alpha: float = 1.0):
    return fm.Color(r=rgb[0] / 255.0, g=rgb[1] / 255.0, b=rgb[2] / 255.0, a=alpha)


def _timestamp(fm, stamp_ns: int):
    return fm.Timestamp(stamp_ns // 10**9, stamp_ns % 10**9)


def image_annotations(rec: dict, image: PublishedImage | None, stamp_ns: int):
    """``foxglove.messages.ImageAnnotations`` of one record (module docstring), in the pixels
    of ``image`` (the working image's when ``None``)."""
    _, fm = _sdk()
    ts = _timestamp(fm, stamp_ns)
    res = ImageResult.from_record(rec)
    w, h = res.width, res.height
    sx = image.width / w if image is not None and w else 1.0
    sy = image.height / h if image is not None and h else 1.0
    y_top, y_bottom = (row_top(res, h), float(h - 1)) if h else (0.0, 0.0)
    ys = np.linspace(y_top, y_bottom, POLYLINE_POINTS)
    px = max(1.0, sy)  # strokes and fonts grow with the published image
    points, texts, circles = [], [], []
    valid = 0
    for i, row in enumerate(res.rows):
        valid += row.valid
        if not (math.isfinite(row.a) and math.isfinite(row.b)):
            continue
        xs = np.asarray(row.x_at(ys), dtype=np.float64)
        color = _color(fm, VALID if row.valid else INVALID)
        points.append(fm.PointsAnnotation(
            timestamp=ts, type=fm.PointsAnnotationType.LineStrip, outline_color=color, thickness=2.0 * px,
            points=[fm.Point2(x=float((x + 0.5) * sx), y=float((y + 0.5) * sy)) for x, y in zip(xs, ys)]))
        label = f"row {i}"
        if math.isfinite(row.confidence):
            label += f" {row.confidence:.2f}"
        if not row.valid:
            label += f" {row.reason}"
        foot = float(np.clip((xs[-1] + 0.5) * sx, 4 * px, w * sx - 60 * px))  # a foot outside: label at the border
        texts.append(fm.TextAnnotation(
            timestamp=ts, position=fm.Point2(x=foot, y=float(h * sy - 4 * px)), text=label,
            font_size=12.0 * px, text_color=color, background_color=fm.Color(r=0, g=0, b=0, a=0.6)))
    if res.sky > 0:
        points.append(fm.PointsAnnotation(
            timestamp=ts, type=fm.PointsAnnotationType.LineStrip, outline_color=_color(fm, HORIZON),
            thickness=2.0 * px, points=[fm.Point2(x=0.0, y=res.sky * sy), fm.Point2(x=w * sx, y=res.sky * sy)]))
    if res.vp is not None and all(math.isfinite(v) for v in res.vp):
        circles.append(fm.CircleAnnotation(
            timestamp=ts, position=fm.Point2(x=(res.vp[0] + 0.5) * sx, y=(res.vp[1] + 0.5) * sy),
            diameter=12.0 * px, thickness=2.0 * px, outline_color=_color(fm, VP_COLOR)))
    status = f"{res.status}  rows {valid}/{len(res.rows)}"
    if rec.get("confidence") is not None:
        status += f"  confidence {rec['confidence']:.2f}"
    if rec.get("hough_ran"):
        status += "  HOUGH"
    if res.error:
        status += f"  {res.error}"
    texts.append(fm.TextAnnotation(timestamp=ts, position=fm.Point2(x=4.0 * px, y=16.0 * px), text=status,
                                   font_size=12.0 * px, text_color=fm.Color(r=1, g=1, b=1, a=1),
                                   background_color=fm.Color(r=0, g=0, b=0, a=0.6)))
    meta = {"scale_x": repr(sx), "scale_y": repr(sy), "y_top": repr(float(y_top)), "y_bottom": repr(float(y_bottom)),
            "samples": str(POLYLINE_POINTS), "working_width": str(w), "working_height": str(h)}
    return fm.ImageAnnotations(timestamp=ts, circles=circles, points=points, texts=texts,
                               metadata=[fm.KeyValuePair(key=k, value=v) for k, v in meta.items()])


def signals(rec: dict, stamp_ns: int, frame: int) -> dict[str, Any]:
    """The signals message of one record (:data:`SIGNALS_SCHEMA`)."""
    rows = rec.get("rows") or []
    msg: dict[str, Any] = {
        "timestamp": {"sec": stamp_ns // 10**9, "nsec": stamp_ns % 10**9},
        "source": rec.get("source"), "frame": int(frame), "name": rec.get("name"), "status": rec.get("status"),
        "valid_rows": sum(1 for r in rows if r.get("valid")), "n_rows": len(rows)}
    msg.update({k: rec.get(k) for k in _FROM_RECORD})
    return msg


@dataclass(frozen=True)
class RecordedMessage:
    """One message of an MCAP file as :func:`read_mcap` returns it."""

    topic: str
    schema: str
    log_time: int
    data: bytes


@dataclass(frozen=True)
class Recording:
    """What :func:`read_mcap` finds: the messages in file order, and whether the file is whole."""

    messages: list[RecordedMessage]
    whole: bool


def read_mcap(path: str | Path) -> Recording:
    """The messages of an MCAP file in file order.

    A run killed while writing leaves the whole chunks and a torn last one (no summary):
    their messages come back with ``whole=False``. Uses the ``mcap`` reader as a stream, so
    it needs no summary section.
    """
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader

    out: list[RecordedMessage] = []
    with open(path, "rb") as fh:
        reader = NonSeekingReader(fh)
        try:
            for schema, channel, msg in reader.iter_messages(log_time_order=False):
                out.append(RecordedMessage(channel.topic, schema.name if schema else "", msg.log_time, msg.data))
        except (McapError, EOFError, ValueError):
            return Recording(out, False)
    return Recording(out, True)


class _Listener:
    """Counts the server's subscriptions (a ``foxglove.websocket.ServerListener``)."""

    def __init__(self) -> None:
        self.subscribed: set[int] = set()
        self.changed = threading.Event()

    def on_subscribe(self, client, channel) -> None:
        self.subscribed.add(channel.id)
        self.changed.set()

    def on_unsubscribe(self, client, channel) -> None:
        return None


class Recorder:
    """Publishes frames to an MCAP file and/or a Foxglove WebSocket server.

    Parameters
    ----------
    labels : one label per sequence (its topic prefix, :func:`topic_prefixes`).
    fps : frames per second of each sequence, for frames without a bag stamp.
    mcap : MCAP file to write (overwritten), or ``None``.
    serve : where the WebSocket server listens (:func:`parse_serve`), or ``None``. With a server, frames are
        paced at their log times (each sequence from its first frame) and the constructor
        waits up to ``serve_wait`` seconds for a first client.
    log : where the server's address and waiting notes go (stderr).

    Use as a context manager: on a normal exit the server keeps the last frame up for one
    frame period (at least 0.5 s, so queued messages reach the clients) before it stops; on
    an exception (Ctrl-C) it stops at once. The MCAP is closed (finished) either way.
    """

    def __init__(self, labels: Sequence[str], fps: Sequence[float], mcap: Path | None = None,
                 serve: ServeAddress | None = None, serve_wait: float = 10.0, log=None) -> None:
        foxglove, fm = _sdk()
        from foxglove.channels import CompressedImageChannel, ImageAnnotationsChannel
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self._fm = fm
        self._log = log if log is not None else (lambda s: print(s, file=sys.stderr, flush=True))
        self.fps = [float(f) for f in fps]
        self.prefixes = topic_prefixes(labels)
        self.labels = list(labels)
        self._ctx = foxglove.Context()
        self._writer: Any = None
        self._server: Any = None
        self._anchor: dict[int, tuple[float, int]] = {}
        self._period = 0.0
        self.published = 0
        if mcap is not None:
            # LZ4: the images are JPEG already; zstd would spend time for a few percent
            opts = MCAPWriteOptions(compression=MCAPCompression.Lz4, chunk_size=CHUNK_BYTES)
            self._writer = foxglove.open_mcap(str(mcap), allow_overwrite=True, context=self._ctx, writer_options=opts)
        self._channels = [(CompressedImageChannel(f"{p}/image", context=self._ctx),
                           ImageAnnotationsChannel(f"{p}/annotations", context=self._ctx),
                           foxglove.Channel(f"{p}/signals", schema=SIGNALS_SCHEMA, context=self._ctx))
                          for p in self.prefixes]
        if serve is not None:
            try:
                self._serve(foxglove, serve, serve_wait)
            except BaseException:
                self._close(linger=False)
                raise

    def _serve(self, foxglove, serve: ServeAddress, wait: float) -> None:
        listener = _Listener()
        try:
            self._server = foxglove.start_server(name="torchrow", host=serve[0], port=serve[1], context=self._ctx,
                                                 server_listener=listener)
        except Exception as exc:
            raise OSError(f"cannot serve on {serve[0]}:{serve[1]}: {exc}") from None
        host = f"[{serve[0]}]" if ":" in serve[0] else serve[0]
        self.url = f"ws://{host}:{self._server.port}"
        self._log(f"torchrow: Foxglove live view on {self.url} (Foxglove: Open connection > Foxglove WebSocket); "
                  f"waiting up to {wait:g} s for a client")
        n_channels = 3 * len(self._channels)
        deadline = time.monotonic() + wait
        first = None
        while True:
            listener.changed.clear()  # before looking: a subscription from now on ends the wait below
            now = time.monotonic()
            if len(listener.subscribed) >= n_channels or (first is not None and now >= first + SETTLE_S):
                return
            if now >= deadline:
                if first is None:
                    self._log(f"torchrow: no client after {wait:g} s; running without one")
                return
            limit = deadline if first is None else min(deadline, first + SETTLE_S)
            listener.changed.wait(max(0.0, limit - now))
            if first is None and listener.subscribed:
                first = time.monotonic()

    def frame(self, seq: int, index: int, rec: dict, rgb: np.ndarray | None = None, origin: object = None) -> dict:
        """Publish frame ``index`` of sequence ``seq`` (its record, working image and source, see
        :func:`published_image`); returns the record with ``stamp_ns`` (the log time) added
        where it had none."""
        fm = self._fm
        stamp = rec.get("stamp_ns")
        if stamp is None:
            stamp = frame_stamp(index, self.fps[seq])
        stamp = int(stamp)
        rec = with_stamp(rec, stamp)
        image = published_image(origin, rgb) if (origin is not None or rgb is not None) else None
        if self._server is not None:
            self._pace(seq, stamp)
        img_ch, ann_ch, sig_ch = self._channels[seq]
        if image is not None:
            img_ch.log(fm.CompressedImage(timestamp=_timestamp(fm, stamp), frame_id=self._frame_id(seq),
                                          data=image.data, format=image.format), log_time=stamp)
        ann_ch.log(image_annotations(rec, image, stamp), log_time=stamp)
        sig_ch.log(signals(rec, stamp, index), log_time=stamp)
        self.published += 1
        return rec

    def _frame_id(self, seq: int) -> str:
        return "camera" if len(self.prefixes) == 1 else self.prefixes[seq].rsplit("/", 1)[1]

    def _pace(self, seq: int, stamp: int) -> None:
        """Sleep until this frame's time: the sequence's first frame's wall time plus the log
        time since it (a tracker slower than the frame rate is never waited for)."""
        if seq not in self._anchor:
            self._anchor[seq] = (time.monotonic(), stamp)
        wall0, stamp0 = self._anchor[seq]
        delay = wall0 + (stamp - stamp0) / 1e9 - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self._period = 1.0 / self.fps[seq]

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._close(linger=exc_type is None)

    def close(self) -> None:
        self._close(linger=True)

    def _close(self, linger: bool) -> None:
        if self._server is not None:
            if linger:
                time.sleep(max(0.5, self._period))
            self._server.stop()
            self._server = None
        if self._writer is not None:
            self._writer.close()
            self._writer = None
