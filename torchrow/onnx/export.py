"""ONNX export of the image-mode detector and of the tracker step: :func:`to_onnx`.

:func:`to_onnx` exports :class:`torchrow.onnx.graphs.StaticDetector` (a static-shape,
scatter-free formulation of ALGORITHM.md sections 1 and 3-7),
:class:`torchrow.onnx.graphs.StaticTrackerStep` or, in improved mode,
:class:`torchrow.onnx.graphs.StaticLatticeStep` with torch's dynamo-based exporter
(``torch.onnx.export(..., dynamo=True)``, opset 18 by default) for one working size and batch
size, under the exporter shims of :mod:`torchrow.onnx.shims`, then applies the passes of
:mod:`torchrow.onnx.passes` and stores the torchrow metadata (:mod:`torchrow.onnx.metadata`).
:class:`torchrow.onnx.runtime.OnnxDetector` runs such a model in onnxruntime and returns the
same :class:`~torchrow.core.batch.BatchResult` / records as :class:`~torchrow.CropRowDetector`.

Graph inputs: ``images`` uint8 ``(B, 3, H, W)`` RGB, ``veg_lab`` float64 ``(B, 3)``.
Outputs: :data:`torchrow.onnx.graphs.GRAPH_OUTPUTS`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from torchrow.core.params import Params
from torchrow.onnx.passes import ORT_NATIVE, compact_names, drop_unused_initializers, legalize, share_initializers
from torchrow.onnx.shims import float64_python_constants, nested_subgraph_opsets

__all__ = ["to_onnx", "DEFAULT_OPSET", "MAX_EXPORT_BATCH"]

DEFAULT_OPSET = 18

#: Largest static batch of an export: the example inputs (and the tracker's ``k_table``, 16 MiB
#: per sequence) are allocated before tracing, and a graph's intermediate tensors grow with it.
MAX_EXPORT_BATCH = {"detector": 256, "tracker": 64}


def _check_shape(height: int, width: int, batch: int, opset: int, params: Params, tracker: bool) -> None:
    """One-line ``ValueError`` for a size that is not an integer in range, checked before any
    tracing or allocation: the working image within ``params.max_pixels`` (ALGORITHM.md 0.1)
    and the batch within :data:`MAX_EXPORT_BATCH`."""
    kind = "tracker" if tracker else "detector"
    for name, v, lo, hi in (("height", height, 1, params.max_pixels), ("width", width, 1, 4096),
                            ("batch", batch, 1, MAX_EXPORT_BATCH[kind]), ("opset", opset, 18, None)):
        if not isinstance(v, int) or isinstance(v, bool) or v < lo:
            raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        if hi is not None and v > hi:
            raise ValueError(f"{name} of a {kind} export must be <= {hi}, got {v}")
    if height * width > params.max_pixels:
        raise ValueError(f"a {width}x{height} working image has {height * width} pixels, more than "
                         f"max_pixels = {params.max_pixels} (ALGORITHM.md 0.1)")


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
        sequences + their state -> rows + new state; run it with :class:`OnnxTracker`), or
        with ``params.mode == "improved"`` the lattice tracker step
        :class:`torchrow.onnx.graphs.StaticLatticeStep` (ALGORITHM.md 11.7; also run by
        :class:`OnnxTracker`). ``width`` must then equal ``params.video_width`` (set it with
        ``params``). The detector exports in faithful mode only.
    control_flow : bool
        Skip work no image needs (default): the line search is one ONNX ``Loop`` that stops
        once every image is finished (its body traced and stored once: the export takes
        about a minute, not twenty), and ``If`` nodes skip vote chunks past every image's
        pixel count and, for the tracker, the Hough stage and the tracked fit. ``False``
        gives a graph without ``Loop`` or ``If`` that always runs every step to the static
        bound and masks the results (slower; same results). The lattice tracker step: the
        refits are ``Loop`` nodes, the VP grid search and the redo pass ``If`` nodes.
    scatter_free : bool
        Vote without ``ScatterElements(reduction="add")`` (prefix sums of constant
        permutations, re-voted at every line-search step) for runtimes without a scatter
        reduction (TensorRT). Slower on a CPU; same results. Not for the lattice tracker step
        (its histograms are scatter-adds).
    progress : callable, optional
        Called with a short phase name (``"trace"``, ``"onnx"``, ``"optimize"``, ``"save"``)
        as each phase of the export starts.

    Returns
    -------
    Path
        ``path``. The detector has inputs ``images`` uint8 ``(B, 3, H, W)`` and ``veg_lab``
        float64 ``(B, 3)`` and the outputs :data:`torchrow.onnx.graphs.GRAPH_OUTPUTS`;
        the tracker step has the inputs :data:`~torchrow.onnx.graphs.TRACKER_INPUTS`
        and outputs :data:`~torchrow.onnx.graphs.TRACKER_OUTPUTS`; the lattice tracker step
        :data:`~torchrow.onnx.graphs.LATTICE_INPUTS` and
        :data:`~torchrow.onnx.graphs.LATTICE_OUTPUTS`.
    """
    import json
    import warnings

    import onnx

    from torchrow.onnx import graphs as static

    params = params or Params()
    _check_shape(height, width, batch, opset, params, tracker)
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {path.parent}")
    images = torch.zeros((batch, 3, height, width), dtype=torch.uint8)
    veg_lab = torch.zeros((batch, 3), dtype=torch.float64)
    module: torch.nn.Module
    if tracker:
        if width != params.video_width:
            raise ValueError(f"the tracker step works at params.video_width = {params.video_width} px, "
                             f"got width {width}")
    elif params.mode != "faithful":
        raise ValueError(f"the detector exports in faithful mode only; got Params.mode={params.mode!r} "
                         "(the improved mode exports its tracker step: tracker=True)")
    if tracker and params.mode == "improved":
        from torchrow.functional import lattice as flattice
        from torchrow.functional.lattice_tracking import LatticeTrackerState

        if scatter_free:
            raise ValueError("scatter_free applies to the faithful mode's Hough vote; the improved mode's "
                             "tracker step has no scatter-free form")
        module = static.StaticLatticeStep(height, width, params, control_flow=control_flow).eval()
        start = LatticeTrackerState.empty(batch)
        args = (images, torch.ones(batch, dtype=torch.bool)) + tuple(getattr(start, f) for f in static.LATTICE_STATE)
        with torch.no_grad():  # builds section 11.2's cached tables, which the graph then holds as constants
            module(*args)
            # the VP search's gather form, which only the exported graph uses (eagerly it scatters)
            flattice.vp_gather_table(height, width, params, images.device)
            flattice.vp_window_table(height, width, params, images.device)  # a tracked window's, in int16
            flattice.vp_fold_tables(height, width, params, images.device)  # and its folds' index lists
        names, outputs = list(static.LATTICE_INPUTS), list(static.LATTICE_OUTPUTS)
    elif tracker:
        from torchrow.functional.tracking import TrackerState

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
        _branch_constants(ep.graph_module)
        # bool <-> uint8/int8 reinterpretations in the vegetation stage only ever hold 0/1,
        # whose bit patterns equal their cast values: export them as Cast, translated rather
        # than decomposed (a second decomposition of the program fails validation with
        # torch.cond subgraphs, and costs as much as the exporter's own without them)
        table: dict[Callable[..., Any], Callable[..., Any]] = {torch.ops.aten.view.dtype: _view_dtype_onnx}
        note("onnx")
        with float64_python_constants(), nested_subgraph_opsets():
            prog = torch.onnx.export(ep, dynamo=True, opset_version=opset, input_names=names,
                                     output_names=outputs, verbose=False, optimize=False,
                                     custom_translation_table=table)
        if prog is None:  # only the TorchScript exporter (dynamo=False) returns None
            raise RuntimeError("torch.onnx.export(dynamo=True) returned no ONNXProgram")
        if optimize:
            # Constant folding and dead-node removal only: the exporter's default optimizer
            # also runs onnxscript's pattern rewriter, which took ~80% of a 9-minute export
            # of this unrolled graph (hundreds of thousands of match attempts) for no gain.
            from onnxscript import optimizer

            note("optimize")
            if tracker and params.mode == "improved":
                _distinct_value_names(prog.model)
            optimizer.fold_constants_ir(prog.model)
            optimizer.remove_unused_nodes(prog.model)
    note("save")
    # onnxruntime runs small-integer arithmetic natively; the scatter-free form is for other
    # runtimes (TensorRT), which need int32
    model = compact_names(drop_unused_initializers(share_initializers(
        legalize(prog.model_proto, None if scatter_free else ORT_NATIVE))))
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


#: Largest tensor constant :func:`_branch_constants` rebuilds from its values.
BRANCH_CONSTANT_MAX = 64


def _branch_constants(root: torch.fx.GraphModule) -> None:
    """Rebuild the tensor constants made inside ``torch.cond``/``while_loop`` subgraphs from
    their values (``aten.full`` of each element), in place.

    torch.export stores a constant a branch creates (``torch.tensor(...)``, the ``0`` of
    ``x[..., i] = 0``) on the branch's own module, and the exporter's decomposition then fails
    on it ("Attempting to use FunctionalTensor on its own": pytorch issue 180354). Branch
    constants are small here; a larger one is a ``ValueError`` naming it, to be made outside
    the branch.
    """
    for name, sub in root.named_modules():
        if sub is root or not isinstance(sub, torch.fx.GraphModule):
            continue
        for node in list(sub.graph.nodes):
            value = getattr(sub, str(node.target), None) if node.op == "get_attr" else None
            if not isinstance(value, torch.Tensor):
                continue
            if value.numel() > BRANCH_CONSTANT_MAX:
                raise ValueError(f"a {tuple(value.shape)} tensor constant is made inside the exported branch "
                                 f"{name}; at most {BRANCH_CONSTANT_MAX} elements can be rebuilt there, make it "
                                 "outside the branch")
            with sub.graph.inserting_before(node):
                items = [sub.graph.call_function(torch.ops.aten.full.default, ([1], v),
                                                 {"dtype": value.dtype, "device": value.device})
                         for v in value.flatten().tolist()]
                flat = sub.graph.call_function(torch.ops.aten.cat.default, (items,)) if items else \
                    sub.graph.call_function(torch.ops.aten.empty.memory_format, ([0],),
                                            {"dtype": value.dtype, "device": value.device})
                made = sub.graph.call_function(torch.ops.aten.view.default, (flat, list(value.shape)))
            made.meta["val"] = node.meta.get("val")
            node.replace_all_uses_with(made)
            sub.graph.erase_node(node)
            delattr(sub, str(node.target))
        sub.recompile()


def _distinct_value_names(model) -> None:
    """Name every value of the (onnx_ir) model's main graph ``v<i>`` but its inputs and outputs,
    in place. The constant folder names its results after the values they replace and then
    renames duplicates ``x`` to ``x_1``, ``x_2``, ..., failing where an initializer already has
    that name (seen in the lattice tracker step: without control flow its unrolled refits
    repeat every name; with section 1 in the graph an initializer ``full`` meets the output
    ``full``); with these names no folded result can meet an existing one."""
    fixed = {v.name for v in list(model.graph.inputs) + list(model.graph.outputs)}
    values = list(model.graph.initializers.values()) + [o for node in model.graph for o in node.outputs]
    for i, v in enumerate(values):
        if v.name not in fixed:
            v.name = f"v{i}"


def _view_dtype_onnx(x, dtype: int):
    """``aten.view.dtype`` of a 0/1 tensor as an ONNX ``Cast``."""
    from onnxscript import opset18 as op

    return op.Cast(x, to=int(dtype))  # the exporter hands over the ONNX element type


def _params_dict(params: Params) -> dict:
    import dataclasses

    return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
