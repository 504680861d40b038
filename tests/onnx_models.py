"""Exported test models, cached on disk: an export takes minutes on a small CPU.

The cache (``TORCHROW_CACHE`` or ``~/.cache/torchrow``, folder ``onnx-tests``) is keyed by
the source of the code that defines the graph, the parameters, the shape and the torch
version, so a change to any of them exports afresh. A file name is
``<kind>-<source hash>-<arguments hash>.onnx``; models of any other source hash can never be
read again, and are deleted when a new model is written (the folder holds the current
models only, not every model ever exported).
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import torch

from torchrow import Params
from torchrow.core.tables import write_atomic
from torchrow.onnx.export import to_onnx

#: Op types the graph may contain: all supported by TensorRT's ONNX parser (CumSum, TopK with
#: k <= 3840, GatherElements, ScatterND without reduction, BitShift/Bitwise ops on ints, MatMul
#: in float32: the exact counts of :func:`torchrow.functional._exact.count`).
ALLOWED_OPS = {
    "Abs", "Add", "And", "ArgMax", "BitShift", "BitwiseAnd", "BitwiseOr", "BitwiseXor", "Cast", "Clip", "Concat",
    "Constant", "CumSum", "Div", "Equal", "Expand", "Floor", "Gather", "GatherElements", "GatherND", "Greater",
    "GreaterOrEqual", "Identity", "Less", "LessOrEqual", "MatMul", "Max", "Min", "Mod", "Mul", "Neg", "Not", "Or", "Pad",
    "Pow", "Range", "ReduceMax", "ReduceMin", "ReduceSum", "Reshape", "ScatterElements", "ScatterND", "Shape",
    "Slice", "Sqrt", "Squeeze", "Sub", "TopK", "Transpose", "Unsqueeze", "Where", "Xor",
}


def _cache_dir() -> Path:
    env = os.environ.get("TORCHROW_CACHE")
    return (Path(env) if env else Path.home() / ".cache" / "torchrow") / "onnx-tests"


def _source_key() -> str:
    root = Path(__file__).resolve().parents[1] / "torchrow"
    h = hashlib.sha256()
    for p in sorted([root / "core" / "params.py", root / "core" / "tables.py", *(root / "functional").glob("*.py"),
                     root / "onnx" / "graphs.py", root / "onnx" / "export.py", root / "onnx" / "passes.py",
                     root / "onnx" / "shims.py"]):
        h.update(p.read_bytes())
    h.update(torch.__version__.encode())
    return h.hexdigest()[:16]


def _prune(cache: Path, source: str) -> None:
    """Delete cached models of other sources (stale: their key can never match again)."""
    for old in cache.glob("*.onnx"):
        if f"-{source}-" not in old.name:
            old.unlink(missing_ok=True)


def exported(params: Params, batch: int, tmp: Path, height: int = 240, width: int = 320,
             tracker: bool = False, control_flow: bool = True, scatter_free: bool = False) -> Path:
    """The model exported with these arguments, from the cache when it is there."""
    cache = _cache_dir()
    kind = ("tracker" if tracker else "detector") + ("" if control_flow else "-masked") + (
        "-scatter-free" if scatter_free else "")
    source = _source_key()
    args = hashlib.sha256(repr((params, batch, height, width, kind)).encode()).hexdigest()[:12]
    path = cache / f"{kind}-{source}-{args}.onnx"
    if path.is_file():
        return path
    out = to_onnx(tmp / f"{kind}.onnx", height=height, width=width, batch=batch, params=params, tracker=tracker,
                  control_flow=control_flow, scatter_free=scatter_free)
    try:
        cache.mkdir(parents=True, exist_ok=True)
        _prune(cache, source)
        # test workers (pytest-xdist) share the cache: a model appears whole or not at all
        with out.open("rb") as src:
            write_atomic(path, lambda fh: shutil.copyfileobj(src, fh))
        return path
    except OSError:
        return out
