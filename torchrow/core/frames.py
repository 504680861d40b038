"""Frame sources for video mode: folders of frames, video files, and the frame-item format.

A *sequence* handed to a tracker's ``track``/``track_iter`` is any iterable of *items*. An
item is a frame or ``(name, frame)``; a frame is an ``(H, W, 3)`` uint8 RGB array, a
callable returning one (it may raise :class:`~torchrow.core.io.ImageError` or ``OSError``), or
``None`` (unreadable). Unreadable frames become ``error`` records and the tracker skips them.
"""

from __future__ import annotations

import contextlib
import functools
import os
import queue
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchrow.core.io import (
    IMAGE_EXTENSIONS,
    ImageError,
    header_size,
    load_image,
    majority_working_size,
    resize_to_width,
    to_rgb8,
)

__all__ = ["prepare_frame", "LoadedFrame", "load_item", "load_items", "READ_AHEAD", "VIDEO_EXTENSIONS", "FrameSource",
           "open_source", "display_name", "cv2_name"]

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")


def display_name(name: str) -> str:
    """``name`` for text that is drawn or encoded (plot titles): a file name that is not valid
    UTF-8 (undecodable bytes kept as surrogates, as Python keeps them) with each such byte as
    U+FFFD."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


@contextlib.contextmanager
def cv2_name(path: str | Path, create: bool = False) -> Iterator[str]:
    """A name of ``path`` that OpenCV can open: the path itself, or, for a name that is not
    valid UTF-8 (OpenCV crashes the process on one), a symbolic link to it in a temporary
    folder, kept while the block runs. ``create``: make the file first (a writer's target), so
    the link is not dangling."""
    name = str(path)
    if display_name(name) == name:
        yield name
        return
    suffix = Path(path).suffix
    if create:
        Path(path).touch()
    with tempfile.TemporaryDirectory(prefix="torchrow-") as tmp:
        link = os.path.join(tmp, "file" + (suffix if display_name(suffix) == suffix else ""))
        os.symlink(os.path.abspath(path), link)
        yield link


@dataclass
class LoadedFrame:
    """One item after loading: working-size RGB or the reason it is missing."""

    name: str | None
    rgb: np.ndarray | None
    error: str | None = None


def prepare_frame(frame: np.ndarray | str | Path, width: int, max_pixels: int | None = None) -> np.ndarray:
    """A frame at working size: a path is loaded (:func:`~torchrow.core.io.load_image`), an
    array converted to RGB8; either resized to ``width`` (within ``max_pixels``)."""
    if isinstance(frame, (str, Path)):
        return load_image(frame, width, max_pixels)
    return resize_to_width(to_rgb8(frame), width, max_pixels)


def load_item(item: object, width: int, max_pixels: int | None = None) -> LoadedFrame:
    """Load and resize one sequence item (module docstring) to the working ``width``.

    A frame whose working size exceeds ``max_pixels`` (``Params.max_pixels``) is unreadable.
    """
    name = None
    if isinstance(item, tuple) and len(item) == 2 and (item[0] is None or isinstance(item[0], str)):
        name, item = item
    try:
        if item is None:
            return LoadedFrame(name, None, "unreadable frame")
        frame = item() if callable(item) else item
        if not isinstance(frame, np.ndarray):
            raise ImageError(f"expected a numpy array (H, W, 3), got {type(frame).__name__}")
        return LoadedFrame(name, resize_to_width(to_rgb8(frame), width, max_pixels))
    except (ImageError, OSError) as exc:
        return LoadedFrame(name, None, str(exc))


#: Items :func:`load_items` decodes ahead of the tracker by default (about 0.4 MB each at 500 px).
READ_AHEAD = 8

_END = object()


def load_items(items: Iterable[object], width: int, max_pixels: int | None = None,
               ahead: int = READ_AHEAD) -> Iterator[LoadedFrame]:
    """:func:`load_item` of every item, in order, decoded up to ``ahead`` items in advance.

    Decoding and resizing a 1280x720 JPEG takes about 11 ms here (8.6 decode, 2.9 resize), a
    quarter of a tracked frame; OpenCV, Pillow and PyAV release the GIL while they decode,
    so a reader thread does it while the tracker works on the frames before. ``ahead=0``
    reads in the calling thread. Only the reader thread pulls from ``items``, one item at a
    time and in order (a live generator is read ahead by at most ``ahead + 1`` items). An
    exception other than the unreadable-frame ones :func:`load_item` turns into records is
    raised here, at its item's place. Closing the iterator (or dropping it) stops the reader.
    """
    if ahead <= 0:
        for item in items:
            yield load_item(item, width, max_pixels)
        return
    out: queue.Queue = queue.Queue(ahead)
    stop = threading.Event()

    def put(x: object) -> bool:
        while not stop.is_set():
            try:
                out.put(x, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def read() -> None:
        try:
            for item in items:
                if not put(load_item(item, width, max_pixels)):
                    return
        except BaseException as exc:  # handed to the consumer, raised at this item's place
            put(exc)
            return
        put(_END)

    reader = threading.Thread(target=read, name="torchrow-read-ahead", daemon=True)
    reader.start()
    try:
        while True:
            got = out.get()
            if got is _END:
                return
            if isinstance(got, BaseException):
                raise got
            yield got
    finally:
        stop.set()
        reader.join()


@dataclass
class FrameSource:
    """A named sequence of frame items: a folder of images (sorted by name) or a video file.

    Iterating yields ``(name, loader)`` items; ``length`` is the number of frames (a video's
    frame count as its container reports it, which may be approximate).
    """

    path: Path
    kind: str  # "folder" or "video"
    files: list[Path]
    length: int
    fps: float | None = None  # frames per second as the container reports it (None: a folder)

    @property
    def name(self) -> str:
        return str(self.path)

    def __iter__(self) -> Iterator[tuple[str, Callable[[], np.ndarray]]]:
        """Items of every frame. A video is read to its real end: a frame that does not
        decode (OpenCV goes on with the next one) is an item that raises :class:`ImageError`,
        and reading stops only after the container's frame count (``length``) when a read
        fails; with an unknown count (0), at the first failed read."""
        if self.kind == "folder":
            for f in self.files:
                yield f.name, functools.partial(load_image, f)
            return
        import cv2

        def unreadable(i: int) -> Callable[[], np.ndarray]:
            def fail() -> np.ndarray:
                raise ImageError(f"frame {i} of {self.path} cannot be decoded")
            return fail

        with cv2_name(self.path) as cv_name:
            cap = cv2.VideoCapture(cv_name)
            try:
                i = 0
                while True:
                    ok, bgr = cap.read()
                    if not ok:
                        if i >= self.length:
                            break
                        yield f"{i:06d}", unreadable(i)
                    else:
                        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                        yield f"{i:06d}", functools.partial(np.asarray, rgb)
                    i += 1
            finally:
                cap.release()

    def working_size(self, width: int, max_pixels: int | None = None) -> tuple[int, int] | None:
        """The sequence's working ``(H, W)``: the one most of its frames have (ties: the
        earliest), so one odd frame, even frame 0, cannot make every other frame an error.

        Folders: from the files' headers (Pillow, EXIF rotation applied), decoding only the
        files whose header cannot be read; videos: the first readable frame (all frames of a
        video have one size). ``None`` if no frame is readable.
        """
        if self.kind == "folder":
            return majority_working_size(
                ((functools.partial(header_size, f), functools.partial(load_image, f)) for f in self.files), width, max_pixels)
        for item in self:
            got = load_item(item, width, max_pixels)
            if got.rgb is not None:
                return got.rgb.shape[:2]
        return None


def open_source(path: str | Path, topic: str | None = None):
    """A folder holding image files, a video file readable by OpenCV, or a ROS bag
    (:func:`torchrow.core.rosbag.open_bag`: a rosbag2 folder or a ROS 1 ``.bag``; ``topic``
    chooses its image topic, by default the only one).

    Raises
    ------
    FileNotFoundError
        If the path does not exist.
    ImageError
        If a folder holds no images or a video cannot be opened (a bag:
        :class:`torchrow.core.rosbag.BagError`, a subclass).
    """
    from torchrow.core.rosbag import is_bag, open_bag

    p = Path(path)
    if is_bag(p):
        return open_bag(p, topic)
    if p.is_dir():
        files = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_EXTENSIONS)
        if not files:
            raise ImageError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in folder {p}")
        return FrameSource(p, "folder", files, len(files))
    if not p.exists():
        raise FileNotFoundError(f"no such file or folder: {p}")
    import cv2

    with cv2_name(p) as cv_name:
        cap = cv2.VideoCapture(cv_name)
        try:
            if not cap.isOpened():
                raise ImageError(f"cannot open video: {p}")
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        finally:
            cap.release()
    return FrameSource(p, "video", [], max(n, 0), fps if 0 < fps < 1000 else None)
