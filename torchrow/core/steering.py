"""Video-mode outputs shared by both trackers: steering signals, confidence, per-frame result.

Definitions (one place; :mod:`torchrow.reference.tracking` and :mod:`torchrow.functional.tracking`
both use them). Pixel coordinates are those of the working image (``x`` = column, ``y`` =
row, origin at the top-left pixel); ``W``, ``H`` = working size; the image centre is
``x = W/2``, the convention of CRBD's ground truth and of :mod:`torchrow.evaluation.synthetic`.

=================  =====================================================================
signal             definition, unit, sign
=================  =====================================================================
``heading_px``     ``vp_x - W/2`` (px): the vanishing point's horizontal offset from the
                   image centre. Image convention: positive = the rows head to the
                   **right** of the optical axis. ``None`` without a vanishing point.
``heading_rad``    ``atan((W/2 - vp_x) / f)`` (rad) with ``f = (W/2) / tan(hfov/2)``
                   from the horizontal field of view: the yaw error in REP 103 sign,
                   positive = the robot must turn **left** (counter-clockwise seen from
                   above) to point along the rows. Note the sign is opposite to
                   ``heading_px``. ``None`` without a field of view or vanishing point.
                   With a camera model instead: the rows' heading on the ground, same
                   sign (:mod:`torchrow.core.camera`).
``lateral_m``      With a camera model (:mod:`torchrow.core.camera`, which defines them
``spacing_m``      and draws their signs): the camera's offset from the central row (m,
                   positive = camera **left** of the row, as ``lateral_px``) and the row
                   spacing on the ground (m). ``None`` without a camera model.
``lateral_px``     ``x_c(H-1) - W/2`` (px): x of the central row on the bottom image row
                   minus the image centre. Image convention: positive = the central row
                   is **right** of the image centre (the robot must move right to sit on
                   it). The central row is the valid row whose bottom x is nearest
                   ``W/2`` (first on ties); the lattice tracker's is its tracked row
                   ``k = 0`` (ALGORITHM.md 11.7), also for ``lateral_m``. ``None`` without
                   a valid row.
``lateral_frac``   ``lateral_px / d`` (dimensionless, same sign), ``d`` = the local row
                   spacing on the bottom image row: the mean distance from the central
                   row to its valid neighbour rows (one or two, in bottom-x order).
                   ``None`` with fewer than two valid rows.
``confidence``     in ``[0, 1]``: the supported fraction of the requested rows,
                   ``sum(coverage_i over valid rows i) / params.n_rows``, where
                   ``coverage_i`` is the fraction of image rows ``y = sky .. H-1`` on
                   which the vegetation mask has a pixel within ``track_band/2``
                   horizontally of the row (``abs(x - (a*y + b)) <= track_band/2``,
                   float64). 1 = all requested rows found, valid and covered with
                   vegetation from the horizon to the bottom; invalid or missing rows
                   count 0. 0 for frames without rows.
=================  =====================================================================

A controller wanting "turn towards the rows and onto the central row" uses, e.g.,
``yaw_rate = k1 * heading_rad - k2 * lateral_frac`` and trusts it in proportion to
``confidence``. Section 8's central row can switch to its neighbour when the robot is half a
row spacing off, so ``lateral_frac`` lives in about ``[-0.5, 0.5]`` and jumps by 1 there; the
lattice tracker's moves to a neighbour only on a frame reporting ``row_change`` (within about
``[-0.6, 0.6]`` otherwise).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from torchrow.core.camera import CameraModel, MetricSteering, metric_steering, row_end_distance
from torchrow.core.results import ImageResult, Row

__all__ = ["LATTICE_STATES", "LatticeTrack", "RowId",
           "FrameResult", "Steering", "steering", "focal_from_fov", "row_coverage", "confidence", "check_optics"]


@dataclass(frozen=True)
class Steering:
    """The four steering signals of one frame (module docstring: definitions and signs)."""

    heading_px: float | None = None
    heading_rad: float | None = None
    lateral_px: float | None = None
    lateral_frac: float | None = None


def focal_from_fov(width: int, hfov_deg: float) -> float:
    """Pinhole focal length (px) of a ``width``-pixel image with horizontal FOV ``hfov_deg``."""
    if not (0 < hfov_deg < 180):
        raise ValueError(f"horizontal field of view must lie in (0, 180) degrees, got {hfov_deg!r}")
    return (width / 2) / math.tan(math.radians(hfov_deg) / 2)


def check_optics(hfov_deg: float | None, camera: CameraModel | None) -> None:
    """One source of ``heading_rad``: a field of view or a camera model, not both (``ValueError``)."""
    if hfov_deg is not None and camera is not None:
        raise ValueError(f"give a field of view or a camera model, not both (hfov_deg={hfov_deg!r} and a camera "
                         "model, which has its own)")
    if camera is not None and not isinstance(camera, CameraModel):
        raise ValueError(f"camera must be a torchrow.core.camera.CameraModel, got {type(camera).__name__}")


def steering(rows: Sequence[Row], vp: tuple[float, float] | None, width: int, height: int,
             hfov_deg: float | None = None, central: int | None = None) -> Steering:
    """Steering signals of one frame from its rows and vanishing point.

    Parameters
    ----------
    rows : sequence of Row
        Fitted rows ``x = e*y**3 + c*y**2 + a*y + b`` (px); only valid rows are used.
    vp : (float, float) or None
        Vanishing point (px).
    width, height : int
        Working image size ``W``, ``H``.
    hfov_deg : float, optional
        Horizontal field of view (degrees) of the working image, for ``heading_rad``.
    central : int, optional
        The central row's index in ``rows`` (the lattice tracker's tracked row ``k = 0``, its
        neighbours the slots beside it); ``None``: the valid row whose bottom x is nearest ``W/2``.

    Returns
    -------
    Steering
        Signals as defined in the module docstring (``None`` where undefined).
    """
    centre = width / 2
    heading_px = heading_rad = lateral_px = lateral_frac = None
    if vp is not None and math.isfinite(vp[0]):
        heading_px = float(vp[0] - centre)
        if hfov_deg is not None:
            heading_rad = math.atan2(-heading_px, focal_from_fov(width, hfov_deg))
    # the whole polynomial: the improved mode's rows bend (faithful rows have c = e = 0, and
    # x_at gives their a * (H-1) + b bit for bit)
    if central is not None:
        def bottom(i: int) -> float | None:
            return float(rows[i].x_at(float(height - 1))) if 0 <= i < len(rows) and rows[i].valid else None

        x, near = bottom(central), [bottom(central - 1), bottom(central + 1)]
        if x is not None:
            lateral_px = x - centre
            gaps = [abs(n - x) for n in near if n is not None]
            spacing = sum(gaps) / len(gaps) if gaps else 0.0
            lateral_frac = lateral_px / spacing if spacing > 0 else None
        return Steering(heading_px, heading_rad, lateral_px, lateral_frac)
    bottoms = sorted(float(r.x_at(float(height - 1))) for r in rows if r.valid)
    if bottoms:
        # min() keeps the first of equal distances, the order being bottom x
        c = min(range(len(bottoms)), key=lambda i: abs(bottoms[i] - centre))
        lateral_px = float(bottoms[c] - centre)
        gaps = [bottoms[c] - bottoms[c - 1]] if c > 0 else []
        gaps += [bottoms[c + 1] - bottoms[c]] if c + 1 < len(bottoms) else []
        if gaps:
            spacing = sum(gaps) / len(gaps)
            lateral_frac = lateral_px / spacing if spacing > 0 else None
    return Steering(heading_px, heading_rad, lateral_px, lateral_frac)


def row_coverage(veg: np.ndarray, a: float, b: float, sky: int, half_band: float) -> float:
    """Fraction of image rows ``y = sky .. H-1`` with a vegetation pixel near the row.

    A row ``y`` counts when some column ``x`` has ``veg[y, x]`` and
    ``abs(x - (a*y + b)) <= half_band`` (float64, this operation order; the tensor tracker
    evaluates the same expression). ``veg`` is ``bool (H, W)``; 0 when no row lies below
    the horizon.
    """
    h, w = veg.shape
    if sky >= h:
        return 0.0
    ys = np.arange(sky, h, dtype=np.int64)
    xc = np.float64(a) * ys.astype(np.float64) + np.float64(b)
    reach = int(math.ceil(half_band)) + 1
    base = np.floor(np.clip(xc, -reach - 1, w + reach)).astype(np.int64)
    hit = np.zeros(ys.size, bool)
    for d in range(-reach, reach + 1):
        xs = base + d
        inside = (xs >= 0) & (xs < w)
        near = np.abs(xs.astype(np.float64) - xc) <= np.float64(half_band)
        hit |= inside & near & veg[ys, np.clip(xs, 0, w - 1)]
    return float(hit.sum()) / ys.size


def confidence(veg: np.ndarray | None, rows: Sequence[Row], sky: int, n_requested: int,
               half_band: float) -> float:
    """``sum(row_coverage of valid rows) / n_requested`` in ``[0, 1]`` (module docstring)."""
    if veg is None or n_requested < 1:
        return 0.0
    total = sum(row_coverage(veg, r.a, r.b, sky, half_band) for r in rows if r.valid)
    return min(1.0, total / n_requested)


#: The lattice tracker's frame states (ALGORITHM.md 11.7), in the order of their tensor codes.
LATTICE_STATES = ("in_row", "row_end_ahead", "headland", "lost")


@dataclass(frozen=True)
class LatticeTrack:
    """What the lattice tracker (ALGORITHM.md 11.7) adds to a frame: ``state`` (one of
    :data:`LATTICE_STATES`), ``row_change`` (-1, 0, +1: the central row is the previous frame's
    row ``k = row_change``), ``row_end_y`` (image row where the rows end, with ``row_end_ahead``),
    ``full_search`` (the unrestricted search ran) and ``redo`` (it ran because the restricted
    search's frame was not ``ok``)."""

    state: str
    row_change: int = 0
    row_end_y: int | None = None
    full_search: bool = True
    redo: bool = False


class RowId:
    """Running identity of the lattice tracker's row 0 in one sequence, for pictures and plots.

    The id is the sum of the ``row_change`` of the sequence's frames so far, counted from 0 at
    the sequence start: ``row 0`` is the row tracked on frame 0, ``row +1`` the next one to its
    right in the image, and a row change moves the id by one on the frame that reports it. After
    a ``lost`` or ``headland`` frame the tracker takes the row nearest the image centre afresh
    (ALGORITHM.md 11.7), so the count goes on from the last tracked row without proof that it
    is the same row. Feed every frame of the sequence in order (frames without ``row_change``,
    e.g. unreadable ones, count 0).
    """

    def __init__(self) -> None:
        self.current = 0

    def update(self, row_change: int | None) -> int:
        """Add one frame's ``row_change`` (``None`` counts 0); returns the id of its row 0."""
        self.current += int(row_change or 0)
        return self.current


@dataclass
class FrameResult(ImageResult):
    """One video frame: an :class:`ImageResult` plus tracking outputs and steering signals.

    ``frame`` is the 0-based index in its sequence, ``source`` names the sequence, ``hough_ran``
    says whether the Hough stage (sections 4-6) ran on this frame (frame 0, after an invalid
    frame, every ``hough_every`` frames, or as the redo of an invalid tracked frame), and
    ``hough_redo`` whether it ran as such a redo. Tracked frames report the vanishing point
    of the last Hough run, no Hough lines, and ``n_rows`` = number of rows tracked.
    """

    source: str | None = None
    frame: int = 0
    hough_ran: bool = False
    hough_redo: bool = False
    confidence: float = 0.0
    heading_px: float | None = None
    heading_rad: float | None = None
    lateral_px: float | None = None
    lateral_frac: float | None = None
    lateral_m: float | None = None
    spacing_m: float | None = None
    stamp_ns: int | None = None
    #: Lattice tracker only (ALGORITHM.md 11.7; absent from the faithful tracker's records).
    state: str | None = None
    row_change: int | None = None
    row_end_y: int | None = None
    row_end_m: float | None = None

    def to_record(self) -> dict[str, Any]:
        """``torchrow detect``'s record keys plus ``source``, ``frame``, ``hough_ran``,
        ``hough_redo``, ``confidence``, ``heading_px``, ``heading_rad``, ``lateral_px``,
        ``lateral_frac``, ``lateral_m``, ``spacing_m`` (``None`` -> JSON null); ``stamp_ns`` after ``frame`` for frames of
        a ROS bag (the message's header stamp), absent otherwise."""
        rec: dict[str, Any] = {"source": self.source, "frame": int(self.frame)}
        if self.stamp_ns is not None:
            rec["stamp_ns"] = int(self.stamp_ns)
        rec.update(super().to_record())

        def num(v: float | None) -> float | None:
            return None if v is None or not math.isfinite(v) else float(v)

        rec.update(hough_ran=bool(self.hough_ran), hough_redo=bool(self.hough_redo),
                   confidence=float(self.confidence), heading_px=num(self.heading_px),
                   heading_rad=num(self.heading_rad), lateral_px=num(self.lateral_px),
                   lateral_frac=num(self.lateral_frac), lateral_m=num(self.lateral_m),
                   spacing_m=num(self.spacing_m))
        if self.state is not None:
            rec.update(state=self.state, row_change=int(self.row_change or 0), row_end_y=self.row_end_y,
                       row_end_m=num(self.row_end_m))
        return rec

    @classmethod
    def build(cls, base: ImageResult, *, source: str | None, frame: int, hough_ran: bool,
              hough_redo: bool, confidence: float, hfov_deg: float | None,
              camera: CameraModel | None = None, lattice: LatticeTrack | None = None) -> FrameResult:
        """Wrap a detection with its tracking flags and the steering signals of its rows.

        ``camera`` (for any image size: scaled to the working size here) gives ``lateral_m``,
        ``spacing_m`` and ``heading_rad`` (:func:`torchrow.core.camera.metric_steering`);
        ``hfov_deg`` the pixel heading's ``heading_rad``; not both (:func:`check_optics`).
        ``lattice``: the lattice tracker's state (its ``row_end_m`` is computed here from the
        central row, :func:`torchrow.core.camera.row_end_distance`, with a camera).
        """
        check_optics(hfov_deg, camera)
        rows_ok = base.status in ("ok", "invalid")
        # the lattice tracker steers by its tracked row (k = 0), which moves to a neighbour only
        # with a reported row change; section 8 by the row nearest the centre
        central = len(base.rows) // 2 if lattice is not None else None
        st = steering(base.rows, base.vp, base.width, base.height, hfov_deg, central) if rows_ok else Steering()
        metric = MetricSteering()
        if camera is not None and rows_ok:
            metric = metric_steering(base.rows, camera.scaled(base.width, base.height), base.height, central)
        fields = {k: getattr(base, k) for k in ImageResult.__dataclass_fields__}
        extra: dict[str, Any] = {}
        if lattice is not None:
            end_m = None
            mid = base.rows[len(base.rows) // 2] if base.rows else None  # row k = 0 of the 2K + 1
            if (camera is not None and lattice.row_end_y is not None and mid is not None and mid.valid
                    and metric.heading_rad is not None):
                end_m = row_end_distance(camera.scaled(base.width, base.height), mid, lattice.row_end_y, metric.heading_rad)
            extra = {"state": lattice.state, "row_change": lattice.row_change, "row_end_y": lattice.row_end_y,
                     "row_end_m": end_m}
        return cls(**extra, **fields, source=source, frame=frame, hough_ran=hough_ran, hough_redo=hough_redo,
                   confidence=confidence, heading_px=st.heading_px,
                   heading_rad=metric.heading_rad if camera is not None else st.heading_rad,
                   lateral_px=st.lateral_px, lateral_frac=st.lateral_frac, lateral_m=metric.lateral_m,
                   spacing_m=metric.spacing_m)

    @classmethod
    def failed_frame(cls, source: str | None, frame: int, name: str | None, error: str) -> FrameResult:
        """Record of a frame that could not be read (status ``error``; the tracker skipped it)."""
        return cls(width=0, height=0, status="error", name=name, error=error, source=source, frame=frame)
