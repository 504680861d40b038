"""The batched result of the tensor engines: :class:`BatchResult`, padded tensors with masks
for ``B`` images, and its per-image :class:`~torchrow.core.results.ImageResult` records (the
records :func:`torchrow.reference.detect` returns). Shared by the eager detector and tracker
and the ONNX runners.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from torchrow.core.results import REASONS, STATUSES, HoughLine, ImageResult, LatticeRow, Row

__all__ = ["BatchResult"]


@dataclass
class BatchResult:
    """Detections of a batch of ``B`` images of one working size ``width x height``.

    Per image: ``status`` int64 (code into :data:`torchrow.core.results.STATUSES`), ``sky``,
    ``k``, ``n_rows`` int64, ``bushy`` bool, ``veg_color`` uint8 ``(B, 3)``, ``vp`` float64
    ``(B, 2)`` with ``has_vp``. Hough lines ``hough_*`` ``(B, n_rows)`` with ``hough_valid``;
    dropped outliers ``out_*`` ``(B, O)`` with ``out_valid``; rows ``row_a``/``row_b`` float64
    ``(B, n_rows)`` (``x = a*y + b``), ``row_valid``, ``row_reason`` (code into
    :data:`torchrow.core.results.REASONS`), ``row_hypothesis``, ``row_present``.
    ``timings`` holds seconds per stage when the detector was asked to profile.
    The improved mode reports none of sections 2-6: ``veg_color``, ``k``, ``bushy``,
    ``hough_*``, ``out_*``, ``vp`` and ``has_vp`` are ``None`` (the records' nulls), and ``sky``
    is the lattice's first image row.
    """

    width: int
    height: int
    status: torch.Tensor
    sky: torch.Tensor
    veg_color: torch.Tensor | None
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
