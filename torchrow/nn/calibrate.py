"""Fit the vegetation colour to ground truth by gradient descent, and measure what it does.

The hard pipeline picks a vegetation colour per image by colour clustering (ALGORITHM.md
section 2) and keeps the pixels inside a LAB box of half-width ``k`` around it (section 3).
Here one colour for a whole field is *learned* instead: a :class:`torchrow.nn.SoftVegetationMask`
(colour and temperature) is fitted on a few training images so that its mask falls on the
ground-truth crop rows, and the learned colour, rounded to 8 bits, is then given to the
unchanged hard pipeline (``CropRowDetector(...)(images, veg_color=...)``) on held-out images.

Target. CRBD's ground truth gives, for every image row ``v >= v0``, the centre offset ``c_v``
and spacing ``d_v`` of the crop rows, so row ``s`` lies at ``x = W/2 + c_v + s d_v``.
:func:`row_band_target` marks the pixels within ``band/2 * d_v`` of any row (a band covering a
fraction ``band`` of the field); the *region* is every pixel of the rows ``v >= v0``.

Loss (:func:`band_loss`), per image, with ``s`` the soft mask restricted to the region::

    precision = sum(s * target) / sum(s)          # share of the mask on the crop rows
    fraction  = sum(s) / sum(region)              # mask size
    loss      = -precision + penalty * relu(1 - fraction / min_fraction)

The precision is what the Hough stage needs (every mask pixel off the rows votes for a wrong
line) and, unlike IoU or BCE against the wide band, it is not improved by blurring the mask
(a uniform mask scores the band's area fraction, about 0.3). The fraction term keeps the mask
from shrinking onto a handful of perfect pixels: below ``min_fraction`` of the region (the
hard masks of CRBD's training images cover 0-11%, median about 2.5%) it costs up to ``penalty``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from torchrow.core.params import Params
from torchrow.evaluation.datasets import CRBD, GroundTruth
from torchrow.nn import SoftVegetationMask

__all__ = ["TrainingSet", "FitResult", "row_band_target", "load_training_set",
           "band_loss", "mask_precision", "fit_vegetation_color"]


def row_band_target(gt: GroundTruth, width: int, band: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Crop-row band mask rendered from one image's ground truth.

    Parameters
    ----------
    gt : GroundTruth
        ``c``, ``d`` (px) for image rows ``v0 .. height-1``.
    width : int
        Image width ``W`` in px (the ground truth is in the image's own pixels).
    band : float, default 0.3
        Fraction of the row spacing covered by each row's band (``|x - x_s(v)| <= band/2 * d_v``).

    Returns
    -------
    target : numpy.ndarray
        ``bool (height, W)``: pixels within the band of some crop row, rows ``v >= v0`` only.
    region : numpy.ndarray
        ``bool (height, W)``: the rows ``v >= v0`` (where the ground truth is defined).
    """
    if not 0 < band <= 1:
        raise ValueError(f"band: expected a fraction in (0, 1], got {band!r}")
    h = gt.height
    target = np.zeros((h, width), dtype=bool)
    region = np.zeros((h, width), dtype=bool)
    region[gt.v0:] = True
    d = np.asarray(gt.d, dtype=np.float64)[:, None]
    x = np.arange(width, dtype=np.float64)[None, :]
    # position in units of the spacing: rows sit at integers
    t = (x - width / 2 - np.asarray(gt.c, dtype=np.float64)[:, None]) / np.where(d > 0, d, np.inf)
    target[gt.v0:] = (np.abs(t - np.round(t)) <= band / 2) & (d > 0)
    return target, region


@dataclass
class TrainingSet:
    """Images with their ground-truth targets, ready for :func:`fit_vegetation_color`.

    ``images`` uint8 ``(B, 3, H, W)`` RGB; ``targets`` and ``regions`` bool ``(B, H, W)``
    (:func:`row_band_target`); ``names`` the image file names.
    """

    images: torch.Tensor
    targets: torch.Tensor
    regions: torch.Tensor
    names: list[str]


def load_training_set(crbd: CRBD, indices: Sequence[int], band: float = 0.3) -> TrainingSet:
    """Load CRBD images ``indices`` with their band targets (:func:`row_band_target`)."""
    rgbs, targets, regions = [], [], []
    for i in indices:
        rgb = crbd.image(i)
        t, r = row_band_target(crbd.ground_truth(i), rgb.shape[1], band)
        if t.shape != rgb.shape[:2]:
            raise ValueError(f"{crbd.names[i]}: ground truth is {t.shape}, image {rgb.shape[:2]}")
        rgbs.append(rgb)
        targets.append(t)
        regions.append(r)
    if not rgbs:
        raise ValueError("load_training_set: no images")
    return TrainingSet(torch.from_numpy(np.stack(rgbs)).permute(0, 3, 1, 2).contiguous(),
                       torch.from_numpy(np.stack(targets)), torch.from_numpy(np.stack(regions)),
                       [crbd.names[i] for i in indices])


def band_loss(mask: torch.Tensor, targets: torch.Tensor, regions: torch.Tensor, min_fraction: float = 0.02,
              penalty: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Loss of soft masks against band targets (module docstring), averaged over images.

    Parameters
    ----------
    mask : torch.Tensor
        Float ``(B, H, W)`` in [0, 1].
    targets, regions : torch.Tensor
        bool ``(B, H, W)``.
    min_fraction, penalty : float
        Mask size below which the size term starts, and its weight.

    Returns
    -------
    loss : torch.Tensor
        ``()``, differentiable.
    precision, fraction : torch.Tensor
        ``(B,)`` per image (detached).
    """
    if mask.shape != targets.shape or mask.shape != regions.shape:
        raise ValueError(f"mask, targets, regions: expected equal shapes (B, H, W), got {tuple(mask.shape)}, "
                         f"{tuple(targets.shape)}, {tuple(regions.shape)}")
    s = mask * regions.to(mask.dtype)
    mass = s.sum(dim=(1, 2))
    on_rows = (s * targets.to(mask.dtype)).sum(dim=(1, 2))
    precision = on_rows / (mass + 1e-9)
    fraction = mass / regions.sum(dim=(1, 2)).clamp(min=1).to(mask.dtype)
    size = torch.relu(1 - fraction / min_fraction)
    loss = (-precision + penalty * size).mean()
    return loss, precision.detach(), fraction.detach()


def mask_precision(masks: torch.Tensor, targets: torch.Tensor, regions: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Precision and size of hard ``bool (B, H, W)`` masks (as :func:`band_loss` measures them).

    Returns ``(precision, fraction)``, float64 ``(B,)`` each; precision is 0 for an empty mask.
    """
    m = masks & regions
    mass = m.sum(dim=(1, 2)).double()
    prec = (m & targets).sum(dim=(1, 2)).double() / mass.clamp(min=1)
    frac = mass / regions.sum(dim=(1, 2)).clamp(min=1).double()
    return prec.numpy(), frac.numpy()


@dataclass
class FitResult:
    """Outcome of :func:`fit_vegetation_color`.

    Attributes
    ----------
    color : numpy.ndarray
        Learned colour, ``uint8 (3,)`` RGB (what ``veg_color=`` takes).
    init_color : numpy.ndarray
        Starting colour, ``uint8 (3,)`` RGB.
    temperature : float
        Learned temperature (LAB units).
    history : list of dict
        Per step: ``step``, ``loss``, ``precision`` (mean soft precision), ``fraction`` (mean
        soft size), ``temperature``, ``color`` (RGB 0..255 floats).
    module : SoftVegetationMask
        The fitted module.
    seconds : float
        Wall time of the fit.
    """

    color: np.ndarray
    init_color: np.ndarray
    temperature: float
    history: list[dict] = field(repr=False)
    module: SoftVegetationMask = field(repr=False)
    seconds: float = 0.0


def fit_vegetation_color(images: torch.Tensor, targets: torch.Tensor, regions: torch.Tensor,
                         init_color: Sequence[int] | np.ndarray | torch.Tensor | None = None,
                         k: float | None = None, temperature: float = 1.0, steps: int = 100,
                         lr: float = 0.05, min_fraction: float = 0.02, penalty: float = 1.0,
                         stride: int = 2, dtype: torch.dtype = torch.float32,
                         params: Params | None = None) -> FitResult:
    """Fit one vegetation colour and a temperature to band targets by gradient descent (Adam).

    Parameters
    ----------
    images : torch.Tensor
        ``uint8 (B, 3, H, W)`` RGB training images.
    targets, regions : torch.Tensor
        bool ``(B, H, W)``, see :func:`row_band_target`.
    init_color : 3 ints (RGB 0..255), optional
        Starting colour. Default: the per-pixel median (over the images) of the colours that
        section 2's clustering picks on each training image.
    k : float, optional
        LAB box half-width; default ``params.veg_tol``.
    temperature : float, default 1.0
        Starting temperature (LAB units), learned in log space.
    steps : int, default 100
        Adam steps on the whole batch.
    lr : float, default 0.05
        Adam step size for the colour logits and the log-temperature.
    min_fraction, penalty : float
        See :func:`band_loss`.
    stride : int, default 2
        The loss sees every ``stride``-th pixel of every ``stride``-th row (precision and
        size are ratios of sums, which a regular subsample estimates well; 4x less work).
    dtype : torch.dtype, default torch.float32
        dtype of the training computation (LAB to float32 moves values by ~1e-5, far below
        the box's scale).
    params : Params, optional

    Returns
    -------
    FitResult

    Notes
    -----
    The images' LAB is computed once (the pipeline's shared float64 table), so a step costs
    the soft box and its gradient only: 25-55 ms per 320x240 image and step with the
    defaults, measured on a shared (busy) 2-core machine.
    """
    from torchrow.functional.color import vegetation_color
    from torchrow.functional.vegetation import lab as lab_of

    p = params or Params()
    if not (isinstance(images, torch.Tensor) and images.dtype == torch.uint8 and images.dim() == 4
            and images.shape[1] == 3 and images.shape[0] >= 1):
        got = f"{images.dtype} {tuple(images.shape)}" if isinstance(images, torch.Tensor) else type(images).__name__
        raise ValueError(f"images: expected uint8 (B, 3, H, W) with B >= 1, got {got}")
    shape = (images.shape[0], images.shape[2], images.shape[3])
    for name, t in (("targets", targets), ("regions", regions)):
        if not isinstance(t, torch.Tensor) or t.dtype != torch.bool or tuple(t.shape) != shape:
            got = f"{t.dtype} {tuple(t.shape)}" if isinstance(t, torch.Tensor) else type(t).__name__
            raise ValueError(f"{name}: expected bool {shape}, got {got}")
    if steps < 0:
        raise ValueError(f"steps: expected >= 0, got {steps}")
    if stride < 1:
        raise ValueError(f"stride: expected >= 1, got {stride}")
    t0 = time.perf_counter()
    if init_color is None:
        init = vegetation_color(images, p).double().median(dim=0).values.to(torch.uint8)
    else:
        init = torch.as_tensor(np.asarray(init_color), dtype=torch.uint8).reshape(3)
    module = SoftVegetationMask(init.tolist(), k=float(p.veg_tol if k is None else k), temperature=temperature)
    # LAB is constant (only the colour and T are learned): computed once, subsampled
    lab = lab_of(images)[..., ::stride, ::stride].to(dtype).contiguous()
    targets, regions = targets[:, ::stride, ::stride], regions[:, ::stride, ::stride]
    opt = torch.optim.Adam(module.parameters(), lr=lr)
    history: list[dict] = []

    def record(step: int, loss: torch.Tensor, prec: torch.Tensor, frac: torch.Tensor) -> None:
        history.append(dict(step=step, loss=float(loss.detach()), precision=float(prec.mean()),
                            fraction=float(frac.mean()), temperature=float(module.temperature.detach()),
                            color=(module.color.detach() * 255).tolist()))

    for step in range(steps + 1):
        opt.zero_grad()
        loss, prec, frac = band_loss(module.from_lab(lab), targets, regions, min_fraction, penalty)
        record(step, loss, prec, frac)
        if step == steps:
            break
        loss.backward()
        opt.step()
    return FitResult(color=module.color_uint8().numpy(), init_color=init.numpy(),
                     temperature=float(module.temperature.detach()), history=history,
                     module=module.requires_grad_(False), seconds=time.perf_counter() - t0)
