"""Frame sources for video mode: folders of frames, video files, and the frame-item format.

A *sequence* handed to a tracker's ``track``/``track_iter`` is any iterable of *items*. An
item is a frame or ``(name, frame)``; a frame is an ``(H, W, 3)`` uint8 RGB array, a
callable returning one (it may raise :class:`~torchrow.core.io.ImageError` or ``OSError``), or
``None`` (unreadable). Unreadable frames become ``error`` records and the tracker skips them.
"""

from __future__ import annotations

import contextlib
import os
import queue
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from torchrow.core.io import IMAGE_EXTENSIONS, ImageError, header_size, load_image, resize_to_width, to_rgb8, working_size

__all__ = ["LoadedFrame", "load_item", "load_items", "READ_AHEAD", "VIDEO_EXTENSIONS", "FrameSource", "open_source",
           "VideoWriter", "display_name"]

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")


def display_name(name: str) -> str:
    """``name`` for text that is drawn or encoded (plot titles): a file name that is not valid
    UTF-8 (undecodable bytes kept as surrogates, as Python keeps them) with each such byte as
    U+FFFD."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


@contextlib.contextmanager
def _cv2_name(path: str | Path, create: bool = False) -> Iterator[str]:
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
                yield f.name, (lambda f=f: load_image(f))
            return
        import cv2

        def unreadable(i: int) -> Callable[[], np.ndarray]:
            def fail() -> np.ndarray:
                raise ImageError(f"frame {i} of {self.path} cannot be decoded")
            return fail

        with _cv2_name(self.path) as cv_name:
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
                        yield f"{i:06d}", (lambda rgb=rgb: rgb)
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
        counts: dict[tuple[int, int], int] = {}
        if self.kind == "folder":
            for f in self.files:
                try:
                    size0 = header_size(f)
                    if size0 is None:
                        h0, w0 = load_image(f).shape[:2]
                    else:
                        w0, h0 = size0
                    w, h = working_size(w0, h0, width, max_pixels)
                except (ImageError, OSError):
                    continue
                counts[(h, w)] = counts.get((h, w), 0) + 1
        else:
            for item in self:
                got = load_item(item, width, max_pixels)
                if got.rgb is not None:
                    return got.rgb.shape[:2]
        return max(counts, key=lambda s: counts[s]) if counts else None  # first of the most common


def open_source(path: str | Path, topic: str | None = None):
    """A folder holding image files, a video file readable by OpenCV, or a ROS bag
    (:func:`torchrow.apps.rosbag.open_bag`: a rosbag2 folder or a ROS 1 ``.bag``; ``topic``
    chooses its image topic, by default the only one).

    Raises
    ------
    FileNotFoundError
        If the path does not exist.
    ImageError
        If a folder holds no images or a video cannot be opened (a bag:
        :class:`torchrow.apps.rosbag.BagError`, a subclass).
    """
    from torchrow.apps.rosbag import is_bag, open_bag

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

    with _cv2_name(p) as cv_name:
        cap = cv2.VideoCapture(cv_name)
        try:
            if not cap.isOpened():
                raise ImageError(f"cannot open video: {p}")
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        finally:
            cap.release()
    return FrameSource(p, "video", [], max(n, 0), fps if 0 < fps < 1000 else None)


class VideoWriter:
    """Writes RGB frames to a video file a browser plays: H.264 (``yuv420p``) through PyAV,
    whose wheels ship the encoder, for ``.mp4``/``.m4v``/``.mov``/``.mkv``; Motion-JPEG through
    OpenCV for ``.avi``.

    Frames are ``(H, W, 3)`` uint8 RGB, all of the size of the first; H.264 needs even sizes,
    so an odd height or width is padded with one black row or column.
    """

    H264 = (".mp4", ".m4v", ".mov", ".mkv")

    def __init__(self, path: str | Path, fps: float) -> None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.path = Path(path)
        self.fps = float(fps)
        self._h264 = self.path.suffix.lower() in self.H264
        self._out: Any = None  # av.OutputContainer or cv2.VideoWriter
        self._stream: Any = None
        self._name = contextlib.ExitStack()  # OpenCV's name of the file while it is written (_cv2_name)
        self._size: tuple[int, int] | None = None

    def _open(self, height: int, width: int) -> None:
        from fractions import Fraction

        if self._h264:
            import av

            self._out = av.open(str(self.path), "w")
            rate = Fraction(self.fps).limit_denominator(1001)
            stream = self._out.add_stream("libx264", rate=rate)
            stream.width, stream.height = width + width % 2, height + height % 2
            stream.pix_fmt = "yuv420p"
            stream.options = {"crf": "20", "preset": "veryfast"}
            self._stream = stream
        else:
            import cv2

            cv_name = self._name.enter_context(_cv2_name(self.path, create=True))
            vw = cv2.VideoWriter(cv_name, cv2.VideoWriter.fourcc(*"MJPG"), self.fps, (width, height))
            if not vw.isOpened():
                self._name.close()
                raise OSError(f"cannot write video {self.path}")
            self._out = vw
        self._size = (height, width)

    def write(self, rgb: np.ndarray) -> None:
        """Append one frame (``(H, W, 3)`` uint8 RGB, the size of the first frame)."""
        if self._size is None:
            self._open(*rgb.shape[:2])
        size = self._size
        assert size is not None
        if rgb.shape[:2] != size:
            raise ValueError(f"frame of size {rgb.shape[1]}x{rgb.shape[0]} in a video of {size[1]}x{size[0]}")
        if self._h264:
            import av

            h, w = rgb.shape[:2]
            if h % 2 or w % 2:
                rgb = np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)))
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
            for packet in self._stream.encode(frame):
                self._out.mux(packet)
        else:
            import cv2

            self._out.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))

    def close(self) -> None:
        """Flush and close the file (a writer that got no frame writes nothing)."""
        if self._out is None:
            return
        if self._h264:
            for packet in self._stream.encode():
                self._out.mux(packet)
            self._out.close()
        else:
            self._out.release()
            self._name.close()
        self._out = None


# ----------------------------------------------------------------------------------------
# summaries, pictures and plots of tracked sequences
# ----------------------------------------------------------------------------------------

def _bottoms(rec: dict) -> list[float | None]:
    """Bottom-row x of every row slot of a record (None for invalid rows)."""
    h = rec.get("height") or 0
    return [r["a"] * (h - 1) + r["b"] if r["valid"] and r["a"] is not None else None for r in rec.get("rows", [])]


def central_jumps(records: list[dict]) -> dict[str, list[float]]:
    """How far the central row moves between consecutive frames of one source (px).

    ``records`` are one source's records in frame order. For consecutive frames ``t-1, t``
    with valid rows, let ``c`` be the central row of frame ``t-1`` (valid row whose bottom x
    is nearest ``W/2``) and ``x`` its bottom x:

    * ``"tracked"``: frame ``t`` is tracked, so its row slot ``c`` is the continuation of
      that row; the jump is ``|x_c(t) - x|``.
    * ``"hough"``: frame ``t`` ran Hough (rows found afresh); the jump is the distance from
      ``x`` to the nearest valid row of frame ``t``.
    * ``"lateral"``: ``|lateral_px(t) - lateral_px(t-1)|``, which also counts a switch of the
      central row to its neighbour when the camera is about half a row spacing off.
    """
    out: dict[str, list[float]] = {"tracked": [], "hough": [], "lateral": []}
    for prev, cur in zip(records, records[1:]):
        if cur.get("frame") != prev.get("frame", -2) + 1:
            continue
        if prev.get("lateral_px") is not None and cur.get("lateral_px") is not None:
            out["lateral"].append(abs(cur["lateral_px"] - prev["lateral_px"]))
        pb, cb = _bottoms(prev), _bottoms(cur)
        valid_p = [(abs(x - prev["width"] / 2), i, x) for i, x in enumerate(pb) if x is not None]
        valid_c = [x for x in cb if x is not None]
        if not valid_p or not valid_c:
            continue
        _, c, x = min(valid_p)
        if not cur.get("hough_ran"):
            xc = cb[c] if c < len(cb) else None
            if xc is not None:
                out["tracked"].append(abs(xc - x))
        else:
            out["hough"].append(min(abs(v - x) for v in valid_c))
    return out


HOUGH_MARK = (255, 80, 0)
LATERAL = (255, 255, 0)


def draw_frame(rgb: np.ndarray, result, scale: int = 2) -> np.ndarray:
    """Annotated frame: :func:`torchrow.apps.annotate.draw_result` plus a Hough-frame marker, the
    steering signals as text (only those the frame has: ``heading_rad`` needs ``--fov``), the
    central row's bottom x with the lateral offset drawn as an arrow from the image centre, and
    a legend strip below. ``(H, W, 3)`` uint8 -> ``(scale*H + legend, scale*W, 3)``."""
    import cv2

    from torchrow.apps.annotate import draw_result, legend, legend_entries

    img = draw_result(rgb, result, scale, with_legend=False)
    h, w = img.shape[:2]
    font = cv2.FONT_HERSHEY_SIMPLEX

    def signal(label: str, parts: list[str]) -> str | None:
        return f"{label} {' / '.join(parts)}" if parts else None

    heading = [f"{v:+.{p}f}{u}" for v, u, p in ((result.heading_px, " px", 1), (result.heading_rad, " rad", 3))
               if v is not None]
    lateral = [f"{v:+.{p}f}{u}" for v, u, p in ((result.lateral_px, " px", 1), (result.lateral_frac, " rows", 2))
               if v is not None]
    lines = [f"frame {result.frame}  k {result.k}  confidence {result.confidence:.2f}",
             signal("heading", heading), signal("lateral offset", lateral)]
    y = 50  # below draw_result's status label
    for text in (t for t in lines if t):
        (tw, th), base = cv2.getTextSize(text, font, 0.5, 1)
        cv2.rectangle(img, (2, y - th - 3), (8 + tw, y + base), (0, 0, 0), -1)
        cv2.putText(img, text, (5, y), font, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        y += th + base + 6
    if result.hough_ran:
        label = "HOUGH (redo)" if result.hough_redo else "HOUGH"
        (tw, th), base = cv2.getTextSize(label, font, 0.6, 2)
        cv2.rectangle(img, (w - tw - 14, 2), (w - 2, th + base + 10), HOUGH_MARK, -1)
        cv2.putText(img, label, (w - tw - 8, th + 6), font, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
    cx = int(round(result.width / 2 * scale))
    cv2.line(img, (cx, h - 1), (cx, h - 25), (255, 255, 255), 1, cv2.LINE_AA)
    entries = legend_entries(result)
    if result.lateral_px is not None:
        xr = int(round((result.width / 2 + result.lateral_px) * scale))
        cv2.arrowedLine(img, (cx, h - 12), (xr, h - 12), LATERAL, 2, cv2.LINE_AA, tipLength=0.2)
        entries.append(("arrow", LATERAL, "lateral offset of the central row"))
    entries.append(("line", HOUGH_MARK, "HOUGH: Hough stage ran on this frame"))
    return np.concatenate([img, legend(w, entries)], 0)


def error_frame(width: int, height: int, text: str, scale: int = 2) -> np.ndarray:
    """A dark picture saying why a frame is missing (keeps an annotated video's timing)."""
    import cv2

    img = np.full((height * scale, width * scale, 3), 40, np.uint8)
    cv2.putText(img, text[:80], (8, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 90, 90), 1, cv2.LINE_AA)
    return img


def plot_tracks(records_by_source: dict[str, list[dict]], path: str | Path) -> None:
    """PNG: per source, the valid rows' bottom x over time (central row highlighted, Hough
    frames marked), then ``heading_px``, ``lateral_px`` and ``confidence`` over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(len(records_by_source), 1)
    fig, axes = plt.subplots(2 * n, 1, figsize=(9, 5.2 * n), squeeze=False)
    for i, (src, recs) in enumerate(records_by_source.items()):
        ax, ax2 = axes[2 * i, 0], axes[2 * i + 1, 0]
        fx, bx = [], []
        for r in recs:
            h = r.get("height") or 0
            for row in r.get("rows", []):
                if row["valid"] and row["a"] is not None:
                    fx.append(r["frame"])
                    bx.append(row["a"] * (h - 1) + row["b"])
        ax.scatter(fx, bx, s=6, c="tab:green", label="valid rows (x at bottom row)")
        cen = [(r["frame"], r["lateral_px"] + r["width"] / 2) for r in recs if r.get("lateral_px") is not None]
        if cen:
            ax.plot(*zip(*cen), c="tab:blue", lw=1.2, label="central row")
        hf = [r["frame"] for r in recs if r.get("hough_ran")]
        for j, f in enumerate(hf):
            ax.axvline(f, c="tab:orange", lw=0.6, alpha=0.6, label="Hough frame" if j == 0 else None)
        err = [r["frame"] for r in recs if r.get("status") == "error"]
        if err:
            ax.scatter(err, [0] * len(err), marker="x", c="red", label="unreadable frame")
        ax.set_title(f"{display_name(str(src))}: rows ({len(hf)} Hough frames of {len(recs)})", fontsize=9)
        ax.set_ylabel("x at bottom row (px)")
        ax.legend(fontsize=7, loc="upper right")
        for key, color in (("heading_px", "tab:purple"), ("lateral_px", "tab:blue")):
            pts = [(r["frame"], r[key]) for r in recs if r.get(key) is not None]
            if pts:
                ax2.plot(*zip(*pts), c=color, lw=1.2, label=key)
        ax2.axhline(0, c="k", lw=0.5)
        ax2.set_ylabel("px (image convention)")
        ax2.set_xlabel("frame")
        ax3 = ax2.twinx()
        conf = [(r["frame"], r["confidence"]) for r in recs if r.get("confidence") is not None and r["status"] != "error"]
        if conf:
            ax3.plot(*zip(*conf), c="tab:gray", lw=0.8, ls="--", label="confidence")
        ax3.set_ylim(0, 1.05)
        ax3.set_ylabel("confidence")
        h1, l1 = ax2.get_legend_handles_labels()
        h2, l2 = ax3.get_legend_handles_labels()
        ax2.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
