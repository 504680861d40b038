"""One frozen parameters object holding every constant of ALGORITHM.md.

Both implementations (``torchrow.reference`` and the tensor path) read their constants from
:class:`Params` and nowhere else. Field names follow the table at the top of ALGORITHM.md;
constants that the specification writes inline inside a stage (box sizes, thresholds) are
fields too, grouped by the section that uses them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

__all__ = ["Params"]


@dataclass(frozen=True)
class Params:
    """Constants of the crop-row detector (ALGORITHM.md, "Parameters").

    Widths in pixels refer to the working image (after resizing to ``image_width``).
    Bands given as ``None`` are derived from the working width ``W`` as the table says:
    ``hough_band = int(W / 30)``, ``ransac_band = int(W / 20)`` (``int(W / 10)`` when bushy).

    Raises
    ------
    ValueError
        On construction, naming the field, for values outside their meaningful range.
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

    # --- section 11 (torchrow extension): improved mode, the row lattice ----------------
    mode: str = "faithful"  # "faithful" (sections 0-7) or "improved" (section 11 replaces 7)
    green_floor: int = 0  # excess-green threshold is max(Otsu, this)
    lattice_vp_max_y: int = 0  # a section-6 VP below this image row is not trusted
    lattice_vp_fallback_y: int = -60  # y of the VP used instead, at x = W // 2
    lattice_vp_margin: int = 10  # px: only pixels this far below the VP are projected
    lattice_min_spacing: int = 40  # px, smallest bottom-row spacing the comb tries
    lattice_max_spacing: int = 180  # px, largest
    lattice_window: float = 0.1  # comb tooth half-width, fraction of the spacing
    lattice_iterations: int = 6  # least-squares refits
    lattice_tolerance: float = 0.15  # inlier: |f - k| < this (fraction of the spacing)
    lattice_half: int = 1  # rows k = -K..K around the central row are fitted and reported
    lattice_min_points: int = 20  # fewer inliers: the refit stops
    lattice_cell_grid: int = 64  # a cell's mean x is rounded to 1/this px (keeps the sums integer)
    lattice_min_spacing_px: float = 2.0  # pixels where d(t) <= this are not assigned
    lattice_pivot_tol: float = 1e-12  # pivot <= this * max(diag, 1): singular normal equations
    lattice_min_confidence: float = 0.0  # rows below this confidence are invalid

    def __post_init__(self) -> None:
        def need(cond: bool, field: str, what: str) -> None:
            if not cond:
                raise ValueError(f"Params.{field} {what}; got {getattr(self, field)!r}")

        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                raise ValueError(f"Params.{f.name} must be a number, not a bool; got {v!r}")
        for name in ("n_rows", "hough_every", "n_colors", "ransac_trials", "image_width",
                     "video_width", "theta_step", "sky_median", "sky_col_median",
                     "ransac_subsample", "ransac_max_points", "max_outliers"):
            v = getattr(self, name)
            need(isinstance(v, int) and v >= 1, name, "must be an integer >= 1")
        for name in ("veg_tol", "track_band", "ransac_min_points", "horizontal_excl", "angle_excl",
                     "sky_lap_max", "sky_min_zero_row", "seed", "video_k_start", "video_k_min",
                     "video_k_max", "canny_low", "canny_high"):
            v = getattr(self, name)
            need(isinstance(v, int) and v >= 0, name, "must be an integer >= 0")
        for name in ("hough_band", "ransac_band", "ransac_band_bushy"):
            v = getattr(self, name)
            need(v is None or (isinstance(v, int) and v >= 0), name, "must be None or an integer >= 0")
        for name in ("bushy_ratio", "crda_sigma", "horizon_angle", "min_angle_diff", "color_tol",
                     "outlier_ratio", "outlier_min_px", "ransac_threshold", "singular_tol",
                     "video_shrink_above", "video_grow_below"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0, name,
                 "must be a finite number >= 0")
        need(self.crda_sigma > 0, "crda_sigma", "must be > 0")
        need(self.ransac_threshold > 0, "ransac_threshold", "must be > 0")
        need(180 % self.theta_step == 0, "theta_step", "must divide 180 degrees")
        need(self.sky_median % 2 == 1, "sky_median", "must be odd (cv2.medianBlur)")
        need(self.sky_col_median % 2 == 1, "sky_col_median", "must be odd (medfilt)")
        need(self.ransac_subsample <= self.ransac_max_points, "ransac_subsample",
             "must be <= ransac_max_points")
        need(self.video_k_min <= self.video_k_start <= self.video_k_max, "video_k_start",
             "must lie in [video_k_min, video_k_max]")
        need(self.seed < 2**63, "seed", "must be < 2**63")
        self._check_improved(need)
        for name in ("sky_blur", "sky_erode", "bushy_erode"):
            v = getattr(self, name)
            need(isinstance(v, tuple) and len(v) == 2 and all(isinstance(e, int) and e >= 1 for e in v),
                 name, "must be a (width, height) tuple of integers >= 1")

    def _check_improved(self, need) -> None:
        """Validation of the section-11 fields (improved mode)."""
        if not isinstance(self.mode, str) or self.mode not in ("faithful", "improved"):
            raise ValueError(f"Params.mode must be 'faithful' or 'improved'; got {self.mode!r}")
        for name in ("green_floor", "lattice_vp_max_y", "lattice_vp_fallback_y"):
            v = getattr(self, name)
            need(isinstance(v, int) and abs(v) < 2**31, name, "must be an integer")
        for name in ("lattice_vp_margin", "lattice_min_spacing", "lattice_max_spacing", "lattice_half",
                     "lattice_min_points", "lattice_cell_grid"):
            v = getattr(self, name)
            need(isinstance(v, int) and v >= 1, name, "must be an integer >= 1")
        need(isinstance(self.lattice_iterations, int) and self.lattice_iterations >= 0, "lattice_iterations",
             "must be an integer >= 0")
        need(self.lattice_max_spacing >= self.lattice_min_spacing, "lattice_max_spacing",
             "must be >= lattice_min_spacing")
        need(self.lattice_vp_fallback_y < 0, "lattice_vp_fallback_y", "must be < 0 (above the image)")
        for name in ("lattice_window", "lattice_tolerance"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and 0 < v < 0.5, name, "must be a number in (0, 0.5)")
        for name in ("lattice_min_spacing_px", "lattice_pivot_tol", "lattice_min_confidence"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0, name, "must be a finite number >= 0")
        need(self.lattice_min_confidence <= 1, "lattice_min_confidence", "must be <= 1")
        need(self.lattice_cell_grid <= 2**16, "lattice_cell_grid", "must be <= 65536 (int64 sums stay exact)")

    # --- derived quantities -------------------------------------------------------------
    @property
    def n_theta(self) -> int:
        """Number of Hough angles, ``180 / theta_step``."""
        return 180 // self.theta_step

    def hough_band_px(self, width: int) -> int:
        """Band (px) erased around each picked Hough line: ``int(W / 30)`` unless set."""
        return self.hough_band if self.hough_band is not None else int(width / 30)

    def ransac_band_px(self, width: int, bushy: bool) -> int:
        """Band (px) whose pixels feed RANSAC: ``int(W/20)``, ``int(W/10)`` when bushy."""
        if bushy:
            return self.ransac_band_bushy if self.ransac_band_bushy is not None else int(width / 10)
        return self.ransac_band if self.ransac_band is not None else int(width / 20)

    def replace(self, **changes: object) -> "Params":
        """A copy with some fields changed (validated like a new object)."""
        return dataclasses.replace(self, **changes)
