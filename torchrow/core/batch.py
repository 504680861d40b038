"""The batched result of the tensor engines: :class:`BatchResult`, padded tensors with masks
for ``B`` images, and its per-image :class:`~torchrow.core.results.ImageResult` records (the
records :func:`torchrow.reference.detect` returns). Shared by the eager detector and tracker
and the ONNX runners.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from torchrow.core.results import REASONS, STATUSES, HoughLine, ImageResult, LatticeRow, Row

__all__ = ["BatchResult", "Detections", "ROW_FIELDS", "LINE_FIELDS"]

#: Field of :class:`BatchResult` <- attribute of a row table (:meth:`BatchResult.build`).
ROW_FIELDS = {"row_a": "a", "row_b": "b", "row_valid": "valid", "row_reason": "reason",
               "row_hypothesis": "hypothesis", "row_present": "present"}
#: Field of :class:`BatchResult` <- attribute of a line search (:meth:`BatchResult.build`).
LINE_FIELDS = {"hough_theta": "theta", "hough_rho": "rho", "hough_weight": "weight", "hough_valid": "valid",
                **{f: f for f in ("out_theta", "out_rho", "out_weight", "out_valid", "n_rows", "vp", "has_vp")}}


@dataclass
class Detections:
    """The per-image detections of a batch, the fields every batched result shares
    (:class:`BatchResult` of the detectors, :class:`~torchrow.functional.tracking.TrackStep`
    of the tracker): ``status`` int64 (code into :data:`torchrow.core.results.STATUSES`),
    ``k``, ``n_rows`` int64, ``bushy`` bool ``(B,)``; Hough lines ``hough_*`` ``(B, n_rows)``
    with ``hough_valid``; dropped outliers ``out_*`` ``(B, O)`` with ``out_valid``; ``vp``
    float64 ``(B, 2)`` with ``has_vp``; rows ``row_a``/``row_b`` float64 ``(B, n_rows)``
    (``x = a*y + b``), ``row_valid``, ``row_reason`` (code into
    :data:`torchrow.core.results.REASONS`), ``row_hypothesis``, ``row_present``.
    The improved mode reports none of sections 2-6: ``k``, ``bushy``, ``hough_*``, ``out_*``,
    ``vp`` and ``has_vp`` are ``None`` there (the records' nulls).
    """

    status: torch.Tensor
    k: torch.Tensor | None
    bushy: torch.Tensor | None
    n_rows: torch.Tensor
    hough_theta: torch.Tensor | None
    hough_rho: torch.Tensor | None
    hough_weight: torch.Tensor | None
    hough_valid: torch.Tensor | None
    out_theta: torch.Tensor | None
    out_rho: torch.Tensor | None
    out_weight: torch.Tensor | None
    out_valid: torch.Tensor | None
    vp: torch.Tensor | None
    has_vp: torch.Tensor | None
    row_a: torch.Tensor
    row_b: torch.Tensor
    row_valid: torch.Tensor
    row_reason: torch.Tensor
    row_hypothesis: torch.Tensor
    row_present: torch.Tensor


@dataclass
class BatchResult(Detections):
    """Detections of a batch of ``B`` images of one working size ``width x height``: the
    :class:`Detections` fields, and per image ``sky`` int64 and ``veg_color`` uint8 ``(B, 3)``.
    ``timings`` holds seconds per stage when the detector was asked to profile. In the improved
    mode ``veg_color`` is ``None`` and ``sky`` is the lattice's first image row.
    """

    width: int
    height: int
    sky: torch.Tensor
    veg_color: torch.Tensor | None
    theta_step: int = 1
    timings: dict[str, float] = field(default_factory=dict)
    #: Improved mode only (None in faithful mode): ``row_c``/``row_e``/``row_confidence`` ``(B, R)``
    #: float64 (``x = e*y**3 + c*y**2 + a*y + b``) and ``image_confidence`` ``(B,)`` float64.
    row_c: torch.Tensor | None = None
    row_e: torch.Tensor | None = None
    row_confidence: torch.Tensor | None = None
    image_confidence: torch.Tensor | None = None
    #: Improved mode only: every visible lattice row (ALGORITHM.md 11.4), ``(B, 2 K_v + 1)`` for rows
    #: ``k = -K_v .. K_v`` (column ``j`` is ``k = j - K_v``): ``lattice_a/b/c/e/confidence`` float64,
    #: ``lattice_present`` bool (the rows reported).
    lattice_a: torch.Tensor | None = None
    lattice_b: torch.Tensor | None = None
    lattice_c: torch.Tensor | None = None
    lattice_e: torch.Tensor | None = None
    lattice_confidence: torch.Tensor | None = None
    lattice_present: torch.Tensor | None = None

    @classmethod
    def build(cls, width: int, height: int, theta_step: int, *, lines: Any = None, rows: Any = None,
              fields: Mapping[str, torch.Tensor] | Any = None, **given: Any) -> BatchResult:
        """The one way the engines assemble a batch result from their stages' outputs.

        Each tensor field comes from the first of: ``given`` by name; ``rows`` (an object with
        ``a, b, valid, reason, hypothesis, present``, e.g.
        :class:`~torchrow.functional.ransac.Rows`: ``row_a = rows.a``, ...); ``lines`` (with
        ``theta, rho, weight, valid, out_*, n_rows, vp, has_vp``, e.g.
        :class:`~torchrow.functional.vanishing.LineSearch`: ``hough_theta = lines.theta``, ...);
        ``fields`` by the field's own name (a mapping, or an object with those attributes such
        as a tracker step). ``given`` also sets the optional fields (``timings``, ``row_c``...).

        Raises
        ------
        TypeError
            Naming the first tensor field that none of them provides.
        """
        out = {}
        for f in dataclasses.fields(cls):
            name = f.name
            if name in given:
                out[name] = given.pop(name)
            elif f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
                continue
            elif name in ("width", "height", "theta_step"):
                continue
            elif rows is not None and name in ROW_FIELDS:
                out[name] = getattr(rows, ROW_FIELDS[name])
            elif lines is not None and name in LINE_FIELDS:
                out[name] = getattr(lines, LINE_FIELDS[name])
            elif isinstance(fields, Mapping) and name in fields:
                out[name] = fields[name]
            elif fields is not None and not isinstance(fields, Mapping) and hasattr(fields, name):
                out[name] = getattr(fields, name)
            else:
                raise TypeError(f"BatchResult.build: no value for the field {name!r}")
        if given:
            raise TypeError(f"BatchResult.build: unknown fields {sorted(given)}")
        return cls(width=width, height=height, theta_step=theta_step, **out)

    def __len__(self) -> int:
        return int(self.status.shape[0])

    def results(self, names: Sequence[str | None] | None = None) -> list[ImageResult]:
        """Per-image records, equal to what :func:`torchrow.reference.detect` returns.

        ``names``: one per image (``ValueError`` otherwise), stored in the records.
        """
        if names is not None and len(names) != len(self):
            raise ValueError(f"results: names must hold one name per image ({len(self)}), got {len(names)}")
        cpu = {k: (v.cpu() if isinstance(v, torch.Tensor) else v) for k, v in self.__dict__.items()}
        out = []
        for b in range(len(self)):
            def lines(th, rh, wt, ok, b=b):
                if th is None:
                    return None
                return [HoughLine(int(th[b, j]), int(rh[b, j]), int(wt[b, j]), self.theta_step)
                        for j in range(th.shape[1]) if bool(ok[b, j])]

            def per_image(key: str, conv, b=b):
                return None if cpu[key] is None else conv(cpu[key][b])

            curved = cpu["row_c"] is not None
            rows = [Row(float(cpu["row_a"][b, j]), float(cpu["row_b"][b, j]), bool(cpu["row_valid"][b, j]),
                        REASONS[int(cpu["row_reason"][b, j])], int(cpu["row_hypothesis"][b, j]),
                        *((float(cpu["row_c"][b, j]), float(cpu["row_confidence"][b, j]),
                           float(cpu["row_e"][b, j])) if curved else ()))
                    for j in range(cpu["row_a"].shape[1]) if bool(cpu["row_present"][b, j])]
            vp = None
            if cpu["vp"] is not None and bool(cpu["has_vp"][b]):
                vp = (float(cpu["vp"][b, 0]), float(cpu["vp"][b, 1]))
            lattice = None
            if cpu["lattice_present"] is not None:
                half = (cpu["lattice_present"].shape[1] - 1) // 2
                lattice = [LatticeRow(j - half, *(float(cpu[f"lattice_{f}"][b, j]) for f in ("a", "b", "c", "e",
                                                                                             "confidence")))
                           for j in range(cpu["lattice_present"].shape[1]) if bool(cpu["lattice_present"][b, j])]
            out.append(ImageResult(
                width=self.width, height=self.height, status=STATUSES[int(cpu["status"][b])],
                sky=int(cpu["sky"][b]), veg_color=per_image("veg_color", lambda v: tuple(int(c) for c in v)),
                k=per_image("k", int), bushy=per_image("bushy", bool), n_rows=int(cpu["n_rows"][b]),
                hough=lines(cpu["hough_theta"], cpu["hough_rho"], cpu["hough_weight"], cpu["hough_valid"]),
                outliers=lines(cpu["out_theta"], cpu["out_rho"], cpu["out_weight"], cpu["out_valid"]),
                vp=vp, rows=rows, name=None if names is None else names[b],
                image_confidence=float(cpu["image_confidence"][b]) if curved else float("nan"),
                lattice_rows=lattice))
        return out
