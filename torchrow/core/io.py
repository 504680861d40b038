"""Loading and input conversion (ALGORITHM.md section 0).

Conversion rule for images that are not 8-bit RGB (documented in the README):

* grey ``(H, W)`` or ``(H, W, 1)``: replicated to three channels;
* RGBA ``(H, W, 4)``: the alpha channel is dropped (no compositing);
* 16-bit: ``(v + 128) // 257`` (exact inverse of the usual ``v * 257`` widening);
* anything else (float, other channel counts, empty): :class:`ImageError`.
"""

from __future__ import annotations

import functools
import io
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

__all__ = ["ImageError", "IMAGE_EXTENSIONS", "MAX_DECODE_PIXELS", "MAX_FILE_BYTES", "to_rgb8", "resize_to_width",
           "load_image", "decode_image", "check_file_size", "working_size", "check_working_size", "lattice_params",
           "check_lattice_size",
           "check_color", "check_color_used", "header_size", "majority_working_size", "evidence_mask",
           "check_evidence_used", "Evidenced", "load_evidence", "load_with_evidence"]

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")


#: Largest image file (W0 * H0 pixels, read from its header) that :func:`load_image` decodes:
#: decoding allocates ``3 * W0 * H0`` bytes (twice, with the BGR->RGB copy) before any
#: resizing, so this bounds the peak memory of loading (2 x 384 MiB) whatever the file's size.
#: (Below Pillow's own bound, ``2 * PIL.Image.MAX_IMAGE_PIXELS``, above which the header read fails.)
MAX_DECODE_PIXELS = 1 << 27

#: Largest image file (or encoded image in a bag message) that :func:`load_image` reads, in
#: bytes: an uncompressed 8-bit RGB image of :data:`MAX_DECODE_PIXELS` pixels plus 1 MiB of
#: headers and metadata. Checked on the file's size before its bytes are read, so a file padded
#: to gigabytes costs nothing (its bytes, read, would be held twice: the file and its decode).
MAX_FILE_BYTES = 3 * MAX_DECODE_PIXELS + (1 << 20)


class ImageError(ValueError):
    """An input image that cannot be read or converted to 8-bit RGB."""


def check_working_size(width: int, height: int, max_pixels: int | None) -> None:
    """The working-size bound (ALGORITHM.md section 0, torchrow extension), one rule for both paths.

    Raises
    ------
    ImageError
        If ``width * height > max_pixels`` (``Params.max_pixels``; ``None``: no bound).
    """
    if max_pixels is not None and width * height > max_pixels:
        raise ImageError(f"working size {width}x{height} ({width * height} px) exceeds Params.max_pixels = "
                         f"{max_pixels} (ALGORITHM.md section 0: at width {width}, at most "
                         f"{max_pixels // max(width, 1)} rows)")


@functools.lru_cache(maxsize=64)
def _lattice_sums_fit(height: int, width: int, basis: tuple[tuple[int, int], ...], half: int, grid: int) -> bool:
    # largest |entry| of M = sum phi phi^T and r = sum q phi over the (2K+1) x H cells, |q| <= G (W-1)
    rows = 2 * half + 1
    top_m = top_r = 0
    for t in range(height):
        mags = [t**p * half**k for p, k in basis]
        top_m += max(mags) ** 2
        top_r += max(mags)
    return rows * top_m < 2**63 and rows * grid * max(width - 1, 1) * top_r < 2**63


@functools.lru_cache(maxsize=64)
def _roll_sums_fit(height: int, width: int, half: int, grid: int) -> bool:
    # section 11.3.2's int64 sums: sum q^2 per lattice row (|q| <= G (W-1)) and sum q k phi over
    # the straight basis (|phi k| <= K^2 (H-1))
    q = grid * max(width - 1, 1)
    return height * q * q < 2**63 and (2 * half + 1) * height * q * half * half * max(height - 1, 1) < 2**63


def check_lattice_size(width: int, height: int, params: Any) -> None:
    """The improved mode's table bound (ALGORITHM.md 11.2) at the actual working size.

    ``Params`` refuses parameters whose tables exceed ``LATTICE_TABLE_BYTES`` at its largest
    working image (``image_width`` wide); a batch of another width (the tensor path takes any)
    is checked here, before anything is allocated.

    Raises
    ------
    ImageError
        If :meth:`Params.lattice_table_bytes` exceeds ``LATTICE_TABLE_BYTES`` (2**30).
    """
    from torchrow.core.params import LATTICE_TABLE_BYTES

    comb, vp = params.lattice_table_bytes(int(width), int(height))
    if max(comb, vp) > LATTICE_TABLE_BYTES:
        raise ImageError(f"working size {width}x{height} needs {max(comb, vp)} bytes of improved-mode tables "
                         f"(comb {comb}, VP search {vp}: Params.lattice_table_bytes) > 2**30 (ALGORITHM.md 11.2); "
                         f"use a smaller working size or Params.image_width")


def lattice_params(width: int, height: int, params: Any) -> Any:
    """The improved mode's refit parameters for a ``width x height`` image (ALGORITHM.md 11.3):
    one rule for both paths.

    The refit sums its normal equations in int64. Where they could overflow with a cubic
    central row (more than 578 rows at ``lattice_half`` 1 and ``lattice_cell_grid`` 64) the
    image is fitted with a quadratic one (``lattice_center_degree`` 2, its records' ``e`` = 0),
    so a large working size still gets rows; the parameters are returned unchanged otherwise.

    Raises
    ------
    ImageError
        If even the quadratic sums could overflow (``lattice_half`` and ``lattice_cell_grid``
        near their bounds on a very tall image), or section 11.2's tables would exceed their
        bound (:func:`check_lattice_size`).
    """
    check_lattice_size(width, height, params)
    if params.lattice_roll_grid and not _roll_sums_fit(int(height), int(width), params.lattice_half,
                                                       params.lattice_cell_grid):
        raise ImageError(f"working size {width}x{height} is too large for the projective spacing's exact sums "
                         f"(ALGORITHM.md 11.3.2, lattice_roll_grid {params.lattice_roll_grid}); use a smaller "
                         f"Params.image_width or lattice_cell_grid")
    for degree in range(params.lattice_center_degree, 1, -1):
        p = params if degree == params.lattice_center_degree else params.replace(lattice_center_degree=degree)
        if _lattice_sums_fit(int(height), int(width), p.lattice_basis(), p.lattice_half, p.lattice_cell_grid):
            return p
    raise ImageError(f"working size {width}x{height} is too large for the improved mode's exact refit "
                     f"(ALGORITHM.md 11.3: int64 sums over {height} rows with lattice_half "
                     f"{params.lattice_half}); use a smaller Params.image_width")


def to_rgb8(image: np.ndarray) -> np.ndarray:
    """Convert an array to contiguous ``uint8 (H, W, 3)`` RGB by the rule above.

    The input is assumed to be in RGB(A) channel order already.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"expected a numpy array, got {type(image).__name__}")
    a = image
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise ImageError(f"expected an image of shape (H, W), (H, W, 3) or (H, W, 4); got {image.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ImageError(f"empty image of shape {image.shape}")
    if a.dtype == np.uint16:
        a = ((a.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise ImageError(f"expected uint8 or uint16 pixels, got {a.dtype}")
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    elif a.shape[2] == 4:
        a = a[:, :, :3]
    return np.ascontiguousarray(a)


def working_size(width0: int, height0: int, width: int, max_pixels: int | None = None) -> tuple[int, int]:
    """Working ``(W, H)`` for an image of ``width0 x height0``: ``h = int(H0 * width / W0)``.

    Raises :class:`ImageError` if ``h < 1`` or ``W * H > max_pixels`` (:func:`check_working_size`).
    """
    if width0 == width:
        w, h = width0, height0
    else:
        w, h = width, int(height0 * width / width0)
        if h < 1:
            raise ImageError(f"image of {width0}x{height0} is too flat to resize to width {width}")
    check_working_size(w, h, max_pixels)
    return w, h


def resize_to_width(rgb: np.ndarray, width: int, max_pixels: int | None = None) -> np.ndarray:
    """Resize to the working width keeping the aspect ratio (``cv2.INTER_AREA``).

    ``max_pixels`` (``Params.max_pixels``) bounds the working size: larger raises
    :class:`ImageError` before anything is allocated.
    """
    h0, w0 = rgb.shape[:2]
    w, h = working_size(w0, h0, width, max_pixels)
    if (w, h) == (w0, h0):
        return rgb
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)


def header_size(path: str | Path | bytes, what: str | None = None) -> tuple[int, int] | None:
    """``(W0, H0)`` of an image file as :func:`load_image` decodes it (EXIF orientations 5-8
    swap the axes), read from its header with Pillow without decoding the pixels; ``None``
    if Pillow cannot read the header (OpenCV then decides).

    Raises :class:`ImageError` for headers beyond Pillow's decompression-bomb bound
    (``2 * PIL.Image.MAX_IMAGE_PIXELS``), which is above :data:`MAX_DECODE_PIXELS`."""
    import warnings

    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # only the size is read
            with Image.open(io.BytesIO(path) if isinstance(path, bytes) else path) as im:
                w, h = im.size
                # Pillow finds a PNG's EXIF only by decoding it: PNG orientation is not read
                if im.format != "PNG" and im.getexif().get(0x0112, 1) in (5, 6, 7, 8):
                    w, h = h, w
                return w, h
    except Image.DecompressionBombError as exc:  # above 2 * Image.MAX_IMAGE_PIXELS: far too large
        raise ImageError(f"image too large to decode ({exc}): {what or path!s}") from None
    except Exception:  # not a format Pillow knows, or a damaged header
        return None


def load_image(path: str | Path, width: int | None = None, max_pixels: int | None = None) -> np.ndarray:
    """Read an image file as ``uint8 (H, W, 3)`` RGB, resized to ``width`` if given.

    ``max_pixels`` bounds the working size (:func:`check_working_size`, checked on the
    header's size before decoding where Pillow reads the header, and before the resize
    allocates it in any case); files of more than :data:`MAX_DECODE_PIXELS` pixels (by their
    header) or :data:`MAX_FILE_BYTES` bytes (by their size, before reading) are refused.

    Raises
    ------
    ImageError
        If the file is missing, unreadable, truncated, of an unsupported pixel type, or
        outside the bounds above.
    """
    p = Path(path)
    return decode_image(_file_bytes(p), width, max_pixels, what=str(p))


def _file_bytes(p: Path) -> bytes:
    """The bytes of file ``p`` under :func:`check_file_size`'s bound (checked before reading);
    :class:`ImageError` if it is missing. Bytes, not ``np.fromfile``: the decode and Pillow's
    header read then share one buffer."""
    if not p.is_file():
        raise ImageError(f"no such file: {p}")
    check_file_size(p.stat().st_size, str(p))
    return p.read_bytes()


def check_file_size(size: int, what: str) -> None:
    """The file-size bound of image reads: :class:`ImageError` if ``size`` (bytes) exceeds
    :data:`MAX_FILE_BYTES`; ``what`` names the input."""
    if size > MAX_FILE_BYTES:
        raise ImageError(f"file of {size} bytes is larger than torchrow reads as an image "
                         f"({MAX_FILE_BYTES} bytes): {what}")


def decode_image(data: bytes | np.ndarray, width: int | None = None, max_pixels: int | None = None,
                 what: str = "image") -> np.ndarray:
    """Decode an encoded image (JPEG, PNG, ... bytes) exactly as :func:`load_image` decodes a
    file with these bytes (same bounds, same errors). ``what`` names the input in messages."""
    img = _decoded(data, what, width, max_pixels)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    rgb = to_rgb8(img)
    return resize_to_width(rgb, width, max_pixels) if width is not None else rgb


def _decoded(data: bytes | np.ndarray, what: str, width: int | None = None,
             max_pixels: int | None = None) -> np.ndarray:
    """OpenCV's decode of ``data`` under :func:`decode_image`'s bounds: grey ``(H, W)`` or BGR
    ``(H, W, 3)``, 8 or 16 bits, as the file holds them. ``width``: the working-size bound too."""
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    if buf.size == 0:
        raise ImageError(f"empty file: {what}")
    check_file_size(buf.size, what)
    size = header_size(data if isinstance(data, bytes) else buf.tobytes(), what)
    if size is not None:
        if size[0] * size[1] > MAX_DECODE_PIXELS:
            raise ImageError(f"image of {size[0]}x{size[1]} pixels is larger than torchrow decodes "
                             f"({MAX_DECODE_PIXELS} px): {what}")
        if width is not None:  # the working-size bound before the decode allocates anything
            working_size(size[0], size[1], width, max_pixels)
    # ANYDEPTH|ANYCOLOR keeps 16-bit and grey data as they are and, unlike IMREAD_UNCHANGED,
    # applies the EXIF orientation as cv2.imread does; an alpha channel is dropped here.
    img = cv2.imdecode(buf, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if img is None:
        raise ImageError(f"cannot decode image: {what}")
    return img


def check_color(color: object, name: str = "veg_color", batched: bool = False) -> np.ndarray:
    """A given RGB colour, validated the same way by both paths: ``int64 (3,)`` (or ``(B, 3)``
    when ``batched``) with every entry an integer in ``[0, 255]``.

    Accepts a sequence, a numpy array or a torch tensor of integers (any integer dtype).

    Raises
    ------
    TypeError
        For non-integer entries (floats are not truncated, bools are not numbers).
    ValueError
        For a wrong shape or an entry outside ``[0, 255]``.
    """
    if hasattr(color, "detach") and hasattr(color, "cpu"):  # a torch tensor, without importing torch
        color = color.detach().cpu().numpy()
    try:  # sequences element by element (numpy would turn True into 1 and mix in floats)
        a = color if isinstance(color, np.ndarray) else np.asarray(color, dtype=object)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name} must be RGB integers in [0, 255], got {color!r} ({exc})") from None
    if a.dtype == np.bool_ or not (np.issubdtype(a.dtype, np.integer) or a.dtype == object):
        raise TypeError(f"{name} must be RGB integers in [0, 255], got dtype {a.dtype}: {color!r}")
    if a.dtype == object:
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) for v in a.flat):
            raise TypeError(f"{name} must be RGB integers in [0, 255], got {color!r}")
        a = a.astype(np.int64)
    shapes = "(3,) or (B, 3)" if batched else "(3,)"
    if not (a.shape == (3,) or (batched and a.ndim == 2 and a.shape[1] == 3)):
        raise ValueError(f"{name} must have shape {shapes}, got {a.shape}")
    a = a.astype(np.int64)
    if a.size and (a.min() < 0 or a.max() > 255):
        raise ValueError(f"{name} must be RGB integers in [0, 255], got {color!r}")
    return a


def check_color_used(color: object, params: Any) -> None:
    """A given vegetation colour must have a use: ``ValueError`` when ``color`` is not ``None``
    but section 2 does not run (the improved mode with ``lattice_vp="search"`` masks excess green,
    ALGORITHM.md 11.1; :meth:`torchrow.core.params.Params.runs_section6`). One rule for both paths."""
    if color is not None and not params.runs_section6():
        raise ValueError(f"veg_color is only used where section 2 runs (mode 'faithful', or 'improved' with "
                         f"lattice_vp 'section6'); got a colour with mode {params.mode!r} and lattice_vp "
                         f"{params.lattice_vp!r}")


def evidence_mask(evidence: np.ndarray, width: int, height: int) -> np.ndarray:
    """A caller's row evidence (ALGORITHM.md 11.1.1) at the working size: ``(height, width)`` bool.

    ``evidence`` is ``(H0, W0)`` or ``(H0, W0, 1)``, bool or any integer or float dtype, non-zero
    (and not NaN) where a crop row is: e.g. a segmentation network's row mask at the input
    image's size. Resized by nearest neighbour in integers, working pixel ``(i, j)`` taking source
    pixel ``((2i + 1) H0 // (2 height), (2j + 1) W0 // (2 width))`` (the source pixel under its
    centre), so both paths and every platform agree. Never modifies ``evidence``.

    Raises
    ------
    TypeError
        If ``evidence`` is not a numpy array.
    ValueError
        If it is not 2-D (or 3-D with one channel) with both sides at least 1.
    """
    if not isinstance(evidence, np.ndarray):
        raise TypeError(f"evidence: expected a numpy array (H, W), got {type(evidence).__name__}")
    ev = evidence[..., 0] if evidence.ndim == 3 and evidence.shape[2] == 1 else evidence
    if ev.ndim != 2 or ev.shape[0] < 1 or ev.shape[1] < 1:
        raise ValueError(f"evidence: expected shape (H, W) or (H, W, 1) with H, W >= 1, got {evidence.shape}")
    if ev.dtype.kind not in "biuf":
        raise ValueError(f"evidence: expected a bool, integer or float array, got dtype {ev.dtype}")
    h0, w0 = ev.shape
    rows = (np.arange(height, dtype=np.int64) * 2 + 1) * h0 // (2 * height)
    cols = (np.arange(width, dtype=np.int64) * 2 + 1) * w0 // (2 * width)
    picked = ev[rows[:, None], cols[None, :]]
    if picked.dtype.kind == "f":
        return (picked != 0) & ~np.isnan(picked)
    return picked != 0


def check_evidence_used(evidence: object, params: Any) -> None:
    """Given row evidence must have a use: ``ValueError`` when ``evidence`` is not ``None`` but
    the mode is not ``"improved"`` (only section 11 reads it, ALGORITHM.md 11.1.1). One rule for
    both paths."""
    if evidence is not None and params.mode != "improved":
        raise ValueError(f"evidence (a row mask) is only used by mode 'improved'; got mode {params.mode!r}")


class Evidenced(NamedTuple):
    """A working image with the caller's row evidence (ALGORITHM.md 11.1.1), as a loader of
    :func:`torchrow.engines.runner.run` may return it: ``image`` uint8 ``(H, W, 3)`` RGB and
    ``evidence`` bool ``(H, W)`` at the same working size (:func:`evidence_mask`)."""

    image: np.ndarray
    evidence: np.ndarray


def load_evidence(path: str | Path) -> np.ndarray:
    """Read a row-evidence mask file (PNG, or any format :func:`load_image` reads) as bool
    ``(H0, W0)`` at its own size: non-zero in any colour channel is a row (an alpha channel is
    dropped, EXIF orientation applied, as :func:`load_image` decodes). Same file bounds as
    :func:`load_image`.

    Raises
    ------
    ImageError
        If the file is missing, empty, too large or cannot be decoded.
    """
    p = Path(path)
    img = _decoded(_file_bytes(p), f"evidence mask {p}")
    return (img != 0).any(axis=2) if img.ndim == 3 else img != 0


def load_with_evidence(path: str | Path, mask_path: str | Path, width: int | None = None,
                       max_pixels: int | None = None) -> Evidenced:
    """:func:`load_image` of ``path`` with the mask of ``mask_path`` (:func:`load_evidence`)
    brought to the working size by :func:`evidence_mask`, as :class:`Evidenced`.

    The mask may have any size of the image's aspect (a network's output at a quarter of the
    image, say); an aspect that differs by more than 2 % (or one working pixel) means the mask
    belongs to another image.

    Raises
    ------
    ImageError
        As :func:`load_image` and :func:`load_evidence`, and if the aspects differ.
    """
    rgb = load_image(path, width, max_pixels)
    mask = load_evidence(mask_path)
    h, w = rgb.shape[:2]
    h0, w0 = mask.shape
    # the working height is rounded to whole pixels: one working pixel of slack besides 2 %
    if abs(h0 * w - w0 * h) > max(0.02 * h0 * w, w0):
        raise ImageError(f"evidence mask {mask_path} is {w0}x{h0}, not the aspect of image {path} "
                         f"({w}x{h} at working size)")
    return Evidenced(rgb, evidence_mask(mask, w, h))


def majority_working_size(frames: Iterable[tuple[Callable[[], tuple[int, int] | None], Callable[[], np.ndarray]]],
                          width: int, max_pixels: int | None = None) -> tuple[int, int] | None:
    """The working ``(H, W)`` most of a sequence's frames have (ties: the earliest; ALGORITHM.md 8).

    ``frames`` yields per frame ``(size, load)``: ``size()`` its source ``(W0, H0)`` from a
    header, or ``None`` when the header cannot tell, and ``load()`` the decoded frame, only
    called then. Frames that fail (:class:`ImageError`, ``OSError``) or exceed ``max_pixels``
    are skipped; ``None`` if no frame is readable.
    """
    counts: dict[tuple[int, int], int] = {}
    for size, load in frames:
        try:
            size0 = size()
            if size0 is None:
                h0, w0 = load().shape[:2]
            else:
                w0, h0 = size0
            w, h = working_size(w0, h0, width, max_pixels)
        except (ImageError, OSError):
            continue
        counts[(h, w)] = counts.get((h, w), 0) + 1
    return max(counts, key=lambda s: counts[s]) if counts else None  # dicts keep order: first of the most common
