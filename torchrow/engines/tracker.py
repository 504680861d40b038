"""The batched video-mode tracker: ``torchrow.Tracker`` (ALGORITHM.md section 8; in improved mode
the lattice tracker of section 11.7, :mod:`torchrow.functional.lattice_tracking`).

A thin :class:`torch.nn.Module` over :mod:`torchrow.functional.tracking`. ``B`` independent
sequences advance in lock-step; :meth:`Tracker.track_iter` segments a chunk of frames of
every sequence in one batched call, then advances the RANSAC/Hough steps frame by frame,
masking sequences that have ended or whose frame is unreadable. Results equal
:class:`torchrow.reference.Tracker`'s frame by frame.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from torchrow.core.camera import CameraModel
from torchrow.core.frames import prepare_frame
from torchrow.core.io import check_evidence_used, check_working_size
from torchrow.core.params import Params, tracker_params
from torchrow.core.results import concat_batches
from torchrow.core.steering import FrameResult, check_optics
from torchrow.engines.detector import evidence_batch
from torchrow.functional import lattice_tracking as flt
from torchrow.functional import tracking as ftrack
from torchrow.functional._checks import check_device, check_images
from torchrow.functional.lattice import check_evidence
from torchrow.functional.lattice_tracking import LatticeStep, LatticeTrackerState
from torchrow.functional.tracking import TrackerState, TrackStep
from torchrow.reference.lattice_tracking import check_lattice_tracker

__all__ = ["Tracker", "TrackerState", "TrackStep", "LatticeTrackerState", "LatticeStep"]

#: Attribute of a state returned by :meth:`Tracker.forward`: the ``(H, W)`` working size its
#: sequences were started at (not a tensor field: the exported graph's state has no size).
_SIZE = "_working_size"


class Tracker(nn.Module):
    """Batched row tracker, identical to :class:`torchrow.reference.Tracker` frame by frame.

    Parameters
    ----------
    params : Params, optional
        Constants; frames are resized to ``params.video_width``, K = ``params.hough_every``.
    device : str or torch.device, optional
        Where the stages run (default CPU).
    hfov_deg : float, optional
        Horizontal field of view (degrees) for ``heading_rad``.
    camera : CameraModel, optional
        The camera (:class:`torchrow.core.camera.CameraModel`, for the source frames' size or
        any size of the same aspect: records scale it to the working size): records carry
        ``lateral_m``, ``spacing_m`` and the ground ``heading_rad``. Not with ``hfov_deg``.
    chunk : int
        Frames per sequence segmented in one batched call by :meth:`track_iter`.
    mode : str, optional
        ``"faithful"`` or ``"improved"``: overrides ``params.mode`` (without ``params``, improved
        mode takes the forward-camera setting: :func:`~torchrow.core.params.tracker_params`).
        Improved mode is the lattice tracker of ALGORITHM.md 11.7 (states
        :class:`LatticeTrackerState`, steps :class:`LatticeStep`; records add ``state``,
        ``row_change``, ``row_end_y``, ``row_end_m``).

    Examples
    --------
    Robot loop, B = 1 camera::

        tracker = torchrow.Tracker(hfov_deg=69)
        state = None
        while True:
            frame = camera.read()                              # (H, W, 3) uint8 RGB
            (result,), state = tracker.step([frame], state)    # FrameResult, TrackerState
            controller.update(result.heading_rad, result.lateral_frac, result.confidence)

    Offline, several sequences of different lengths::

        results = tracker.track([frames_a, frames_b])          # list of lists of FrameResult
    """

    def __init__(self, params: Params | None = None, device: str | torch.device | None = None,
                 hfov_deg: float | None = None, chunk: int = 8, workers: int | None = None,
                 camera: CameraModel | None = None, mode: str | None = None) -> None:
        super().__init__()
        self.params = tracker_params(params, mode)
        self.improved = self.params.mode == "improved"
        if self.improved:
            check_lattice_tracker(self.params)
        self.device = check_device(device)
        check_optics(hfov_deg, camera)
        self.hfov_deg = hfov_deg
        self.camera = camera
        if chunk < 1:
            raise ValueError(f"chunk must be >= 1, got {chunk}")
        self.chunk = chunk
        if workers is not None and workers < 1:
            raise ValueError(f"workers must be None or >= 1, got {workers}")
        # As CropRowDetector: on a CPU, groups of sequences advance concurrently on
        # single-threaded workers (most ops are small and run on one thread anyway).
        # Sequences are independent, so results never depend on it (tested).
        self.workers = workers if workers is not None else (
            torch.get_num_threads() if self.device.type == "cpu" else 1)

    # -- tensors in, tensors out ----------------------------------------------------------
    @torch.no_grad()
    def forward(self, frames: torch.Tensor, state: Any = None,
                active: torch.Tensor | None = None, evidence: torch.Tensor | None = None) -> tuple[Any, Any]:
        """One lock-step frame of ``B`` sequences.

        Parameters
        ----------
        frames : torch.Tensor
            ``uint8 (B, 3, H, W)`` RGB at working size (``params.video_width`` wide).
        state : TrackerState, optional
            From the previous call; ``None`` starts ``B`` new sequences.
        active : torch.Tensor, optional
            ``bool (B,)``: sequences that have a frame now (default all); the others keep
            their state. An active sequence that has not seen a frame yet takes this one
            as its frame 0.
        evidence : torch.Tensor, optional
            Improved mode only: ``bool (B, H, W)``, the caller's row masks at the working size,
            read in place of the green mask (ALGORITHM.md 11.1.1, 11.7).

        Returns
        -------
        (TrackStep, TrackerState) or, in improved mode, (LatticeStep, LatticeTrackerState)
            The new state remembers the working size; a later call with frames of another
            size raises ``ValueError`` (as :meth:`torchrow.reference.Tracker.step`): the
            sky row and rows of the state belong to that size.
        """
        check_images(frames, "frames")
        check_evidence_used(evidence, self.params)
        if evidence is not None:
            check_evidence(frames, evidence)
        h, w = frames.shape[2], frames.shape[3]
        check_working_size(w, h, self.params.max_pixels)
        size = getattr(state, _SIZE, None)
        if size is not None and size != (h, w):
            raise ValueError(f"frame of working size {w}x{h} in a sequence of {size[1]}x{size[0]}")
        x = frames.to(self.device)
        bsz = x.shape[0]
        if self.improved:
            lstate = LatticeTrackerState.empty(bsz, self.device) if state is None else state
            if len(lstate) != bsz:
                raise ValueError(f"state holds {len(lstate)} sequences, frames {bsz}")
            act = torch.ones(bsz, dtype=torch.bool, device=self.device) if active is None else active.to(self.device)
            lstep, lnew = flt.lattice_advance(x, act, lstate, self.params,
                                              evidence=None if evidence is None else evidence.to(self.device))
            setattr(lnew, _SIZE, (h, w))
            return lstep, lnew
        if state is None:
            state = TrackerState.empty(bsz, self.params, self.device)
        if len(state) != bsz:
            raise ValueError(f"state holds {len(state)} sequences, frames {bsz}")
        act = torch.ones(bsz, dtype=torch.bool, device=self.device) if active is None else active.to(self.device)
        state = self._start(x, state, act)
        veg, k, bushy = self._segment(x, state.sky, state.veg_color, state.info0)
        stepped, new = self._advance(veg, k, bushy, act, state)
        if bool(new.ready.any()):
            setattr(new, _SIZE, (h, w))
        return stepped, new

    # -- sequences in groups on worker threads (CPU) ---------------------------------------
    def _groups(self, batch: int) -> list[slice]:
        n = min(self.workers, batch) if self.device.type == "cpu" else 1
        edges = [round(i * batch / n) for i in range(n + 1)] if n > 1 else [0, batch]
        return [slice(edges[i], edges[i + 1]) for i in range(len(edges) - 1)]

    def _parallel(self, fn, groups: list[slice]) -> list:
        """``fn(group)`` for every group, concurrently on single-threaded workers."""
        if len(groups) == 1:
            return [fn(groups[0])]
        from torchrow.core.tables import lab_table_torch
        from torchrow.functional import hough as fhough
        from torchrow.functional import ransac as fransac

        fhough.trig(self.params, self.device)  # shared constants exist before the threads read them
        fransac.hypotheses(self.params, self.device)
        lab_table_torch(self.device)

        def run(g: slice):
            torch.set_num_threads(1)  # per-thread settings (OpenMP, grad mode)
            with torch.no_grad():
                return fn(g)

        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with ThreadPoolExecutor(max_workers=len(groups)) as pool:
                return list(pool.map(run, groups))
        finally:
            torch.set_num_threads(threads)

    def _segment(self, x: torch.Tensor, sky: torch.Tensor, color: torch.Tensor, info0: torch.Tensor):
        """:func:`torchrow.functional.tracking.segment` over groups of frames."""
        parts = self._parallel(lambda g: ftrack.segment(x[g], sky[g], color[g], info0[g], self.params),
                               self._groups(x.shape[0]))
        return tuple(torch.cat(t) for t in zip(*parts)) if len(parts) > 1 else parts[0]

    def _advance(self, veg: torch.Tensor, k: torch.Tensor, bushy: torch.Tensor, act: torch.Tensor,
                 state: TrackerState) -> tuple[TrackStep, TrackerState]:
        """:func:`torchrow.functional.tracking.advance` over groups of sequences."""
        groups = self._groups(veg.shape[0])
        if veg.shape[0] >= 2 and len(groups) > 1:
            # rho_table is per working size: build it once, outside the threads
            from torchrow.functional import hough as fhough
            fhough.rho_table(veg.shape[1], veg.shape[2], self.params, self.device)
        parts = self._parallel(lambda g: ftrack.advance(veg[g], k[g], bushy[g], act[g], state.select(g), self.params),
                               groups)
        return concat_batches([q[0] for q in parts]), concat_batches([q[1] for q in parts])

    def _start(self, frames: torch.Tensor, state: TrackerState, active: torch.Tensor) -> TrackerState:
        """Initialise the active sequences that have not seen a frame yet from ``frames``."""
        new = active & ~state.ready
        if not bool(new.any()):
            return state
        idx = torch.nonzero(new).view(-1)  # composition, not a stage: only which inputs to init
        init = ftrack.init_state(frames.index_select(0, idx), self.params)
        full = TrackerState.empty(len(state), self.params, self.device)
        for name in ("sky", "veg_color", "info0", "ready"):
            getattr(full, name).index_copy_(0, idx, getattr(init, name))
        return ftrack.merge_state(state, full, new)

    # -- records ----------------------------------------------------------------------------
    def results(self, step: Any, state: Any, width: int, height: int,
                names: Sequence[str | None] | None = None, sources: Sequence[str | None] | None = None,
                indices: Sequence[int] | None = None) -> list[FrameResult | None]:
        """Per-sequence :class:`FrameResult` of a step (``None`` for inactive sequences):
        :func:`torchrow.functional.tracking.records` with this tracker's parameters and optics (in
        improved mode, the lattice's records with the tracker's fields, ALGORITHM.md 11.7)."""
        if isinstance(step, LatticeStep):
            return flt.records(step, state, width, height, self.params, self.hfov_deg, names, sources, indices,
                               camera=self.camera)
        return ftrack.records(step, state, width, height, self.params, self.hfov_deg, names, sources, indices,
                              camera=self.camera)

    # -- arrays in, records out -------------------------------------------------------------
    def prepare(self, frame: np.ndarray | str | Path) -> np.ndarray:
        """Load a path or convert an array; resize to ``params.video_width``
        (:func:`torchrow.core.frames.prepare_frame`)."""
        return prepare_frame(frame, self.params.video_width, self.params.max_pixels)

    def step(self, frames: Sequence[np.ndarray] | torch.Tensor, state: TrackerState | None = None,
             names: Sequence[str | None] | None = None,
             evidence: Sequence[np.ndarray] | torch.Tensor | None = None) -> tuple[list[FrameResult], TrackerState]:
        """One frame of each of ``B`` sequences (the robot's loop): records and the new state.

        ``frames``: ``B`` RGB arrays (any size, resized to the working width, all of one
        working size) or a ``uint8 (B, 3, H, W)`` tensor already at working size.
        ``evidence`` (improved mode only, ALGORITHM.md 11.1.1): the caller's row masks, with
        arrays one per frame at that frame's own size (resized by
        :func:`torchrow.core.io.evidence_mask`, as :meth:`torchrow.reference.Tracker.step` does),
        with a tensor ``bool (B, H, W)`` at the working size.
        """
        check_evidence_used(evidence, self.params)
        if isinstance(frames, torch.Tensor):
            x, masks = frames, evidence_batch(evidence, None)
        else:
            arrays = [self.prepare(f) for f in frames]
            if len({a.shape for a in arrays}) != 1:
                raise ValueError(f"frames of different working sizes: {sorted({a.shape for a in arrays})}")
            x = torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2).contiguous()
            masks = evidence_batch(evidence, arrays)
        stepped, new = self(x, state, evidence=masks)
        res = self.results(stepped, new, x.shape[3], x.shape[2], names)
        return [r for r in res if r is not None], new

    def track_iter(self, sequences: Sequence[Iterable[object]], sources: Sequence[str | None] | None = None,
                   size: tuple[int, int] | None = None) -> Iterator[tuple[int, FrameResult, np.ndarray | None]]:
        """Track ``B`` sequences in lock-step, lazily.

        Parameters
        ----------
        sequences : sequence of iterables
            One iterable of items per sequence (frames or ``(name, frame)``, see
            :mod:`torchrow.core.frames`); lengths may differ.
        sources : sequence of str, optional
            Sequence names stored in the records.
        size : (int, int), optional
            Working ``(H, W)`` of the batch (e.g. the sequences'
            :meth:`torchrow.core.frames.FrameSource.working_size`); default: the first loaded
            frame's.

        Yields
        ------
        (sequence index, FrameResult, working RGB or None)
            In lock-step order: frame ``t`` of every sequence before frame ``t + 1``. Every
            item gets a record: unreadable frames, and frames whose working size differs from
            the batch's, get ``error`` records and are skipped.

        Notes
        -----
        The frame loop is :func:`torchrow.functional.tracking.lockstep` (shared with
        :class:`torchrow.onnx.runtime.OnnxTracker`); this tracker's step starts the sequences
        whose frame 0 is in a chunk, segments the chunk's readable frames in one call, then
        advances frame by frame.
        """
        bsz = len(sequences)
        p = self.params
        state: Any = LatticeTrackerState.empty(bsz, self.device) if self.improved else TrackerState.empty(
            bsz, p, self.device)
        ready = [False] * bsz

        def step(chunk: ftrack.FrameChunk) -> Iterator[tuple[TrackStep | LatticeStep, Any] | None]:
            nonlocal state
            h, w = chunk.size
            got, t_max = chunk.items, chunk.length
            if self.improved:  # the lattice tracker: no frame-0 colour, no segmentation, frame by frame
                for t in range(t_max):
                    act_list = chunk.active(t)
                    if not any(act_list):
                        yield None
                        continue
                    x = torch.zeros((bsz, 3, h, w), dtype=torch.uint8)
                    for b in range(bsz):
                        rgb = chunk.rgb(b, t)
                        if rgb is not None:
                            x[b] = torch.from_numpy(rgb).permute(2, 0, 1)
                    act = torch.tensor(act_list, dtype=torch.bool, device=self.device)
                    lstep, state = flt.lattice_advance(x.to(self.device), act, state, p)
                    yield lstep, state
                return
            # frame 0 of sequences starting in this chunk: their first readable frame
            starts = []
            for b in range(bsz):
                if not ready[b]:
                    first = next((it.frame.rgb for it in got[b] if it.frame.rgb is not None), None)
                    if first is not None:
                        starts.append((b, first))
                        ready[b] = True
            if starts:
                idx = torch.tensor([b for b, _ in starts], dtype=torch.int64, device=self.device)
                x0 = torch.from_numpy(np.stack([f for _, f in starts])).permute(0, 3, 1, 2).contiguous()
                state = self._start(torch.zeros((bsz, 3, h, w), dtype=torch.uint8).index_copy_(
                    0, idx.cpu(), x0).to(self.device), state,
                    torch.zeros(bsz, dtype=torch.bool, device=self.device).index_fill_(0, idx, True))
            # segment every readable frame of the chunk in one call
            where = [(b, t, rgb) for t in range(t_max) for b in range(bsz) if (rgb := chunk.rgb(b, t)) is not None]
            veg = torch.zeros((bsz, t_max, h, w), dtype=torch.bool, device=self.device)
            kk = torch.zeros((bsz, t_max), dtype=torch.int64, device=self.device)
            bushy = torch.zeros((bsz, t_max), dtype=torch.bool, device=self.device)
            if where:
                seq = torch.tensor([b for b, _, _ in where], dtype=torch.int64, device=self.device)
                x = torch.from_numpy(np.stack([rgb for _, _, rgb in where])).permute(0, 3, 1, 2)
                v, k1, b1 = self._segment(x.contiguous().to(self.device), state.sky[seq], state.veg_color[seq],
                                          state.info0[seq])
                flat = seq * t_max + torch.tensor([t for _, t, _ in where], dtype=torch.int64, device=self.device)
                veg.view(bsz * t_max, h, w)[flat] = v
                kk.view(-1)[flat] = k1
                bushy.view(-1)[flat] = b1
            # advance frame by frame in lock-step
            for t in range(t_max):
                act_list = chunk.active(t)
                if not any(act_list):
                    yield None
                    continue
                act = torch.tensor(act_list, dtype=torch.bool, device=self.device)
                stepped, state = self._advance(veg[:, t], kk[:, t], bushy[:, t], act, state)
                yield stepped, state

        return ftrack.lockstep(sequences, step, self.params, chunk=self.chunk, size=size, sources=sources,
                               hfov_deg=self.hfov_deg, camera=self.camera, records_fn=self.results)

    def track(self, sequences: Sequence[Iterable[object]], sources: Sequence[str | None] | None = None
              ) -> list[list[FrameResult]]:
        """Track ``B`` sequences; one list of records per sequence, in frame order."""
        out: list[list[FrameResult]] = [[] for _ in sequences]
        for b, res, _ in self.track_iter(sequences, sources):
            out[b].append(res)
        return out
