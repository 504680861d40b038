"""Reference per-image pipeline (ALGORITHM.md sections 0-7, 9 and 11): composes the stages."""

from __future__ import annotations

import numpy as np

from torchrow.core.io import check_color, check_color_used, check_evidence_used, evidence_mask, resize_to_width, to_rgb8
from torchrow.core.params import Params
from torchrow.core.results import ImageResult
from torchrow.reference.color import vegetation_color
from torchrow.reference.lattice import horizon_row, improved_result, improved_rows
from torchrow.reference.ransac import fit_row, validate_rows
from torchrow.reference.sky import sky_row
from torchrow.reference.vanishing import find_lines
from torchrow.reference.vegetation import hough_input, raw_mask, remove_bushy

__all__ = ["detect", "prepare"]


def prepare(image: np.ndarray, params: Params) -> np.ndarray:
    """Section 0 on an in-memory array: validate, convert to 8-bit RGB, resize to the working width.

    Raises
    ------
    TypeError
        If ``image`` is not a numpy array.
    ImageError
        (a ``ValueError``) if it is empty, not convertible to ``uint8 (H, W, 3)``, or its
        working size exceeds ``params.max_pixels`` (:func:`torchrow.core.io.check_working_size`).
    """
    if not isinstance(image, np.ndarray):
        raise TypeError(f"detect expects a numpy array of shape (H, W, 3), got {type(image).__name__}")
    return resize_to_width(to_rgb8(image), params.image_width, params.max_pixels)


def detect(image: np.ndarray, params: Params | None = None, name: str | None = None,
           veg_color: tuple[int, int, int] | None = None, evidence: np.ndarray | None = None) -> ImageResult:
    """Detect crop rows in one RGB image, the plain per-image way.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W, 3)`` uint8 RGB (grey, RGBA and 16-bit are converted, see :mod:`torchrow.core.io`).
        Resized to ``params.image_width`` (``cv2.INTER_AREA``) unless already that wide.
    params : Params, optional
        Constants; ``Params()`` by default.
    name : str, optional
        Stored in the result (e.g. the file name).
    veg_color : (int, int, int), optional
        RGB vegetation colour to use instead of section 2's clustering (a colour calibrated
        once for a field, or a video's frame-0 colour): integers in [0, 255], checked by
        :func:`torchrow.core.io.check_color` as in the tensor path (floats raise ``TypeError``).
        Only where section 2 runs (:func:`torchrow.core.io.check_color_used`: not in the improved
        mode with ``lattice_vp="search"``, whose green mask is excess green).
    evidence : numpy.ndarray, optional
        Improved mode only (ALGORITHM.md 11.1.1): the caller's row mask ``(H, W)`` at the
        image's own size, non-zero on crop rows (e.g. a segmentation network's output), used in
        place of the green mask; resized to the working size by
        :func:`torchrow.core.io.evidence_mask`.

    Returns
    -------
    ImageResult
        Rows ``x = a*y + b`` in working-image pixels, with validity and reasons (improved mode:
        the lattice's rows, every visible row in ``lattice_rows``, sections 2-6's fields ``None``).
    """
    params = params or Params()
    check_color_used(veg_color, params)
    check_evidence_used(evidence, params)
    rgb = prepare(image, params)
    h, w = rgb.shape[:2]
    if params.mode == "improved":
        return _improved(rgb, params, name, veg_color, None if evidence is None else evidence_mask(evidence, w, h))
    sky = sky_row(rgb, params)
    color = _color(rgb, params, veg_color)
    k = params.veg_tol
    veg = remove_bushy(raw_mask(rgb, color, k, sky), sky, params)
    res = ImageResult(width=w, height=h, status="no_vp", sky=sky, veg_color=color, k=k, name=name)
    if not veg.any():
        res.status = "no_vegetation"
        res.n_rows = 0
        return res
    hin, res.bushy = hough_input(veg, sky, params)
    search = find_lines(hin, params)
    res.hough, res.outliers, res.n_rows, res.vp = search.lines, search.outliers, search.n_rows, search.vp
    if search.vp is None:
        return res
    band = params.ransac_band_px(w, res.bushy)
    fits = [fit_row(veg, line, search.vp, band, params) for line in search.lines]
    res.rows = validate_rows(fits, h, w, params)
    res.status = "ok" if all(r.valid for r in res.rows) else "invalid"
    return res


def _color(rgb: np.ndarray, params: Params, veg_color: tuple[int, int, int] | None) -> tuple[int, int, int]:
    """Section 2's colour, or the one given."""
    if veg_color is None:
        return vegetation_color(rgb, params)[0]
    r, g, b = (int(c) for c in check_color(veg_color))
    return (r, g, b)


def _improved(rgb: np.ndarray, params: Params, name: str | None,
              veg_color: tuple[int, int, int] | None, evidence: np.ndarray | None = None) -> ImageResult:
    """Section 11 in place of section 7, running only the earlier stages it uses
    (:meth:`Params.runs_sky`, :meth:`Params.runs_section6`); their outputs stay out of the record."""
    h, w = rgb.shape[:2]
    sky = sky_row(rgb, params) if params.runs_sky() else 0
    vp = None
    if params.runs_section6():
        veg = remove_bushy(raw_mask(rgb, _color(rgb, params, veg_color), params.veg_tol, sky), sky, params)
        if veg.any():
            vp = find_lines(hough_input(veg, sky, params)[0], params).vp
    return improved_result(improved_rows(rgb, sky, vp, params, evidence=evidence), w, h, horizon_row(sky, params),
                           params, name)
