"""ONNX: the exportable graphs of the detector and the tracker step, their export (passes,
version-checked exporter shims, metadata), the onnxruntime runners and the checks that
compare them with the eager engines.
"""
