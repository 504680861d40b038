"""Patches of private torch / onnx_ir internals that the export needs, each applied only inside
a context manager and each checked before it patches anything.

A patch replaces a private function whose behaviour is not an API: a new torch or onnx_ir may
rename it, change its arguments or fix the problem. Every patch is described by a
:class:`Shim` (the module and attribute it replaces, the parameters it expects, the upstream
problem it works around); :func:`check_shims` checks every one against the installed
packages, :func:`require` raises :class:`ShimError` naming what changed before a patch is
applied, and ``tests/test_onnx_shims.py`` fails as soon as an installed version differs.
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
from dataclasses import dataclass
from typing import Any

__all__ = ["Shim", "ShimError", "SHIMS", "check_shims", "require", "float64_python_constants",
           "nested_subgraph_opsets"]


class ShimError(RuntimeError):
    """A patched internal is missing or has another signature than the shim was written for."""


@dataclass(frozen=True)
class Shim:
    """One patched internal: ``module.owner.attribute`` (``owner`` empty for a module-level
    function) taking ``parameters`` (names, in order); ``upstream`` says what it works around
    and where the upstream code is."""

    name: str
    module: str
    owner: str
    attribute: str
    parameters: tuple[str, ...]
    upstream: str

    def target(self) -> Any:
        """The object whose attribute is patched (a module or a class)."""
        mod = importlib.import_module(self.module)
        return getattr(mod, self.owner) if self.owner else mod

    def problem(self) -> str | None:
        """Why this shim cannot be applied to the installed packages, or ``None``."""
        where = f"{self.module}.{self.owner + '.' if self.owner else ''}{self.attribute}"
        try:
            fn = getattr(self.target(), self.attribute)
        except (ImportError, AttributeError) as exc:
            return f"{self.name}: expected {where}, not found ({exc}); installed {_versions()}"
        got = tuple(inspect.signature(fn).parameters)
        if got != self.parameters:
            return (f"{self.name}: expected {where}{self.parameters}, got {got}; installed {_versions()} "
                    f"(upstream: {self.upstream})")
        return None


def _versions() -> str:
    out = []
    for name in ("torch", "onnxscript", "onnx_ir"):
        try:
            out.append(f"{name} {importlib.import_module(name).__version__}")
        except ImportError:
            out.append(f"{name} absent")
    return ", ".join(out)


#: The patches :func:`torchrow.onnx.export.to_onnx` applies, checked by :func:`check_shims`.
SHIMS = {
    # torch/onnx/_internal/exporter/_building.py: a Python float operand whose ONNX type
    # constraint is not bound by a tensor input becomes a FLOAT (float32) constant, also in
    # float64 graphs (0.412453 -> 0.41245299577713013)
    "float64_python_constants": Shim(
        "float64_python_constants", "torch.onnx._internal.exporter._building", "", "_determine_input_dtype",
        ("param", "arg", "type_binding"),
        "torch.onnx exporter, _building._determine_input_dtype: Python float constants typed float32"),
    # onnx_ir/passes/common/inliner.py: a function nested in another is called at the model's
    # opset of the private pkg.torch.__subgraph__ domain but defined at its version 1, and the
    # inliner refuses the mismatch (a torch.cond inside a torch.while_loop body)
    "nested_subgraph_opsets": Shim(
        "nested_subgraph_opsets", "onnx_ir.passes.common.inliner", "InlinePass", "_instantiate_call",
        ("self", "node", "call_site_id"),
        "onnx_ir InlinePass._instantiate_call: opset version mismatch of nested pkg.torch.__subgraph__ functions"),
}


def check_shims() -> list[str]:
    """One line per shim that does not fit the installed packages (empty: all fit)."""
    return [p for p in (s.problem() for s in SHIMS.values()) if p is not None]


def require(name: str) -> tuple[Any, Any]:
    """``(owner, original function)`` of the shim ``name``; :class:`ShimError` if it does not
    fit the installed packages."""
    shim = SHIMS[name]
    problem = shim.problem()
    if problem is not None:
        raise ShimError(problem)
    owner = shim.target()
    return owner, getattr(owner, shim.attribute)


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

    building, orig = require("float64_python_constants")

    def determine(param, arg, type_binding):
        dtype = orig(param, arg, type_binding)
        if (dtype == ir.DataType.FLOAT and isinstance(arg, float) and param.type_constraint not in type_binding
                and len(param.type_constraint.allowed_types) != 1):
            return ir.DataType.DOUBLE
        return dtype

    building._determine_input_dtype = determine
    try:
        yield
    finally:
        building._determine_input_dtype = orig


@contextlib.contextmanager
def nested_subgraph_opsets():
    """Let the exporter inline a ``torch.cond`` nested in a ``while_loop`` body.

    The exporter records the call of a nested subgraph function at the model's opset
    version, the function itself at version 1 of the same private domain
    (``pkg.torch.__subgraph__``), and its inliner then refuses the mismatch. The domain only
    names the functions being inlined (nothing of it is left in the model), so its version
    is made to agree.
    """
    pass_class, orig = require("nested_subgraph_opsets")

    def instantiate(self, node, call_site_id):
        function = self._functions[node.op_identifier()]
        for key in list(function.opset_imports):
            if key.startswith("pkg.torch.__subgraph__") and key in self._opset_imports:
                function.opset_imports[key] = self._opset_imports[key]
        return orig(self, node, call_site_id)

    pass_class._instantiate_call = instantiate
    try:
        yield
    finally:
        pass_class._instantiate_call = orig
