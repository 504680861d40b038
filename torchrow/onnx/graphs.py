"""Static-shape, scatter-free formulation of the image-mode detector and of the tracker step
(:class:`StaticTrackerStep`), and the lattice tracker step of the improved mode
(:class:`StaticLatticeStep`, at the end), for ONNX export (:mod:`torchrow.onnx.export`).

Same results as :class:`torchrow.engines.detector.CropRowDetector` (ALGORITHM.md sections 1 and 3-7),
written so that ``torch.onnx.export(..., dynamo=True)`` gives a graph whose every shape is
fixed by ``(B, H, W)`` and the parameters alone:

* **LAB** (section 3) is computed in the graph in float64
  (:func:`torchrow.functional.cielab.lab_formula`), not gathered from the
  400 MB shared table. Its values are not always bit-identical to the table (the table comes
  from kornia's BLAS ``einsum``), but the box decisions are: ``scripts``/tests check all
  2**24 colours (see :func:`torchrow.onnx.checks.check_lab`). The vegetation colour's own LAB
  ``c`` is a graph **input** read from the shared table on the host, so ``c - k`` and
  ``c + k`` are the reference's bits.
* **Hough voting** (section 5), :class:`~torchrow.functional.hough.StaticVoter`: by default
  one scatter-add vote (``ScatterElements`` with ``reduction="add"``, onnxruntime) of the
  Hough input's compact pixel list, updated by the erased band only. With
  ``scatter_free=True`` (TensorRT cannot take a scatter with a reduction) for every pickable
  angle a constant permutation (:func:`~torchrow.functional.hough.vote_tables`) lists the
  pixels sorted by their rho index (from the shared
  :func:`torchrow.core.tables.rho_index_table`), so the votes of one rho cell are a run of
  that order: votes = differences of the prefix sum of the gathered alive mask at the runs'
  constant ends (``Gather``, ``CumSum``, ``GatherElements``, ``Sub``), re-voted at every
  step. Both are exact (integer counts, no float in the graph decides a vote).
* **Line search** (sections 5-6): the one state machine of
  :func:`~torchrow.functional.vanishing.find_lines`, as one ONNX ``Loop`` that stops once
  every image is done (bounded by :func:`~torchrow.functional.vanishing.max_steps`); in a
  step, the extraction and the vanishing-point check each sit in an ``If`` that runs only
  when some image needs it. ``control_flow=False``: every step to the bound, masked.
* **RANSAC band points** (section 7) keep a static ``P = max(ransac_max_points,
  ransac_subsample)`` points per row (``TopK`` with a static ``k``) and score every
  hypothesis with the spec's exact expression (no matmul, no data-dependent fallback).
* The last lines of 7.5 (``atan2``/``cos``/``sin`` of the principal direction) and the row
  validity of 7.6 run on the host (:func:`finish_rows`): ONNX has no ``Atan2`` and
  onnxruntime's CPU ``Atan`` is float32-only. The graph returns the weighted centroid and
  scatter moments of each row's inliers instead.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch
from torch import nn

from torchrow.core.batch import LINE_FIELDS
from torchrow.core.params import Params
from torchrow.core.tables import hypothesis_table, rgb_code
from torchrow.functional import lattice as flattice
from torchrow.functional import lattice_tracking as flt
from torchrow.functional import ransac as fransac
from torchrow.functional import sky as fsky
from torchrow.functional import tracking as ftrack
from torchrow.functional import vegetation as fveg
from torchrow.functional._checks import below_horizon
from torchrow.functional._flow import check_flow, choose
from torchrow.functional.cielab import lab_formula, linear_lut
from torchrow.functional.hough import StaticVoter, pixel_list
from torchrow.functional.vanishing import LineSearch, find_lines
from torchrow.reference.lattice_tracking import check_lattice_tracker

__all__ = ["StaticDetector", "finish_rows", "GRAPH_OUTPUTS", "StaticTrackerStep", "TRACKER_STATE", "TRACKER_STEP",
           "TRACKER_INPUTS", "TRACKER_OUTPUTS", "StaticLatticeStep", "LATTICE_STATE", "LATTICE_INPUTS",
           "LATTICE_OUTPUTS", "lattice_results"]

def raw_mask(images: torch.Tensor, veg_lab: torch.Tensor, k: float, sky: torch.Tensor,
             lut: torch.Tensor | None = None) -> torch.Tensor:
    """Section 3.2 with the colour's LAB ``veg_lab`` float64 ``(B, 3)`` given: bool ``(B, H, W)``."""
    lo = (veg_lab - k).view(-1, 3, 1, 1)
    hi = (veg_lab + k).view(-1, 3, 1, 1)
    v = lab_formula(images, lut)
    inside = ((lo <= v) & (v <= hi)).all(dim=1)
    return inside & below_horizon(sky, images.shape[2], as_bool=True)


#: Names of the exported graph's outputs, in order (see :class:`StaticDetector`).
GRAPH_OUTPUTS = ("sky", "bushy", "has_veg", "n_rows", "hough_theta", "hough_rho", "hough_weight", "hough_valid",
                 "out_theta", "out_rho", "out_weight", "out_valid", "vp", "has_vp", "fit_cx", "fit_cy",
                 "fit_sxx", "fit_syy", "fit_sxy", "row_hypothesis", "row_support", "row_present")


class StaticDetector(nn.Module):
    """The exportable image-mode detector for one static working size ``width x height``.

    ``forward(images uint8 (B, 3, H, W), veg_lab float64 (B, 3))`` -> the tuple of
    :data:`GRAPH_OUTPUTS`: ``sky``/``n_rows`` int64 ``(B,)``, ``bushy``/``has_veg``/``has_vp``
    bool ``(B,)``; Hough lines int64 ``(B, n_rows)`` + bool valid; dropped outliers int64
    ``(B, O)`` + bool valid; ``vp`` float64 ``(B, 2)``; per row ``(B, n_rows)``: weighted
    inlier centroid ``fit_cx/fit_cy`` and scatter ``fit_sxx/fit_syy/fit_sxy`` (float64),
    ``row_hypothesis`` int64 (best hypothesis), ``row_support``/``row_present`` bool.
    ``veg_lab`` is the LAB of the vegetation colour (ALGORITHM.md section 2, computed on the
    host). :func:`finish_rows` turns the fits into rows.

    Parameters
    ----------
    height, width : int
        The working size the graph is built for.
    params : Params, optional
    score_chunks : int
        The RANSAC hypotheses are scored in this many static chunks (bounds memory).
    flow : str
        How the line search skips finished work (:mod:`torchrow.functional._flow`):
        ``"loop"`` (default: the line search is one ONNX ``Loop`` that stops when every image
        is done, vote chunks past every image's pixel count sit in ``If`` nodes), ``"cond"``
        (the line search unrolled to its static bound, one ``If`` per step: a graph ~12x
        larger that takes ~20x longer to export), ``"always"`` (no control flow in the
        graph), ``"sync"`` (eager only).
    scatter_free : bool
        Vote by prefix sums of constant permutations, re-voting at every step, instead of one
        scatter-add vote updated by the erased bands (:class:`~torchrow.functional.hough.StaticVoter`).
    """

    lut: torch.Tensor  # buffers: the linearisation table and the RANSAC hypotheses
    u: torch.Tensor

    def __init__(self, height: int = 240, width: int = 320, params: Params | None = None,
                 score_chunks: int = 4, flow: str = "loop", scatter_free: bool = False) -> None:
        super().__init__()
        self.params = params or Params()
        self.height, self.width = int(height), int(width)
        self.score_chunks = int(score_chunks)
        self.flow = check_flow(flow)
        self.voter = StaticVoter(self.height, self.width, self.params, flow, scatter_free)
        hw = self.height * self.width
        #: list entries the short band-point form covers (an eighth of the image)
        self.band_tier = max(min(hw, fransac.max_kept(self.params)), hw // 8)
        self.register_buffer("lut", torch.from_numpy(linear_lut().copy()), persistent=False)
        self.register_buffer("u", torch.from_numpy(hypothesis_table(self.params.seed, self.params.ransac_trials).copy()),
                             persistent=False)

    # one copy of each constant: the shared trig tables are the voter's
    cos = property(lambda self: self.voter.cos)
    sin = property(lambda self: self.voter.sin)

    # -- sections 5-6 ---------------------------------------------------------------------
    def find_lines(self, hin: torch.Tensor) -> LineSearch:
        """Sections 5-6: :func:`torchrow.functional.vanishing.find_lines` with this graph's
        :class:`~torchrow.functional.hough.StaticVoter` and flow."""
        # hin may be a dtype view (Canny works on uint8): a copy keeps the view's
        # decomposition out of the torch.cond branches, which an exported program could not
        # re-decompose
        return find_lines(hin.clone(), self.params, self.voter, self.flow)

    # -- section 7 ------------------------------------------------------------------------
    def band_points(self, veg: torch.Tensor, theta: torch.Tensor, rho: torch.Tensor, band: torch.Tensor,
                    track: tuple[torch.Tensor, torch.Tensor] | None = None) -> fransac.BandPoints:
        """Steps 7 and 7.2 with a static ``P``
        (:func:`~torchrow.functional.ransac.list_band_points`) on the vegetation's compact
        pixel list: its first :attr:`band_tier` entries when no image has more vegetation
        (on CRBD at most 12%, on the Caterra video 7% of the image), the whole list
        otherwise. ``track = (a, b)``: the band around rows ``x = a*y + b`` (video mode)."""
        p = self.params
        hw = self.height * self.width
        size = min(hw, fransac.max_kept(p))  # 467 with the defaults: no row keeps more
        idx, count = pixel_list(veg)

        def over(n: int):
            def run(idx, count, theta, rho, band, *track):
                return fransac.list_band_points(idx[:, :n], count, theta, rho, band, self.width, p, self.cos,
                                                self.sin, tuple(track) or None, size).astuple()
            return run

        operands = (idx, count, theta, rho, band) + (tuple(track) if track is not None else ())
        if self.band_tier >= hw:
            return fransac.BandPoints(*over(hw)(*operands))
        return fransac.BandPoints(*choose(self.flow, count.max() <= self.band_tier, over(self.band_tier), over(hw),
                                          operands))

    def fit_rows(self, veg, theta, rho, present, vp, band, track=None) -> fransac.RowMoments:
        """Steps 7.1-7.5 up to the weighted moments of the best hypothesis' inliers (the
        arguments of :func:`torchrow.functional.ransac.fit_rows`)."""
        p = self.params
        dev = veg.device
        px, py, n_keep, v_keep, n = self.band_points(veg, theta, rho, band, track).astuple()
        pp = px.shape[2]
        support = present & (n + n // 2 >= p.ransac_min_points)
        total = (n_keep + v_keep).to(torch.float64)
        valid_pt = torch.arange(pp, device=dev) < n_keep.unsqueeze(2)
        step = -(-self.u.shape[0] // max(1, self.score_chunks))
        best_score, best_t = fransac.score_hypotheses(px, py, n_keep, v_keep, vp, self.u, step, p.ransac_threshold,
                                                      fransac.exact_counts(*fransac.padded_points(px, py, valid_pt)))
        support = support & (best_score >= 0)
        cx, cy, sxx, syy, sxy = fransac.best_moments(self.u, best_t, total, px, py, n_keep, v_keep, valid_pt, vp,
                                                     p.ransac_threshold)
        hyp = torch.where(support, best_t, torch.full_like(best_t, -1))
        return fransac.RowMoments(cx, cy, sxx, syy, sxy, hyp, support)

    def forward(self, images: torch.Tensor, veg_lab: torch.Tensor):
        p = self.params
        _bsz, _, h, w = images.shape
        if (h, w) != (self.height, self.width):
            raise ValueError(f"StaticDetector built for {self.width}x{self.height}, got images {w}x{h}")
        sky = fsky.sky_row(images, p)
        raw = raw_mask(images, veg_lab.to(torch.float64), float(p.veg_tol), sky, self.lut)
        veg = fveg.remove_bushy(raw, sky, p)
        has_veg = veg.flatten(1).any(dim=1)
        hin, bushy = fveg.hough_input(veg, sky, p)
        ls = self.find_lines(hin)
        band = fransac.ransac_band(bushy, w, p)
        present = ls.valid & ls.has_vp.unsqueeze(1)
        fit = self.fit_rows(veg, ls.theta, ls.rho, present, ls.vp, band)
        # outputs matched to GRAPH_OUTPUTS by name; a flat tuple, the form every exporter takes
        named = {"sky": sky, "bushy": bushy, "has_veg": has_veg, "row_present": present,
                 **{f: getattr(ls, a) for f, a in LINE_FIELDS.items()},
                 **{"fit_" + f: getattr(fit, f) for f in ("cx", "cy", "sxx", "syy", "sxy")},
                 "row_hypothesis": fit.hypothesis, "row_support": fit.support}
        return tuple(named[f] for f in GRAPH_OUTPUTS)


def finish_rows(outputs: dict, height: int, width: int, params: Params) -> fransac.Rows:
    """Host side of 7.5-7.6 from the graph's outputs (``{name: tensor}`` of
    :data:`GRAPH_OUTPUTS`): the principal direction of each row's moments (exactly as
    :func:`torchrow.functional.ransac.fit_rows` computes it), then validity."""
    o = outputs
    moments = fransac.RowMoments(o["fit_cx"], o["fit_cy"], o["fit_sxx"], o["fit_syy"], o["fit_sxy"],
                                 o["row_hypothesis"], o["row_support"])
    present = o["row_present"]
    band = torch.full(present.shape[:1], params.hough_band_px(width), dtype=torch.int64)
    return fransac.validate_rows(moments.direction(), present, height, band, params)


# ------------------------------------------------------------------------------------------
# The tracker step (ALGORITHM.md section 8)
# ------------------------------------------------------------------------------------------

#: Tracker-state fields that travel through the graph (``veg_color`` stays on the host; the
#: graph takes its :func:`~torchrow.functional.vegetation.min_k_table`, ``k_table``).
TRACKER_STATE = ("sky", "info0", "ready", "frames", "age", "prev_valid", "vp", "has_vp", "row_a", "row_b",
                 "row_present")
#: Inputs of the exported tracker step, in order (see :class:`StaticTrackerStep`): the frames,
#: each sequence's ``k`` table, the active mask, then ``state_<field>`` of the state.
TRACKER_INPUTS = ("images", "k_table", "active") + tuple("state_" + f for f in TRACKER_STATE)
#: Fields of :class:`~torchrow.functional.tracking.TrackStep` the graph returns (all but ``active``).
TRACKER_STEP = tuple(f for f in ftrack.TrackStep.__dataclass_fields__ if f != "active")
#: Outputs of the exported tracker step: the step's fields, then ``next_<field>`` of the new state.
TRACKER_OUTPUTS = TRACKER_STEP + tuple("next_" + f for f in TRACKER_STATE)


class StaticTrackerStep(nn.Module):
    """The exportable tracker step: one frame of ``B`` sequences + their state -> rows + new state.

    The rules are :func:`torchrow.functional.tracking.advance` itself, composed from the
    static stages of :class:`StaticDetector`. With ``control_flow=True`` (default) the
    tracked fit and the Hough stage each sit in a ``torch.cond`` (an ONNX ``If``) that skips
    them when no sequence of the batch needs them: a tracked frame of one camera then costs
    a small part of a Hough frame. ``control_flow=False`` runs both for the whole batch and
    lets masks choose (no ``If``; for runtimes without control flow).
    Differences from the eager :class:`torchrow.Tracker`, all outside its results:

    * **Frame 0 on the host and in the graph.** A sequence with ``active & ~ready`` takes
      this frame as frame 0. The host computes its vegetation colour (section 2: colour
      clustering has data-dependent shapes) and its sky (section 1, passed as ``state_sky``:
      it is needed once per sequence, and in the graph it cost every frame about 5 ms, since
      a graph cannot skip it without an ``If`` whose branch, the sky's median filters,
      takes torch's exporter tens of minutes to trace); the graph computes ``info0`` (the
      raw fraction at ``video_k_start``).
    * **Segmentation by lookup.** The colour is fixed for the whole sequence, so the host
      turns it once into the smallest admitting ``k`` of every 24-bit colour
      (:func:`~torchrow.functional.vegetation.min_k_table`, from the shared LAB table: the
      eager tracker's values by construction), the graph input ``k_table`` uint8
      ``(B, 2**24)``. A frame's section 3 is then one ``Gather`` per pixel: computing LAB in
      the graph (three float64 ``Pow`` per pixel) was half of onnxruntime's time per frame
      (34 of 70 ms at 500x281).
    * **Adaptive k** counts the pixels of every ``k`` with one histogram
      (``ScatterElements`` add) and its prefix sum; the scatter-free form counts with
      comparisons.
    * **Step 7.5-7.6 in the graph without** ``atan2`` (ONNX has none):
      :func:`~torchrow.functional.ransac.principal_direction` and
      :func:`~torchrow.functional.ransac.validate_rows` with ``trig_free=True``. Rows agree
      with the eager tracker to a few ulps; a decision could differ only for a value within
      rounding of a threshold.

    ``forward(images uint8 (B, 3, H, W), k_table uint8 (B, 2**24), active bool (B,), *state)``
    with the state fields :data:`TRACKER_STATE` (dtypes and shapes of
    :class:`~torchrow.functional.tracking.TrackerState`) returns the tuple
    :data:`TRACKER_OUTPUTS`. Inactive sequences keep their state.

    Memory: the detector's (the vote gathers ``(B, A, H*W)`` int32, band temporaries
    ``(B, n_rows, H*W)``), the input ``k_table`` (16 MiB per sequence) and, in the scatter-free
    form, ``(B, video_k_max - video_k_min + 1, H*W)`` comparisons for adaptive k: an estimated
    250 MB per frame at 500x281 (three int32 copies of the vote gather).

    Parameters
    ----------
    height, width : int
        Working size of the frames (``params.video_width`` wide).
    params : Params, optional
    score_chunks : int
        RANSAC scoring chunks (bounds memory).
    control_flow : bool
        Skip unneeded branches with ``torch.cond`` (ONNX ``If``) instead of masking them
        (the Hough stage with its Canny input, the tracked fit, and the line search's finished
        steps).
    scatter_free : bool
        The detector's scatter-free vote (:class:`StaticDetector`).
    """

    def __init__(self, height: int, width: int, params: Params | None = None, score_chunks: int = 4,
                 control_flow: bool = True, scatter_free: bool = False) -> None:
        super().__init__()
        self.control_flow = bool(control_flow)
        self.det = StaticDetector(height, width, params, score_chunks, "loop" if self.control_flow else "always",
                                  scatter_free)
        self.scatter_free = bool(scatter_free)
        self.params = self.det.params
        self.height, self.width = self.det.height, self.det.width

    def _fit_rows(self, veg, theta, rho, present, vp, band, track=None) -> fransac.RowFit:
        return self.det.fit_rows(veg, theta, rho, present, vp, band, track).direction(trig_free=True)

    def segment(self, images: torch.Tensor, k_table: torch.Tensor, sky: torch.Tensor, info0: torch.Tensor,
                start: torch.Tensor):
        """Section 3 with adaptive ``k`` (and frame 0's ``info0`` where ``start``):
        ``veg`` bool ``(B, H, W)``, ``k`` int64, ``bushy`` bool, ``info0`` float64 ``(B,)``.

        ``k_table`` uint8 ``(B, 2**24)``: each sequence's
        :func:`~torchrow.functional.vegetation.min_k_table`, so a pixel's smallest admitting
        ``k`` is one lookup of its colour code (no LAB in the graph)."""
        p = self.params
        bsz, _, h, w = images.shape
        n_k = p.video_k_max - p.video_k_min + 1
        skyc = sky.clamp(0, h)
        below = below_horizon(skyc, h, as_bool=True).expand(bsz, h, w)
        below = below.reshape(bsz, 1, h * w)
        x = images.to(torch.int32)
        code = rgb_code(x[:, 0], x[:, 1], x[:, 2]).reshape(bsz, h * w).to(torch.int64)
        code = code + (torch.arange(bsz, device=images.device) * (1 << 24)).view(-1, 1)
        # a flat index_select exports as one Gather; uint8 k indices (k - video_k_min, n_k: none)
        kstar = torch.index_select(k_table.reshape(-1), 0, code.reshape(-1)).view(bsz, 1, h * w)
        if self.scatter_free:  # (B, n_k) by comparisons; int32 sums (at most H*W) halve the traffic
            ks = torch.arange(n_k, device=images.device, dtype=torch.uint8).view(1, -1, 1)
            counts = ((kstar <= ks) & below).sum(2, dtype=torch.int32)
        else:  # a histogram (one ScatterElements add) and its prefix sum: a tenth of the comparisons' time
            hist = torch.zeros((bsz, n_k + 1), dtype=torch.int32, device=images.device).scatter_add(
                1, kstar.view(bsz, h * w).to(torch.int64), below.view(bsz, h * w).to(torch.int32))
            counts = torch.cumsum(hist[:, :n_k], dim=1, dtype=torch.int32)
        frac = fveg.k_fractions(counts, skyc, h, w)
        info0 = torch.where(start, frac[:, p.video_k_start - p.video_k_min], info0)
        k = fveg.choose_k(frac, info0, p)
        raw = ((kstar <= (k - p.video_k_min).to(torch.uint8).view(-1, 1, 1)) & below).view(bsz, h, w)
        veg, bushy = ftrack.finish_segment(raw, sky, p)
        return veg, k, bushy, info0

    def forward(self, images: torch.Tensor, k_table: torch.Tensor, active: torch.Tensor, sky: torch.Tensor,
                info0: torch.Tensor, ready: torch.Tensor, frames: torch.Tensor, age: torch.Tensor,
                prev_valid: torch.Tensor, vp: torch.Tensor, has_vp: torch.Tensor, row_a: torch.Tensor,
                row_b: torch.Tensor, row_present: torch.Tensor):
        p = self.params
        bsz, _, h, w = images.shape
        if (h, w) != (self.height, self.width):
            raise ValueError(f"StaticTrackerStep built for {self.width}x{self.height}, got frames {w}x{h}")
        start = active & ~ready
        flow = "cond" if self.control_flow else "always"
        veg, k, bushy, info0 = self.segment(images, k_table, sky, info0, start)
        state = ftrack.TrackerState(
            sky=sky, veg_color=torch.zeros((bsz, 3), dtype=torch.uint8, device=images.device), info0=info0,
            ready=ready | start, frames=frames, age=age, prev_valid=prev_valid, vp=vp, has_vp=has_vp, row_a=row_a,
            row_b=row_b, row_present=row_present)
        stages = ftrack.Stages(find_lines=self.det.find_lines, fit_rows=self._fit_rows, trig_free=True,
                               branches=flow)
        step, new = ftrack.advance(veg, k, bushy, active, state, p, stages)
        return tuple(getattr(step, f) for f in TRACKER_STEP) + tuple(getattr(new, f) for f in TRACKER_STATE)


# ------------------------------------------------------------------------------------------
# The lattice tracker step (ALGORITHM.md 11.7, improved mode)
# ------------------------------------------------------------------------------------------

#: Fields of :class:`~torchrow.functional.lattice_tracking.LatticeTrackerState`, the lattice
#: tracker's state, in the order they travel through the graph.
LATTICE_STATE = tuple(f.name for f in dataclasses.fields(flt.LatticeTrackerState))
_ROWS = tuple(f.name for f in dataclasses.fields(flattice.LatticeRows))
_STEP = tuple(f.name for f in dataclasses.fields(flt.LatticeStep) if f.name not in ("rows", "active"))
#: Inputs of the exported lattice tracker step, in order (see :class:`StaticLatticeStep`): the
#: frames, the active mask, then ``state_<field>`` of the state.
LATTICE_INPUTS = ("images", "active") + tuple("state_" + f for f in LATTICE_STATE)
#: Outputs of the exported lattice tracker step, in order: ``rows_<field>`` of the step's
#: :class:`~torchrow.functional.lattice.LatticeRows`, the other fields of
#: :class:`~torchrow.functional.lattice_tracking.LatticeStep` (all but ``rows`` and
#: ``active``), then ``next_<field>`` of the new state.
LATTICE_OUTPUTS = tuple("rows_" + f for f in _ROWS) + _STEP + tuple("next_" + f for f in LATTICE_STATE)


def lattice_results(outputs: Sequence[torch.Tensor],
                    active: torch.Tensor) -> tuple[flt.LatticeStep, flt.LatticeTrackerState]:
    """The step and the new state from the graph's outputs (:data:`LATTICE_OUTPUTS`, in order)
    and the ``active`` mask it was given: the inverse of :class:`StaticLatticeStep`'s outputs."""
    n_rows, n_step = len(_ROWS), len(_STEP)
    rows = flattice.LatticeRows(*outputs[:n_rows])
    step = flt.LatticeStep(rows=rows, **dict(zip(_STEP, outputs[n_rows:n_rows + n_step])), active=active)
    return step, flt.LatticeTrackerState(*outputs[n_rows + n_step:])


class StaticLatticeStep(nn.Module):
    """The exportable lattice tracker step (improved mode): one frame of ``B`` sequences + their
    state -> the lattice, the tracker's fields and the new state.

    The rules are :func:`torchrow.functional.lattice_tracking.lattice_advance` itself, with
    ``flow="loop"`` (``control_flow=True``, default): the least-squares refits of each fit are
    one ONNX ``Loop`` that stops once every image has stopped, and the VP grid search and the
    full-search redo of a failed tracked frame each sit in an ``If`` that runs only when some
    sequence needs it. ``control_flow=False`` (``flow="always"``) runs every refit, the grid
    search and the redo for the whole batch and lets masks choose (no ``Loop`` or ``If``).
    Section 11.2's tables (the VP search's bins, the comb's candidate tables) are constants of
    the graph, built for its working size (:func:`~torchrow.onnx.export.to_onnx` builds them
    with one eager step before tracing).
    Unlike section 8's tracker step, nothing runs on the host: the lattice tracker has no
    frame-0 colour or sky (ALGORITHM.md 11.7).

    ``forward(images uint8 (B, 3, H, W), active bool (B,), *state)`` with the state fields
    :data:`LATTICE_STATE` (dtypes and shapes of
    :class:`~torchrow.functional.lattice_tracking.LatticeTrackerState`) returns the tuple
    :data:`LATTICE_OUTPUTS` (:func:`lattice_results` reads it back). Inactive sequences keep
    their state.

    Parameters
    ----------
    height, width : int
        Working size of the frames (``params.video_width`` wide).
    params : Params
        Improved mode under the lattice tracker's conditions
        (:func:`torchrow.reference.lattice_tracking.check_lattice_tracker`).
    control_flow : bool
        ``Loop`` and ``If`` (default), or masks.
    """

    def __init__(self, height: int, width: int, params: Params, control_flow: bool = True) -> None:
        super().__init__()
        check_lattice_tracker(params)
        self.params = params
        self.height, self.width = int(height), int(width)
        self.flow = "loop" if control_flow else "always"

    def forward(self, images: torch.Tensor, active: torch.Tensor, *state: torch.Tensor):
        h, w = images.shape[2], images.shape[3]
        if (h, w) != (self.height, self.width):
            raise ValueError(f"StaticLatticeStep built for {self.width}x{self.height}, got frames {w}x{h}")
        step, new = flt.lattice_advance(images, active, flt.LatticeTrackerState(*state), self.params, self.flow)
        return (tuple(getattr(step.rows, f) for f in _ROWS) + tuple(getattr(step, f) for f in _STEP)
                + tuple(getattr(new, f) for f in LATTICE_STATE))
