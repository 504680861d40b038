"""How a stage skips work no image of the batch needs, in eager code and in exported graphs.

``flow`` names one of three forms of the same choice (results never depend on it):

* ``"sync"``: a host synchronisation (``bool(pred)``), eager only;
* ``"cond"``: ``torch.cond`` while ``torch.export`` traces (an ONNX ``If``: the graph keeps
  the static bound and skips the work at run time); eagerly the same as ``"sync"``;
* ``"always"``: never skipped, masks choose (a graph without control flow).
"""

from __future__ import annotations

from typing import Callable

import torch

FLOWS = ("sync", "cond", "always")


def check_flow(flow: str) -> str:
    if flow not in FLOWS:
        raise ValueError(f"flow must be one of {FLOWS}, got {flow!r}")
    return flow


def branch(flow: str, pred: torch.Tensor, fn: Callable, skip: Callable, operands: tuple) -> tuple:
    """``fn(*operands)`` if ``pred`` (bool scalar tensor) else ``skip(*operands)``, per ``flow``;
    both return tuples of tensors of the same shapes and dtypes (``skip`` must not return its
    operands themselves: a ``torch.cond`` branch may not alias its inputs)."""
    check_flow(flow)
    if flow == "always":
        return tuple(fn(*operands))
    if flow == "cond" and torch.compiler.is_exporting():
        def dense(f):  # torch.cond wants dense outputs of matching strides
            return lambda *a: tuple(t.contiguous() for t in f(*a))

        return tuple(torch.cond(pred, dense(fn), dense(skip), operands))
    return tuple(fn(*operands)) if bool(pred) else tuple(skip(*operands))


def keep(*operands: torch.Tensor) -> tuple:
    """The skip branch that changes nothing (copies: branches may not alias their inputs)."""
    return tuple(t.clone() for t in operands)
