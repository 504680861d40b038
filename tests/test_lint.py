"""Static checks run with the tests, so that CI (the README's one test command) runs them too:
ruff (pyflakes, pycodestyle, import order, bugbear) and mypy over the package."""

from __future__ import annotations

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
