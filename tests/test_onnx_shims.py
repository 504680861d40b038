"""The exporter shims (torchrow.onnx.shims) fit the installed torch / onnx_ir internals they
patch, and refuse to patch an internal that changed."""

from __future__ import annotations

import pytest

pytest.importorskip("onnxscript")
pytest.importorskip("onnx_ir")

from torchrow.onnx import shims


def test_every_shim_fits_the_installed_internals():
    """Fails as soon as a torch / onnx_ir release renames or re-signs a patched internal: read
    the shim's ``upstream`` note, check whether the problem is fixed there, then update or drop it."""
    assert shims.check_shims() == []


@pytest.mark.parametrize("name", sorted(shims.SHIMS))
def test_a_changed_internal_is_refused_before_patching(name, monkeypatch):
    shim = shims.SHIMS[name]
    owner = shim.target()
    original = getattr(owner, shim.attribute)

    def changed(a, b):  # another signature than the shim was written for
        return None

    monkeypatch.setattr(owner, shim.attribute, changed)
    with pytest.raises(shims.ShimError, match=f"{name}: expected .*{shim.attribute}"):
        shims.require(name)
    cm = shims.float64_python_constants() if name == "float64_python_constants" else shims.nested_subgraph_opsets()
    with pytest.raises(shims.ShimError):
        with cm:
            pass
    assert getattr(owner, shim.attribute) is changed  # nothing was patched
    monkeypatch.setattr(owner, shim.attribute, original)


def test_a_missing_internal_is_named():
    shim = shims.Shim("gone", "types", "", "no_such_function", (), "nowhere")
    assert shim.problem() is not None and "gone: expected types.no_such_function, not found" in shim.problem()


def test_the_patches_are_undone_on_exit():
    for name, cm in (("float64_python_constants", shims.float64_python_constants),
                     ("nested_subgraph_opsets", shims.nested_subgraph_opsets)):
        shim = shims.SHIMS[name]
        before = getattr(shim.target(), shim.attribute)
        with cm():
            assert getattr(shim.target(), shim.attribute) is not before
        assert getattr(shim.target(), shim.attribute) is before
