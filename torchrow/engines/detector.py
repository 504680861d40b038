"""The batched detector: composes the tensor stages of :mod:`torchrow.functional`.

:class:`CropRowDetector` runs ALGORITHM.md sections 1-7 on ``uint8 (B, 3, H, W)`` batches and
returns a :class:`BatchResult` of padded tensors with masks; :meth:`BatchResult.results`
turns it into the same per-image :class:`~torchrow.core.results.ImageResult` records as
:func:`torchrow.reference.detect`.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn

from torchrow.core.io import check_color, check_working_size, load_image, resize_to_width, to_rgb8
from torchrow.core.params import Params
from torchrow.core.results import REASONS, STATUSES, HoughLine, ImageResult, Row, concat_batches
from torchrow.functional import color as fcolor
from torchrow.functional import lattice as flattice
from torchrow.functional import ransac as fransac
from torchrow.functional import sky as fsky
from torchrow.functional import vanishing as fvan
from torchrow.functional import vegetation as fveg
from torchrow.functional._checks import check_device, check_images

__all__ = ["BatchResult", "CropRowDetector", "STATUS_CODES"]

STATUS_CODES = {s: i for i, s in enumerate(STATUSES)}


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
    """

    width: int
    height: int
    status: torch.Tensor
    sky: torch.Tensor
    veg_color: torch.Tensor
    k: torch.Tensor
    bushy: torch.Tensor
    n_rows: torch.Tensor
    hough_theta: torch.Tensor
    hough_rho: torch.Tensor
    hough_weight: torch.Tensor
    hough_valid: torch.Tensor
    out_theta: torch.Tensor
    out_rho: torch.Tensor
    out_weight: torch.Tensor
    out_valid: torch.Tensor
    vp: torch.Tensor
    has_vp: torch.Tensor
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
                return [HoughLine(int(th[b, j]), int(rh[b, j]), int(wt[b, j]), self.theta_step)
                        for j in range(th.shape[1]) if bool(ok[b, j])]

            curved = cpu["row_c"] is not None
            rows = [Row(float(cpu["row_a"][b, j]), float(cpu["row_b"][b, j]), bool(cpu["row_valid"][b, j]),
                        REASONS[int(cpu["row_reason"][b, j])], int(cpu["row_hypothesis"][b, j]),
                        *((float(cpu["row_c"][b, j]), float(cpu["row_confidence"][b, j]),
                           float(cpu["row_e"][b, j])) if curved else ()))
                    for j in range(cpu["row_a"].shape[1]) if bool(cpu["row_present"][b, j])]
            vp = (float(cpu["vp"][b, 0]), float(cpu["vp"][b, 1])) if bool(cpu["has_vp"][b]) else None
            out.append(ImageResult(
                width=self.width, height=self.height, status=STATUSES[int(cpu["status"][b])],
                sky=int(cpu["sky"][b]), veg_color=tuple(int(c) for c in cpu["veg_color"][b]),  # type: ignore[arg-type]
                k=int(cpu["k"][b]), bushy=bool(cpu["bushy"][b]), n_rows=int(cpu["n_rows"][b]),
                hough=lines(cpu["hough_theta"], cpu["hough_rho"], cpu["hough_weight"], cpu["hough_valid"]),
                outliers=lines(cpu["out_theta"], cpu["out_rho"], cpu["out_weight"], cpu["out_valid"]),
                vp=vp, rows=rows, name=None if names is None else names[b],
                image_confidence=float(cpu["image_confidence"][b]) if curved else float("nan")))
        return out


def _color_override(color: object, batch: int, device: torch.device) -> torch.Tensor:
    """Validate a given vegetation colour (:func:`torchrow.core.io.check_color`, the reference's
    rule: integers in [0, 255], any integer dtype or a list) and broadcast it to ``uint8 (B, 3)``."""
    a = check_color(color, batched=True)
    if a.shape == (3,):
        a = np.broadcast_to(a, (batch, 3))
    if a.shape != (batch, 3):
        raise ValueError(f"veg_color must have shape (3,) or (B, 3) = ({batch}, 3), got {a.shape}")
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.uint8)).to(device)


class CropRowDetector(nn.Module):
    """Batched crop-row detector (ALGORITHM.md, image mode), identical to the reference.

    Parameters
    ----------
    params : Params
        Constants (defaults as in ALGORITHM.md).
    device : str or torch.device, optional
        Where the stages run; inputs are moved there. Default: CPU.

    Examples
    --------
    >>> det = CropRowDetector()
    >>> batch = det(images)            # uint8 (B, 3, H, W) -> BatchResult
    >>> records = batch.results()      # list[ImageResult], as torchrow.reference.detect
    """

    def __init__(self, params: Params | None = None, device: str | torch.device | None = None,
                 chunk: int | None = None, workers: int | None = None) -> None:
        super().__init__()
        self.params = params or Params()
        self.device = check_device(device)
        if chunk is not None and chunk < 1:
            raise ValueError(f"chunk must be None or >= 1, got {chunk}")
        if workers is not None and workers < 1:
            raise ValueError(f"workers must be None or >= 1, got {workers}")
        # Hough/VP/RANSAC keep per-image accumulators of ~0.6 MB: on a CPU, groups of 8 images
        # stay in cache (measured 1.5x faster per image than 64 at once); a GPU takes all.
        self.chunk = chunk if chunk is not None else (8 if self.device.type == "cpu" else None)
        # Most of the work is many small ops (sorts, cumsums, scatters, argmax over one
        # chunk) that torch runs on one thread, so on a CPU whole chunks run concurrently on
        # single-threaded workers instead (measured 1.5x the images/s of 2 intra-op threads
        # on 2 cores). Results never depend on it: chunks are independent.
        if workers is None:
            workers = torch.get_num_threads() if self.device.type == "cpu" else 1
        self.workers = workers

    @torch.no_grad()
    def forward(self, images: torch.Tensor, profile: bool = False,
                veg_color: torch.Tensor | None = None) -> BatchResult:
        """Detect rows in ``uint8 (B, 3, H, W)`` RGB images already at working size.

        With ``profile=True`` the result's ``timings`` holds seconds per stage (this adds a
        device synchronisation after each stage, and runs the chunks one after the other).
        ``veg_color`` (``(B, 3)`` or ``(3,)`` RGB integers in [0, 255]: a tensor of any
        integer dtype, an array or a list) replaces section 2's per-image colour
        clustering, e.g. a colour calibrated once for a field, or the frame-0 colour of a
        video.

        On a CPU with ``workers > 1`` and more than one chunk, chunks of ``chunk`` images run
        in a thread pool with one torch thread each (the global intra-op thread count is
        restored afterwards). Peak memory: about 90 MB per chunk of 8 images at 320x240 in
        flight, plus the LAB table pages touched (a shared read-only memory map).
        """
        check_images(images)
        check_working_size(images.shape[3], images.shape[2], self.params.max_pixels)
        bsz = images.shape[0]
        color = None if veg_color is None else _color_override(veg_color, bsz, self.device)
        step = self.chunk or max(bsz, 1)
        if profile or self.workers <= 1 or bsz <= step or self.device.type != "cpu":
            return self._forward(images, profile, color)
        self._warm(images.shape[2], images.shape[3])
        starts = range(0, bsz, step)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with ThreadPoolExecutor(max_workers=min(self.workers, len(starts))) as pool:
                parts = list(pool.map(lambda s0: self._worker(
                    images[s0:s0 + step], None if color is None else color[s0:s0 + step]), starts))
        finally:
            torch.set_num_threads(threads)
        return concat_batches(parts)

    def _warm(self, height: int, width: int) -> None:
        """Build the shared constant tables once, before worker threads read them."""
        from torchrow.core.tables import lab_table_torch
        from torchrow.functional import hough as fhough
        fhough.trig(self.params, self.device)
        fhough.rho_table(height, width, self.params, self.device)
        fransac._table(self.params, self.device)
        lab_table_torch(self.device)
        if self.params.mode == "improved" and self.params.lattice_vp == "search":
            flattice.vp_table(height, width, self.params, self.device)

    def _worker(self, images: torch.Tensor, veg_color: torch.Tensor | None) -> BatchResult:
        # Thread count (OpenMP's is per thread) and grad mode are thread-local settings.
        torch.set_num_threads(1)
        with torch.no_grad():
            return self._forward(images, False, veg_color)

    def _forward(self, images: torch.Tensor, profile: bool, veg_color: torch.Tensor | None) -> BatchResult:
        p = self.params
        x = images.to(self.device)
        bsz, _, h, w = x.shape
        timings: dict[str, float] = {}
        clock = [time.perf_counter()]

        def lap(name: str) -> None:
            if profile:
                if x.device.type == "cuda":
                    torch.cuda.synchronize(x.device)
                now = time.perf_counter()
                timings[name] = now - clock[0]
                clock[0] = now

        i64 = dict(dtype=torch.int64, device=x.device)
        sky = fsky.sky_row(x, p)
        lap("sky")
        if veg_color is None:
            # a GPU sorts and clusters the whole batch at once; a CPU in cache-sized chunks
            chunk_pixels = fcolor.DEFAULT_CHUNK_PIXELS if x.device.type == "cpu" else None
            color = fcolor.vegetation_color(x, p, chunk_pixels=chunk_pixels)
        else:
            color = veg_color.to(x.device)
        lap("color")
        k = torch.full((bsz,), p.veg_tol, **i64)
        veg = fveg.remove_bushy(fveg.raw_mask(x, color, k, sky), sky, p)
        has_veg = veg.flatten(1).any(dim=1)
        hin, bushy = fveg.hough_input(veg, sky, p)
        lap("vegetation")
        band = fransac.ransac_band(bushy, w, p)
        step = self.chunk or max(bsz, 1)
        parts = []
        for s0 in range(0, max(bsz, 1), step):  # chunks of images: memory and cache, never results
            sl = slice(s0, s0 + step)
            ls = fvan.find_lines(hin[sl], p)
            present = ls.valid & ls.has_vp.unsqueeze(1)
            if p.mode == "improved":  # section 11 replaces section 7
                parts.append((ls, flattice.improved_rows(x[sl], sky[sl], ls.vp, ls.has_vp & has_veg[sl], p)))
                continue
            fit = fransac.fit_rows(veg[sl], ls.theta, ls.rho, present, ls.vp, band[sl], p)
            rows = fransac.validate_rows(fit, present, h, torch.full_like(band[sl], p.hough_band_px(w)), p)
            parts.append((ls, rows))
        ls = concat_batches([q[0] for q in parts])
        rows = concat_batches([q[1] for q in parts])
        if p.mode == "improved":
            rows, curved = flattice.as_row_fits(rows), rows
        lap("hough+vp+ransac")
        faithful = p.mode == "faithful"
        status = fransac.image_status(rows, ls.has_vp if faithful else None, has_veg if faithful else None)
        if not faithful:
            status = flattice.improved_status(curved, status, p)
        return BatchResult(
            width=w, height=h, status=status, sky=sky.to(torch.int64), veg_color=color, k=k, bushy=bushy,
            n_rows=ls.n_rows if p.mode == "faithful" else torch.full_like(ls.n_rows, rows.a.shape[1]),
            hough_theta=ls.theta, hough_rho=ls.rho, hough_weight=ls.weight,
            hough_valid=ls.valid, out_theta=ls.out_theta, out_rho=ls.out_rho, out_weight=ls.out_weight,
            out_valid=ls.out_valid, vp=ls.vp, has_vp=ls.has_vp, row_a=rows.a, row_b=rows.b,
            row_valid=rows.valid, row_reason=rows.reason, row_hypothesis=rows.hypothesis,
            row_present=rows.present, theta_step=p.theta_step, timings=timings,
            **(flattice.curve_fields(curved) if p.mode == "improved" else {}))

    def prepare(self, image: np.ndarray | str | Path) -> np.ndarray:
        """Section 0 for one input: load a path or convert an array, resize to the working width."""
        if isinstance(image, (str, Path)):
            return load_image(image, self.params.image_width, self.params.max_pixels)
        if not isinstance(image, np.ndarray):
            raise TypeError(f"expected a path or a numpy array (H, W, 3), got {type(image).__name__}")
        return resize_to_width(to_rgb8(image), self.params.image_width, self.params.max_pixels)

    def detect(self, images: torch.Tensor | Sequence[np.ndarray | str | Path]) -> BatchResult:
        """Detect rows in a ``uint8 (B, 3, H, W)`` tensor, or a list of same-sized arrays or paths.

        Lists are converted and resized as :func:`torchrow.reference.detect` does. Inputs of
        different working sizes go through :func:`torchrow.engines.runner.run`, which groups them.
        """
        if isinstance(images, torch.Tensor):
            return self(images)
        arrays = [self.prepare(im) for im in images]
        if len({a.shape for a in arrays}) > 1:
            raise ValueError("images of different working sizes: use torchrow.engines.runner.run, which groups them")
        if not arrays:
            raise ValueError("detect got an empty list")
        return self(torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2).contiguous())
