"""Synthetic crop-row fields with exact CRBD-style ground truth (NumPy + OpenCV only).

The renderer draws a field of green plant rows on textured brown soil as seen by a forward
looking camera, optionally with sky at the top, weeds, darker soil patches and sensor noise,
and returns the ground truth in the Crop Row Benchmark Dataset's ``.crp`` convention.

Geometry (pixel coordinates: ``x`` = column, ``y``/``v`` = row, origin at the top-left
pixel centre, as everywhere in ``torchrow``)
-----------------------------------------------------------------------------------------
Let ``W, H`` be the image size, ``v0 = sky_rows`` the first ground row, ``(vx, vy)`` the
vanishing point (``vy < v0``), ``L = (H - 1) - vy`` and the perspective scale of image row
``v``::

    s(v) = (v - vy) / L          # 1 at the bottom row, 0 at the vanishing point

Ground rows are equally spaced, so with a camera without roll the rows seen on one image row
are equally spaced too. Row ``j`` (``j = 0`` is the central row, ``j > 0`` to its right) has
its centre at::

    x_j(v) = xc(v) + j * d(v)
    xc(v)  = vx + (xb - vx) * s(v) + k(v)          # central row, xb = W/2 + lateral_offset_px
    d(v)   = spacing_px * s(v)                     # spacing between adjacent rows
    k(v)   = curvature * ((H - 1 - v) / (H - 1 - v0)) ** 2   # 0 at the bottom row

With ``curvature == 0`` every row is the straight line ``x = a_j * y + b_j`` through the
vanishing point, ``a_j = (xb + j * spacing_px - vx) / L``, ``b_j = vx - a_j * vy``. The
curvature term is an image-space quadratic bend shared by all rows (so adjacent rows stay
exactly ``d(v)`` apart and the CRBD model ``c_v + j * d_v`` stays exact). The ground truth is
``c_v = xc(v) - W/2`` and ``d_v = d(v)`` for ``v = v0 .. H-1`` (CRBD: ``u = W/2 + c_v +
j * d_v`` is the 0-based column of row ``j``).

Ground attachment
-----------------
Plants, weeds, soil texture and dark patches live on the ground, in coordinates ``p``
(across the rows, in row spacings, ``p = j`` on the centre of row ``j``) and ``u = 1 / s``
(along the rows, proportional to depth; ``u = 1`` on the bottom image row) shifted by the
forward travel ``travel_px / L``. Everything on the ground is generated from
``numpy.random.default_rng`` seeded with ``(seed, ...)`` and a ground cell index, never from
the frame's geometry, so a sequence of frames that only changes the camera pose shows the
same plants moving coherently. Per-frame sensor noise is seeded with ``(seed, frame)``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from torchrow.core.camera import CameraModel
from torchrow.core.params import Rule, check_fields

__all__ = [
    "FieldSpec",
    "SyntheticField",
    "render",
    "render_batch",
    "demo_field",
    "rowless_scenes",
    "write_crp",
    "save",
    "sequence",
    "GroundField",
    "CameraPose",
    "CameraFrame",
    "render_camera",
    "camera_path",
]

# Texture extent on the ground: p in [-_TEX_P, _TEX_P] row spacings, u in [0, _TEX_U];
# beyond it the texture is mirrored.
_TEX_P = 8.0
_TEX_U = 4.0
_TEX_MAX = 1024  # at most this many texels along each texture axis
# soil brightness octaves: (feature size in px at the bottom row, amplitude), and the
# brightness of light / dark specks (stones, crumbs), all in units of soil_texture
_SOIL_OCTAVES = ((4.0, 1.2), (12.0, 0.6), (60.0, 0.5))
_SPECKS = (1.8, -1.4)
_SHADOW_STRENGTH = 0.38  # brightness removed at the centre of a dark soil patch
_ROW_MIN_RADIUS = 1.0  # px: beyond the depth where a plant is thinner, rows are drawn as lines
_ID_OFFSET = 1 << 24  # keeps cell indices non-negative for numpy.random.SeedSequence
_CELL_ROWS = 8  # rows per ground cell (one random stream per cell)
_SHIFT = 4  # sub-pixel bits for OpenCV drawing
_ONE = 1 << _SHIFT

# random-stream tags (first entry after the seed)
_STREAM_TEXTURE = 0
_STREAM_CELL = 1
_STREAM_NOISE = 2


@dataclass(frozen=True)
class FieldSpec:
    """Everything that defines one synthetic field image (all lengths in pixels).

    Lengths "at the bottom" are measured on the bottom image row ``y = H - 1``; towards the
    vanishing point they shrink with the perspective scale ``s(v)`` (module docstring).

    Parameters
    ----------
    width, height : int
        Image size ``W x H`` (px), at least 16 x 16.
    n_rows : int or None
        Number of plant rows drawn, centred on the central row (``j = -(n//2) ..
        n - 1 - n//2``). ``None`` (default) draws every row that enters the image, like a
        real field: about 5 rows at the bottom of the default view and many more towards the
        horizon.
    spacing_px : float
        Distance between adjacent row centres on the bottom image row (px), > 0.
    vp : (float, float) or None
        Vanishing point ``(x, y)`` (px). Must satisfy ``y < sky_rows`` (above the first
        ground row, so every ground-truth row has a positive spacing). ``None``:
        ``(W/2 + 0.025*W, -0.4*H)`` without sky, ``(W/2 + 0.025*W, sky_rows - 0.1*H)`` with
        sky (the field is cut by its far edge a little below the horizon).
    sky_rows : int
        Rows ``0 .. sky_rows-1`` are sky (bluish-white vertical gradient); ``0`` = no sky.
        Must be ``< H - 1``. The ground truth covers rows ``v0 = sky_rows .. H-1``.
    lateral_offset_px : float
        x of the central row on the bottom image row minus ``W/2`` (px).
    curvature : float
        Lateral bend (px) of every row on the first ground row ``v0`` relative to the
        straight row, growing quadratically from 0 on the bottom row. 0 = straight rows.
    plant_width_px : float
        Width of a plant row at the bottom (px, > 0); a row at scale ``s`` is
        ``plant_width_px * s`` wide.
    plant_spacing_px : float
        Mean distance (image rows at the bottom, px, > 0) between consecutive leaf clumps of
        a row (sown: a jittered regular spacing); clumps are placed on the ground, so they
        crowd together towards the horizon.
    plant_density : float
        Fraction in ``(0, 1]`` of each row's length that carries plants; the rest are
        missing-plant gaps (mean length about 25 px at the bottom). 1 = continuous rows.
    missing_rows : tuple of int
        Row indices ``j`` drawn without any plants (their ground truth is unchanged).
    weeds : float
        Expected number of weed blobs between the rows per ``spacing_px**2`` of soil at the
        bottom-row scale (>= 0; 0 = clean field).
    shadows : float
        Expected number of darker soil patches per ``spacing_px**2`` of soil at the
        bottom-row scale (>= 0; 0 = none; 0.02 gives a few in view).
    noise : float
        Standard deviation (intensity levels, >= 0) of per-pixel Gaussian sensor noise.
    blur : float
        Standard deviation (px, >= 0) of the Gaussian optical blur applied before the noise.
    soil_color, plant_color : (int, int, int)
        Mean RGB of the soil and of the plant leaves. The plant colour must be green-dominant
        (``G >= R + 20`` and ``G >= B + 20``).
    soil_texture : float
        Standard deviation (intensity levels, >= 0) of the soil brightness texture (clods,
        furrows along the rows).
    color_jitter : float
        Standard deviation (intensity levels, >= 0) of the per-clump leaf colour; leaf
        colours are clamped to stay green-dominant (``G - R >= 20``, ``G - B >= 30``).
    travel_px : float
        Forward travel of the camera over the ground, in image rows at the bottom (px). The
        plants move towards the bottom of the image as it grows; the rows do not change.
    frame : int
        Index of the sensor-noise stream (>= 0); used by :func:`sequence`.
    focal_px : float or None
        Focal length (px) used only to convert the heading to radians
        (``heading_rad = atan((vp_x - W/2) / focal_px)``). ``None``: ``0.75 * W``.
    seed : int
        Seed (>= 0) of every random choice.

    Raises
    ------
    ValueError
        On construction, naming the field, for values outside the ranges above.
    """

    width: int = 320
    height: int = 240
    n_rows: int | None = None
    spacing_px: float = 60.0
    vp: tuple[float, float] | None = None
    sky_rows: int = 0
    lateral_offset_px: float = 0.0
    curvature: float = 0.0
    plant_width_px: float = 13.0
    plant_spacing_px: float = 7.0
    plant_density: float = 1.0
    missing_rows: tuple[int, ...] = ()
    weeds: float = 0.12
    shadows: float = 0.0
    noise: float = 3.0
    blur: float = 0.6
    soil_color: tuple[int, int, int] = (148, 124, 96)
    plant_color: tuple[int, int, int] = (84, 136, 52)
    soil_texture: float = 20.0
    color_jitter: float = 9.0
    travel_px: float = 0.0
    frame: int = 0
    focal_px: float | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self, _SPEC_RULES, _SPEC_CROSS_RULES)

    # ------------------------------------------------------------------------------------
    @property
    def vanishing_point(self) -> tuple[float, float]:
        """The vanishing point ``(x, y)`` in px, with the default of ``vp=None`` resolved."""
        if self.vp is not None:
            return (float(self.vp[0]), float(self.vp[1]))
        x = self.width / 2 + 0.025 * self.width
        y = -0.4 * self.height if self.sky_rows == 0 else self.sky_rows - 0.1 * self.height
        return (float(x), float(y))

    @property
    def focal(self) -> float:
        """Focal length (px) for heading conversions: ``focal_px`` or ``0.75 * W``."""
        return float(self.focal_px) if self.focal_px is not None else 0.75 * self.width

    def replace(self, **changes: object) -> FieldSpec:
        """A copy with some fields changed (validated like a new object)."""
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]

    @classmethod
    def at_size(cls, width: int, height: int, **changes: object) -> FieldSpec:
        """The default field scaled to ``width x height`` (then ``changes`` applied).

        Lengths of the 320 x 240 defaults (``spacing_px``, ``plant_width_px``,
        ``plant_spacing_px``) are multiplied by ``width / 320``, so the picture looks the
        same at every size; the default vanishing point is already relative to the size.

        Parameters
        ----------
        width, height : int
            Image size (px).
        **changes
            Any :class:`FieldSpec` field, applied after scaling (not scaled).
        """
        k = width / 320.0
        base = cls()
        kw: dict[str, object] = dict(
            width=width, height=height,
            spacing_px=base.spacing_px * k,
            plant_width_px=base.plant_width_px * k,
            plant_spacing_px=base.plant_spacing_px * k,
        )
        kw.update(changes)
        return cls(**kw)  # type: ignore[arg-type]


_POSITIVE = Rule("float", 0, extra=(lambda v: v > 0, "must be > 0"))
_AT_LEAST_0 = Rule("float", 0)

#: Every field's rule (:class:`torchrow.core.params.Rule`, as :class:`~torchrow.core.params.Params`').
_SPEC_RULES: dict[str, Rule] = {
    "width": Rule("int", 16), "height": Rule("int", 16), "n_rows": Rule("int?", 1),
    "spacing_px": _POSITIVE, "vp": Rule("xy?"), "sky_rows": Rule("int", 0),
    "lateral_offset_px": Rule("float"), "curvature": Rule("float"),
    "plant_width_px": _POSITIVE, "plant_spacing_px": _POSITIVE,
    "plant_density": Rule("float", 0, 1, extra=(lambda v: v > 0, "must lie in (0, 1]")),
    "missing_rows": Rule("ints", count=(0, 1 << 20)),
    "weeds": _AT_LEAST_0, "shadows": _AT_LEAST_0, "noise": _AT_LEAST_0, "blur": _AT_LEAST_0,
    "soil_color": Rule("rgb", 0, 255),
    "plant_color": Rule("rgb", 0, 255, extra=(lambda c: c[1] >= c[0] + 20 and c[1] >= c[2] + 20,
                                              "must be green-dominant (G >= R + 20 and G >= B + 20)")),
    "soil_texture": _AT_LEAST_0, "color_jitter": _AT_LEAST_0, "travel_px": Rule("float"),
    "frame": Rule("int", 0), "focal_px": Rule("float?", 0, extra=(lambda v: v > 0, "must be > 0")),
    "seed": Rule("int", 0, 2**63 - 1),
}

#: Rules that tie fields together: (field named in the error, condition, wording).
_SPEC_CROSS_RULES: tuple[tuple[str, Callable[[FieldSpec], bool], str], ...] = (
    ("sky_rows", lambda s: s.sky_rows < s.height - 1, "must lie in [0, height - 1)"),
    ("vp", lambda s: s.vp is None or s.vp[1] < s.sky_rows,
     "must lie above the first ground row (y < sky_rows)"),
)


@dataclass(frozen=True, eq=False)
class SyntheticField:
    """One rendered field and its exact ground truth.

    Attributes
    ----------
    image : numpy.ndarray, shape (H, W, 3), uint8
        RGB image.
    crp : numpy.ndarray, shape (H - sky, 2), float64
        Ground truth in CRBD's ``.crp`` convention, image rows ``v0 = sky .. H-1``: column 0
        is ``c_v`` (x of the central row minus ``W/2``, px), column 1 is ``d_v`` (spacing
        between adjacent rows, px).
    rows : list of (float, float)
        ``(a, b)`` with ``x = a*y + b`` (px) for every row in :attr:`row_ids`, left to right:
        the true row centre lines, through :attr:`vp`. With ``curvature != 0`` these are the
        straight rows before bending; the exact centres are in :attr:`centers`.
    row_ids : list of int
        Row index ``j`` of each entry of :attr:`rows` (0 = central row, the one ``crp``
        describes; negative to its left). Every row whose centre crosses the image below
        the sky is listed (restricted to the drawn rows when ``spec.n_rows`` is set).
    centers : numpy.ndarray, shape (len(rows), H - sky), float64
        Exact x (px) of each listed row's centre on image rows ``sky .. H-1``
        (``W/2 + c_v + j * d_v``, curvature included).
    vp : (float, float)
        Vanishing point ``(x, y)`` (px).
    sky : int
        Number of sky rows at the top (= ``v0``).
    spec : FieldSpec
        The specification that produced it.
    """

    image: np.ndarray
    crp: np.ndarray
    rows: list[tuple[float, float]]
    row_ids: list[int]
    centers: np.ndarray
    vp: tuple[float, float]
    sky: int
    spec: FieldSpec

    @property
    def v0(self) -> int:
        """First ground-truth image row (= :attr:`sky`)."""
        return self.sky

    @property
    def heading_px(self) -> float:
        """Heading as the vanishing point's x offset from the image centre: ``vp_x - W/2`` (px)."""
        return self.vp[0] - self.spec.width / 2

    @property
    def heading_rad(self) -> float:
        """Heading in radians, ``atan(heading_px / spec.focal)`` (pinhole model)."""
        return math.atan2(self.heading_px, self.spec.focal)

    @property
    def lateral_px(self) -> float:
        """Lateral offset: x of the central row on the bottom image row minus ``W/2`` (px)."""
        return float(self.crp[-1, 0])

    def x_at(self, j: int, y: np.ndarray | float) -> np.ndarray | float:
        """Exact x (px) of row ``j``'s centre on image row(s) ``y`` (curvature included)."""
        return _Geometry(self.spec).x(j, y)


# ----------------------------------------------------------------------------------------
class _Geometry:
    """The perspective model of the module docstring for one spec (all float64)."""

    def __init__(self, spec: FieldSpec) -> None:
        self.W = spec.width
        self.H = spec.height
        self.v0 = spec.sky_rows
        self.vx, self.vy = spec.vanishing_point
        self.L = (self.H - 1) - self.vy
        self.xb = self.W / 2 + float(spec.lateral_offset_px)
        self.spacing = float(spec.spacing_px)
        self.curv = float(spec.curvature)
        self.travel_u = float(spec.travel_px) / self.L

    def s(self, v: np.ndarray | float) -> np.ndarray:  # 0-d for a scalar v
        return (np.asarray(v, dtype=np.float64) - self.vy) / self.L

    def bend(self, v: np.ndarray | float) -> np.ndarray:  # 0-d for a scalar v
        if self.curv == 0.0:
            return np.zeros_like(np.asarray(v, dtype=np.float64))
        t = ((self.H - 1) - np.asarray(v, dtype=np.float64)) / ((self.H - 1) - self.v0)
        return self.curv * t * t

    def xc(self, v: np.ndarray | float) -> np.ndarray:  # 0-d for a scalar v
        return self.vx + (self.xb - self.vx) * self.s(v) + self.bend(v)

    def d(self, v: np.ndarray | float) -> np.ndarray:  # 0-d for a scalar v
        return self.spacing * self.s(v)

    def x(self, j: int, v: np.ndarray | float) -> np.ndarray | float:
        v = np.asarray(v, dtype=np.float64)
        out = np.asarray(self.xc(v) + j * self.d(v))
        return float(out) if out.ndim == 0 else out

    def line(self, j: int) -> tuple[float, float]:
        a = (self.xb + j * self.spacing - self.vx) / self.L
        return (float(a), float(self.vx - a * self.vy))

    def v_of_u(self, u: np.ndarray) -> np.ndarray:
        return self.vy + self.L / u

    def j_range(self, v: np.ndarray, x_lo: float, x_hi: float) -> tuple[int, int]:
        """Smallest/largest j whose centre lies in [x_lo, x_hi] on some row of ``v``."""
        xc, d = self.xc(v), self.d(v)
        lo = np.ceil((x_lo - xc) / d)
        hi = np.floor((x_hi - xc) / d)
        ok = lo <= hi
        if not ok.any():
            return (0, -1)
        return (int(lo[ok].min()), int(hi[ok].max()))


def _fold(t: np.ndarray, n: int) -> np.ndarray:
    """Mirror texel coordinates ``t`` into ``[0, n-1]`` (reflect-101, any magnitude)."""
    if n <= 1:
        return np.zeros_like(t)
    if t.size and t.min() >= 0 and t.max() <= n - 1:
        return t
    period = t.dtype.type(2 * (n - 1))
    return np.abs(np.mod(t + t.dtype.type(n - 1), period) - t.dtype.type(n - 1))


def _noise_octave(rng: np.random.Generator, shape: tuple[int, int], cell_u: float,
                  cell_p: float) -> np.ndarray:
    """Smooth value noise, about unit variance, features ``cell_u x cell_p`` texels large."""
    gh = max(2, int(math.ceil(shape[0] / max(1.0, cell_u))) + 1)
    gw = max(2, int(math.ceil(shape[1] / max(1.0, cell_p))) + 1)
    g = rng.standard_normal((gh, gw), dtype=np.float32)
    if (gh, gw) == shape:
        return g
    return cv2.resize(g, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


@functools.lru_cache(maxsize=8)
def _ground_texture(seed: int, n_u: int, n_p: int, tpu: float, tpp: float, fu: float, fp: float,
                    shadow_count_mean: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Soil texture on the ground grid (texel ``[iu, ip]``), cached per seed and size.

    ``tpu``/``tpp`` are texels per unit of ``u``/``p``; ``fu``/``fp`` texels per bottom-row
    pixel along/across the rows. Returns the brightness texture (float32 (n_u, n_p), of
    order unit variance), its blurred copy (used where the image minifies the texture) and
    the dark-patch map in [0, 1] (``None`` without patches). The arrays are shared and
    read-only.
    """
    rng = np.random.default_rng((seed, _STREAM_TEXTURE))
    shape = (n_u, n_p)

    def octave(cell_px: float) -> np.ndarray:
        return _noise_octave(rng, shape, cell_px * fu, cell_px * fp)

    tex = np.zeros(shape, np.float32)
    for cell_px, amp in _SOIL_OCTAVES:
        tex += np.float32(amp) * octave(cell_px)
    # stones and crumbs: sparse light and dark specks of a texel or two
    speck = octave(1.0)
    tex += np.where(speck > 2.0, _SPECKS[0], 0.0).astype(np.float32)
    tex += np.where(speck < -2.2, _SPECKS[1], 0.0).astype(np.float32)
    # furrows along the rows: slightly lighter midway between rows (p = j + 1/2); the
    # copy without them is used where rows are so close that they would alias into moire
    tex_soft = tex.copy()
    p = (np.arange(n_p, dtype=np.float32) / np.float32(tpp)) - np.float32(_TEX_P)
    tex += (-0.45 * np.cos(2 * np.pi * p)).astype(np.float32)[None, :]
    n_sh = int(rng.poisson(shadow_count_mean)) if shadow_count_mean > 0 else 0
    shade = None
    if n_sh:
        shade = np.zeros(shape, np.float32)
        r = rng.random((n_sh, 6))
        for i in range(n_sh):
            cp, cu = r[i, 0] * n_p, r[i, 1] * n_u
            ap = (0.3 + 0.7 * r[i, 2]) * tpp  # half-axes in texels
            au = (0.05 + 0.2 * r[i, 3]) * tpu
            cv2.ellipse(shade, (int(cp * _ONE), int(cu * _ONE)),
                        (max(_ONE, int(ap * _ONE)), max(_ONE, int(au * _ONE))),
                        -20.0 + 40.0 * r[i, 4], 0, 360, 0.6 + 0.4 * r[i, 5], -1, cv2.LINE_8, _SHIFT)
        shade = np.asarray(cv2.GaussianBlur(shade, (0, 0), max(1.5, 0.2 * min(tpp, tpu))), np.float32)
    for a in (tex, tex_soft, shade):
        if a is not None:
            a.setflags(write=False)
    return tex, tex_soft, shade


def _soil(spec: FieldSpec, geo: _Geometry, v: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Soil RGB (float32, (H - v0, W, 3)) for ground rows ``v`` and columns ``x``."""
    # texel densities: one texel per 3 px at the bottom, capped to keep the texture small
    tpp = min(geo.spacing / 3.0, _TEX_MAX / (2 * _TEX_P))  # texels per row spacing
    tpu = min(geo.L / 3.0, _TEX_MAX / _TEX_U)  # texels per unit of u
    n_p = max(2, int(round(2 * _TEX_P * tpp)))
    n_u = max(2, int(round(_TEX_U * tpu)))
    area = (2 * _TEX_P) * _TEX_U * geo.L / geo.spacing  # in spacing_px**2 at the bottom scale
    tex, tex_soft, shade = _ground_texture(spec.seed, n_u, n_p, tpu, tpp, tpu / geo.L,
                                           tpp / geo.spacing, spec.shadows * area)

    # ground coordinates of every pixel (float32 is ample for texture look-ups)
    vv = v[:, None]
    s = geo.s(vv)
    inv_d = (1.0 / geo.d(vv)).astype(np.float32)
    xc = geo.xc(vv).astype(np.float32)
    tp = (x[None, :].astype(np.float32) - xc) * (inv_d * np.float32(tpp)) + np.float32(_TEX_P * tpp)
    tu = np.broadcast_to(((1.0 / s + geo.travel_u) * tpu).astype(np.float32), tp.shape)
    tp = _fold(tp, n_p)
    tu = np.ascontiguousarray(_fold(tu, n_u))
    # where adjacent rows are less than 8 px apart, fade to the level without furrows
    wgt = np.clip((8.0 - geo.d(vv)) / 4.0, 0.0, 1.0).astype(np.float32)
    if np.all(wgt == 0):
        t = cv2.remap(tex, tp, tu, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    else:
        sharp = cv2.remap(tex, tp, tu, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        soft = cv2.remap(tex_soft, tp, tu, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        t = sharp + (soft - sharp) * wgt
    t = np.asarray(t, np.float32) * np.float32(spec.soil_texture)
    out = (np.asarray(spec.soil_color, np.float32)[None, None, :]
           + t[:, :, None] * np.array([1.0, 0.92, 0.8], np.float32))
    if shade is not None:
        sh = cv2.remap(shade, tp, tu, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out *= (1.0 - np.float32(_SHADOW_STRENGTH) * np.clip(sh, 0, 1))[:, :, None]
    return out


def _sky(spec: FieldSpec, n: int, width: int) -> np.ndarray:
    """Sky RGB (float32, (n, W, 3)): blue at the top to hazy white at the horizon."""
    top = np.array([118.0, 158.0, 214.0], np.float32)
    hor = np.array([208.0, 216.0, 228.0], np.float32)
    t = (np.arange(n, dtype=np.float32) / max(1, n - 1)) ** 0.7 if n > 1 else np.ones(1, np.float32)
    col = top[None, :] * (1 - t[:, None]) + hor[None, :] * t[:, None]
    # a faint horizontal brightness drift across the sky
    xs = np.linspace(-1.0, 1.0, width, dtype=np.float32)
    drift = (6.0 * xs)[None, :, None]
    return col[:, None, :] + drift


def _green(base: np.ndarray, z: np.ndarray, jitter: float,
           tint: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Leaf colours (float64 (n, 3)) around ``base`` from standard normals ``z`` (n, 4).

    Column 0 of ``z`` drives the brightness, columns 1..3 the per-channel tint; the result
    is clamped to stay green-dominant (``G - R >= 20``, ``G - B >= 30``).
    """
    c = (base[None, :] + np.asarray(tint)[None, :]
         + (z[:, 0:1] * jitter) * np.array([0.8, 1.0, 0.55]) + z[:, 1:4] * (0.35 * jitter))
    c[:, 1] = np.clip(c[:, 1], 60, 235)
    c[:, 0] = np.clip(c[:, 0], 0, c[:, 1] - 20)
    c[:, 2] = np.clip(c[:, 2], 0, c[:, 1] - 30)
    return c


def _draw_ellipses(img: np.ndarray, depth: np.ndarray, x: np.ndarray, y: np.ndarray,
                   ax: np.ndarray, ay: np.ndarray, ang: np.ndarray, col: np.ndarray) -> None:
    """Fill ellipses (centres/half-axes in px, angles in degrees) far-to-near (``depth`` desc)."""
    if depth.size == 0:
        return
    order = np.argsort(-depth, kind="stable")
    cx = np.rint(x[order] * _ONE).astype(np.int64).tolist()
    cy = np.rint(y[order] * _ONE).astype(np.int64).tolist()
    a1 = np.maximum(np.rint(ax[order] * _ONE), _ONE // 2).astype(np.int64).tolist()
    a2 = np.maximum(np.rint(ay[order] * _ONE), _ONE // 2).astype(np.int64).tolist()
    an = ang[order].tolist()
    cl = col[order].tolist()
    ellipse, line8 = cv2.ellipse, cv2.LINE_8
    for i in range(len(cx)):
        ellipse(img, (cx[i], cy[i]), (a1[i], a2[i]), an[i], 0, 360, cl[i], -1, line8, _SHIFT)


def _plants(spec: FieldSpec, geo: _Geometry, img: np.ndarray, drawn: range | None) -> None:
    """Draw the plant rows and weeds onto ``img`` (float32 (H, W, 3), modified in place).

    The ground is cut into cells ``(b, g)``: ``u`` in ``[b, b+1)`` along the rows
    ``j = 8g .. 8g+7`` (plus, for weeds, the strip between each row ``j`` and ``j+1``). Each
    cell's content comes from its own ``default_rng((seed, 1, b, g))`` stream, drawn in a
    fixed order whatever is visible, so it does not depend on the camera pose.
    """
    W, H = geo.W, geo.H
    half_w = spec.plant_width_px / 2.0
    base = np.asarray(spec.plant_color, np.float64)
    # image u range that can touch the image: a little below the bottom row up to the
    # depth where plants get thinner than _ROW_MIN_RADIUS (farther: drawn as lines)
    u_top = geo.L / (geo.v0 - geo.vy)
    u_bot = geo.L / ((H - 1) + 1.2 * half_w - geo.vy)
    s_min = _ROW_MIN_RADIUS / (half_w * 0.8)
    u_cap = min(u_top, 1.0 / s_min) if s_min < 1.0 else u_bot
    n_per = max(1, int(round(geo.L / spec.plant_spacing_px)))  # clumps per unit u per row
    slot = np.tile(np.arange(n_per, dtype=np.float64), _CELL_ROWS)
    # missing-plant gaps: a Poisson process of stretches of mean length gap_len (u units,
    # about 25 px at the bottom for the default spacing); a point is outside every gap with
    # probability exp(-gap_rate * gap_len) = plant_density
    gap_len = 25.0 / geo.L * (spec.spacing_px / 60.0)
    gap_rate = -math.log(spec.plant_density) / gap_len
    weed_rate = spec.weeds * geo.L / geo.spacing  # per ground cell (1 spacing x 1 u)
    missing = set(int(j) for j in spec.missing_rows)
    tu = geo.travel_u
    margin = 2.0 * half_w + 2.0  # px at the bottom scale: leaf radius + lateral jitter

    clumps: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (j, uniforms (n, 8), normals (n, 5))
    weeds: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (j, uniforms (n, 12), normals (n, 10))
    G = _CELL_ROWS
    if u_cap > u_bot:
        for b in range(int(math.floor(u_bot + tu)), int(math.floor(u_cap + tu)) + 1):
            ua = max(b - tu, u_bot)  # image-u interval of this ground block
            ub = min(b + 1 - tu, u_cap)
            if ub <= ua:
                continue
            vs = geo.v_of_u(np.linspace(ua, ub, 9))
            j_lo, j_hi = geo.j_range(vs, -margin, W - 1 + margin)
            for g in range((j_lo - 1) // G, (j_hi + 1) // G + 1):
                rng = np.random.default_rng((spec.seed, _STREAM_CELL, b + _ID_OFFSET, g + _ID_OFFSET))
                rows_j = np.arange(g * G, g * G + G)
                # sown crops: clumps on a jittered regular grid along each row
                cu = rng.random((G * n_per, 8))
                cn = rng.standard_normal((len(cu), 5))
                cj = np.repeat(rows_j, n_per)
                cu[:, 0] = (slot + 0.5 + 0.7 * (cu[:, 0] - 0.5)) / n_per
                n_gap = rng.poisson(gap_rate, G) if spec.plant_density < 1 else np.zeros(G, np.int64)
                gu = rng.random((int(n_gap.sum()), 2))
                gj = np.repeat(rows_j, n_gap)
                n_w = rng.poisson(weed_rate, G) if weed_rate > 0 else np.zeros(G, np.int64)
                wu = rng.random((int(n_w.sum()), 12))
                wn = rng.standard_normal((len(wu), 10))
                wj = np.repeat(rows_j, n_w)
                cu[:, 0] += b
                wu[:, 0] += b
                keep = np.ones(len(cu), bool)
                if drawn is not None:
                    keep &= (cj >= drawn.start) & (cj < drawn.stop)
                for jm in missing:
                    keep &= cj != jm
                if len(gu):  # missing-plant stretches: drop the clumps inside them
                    g0 = b + gu[:, 0] - 0.5 * gap_len
                    g1 = g0 - gap_len * np.log1p(-gu[:, 1])
                    inside = ((cj[:, None] == gj[None, :]) & (cu[:, 0:1] >= g0[None, :])
                              & (cu[:, 0:1] < g1[None, :]))
                    keep &= ~inside.any(axis=1)
                clumps.append((cj[keep], cu[keep], cn[keep]))
                weeds.append((wj, wu, wn))

    depth_l: list[np.ndarray] = []
    x_l: list[np.ndarray] = []
    y_l: list[np.ndarray] = []
    ax_l: list[np.ndarray] = []
    ay_l: list[np.ndarray] = []
    ang_l: list[np.ndarray] = []
    col_l: list[np.ndarray] = []
    if clumps:
        jj = np.concatenate([c[0] for c in clumps]).astype(np.float64)
        cu = np.concatenate([c[1] for c in clumps])
        cn = np.concatenate([c[2] for c in clumps])
        ui = cu[:, 0] - tu
        ok = (ui >= u_bot) & (ui <= u_cap)
        s = 1.0 / np.where(ok, ui, 1.0)
        # far away the clumps crowd together: draw a share that keeps the row covered
        ok &= cu[:, 7] < np.clip(1.8 * s, 0.0, 1.0)
        ui, s, jj, cu, cn = ui[ok], s[ok], jj[ok], cu[ok], cn[ok]
        v = geo.v_of_u(ui)
        size = 0.55 + 0.45 * cu[:, 1]
        x = geo.xc(v) + jj * geo.d(v) + cn[:, 0] * (0.12 * spec.plant_width_px) * s
        r = half_w * size * s
        on = (x + r >= -1) & (x - r <= W) & (v - r <= H) & (v + r >= -1)
        ui, s, v, x, r, cu, cn = ui[on], s[on], v[on], x[on], r[on], cu[on], cn[on]
        aspect = 0.4 + 0.45 * cu[:, 3]
        ang = 180.0 * cu[:, 2]
        col = _green(base, cn[:, 1:5], spec.color_jitter)
        for acc, item in ((depth_l, ui), (x_l, x), (y_l, v), (ax_l, r), (ay_l, r * aspect), (ang_l, ang),
                          (col_l, col)):
            acc.append(item)
        # a second leaf on most clumps big enough to show it
        two = (cu[:, 4] < 0.6) & (r > 2.0)
        r2 = (r * (0.5 + 0.4 * cu[:, 6]))[two]
        for acc, item in ((depth_l, ui[two] - 1e-9), (x_l, x[two]), (y_l, v[two]), (ax_l, r2),
                          (ay_l, r2 * aspect[two] * 0.9), (ang_l, ang[two] + 50.0 + 80.0 * cu[two, 5]),
                          (col_l, np.clip(col[two] + np.array([4.0, 8.0, 2.0]), 0, 255))):
            acc.append(item)
    if weeds:
        jj = np.concatenate([w[0] for w in weeds]).astype(np.float64)
        wu = np.concatenate([w[1] for w in weeds])
        wn = np.concatenate([w[2] for w in weeds])
        ui = wu[:, 0] - tu
        ok = (ui >= u_bot) & (ui <= u_cap)
        ui, jj, wu, wn = ui[ok], jj[ok], wu[ok], wn[ok]
        s = 1.0 / ui
        v = geo.v_of_u(ui)
        p = jj + 0.22 + 0.56 * wu[:, 1]
        xw = geo.xc(v) + p * geo.d(v)
        rw = (0.12 + 0.2 * wu[:, 2]) * spec.plant_width_px * s
        k = 1 + np.floor(3.0 * wu[:, 3])  # 1..3 leaves
        col = _green(base, wn[:, 6:10], spec.color_jitter, tint=(18.0, 8.0, -4.0))
        for m in range(3):
            sel = k > m
            rr = rw[sel] * (1.0 - 0.25 * m)
            cx = xw[sel] + wn[sel, 2 * m] * rw[sel] * 0.8
            cy = v[sel] + wn[sel, 2 * m + 1] * rw[sel] * 0.5
            on = (cx + rr >= -1) & (cx - rr <= W) & (cy - rr <= H) & (cy + rr >= -1)
            for acc, item in ((depth_l, ui[sel][on]), (x_l, cx[on]), (y_l, cy[on]), (ax_l, rr[on]),
                              (ay_l, rr[on] * (0.35 + 0.55 * wu[sel, 4 + m][on])),
                              (ang_l, 180.0 * wu[sel, 7 + m][on]), (col_l, col[sel][on])):
                acc.append(item)
    if depth_l:
        _draw_ellipses(img, *(np.concatenate(a) for a in
                              (depth_l, x_l, y_l, ax_l, ay_l, ang_l, col_l)))

    # far field: rows thinner than _ROW_MIN_RADIUS are drawn as 1-px lines
    if u_cap < u_top:
        v_cap = min(float(geo.v_of_u(np.asarray(max(u_cap, u_bot)))), H - 1.0)
        vs = np.arange(v_cap, geo.v0 - 1.0, -1.0)
        if vs.size >= 2:
            j_lo, j_hi = geo.j_range(vs, -2.0, W + 1.0)
            colour = tuple(float(c) for c in (base * np.array([0.97, 0.97, 0.95])))
            js = np.array([j for j in range(j_lo, j_hi + 1)
                           if (drawn is None or j in drawn) and j not in missing], np.float64)
            if js.size:
                px = np.rint((geo.xc(vs)[None, :] + js[:, None] * geo.d(vs)[None, :]) * _ONE)
                py = np.broadcast_to(np.rint(vs * _ONE), px.shape)
                pts = np.stack([px, py], axis=2).astype(np.int32)  # (rows, points, 2)
                cv2.polylines(img, list(pts[:, :, None, :]), False, colour, 1, cv2.LINE_8, _SHIFT)


def render(spec: FieldSpec | None = None) -> SyntheticField:
    """Render one synthetic field.

    Parameters
    ----------
    spec : FieldSpec, optional
        What to draw; default ``FieldSpec()`` (320 x 240, straight rows, no sky).

    Returns
    -------
    SyntheticField
        ``image`` uint8 (H, W, 3) RGB, ``crp`` float64 (H - sky_rows, 2) as ``(c_v, d_v)``,
        the row lines, vanishing point and sky height. Identical bytes for identical specs.
    """
    spec = FieldSpec() if spec is None else spec
    geo = _Geometry(spec)
    W, H, v0 = geo.W, geo.H, geo.v0
    v = np.arange(v0, H, dtype=np.float64)
    x = np.arange(W, dtype=np.float64)

    img = np.empty((H, W, 3), np.float32)
    img[v0:] = _soil(spec, geo, v, x)
    drawn = None
    if spec.n_rows is not None:
        drawn = range(-(spec.n_rows // 2), spec.n_rows - spec.n_rows // 2)
    _plants(spec, geo, img, drawn)
    if v0 > 0:
        img[:v0] = _sky(spec, v0, W)
    if spec.blur > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), float(spec.blur)), np.float32)
    if spec.noise > 0:
        rng = np.random.default_rng((spec.seed, _STREAM_NOISE, spec.frame))
        noise = rng.standard_normal(img.shape, dtype=np.float32)
        noise *= np.float32(spec.noise)
        img += noise
    np.rint(img, out=img)
    np.clip(img, 0, 255, out=img)
    image = img.astype(np.uint8)

    # ground truth
    c = geo.xc(v) - W / 2.0
    d = geo.d(v)
    crp = np.stack([c, d], axis=1).astype(np.float64)
    j_lo, j_hi = geo.j_range(v, 0.0, W - 1.0)
    js = np.arange(j_lo, j_hi + 1)
    if drawn is not None:
        js = js[(js >= drawn.start) & (js < drawn.stop)]
    centers = geo.xc(v)[None, :] + js[:, None].astype(np.float64) * d[None, :]
    # keep only rows whose centre really enters the image on some ground row
    inside = np.any((centers >= 0) & (centers <= W - 1), axis=1)
    centers = np.ascontiguousarray(centers[inside])
    ids = [int(j) for j in js[inside]]
    rows = [geo.line(j) for j in ids]
    return SyntheticField(image=image, crp=crp, rows=rows, row_ids=ids, centers=centers,
                          vp=(geo.vx, geo.vy), sky=v0, spec=spec)


def render_batch(specs: Sequence[FieldSpec]) -> np.ndarray:
    """Render several fields of one size as a batch.

    Parameters
    ----------
    specs : sequence of FieldSpec
        ``B >= 1`` specs, all with the same ``width`` and ``height``.

    Returns
    -------
    numpy.ndarray, shape (B, 3, H, W), uint8
        RGB images, channels first (the tensor path's input layout).

    Raises
    ------
    ValueError
        If ``specs`` is empty or the sizes differ.
    """
    specs = list(specs)
    if not specs:
        raise ValueError("render_batch needs at least one spec")
    size = (specs[0].width, specs[0].height)
    for i, s in enumerate(specs):
        if (s.width, s.height) != size:
            raise ValueError(f"render_batch: spec {i} is {s.width}x{s.height}, spec 0 is {size[0]}x{size[1]}")
    out = np.empty((len(specs), 3, size[1], size[0]), np.uint8)
    for i, s in enumerate(specs):
        out[i] = render(s).image.transpose(2, 0, 1)
    return out


def demo_field() -> SyntheticField:
    """The default field, ``render(FieldSpec())`` (320 x 240, used by ``torchrow demo``)."""
    return render(FieldSpec())


def rowless_scenes(seed: int = 0, height: int = 240, width: int = 320) -> dict[str, np.ndarray]:
    """Ten RGB images without crop rows, for checking that a detector does not call them ``ok``.

    A grey wall, uniform noise, green noise, sky, bare soil, soil with weed spots, asphalt, a
    fine and a coarse lawn, and a road under sky: ``uint8 (height, width, 3)`` each, in that
    order, from ``numpy.random.default_rng(seed)`` (the same images for the same arguments).
    """
    if height < 2 or width < 2:
        raise ValueError(f"scenes need at least 2x2 pixels, got {width}x{height}")
    rng = np.random.default_rng(seed)
    h, w = height, width

    def smooth(sigma: float) -> np.ndarray:  # unit-variance texture, features of about sigma px
        a = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), sigma)
        return (a / max(float(a.std()), 1e-6))[..., None]

    def u8(a: np.ndarray) -> np.ndarray:
        return np.clip(a, 0, 255).astype(np.uint8)

    g = np.linspace(0, 1, h)[:, None, None]
    sky = u8(np.array([120, 170, 235]) * (1 - 0.3 * g) + rng.normal(0, 3, (h, w, 3)))
    coarse = smooth(6)
    spots = smooth(3) > 0.35
    horizon = max(1, h // 3)
    return {
        "wall": np.full((h, w, 3), 128, np.uint8),
        "noise": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        "green noise": u8(rng.normal([90, 120, 70], 40, (h, w, 3))),
        "sky": sky,
        "soil": u8(np.array([110, 80, 55]) + 25 * smooth(2) + rng.normal(0, 6, (h, w, 3))),
        "soil with weed spots": u8(np.where(spots, np.array([60, 140, 50]), np.array([120, 90, 60]) + 20 * coarse)),
        "asphalt": u8(90 + rng.normal(0, 18, (h, w, 1)).repeat(3, 2)),
        "lawn": u8(np.array([70, 130, 50]) + 30 * smooth(1.5) + rng.normal(0, 8, (h, w, 3))),
        "coarse lawn": u8(np.array([60, 120, 45]) + 40 * coarse),
        "road under sky": np.concatenate([sky[:horizon], u8(85 + rng.normal(0, 10, (h - horizon, w, 1)).repeat(3, 2))]),
    }


def write_crp(path: str | Path, crp: np.ndarray) -> Path:
    """Write ground truth in CRBD's ``.crp`` text format.

    Parameters
    ----------
    path : str or path-like
        Output file (parent folders are created).
    crp : numpy.ndarray, shape (n, 2)
        ``(c_v, d_v)`` rows (px) for image rows ``H - n .. H - 1``.

    Returns
    -------
    pathlib.Path
        The file written: one line ``"%f\\t%f"`` per image row, each ending in ``"\\n"``.
    """
    a = np.asarray(crp, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"crp must have shape (n, 2); got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("crp holds non-finite values")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text("".join(f"{c:f}\t{d:f}\n" for c, d in a.tolist()))
    return p


def save(fld: SyntheticField, folder: str | Path, name: str, ext: str = ".png",
         jpeg_quality: int = 95) -> tuple[Path, Path]:
    """Write a field as an image plus its ``.crp`` ground truth.

    Parameters
    ----------
    fld : SyntheticField
        The rendered field.
    folder : str or path-like
        Output folder (created if needed).
    name : str
        File stem, e.g. ``"synth_000"``.
    ext : str
        Image extension: ``".png"`` (lossless, default), ``".jpg"``/``".JPG"``/``".jpeg"``.
    jpeg_quality : int
        JPEG quality 0..100 when writing a JPEG.

    Returns
    -------
    (pathlib.Path, pathlib.Path)
        The image file and the ``.crp`` file (``folder/name.crp``).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if not ext.startswith("."):
        ext = "." + ext
    if ext.lower() not in (".png", ".jpg", ".jpeg"):
        raise ValueError(f"unsupported image extension {ext!r} (use .png or .jpg)")
    img_path = folder / f"{name}{ext}"
    bgr = cv2.cvtColor(fld.image, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if ext.lower() != ".png" else []
    ok, buf = cv2.imencode(ext.lower(), bgr, params)
    if not ok:
        raise OSError(f"cannot encode {img_path}")
    buf.tofile(str(img_path))
    crp_path = write_crp(folder / f"{name}.crp", fld.crp)
    return img_path, crp_path


def sequence(spec: FieldSpec | None, n_frames: int, drift_px_per_frame: float = 1.0,
             heading_rad_per_frame: float = 0.0, gap: tuple[int, int] | None = None,
             seed: int | None = None, speed_px_per_frame: float = 4.0,
             gap_row: int = 0) -> list[SyntheticField]:
    """Frames of a camera driving along the field.

    Frame ``k`` (0-based) is ``render`` of ``spec`` with

    * ``lateral_offset_px = spec.lateral_offset_px + k * drift_px_per_frame`` (the rows
      shift sideways; ground truth :attr:`SyntheticField.lateral_px`),
    * heading ``psi_k = psi_0 + k * heading_rad_per_frame`` with ``psi_0 = atan((vp_x -
      W/2) / focal)``, i.e. ``vp_x = W/2 + focal * tan(psi_k)`` (``vp_y`` fixed; ground
      truth :attr:`SyntheticField.heading_px` / :attr:`SyntheticField.heading_rad`),
    * ``travel_px = spec.travel_px + k * speed_px_per_frame`` (plants flow downwards),
    * ``frame = k`` (fresh sensor noise), the same seed (the same plants on the ground),
    * for ``gap[0] <= k < gap[1]``: row ``gap_row`` without plants (``missing_rows``).

    Parameters
    ----------
    spec : FieldSpec or None
        Frame-0 field; ``None`` = ``FieldSpec()``.
    n_frames : int
        Number of frames (>= 0).
    drift_px_per_frame : float
        Lateral offset change per frame (px at the bottom row).
    heading_rad_per_frame : float
        Heading change per frame (rad); positive moves the vanishing point right.
    gap : (int, int) or None
        Half-open frame range ``[start, stop)`` in which ``gap_row`` has no plants.
    seed : int, optional
        Overrides ``spec.seed``.
    speed_px_per_frame : float
        Forward travel per frame (image rows at the bottom, px).
    gap_row : int
        Row index ``j`` that loses its plants during ``gap`` (0 = central row).

    Returns
    -------
    list of SyntheticField
        ``n_frames`` frames.

    Raises
    ------
    ValueError
        If the heading leaves ``(-pi/2, pi/2)`` or ``n_frames < 0``.
    """
    spec = FieldSpec() if spec is None else spec
    if n_frames < 0:
        raise ValueError(f"n_frames must be >= 0; got {n_frames}")
    if seed is not None:
        spec = spec.replace(seed=int(seed))
    vx0, vy0 = spec.vanishing_point
    f = spec.focal
    psi0 = math.atan2(vx0 - spec.width / 2, f)
    frames: list[SyntheticField] = []
    for k in range(n_frames):
        psi = psi0 + k * heading_rad_per_frame
        if not -math.pi / 2 < psi < math.pi / 2:
            raise ValueError(f"frame {k}: heading {psi} rad leaves (-pi/2, pi/2)")
        vx = vx0 if k == 0 else spec.width / 2 + f * math.tan(psi)
        missing = spec.missing_rows
        if gap is not None and gap[0] <= k < gap[1]:
            missing = tuple(sorted(set(missing) | {int(gap_row)}))
        sk = spec.replace(
            vp=(vx, vy0),
            lateral_offset_px=spec.lateral_offset_px + k * drift_px_per_frame,
            travel_px=spec.travel_px + k * speed_px_per_frame,
            frame=k,
            missing_rows=missing,
        )
        frames.append(render(sk))
    return frames


# ----------------------------------------------------------------------------------------
# Pinhole mode: a camera at a known pose over a field measured in metres
# ----------------------------------------------------------------------------------------

#: Supersampling factor per axis of :func:`render_camera` (anti-aliasing of thin far rows).
_CAM_SUPERSAMPLE = 2
#: Soil value-noise cells (m) and their amplitudes (units of ``GroundField.soil_texture``).
_CAM_SOIL_OCTAVES = ((0.02, 0.8), (0.08, 0.6), (0.4, 0.5))
#: Rows the truth lists: those crossing the image below the ground this many spacings ahead.
_CAM_FAR_SPACINGS = 40.0
#: Random tables of the ground (rows x clumps per row; soil cells per side): the field repeats
#: every 64 rows, every 4096 clumps along a row, and every 256 cells of each soil octave.
_CAM_TABLE_ROWS = 64
_CAM_TABLE_CLUMPS = 4096
_CAM_TABLE_SOIL = 256


@functools.lru_cache(maxsize=4)
def _ground_tables(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The ground's random content, a function of ``seed`` only (never of a pose): per clump
    ``(k mod 64, c mod 4096)`` 3 uniforms (along, across, radius) and 4 normals (colour),
    float64 ``(7, 64, 4096)``; per soil octave a float32 ``(256, 256)`` table of normals."""
    rng = np.random.default_rng((seed, _STREAM_CELL, _ID_OFFSET))
    clumps = np.concatenate([rng.random((3, _CAM_TABLE_ROWS, _CAM_TABLE_CLUMPS)),
                             rng.standard_normal((4, _CAM_TABLE_ROWS, _CAM_TABLE_CLUMPS))])
    soil = rng.standard_normal((len(_CAM_SOIL_OCTAVES), _CAM_TABLE_SOIL, _CAM_TABLE_SOIL), dtype=np.float32)
    clumps.setflags(write=False)
    soil.setflags(write=False)
    return clumps, soil


@dataclass(frozen=True)
class GroundField:
    """A field measured on the ground (metres) for :func:`render_camera`.

    Field frame: ``x_f`` along the rows (forward), ``y_f`` to the left; row ``k`` (``k > 0`` to
    the right) is the line ``y_f = -k·spacing_m``. Plants are discs (leaf clumps) on the rows.

    Parameters
    ----------
    spacing_m : float
        Distance between adjacent rows (m), > 0.
    n_rows : int or None
        Rows ``k = -(n//2) .. n - 1 - n//2`` are planted; ``None`` (default): every row.
    plant_radius_m : float
        Mean radius of a leaf clump (m), > 0.
    plant_spacing_m : float
        Distance between consecutive clumps of a row (m), > 0 (each clump jitters by 35% of it).
    row_end_m : float or None
        ``x_f`` where the rows end (m): bare soil beyond it. ``None``: endless rows.
    soil_color, plant_color : (int, int, int)
        Mean RGB; the plant colour must be green-dominant (``G >= R + 20``, ``G >= B + 20``).
    soil_texture : float
        Standard deviation (intensity levels, >= 0) of the soil brightness texture.
    color_jitter : float
        Standard deviation (intensity levels, >= 0) of the per-clump leaf colour.
    noise : float
        Standard deviation (intensity levels, >= 0) of per-pixel Gaussian sensor noise.
    seed : int
        Seed (>= 0) of the plants, the soil and the noise.
    """

    spacing_m: float = 0.5
    n_rows: int | None = None
    plant_radius_m: float = 0.05
    plant_spacing_m: float = 0.08
    row_end_m: float | None = None
    soil_color: tuple[int, int, int] = (148, 124, 96)
    plant_color: tuple[int, int, int] = (84, 136, 52)
    soil_texture: float = 14.0
    color_jitter: float = 9.0
    noise: float = 3.0
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self, _GROUND_RULES)

    def planted(self, k: np.ndarray) -> np.ndarray:
        """Whether rows ``k`` (int array) are planted."""
        if self.n_rows is None:
            return np.ones(np.shape(k), bool)
        lo = -(self.n_rows // 2)
        return (k >= lo) & (k < lo + self.n_rows)


#: :class:`GroundField`'s rules (:class:`torchrow.core.params.Rule`, as :class:`FieldSpec`'s).
_GROUND_RULES: dict[str, Rule] = {
    "spacing_m": _POSITIVE, "plant_radius_m": _POSITIVE, "plant_spacing_m": _POSITIVE,
    "n_rows": Rule("int?", 1), "row_end_m": Rule("float?"),
    "soil_color": Rule("rgb", 0, 255),
    "plant_color": Rule("rgb", 0, 255, extra=(lambda c: c[1] >= c[0] + 20 and c[1] >= c[2] + 20,
                                              "must be green-dominant (G >= R + 20 and G >= B + 20)")),
    "soil_texture": _AT_LEAST_0, "color_jitter": _AT_LEAST_0, "noise": _AT_LEAST_0,
    "seed": Rule("int", 0, 2**63 - 1),
}


@dataclass(frozen=True)
class CameraPose:
    """Where the camera's nadir is in the field of :class:`GroundField`, and where it looks.

    ``lateral_m``: the nadir's ``y_f`` (m; > 0 = left of row 0, as the steering signal
    ``lateral_m``); ``heading_rad``: angle from the camera's forward direction to the rows'
    (counter-clockwise, > 0 = the rows point to the camera's left, as the steering signal);
    ``along_m``: the nadir's ``x_f`` (m, the distance driven along the rows).
    """

    lateral_m: float = 0.0
    heading_rad: float = 0.0
    along_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("lateral_m", "heading_rad", "along_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(float(v)):
                raise ValueError(f"CameraPose.{name} must be a finite number; got {v!r}")
        if not abs(float(self.heading_rad)) < math.pi / 2:
            raise ValueError(f"CameraPose.heading_rad must lie in (-pi/2, pi/2); got {self.heading_rad!r}")

    def to_field(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ground-frame points (m, :mod:`torchrow.core.camera`) in field coordinates ``(x_f, y_f)``."""
        ch, sh = math.cos(self.heading_rad), math.sin(self.heading_rad)
        return self.along_m + x_m * ch + y_m * sh, self.lateral_m - x_m * sh + y_m * ch


@dataclass(frozen=True, eq=False)
class CameraFrame:
    """One :func:`render_camera` image and its exact ground truth.

    Attributes
    ----------
    image : numpy.ndarray, shape (H, W, 3), uint8
        RGB image of ``camera.image_width x camera.image_height``.
    lateral_m, heading_rad, spacing_m : float
        The steering signals' true values (:mod:`torchrow.core.camera`): the nadir's signed
        distance from the nearest planted row (m, > 0 = camera left of it), the rows' heading
        (rad, > 0 = rows point left), the row spacing (m).
    row_end_m : float or None
        Distance (m) along the rows from the nadir to the rows' end; ``None``: endless rows.
    rows : list of (float, float)
        ``(a, b)`` with ``x = a*y + b`` (px) for every planted row seen below the horizon, left
        to right (the rows end at ``row_end_m``; the lines are the rows' infinite extension).
    row_ids : list of int
        Row index ``k`` of each entry of :attr:`rows`, relative to the central row (0, the
        row ``lateral_m`` refers to; negative to its left). Listed: every planted row that
        crosses the image below the image row of the ground 40 row spacings ahead (towards the
        horizon all rows enter the image).
    camera : CameraModel
    pose : CameraPose
    """

    image: np.ndarray
    lateral_m: float
    heading_rad: float
    spacing_m: float
    row_end_m: float | None
    rows: list[tuple[float, float]]
    row_ids: list[int]
    camera: CameraModel
    pose: CameraPose


def camera_path(keys: Sequence[CameraPose], frames_per_leg: int) -> list[CameraPose]:
    """Poses along a drive: ``frames_per_leg`` poses from each key pose towards the next
    (linear in ``lateral_m``, ``heading_rad`` and ``along_m``), then the last key.

    E.g. along a row, turning, changing rows (``lateral_m`` moving by a spacing) and reaching
    the rows' end (``along_m`` passing ``GroundField.row_end_m``).
    """
    if len(keys) < 1 or frames_per_leg < 1:
        raise ValueError(f"camera_path needs >= 1 key pose and frames_per_leg >= 1, got {len(keys)} and {frames_per_leg}")
    out = []
    for p, q in itertools.pairwise(keys):
        for i in range(frames_per_leg):
            t = i / frames_per_leg
            out.append(CameraPose(p.lateral_m + t * (q.lateral_m - p.lateral_m),
                                  p.heading_rad + t * (q.heading_rad - p.heading_rad),
                                  p.along_m + t * (q.along_m - p.along_m)))
    return out + [keys[-1]]


def render_camera(field: GroundField, camera: CameraModel, pose: CameraPose, frame: int = 0) -> CameraFrame:
    """Render what a pinhole ``camera`` at ``pose`` sees of ``field``, with the exact truth.

    The image is drawn per pixel (supersampled 2 x 2, then averaged): each pixel's ray meets
    the ground (:meth:`CameraModel.image_to_ground`), which is soil (hashed value noise) or a
    leaf clump; rays above the horizon see sky. Then Gaussian sensor noise. Everything on the
    ground is a function of field coordinates and ``field.seed`` only, so frames along a
    path of poses show the same plants; the noise depends on ``(seed, frame)``.

    Parameters
    ----------
    field : GroundField
    camera : CameraModel
        Height, tilt and intrinsics; the image has its ``image_width x image_height``.
    pose : CameraPose
    frame : int
        Index of the sensor-noise stream (>= 0).

    Returns
    -------
    CameraFrame
        Identical bytes for identical arguments.
    """
    ss = _CAM_SUPERSAMPLE
    w, h = camera.image_width, camera.image_height
    # sample centres of the supersampled grid, in pixels of the output image
    su = (np.arange(w * ss, dtype=np.float64) + 0.5) / ss - 0.5
    sv = (np.arange(h * ss, dtype=np.float64) + 0.5) / ss - 0.5
    gx, gy = camera.image_to_ground(su[None, :], sv[:, None])
    ground = np.isfinite(gx)
    xf, yf = pose.to_field(np.where(ground, gx, 0.0), np.where(ground, gy, 0.0))
    clumps, soil = _ground_tables(field.seed)
    # soil: octaves of bilinear value noise, looked up in periodic tables
    n = _CAM_TABLE_SOIL
    tex = np.zeros(xf.shape, np.float32)
    for i, (cell, amp) in enumerate(_CAM_SOIL_OCTAVES):
        mx = np.mod(xf / cell, n).astype(np.float32)
        my = np.mod(yf / cell, n).astype(np.float32)
        tex += np.float32(amp) * cv2.remap(soil[i], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    tex *= np.float32(field.soil_texture)
    img = np.asarray(field.soil_color, np.float32) + tex[:, :, None] * np.array([1.0, 0.92, 0.8], np.float32)
    # plants: the nearest row's clumps of this and the two neighbouring along-row cells
    sp, ps, r0 = field.spacing_m, field.plant_spacing_m, field.plant_radius_m
    k = np.rint(-yf / sp).astype(np.int64)
    dy = yf + k * sp
    near = np.flatnonzero(ground & field.planted(k) & (np.abs(dy) < 1.25 * r0 + 0.125 * r0))
    xn, dn, kn = xf.reshape(-1)[near], dy.reshape(-1)[near], k.reshape(-1)[near]
    kt = np.mod(kn, _CAM_TABLE_ROWS)
    hit = np.zeros(near.size, bool)
    colour = np.zeros((near.size, 3), np.float64)
    base = np.asarray(field.plant_color, np.float64)
    for dc in (-1, 0, 1):
        c = np.floor(xn / ps).astype(np.int64) + dc
        t = clumps[:, kt, np.mod(c, _CAM_TABLE_CLUMPS)]
        cx = (c + 0.5 + 0.35 * (t[0] - 0.5)) * ps
        cy = 0.25 * r0 * (t[1] - 0.5)
        rad = r0 * (0.75 + 0.5 * t[2])
        inside = ~hit & ((xn - cx) ** 2 + (dn - cy) ** 2 < rad * rad)
        if field.row_end_m is not None:
            inside &= cx <= field.row_end_m
        colour[inside] = _green(base, t[3:, inside].T, field.color_jitter)
        hit |= inside
    flat = img.reshape(-1, 3)
    flat[near[hit]] = colour[hit]
    if not ground.all():
        rows_sky = int(np.count_nonzero(~ground.all(axis=1)))  # no roll: the sky is the top rows
        sky = _sky(FieldSpec(), rows_sky, w * ss)
        img[:rows_sky] = np.where(ground[:rows_sky, :, None], img[:rows_sky], sky)
    img = np.asarray(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA), np.float32)
    if field.noise > 0:
        rng = np.random.default_rng((field.seed, _STREAM_NOISE, frame))
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(field.noise)
    np.rint(img, out=img)
    np.clip(img, 0, 255, out=img)

    # ground truth: rows as image lines (a ground line maps by the inverse transpose)
    m_inv_t = np.linalg.inv(camera.ground_to_image_matrix()).T
    ch, sh = math.cos(pose.heading_rad), math.sin(pose.heading_rad)
    k_near = int(np.rint(-pose.lateral_m / sp))
    if field.n_rows is not None:
        lo = -(field.n_rows // 2)
        k_near = min(max(k_near, lo), lo + field.n_rows - 1)
    # listed: the rows that cross the image below `top`, the image row of the ground
    # _CAM_FAR_SPACINGS row spacings ahead (towards the horizon every row enters the image)
    _, v_far = camera.ground_to_image(_CAM_FAR_SPACINGS * sp, 0.0)
    top = max(float(v_far), 0.0)
    rows: list[tuple[float, float]] = []
    ids: list[int] = []
    if top < h - 1:
        corners = camera.image_to_ground(np.array([0.0, w - 1.0, 0.0, w - 1.0]), np.array([top, top, h - 1.0, h - 1.0]))
        k_seen = -pose.to_field(*corners)[1] / sp
        for kk in range(int(math.floor(k_seen.min())) - 1, int(math.ceil(k_seen.max())) + 2):
            if not field.planted(np.array(kk)):
                continue
            li = m_inv_t @ np.array([-sh, ch, pose.lateral_m + kk * sp])
            if li[0] == 0:
                continue
            a, b = -li[1] / li[0], -li[2] / li[0]
            x_bot, x_top = a * (h - 1) + b, a * top + b
            if max(x_bot, x_top) >= 0 and min(x_bot, x_top) <= w - 1:
                rows.append((float(a), float(b)))
                ids.append(kk - k_near)
    order = sorted(range(len(rows)), key=lambda i: ids[i])
    return CameraFrame(
        image=img.astype(np.uint8), lateral_m=float(pose.lateral_m + k_near * sp), heading_rad=float(pose.heading_rad),
        spacing_m=float(sp), row_end_m=None if field.row_end_m is None else float(field.row_end_m - pose.along_m),
        rows=[rows[i] for i in order], row_ids=[ids[i] for i in order], camera=camera, pose=pose)
