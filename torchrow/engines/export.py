"""ONNX export of the image-mode detector and of the tracker step, and onnxruntime runners.

The tracker step (``to_onnx(..., tracker=True)``, :class:`OnnxTracker`) is one graph from a
frame and the previous state to rows and the new state; see
:class:`torchrow.onnx.graphs.StaticTrackerStep` for what runs where. The rest of this
docstring describes the image-mode detector.

:func:`to_onnx` exports :class:`torchrow.onnx.graphs.StaticDetector` (a static-shape,
scatter-free formulation of ALGORITHM.md sections 1 and 3-7) with torch's dynamo-based
exporter (``torch.onnx.export(..., dynamo=True)``, opset 18 by default) for one working
size and batch size. :class:`OnnxDetector` runs such a model in onnxruntime and returns the
same :class:`~torchrow.engines.detector.BatchResult` / records as :class:`~torchrow.engines.detector.CropRowDetector`.

What runs where:

* host, before the graph: section 2 (vegetation colour: colour clustering has data-dependent
  shapes) with :func:`torchrow.functional.color.vegetation_color`, and the colour's LAB from
  the shared table (graph input ``veg_lab``, float64 ``(B, 3)``);
* graph: sky, LAB box, bushy removal, Canny, Hough votes and the line search with outliers
  and restarts, vanishing point, RANSAC band points, scoring and the weighted moments of
  the best hypothesis' inliers;
* host, after the graph: the principal direction (``atan2``, ``cos``, ``sin``: ONNX has no
  ``Atan2``, onnxruntime's ``Atan`` is float32-only) and the row validity of 7.6 on ``B x
  n_rows`` numbers (:func:`torchrow.onnx.graphs.finish_rows`).

Graph inputs: ``images`` uint8 ``(B, 3, H, W)`` RGB, ``veg_lab`` float64 ``(B, 3)``.
Outputs: :data:`torchrow.onnx.graphs.GRAPH_OUTPUTS`.

onnxruntime's CPU kernels lack some small-integer and bool types the exporter emits as torch
computed them (``Where`` on bool, ``Min`` on int16); :func:`legalize` widens those nodes to
int32 (values never overflow: every such tensor holds small counts, pixel values or 0/1
masks) and leaves the ones onnxruntime runs natively (:data:`ORT_NATIVE`) narrow. The
scatter-free form, meant for other runtimes (TensorRT), has every small-integer node widened.
"""

from __future__ import annotations

import contextlib
import functools
from collections import Counter
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from torchrow.core.batch import BatchResult
from torchrow.core.params import Params
from torchrow.core.results import concat_batches

__all__ = ["to_onnx", "OnnxDetector", "OnnxTracker", "step_differences", "float64_python_constants", "legalize",
           "op_counts", "model_info", "model_meta", "ort_optimized",
           "FORBIDDEN_OPS", "DEFAULT_OPSET"]

DEFAULT_OPSET = 18

#: Ops the scatter-free graph without control flow (the TensorRT form) must not contain:
#: scatters with a reduction (TensorRT has none), control flow, and any op whose output
#: shape depends on data.
FORBIDDEN_OPS = ("NonZero", "Unique", "Loop", "If", "Scan", "ScatterElements_reduction", "ScatterND_reduction")

# Elementwise/compute ops whose small-integer and bool inputs are widened to int32. Pure
# data movement (Reshape, Slice, Gather, Concat, Expand, ScatterND, ...) keeps its type.
_LOGICAL = {"And", "Or", "Not", "Xor"}
_MOVE = {"Reshape", "Slice", "Gather", "GatherElements", "Concat", "Expand", "ScatterND", "ScatterElements",
         "Transpose", "Squeeze", "Unsqueeze", "Identity", "Cast", "Shape", "Size", "Flatten", "Split",
         "Constant", "ConstantOfShape", "Pad"}


def _ort():
    try:
        import onnxruntime as ort
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError("onnxruntime is not installed: pip install 'torchrow[onnx]'") from None
    return ort


def _narrow_types():
    from onnx import TensorProto as T

    return {T.BOOL, T.UINT8, T.INT8, T.INT16, T.UINT16}


def _subgraphs(node):
    """The graphs held by a node's attributes (an ``If``'s branches, a ``Loop``'s body)."""
    from onnx import AttributeProto

    for attr in node.attribute:
        if attr.type == AttributeProto.GRAPH:
            yield attr.g
        elif attr.type == AttributeProto.GRAPHS:
            yield from attr.graphs


def _graph_types(graph, types: dict) -> None:
    for v in list(graph.value_info) + list(graph.input) + list(graph.output):
        types[v.name] = v.type.tensor_type.elem_type
    types.update({i.name: i.data_type for i in graph.initializer})
    for node in graph.node:
        for g in _subgraphs(node):
            _graph_types(g, types)


#: Compute ops onnxruntime's CPU kernels (1.32) run natively on small integer types, by
#: ONNX element type name: :func:`legalize` leaves them narrow for the onnxruntime graph
#: (``tests/test_export.py`` runs every entry in the installed onnxruntime). Integer
#: ``Div``/``Mod`` are left out on purpose (their rounding of negatives is op-specific).
ORT_NATIVE = {
    "UINT8": {"Abs", "Add", "ArgMax", "BitwiseAnd", "BitwiseNot", "BitwiseOr", "BitwiseXor", "Clip", "Equal",
              "Greater", "GreaterOrEqual", "Less", "LessOrEqual", "Max", "Min", "Mul", "ReduceMax", "ReduceMin",
              "Sub", "Where"},
    "INT8": {"Abs", "Add", "ArgMax", "BitwiseAnd", "BitwiseNot", "BitwiseOr", "BitwiseXor", "Clip", "Equal",
             "Greater", "GreaterOrEqual", "Less", "LessOrEqual", "Max", "Min", "Mul", "Neg", "ReduceMax",
             "ReduceMin", "Sub", "Where"},
    "INT16": {"Abs", "Add", "BitwiseAnd", "BitwiseNot", "BitwiseOr", "BitwiseXor", "Clip", "Equal", "Greater",
              "GreaterOrEqual", "Less", "LessOrEqual", "Mul", "Neg", "Sub"},
}


def legalize(model, native: dict | None = None):
    """Widen small-integer/bool inputs of compute nodes to int32 (in place; returns the model).

    For each node that is neither data movement, a logical op nor control flow, every input
    of type bool/uint8/int8/int16/uint16 (except ``Where``'s condition) is cast to int32, and
    each such output is computed in int32 and cast back to its type; with ``native`` (e.g.
    :data:`ORT_NATIVE`), nodes the runtime runs on their narrow types stay as they are. The
    default (``None``: every such node widened) is for runtimes without small-integer
    arithmetic (TensorRT); results are the same, since every such tensor here holds small
    counts, pixel values or 0/1 masks that no step overflows. ``If`` and ``Loop`` bodies are
    walked too. Node names are made unique.

    Two rewrites keep the casts few (the median network and the morphology of the sky and
    vegetation stages are long chains of ``Min``/``Max``/``Where`` on uint8): a bitwise op
    whose inputs are all bool becomes its logical op (same truth table, no cast), and the
    int32 result of a range-preserving op (:data:`_IN_RANGE`: its output lies between its
    inputs' values, so the cast back to the narrow type is exact) feeds the next widened
    node directly instead of through a narrow copy; narrow copies no node reads are dropped.
    """
    import onnx

    types: dict = {}
    _graph_types(onnx.shape_inference.infer_shapes(model).graph, types)
    from onnx import TensorProto

    keep = {(op, getattr(TensorProto, t)) for t, ops in (native or {}).items() for op in ops}
    _legalize_graph(model.graph, types, "n", keep)
    used = _used_values(model.graph)
    _drop_dead_casts(model.graph, used)
    return model


# Ops whose every output value is one of (or between) their inputs' values.
_IN_RANGE = {"Min", "Max", "Where", "ReduceMin", "ReduceMax", "Clip"}
_BITWISE_LOGICAL = {"BitwiseAnd": "And", "BitwiseOr": "Or", "BitwiseXor": "Xor", "BitwiseNot": "Not"}


def _legalize_graph(graph, types: dict, prefix: str, keep: set) -> None:
    from onnx import TensorProto, helper

    narrow = _narrow_types()
    out_nodes = []
    wide_of: dict = {}  # narrow value -> the exact int32 value it was cast from
    for i, node in enumerate(graph.node):
        node.name = f"{prefix}{i}_{node.op_type}"
        for j, g in enumerate(_subgraphs(node)):
            _legalize_graph(g, types, f"{prefix}{i}g{j}_", keep)
        if node.op_type in _BITWISE_LOGICAL and all(types.get(x) == TensorProto.BOOL for x in node.input):
            node.op_type = _BITWISE_LOGICAL[node.op_type]
        if node.op_type in _MOVE or node.op_type in _LOGICAL or node.op_type in ("If", "Loop"):
            out_nodes.append(node)
            continue
        small = [x for k, x in enumerate(node.input)
                 if x and types.get(x) in narrow and not (node.op_type == "Where" and k == 0)]
        if small and all((node.op_type, types[x]) in keep for x in small):
            out_nodes.append(node)  # the runtime's own kernel for this type
            continue
        pre, post = [], []
        widened = False
        for k, name in enumerate(node.input):
            if not name or types.get(name) not in narrow or (node.op_type == "Where" and k == 0):
                continue
            if node.op_type in ("Equal",) and types.get(name) == TensorProto.BOOL:
                continue
            widened = True
            if name in wide_of:
                node.input[k] = wide_of[name]
                continue
            wide = f"{name}__i32_{prefix}{i}_{k}"
            pre.append(helper.make_node("Cast", [name], [wide], to=TensorProto.INT32, name=f"{wide}_cast"))
            node.input[k] = wide
        if widened:
            for k, name in enumerate(node.output):
                if types.get(name) in narrow:
                    wide = f"{name}__i32"
                    post.append(helper.make_node("Cast", [wide], [name], to=types[name], name=f"{wide}_cast"))
                    node.output[k] = wide
                    if node.op_type in _IN_RANGE:
                        wide_of[name] = wide
        out_nodes += pre + [node] + post
    del graph.node[:]
    graph.node.extend(out_nodes)


def _used_values(graph) -> set:
    """Names read by any node of ``graph`` or its bodies, and the graphs' outputs."""
    used = {o.name for o in graph.output}
    for node in graph.node:
        used.update(node.input)
        for g in _subgraphs(node):
            used |= _used_values(g)
    return used


def _drop_dead_casts(graph, used: set) -> None:
    """Remove the narrow copies :func:`legalize` made that no node reads."""
    keep = []
    for node in graph.node:
        for g in _subgraphs(node):
            _drop_dead_casts(g, used)
        if node.op_type == "Cast" and node.name.endswith("__i32_cast") and node.output[0] not in used:
            continue
        keep.append(node)
    del graph.node[:]
    graph.node.extend(keep)


def op_counts(model) -> Counter:
    """``Counter`` of op types in the graph and its ``If``/``Loop`` bodies; scatters with a reduction
    counted as ``<Op>_reduction``."""
    c: Counter = Counter()

    def nodes(graph):
        for node in graph.node:
            yield node
            for g in _subgraphs(node):
                yield from nodes(g)

    for node in nodes(model.graph):
        name = node.op_type
        if name in ("ScatterElements", "ScatterND"):
            red = [a for a in node.attribute if a.name == "reduction"]
            if red and red[0].s.decode() not in ("", "none"):
                name += "_reduction"
        c[name] += 1
    return c


def _check_shape(height: int, width: int, batch: int, opset: int) -> None:
    for name, v, lo in (("height", height, 1), ("width", width, 1), ("batch", batch, 1), ("opset", opset, 18)):
        if not isinstance(v, int) or isinstance(v, bool) or v < lo:
            raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")


def to_onnx(path: str | Path, height: int = 240, width: int = 320, batch: int = 1, params: Params | None = None,
            opset: int = DEFAULT_OPSET, optimize: bool = True, tracker: bool = False,
            control_flow: bool = True, scatter_free: bool = False, progress=None) -> Path:
    """Export the image-mode detector (or, with ``tracker=True``, the tracker step) as a
    static-shape ONNX graph.

    Parameters
    ----------
    path : str or Path
        Output ``.onnx`` file (its folder must exist).
    height, width : int
        Working size of the images the graph takes (CRBD: 240 x 320).
    batch : int
        Static batch size ``B``.
    params : Params, optional
        Detector constants, baked into the graph (stored in the model's metadata).
    opset : int
        ONNX opset, 18 or newer (default 18).

    tracker : bool
        Export :class:`torchrow.onnx.graphs.StaticTrackerStep` (one frame of ``B``
        sequences + their state -> rows + new state; run it with :class:`OnnxTracker`).
        ``width`` must then equal ``params.video_width`` (set it with ``params``).
    control_flow : bool
        Skip work no image needs (default): the line search is one ONNX ``Loop`` that stops
        once every image is finished (its body traced and stored once: the export takes
        about a minute, not twenty), and ``If`` nodes skip vote chunks past every image's
        pixel count and, for the tracker, the Hough stage and the tracked fit. ``False``
        gives a graph without ``Loop`` or ``If`` that always runs every step to the static
        bound and masks the results (slower; same results).
    scatter_free : bool
        Vote without ``ScatterElements(reduction="add")`` (prefix sums of constant
        permutations, re-voted at every line-search step) for runtimes without a scatter
        reduction (TensorRT). Slower on a CPU; same results.
    progress : callable, optional
        Called with a short phase name (``"trace"``, ``"onnx"``, ``"optimize"``, ``"save"``)
        as each phase of the export starts.

    Returns
    -------
    Path
        ``path``. The detector has inputs ``images`` uint8 ``(B, 3, H, W)`` and ``veg_lab``
        float64 ``(B, 3)`` and the outputs :data:`torchrow.onnx.graphs.GRAPH_OUTPUTS`;
        the tracker step has the inputs :data:`~torchrow.onnx.graphs.TRACKER_INPUTS`
        and outputs :data:`~torchrow.onnx.graphs.TRACKER_OUTPUTS`.
    """
    import json
    import warnings

    import onnx

    from torchrow.onnx import graphs as static

    _check_shape(height, width, batch, opset)
    params = params or Params()
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {path.parent}")
    images = torch.zeros((batch, 3, height, width), dtype=torch.uint8)
    veg_lab = torch.zeros((batch, 3), dtype=torch.float64)
    if tracker:
        if width != params.video_width:
            raise ValueError(f"the tracker step works at params.video_width = {params.video_width} px, "
                             f"got width {width}")
        from torchrow.functional.tracker import TrackerState

        module = static.StaticTrackerStep(height, width, params, control_flow=control_flow,
                                          scatter_free=scatter_free).eval()
        empty = TrackerState.empty(batch, params)
        k_table = torch.zeros((batch, 1 << 24), dtype=torch.uint8)
        args = (images, k_table, torch.ones(batch, dtype=torch.bool)) + tuple(
            getattr(empty, f) for f in static.TRACKER_STATE)
        names, outputs = list(static.TRACKER_INPUTS), list(static.TRACKER_OUTPUTS)
    else:
        module = static.StaticDetector(height, width, params, flow="loop" if control_flow else "always",
                                       scatter_free=scatter_free).eval()
        args = (images, veg_lab)
        names, outputs = ["images", "veg_lab"], list(static.GRAPH_OUTPUTS)
    import sys

    shown = sys.stdout  # the exporter's own prints are silenced below; the caller's progress is not

    def note(phase: str) -> None:
        if progress is not None:
            with contextlib.redirect_stdout(shown):
                progress(phase)

    with warnings.catch_warnings(), torch.no_grad(), _quiet_exporter():
        warnings.simplefilter("ignore")
        note("trace")
        ep = torch.export.export(module, args, strict=False)
        # bool <-> uint8/int8 reinterpretations in the vegetation stage only ever hold 0/1,
        # whose bit patterns equal their cast values: export them as Cast.
        if not control_flow:
            ep = ep.run_decompositions({torch.ops.aten.view.dtype: _view_as_cast})
            table = None
        else:  # re-decomposing a program with torch.cond subgraphs fails validation: translate instead
            table = {torch.ops.aten.view.dtype: _view_dtype_onnx}
        note("onnx")
        with float64_python_constants(), _nested_subgraph_opsets():
            prog = torch.onnx.export(ep, dynamo=True, opset_version=opset, input_names=names,
                                     output_names=outputs, verbose=False, optimize=False,
                                     custom_translation_table=table)
        if optimize:
            # Constant folding and dead-node removal only: the exporter's default optimizer
            # also runs onnxscript's pattern rewriter, which took ~80% of a 9-minute export
            # of this unrolled graph (hundreds of thousands of match attempts) for no gain.
            from onnxscript import optimizer

            note("optimize")
            optimizer.fold_constants_ir(prog.model)
            optimizer.remove_unused_nodes(prog.model)
    note("save")
    # onnxruntime runs small-integer arithmetic natively; the scatter-free form is for other
    # runtimes (TensorRT), which need int32
    model = _compact(_drop_unused_initializers(legalize(prog.model_proto, None if scatter_free else ORT_NATIVE)))
    meta = {"torchrow_format": "1", "kind": "tracker" if tracker else "detector", "height": str(height),
            "width": str(width), "batch": str(batch), "control_flow": str(bool(control_flow)),
            "scatter_free": str(bool(scatter_free)),
            "params": json.dumps(_params_dict(params)), "exporter": f"torch.onnx dynamo, torch {torch.__version__}",
            "opset": str(opset)}
    for k, v in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.save(model, str(path))
    return path


@contextlib.contextmanager
def _quiet_exporter():
    """Silence the exporter's logged notices (``torchvision is not installed. Skipping ...``,
    one line per torchvision op) and its progress prints, which are not warnings."""
    import io
    import logging

    names = ("torch.onnx", "torch.onnx._internal.exporter._registration", "torch.export", "torch._export",
             "onnxscript")
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        for lg, lv in zip(loggers, levels):
            lg.setLevel(lv)


@contextlib.contextmanager
def float64_python_constants():
    """Export Python float constants as float64 while this is active.

    torch's ONNX exporter gives a Python ``float`` operand whose type the ONNX op does not fix
    (``x * 0.412453``, ``frac < 1.2 * info0`` on float64 tensors) a *float32* constant and
    casts it: 0.412453 becomes 0.41245299577713013. In this float64 pipeline that moved the
    graph's LAB by up to 7e-6 and thresholds such as ``bushy_ratio = 0.1`` or
    ``video_grow_below = 1.2``. Inside this context such constants are float64; the op's own
    cast then gives float32 graphs the same float32 value as before.
    """
    from onnxscript import ir
    from torch.onnx._internal.exporter import _building

    orig = _building._determine_input_dtype

    def determine(param, arg, type_binding):
        dtype = orig(param, arg, type_binding)
        if (dtype == ir.DataType.FLOAT and isinstance(arg, float) and param.type_constraint not in type_binding
                and len(param.type_constraint.allowed_types) != 1):
            return ir.DataType.DOUBLE
        return dtype

    _building._determine_input_dtype = determine
    try:
        yield
    finally:
        _building._determine_input_dtype = orig


@contextlib.contextmanager
def _nested_subgraph_opsets():
    """Let the exporter inline a ``torch.cond`` nested in a ``while_loop`` body.

    The exporter records the call of a nested subgraph function at the model's opset
    version, the function itself at version 1 of the same private domain
    (``pkg.torch.__subgraph__``), and its inliner then refuses the mismatch. The domain only
    names the functions being inlined (nothing of it is left in the model), so its version
    is made to agree.
    """
    from onnx_ir.passes.common import inliner

    orig = inliner.InlinePass._instantiate_call

    def instantiate(self, node, call_site_id):
        function = self._functions[node.op_identifier()]
        for key in list(function.opset_imports):
            if key.startswith("pkg.torch.__subgraph__") and key in self._opset_imports:
                function.opset_imports[key] = self._opset_imports[key]
        return orig(self, node, call_site_id)

    inliner.InlinePass._instantiate_call = instantiate
    try:
        yield
    finally:
        inliner.InlinePass._instantiate_call = orig


def _drop_unused_initializers(model):
    """Remove initializers no node reads (``If``/``Loop`` bodies included): constant folding leaves
    some behind in graphs with control flow, and onnxruntime warns about each."""
    used: set = set()

    def walk(graph):
        for node in graph.node:
            used.update(node.input)
            for g in _subgraphs(node):
                walk(g)
        used.update(o.name for o in graph.output)

    walk(model.graph)
    keep = [i for i in model.graph.initializer if i.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(keep)
    return model


def _compact(model):
    """Drop per-node metadata and rename every value except the graph's inputs and outputs
    to ``t<n>``.

    The exporter attaches the tracing Python's stack and module path to every node and names
    values after closure paths (~100 characters inside ``torch.cond`` branches); on the
    unrolled tracker step that was about half the file. One mapping over all graphs keeps the
    ``If``/``Loop`` bodies' references to outer values consistent.
    """
    keep = {v.name for v in model.graph.input} | {v.name for v in model.graph.output} | {""}
    mapping: dict = {}

    def new(name: str) -> str:
        if name in keep:
            return name
        if name not in mapping:
            mapping[name] = f"t{len(mapping)}"
        return mapping[name]

    def walk(graph, top: bool):
        for v in graph.initializer:
            v.name = new(v.name)
        for v in graph.value_info:
            v.name = new(v.name)
        if not top:
            for v in list(graph.input) + list(graph.output):
                v.name = new(v.name)
        for node in graph.node:
            del node.metadata_props[:]
            node.doc_string = ""
            node.input[:] = [new(x) for x in node.input]
            node.output[:] = [new(x) for x in node.output]
            for g in _subgraphs(node):
                walk(g, False)

    walk(model.graph, True)
    return model


def _view_dtype_onnx(x, dtype: int):
    """``aten.view.dtype`` of a 0/1 tensor as an ONNX ``Cast``."""
    from onnxscript import opset18 as op

    return op.Cast(x, to=int(dtype))  # the exporter hands over the ONNX element type


def _view_as_cast(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return x.to(dtype)


def _params_dict(params: Params) -> dict:
    import dataclasses

    return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}


def model_info(path: str | Path) -> dict:
    """Size (bytes), kind (``detector`` or ``tracker``), static shape, params, exporter and op
    counts of an exported model (:func:`model_meta` plus ``ops``, which parses the graph)."""
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
    import json

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
    return {"size": size, "kind": meta.get("kind", "detector"),
            "control_flow": meta.get("control_flow") == "True", "height": int(meta["height"]),
            "width": int(meta["width"]),
            "batch": int(meta["batch"]), "params": Params(**raw), "exporter": meta.get("exporter", ""),
            "opset": int(meta.get("opset", 0))}


class OnnxDetector:
    """Run an exported detector in onnxruntime; results equal :class:`CropRowDetector`'s.

    Parameters
    ----------
    model_path : str or Path
        A model written by :func:`to_onnx`.
    threads : int, optional
        onnxruntime intra-op threads (default: onnxruntime's choice).
    cache : bool
        Open onnxruntime's pre-optimised copy of the model (:func:`ort_optimized`; written
        on the first open): the session opens in about half the time.

    Notes
    -----
    Graph optimisations are limited to onnxruntime's *basic* level (constant folding and
    redundant-node removal); the extended levels may fuse float64 multiply-adds, which would
    change the rounding the spec prescribes.
    """

    def __init__(self, model_path: str | Path, threads: int | None = None, cache: bool = True) -> None:
        _open(self, model_path, "detector", threads, cache)

    def __call__(self, images: torch.Tensor, veg_color: torch.Tensor | None = None) -> BatchResult:
        """Detect rows in ``uint8 (N, 3, H, W)`` images (any ``N``; run in batches of the
        model's ``B``, the last one padded). ``veg_color`` ``uint8 (N, 3)`` or ``(3,)``
        replaces the per-image colour clustering, as for :class:`CropRowDetector`."""
        from torchrow.core.tables import lab_table_torch, pack_rgb
        from torchrow.functional import color as fcolor
        from torchrow.functional._checks import check_images

        check_images(images)
        n, _, h, w = images.shape
        if (h, w) != (self.height, self.width):
            raise ValueError(f"the model {self.path.name} takes {self.width}x{self.height} images, "
                             f"got {w}x{h} (export one with --width {w} --height {h})")
        images = images.cpu().contiguous()
        if veg_color is None:
            color = fcolor.vegetation_color(images, self.params) if n else torch.zeros((0, 3), dtype=torch.uint8)
        else:
            color = fcolor.color_override(veg_color, n, torch.device("cpu"))
        lab = lab_table_torch("cpu")[torch.from_numpy(pack_rgb(color.numpy()))].clone()
        parts = []
        for s0 in range(0, max(n, 1), self.batch):
            x = images[s0:s0 + self.batch]
            c = lab[s0:s0 + self.batch]
            m = x.shape[0]
            if m < self.batch:  # pad the last batch by repeating an image (or zeros)
                fill = self.batch - m
                x = torch.cat([x, torch.zeros((fill, 3, h, w), dtype=torch.uint8)])
                c = torch.cat([c, torch.zeros((fill, 3), dtype=torch.float64)])
            outs = self.session.run(None, {"images": x.numpy(), "veg_lab": c.numpy()})
            parts.append(self._result([torch.from_numpy(o[:m]) for o in outs], color[s0:s0 + m]))
        return concat_batches(parts)

    def _result(self, outs: list[torch.Tensor], color: torch.Tensor) -> BatchResult:
        from torchrow.functional import ransac as fransac
        from torchrow.onnx.graphs import GRAPH_OUTPUTS, finish_rows

        o = dict(zip(GRAPH_OUTPUTS, outs))
        p = self.params
        b = color.shape[0]
        rows = finish_rows(o, self.height, self.width, p)
        i64 = dict(dtype=torch.int64)
        status = fransac.image_status(rows, o["has_vp"], o["has_veg"])
        return BatchResult(
            width=self.width, height=self.height, status=status, sky=o["sky"], veg_color=color,
            k=torch.full((b,), p.veg_tol, **i64), bushy=o["bushy"], n_rows=o["n_rows"],
            hough_theta=o["hough_theta"], hough_rho=o["hough_rho"], hough_weight=o["hough_weight"],
            hough_valid=o["hough_valid"], out_theta=o["out_theta"], out_rho=o["out_rho"],
            out_weight=o["out_weight"], out_valid=o["out_valid"], vp=o["vp"], has_vp=o["has_vp"],
            row_a=rows.a, row_b=rows.b, row_valid=rows.valid, row_reason=rows.reason,
            row_hypothesis=rows.hypothesis, row_present=rows.present, theta_step=p.theta_step)

    def detect(self, images: Sequence[np.ndarray]) -> BatchResult:
        """Detect rows in a list of same-sized working-size RGB arrays ``(H, W, 3)``."""
        x = torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()
        return self(x)


#: Pre-optimised models kept in the cache folder (the oldest beyond this are deleted).
ORT_CACHE_KEEP = 8


def ort_optimized(path: str | Path) -> Path | None:
    """onnxruntime's basic-level optimisation of the model ``path``, cached on disk.

    onnxruntime optimises a graph every time a session opens it (about half of the open
    time: 0.5 of 1.0 s for the default tracker). The optimised graph is written once, under
    ``TORCHROW_CACHE`` (or ``~/.cache/torchrow``) in ``ort/``, keyed by the SHA-256 of the
    model file and the onnxruntime version, and later opens load it with optimisations
    disabled: the same graph onnxruntime would run, so the same results (checked on every
    CRBD image and Caterra frame in ``benchmarks/``). Returns ``None`` (open the original with
    basic optimisations) when the folder cannot be written; ``TORCHROW_ORT_CACHE=0``
    disables the cache.
    """
    import hashlib
    import os

    if os.environ.get("TORCHROW_ORT_CACHE", "1") == "0":
        return None
    ort = _ort()
    from torchrow.core.tables import cache_dir

    digest = hashlib.sha256(Path(path).read_bytes())
    digest.update(ort.__version__.encode())
    folder = cache_dir() / "ort"
    out = folder / f"{digest.hexdigest()[:32]}.onnx"
    if out.is_file():
        os.utime(out)  # recently used: kept by the pruning below
        return out
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f".{out.name}.{os.getpid()}.tmp"
        so = ort.SessionOptions()
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
        so.log_severity_level = 3
        so.optimized_model_filepath = str(tmp)
        ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        os.replace(tmp, out)
        old = sorted(folder.glob("*.onnx"), key=lambda f: f.stat().st_mtime, reverse=True)[ORT_CACHE_KEEP:]
        for f in old:
            f.unlink(missing_ok=True)
    except OSError:
        return None
    return out


def _open(runner, model_path: str | Path, kind: str, threads: int | None, cache: bool = True) -> None:
    """Check ``model_path`` (present, a ``kind`` model), open an onnxruntime session on
    ``runner.session`` (from the :func:`ort_optimized` copy when ``cache``) and set
    ``runner.path``, ``height``, ``width``, ``batch``, ``params``."""
    ort = _ort()
    path = Path(model_path)
    if not path.is_file():
        raise FileNotFoundError(f"ONNX model not found: {path}")
    info = model_meta(path)
    if info["kind"] != kind:
        other = {"detector": "OnnxDetector", "tracker": "OnnxTracker"}[info["kind"]]
        raise ValueError(f"{path.name} is a torchrow {info['kind']} model; run it with {other}")
    so = ort.SessionOptions()
    so.log_severity_level = 3  # errors only: normal use prints nothing
    # no spin-waiting between operations: this graph's many small nodes left onnxruntime's
    # second thread spinning while the host's frame reader or colour clustering wanted the core
    # (tracker step 65-72 -> 58-62 ms per frame with frames read ahead; the detector no slower)
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if threads:
        so.intra_op_num_threads = int(threads)
    ready = ort_optimized(path) if cache else None
    # basic optimisations only: no fusions that could change float64 rounding
    so.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_DISABLE_ALL if ready is not None
                                   else ort.GraphOptimizationLevel.ORT_ENABLE_BASIC)
    runner.session = ort.InferenceSession(str(ready or path), so, providers=["CPUExecutionProvider"])
    runner.path = path
    runner.height, runner.width, runner.batch = info["height"], info["width"], info["batch"]
    runner.params = info["params"]


class OnnxTracker:
    """Run an exported tracker step (``to_onnx(..., tracker=True)``) in onnxruntime.

    Same interface and results as :class:`torchrow.Tracker` for ``B`` sequences in
    lock-step, ``B`` the model's static batch: :meth:`forward` (tensors) and :meth:`step`
    (arrays in, :class:`~torchrow.core.steering.FrameResult` records out). The host computes only
    what a sequence needs once, on its frame 0: the vegetation colour (section 2), its ``k``
    table (:func:`~torchrow.functional.vegetation.min_k_table`, about 30 ms, rebuilt only when
    a slot's colour changes) and the sky (section 1); everything else, frame 0's ``info0``
    included, runs in the graph.

    Parameters
    ----------
    model_path : str or Path
    hfov_deg : float, optional
        Horizontal field of view for the records' ``heading_rad``.
    threads : int, optional
        onnxruntime intra-op threads.
    cache : bool
        Open onnxruntime's pre-optimised copy of the model, as :class:`OnnxDetector`.
    """

    def __init__(self, model_path: str | Path, hfov_deg: float | None = None, threads: int | None = None,
                 cache: bool = True) -> None:
        _open(self, model_path, "tracker", threads, cache)
        if self.session.get_inputs()[1].name != "k_table":
            raise ValueError(f"{self.path.name} is a tracker model of an older torchrow (it takes veg_lab, not "
                             "k_table); export it again with `torchrow export onnx --tracker`")
        self.hfov_deg = hfov_deg
        n_k = self.params.video_k_max - self.params.video_k_min + 1
        self._table = np.full((self.batch, 1 << 24), n_k, dtype=np.uint8)  # the graph's k_table feed
        self._table_color: list = [None] * self.batch  # the colour each slot's table row holds

    def _k_tables(self, color: torch.Tensor) -> np.ndarray:
        """The ``k_table`` feed for the sequences' colours ``uint8 (B, 3)``: each slot's row is
        rebuilt (:func:`~torchrow.functional.vegetation.min_k_table`) only when its colour
        changes, i.e. when a sequence starts on that slot with another colour."""
        from torchrow.functional.vegetation import min_k_table

        for b, c in enumerate(color.tolist()):
            if self._table_color[b] != c:
                self._table[b] = min_k_table(color[b:b + 1], self.params)[0].numpy()
                self._table_color[b] = c
        return self._table

    def forward(self, frames: torch.Tensor, state=None, active: torch.Tensor | None = None):
        """One lock-step frame: ``uint8 (B, 3, H, W)`` frames at working size ->
        ``(TrackStep, TrackerState)``, as :meth:`torchrow.Tracker.forward`."""
        from torchrow.functional import color as fcolor
        from torchrow.functional import sky as fsky
        from torchrow.functional._checks import check_images
        from torchrow.functional.tracker import TrackerState, TrackStep
        from torchrow.onnx.graphs import TRACKER_STATE, TRACKER_STEP

        check_images(frames, "frames")
        b, _, h, w = frames.shape
        if (b, h, w) != (self.batch, self.height, self.width):
            raise ValueError(f"the model {self.path.name} takes {self.batch} frames of {self.width}x{self.height}, "
                             f"got {b} of {w}x{h}")
        x = frames.cpu().contiguous()
        state = state if state is not None else TrackerState.empty(b, self.params)
        act = torch.ones(b, dtype=torch.bool) if active is None else active.to("cpu", torch.bool)
        color = state.veg_color.clone()
        sky = state.sky.clone()
        start = act & ~state.ready
        if bool(start.any()):
            idx = torch.nonzero(start).view(-1)  # host side: which sequences begin now
            first = x.index_select(0, idx)
            color[idx] = fcolor.vegetation_color(first, self.params)
            sky[idx] = fsky.sky_row(first, self.params).to(torch.int64)
        feed = {"images": x.numpy(), "k_table": self._k_tables(color), "active": act.numpy()}
        feed.update({"state_" + f: getattr(state, f).cpu().numpy() for f in TRACKER_STATE})
        feed["state_sky"] = sky.numpy()
        outs = [torch.from_numpy(o) for o in self.session.run(None, feed)]
        step = TrackStep(**dict(zip(TRACKER_STEP, outs)), active=act)
        new = TrackerState(veg_color=color, **{f: o for f, o in zip(TRACKER_STATE, outs[len(TRACKER_STEP):])})
        return step, new

    __call__ = forward

    def step(self, frames, state=None, names=None):
        """Arrays (any size, resized to the working width) or a working-size tensor in;
        ``(list of FrameResult, TrackerState)`` out, as :meth:`torchrow.Tracker.step`."""
        if isinstance(frames, torch.Tensor):
            x = frames
        else:
            from torchrow.core.frames import prepare_frame

            x = torch.from_numpy(np.stack([prepare_frame(f, self.params.video_width, self.params.max_pixels)
                                           for f in frames])).permute(0, 3, 1, 2)
        stepped, new = self.forward(x.contiguous(), state)
        from torchrow.functional.tracker import records

        return records(stepped, new, x.shape[3], x.shape[2], self.params, self.hfov_deg, names), new


    def track_iter(self, sequences, sources=None):
        """Track up to ``B`` (the model's batch) sequences in lock-step, lazily, as
        :meth:`torchrow.Tracker.track_iter`: yields ``(sequence index, FrameResult, working
        RGB or None)``; unreadable frames and frames of another working size than the
        model's get ``error`` records. Slots without a sequence, or whose sequence has ended
        or has no readable frame now, are fed as inactive (they keep their state)."""
        from torchrow.core.frames import load_items
        from torchrow.core.steering import FrameResult
        from torchrow.functional.tracker import records

        n = len(sequences)
        if n > self.batch:
            raise ValueError(f"the model {self.path.name} tracks {self.batch} sequence(s) at once, got {n}")
        srcs = list(sources) if sources is not None else [None] * n
        iters = [load_items(s, self.params.video_width, self.params.max_pixels) for s in sequences]
        alive = [True] * n
        index = [0] * n
        state = None
        h, w = self.height, self.width
        while any(alive):
            got: list = [None] * n
            frames = np.zeros((self.batch, h, w, 3), dtype=np.uint8)
            act = np.zeros(self.batch, dtype=bool)
            for b in range(n):
                if not alive[b]:
                    continue
                fr = next(iters[b], None)
                if fr is None:
                    alive[b] = False
                    continue
                if fr.rgb is not None and fr.rgb.shape[:2] != (h, w):
                    fr.error = (f"frame of working size {fr.rgb.shape[1]}x{fr.rgb.shape[0]}; the model "
                                f"{self.path.name} takes {w}x{h}")
                    fr.rgb = None
                if fr.rgb is not None:
                    frames[b], act[b] = fr.rgb, True
                got[b] = (index[b], fr)
                index[b] += 1
            recs: list = [None] * self.batch
            if act.any():
                x = torch.from_numpy(frames).permute(0, 3, 1, 2).contiguous()
                stepped, state = self.forward(x, state, torch.from_numpy(act))
                names = [g[1].name if g is not None else None for g in got] + [None] * (self.batch - n)
                idxs = [g[0] if g is not None else 0 for g in got] + [0] * (self.batch - n)
                recs = records(stepped, state, w, h, self.params, self.hfov_deg, names,
                               srcs + [None] * (self.batch - n), idxs)
            for b in range(n):
                if got[b] is None:
                    continue
                i, fr = got[b]
                if recs[b] is not None:
                    yield b, recs[b], fr.rgb
                else:
                    yield b, FrameResult.failed_frame(srcs[b], i, fr.name, fr.error or "unreadable frame"), None


def step_differences(ref, got, tol: float = 1e-9) -> list[str]:
    """Field-by-field differences between two tracker steps or states of the same sequences.

    ``ref``/``got``: :class:`~torchrow.functional.tracker.TrackStep` or
    :class:`~torchrow.functional.tracker.TrackerState` (e.g. :class:`torchrow.Tracker` vs
    :class:`OnnxTracker`). Only active sequences are compared (a step's ``active``); Hough
    line and outlier slots only where valid (the others carry no meaning); float64 fields
    within ``tol`` (NaN equals NaN), all others exactly. Returns one line per differing field.
    """
    import dataclasses

    from torchrow.functional.tracker import TrackStep

    out = []
    act = ref.active if isinstance(ref, TrackStep) else torch.ones(len(ref.sky), dtype=torch.bool)
    for f in dataclasses.fields(ref):
        a, b = getattr(ref, f.name)[act], getattr(got, f.name)[act]
        if isinstance(ref, TrackStep) and f.name in ("hough_theta", "hough_rho", "hough_weight", "out_theta",
                                                      "out_rho", "out_weight"):
            valid = (ref.hough_valid if f.name.startswith("hough") else ref.out_valid)[act]
            a, b = torch.where(valid, a, 0), torch.where(valid, b, 0)
        if a.dtype == torch.float64:
            same = a.shape == b.shape and bool(torch.isclose(a, b, rtol=0, atol=tol, equal_nan=True).all())
        else:
            same = torch.equal(a, b)
        if not same:
            out.append(f"{type(ref).__name__}.{f.name}: {a.tolist()} != {b.tolist()}")
    return out


class _Lab(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        from torchrow.functional.cielab import linear_lut

        self.register_buffer("lut", torch.from_numpy(linear_lut().copy()), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        from torchrow.functional.cielab import lab_formula

        return lab_formula(images, self.lut)


def check_lab(k: Sequence[float] | None = None, params: Params | None = None, progress: bool = False) -> dict:
    """Exhaustive check of the graph's LAB against the shared table, all 2**24 colours.

    Exports the graph's LAB (:func:`torchrow.functional.cielab.lab_formula`) alone, runs every
    8-bit colour through onnxruntime (256 slabs of 65536 colours) and compares with
    :func:`torchrow.core.tables.lab_table` bit for bit. For every colour whose value differs in a
    channel, it then checks whether any vegetation box bound ``c - k`` or ``c + k`` (``c`` any
    of the 2**24 table values of that channel, ``k`` in ``k``, default ``params.veg_tol``)
    lies between the two values (inclusive): only then could a box decision of
    ALGORITHM.md 3.2 differ for some vegetation colour.

    Returns
    -------
    dict
        ``colors`` (2**24), ``mismatched_colors``, ``mismatched_values`` per channel,
        ``max_abs_diff``, ``max_ulps`` (in ulps of ``max(|value|, 1)``), ``flippable`` (number
        of (colour, channel, k) with a bound between graph and table value; 0 means every box
        decision is identical for every vegetation colour and every ``k``) and ``k``.
    """
    import tempfile
    import warnings

    from torchrow.core.tables import lab_table

    ort = _ort()
    params = params or Params()
    ks = [float(v) for v in (k if k is not None else [params.veg_tol])]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "lab.onnx"
        x = torch.zeros((1, 3, 256, 256), dtype=torch.uint8)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            with float64_python_constants(), _nested_subgraph_opsets():
                prog = torch.onnx.export(_Lab(), (x,), dynamo=True, opset_version=DEFAULT_OPSET,
                                         input_names=["images"], verbose=False)
        import onnx

        onnx.save(legalize(prog.model_proto), str(path))
        so = ort.SessionOptions()
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
        sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        table = lab_table()
        gb = np.arange(256, dtype=np.uint8)
        g = np.repeat(gb, 256).reshape(256, 256)
        b = np.tile(gb, 256).reshape(256, 256)
        bad_idx, bad_graph = [], []
        for r in range(256):
            img = np.stack([np.full((256, 256), r, np.uint8), g, b])[None]
            out = sess.run(None, {"images": img})[0][0].reshape(3, -1).T  # (65536, 3)
            ref = table[r << 16:(r + 1) << 16]
            diff = np.any(out != ref, axis=1)
            if diff.any():
                bad_idx.append(np.nonzero(diff)[0] + (r << 16))
                bad_graph.append(out[diff])
    idx = np.concatenate(bad_idx) if bad_idx else np.zeros(0, np.int64)
    got = np.concatenate(bad_graph) if bad_graph else np.zeros((0, 3))
    want = np.asarray(table[idx]) if idx.size else np.zeros((0, 3))
    res = {"colors": 1 << 24, "mismatched_colors": int(idx.size), "k": ks,
           "mismatched_values": [int((got[:, c] != want[:, c]).sum()) for c in range(3)],
           "max_abs_diff": float(np.abs(got - want).max()) if idx.size else 0.0,
           "max_ulps": int(np.max(np.abs(got - want) / np.spacing(np.maximum(np.abs(want), 1.0)))) if idx.size else 0,
           "flippable": 0}
    for c in range(3):
        m = got[:, c] != want[:, c]
        if not m.any():
            continue
        lo = np.minimum(got[m, c], want[m, c])
        hi = np.maximum(got[m, c], want[m, c])
        order = np.argsort(lo, kind="stable")  # sorted queries: cache-friendly searches
        lo, hi = lo[order], hi[order]
        col = np.sort(np.asarray(table[:, c]))
        for kk in ks:
            # fl(v - k) and fl(v + k) are non-decreasing in v: both bound lists are sorted as is
            hit = np.zeros(lo.shape, dtype=bool)
            for bounds in (col - kk, col + kk):
                hit |= np.searchsorted(bounds, hi, side="right") > np.searchsorted(bounds, lo, side="left")
            res["flippable"] += int(hit.sum())
    return res
