"""Typed per-image result of the detector (ALGORITHM.md section 9) and its JSON record."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["HoughLine", "Row", "LatticeRow", "ImageResult", "STATUSES", "REASONS", "record_differences", "concat_batches"]

#: ``ok``: every row valid. ``invalid``: at least one row invalid. ``no_vp``: fewer than two
#: Hough lines or a singular vanishing-point system, so no rows. ``no_vegetation``: the
#: vegetation mask is empty below the horizon (a special case of ``no_vp``). ``error``: the
#: input could not be read or converted (only in records written by the CLI). ``weak``
#: (improved mode, ALGORITHM.md 11.4): rows found, but the image's evidence (comb contrast,
#: image confidence) is below the calibrated thresholds: do not steer by them.
STATUSES = ("ok", "invalid", "no_vp", "no_vegetation", "error", "weak")

#: Why a row is invalid (``""`` when valid), section 7.
REASONS = ("", "no_support", "horizon", "parallel", "too_close")


@dataclass(frozen=True)
class HoughLine:
    """A Hough peak: angle index ``j`` (theta = j * theta_step degrees), ``rho`` (px), votes."""

    theta_index: int
    rho: int
    weight: int
    theta_step: int = 1

    @property
    def theta(self) -> float:
        """Angle in radians (``numpy.deg2rad(j * theta_step)``)."""
        return float(np.deg2rad(np.float64(self.theta_index * self.theta_step)))

    def to_list(self) -> list[float | int]:
        return [self.theta, int(self.rho), int(self.weight)]


@dataclass(frozen=True)
class Row:
    """A fitted crop row ``x = e*y**3 + c*y**2 + a*y + b`` in working-image pixels.

    ``a``/``b`` are NaN when the row had no support. ``hypothesis`` is the index of the
    winning RANSAC hypothesis (-1 when none was scored). ``c`` and ``e`` are 0 in faithful mode
    (straight rows); ``confidence`` in ``[0, 1]`` is set by the improved mode (ALGORITHM.md
    11.4) and NaN in faithful mode.
    """

    a: float
    b: float
    valid: bool
    reason: str = ""
    hypothesis: int = -1
    c: float = 0.0
    confidence: float = float("nan")
    e: float = 0.0

    def x_at(self, y: np.ndarray | float) -> np.ndarray | float:
        return _poly_x(self.a, self.b, self.c, self.e, y)


def _poly_x(a: float, b: float, c: float, e: float, y: np.ndarray | float) -> np.ndarray | float:
    """x of ``x = e*y**3 + c*y**2 + a*y + b`` at ``y`` (px, float64)."""
    x = (c * y) * y + a * y + b
    return x if e == 0.0 else x + ((e * y) * y) * y


@dataclass(frozen=True)
class LatticeRow:
    """One visible row of the improved mode's lattice (ALGORITHM.md 11.4): ``k`` = its index
    relative to the central row (negative to the left at the bottom when the spacing is
    positive), ``x = e*y**3 + c*y**2 + a*y + b`` in working-image pixels, ``confidence`` in
    ``(0, 1]`` (image rows holding one of its inliers / image rows from the lattice's top row)."""

    k: int
    a: float
    b: float
    c: float
    e: float
    confidence: float

    def x_at(self, y: np.ndarray | float) -> np.ndarray | float:
        return _poly_x(self.a, self.b, self.c, self.e, y)


@dataclass
class ImageResult:
    """Everything the detector says about one image (ALGORITHM.md section 9).

    The improved mode (section 11) runs none of sections 2-6 unless its comb starts from
    section 6's VP, and reports none of their outputs in any case: ``veg_color``, ``k``,
    ``bushy``, ``hough``, ``outliers`` are ``None`` and ``vp`` is ``None``; ``sky`` is the
    lattice's first image row (0, or section 1's row with ``lattice_horizon="sky"``).
    """

    width: int
    height: int
    status: str
    sky: int = 0
    veg_color: tuple[int, int, int] | None = (0, 0, 0)
    k: int | None = 4
    bushy: bool | None = False
    n_rows: int = 0
    hough: list[HoughLine] | None = field(default_factory=list)
    outliers: list[HoughLine] | None = field(default_factory=list)
    vp: tuple[float, float] | None = None
    rows: list[Row] = field(default_factory=list)
    name: str | None = None
    error: str | None = None
    #: Image confidence (improved mode, ALGORITHM.md 11.4): mean of the rows'; NaN in faithful mode.
    #: (Not ``confidence``: a video frame's ``confidence`` is the tracker's, see torchrow.core.steering.)
    image_confidence: float = float("nan")
    #: Every visible row of the lattice (improved mode, ALGORITHM.md 11.4), ``k`` ascending; ``None`` in
    #: faithful mode.
    lattice_rows: list[LatticeRow] | None = None

    @property
    def valid(self) -> bool:
        return self.status == "ok"

    def valid_rows(self) -> list[Row]:
        return [r for r in self.rows if r.valid]

    def to_record(self) -> dict[str, Any]:
        """JSON-ready dict with the keys documented in the README (NaN -> null)."""

        def num(v: float) -> float | None:
            return None if v is None or not math.isfinite(v) else float(v)

        rec: dict[str, Any] = {
            "name": self.name,
            "status": self.status,
            "width": int(self.width),
            "height": int(self.height),
            "sky": int(self.sky),
            "veg_color": None if self.veg_color is None else [int(c) for c in self.veg_color],
            "k": None if self.k is None else int(self.k),
            "bushy": None if self.bushy is None else bool(self.bushy),
            "n_rows": int(self.n_rows),
            "hough": None if self.hough is None else [h.to_list() for h in self.hough],
            "outliers": None if self.outliers is None else [h.to_list() for h in self.outliers],
            "vp": None if self.vp is None else [num(self.vp[0]), num(self.vp[1])],
            "rows": [{"a": num(r.a), "b": num(r.b), "c": num(r.c), "e": num(r.e), "valid": bool(r.valid), "reason": r.reason,
                      "confidence": num(r.confidence)} for r in self.rows],
            "image_confidence": num(self.image_confidence),
            "lattice_rows": None if self.lattice_rows is None else [
                {"k": int(r.k), "a": num(r.a), "b": num(r.b), "c": num(r.c), "e": num(r.e),
                 "confidence": num(r.confidence)} for r in self.lattice_rows],
        }
        if self.error is not None:
            rec["error"] = self.error
        return rec

    @classmethod
    def from_record(cls, rec: dict[str, Any], theta_step: int = 1) -> ImageResult:
        """Inverse of :meth:`to_record` (hypothesis indices are not stored in records)."""

        def line(v: list) -> HoughLine:
            j = int(round(math.degrees(v[0]) / theta_step))
            return HoughLine(j, int(v[1]), int(v[2]), theta_step)

        def f(v: Any) -> float:
            return float("nan") if v is None else float(v)

        def opt(key: str, default: Any, conv: Callable[[Any], Any]) -> Any:
            v = rec.get(key, default)  # absent: an older record's default; null: not computed
            return None if v is None else conv(v)

        lattice = rec.get("lattice_rows")
        return cls(
            width=int(rec.get("width", 0)), height=int(rec.get("height", 0)),
            status=rec["status"], sky=int(rec.get("sky", 0)),
            veg_color=opt("veg_color", (0, 0, 0), lambda v: tuple(int(c) for c in v)),
            k=opt("k", 4, int), bushy=opt("bushy", False, bool),
            n_rows=int(rec.get("n_rows", 0)),
            hough=opt("hough", [], lambda v: [line(x) for x in v]),
            outliers=opt("outliers", [], lambda v: [line(x) for x in v]),
            vp=None if rec.get("vp") is None else (f(rec["vp"][0]), f(rec["vp"][1])),
            rows=[Row(f(r["a"]), f(r["b"]), bool(r["valid"]), r.get("reason", ""), -1, f(r.get("c", 0.0)),
                      f(r.get("confidence")), f(r.get("e", 0.0))) for r in rec.get("rows", [])],
            name=rec.get("name"), error=rec.get("error"), image_confidence=f(rec.get("image_confidence")),
            lattice_rows=None if lattice is None else [
                LatticeRow(int(r["k"]), f(r["a"]), f(r["b"]), f(r["c"]), f(r["e"]), f(r["confidence"])) for r in lattice],
        )

    @classmethod
    def failed(cls, name: str | None, error: str, width: int = 0, height: int = 0) -> ImageResult:
        """Record for an input that could not be processed (status ``error``)."""
        return cls(width=width, height=height, status="error", name=name, error=error)


def record_differences(a: Any, b: Any, tol: float = 1e-6, path: str = "") -> list[str]:
    """Where two JSON records (or any nested lists/dicts of them) differ by the rule of
    ALGORITHM.md's "Identical results": every discrete value (str, bool, int, None, keys,
    lengths) equal, every float within ``tol`` (absolute; px for rows and points).

    Returns one ``"path: a != b"`` line per difference (empty when the records agree), so
    ``not record_differences(r1, r2)`` is the check, and a failure says where.
    """
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{path or '.'}: keys {sorted(a)} != {sorted(b)}"]
        return [d for k in a for d in record_differences(a[k], b[k], tol, f"{path}.{k}")]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return [f"{path or '.'}: length {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in record_differences(x, y, tol, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and not (isinstance(a, bool) or isinstance(b, bool)):
        same = (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol
    else:
        same = type(a) is type(b) and a == b
    return [] if same else [f"{path or '.'}: {a!r} != {b!r}"]


def concat_batches(parts: list) -> Any:
    """One dataclass of batched tensors from consecutive chunks of a batch (the one
    concatenator of the detectors, the exported runners and the tracker).

    ``parts``: dataclasses of one type whose tensor fields have the batch as their first
    dimension. Tensor fields are concatenated along it; other fields (working sizes,
    ``None``) are taken from the first part. A single part is returned as it is.
    """
    import dataclasses

    import torch

    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    return type(first)(**{f.name: (torch.cat([getattr(q, f.name) for q in parts])
                                   if isinstance(getattr(first, f.name), torch.Tensor) else getattr(first, f.name))
                          for f in dataclasses.fields(first)})
