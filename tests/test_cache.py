"""The on-disk LAB table (torchrow.core.tables.lab_table): verified at load, rebuilt on damage with
one notice, never leaving temporary files, usable without a writable folder (issue 11, 5-7).

Most tests shrink the table (``_N_COLORS``) and replace the kornia build by a fast fill: the
cache logic does not depend on the size. One test runs the real 400 MB build end to end.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

from torchrow.core import tables as shared

SMALL = 1 << 12


def _fill(out: np.ndarray) -> None:
    out[:] = np.arange(out.size, dtype=np.float64).reshape(out.shape) / 7.0


@pytest.fixture
def small_cache(tmp_path: Path, monkeypatch):
    """A temporary TORCHROW_CACHE with a 4096-colour table built by a fast fill."""
    builds: list[int] = []

    def build(out: np.ndarray) -> None:
        builds.append(1)
        _fill(out)

    monkeypatch.setenv("TORCHROW_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(shared, "_N_COLORS", SMALL)
    monkeypatch.setattr(shared, "_build_lab_table", build)
    shared.lab_table.cache_clear()
    yield tmp_path / "cache", builds
    shared.lab_table.cache_clear()  # later tests load the real table again


def _load(capsys=None):
    shared.lab_table.cache_clear()
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        table = shared.lab_table()
    return table, [str(w.message) for w in got if issubclass(w.category, shared.CacheWarning)]


def _expected() -> np.ndarray:
    e = np.empty((SMALL, 3))
    _fill(e)
    return e


def test_build_once_with_one_notice_mode_0644_and_a_check_record(small_cache, capsys) -> None:
    folder, builds = small_cache
    table, warned = _load()
    err = capsys.readouterr().err
    assert builds == [1] and warned == []
    assert err.count("building the shared LAB table") == 1 and str(folder) in err
    path = folder / shared._table_name()
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert stat.S_IMODE(shared._check_path(path).stat().st_mode) == 0o644
    assert json.loads(shared._check_path(path).read_text())["crc32"] == shared._crc32(path)
    np.testing.assert_array_equal(table, _expected())
    # a second load is the memory map, no build, no word
    again, warned = _load()
    assert builds == [1] and warned == [] and capsys.readouterr().err == ""
    assert isinstance(again, np.memmap)
    assert sorted(p.name for p in folder.iterdir()) == sorted([path.name, shared._check_path(path).name])


@pytest.mark.parametrize("damage", ["empty", "zero_slice", "truncated", "no_record", "garbage_record"])
def test_damaged_table_is_rebuilt_with_one_warning(small_cache, damage: str) -> None:
    folder, builds = small_cache
    _load()
    path = folder / shared._table_name()
    if damage == "empty":  # `: > lab_*.npy`
        path.write_bytes(b"")
    elif damage == "zero_slice":  # header intact, content changed
        with open(path, "r+b") as fh:
            fh.seek(path.stat().st_size // 2)
            fh.write(b"\0" * 4096)
    elif damage == "truncated":
        with open(path, "r+b") as fh:
            fh.truncate(path.stat().st_size - 8)
    elif damage == "no_record":
        shared._check_path(path).unlink()
    else:
        shared._check_path(path).write_text("{not json")
    table, warned = _load()
    assert builds == [1, 1]
    assert len(warned) == 1 and "rebuilding" in warned[0] and "\n" not in warned[0]
    np.testing.assert_array_equal(table, _expected())
    _, warned = _load()  # repaired: silent again
    assert warned == [] and builds == [1, 1]


def test_touched_but_unchanged_table_is_reverified_not_rebuilt(small_cache) -> None:
    folder, builds = small_cache
    _load()
    path = folder / shared._table_name()
    os.utime(path, ns=(1, 1))  # the cheap stamp no longer matches: the CRC decides
    _, warned = _load()
    assert warned == [] and builds == [1]
    assert json.loads(shared._check_path(path).read_text())["mtime_ns"] == 1


def test_table_changed_in_place_with_its_mtime_put_back_is_caught(small_cache) -> None:
    """Issue 26: bytes changed in place, then `touch -d` back to the recorded time, went
    undetected (3 of 10 records changed). The inode change time cannot be put back."""
    folder, builds = small_cache
    _load()
    path = folder / shared._table_name()
    st = path.stat()
    with open(path, "r+b") as fh:
        fh.seek(st.st_size // 2)
        fh.write(b"\1" * 64)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert path.stat().st_mtime_ns == st.st_mtime_ns and path.stat().st_size == st.st_size
    table, warned = _load()
    assert builds == [1, 1] and len(warned) == 1 and "checksum" in warned[0]
    np.testing.assert_array_equal(table, _expected())


def test_the_tensor_path_shows_the_cache_warning(small_cache, monkeypatch) -> None:
    """Issue 26: the tensor path's table (lab_table_torch) silenced every UserWarning, so a
    damaged or unwritable cache was rebuilt without a word there."""
    folder, builds = small_cache
    _load()
    (folder / shared._table_name()).write_bytes(b"")
    monkeypatch.setattr(shared, "_TORCH_TABLES", {})
    shared.lab_table.cache_clear()
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        t = shared.lab_table_torch("cpu")
    msgs = [str(w.message) for w in got if issubclass(w.category, shared.CacheWarning)]
    assert len(msgs) == 1 and "rebuilding" in msgs[0] and builds == [1, 1]
    assert not [w for w in got if "not writable" in str(w.message)]  # torch's own notice stays hidden
    np.testing.assert_array_equal(t.numpy(), _expected())


def test_unwritable_folder_one_warning_and_a_table_in_memory(tmp_path: Path, small_cache, monkeypatch) -> None:
    _, builds = small_cache
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("TORCHROW_CACHE", str(blocker / "cache"))  # mkdir fails, even for root
    table, warned = _load()
    assert builds == [1] and len(warned) == 1 and "cannot write" in warned[0] and "TORCHROW_CACHE" in warned[0]
    np.testing.assert_array_equal(table, _expected())


def test_failed_write_leaves_no_temporary_file(tmp_path: Path) -> None:
    """A file-size limit (as a full disk) makes the write fail part way: one warning, the
    table is still returned, and nothing but the (absent) table is left in the folder."""
    folder = tmp_path / "cache"
    code = textwrap.dedent(f"""
        import resource, warnings
        import numpy as np
        from torchrow.core import tables as shared
        shared._N_COLORS = {SMALL}
        shared._build_lab_table = lambda out: out.fill(1.5)
        resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, 50_000))  # the table is 98 kB
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            t = shared.lab_table()
        assert t.shape == ({SMALL}, 3) and float(t[7, 2]) == 1.5
        msgs = [str(x.message) for x in w if issubclass(x.category, shared.CacheWarning)]
        assert len(msgs) == 1 and "cannot write" in msgs[0], msgs
    """)
    env = {**os.environ, "TORCHROW_CACHE": str(folder)}
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert list(folder.iterdir()) == []


def test_empty_real_cache_file_is_rebuilt_and_demo_runs(tmp_path: Path) -> None:
    """Reproducer 5 with the real table: an empty cache file made every record `error` and
    `demo` end in a traceback. One real build (~10-40 s)."""
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / shared._table_name()).write_bytes(b"")
    env = {**os.environ, "TORCHROW_CACHE": str(cache)}
    r = subprocess.run([sys.executable, "-m", "torchrow", "demo", "--out", str(tmp_path / "demo.png")],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.count("rebuilding it") == 1 and r.stderr.count("building the shared LAB table") == 1
    assert "status ok" in r.stdout or "status invalid" in r.stdout
    path = cache / shared._table_name()
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert sorted(p.name for p in cache.iterdir()) == sorted([path.name, shared._check_path(path).name])
    # the rebuilt table is the one the rest of the suite uses (same bits)
    np.testing.assert_array_equal(np.load(path, mmap_mode="r")[::9973], shared.lab_table()[::9973])


def test_onnx_test_model_cache_keeps_the_current_source_only(tmp_path: Path):
    """Cached test models of an older source are deleted when a model is written; those of
    the current source (any arguments) stay."""
    from onnx_models import _prune, _source_key

    src = _source_key()
    keep = [tmp_path / f"detector-{src}-aaaaaaaaaaaa.onnx", tmp_path / f"tracker-masked-{src}-bbbbbbbbbbbb.onnx"]
    stale = [tmp_path / "detector-0123456789abcdef-aaaaaaaaaaaa.onnx", tmp_path / "tracker-77cf9d0f723f56a3.onnx"]
    for f in keep + stale:
        f.write_bytes(b"x")
    _prune(tmp_path, src)
    assert sorted(tmp_path.iterdir()) == sorted(keep)
