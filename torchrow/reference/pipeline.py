"""Reference per-image pipeline (ALGORITHM.md sections 0-7 and 9): composes the stages."""

from __future__ import annotations

import numpy as np

from torchrow.core.io import check_color, resize_to_width, to_rgb8
from torchrow.core.params import Params
from torchrow.core.results import ImageResult
from torchrow.reference.color import vegetation_color
from torchrow.reference.lattice import improved_rows, improved_status
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
           veg_color: tuple[int, int, int] | None = None) -> ImageResult:
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

    Returns
    -------
    ImageResult
        Rows ``x = a*y + b`` in working-image pixels, with validity and reasons.
    """
    params = params or Params()
    rgb = prepare(image, params)
    h, w = rgb.shape[:2]
    sky = sky_row(rgb, params)
    if veg_color is None:
        color, _ = vegetation_color(rgb, params)
    else:
        r, g, b = (int(c) for c in check_color(veg_color))
        color = (r, g, b)
    k = params.veg_tol
    veg = remove_bushy(raw_mask(rgb, color, k, sky), sky, params)
    res = ImageResult(width=w, height=h, status="no_vp", sky=sky, veg_color=color, k=k, name=name)
    vp = None
    if veg.any():
        hin, res.bushy = hough_input(veg, sky, params)
        search = find_lines(hin, params)
        res.hough, res.outliers, res.n_rows, res.vp = search.lines, search.outliers, search.n_rows, search.vp
        vp = search.vp
    else:
        res.status = "no_vegetation"
        res.n_rows = 0
    if params.mode == "improved":  # section 11 replaces section 7 (and runs without a VP too)
        res.rows, res.image_confidence, fit = improved_rows(rgb, sky, vp, params)
        res.n_rows = len(res.rows)  # the rows asked: 2K + 1
        res.status = improved_status(res.rows, fit.contrast, res.image_confidence, params)
        return res
    if vp is None:
        return res
    band = params.ransac_band_px(w, res.bushy)
    fits = [fit_row(veg, line, vp, band, params) for line in search.lines]
    res.rows = validate_rows(fits, h, w, params)
    res.status = "ok" if all(r.valid for r in res.rows) else "invalid"
    return res
