"""Loading and input conversion (ALGORITHM.md section 0).

Conversion rule for images that are not 8-bit RGB (documented in the README):

* grey ``(H, W)`` or ``(H, W, 1)``: replicated to three channels;
* RGBA ``(H, W, 4)``: the alpha channel is dropped (no compositing);
* 16-bit: ``(v + 128) // 257`` (exact inverse of the usual ``v * 257`` widening);
* anything else (float, other channel counts, empty): :class:`ImageError`.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

__all__ = ["ImageError", "IMAGE_EXTENSIONS", "to_rgb8", "resize_to_width", "load_image", "decode_image",
           "working_size"]

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")


class ImageError(ValueError):
    """An input image that cannot be read or converted to 8-bit RGB."""


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


def working_size(width0: int, height0: int, width: int) -> tuple[int, int]:
    """Working ``(W, H)`` for an image of ``width0 x height0``: ``h = int(H0 * width / W0)``."""
    if width0 == width:
        return width0, height0
    h = int(height0 * width / width0)
    if h < 1:
        raise ImageError(f"image of {width0}x{height0} is too flat to resize to width {width}")
    return width, h


def resize_to_width(rgb: np.ndarray, width: int) -> np.ndarray:
    """Resize to the working width keeping the aspect ratio (``cv2.INTER_AREA``)."""
    h0, w0 = rgb.shape[:2]
    w, h = working_size(w0, h0, width)
    if (w, h) == (w0, h0):
        return rgb
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)


def load_image(path: str | Path, width: int | None = None) -> np.ndarray:
    """Read an image file as ``uint8 (H, W, 3)`` RGB, resized to ``width`` if given.

    Raises
    ------
    ImageError
        If the file is missing, unreadable, truncated or of an unsupported pixel type.
    """
    p = Path(path)
    if not p.is_file():
        raise ImageError(f"no such file: {p}")
    return decode_image(np.fromfile(p, dtype=np.uint8), width, what=str(p))


def decode_image(data: bytes | np.ndarray, width: int | None = None, what: str = "image") -> np.ndarray:
    """Decode an encoded image (JPEG, PNG, ... bytes) as :func:`load_image` decodes a file.

    ``what`` names the input in error messages ("empty file: WHAT", "cannot decode image: WHAT").
    """
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    if buf.size == 0:
        raise ImageError(f"empty file: {what}")
    # ANYDEPTH|ANYCOLOR keeps 16-bit and grey data as they are and, unlike IMREAD_UNCHANGED,
    # applies the EXIF orientation as cv2.imread does; an alpha channel is dropped here.
    img = cv2.imdecode(buf, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if img is None:
        raise ImageError(f"cannot decode image: {what}")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    rgb = to_rgb8(img)
    return resize_to_width(rgb, width) if width is not None else rgb
