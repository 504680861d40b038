"""ROS bags as frame sources: rosbag2 folders (sqlite3 or MCAP) and ROS 1 ``.bag`` files.

Read with the pure-Python ``rosbags`` library (``pip install 'torchrow[ros]'``; no ROS
installation needed). One image topic of a bag is one sequence of frames, in the bag's
message order (log time):

* ``sensor_msgs/Image`` with encoding ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8`` or
  ``mono16`` (rows may be padded: ``step`` is honoured; ``is_bigendian`` for ``mono16``),
  converted by :func:`torchrow.core.io.to_rgb8` (alpha dropped, grey replicated, 16-bit
  ``(v + 128) // 257``); any other encoding makes that frame an ``error`` record;
* ``sensor_msgs/CompressedImage`` whose data OpenCV decodes (``jpeg``, ``png``), decoded as
  :func:`torchrow.core.io.load_image` decodes a file, so a bag of a folder's JPEG files gives
  the folder's pixels exactly.

Each frame carries the message's header stamp, ``stamp_ns = sec * 10**9 + nanosec``, which
the command line writes into its record beside ``frame``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchrow.core.io import ImageError, decode_image, resize_to_width, to_rgb8

__all__ = ["BagError", "BagFrame", "BagSource", "ENCODINGS", "IMAGE_TYPES", "is_bag", "open_bag"]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")

#: ``sensor_msgs/Image`` encodings read: channels, bytes per channel.
ENCODINGS = {"rgb8": (3, 1), "bgr8": (3, 1), "rgba8": (4, 1), "bgra8": (4, 1), "mono8": (1, 1), "mono16": (1, 2)}


class BagError(ImageError):
    """A bag that cannot be used as a source (unreadable, no or several image topics, ...)."""


def is_bag(path: str | Path) -> bool:
    """A rosbag2 folder (holding ``metadata.yaml``) or a ROS 1 ``.bag`` file."""
    p = Path(path)
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or (p.is_file() and p.suffix.lower() == ".bag")


def _msgtype(name: str) -> str:
    """``sensor_msgs/Image`` (ROS 1 spelling) -> ``sensor_msgs/msg/Image``."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


@dataclass
class BagFrame:
    """One image message, decoded on call: ``uint8 (H, W, 3)`` RGB (resized to ``width`` if set).

    Holds the message's bytes only, so it pickles small (the Ray engine ships it to workers).
    """

    stamp_ns: int
    frame: int
    what: str
    compressed: bool
    data: bytes
    encoding: str = ""
    height: int = 0
    width_px: int = 0
    step: int = 0
    bigendian: bool = False
    width: int | None = None

    def __call__(self) -> np.ndarray:
        rgb = decode_image(self.data, what=self.what) if self.compressed else self._raw()
        return resize_to_width(rgb, self.width) if self.width is not None else rgb

    def _raw(self) -> np.ndarray:
        enc = self.encoding.lower()
        if enc not in ENCODINGS:
            raise ImageError(f"{self.what}: unsupported Image encoding {self.encoding!r} "
                             f"(supported: {', '.join(ENCODINGS)})")
        ch, size = ENCODINGS[enc]
        h, w, step = self.height, self.width_px, self.step
        row = w * ch * size
        buf = np.frombuffer(self.data, dtype=np.uint8)
        if h < 1 or w < 1 or step < row or buf.size < h * step:
            raise ImageError(f"{self.what}: Image of {w}x{h} {enc} with step {step} needs {h * step} bytes "
                             f"(step >= {row}), got {buf.size}")
        a = buf[:h * step].reshape(h, step)[:, :row]
        if size == 2:
            a = np.ascontiguousarray(a).view(">u2" if self.bigendian else "<u2").astype(np.uint16)
        a = a.reshape(h, w, ch) if ch > 1 else a.reshape(h, w)
        if enc == "bgr8":
            a = a[:, :, ::-1]
        elif enc == "bgra8":
            a = a[:, :, [2, 1, 0, 3]]
        return to_rgb8(a)


@dataclass
class BagSource:
    """One image topic of a bag as a frame source (the interface of
    :class:`torchrow.core.frames.FrameSource`): iterating yields ``(name, BagFrame)`` items named
    by the frame number, ``length`` is the topic's message count."""

    path: Path
    topic: str
    length: int
    msgtype: str
    kind: str = "rosbag"
    files: list[Path] = field(default_factory=list)

    @property
    def name(self) -> str:
        return str(self.path)

    def frames(self, width: int | None = None) -> Iterator[BagFrame]:
        """The topic's messages as :class:`BagFrame` (decoded to ``width`` when called)."""
        reader, _ = _open(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for i, (conn, _t, raw) in enumerate(reader.messages(connections=conns)):
                what = f"{self.path.name}:{self.topic}#{i}"
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:  # a corrupt message is an error record, not a crash
                    yield _Broken(what, str(exc), i, width)
                    continue
                stamp = int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
                if _msgtype(conn.msgtype).endswith("CompressedImage"):
                    yield BagFrame(stamp, i, what, True, bytes(msg.data), width=width)
                else:
                    yield BagFrame(stamp, i, what, False, bytes(msg.data), msg.encoding, int(msg.height),
                                   int(msg.width), int(msg.step), bool(msg.is_bigendian), width)
        finally:
            reader.close()

    def __iter__(self) -> Iterator[tuple[str, BagFrame]]:
        for f in self.frames():
            yield f"{f.frame:06d}", f


class _Broken(BagFrame):
    """A message that could not be deserialized: calling it raises."""

    def __init__(self, what: str, why: str, frame: int, width: int | None = None) -> None:
        super().__init__(0, frame, what, True, b"", width=width)
        self.why = why

    def __call__(self) -> np.ndarray:
        raise ImageError(f"{self.what}: cannot deserialize message: {self.why}")


def _open(path: Path):
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise BagError("ROS bags need the rosbags package: pip install 'torchrow[ros]'") from None
    try:
        # bags without embedded message definitions (old rosbag2) fall back to ROS 2 Humble's
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:
        raise BagError(f"cannot read ROS bag {path}: {exc}") from None
    return reader, reader.topics


def open_bag(path: str | Path, topic: str | None = None) -> BagSource:
    """The image topic ``topic`` of a bag, or its only image topic.

    Raises
    ------
    BagError
        If the bag cannot be read, ``topic`` is not one of its image topics, or ``topic`` is
        None and the bag has no or several image topics (the message lists them).
    """
    p = Path(path)
    reader, topics = _open(p)
    try:
        images = {t: _msgtype(info.msgtype or "") for t, info in topics.items()
                  if _msgtype(info.msgtype or "") in IMAGE_TYPES}
        counts = {t: topics[t].msgcount for t in images}
    finally:
        reader.close()
    listing = ", ".join(f"{t} ({images[t].rsplit('/', 1)[1]}, {counts[t]} messages)" for t in sorted(images)) or "none"
    if topic is not None:
        if topic not in images:
            raise BagError(f"topic {topic!r} is not an image topic of {p}; image topics: {listing}")
    elif len(images) != 1:
        how = "no image topic" if not images else "several image topics; choose one with --topic"
        raise BagError(f"ROS bag {p} has {how} (sensor_msgs/Image or CompressedImage): {listing}")
    else:
        topic = next(iter(images))
    return BagSource(p, topic, int(counts[topic]), images[topic])
