"""Static checks run with the tests, so that CI (the README's one test command) runs them too:
ruff, mypy over the package, the layer map (import-linter) and private names kept private."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _tool(name: str) -> list[str]:
    pytest.importorskip(name, reason=f"{name} is in the dev extra")
    return [sys.executable, "-m", name]


def test_ruff():
    proc = subprocess.run(_tool("ruff") + ["check", "torchrow", "tests", "benchmarks", "notebooks", "docs"],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]


@pytest.mark.slow
def test_mypy():
    if shutil.which("git") is None:
        pytest.skip("git not found")
    proc = subprocess.run(_tool("mypy") + ["torchrow"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-2000:]


def test_import_layers():
    """The layer map in ``.importlinter`` (README "Architecture"): no upward import, ``reference``
    independent of ``functional``, no import cycle inside a package."""
    pytest.importorskip("importlinter", reason="import-linter is in the dev extra")
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-c", "from importlinter.cli import lint_imports_command; "
                                                                  "lint_imports_command()"]
    proc = subprocess.run(cmd + ["--no-cache"], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-2000:]


def private_imports(package: Path = ROOT / "torchrow") -> list[str]:
    """``file:line`` of every private name (``_x``, not a dunder) one module of ``package`` takes
    from another: ``from torchrow.m import _x`` or ``alias._x`` on an imported module of the
    package. Modules named ``_x`` (``torchrow.functional._flow``) are not another module's names:
    they are their package's shared helpers."""
    base, top = package.parent, package.name

    def private(name: str) -> bool:
        return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))

    def is_module(name: str) -> bool:
        p = base.joinpath(*name.split("."))
        return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()

    found = []
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(base).with_suffix("").parts)
        me = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        where = path.relative_to(base).as_posix()
        tree = ast.parse(path.read_text(), str(path))
        aliases: dict[str, str] = {}  # local name -> module of the package
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == top:
                for a in node.names:
                    if is_module(f"{node.module}.{a.name}"):
                        aliases[a.asname or a.name] = f"{node.module}.{a.name}"
                    elif private(a.name) and node.module != me:
                        found.append(f"{where}:{node.lineno}: {a.name} from {node.module}")
            elif isinstance(node, ast.Import):
                aliases.update({a.asname: a.name for a in node.names if a.asname and a.name.split(".")[0] == top})
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and private(node.attr) and aliases[node.value.id] != me):
                found.append(f"{where}:{node.lineno}: {node.attr} of {aliases[node.value.id]}")
    return found


def test_no_private_imports_across_modules():
    """A private name is its module's own: another module that needs it needs a public name."""
    assert private_imports() == []


def test_private_import_check_sees_both_forms(tmp_path):
    pkg = tmp_path / "torchrow"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "a.py").write_text("def _helper():\n    pass\n\n\n_helper()\n")
    (pkg / "b.py").write_text("from torchrow.sub import a as mod\nfrom torchrow.sub.a import _helper\n"
                              "mod._helper()\nmod.__name__\n")
    assert private_imports(pkg) == ["torchrow/b.py:2: _helper from torchrow.sub.a",
                                    "torchrow/b.py:3: _helper of torchrow.sub.a"]
