"""Checks of the exported graphs against the eager engines: :func:`step_differences` (tracker
steps and states field by field) and :func:`check_lab` (the graph's LAB on all 2**24 colours).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchrow.core.params import Params
from torchrow.onnx.export import DEFAULT_OPSET
from torchrow.onnx.passes import legalize
from torchrow.onnx.runtime import import_ort
from torchrow.onnx.shims import float64_python_constants, nested_subgraph_opsets

__all__ = ["step_differences", "check_lab"]

def step_differences(ref, got, tol: float = 1e-9, active: torch.Tensor | None = None) -> list[str]:
    """Field-by-field differences between two tracker steps or states of the same sequences.

    ``ref``/``got``: :class:`~torchrow.functional.tracking.TrackStep` or
    :class:`~torchrow.functional.tracking.TrackerState`, or the lattice tracker's
    :class:`~torchrow.functional.lattice_tracking.LatticeStep` (its ``rows`` compared field by
    field) or :class:`~torchrow.functional.lattice_tracking.LatticeTrackerState` (e.g.
    :class:`torchrow.Tracker` vs :class:`OnnxTracker`). Only active sequences are compared (a
    step's ``active``, or ``active`` if given); Hough line and outlier slots only where valid
    (the others carry no meaning); float64 fields within ``tol`` (NaN equals NaN), all others
    exactly. Returns one line per differing field.
    """
    import dataclasses

    from torchrow.functional.lattice_tracking import LatticeStep
    from torchrow.functional.tracking import TrackStep

    out = []
    if active is not None:
        act = active
    else:
        act = ref.active if isinstance(ref, (TrackStep, LatticeStep)) else torch.ones(len(ref), dtype=torch.bool)
    for f in dataclasses.fields(ref):
        ra, ga = getattr(ref, f.name), getattr(got, f.name)
        if ra is None or ga is None:  # a field the mode does not compute
            continue
        if dataclasses.is_dataclass(ra):  # the lattice step's rows
            out += step_differences(ra, ga, tol, act)
            continue
        a, b = ra[act], ga[act]
        if isinstance(ref, TrackStep) and f.name in ("hough_theta", "hough_rho", "hough_weight", "out_theta",
                                                      "out_rho", "out_weight"):
            mask = ref.hough_valid if f.name.startswith("hough") else ref.out_valid
            assert mask is not None  # the tracker is faithful: it computes sections 4-6
            valid = mask[act]
            a, b = torch.where(valid, a, 0), torch.where(valid, b, 0)
        if a.dtype == torch.float64:
            same = a.shape == b.shape and bool(torch.isclose(a, b, rtol=0, atol=tol, equal_nan=True).all())
        else:
            same = torch.equal(a, b)
        if not same:
            out.append(f"{type(ref).__name__}.{f.name}: {a.tolist()} != {b.tolist()}")
    return out


class _Lab(torch.nn.Module):
    lut: torch.Tensor
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

    ort = import_ort()
    params = params or Params()
    ks = [float(v) for v in (k if k is not None else [params.veg_tol])]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "lab.onnx"
        x = torch.zeros((1, 3, 256, 256), dtype=torch.uint8)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            with float64_python_constants(), nested_subgraph_opsets():
                prog = torch.onnx.export(_Lab(), (x,), dynamo=True, opset_version=DEFAULT_OPSET,
                                         input_names=["images"], verbose=False)
        import onnx

        if prog is None:
            raise RuntimeError("torch.onnx.export returned no program for the LAB graph")
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
    res: dict[str, Any] = {"colors": 1 << 24, "mismatched_colors": int(idx.size), "k": ks,
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
