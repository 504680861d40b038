"""One frozen parameters object holding every constant of ALGORITHM.md.

Both implementations (``torchrow.reference`` and the tensor path) read their constants from
:class:`Params` and nowhere else. Field names follow the table at the top of ALGORITHM.md;
constants that the specification writes inline inside a stage (box sizes, thresholds) are
fields too, grouped by the section that uses them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["Params", "Rule", "check_fields", "FORWARD_CAMERA", "tracker_params", "LATTICE_ROLL_SCALE",
           "LATTICE_WARP_SCALE", "LATTICE_WARP_MARGIN"]

#: Section 11.3.2: the projective spacing's grid, ``g = i / LATTICE_ROLL_SCALE`` (an integer scale,
#: so that the refit's right-hand sides stay integer sums).
LATTICE_ROLL_SCALE = 100

#: Section 11.3.2: the comb's warps, ``gamma = j / (LATTICE_WARP_SCALE / 2 * W)`` per pixel (``j / 20``
#: relative to half the working width).
LATTICE_WARP_SCALE = 20

#: Section 11.3.2: a warped comb takes the start from the unwarped one only where its contrast exceeds
#: the unwarped comb's by this fraction of it (chosen on training data: upright fields keep their comb).
LATTICE_WARP_MARGIN = 0.15


@dataclass(frozen=True)
class Params:
    """Constants of the crop-row detector (ALGORITHM.md, "Parameters").

    Widths in pixels refer to the working image (after resizing to ``image_width``).
    Bands given as ``None`` are derived from the working width ``W`` as the table says:
    ``hough_band = int(W / 30)``, ``ransac_band = int(W / 20)`` (``int(W / 10)`` when bushy).

    Every field is checked on construction by its :class:`Rule` in ``_RULES`` (below the class);
    integral numbers become ``int`` and lists for ``(width, height)`` fields become tuples.

    Raises
    ------
    TypeError
        Naming the field, for a value of the wrong kind (a float or bool for an integer...).
    ValueError
        Naming the field, for a value outside its range (ALGORITHM.md section 0.1 for the
        upper bounds that keep costs bounded).
    """

    # --- table of ALGORITHM.md -------------------------------------------------------
    n_rows: int = 5
    hough_every: int = 5
    bushy_ratio: float = 0.1
    crda_sigma: float = 0.3
    horizon_angle: float = 0.2  # rad
    min_angle_diff: float = 0.1  # rad
    color_tol: float = 6.0  # CIE76 distance
    n_colors: int = 10
    veg_tol: int = 4
    max_outliers: int = 5
    outlier_ratio: float = 1.25
    outlier_min_px: float = 20.0
    theta_step: int = 1  # degrees
    horizontal_excl: int = 25  # degrees
    angle_excl: int = 10  # degrees
    hough_band: int | None = None  # px, None -> int(W / 30)
    ransac_band: int | None = None  # px, None -> int(W / 20)
    ransac_band_bushy: int | None = None  # px, None -> int(W / 10)
    track_band: int = 10  # px
    ransac_trials: int = 1000
    ransac_threshold: float = 1.0  # px
    ransac_min_points: int = 20
    ransac_max_points: int = 700
    ransac_subsample: int = 500
    seed: int = 0
    image_width: int = 320
    video_width: int = 500

    # --- section 1, sky removal ------------------------------------------------------
    sky_blur: tuple[int, int] = (9, 3)  # (width, height) of the box blur
    sky_median: int = 5  # cv2.medianBlur aperture
    sky_lap_max: int = 4  # m = laplacian < sky_lap_max
    sky_erode: tuple[int, int] = (9, 3)  # (width, height) of the erosion rectangle
    sky_col_median: int = 19  # per-column median filter length
    sky_min_zero_row: int = 20  # the column rule needs z > this

    # --- sections 3-4, vegetation and Hough input ------------------------------------
    bushy_erode: tuple[int, int] = (2, 3)  # (width, height), OpenCV default anchor
    canny_low: int = 100
    canny_high: int = 200
    video_k_start: int = 4
    video_k_min: int = 3
    video_k_max: int = 13
    video_shrink_above: float = 2.0  # k -= 1 while fraction > this * info0
    video_grow_below: float = 1.2  # k += 1 while fraction < this * info0

    # --- section 6, vanishing point ----------------------------------------------------
    singular_tol: float = 1e-9  # |det| < singular_tol * trace^2 -> singular

    # --- section 7, RANSAC subsampling key ----------------------------------------------
    subsample_hash: int = 2654435761

    # --- section 0, working-size bound (torchrow extension, ALGORITHM.md section 0) ----------
    max_pixels: int = 1 << 19  # working W*H above this: status "error" (memory bound)

    # --- section 11 (torchrow extension): improved mode, the row lattice ----------------
    mode: str = "faithful"  # "faithful" (sections 0-7) or "improved" (section 11 replaces 7)
    lattice_horizon: str = "image"  # "image": the lattice sees every image row; "sky": only rows below section 2's
    green_floor: int = 0  # excess-green threshold is max(Otsu, this)
    lattice_green: str = "row_mean"  # "row_mean": green also above its image row's mean excess green; "otsu": Otsu only
    lattice_comb: str = "contrast"  # comb score: "contrast" (teeth minus the anti-teeth between them) or "uniform"
    lattice_vp: str = "search"  # VP of the comb: "search" (the grid search of 11.2) or "section6" (section 6's)
    lattice_vp_step: int = 20  # px between the search grid's VPs in x, from 0 to W
    lattice_vp_heights: tuple[int, ...] = (-20, -40, -60, -90, -130, -180, -250)  # the grid's VP rows (y < 0)
    lattice_vp_cell: int = 2  # px, side of the square cells whose counts the search projects
    lattice_vp_spacing_step: int = 2  # the search tries every this-th spacing of the comb's range
    lattice_vp_max_y: int = 0  # a section-6 VP below this image row is not trusted
    lattice_vp_fallback_y: int = -60  # y of the VP used instead, at x = W // 2
    lattice_vp_margin: int = 10  # px: only pixels this far below the VP are projected
    lattice_vp_origin: str = "top"  # grid heights from: "top" (row 0) or "sky" (a horizon in view; forward cameras, 11.2)
    lattice_vp_sky: int = 40  # px: with a horizon in view the heights count from section 1's row + this
    lattice_vp_sky_div: int = 16  # a horizon is in view when section 1's row s has lattice_vp_sky_div * s >= H
    lattice_min_spacing: int = 40  # px, smallest bottom-row spacing the comb tries
    lattice_max_spacing: int = 180  # px, largest (forward cameras: 320, ALGORITHM.md 11.3.1)
    lattice_window: float = 0.1  # comb tooth half-width, fraction of the spacing
    lattice_iterations: int = 20  # least-squares refits at most (a refit whose cells repeat stops early)
    lattice_center_degree: int = 3  # degree of the central row c(t): 3 (S-bends; 2 above 578 rows) or 2
    lattice_tolerance: float = 0.15  # inlier: within this fraction of the spacing of its row
    lattice_half: int = 1  # rows k = -K..K around the central row are fitted and reported
    lattice_min_points: int = 20  # fewer inliers: the refit stops
    lattice_cell_grid: int = 64  # a cell's mean x is rounded to 1/this px (keeps the sums integer)
    lattice_min_spacing_px: float = 2.0  # pixels where d(t) <= this are not assigned
    lattice_pivot_tol: float = 1e-12  # pivot <= this * max(its diagonal entry, 1): singular normal equations
    lattice_min_confidence: float = 0.0  # rows below this confidence are invalid
    lattice_model: str = "curved"  # "curved" (one curved refit); "straight"; "auto": straight, curved where it gains support
    lattice_curve_gain: float = 0.02  # "auto": the curved refit must hold this fraction more inlier pixels
    lattice_roll_grid: int = 0  # straight refits ("auto", "straight"): projective spacing g = i / 100, |i| <= this (11.3.2)
    lattice_comb_warps: int = 0  # the comb also on the bottom row warped projectively, j = -this..this (11.3.2)
    lattice_min_contrast: float = 0.2  # status ok needs the comb's contrast per binned pixel at least this
    lattice_min_image_confidence: float = 0.0  # status ok needs the image confidence at least this
    lattice_min_dominance: float = 0.0  # status ok needs rows -K..K to outnumber their gaps on this share of lit cells
    # --- section 11.7 (torchrow extension): the lattice tracker ------------------------------
    lattice_track_every: int = 10  # video: a full (unrestricted) search at least every this many frames
    lattice_track_vp_cols: int = 2  # video: a tracked sequence's full search: grid columns within this many of its last
    lattice_track_vp_rows: int = 1  # ... grid VP's, and heights within this many (a window beyond the grid: all of it)
    lattice_track_iterations: int = 8  # video: a frame's refits stop after this many steps (images: lattice_iterations)
    lattice_track_spacing_tol: float = 0.15  # prior: comb spacings within this fraction of the last spacing
    lattice_track_phase_tol: float = 0.25  # prior: a tooth within this fraction of the spacing of the tracked row
    lattice_track_hysteresis: float = 0.2  # row change: the tracked row is (0.5 + this) spacings off the centre
    lattice_end_drop: float = 0.02  # row end: this fraction of the supported cells, the topmost, is ignored
    lattice_end_margin: int = 24  # px: the rows end ahead when their end lies this far below the resolvable rows
    lattice_headland_frac: float = 0.25  # rows ending in this bottom fraction of the image: headland

    def __post_init__(self) -> None:
        check_fields(self, _RULES, _CROSS_RULES)

    # --- derived quantities -------------------------------------------------------------
    @property
    def n_theta(self) -> int:
        """Number of Hough angles, ``180 / theta_step``."""
        return 180 // self.theta_step

    def lattice_basis(self, straight: bool = False) -> tuple[tuple[int, int], ...]:
        """Section 11.3: the refit's basis as ``(power of t, power of k)`` pairs, in order.

        Curved (``straight=False``): ``1, t, t^2 (, t^3)`` for the central row ``c(t)`` (degree
        ``lattice_center_degree``), then ``k, k t, k t^2`` for the spacing ``d(t)``. Straight
        (11.3.1): ``1, t, k, k t``, straight rows through one vanishing point.
        """
        if straight:
            return ((0, 0), (1, 0), (0, 1), (1, 1))
        return tuple((j, 0) for j in range(self.lattice_center_degree + 1)) + ((0, 1), (1, 1), (2, 1))

    def lattice_coef_index(self, straight: bool = False) -> list[int]:
        """Where each function of :meth:`lattice_basis` sits in the coefficients ``(c0, c1, c2, c3,
        d0, d1, d2)`` of section 11.3 (the refit's solution fills these, the others are 0)."""
        return [p if k == 0 else 4 + p for p, k in self.lattice_basis(straight)]

    def lattice_rolls(self) -> tuple[int, ...]:
        """Section 11.3.2: the integers ``i`` of the projective spacings ``g = i / 100`` a straight
        refit searches, ascending (``(0,)`` where ``lattice_roll_grid`` is 0: equal spacing)."""
        return tuple(range(-self.lattice_roll_grid, self.lattice_roll_grid + 1))

    def lattice_warps(self) -> tuple[int, ...]:
        """Section 11.3.2: the comb's warps ``j`` in search order, ``0, -1, 1, -2, 2, ...`` up to
        ``lattice_comb_warps`` (``(0,)`` where it is 0: the bottom row as projected)."""
        return (0,) + tuple(j for n in range(1, self.lattice_comb_warps + 1) for j in (-n, n))

    def runs_section6(self) -> bool:
        """Whether sections 2-6 (colour, vegetation mask, Hough, vanishing point) run: always in
        the faithful mode; in the improved mode only with ``lattice_vp="section6"``, whose comb
        starts from section 6's VP (ALGORITHM.md 11)."""
        return self.mode == "faithful" or self.lattice_vp == "section6"

    def runs_sky(self) -> bool:
        """Whether section 1 (the sky row) runs: for sections 2-6, or for the improved mode's
        ``lattice_horizon="sky"`` (ALGORITHM.md 11.1) or its VP grid below a horizon in view (11.2)."""
        return self.runs_section6() or self.lattice_horizon == "sky" or self.lattice_vp_sky_origin()

    def reads_dominance(self) -> bool:
        """Whether a status rule reads the rows' dominance (ALGORITHM.md 11.4): only then do the
        gaps' cells run, in both paths (``lattice_min_dominance > 0``)."""
        return self.lattice_min_dominance > 0

    def tracking(self) -> Params:
        """The parameters the lattice tracker (ALGORITHM.md 11.7) runs section 11 with, in both
        paths: ``lattice_iterations`` = ``lattice_track_iterations`` (built once per
        parameter set: a validated copy costs about 0.1 ms, on every frame otherwise)."""
        return _tracking(self)

    def lattice_vp_sky_origin(self) -> bool:
        """Whether the improved mode's VP grid is measured from a horizon in view (``lattice_vp="search"``,
        ``lattice_vp_origin="sky"``; ALGORITHM.md 11.2), so section 1's row is needed."""
        return self.mode == "improved" and self.lattice_vp == "search" and self.lattice_vp_origin == "sky"

    def lattice_visible_half(self, width: int) -> int:
        """Section 11.4's static bound ``K_v`` on the visible rows ``k = -K_v .. K_v`` of a
        ``width``-px image: ``ceil(3 W / (2 lattice_min_spacing))`` (the comb bins the bottom row
        on ``[-W, 2W)``, its rows lie at least ``lattice_min_spacing`` apart), at least ``lattice_half``."""
        return max(self.lattice_half, -(-3 * int(width) // (2 * self.lattice_min_spacing)))

    def lattice_table_bytes(self, width: int, height: int) -> tuple[int, int]:
        """Section 11.2's tables for one ``width x height`` working image, in bytes: ``(comb, vp)``.

        ``comb = Q (64 J + 400)``: the reference's comb builds four ``(Q, J)`` int64 index
        tables from ``Q`` per-candidate pieces (so twice while stacking them) with about 400
        bytes of per-candidate overhead; ``Q`` = the sum of the spacings
        ``lattice_min_spacing .. lattice_max_spacing`` (one candidate per spacing and phase),
        ``J = 3W // lattice_min_spacing + 1`` teeth. The tensor path keeps ``16 Q`` bytes of
        scores per image.

        ``vp = 8 V (C + 3W + 8 lattice_max_spacing)`` (0 unless ``lattice_vp ==
        "search"``): the tensor path's cached ``(V, C)`` int64 bin table, the ``(V, 3W)``
        histograms and the folds of one spacing (about eight ``(V, d)`` arrays);
        ``V = (W // lattice_vp_step + 1) * len(lattice_vp_heights)`` grid VPs,
        ``C = ceil(H / lattice_vp_cell) * ceil(W / lattice_vp_cell)`` cells.
        Both paths build their per-VP projections in slices of bounded size.
        """
        q = (self.lattice_min_spacing + self.lattice_max_spacing) * (self.lattice_max_spacing - self.lattice_min_spacing + 1) // 2
        comb = q * (64 * (3 * width // self.lattice_min_spacing + 1) + 400)
        if self.lattice_vp != "search":
            return comb, 0
        s = self.lattice_vp_cell
        nv = (width // self.lattice_vp_step + 1) * len(self.lattice_vp_heights)
        cells = -(-height // s) * -(-width // s)
        return comb, 8 * nv * (cells + 3 * width + 8 * self.lattice_max_spacing)

    def hough_band_px(self, width: int) -> int:
        """Band (px) erased around each picked Hough line: ``int(W / 30)`` unless set."""
        return self.hough_band if self.hough_band is not None else int(width / 30)

    def ransac_band_px(self, width: int, bushy: bool) -> int:
        """Band (px) whose pixels feed RANSAC: ``int(W/20)``, ``int(W/10)`` when bushy."""
        if bushy:
            return self.ransac_band_bushy if self.ransac_band_bushy is not None else int(width / 10)
        return self.ransac_band if self.ransac_band is not None else int(width / 20)

    def replace(self, **changes: Any) -> Params:
        """A copy with some fields changed (validated like a new object, so any value type is
        accepted here and checked by the field's rule)."""
        return dataclasses.replace(self, **changes)


# --- validation: one rule per field ---------------------------------------------------------
#: Kinds of :class:`Rule` that hold a fixed number of entries: (entries, integers?, wording).
_TUPLES = {"pair": (2, True, "a (width, height) tuple of 2 integers"),
           "rgb": (3, True, "an (R, G, B) triple of integers"),
           "xy": (2, False, "a pair of finite numbers (x, y)")}


@dataclass(frozen=True)
class Rule:
    """How one field of a frozen settings object (:class:`Params`,
    :class:`torchrow.evaluation.synthetic.FieldSpec`) is checked: ``kind`` (``int``, ``float``,
    ``pair`` = ``(width, height)`` of ints, ``rgb`` = ``(R, G, B)`` of ints, ``xy`` = two
    floats, ``ints`` = ``count`` ints, ``choice`` = a str out of ``choices``; a trailing ``?``
    also allows ``None``), inclusive bounds ``lo``/``hi`` (for a tuple kind they bound each
    entry) and an optional extra condition with its wording.

    A value of the wrong kind raises ``TypeError``; a value of the right kind outside the
    rule raises ``ValueError``; both name ``owner.field``. Integral numbers (``numpy.int64``)
    become ``int``, float fields ``float``, lists for tuple kinds tuples, so equal settings
    compare and hash equal.
    """

    kind: str
    lo: float | None = None
    hi: float | None = None
    extra: tuple[Callable[[Any], bool], str] | None = None
    why: str = ""  # reason for an upper bound, quoted in the error
    choices: tuple[str, ...] = ()
    count: tuple[int, int] = (1, 64)  # ``ints``: how many entries
    count_why: str = ""  # ``ints``: reason for the count, quoted in the error

    def _bounds(self) -> str:
        def f(b: float) -> str:
            return f"{b:d}" if isinstance(b, int) else f"{b:g}"

        if self.lo is not None and self.hi is not None:
            return f" in [{f(self.lo)}, {f(self.hi)}]"
        if self.lo is None and self.hi is None:
            return ""
        return f" >= {f(self.lo)}" if self.lo is not None else f" <= {f(self.hi)}"  # type: ignore[arg-type]

    def _number(self, name: str, v: object, integral: bool) -> object:
        what = "an integer" if integral else "a finite number"
        if isinstance(v, bool) or not isinstance(v, numbers.Integral if integral else numbers.Real):
            raise TypeError(f"{name} must be {what}, not {type(v).__name__}; got {v!r}")
        given = v
        if integral:
            v = int(v)  # type: ignore[call-overload]
        else:
            # a float field holds a float (the tensor path makes float64 tensors of it); an
            # integer too large for float64 is out of range like any other
            try:
                v = float(v)
            except OverflowError:
                v = math.inf
        if not integral and not math.isfinite(v):  # type: ignore[arg-type]
            raise ValueError(f"{name} must be {what}{self._bounds()}; got {given!r}")
        if (self.lo is not None and v < self.lo) or (self.hi is not None and v > self.hi):  # type: ignore[operator]
            why = f" ({self.why})" if self.why and self.hi is not None and v > self.hi else ""  # type: ignore[operator]
            raise ValueError(f"{name} must be {what}{self._bounds()}{why}; got {given!r}")
        return v

    def check(self, field: str, v: object, owner: str = "Params") -> object:
        """``v`` checked and normalised for the field ``field`` of ``owner`` (named in errors)."""
        name = f"{owner}.{field}"
        kind = self.kind.rstrip("?")
        if v is None and kind != self.kind:
            return v
        if kind == "choice":
            if not isinstance(v, str):
                raise TypeError(f"{name} must be a str, not {type(v).__name__}; got {v!r}")
            if v not in self.choices:
                raise ValueError(f"{name} must be one of {', '.join(map(repr, self.choices))}; got {v!r}")
            return v
        if kind == "ints":
            if not isinstance(v, (tuple, list)):
                raise TypeError(f"{name} must be a tuple of integers, not {type(v).__name__}; got {v!r}")
            if not self.count[0] <= len(v) <= self.count[1]:
                why = f" ({self.count_why})" if self.count_why else ""
                raise ValueError(f"{name} must hold {self.count[0]} to {self.count[1]} integers{why}; got {len(v)}")
            return tuple(self._number(f"{name}[{i}]", e, True) for i, e in enumerate(v))
        if kind in _TUPLES:
            n, integral, wording = _TUPLES[kind]
            if not isinstance(v, (tuple, list)):
                raise TypeError(f"{name} must be {wording}, not {type(v).__name__}; got {v!r}")
            if len(v) != n:
                raise ValueError(f"{name} must be {wording}; got {v!r}")
            v = tuple(self._number(f"{name}[{i}]", e, integral) for i, e in enumerate(v))
        else:
            v = self._number(name, v, kind != "float")
        if self.extra is not None and not self.extra[0](v):
            raise ValueError(f"{name} {self.extra[1]}; got {v!r}")
        return v


def check_fields(obj: Any, rules: dict[str, Rule],
                 cross: Sequence[tuple[str, Callable[[Any], bool], str | Callable[[Any], str]]] = ()) -> None:
    """Check and normalise every field of the frozen dataclass ``obj`` by its rule in ``rules``,
    then the ``cross`` rules that tie fields together: ``(field named in the error, condition
    on obj, wording or a function of obj giving it)``. Called by ``__post_init__``; errors name
    ``TypeName.field``."""
    owner = type(obj).__name__
    for f in dataclasses.fields(obj):
        object.__setattr__(obj, f.name, rules[f.name].check(f.name, getattr(obj, f.name), owner))
    for field, ok, what in cross:
        if not ok(obj):
            said = what(obj) if callable(what) else what
            raise ValueError(f"{owner}.{field} {said}; got {getattr(obj, field)!r}")


def _odd(v: object) -> bool:
    return int(v) % 2 == 1  # type: ignore[call-overload]


_COST = "the tensor path's cost grows with it; ALGORITHM.md 0.1"
# Every numeric field has an upper bound (ALGORITHM.md 0.1), so that no value reaches the
# tensor path outside int64/float64 or makes a loop run once per unit of an absurd value:
#: pixels (counts of points, rows of an image): a working image holds at most 2**22 pixels
_PX = 1 << 22
#: bands around a line or row, in px across the image: the widest working image is 4096 px
_BAND = 4096
_PXS = "a working image holds at most 2**22 pixels (max_pixels)"
_BANDS = "wider than the widest working image (4096 px)"
_INT_PX = Rule("int", 0, _PX, why=_PXS)
_DEG = Rule("int", 0, 180, why="an angle in degrees")
#: ratios and tolerances that have no natural bound: far beyond any meaningful value
_F0 = Rule("float", 0, 1e6, why="far beyond any meaningful value")

#: Every field's rule. Upper bounds exist where the tensor path's cost grows with the value
#: faster than the reference's (ALGORITHM.md section 0, "Bounds"); defaults are far inside.
_RULES: dict[str, Rule] = {
    # shapes of the padded tensors and static loop bounds grow with these (max_steps ~ n_rows**2)
    "n_rows": Rule("int", 1, 64, why=_COST), "max_outliers": Rule("int", 1, 64, why=_COST),
    "n_colors": Rule("int", 1, 1024, why=_COST),
    "ransac_trials": Rule("int", 1, 100_000, why="the hypothesis table holds 16 bytes per trial"),
    "hough_every": Rule("int", 1, 1_000_000, why="frames; a day of video at 10 fps has 864,000"),
    "theta_step": Rule("int", 1, 180, (lambda v: 180 % v == 0, "must divide 180 degrees")),
    "ransac_subsample": Rule("int", 1, _PX, why=_PXS), "ransac_max_points": Rule("int", 1, _PX, why=_PXS),
    "image_width": Rule("int", 1, 4096, why=_COST), "video_width": Rule("int", 1, 4096, why=_COST),
    "sky_median": Rule("int", 1, 15, (_odd, "must be odd (cv2.medianBlur)"),
                        why="the exact median network's cost explodes above 15"),
    "sky_col_median": Rule("int", 1, 255, (_odd, "must be odd (medfilt)"), why=_COST),
    # the tracker's band search takes one step per pixel of band
    "track_band": Rule("int", 0, _BAND, why=_BANDS), "ransac_min_points": _INT_PX,
    "horizontal_excl": _DEG, "angle_excl": _DEG,
    "sky_lap_max": Rule("int", 0, 256, why="the Laplacian is uint8"), "sky_min_zero_row": _INT_PX,
    # adaptive k evaluates every k in [video_k_min, video_k_max]; 255 already boxes all of LAB
    "veg_tol": Rule("int", 0, 255, why="255 already boxes all of LAB"),
    "video_k_start": Rule("int", 0, 255, why=_COST), "video_k_min": Rule("int", 0, 255, why=_COST),
    "video_k_max": Rule("int", 0, 255, why=_COST),
    "canny_low": Rule("int", 0, 1 << 16, why="Sobel gradients of uint8 images stay far below"),
    "canny_high": Rule("int", 0, 1 << 16, why="Sobel gradients of uint8 images stay far below"),
    "seed": Rule("int", 0, 2**63 - 1),
    "hough_band": Rule("int?", 0, _BAND, why=_BANDS), "ransac_band": Rule("int?", 0, _BAND, why=_BANDS),
    "ransac_band_bushy": Rule("int?", 0, _BAND, why=_BANDS),
    "bushy_ratio": Rule("float", 0, 1, why="a fraction of the image's pixels"),
    "horizon_angle": Rule("float", 0, math.pi, why="an angle in radians"),
    "min_angle_diff": Rule("float", 0, math.pi, why="an angle in radians"), "outlier_ratio": _F0,
    "outlier_min_px": _F0, "singular_tol": Rule("float", 0, 1, why="a fraction of trace**2"),
    "video_shrink_above": _F0, "video_grow_below": _F0,
    # below ~1 LAB unit (the spacing of 8-bit colours) clusters degenerate to single colours
    # and section 2 loops once per distinct colour of the image
    "color_tol": Rule("float", 1.0, 1000.0, why="CIE76 distances of 8-bit colours stay below 400"),
    "crda_sigma": Rule("float", 0, 1e6, extra=(lambda v: v > 0, "must be > 0")),
    "ransac_threshold": Rule("float", 0, 1e6, extra=(lambda v: v > 0, "must be > 0")),
    "sky_blur": Rule("pair", 1, 64, why="cv2.blur's division table has 255*w*h entries"),
    "sky_erode": Rule("pair", 1, 255, why=_COST), "bushy_erode": Rule("pair", 1, 255, why=_COST),
    # odd: x -> x*mult mod 2**32 is then a bijection, so subsampling keys never tie (section 7.2)
    "subsample_hash": Rule("int", 1, 2**32 - 1, (_odd, "must be odd (distinct subsampling keys)")),
    "max_pixels": Rule("int", 1, 1 << 22, why="peak memory is about 2.5 KB per working pixel"),
    # section 11 (torchrow extension): the improved mode's row lattice
    "mode": Rule("choice", choices=("faithful", "improved")),
    "lattice_horizon": Rule("choice", choices=("image", "sky")),
    "lattice_green": Rule("choice", choices=("row_mean", "otsu")),
    "lattice_comb": Rule("choice", choices=("contrast", "uniform")),
    "lattice_vp": Rule("choice", choices=("search", "section6")),
    "lattice_vp_step": Rule("int", 1, 4096), "lattice_vp_cell": Rule("int", 1, 64),
    "lattice_vp_spacing_step": Rule("int", 1, 4096),
    "lattice_vp_heights": Rule("ints", -(2**20), 2**20, why="image rows of the grid's VPs",
                               count_why="the search runs one comb per VP"),
    "green_floor": Rule("int", -(2**31) + 1, 2**31 - 1),
    "lattice_vp_max_y": Rule("int", -(2**31) + 1, 2**31 - 1),
    "lattice_vp_fallback_y": Rule("int", -(2**31) + 1, -1, why="the fallback VP lies above the image"),
    "lattice_vp_margin": _INT_PX,
    "lattice_vp_origin": Rule("choice", choices=("sky", "top")),
    "lattice_vp_sky": Rule("int", -(2**20), 2**20, why="image rows"),
    "lattice_vp_sky_div": Rule("int", 1, 2**20),
    "lattice_min_spacing": Rule("int", 1, 4096, why=_COST), "lattice_max_spacing": Rule("int", 1, 4096, why=_COST),
    "lattice_half": Rule("int", 1, 64, why=_COST), "lattice_min_points": Rule("int", 1, _PX, why=_PXS),
    "lattice_iterations": Rule("int", 0, 1000, why=_COST),
    "lattice_center_degree": Rule("int", 2, 3, why="the refit's int64 sums; the records hold x up to y**3"),
    "lattice_cell_grid": Rule("int", 1, 2**16, why="the int64 sums stay exact"),
    "lattice_window": Rule("float", 0, 0.5, (lambda v: 0 < v < 0.5, "must lie in (0, 0.5)")),
    "lattice_tolerance": Rule("float", 0, 0.5, (lambda v: 0 < v < 0.5, "must lie in (0, 0.5)")),
    "lattice_model": Rule("choice", choices=("auto", "straight", "curved")),
    "lattice_curve_gain": Rule("float", 0, 100, why="a fraction of the straight lattice's inlier pixels"),
    "lattice_roll_grid": Rule("int", 0, LATTICE_ROLL_SCALE - 1, why="g = i / 100 with |g| < 1"),
    "lattice_comb_warps": Rule("int", 0, LATTICE_WARP_SCALE - 1, why="each warp is one more comb; |j| / 20 < 1"),
    "lattice_min_contrast": Rule("float", 0, 1, why="a fraction of the comb's binned pixels"),
    "lattice_min_image_confidence": Rule("float", 0, 1, why="a fraction of the image rows"),
    "lattice_min_dominance": Rule("float", 0, 1, why="a fraction of the rows' lit cells"),
    "lattice_min_spacing_px": _F0, "lattice_pivot_tol": Rule("float", 0, 1, why="a fraction of a pivot"),
    "lattice_min_confidence": Rule("float", 0, 1),
    "lattice_track_every": Rule("int", 1, 2**31 - 1),
    "lattice_track_iterations": Rule("int", 0, 1000, why=_COST),
    "lattice_track_vp_cols": Rule("int", 0, 2**16, why="grid steps; a window beyond the grid is the whole grid"),
    "lattice_track_vp_rows": Rule("int", 0, 2**16, why="grid heights; a window beyond the grid is the whole grid"),
    "lattice_track_spacing_tol": Rule("float", 0, 1, why="a fraction of the spacing"),
    "lattice_track_phase_tol": Rule("float", 0, 0.5, why="a fraction of the spacing (0.5: any phase)"),
    "lattice_track_hysteresis": Rule("float", 0, 0.5, why="a fraction of the spacing"),
    "lattice_end_drop": Rule("float", 0, 1, why="a fraction of the supported cells"),
    "lattice_end_margin": _INT_PX,
    "lattice_headland_frac": Rule("float", 0, 1, why="a fraction of the image height"),
}

@functools.lru_cache(maxsize=16)
def _tracking(params: Params) -> Params:
    return params.replace(lattice_iterations=params.lattice_track_iterations)


#: The improved mode's forward-camera setting (ALGORITHM.md 11.2, 11.3.1): a camera that sees
#: the horizon, rows converging near the top edge or inside the image. ``--forward`` on the
#: command line; ``Params(mode="improved", **FORWARD_CAMERA)`` in Python. Its
#: ``lattice_min_confidence`` (11.4): a row seen on fewer than 2 % of the image rows is no row
#: (with spacings up to 320 px a forward camera's lattice puts neighbours outside the image); its
#: ``lattice_min_dominance`` (11.4): ``ok`` needs the rows to outnumber the gaps beside them on
#: 60 % of the image rows where either holds green (rows across the view, weeds, a wrong lattice).
FORWARD_CAMERA: dict[str, Any] = {"lattice_model": "auto", "lattice_min_spacing": 16, "lattice_max_spacing": 320,
                                  "lattice_vp_origin": "sky", "lattice_min_confidence": 0.02,
                                  "lattice_min_dominance": 0.6}



def tracker_params(params: Params | None, mode: str | None) -> Params:
    """The parameters of a tracker built with ``params`` and ``mode`` (``torchrow.Tracker`` and
    ``torchrow.reference.Tracker``): ``params`` with ``mode`` in place of ``params.mode``; without
    ``params``, ``Params()``, or in improved mode the forward-camera setting
    (:data:`FORWARD_CAMERA`), since the lattice tracker's camera is a robot's, which looks
    forward (ALGORITHM.md 11.7)."""
    if params is None:
        params = Params(mode="improved", **FORWARD_CAMERA) if mode == "improved" else Params()
    return params if mode is None else params.replace(mode=mode)


#: Bytes section 11.2's tables may take for one working image (:meth:`Params.lattice_table_bytes`):
#: with them an image of ``max_pixels`` pixels at ``image_width`` runs under 3 GiB in either path.
LATTICE_TABLE_BYTES = 1 << 30
#: The VP search projects its cells through this many (VP, cell) pairs at a time (both paths),
#: so its temporaries stay ~50 bytes each, ~200 MB, whatever the grid and the image size.
VP_SLICE = 1 << 22


def _lattice_size(p: Params) -> tuple[int, int]:
    """The largest working image of improved mode: ``image_width x max_pixels // image_width``."""
    return p.image_width, p.max_pixels // p.image_width


def _comb_what(p: Params) -> str:
    w, h = _lattice_size(p)
    q = (p.lattice_min_spacing + p.lattice_max_spacing) * (p.lattice_max_spacing - p.lattice_min_spacing + 1) // 2
    return (f"makes the improved mode's comb tables too large: Q (64 J + 400) = {p.lattice_table_bytes(w, h)[0]} "
            f"bytes > 2**30 at image_width {w} (Q = {q}, the sum of the spacings lattice_min_spacing.."
            f"lattice_max_spacing; J = 3 * image_width // lattice_min_spacing + 1 = {3 * w // p.lattice_min_spacing + 1}"
            f"; ALGORITHM.md 11.2)")


def _vp_what(p: Params) -> str:
    w, h = _lattice_size(p)
    nv = (w // p.lattice_vp_step + 1) * len(p.lattice_vp_heights)
    cells = -(-h // p.lattice_vp_cell) * -(-w // p.lattice_vp_cell)
    return (f"makes the improved mode's VP search tables too large: 8 V (C + 3W + 8 lattice_max_spacing) = "
            f"{p.lattice_table_bytes(w, h)[1]} bytes > 2**30 at the largest working image W x H = {w} x {h} "
            f"(image_width x max_pixels // image_width; V = (W // lattice_vp_step + 1) * len(lattice_vp_heights) = "
            f"{nv} VPs, C = ceil(H / lattice_vp_cell) * ceil(W / lattice_vp_cell) = {cells} cells; ALGORITHM.md 11.2)"
            f": raise lattice_vp_step or lattice_vp_cell, use fewer lattice_vp_heights, or lower max_pixels")


#: Rules that tie fields together: (field named in the error, condition, wording or a function
#: of the parameters giving it).
_CROSS_RULES: tuple[tuple[str, Callable[[Params], bool], str | Callable[[Params], str]], ...] = (
    ("ransac_subsample", lambda p: p.ransac_subsample <= p.ransac_max_points, "must be <= ransac_max_points"),
    ("video_k_start", lambda p: p.video_k_min <= p.video_k_start <= p.video_k_max,
     "must lie in [video_k_min, video_k_max]"),
    ("lattice_max_spacing", lambda p: p.lattice_max_spacing >= p.lattice_min_spacing, "must be >= lattice_min_spacing"),
    ("lattice_roll_grid", lambda p: p.lattice_roll_grid * p.lattice_half < LATTICE_ROLL_SCALE,
     "times lattice_half must be < 100 (1 + g k > 0 on every fitted row, ALGORITHM.md 11.3.2)"),
    ("lattice_comb_warps", lambda p: p.lattice_comb_warps == 0 or p.lattice_roll_grid > 0,
     "needs lattice_roll_grid > 0 (a warped comb starts the refit with a projective spacing that only "
     "the roll search refits, ALGORITHM.md 11.3.2)"),
    # improved mode only (section 11): the faithful mode never builds these tables
    ("lattice_max_spacing", lambda p: p.mode != "improved"
     or p.lattice_table_bytes(*_lattice_size(p))[0] <= LATTICE_TABLE_BYTES, _comb_what),
    ("lattice_vp_step", lambda p: p.mode != "improved"
     or p.lattice_table_bytes(*_lattice_size(p))[1] <= LATTICE_TABLE_BYTES, _vp_what),
)
