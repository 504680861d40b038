"""The batched detector: composes the tensor stages of :mod:`torchrow.functional`.

:class:`CropRowDetector` runs ALGORITHM.md sections 1-7 (improved mode: section 11 and the
earlier stages it uses) on ``uint8 (B, 3, H, W)`` batches and
returns a :class:`BatchResult` of padded tensors with masks; :meth:`BatchResult.results`
turns it into the same per-image :class:`~torchrow.core.results.ImageResult` records as
:func:`torchrow.reference.detect`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from torch import nn

from torchrow.core.batch import BatchResult
from torchrow.core.io import (
    check_color_used,
    check_evidence_used,
    check_working_size,
    evidence_mask,
    load_image,
    resize_to_width,
    to_rgb8,
)
from torchrow.core.params import Params
from torchrow.core.results import STATUSES, concat_batches
from torchrow.functional import color as fcolor
from torchrow.functional import lattice as flattice
from torchrow.functional import ransac as fransac
from torchrow.functional import sky as fsky
from torchrow.functional import vanishing as fvan
from torchrow.functional import vegetation as fveg
from torchrow.functional._checks import check_device, check_images

__all__ = ["BatchResult", "CropRowDetector", "STATUS_CODES"]

STATUS_CODES = {s: i for i, s in enumerate(STATUSES)}


def evidence_batch(evidence: torch.Tensor | Sequence[np.ndarray] | None,
                   arrays: Sequence[np.ndarray] | None) -> torch.Tensor | None:
    """The caller's row evidence (ALGORITHM.md 11.1.1) in the form the engines' ``forward`` takes.

    With ``arrays`` ``None`` (the images came as a ``(B, 3, H, W)`` tensor) ``evidence`` must be
    a tensor too (``bool (B, H, W)`` at the working size, checked by ``forward``) and is returned
    as it is; with ``arrays`` (the working images, ``(H, W, 3)`` each, of one size) it must be a
    list of as many masks, each at its own image's size, resized by
    :func:`torchrow.core.io.evidence_mask` and stacked into ``bool (B, H, W)``. One rule for
    :meth:`CropRowDetector.detect` and :meth:`torchrow.engines.tracker.Tracker.step`.

    Raises
    ------
    TypeError
        If the images are a tensor and ``evidence`` is not.
    ValueError
        If the images are arrays and ``evidence`` is not a list of one mask per image.
    """
    if evidence is None:
        return None
    if arrays is None:
        if not isinstance(evidence, torch.Tensor):
            raise TypeError(f"evidence: with a tensor of images expected a bool tensor (B, H, W), "
                            f"got {type(evidence).__name__}")
        return evidence
    if isinstance(evidence, torch.Tensor) or len(evidence) != len(arrays):
        got = "a tensor" if isinstance(evidence, torch.Tensor) else f"{len(evidence)} arrays"
        raise ValueError(f"evidence: expected a list of {len(arrays)} arrays (one per image), got {got}")
    h, w = arrays[0].shape[:2]
    return torch.from_numpy(np.stack([evidence_mask(e, w, h) for e in evidence]))


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
        # stay in cache (measured 1.5x faster per image than 64 at once); a GPU takes all. The
        # improved mode takes 12: at batch 64 on 2 workers, 12 was within 1 % of 8 on one day and
        # 9-13 % faster on another, where 16 ranged from 11 % slower to 18 % faster
        # (benchmarks/RESULTS.md); its many small ops contend for the GIL across the workers.
        default = 12 if self.params.mode == "improved" else 8
        self.chunk = chunk if chunk is not None else (default if self.device.type == "cpu" else None)
        # Most of the work is many small ops (sorts, cumsums, scatters, argmax over one
        # chunk) that torch runs on one thread, so on a CPU whole chunks run concurrently on
        # single-threaded workers instead (measured 1.5x the images/s of 2 intra-op threads
        # on 2 cores). Results never depend on it: chunks are independent.
        if workers is None:
            workers = torch.get_num_threads() if self.device.type == "cpu" else 1
        self.workers = workers

    @torch.no_grad()
    def forward(self, images: torch.Tensor, profile: bool = False,
                veg_color: torch.Tensor | None = None, evidence: torch.Tensor | None = None) -> BatchResult:
        """Detect rows in ``uint8 (B, 3, H, W)`` RGB images already at working size.

        With ``profile=True`` the result's ``timings`` holds seconds per stage (this adds a
        device synchronisation after each stage, and runs the chunks one after the other).
        ``veg_color`` (``(B, 3)`` or ``(3,)`` RGB integers in [0, 255]: a tensor of any
        integer dtype, an array or a list) replaces section 2's per-image colour
        clustering, e.g. a colour calibrated once for a field, or the frame-0 colour of a
        video; only where section 2 runs (:func:`torchrow.core.io.check_color_used`).
        ``evidence`` (``bool (B, H, W)`` at the working size; improved mode only): the caller's
        row mask in place of the green mask (ALGORITHM.md 11.1.1), e.g. a segmentation network's.

        On a CPU with ``workers > 1`` and more than one chunk, chunks of ``chunk`` images run
        in a thread pool with one torch thread each (the global intra-op thread count is
        restored afterwards). Peak memory: about 90 MB per chunk of 8 images at 320x240 in
        flight, plus the LAB table pages touched (a shared read-only memory map); in the
        improved mode a batch of 64 CRBD images peaks at about 0.6 GiB RSS in all.
        """
        check_images(images)
        check_working_size(images.shape[3], images.shape[2], self.params.max_pixels)
        check_color_used(veg_color, self.params)
        check_evidence_used(evidence, self.params)
        if evidence is not None:
            flattice.check_evidence(images, evidence)  # before the chunks slice it
        bsz = images.shape[0]
        color = None if veg_color is None else fcolor.color_override(veg_color, bsz, self.device)
        step = self.chunk or max(bsz, 1)
        if profile or self.workers <= 1 or bsz <= step or self.device.type != "cpu":
            return self._forward(images, profile, color, evidence)
        self._warm(images.shape[2], images.shape[3])
        starts = range(0, bsz, step)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with ThreadPoolExecutor(max_workers=min(self.workers, len(starts))) as pool:
                parts = list(pool.map(lambda s0: self._worker(
                    images[s0:s0 + step], None if color is None else color[s0:s0 + step],
                    None if evidence is None else evidence[s0:s0 + step]), starts))
        finally:
            torch.set_num_threads(threads)
        return concat_batches(parts)

    def _warm(self, height: int, width: int) -> None:
        """Build the shared constant tables once, before worker threads read them."""
        from torchrow.core.tables import lab_table_torch
        from torchrow.functional import hough as fhough
        fhough.trig(self.params, self.device)
        fhough.rho_table(height, width, self.params, self.device)
        fransac.hypotheses(self.params, self.device)
        lab_table_torch(self.device)
        if self.params.mode == "improved" and self.params.lattice_vp == "search":
            flattice.vp_table(height, width, self.params, self.device)
            if self.device.type == "cpu":
                flattice.vp_product_table(height, width, self.params, self.device)

    def _worker(self, images: torch.Tensor, veg_color: torch.Tensor | None,
                evidence: torch.Tensor | None) -> BatchResult:
        # Thread count (OpenMP's is per thread) and grad mode are thread-local settings.
        torch.set_num_threads(1)
        with torch.no_grad():
            return self._forward(images, False, veg_color, evidence)

    def _forward(self, images: torch.Tensor, profile: bool, veg_color: torch.Tensor | None,
                 evidence: torch.Tensor | None = None) -> BatchResult:
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

        if p.mode == "improved":
            return self._improved(x, veg_color, lap, timings, evidence)
        sky = fsky.sky_row(x, p)
        lap("sky")
        veg, has_veg, hin, bushy, color, k = self._vegetation(x, sky, veg_color, lap)
        band = fransac.ransac_band(bushy, w, p)
        step = self.chunk or max(bsz, 1)
        parts: list[tuple[fvan.LineSearch, fransac.Rows]] = []
        for s0 in range(0, max(bsz, 1), step):  # chunks of images: memory and cache, never results
            sl = slice(s0, s0 + step)
            ls = fvan.find_lines(hin[sl], p)
            present = ls.valid & ls.has_vp.unsqueeze(1)
            fit = fransac.fit_rows(veg[sl], ls.theta, ls.rho, present, ls.vp, band[sl], p)
            rows = fransac.validate_rows(fit, present, h, torch.full_like(band[sl], p.hough_band_px(w)), p)
            parts.append((ls, rows))
        ls = concat_batches([q[0] for q in parts])
        rows = concat_batches([q[1] for q in parts])
        lap("hough+vp+ransac")
        status = fransac.image_status(rows, ls.has_vp, has_veg)
        return BatchResult.build(w, h, p.theta_step, lines=ls, rows=rows, status=status, sky=sky.to(torch.int64),
                                 veg_color=color, k=k, bushy=bushy, timings=timings)

    def _vegetation(self, x: torch.Tensor, sky: torch.Tensor, veg_color: torch.Tensor | None, lap):
        """Sections 2-4: ``(veg, has_veg, hough input, bushy, colour, k)``."""
        p = self.params
        if veg_color is None:
            # a GPU sorts and clusters the whole batch at once; a CPU in cache-sized chunks
            chunk_pixels = fcolor.DEFAULT_CHUNK_PIXELS if x.device.type == "cpu" else None
            color = fcolor.vegetation_color(x, p, chunk_pixels=chunk_pixels)
        else:
            color = veg_color.to(x.device)
        lap("color")
        k = torch.full((x.shape[0],), p.veg_tol, dtype=torch.int64, device=x.device)
        veg = fveg.remove_bushy(fveg.raw_mask(x, color, k, sky), sky, p)
        has_veg = veg.flatten(1).any(dim=1)
        hin, bushy = fveg.hough_input(veg, sky, p)
        lap("vegetation")
        return veg, has_veg, hin, bushy, color, k

    def _improved(self, x: torch.Tensor, veg_color: torch.Tensor | None, lap, timings: dict[str, float],
                  evidence: torch.Tensor | None = None) -> BatchResult:
        """Section 11 in place of section 7, running only the earlier stages it uses
        (:meth:`Params.runs_sky`, :meth:`Params.runs_section6`); their outputs stay out of the result."""
        p = self.params
        bsz, _, h, w = x.shape
        sky = fsky.sky_row(x, p) if p.runs_sky() else torch.zeros(bsz, dtype=torch.int64, device=x.device)
        lap("sky")
        hin = has_veg = None
        if p.runs_section6():
            _, has_veg, hin, _, _, _ = self._vegetation(x, sky, veg_color, lap)
        step = self.chunk or max(bsz, 1)
        parts: list[flattice.LatticeRows] = []
        for s0 in range(0, max(bsz, 1), step):  # chunks of images: memory and cache, never results
            sl = slice(s0, s0 + step)
            vp = has_vp = None
            if hin is not None and has_veg is not None:
                ls = fvan.find_lines(hin[sl], p)
                vp, has_vp = ls.vp, ls.has_vp & has_veg[sl]
            parts.append(flattice.improved_rows(x[sl], sky[sl], vp, has_vp, p,
                                                evidence=None if evidence is None else evidence[sl]))
        curved = concat_batches(parts)
        lap("lattice")
        status = flattice.improved_status(curved, fransac.image_status(flattice.as_row_fits(curved)), p)
        return flattice.improved_batch(curved, status, flattice.horizon_row(sky, p), p, w, h, timings)

    def prepare(self, image: np.ndarray | str | Path) -> np.ndarray:
        """Section 0 for one input: load a path or convert an array, resize to the working width."""
        if isinstance(image, (str, Path)):
            return load_image(image, self.params.image_width, self.params.max_pixels)
        if not isinstance(image, np.ndarray):
            raise TypeError(f"expected a path or a numpy array (H, W, 3), got {type(image).__name__}")
        return resize_to_width(to_rgb8(image), self.params.image_width, self.params.max_pixels)

    def detect(self, images: torch.Tensor | Sequence[np.ndarray | str | Path],
               evidence: torch.Tensor | Sequence[np.ndarray] | None = None) -> BatchResult:
        """Detect rows in a ``uint8 (B, 3, H, W)`` tensor, or a list of same-sized arrays or paths.

        Lists are converted and resized as :func:`torchrow.reference.detect` does. Inputs of
        different working sizes go through :func:`torchrow.engines.runner.run`, which groups them.
        ``evidence`` (improved mode only, ALGORITHM.md 11.1.1): the caller's row masks, with a
        tensor ``bool (B, H, W)`` at the working size, with a list one array per image at that
        image's own size (:func:`torchrow.core.io.evidence_mask` resizes it).
        """
        check_evidence_used(evidence, self.params)
        if isinstance(images, torch.Tensor):
            return self(images, evidence=evidence_batch(evidence, None))
        arrays = [self.prepare(im) for im in images]
        if len({a.shape for a in arrays}) > 1:
            raise ValueError("images of different working sizes: use torchrow.engines.runner.run, which groups them")
        if not arrays:
            raise ValueError("detect got an empty list")
        masks = evidence_batch(evidence, arrays)
        return self(torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2).contiguous(), evidence=masks)
