"""The contract every batched stage keeps, checked by one helper (torchvision's kernel-test pattern).

:func:`check_batched_stage` calls a stage on a batch and checks, for every tensor it returns
(a tensor, a tuple/NamedTuple or a dataclass of tensors, nested):

* batched equals unbatched: item ``i`` of the batch's result equals the result of item ``i`` alone;
* order: a permuted batch gives the permuted result;
* empty batch: a batch of 0 gives outputs with 0 rows and the same dtypes and trailing shapes;
* the inputs are not modified, and no output aliases an input;
* dtype and device: outputs live on the inputs' device, with the dtypes of the CPU run;
* CPU equals CUDA, where a GPU is available.

Inputs are given as ``(tensor, batched)`` pairs (``batched=False`` for per-call arguments such
as a table); everything else (``Params``, numbers) is passed through unchanged.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import torch

__all__ = ["check_batched_stage", "leaves", "same", "DEVICES"]

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def leaves(out: Any, prefix: str = "out") -> list[tuple[str, torch.Tensor]]:
    """Named tensors of a stage's output, in a fixed order."""
    if isinstance(out, torch.Tensor):
        return [(prefix, out)]
    if dataclasses.is_dataclass(out) and not isinstance(out, type):
        return [leaf for f in dataclasses.fields(out) for leaf in leaves(getattr(out, f.name), f"{prefix}.{f.name}")]
    if isinstance(out, tuple):
        names = getattr(out, "_fields", None) or [str(i) for i in range(len(out))]
        return [leaf for n, v in zip(names, out) for leaf in leaves(v, f"{prefix}.{n}")]
    return []  # ints, strings, None: not batched data


def same(a: torch.Tensor, b: torch.Tensor, tol: float = 0.0) -> bool:
    """Equal shapes, dtypes and values; NaN equals NaN (rows without support are NaN). Floats
    within ``tol * max(1, |b|)`` where ``tol > 0``."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if a.is_floating_point():
        close = (a == b) if tol == 0 else ((a - b).abs() <= tol * b.abs().clamp(min=1.0))
        return bool((close | (a.isnan() & b.isnan())).all())
    return torch.equal(a, b)


def _is_input(a: Any) -> bool:
    """Whether ``a`` is a ``(tensor, batched)`` pair of the spec."""
    return isinstance(a, tuple) and len(a) == 2 and isinstance(a[0], torch.Tensor) and isinstance(a[1], bool)


def _args(spec: Sequence[Any], pick: Callable[[torch.Tensor], torch.Tensor]) -> list[Any]:
    out = []
    for a in spec:
        if _is_input(a):
            out.append(pick(a[0]) if a[1] else a[0])
        else:
            out.append(a)
    return out


def _batch_size(spec: Sequence[Any]) -> int:
    sizes = {a[0].shape[0] for a in spec if _is_input(a) and a[1]}
    assert len(sizes) == 1, f"batched inputs disagree on the batch size: {sizes}"
    return sizes.pop()


def check_batched_stage(fn: Callable[..., Any], *spec: Any, name: str = "stage", empty: bool = True,
                        batch_dims: dict[str, int] | None = None, device_tol: float = 0.0) -> Any:
    """Run the contract checks (module docstring) on ``fn(*spec)``; returns the CPU result.

    ``batch_dims`` names outputs whose batch axis is not 0 (rare); an output whose first axis is
    not the batch (a per-call table) is compared whole. ``device_tol``: float outputs on another
    device agree with the CPU's within this relative tolerance (0: exactly; ALGORITHM.md,
    "Identical results", allows 1e-6 px for continuous outputs on a GPU).
    """
    batch_dims = batch_dims or {}
    b = _batch_size(spec)
    assert b >= 2, "use a batch of at least 2 items"
    tensors = [a[0] for a in spec if _is_input(a)]
    saved = [t.clone() for t in tensors]
    full = fn(*_args(spec, lambda t: t))
    got = leaves(full)
    assert got, f"{name}: returned no tensors"
    for t, s in zip(tensors, saved):
        assert torch.equal(t, s), f"{name}: modified its input"
    for lname, t in got:
        for x in tensors:
            assert t.data_ptr() != x.data_ptr() or t.numel() == 0, f"{name}: {lname} aliases an input"

    def per_item(lname: str, t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        d = batch_dims.get(lname, 0)
        return t.index_select(d, idx.to(t.device)) if t.dim() > d and t.shape[d] == b else t

    for i in range(b):
        one = leaves(fn(*_args(spec, lambda t, i=i: t[i:i + 1])))
        assert [n for n, _ in one] == [n for n, _ in got], f"{name}: output structure depends on the batch"
        for (lname, t1), (_, tb) in zip(one, got):
            want = per_item(lname, tb, torch.tensor([i]))
            assert t1.dtype == tb.dtype, f"{name}: {lname} dtype {t1.dtype} alone, {tb.dtype} in a batch"
            assert same(t1, want), f"{name}: {lname} of item {i} differs alone and in a batch"
    perm = torch.randperm(b, generator=torch.Generator().manual_seed(0))
    if torch.equal(perm, torch.arange(b)):
        perm = perm.flip(0)
    shuffled = leaves(fn(*_args(spec, lambda t: t.index_select(0, perm.to(t.device)))))
    for (lname, ts), (_, tb) in zip(shuffled, got):
        assert same(ts, per_item(lname, tb, perm)), f"{name}: {lname} is not permuted with the batch"
    if empty:
        none = leaves(fn(*_args(spec, lambda t: t[:0])))
        for (lname, t0), (_, tb) in zip(none, got):
            d = batch_dims.get(lname, 0)
            assert t0.dtype == tb.dtype, f"{name}: {lname} dtype {t0.dtype} for an empty batch, {tb.dtype} otherwise"
            if tb.dim() > d and tb.shape[d] == b:
                assert t0.shape[d] == 0, f"{name}: {lname} has shape {tuple(t0.shape)} for an empty batch"
    for dev in DEVICES:
        if dev == "cpu":
            continue
        # every tensor input moves, per-call tables too: a stage takes its device from them
        moved = leaves(fn(*[a[0].to(dev) if _is_input(a) else a for a in spec]))
        for (lname, tg), (_, tc) in zip(moved, got):
            assert tg.device.type == dev, f"{name}: {lname} left the {dev} device"
            assert same(tg.cpu(), tc, device_tol), (
                f"{name}: {lname} differs on {dev} and cpu" + (
                    f" (largest difference {float((tg.cpu() - tc).abs().nan_to_num().max()):.3g})"
                    if tc.is_floating_point() and tg.shape == tc.shape else ""))
    for lname, t in got:
        assert t.device.type == "cpu", f"{name}: {lname} left the inputs' device"
    return full
