"""``--engine ray --address``: an address that cannot work fails at once with one line
(issue 26: ``127.0.0.1:1`` hung over 150 s, ``ray://`` without the client gave a traceback).
No Ray cluster is started here."""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

import pytest

pytest.importorskip("ray.data")

from torchrow.apps.cli import main


@pytest.mark.parametrize("address", ["127.0.0.1:1", "ray://127.0.0.1:1"])
def test_unreachable_address_fails_fast_with_one_line(tmp_path: Path, capsys, address: str) -> None:
    import ray

    if ray.is_initialized():
        pytest.skip("a Ray of another test module is initialised in this process (it would be used as it is)")
    img = tmp_path / "a.png"
    img.write_bytes(b"")
    t0 = time.monotonic()
    assert main(["detect", str(img), "--out", str(tmp_path / "r.jsonl"), "-q", "--engine", "ray",
                 "--address", address]) == 2
    assert time.monotonic() - t0 < 30
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"torchrow: error: --address {address}: ") and "\n" not in err, err
    client = importlib.util.find_spec("grpc") is not None
    assert ("ray[client]" in err) if address.startswith("ray://") and not client else "no Ray cluster answers" in err
    assert not (tmp_path / "r.jsonl").exists()
