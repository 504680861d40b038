"""Differentiable building blocks: soft vegetation mask, Hough voting, weighted vanishing point.

The hard pipeline (:mod:`torchrow.functional`, :class:`torchrow.CropRowDetector`) makes
discrete decisions (an inclusive LAB box, integer votes, picked peaks) and has no useful
gradient. The blocks here are smooth counterparts of three of its stages, written so that a
loss on their outputs can be minimised by gradient descent (for instance to fit the
vegetation colour to ground truth, :mod:`torchrow.nn.calibrate`). Each is a typed functional op
plus a thin :class:`torch.nn.Module` holding its parameters, kornia style:

* :class:`SoftVegetationMask`: float ``(B, 3, H, W)`` RGB in [0, 1] -> float ``(B, H, W)``
  in [0, 1]; hard counterpart ALGORITHM.md 3.2,
  :func:`torchrow.functional.vegetation.raw_mask` (its limit as the temperature -> 0);
* :class:`HoughVoting`: float ``(B, H, W)`` weights -> float ``(B, n_theta, 2D+1)``
  accumulator; hard counterpart ALGORITHM.md 5, :func:`torchrow.functional.hough.votes`
  (equal for 0/1 weights);
* :class:`WeightedVanishingPoint`: float ``(B, N)`` theta (rad), rho (px), weight and an
  optional bool ``valid`` -> ``(B, 2)`` px; hard counterpart ALGORITHM.md 6,
  :func:`torchrow.functional.vanishing.vanishing_point`.

None of this is used by the hard pipeline; importing or running it changes no result there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import kornia
import numpy as np
import torch
from torch import nn

from torchrow.core.params import Params
from torchrow.core.tables import rho_index_table, rho_offset
from torchrow.functional._checks import below_horizon

__all__ = [
    "soft_lab_box",
    "soft_vegetation_mask",
    "hough_voting",
    "weighted_vanishing_point",
    "SoftVegetationMask",
    "HoughVoting",
    "WeightedVanishingPoint",
]

# RGB colours are kept a quarter of an 8-bit level inside [0, 1] so that their logit is
# finite and rounding the initial value back to 8 bits gives the colour that was asked for.
_RGB_EPS = 0.25 / 255.0


# ---------------------------------------------------------------------------------------------
# input guards: one error naming what was expected and what was given
# ---------------------------------------------------------------------------------------------
def _describe(x: object) -> str:
    if isinstance(x, torch.Tensor):
        return f"{x.dtype} {tuple(x.shape)}"
    return type(x).__name__


def _check_float(x: object, name: str, expect: str, ndim: int | None = None) -> torch.Tensor:
    if (not isinstance(x, torch.Tensor) or not x.dtype.is_floating_point
            or (ndim is not None and x.dim() != ndim)):
        raise ValueError(f"{name}: expected a floating-point tensor {expect}, got {_describe(x)}")
    return x


def _check_rgb_float(images: object, name: str = "images") -> torch.Tensor:
    x = _check_float(images, name, "(B, 3, H, W) RGB in [0, 1]", ndim=4)
    if x.shape[1] != 3:
        raise ValueError(f"{name}: expected a floating-point tensor (B, 3, H, W) RGB in [0, 1], "
                         f"got {_describe(x)}")
    return x


def _check_sky(sky: object, batch: int) -> torch.Tensor | None:
    if sky is None:
        return None
    if not isinstance(sky, torch.Tensor) or sky.shape != (batch,) or sky.dtype.is_floating_point \
            or sky.dtype == torch.bool:
        raise ValueError(f"sky: expected an integer tensor of shape ({batch},), got {_describe(sky)}")
    return sky


def _per_image(v: torch.Tensor | float, batch: int, like: torch.Tensor, name: str, width: int = 1) -> torch.Tensor:
    """Broadcast a scalar / ``(width,)`` / ``(B, width)`` value to ``(B, width)`` in ``like``'s dtype."""
    t = torch.as_tensor(v, dtype=like.dtype, device=like.device)
    if t.dim() == 0:
        t = t.expand(width)
    if width == 1 and t.shape == (batch,):
        t = t.unsqueeze(1)
    elif t.shape == (width,):
        t = t.unsqueeze(0).expand(batch, width)
    if t.shape != (batch, width):
        want = "a scalar, " if width == 1 else ""
        raise ValueError(f"{name}: expected {want}({width},) or ({batch}, {width}), got {tuple(t.shape)}")
    return t


# ---------------------------------------------------------------------------------------------
# soft vegetation mask (ALGORITHM.md section 3.2)
# ---------------------------------------------------------------------------------------------
def soft_lab_box(lab: torch.Tensor, center: torch.Tensor, k: torch.Tensor | float,
                 temperature: torch.Tensor | float) -> torch.Tensor:
    """Smooth inclusive LAB box: the soft version of ``all(c - k <= lab <= c + k)``.

    Each of the six half-space tests of the box becomes a logistic sigmoid of its signed
    distance (LAB units) divided by the temperature, and the tests are multiplied::

        soft = prod_ch sigmoid((lab_ch - (c_ch - k)) / T) * sigmoid(((c_ch + k) - lab_ch) / T)

    Parameters
    ----------
    lab : torch.Tensor
        Float ``(B, 3, H, W)`` CIE L*a*b* (``kornia.color.rgb_to_lab`` of RGB in [0, 1]).
    center : torch.Tensor
        Box centre ``c`` in LAB, float ``(3,)`` or ``(B, 3)``.
    k : float or torch.Tensor
        Box half-width in LAB units, a scalar or ``(B,)``.
    temperature : float or torch.Tensor
        ``T > 0`` in LAB units, a scalar or ``(B,)``.

    Returns
    -------
    torch.Tensor
        ``(B, H, W)`` in [0, 1], ``lab``'s dtype and device. Smooth in every argument.

    Notes
    -----
    Convergence to the hard box: a pixel whose six signed distances are all ``>= m`` (inside,
    margin ``m``) has ``soft >= sigmoid(m/T)**6 >= 1 - 6 exp(-m/T)``; a pixel with one of
    them ``<= -m`` (outside by ``m``) has ``soft <= sigmoid(-m/T) <= exp(-m/T)``. So
    ``|soft - hard| <= 6 exp(-m/T)`` for every pixel at least ``m`` from the box boundary,
    and the soft mask tends to the hard mask pointwise (off the boundary) as ``T -> 0``.
    Inside the box the value is at most ``sigmoid(k/T)**6`` (0.89 at ``k = 4``, ``T = 1``).
    """
    _check_float(lab, "lab", "(B, 3, H, W) L*a*b*", ndim=4)
    if lab.shape[1] != 3:
        raise ValueError(f"lab: expected a floating-point tensor (B, 3, H, W) L*a*b*, got {_describe(lab)}")
    b = lab.shape[0]
    c = _per_image(center, b, lab, "center", width=3).reshape(b, 3, 1, 1)
    kk = _per_image(k, b, lab, "k").reshape(b, 1, 1, 1)
    t = _per_image(temperature, b, lab, "temperature").reshape(b, 1, 1, 1)
    lo, hi = c - kk, c + kk  # rounded first, as the hard test is written
    # logsigmoid summed then exp: the product of six sigmoids without underflow of the factors
    log_soft = (nn.functional.logsigmoid((lab - lo) / t) + nn.functional.logsigmoid((hi - lab) / t)).sum(dim=1)
    return log_soft.exp()


def soft_vegetation_mask(images: torch.Tensor, color: torch.Tensor, k: torch.Tensor | float = 4.0,
                         temperature: torch.Tensor | float = 1.0,
                         sky: torch.Tensor | None = None) -> torch.Tensor:
    """Soft vegetation mask of RGB images around an RGB vegetation colour.

    Parameters
    ----------
    images : torch.Tensor
        Float ``(B, 3, H, W)`` RGB in [0, 1] (``uint8 / 255``). Gradients flow to it.
    color : torch.Tensor
        Vegetation colour, RGB in [0, 1], float ``(3,)`` or ``(B, 3)``; its LAB is the box
        centre.
    k : float or torch.Tensor
        Box half-width in LAB units (``Params.veg_tol`` = 4), scalar or ``(B,)``.
    temperature : float or torch.Tensor
        Softness ``T > 0`` in LAB units, scalar or ``(B,)``; ``T -> 0`` gives the hard box.
    sky : torch.Tensor, optional
        Integer ``(B,)`` horizon rows; rows ``y < sky[b]`` are 0 (as in the hard mask).

    Returns
    -------
    torch.Tensor
        ``(B, H, W)`` in [0, 1], the images' dtype and device.

    See Also
    --------
    soft_lab_box : the formula and its convergence bound.
    """
    x = _check_rgb_float(images)
    b, _, h, _ = x.shape
    sky = _check_sky(sky, b)
    col = _per_image(color, b, x, "color", width=3)
    center = kornia.color.rgb_to_lab(col.reshape(b, 3, 1, 1)).reshape(b, 3)
    out = soft_lab_box(kornia.color.rgb_to_lab(x), center, k, temperature)
    if sky is not None:
        out = out * below_horizon(sky.to(x.device), h, as_bool=True).to(out.dtype)
    return out


class SoftVegetationMask(nn.Module):
    """Learnable soft vegetation mask (ALGORITHM.md section 3.2 with a smooth box).

    Parameters
    ----------
    color_rgb : sequence of 3 numbers or torch.Tensor, default (0, 255, 0)
        Initial vegetation colour, 8-bit RGB (0..255; need not be integer). Clamped a quarter
        level inside [0, 255] so that its logit is finite.
    k : float, default 4.0
        LAB box half-width (``Params.veg_tol``); a fixed buffer, not learned.
    temperature : float, default 1.0
        Initial softness ``T > 0`` in LAB units.
    learn_color, learn_temperature : bool, default True
        Whether the colour / temperature are :class:`torch.nn.Parameter` (else buffers).
    dtype : torch.dtype, default torch.float64
        dtype of the parameters (the computation runs in the images' dtype).

    Attributes
    ----------
    color_logit : torch.Tensor
        ``(3,)``: the colour is ``sigmoid(color_logit)``, RGB in (0, 1). Learning the RGB
        colour through a sigmoid keeps it a valid colour, so it can always be rounded to the
        ``uint8`` colour that the hard pipeline takes (``veg_color=``).
    log_temperature : torch.Tensor
        ``()``: ``T = exp(log_temperature)`` stays positive.

    Shape
    -----
    - images: float ``(B, 3, H, W)``, RGB in [0, 1]
    - output: ``(B, H, W)`` in [0, 1], the images' dtype

    Examples
    --------
    >>> m = SoftVegetationMask(color_rgb=(60, 120, 40), temperature=0.5)
    >>> soft = m(images.float() / 255)          # (B, H, W), differentiable
    >>> hard = m.hard(images)                   # bool (B, H, W), the pipeline's mask
    >>> det(images, veg_color=m.color_uint8())  # detect with the (learned) colour
    """

    color_logit: torch.Tensor
    log_temperature: torch.Tensor
    k: torch.Tensor

    def __init__(self, color_rgb: Sequence[float] | torch.Tensor = (0, 255, 0), k: float = 4.0,
                 temperature: float = 1.0, learn_color: bool = True, learn_temperature: bool = True,
                 dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        rgb = torch.as_tensor(color_rgb, dtype=torch.float64).flatten()
        if rgb.shape != (3,) or not torch.isfinite(rgb).all():
            raise ValueError(f"color_rgb: expected 3 finite numbers (0..255), got {color_rgb!r}")
        if not (isinstance(k, (int, float)) and math.isfinite(k) and k >= 0):
            raise ValueError(f"k: expected a finite number >= 0, got {k!r}")
        if not (isinstance(temperature, (int, float)) and math.isfinite(temperature) and temperature > 0):
            raise ValueError(f"temperature: expected a finite number > 0, got {temperature!r}")
        p = (rgb / 255.0).clamp(_RGB_EPS, 1.0 - _RGB_EPS)
        logit = torch.log(p) - torch.log1p(-p)
        log_t = torch.tensor(math.log(temperature), dtype=torch.float64)
        self._set("color_logit", logit.to(dtype), learn_color)
        self._set("log_temperature", log_t.to(dtype), learn_temperature)
        self.register_buffer("k", torch.tensor(float(k), dtype=dtype))

    def _set(self, name: str, value: torch.Tensor, learn: bool) -> None:
        if learn:
            self.register_parameter(name, nn.Parameter(value))
        else:
            self.register_buffer(name, value)

    @property
    def color(self) -> torch.Tensor:
        """Current colour, RGB in (0, 1), ``(3,)`` (differentiable)."""
        return torch.sigmoid(self.color_logit)

    @property
    def temperature(self) -> torch.Tensor:
        """Current temperature ``T = exp(log_temperature) > 0``, ``()`` (differentiable)."""
        return self.log_temperature.exp()

    def center_lab(self, dtype: torch.dtype | None = None) -> torch.Tensor:
        """LAB box centre ``(3,)``: ``kornia.color.rgb_to_lab`` of :attr:`color`."""
        c = self.color if dtype is None else self.color.to(dtype)
        return kornia.color.rgb_to_lab(c.reshape(1, 3, 1, 1)).reshape(3)

    def color_uint8(self) -> torch.Tensor:
        """The colour rounded to 8-bit RGB, ``uint8 (3,)``: what the hard pipeline takes."""
        with torch.no_grad():
            return (self.color.double() * 255.0).round().clamp(0, 255).to(torch.uint8).cpu()

    def forward(self, images: torch.Tensor, sky: torch.Tensor | None = None) -> torch.Tensor:
        """Soft mask of float ``(B, 3, H, W)`` RGB in [0, 1] -> ``(B, H, W)`` in [0, 1].

        ``sky`` (integer ``(B,)``, optional) zeroes the rows above each horizon.
        """
        x = _check_rgb_float(images)
        return soft_vegetation_mask(x, self.color.to(x.dtype), self.k.to(x.dtype),
                                    self.temperature.to(x.dtype), sky)

    def from_lab(self, lab: torch.Tensor, sky: torch.Tensor | None = None) -> torch.Tensor:
        """Soft mask from precomputed LAB ``(B, 3, H, W)`` (saves the conversion in a training loop).

        Gradients flow to the colour and the temperature, not to ``lab``'s source images
        unless ``lab`` itself carries them.
        """
        _check_float(lab, "lab", "(B, 3, H, W) L*a*b*", ndim=4)
        out = soft_lab_box(lab, self.center_lab(lab.dtype), self.k.to(lab.dtype),
                           self.temperature.to(lab.dtype))
        sky = _check_sky(sky, lab.shape[0])
        if sky is not None:
            out = out * below_horizon(sky.to(lab.device), lab.shape[2], as_bool=True).to(out.dtype)
        return out

    def hard(self, images: torch.Tensor, sky: torch.Tensor | None = None) -> torch.Tensor:
        """The hard mask the pipeline computes with this colour: ``bool (B, H, W)``.

        Exactly :func:`torchrow.functional.vegetation.raw_mask` (shared LAB table, inclusive
        box ``c - k <= lab <= c + k`` in float64) with :meth:`color_uint8` and ``k``.

        Parameters
        ----------
        images : torch.Tensor
            ``uint8 (B, 3, H, W)`` RGB.
        sky : torch.Tensor, optional
            Integer ``(B,)`` horizon rows (default: no sky, 0).
        """
        from torchrow.functional.vegetation import raw_mask

        if not isinstance(images, torch.Tensor) or images.dtype != torch.uint8:
            raise ValueError(f"images: expected a uint8 tensor (B, 3, H, W) RGB, got {_describe(images)}")
        b = images.shape[0]
        color = self.color_uint8().to(images.device).expand(b, 3).contiguous()
        k = torch.full((b,), float(self.k), dtype=torch.float64, device=images.device)
        if sky is None:
            sky = torch.zeros(b, dtype=torch.int64, device=images.device)
        return raw_mask(images, color, k, sky)

    def extra_repr(self) -> str:
        rgb = tuple(int(v) for v in self.color_uint8())
        return f"color_rgb≈{rgb}, k={float(self.k):g}, temperature={float(self.temperature.detach()):.4g}"


# ---------------------------------------------------------------------------------------------
# Hough voting (ALGORITHM.md section 5, votes)
# ---------------------------------------------------------------------------------------------
def _cell_table(height: int, width: int, theta_step: int) -> torch.Tensor:
    """``int32 (H*W, n_theta)``: flat accumulator cell ``j*(2D+1) + rho_index`` of every pixel and angle."""
    rho_idx = torch.from_numpy(rho_index_table(height, width, theta_step).astype(np.int32))  # (T, HW)
    n_rho = 2 * rho_offset(height, width) + 1
    rho_idx = rho_idx + torch.arange(rho_idx.shape[0], dtype=torch.int32).view(-1, 1) * n_rho
    return rho_idx.T.contiguous()


#: Bound on the ``(B, pixels, n_theta)`` vote values materialised at once by :func:`hough_voting`.
_VOTE_CHUNK = 1 << 23


def hough_voting(weights: torch.Tensor, cells: torch.Tensor, n_rho: int) -> torch.Tensor:
    """Weighted Hough votes through a precomputed cell table (linear in ``weights``).

    Parameters
    ----------
    weights : torch.Tensor
        Float ``(B, H, W)`` per-pixel vote weights (a soft mask, or 0/1).
    cells : torch.Tensor
        ``int32`` or ``int64 (H*W, n_theta)`` flat cell ``j*n_rho + rho_index`` of every
        pixel (raster order) and angle, as built by :class:`HoughVoting`.
    n_rho : int
        Accumulator height ``2D + 1``.

    Returns
    -------
    torch.Tensor
        ``(B, n_theta, n_rho)`` in ``weights``' dtype: cell ``(j, r)`` holds the sum of the
        weights of the pixels with ``rint(x cos_j + y sin_j) + D == r``. The gradient with
        respect to ``weights[b, y, x]`` is the accumulator gradient gathered at that pixel's
        ``n_theta`` cells.
    """
    w = _check_float(weights, "weights", "(B, H, W)", ndim=3)
    b, h, wd = w.shape
    n_pix, n_theta = cells.shape
    if n_pix != h * wd:
        raise ValueError(f"weights: expected (B, H, W) with H*W = {n_pix} (the table's image size), "
                         f"got {_describe(w)}")
    flat = w.reshape(b, n_pix)
    acc = torch.zeros((b, n_theta * n_rho), dtype=w.dtype, device=w.device)
    if b == 0:
        return acc.view(b, n_theta, n_rho)
    step = max(1, _VOTE_CHUNK // max(1, b * n_theta))
    for p0 in range(0, n_pix, step):  # bounded temporaries; sums are order-independent for 0/1
        idx = cells[p0:p0 + step].reshape(-1)
        src = flat[:, p0:p0 + step].unsqueeze(2).expand(b, idx.numel() // n_theta, n_theta).reshape(b, idx.numel())
        acc.index_add_(1, idx, src)
    return acc.view(b, n_theta, n_rho)


class HoughVoting(nn.Module):
    """Differentiable Hough accumulator of per-pixel weights (ALGORITHM.md section 5).

    Every pixel adds its weight to the cells ``(j, rint(x cos_j + y sin_j) + D)`` read from the
    same shared table as the hard path (:func:`torchrow.core.tables.rho_index_table`), so with 0/1
    weights the result equals :func:`torchrow.functional.hough.votes` exactly (as floats).

    Parameters
    ----------
    height, width : int
        Working image size; inputs must have it.
    params : Params, optional
        Uses ``theta_step`` (angles ``0, step, ..., 180 - step`` degrees).

    Attributes
    ----------
    cells : torch.Tensor
        Non-persistent buffer ``int32 (H*W, n_theta)`` (720 bytes per pixel at 1°: 55 MB at
        320x240); follows ``.to(device)``.

    Notes
    -----
    Cost: one ``index_add`` of ``n_theta`` values per pixel, about 0.4 s per 320x240 image on
    one CPU core (forward; the backward is a gather of the same size). Meant for training
    and analysis, not for the detector's speed path.
    d : int
        ``D = ceil(sqrt(H^2 + W^2))``; cell row ``r`` is ``rho = r - D`` px.

    Shape
    -----
    - weights: float ``(B, H, W)``
    - output: ``(B, n_theta, 2D+1)``, the weights' dtype
    """

    cells: torch.Tensor

    def __init__(self, height: int, width: int, params: Params | None = None) -> None:
        super().__init__()
        if not (isinstance(height, int) and isinstance(width, int) and height >= 1 and width >= 1):
            raise ValueError(f"height, width: expected integers >= 1, got {height!r}, {width!r}")
        self.params = params or Params()
        self.height, self.width = height, width
        self.d = rho_offset(height, width)
        self.n_rho = 2 * self.d + 1
        self.n_theta = self.params.n_theta
        self.register_buffer("cells", _cell_table(height, width, self.params.theta_step), persistent=False)

    def theta(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Angles of the accumulator's rows in radians, ``(n_theta,)``."""
        deg = np.arange(0, 180, self.params.theta_step, dtype=np.float64)
        return torch.tensor(np.deg2rad(deg), dtype=dtype, device=self.cells.device)

    def rho(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """``rho`` (px) of the accumulator's columns, ``(2D+1,)``: ``index - D``."""
        return torch.arange(-self.d, self.d + 1, dtype=dtype, device=self.cells.device)

    def forward(self, weights: torch.Tensor) -> torch.Tensor:
        """Float ``(B, H, W)`` weights -> ``(B, n_theta, 2D+1)`` accumulator."""
        w = _check_float(weights, "weights", f"(B, {self.height}, {self.width})", ndim=3)
        if w.shape[1:] != (self.height, self.width):
            raise ValueError(f"weights: expected a floating-point tensor (B, {self.height}, {self.width}), "
                             f"got {_describe(w)}")
        return hough_voting(w, self.cells, self.n_rho)

    def extra_repr(self) -> str:
        return f"height={self.height}, width={self.width}, n_theta={self.n_theta}, n_rho={self.n_rho}"


# ---------------------------------------------------------------------------------------------
# weighted vanishing point (ALGORITHM.md section 6)
# ---------------------------------------------------------------------------------------------
def weighted_vanishing_point(theta: torch.Tensor, rho: torch.Tensor, weight: torch.Tensor,
                             valid: torch.Tensor | None = None,
                             singular_tol: float = 1e-9) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares intersection of weighted lines ``x cos(theta) + y sin(theta) = rho``.

    Solves ``[[A, C], [C, B]] [x0, y0] = [D, E]`` by Cramer's rule with ``A = sum w cos^2``,
    ``B = sum w sin^2``, ``C = sum w sin cos``, ``D = sum w rho cos``, ``E = sum w rho sin``
    over the valid lines (ALGORITHM.md section 6, thesis eq. 3.3-3.5).

    Parameters
    ----------
    theta : torch.Tensor
        Float ``(B, N)`` line normals' angles in radians.
    rho : torch.Tensor
        Float ``(B, N)`` signed distances of the lines from the image origin, px.
    weight : torch.Tensor
        Float ``(B, N)`` line weights (Hough votes), ``>= 0``.
    valid : torch.Tensor, optional
        ``bool (B, N)`` which slots hold a line (default: all).
    singular_tol : float, default 1e-9
        The system is singular when ``|det| < singular_tol * trace**2`` (``Params.singular_tol``).

    Returns
    -------
    vp : torch.Tensor
        ``(B, 2)`` ``(x0, y0)`` px, ``theta``'s dtype; ``(0, 0)`` where not ``ok`` (with a zero,
        finite gradient there).
    ok : torch.Tensor
        ``bool (B,)``: at least two valid lines and a regular system.
    """
    th = _check_float(theta, "theta", "(B, N) radians", ndim=2)
    r = _check_float(rho, "rho", f"(B, N) = {tuple(th.shape)} px", ndim=2)
    w = _check_float(weight, "weight", f"(B, N) = {tuple(th.shape)}", ndim=2)
    if r.shape != th.shape or w.shape != th.shape:
        raise ValueError(f"theta, rho, weight: expected equal shapes (B, N), got {tuple(th.shape)}, "
                         f"{tuple(r.shape)}, {tuple(w.shape)}")
    if valid is None:
        valid = torch.ones(th.shape, dtype=torch.bool, device=th.device)
    elif not isinstance(valid, torch.Tensor) or valid.dtype != torch.bool or valid.shape != th.shape:
        raise ValueError(f"valid: expected a bool tensor {tuple(th.shape)}, got {_describe(valid)}")
    zero = torch.zeros((), dtype=th.dtype, device=th.device)
    # invalid slots contribute exactly 0 (and get a zero gradient), whatever they hold
    wv = torch.where(valid, w, zero)
    co, si = torch.cos(th), torch.sin(th)
    rv = torch.where(valid, r, zero)
    a = (wv * co * co).sum(1)
    bb = (wv * si * si).sum(1)
    c = (wv * si * co).sum(1)
    d = (wv * rv * co).sum(1)
    e = (wv * rv * si).sum(1)
    det = a * bb - c * c
    trace = a + bb
    ok = (valid.sum(1) >= 2) & ~(det.abs() < singular_tol * trace * trace)
    safe = torch.where(ok, det, torch.ones_like(det))
    x0 = torch.where(ok, (d * bb - c * e) / safe, zero)
    y0 = torch.where(ok, (a * e - c * d) / safe, zero)
    return torch.stack([x0, y0], dim=1), ok


class WeightedVanishingPoint(nn.Module):
    """Differentiable weighted vanishing point of Hough lines (ALGORITHM.md section 6).

    No parameters; see :func:`weighted_vanishing_point`.

    Parameters
    ----------
    singular_tol : float, default ``Params().singular_tol`` (1e-9)

    Shape
    -----
    - theta (rad), rho (px), weight: float ``(B, N)``; valid: bool ``(B, N)``, optional
    - output: ``(vp, ok)``: ``(B, 2)`` px in ``theta``'s dtype and ``bool (B,)``
    """

    def __init__(self, singular_tol: float | None = None) -> None:
        super().__init__()
        self.singular_tol = Params().singular_tol if singular_tol is None else float(singular_tol)

    def forward(self, theta: torch.Tensor, rho: torch.Tensor, weight: torch.Tensor,
                valid: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        return weighted_vanishing_point(theta, rho, weight, valid, self.singular_tol)

    def extra_repr(self) -> str:
        return f"singular_tol={self.singular_tol:g}"
