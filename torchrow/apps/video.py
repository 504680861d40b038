"""Video output of the ``video`` command: the annotated video writer, frame pictures and the
tracks plot. Frame sources (folders, video files, bags) are :mod:`torchrow.core.frames`.
"""

from __future__ import annotations

import contextlib
import itertools
from pathlib import Path
from typing import Any

import numpy as np

from torchrow.core.frames import (
    cv2_name,
    display_name,
    open_source,  # noqa: F401  (the README's import path for frame sources)
)

__all__ = ["VideoWriter", "draw_frame", "error_frame", "central_jumps", "plot_tracks"]


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
    steering signals as text (only those the frame has: ``heading_rad`` needs ``--fov`` or
    ``--camera``, ``lateral_m`` ``--camera``), the
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
