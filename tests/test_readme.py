"""The README's Python blocks run as written and print what the README says they print."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: a ```python block, optionally followed by "prints" and a ```text block of its exact output
BLOCK = re.compile(r"```python\n(?P<code>.*?)```\n(?:\s*prints\s*\n\s*```text\n(?P<out>.*?)```\n)?", re.S)
NEEDS_DATA = ("CRBD(", "resolve_data_root", "TORCHROW_DATA")
#: blocks that export an ONNX model take minutes on a small CPU, and the Ray block starts a
#: local cluster (about 18 s; ``tests/test_distributed.py`` checks the engine by default): run
#: them with ``-m heavy``
HEAVY = ("to_onnx(", "distributed.init(")


def _blocks() -> list[tuple[str, str, str | None]]:
    text = (ROOT / "README.md").read_text()
    found = []
    for m in BLOCK.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        heading = [h for h in re.findall(r"^#+ (.*)$", text[: m.start()], re.M)][-1:] or ["top"]
        found.append((f"line{line}-{heading[0][:30]}", m.group("code"), m.group("out")))
    return found


def test_readme_has_blocks_with_outputs():
    blocks = _blocks()
    assert len(blocks) >= 3 and sum(out is not None for _, _, out in blocks) >= 3


def _params():
    return [pytest.param(*b, id=b[0], marks=[pytest.mark.heavy] if any(k in b[1] for k in HEAVY) else [])
            for b in _blocks()]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "code", "expected"), _params())
def test_readme_block_runs(name, code, expected, tmp_path, request):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    if any(k in code for k in NEEDS_DATA):
        env["TORCHROW_DATA"] = str(request.getfixturevalue("data_dir"))  # skips cleanly without the data
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, f"README block {name} failed:\n{proc.stderr[-3000:]}"
    if expected is not None:
        assert proc.stdout == expected, f"README block {name} printed:\n{proc.stdout}"
