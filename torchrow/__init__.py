"""torchrow: crop-row detection as batched tensor programs, with a per-image reference."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from torchrow.core.params import Params
from torchrow.core.results import HoughLine, ImageResult, Row

if TYPE_CHECKING:  # what editors and type checkers see; at run time these load on first use
    from torchrow.core.batch import BatchResult
    from torchrow.engines.detector import CropRowDetector
    from torchrow.engines.tracker import Tracker
    from torchrow.onnx.runtime import OnnxDetector

__version__ = "0.1.0"

__all__ = ["Params", "ImageResult", "Row", "HoughLine", "CropRowDetector", "BatchResult", "Tracker", "OnnxDetector",
           "__version__"]

# torch (and onnxruntime) are imported only when the tensor path (or the ONNX runner) is asked for
_LAZY = {"CropRowDetector": "torchrow.engines.detector", "BatchResult": "torchrow.core.batch",
         "Tracker": "torchrow.engines.tracker", "OnnxDetector": "torchrow.onnx.runtime"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'torchrow' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
