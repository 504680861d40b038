"""torchrow: crop-row detection as batched tensor programs, with a per-image reference."""

from .params import Params
from .results import HoughLine, ImageResult, Row

__version__ = "0.1.0"

__all__ = ["Params", "ImageResult", "Row", "HoughLine", "__version__"]
