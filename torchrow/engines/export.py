"""The ONNX export and onnxruntime runners under the import path the README's examples used:
the code lives in :mod:`torchrow.onnx` (graphs, export, passes, shims, metadata, runtime,
checks)."""

from torchrow.onnx.checks import check_lab, step_differences
from torchrow.onnx.export import DEFAULT_OPSET, MAX_EXPORT_BATCH, to_onnx
from torchrow.onnx.metadata import model_info, model_meta
from torchrow.onnx.passes import FORBIDDEN_OPS, ORT_NATIVE, legalize, op_counts
from torchrow.onnx.runtime import OnnxDetector, OnnxTracker, ort_optimized
from torchrow.onnx.shims import float64_python_constants

__all__ = ["to_onnx", "OnnxDetector", "OnnxTracker", "step_differences", "float64_python_constants", "legalize",
           "op_counts", "model_info", "model_meta", "ort_optimized", "check_lab", "FORBIDDEN_OPS", "ORT_NATIVE",
           "DEFAULT_OPSET", "MAX_EXPORT_BATCH"]
