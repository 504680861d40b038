"""Graph passes applied to an exported model (:func:`torchrow.onnx.export.to_onnx`) and the op
census of a graph.

onnxruntime's CPU kernels lack some small-integer and bool types the exporter emits as torch
computed them (``Where`` on bool, ``Min`` on int16); :func:`legalize` widens those nodes to
int32 (values never overflow: every such tensor holds small counts, pixel values or 0/1
masks) and leaves the ones onnxruntime runs natively (:data:`ORT_NATIVE`) narrow. The
scatter-free form, meant for other runtimes (TensorRT), has every small-integer node widened.
:func:`share_initializers`, :func:`drop_unused_initializers` and :func:`compact_names` shrink the
saved file;
:func:`op_counts` lists the op types (the TensorRT form must hold none of :data:`FORBIDDEN_OPS`).
"""

from __future__ import annotations

import hashlib
from collections import Counter

__all__ = ["FORBIDDEN_OPS", "ORT_NATIVE", "legalize", "op_counts", "share_initializers", "drop_unused_initializers",
           "compact_names"]

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


def _defined(graph) -> set:
    """Names a graph defines itself (inputs, initializers, node outputs)."""
    return ({v.name for v in graph.input} | {i.name for i in graph.initializer}
            | {o for node in graph.node for o in node.output})


def _rename_reads(graph, mapping: dict) -> None:
    """Rename what the nodes of ``graph`` and of its bodies read (ONNX names are single
    assignment across nested graphs, so no body redefines an outer name)."""
    for node in graph.node:
        node.input[:] = [mapping.get(x, x) for x in node.input]
        for g in _subgraphs(node):
            _rename_reads(g, mapping)


def share_initializers(model, min_bytes: int = 1024):
    """Keep one copy of equal initializers (same type, shape and values; ``min_bytes`` or more),
    in the main graph, where every ``If``/``Loop`` body reads it as an outer value (in place;
    returns the model).

    Constant folding gives every use of a constant table its own copy: the lattice tracker's
    step unrolls the comb (ALGORITHM.md 11.2) once per VP-search window and per warp (11.3.2),
    and each unrolled comb carried its own index tables and zero buffers. An initializer that
    is itself one of its graph's outputs stays where it is.
    """
    from onnx import TensorProto

    main = model.graph
    names: set = set()

    def key(t):
        bare = TensorProto()
        bare.CopyFrom(t)
        bare.name = ""
        data = bare.SerializeToString()
        return hashlib.sha256(data).digest() if len(data) >= min_bytes else None

    # One walk hashes every initializer (graph order, then its bodies); a second pass over the
    # stored keys keeps the first copy, so the main graph's own copy wins where there is one.
    graphs: list = []

    def walk(graph, top: bool):
        names.update(_defined(graph))
        outputs = {o.name for o in graph.output}
        graphs.append((graph, top, [None if t.name in outputs else key(t) for t in graph.initializer]))
        for node in graph.node:
            for g in _subgraphs(node):
                walk(g, False)

    walk(main, True)
    copies = Counter(k for _, _, keys in graphs for k in keys if k is not None)
    first: dict = {}
    for graph, top, keys in graphs:
        mapping, kept = {}, []
        for t, k in zip(list(graph.initializer), keys):
            if k is None or copies[k] < 2:
                kept.append(t)
            elif k in first:
                mapping[t.name] = first[k]
            elif top:
                first[k] = t.name
                kept.append(t)
            else:
                fresh, n = f"shared_{len(first)}", len(first)
                while fresh in names:
                    n += 1
                    fresh = f"shared_{n}"
                names.add(fresh)
                moved = main.initializer.add()
                moved.CopyFrom(t)
                moved.name = fresh
                first[k] = mapping[t.name] = fresh
        if mapping:
            del graph.initializer[:]
            graph.initializer.extend(kept)
            _rename_reads(graph, mapping)
    return model


def drop_unused_initializers(model):
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


def compact_names(model):
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
