"""Reference lattice tracker (ALGORITHM.md 11.7, torchrow extension), one sequence, plain loop.

The improved mode's lattice (section 11) carried from frame to frame: the previous frame's
lattice VP, comb spacing and tracked row are the next frame's prior (its VP is not searched,
its comb is restricted), the central
row keeps its identity, and each frame gets a state (``in_row``, ``row_end_ahead``,
``headland``, ``lost``) and a ``row_change``. The batched twin is
:mod:`torchrow.functional.lattice_tracking`; both follow the same rules, stated in the spec.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from torchrow.core.camera import CameraModel
from torchrow.core.io import evidence_mask, resize_to_width, to_rgb8
from torchrow.core.params import Params
from torchrow.core.steering import FrameResult, LatticeTrack, check_optics
from torchrow.reference.lattice import LatticePrior, centre_spacing, horizon_row, improved_result, improved_rows, spacing_near
from torchrow.reference.sky import sky_row

__all__ = ["LatticeSequenceState", "LatticeTracker", "row_end", "resolvable_row", "lattice_vp", "check_lattice_tracker",
           "confirms", "frame_state"]


def check_lattice_tracker(params: Params) -> None:
    """The lattice tracker's parameters: improved mode with the VP search on the whole image
    (``ValueError`` naming the field otherwise)."""
    if params.mode != "improved":
        raise ValueError(f"the lattice tracker runs in improved mode; got Params.mode={params.mode!r}")
    if params.lattice_vp != "search" or params.lattice_horizon != "image":
        raise ValueError("the lattice tracker needs lattice_vp='search' and lattice_horizon='image'; got "
                         f"lattice_vp={params.lattice_vp!r}, lattice_horizon={params.lattice_horizon!r}")


def row_end(lit: Iterable[int], params: Params) -> int | None:
    """Section 11.7: the image row where the rows end, ``None`` without support.

    ``lit[y]`` = rows ``-K .. K`` with an inlier on image row ``y``; ``total`` their sum,
    ``drop = floor(lattice_end_drop * total)`` (float64): the first ``y`` whose cumulative sum from
    the top exceeds ``drop``.
    """
    cum = np.cumsum(np.asarray(tuple(lit), np.int64))
    if cum.size == 0 or cum[-1] == 0:
        return None
    drop = int(math.floor(np.float64(params.lattice_end_drop) * np.float64(cum[-1])))
    return int(np.argmax(cum > drop))


def resolvable_row(coef: Iterable[float], height: int, params: Params, roll: float = 0.0) -> int:
    """Section 11.7: the first image row whose lattice spacing ``d(t) >= lattice_min_spacing``
    (float64), ``height`` where none is. With ``lattice_roll_grid > 0`` the central row's own
    spacing ``d(t) - g c(t)`` (11.3.2, ``g`` = ``roll``) in place of ``d(t)``."""
    cc, dd = centre_spacing(np.arange(height, dtype=np.float64) - np.float64(height - 1),
                            np.asarray(tuple(coef), np.float64))
    if params.lattice_roll_grid:
        dd = dd - np.float64(roll) * cc
    ok = dd >= np.float64(params.lattice_min_spacing)
    return int(np.argmax(ok)) if ok.any() else height


def lattice_vp(coef: Iterable[float], height: int, fallback: tuple[int, int],
               roll: float | None = None) -> tuple[int, int]:
    """Section 11.7: where the fitted rows converge, the next tracked frame's VP (int px).

    From the lattice's terms of degree at most one at the bottom (``c0, c1, d0, d1``), ``d(t) = 0``
    at ``t = -d0 / d1``, clamped to ``[-8 H, -H / 4]`` (``-8 H`` where ``d1 <= 0``: rows that do
    not converge upwards keep their bottom direction through a far VP); the VP is
    ``(round_half_even(c0 + c1 t), round_half_even((H-1) + t))`` (float64, this order),
    ``fallback`` (the comb's VP) where that is not finite. ``roll``: 11.3.2's ``g`` where
    ``lattice_roll_grid > 0`` (else ``None``): the rows converge where the central row's own
    spacing vanishes, so ``d0 - g c0`` and ``d1 - g c1`` (float64) take the places of ``d0`` and ``d1``.
    """
    c = np.asarray(tuple(coef), np.float64)
    c0, c1, d0, d1 = c[0], c[1], c[4], c[5]
    if roll is not None:
        d0, d1 = d0 - np.float64(roll) * c0, d1 - np.float64(roll) * c1
    far, near = -np.float64(8 * height), -np.float64(height) / 4
    t = min(max(-d0 / d1, far), near) if d1 > 0 else far
    x, y = c0 + c1 * t, np.float64(height - 1) + t
    if not (np.isfinite(x) and np.isfinite(y)):
        return fallback
    return int(np.rint(x)), int(np.rint(y))


def confirms(spacing: int, previous: int, params: Params) -> bool:
    """Section 11.7's acquisition: a lattice found without a tracked row is trusted when the
    frame before had an ``ok`` lattice (``previous`` its comb spacing, 0 if none) whose spacing
    agrees (:func:`~torchrow.reference.lattice.spacing_near`, the tracked comb's rule)."""
    return previous > 0 and bool(spacing_near(spacing, previous, params))


def frame_state(status: str, last: str | None, y_end: int | None, y_res: int, height: int, params: Params,
                confirmed: bool) -> str:
    """Section 11.7's state of a frame: ``lost`` / ``headland`` when not ``ok``, else by the row
    end; ``lost`` too where rows lie ahead but the lattice is not ``confirmed`` (:func:`confirms`)."""
    if status != "ok":
        return "headland" if last in ("row_end_ahead", "headland") else "lost"
    if y_end is None or y_end > (height - 1) - int(math.floor(np.float64(params.lattice_headland_frac) * height)):
        return "headland"
    if not confirmed:
        return "lost"
    if y_end > y_res + params.lattice_end_margin:
        return "row_end_ahead"
    return "in_row"


@dataclass(frozen=True)
class LatticeSequenceState:
    """What the lattice tracker carries for one sequence (11.7).

    ``frames``: frames processed; ``age``: frames since the last full search (that frame counts
    1); ``last``: the previous frame's state; ``vp``: its lattice VP (:func:`lattice_vp`);
    ``spacing``: its comb spacing where its status was ``ok``, else 0 (the lattice a full search
    without a tracked row confirms, :func:`confirms`);
    ``centre``: the tracked row's bottom-row x for the next frame (``None``: no identity, the next
    frame starts from ``W/2`` with a full search); ``pending``: the row change the next frame
    reports (its central row is the previous frame's row ``k = pending``); ``grid_vp``: the VP
    the last full search of an ``ok`` frame (or of frame 0) chose on the grid, whose window the
    next full search takes.
    """

    width: int
    height: int
    frames: int = 0
    age: int = 0
    last: str | None = None
    vp: tuple[int, int] | None = None
    spacing: int = 0
    centre: float | None = None
    pending: int = 0
    grid_vp: tuple[int, int] | None = None


class LatticeTracker:
    """Section 11.7 on one sequence of frames, frame by frame (:class:`torchrow.reference.Tracker`
    runs it in improved mode, with its ``track_iter``/``track``).

    Parameters
    ----------
    params : Params
        Improved-mode constants (:func:`check_lattice_tracker`); frames are resized to ``video_width``.
    hfov_deg, camera : optional
        As :class:`torchrow.reference.Tracker`; with a camera the records carry ``lateral_m``,
        ``heading_rad``, ``spacing_m`` and ``row_end_m``.
    """

    def __init__(self, params: Params, hfov_deg: float | None = None, camera: CameraModel | None = None) -> None:
        check_lattice_tracker(params)
        check_optics(hfov_deg, camera)
        self.params = params
        self.hfov_deg = hfov_deg
        self.camera = camera

    def prepare(self, frame: np.ndarray) -> np.ndarray:
        """Convert to ``uint8 (H, W, 3)`` RGB and resize to ``params.video_width``."""
        if not isinstance(frame, np.ndarray):
            raise TypeError(f"expected a numpy array (H, W, 3), got {type(frame).__name__}")
        return resize_to_width(to_rgb8(frame), self.params.video_width, self.params.max_pixels)

    def step(self, frame: np.ndarray, state: LatticeSequenceState | None = None, *, name: str | None = None,
             source: str | None = None, index: int | None = None,
             evidence: np.ndarray | None = None) -> tuple[FrameResult, LatticeSequenceState]:
        """One frame (any size, resized): its record and the new state (``None`` starts a sequence).

        ``evidence``: the caller's row mask at the frame's own size (11.1.1), resized by
        :func:`torchrow.core.io.evidence_mask` and read in place of the green mask by every
        section 11 pass of this frame (the tracked pass and a redo)."""
        rgb = self.prepare(frame)
        h, w = rgb.shape[:2]
        mask = None if evidence is None else evidence_mask(evidence, w, h)
        if state is None:
            state = LatticeSequenceState(width=w, height=h)
        elif (h, w) != (state.height, state.width):
            raise ValueError(f"frame of working size {w}x{h} in a sequence of {state.width}x{state.height}")
        p = self.params.tracking()  # section 11 with the tracker's bound on the refits
        top = horizon_row(0, p)
        tracked = state.centre is not None
        full = not tracked or state.age >= p.lattice_track_every
        centre = state.centre if state.centre is not None else np.float64(w) / 2
        # a sequence's full search takes the grid near its last grid VP (frame 0: the whole grid);
        # after a frame that was not ok, one more grid height, in turn, so that a loss sweeps the
        # whole grid in len(lattice_vp_heights) frames at a bounded cost per frame (11.7)
        sweep = state.frames % len(p.lattice_vp_heights) if state.grid_vp is not None and state.spacing == 0 else None
        wide = LatticePrior(float(centre), near=state.grid_vp, sweep=sweep)
        # section 1 only where the grid is searched (a full search or a redo) and counts from it
        def grid_sky() -> int:
            return sky_row(rgb, p) if p.lattice_vp_sky_origin() else 0

        imp = improved_rows(rgb, 0, None, p, wide if full else LatticePrior(float(centre), state.vp, state.spacing),
                            grid_sky() if full else 0, mask)
        res = improved_result(imp, w, h, top, p, name)
        redo = False
        if not full and res.status != "ok":  # a tracked frame that fails is searched again in full
            redo = True
            imp = improved_rows(rgb, 0, None, p, wide, grid_sky(), mask)
            res = improved_result(imp, w, h, top, p, name)
        fit = imp.fit
        ok = res.status == "ok"
        y_end = row_end(fit.lit, p) if ok else None
        st = frame_state(res.status, state.last, y_end, resolvable_row(fit.coef, h, p, fit.roll), h, p,
                         tracked or confirms(fit.spacing, state.spacing, p))
        change = state.pending if tracked and ok else 0
        new_centre, pending = None, 0
        rolled = p.lattice_roll_grid > 0
        g = np.float64(fit.roll)
        if st in ("in_row", "row_end_ahead"):
            x0, d0 = np.float64(fit.coef[0]), np.float64(fit.coef[4])
            # with a projective spacing (11.3.2) the central row's own spacing, and the neighbour's own x
            lim = (np.float64(0.5) + np.float64(p.lattice_track_hysteresis)) * (d0 - g * x0 if rolled else d0)
            off = x0 - np.float64(w) / 2
            pending = -1 if off > lim else 1 if off < -lim else 0
            nxt = x0 + np.float64(pending) * d0
            new_centre = float(nxt / (np.float64(1.0) + g * np.float64(pending)) if rolled else nxt)
        new = LatticeSequenceState(width=w, height=h, frames=state.frames + 1,
                                   age=1 if (full or redo) else state.age + 1, last=st,
                                   vp=lattice_vp(fit.coef, h, fit.vp, fit.roll if rolled else None),
                                   spacing=int(fit.spacing) if ok else 0, centre=new_centre, pending=pending,
                                   grid_vp=fit.vp if (full or redo) and (ok or state.grid_vp is None) else state.grid_vp)
        track = LatticeTrack(st, change, y_end if st == "row_end_ahead" else None, full or redo, redo)
        out = FrameResult.build(res, source=source, frame=state.frames if index is None else index,
                                hough_ran=full or redo, hough_redo=redo, confidence=imp.image_confidence,
                                hfov_deg=self.hfov_deg, camera=self.camera, lattice=track)
        return out, new
