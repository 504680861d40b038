"""Batched lattice tracker (ALGORITHM.md 11.7, torchrow extension): ``B`` sequences in lock-step.

The tensor twin of :mod:`torchrow.reference.lattice_tracking`, rule by rule: the prior of a
tracked frame is a mask over section 11.2's static grids (:class:`LatticePriorBatch`), the
restricted search's failures are searched again in full (that second pass runs only when some
sequence needs it), and the state, the row end and the identity are ``torch.where`` over the
batch. Discrete results equal the reference's; floats are the reference's expressions.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from torchrow.core.camera import CameraModel
from torchrow.core.params import Params
from torchrow.core.results import STATUSES
from torchrow.core.steering import LATTICE_STATES, FrameResult, LatticeTrack
from torchrow.functional import lattice as flattice
from torchrow.functional import sky as fsky
from torchrow.functional._flow import branch
from torchrow.functional.lattice import LatticePriorBatch, LatticeRows
from torchrow.functional.ransac import image_status

__all__ = ["LatticeTrackerState", "LatticeStep", "lattice_advance", "row_end", "resolvable_row", "confirms",
           "frame_state", "lattice_vp", "records"]

_OK = STATUSES.index("ok")
_CODE = {s: i for i, s in enumerate(LATTICE_STATES)}


@dataclass
class LatticeTrackerState:
    """The lattice tracker's state of ``B`` sequences (the reference's ``LatticeSequenceState``).

    ``ready`` bool: a frame was seen; ``frames``/``age`` int64 (frames processed; since the last
    full search, that frame counting 1); ``last`` int64: the previous frame's state code
    (:data:`~torchrow.core.steering.LATTICE_STATES`, -1 before frame 0); ``vp`` ``(B, 2)`` int64:
    its lattice VP (:func:`lattice_vp`); ``spacing`` int64: its comb spacing where its status was
    ``ok``, else 0 (0 before frame 0; the lattice an acquiring frame confirms, :func:`confirms`);
    ``centre`` float64 with ``has_centre`` bool: the tracked row's bottom-row x for the next
    frame; ``pending`` int64: the row change the next frame reports; ``grid_vp`` ``(B, 2)``
    int64: the VP the last full search of an ``ok`` frame (or of frame 0) chose on the grid,
    whose window the next full search takes (11.7).
    """

    ready: torch.Tensor
    frames: torch.Tensor
    age: torch.Tensor
    last: torch.Tensor
    vp: torch.Tensor
    spacing: torch.Tensor
    centre: torch.Tensor
    has_centre: torch.Tensor
    pending: torch.Tensor
    grid_vp: torch.Tensor

    @classmethod
    def empty(cls, batch: int, device: torch.device | str = "cpu") -> LatticeTrackerState:
        """State of ``batch`` sequences that have not seen a frame yet."""
        dev = torch.device(device)
        i64: dict[str, Any] = dict(dtype=torch.int64, device=dev)
        no = torch.zeros(batch, dtype=torch.bool, device=dev)
        return cls(ready=no, frames=torch.zeros(batch, **i64), age=torch.zeros(batch, **i64),
                   last=torch.full((batch,), -1, **i64), vp=torch.zeros((batch, 2), **i64),
                   spacing=torch.zeros(batch, **i64), centre=torch.zeros(batch, dtype=torch.float64, device=dev),
                   has_centre=no.clone(), pending=torch.zeros(batch, **i64), grid_vp=torch.zeros((batch, 2), **i64))

    def __len__(self) -> int:
        return int(self.ready.shape[0])

    def select(self, index: torch.Tensor | slice) -> LatticeTrackerState:
        """The state of some sequences (index along the batch dimension)."""
        return LatticeTrackerState(**{f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)})


@dataclass
class LatticeStep:
    """One lock-step frame of ``B`` sequences: the lattice (``rows``), ``status`` int64 codes into
    :data:`~torchrow.core.results.STATUSES`, ``state`` int64 codes into
    :data:`~torchrow.core.steering.LATTICE_STATES`, ``row_change`` int64, ``row_end`` int64 (the
    image row where the rows end, -1 where the state is not ``row_end_ahead``), ``full`` and
    ``redo`` bool (the full search ran; as the redo of a restricted frame), ``active`` bool (the
    sequence had a frame), all ``(B,)``."""

    rows: LatticeRows
    status: torch.Tensor
    state: torch.Tensor
    row_change: torch.Tensor
    row_end: torch.Tensor
    full: torch.Tensor
    redo: torch.Tensor
    active: torch.Tensor


def _fields(rows: LatticeRows) -> tuple[torch.Tensor, ...]:
    """A dataclass of tensors as a flat tuple (a graph branch's operands and results)."""
    return tuple(getattr(rows, f.name) for f in dataclasses.fields(rows))


def _where(mask: torch.Tensor, a: Any, b: Any) -> Any:
    """Dataclass ``a`` where ``mask`` (bool (B,)), ``b`` elsewhere, field by field."""
    out = {}
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        out[f.name] = torch.where(mask.view(-1, *([1] * (x.dim() - 1))), x, y)
    return type(a)(**out)


def row_end(lit: torch.Tensor, params: Params) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched :func:`torchrow.reference.lattice_tracking.row_end` of ``lit (B, H)`` int64:
    ``(y_end (B,) int64, found (B,) bool)``."""
    cum = torch.cumsum(lit, dim=1)
    total = cum[:, -1]
    drop = torch.floor(params.lattice_end_drop * total.to(torch.float64)).to(torch.int64)
    return torch.argmax((cum > drop.unsqueeze(1)).to(torch.int64), dim=1), total > 0


def resolvable_row(coef: torch.Tensor, height: int, params: Params, roll: torch.Tensor | None = None) -> torch.Tensor:
    """Batched :func:`torchrow.reference.lattice_tracking.resolvable_row`, ``(B,)`` int64 (``roll (B,)``
    float64: 11.3.2's ``g``, read where ``lattice_roll_grid > 0``)."""
    t = (torch.arange(height, device=coef.device, dtype=torch.float64) - (height - 1)).view(1, height, 1)
    cc, dd = flattice.centre_spacing(t, coef)
    if params.lattice_roll_grid and roll is not None:
        dd = dd - roll.view(-1, 1, 1) * cc
    ok = dd[:, :, 0] >= float(params.lattice_min_spacing)
    first = torch.argmax(ok.to(torch.int64), dim=1)
    return torch.where(ok.any(dim=1), first, torch.full_like(first, height))


def confirms(spacing: torch.Tensor, previous: torch.Tensor, params: Params) -> torch.Tensor:
    """Batched :func:`torchrow.reference.lattice_tracking.confirms`: ``(B,)`` bool, the comb
    spacings ``spacing`` agree with the previous frame's ``ok`` lattice's ``previous`` (0: none),
    both ``(B,)`` int64."""
    return (previous > 0) & flattice.spacing_near(spacing, previous, params)


def frame_state(ok: torch.Tensor, last: torch.Tensor, y_end: torch.Tensor, has_end: torch.Tensor,
                y_res: torch.Tensor, height: int, params: Params, confirmed: torch.Tensor) -> torch.Tensor:
    """Batched :func:`torchrow.reference.lattice_tracking.frame_state`: ``(B,)`` int64 codes into
    :data:`~torchrow.core.steering.LATTICE_STATES` from ``ok`` (status ``ok``), the previous
    frame's code ``last``, the row end ``y_end`` (where ``has_end``), ``y_res`` and ``confirmed``
    (bool), all ``(B,)``."""
    head_rows = int(math.floor(params.lattice_headland_frac * height))
    code = torch.full_like(y_end, _CODE["in_row"])
    code = torch.where(y_end > y_res + params.lattice_end_margin, torch.full_like(code, _CODE["row_end_ahead"]), code)
    code = torch.where(confirmed, code, torch.full_like(code, _CODE["lost"]))
    code = torch.where(~has_end | (y_end > (height - 1) - head_rows), torch.full_like(code, _CODE["headland"]), code)
    ended = (last == _CODE["row_end_ahead"]) | (last == _CODE["headland"])
    failed = torch.where(ended, torch.full_like(code, _CODE["headland"]), torch.full_like(code, _CODE["lost"]))
    return torch.where(ok, code, failed)


def lattice_vp(coef: torch.Tensor, height: int, fallback: torch.Tensor, roll: torch.Tensor | None = None) -> torch.Tensor:
    """Batched :func:`torchrow.reference.lattice_tracking.lattice_vp` of ``coef (B, 7)`` float64:
    ``(B, 2)`` int64, ``fallback`` ``(B, 2)`` int64 where not finite; ``roll (B,)`` float64 where
    ``lattice_roll_grid > 0`` (11.3.2), else ``None``."""
    c0, c1, d0, d1 = coef[:, 0], coef[:, 1], coef[:, 4], coef[:, 5]
    if roll is not None:
        d0, d1 = d0 - roll * c0, d1 - roll * c1
    far, near = -float(8 * height), -float(height) / 4
    pos = d1 > 0
    t = torch.where(pos, torch.clamp(-d0 / torch.where(pos, d1, torch.ones_like(d1)), min=far, max=near),
                    torch.full_like(d1, far))
    xy = torch.stack([c0 + c1 * t, float(height - 1) + t], dim=1)
    fine = torch.isfinite(xy).all(dim=1, keepdim=True)
    return torch.where(fine, torch.round(torch.where(fine, xy, torch.zeros_like(xy))).to(torch.int64), fallback)


def grid_sky(images: torch.Tensor, search: torch.Tensor, params: Params, flow: str) -> torch.Tensor:
    """Section 1's row where the VP grid counts from it (:meth:`Params.lattice_vp_sky_origin`),
    ``(B,)`` int64 (zeros elsewhere; only the images of ``search``, bool ``(B,)``, use it). It
    runs only when some image searches the grid (an ONNX ``If`` in an exported graph). Results
    never depend on it."""
    zeros = torch.zeros(images.shape[0], dtype=torch.int64, device=images.device)
    if not params.lattice_vp_sky_origin():
        return zeros
    return branch(flow, search.any(), lambda images, zeros: (fsky.sky_row(images, params),),
                  lambda images, zeros: (zeros.clone(),), (images, zeros))[0]


def _lattice(images: torch.Tensor, active: torch.Tensor, prior: LatticePriorBatch, params: Params, flow: str,
             sky: torch.Tensor, have_sky: bool, switch: bool = True,
             evidence: torch.Tensor | None = None) -> tuple[LatticeRows, torch.Tensor, torch.Tensor]:
    """Section 11 with the prior and the VP grid's ``sky`` rows (computed here where needed
    unless ``have_sky``): rows, status codes (as the detector's improved mode) and ``switched``
    ``(B,)`` bool. ``evidence``: the caller's row masks in place of the green mask (11.1.1).

    A tracked image of an ``active`` sequence whose restricted comb is too weak for ``ok`` (``contrast <
    lattice_min_contrast``) would be redone in full whatever its refits give (11.7); it is
    switched to the full search here, before its refits, on the same green mask: the same
    lattice as the redo (the VP search, then the comb with the prior's centre and nothing
    restricted), without a second mask, refit or row pass. The switch runs only when some
    image needs it (an ONNX ``If`` in an exported graph; not built without ``switch``: a pass
    with nothing restricted)."""
    bsz, _, h = images.shape[:3]
    begun = flattice.improved_start(images, torch.zeros(bsz, dtype=torch.int64, device=images.device), None, None,
                                    params, prior, flow, grid_sky=sky, evidence=evidence)
    mask, start, fparams = begun.mask, begun.start, begun.fit_params
    counted = params.lattice_vp_sky_origin()
    weak = active & prior.restrict & (start.contrast < params.lattice_min_contrast)
    if switch:
        # the start's fields that this setting fills (bent and roll only with a warped comb, 11.3.2)
        present = [i for i, x in enumerate(start) if x is not None]

        def search(images, mask, weak, centre, restrict, vp, spacing, near, sky, *now):
            if counted and not have_sky:
                sky = fsky.sky_row(images, params)
            wide = LatticePriorBatch(centre, restrict & ~weak, vp, spacing)
            # a weak frame is tracked: the grid near its last grid VP (11.7)
            grid = flattice.vp_search(mask, fparams, flattice.vp_origin(sky, h, params) if counted else None, near)
            got = flattice.comb_start(mask, torch.where(weak.view(-1, 1), grid, now[4]), fparams, wide, flow)
            filled = [t for t in got if t is not None]  # the same fields as ``now``: one setting
            return tuple(torch.where(weak.view(-1, *([1] * (x.dim() - 1))), x, y) for x, y in zip(filled, now))

        def keep(images, mask, weak, centre, restrict, vp, spacing, near, sky, *now):
            return tuple(t.clone() for t in now)

        fields: list[torch.Tensor | None] = list(start)
        for i, x in zip(present, branch(flow, weak.any(), search, keep,
                                        (images, mask, weak, prior.centre, prior.restrict, prior.vp,
                                         prior.spacing, prior.near, sky) + tuple(fields[i] for i in present))):
            fields[i] = x
        start = flattice.LatticeStartBatch._make(fields)
        prior = prior._replace(restrict=prior.restrict & ~weak)
    else:
        weak = torch.zeros_like(weak)
    rows = flattice.improved_finish(begun._replace(start=start), params, prior, flow)
    return rows, flattice.improved_status(rows, image_status(flattice.as_row_fits(rows)), params), weak


def lattice_advance(images: torch.Tensor, active: torch.Tensor, state: LatticeTrackerState,
                    params: Params, flow: str = "sync",
                    evidence: torch.Tensor | None = None) -> tuple[LatticeStep, LatticeTrackerState]:
    """One lock-step frame of ``B`` sequences (11.7); ``images`` ``uint8 (B, 3, H, W)`` at working
    size, ``active`` bool ``(B,)``: the sequences with a frame now (the others keep their state;
    their step entries are meaningless).

    ``flow`` (:mod:`torchrow.functional._flow`) says how work no sequence needs is skipped:
    eagerly (``"sync"``) the redo pass and the VP grid search run only when some sequence
    needs them and the refits end once every image has stopped; in an exported graph
    (``"loop"``, :class:`torchrow.onnx.graphs.StaticLatticeStep`) the redo pass and the grid
    search are ONNX ``If`` nodes and the refits ONNX ``Loop`` nodes; ``"always"`` runs all of
    them to their static bounds, masked. Results never depend on it. Section 11 runs with
    :meth:`Params.tracking` (the refits' bound ``lattice_track_iterations``). ``evidence``: the
    caller's row masks, ``bool (B, H, W)`` at the working size, read in place of the green mask
    by every section 11 pass of the frame, a redo's too (11.1.1; the exported step,
    :class:`torchrow.onnx.graphs.StaticLatticeStep`, has no such input)."""
    params = params.tracking()
    h, w = images.shape[2], images.shape[3]
    tracked = state.ready & state.has_centre
    full = ~tracked | (state.age >= params.lattice_track_every)
    centre = torch.where(tracked, state.centre, torch.full_like(state.centre, float(w) / 2))
    # a full search takes the grid near the last grid VP (frame 0: the whole grid), not near the
    # lattice's own VP, which lies far off where a bent refit extrapolates; after a frame that was
    # not ok, one more grid height, in turn: a loss sweeps the grid at a bounded cost per frame (11.7)
    sweep = torch.where(state.spacing > 0, torch.full_like(state.frames, -1), state.frames % len(params.lattice_vp_heights))
    prior = LatticePriorBatch(centre, ~full, state.vp, state.spacing, state.ready, state.grid_vp, sweep)
    # section 1 where the grid is searched: on frames with a full search (here) or a redo (again;
    # computed there unless it is known here to have run: eagerly, or in the unbranched graph)
    sky = grid_sky(images, full, params, flow)
    have_sky = not params.lattice_vp_sky_origin() or flow == "always" or (flow == "sync" and bool(full.any()))
    rows, status, switched = _lattice(images, active, prior, params, flow, sky, have_sky, evidence=evidence)
    # a tracked frame that still fails is redone in full (switched frames were searched in full)
    redo = active & ~full & ~switched & (status != _OK)
    n_rows = len(dataclasses.fields(LatticeRows))

    def again(images, redo, centre, vp, spacing, near, sky, *now):  # a tracked frame that fails is searched again in full
        sky = sky if have_sky else fsky.sky_row(images, params)
        # redone frames are tracked: the grid near their last grid VP (the others' results are not kept)
        wide, wide_status, _ = _lattice(images, redo, LatticePriorBatch(centre, torch.zeros_like(redo), vp, spacing,
                                                                        torch.ones_like(redo), near),
                                        params, flow, sky, True, switch=False, evidence=evidence)
        picked = _where(redo, wide, LatticeRows(*now[:n_rows]))
        return _fields(picked) + (torch.where(redo, wide_status, now[n_rows]),)

    def unchanged(images, redo, centre, vp, spacing, near, sky, *now):  # no sequence needs it (a branch may not alias inputs)
        return tuple(t.clone() for t in now)

    out = branch(flow, redo.any(), again, unchanged,
                 (images, redo, centre, state.vp, state.spacing, state.grid_vp, sky) + _fields(rows) + (status,))
    rows, status = LatticeRows(*out[:n_rows]), out[n_rows]
    ok = status == _OK
    y_end, has_end = row_end(rows.lit, params)
    y_res = resolvable_row(rows.coef, h, params, rows.roll)
    code = frame_state(ok, state.last, y_end, has_end, y_res, h, params, tracked | confirms(rows.spacing, state.spacing, params))
    change = torch.where(tracked & ok, state.pending, torch.zeros_like(state.pending))
    # identity: the tracked row, or its neighbour once the neighbour is clearly nearer the centre
    x0, d0 = rows.coef[:, 0], rows.coef[:, 4]
    rolled = params.lattice_roll_grid > 0  # 11.3.2: the central row's own spacing, the neighbour's own x
    lim = (0.5 + params.lattice_track_hysteresis) * (d0 - rows.roll * x0 if rolled else d0)
    off = x0 - float(w) / 2
    one = torch.ones_like(change)
    pend = torch.where(off > lim, -one, torch.where(off < -lim, one, torch.zeros_like(one)))
    nxt = x0 + pend.to(torch.float64) * d0
    if rolled:
        nxt = nxt / (1.0 + rows.roll * pend.to(torch.float64))
    keep = code <= _CODE["row_end_ahead"]
    redo = redo | (active & switched)
    searched_full = full | redo
    new = LatticeTrackerState(
        ready=torch.ones_like(state.ready), frames=state.frames + 1,
        age=torch.where(searched_full, one, state.age + 1), last=code,
        vp=lattice_vp(rows.coef, h, rows.vp, rows.roll if rolled else None),
        spacing=torch.where(ok, rows.spacing, torch.zeros_like(rows.spacing)),
        centre=nxt, has_centre=keep, pending=torch.where(keep, pend, torch.zeros_like(pend)),
        grid_vp=torch.where((searched_full & (ok | ~state.ready)).view(-1, 1), rows.vp, state.grid_vp))
    new = _where(active, new, state)
    end = torch.where(code == _CODE["row_end_ahead"], y_end, torch.full_like(y_end, -1))
    return LatticeStep(rows, status, code, change, end, searched_full, redo, active), new


def records(step: LatticeStep, state: LatticeTrackerState, width: int, height: int, params: Params,
            hfov_deg: float | None = None, names: Sequence[str | None] | None = None,
            sources: Sequence[str | None] | None = None, indices: Sequence[int] | None = None,
            camera: CameraModel | None = None) -> list[FrameResult | None]:
    """Per-sequence :class:`~torchrow.core.steering.FrameResult` of a lattice step (``None`` for
    inactive sequences), shared by the eager and the ONNX trackers: the lattice's records
    (:func:`~torchrow.functional.lattice.improved_batch`) with the tracker's fields of 11.7
    (``state``, ``row_change``, ``row_end_y``; ``hough_ran``/``hough_redo``: the full search
    ran, as a redo). ``indices`` default to ``state.frames - 1``; ``hfov_deg`` and ``camera``
    as :func:`torchrow.functional.tracking.records`."""
    top = torch.zeros_like(step.status)
    images = flattice.improved_batch(step.rows, step.status, top, params, width, height).results()
    conf = step.rows.image_confidence.cpu().tolist()
    cols = [t.cpu().tolist() for t in (step.state, step.row_change, step.row_end, step.full, step.redo,
                                       step.active, state.frames)]
    out: list[FrameResult | None] = []
    for b, img in enumerate(images):
        st, change, end, full, redo, active, frames = (c[b] for c in cols)
        if not active:
            out.append(None)
            continue
        img.name = None if names is None else names[b]
        track = LatticeTrack(LATTICE_STATES[st], int(change), None if end < 0 else int(end), bool(full), bool(redo))
        out.append(FrameResult.build(img, source=None if sources is None else sources[b],
                                     frame=frames - 1 if indices is None else indices[b], hough_ran=bool(full),
                                     hough_redo=bool(redo), confidence=conf[b], hfov_deg=hfov_deg,
                                     camera=camera, lattice=track))
    return out
