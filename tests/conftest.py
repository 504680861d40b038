"""Shared fixtures. Data-dependent tests skip cleanly when the data folder is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

_DEFAULT = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def data_root() -> Path | None:
    """The data folder (holding ``crbd/``, ``caterra_video/``): TORCHROW_DATA or ../shared/data."""
    env = os.environ.get("TORCHROW_DATA")
    p = Path(env) if env else _DEFAULT
    return p if p.is_dir() else None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    p = data_root()
    if p is None:
        pytest.skip("data folder not found (set TORCHROW_DATA or place it at ../shared/data)")
    return p


@pytest.fixture(scope="session")
def crbd_dir(data_dir: Path) -> Path:
    p = data_dir / "crbd"
    if not (p / "Images").is_dir():
        pytest.skip(f"CRBD not found under {data_dir}")
    return p
