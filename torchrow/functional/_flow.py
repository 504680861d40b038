"""How a stage skips work no image of the batch needs, in eager code and in exported graphs.

``flow`` names one of three forms of the same choice (results never depend on it):

* ``"sync"``: a host synchronisation (``bool(pred)``), eager only;
* ``"cond"``: ``torch.cond`` while ``torch.export`` traces (an ONNX ``If``: the graph keeps
  the static bound and skips the work at run time); eagerly the same as ``"sync"``;
* ``"loop"``: as ``"cond"`` for :func:`branch`; a bounded loop (:func:`repeat`) becomes
  one ``torch._higher_order_ops.while_loop`` while ``torch.export`` traces (an ONNX
  ``Loop`` whose body is traced and stored once, and which stops when every image is done);
  eagerly the same as ``"sync"``;
* ``"always"``: never skipped, masks choose (a graph without control flow).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

FLOWS = ("sync", "cond", "loop", "always")


def int_max(a: int, b: int) -> int:
    """``max(a, b)`` of two sizes, also where they are symbolic: traced inside a ``torch.cond``
    branch by non-strict ``torch.export`` (torch 2.13), the built-in ``max`` of symbolic ints
    returned their minimum (a chunk of 1 where 118 was meant: one scatter per VP)."""
    return a if a >= b else b


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
    if flow in ("cond", "loop") and torch.compiler.is_exporting():
        def dense(f):  # torch.cond wants dense outputs of matching strides
            return lambda *a: tuple(t.contiguous() for t in f(*a))

        return tuple(torch.cond(pred, dense(fn), dense(skip), operands))
    return tuple(fn(*operands)) if bool(pred) else tuple(skip(*operands))


def choose(flow: str, pred: torch.Tensor, fn: Callable, other: Callable, operands: tuple) -> tuple:
    """``fn(*operands)`` if ``pred`` else ``other(*operands)``, where both are exact forms of
    the same result (e.g. a list cut short when no image has more entries, and the whole
    list): unlike :func:`branch`, not a skip. ``"always"`` (no control flow) takes ``other``,
    the form that holds without the predicate."""
    check_flow(flow)
    if flow == "always":
        return tuple(other(*operands))
    return branch(flow, pred, fn, other, operands)


def keep(*operands: torch.Tensor) -> tuple:
    """The skip branch that changes nothing (copies: branches may not alias their inputs)."""
    return tuple(t.clone() for t in operands)


def repeat(flow: str, steps: int, done: Callable, step: Callable, carry: tuple) -> tuple:
    """Apply ``step`` (tuple of tensors -> same shapes and dtypes) at most ``steps`` times,
    stopping once ``done(*carry)`` (bool scalar tensor) holds, per ``flow``: ``"sync"`` checks
    on the host before each step; ``"cond"`` unrolls ``steps`` :func:`branch` calls (one
    ``If`` each); ``"loop"`` is one ``while_loop`` while exporting (sync otherwise);
    ``"always"`` runs every step unmasked by any check (``step`` must leave a done carry
    unchanged, which the line search's masks guarantee)."""
    check_flow(flow)
    if flow == "loop" and torch.compiler.is_exporting():
        from torch._higher_order_ops import while_loop

        def cond_fn(i, *c):
            return (i < steps) & ~done(*c)

        def body_fn(i, *c):
            return (i + 1,) + tuple(t.contiguous() for t in step(*c))

        i0 = torch.zeros((), dtype=torch.int64, device=carry[0].device)
        return tuple(while_loop(cond_fn, body_fn, (i0,) + tuple(carry)))[1:]
    unrolled = flow == "cond" and torch.compiler.is_exporting()
    for _ in range(steps):
        if unrolled:
            carry = branch(flow, ~done(*carry), step, keep, carry)
            continue
        if flow != "always" and bool(done(*carry)):
            break
        carry = tuple(step(*carry))
    return carry
