"""Small helpers behind the notebooks in ``notebooks/``: finding the data, stage pictures, ground truth.

Kept in the package (and tested) so that the notebooks stay short and a change in the
pipeline breaks a test rather than a notebook only.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from torchrow.core.params import Params
from torchrow.core.results import ImageResult
from torchrow.evaluation.datasets import ENV_VAR, GroundTruth

__all__ = ["find_data_root", "gt_polylines", "stage_pictures", "show_grid", "result_summary"]


def find_data_root(start: str | os.PathLike[str] | None = None) -> Path:
    """The data folder: ``TORCHROW_DATA`` if set, else ``../shared/data`` beside the repository.

    The repository root is the first folder holding ``pyproject.toml`` at or above ``start``
    (default: the working directory, e.g. ``notebooks/``).

    Raises
    ------
    FileNotFoundError
        If neither exists.
    """
    env = os.environ.get(ENV_VAR, "")
    if env:
        return Path(env).expanduser()
    here = Path(start or Path.cwd()).resolve()
    for d in (here, *here.parents):
        if (d / "pyproject.toml").is_file():
            cand = d.parent / "shared" / "data"
            if cand.is_dir():
                return cand
            break
    raise FileNotFoundError(f"no data folder: set {ENV_VAR} or place the data at ../shared/data "
                            f"beside the repository (searched from {here})")


def gt_polylines(gt: GroundTruth, width: int, shifts: Sequence[int] = range(-4, 5)) -> list[tuple[np.ndarray, np.ndarray]]:
    """Ground-truth crop rows as ``(ys, xs)`` polylines (image rows ``v0 .. H-1``), for
    :func:`torchrow.apps.annotate.draw_result`; only the parts inside ``[0, width)`` are kept."""
    ys = np.arange(gt.v0, gt.height, dtype=np.float64)
    out = []
    for s in shifts:
        xs = gt.centre_x(s, width)
        inside = (xs >= 0) & (xs <= width - 1)
        if inside.sum() >= 2:
            out.append((ys[inside], xs[inside]))
    return out


def stage_pictures(rgb: np.ndarray, params: Params | None = None, gt: GroundTruth | None = None,
                   veg_color: Sequence[int] | None = None) -> dict[str, np.ndarray]:
    """Pictures of every stage of the tensor pipeline on one working image.

    Parameters
    ----------
    rgb : numpy.ndarray
        ``uint8 (H, W, 3)`` RGB working image.
    params : Params, optional
    gt : GroundTruth, optional
        Drawn on the detection picture when given.
    veg_color : 3 ints, optional
        Fixed vegetation colour instead of per-image clustering.

    Returns
    -------
    dict
        ``input`` (H, W, 3) with the horizon drawn, ``colour`` (H, W, 3) the vegetation colour
        as a flat swatch, ``raw mask`` / ``vegetation`` / ``hough input`` (H, W) bool,
        ``hough votes`` (n_theta, 2D+1) float (votes of the Hough input, angle down, rho
        across), ``detection`` (2H + legend, 2W, 3) uint8 (:func:`torchrow.apps.annotate.draw_result`), and
        ``result`` the :class:`~torchrow.core.results.ImageResult`.
    """
    import torch

    from torchrow.apps.annotate import draw_result
    from torchrow.engines.detector import CropRowDetector
    from torchrow.functional import color as fcolor
    from torchrow.functional import hough as fhough
    from torchrow.functional import sky as fsky
    from torchrow.functional import vegetation as fveg

    p = params or Params()
    x = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).unsqueeze(0).contiguous()
    sky = fsky.sky_row(x, p)
    color = (fcolor.vegetation_color(x, p) if veg_color is None
             else torch.tensor(list(veg_color), dtype=torch.uint8).view(1, 3))
    k = torch.full((1,), p.veg_tol, dtype=torch.int64)
    raw = fveg.raw_mask(x, color, k, sky)
    veg = fveg.remove_bushy(raw, sky, p)
    hin, _ = fveg.hough_input(veg, sky, p)
    acc = fhough.votes(hin, p)[0].double().numpy()
    res = CropRowDetector(p)(x, veg_color=None if veg_color is None else color[0]).results()[0]
    shown = rgb.copy()
    s = int(sky[0])
    if s > 0:
        shown[max(s - 1, 0):s + 1] = (255, 220, 0)
    return {
        "input": shown,
        "colour": np.broadcast_to(color[0].numpy().reshape(1, 1, 3), rgb.shape).copy(),
        "raw mask": raw[0].numpy(),
        "vegetation": veg[0].numpy(),
        "hough input": hin[0].numpy(),
        "hough votes": acc,
        "detection": draw_result(rgb, res, scale=2,
                                 ground_truth=None if gt is None else gt_polylines(gt, rgb.shape[1])),
        "result": res,
    }


def show_grid(pictures: Sequence[np.ndarray], titles: Sequence[str] | None = None, ncols: int = 4,
              size: float = 2.2, dpi: int = 70, suptitle: str | None = None):
    """One matplotlib figure with the pictures in a grid (grey colour map for 2-D arrays).

    Small by default (``size`` inches per panel, ``dpi`` 70) so that notebook outputs stay small.
    Returns the figure (closed by the caller or shown by the notebook).
    """
    import matplotlib.pyplot as plt

    n = len(pictures)
    ncols = max(1, min(ncols, n))
    nrows = (n + ncols - 1) // ncols
    fig, axes = plt.subplots(nrows, ncols, figsize=(size * ncols * 4 / 3, size * nrows), dpi=dpi, squeeze=False)
    for i, ax in enumerate(axes.flat):
        ax.axis("off")
        if i >= n:
            continue
        pic = pictures[i]
        if pic.ndim == 2:
            ax.imshow(pic, cmap="gray", aspect="auto" if pic.shape[0] * 2 < pic.shape[1] else "equal",
                      interpolation="nearest")
        else:
            ax.imshow(pic)
        if titles is not None:
            ax.set_title(titles[i], fontsize=8)
    if suptitle:
        fig.suptitle(suptitle, fontsize=9)
    fig.tight_layout()
    return fig


def result_summary(res: ImageResult) -> str:
    """One line: status, valid rows, vanishing point, vegetation colour (improved mode: none)."""
    vp = "none" if res.vp is None else f"({res.vp[0]:.0f}, {res.vp[1]:.0f})"
    colour = "none" if res.veg_color is None else tuple(res.veg_color)
    return (f"{res.name or ''} {res.status}: {sum(r.valid for r in res.rows)}/{len(res.rows)} valid rows, "
            f"vp {vp}, colour {colour}, sky {res.sky}").strip()

