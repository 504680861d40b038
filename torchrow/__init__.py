"""torchrow: crop-row detection as batched tensor programs, with a per-image reference."""

from torchrow.core.params import Params
from torchrow.core.results import HoughLine, ImageResult, Row

__version__ = "0.1.0"

__all__ = ["Params", "ImageResult", "Row", "HoughLine", "CropRowDetector", "BatchResult", "Tracker",
           "__version__"]


def __getattr__(name: str):
    # torch is imported only when the tensor path is asked for
    if name in ("CropRowDetector", "BatchResult"):
        from torchrow.engines import detector

        return getattr(detector, name)
    if name == "Tracker":
        from torchrow.engines import tracker

        return tracker.Tracker
    raise AttributeError(f"module 'torchrow' has no attribute {name!r}")
