"""Video output of the ``video`` command: the annotated video writer, frame pictures and the
tracks plot. Frame sources (folders, video files, bags) are :mod:`torchrow.core.frames`.
"""

from __future__ import annotations

import contextlib
import itertools
import math
from pathlib import Path
from typing import Any

import numpy as np

from torchrow.core.frames import (
    cv2_name,
    display_name,
    open_source,  # noqa: F401  (the README's import path for frame sources)
)
from torchrow.evaluation.tracking import RowMoves, bottom_x

__all__ = ["VideoWriter", "draw_frame", "draw_lattice_frame", "error_frame", "central_jumps", "moves_line", "plot_tracks",
           "STATE_COLORS"]


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
        self._name = contextlib.ExitStack()  # OpenCV's name of the file while it is written (cv2_name)
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

            cv_name = self._name.enter_context(cv2_name(self.path, create=True))
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
    return [bottom_x(r, h) for r in rec.get("rows", [])]


def moves_line(m: RowMoves) -> str:
    """One line on a lattice-tracker sequence's stability (:func:`torchrow.evaluation.tracking.row_moves`):
    the median and largest move of row 0 in row spacings and the moves above a quarter spacing."""
    big = m.largest
    if big is None:
        return f"row 0 moves: none measured ({m.skipped} of {m.pairs} frame pairs without a tracked row 0)"
    above = m.above()
    frames = ", ".join(str(x.frame) for x in above[:8]) + (", ..." if len(above) > 8 else "")
    where = f" (frame{'s' if len(above) > 1 else ''} {frames})" if above else ""
    return (f"row 0 moves (row changes aside) a median {m.median:.3f} spacings, at most {big.frac:.2f} "
            f"({big.px:.1f} px into {'full-search ' if big.full else 'tracked '}frame {big.frame}); "
            f"{len(above)} of {len(m.moves)} above a quarter spacing{where}"
            + (f"; {m.skipped} frame pair(s) not measured" if m.skipped else ""))


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

    A frame that reports a row change (the lattice tracker's ``row_change``) is left out of
    ``"tracked"`` and ``"hough"``: its rows are labelled from the neighbouring row by design.
    """
    out: dict[str, list[float]] = {"tracked": [], "hough": [], "lateral": []}
    for prev, cur in itertools.pairwise(records):
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
        if cur.get("row_change"):
            continue
        if not cur.get("hough_ran"):
            xc = cb[c] if c < len(cb) else None
            if xc is not None:
                out["tracked"].append(abs(xc - x))
        else:
            out["hough"].append(min(abs(v - x) for v in valid_c))
    return out


HOUGH_MARK = (255, 80, 0)
LATERAL = (255, 255, 0)


def _lateral_arrow(img: np.ndarray, result, scale: int) -> bool:
    """The image centre's tick at the bottom of ``img`` and, when the frame has ``lateral_px``,
    an arrow from it to the central row's bottom x (in place); returns whether it has one."""
    import cv2

    h = img.shape[0]
    cx = int(round(result.width / 2 * scale))
    cv2.line(img, (cx, h - 1), (cx, h - 25), (255, 255, 255), 1, cv2.LINE_AA)
    if result.lateral_px is None:
        return False
    xr = int(round((result.width / 2 + result.lateral_px) * scale))
    cv2.arrowedLine(img, (cx, h - 12), (xr, h - 12), LATERAL, 2, cv2.LINE_AA, tipLength=0.2)
    return True


def draw_frame(rgb: np.ndarray, result, scale: int = 2, row_id: int | None = None) -> np.ndarray:
    """Annotated frame: :func:`torchrow.apps.annotate.draw_result` plus a Hough-frame marker, the
    steering signals as text (only those the frame has: ``heading_rad`` needs ``--fov`` or
    ``--camera``, ``lateral_m`` ``--camera``), the
    central row's bottom x with the lateral offset drawn as an arrow from the image centre, and
    a legend strip below, the same on every frame (so a video's frames keep one size).
    ``(H, W, 3)`` uint8 -> ``(scale*H + legend, scale*W, 3)``.

    A frame of the lattice tracker (``result.state`` set, ALGORITHM.md 11.7) is drawn by
    :func:`draw_lattice_frame` instead; ``row_id`` (:class:`torchrow.core.steering.RowId`) only
    names its tracked row."""
    if getattr(result, "state", None) is not None:
        return draw_lattice_frame(rgb, result, scale, row_id)
    import cv2

    from torchrow.apps.annotate import HORIZON, INVALID, VALID, VP_COLOR, draw_result, legend

    img = draw_result(rgb, result, scale, with_legend=False)
    w = img.shape[1]
    font = cv2.FONT_HERSHEY_SIMPLEX

    def signal(label: str, parts: list[str]) -> str | None:
        return f"{label} {' / '.join(parts)}" if parts else None

    heading = [f"{v:+.{p}f}{u}" for v, u, p in ((result.heading_px, " px", 1), (result.heading_rad, " rad", 3))
               if v is not None]
    lateral = [f"{v:+.{p}f}{u}" for v, u, p in ((result.lateral_px, " px", 1), (result.lateral_frac, " rows", 2),
                                               (getattr(result, "lateral_m", None), " m", 3)) if v is not None]
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
    _lateral_arrow(img, result, scale)
    # one legend for every frame: a legend that follows each frame's marks changes the picture's
    # height, and a video's frames must keep the first one's size
    entries = [("line", VALID, "detected row"), ("line", INVALID, "invalid row (reason at its foot)"),
               ("line", HORIZON, "horizon (rows above ignored)"), ("cross", VP_COLOR, "vanishing point"),
               ("arrow", VP_COLOR, "towards the vanishing point (outside the picture)"),
               ("arrow", LATERAL, "lateral offset of the central row"),
               ("line", HOUGH_MARK, "HOUGH: Hough stage ran on this frame")]
    return np.concatenate([img, legend(w, entries)], 0)


#: Colour of each lattice tracker state (``LATTICE_STATES``, RGB) on annotated frames and in the plot.
STATE_COLORS = {"in_row": (40, 185, 70), "row_end_ahead": (255, 170, 0), "headland": (80, 150, 255),
                "lost": (230, 40, 40)}
TRACKED = (255, 60, 200)  # the tracked row 0 and the row-change flash: unlike any mark of draw_result
ROW_END = STATE_COLORS["row_end_ahead"]
GAUGE_BG = (70, 70, 70)


def _row_name(row_id: int) -> str:
    return f"row {row_id:+d}" if row_id else "row 0"


def _state_text(result) -> str:
    """The state badge: the state, with the distance to the row end when it is ahead."""
    if result.state == "row_end_ahead":
        if result.row_end_m is not None:
            return f"ROW END {result.row_end_m:.1f} m"
        return f"ROW END y={result.row_end_y} px" if result.row_end_y is not None else "ROW END AHEAD"
    return result.state.replace("_", " ").upper()


def _box(img: np.ndarray, text: str, x: int, y: int, bg, fg, scale: float = 0.5, thick: int = 1,
         right: bool = False) -> tuple[int, int, int, int]:
    """Text on a filled box with its top-left corner (top-right when ``right``) at ``(x, y)``,
    kept inside the picture; returns the box ``(x0, y0, x1, y1)``."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    (tw, th), base = cv2.getTextSize(text, font, scale, thick)
    bw, bh = tw + 8, th + base + 8
    x0 = int(np.clip(x - bw if right else x, 0, max(0, img.shape[1] - bw)))
    y0 = int(np.clip(y, 0, max(0, img.shape[0] - bh)))
    cv2.rectangle(img, (x0, y0), (x0 + bw - 1, y0 + bh - 1), bg, -1)
    cv2.putText(img, text, (x0 + 4, y0 + 4 + th), font, scale, fg, thick, cv2.LINE_AA)
    return x0, y0, x0 + bw, y0 + bh


def _top_view(img: np.ndarray, result, size: int, corner: tuple[int, int]) -> None:
    """A top view of the rows around the camera from ``lateral_m``, ``heading_rad`` and
    ``spacing_m``: forward is up, the camera's nadir a white triangle, the row nearest it thick,
    the lateral offset a yellow line to it, the row end (``row_end_m``) amber across the rows.
    ``corner`` is the view's top-left pixel."""
    import cv2

    from torchrow.apps.annotate import VALID

    x0, y0 = corner
    view = img[y0:y0 + size, x0:x0 + size]
    view[:] = (view * 0.3).astype(np.uint8)
    cv2.rectangle(img, (x0, y0), (x0 + size - 1, y0 + size - 1), GAUGE_BG, 1)
    spacing = result.spacing_m if result.spacing_m and result.spacing_m > 0 else None
    half = 2.5 * spacing if spacing else 1.0  # metres from the nadir to the view's side
    px = size / (2 * half)
    cx, cy = x0 + size / 2, y0 + 0.8 * size
    h = result.heading_rad
    # (right, forward) ground axes: the rows run along (-sin h, cos h) (h > 0: towards the left),
    # and a row lateral_m to the right of the nadir crosses the normal (cos h, sin h) there
    along, normal = np.array([-np.sin(h), np.cos(h)]), np.array([np.cos(h), np.sin(h)])

    def pix(p: np.ndarray) -> tuple[int, int]:
        return int(round(cx + p[0] * px)), int(round(cy - p[1] * px))

    rect = (x0 + 1, y0 + 1, size - 2, size - 2)
    end = result.row_end_m if result.state == "row_end_ahead" else None  # along the rows from the nadir
    for j in range(-4, 5) if spacing else [0]:
        foot = (result.lateral_m + j * (spacing or 0.0)) * normal
        ok, a, b = cv2.clipLine(rect, pix(foot - 3 * half * along), pix(foot + (end or 3 * half) * along))
        if ok:
            cv2.line(img, a, b, VALID, 2 if j == 0 else 1, cv2.LINE_AA)
    if end is not None:
        ok, a, b = cv2.clipLine(rect, pix(end * along - 3 * half * normal), pix(end * along + 3 * half * normal))
        if ok:
            cv2.line(img, a, b, ROW_END, 2, cv2.LINE_AA)
    ok, a, b = cv2.clipLine(rect, pix(np.zeros(2)), pix(result.lateral_m * normal))
    if ok:
        cv2.line(img, a, b, LATERAL, 2, cv2.LINE_AA)
    n = int(round(cx)), int(round(cy))
    tri = np.array([[n[0], n[1] - 9], [n[0] - 6, n[1] + 5], [n[0] + 6, n[1] + 5]], np.int32)
    cv2.fillPoly(img, [tri], (255, 255, 255), cv2.LINE_AA)
    cv2.putText(img, "top view", (x0 + 4, y0 + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (230, 230, 230), 1, cv2.LINE_AA)


def _lattice_legend() -> list[tuple[str, tuple[int, int, int], str]]:
    """The legend of :func:`draw_lattice_frame`: every mark its frames can show, the same on
    every frame so that the frames of a video keep one size."""
    from torchrow.apps.annotate import INVALID, VALID

    return ([("thin", VALID, "visible row"), ("line", TRACKED, "tracked row 0: row id = row changes since the start"),
             ("line", INVALID, "invalid row (reason at its foot)"), ("line", ROW_END, "where the rows end"),
             ("arrow", LATERAL, "lateral offset of the central row")]
            + [("box", STATE_COLORS[s], s.replace("_", " ")) for s in STATE_COLORS]
            + [("box", TRACKED, "ROW CHANGE (frame border)"), ("box", HOUGH_MARK, "FULL SEARCH: unrestricted search ran"),
               ("box", GAUGE_BG, "top view (with --camera)")])


def draw_lattice_frame(rgb: np.ndarray, result, scale: int = 2, row_id: int | None = None) -> np.ndarray:
    """Annotated frame of the lattice tracker (ALGORITHM.md 11.7), for a robot engineer.

    Parameters
    ----------
    rgb : ``(H, W, 3)`` uint8 RGB working image.
    result : FrameResult with ``state`` (the lattice tracker's).
    scale : integer upscaling of the picture.
    row_id : the tracked row's identity (:class:`torchrow.core.steering.RowId`); ``None``: the
        row is named "row 0 (tracked)" and a row change by its step only.

    Returns
    -------
    ``(scale*H + legend, scale*W, 3)`` uint8 RGB: every visible lattice row thin
    (:func:`torchrow.apps.annotate.draw_result` with ``thin_rows``), the tracked row 0 thick in
    pink and labelled with its id; a state badge top right (:data:`STATE_COLORS`; with
    ``row_end_ahead`` the distance to the row end, or its image row without a camera) and the
    row end as a dashed amber line; ``FULL SEARCH`` when the unrestricted search ran; on the
    frame of a row change a pink border and "ROW CHANGE row a -> row b"; the signals as text
    top left (``lateral_m`` first, ``heading_rad`` in degrees); the lateral offset as an arrow
    at the bottom; with ``lateral_m`` and ``heading_rad`` (a camera model) a top view of the
    rows around the camera bottom right; and a legend strip of fixed content below.
    """
    import cv2

    from torchrow.apps.annotate import draw_result, draw_status, legend, row_top

    img = draw_result(rgb, result, scale, with_legend=False, thin_rows=True)
    h, w = img.shape[:2]
    s = float(scale)
    end_y = result.row_end_y if result.state == "row_end_ahead" else None
    if end_y is not None:
        y = int(round(end_y * s))
        for x in range(0, w, 18):
            cv2.line(img, (x, y), (min(x + 10, w - 1), y), ROW_END, 2)
    mid = result.rows[len(result.rows) // 2] if result.rows else None  # row k = 0 of the 2K + 1
    if mid is not None and mid.valid and result.state in ("in_row", "row_end_ahead"):  # a row is tracked
        top = max(row_top(result, result.height), float(end_y or 0))
        ys = np.linspace(top, result.height - 1, 48)
        pts = np.stack([np.asarray(mid.x_at(ys)) * s, ys * s], 1)
        if np.isfinite(pts).all():
            line = pts.round().astype(np.int32)
            cv2.polylines(img, [line], False, (0, 0, 0), scale + 4, cv2.LINE_AA)  # an outline: legible on any ground
            cv2.polylines(img, [line], False, TRACKED, scale + 2, cv2.LINE_AA)
            at = line[int(0.6 * (len(line) - 1))]
            name = _row_name(row_id) if row_id is not None else "row 0 (tracked)"
            _box(img, name, int(at[0]) + 10, int(at[1]) - 10, (0, 0, 0), TRACKED, 0.6, 2)
            draw_status(img, result)  # again, over the row
    # signals, top left, below draw_result's status label
    lat = [f"{v:+.{p}f}{u}" for v, u, p in ((result.lateral_m, " m", 3), (result.lateral_px, " px", 1),
                                           (result.lateral_frac, " rows", 2)) if v is not None]
    head = [f"{v:+.{p}f}{u}" for v, u, p in
            ((None if result.heading_rad is None else np.degrees(result.heading_rad), " deg", 1),
             (result.heading_px, " px", 1)) if v is not None]
    spacing = f"  spacing {result.spacing_m:.2f} m" if result.spacing_m is not None else ""
    lines = [f"frame {result.frame}  confidence {result.confidence:.2f}{spacing}",
             "lateral offset " + " / ".join(lat) if lat else None, "heading " + " / ".join(head) if head else None]
    left = (0, 0, 0, 28)  # draw_result's status label
    for text in (t for t in lines if t):
        box = _box(img, text, 2, left[3] + 3, (0, 0, 0), (255, 255, 255))
        left = (0, 0, max(left[2], box[2]), box[3])
    # badges, top right: below the signals where they would overlap them
    y = 2
    badges = [(_state_text(result), STATE_COLORS.get(result.state, (128, 128, 128)), 0.7, 2)]
    if result.hough_ran:
        badges.append(("FULL SEARCH (redo)" if result.hough_redo else "FULL SEARCH", HOUGH_MARK, 0.5, 1))
    if result.row_change:
        step = (f"{_row_name(row_id - result.row_change)} -> {_row_name(row_id)}" if row_id is not None
                else f"{result.row_change:+d}")
        badges.append((f"ROW CHANGE {step}", TRACKED, 0.6, 2))
        cv2.rectangle(img, (0, 0), (w - 1, h - 1), TRACKED, 6)
    for text, bg, size, thick in badges:
        (tw, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, size, thick)
        if w - 8 - tw - 8 < left[2] + 6 and y < left[3]:
            y = left[3] + 4
        fg = (255, 255, 255) if sum(bg) < 400 else (0, 0, 0)
        y = _box(img, text, w - 8, y, bg, fg, size, thick, right=True)[3] + 4
    _lateral_arrow(img, result, scale)
    if result.lateral_m is not None and result.heading_rad is not None:
        size = max(48, int(0.3 * min(h, w)))
        if h - size - 30 > y + 4 and size + 16 < w:  # below the badges (small pictures: none)
            _top_view(img, result, size, (w - size - 8, h - size - 30))
    return np.concatenate([img, legend(w, _lattice_legend())], 0)


def error_frame(width: int, height: int, text: str, scale: int = 2) -> np.ndarray:
    """A dark picture saying why a frame is missing (keeps an annotated video's timing)."""
    import cv2

    img = np.full((height * scale, width * scale, 3), 40, np.uint8)
    cv2.putText(img, text[:80], (8, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 90, 90), 1, cv2.LINE_AA)
    return img


def _confidence_axis(ax, recs: list[dict]) -> None:
    """The frames' confidence (dashed grey, 0-1) on a second y axis of ``ax``, one legend for both."""
    conf = [(r["frame"], r["confidence"]) for r in recs if r.get("confidence") is not None and r.get("status") != "error"]
    twin = ax.twinx()
    if conf:
        twin.plot(*zip(*conf), c="tab:gray", lw=0.8, ls="--", label="confidence")
    twin.set_ylim(0, 1.05)
    twin.set_ylabel("confidence")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = twin.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper right")


def plot_tracks(records_by_source: dict[str, list[dict]], path: str | Path) -> None:
    """PNG: per source, the valid rows' bottom x over time (central row highlighted, Hough
    frames marked), then ``heading_px``, ``lateral_px`` and ``confidence`` over time.

    Records of the lattice tracker (with ``state``) get :func:`plot_lattice_tracks` instead."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if any("state" in r for recs in records_by_source.values() for r in recs):
        plot_lattice_tracks(records_by_source, path)
        return
    n = max(len(records_by_source), 1)
    fig, axes = plt.subplots(2 * n, 1, figsize=(9, 5.2 * n), squeeze=False)
    for i, (src, recs) in enumerate(records_by_source.items()):
        ax, ax2 = axes[2 * i, 0], axes[2 * i + 1, 0]
        fx, bx = [], []
        for r in recs:
            h = r.get("height") or 0
            for row in r.get("rows", []):
                x = bottom_x(row, h)
                if x is not None:
                    fx.append(r["frame"])
                    bx.append(x)
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
        _confidence_axis(ax2, recs)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _runs(frames: list[int], states: list[str]) -> list[tuple[int, int, str]]:
    """Consecutive frames of one state as ``(first, last, state)``."""
    out: list[tuple[int, int, str]] = []
    for f, st in zip(frames, states):
        if out and out[-1][2] == st and out[-1][1] == f - 1:
            out[-1] = (out[-1][0], f, st)
        else:
            out.append((f, f, st))
    return out


def plot_lattice_tracks(records_by_source: dict[str, list[dict]], path: str | Path) -> None:
    """PNG of the lattice tracker's records (ALGORITHM.md 11.7): per source, four panels over
    the frames sharing one axis, row changes as pink dashed lines through all of them.

    1. Lateral offset: ``lateral_m`` (m) when the records have it (``--camera``), else
       ``lateral_px``; ``confidence`` dashed grey on the right axis.
    2. Heading: ``heading_rad`` in degrees, else ``heading_px``.
    3. The row end ahead: ``row_end_m`` (m), else ``row_end_y`` (image row, px).
    4. The state as a coloured band (:data:`STATE_COLORS`) under the tracked row's id
       (:class:`torchrow.core.steering.RowId`), full-search frames as orange ticks on top,
       unreadable frames as red crosses.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from torchrow.core.steering import RowId

    def rgb(c: tuple[int, int, int]) -> tuple[float, float, float]:
        return c[0] / 255, c[1] / 255, c[2] / 255

    n = max(len(records_by_source), 1)
    fig, axes = plt.subplots(4 * n, 1, figsize=(9, 7.8 * n), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 2.4, 2, 1.5] * n})
    for i, (src, recs) in enumerate(records_by_source.items()):
        ax_lat, ax_head, ax_end, ax_state = (axes[4 * i + j, 0] for j in range(4))
        frames = [r["frame"] for r in recs]

        def series(key: str, recs: list[dict] = recs) -> list[tuple[int, float]]:
            return [(r["frame"], r[key]) for r in recs if r.get(key) is not None]

        changes = [r["frame"] for r in recs if r.get("row_change")]
        full = [r["frame"] for r in recs if r.get("hough_ran")]
        for ax in (ax_lat, ax_head, ax_end, ax_state):
            for j, f in enumerate(changes):
                ax.axvline(f, c=rgb(TRACKED), lw=1.2, ls="--", zorder=3, label="row change" if j == 0 else None)
            if frames:
                ax.set_xlim(min(frames) - 0.5, max(frames) + 0.5)
        lat_m = series("lateral_m")
        lat, unit = (lat_m, "m") if lat_m else (series("lateral_px"), "px")
        if lat:
            ax_lat.plot(*zip(*lat), c="tab:blue", lw=1.2, marker=".", ms=3, label=f"lateral offset ({unit})")
        ax_lat.axhline(0, c="k", lw=0.5)
        ax_lat.set_ylabel(f"lateral offset ({unit})")
        _confidence_axis(ax_lat, recs)
        ax_lat.set_title(f"{display_name(str(src))}: lattice tracker, full search on {len(full)} of {len(recs)} "
                         f"frames, {len(changes)} row change(s)", fontsize=9)
        head = [(f, math.degrees(v)) for f, v in series("heading_rad")]
        head, unit = (head, "deg") if head else (series("heading_px"), "px")
        if head:
            ax_head.plot(*zip(*head), c="tab:purple", lw=1.2, marker=".", ms=3)
            ax_head.axhline(0, c="k", lw=0.5)
        else:
            ax_head.text(0.5, 0.5, "no heading (needs --camera or --fov)", ha="center", va="center",
                         transform=ax_head.transAxes, fontsize=8, color="gray")
        ax_head.set_ylabel(f"heading ({unit})")
        end_m = series("row_end_m")
        end, label = (end_m, "row end ahead (m)") if end_m else (series("row_end_y"), "row end: image row (px)")
        if end:
            ax_end.plot(*zip(*end), c=rgb(ROW_END), lw=1.2, marker="o", ms=3)
        else:
            ax_end.text(0.5, 0.5, "no row end ahead", ha="center", va="center", transform=ax_end.transAxes,
                        fontsize=8, color="gray")
        ax_end.set_ylabel(label, fontsize=8)
        if end_m:
            ax_end.set_ylim(bottom=0)
        else:  # image rows: up is farther, as with metres
            ax_end.set_ylim(max((r.get("height") or 0 for r in recs), default=0) or 1, 0)
        lattice = [r for r in recs if r.get("state") is not None]
        for first, last, st in _runs([r["frame"] for r in lattice], [r["state"] for r in lattice]):
            ax_state.axvspan(first - 0.5, last + 0.5, color=rgb(STATE_COLORS.get(st, (128, 128, 128))), alpha=0.45, lw=0)
        ids = RowId()
        track = [(r["frame"], ids.update(r.get("row_change"))) for r in recs]
        if track:
            ax_state.step(*zip(*track), where="mid", c="k", lw=1.4)
            lo, hi = min(t[1] for t in track), max(t[1] for t in track)
            ax_state.set_ylim(lo - 0.7, hi + 0.9)
            ax_state.set_yticks(range(lo, hi + 1))
        if full:
            ax_state.plot(full, [0.9] * len(full), ls="none", marker="|", ms=9, mew=2, c=rgb(HOUGH_MARK),
                          transform=ax_state.get_xaxis_transform())
        err = [r["frame"] for r in recs if r.get("status") == "error"]
        if err:
            ax_state.plot(err, [0.5] * len(err), ls="none", marker="x", c="red",
                          transform=ax_state.get_xaxis_transform())
        ax_state.set_ylabel("row id", fontsize=8)
        ax_state.set_xlabel("frame")
        seen = {r["state"] for r in lattice}
        ax_state.legend(handles=[Patch(color=rgb(STATE_COLORS[s]), alpha=0.45, label=s) for s in STATE_COLORS
                                 if s in seen] + [plt.Line2D([], [], c="k", label="tracked row id"),
                                                  plt.Line2D([], [], ls="none", marker="|", c=rgb(HOUGH_MARK),
                                                             label="full search")]
                        + ([plt.Line2D([], [], ls="none", marker="x", c="red", label="unreadable frame")] if err else []),
                        fontsize=7, loc="lower left", ncol=7, bbox_to_anchor=(0, 1.0), frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
