"""A pinhole camera over a flat field, and steering signals in metres and radians.

Frames (ALGORITHM.md, "Camera model and steering")
--------------------------------------------------
*Ground frame* (REP 103): origin at the **nadir**, the ground point right below the optical
centre; ``X`` forward along the optical axis' direction on the ground, ``Y`` to the left,
``Z`` up; the ground is the plane ``Z = 0`` and the optical centre is ``(0, 0, height_m)``.

*Camera frame* (OpenCV): ``x`` right, ``y`` down, ``z`` along the optical axis, which points
``tilt_deg`` below the horizontal; no roll. In ground coordinates ``z = (cos t, 0, -sin t)``,
``x = (0, -1, 0)``, ``y = (-sin t, 0, -cos t)``. A camera point projects to the pixel
``u = cx + fx·x/z``, ``v = cy + fy·y/z`` (``u`` = column, ``v`` = row, origin at the centre of
the top-left pixel, as everywhere in torchrow).

Steering signals (signs)
------------------------
Seen from above, the camera at the nadir ``N`` looking up the page, rows ``-1, 0, +1``
(row 0, the *central row*, is the one whose ground line passes nearest ``N``)::

        rows:  -1     0     +1          heading_rad = angle from X (the camera's
               \\      \\      \\                     forward) to the rows' forward
                \\      \\      \\                    direction, counter-clockwise
          X ^    \\      \\      \\                   (REP 103): > 0 = the rows point
            |     \\      \\      \\                  to the camera's left, the robot
            |      \\      \\      \\                 must turn left. Drawn: > 0.
       Y <--N       \\      \\      \\
            |<-lat->|                  lateral_m = the nadir's signed distance
                    |<-sp->|                       from row 0, > 0 = the camera is LEFT
                                                   of the row (the row lies to its right;
                                                   REP 103's +Y), as lateral_px > 0.
                                                   Drawn: > 0. spacing_m = the distance
                                                   between adjacent rows, > 0.

``lateral_m`` lies in ``[-spacing_m/2, spacing_m/2]`` where the rows are equally spaced and
jumps by a spacing when the central row switches. A controller steering onto the central row
and along it uses, e.g., ``yaw_rate = k1·heading_rad - k2·lateral_m``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from torchrow.core.results import Row

__all__ = ["row_end_distance", "CameraModel", "MetricSteering", "metric_steering", "ground_line", "CAMERA_KEYS"]

#: Keys of a camera JSON object: required, and the two ways of giving the intrinsics.
CAMERA_KEYS = {"required": ("height_m", "tilt_deg"), "fov": ("hfov_deg",), "pixels": ("fx", "fy", "cx", "cy")}
#: Largest accepted camera height (m): a mast, not a drone survey (the model needs rows near
#: the camera to be seen at all).
MAX_HEIGHT_M = 100.0


def _number(value: object) -> bool:
    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
            and math.isfinite(float(value)))


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera at a known height and tilt over the ground plane (module docstring).

    Parameters
    ----------
    height_m : float
        Height of the optical centre above the ground (m), in ``(0, 100]``.
    tilt_deg : float
        Angle of the optical axis below the horizontal (degrees), in ``[0, 90]``.
    fx, fy : float
        Focal lengths (px of an ``image_width x image_height`` image), > 0.
    cx, cy : float
        Principal point (px, origin at the centre of the top-left pixel), inside the image:
        ``0 <= cx <= image_width - 1``, ``0 <= cy <= image_height - 1``.
    image_width, image_height : int
        Size (px) of the images the intrinsics describe, >= 1.

    Raises
    ------
    ValueError
        On construction, one line naming the field, the expected range and the value.
    """

    height_m: float
    tilt_deg: float
    fx: float
    fy: float
    cx: float
    cy: float
    image_width: int
    image_height: int

    def __post_init__(self) -> None:
        for name in ("image_width", "image_height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"camera model: {name} must be an integer >= 1, got {v!r}")
            object.__setattr__(self, name, int(v))
        rules = (("height_m", 0.0, MAX_HEIGHT_M, False), ("tilt_deg", 0.0, 90.0, True),
                 ("fx", 0.0, math.inf, False), ("fy", 0.0, math.inf, False),
                 ("cx", 0.0, self.image_width - 1.0, True), ("cy", 0.0, self.image_height - 1.0, True))
        for name, lo, hi, closed in rules:
            v = getattr(self, name)
            if not _number(v):
                raise ValueError(f"camera model: {name} must be a finite number, got {v!r}")
            v = float(v)
            if not ((lo <= v if closed else lo < v) and v <= hi):
                span = f"{'[' if closed else '('}{lo:g}, {hi:g}]"
                raise ValueError(f"camera model: {name} must lie in {span}, got {v!r}")
            object.__setattr__(self, name, v)

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_json(cls, source: str | Path | Mapping[str, Any], source_size: tuple[int, int]) -> CameraModel:
        """A camera from its JSON object (a file path or an already parsed mapping).

        Parameters
        ----------
        source : str, Path or mapping
            A JSON file, or its object already parsed: ``{"height_m", "tilt_deg"}`` plus either
            ``"hfov_deg"`` (horizontal field of view, degrees in ``(0, 180)``:
            ``fx = fy = (W0/2) / tan(hfov/2)``, ``cx = (W0-1)/2``, ``cy = (H0-1)/2``) or all
            of ``"fx", "fy", "cx", "cy"`` (px of the source frame).
        source_size : (int, int)
            ``(W0, H0)``: the source frames' size (px), before any resizing.

        Raises
        ------
        ValueError
            One line: an unreadable file, a missing, unknown or conflicting key, or a value out
            of range (naming what was expected and what was given).
        """
        if not isinstance(source, (str, Path)):  # already parsed (checked below)
            obj: object = source
            where = "camera model"
        else:
            where = f"camera model {source}"
            try:
                obj = json.loads(Path(source).read_text(encoding="utf-8"))
            except OSError as exc:
                raise ValueError(f"{where}: cannot be read ({exc.strerror or exc})") from None
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise ValueError(f"{where}: not JSON ({exc})") from None
        if not isinstance(obj, Mapping):
            raise ValueError(f"{where}: expected a JSON object, got {type(obj).__name__}")
        keys = set(obj)
        known = set(CAMERA_KEYS["required"]) | set(CAMERA_KEYS["fov"]) | set(CAMERA_KEYS["pixels"])
        if keys - known:
            raise ValueError(f"{where}: unknown key(s) {sorted(keys - known)}; expected height_m, tilt_deg and "
                             "either hfov_deg or fx, fy, cx, cy")
        missing = [k for k in CAMERA_KEYS["required"] if k not in keys]
        pix = [k for k in CAMERA_KEYS["pixels"] if k in keys]
        if "hfov_deg" in keys and pix:
            raise ValueError(f"{where}: give either hfov_deg or fx, fy, cx, cy, got both (hfov_deg and {', '.join(pix)})")
        if "hfov_deg" not in keys:
            missing += [k for k in CAMERA_KEYS["pixels"] if k not in keys] if pix else ["hfov_deg (or fx, fy, cx, cy)"]
        if missing:
            raise ValueError(f"{where}: missing key(s) {', '.join(missing)}")
        if not (isinstance(source_size, (tuple, list)) and len(source_size) == 2
                and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1 for v in source_size)):
            raise ValueError(f"camera model: source_size must be (width, height) in px, integers >= 1, got {source_size!r}")
        w0, h0 = source_size
        try:
            if "hfov_deg" in keys:
                fov = obj["hfov_deg"]
                if not (_number(fov) and 0 < float(fov) < 180):
                    raise ValueError(f"camera model: hfov_deg must be a finite number in (0, 180), got {fov!r}")
                f = (w0 / 2) / math.tan(math.radians(float(fov)) / 2)
                return cls(obj["height_m"], obj["tilt_deg"], f, f, (w0 - 1) / 2, (h0 - 1) / 2, w0, h0)
            return cls(obj["height_m"], obj["tilt_deg"], obj["fx"], obj["fy"], obj["cx"], obj["cy"], w0, h0)
        except ValueError as exc:
            raise ValueError(str(exc).replace("camera model", where, 1)) from None

    def scaled(self, working_width: int, working_height: int) -> CameraModel:
        """The same camera for its images resized to ``working_width x working_height``.

        Each axis scales by its own factor, as ``cv2.resize`` maps pixel centres:
        ``x' = (x + 0.5)·W'/W - 0.5`` (so the centre stays the centre).
        """
        if (working_width, working_height) == (self.image_width, self.image_height):
            return self
        sx, sy = working_width / self.image_width, working_height / self.image_height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=(self.cx + 0.5) * sx - 0.5,
                       cy=(self.cy + 0.5) * sy - 0.5, image_width=working_width, image_height=working_height)

    # -- geometry ----------------------------------------------------------------------------
    @property
    def horizon_v(self) -> float:
        """Image row ``v`` of the horizon (px); the ground is seen on rows ``v > horizon_v``."""
        return self.cy - self.fy * math.tan(math.radians(self.tilt_deg))

    def ground_to_image_matrix(self) -> np.ndarray:
        """``float64 (3, 3)``: ground ``(X, Y, 1)`` (m) to homogeneous image ``(u, v, 1)·w`` (px)."""
        t = math.radians(self.tilt_deg)
        h, st, ct = self.height_m, math.sin(t), math.cos(t)
        # rows: camera x, y, z of the ground point (X, Y, 0) seen from (0, 0, h)
        g = np.array([[0.0, -1.0, 0.0], [-st, 0.0, h * ct], [ct, 0.0, h * st]])
        k = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        return k @ g

    def ground_to_image(self, x_m: np.ndarray | float, y_m: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``(u, v)`` (float64, px) of ground points ``(X, Y)`` (m); NaN where a point is not
        in front of the camera (camera ``z <= 0``)."""
        x, y = np.broadcast_arrays(np.asarray(x_m, np.float64), np.asarray(y_m, np.float64))
        m = self.ground_to_image_matrix()
        w = m[2, 0] * x + m[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(w > 0, (m[0, 0] * x + m[0, 1] * y + m[0, 2]) / w, np.nan)
            v = np.where(w > 0, (m[1, 0] * x + m[1, 2]) / w, np.nan)
        return u, v

    def image_to_ground(self, u: np.ndarray | float, v: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Ground points ``(X, Y)`` (float64, m) seen at pixels ``(u, v)``; NaN on and above the
        horizon (the ray does not meet the ground ahead)."""
        uu, vv = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(v, np.float64))
        t = math.radians(self.tilt_deg)
        st, ct = math.sin(t), math.cos(t)
        n = (vv - self.cy) / self.fy
        m = (uu - self.cx) / self.fx
        down = st + n * ct  # the ray's downward component (ground direction: cos t - n sin t)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(down > 0, self.height_m * (ct - n * st) / down, np.nan)
            y = np.where(down > 0, -self.height_m * m / down, np.nan)
        return x, y


@dataclass(frozen=True)
class MetricSteering:
    """Steering in metres and radians (module docstring: definitions and signs); ``None``
    where undefined."""

    lateral_m: float | None = None
    heading_rad: float | None = None
    spacing_m: float | None = None


def ground_line(camera: CameraModel, row: Row, y0: float) -> tuple[float, float] | None:
    """A row's ground line near the camera: ``(heading_rad, lateral_m)`` of the tangent of
    ``x = e·y³ + c·y² + a·y + b`` at image row ``y0``.

    The tangent line is mapped to the ground exactly (the transpose of
    :meth:`CameraModel.ground_to_image_matrix` maps image lines to ground lines) and written
    ``-sin(h)·X + cos(h)·Y + l = 0`` with ``|h| < pi/2``: ``h`` is its heading and ``l`` the
    nadir's signed distance from it (> 0: the nadir lies to the line's left). ``None`` where
    ``y0`` is not below the horizon, the coefficients are not finite, or the line is the
    horizon or runs across the camera's forward direction (``cos(h) = 0``).
    """
    if not y0 > camera.horizon_v:
        return None
    slope = (3.0 * row.e * y0 + 2.0 * row.c) * y0 + row.a
    x0 = float(row.x_at(y0))
    if not (math.isfinite(slope) and math.isfinite(x0)):
        return None
    # image line x - slope·y - (x0 - slope·y0) = 0 to the ground
    p, q, r = camera.ground_to_image_matrix().T @ np.array([1.0, -slope, slope * y0 - x0])
    norm = math.hypot(p, q)
    if not norm > 0 or q == 0 or abs(q) <= 1e-12 * norm:
        return None
    if q < 0:
        p, q, r = -p, -q, -r
    return math.atan2(-p, q), float(r / norm)


def metric_steering(rows: Sequence[Row], camera: CameraModel, height: int,
                    central: int | None = None) -> MetricSteering:
    """``lateral_m``, ``heading_rad``, ``spacing_m`` of one frame from its rows.

    Parameters
    ----------
    rows : sequence of Row
        Fitted rows in working-image pixels; only valid rows are used.
    camera : CameraModel
        The camera at the working size (:meth:`CameraModel.scaled`).
    height : int
        Working image height ``H``: each row's ground line is its tangent at the bottom image
        row ``y = H-1``, the ground nearest the camera (exact for straight rows).

    Returns
    -------
    MetricSteering
        The central row is the valid row whose ground line passes nearest the nadir (the first
        in row order on ties); its neighbours are the rows next to it in the order of their
        ground lines' ``l`` (left to right). ``lateral_m`` = the central row's ``l``;
        ``heading_rad`` = the mean heading of the central row and its neighbours;
        ``spacing_m`` = the mean ``|l_n - l_c|`` over the neighbours (``None`` without one).
        All ``None`` without a valid row seen below the horizon.
    central : int, optional
        The central row's index in ``rows`` instead (the lattice tracker's tracked row; its
        neighbours are the slots beside it): all ``None`` where that row is invalid or has no
        ground line.
    """
    if central is not None:
        def line(i: int) -> tuple[float, float] | None:
            return ground_line(camera, rows[i], height - 1.0) if 0 <= i < len(rows) and rows[i].valid else None

        mid = line(central)
        if mid is None:
            return MetricSteering()
        beside = [g for g in (line(central - 1), line(central + 1)) if g is not None]
        heading = sum(g[0] for g in [mid, *beside]) / (1 + len(beside))
        spacing = sum(abs(g[1] - mid[1]) for g in beside) / len(beside) if beside else None
        return MetricSteering(mid[1], heading, spacing)
    lines = [g for g in (ground_line(camera, r, height - 1.0) for r in rows if r.valid) if g is not None]
    if not lines:
        return MetricSteering()
    c = min(range(len(lines)), key=lambda i: abs(lines[i][1]))
    order = sorted(range(len(lines)), key=lambda i: lines[i][1])
    k = order.index(c)
    near = [order[j] for j in (k - 1, k + 1) if 0 <= j < len(order)]
    lat = lines[c][1]
    heading = sum(lines[i][0] for i in [c] + near) / (1 + len(near))
    spacing = sum(abs(lines[i][1] - lat) for i in near) / len(near) if near else None
    return MetricSteering(lat, heading, spacing)


def row_end_distance(camera: CameraModel, row: Row, y_end: float, heading_rad: float) -> float | None:
    """Distance (m) along the rows from the nadir to where ``row`` ends (ALGORITHM.md 11.7).

    The row's image point at row ``y_end``, ``(x(y_end), y_end)`` (working px; ``camera`` at the
    working size), is back-projected to the ground ``(X, Y)`` and projected on the rows' forward
    direction ``(cos h, sin h)``: ``X cos h + Y sin h``. ``None`` where that point is not below
    the horizon or not finite.
    """
    x = float(row.x_at(float(y_end)))
    gx, gy = camera.image_to_ground(x, float(y_end))
    d = float(gx) * math.cos(heading_rad) + float(gy) * math.sin(heading_rad)
    return d if math.isfinite(d) else None
