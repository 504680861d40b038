"""Reference video-mode row tracker (ALGORITHM.md section 8), one sequence, plain loop.

Rules (the spec's, plus the choices it leaves open, marked *choice*):

* The first frame the tracker sees (frame 0) fixes ``sky`` (section 1), the vegetation colour
  (section 2, clustering on that frame) and ``info0`` = raw fraction at ``k = video_k_start``
  below the horizon. Every frame, frame 0 included, is segmented with adaptive ``k``
  (section 3.3).
* The Hough stage (sections 4-6) runs on frame 0, after a frame whose status was not
  ``ok``, and when ``hough_every`` (K) processed frames have passed since the last Hough
  frame; otherwise the frame is *tracked*: each row of the previous frame gets a RANSAC band
  of ``track_band`` px around it (:func:`~torchrow.reference.ransac.track_band_points`) and
  the vanishing point of the last Hough run (VP weight ``v = n // 2``, section 7).
* A tracked frame whose status is not ``ok`` (an invalid row, or no vegetation) is redone
  once with the Hough stage; that result is the frame's. A Hough frame that is not ``ok``
  is kept and the next frame runs the Hough stage. Every Hough run starts from ``n_rows``.
* *choice*: a frame that cannot be read gets an ``error`` record and leaves the state
  untouched; it does not count towards K (K counts the frames the tracker processed, so the
  schedule is the same as if the bad frame had been cut out of the video). If frame 0 is
  unreadable, the first readable frame becomes frame 0.
* *choice*: a frame whose working size differs from the sequence's is unreadable in that
  sense. The sequence's size is given to :meth:`Tracker.track_iter` (the CLI gives the size
  most frames have, :meth:`torchrow.core.frames.FrameSource.working_size`) or is frame 0's.
* *choice*: tracked frames carry all rows of the previous frame (it was ``ok``, so all of
  them are valid); ``n_rows`` of a tracked frame is their number.

State is an immutable :class:`SequenceState`; :meth:`Tracker.step` returns a new one.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from torchrow.core.camera import CameraModel
from torchrow.core.frames import load_items
from torchrow.core.io import check_evidence_used, resize_to_width, to_rgb8
from torchrow.core.params import Params, tracker_params
from torchrow.core.results import ImageResult
from torchrow.core.steering import FrameResult, check_optics, confidence
from torchrow.reference.color import vegetation_color
from torchrow.reference.lattice_tracking import LatticeSequenceState, LatticeTracker
from torchrow.reference.ransac import fit_row, fit_tracked_row, validate_rows
from torchrow.reference.sky import sky_row
from torchrow.reference.vanishing import find_lines
from torchrow.reference.vegetation import adapt_k, density, hough_input, raw_fraction, raw_mask, remove_bushy

__all__ = ["SequenceState", "Tracker"]


@dataclass(frozen=True)
class SequenceState:
    """Everything the tracker carries from one frame to the next for one sequence (plain Python
    values; the batched tracker's is :class:`torchrow.functional.tracking.TrackerState`).

    Attributes
    ----------
    width, height : int
        Working size of the sequence (frames must keep it).
    sky : int
        Horizon row fixed on frame 0.
    veg_color : (int, int, int)
        Vegetation RGB fixed on frame 0.
    info0 : float
        Raw-mask fraction at ``k = video_k_start`` on frame 0, below the horizon.
    frames : int
        Frames processed so far (unreadable frames excluded).
    age : int
        Frames processed since the last Hough frame (that frame counts 1).
    prev_valid : bool
        Whether the last processed frame had status ``ok``.
    vp : (float, float) or None
        Vanishing point of the last Hough run.
    rows : tuple of (float, float)
        ``(a, b)`` of the last processed frame's rows (tracked next when ``prev_valid``).
    """

    width: int
    height: int
    sky: int
    veg_color: tuple[int, int, int]
    info0: float
    frames: int = 0
    age: int = 0
    prev_valid: bool = False
    vp: tuple[float, float] | None = None
    rows: tuple[tuple[float, float], ...] = ()


class Tracker:
    """Section 8 on one sequence of frames, the plain way.

    Parameters
    ----------
    params : Params, optional
        Constants; frames are resized to ``params.video_width``; K = ``params.hough_every``.
    hfov_deg : float, optional
        Horizontal field of view of the camera (degrees), for ``heading_rad``.
    camera : CameraModel, optional
        For ``lateral_m``, ``spacing_m`` and the ground ``heading_rad`` (as
        :class:`torchrow.Tracker`); not with ``hfov_deg``.
    mode : str, optional
        ``"faithful"`` or ``"improved"``: overrides ``params.mode`` (without ``params``, improved
        mode takes the forward-camera setting: :func:`~torchrow.core.params.tracker_params`).
        Improved mode runs the lattice tracker of section 11.7
        (:class:`~torchrow.reference.lattice_tracking.LatticeTracker`; its states are
        :class:`~torchrow.reference.lattice_tracking.LatticeSequenceState`).

    Examples
    --------
    >>> tr = Tracker()
    >>> state = None
    >>> for frame in frames:                     # (H, W, 3) uint8 RGB
    ...     result, state = tr.step(frame, state)
    """

    def __init__(self, params: Params | None = None, hfov_deg: float | None = None,
                 camera: CameraModel | None = None, mode: str | None = None) -> None:
        self.params = tracker_params(params, mode)
        check_optics(hfov_deg, camera)
        self.hfov_deg = hfov_deg
        self.camera = camera
        self.lattice = LatticeTracker(self.params, hfov_deg, camera) if self.params.mode == "improved" else None

    # -- section 0 ------------------------------------------------------------------------
    def prepare(self, frame: np.ndarray) -> np.ndarray:
        """Convert to ``uint8 (H, W, 3)`` RGB and resize to ``params.video_width``."""
        if not isinstance(frame, np.ndarray):
            raise TypeError(f"expected a numpy array (H, W, 3), got {type(frame).__name__}")
        return resize_to_width(to_rgb8(frame), self.params.video_width, self.params.max_pixels)

    def init(self, rgb: np.ndarray) -> SequenceState:
        """State from frame 0 (a working-size RGB image): sky, colour, info0."""
        p = self.params
        h, w = rgb.shape[:2]
        sky = sky_row(rgb, p)
        color, _ = vegetation_color(rgb, p)
        info0 = raw_fraction(raw_mask(rgb, color, p.video_k_start, sky), sky)
        return SequenceState(width=w, height=h, sky=sky, veg_color=color, info0=info0)

    # -- one frame ------------------------------------------------------------------------
    def step(self, frame: np.ndarray, state: SequenceState | LatticeSequenceState | None = None, *,
             name: str | None = None, source: str | None = None, index: int | None = None,
             evidence: np.ndarray | None = None) -> tuple[FrameResult, SequenceState | LatticeSequenceState]:
        """Process one frame.

        Parameters
        ----------
        frame : numpy.ndarray
            ``(H, W, 3)`` uint8 RGB, any size (resized to ``video_width``).
        state : SequenceState or None
            The state returned for the previous frame; ``None`` starts a sequence (this
            frame is frame 0).
        name, source, index : optional
            Stored in the result (file name, sequence name, frame index; the index defaults
            to the number of frames processed before this one).
        evidence : numpy.ndarray, optional
            Improved mode only: the caller's row mask for this frame at the frame's own size
            (ALGORITHM.md 11.1.1, resized by :func:`torchrow.core.io.evidence_mask`), in place of
            the green mask in every section 11 pass of the frame (11.7).

        Returns
        -------
        (FrameResult, SequenceState)
            The frame's result and the new state (the given one is not modified).
        """
        check_evidence_used(evidence, self.params)
        if self.lattice is not None:
            if state is not None and not isinstance(state, LatticeSequenceState):
                raise ValueError(f"an improved-mode tracker takes a LatticeSequenceState, got {type(state).__name__}")
            return self.lattice.step(frame, state, name=name, source=source, index=index, evidence=evidence)
        if state is not None and not isinstance(state, SequenceState):
            raise ValueError(f"a faithful tracker takes a SequenceState, got {type(state).__name__}")
        rgb = self.prepare(frame)
        if state is None:
            state = self.init(rgb)
        elif rgb.shape[:2] != (state.height, state.width):
            raise ValueError(f"frame of working size {rgb.shape[1]}x{rgb.shape[0]} in a sequence of "
                             f"{state.width}x{state.height}")
        p = self.params
        k, raw = adapt_k(rgb, state.veg_color, state.sky, state.info0, p)
        veg = remove_bushy(raw, state.sky, p)
        base = ImageResult(width=state.width, height=state.height, status="no_vp", sky=state.sky,
                           veg_color=state.veg_color, k=k, name=name)
        base.bushy = density(veg, state.sky) > p.bushy_ratio
        need_hough = not state.prev_valid or state.age >= p.hough_every
        redo = False
        res = None
        if not need_hough:
            res = self._tracked(veg, base, state)
            if res.status != "ok":
                redo = True
        if need_hough or redo:
            res = self._hough(veg, base, state)
        assert res is not None
        hough_ran = need_hough or redo
        new = replace(
            state, frames=state.frames + 1, age=1 if hough_ran else state.age + 1,
            prev_valid=res.status == "ok", vp=res.vp if hough_ran else state.vp,
            rows=tuple((r.a, r.b) for r in res.rows))
        conf = confidence(veg, res.rows, state.sky, p.n_rows, p.track_band / 2)
        out = FrameResult.build(res, source=source, frame=state.frames if index is None else index,
                                hough_ran=hough_ran, hough_redo=redo, confidence=conf, hfov_deg=self.hfov_deg,
                                camera=self.camera)
        return out, new

    def _fresh(self, base: ImageResult) -> ImageResult:
        return ImageResult(**{k: getattr(base, k) for k in ImageResult.__dataclass_fields__})

    def _hough(self, veg: np.ndarray, base: ImageResult, state: SequenceState) -> ImageResult:
        """Sections 4-7 on the segmented frame (image mode after segmentation)."""
        p = self.params
        res = self._fresh(base)
        if not veg.any():
            res.status, res.n_rows = "no_vegetation", 0
            return res
        hin, _ = hough_input(veg, state.sky, p)
        search = find_lines(hin, p)
        res.hough, res.outliers, res.n_rows, res.vp = search.lines, search.outliers, search.n_rows, search.vp
        if search.vp is None:
            return res
        band = p.ransac_band_px(state.width, bool(res.bushy))  # a frame result is faithful: never None
        fits = [fit_row(veg, line, search.vp, band, p) for line in search.lines]
        res.rows = validate_rows(fits, state.height, state.width, p)
        res.status = "ok" if all(r.valid for r in res.rows) else "invalid"
        return res

    def _tracked(self, veg: np.ndarray, base: ImageResult, state: SequenceState) -> ImageResult:
        """Section 7 with bands around the previous frame's rows and the last Hough VP."""
        p = self.params
        res = self._fresh(base)
        res.vp, res.n_rows = state.vp, len(state.rows)
        if not veg.any():
            res.status = "no_vegetation"
            return res
        assert state.vp is not None  # the previous frame was ok, so a Hough run gave a VP
        fits = [fit_tracked_row(veg, a, b, state.vp, p.track_band, p) for a, b in state.rows]
        res.rows = validate_rows(fits, state.height, state.width, p)
        res.status = "ok" if all(r.valid for r in res.rows) else "invalid"
        return res

    # -- whole sequences --------------------------------------------------------------------
    def track_iter(self, items: Iterable[object], source: str | None = None,
                   size: tuple[int, int] | None = None) -> Iterator[tuple[FrameResult, np.ndarray | None]]:
        """Track one sequence lazily: yields ``(result, working RGB or None)`` per item.

        Items are frames or ``(name, frame)`` (:mod:`torchrow.core.frames`); unreadable frames,
        and frames whose working size differs from the sequence's, get ``error`` records.
        The sequence's working ``size`` ``(H, W)`` is given (e.g.
        :meth:`torchrow.core.frames.FrameSource.working_size`, the size most frames have) or, by
        default, that of the first readable frame; frame 0 is the first readable frame of it.
        """
        state: SequenceState | LatticeSequenceState | None = None
        for i, got in enumerate(load_items(items, self.params.video_width, self.params.max_pixels)):
            if got.rgb is not None and size is None:
                size = got.rgb.shape[:2]
            if got.rgb is not None and got.rgb.shape[:2] != size:
                assert size is not None
                got.error = (f"frame of working size {got.rgb.shape[1]}x{got.rgb.shape[0]} in a sequence of "
                             f"{size[1]}x{size[0]}")
                got.rgb = None
            if got.rgb is None:
                yield FrameResult.failed_frame(source, i, got.name, got.error or "unreadable frame"), None
                continue
            res, state = self.step(got.rgb, state, name=got.name, source=source, index=i)
            yield res, got.rgb

    def track(self, items: Iterable[object], source: str | None = None) -> list[FrameResult]:
        """Track a whole sequence; one result per item (see :meth:`track_iter`)."""
        return [r for r, _ in self.track_iter(items, source)]
