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

import bisect
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchrow.core.io import ImageError, decode_image, header_size, majority_working_size, resize_to_width, to_rgb8, working_size

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
    With ``width`` set, ``max_pixels`` (``Params.max_pixels``) bounds the working size as for an
    image file, checked on the message's own sizes (``height`` and ``width`` of an ``Image``, the
    encoded image's header for a ``CompressedImage``) before anything is decoded or resized.
    """

    stamp_ns: int | None
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
    max_pixels: int | None = None

    def __call__(self) -> np.ndarray:
        if self.compressed:
            return decode_image(self.data, self.width, self.max_pixels, what=self.what)
        w0, h0 = self._raw_size()
        if self.width is not None:
            working_size(w0, h0, self.width, self.max_pixels)
        rgb = self._raw()
        return resize_to_width(rgb, self.width, self.max_pixels) if self.width is not None else rgb

    def size(self) -> tuple[int, int] | None:
        """``(W0, H0)`` of the frame as decoded, from the message without decoding it; ``None``
        for a ``CompressedImage`` whose header Pillow cannot read.

        Raises :class:`ImageError` for an ``Image`` that cannot be decoded (encoding, sizes)."""
        return header_size(self.data, self.what) if self.compressed else self._raw_size()

    def _raw_size(self) -> tuple[int, int]:
        enc = self.encoding.lower()
        if enc not in ENCODINGS:
            raise ImageError(f"{self.what}: unsupported Image encoding {self.encoding!r} "
                             f"(supported: {', '.join(ENCODINGS)})")
        ch, size = ENCODINGS[enc]
        h, w, step = self.height, self.width_px, self.step
        row = w * ch * size
        if h < 1 or w < 1 or step < row or len(self.data) < h * step:
            raise ImageError(f"{self.what}: Image of {w}x{h} {enc} with step {step} needs {h * step} bytes "
                             f"(step >= {row}), got {len(self.data)}")
        return w, h

    def _raw(self) -> np.ndarray:
        self._raw_size()  # the encoding and sizes are usable
        enc = self.encoding.lower()
        ch, size = ENCODINGS[enc]
        h, w, step = self.height, self.width_px, self.step
        row = w * ch * size
        buf = np.frombuffer(self.data, dtype=np.uint8)
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
    by the frame number, ``length`` is the topic's message count by the bag's index (by its
    metadata where it has no usable index: then a hint for progress bars, nothing is sized by it)."""

    path: Path
    topic: str
    length: int
    msgtype: str
    kind: str = "rosbag"
    files: list[Path] = field(default_factory=list)
    _sizes: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def name(self) -> str:
        return str(self.path)

    def frames(self, width: int | None = None, max_pixels: int | None = None) -> Iterator[BagFrame]:
        """The topic's messages as :class:`BagFrame` (decoded to ``width``, bounded by
        ``max_pixels``, when called), ``frame`` numbering the messages in log-time order.

        A damaged bag loses only its damaged messages: a message that cannot be read is a
        frame that raises :class:`ImageError` when called, with the message's own index, and
        reading goes on after it where the bag's index (ROS 1 index records, the MCAP
        message indexes, the rosbag2 sqlite3 timestamp index) gives the log times of the
        messages: reading restarts at the next message's log time, and a message the index
        lists but the data lacks is such a frame too. Without a usable index, reading stops
        at the damage. Nothing here raises after the bag has opened."""
        reader, _ = _open(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == self.topic]
            times = _index_times(reader, conns)
            n = len(times) if times is not None else 0
            i, start, skip = 0, None, 0
            while True:
                try:
                    for conn, t, raw in reader.messages(connections=conns, start=start):
                        if skip:  # read again after a restart at a log time shared with handled messages
                            skip -= 1
                            continue
                        while i < n and times[i] < t:  # type: ignore[index]
                            yield _Broken(self._what(i), "message listed in the bag's index is missing from its "
                                                         "data (damaged bag)", i, width)
                            i += 1
                        yield _frame(reader, conn, raw, self._what(i), i, width, max_pixels)
                        i += 1
                    break
                except Exception as exc:  # damage the reader cannot pass: this message, then go on
                    more = i + 1 < n
                    how = "" if more else "; the rest of the bag cannot be read"
                    yield _Broken(self._what(i), f"cannot read message ({type(exc).__name__}: {exc}){how}", i, width)
                    i += 1
                    if not more:
                        return
                    start = int(times[i])  # type: ignore[index]
                    skip = i - bisect.bisect_left(times, start)  # type: ignore[arg-type]
            for j in range(i, n):
                yield _Broken(self._what(j), "message listed in the bag's index is missing from its data "
                                             "(damaged bag)", j, width)
        finally:
            try:
                reader.close()
            except Exception:  # a damaged bag may fail to close; its frames are out already
                pass

    def _what(self, i: int) -> str:
        return f"{self.path.name}:{self.topic}#{i}"

    def __iter__(self) -> Iterator[tuple[str, BagFrame]]:
        for f in self.frames():
            yield f"{f.frame:06d}", f

    def working_size(self, width: int, max_pixels: int | None = None) -> tuple[int, int] | None:
        """The sequence's working ``(H, W)``: the one most of its frames have (ties: the
        earliest), as :meth:`torchrow.core.frames.FrameSource.working_size` for a folder, so an
        odd first frame cannot make every other frame an error. Sizes come from the messages
        (an ``Image``'s fields, a ``CompressedImage``'s header; decoded only where the header
        cannot be read); ``None`` if no frame is readable. Read once per ``(width, max_pixels)``."""
        key = (width, max_pixels)
        if key not in self._sizes:
            self._sizes[key] = majority_working_size(((f.size, f) for f in self.frames()), width, max_pixels)
        return self._sizes[key]


def _frame(reader: Any, conn: Any, raw: bytes, what: str, i: int, width: int | None,
           max_pixels: int | None) -> BagFrame:
    """The :class:`BagFrame` of one raw message (a :class:`_Broken` one if it does not deserialize)."""
    try:
        msg = reader.deserialize(raw, conn.msgtype)
        stamp = int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
        if _msgtype(conn.msgtype).endswith("CompressedImage"):
            return BagFrame(stamp, i, what, True, bytes(msg.data), width=width, max_pixels=max_pixels)
        return BagFrame(stamp, i, what, False, bytes(msg.data), msg.encoding, int(msg.height), int(msg.width),
                        int(msg.step), bool(msg.is_bigendian), width, max_pixels)
    except Exception as exc:  # a corrupt message is an error record, not a crash
        return _Broken(what, f"cannot deserialize message: {exc}", i, width)


def _index_times(reader: Any, conns: list) -> np.ndarray | None:
    """``int64`` log times of the messages of ``conns``, in the order the reader yields them,
    from the bag's index without reading the messages' data; ``None`` where the bag has no
    usable index (an unindexed MCAP file, a damaged index) or the times are not in order."""
    try:
        (r,) = reader.readers
        ids = {c.id for c in conns}
        if hasattr(r, "indexes"):  # ROS 1: index records read at open
            parts = [np.array(sorted(e.time for cid in ids for e in r.indexes[cid]), np.int64)]
        else:
            parts = []
            topics = {c.topic for c in conns}
            for st in getattr(r.storage, "storages", [r.storage]):
                sids = [c.id for c in st.connections if c.topic in topics]
                if hasattr(st, "dbconn"):  # sqlite3: the timestamp index, not the data pages
                    q = (f"SELECT timestamp FROM messages WHERE topic_id IN ({','.join('?' * len(sids))}) "
                         "ORDER BY timestamp")
                    parts.append(np.array([t for (t,) in st.dbconn.execute(q, sids)], np.int64))
                elif getattr(st, "chunks", None):  # MCAP: the message index records after each chunk
                    parts.append(np.sort(np.concatenate([np.zeros(0, np.int64)] + [
                        _mcap_index(st.bio, off, cid) for ch in st.chunks
                        for cid, off in ch.message_index_offsets.items() if cid in sids])))
                else:
                    return None
        times = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        return times if bool(np.all(times[1:] >= times[:-1])) else None
    except Exception:  # an index that cannot be read: reading stops at the first damage
        return None


def _mcap_index(bio: Any, offset: int, channel: int) -> np.ndarray:
    """Log times of one MCAP Message Index record (opcode 0x07: channel id, then
    ``(log_time, offset)`` uint64 pairs behind a uint32 byte length)."""
    bio.seek(offset)
    head = bio.read(15)
    if len(head) != 15 or head[0] != 0x07 or int.from_bytes(head[9:11], "little") != channel:
        raise ValueError(f"no MCAP message index of channel {channel} at offset {offset}")
    size = int.from_bytes(head[11:15], "little")
    if size % 16 or size != int.from_bytes(head[1:9], "little") - 6:
        raise ValueError(f"damaged MCAP message index at offset {offset}")
    data = bio.read(size)
    if len(data) != size:
        raise ValueError(f"truncated MCAP message index at offset {offset}")
    return np.frombuffer(data, "<u8").reshape(-1, 2)[:, 0].astype(np.int64)


class _Broken(BagFrame):
    """A message that could not be read or deserialized: calling it raises."""

    def __init__(self, what: str, why: str, frame: int, width: int | None = None) -> None:
        super().__init__(None, frame, what, True, b"", width=width)
        self.why = why

    def __call__(self) -> np.ndarray:
        raise ImageError(f"{self.what}: {self.why}")

    def size(self) -> tuple[int, int] | None:
        raise ImageError(f"{self.what}: {self.why}")


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
        # a topic's type from its connections: one topic may carry both Image and CompressedImage
        # (each message is decoded by its own connection's type); any other type makes it no image topic
        kinds = {t: sorted({_msgtype(c.msgtype or "") for c in info.connections}) for t, info in topics.items()}
        images = {t: "+".join(k) for t, k in kinds.items() if k and set(k) <= set(IMAGE_TYPES)}
        counts = {t: topics[t].msgcount for t in images}

        def label(t: str) -> str:
            return "+".join(k.rsplit("/", 1)[1] for k in images[t].split("+"))

        listing = ", ".join(f"{t} ({label(t)}, {counts[t]} messages)" for t in sorted(images)) or "none"
        if topic is not None:
            if topic not in images:
                raise BagError(f"topic {topic!r} is not an image topic of {p}; image topics: {listing}")
        elif len(images) != 1:
            how = "no image topic" if not images else "several image topics; choose one with --topic"
            raise BagError(f"ROS bag {p} has {how} (sensor_msgs/Image or CompressedImage): {listing}")
        else:
            topic = next(iter(images))
        # the count by the bag's index where it has one: a rosbag2 metadata.yaml may state anything
        times = _index_times(reader, [c for c in reader.connections if c.topic == topic])
        length = len(times) if times is not None else int(counts[topic])
    finally:
        reader.close()
    return BagSource(p, topic, length, images[topic])
