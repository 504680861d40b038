"""The torchrow metadata of an exported model (kind, working size, batch, params, exporter),
read from the protobuf wire format without the ``onnx`` package, and the model's op counts.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

from torchrow.core.params import Params
from torchrow.onnx.passes import op_counts

__all__ = ["model_info", "model_meta"]

def model_info(path: str | Path) -> dict:
    """Size (bytes), kind (``detector`` or ``tracker``), mode (``params.mode``: an improved-mode
    tracker is the lattice tracker step), static shape, params, exporter and op counts of an
    exported model (:func:`model_meta` plus ``ops``, which parses the graph)."""
    import onnx

    info = model_meta(path)
    info["ops"] = op_counts(onnx.load(str(path)))
    return info


def model_meta(path: str | Path) -> dict:
    """:func:`model_info` without the op counts, read without the ``onnx`` package (whose
    import alone took 1.4 s here): the model's top-level ``metadata_props`` are found in
    the protobuf wire format and the graph is skipped unread. Cached per file version (the
    CLI's checks and the runner ask for the same file)."""
    path = Path(path)
    st = path.stat()
    return dict(_model_meta(str(path.resolve()), st.st_mtime_ns, st.st_size))


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        if i >= len(buf):
            raise ValueError("truncated")
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, i
        shift += 7


def _fields(buf: bytes):
    """``(field number, bytes)`` of the length-delimited fields of one protobuf message (other
    wire types skipped)."""
    i = 0
    while i < len(buf):
        tag, i = _varint(buf, i)
        kind = tag & 7
        if kind == 0:
            _, i = _varint(buf, i)
        elif kind == 1:
            i += 8
        elif kind == 5:
            i += 4
        elif kind == 2:
            n, i = _varint(buf, i)
            if i + n > len(buf):
                raise ValueError("truncated")
            yield tag >> 3, buf[i:i + n]
            i += n
        else:
            raise ValueError(f"wire type {kind}")


_METADATA_PROPS = 14  # onnx.ModelProto.metadata_props: StringStringEntryProto {key = 1, value = 2}


@functools.lru_cache(maxsize=8)
def _model_meta(path_str: str, mtime_ns: int, size: int) -> dict:

    path = Path(path_str)
    meta: dict = {}
    try:
        for field, entry in _fields(path.read_bytes()):
            if field == _METADATA_PROPS:
                kv = {k: v.decode("utf-8") for k, v in _fields(entry)}
                meta[kv.get(1, "")] = kv.get(2, "")
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not an ONNX model ({exc})") from None
    if meta.get("torchrow_format") != "1":
        raise ValueError(f"{path} is not a torchrow ONNX detector (no torchrow metadata)")
    raw = json.loads(meta["params"])
    raw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in raw.items()}
    params = Params(**raw)
    return {"size": size, "kind": meta.get("kind", "detector"), "mode": params.mode,
            "control_flow": meta.get("control_flow") == "True", "height": int(meta["height"]),
            "width": int(meta["width"]),
            "batch": int(meta["batch"]), "params": params, "exporter": meta.get("exporter", ""),
            "opset": int(meta.get("opset", 0))}
