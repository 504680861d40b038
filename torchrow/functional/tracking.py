"""Batched video-mode row tracker (ALGORITHM.md section 8): B sequences in lock-step.

The rules are those of :mod:`torchrow.reference.tracking` (read its docstring); this module
runs them on ``B`` independent sequences at once:

* :func:`init_state` fixes sky, vegetation colour and ``info0`` from each sequence's frame 0;
* :func:`segment` runs section 3 (adaptive ``k``, bushy-region removal) on any number of
  frames in one call; it depends only on the frame-0 values, never on the tracking state,
  so a chunk of frames of every sequence is segmented at once;
* :func:`advance` moves every *active* sequence one frame forward: tracked RANSAC for the
  sequences that may track, then the Hough stage (sections 4-7) for those that must run it
  (frame 0, previous frame not ``ok``, K frames since the last Hough run) or redo an
  invalid tracked frame. Inactive sequences (ended, or an unreadable frame) keep their state.

Every choice between the tracked and the Hough result is a ``torch.where`` on per-sequence
masks; stages whose mask is empty for the whole batch are skipped (a batch-wide early exit
that changes no result). Sequences that do not need a stage get an empty mask for it, so
they cost little and never influence the others.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

from torchrow.core.batch import BatchResult, Detections
from torchrow.core.camera import CameraModel
from torchrow.core.frames import LoadedFrame, load_items
from torchrow.core.params import Params
from torchrow.core.steering import FrameResult
from torchrow.functional import color as fcolor
from torchrow.functional import ransac as fransac
from torchrow.functional import sky as fsky
from torchrow.functional import vanishing as fvan
from torchrow.functional import vegetation as fveg
from torchrow.functional._checks import below_horizon, check_images
from torchrow.functional._flow import branch

__all__ = ["TrackerState", "TrackStep", "init_state", "merge_state", "segment", "finish_segment", "advance",
           "coverage", "Stages", "eager_stages", "records", "ChunkItem", "FrameChunk", "ChunkStep", "lockstep",
           "STATUS_OK", "STATUS_INVALID", "STATUS_NO_VP", "STATUS_NO_VEGETATION"]

# codes into torchrow.core.results.STATUSES
STATUS_OK, STATUS_INVALID, STATUS_NO_VP, STATUS_NO_VEGETATION = 0, 1, 2, 3


@dataclass
class TrackerState:
    """Tracking state of ``B`` sequences (the tensor twin of the reference's TrackerState).

    Attributes
    ----------
    sky : int64 (B,)
        Horizon rows fixed on frame 0.
    veg_color : uint8 (B, 3)
        Vegetation RGB fixed on frame 0.
    info0 : float64 (B,)
        Raw-mask fraction at ``k = video_k_start`` on frame 0, below the horizon.
    ready : bool (B,)
        Frame 0 has been seen (the three fields above are set).
    frames : int64 (B,)
        Frames processed so far.
    age : int64 (B,)
        Frames processed since the last Hough frame (that frame counts 1).
    prev_valid : bool (B,)
        The last processed frame had status ``ok``.
    vp : float64 (B, 2)
        Vanishing point of the last Hough run (``has_vp`` bool (B,) says whether it has one).
    row_a, row_b : float64 (B, S)
        Rows ``x = a*y + b`` of the last processed frame, ``S = params.n_rows`` slots,
        ``row_present`` bool (B, S) marks the used ones.
    """

    sky: torch.Tensor
    veg_color: torch.Tensor
    info0: torch.Tensor
    ready: torch.Tensor
    frames: torch.Tensor
    age: torch.Tensor
    prev_valid: torch.Tensor
    vp: torch.Tensor
    has_vp: torch.Tensor
    row_a: torch.Tensor
    row_b: torch.Tensor
    row_present: torch.Tensor

    @classmethod
    def empty(cls, batch: int, params: Params, device: torch.device | str = "cpu") -> TrackerState:
        """State of ``batch`` sequences that have not seen a frame yet."""
        dev = torch.device(device)
        i64: dict[str, Any] = dict(dtype=torch.int64, device=dev)
        f64: dict[str, Any] = dict(dtype=torch.float64, device=dev)
        s = params.n_rows
        return cls(sky=torch.zeros(batch, **i64), veg_color=torch.zeros((batch, 3), dtype=torch.uint8, device=dev),
                   info0=torch.zeros(batch, **f64), ready=torch.zeros(batch, dtype=torch.bool, device=dev),
                   frames=torch.zeros(batch, **i64), age=torch.zeros(batch, **i64),
                   prev_valid=torch.zeros(batch, dtype=torch.bool, device=dev),
                   vp=torch.zeros((batch, 2), **f64), has_vp=torch.zeros(batch, dtype=torch.bool, device=dev),
                   row_a=torch.zeros((batch, s), **f64), row_b=torch.zeros((batch, s), **f64),
                   row_present=torch.zeros((batch, s), dtype=torch.bool, device=dev))

    def __len__(self) -> int:
        return int(self.sky.shape[0])

    def select(self, index: torch.Tensor | slice) -> TrackerState:
        """The state of some sequences (index along the batch dimension)."""
        return TrackerState(**{f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)})


def merge_state(old: TrackerState, new: TrackerState, mask: torch.Tensor) -> TrackerState:
    """``new`` where ``mask`` (bool (B,)), ``old`` elsewhere, field by field."""
    out = {}
    for f in dataclasses.fields(old):
        a, b = getattr(old, f.name), getattr(new, f.name)
        m = mask.view(-1, *([1] * (a.dim() - 1)))
        out[f.name] = torch.where(m, b, a)
    return TrackerState(**out)


@dataclass
class TrackStep(Detections):
    """One lock-step frame of ``B`` sequences: the :class:`~torchrow.core.batch.Detections`
    fields (rows ``(B, S)``; Hough lines and outliers all invalid on tracked frames), then
    ``hough_ran``, ``hough_redo`` bool ``(B,)``, ``confidence`` float64 ``(B,)`` in [0, 1] and
    ``active`` bool ``(B,)`` (sequences that processed a frame in this step; the other
    entries are meaningless for the rest).
    """

    hough_ran: torch.Tensor
    hough_redo: torch.Tensor
    confidence: torch.Tensor
    active: torch.Tensor


def init_state(frames: torch.Tensor, params: Params) -> TrackerState:
    """State of ``B`` sequences from their frame 0, ``uint8 (B, 3, H, W)`` at working size.

    Sky (section 1), vegetation colour (section 2) and ``info0`` = :func:`raw_fraction` of
    the raw mask at ``k = video_k_start`` (section 3.3).
    """
    check_images(frames, "frames")
    b = frames.shape[0]
    sky = fsky.sky_row(frames, params).to(torch.int64)
    color = fcolor.vegetation_color(frames, params)
    k0 = torch.full((b,), params.video_k_start, dtype=torch.int64, device=frames.device)
    info0 = fveg.raw_fraction(fveg.raw_mask(frames, color, k0, sky), sky)
    st = TrackerState.empty(b, params, frames.device)
    st.sky, st.veg_color, st.info0 = sky, color, info0.to(torch.float64)
    st.ready = torch.ones(b, dtype=torch.bool, device=frames.device)
    return st


def segment(frames: torch.Tensor, sky: torch.Tensor, color: torch.Tensor, info0: torch.Tensor,
            params: Params) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Section 3 with adaptive ``k`` on ``N`` frames (any mix of sequences) in one call.

    Parameters
    ----------
    frames : uint8 (N, 3, H, W)
    sky, color, info0 : int64 (N,), uint8 (N, 3), float64 (N,)
        Frame-0 values of each frame's sequence.

    Returns
    -------
    veg : bool (N, H, W)
        Bushy-removed vegetation mask.
    k : int64 (N,)
        Adaptive LAB half-width.
    bushy : bool (N,)
        ``density > bushy_ratio`` (section 4).
    """
    k, raw = fveg.adapt_k(frames, color, sky, info0, params)
    veg, bushy = finish_segment(raw, sky, params)
    return veg, k, bushy


def finish_segment(raw: torch.Tensor, sky: torch.Tensor, params: Params) -> tuple[torch.Tensor, torch.Tensor]:
    """Section 3.4 and the bushy flag of section 4 on the adaptive-``k`` raw mask ``raw`` bool
    ``(N, H, W)``: ``veg`` bool ``(N, H, W)`` and ``bushy`` bool ``(N,)``."""
    veg = fveg.remove_bushy(raw, sky, params)
    return veg, fveg.density(veg, sky) > params.bushy_ratio


def coverage(veg: torch.Tensor, a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor, sky: torch.Tensor,
             half_band: float) -> torch.Tensor:
    """Per-row coverage of :func:`torchrow.core.steering.row_coverage`, batched: float64 (B, S).

    ``veg`` bool (B, H, W); rows ``x = a*y + b`` (B, S) with ``valid``; ``sky`` int64 (B,).
    A row ``y >= sky`` counts when a column ``x`` has ``veg`` and
    ``abs(x - (a*y + b)) <= half_band`` (float64, same order as the reference); invalid
    rows get 0.
    """
    bsz, h, w = veg.shape
    s = a.shape[1]
    dev = veg.device
    ys = torch.arange(h, device=dev)
    yf = ys.to(torch.float64).view(1, 1, h)
    aa = torch.where(valid, a, torch.zeros_like(a)).unsqueeze(2)
    bb = torch.where(valid, b, torch.zeros_like(b)).unsqueeze(2)
    xc = aa * yf + bb  # (B, S, H)
    reach = int(math.ceil(half_band)) + 1
    base = torch.floor(xc.clamp(-reach - 1, w + reach)).to(torch.int64)
    flat = veg.reshape(bsz, h * w)
    hit = torch.zeros((bsz, s, h), dtype=torch.bool, device=dev)
    for d in range(-reach, reach + 1):  # static window of columns around the row
        xs = base + d
        inside = (xs >= 0) & (xs < w)
        near = (xs.to(torch.float64) - xc).abs() <= half_band
        idx = (ys.view(1, 1, h) * w + xs.clamp(0, w - 1)).reshape(bsz, s * h)
        on = torch.gather(flat, 1, idx).view(bsz, s, h)
        hit |= inside & near & on
    count = (hit & below_horizon(sky, h, as_bool=True).view(-1, 1, h)).sum(2)
    rows_below = (h - sky.clamp(0, h)).view(-1, 1)
    cov = count.to(torch.float64) / rows_below.clamp(min=1).to(torch.float64)
    cov = torch.where(rows_below > 0, cov, torch.zeros_like(cov))
    return torch.where(valid, cov, torch.zeros_like(cov))


def _where(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.where(mask.view(-1, *([1] * (a.dim() - 1))), a, b)


@dataclass(frozen=True)
class Stages:
    """The stages :func:`advance` composes, so that the eager tracker and the exportable
    tracker step (:class:`torchrow.onnx.graphs.StaticTrackerStep`) share one set of rules.

    ``find_lines(hin bool (B, H, W)) -> LineSearch`` (sections 5-6);
    ``fit_rows(veg, theta, rho, present, vp, band, track=None) ->``
    :class:`~torchrow.functional.ransac.RowFit` (steps 7.1-7.5, as
    :func:`torchrow.functional.ransac.fit_rows`);
    ``trig_free``: step 7.6's angle rules without ``atan2`` (see
    :func:`~torchrow.functional.ransac.validate_rows`). ``branches`` says how the tracked
    and the Hough branch are skipped when no sequence of the batch needs them: ``"sync"``
    (a host sync, eager), ``"cond"`` (``torch.cond``: an ONNX ``If``), ``"always"`` (never
    skipped; masks choose, so a graph has no control flow at all). Results never depend on it.
    """

    find_lines: Callable
    fit_rows: Callable
    trig_free: bool = False
    branches: str = "sync"

    def run(self, pred: torch.Tensor, fn: Callable, skip: Callable, operands: tuple) -> tuple:
        """``fn(*operands)`` if ``pred`` (bool scalar tensor) else ``skip(*operands)``, per
        :attr:`branches`; both return tuples of tensors of the same shapes and dtypes."""
        return branch(self.branches, pred, fn, skip, operands)


def eager_stages(params: Params) -> Stages:
    """The :class:`Stages` of the eager tracker: :func:`torchrow.functional.vanishing.find_lines`
    and :func:`torchrow.functional.ransac.fit_rows`."""
    def fit(veg, theta, rho, present, vp, band, track=None):
        return fransac.fit_rows(veg, theta, rho, present, vp, band, params, track=track)

    return Stages(find_lines=lambda hin: fvan.find_lines(hin, params), fit_rows=fit)


def advance(veg: torch.Tensor, k: torch.Tensor, bushy: torch.Tensor, active: torch.Tensor,
            state: TrackerState, params: Params, stages: Stages | None = None) -> tuple[TrackStep, TrackerState]:
    """Move every active sequence one frame forward (section 8).

    Parameters
    ----------
    veg : bool (B, H, W)
        This frame's segmentation (:func:`segment`) of every sequence.
    k, bushy : int64 (B,), bool (B,)
        From :func:`segment`.
    active : bool (B,)
        Sequences that have a (readable) frame at this step; they must be ``ready``.
    state : TrackerState
        State after the previous frame (not modified).
    params : Params
    stages : Stages, optional
        Default :func:`eager_stages`.

    Returns
    -------
    (TrackStep, TrackerState)
        This frame's outputs and the new state (inactive sequences keep theirs).
    """
    p = params
    st = stages or eager_stages(p)
    bsz, h, w = veg.shape
    dev = veg.device
    i64: dict[str, Any] = dict(dtype=torch.int64, device=dev)
    s = p.n_rows
    o = max(p.n_rows - 1, 1) * p.max_outliers
    sky = state.sky
    has_veg = veg.flatten(1).any(dim=1)
    hough_band = torch.full((bsz,), p.hough_band_px(w), **i64)
    need = active & (~state.prev_valid | (state.age >= p.hough_every))
    trk = active & ~need

    def rows_of(fit: tuple, present):  # a branch's outputs are the fields of a RowFit
        return fransac.validate_rows(fransac.RowFit(*fit), present, h, hough_band, p, trig_free=st.trig_free)

    def no_fit(*_):
        z = torch.zeros((bsz, s), dtype=torch.float64, device=dev)
        return fransac.RowFit(z, z.clone(), z.clone(), torch.ones_like(z), torch.full((bsz, s), -1, **i64),
                              torch.zeros((bsz, s), dtype=torch.bool, device=dev)).astuple()

    # --- tracked frames: bands around the previous rows, VP of the last Hough run ---------
    # Only the fits sit in the branches (st.run): they are the cost; the cheap rules around
    # them run on every frame and see no row where a branch was skipped.
    present_t = state.row_present & trk.unsqueeze(1)
    veg_t = veg & trk.view(-1, 1, 1)  # other sequences' pixels only widen the temporaries

    def tracked(veg_t, present_t, vp, row_a, row_b):
        zeros_rows = torch.zeros((bsz, s), **i64)
        return st.fit_rows(veg_t, zeros_rows, zeros_rows, present_t, vp, torch.full((bsz,), p.track_band, **i64),
                           track=(row_a, row_b)).astuple()

    fit = st.run(trk.any(), tracked, no_fit, (veg_t, present_t, state.vp, state.row_a, state.row_b))
    rows_t = rows_of(fit, present_t)
    ok_t = (rows_t.valid | ~rows_t.present).all(dim=1) & has_veg & trk
    redo = trk & ~ok_t
    use_h = need | redo

    # --- Hough frames: sections 4-7 as in image mode ------------------------------------
    veg_h = veg & use_h.view(-1, 1, 1)
    band = fransac.ransac_band(bushy, w, p)

    def no_lines():
        z = torch.zeros((bsz, s), **i64)
        zo = torch.zeros((bsz, o), **i64)
        b8: dict[str, Any] = dict(dtype=torch.bool, device=dev)
        return fvan.LineSearch(z, z.clone(), z.clone(), torch.zeros((bsz, s), **b8), zo, zo.clone(), zo.clone(),
                               torch.zeros((bsz, o), **b8), torch.zeros(bsz, **i64),
                               torch.zeros((bsz, 2), dtype=torch.float64, device=dev), torch.zeros(bsz, **b8))

    # The line search runs outside any branch: where no sequence needs it, its input is empty
    # and it finishes in two steps (an exported search skips the rest itself; eagerly it is
    # skipped at once). Its input (section 4: Canny on every pixel, about 4 ms per frame in
    # onnxruntime) and the fit sit in branches.
    if st.branches == "sync" and not bool(use_h.any()):
        ls = no_lines()
    else:
        hin = st.run(use_h.any(), lambda v, sk: (fveg.hough_input(v, sk, p)[0],), lambda v, sk: (torch.zeros_like(v),),
                     (veg_h, sky))[0]
        ls = st.find_lines(hin)
    present_h = ls.valid & ls.has_vp.unsqueeze(1) & use_h.unsqueeze(1)

    def hough_fit(veg_h, theta, rho, present_h, vp, band):
        return st.fit_rows(veg_h, theta, rho, present_h, vp, band).astuple()

    fit_h = st.run(use_h.any(), hough_fit, no_fit, (veg_h, ls.theta, ls.rho, present_h, ls.vp, band))
    rows_h = rows_of(fit_h, present_h)
    status_h = fransac.image_status(rows_h, ls.has_vp, has_veg)

    # --- this frame's outputs: the Hough result where it ran, else the tracked one --------
    status = torch.where(use_h, status_h, torch.full_like(status_h, STATUS_OK))
    rows = fransac.Rows(*(_where(use_h, a, b) for a, b in zip(rows_h.astuple(), rows_t.astuple())))
    vp = _where(use_h, ls.vp, state.vp)
    has_vp = torch.where(use_h, ls.has_vp, state.has_vp)
    n_rows = torch.where(use_h, ls.n_rows, state.row_present.sum(1))
    hv = ls.valid & use_h.unsqueeze(1)
    ov = ls.out_valid & use_h.unsqueeze(1)
    cov = coverage(veg, rows.a, rows.b, rows.valid, sky, p.track_band / 2)
    conf = (cov.sum(1) / p.n_rows).clamp(max=1.0)
    step = TrackStep(status=status, k=k, bushy=bushy, n_rows=n_rows, hough_theta=ls.theta, hough_rho=ls.rho,
                     hough_weight=ls.weight, hough_valid=hv, out_theta=ls.out_theta, out_rho=ls.out_rho,
                     out_weight=ls.out_weight, out_valid=ov, vp=vp, has_vp=has_vp, row_a=rows.a, row_b=rows.b,
                     row_valid=rows.valid, row_reason=rows.reason, row_hypothesis=rows.hypothesis,
                     row_present=rows.present, hough_ran=use_h & active, hough_redo=redo, confidence=conf,
                     active=active)

    # --- the next state ----------------------------------------------------------------
    new = dataclasses.replace(
        state, frames=state.frames + 1, age=torch.where(use_h, torch.ones_like(state.age), state.age + 1),
        prev_valid=status == STATUS_OK, vp=vp, has_vp=has_vp, row_a=rows.a, row_b=rows.b,
        row_present=rows.present)
    return step, merge_state(state, new, active)


def records(step: TrackStep, state: TrackerState, width: int, height: int, params: Params,
            hfov_deg: float | None = None, names: Sequence[str | None] | None = None,
            sources: Sequence[str | None] | None = None,
            indices: Sequence[int] | None = None, camera: CameraModel | None = None) -> list[FrameResult | None]:
    """Per-sequence :class:`~torchrow.core.steering.FrameResult` of a step (``None`` for
    inactive sequences), shared by the eager and the ONNX trackers.

    ``state`` is any state of these sequences after frame 0 (for sky and colour);
    ``indices`` default to the frame count of ``state`` minus one; ``hfov_deg`` gives the
    records' heading, ``camera`` their metric steering (:meth:`~torchrow.core.steering.FrameResult.build`).
    """
    batch = BatchResult.build(width, height, params.theta_step, fields=step, sky=state.sky,
                              veg_color=state.veg_color)
    base = batch.results(names)
    active = step.active.cpu().tolist()
    ran, redo = step.hough_ran.cpu().tolist(), step.hough_redo.cpu().tolist()
    conf = step.confidence.cpu().tolist()
    idx = indices if indices is not None else (state.frames - 1).cpu().tolist()
    out: list[FrameResult | None] = []
    for b, r in enumerate(base):
        if not active[b]:
            out.append(None)
            continue
        out.append(FrameResult.build(r, source=None if sources is None else sources[b], frame=int(idx[b]),
                                     hough_ran=ran[b], hough_redo=redo[b], confidence=conf[b],
                                     hfov_deg=hfov_deg, camera=camera))
    return out


# ------------------------------------------------------------------------------------------
# The lock-step frame loop of both trackers' ``track_iter``
# ------------------------------------------------------------------------------------------

class ChunkItem(NamedTuple):
    """One loaded item of a sequence: its place in the sequence and the loaded frame."""

    position: int
    frame: LoadedFrame


@dataclass(frozen=True)
class FrameChunk:
    """Up to ``chunk`` consecutive items of each of ``B`` sequences, all of working size
    ``size`` = ``(H, W)`` or unreadable (``frame.rgb`` is ``None``)."""

    items: list[list[ChunkItem]]
    size: tuple[int, int]

    @property
    def length(self) -> int:
        """Frames of the longest sequence in the chunk (the lock-step frames ``t``)."""
        return max((len(g) for g in self.items), default=0)

    def rgb(self, b: int, t: int) -> np.ndarray | None:
        """Working RGB ``uint8 (H, W, 3)`` of frame ``t`` of sequence ``b``; ``None`` when the
        sequence has no readable frame ``t`` in this chunk."""
        g = self.items[b]
        return g[t].frame.rgb if t < len(g) else None

    def active(self, t: int) -> list[bool]:
        """Per sequence: it has a readable frame ``t``."""
        return [self.rgb(b, t) is not None for b in range(len(self.items))]


#: A tracker's part of :func:`lockstep`: given a chunk, yields for every frame ``t`` of it
#: (in order) the step and state after that frame, or ``None`` when no sequence was active.
ChunkStep = Callable[[FrameChunk], Iterator["tuple[Any, Any] | None"]]  # (step, state): records_fn reads them


def lockstep(sequences: Sequence[Iterable[object]], step: ChunkStep, params: Params, *, chunk: int = 1,
             size: tuple[int, int] | None = None, sources: Sequence[str | None] | None = None,
             hfov_deg: float | None = None, camera: CameraModel | None = None, size_note: str = "",
             records_fn: Callable[..., list[FrameResult | None]] | None = None
             ) -> Iterator[tuple[int, FrameResult, np.ndarray | None]]:
    """Track ``B`` sequences in lock-step, lazily: the frame loop of the eager and the ONNX
    trackers' ``track_iter``, which differ only in ``step``.

    Parameters
    ----------
    sequences : sequence of iterables
        One iterable of items per sequence (:mod:`torchrow.core.frames`); lengths may differ.
    step : ChunkStep
        Advances the tracker over a :class:`FrameChunk` (it holds the tracker state).
    params : Params
        ``video_width`` and ``max_pixels`` load the items; records use the rest.
    chunk : int
        Items pulled from every sequence per call of ``step``.
    size : (int, int), optional
        Working ``(H, W)`` of the batch; default: the first readable frame's.
    sources : sequence of str, optional
        Sequence names stored in the records.
    hfov_deg : float, optional
        Horizontal field of view of the records' ``heading_rad``.
    camera : CameraModel, optional
        The records' metric steering (:func:`records`).
    size_note : str
        Appended to the error of a frame of another working size (e.g. where the size comes from).
    records_fn : callable, optional
        ``(stepped, state, width, height, names, sources, indices) -> records`` of a step;
        default :func:`records` with ``params``, ``hfov_deg`` and ``camera`` (the lattice tracker
        passes its own).

    Yields
    ------
    (sequence index, FrameResult, working RGB or None)
        Frame ``t`` of every sequence before frame ``t + 1``. Every item gets a record:
        unreadable frames, and frames whose working size differs from the batch's, get
        ``error`` records and are skipped (their sequence is inactive at that frame).
    """
    bsz = len(sequences)
    iters = [load_items(s, params.video_width, params.max_pixels) for s in sequences]
    alive = [True] * bsz
    next_index = [0] * bsz
    srcs: list[str | None] = list(sources) if sources is not None else [None] * bsz
    while any(alive):
        got: list[list[ChunkItem]] = [[] for _ in range(bsz)]
        for b in range(bsz):
            while alive[b] and len(got[b]) < chunk:
                fr = next(iters[b], None)
                if fr is None:
                    alive[b] = False
                    break
                if fr.rgb is not None:
                    if size is None:
                        size = (int(fr.rgb.shape[0]), int(fr.rgb.shape[1]))
                    elif fr.rgb.shape[:2] != size:
                        fr.error = (f"frame of working size {fr.rgb.shape[1]}x{fr.rgb.shape[0]} in a batch of "
                                    f"{size[1]}x{size[0]}{size_note}")
                        fr.rgb = None
                got[b].append(ChunkItem(next_index[b], fr))
                next_index[b] += 1
        part = FrameChunk(got, size if size is not None else (0, 0))
        if part.length == 0:
            break
        # nothing readable yet (no size): only error records, the tracker never runs
        steps = step(part) if size is not None else iter(())
        for t in range(part.length):
            done = next(steps, None)
            recs: list[FrameResult | None] = [None] * bsz
            if done is not None:
                stepped, state = done
                pad: list[Any] = [None] * (len(state) - bsz)  # a static batch larger than the sequences
                names = [g[t].frame.name if t < len(g) else None for g in got]
                idxs = [g[t].position if t < len(g) else 0 for g in got]
                if records_fn is None:
                    recs = records(stepped, state, part.size[1], part.size[0], params, hfov_deg, names + pad,
                                   srcs + pad, idxs + [0] * len(pad), camera=camera)
                else:
                    recs = records_fn(stepped, state, part.size[1], part.size[0], names + pad, srcs + pad,
                                      idxs + [0] * len(pad))
            for b in range(bsz):
                if t >= len(got[b]):
                    continue
                i, fr = got[b][t]
                rec = recs[b]
                if rec is not None:
                    yield b, rec, fr.rgb
                else:
                    yield b, FrameResult.failed_frame(srcs[b], i, fr.name, fr.error or "unreadable frame"), None
