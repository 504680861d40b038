"""Helpers shared by the benchmark scripts: environment description and RESULTS.md output."""

from __future__ import annotations

import datetime as _dt
import os
import platform
import subprocess
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


def data_root(arg: str | None) -> Path:
    """Data folder from the argument, ``TORCHROW_DATA`` or ``../shared/data``."""
    for cand in (arg, os.environ.get("TORCHROW_DATA"), Path(__file__).resolve().parents[2] / "shared" / "data"):
        if cand and Path(cand).is_dir():
            return Path(cand)
    raise SystemExit("benchmark needs the data folder: --data DIR or TORCHROW_DATA")


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def environment() -> str:
    """One line: date, commit, machine, versions."""
    import cv2
    import kornia
    import numpy
    import torch

    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=RESULTS.parent).stdout.strip() or "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, cwd=RESULTS.parent).stdout.strip()
        commit += "+dirty" if dirty else ""
    except OSError:
        commit = "unknown"
    return (f"{_dt.date.today().isoformat()}, commit {commit}, {_cpu_name()} ({os.cpu_count()} cores, "
            f"torch threads {torch.get_num_threads()}), Python {platform.python_version()}, "
            f"torch {torch.__version__}, kornia {kornia.__version__}, numpy {numpy.__version__}, "
            f"OpenCV {cv2.__version__}")


def append_results(title: str, command: str, body: str) -> None:
    """Append a dated section to benchmarks/RESULTS.md."""
    header = "" if RESULTS.exists() else "# Benchmark results\n\nEach section is appended by the script named in it.\n"
    with open(RESULTS, "a") as fh:
        fh.write(f"{header}\n## {title}\n\n{environment()}\n\n`{command}`\n\n{body}\n")
