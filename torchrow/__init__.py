"""torchrow: crop-row detection as batched tensor programs, with a per-image reference."""

from .params import Params
from .results import HoughLine, ImageResult, Row

__version__ = "0.1.0"

__all__ = ["Params", "ImageResult", "Row", "HoughLine", "CropRowDetector", "BatchResult", "__version__"]


def __getattr__(name: str):
    # torch is imported only when the tensor path is asked for
    if name in ("CropRowDetector", "BatchResult"):
        from . import detector

        return getattr(detector, name)
    raise AttributeError(f"module 'torchrow' has no attribute {name!r}")
