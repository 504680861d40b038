"""Streaming output: the record sink (flush, torn lines, resume, Parquet), the runner's
bounded ordering window, and a run killed with SIGKILL then resumed (subprocess)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest

from torchrow.apps.cli import main
from torchrow.apps.sink import RecordSink, SinkError, frame_key, journal_path, read_records
from torchrow.engines.runner import run
from torchrow.evaluation.synthetic import FieldSpec, render, sequence


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


# -- the sink ----------------------------------------------------------------------------

def test_each_record_is_on_disk_when_write_returns(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    sink = RecordSink(out)
    for i in range(3):
        sink.write({"name": f"im{i}", "status": "ok"})
        # another reader sees the record at once (flushed to the OS, not buffered)
        assert [json.loads(s)["name"] for s in _lines(out)] == [f"im{j}" for j in range(i + 1)]
    sink.close()


def test_resume_cuts_a_torn_last_line_and_appends(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    with RecordSink(out) as sink:
        sink.write({"name": "a", "status": "ok"})
        sink.write({"name": "b", "status": "ok"})
    with open(out, "ab") as fh:
        fh.write(b'{"name": "c", "stat')  # a write cut short by a kill
    sink = RecordSink(out, resume=True)
    assert sink.done == {"a", "b"} and "c" not in sink
    sink.write({"name": "c", "status": "ok"})
    sink.close()
    assert [json.loads(s)["name"] for s in _lines(out)] == ["a", "b", "c"]


def test_resume_cuts_a_last_line_that_is_not_json_even_with_newline(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    out.write_bytes(b'{"name": "a"}\n{"name": "b", \n')
    assert RecordSink(out, resume=True).done == {"a"}
    assert out.read_bytes() == b'{"name": "a"}\n'


def test_resume_refuses_a_corrupt_line_before_the_end(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    out.write_bytes(b'{"name": "a"}\nGARBAGE\n{"name": "b"}\n')
    with pytest.raises(SinkError, match="line 2"):
        RecordSink(out, resume=True)
    assert out.read_bytes() == b'{"name": "a"}\nGARBAGE\n{"name": "b"}\n'  # untouched


def test_without_resume_the_file_is_replaced(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    out.write_text('{"name": "old"}\n')
    with RecordSink(out) as sink:
        sink.write({"name": "new"})
    assert _lines(out) == ['{"name": "new"}']


def test_video_keys_are_source_and_frame(tmp_path: Path) -> None:
    out = tmp_path / "v.jsonl"
    with RecordSink(out, key=frame_key) as sink:
        sink.write({"source": "s", "frame": 0})
        sink.write({"source": "t", "frame": 0})
    assert RecordSink(out, key=frame_key, resume=True).done == {("s", 0), ("t", 0)}


def _cli_records(folder: Path, out: Path, *extra: str) -> None:
    assert main(["detect", str(folder), "--out", str(out), "-q", "--batch-size", "2", *extra]) == 0


@pytest.fixture(scope="module")
def field_folder(tmp_path_factory) -> Path:
    """Three synthetic fields (one of another size, sorted first) and one unreadable file."""
    d = tmp_path_factory.mktemp("fields")
    cv2.imwrite(str(d / "a_wide.png"), cv2.cvtColor(render(FieldSpec(seed=9, width=640, height=360)).image,
                                                    cv2.COLOR_RGB2BGR))
    for i in range(2):
        cv2.imwrite(str(d / f"f{i}.png"), cv2.cvtColor(render(FieldSpec(seed=i)).image, cv2.COLOR_RGB2BGR))
    (d / "z_bad.jpg").write_bytes(b"not an image")
    return d


def test_parquet_output_holds_the_jsonl_records(field_folder: Path, tmp_path: Path) -> None:
    pytest.importorskip("pyarrow")
    _cli_records(field_folder, tmp_path / "r.jsonl")
    _cli_records(field_folder, tmp_path / "r.parquet")
    want = [json.loads(s) for s in _lines(tmp_path / "r.jsonl")]
    assert list(read_records(tmp_path / "r.parquet")) == want
    assert not journal_path(tmp_path / "r.parquet").exists()
    # resuming a finished Parquet run keeps every record once
    _cli_records(field_folder, tmp_path / "r.parquet", "--resume")
    assert list(read_records(tmp_path / "r.parquet")) == want


# -- the runner's ordering window --------------------------------------------------------

_SMALL = [render(FieldSpec(seed=s, width=64, height=48)).image for s in range(3)]
_ODD = render(FieldSpec(seed=7, width=64, height=40)).image


def _small_items(n: int, odd_first: bool, pulled: list[int]):
    imgs = [_SMALL[i % 3] for i in range(n)]
    if odd_first:
        imgs[0] = _ODD
    for i, im in enumerate(imgs):
        pulled.append(i)
        yield f"im{i}", (lambda im=im: im)


def test_odd_sized_first_image_does_not_hold_the_output_back() -> None:
    """Before the window, the odd image's record (and so every record) came out only after
    the last input was read; now it comes out once ``window`` inputs are read ahead."""
    pulled: list[int] = []
    gen = run(_small_items(20, True, pulled), batch_size=4, window=8, progress=False)
    i, _, res, _ = next(gen)
    assert i == 0 and res.name == "im0" and res.height == 40
    assert len(pulled) <= 8
    rest = list(gen)
    assert [r[0] for r in rest] == list(range(1, 20))


def test_window_changes_no_record() -> None:
    a = [r.to_record() for _, _, r, _ in run(_small_items(13, True, []), batch_size=4, window=4, progress=False)]
    b = [r.to_record() for _, _, r, _ in run(_small_items(13, True, []), batch_size=64, window=1000,
                                             progress=False)]
    assert a == b


def test_window_smaller_than_batch_is_refused() -> None:
    with pytest.raises(ValueError, match="window"):
        list(run([], batch_size=8, window=4, progress=False))


# -- kill -9 and --resume ----------------------------------------------------------------

def _spawn_detect(folder: Path, out: Path, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    return subprocess.Popen([sys.executable, "-m", "torchrow", "detect", str(folder), "--out", str(out),
                             "--batch-size", "1", "-q", *extra], env=env, stderr=subprocess.PIPE)


@pytest.fixture(scope="module")
def many_fields(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("many")
    for i in range(10):
        img = render(FieldSpec(seed=100 + i, width=320, height=160)).image
        cv2.imwrite(str(d / f"im{i:02d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    (d / "im99_bad.png").write_bytes(b"")
    return d


def test_killed_run_resumed_equals_a_clean_run(many_fields: Path, tmp_path: Path) -> None:
    clean = tmp_path / "clean.jsonl"
    _cli_records(many_fields, clean)
    out = tmp_path / "killed.jsonl"
    proc = _spawn_detect(many_fields, out)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if out.exists() and len(out.read_bytes().splitlines()) >= 3:
            break
        time.sleep(0.01)
    assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""  # still running
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    n_before = len(out.read_bytes().splitlines())
    assert 3 <= n_before < 11, n_before  # streamed, not held back to the end
    with open(out, "ab") as fh:
        fh.write(b'{"name": "im2')  # and a torn line, as a kill during a write leaves
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    res = subprocess.run([sys.executable, "-m", "torchrow", "detect", str(many_fields), "--out", str(out),
                          "--batch-size", "2", "-q", "--resume"], env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "kept from the earlier run" in res.stderr
    got = _lines(out)
    names = [json.loads(s)["name"] for s in got]
    assert len(names) == len(set(names)) == 11
    assert got == _lines(clean)  # records in input order: the same file as a clean run


def test_video_resume_after_a_cut_equals_a_clean_run(tmp_path: Path) -> None:
    srcs = []
    for k in range(2):
        d = tmp_path / f"seq{k}"
        d.mkdir()
        for t, f in enumerate(sequence(FieldSpec(seed=k, width=200, height=120), 6 + 2 * k)):
            cv2.imwrite(str(d / f"{t:03d}.png"), cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
        srcs.append(str(d))
    clean, cut = tmp_path / "clean.jsonl", tmp_path / "cut.jsonl"
    base = ["video", *srcs, "-q", "--plot", "none", "--param", "video_width=200"]
    assert main([*base, "--out", str(clean)]) == 0
    lines = clean.read_bytes().splitlines(keepends=True)
    assert len(lines) == 14
    cut.write_bytes(b"".join(lines[:5]) + lines[5][:30])  # sequence 1 cut short, torn line
    assert main([*base, "--out", str(cut), "--resume"]) == 0
    assert sorted(_lines(cut)) == sorted(_lines(clean))
    assert len(_lines(cut)) == 14
